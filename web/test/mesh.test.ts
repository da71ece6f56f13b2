import { describe, expect, it } from "vitest";
import { readFileSync } from "node:fs";
import { decodeStrip, decodeTile, MeshFormatError, stitch, stitchedTriangles } from "../src/mesh";
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
    const m = decodeTile(b);
    expect([...m.positions]).toEqual([0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0.5]);
    expect([...m.normals]).toEqual([0, 0, 32767, 0, 0, 32767, 0, 0, 32767, 0, 0, 32767]);
    expect([...m.indices]).toEqual([0, 1, 2, 0, 2, 3]);
    expect(m.min).toEqual([0, 0, 0]);
    expect(m.max).toEqual([1, 1, 0.5]);
    expect(m.moves).toBeNull();
    expect([...decodeStrip(b).indices]).toEqual([0, 1, 2, 0, 2, 3]);
  });

  it("refuses what the Rust decoder refuses", () => {
    const b = quad();
    for (let cut = 0; cut < b.byteLength - 12; cut++) {
      expect(() => decodeTile(b.slice(0, cut)), `cut at ${cut}`).toThrow(MeshFormatError);
    }
    const badIndex = b.slice(0);
    new DataView(badIndex).setUint16(40 + 48 + 24, 9, true);
    expect(() => decodeTile(badIndex)).toThrow(/index 9/);
    const huge = b.slice(0);
    new DataView(huge).setUint32(8, 0xffffffff, true);
    expect(() => decodeTile(huge)).toThrow(MeshFormatError);
    // Version 3 without its move section; version 2 (strips inside) and unknown versions; a
    // tile is no strip.
    expect(() => decodeTile(compactMesh([], [], [], { version: 3 }))).toThrow(/move section/);
    expect(() => decodeTile(compactMesh([], [], [], { version: 2 }))).toThrow(/version 2/);
    expect(() => decodeTile(compactMesh([], [], [], { version: 4 }))).toThrow(/version 4/);
    expect(() => decodeStrip(compactMesh([], [], [], { version: 3 }))).toThrow(/version 3/);
  });

  it("reads the material section (flag bit 1) and stitches it with the strips", () => {
    const normal = [0, 0, 1];
    const tri = (z: number) => [[0, 0, z], [1, 0, z], [0, 1, z]];
    // 3 vertices, 3 u16 indices: 40 + 54 + 6 = 100 bytes, a multiple of 4; the section follows.
    const b = compactMesh(tri(0), [normal, normal, normal], [0, 1, 2], {
      materials: [[1, 1, 0, 0], [1, 6, 128, 0], [6, 6, 255, 0]],
    });
    expect(b.byteLength).toBe(112);
    const t = decodeTile(b);
    expect([...t.materials!]).toEqual([1, 1, 0, 0, 1, 6, 128, 0, 6, 6, 255, 0]);
    expect([...t.indices]).toEqual([0, 1, 2]);
    // Cut anywhere in the section, or a padding byte that is not 0: refused.
    for (let cut = 100; cut < 112; cut++) expect(() => decodeTile(b.slice(0, cut))).toThrow(/material section/);
    const patched = b.slice(0);
    new Uint8Array(patched)[111] = 1;
    expect(() => decodeTile(patched)).toThrow(/padding/);
    // A strip with materials is appended after the tile's: its values follow the tile's.
    const strip = decodeStrip(
      compactMesh(tri(1), [normal, normal, normal], [0, 1, 2], { materials: [[2, 2, 0, 0], [2, 3, 64, 0], [3, 3, 0, 0]] }),
    );
    const drawn = stitch(t, 1, [strip]);
    expect([...drawn.materials!]).toEqual([1, 1, 0, 0, 1, 6, 128, 0, 6, 6, 255, 0, 2, 2, 0, 0, 2, 3, 64, 0, 3, 3, 0, 0]);
    expect([...drawn.indices]).toEqual([0, 1, 2, 3, 4, 5]);
    // Without the flag there is no section.
    expect(decodeTile(triangle()).materials).toBeNull();
  });

  it("reads u32 indices at an unaligned offset", () => {
    // 3 vertices with wide indices: the indices start at 40 + 54 = 94, not a multiple of 4.
    const b = triangle([2, 1, 0], { wide: true });
    const m = decodeTile(b);
    expect(m.indices).toBeInstanceOf(Uint32Array);
    expect([...m.indices]).toEqual([2, 1, 0]);
  });
});

interface Stitched {
  mask: number;
  positions: number[];
  normals: number[];
  indices: number[];
}
// Written by the Rust test proto/tests/lod_vectors.rs from proto's own encoders and stitch.
const vectors = JSON.parse(
  readFileSync(new URL("../test-vectors/mesh.json", import.meta.url), "utf8"),
) as { tiles: { bytes: string; strips: string[]; stitched: Stitched[] }[] };

const bytesOf = (hex: string): ArrayBuffer => {
  const out = new Uint8Array(hex.length / 2);
  for (let i = 0; i < out.length; i++) out[i] = parseInt(hex.slice(2 * i, 2 * i + 2), 16);
  return out.buffer;
};

describe("tiles with moves and their strips equal proto/src/mesh.rs", () => {
  it("has vectors", () => {
    expect(vectors.tiles.length).toBe(3);
  });

  it("decodes version 3 and the strips, and stitches every mask as stitch() does", () => {
    for (const v of vectors.tiles) {
      const tile = decodeTile(bytesOf(v.bytes));
      expect(tile.moves).not.toBeNull();
      const strips = v.strips.map((s) => decodeStrip(bytesOf(s)));
      expect(strips.length).toBe(6);
      for (const want of v.stitched) {
        const got = stitch(tile, want.mask, strips);
        expect([...got.positions], `mask ${want.mask}`).toEqual(want.positions.map(Math.fround));
        expect([...got.normals], `mask ${want.mask}`).toEqual(want.normals);
        expect([...got.indices], `mask ${want.mask}`).toEqual(want.indices);
        expect(stitchedTriangles(tile, want.mask, strips)).toBe(want.indices.length / 3);
      }
    }
  });

  it("refuses a cut or patched move section", () => {
    const b = bytesOf(vectors.tiles[0]?.bytes ?? "");
    const tile = decodeTile(b);
    const n = tile.positions.length / 3;
    const at = Math.ceil((40 + n * 18 + tile.indices.length * 2) / 4) * 4;
    for (let cut = at; cut < b.byteLength; cut++) {
      expect(() => decodeTile(b.slice(0, cut)), `cut at ${cut}`).toThrow(MeshFormatError);
    }
    const patched = (offset: number, value: number, float = false) => {
      const c = b.slice(0);
      const v = new DataView(c);
      if (float) v.setFloat32(offset, value, true);
      else v.setUint32(offset, value, true);
      return () => decodeTile(c);
    };
    const firstFace = [0, 1, 2, 3, 4, 5].find((f) => new DataView(b).getUint32(at + 4 * f, true) > 0) ?? 0;
    const moves = at + 24;
    expect(patched(at + 4 * firstFace, 0xffffffff)).toThrow(/moves do not fit/);
    expect(patched(moves, n)).toThrow(/moved vertex/);
    expect(patched(moves, n - 1)).not.toThrow();
    expect(patched(moves + 4, NaN, true)).toThrow(/not finite/);
    expect(patched(moves + 4, Infinity, true)).toThrow(/not finite/);
    // A strip refuses what decode_strip refuses.
    const strip = bytesOf(vectors.tiles[0]?.strips[0] ?? "");
    for (let cut = 0; cut < strip.byteLength - 2; cut++) {
      expect(() => decodeStrip(strip.slice(0, cut)), `strip cut at ${cut}`).toThrow(MeshFormatError);
    }
  });
});
