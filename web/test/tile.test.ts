import { readFileSync } from "node:fs";
import { describe, expect, it } from "vitest";
import { keyText, Layout, type TileKey } from "../src/lod";
import { stitch, type TileMesh } from "../src/mesh";
import {
  bricksOf,
  cells,
  coarseBox,
  fieldBox,
  footprint,
  hasStrip,
  meshTileReads,
  reachedBy,
  storedBox,
  stripCoarseBox,
  stripFieldBox,
  stripReads,
  type GridBox,
  type TileRead,
  valueRange,
} from "../src/tile";

// What the viewer computes about tiles must be what the server computes: a content key that
// names other bricks than the server reads would keep showing a stale tile after an edit, and
// a "no surface can cross" the server does not agree with would leave a hole. These vectors are
// written by the Rust tests from the functions tile.ts and mesh.ts port:
// proto/tests/lod_vectors.rs (tile.json: proto/src/tile.rs and proto::mesh::apply_moves) and
// server/src/mesh/lattice.rs (value_range.json), which fail when the files are stale.

/** A read as the vectors list it: level, bricks, crossing. */
type Read = [number, GridBox, GridBox];
interface StripCase {
  field: GridBox;
  coarse: GridBox;
  reads: Read[];
}
interface TileCase {
  key: [number, number, number, number];
  cells: GridBox;
  field: GridBox;
  coarse: GridBox;
  reads: Read[];
  /** Faces 0..=6; 6 is out of range. */
  has_strip: boolean[];
  /** Faces 0..6. */
  strips: StripCase[];
}
interface MoveCase {
  positions: number[];
  /** Vertex, face, distance; grouped by face. */
  moves: [number, number, number][];
  /** Per face mask 0..64, the positions after the moves. */
  moved: number[][];
}
const tileVectors = JSON.parse(readFileSync(new URL("../test-vectors/tile.json", import.meta.url), "utf8")) as {
  layouts: { dims: [number, number, number]; brick: number; levels: number; tiles: TileCase[] }[];
  boxes: { level: number; brick: number; box: GridBox; stored: GridBox; bricks: GridBox }[];
  moves: MoveCase[];
};
const rangeVectors = JSON.parse(
  readFileSync(new URL("../test-vectors/value_range.json", import.meta.url), "utf8"),
) as { cases: [number, number, number, number, number][] };

const keyOf = ([level, x, y, z]: number[]): TileKey => ({ level: level ?? 0, x: x ?? 0, y: y ?? 0, z: z ?? 0 });
const readsOf = (reads: TileRead[]): Read[] => reads.map((r) => [r.level, r.bricks, r.crossing]);

// Boxes are integers on both sides: exact equality.
describe("tile geometry equals proto/src/tile.rs", () => {
  const tiles = tileVectors.layouts.flatMap((l) => l.tiles.map((t) => ({ layout: l, t })));

  it("has vectors of every level of every layout", () => {
    expect(tileVectors.layouts.length).toBe(5);
    for (const l of tileVectors.layouts) {
      const layout = new Layout(l.dims, l.brick);
      expect(layout.levels, JSON.stringify(l.dims)).toBe(l.levels);
      const levels = new Set(l.tiles.map((t) => t.key[0]));
      expect(levels.size).toBe(l.levels);
    }
    // Strips that read, and faces without one, both occur.
    expect(tiles.some(({ t }) => t.has_strip.some((s) => s))).toBe(true);
    expect(tiles.some(({ t }) => t.has_strip.slice(0, 6).some((s) => !s))).toBe(true);
    expect(tileVectors.boxes.length).toBeGreaterThan(40);
  });

  it("gives every tile the same cells, field and coarse boxes", () => {
    for (const { layout: l, t } of tiles) {
      const layout = new Layout(l.dims, l.brick);
      const k = keyOf(t.key);
      const at = `${l.dims.join("x")}/${l.brick} tile ${keyText(k)}`;
      const c = cells(layout, k);
      expect([c.lo, c.hi], at).toEqual(t.cells);
      expect(fieldBox(layout, k), at).toEqual(t.field);
      expect(coarseBox(layout, k), at).toEqual(t.coarse);
    }
  });

  it("reads the same bricks for every mesh tile, and decides crossing on the same ones", () => {
    for (const { layout: l, t } of tiles) {
      const layout = new Layout(l.dims, l.brick);
      const k = keyOf(t.key);
      expect(readsOf(meshTileReads(layout, k)), `${l.dims.join("x")} tile ${keyText(k)}`).toEqual(t.reads);
    }
  });

  it("has the same strips, with the same boxes and reads, on every face", () => {
    for (const { layout: l, t } of tiles) {
      const layout = new Layout(l.dims, l.brick);
      const k = keyOf(t.key);
      const at = (f: number) => `${l.dims.join("x")} tile ${keyText(k)} face ${f}`;
      expect(t.has_strip.length).toBe(7);
      t.has_strip.forEach((want, f) => expect(hasStrip(layout, k, f), at(f)).toBe(want));
      // A face Rust cannot name (usize): never a strip.
      expect(hasStrip(layout, k, -1), at(-1)).toBe(false);
      expect(stripReads(layout, k, -1)).toEqual([]);
      expect(stripReads(layout, k, 6)).toEqual([]);
      t.strips.forEach((s, f) => {
        expect(stripFieldBox(layout, k, f), at(f)).toEqual(s.field);
        expect(stripCoarseBox(layout, k, f), at(f)).toEqual(s.coarse);
        expect(readsOf(stripReads(layout, k, f)), at(f)).toEqual(s.reads);
      });
    }
  });

  it("maps boxes to stored voxels and bricks as stored_box and bricks_of do", () => {
    for (const b of tileVectors.boxes) {
      const at = JSON.stringify(b.box);
      expect(storedBox(b.level, b.box), `level ${b.level} ${at}`).toEqual(b.stored);
      expect(bricksOf(b.brick, b.box), `brick ${b.brick} ${at}`).toEqual(b.bricks);
    }
  });
});

describe("moves equal proto::mesh::apply_moves under every face mask", () => {
  it("has vectors", () => {
    expect(tileVectors.moves.length).toBe(2);
    for (const c of tileVectors.moves) expect(c.moved.length).toBe(64);
  });

  it("moves the same vertices by the same f32 sums", () => {
    for (const [i, c] of tileVectors.moves.entries()) {
      const n = c.positions.length / 3;
      const tile: TileMesh = {
        positions: new Float32Array(c.positions),
        normals: new Int16Array(3 * n),
        indices: new Uint16Array(0),
        min: [0, 0, 0],
        max: [0, 0, 0],
        moves: {
          vertex: new Uint32Array(c.moves.map((m) => m[0])),
          face: new Uint8Array(c.moves.map((m) => m[1])),
          distance: new Float32Array(c.moves.map((m) => m[2])),
        },
        bytes: 0,
      };
      c.moved.forEach((want, mask) => {
        // Bit for bit, not within a tolerance: a strip's vertices along the face are copies of
        // the moved vertices, and the two join only where the positions are equal.
        expect([...stitch(tile, mask).positions], `tile ${i} mask ${mask}`).toEqual(want.map(Math.fround));
      });
    }
  });
});

describe("valueRange equals server/src/mesh/lattice.rs value_range", () => {
  it("has vectors", () => {
    expect(rangeVectors.cases.length).toBeGreaterThan(100);
  });

  it("gives the same f32 bounds, bit for bit", () => {
    // Exact, not within a tolerance: the server compares its bound with the iso value to
    // decide whether a tile or strip can hold a surface (`may_cross`), the viewer compares its
    // own to skip what it calls empty without asking, and an f32 rounding of difference flips
    // that decision for some voxel ranges and surfaces. The port rounds where Rust computes in
    // f32 (as lod.ts does), so equality is what it can reach.
    for (const [level, min, max, low, high] of rangeVectors.cases) {
      const at = `level ${level} [${min}, ${max}]`;
      expect(valueRange(level, min, max), at).toEqual([Math.fround(low), Math.fround(high)]);
    }
  });
});

describe("the level-0 voxels a tile's mesh is made of", () => {
  // 64^3, brick 8: grids 8, 4, 2, 1 (proto/src/tile.rs's reads_by_hand).
  const layout = new Layout([64, 64, 64], 8);
  const key = (level: number, x: number, y: number, z: number): TileKey => ({ level, x, y, z });
  const box = (min: [number, number, number], max: [number, number, number]) => ({ min, max });

  it("is the stored voxels read, scaled by the level", () => {
    // Level-0 tile (2, 0, 5): field x 15..=25, y -2..=9 (first on y), z 39..=49: the level-0
    // voxels [15, 26) x [-2, 10) x [39, 50).
    const [tile] = meshTileReads(layout, key(0, 2, 0, 5));
    expect(tile!.voxels).toEqual([[15, -2, 39], [25, 9, 49]]);
    expect(footprint(tile!)).toEqual(box([15, -2, 39], [26, 10, 50]));
    // Level 2, tile (1, 1, 1): stored voxels 5..=18 of level 2, each the mean of 4^3 level-0
    // voxels: [20, 76) on every axis.
    expect(footprint(meshTileReads(layout, key(2, 1, 1, 1))[0]!)).toEqual(box([20, 20, 20], [76, 76, 76]));
    // The +x strip of (0, 2, 0, 5): the tile's level x 22..=25 (y, z as the tile), and level 1's
    // stored x 9..=14, y -4..=6, z 17..=26: level-0 x [18, 30), y [-8, 14), z [34, 54).
    const [fine, coarse] = stripReads(layout, key(0, 2, 0, 5), 1);
    expect(footprint(fine!)).toEqual(box([22, -2, 39], [26, 10, 50]));
    expect(footprint(coarse!)).toEqual(box([18, -8, 34], [30, 14, 54]));
  });

  it("is reached by a box one voxel beyond the tile's cells, and not by one two beyond", () => {
    // Level-0 tile (3, 1, 2): cells x [24, 32), y [8, 16), z [16, 24); its cells' far corners are
    // the points 32 and its normals read 33: voxels [23, 34) on x.
    const reads = meshTileReads(layout, key(0, 3, 1, 2));
    const at = (x0: number, x1: number) => box([x0, 10, 18], [x1, 13, 21]);
    // A box wholly in the next tile's cells (x 33..35): still its neighbour's business.
    expect(reachedBy(reads, [at(33, 36)])).toBe(true);
    expect(reachedBy(reads, [at(34, 36)])).toBe(false);
    // On the low side: voxel 23 (the normals of the first cells) is read, 22 is not.
    expect(reachedBy(reads, [at(20, 24)])).toBe(true);
    expect(reachedBy(reads, [at(20, 23)])).toBe(false);
    // Any of several boxes; none at all reaches nothing.
    expect(reachedBy(reads, [at(40, 41), at(33, 34)])).toBe(true);
    expect(reachedBy(reads, [])).toBe(false);
  });

  it("reaches two level-0 voxels a side per level-1 voxel of the interpolation's reach", () => {
    // The box x [33, 36) lies in level-1 tile 2's cells (level-0 [32, 64)). Level-1 tile 1 (cells
    // 8..16 of level 1) reads stored voxels 5..=18: level-0 [10, 38), reached. Tile 3 (cells
    // 24..32) reads 21..=34: level-0 [42, 70), not reached, although it reads level-1 brick 2
    // (voxels 16..=23), which holds the level-1 voxels the box changes (16 and 17).
    const at = box([33, 20, 20], [36, 23, 23]);
    expect(reachedBy(meshTileReads(layout, key(1, 1, 1, 1)), [at])).toBe(true);
    const far = meshTileReads(layout, key(1, 3, 1, 1));
    expect(far[0]!.bricks[0][0]).toBe(2);
    expect(reachedBy(far, [at])).toBe(false);
  });
});
