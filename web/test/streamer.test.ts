import { describe, expect, it } from "vitest";
import { ApiError, type Api, type LevelGrid, type MeshLook, type Vec3 } from "../src/api";
import { balancedTiles, keyText, Layout, stitchMasks, tileDistance, type TileKey } from "../src/lod";
import type { TileMesh } from "../src/mesh";
import { changeBoxes, Streamer } from "../src/streamer";
import { triangle } from "./compact";

// The streamer against a scripted server: level grids answer at once, mesh tiles wait until the
// test answers them, so the order, the bound and the cancellation of requests can be watched.

const DIMS: Vec3 = [64, 32, 64];
const BRICK = 8; // grids 8x4x8, 4x2x4, 2x1x2, 1x1x1
const layout = new Layout(DIMS, BRICK);
const INFO = {
  name: "t",
  dims: DIMS,
  voxel_type: "u8" as const,
  low: 0,
  high: 255,
  surface: 127,
  brick: BRICK,
  levels: layout.grids.map((grid, level) => ({ level, grid: [...grid] as Vec3, dims: DIMS.map((d) => Math.ceil(d / 2 ** level)) as Vec3 })),
  voxel_scale: [1, 1, 1] as Vec3,
  version: 1,
};
const TRIANGLE = triangle();

interface MeshCall {
  key: TileKey;
  /** The face, for a strip request. */
  face?: number;
  version: number;
  /** The channel the request asked the vertices to carry (`?channel=`), or null. */
  channel: string | null;
  signal: AbortSignal;
  answer: () => void;
  /** Answers 503 with `Retry-After: 0`, as a server whose CPU queue is full. */
  refuse: () => void;
}

/** A server whose bricks all straddle the surface; `edit` changes bricks' content hashes. */
class ScriptedServer {
  meshCalls: MeshCall[] = [];
  stripCalls: MeshCall[] = [];
  /** Mesh tile and strip requests, in the order they came. */
  calls: MeshCall[] = [];
  gridCalls: Array<{ level: number; version: number }> = [];
  private revision = new Map<string, number>();

  edit(level: number, bricks: Vec3[]): void {
    for (const [x, y, z] of bricks) {
      const id = `${level}/${x}/${y}/${z}`;
      this.revision.set(id, (this.revision.get(id) ?? 0) + 1);
    }
  }

  api(): Api {
    return {
      levelGrid: async (_name: string, level: number, min: Vec3, max: Vec3, version: number) => {
        this.gridCalls.push({ level, version });
        const bricks = [];
        for (let z = min[2]; z < max[2]; z++)
          for (let y = min[1]; y < max[1]; y++)
            for (let x = min[0]; x < max[0]; x++) {
              const r = this.revision.get(`${level}/${x}/${y}/${z}`) ?? 0;
              bricks.push({ hash: `${level}-${x}-${y}-${z}-${r}`, min: 0, max: 255 });
            }
        const grid: LevelGrid = { level, grid: [...layout.grid(level)] as Vec3, min, max, version, bricks };
        return { grid, bytes: 100 };
      },
      meshTile: (_name: string, key: TileKey, version: number, signal?: AbortSignal, look?: MeshLook) =>
        new Promise<ArrayBuffer>((resolve, reject) => {
          const s = signal ?? new AbortController().signal;
          s.addEventListener("abort", () => reject(new DOMException("aborted", "AbortError")));
          this.calls.push({
            key,
            version,
            channel: look?.channel ?? null,
            signal: s,
            answer: () => resolve(TRIANGLE.slice(0)),
            refuse: () => reject(new ApiError(503, "the CPU queue is full", 0, null)),
          });
          this.meshCalls.push(this.calls[this.calls.length - 1]!);
        }),
      meshStrip: (_name: string, key: TileKey, face: number, version: number, signal?: AbortSignal, look?: MeshLook) =>
        new Promise<ArrayBuffer>((resolve, reject) => {
          const s = signal ?? new AbortController().signal;
          s.addEventListener("abort", () => reject(new DOMException("aborted", "AbortError")));
          this.calls.push({
            key,
            face,
            version,
            channel: look?.channel ?? null,
            signal: s,
            answer: () => resolve(TRIANGLE.slice(0)),
            refuse: () => reject(new ApiError(503, "the CPU queue is full", 0, null)),
          });
          this.stripCalls.push(this.calls[this.calls.length - 1]!);
        }),
    } as unknown as Api;
  }

  /** Mesh tile requests in flight. */
  pending(): MeshCall[] {
    return this.meshCalls.filter((c) => !c.signal.aborted && !(c as { done?: boolean }).done);
  }

  /** Mesh tile and strip requests in flight. */
  pendingAll(): MeshCall[] {
    return this.calls.filter((c) => !c.signal.aborted && !(c as { done?: boolean }).done);
  }

  /** Answers the oldest pending mesh tile or strip request. */
  async answerOne(): Promise<MeshCall | undefined> {
    const c = this.pendingAll()[0];
    if (!c) return undefined;
    (c as { done?: boolean }).done = true;
    c.answer();
    await settle();
    return c;
  }
}

const settle = () => new Promise((r) => setTimeout(r, 0));

function start(server: ScriptedServer, camera: Vec3, maxInFlight = 3) {
  const shown = new Map<string, TileMesh>();
  const s = new Streamer({
    api: server.api(),
    info: INFO,
    sink: { show: (id, _k, m) => shown.set(id, m), hide: (id) => shown.delete(id) },
    radii: [12, 24, 48],
    maxInFlight,
  });
  s.setCamera(camera);
  return { s, shown };
}

describe("the streamer", () => {
  it("fetches coarse first, then nearest, never more than the bound at once", async () => {
    const server = new ScriptedServer();
    const camera: Vec3 = [0, 40, 0];
    const { s, shown } = start(server, camera);
    await settle();
    const order: TileKey[] = [];
    for (;;) {
      expect(server.pendingAll().length).toBeLessThanOrEqual(3);
      const c = await server.answerOne();
      if (!c) break;
      if (c.face === undefined) order.push(c.key);
    }
    const desired = balancedTiles(layout, [1, 1, 1], camera, [12, 24, 48]);
    const coarsest = Math.max(...desired.map((k) => k.level));
    // Every tile of the selection, and no tile twice.
    const fetched = new Set(order.map(keyText));
    expect(fetched.size).toBe(order.length);
    for (const k of desired) expect(fetched.has(keyText(k))).toBe(true);
    // Levels never get finer then coarser again; within a level, nearer first (in the order
    // the bound lets through: the first three start together).
    const levels = order.map((k) => k.level);
    expect(levels[0]).toBe(coarsest);
    for (let i = 1; i < levels.length; i++) expect(levels[i]!).toBeLessThanOrEqual(levels[i - 1]!);
    const dist = (k: TileKey) => tileDistance(layout, [1, 1, 1], k, camera);
    for (let i = 3; i < order.length; i++) {
      if (order[i]!.level === order[i - 3]!.level) expect(dist(order[i]!)).toBeGreaterThanOrEqual(dist(order[i - 3]!));
    }
    // Strips: exactly those of the faces in the selection's masks (lod.rs face_masks), each
    // once.
    const masks = stitchMasks(layout, desired);
    const wantStrips = desired.flatMap((k) =>
      [0, 1, 2, 3, 4, 5].filter((f) => ((masks.get(keyText(k)) ?? 0) & (1 << f)) !== 0).map((f) => `${keyText(k)}/${f}`),
    );
    expect(wantStrips.length).toBeGreaterThan(0);
    const gotStrips = server.stripCalls.map((c) => `${keyText(c.key)}/${c.face}`);
    expect(gotStrips.sort()).toEqual(wantStrips.sort());
    const st = s.stats();
    expect(st.complete).toBe(true);
    expect(st.ready).toBe(desired.length);
    expect(shown.size).toBe(desired.length);
    s.stop();
  });

  it("puts its plans off by their pause, keeping the bound full from the last plan's queue", async () => {
    const server = new ScriptedServer();
    const camera: Vec3 = [0, 40, 0];
    const shown = new Map<string, TileMesh>();
    let plans = 0;
    const s = new Streamer({
      api: server.api(),
      info: INFO,
      sink: { show: (id, _k, m) => shown.set(id, m), hide: (id) => shown.delete(id) },
      radii: [12, 24, 48],
      maxInFlight: 3,
      // A pause that never ends: a response plans only when nothing else is in flight.
      planPause: 1e6,
      onChange: () => plans++,
    });
    s.setCamera(camera);
    await settle();
    const plansBefore = plans;
    const inFlightAfter: number[] = [];
    const tiles: string[] = [];
    for (;;) {
      const c = await server.answerOne();
      if (!c) break;
      if (c.face === undefined) tiles.push(keyText(c.key));
      inFlightAfter.push(server.pendingAll().length);
    }
    const desired = balancedTiles(layout, [1, 1, 1], camera, [12, 24, 48]);
    // Every tile (and stand-in) once, all shown, complete: the plan after the last response
    // draws them.
    expect(new Set(tiles).size).toBe(tiles.length);
    for (const k of desired) expect(tiles).toContain(keyText(k));
    expect(s.stats().complete).toBe(true);
    expect(shown.size).toBe(desired.length);
    // Between plans, each answer started the next queued request: three in flight after every
    // answer but the last three.
    const answers = inFlightAfter.length;
    expect(answers).toBeGreaterThan(10);
    expect(inFlightAfter.slice(0, answers - 3)).toEqual(new Array(answers - 3).fill(3));
    expect(inFlightAfter.slice(answers - 3)).toEqual([2, 1, 0]);
    // And far fewer plans than answers.
    expect(plans - plansBefore).toBeLessThan(answers / 4);
    s.stop();
  });

  it("fetches only the newly needed strips when the camera moves, and tiles only once", async () => {
    const server = new ScriptedServer();
    const { s } = start(server, [0, 40, 0]);
    await settle();
    while (await server.answerOne());
    const asked = new Set(server.stripCalls.map((c) => `${keyText(c.key)}/${c.face}`));
    const meshes = new Set(server.meshCalls.map((c) => keyText(c.key)));
    const [before, beforeStrips] = [server.meshCalls.length, server.stripCalls.length];
    const camera: Vec3 = [12, 40, 4];
    s.setCamera(camera);
    await settle();
    while (await server.answerOne());
    const desired = balancedTiles(layout, [1, 1, 1], camera, [12, 24, 48]);
    const masks = stitchMasks(layout, desired);
    const wanted = desired.flatMap((k) =>
      [0, 1, 2, 3, 4, 5].filter((f) => ((masks.get(keyText(k)) ?? 0) & (1 << f)) !== 0).map((f) => `${keyText(k)}/${f}`),
    );
    const fresh = wanted.filter((w) => !asked.has(w));
    expect(fresh.length).toBeGreaterThan(0);
    expect(server.stripCalls.slice(beforeStrips).map((c) => `${keyText(c.key)}/${c.face}`).sort()).toEqual(fresh.sort());
    // Tiles fetched: only those not fetched before.
    const newTiles = desired.map(keyText).filter((k) => !meshes.has(k));
    expect(server.meshCalls.slice(before).map((c) => keyText(c.key)).sort()).toEqual(newTiles.sort());
    expect(s.stats()).toMatchObject({ complete: true, ready: desired.length });
    s.stop();
  });

  it("cancels requests the camera no longer needs", async () => {
    const server = new ScriptedServer();
    const { s } = start(server, [0, 40, 0], 4);
    await settle();
    // Let the coarser tiles through, until fine tiles near the first camera are in flight.
    for (let i = 0; i < 100 && !server.pending().some((c) => c.key.level === 0); i++) {
      await server.answerOne();
    }
    const inFlight = server.pending();
    expect(inFlight.some((c) => c.key.level === 0)).toBe(true);
    s.setCamera([64, 40, 64]); // the far corner
    await settle();
    const wanted = new Set(balancedTiles(layout, [1, 1, 1], [64, 40, 64], [12, 24, 48]).map(keyText));
    for (const c of inFlight) {
      expect(c.signal.aborted).toBe(!wanted.has(keyText(c.key)) && c.key.level < 3);
    }
    expect(server.pending().length).toBeLessThanOrEqual(4);
    s.stop();
  });

  it("refetches exactly the tiles whose inputs an edit changed, at the new version", async () => {
    const server = new ScriptedServer();
    const camera: Vec3 = [20, 40, 20];
    const { s } = start(server, camera);
    await settle();
    while (await server.answerOne());
    expect(s.stats().complete).toBe(true);
    const [before, beforeStrips] = [server.meshCalls.length, server.stripCalls.length];
    const changed: Vec3[][] = [[[2, 1, 2]], [[1, 1, 1]], [[0, 0, 0]], [[0, 0, 0]]];
    changed.forEach((bricks, level) => server.edit(level, bricks));
    s.applyCommit({ version: 2, timestamp_ms: 0, changed });
    await settle();
    while (await server.answerOne());
    const refetched = server.meshCalls.slice(before);
    const restripped = server.stripCalls.slice(beforeStrips);
    const desired = balancedTiles(layout, [1, 1, 1], camera, [12, 24, 48]);
    const masks = stitchMasks(layout, desired);
    // What a tile reads (server/src/mesh/tile.rs, brick 8): the bricks of its level at offsets
    // -1..=1. What the strip of face f reads: of the tile's level the layer of cells along the
    // face (lattice 8 t + 6 ..= 8 t + 9 on a high face, 8 t - 1 ..= 8 t + 2 on a low one, the
    // tile's field 8 t - 1 ..= 8 t + 9 across, from -2 for a first tile); of the next level the
    // stored voxels 4 t + 1 ..= 4 t + 6 (high) or 4 t - 3 ..= 4 t + 2 (low) on the face's axis
    // and 4 t - 3 ..= 4 t + 6 across (from -4 for a first tile).
    const within = (lo: number, hi: number, p: number) => Math.floor(lo / 8) <= p && p <= Math.floor(hi / 8);
    const stripReads = (k: TileKey, f: number, level: number, b: Vec3) => {
      const t = [k.x, k.y, k.z];
      return [0, 1, 2].every((a) => {
        const c = t[a] ?? 0;
        const along = a === f >> 1;
        const high = (f & 1) === 1;
        if (level === k.level) {
          if (along) return high ? within(8 * c + 6, 8 * c + 9, b[a]!) : within(8 * c - 1, 8 * c + 2, b[a]!);
          return within(c === 0 ? -2 : 8 * c - 1, 8 * c + 9, b[a]!);
        }
        if (along) return high ? within(4 * c + 1, 4 * c + 6, b[a]!) : within(4 * c - 3, 4 * c + 2, b[a]!);
        return within(c === 0 ? -4 : 4 * c - 3, 4 * c + 6, b[a]!);
      });
    };
    const readLevels = new Set<number>();
    const staleStrips: string[] = [];
    const stale = desired.filter((k) => {
      const same = (changed[k.level] ?? []).some(
        ([x, y, z]) => Math.abs(x - k.x) <= 1 && Math.abs(y - k.y) <= 1 && Math.abs(z - k.z) <= 1,
      );
      if (same) readLevels.add(k.level);
      for (let f = 0; f < 6; f++) {
        if (((masks.get(keyText(k)) ?? 0) & (1 << f)) === 0) continue;
        let reads = false;
        for (const level of [k.level, k.level + 1]) {
          for (const b of changed[level] ?? []) {
            if (stripReads(k, f, level, b)) {
              reads = true;
              readLevels.add(level);
            }
          }
        }
        if (reads) staleStrips.push(`${keyText(k)}/${f}`);
      }
      return same;
    });
    expect(staleStrips.length).toBeGreaterThan(0); // the strips' inputs count
    expect(refetched.map((c) => keyText(c.key)).sort()).toEqual(stale.map(keyText).sort());
    expect(restripped.map((c) => `${keyText(c.key)}/${c.face}`).sort()).toEqual(staleStrips.sort());
    expect(refetched.every((c) => c.version === 2)).toBe(true);
    expect(restripped.every((c) => c.version === 2)).toBe(true);
    expect(s.stats()).toMatchObject({ version: 2, complete: true, stale: 0 });
    // Grids were asked again at the new version, once per level whose changed bricks a
    // selected tile reads (each level's changes lie in one chunk here).
    const regridded = server.gridCalls.filter((g) => g.version === 2).map((g) => g.level);
    expect(regridded.sort()).toEqual([...readLevels].sort());
    s.stop();
  });
  it("halves its requests in flight when the server refuses them, and grows back", async () => {
    const server = new ScriptedServer();
    const { s } = start(server, [0, 40, 0], 8);
    await settle();
    const first = server.pendingAll();
    expect(first.length).toBe(8);
    // One burst of refusals (all started before the cut) halves the limit once: 8 -> 4.
    for (const c of first) {
      (c as { done?: boolean }).done = true;
      c.refuse();
    }
    await settle();
    expect(s.stats().inFlightLimit).toBe(4);
    expect(server.pendingAll().length).toBeLessThanOrEqual(4);
    expect(s.stats().lastError).toContain("503");
    // Four successes (a window as long as the limit) grow it by one.
    for (let i = 0; i < 4; i++) expect(await server.answerOne()).toBeDefined();
    expect(s.stats().inFlightLimit).toBe(5);
    expect(server.pendingAll().length).toBeLessThanOrEqual(5);
    s.stop();
  });

  it("swaps a commit's changed tiles only together with every changed tile they touch", async () => {
    const server = new ScriptedServer();
    const camera: Vec3 = [20, 40, 20];
    // What each tile shows, as the identities of its mesh, mask and strips.
    const ids = new WeakMap<object, number>();
    let count = 0;
    const idOf = (o: object | null) => {
      if (!o) return "-";
      if (!ids.has(o)) ids.set(o, ++count);
      return String(ids.get(o));
    };
    const shown = new Map<string, { key: TileKey; drawing: string }>();
    const s = new Streamer({
      api: server.api(),
      info: INFO,
      sink: {
        show: (id, key, m, mask, strips) =>
          shown.set(id, { key, drawing: [idOf(m), mask, ...strips.map(idOf)].join(",") }),
        hide: (id) => shown.delete(id),
      },
      radii: [12, 24, 48],
      maxInFlight: 3,
    });
    s.setCamera(camera);
    await settle();
    while (await server.answerOne());
    const before = new Map([...shown].map(([id, v]) => [id, v.drawing]));
    const snapshots: Array<Map<string, { key: TileKey; drawing: string }>> = [];
    // Two commits in a burst at one place: the second lands before any tile of the first.
    const changed: Vec3[][] = [[[2, 1, 2], [3, 1, 2]], [[1, 0, 1]], [], []];
    changed.forEach((bricks, level) => server.edit(level, bricks));
    s.applyCommit({ version: 2, timestamp_ms: 0, changed });
    await settle();
    const firstCalls = server.pendingAll();
    expect(firstCalls.length).toBeGreaterThan(0);
    expect(firstCalls.every((c) => c.version === 2)).toBe(true);
    changed.forEach((bricks, level) => server.edit(level, bricks));
    s.applyCommit({ version: 3, timestamp_ms: 0, changed });
    await settle();
    // The requests for version 2's drawings are cancelled: version 3 replaces them.
    expect(firstCalls.every((c) => c.signal.aborted)).toBe(true);
    snapshots.push(new Map(shown));
    while (await server.answerOne()) snapshots.push(new Map(shown));
    expect(s.stats()).toMatchObject({ version: 3, complete: true, stale: 0 });
    const after = new Map([...shown].map(([id, v]) => [id, v.drawing]));
    const swapped = [...after.keys()].filter((id) => before.has(id) && before.get(id) !== after.get(id));
    expect(swapped.length).toBeGreaterThan(3);
    // In every state shown, a tile already showing its new drawing never touches a tile still
    // showing an old drawing it will replace.
    const box = (k: TileKey) => {
      const span = BRICK * 2 ** k.level;
      return [k.x, k.y, k.z].map((c) => [c * span, (c + 1) * span] as const);
    };
    const touch = (a: TileKey, b: TileKey) =>
      box(a).every(([lo, hi], i) => lo <= box(b)[i]![1] && box(b)[i]![0] <= hi);
    let mixed = 0;
    let swaps = 0;
    for (const snap of snapshots) {
      const isNew = (id: string) => before.get(id) !== after.get(id) && snap.get(id)?.drawing === after.get(id);
      const isOld = (id: string) => before.get(id) !== after.get(id) && snap.get(id)?.drawing === before.get(id);
      if (swapped.some(isNew)) swaps++;
      for (const [a, va] of snap) {
        if (!isNew(a)) continue;
        for (const [b, vb] of snap) if (isOld(b) && touch(va.key, vb.key)) mixed++;
      }
    }
    expect(mixed).toBe(0);
    // And the whole region swapped at once: from the first state with a new drawing on.
    const firstNew = snapshots.findIndex((snap) => swapped.some((id) => snap.get(id)?.drawing === after.get(id)));
    expect(firstNew).toBeGreaterThan(0);
    for (const snap of snapshots.slice(firstNew)) {
      for (const id of swapped) expect(snap.get(id)?.drawing).toBe(after.get(id));
    }
    expect(swaps).toBeGreaterThan(0);
    s.stop();
  });

  it("fetches the tiles an edit made stale before the rest of a load", async () => {
    const server = new ScriptedServer();
    const { s } = start(server, [20, 40, 20], 2);
    await settle();
    while (await server.answerOne());
    // The camera moves (a load starts), then a commit changes tiles on screen.
    s.setCamera([60, 40, 60]);
    await settle();
    const loading = server.pendingAll().length;
    expect(loading).toBe(2);
    // A tile shown before the move and still needed after it (it has the same mask and content
    // in both selections, so it is on screen), changed by a commit.
    const keep = (c: Vec3) => {
      const d = balancedTiles(layout, [1, 1, 1], c, [12, 24, 48]);
      const m = stitchMasks(layout, d);
      return new Map(d.map((k) => [keyText(k), `${m.get(keyText(k))}`]));
    };
    const [a, b] = [keep([20, 40, 20]), keep([60, 40, 60])];
    const both = [...a.keys()].filter((id) => b.get(id) === a.get(id) && id.startsWith("1/"));
    expect(both.length).toBeGreaterThan(0);
    const [level, x, y, z] = both[0]!.split("/").map(Number) as [number, number, number, number];
    const changed: Vec3[][] = [[], [], [], []];
    changed[level] = [[x, y, z]];
    changed.forEach((bricks, l) => server.edit(l, bricks));
    s.applyCommit({ version: 2, timestamp_ms: 0, changed });
    await settle();
    // One place beyond the bound goes to the stale tiles at once, ahead of the load.
    const first = server.pendingAll().filter((c) => c.version === 2);
    expect(first.length).toBe(1);
    expect(server.pendingAll().length).toBe(3);
    expect(first[0]!.key.level).toBe(level);
    // It is answered before any of the load: the next request is again for the edit.
    await server.answerOne();
    await server.answerOne();
    const next = server.pendingAll().filter((c) => c.version === 2 && !first.includes(c));
    expect(next.length).toBeGreaterThan(0);
    s.stop();
  });
  it("refetches only the tiles and strips an edit's box reaches, and keeps the rest at the new version", async () => {
    const server = new ScriptedServer();
    const camera: Vec3 = [20, 40, 20];
    const shown = new Map<string, TileMesh>();
    const shows: string[] = [];
    const s = new Streamer({
      api: server.api(),
      info: INFO,
      sink: {
        show: (id, _k, m) => {
          shows.push(id);
          shown.set(id, m);
        },
        hide: (id) => shown.delete(id),
      },
      radii: [12, 24, 48],
      maxInFlight: 3,
    });
    s.setCamera(camera);
    await settle();
    while (await server.answerOne());
    expect(s.stats().complete).toBe(true);
    const desired = balancedTiles(layout, [1, 1, 1], camera, [12, 24, 48]);
    const masks = stitchMasks(layout, desired);
    const before = new Map(shown);
    const [meshes, strips] = [server.meshCalls.length, server.stripCalls.length];
    shows.length = 0;

    // A small edit in level-0 brick (2, 2, 1): the voxels x 17..19, y 20..22, z 10..12, and
    // the bricks over it on every level (level 1: voxels x 8..9, y 10..11, z 5..6).
    const box = { min: [17, 20, 10] as Vec3, max: [20, 23, 13] as Vec3 };
    const changed: Vec3[][] = [[[2, 2, 1]], [[1, 1, 0]], [[0, 0, 0]], [[0, 0, 0]]];
    changed.forEach((bricks, level) => server.edit(level, bricks));
    const edit = { version: 2, timestamp_ms: 0, kind: "edit" as const, changed };
    s.applyCommit({ ...edit, op: { op: "union", leaves: ["ellipsoid"], box } });
    await settle();
    while (await server.answerOne());
    const refetched = server.meshCalls.slice(meshes).map((c) => keyText(c.key));
    const restripped = server.stripCalls.slice(strips).map((c) => `${keyText(c.key)}/${c.face}`);

    // By hand: a level-0 tile t (cells 8t..8t+8, from -1 for the first) reads the voxels
    // [8t - 1, 8t + 10) (from -2 for the first); level-1 tile t the level-1 voxels
    // 8t - 3 ..= 8t + 10 (from -4), so level-0 [16t - 6, 16t + 22) (from -8).
    // Level 0 on x: tiles 1 [7, 18) and 2 [15, 26) meet 17..19, tile 3 [23, 34) does not;
    // on y: tile 2 [15, 26) meets 20..22, tile 3 [23, 34) does not; on z: tile 1 [7, 18) meets
    // 10..12, tile 0 [-2, 10) and tile 2 [15, 26) do not. Level 1: tiles 0 [-8, 22) and 1
    // [10, 38) on every axis, tile 2 [26, 54) on none. Tile (0, 1, 2, 1) lies beside the box
    // (its cells end at x 16) and must be refetched: its normals read voxel 17.
    expect(refetched.sort()).toEqual(["0/1/2/1", "0/2/2/1", "1/0/0/0", "1/0/0/1", "1/1/0/0", "1/1/0/1"]);
    // Without the box, every tile reading a changed brick would have been: 18 of level 0 (x
    // 1..3, y 2..3, z 0..2) and 8 of level 1.
    const readers = desired.filter((k) =>
      (changed[k.level] ?? []).some(([x, y, z]) => Math.abs(x - k.x) <= 1 && Math.abs(y - k.y) <= 1 && Math.abs(z - k.z) <= 1),
    );
    expect(readers.length).toBe(26);

    // Strips, by the same rule: of the tile's level, the layer of cells along the face; of the
    // next, level-(k+1) voxels c - 3 ..= c + 2 on the face's axis (c = lo/2 on a low face, hi/2 on
    // a high one) and lo/2 - 3 ..= hi/2 + 2 across; each voxel of level k is 2^k of level 0.
    const stripVoxels = (k: TileKey, f: number): Array<[number, number][]> => {
      const t = [k.x, k.y, k.z];
      const lo = t.map((c) => 8 * c - (c === 0 ? 1 : 0));
      const hi = t.map((c) => 8 * c + 8);
      const grow = k.level === 0 ? [1, 1] : [3, 2];
      const fine = [0, 1, 2].map((a): [number, number] => {
        if (a !== f >> 1) return [lo[a]! - grow[0]!, hi[a]! + grow[1]!];
        return f & 1 ? [hi[a]! - 1 - grow[0]!, hi[a]! + grow[1]!] : [lo[a]! - grow[0]!, lo[a]! + 1 + grow[1]!];
      });
      const coarse = [0, 1, 2].map((a): [number, number] => {
        const c = f & 1 ? hi[a]! / 2 : Math.floor(lo[a]! / 2);
        if (a === f >> 1) return [c - 3, c + 2];
        return [Math.floor(lo[a]! / 2) - 3, hi[a]! / 2 + 2];
      });
      const s0 = 2 ** k.level;
      return [fine.map(([a, b]) => [a * s0, (b + 1) * s0]), coarse.map(([a, b]) => [a * 2 * s0, (b + 1) * 2 * s0])];
    };
    const meets = (r: [number, number][]) => [0, 1, 2].every((a) => r[a]![0] < box.max[a]! && box.min[a]! < r[a]![1]);
    const wantStrips: string[] = [];
    for (const k of desired) {
      for (let f = 0; f < 6; f++) {
        if (((masks.get(keyText(k)) ?? 0) & (1 << f)) === 0) continue;
        if (stripVoxels(k, f).some(meets)) wantStrips.push(`${keyText(k)}/${f}`);
      }
    }
    expect(wantStrips.length).toBeGreaterThan(0);
    expect(restripped.sort()).toEqual(wantStrips.sort());
    // Every request at the new version, and the view is that version's, whole. No grid chunk
    // was asked for first: the meshes of version 2 are asked for by version, and the tiles kept
    // need no new hash.
    expect(server.calls.slice(meshes + strips).every((c) => c.version === 2)).toBe(true);
    expect(server.gridCalls.filter((g) => g.version === 2)).toEqual([]);
    expect(s.stats()).toMatchObject({ version: 2, complete: true, stale: 0, ready: desired.length });
    // The tiles kept were not drawn again: only those refetched (or whose strips were) swapped.
    const redrawn = new Set([...refetched, ...restripped.map((id) => id.split("/").slice(0, 4).join("/"))]);
    expect(shows.length).toBeGreaterThan(0);
    expect(shows.filter((id) => !redrawn.has(id))).toEqual([]);
    for (const [id, m] of shown) if (!redrawn.has(id)) expect(m).toBe(before.get(id));

    // A second edit whose box reaches a tile the first one left alone (level-0 tile (3, 2, 1):
    // voxels [23, 34) on x) refetches it: what a tile keeps holds only until a box reaches it.
    const [meshes2] = [server.meshCalls.length];
    const second: Vec3[][] = [[[3, 2, 1]], [[1, 1, 0]], [[0, 0, 0]], [[0, 0, 0]]];
    second.forEach((bricks, level) => server.edit(level, bricks));
    const box2 = { min: [29, 20, 10] as Vec3, max: [31, 22, 12] as Vec3 };
    s.applyCommit({ version: 3, timestamp_ms: 0, kind: "edit", changed: second, op: { op: "union", leaves: [], box: box2 } });
    await settle();
    while (await server.answerOne());
    const again = server.meshCalls.slice(meshes2).map((c) => keyText(c.key));
    expect(again).toContain("0/3/2/1");
    // Tile (1, 2, 1) shows its mesh of version 2, which the second box does not reach.
    expect(again).not.toContain("0/1/2/1");
    expect(server.meshCalls.slice(meshes2).every((c) => c.version === 3)).toBe(true);
    expect(s.stats()).toMatchObject({ version: 3, complete: true, stale: 0 });
    s.stop();
  });
  it("asks again for a version's meshes after a reload, whose versions may name other content", async () => {
    const server = new ScriptedServer();
    const { s } = start(server, [20, 40, 20]);
    await settle();
    while (await server.answerOne());
    const box = { min: [17, 20, 10] as Vec3, max: [20, 23, 13] as Vec3 };
    const changed: Vec3[][] = [[[2, 2, 1]], [[1, 1, 0]], [[0, 0, 0]], [[0, 0, 0]]];
    const commit = { version: 2, timestamp_ms: 0, kind: "edit" as const, changed, op: { op: "union", leaves: [], box } };
    changed.forEach((bricks, level) => server.edit(level, bricks));
    s.applyCommit(commit);
    await settle();
    while (await server.answerOne());
    expect(server.meshCalls.filter((c) => c.version === 2).map((c) => keyText(c.key))).toContain("0/2/2/1");
    // The server's file was replaced by one at version 1, and another edit made its version 2.
    const before = server.meshCalls.length;
    s.reload({ ...INFO, version: 1 });
    await settle();
    while (await server.answerOne());
    changed.forEach((bricks, level) => server.edit(level, bricks));
    s.applyCommit(commit);
    await settle();
    while (await server.answerOne());
    expect(server.meshCalls.slice(before).filter((c) => c.version === 2).map((c) => keyText(c.key))).toContain("0/2/2/1");
    expect(s.stats()).toMatchObject({ version: 2, complete: true, stale: 0 });
    s.stop();
  });
});

describe("grids from the change feed", () => {
  const box = { min: [17, 20, 10] as Vec3, max: [20, 23, 13] as Vec3 };
  const changed: Vec3[][] = [[[2, 2, 1]], [[1, 1, 0]], [[0, 0, 0]], [[0, 0, 0]]];
  const close: Vec3 = [18, 14, 6];

  /**
   * The camera close to where the edit will be, then away; an edit (its event listing the
   * changed bricks' new hashes, or not); the camera close again: the grid chunks and meshes
   * asked for after the move back.
   */
  async function editThenClose(withBricks: boolean) {
    const server = new ScriptedServer();
    const { s } = start(server, close);
    await settle();
    while (await server.answerOne());
    s.setCamera([60, 30, 60]);
    await settle();
    while (await server.answerOne());
    changed.forEach((bricks, level) => server.edit(level, bricks));
    // The hashes the scripted server's grids give the changed bricks now (revision 1).
    const bricks = changed.map((level, l) => level.map(([x, y, z]) => ({ hash: `${l}-${x}-${y}-${z}-1`, min: 0, max: 255 })));
    s.applyCommit({ version: 2, timestamp_ms: 0, kind: "edit", changed, ...(withBricks ? { bricks } : {}), op: { op: "union", leaves: [], box } });
    await settle();
    while (await server.answerOne());
    const [grids, calls] = [server.gridCalls.length, server.calls.length];
    s.setCamera(close);
    await settle();
    while (await server.answerOne());
    expect(s.stats()).toMatchObject({ version: 2, complete: true, stale: 0 });
    s.stop();
    return {
      grids: server.gridCalls.slice(grids),
      meshes: server.calls.slice(calls).map((c) => `${keyText(c.key)}/${c.face ?? "t"}@${c.version}`).sort(),
    };
  }

  it("takes the changed bricks' hashes from a commit that lists them, and asks no grid chunk for them", async () => {
    // Tile (0, 2, 2, 1), which reads the changed level-0 brick, is selected close to the edit
    // and not from away: when the camera comes back its key comes from the hashes, and only the
    // changed brick's new hash tells it from the mesh fetched before the edit.
    const away = new Set(balancedTiles(layout, [1, 1, 1], [60, 30, 60], [12, 24, 48]).map(keyText));
    expect(away.has("0/2/2/1")).toBe(false);
    expect(balancedTiles(layout, [1, 1, 1], close, [12, 24, 48]).map(keyText)).toContain("0/2/2/1");
    const listed = await editThenClose(true);
    const unlisted = await editThenClose(false);
    expect(listed.grids).toEqual([]);
    expect(unlisted.grids.filter((g) => g.version === 2).length).toBeGreaterThan(0);
    // The same meshes either way, the changed tile among them: the hashes the event gave are
    // the grid's (the old one would have shown the cached mesh of before the edit).
    expect(listed.meshes).toContain("0/2/2/1/t@2");
    expect(listed.meshes).toEqual(unlisted.meshes);
  });
});

describe("meshes with materials", () => {
  // The paint of the union test's box: the material channel's bricks over it changed on every
  // level, density's none.
  const box = { min: [17, 20, 10] as Vec3, max: [20, 23, 13] as Vec3 };
  const painted: Vec3[][] = [[[2, 2, 1]], [[1, 1, 0]], [[0, 0, 0]], [[0, 0, 0]]];
  const paint = (version: number) => ({
    version,
    timestamp_ms: 0,
    kind: "edit" as const,
    changed: [[], [], [], []] as Vec3[][],
    channels: { material: painted },
    op: { op: "paint", leaves: ["ellipsoid"], box },
  });

  it("asks for them with the channel, refetches what a paint reaches, and asks again for painted tiles it selects later", async () => {
    const server = new ScriptedServer();
    const camera: Vec3 = [20, 40, 20];
    const { s } = start(server, camera);
    s.setChannel("material");
    await settle();
    while (await server.answerOne());
    expect(server.calls.length).toBeGreaterThan(0);
    const plain = server.calls.filter((c) => c.channel === null).length;
    const fresh = server.calls.slice(plain);
    expect(fresh.length).toBeGreaterThan(0);
    expect(fresh.every((c) => c.channel === "material")).toBe(true);
    expect(s.stats().complete).toBe(true);

    // The paint changes no density: the hashes stay, and still the tiles its box reaches (the
    // same six as the union's) are fetched at its version.
    const before = server.meshCalls.length;
    s.applyCommit(paint(2));
    await settle();
    while (await server.answerOne());
    const refetched = server.meshCalls.slice(before);
    expect(refetched.map((c) => keyText(c.key)).sort()).toEqual(["0/1/2/1", "0/2/2/1", "1/0/0/0", "1/0/0/1", "1/1/0/0", "1/1/0/1"]);
    expect(refetched.every((c) => c.version === 2 && c.channel === "material")).toBe(true);
    expect(s.stats()).toMatchObject({ version: 2, complete: true, stale: 0 });

    // Away (the level-0 tiles there leave the selection), an edit there (after which tiles
    // out of the selection keep nothing from the paint), and back: a tile reading a painted
    // brick is asked again (its cached mesh from before has the old materials), one reading
    // neither a painted brick nor one the edit changed is not.
    const away = server.meshCalls.length;
    s.setCamera([60, 30, 60]);
    await settle();
    while (await server.answerOne());
    expect(balancedTiles(layout, [1, 1, 1], [60, 30, 60], [12, 24, 48]).some((k) => keyText(k) === "0/2/2/1")).toBe(false);
    const edited: Vec3[][] = [[[7, 3, 7]], [[3, 1, 3]], [[1, 0, 1]], [[0, 0, 0]]];
    edited.forEach((bricks, level) => server.edit(level, bricks));
    const far = { min: [58, 26, 58] as Vec3, max: [61, 29, 61] as Vec3 };
    s.applyCommit({ version: 3, timestamp_ms: 0, kind: "edit", changed: edited, op: { op: "union", leaves: [], box: far } });
    await settle();
    while (await server.answerOne());
    const back = server.meshCalls.length;
    s.setCamera(camera);
    await settle();
    while (await server.answerOne());
    const again = server.meshCalls.slice(back).map((c) => c.key);
    expect(again.map(keyText)).toContain("0/2/2/1");
    const reads = (bricks: Vec3[][], k: TileKey) =>
      (bricks[k.level] ?? []).some(([x, y, z]) => Math.abs(x - k.x) <= 1 && Math.abs(y - k.y) <= 1 && Math.abs(z - k.z) <= 1);
    expect(again.filter((k) => !reads(painted, k) && !reads(edited, k))).toEqual([]);
    expect(server.meshCalls.slice(away, back).length).toBeGreaterThan(0);
    s.stop();
  });

  it("does not refetch for a paint while the meshes carry no channel", async () => {
    const server = new ScriptedServer();
    const { s } = start(server, [20, 40, 20]);
    await settle();
    while (await server.answerOne());
    const before = server.calls.length;
    s.applyCommit(paint(2));
    await settle();
    while (await server.answerOne());
    expect(server.calls.length).toBe(before);
    expect(s.stats()).toMatchObject({ version: 2, complete: true, stale: 0 });
    // The channel's own level-0 bricks count as changed voxels only when it is drawn.
    expect(changeBoxes(paint(2), 8)).toEqual([]);
    expect(changeBoxes(paint(2), 8, "material")).toEqual([box]);
    s.stop();
  });
});

describe("the voxels a commit changed", () => {
  const brick = 8;
  const box = { min: [30, 5, 5] as Vec3, max: [36, 9, 9] as Vec3 };
  const changed: Vec3[][] = [[[3, 0, 0], [4, 0, 0]], [[1, 0, 0], [2, 0, 0]], [[0, 0, 0]], [[0, 0, 0]]];
  const op = { op: "difference", leaves: ["ellipsoid"], box };

  it("is an edit's box within each changed level-0 brick", () => {
    // Brick (3, 0, 0) is voxels [24, 32) x [0, 8) x [0, 8); (4, 0, 0) [32, 40) x ...
    expect(changeBoxes({ version: 2, timestamp_ms: 0, kind: "edit", op, changed }, brick)).toEqual([
      { min: [30, 5, 5], max: [32, 8, 8] },
      { min: [32, 5, 5], max: [36, 8, 8] },
    ]);
    // A changed brick the box misses adds nothing; an edit that changed nothing changed no voxel.
    const far: Vec3[][] = [[[3, 0, 0], [7, 3, 7]], [], [], []];
    expect(changeBoxes({ version: 2, timestamp_ms: 0, kind: "edit", op, changed: far }, brick)).toEqual([
      { min: [30, 5, 5], max: [32, 8, 8] },
    ]);
    expect(changeBoxes({ version: 2, timestamp_ms: 0, kind: "edit", op, changed: [[], [], [], []] }, brick)).toEqual([]);
  });

  it("is the changed level-0 bricks whole for an undo, a redo or a revert", () => {
    for (const kind of ["undo", "redo", "revert"] as const) {
      expect(changeBoxes({ version: 2, timestamp_ms: 0, kind, op, changed }, brick)).toEqual([
        { min: [24, 0, 0], max: [32, 8, 8] },
        { min: [32, 0, 0], max: [40, 8, 8] },
      ]);
    }
  });

  it("is unknown for a commit that does not say what it was, or changed no level-0 brick but coarser ones", () => {
    expect(changeBoxes({ version: 2, timestamp_ms: 0, changed }, brick)).toBeNull();
    expect(changeBoxes({ version: 2, timestamp_ms: 0, op, changed }, brick)).toBeNull();
    const coarseOnly: Vec3[][] = [[], [[1, 0, 0]], [], []];
    expect(changeBoxes({ version: 2, timestamp_ms: 0, kind: "edit", op, changed: coarseOnly }, brick)).toBeNull();
  });
});
