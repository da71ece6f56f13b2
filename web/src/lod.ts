// Which tiles a camera needs: a port of `proto/src/lod.rs` (the spherical detail bias, balanced
// so that tiles that touch differ by at most one level, and each tile's face mask), kept equal
// to it by the vectors the Rust tests write to `web/test-vectors/lod.json`.
//
// The Rust code computes in f32. JavaScript numbers are f64, so every operation below is
// rounded back to f32 with `Math.fround`: for +, -, *, / and sqrt of f32 operands, rounding the
// exact f64 result once more to f32 gives the f32 result bit for bit (f64 has more than twice
// f32's precision plus two bits), so the comparisons against the radii agree with Rust's even on
// the boundary.

const f = Math.fround;

/** The address of one brick (and of one mesh tile): a level and a position in its grid. */
export interface TileKey {
  level: number;
  x: number;
  y: number;
  z: number;
}

/** `level/x/y/z`, the key's text form (as in the API's paths). */
export function keyText(k: TileKey): string {
  return `${k.level}/${k.x}/${k.y}/${k.z}`;
}

/** The order of `BrickKey` in Rust: level, then x, y, z. */
export function compareKeys(a: TileKey, b: TileKey): number {
  return a.level - b.level || a.x - b.x || a.y - b.y || a.z - b.z;
}

/** The shape of a volume's brick octree (`proto/src/layout.rs`): levels and their grids. */
export class Layout {
  readonly dims: readonly [number, number, number];
  readonly brick: number;
  readonly grids: ReadonlyArray<readonly [number, number, number]>;

  constructor(dims: readonly [number, number, number], brick: number) {
    if (dims.some((d) => !Number.isInteger(d) || d <= 0)) {
      throw new Error(`volume dimensions ${dims.join("x")} are not positive integers`);
    }
    if (!Number.isInteger(brick) || brick < 2 || brick > 256 || (brick & (brick - 1)) !== 0) {
      throw new Error(`brick size ${brick} is not a power of two in [2, 256]`);
    }
    this.dims = dims;
    this.brick = brick;
    const grids: Array<[number, number, number]> = [];
    for (let level = 0; ; level++) {
      const span = brick * 2 ** level;
      const g: [number, number, number] = [
        Math.ceil(dims[0] / span),
        Math.ceil(dims[1] / span),
        Math.ceil(dims[2] / span),
      ];
      grids.push(g);
      if (g[0] === 1 && g[1] === 1 && g[2] === 1) break;
    }
    this.grids = grids;
  }

  /** Levels of detail, level 0 up to the single root brick. */
  get levels(): number {
    return this.grids.length;
  }

  grid(level: number): readonly [number, number, number] {
    const g = this.grids[level];
    if (g === undefined) throw new Error(`level ${level} out of range`);
    return g;
  }

  contains(k: TileKey): boolean {
    const g = this.grids[k.level];
    return (
      g !== undefined &&
      k.x >= 0 && k.y >= 0 && k.z >= 0 &&
      k.x < g[0] && k.y < g[1] && k.z < g[2]
    );
  }

  /** The up to 8 bricks of the next finer level that `k` is made from (none at level 0). */
  children(k: TileKey): TileKey[] {
    if (k.level === 0) return [];
    const out: TileKey[] = [];
    for (let octant = 0; octant < 8; octant++) {
      const c = {
        level: k.level - 1,
        x: k.x * 2 + (octant & 1),
        y: k.y * 2 + ((octant >> 1) & 1),
        z: k.z * 2 + (octant >> 2),
      };
      if (this.contains(c)) out.push(c);
    }
    return out;
  }

  /** The tile of `k`'s level displaced by `d`, if it lies in the grid. */
  neighbour(k: TileKey, d: readonly number[]): TileKey | null {
    const n = { level: k.level, x: k.x + (d[0] ?? 0), y: k.y + (d[1] ?? 0), z: k.z + (d[2] ?? 0) };
    return this.contains(n) ? n : null;
  }

  /** The brick of `level` (>= k.level) that covers `k`. */
  ancestor(k: TileKey, level: number): TileKey {
    const s = 2 ** (level - k.level);
    return { level, x: Math.floor(k.x / s), y: Math.floor(k.y / s), z: Math.floor(k.z / s) };
  }
}

/**
 * The distance from `camera` to the nearest point of tile `k`'s box, in world units (voxel
 * coordinates times `voxelScale`); 0 inside the box. `lod::tile_distance` in f32.
 */
export function tileDistance(
  layout: Layout,
  voxelScale: readonly number[],
  k: TileKey,
  camera: readonly number[],
): number {
  const span = f(f(layout.brick) * f(2 ** k.level));
  let d2 = f(0);
  const pos = [k.x, k.y, k.z];
  for (let a = 0; a < 3; a++) {
    const c = f(pos[a] ?? 0);
    const s = f(voxelScale[a] ?? 1);
    const cam = f(camera[a] ?? 0);
    const lo = f(f(c * span) * s);
    const hi = f(f(f(c + 1) * span) * s);
    const d = cam < lo ? f(lo - cam) : cam > hi ? f(cam - hi) : 0;
    d2 = f(d2 + f(d * d));
  }
  return f(Math.sqrt(d2));
}

/**
 * How far, as a fraction of its level's radius, a tile out of the view frustum is refined: at
 * half the reach it ends about one level coarser than a tile in view at the same distance. It is
 * there for when the camera turns, drawn nowhere until then, so it need not be as fine as
 * what is on screen (a level coarser: an eighth as many tiles there; fetched after those in view).
 */
export const OUT_OF_VIEW_REACH = 0.5;

/**
 * The tiles the spherical detail bias selects, sorted: with radii `r0 < r1 < ... < r(n-1)`,
 * level k where the tile's nearest point lies within `r(k)` of the camera, level n (or the
 * coarsest) beyond the last radius. `lod::adaptive_tiles`: walking down from the root, a tile of
 * level k+1 is refined when it is within `r(k)`, and always while k+1 > n. With `inView`, a tile
 * it says is out of the view frustum is refined only within `OUT_OF_VIEW_REACH` of that radius;
 * without it every tile counts as in view (the Rust streamer's and the server's selection).
 */
export function adaptiveTiles(
  layout: Layout,
  voxelScale: readonly number[],
  camera: readonly number[],
  radii: readonly number[],
  inView?: (k: TileKey) => boolean,
): TileKey[] {
  const top = layout.levels - 1;
  const g = layout.grid(top);
  const stack: TileKey[] = [];
  for (let z = 0; z < g[2]; z++) {
    for (let y = 0; y < g[1]; y++) {
      for (let x = 0; x < g[0]; x++) stack.push({ level: top, x, y, z });
    }
  }
  const r = radii.map(f);
  const out: TileKey[] = [];
  for (let k = stack.pop(); k !== undefined; k = stack.pop()) {
    const reach = (r[k.level - 1] ?? NaN) * (inView && !inView(k) ? OUT_OF_VIEW_REACH : 1);
    const refine =
      k.level > r.length || (k.level > 0 && tileDistance(layout, voxelScale, k, camera) <= reach);
    if (refine) stack.push(...layout.children(k));
    else out.push(k);
  }
  return out.sort(compareKeys);
}

/**
 * The tiles to stitch for a camera (`lod::balanced_tiles`): `adaptiveTiles`, refined until no
 * two tiles that touch (by a face, an edge or a corner) differ by more than one level: a tile
 * with a neighbour two or more levels finer is split into its children, repeatedly. Sorted.
 */
export function balancedTiles(
  layout: Layout,
  voxelScale: readonly number[],
  camera: readonly number[],
  radii: readonly number[],
  inView?: (k: TileKey) => boolean,
): TileKey[] {
  return balance(layout, adaptiveTiles(layout, voxelScale, camera, radii, inView));
}

/** `lod::balance`: refines `tiles` (covering the volume once) until it is 2:1 balanced. */
export function balance(layout: Layout, tiles: readonly TileKey[]): TileKey[] {
  const set = new Map(tiles.map((k) => [keyText(k), k]));
  const covering = (k: TileKey): TileKey | undefined => {
    for (let level = k.level; level < layout.levels; level++) {
      const a = set.get(keyText(layout.ancestor(k, level)));
      if (a) return a;
    }
    return undefined;
  };
  const around: number[][] = [];
  for (let i = 0; i < 27; i++) {
    const d = [(i % 3) - 1, (Math.floor(i / 3) % 3) - 1, Math.floor(i / 9) - 1];
    if (d.some((c) => c !== 0)) around.push(d);
  }
  const work = [...tiles];
  for (let fine = work.pop(); fine !== undefined; fine = work.pop()) {
    if (!set.has(keyText(fine))) continue;
    for (const d of around) {
      const n = layout.neighbour(fine, d);
      const coarse = n && covering(n);
      if (coarse && coarse.level >= fine.level + 2) {
        set.delete(keyText(coarse));
        for (const c of layout.children(coarse)) {
          set.set(keyText(c), c);
          work.push(c);
        }
        work.push(fine);
        break;
      }
    }
  }
  return [...set.values()].sort(compareKeys);
}

/**
 * Radii from a screen-space error target, as the Rust streamer derives them
 * (`StreamerConfig::radii_for_screen_error`): level k's tiles have a geometric error of about
 * 2^k voxels, so level k+1 is good enough beyond `2^(k+1) s H / (2 tan(fov/2) maxErrorPx)`.
 */
export function radiiForScreenError(
  levels: number,
  voxelScale: readonly number[],
  fovYRadians: number,
  viewportHeightPx: number,
  maxErrorPx: number,
): number[] {
  const s = voxelScale.reduce((a, b) => Math.max(a, Math.abs(b)), 0);
  const perWorld = viewportHeightPx / (2 * Math.tan(fovYRadians / 2) * maxErrorPx);
  if (!(Number.isFinite(perWorld) && perWorld > 0 && Number.isFinite(s) && s > 0)) return [];
  const out: number[] = [];
  for (let k = 0; k + 1 < levels; k++) out.push(2 ** (k + 1) * s * perWorld);
  return out;
}

/** Faces of a tile in the order of the stitch mask's bits: -x, +x, -y, +y, -z, +z. */
export const FACES: ReadonlyArray<readonly [number, number, number]> = [
  [-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1],
];

/**
 * For each selected tile, the 6-bit mask of its faces that touch a coarser selected tile (bit i
 * for `FACES[i]`): where a mesh tile carries transition data (crack-free level-of-detail
 * meshes), the renderer moves the vertices along those faces to their secondary positions and
 * draws those faces' transition strips (`mesh.ts` `stitch`). Faces on the volume's boundary, or
 * touching tiles of the same or a finer level, are 0. `lod::face_masks`; `tiles` must be a
 * balanced selection covering the volume once (as `balancedTiles` returns it).
 */
export function stitchMasks(layout: Layout, tiles: readonly TileKey[]): Map<string, number> {
  const selected = new Set(tiles.map(keyText));
  const out = new Map<string, number>();
  for (const k of tiles) {
    let mask = 0;
    FACES.forEach(([dx, dy, dz], bit) => {
      const n = { level: k.level, x: k.x + dx, y: k.y + dy, z: k.z + dz };
      if (!layout.contains(n)) return;
      for (let level = k.level + 1; level < layout.levels; level++) {
        if (selected.has(keyText(layout.ancestor(n, level)))) {
          mask |= 1 << bit;
          return;
        }
      }
    });
    out.set(keyText(k), mask);
  }
  return out;
}
