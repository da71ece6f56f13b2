// Builds compact mesh bytes by hand, following the layout in proto/src/mesh.rs (not the code
// under test), for the decoder's and the streamer's tests.

export function compactMesh(
  positions: number[][],
  normals: number[][],
  indices: number[],
  options: { version?: number; wide?: boolean; materials?: number[][] } = {},
): ArrayBuffer {
  const n = positions.length;
  const m = indices.length;
  const wide = options.wide ?? n > 65536;
  const size = 40 + n * 18 + m * (wide ? 4 : 2);
  // The material section (flag bit 1): four bytes per vertex after the indices' padding.
  const materials = options.materials;
  const buffer = new ArrayBuffer(Math.ceil(size / 4) * 4 + (materials ? 4 * n : 0));
  const v = new DataView(buffer);
  [0x49, 0x56, 0x4d, 0x53].forEach((b, i) => v.setUint8(i, b)); // "IVMS"
  v.setUint16(4, options.version ?? 1, true);
  v.setUint16(6, (wide ? 1 : 0) | (materials ? 2 : 0), true);
  v.setUint32(8, n, true);
  v.setUint32(12, m, true);
  const lo = [0, 1, 2].map((a) => Math.min(...positions.map((p) => p[a] ?? 0)));
  const hi = [0, 1, 2].map((a) => Math.max(...positions.map((p) => p[a] ?? 0)));
  [...lo, ...hi].forEach((c, i) => v.setFloat32(16 + 4 * i, n ? c : 0, true));
  let at = 40;
  for (const p of positions) for (const c of p) (v.setFloat32(at, c, true), (at += 4));
  for (const q of normals) for (const c of q) (v.setInt16(at, Math.round(c * 32767), true), (at += 2));
  for (const i of indices) {
    if (wide) v.setUint32(at, i, true);
    else v.setUint16(at, i, true);
    at += wide ? 4 : 2;
  }
  at = Math.ceil(at / 4) * 4;
  for (const q of materials ?? []) for (const b of q) v.setUint8(at++, b);
  return buffer;
}

/** One triangle in the z = 0 plane, facing +z. */
export function triangle(indices = [0, 1, 2], options: { wide?: boolean } = {}): ArrayBuffer {
  const normal = [0, 0, 1];
  return compactMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [normal, normal, normal], indices, options);
}
