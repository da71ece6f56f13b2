import { afterEach, describe, expect, it, vi } from "vitest";
import { Api, ApiError, readErrorWords, type ChangeEvent, type ChangeList } from "../src/api";
import { Feed, type FeedState } from "../src/feed";
import { SseParser } from "../src/sse";

describe("server-sent events", () => {
  it("parses events, data lines, ids and comments as the HTML standard says", () => {
    const p = new SseParser();
    const text =
      ": keep-alive\n\nevent: hello\ndata: {\"version\":3}\n\nid: 4\nevent:commit\ndata:a\ndata: b\n\ndata: plain\n\n";
    expect(p.push(text)).toEqual([
      { event: "hello", data: '{"version":3}', id: "" },
      { event: "commit", data: "a\nb", id: "4" },
      // No event name: `message`; the id carries on.
      { event: "message", data: "plain", id: "4" },
    ]);
  });

  it("gives the same events however the stream is cut, with CRLF, LF or CR line ends", () => {
    const whole = "event: commit\r\ndata: 1\r\n\r\nevent: commit\rdata: 2\r\rdata: 3\n\n";
    const expected = [
      { event: "commit", data: "1", id: "" },
      { event: "commit", data: "2", id: "" },
      { event: "message", data: "3", id: "" },
    ];
    expect(new SseParser().push(whole)).toEqual(expected);
    for (let cut = 1; cut < whole.length; cut++) {
      const p = new SseParser();
      expect([...p.push(whole.slice(0, cut)), ...p.push(whole.slice(cut))], `cut at ${cut}`).toEqual(expected);
    }
    // One character at a time.
    const p = new SseParser();
    expect([...whole].flatMap((c) => p.push(c))).toEqual(expected);
  });

  it("dispatches nothing for an event without data, and waits for the blank line", () => {
    const p = new SseParser();
    expect(p.push("event: resync\n\n")).toEqual([]);
    expect(p.push("event: resync\ndata: {}\n")).toEqual([]);
    expect(p.push("\n")).toEqual([{ event: "resync", data: "{}", id: "" }]);
  });
});

describe("the token on every request", () => {
  afterEach(() => vi.unstubAllGlobals());

  /** Records the Authorization header of each request `fetch` is given. */
  function recordFetch(): Array<{ url: string; auth: string | null }> {
    const seen: Array<{ url: string; auth: string | null }> = [];
    vi.stubGlobal("fetch", (url: string, init: RequestInit) => {
      seen.push({ url, auth: new Headers(init.headers).get("authorization") });
      return Promise.resolve(new Response("{}", { status: 200 }));
    });
    return seen;
  }

  it("sends `Authorization: Bearer` on reads, batches and the change feed once there is a token", async () => {
    const seen = recordFetch();
    let token: string | null = null;
    const api = new Api("", () => token);
    await api.volumes();
    token = "secret-0123456789abcdef";
    await api.volume("demo");
    await api.changes("demo", 3);
    await api.batch("demo", [[0, 0, 0, 0]], 3);
    await api.events("demo", 3, new AbortController().signal);
    expect(seen.map((s) => s.auth)).toEqual([null, ...Array(4).fill("Bearer secret-0123456789abcdef")]);
    expect(seen[4]?.url).toBe("/v1/volumes/demo/events?since=3");
  });

  it("puts a refused read into words that say whether a token was sent", () => {
    const refused = new ApiError(401, "unknown token", null, null);
    expect(readErrorWords(refused, false)).toMatch(/private \(401 Unauthorized\): enter a token/);
    expect(readErrorWords(refused, true)).toMatch(/refused the token \(401 Unauthorized\): nothing can be shown/);
    expect(readErrorWords(new ApiError(0, "down", null, null), true)).toMatch(/cannot be reached/);
    expect(readErrorWords(new ApiError(404, "no volume x", null, null), true)).toMatch(/404.*no volume x/);
  });
});

describe("the change feed read with fetch", () => {
  const commit = (version: number): ChangeEvent => ({ version, timestamp_ms: 0, changed: [[[version, 0, 0]]] });
  const sse = (events: Array<[string, unknown]>) =>
    events.map(([name, data]) => `event: ${name}\ndata: ${JSON.stringify(data)}\n\n`).join("");

  /**
   * A server whose feed streams are scripted: each `events` call takes the next script, a text
   * and whether the stream ends after it.
   */
  class ScriptedFeed {
    opened: number[] = [];
    listed: number[] = [];
    constructor(
      private readonly streams: Array<[string, "ends" | "stays open"]>,
      private readonly history: ChangeEvent[],
    ) {}

    events(_name: string, since: number): Promise<ReadableStream<Uint8Array>> {
      this.opened.push(since);
      const [text, end] = this.streams.shift() ?? ["", "stays open"];
      return Promise.resolve(
        new ReadableStream<Uint8Array>({
          start(c) {
            c.enqueue(new TextEncoder().encode(text));
            if (end === "ends") c.close();
          },
        }),
      );
    }

    changes(_name: string, since: number): Promise<ChangeList> {
      this.listed.push(since);
      const changes = this.history.filter((c) => c.version > since);
      return Promise.resolve({ since, head: 9, oldest: 0, more: false, changes });
    }
  }

  it("applies commits in order, and after the stream ends lists what it missed and resumes from there", async () => {
    // The first stream delivers 2 and 3, then ends (a server restart); 4 and 5 were committed
    // meanwhile; the second stream replays 5 (already listed) and goes on with 6.
    const server = new ScriptedFeed(
      [
        [sse([["hello", { version: 3 }], ["commit", commit(2)], ["commit", commit(3)]]), "ends"],
        [sse([["hello", { version: 5 }], ["commit", commit(5)], ["commit", commit(6)]]), "stays open"],
      ],
      [commit(2), commit(3), commit(4), commit(5)],
    );
    const applied: number[] = [];
    const states: FeedState[] = [];
    const feed = new Feed(server as unknown as Api, "demo", 1, {
      commit: (ev) => applied.push(ev.version),
      reload: () => Promise.reject(new Error("no reload expected")),
      state: (s) => states.push(s),
    });
    await vi.waitFor(() => expect(applied).toEqual([2, 3, 4, 5, 6]));
    expect(server.opened).toEqual([1, 5]);
    expect(server.listed).toEqual([3]);
    expect(feed.version).toBe(6);
    expect(states).toContain("live");
    expect(states).toContain("reconnecting");
    feed.close();
  });
});
