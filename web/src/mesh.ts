// Mesh tiles as the server sends them: the compact encoding (`docs/mesh-encoding.md`,
// `proto/src/mesh.rs`), decoded into typed arrays that go to the GPU as they are (positions
// f32, normals snorm16, indices u16/u32), with the same checks as the Rust decoder so a bad
// response is an error, never an out-of-range draw.
//
// Where tiles of neighbouring levels meet, crack-free meshes need transition data (Transvoxel,
// as godot_voxel carries it; `docs/lod-meshes.md`). A tile stays one cacheable object: version 2
// of the encoding carries, after the regular mesh, the vertices only the transition strips use,
// the moves ("move vertex i by d when the faces in f touch a coarser tile") and one strip per
// face. The viewer picks per tile a 6-bit mask of the faces that touch a coarser tile
// (`lod.ts` `stitchMasks`) and draws `stitch(tile, mask)`: the regular mesh with those moves
// applied and those faces' strips appended, exactly as `proto::mesh::stitch` does.

export interface TriangleSet {
  /** x, y, z per vertex, world coordinates. */
  positions: Float32Array;
  /** x, y, z per vertex, each `round(c * 32767)`. */
  normals: Int16Array;
  /** Three per triangle, counter-clockwise seen from outside. */
  indices: Uint16Array | Uint32Array;
}

export interface TransitionData {
  /** x, y, z per transition vertex (their indices follow the regular vertices'). */
  positions: Float32Array;
  /** x, y, z per transition vertex, snorm16. */
  normals: Int16Array;
  /** Per move: the vertex it moves (regular vertices first, then transition ones). */
  moveVertex: Uint32Array;
  /** Per move: the faces (bits as in `lod.ts` `FACES`) that must all be stitched. */
  moveFaces: Uint8Array;
  /** x, y, z per move: what is added to the vertex's position. */
  moveOffset: Float32Array;
  /** Per face (order of `FACES`): the strip's triangles, indices as the moves'. */
  strips: ReadonlyArray<Uint16Array | Uint32Array>;
}

export interface TileMesh extends TriangleSet {
  min: [number, number, number];
  max: [number, number, number];
  /** Version 2 tiles: what joins the tile to coarser neighbours (null in version 1). */
  transitions: TransitionData | null;
  /** Bytes the tile takes in memory (for the cache's budget). */
  bytes: number;
}

const MAGIC = 0x534d5649; // "IVMS" little endian
const HEADER = 40;
/** t, k, six strip counts. */
const SECTION_HEADER = 32;
const MOVE_BYTES = 20;

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
 * Decodes a compact mesh tile, version 1 (no transition data) or 2; throws `MeshFormatError` on
 * anything the Rust decoder (`decode_tile`) refuses.
 */
export function decodeTile(buffer: ArrayBuffer): TileMesh {
  const view = new DataView(buffer);
  const fail = (why: string): never => {
    throw new MeshFormatError(`compact mesh: ${why}`);
  };
  if (buffer.byteLength < HEADER) fail(`${buffer.byteLength} bytes are shorter than the header`);
  if (view.getUint32(0, true) !== MAGIC) fail("bad magic");
  const version = view.getUint16(4, true);
  if (version !== 1 && version !== 2) fail(`unsupported version ${version}`);
  const wide = (view.getUint16(6, true) & 1) === 1;
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
  // Version 2: the regular triangles name regular vertices only.
  const indices = readIndices(buffer, at, m, wide, n, fail);
  at = Math.ceil((at + m * indexBytes) / 4) * 4;
  const transitions = version === 2 ? decodeSection(buffer, at, n, wide, fail) : null;
  return { positions, normals, indices, min, max, transitions, bytes: buffer.byteLength };
}

/** The transition section at `at` of a tile with `n` regular vertices. */
function decodeSection(
  buffer: ArrayBuffer,
  at: number,
  n: number,
  wide: boolean,
  fail: (why: string) => never,
): TransitionData {
  const view = new DataView(buffer);
  if (at + SECTION_HEADER > buffer.byteLength) fail("the transition section is cut short");
  const t = view.getUint32(at, true);
  const k = view.getUint32(at + 4, true);
  const counts = [0, 1, 2, 3, 4, 5].map((face) => view.getUint32(at + 8 + 4 * face, true));
  const indexBytes = wide ? 4 : 2;
  const stripIndices = counts.reduce((a, c) => a + c, 0);
  const vertexBytes = Math.ceil((t * 18) / 4) * 4;
  const need = SECTION_HEADER + vertexBytes + k * MOVE_BYTES + stripIndices * indexBytes;
  if (counts.some((c) => c % 3 !== 0)) fail("a strip's index count is not a multiple of 3");
  if (at + need > buffer.byteLength) {
    fail(`${t} transition vertices, ${k} moves and ${stripIndices} strip indices do not fit`);
  }
  let p = at + SECTION_HEADER;
  const positions = new Float32Array(buffer.slice(p, p + t * 12));
  const normals = new Int16Array(buffer.slice(p + t * 12, p + t * 18));
  p += vertexBytes;
  const all = n + t;
  const moveVertex = new Uint32Array(k);
  const moveFaces = new Uint8Array(k);
  const moveOffset = new Float32Array(k * 3);
  for (let i = 0; i < k; i++, p += MOVE_BYTES) {
    const v = view.getUint32(p, true);
    const faces = view.getUint8(p + 4);
    if (v >= all) fail(`moved vertex ${v} >= vertex count ${all}`);
    if (faces === 0 || faces >= 64) fail(`move face mask ${faces} is not in 1..63`);
    moveVertex[i] = v;
    moveFaces[i] = faces;
    for (let c = 0; c < 3; c++) moveOffset[3 * i + c] = view.getFloat32(p + 8 + 4 * c, true);
  }
  const strips = counts.map((count) => {
    const s = readIndices(buffer, p, count, wide, all, fail);
    p += count * indexBytes;
    return s;
  });
  return { positions, normals, moveVertex, moveFaces, moveOffset, strips };
}

/**
 * Tile `tile` as drawn next to its neighbours (`proto::mesh::stitch`): `mask` has bit f set
 * when face f touches a coarser tile. The regular mesh with the moves whose faces are all in
 * `mask` applied (in order), and the strips of the faces in `mask` appended with the transition
 * vertices they use (numbered after the regular ones in order of first use). Mask 0, or a tile
 * without transition data, gives the regular mesh.
 */
export function stitch(tile: TileMesh, mask: number): TriangleSet {
  const tr = tile.transitions;
  if (!tr || mask === 0) {
    return { positions: tile.positions, normals: tile.normals, indices: tile.indices };
  }
  const n = tile.positions.length / 3;
  const t = tr.positions.length / 3;
  const remap = new Int32Array(t).fill(-1);
  const stripTriangles: number[] = [];
  let added = 0;
  const order: number[] = [];
  tr.strips.forEach((strip, face) => {
    if ((mask & (1 << face)) === 0) return;
    for (const i of strip) {
      if (i < n) stripTriangles.push(i);
      else {
        const j = i - n;
        if ((remap[j] ?? -1) < 0) {
          remap[j] = n + added++;
          order.push(j);
        }
        stripTriangles.push(remap[j] ?? 0);
      }
    }
  });
  const count = n + added;
  const positions = new Float32Array(count * 3);
  const normals = new Int16Array(count * 3);
  positions.set(tile.positions);
  normals.set(tile.normals);
  order.forEach((j, k) => {
    positions.set(tr.positions.subarray(3 * j, 3 * j + 3), 3 * (n + k));
    normals.set(tr.normals.subarray(3 * j, 3 * j + 3), 3 * (n + k));
  });
  for (let i = 0; i < tr.moveVertex.length; i++) {
    const faces = tr.moveFaces[i] ?? 0;
    if ((faces & ~mask) !== 0) continue;
    const v = tr.moveVertex[i] ?? 0;
    const target = v < n ? v : (remap[v - n] ?? -1);
    if (target < 0) continue;
    for (let c = 0; c < 3; c++) {
      // f32 arithmetic, as Rust's `+=` on f32.
      positions[3 * target + c] = Math.fround(
        (positions[3 * target + c] ?? 0) + (tr.moveOffset[3 * i + c] ?? 0),
      );
    }
  }
  const total = tile.indices.length + stripTriangles.length;
  const indices = count > 65536 ? new Uint32Array(total) : new Uint16Array(total);
  indices.set(tile.indices);
  indices.set(stripTriangles, tile.indices.length);
  return { positions, normals, indices };
}

/** Triangles the tile draws with `mask`. */
export function stitchedTriangles(tile: TileMesh, mask: number): number {
  let count = tile.indices.length;
  tile.transitions?.strips.forEach((s, face) => {
    if ((mask & (1 << face)) !== 0) count += s.length;
  });
  return count / 3;
}
