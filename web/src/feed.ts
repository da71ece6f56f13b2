// Following a volume's change feed (`GET /v1/volumes/{name}/events`, server-sent events;
// docs/editing.md): every committed version once, in order, across lost connections and
// server restarts.
//
// The stream is read with `fetch` (`sse.ts` parses it), not `EventSource`: a server with private
// reads wants the token in an `Authorization` header, which an `EventSource` cannot send (and
// its own retry, a fixed 3 s with errors the page cannot read, is not wanted either).
//
// The page keeps the last version it applied. When the stream breaks (or ends) it closes it, asks `changes?since=LAST` until that answers (backoff 100 ms doubling to 2 s), applies
// the versions listed there, and opens the stream again with `?since=` the last of them, which
// is what `Last-Event-ID` would carry: the server replays anything committed in between. A 410
// (the history after LAST was compacted away) or a 409 (the server is now behind the page: its
// file was replaced) means the page must reload the volume; so does a `hello` whose version is
// below the page's. A `resync` (the page fell more than 1024 versions behind the live stream)
// is filled the same way from `changes`.

import { Api, ApiError, isAbort, type ChangeEvent, type Presence } from "./api";
import { SseParser, type ServerEvent } from "./sse";

const RETRY_MIN_MS = 100;
const RETRY_MAX_MS = 2_000;

export type FeedState = "connecting" | "live" | "reconnecting";

export interface FeedHandlers {
  /** One version, in order. */
  commit(ev: ChangeEvent): void;
  /** The page's version cannot be continued from: load the volume anew. Resolves when done. */
  reload(): Promise<number>;
  state?(state: FeedState): void;
  /** Another user's whereabouts (not versioned: never replayed). */
  presence?(p: Presence): void;
}

export class Feed {
  private readonly api: Api;
  private readonly volume: string;
  private readonly handlers: FeedHandlers;
  /** Aborts the stream being read; null while none is open. */
  private stream: AbortController | null = null;
  /** Whether the open stream said `hello` (one refused at once is retried with backoff). */
  private heard = false;
  private last: number;
  private delay = RETRY_MIN_MS;
  private timer: ReturnType<typeof setTimeout> | null = null;
  private closed = false;
  /** Set while catching up, so stream events wait for it. */
  private catchingUp: Promise<void> | null = null;

  constructor(api: Api, volume: string, since: number, handlers: FeedHandlers) {
    this.api = api;
    this.volume = volume;
    this.last = since;
    this.handlers = handlers;
    this.open();
  }

  /** The last version applied. */
  get version(): number {
    return this.last;
  }

  close(): void {
    this.closed = true;
    this.stream?.abort();
    this.stream = null;
    if (this.timer !== null) clearTimeout(this.timer);
  }

  private setState(s: FeedState): void {
    this.handlers.state?.(s);
  }

  private open(): void {
    if (this.closed) return;
    this.setState(this.delay === RETRY_MIN_MS ? "connecting" : "reconnecting");
    const stream = new AbortController();
    this.stream = stream;
    this.heard = false;
    void this.read(stream).then(
      () => this.broke(stream),
      (e: unknown) => (isAbort(e) ? undefined : this.broke(stream)),
    );
  }

  /** Reads the stream until it ends, handing each event on. */
  private async read(stream: AbortController): Promise<void> {
    const body = await this.api.events(this.volume, this.last, stream.signal);
    const reader = body.getReader();
    const decoder = new TextDecoder();
    const parser = new SseParser();
    for (;;) {
      const { done, value } = await reader.read();
      if (done || this.stream !== stream) return;
      for (const e of parser.push(decoder.decode(value, { stream: true }))) this.dispatch(e);
    }
  }

  /** The stream ended, was refused or was cut: catch up and open it again. */
  private async broke(stream: AbortController): Promise<void> {
    if (this.stream !== stream) return;
    if (!this.heard) {
      // Refused before it began (a 503, a token the feed does not take): do not hammer.
      this.setState("reconnecting");
      await new Promise((r) => (this.timer = setTimeout(r, this.delay)));
      this.delay = Math.min(this.delay * 2, RETRY_MAX_MS);
      if (this.stream !== stream) return;
    }
    await this.restart(() => this.catchUp());
  }

  private dispatch(e: ServerEvent): void {
    if (e.event === "hello") {
      const { version } = JSON.parse(e.data) as { version: number };
      this.heard = true;
      this.delay = RETRY_MIN_MS;
      this.setState("live");
      if (version < this.last) void this.restart(() => this.reloadVolume());
    } else if (e.event === "commit") {
      const ev = JSON.parse(e.data) as ChangeEvent;
      if (this.catchingUp) void this.catchingUp.then(() => this.apply(ev));
      else this.apply(ev);
    } else if (e.event === "presence") {
      this.handlers.presence?.(JSON.parse(e.data) as Presence);
    } else if (e.event === "resync") {
      void this.restart(() => this.catchUp());
    }
  }

  private apply(ev: ChangeEvent): void {
    if (ev.version <= this.last) return; // already applied from `changes`
    if (ev.version !== this.last + 1) {
      // A gap the server should never leave; fill it from the list.
      void this.restart(() => this.catchUp());
      return;
    }
    this.last = ev.version;
    this.handlers.commit(ev);
  }

  /** Closes the stream, runs `step` until it succeeds (with backoff), and opens it again. */
  private async restart(step: () => Promise<void>): Promise<void> {
    if (this.catchingUp || this.closed) return;
    this.stream?.abort();
    this.stream = null;
    this.setState("reconnecting");
    let done!: () => void;
    this.catchingUp = new Promise((r) => (done = r));
    for (;;) {
      try {
        await step();
        break;
      } catch (e) {
        if (this.closed) break;
        if (e instanceof ApiError && (e.status === 410 || e.status === 409)) {
          step = () => this.reloadVolume();
          continue;
        }
        if (!isAbort(e)) await new Promise((r) => (this.timer = setTimeout(r, this.delay)));
        this.delay = Math.min(this.delay * 2, RETRY_MAX_MS);
      }
    }
    this.catchingUp = null;
    done();
    this.open();
  }

  /** Applies every version after the last one from `changes?since=`. */
  private async catchUp(): Promise<void> {
    for (;;) {
      const list = await this.api.changes(this.volume, this.last);
      for (const ev of list.changes) this.apply(ev);
      if (!list.more) return;
    }
  }

  private async reloadVolume(): Promise<void> {
    this.last = await this.handlers.reload();
  }
}
