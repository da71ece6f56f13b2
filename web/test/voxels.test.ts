import { describe, expect, it } from "vitest";
import { decodeVoxels, voxelValue } from "../src/voxels";

// Little-endian bytes written out by hand, lowest byte first.
const U16 = [0x01, 0x00, 0xff, 0xff, 0x34, 0x12];
const U32 = [0x78, 0x56, 0x34, 0x12, 0xff, 0xff, 0xff, 0xff, 0x00, 0x00, 0x01, 0x00];
const U64 = [
  // 2^64 - 1
  0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff,
  // 2^53 + 1 = 0x0020_0000_0000_0001
  0x01, 0x00, 0x00, 0x00, 0x00, 0x00, 0x20, 0x00,
  // 2^53 + 2
  0x02, 0x00, 0x00, 0x00, 0x00, 0x00, 0x20, 0x00,
  // 5
  0x05, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
];
const U64_VALUES = ["18446744073709551615", "9007199254740993", "9007199254740994", "5"];

/** `bytes` in a fresh ArrayBuffer, as `api.brick` gives them. */
const buffer = (bytes: number[]) => new Uint8Array(bytes).buffer;

/** `bytes` as a view starting `skip` bytes into a larger buffer (unaligned for skip 1, 3, ...). */
function at(skip: number, bytes: number[]): Uint8Array {
  return new Uint8Array([...Array<number>(skip).fill(0xaa), ...bytes, 0xbb]).subarray(skip, skip + bytes.length);
}

describe("voxel bytes as values", () => {
  it("reads u8 and u16 as numbers", () => {
    expect([...decodeVoxels(buffer([0, 1, 255]), "u8")]).toEqual([0, 1, 255]);
    expect([...decodeVoxels(buffer(U16), "u16")]).toEqual([1, 65535, 0x1234]);
  });

  it("reads u32 as numbers", () => {
    expect([...decodeVoxels(buffer(U32), "u32")]).toEqual([0x12345678, 4294967295, 65536]);
  });

  it("reads u64 as bigints, every digit kept past 2^53", () => {
    const v = decodeVoxels(buffer(U64), "u64");
    expect(v).toBeInstanceOf(BigUint64Array);
    expect([...v]).toEqual([18446744073709551615n, 9007199254740993n, 9007199254740994n, 5n]);
    expect([0, 1, 2, 3].map((i) => voxelValue(v, i))).toEqual(U64_VALUES);
  });

  it("reads unaligned views (a slice of a larger response) the same", () => {
    for (const skip of [1, 2, 3, 5, 8]) {
      expect([...decodeVoxels(at(skip, U16), "u16")], `u16 at ${skip}`).toEqual([1, 65535, 0x1234]);
      expect([...decodeVoxels(at(skip, U32), "u32")], `u32 at ${skip}`).toEqual([0x12345678, 4294967295, 65536]);
      const v = decodeVoxels(at(skip, U64), "u64");
      expect([0, 1, 2, 3].map((i) => voxelValue(v, i)), `u64 at ${skip}`).toEqual(U64_VALUES);
    }
    expect([...decodeVoxels(at(3, [7, 8, 9]), "u8")]).toEqual([7, 8, 9]);
  });

  it("refuses bytes that are not a whole number of voxels", () => {
    expect(() => decodeVoxels(buffer([1, 2, 3]), "u16")).toThrow(/u16/);
    expect(() => decodeVoxels(buffer([1, 2, 3, 4, 5, 6]), "u32")).toThrow(/u32/);
    expect(() => decodeVoxels(buffer(U64.slice(0, 12)), "u64")).toThrow(/u64/);
  });

  it("gives each value exactly: numbers up to u32, decimal strings for u64", () => {
    expect(voxelValue(decodeVoxels(buffer(U32), "u32"), 1)).toBe(4294967295);
    expect(voxelValue(decodeVoxels(buffer([9]), "u8"), 0)).toBe(9);
    // Past the end: 0, in the type's form.
    expect(voxelValue(decodeVoxels(buffer([9]), "u8"), 4)).toBe(0);
    expect(voxelValue(decodeVoxels(buffer(U64), "u64"), 4)).toBe("0");
  });
});
