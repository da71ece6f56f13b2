// What a mesh tile and its transition strips read: a port of `proto/src/tile.rs` (the seam
// rule's arithmetic) and of the bound `server/src/mesh/lattice.rs` puts on a coarse level's
// lattice values, for the viewer's content keys (`streamer.ts`): a tile's key names every brick
// it reads, of its level; a strip's, those of the tile's level along its face and of the next
// coarser one; and whether a surface can cross them at all. Kept equal to the Rust by the vectors
// its tests write: `web/test-vectors/tile.json` (proto/tests/lod_vectors.rs) and
// `value_range.json` (server/src/mesh/lattice.rs), checked by `test/tile.test.ts`.

import type { Layout, TileKey } from "./lod";

type Vec3 = [number, number, number];
/** A box of grid points or voxels of one level, both ends included. */
export type GridBox = [Vec3, Vec3];

/** The cells `[lo, hi)` of tile `k` (lattice points of its level): `tile::cells`. */
export function cells(layout: Layout, k: TileKey): { lo: Vec3; hi: Vec3 } {
  const b = layout.brick;
  const pos: Vec3 = [k.x, k.y, k.z];
  return {
    lo: pos.map((c) => c * b - (c === 0 ? 1 : 0)) as Vec3,
    hi: pos.map((c) => (c + 1) * b) as Vec3,
  };
}

/** The stored voxels of `level` whose lattice values cover `points`: `tile::stored_box`. */
export function storedBox(level: number, [lo, hi]: GridBox): GridBox {
  if (level === 0) return [lo, hi];
  return [lo.map((c) => c - 2) as Vec3, hi.map((c) => c + 1) as Vec3];
}

/** The lattice points marching reads: cells' corners and the normals' halo. */
export function fieldBox(layout: Layout, k: TileKey): GridBox {
  const { lo, hi } = cells(layout, k);
  return [lo.map((c) => c - 1) as Vec3, hi.map((c) => c + 1) as Vec3];
}

/** The next coarser level's lattice points the strips read, in that level's units. */
export function coarseBox(layout: Layout, k: TileKey): GridBox {
  const { lo, hi } = cells(layout, k);
  return [lo.map((c) => Math.floor(c / 2) - 1) as Vec3, hi.map((c) => c / 2 + 1) as Vec3];
}

/** The bricks holding `voxels`: first and last brick position per axis (maybe outside the grid). */
export function bricksOf(brick: number, [lo, hi]: GridBox): GridBox {
  return [lo.map((c) => Math.floor(c / brick)) as Vec3, hi.map((c) => Math.floor(c / brick)) as Vec3];
}

/** What a mesh tile or strip reads (`tile::mesh_tile_reads`, `tile::strip_reads`), per level. */
export interface TileRead {
  level: number;
  /** The stored voxels of `level` read (their lattice values are what the mesh is made of). */
  voxels: GridBox;
  /** The bricks read: those holding `voxels`. */
  bricks: GridBox;
  /** The bricks whose voxels decide whether a surface crosses the tile or strip. */
  crossing: GridBox;
}

export function meshTileReads(layout: Layout, k: TileKey): TileRead[] {
  const { lo, hi } = cells(layout, k);
  const voxels = storedBox(k.level, fieldBox(layout, k));
  return [
    {
      level: k.level,
      voxels,
      bricks: bricksOf(layout.brick, voxels),
      crossing: bricksOf(layout.brick, storedBox(k.level, [lo, hi])),
    },
  ];
}

/** Whether face `face` of tile `k` can ever touch a coarser tile (`tile::has_strip`). */
export function hasStrip(layout: Layout, k: TileKey, face: number): boolean {
  if (k.level + 1 >= layout.levels || face < 0 || face > 5) return false;
  const axis = face >> 1;
  const p: Vec3 = [k.x, k.y, k.z];
  p[axis] = (p[axis] ?? 0) + (face & 1 ? 1 : -1);
  return layout.contains({ level: k.level, x: p[0], y: p[1], z: p[2] });
}

/** The lattice points of the tile's level the strip of `face` reads (`tile::strip_field_box`). */
export function stripFieldBox(layout: Layout, k: TileKey, face: number): GridBox {
  const { lo, hi } = cells(layout, k);
  const a: Vec3 = [...lo];
  const b: Vec3 = [...hi];
  const axis = face >> 1;
  if (face & 1) a[axis] = (hi[axis] ?? 0) - 1;
  else b[axis] = (lo[axis] ?? 0) + 1;
  return [a.map((c) => c - 1) as Vec3, b.map((c) => c + 1) as Vec3];
}

/** The next coarser level's lattice points the strip of `face` reads (`tile::strip_coarse_box`). */
export function stripCoarseBox(layout: Layout, k: TileKey, face: number): GridBox {
  const [c, d] = coarseBox(layout, k);
  const axis = face >> 1;
  const at = face & 1 ? (d[axis] ?? 0) - 1 : (c[axis] ?? 0) + 1;
  const lo: Vec3 = [...c];
  const hi: Vec3 = [...d];
  lo[axis] = at - 1;
  hi[axis] = at + 1;
  return [lo, hi];
}

/** What the strip of `face` of tile `k` reads (`tile::strip_reads`); none without a strip. */
export function stripReads(layout: Layout, k: TileKey, face: number): TileRead[] {
  if (!hasStrip(layout, k, face)) return [];
  const fine = storedBox(k.level, stripFieldBox(layout, k, face));
  const coarse = storedBox(k.level + 1, stripCoarseBox(layout, k, face));
  const [fineBricks, coarseBricks] = [bricksOf(layout.brick, fine), bricksOf(layout.brick, coarse)];
  return [
    { level: k.level, voxels: fine, bricks: fineBricks, crossing: fineBricks },
    { level: k.level + 1, voxels: coarse, bricks: coarseBricks, crossing: coarseBricks },
  ];
}

/** Level-0 voxels `[min, max)` on each axis (max exclusive, as an edit's `op.box`). */
export interface VoxelBox {
  min: Vec3;
  max: Vec3;
}

/**
 * The level-0 voxels a read's stored voxels are made of: voxel i of level k is the mean of a
 * 2x2x2 group of level k-1 voxels, level by level, so of the level-0 voxels
 * `[2^k i, 2^k (i + 1))` on each axis and no others (`server/src/store/pyramid.rs`; a voxel
 * outside the volume is L whatever is edited).
 */
export function footprint(read: TileRead): VoxelBox {
  const s = 2 ** read.level;
  const [lo, hi] = read.voxels;
  return { min: lo.map((c) => c * s) as Vec3, max: hi.map((c) => (c + 1) * s) as Vec3 };
}

/** Whether two boxes of level-0 voxels (max exclusive) share a voxel. */
export function overlaps(a: VoxelBox, b: VoxelBox): boolean {
  return [0, 1, 2].every((i) => a.min[i]! < b.max[i]! && b.min[i]! < a.max[i]!);
}

/**
 * Whether a change confined to the level-0 voxels `boxes` can change what `reads` read (so the
 * mesh tile or strip made of them). False means its mesh at the new version is the one at the
 * old version: a tile's regular mesh, moves and strips are functions of the stored voxels it
 * reads alone (and whether the server meshes it at all, its `may_cross` bound, is decided by
 * those voxels' bricks: a bound that changed while the voxels did not only says again that no
 * surface crosses them, and none did).
 */
export function reachedBy(reads: readonly TileRead[], boxes: readonly VoxelBox[]): boolean {
  return reads.some((r) => {
    const f = footprint(r);
    return boxes.some((b) => overlaps(f, b));
  });
}

/**
 * Bounds of the lattice values of `level` computed from stored voxels within `[min, max]`
 * (`lattice::value_range`): Catmull-Rom's negative weights overshoot the range by a fraction of
 * its width, rounding adds a half; level 0 is exact.
 *
 * Bit for bit the server's bound, so that the viewer calls a tile or strip empty (no request)
 * exactly when the server's `may_cross` does: the weights and the overshoot in f64 with the same
 * operations in the same order (powers as products, as Rust's `s * s * s` and `powi(3)`), the
 * spill and both ends rounded to f32 (`Math.fround`) where Rust computes in f32. The port used
 * to stay in f64 and widen by a millionth of the spill, meant as "a hair more than the Rust
 * bound"; but an end's f32 rounding (up to half an f32 step, 0.002 near 65535) exceeds that
 * millionth, and it came out narrower than the server's for some ranges (`value_range.json`,
 * level 1 over [55719, 58118]: high 58927.636 against 58927.637; level 4 over
 * [64825, 65000]: 65083.498 against 65083.5, so at surface 65084 the server meshed a tile the
 * viewer called empty). Lattice values are integers and the iso value a half, so that f64 bound
 * still lay above every value that crosses and no surface was lost; but two copies of one rule
 * drift apart unseen unless a test can ask them to be equal.
 */
export function valueRange(level: number, min: number, max: number): [number, number] {
  if (level === 0) return [min, max];
  const f = Math.fround;
  const s = 0.5 + 1 / 2 ** (level + 1);
  const s2 = s * s;
  const s3 = s * s * s;
  const w = [(-s3 + 2 * s2 - s) / 2, (3 * s3 - 5 * s2 + 2) / 2, (-3 * s3 + 4 * s2 + s) / 2, (s3 - s2) / 2];
  const negative = w.filter((x) => x < 0).reduce((a, x) => a + -x, 0);
  const positive = 1 + negative;
  const overshoot = 3 * positive * positive * negative + negative * negative * negative;
  const spill = f(overshoot * f(max - min));
  return [f(f(min - spill) - 0.5), f(f(max + spill) + 0.5)];
}
