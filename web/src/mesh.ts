// Mesh tiles as the server sends them: the compact encoding (`proto/src/mesh.rs`), decoded
// into typed arrays that go to the GPU as they are (positions f32, normals snorm16, indices
// u16/u32), with the same checks as the Rust decoder so a bad response is an error, never an
// out-of-range draw.
//
// Where tiles of neighbouring levels meet, crack-free meshes need transition data (Transvoxel,
// as godot_voxel carries it): per vertex a secondary position and the faces whose boundary cells
// it lies in, and per face a transition strip. A tile stays one cacheable object; the viewer
// picks per tile a 6-bit mask of the faces that touch a coarser tile (`lod.ts` `stitchMasks`),
// moves the vertices of those faces to their secondary positions and draws those faces' strips.
// `TileMesh.transitions` is where a decoder of an encoding that carries it puts it; the
// renderer (`scene.ts`) applies the mask whenever it is there. Version 1 of the encoding carries
// none.

export interface TriangleSet {
  /** x, y, z per vertex, world coordinates. */
  positions: Float32Array;
  /** x, y, z per vertex, each `round(c * 32767)`. */
  normals: Int16Array;
  /** Three per triangle, counter-clockwise seen from outside. */
  indices: Uint16Array | Uint32Array;
}

export interface TransitionData {
  /** x, y, z per vertex of the regular mesh: where it goes when one of its faces is stitched. */
  secondary: Float32Array;
  /** Per vertex of the regular mesh: the faces (bits as in `lod.ts` `FACES`) it lies along. */
  vertexFaces: Uint8Array;
  /** Per face (order of `FACES`): the triangles drawn when that face touches a coarser tile. */
  strips: readonly TriangleSet[];
}

export interface TileMesh extends TriangleSet {
  min: [number, number, number];
  max: [number, number, number];
  transitions: TransitionData | null;
  /** Bytes the tile takes in memory (for the cache's budget). */
  bytes: number;
}

const MAGIC = 0x534d5649; // "IVMS" little endian
const HEADER = 40;

export class MeshFormatError extends Error {}

/** Decodes a compact mesh; throws `MeshFormatError` on anything the Rust decoder refuses. */
export function decodeCompact(buffer: ArrayBuffer): TileMesh {
  const view = new DataView(buffer);
  const fail = (why: string): never => {
    throw new MeshFormatError(`compact mesh: ${why}`);
  };
  if (buffer.byteLength < HEADER) fail(`${buffer.byteLength} bytes are shorter than the header`);
  if (view.getUint32(0, true) !== MAGIC) fail("bad magic");
  const version = view.getUint16(4, true);
  if (version !== 1) fail(`unsupported version ${version}`);
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
  const at = HEADER + n * 18;
  let indices: Uint16Array | Uint32Array;
  if (!wide) indices = new Uint16Array(buffer, at, m);
  else if (at % 4 === 0) indices = new Uint32Array(buffer, at, m);
  else indices = new Uint32Array(buffer.slice(at, at + m * 4));
  for (let i = 0; i < m; i++) {
    if ((indices[i] ?? 0) >= n) fail(`index ${indices[i]} >= vertex count ${n}`);
  }
  return {
    positions,
    normals,
    indices,
    min,
    max,
    transitions: null,
    bytes: buffer.byteLength,
  };
}
