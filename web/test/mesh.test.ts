import { describe, expect, it } from "vitest";
import { decodeCompact, MeshFormatError } from "../src/mesh";
import { compactMesh, triangle } from "./compact";

// The quad of proto/src/mesh.rs's golden test: 4 vertices, 2 triangles, 124 bytes.
const quad = () =>
  compactMesh(
    [
      [0, 0, 0],
      [1, 0, 0],
      [1, 1, 0],
      [0, 1, 0.5],
    ],
    [
      [0, 0, 1],
      [0, 0, 1],
      [0, 0, 1],
      [0, 0, 1],
    ],
    [0, 1, 2, 0, 2, 3],
  );

describe("compact mesh decoding", () => {
  it("reads the golden quad", () => {
    const b = quad();
    expect(b.byteLength).toBe(124);
    expect([...new Uint8Array(b, 0, 16)]).toEqual([73, 86, 77, 83, 1, 0, 0, 0, 4, 0, 0, 0, 6, 0, 0, 0]);
    const m = decodeCompact(b);
    expect([...m.positions]).toEqual([0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0.5]);
    expect([...m.normals]).toEqual([0, 0, 32767, 0, 0, 32767, 0, 0, 32767, 0, 0, 32767]);
    expect([...m.indices]).toEqual([0, 1, 2, 0, 2, 3]);
    expect(m.min).toEqual([0, 0, 0]);
    expect(m.max).toEqual([1, 1, 0.5]);
    expect(m.transitions).toBeNull();
  });

  it("refuses what the Rust decoder refuses", () => {
    const b = quad();
    for (let cut = 0; cut < b.byteLength - 12; cut++) {
      expect(() => decodeCompact(b.slice(0, cut)), `cut at ${cut}`).toThrow(MeshFormatError);
    }
    const badIndex = b.slice(0);
    new DataView(badIndex).setUint16(40 + 48 + 24, 9, true);
    expect(() => decodeCompact(badIndex)).toThrow(/index 9/);
    const huge = b.slice(0);
    new DataView(huge).setUint32(8, 0xffffffff, true);
    expect(() => decodeCompact(huge)).toThrow(MeshFormatError);
    expect(() => decodeCompact(compactMesh([], [], [], { version: 2 }))).toThrow(/version 2/);
  });

  it("reads u32 indices at an unaligned offset", () => {
    // 3 vertices with wide indices: the indices start at 40 + 54 = 94, not a multiple of 4.
    const b = triangle([2, 1, 0], { wide: true });
    const m = decodeCompact(b);
    expect(m.indices).toBeInstanceOf(Uint32Array);
    expect([...m.indices]).toEqual([2, 1, 0]);
  });
});
