import { readFileSync } from "node:fs";
import { describe, expect, it } from "vitest";
import {
  adaptiveTiles,
  balancedTiles,
  keyText,
  Layout,
  OUT_OF_VIEW_REACH,
  radiiForScreenError,
  stitchMasks,
  tileDistance,
  type TileKey,
} from "../src/lod";
import { hasStrip, meshTileReads, stripReads, valueRange } from "../src/tile";

type Vec3 = [number, number, number];
interface Case {
  dims: Vec3;
  brick: number;
  voxel_scale: Vec3;
  camera: Vec3;
  radii: number[];
  tiles: [number, number, number, number][];
  /** The balanced selection, each tile with its face mask: level, x, y, z, mask. */
  balanced: [number, number, number, number, number][];
}
interface DistanceCase {
  dims: Vec3;
  brick: number;
  voxel_scale: Vec3;
  key: [number, number, number, number];
  camera: Vec3;
  distance: number;
}

// Written by the Rust test proto/tests/lod_vectors.rs from proto's own lod.rs.
const vectors = JSON.parse(
  readFileSync(new URL("../test-vectors/lod.json", import.meta.url), "utf8"),
) as { cases: Case[]; distances: DistanceCase[] };

const key = ([level, x, y, z]: number[]): TileKey => ({
  level: level ?? 0,
  x: x ?? 0,
  y: y ?? 0,
  z: z ?? 0,
});

describe("tile selection equals proto/src/lod.rs", () => {
  it("has vectors", () => {
    expect(vectors.cases.length).toBeGreaterThan(100);
    expect(vectors.distances.length).toBeGreaterThan(100);
  });

  it("selects the same tiles, in the same order, for every case", () => {
    for (const c of vectors.cases) {
      const layout = new Layout(c.dims, c.brick);
      const got = adaptiveTiles(layout, c.voxel_scale, c.camera, c.radii).map(keyText);
      const want = c.tiles.map((t) => keyText(key(t)));
      expect(got, JSON.stringify({ dims: c.dims, camera: c.camera, radii: c.radii })).toEqual(want);
    }
  });

  it("balances the same selection, with the same face masks", () => {
    for (const c of vectors.cases) {
      const layout = new Layout(c.dims, c.brick);
      const tiles = balancedTiles(layout, c.voxel_scale, c.camera, c.radii);
      const masks = stitchMasks(layout, tiles);
      const got = tiles.map((k) => `${keyText(k)}:${masks.get(keyText(k))}`);
      const want = c.balanced.map(([l, x, y, z, m]) => `${keyText(key([l, x, y, z]))}:${m}`);
      expect(got, JSON.stringify({ dims: c.dims, camera: c.camera, radii: c.radii })).toEqual(want);
    }
  });

  it("measures the same f32 distances, bit for bit", () => {
    for (const d of vectors.distances) {
      const layout = new Layout(d.dims, d.brick);
      const got = tileDistance(layout, d.voxel_scale, key(d.key), d.camera);
      expect(got).toBe(Math.fround(d.distance));
    }
  });
});

describe("layout", () => {
  it("has the grids of proto's layout tests", () => {
    // 200x160x160, brick 16: 13x10x10, 7x5x5, 4x3x3, 2x2x2, 1x1x1 (layout.rs).
    const l = new Layout([200, 160, 160], 16);
    expect(l.grids).toEqual([
      [13, 10, 10],
      [7, 5, 5],
      [4, 3, 3],
      [2, 2, 2],
      [1, 1, 1],
    ]);
    // Brick (1,1,1) of a 2x2x2 level over a 3x3x3 one has only child (2,2,2).
    const m = new Layout([40, 40, 40], 16);
    expect(m.children({ level: 1, x: 1, y: 1, z: 1 })).toEqual([{ level: 0, x: 2, y: 2, z: 2 }]);
  });

  it("rejects bad shapes", () => {
    expect(() => new Layout([0, 1, 1], 16)).toThrow();
    expect(() => new Layout([8, 8, 8], 12)).toThrow();
  });
});

describe("tiles out of the view frustum", () => {
  // 64^3, brick 8: grids 8^3, 4^3, 2^3, 1. Camera at the centre of level-0 tile (0, 0, 0).
  const layout = new Layout([64, 64, 64], 8);
  const camera = [4, 4, 4];
  const radii = [8, 20, 40];

  it("are refined within half their level's radius", () => {
    // Every tile out of view: the selection of radii 4, 10, 20.
    const none = adaptiveTiles(layout, [1, 1, 1], camera, radii, () => false).map(keyText);
    const halved = adaptiveTiles(layout, [1, 1, 1], camera, radii.map((r) => r * OUT_OF_VIEW_REACH));
    expect(none).toEqual(halved.map(keyText));
    // Every tile in view: the plain selection, as the Rust streamer makes it.
    const all = adaptiveTiles(layout, [1, 1, 1], camera, radii, () => true).map(keyText);
    expect(all).toEqual(adaptiveTiles(layout, [1, 1, 1], camera, radii).map(keyText));
  });

  it("are never finer than without a frustum, and cover the volume once", () => {
    // In view: tiles whose box starts below x = 32 (the camera's half).
    const wide = [16, 40, 80];
    const inView = (k: TileKey) => k.x * 8 * 2 ** k.level < 32;
    const plain = balancedTiles(layout, [1, 1, 1], camera, wide);
    const framed = balancedTiles(layout, [1, 1, 1], camera, wide, inView);
    expect(framed.length).toBeLessThan(plain.length);
    // Where a tile out of view lies, the plain selection has it or finer tiles under it.
    const levelAt = (tiles: TileKey[], x: number, y: number, z: number) =>
      tiles.find((k) => {
        const e = 8 * 2 ** k.level;
        return [k.x, k.y, k.z].every((c, a) => c * e <= [x, y, z][a]! && [x, y, z][a]! < (c + 1) * e);
      })?.level;
    for (let z = 0; z < 64; z += 8) {
      for (let y = 0; y < 64; y += 8) {
        for (let x = 32; x < 64; x += 8) {
          expect(levelAt(framed, x, y, z)).toBeGreaterThanOrEqual(levelAt(plain, x, y, z)!);
        }
      }
    }
    // Covering the volume once: the level-0 voxels of the tiles add up to 64^3, none overlap.
    expect(framed.reduce((n, k) => n + (8 * 2 ** k.level) ** 3, 0)).toBe(64 ** 3);
    for (let z = 0; z < 64; z += 8) {
      for (let y = 0; y < 64; y += 8) {
        for (let x = 0; x < 64; x += 8) expect(levelAt(framed, x, y, z)).toBeDefined();
      }
    }
  });
});

describe("radii for a screen error", () => {
  it("follows 2^(k+1) s H / (2 tan(fov/2) e)", () => {
    // 90 degrees: tan(45) = 1; H 1000, e 10: 50 per world unit; s = 2.
    const r = radiiForScreenError(4, [1, 2, 1], Math.PI / 2, 1000, 10);
    expect(r.map((x) => Math.round(x * 1e6) / 1e6)).toEqual([200, 400, 800]);
    expect(radiiForScreenError(4, [1, 1, 1], Math.PI / 2, 1000, 0)).toEqual([]);
  });
});

describe("stitch masks", () => {
  it("marks the faces that touch a coarser tile", () => {
    // Grids 4x1x1 (brick 8, 32x8x8) and 2x1x1, 1x1x1: select level-0 tiles 0 and 1 and the
    // level-1 tile 1 (covering level-0 tiles 2 and 3).
    const l = new Layout([32, 8, 8], 8);
    const tiles = [
      { level: 0, x: 0, y: 0, z: 0 },
      { level: 0, x: 1, y: 0, z: 0 },
      { level: 1, x: 1, y: 0, z: 0 },
    ];
    const m = stitchMasks(l, tiles);
    expect(m.get("0/0/0/0")).toBe(0); // its +x neighbour is level 0
    expect(m.get("0/1/0/0")).toBe(0b10); // +x touches the level-1 tile
    expect(m.get("1/1/0/0")).toBe(0); // coarser side: nothing to stitch
  });
});

describe("what a mesh tile reads", () => {
  it("matches proto/src/tile.rs's hand-computed example", () => {
    // 64^3, brick 8. Level-0 tile (2, 0, 5): bricks x 1..=3, y -1..=1, z 4..=6 of level 0.
    const l = new Layout([64, 64, 64], 8);
    const k = { level: 0, x: 2, y: 0, z: 5 };
    const reads = meshTileReads(l, k);
    expect(reads.map((r) => [r.level, r.bricks])).toEqual([[0, [[1, -1, 4], [3, 1, 6]]]]);
    // The cells' corners alone decide whether a surface crosses: bricks x 2..=3, y -1..=1.
    expect(reads[0]?.crossing).toEqual([[2, -1, 5], [3, 1, 6]]);
    // Its +x strip: level-0 bricks x 2..=3 (the layer of cells along the face), level-1
    // bricks x 1, y -1..=0, z 2..=3; its -x strip: x 1..=2 and x 0..=1.
    expect(stripReads(l, k, 1).map((r) => [r.level, r.bricks])).toEqual([
      [0, [[2, -1, 4], [3, 1, 6]]],
      [1, [[1, -1, 2], [1, 0, 3]]],
    ]);
    expect(stripReads(l, k, 0).map((r) => [r.level, r.bricks])).toEqual([
      [0, [[1, -1, 4], [2, 1, 6]]],
      [1, [[0, -1, 2], [1, 0, 3]]],
    ]);
    // -y of a first tile, and every face of the root: no strip.
    expect(hasStrip(l, k, 2)).toBe(false);
    expect(stripReads(l, k, 2)).toEqual([]);
    expect([0, 1, 2, 3, 4, 5].some((f) => hasStrip(l, { level: 3, x: 0, y: 0, z: 0 }, f))).toBe(false);
    expect(meshTileReads(l, { level: 3, x: 0, y: 0, z: 0 }).length).toBe(1);
  });

  it("bounds interpolated values as lattice.rs does", () => {
    const [lo, hi] = valueRange(1, 0, 100);
    expect(lo).toBeCloseTo(-34.228, 3);
    expect(hi).toBeCloseTo(134.228, 3);
    expect(valueRange(0, 3, 9)).toEqual([3, 9]);
  });
});
