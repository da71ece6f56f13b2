import { afterEach, beforeEach, describe, expect, it, vi } from "vitest";
import { ApiError, type ChangeEvent, type HistoryEntry } from "../src/api";
import { applyCommit, describe as describeCommit, distanceToBox, mergeHistory, nearNote } from "../src/history";
import { colourFor, fnv1a, PresenceSender, type Whereabouts } from "../src/presence";
import { authorizationUrl, challengeOf, claimsOf, pickToken } from "../src/signin";
import { UndoStack, undoErrorWords, undoWords } from "../src/undo";

describe("the undo stack of the page's own edits", () => {
  it("undoes the last edit in effect, redoes through the undo's version, and a new edit clears redo", () => {
    const u = new UndoStack();
    expect(u.nextUndo).toBeNull();
    u.edited(3);
    u.edited(7); // others may have committed 4..6: the page only keeps its own
    expect(u.nextUndo).toBe(7);
    u.undone(9); // the server committed the undo of 7 as 9
    expect(u.nextUndo).toBe(3);
    expect(u.nextRedo).toBe(9); // redo sends the undo's version
    u.redone(12); // the redo of 9 committed as 12: undoing again sends 12
    expect(u.nextUndo).toBe(12);
    expect(u.nextRedo).toBeNull();
    u.undone(13);
    u.edited(14);
    expect(u.nextRedo).toBeNull();
    expect(u.nextUndo).toBe(14);
  });

  it("drops a version the server will never take back, and survives the session storage", () => {
    const u = new UndoStack();
    u.edited(2);
    u.edited(5);
    u.drop(5);
    expect(u.nextUndo).toBe(2);
    const back = UndoStack.from(u.save());
    expect(back.nextUndo).toBe(2);
    back.undone(6);
    expect(UndoStack.from(back.save()).nextRedo).toBe(6);
    expect(UndoStack.from("not json").nextUndo).toBeNull();
    expect(UndoStack.from('{"undo": [1, "x", -2, 3.5, 4]}').nextUndo).toBe(4);
  });

  it("says what happened, with the later edits applied again", () => {
    expect(undoWords("undo", { version: 9, replayed: 1 })).toBe("Undone as version 9; 1 later edit applied again.");
    expect(undoWords("redo", { version: 12, replayed: 2 })).toBe("Redone as version 12; 2 later edits applied again.");
    expect(undoWords("undo", { version: 4 })).toBe("Undone as version 4; no later edit over it.");
  });

  it("puts the server's refusals into words with its detail", () => {
    const e = (status: number) => new ApiError(status, "the detail", null, null);
    expect(undoErrorWords("undo", 7, e(403))).toBe("The server refused to undo version 7 (403 Forbidden): the detail");
    expect(undoErrorWords("undo", 7, e(409))).toMatch(/^Version 7 cannot be undone \(409 Conflict\): the detail/);
    expect(undoErrorWords("redo", 9, e(409))).toMatch(/^Version 9 cannot be redone/);
    expect(undoErrorWords("undo", 7, e(503))).toMatch(/^The server is busy/);
  });
});

describe("a colour per user", () => {
  it("is FNV-1a's hue: the same name the same colour on every page", () => {
    // FNV-1a 32 of "a" is 0xe40c292c (the FNV reference vectors); 3826002220 mod 360 = 340.
    expect(fnv1a("a")).toBe(0xe40c292c);
    expect(fnv1a("")).toBe(0x811c9dc5);
    expect(colourFor("a")).toBe("hsl(340, 70%, 45%)");
    expect(colourFor("alice")).toBe(colourFor("alice"));
    expect(colourFor("alice")).not.toBe(colourFor("bob"));
  });

  it("spreads names over the hues", () => {
    const names = ["alice", "bob", "carol", "dave", "erin", "frank", "grace", "heidi", "ivan", "judy"];
    const hues = new Set(names.map((n) => Math.floor((fnv1a(n) % 360) / 36)));
    expect(hues.size).toBeGreaterThanOrEqual(5);
  });
});

describe("posting presence", () => {
  beforeEach(() => vi.useFakeTimers());
  afterEach(() => vi.useRealTimers());
  const at = (x: number): Whereabouts => ({ position: [x, 0, 0], looking: [0, 0, 0] });

  it("sends at most twice a second, the latest position, and again while standing still", () => {
    const sent: number[] = [];
    const s = new PresenceSender((w) => sent.push(w.position[0]), () => Date.now());
    s.moved(at(1)); // at once
    expect(sent).toEqual([1]);
    vi.advanceTimersByTime(100);
    s.moved(at(2));
    s.moved(at(3)); // within 500 ms of the last post: only the latest, at 500 ms
    expect(sent).toEqual([1]);
    vi.advanceTimersByTime(399);
    expect(sent).toEqual([1]);
    vi.advanceTimersByTime(1);
    expect(sent).toEqual([1, 3]);
    vi.advanceTimersByTime(2_000);
    s.moved(at(4)); // long after: at once
    expect(sent).toEqual([1, 3, 4]);
    // Standing still: once every 4 s, so the server does not announce the page gone (10 s).
    vi.advanceTimersByTime(8_000);
    expect(sent.slice(3).every((x) => x === 4)).toBe(true);
    expect(sent.length).toBeGreaterThanOrEqual(4);
    expect(sent.length).toBeLessThanOrEqual(6);
    s.stop();
    const n = sent.length;
    vi.advanceTimersByTime(20_000);
    s.moved(at(5));
    expect(sent.length).toBe(n);
  });

  it("never sends more than 2 in any second of constant movement", () => {
    const times: number[] = [];
    const s = new PresenceSender(() => times.push(Date.now()), () => Date.now());
    for (let t = 0; t < 5_000; t += 16) {
      s.moved(at(t));
      vi.advanceTimersByTime(16);
    }
    s.stop();
    for (const t of times) expect(times.filter((u) => u >= t && u < t + 1_000).length).toBeLessThanOrEqual(2);
    expect(times.length).toBeGreaterThanOrEqual(9);
  });
});

describe("the history", () => {
  const box = { min: [10, 10, 10] as [number, number, number], max: [20, 20, 20] as [number, number, number] };
  const edit = (version: number, author: string): HistoryEntry => ({
    version,
    timestamp_ms: 1_000 * version,
    author,
    kind: "edit",
    op: { op: "difference", leaves: ["ellipsoid"], box },
    bricks_changed: 2,
    undone: false,
  });
  const commit = (version: number, extra: Partial<ChangeEvent>): ChangeEvent => ({
    version,
    timestamp_ms: 1_000 * version,
    changed: [[[0, 0, 0], [1, 0, 0]], [[0, 0, 0]]],
    ...extra,
  });

  it("merges pages newest first, one entry per version", () => {
    const m = mergeHistory([edit(3, "a"), edit(1, "a")], [edit(2, "b"), { ...edit(3, "c") }]);
    expect(m.map((e) => [e.version, e.author])).toEqual([[3, "c"], [2, "b"], [1, "a"]]);
  });

  it("adds the feed's commits and marks undo, redo and revert", () => {
    let list = [edit(2, "alice"), edit(1, "bob")];
    ({ list } = applyCommit(list, commit(3, { author: "bob", kind: "edit", op: edit(0, "").op! })));
    expect(list[0]).toMatchObject({ version: 3, author: "bob", kind: "edit", bricks_changed: 3, undone: false });
    expect("changed" in list[0]!).toBe(false);
    ({ list } = applyCommit(list, commit(4, { author: "alice", kind: "undo", target: 2, replayed: 1 })));
    expect(list.find((e) => e.version === 2)?.undone).toBe(true);
    expect(describeCommit(list[0]!)).toBe("undid version 2 (1 later edit applied again)");
    ({ list } = applyCommit(list, commit(5, { author: "alice", kind: "redo", target: 2 })));
    expect(list.find((e) => e.version === 2)?.undone).toBe(false);
    const r = applyCommit(list, commit(6, { author: "carol", kind: "revert", to: 1 }));
    expect(r.refetch).toBe(true);
    expect(r.list.filter((e) => e.undone).map((e) => e.version)).toEqual([3, 2]);
    expect(r.list.find((e) => e.version === 1)?.undone).toBe(false);
    expect(r.list.map((e) => e.version)).toEqual([6, 5, 4, 3, 2, 1]);
  });

  it("says what a commit did", () => {
    expect(describeCommit(edit(1, "a"))).toBe("carved (difference: ellipsoid)");
    expect(describeCommit({ ...edit(1, "a"), op: { op: "union", leaves: ["cuboid", "torus"], box } })).toBe("added (union: cuboid, torus)");
    expect(describeCommit({ version: 2, timestamp_ms: 0, bricks_changed: 0, kind: "revert", to: 1 })).toBe("reverted to version 1");
    expect(describeCommit({ version: 2, timestamp_ms: 0, bricks_changed: 0 })).toBe("committed");
  });

  it("notes someone else's edit near the camera, not mine, not far away", () => {
    const ev = commit(3, { author: "alice", kind: "edit", op: edit(0, "").op! });
    // (14, 15, 40) is 20 voxels above the box's z face (20).
    expect(distanceToBox([14, 15, 40], box)).toBe(20);
    expect(distanceToBox([15, 15, 15], box)).toBe(0);
    expect(distanceToBox([23, 24, 10], box)).toBe(5);
    expect(nearNote(ev, "bob", [[14, 15, 40]], 48)).toBe("alice carved here");
    expect(nearNote(ev, "alice", [[14, 15, 40]], 48)).toBeNull();
    expect(nearNote(ev, "bob", [[14, 15, 100]], 48)).toBeNull();
    expect(nearNote(ev, "bob", [[500, 0, 0], [14, 15, 40]], 48)).toBe("alice carved here");
    expect(nearNote(commit(3, { author: "alice" }), "bob", [[15, 15, 15]], 48)).toBeNull();
  });
});

describe("sign-in with PKCE", () => {
  it("computes the S256 challenge of RFC 7636's example", async () => {
    expect(await challengeOf("dBjftJeZ4CVP-mB92K27uhbUJU1p1r_wW1gFWFOEjXk")).toBe(
      "E9Melhoa2OwvFrEMTJguCHaoeK1t8URWbuGJSstw-cM",
    );
  });

  it("asks for a code with the challenge, and keeps the token the server's audience takes", () => {
    const u = new URL(authorizationUrl("https://id.example/auth?x=1", "isovox-web", "http://127.0.0.1:7070/", "st", "ch"));
    expect(u.searchParams.get("x")).toBe("1");
    expect(u.searchParams.get("response_type")).toBe("code");
    expect(u.searchParams.get("client_id")).toBe("isovox-web");
    expect(u.searchParams.get("redirect_uri")).toBe("http://127.0.0.1:7070/");
    expect(u.searchParams.get("code_challenge_method")).toBe("S256");
    expect(u.searchParams.get("code_challenge")).toBe("ch");
    expect(u.searchParams.get("state")).toBe("st");
    const jwt = (claims: object) =>
      `e30.${Buffer.from(JSON.stringify(claims)).toString("base64url")}.sig`;
    expect(claimsOf(jwt({ aud: "isovox", sub: "ü" }))).toEqual({ aud: "isovox", sub: "ü" });
    const access = jwt({ aud: ["account", "isovox"] });
    const id = jwt({ aud: "isovox-web" });
    expect(pickToken({ access_token: access, id_token: id }, "isovox")).toBe(access);
    expect(pickToken({ access_token: access, id_token: id }, "isovox-web")).toBe(id);
    expect(pickToken({ access_token: "opaque", id_token: id }, "other")).toBeNull();
  });
});
