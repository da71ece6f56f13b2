// Server-sent events read from a byte stream (the change feed fetched with `fetch`, which, unlike
// `EventSource`, can send an `Authorization` header). The parsing rules of the HTML standard's
// event stream format: lines end in CRLF, LF or CR; `:` starts a comment (the server's
// keep-alives); `event`, `data` and `id` fields; a blank line dispatches the event, if it has
// data; a field's value loses one leading space.

export interface ServerEvent {
  /** `message` when the stream named none. */
  event: string;
  data: string;
  /** The last `id` seen so far in the stream (what `Last-Event-ID` would carry). */
  id: string;
}

export class SseParser {
  private pending = "";
  /** The previous chunk ended in CR: an LF that starts the next one belongs to it. */
  private afterCr = false;
  private event = "";
  private data: string[] = [];
  private id = "";

  /** Parses one more piece of the stream's text; returns the events it completed. */
  push(text: string): ServerEvent[] {
    if (this.afterCr && text.startsWith("\n")) text = text.slice(1);
    this.afterCr = text.endsWith("\r");
    const lines = (this.pending + text).split(/\r\n|\r|\n/);
    this.pending = lines.pop() ?? "";
    const out: ServerEvent[] = [];
    for (const line of lines) {
      const e = this.line(line);
      if (e) out.push(e);
    }
    return out;
  }

  private line(line: string): ServerEvent | null {
    if (line === "") {
      const data = this.data;
      const event = this.event || "message";
      this.data = [];
      this.event = "";
      return data.length > 0 ? { event, data: data.join("\n"), id: this.id } : null;
    }
    if (line.startsWith(":")) return null;
    const colon = line.indexOf(":");
    const field = colon < 0 ? line : line.slice(0, colon);
    let value = colon < 0 ? "" : line.slice(colon + 1);
    if (value.startsWith(" ")) value = value.slice(1);
    if (field === "event") this.event = value;
    else if (field === "data") this.data.push(value);
    else if (field === "id" && !value.includes("\0")) this.id = value;
    return null;
  }
}
