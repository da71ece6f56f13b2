import { describe, expect, it } from "vitest";
import type { Api, LevelGrid, Vec3 } from "../src/api";
import { balancedTiles, keyText, Layout, tileDistance, type TileKey } from "../src/lod";
import type { TileMesh } from "../src/mesh";
import { Streamer } from "../src/streamer";
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
  version: number;
  signal: AbortSignal;
  answer: () => void;
}

/** A server whose bricks all straddle the surface; `edit` changes bricks' content hashes. */
class ScriptedServer {
  meshCalls: MeshCall[] = [];
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
      meshTile: (_name: string, key: TileKey, version: number, signal?: AbortSignal) =>
        new Promise<ArrayBuffer>((resolve, reject) => {
          const s = signal ?? new AbortController().signal;
          s.addEventListener("abort", () => reject(new DOMException("aborted", "AbortError")));
          this.meshCalls.push({ key, version, signal: s, answer: () => resolve(TRIANGLE.slice(0)) });
        }),
    } as unknown as Api;
  }

  pending(): MeshCall[] {
    return this.meshCalls.filter((c) => !c.signal.aborted && !(c as { done?: boolean }).done);
  }

  /** Answers the oldest pending mesh request. */
  async answerOne(): Promise<MeshCall | undefined> {
    const c = this.pending()[0];
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
      expect(server.pending().length).toBeLessThanOrEqual(3);
      const c = await server.answerOne();
      if (!c) break;
      order.push(c.key);
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
    const st = s.stats();
    expect(st.complete).toBe(true);
    expect(st.ready).toBe(desired.length);
    expect(shown.size).toBe(desired.length);
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
    const before = server.meshCalls.length;
    const changed: Vec3[][] = [[[2, 1, 2]], [[1, 1, 1]], [[0, 0, 0]], [[0, 0, 0]]];
    changed.forEach((bricks, level) => server.edit(level, bricks));
    s.applyCommit({ version: 2, timestamp_ms: 0, changed });
    await settle();
    while (await server.answerOne());
    const refetched = server.meshCalls.slice(before);
    const desired = balancedTiles(layout, [1, 1, 1], camera, [12, 24, 48]);
    // What a tile reads (server/src/mesh/tile.rs, brick 8): the bricks of its level at offsets
    // -1..=1, and for its strips the next level's voxels [4 t - 3, 4 t + 6] on each axis
    // (from -4 for a first tile): bricks floor(first / 8) ..= floor((4 t + 6) / 8).
    const readsCoarse = (t: number, p: number) =>
      Math.floor((t === 0 ? -4 : 4 * t - 3) / 8) <= p && p <= Math.floor((4 * t + 6) / 8);
    const readLevels = new Set<number>();
    let coarseOnly = 0;
    const stale = desired.filter((k) => {
      const same = (changed[k.level] ?? []).some(
        ([x, y, z]) => Math.abs(x - k.x) <= 1 && Math.abs(y - k.y) <= 1 && Math.abs(z - k.z) <= 1,
      );
      const coarse =
        k.level + 1 < layout.levels &&
        (changed[k.level + 1] ?? []).some(
          ([x, y, z]) => readsCoarse(k.x, x) && readsCoarse(k.y, y) && readsCoarse(k.z, z),
        );
      if (same) readLevels.add(k.level);
      if (coarse) readLevels.add(k.level + 1);
      if (coarse && !same) coarseOnly++;
      return same || coarse;
    });
    expect(coarseOnly).toBeGreaterThan(0); // the strips' inputs count
    expect(refetched.map((c) => keyText(c.key)).sort()).toEqual(stale.map(keyText).sort());
    expect(refetched.every((c) => c.version === 2)).toBe(true);
    expect(s.stats()).toMatchObject({ version: 2, complete: true, stale: 0 });
    // Grids were asked again at the new version, once per level whose changed bricks a
    // selected tile reads (each level's changes lie in one chunk here).
    const regridded = server.gridCalls.filter((g) => g.version === 2).map((g) => g.level);
    expect(regridded.sort()).toEqual([...readLevels].sort());
    s.stop();
  });
});
