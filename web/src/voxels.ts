// Voxel bytes as values: a brick of density or of a channel (`api.brick`), a level in
// `format=voxels` and a batch entry all carry one little-endian value per voxel, x fastest,
// 1, 2, 4 or 8 bytes wide by the type. Typed arrays read the platform's byte order, and every
// platform a browser runs on is little-endian (mesh.ts relies on it too).

/** The types of density (u8, u16) and of channels (any of the four). */
export type VoxelType = "u8" | "u16" | "u32" | "u64";

/** Decoded voxels: u64 in a BigUint64Array, since a number holds integers exactly only to 2^53. */
export type Voxels = Uint8Array | Uint16Array | Uint32Array | BigUint64Array;

/** Bytes per voxel of each type. */
export const VOXEL_BYTES: Record<VoxelType, number> = { u8: 1, u16: 2, u32: 4, u64: 8 };

/**
 * The values of voxel bytes `bytes` of type `type`. Wider types want an offset and a length
 * that are multiples of their width: an unaligned view (a slice of a batch response, say) is
 * copied first; a length that is not a whole number of voxels is an error.
 */
export function decodeVoxels(bytes: ArrayBuffer | ArrayBufferView, type: VoxelType): Voxels {
  const width = VOXEL_BYTES[type];
  const view = ArrayBuffer.isView(bytes)
    ? new Uint8Array(bytes.buffer, bytes.byteOffset, bytes.byteLength)
    : new Uint8Array(bytes);
  if (view.byteLength % width !== 0) {
    throw new Error(`${view.byteLength} bytes are not a whole number of ${type} voxels`);
  }
  // A fresh copy starts at offset 0 of its own buffer, so it is aligned for every width.
  const aligned = view.byteOffset % width === 0 ? view : view.slice();
  const { buffer, byteOffset } = aligned;
  const n = aligned.byteLength / width;
  switch (type) {
    case "u8":
      return aligned;
    case "u16":
      return new Uint16Array(buffer, byteOffset, n);
    case "u32":
      return new Uint32Array(buffer, byteOffset, n);
    case "u64":
      return new BigUint64Array(buffer, byteOffset, n);
  }
}

/**
 * Voxel `i` of `voxels` exactly, as the server's JSON writes such values: a number, or for u64
 * a decimal string (every digit kept; the form of u64 segment ids). 0 past the end.
 */
export function voxelValue(voxels: Voxels, i: number): number | string {
  if (voxels instanceof BigUint64Array) return (voxels[i] ?? 0n).toString();
  return voxels[i] ?? 0;
}
