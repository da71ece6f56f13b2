// Mesh tiles as the server sends them: the compact encoding (`docs/mesh-encoding.md`,
// `proto/src/mesh.rs`), decoded into typed arrays that go to the GPU as they are (positions
// f32, normals snorm16, indices u16/u32), with the same checks as the Rust decoder so a bad
// response is an error, never an out-of-range draw.
//
// Where tiles of neighbouring levels meet, crack-free meshes need transition data (Transvoxel,
// as godot_voxel carries it; `docs/lod-meshes.md`). A tile stays one cacheable object: version 3
// of the encoding carries, after the regular mesh, the moves ("move vertex i by d along face f's
// axis when face f touches a coarser tile"); the strip of each face is an object of its own
// (`.../strips/{face}`, a plain mesh, version 1) whose vertices are already at their drawn
// positions. The viewer picks per tile a 6-bit mask of the faces that touch a coarser tile
// (`lod.ts` `stitchMasks`), fetches those faces' strips and draws `stitch(tile, mask, strips)`:
// the regular mesh with those moves applied and those strips appended, exactly as
// `proto::mesh::stitch` does.

export interface TriangleSet {
  /** x, y, z per vertex, world coordinates. */
  positions: Float32Array;
  /** x, y, z per vertex, each `round(c * 32767)`. */
  normals: Int16Array;
  /** Three per triangle, counter-clockwise seen from outside. */
  indices: Uint16Array | Uint32Array;
  /**
   * Four bytes per vertex when asked for with a channel (`?channel=`): the values at the two
   * ends of the lattice edge the vertex lies on, the weight of the second (0..255), and 0.
   */
  materials?: Uint8Array | null;
}

export interface Moves {
  /** Per move: the vertex it moves. */
  vertex: Uint32Array;
  /** Per move: the face (0..5, order of `lod.ts` `FACES`) that must be stitched. */
  face: Uint8Array;
  /** Per move: what is added to the vertex's coordinate on the face's axis. */
  distance: Float32Array;
}

export interface TileMesh extends TriangleSet {
  min: [number, number, number];
  max: [number, number, number];
  /** Version 3 tiles: the moves that make room for the strips (null in version 1). */
  moves: Moves | null;
  /** Bytes the tile takes in memory (for the cache's budget). */
  bytes: number;
}

const MAGIC = 0x534d5649; // "IVMS" little endian
const HEADER = 40;
/** Six per-face move counts. */
const MOVES_HEADER = 24;
const MOVE_BYTES = 8;

export class MeshFormatError extends Error {}

/** Indices `count` at `at`, u16 or u32, copied when u32 is unaligned; each below `limit`. */
function readIndices(
  buffer: ArrayBuffer,
  at: number,
  count: number,
  wide: boolean,
  limit: number,
  fail: (why: string) => never,
): Uint16Array | Uint32Array {
  let indices: Uint16Array | Uint32Array;
  if (!wide) {
    indices = at % 2 === 0 ? new Uint16Array(buffer, at, count) : new Uint16Array(buffer.slice(at, at + count * 2));
  } else if (at % 4 === 0) indices = new Uint32Array(buffer, at, count);
  else indices = new Uint32Array(buffer.slice(at, at + count * 4));
  for (let i = 0; i < count; i++) {
    if ((indices[i] ?? 0) >= limit) fail(`index ${indices[i]} >= vertex count ${limit}`);
  }
  return indices;
}

/**
 * Decodes a compact mesh tile, version 1 (no moves) or 3, or with `strip` a transition strip
 * (version 1 only); throws `MeshFormatError` on anything the Rust decoders (`decode_tile`,
 * `decode_strip`) refuse.
 */
export function decodeTile(buffer: ArrayBuffer, strip = false): TileMesh {
  const view = new DataView(buffer);
  const fail = (why: string): never => {
    throw new MeshFormatError(`compact mesh: ${why}`);
  };
  if (buffer.byteLength < HEADER) fail(`${buffer.byteLength} bytes are shorter than the header`);
  if (view.getUint32(0, true) !== MAGIC) fail("bad magic");
  const version = view.getUint16(4, true);
  if (version !== 1 && (strip || version !== 3)) fail(`unsupported version ${version}`);
  const flags = view.getUint16(6, true);
  const wide = (flags & 1) === 1;
  const n = view.getUint32(8, true);
  const m = view.getUint32(12, true);
  const indexBytes = wide ? 4 : 2;
  if (m % 3 !== 0 || HEADER + n * 18 + m * indexBytes > buffer.byteLength) {
    fail(`${n} vertices and ${m} indices do not fit ${buffer.byteLength} bytes`);
  }
  const f = (at: number) => view.getFloat32(at, true);
  const min: [number, number, number] = [f(16), f(20), f(24)];
  const max: [number, number, number] = [f(28), f(32), f(36)];
  // Views where the alignment allows (always for positions and normals), copies otherwise.
  const positions = new Float32Array(buffer, HEADER, n * 3);
  const normals = new Int16Array(buffer, HEADER + n * 12, n * 3);
  let at = HEADER + n * 18;
  const indices = readIndices(buffer, at, m, wide, n, fail);
  at = Math.ceil((at + m * indexBytes) / 4) * 4;
  let materials: Uint8Array | null = null;
  if ((flags & 2) !== 0) {
    if (at + n * 4 > buffer.byteLength) fail("the material section is cut short");
    materials = new Uint8Array(buffer, at, n * 4);
    for (let i = 0; i < n; i++) {
      if (materials[4 * i + 3] !== 0) fail(`vertex ${i}'s material padding is not 0`);
    }
    at += n * 4;
  }
  const moves = version === 3 ? decodeMoves(buffer, at, n, fail) : null;
  return { positions, normals, indices, materials, min, max, moves, bytes: buffer.byteLength };
}

/** A transition strip (`decode_strip`): a plain mesh, version 1. */
export function decodeStrip(buffer: ArrayBuffer): TileMesh {
  return decodeTile(buffer, true);
}

/** The move section at `at` of a tile with `n` vertices. */
function decodeMoves(buffer: ArrayBuffer, at: number, n: number, fail: (why: string) => never): Moves {
  const view = new DataView(buffer);
  if (at + MOVES_HEADER > buffer.byteLength) fail("the move section is cut short");
  const counts = [0, 1, 2, 3, 4, 5].map((face) => view.getUint32(at + 4 * face, true));
  const k = counts.reduce((a, c) => a + c, 0);
  if (at + MOVES_HEADER + k * MOVE_BYTES > buffer.byteLength) fail(`${k} moves do not fit`);
  const vertex = new Uint32Array(k);
  const face = new Uint8Array(k);
  const distance = new Float32Array(k);
  let p = at + MOVES_HEADER;
  let i = 0;
  counts.forEach((count, f) => {
    for (let j = 0; j < count; j++, i++, p += MOVE_BYTES) {
      const v = view.getUint32(p, true);
      const d = view.getFloat32(p + 4, true);
      if (v >= n) fail(`moved vertex ${v} >= vertex count ${n}`);
      if (!Number.isFinite(d)) fail(`move distance ${d} is not finite`);
      vertex[i] = v;
      face[i] = f;
      distance[i] = d;
    }
  });
  return { vertex, face, distance };
}

/**
 * Tile `tile` as drawn next to its neighbours (`proto::mesh::stitch`): `mask` has bit f set
 * when face f touches a coarser tile. The regular mesh with the moves of the faces in `mask`
 * applied (in order, in f32), and the strips of those faces (`strips[f]`; missing ones are
 * skipped) appended as they are. Mask 0 gives the regular mesh.
 */
export function stitch(
  tile: TileMesh,
  mask: number,
  strips: ReadonlyArray<TriangleSet | null | undefined> = [],
): TriangleSet {
  const drawn = [0, 1, 2, 3, 4, 5]
    .filter((f) => (mask & (1 << f)) !== 0)
    .map((f) => strips[f])
    .filter((s): s is TriangleSet => !!s);
  const moves = tile.moves;
  const moved = moves !== null && moves.face.some((f) => (mask & (1 << f)) !== 0);
  if (!moved && drawn.length === 0) {
    return { positions: tile.positions, normals: tile.normals, indices: tile.indices, materials: tile.materials ?? null };
  }
  const n = tile.positions.length / 3;
  const count = drawn.reduce((a, s) => a + s.positions.length / 3, n);
  const positions = new Float32Array(count * 3);
  const normals = new Int16Array(count * 3);
  positions.set(tile.positions);
  normals.set(tile.normals);
  // Materials when the tile has them (a strip without gets zeros: none).
  const materials = tile.materials ? new Uint8Array(count * 4) : null;
  materials?.set(tile.materials!);
  if (moves) {
    for (let i = 0; i < moves.vertex.length; i++) {
      const f = moves.face[i] ?? 0;
      if ((mask & (1 << f)) === 0) continue;
      const at = 3 * (moves.vertex[i] ?? 0) + (f >> 1);
      // f32 arithmetic, as Rust's `+=` on f32.
      positions[at] = Math.fround((positions[at] ?? 0) + (moves.distance[i] ?? 0));
    }
  }
  const total = drawn.reduce((a, s) => a + s.indices.length, tile.indices.length);
  const indices = count > 65536 ? new Uint32Array(total) : new Uint16Array(total);
  indices.set(tile.indices);
  let base = n;
  let at = tile.indices.length;
  for (const s of drawn) {
    positions.set(s.positions, 3 * base);
    normals.set(s.normals, 3 * base);
    if (materials && s.materials) materials.set(s.materials, 4 * base);
    for (let i = 0; i < s.indices.length; i++) indices[at + i] = (s.indices[i] ?? 0) + base;
    at += s.indices.length;
    base += s.positions.length / 3;
  }
  return { positions, normals, indices, materials };
}

/** Triangles the tile draws with `mask` and `strips`. */
export function stitchedTriangles(
  tile: TileMesh,
  mask: number,
  strips: ReadonlyArray<TriangleSet | null | undefined> = [],
): number {
  let count = tile.indices.length;
  strips.forEach((s, face) => {
    if (s && (mask & (1 << face)) !== 0) count += s.indices.length;
  });
  return count / 3;
}
