import { describe, expect, it } from "vitest";
import { ApiError, editErrorWords } from "../src/api";
import { editRequest, previewOf, primitiveTerm, PRIMITIVES } from "../src/edit";
import { decodeBatch, planeAxes, windowLevel } from "../src/slice";
import { readUrl, urlQuery } from "../src/url";
import { colorAt, lut, neuroglancerUrl } from "../src/colormap";

describe("edit errors in words", () => {
  const words = (status: number, retry: number | null = null, version: number | null = null) =>
    editErrorWords(new ApiError(status, "detail from the server", retry, version));
  it("says what happened and that nothing changed", () => {
    expect(words(401)).toMatch(/refused the write token \(401 Unauthorized\): nothing was changed/);
    expect(words(403)).toMatch(/only read \(403/);
    expect(words(409, null, 42)).toMatch(/now at version 42 \(409 Conflict\)/);
    expect(words(413)).toMatch(/too large.*413/);
    expect(words(422)).toMatch(/422\): detail from the server/);
    expect(words(429, 2)).toMatch(/Too many edits.*429.*Try again in 2 s/);
    expect(words(503, 1)).toMatch(/busy.*503.*Try again in 1 s/);
    expect(words(0)).toMatch(/cannot be reached/);
  });
});

describe("edit requests", () => {
  it("places the primitive and bounds the edit by its box, clipped to the volume", () => {
    const r = editRequest("union", "cuboid", [10.4, 20.6, 30], 5, [64, 64, 64]);
    expect(r).toEqual({
      op: "union",
      term: { cuboid: { origin: [5, 16, 25], size: [11, 11, 11] } },
      region: { min: [3, 14, 23], max: [18, 29, 38] },
    });
    const edge = editRequest("difference", "ellipsoid", [1, 1, 1], 8, [64, 64, 64]);
    expect(edge?.["region"]).toEqual({ min: [0, 0, 0], max: [12, 12, 12] });
    expect(editRequest("union", "ellipsoid", [-50, 0, 0], 8, [64, 64, 64])).toBeNull();
    expect(editRequest("divide", "ellipsoid", [9, 9, 9], 3, [64, 64, 64])?.["s_l"]).toBe(0.5);
  });

  it("puts the chosen material on the leaf, and paints the material channel in the chosen mode", () => {
    const union = editRequest("union", "cuboid", [10, 20, 30], 5, [64, 64, 64], { material: 6, overwrite: "all" });
    expect(union?.["term"]).toEqual({ cuboid: { origin: [5, 15, 25], size: [11, 11, 11], material: 6 } });
    expect(union).not.toHaveProperty("channel");
    const paint = editRequest("paint", "ellipsoid", [10, 20, 30], 4, [64, 64, 64], { material: 3, overwrite: "empty" });
    expect(paint).toEqual({
      op: "paint",
      channel: "material",
      overwrite: "empty",
      term: { ellipsoid: { center: [10, 20, 30], radii: [4, 4, 4], material: 3 } },
      region: { min: [4, 14, 24], max: [17, 27, 37] },
    });
  });

  it("keeps every primitive within the documented limits and its box", () => {
    for (const p of PRIMITIVES) {
      for (const s of [2, 3, 7, 30]) {
        const t = primitiveTerm(p, [100, 100, 100], s) as Record<string, Record<string, number | number[]>>;
        const body = t[p]!;
        if (p === "cuboid") expect((body["size"] as number[]).every((x) => x > 2)).toBe(true);
        if (p === "prism" || p === "pyramid") expect((body["size"] as number[]).every((x) => x >= 4)).toBe(true);
        if (p === "cylinder" || p === "cone") expect(body["height"]).toBeGreaterThanOrEqual(3);
        if (p === "torus") expect((body["major"] as number) + (body["minor"] as number)).toBeLessThanOrEqual(s);
        if (p === "capsule") {
          // Extension along y: 2 ceil(length / 2) + 2 radius + 1 (docs/icvg.md).
          const ext = 2 * Math.ceil((body["length"] as number) / 2) + 2 * (body["radius"] as number) + 1;
          expect(ext).toBeLessThanOrEqual(2 * Math.max(2, s) + 1);
        }
      }
    }
  });
});

describe("the preview of the page's own edit", () => {
  it("draws the primitive where the request puts it, by its effect", () => {
    // The request's cuboid: origin 5, 16, 25 and sides 11; its surface (the S layer) 6..=14 on
    // x, so centred on 10 with half extent 4.
    expect(previewOf("union", "cuboid", [10.4, 20.6, 30], 5)).toEqual({
      primitive: "cuboid",
      effect: "add",
      center: [10, 21, 30],
      half: [4, 4, 4],
    });
    expect(previewOf("difference", "ellipsoid", [1, 1, 1], 8)).toMatchObject({ effect: "carve", center: [1, 1, 1], half: [8, 8, 8] });
    expect(previewOf("difference_b", "ellipsoid", [1, 1, 1], 8).effect).toBe("carve");
    expect(previewOf("add", "ellipsoid", [1, 1, 1], 8).effect).toBe("add");
    expect(previewOf("intersection", "ellipsoid", [1, 1, 1], 8).effect).toBe("other");
    // A torus of size 9: tube 3, ring 6 (the term's), so 9 across and 3 up from the centre.
    expect(previewOf("union", "torus", [50, 50, 50], 9)).toMatchObject({ half: [9, 3, 9], minor: 3 });
  });

  it("stays within the edit's region, for every primitive and size", () => {
    for (const p of PRIMITIVES) {
      for (const size of [2, 3, 7, 30]) {
        const c: [number, number, number] = [100.3, 99.6, 100];
        const r = editRequest("union", p, c, size, [256, 256, 256]) as { region: { min: number[]; max: number[] } };
        const v = previewOf("union", p, c, size);
        for (let a = 0; a < 3; a++) {
          expect(v.half[a]!, `${p} ${size}`).toBeGreaterThan(0);
          expect(v.center[a]! - v.half[a]!, `${p} ${size}`).toBeGreaterThanOrEqual(r.region.min[a]!);
          expect(v.center[a]! + v.half[a]!, `${p} ${size}`).toBeLessThan(r.region.max[a]!);
        }
      }
    }
  });
});

describe("slice", () => {
  it("maps values through window/level", () => {
    // u8 with the full window: the identity.
    for (const v of [0, 1, 127, 128, 254, 255]) expect(windowLevel(v, 127.5, 255)).toBe(v);
    // u16, window 20000 around 30000: 20000 -> 0, 40000 -> 255, 30000 -> 128 (127.5 rounded).
    expect(windowLevel(20000, 30000, 20000)).toBe(0);
    expect(windowLevel(10000, 30000, 20000)).toBe(0);
    expect(windowLevel(40000, 30000, 20000)).toBe(255);
    expect(windowLevel(65535, 30000, 20000)).toBe(255);
    expect(windowLevel(30000, 30000, 20000)).toBe(128);
  });

  it("orients the planes as documented", () => {
    expect(planeAxes("z")).toEqual({ col: 0, row: 1, rowDown: false });
    expect(planeAxes("x")).toEqual({ col: 2, row: 1, rowDown: false });
    expect(planeAxes("y")).toEqual({ col: 0, row: 2, rowDown: true });
  });

  it("decodes a raw batch laid out as proto/src/batch.rs says", () => {
    // Two u16 bricks of 2^3 voxels: entries of 28 bytes, then the payloads.
    const b = new ArrayBuffer(8 + 2 * 28 + 2 * 16);
    const v = new DataView(b);
    [0x49, 0x56, 0x42, 0x42].forEach((c, i) => v.setUint8(i, c)); // "IVBB"
    v.setUint32(4, 2, true);
    for (let e = 0; e < 2; e++) {
      const at = 8 + e * 28;
      v.setUint8(at, 1); // level
      v.setUint8(at + 1, 0); // raw
      v.setUint32(at + 4, e, true);
      v.setUint32(at + 8, 2, true);
      v.setUint32(at + 12, 3, true);
      v.setUint32(at + 24, 16, true);
      for (let i = 0; i < 8; i++) v.setUint16(8 + 56 + e * 16 + i * 2, 1000 * e + i, true);
    }
    const d = decodeBatch(b, true);
    expect(d.map((e) => [e.level, e.x, e.y, e.z])).toEqual([
      [1, 0, 2, 3],
      [1, 1, 2, 3],
    ]);
    expect([...d[1]!.voxels]).toEqual([1000, 1001, 1002, 1003, 1004, 1005, 1006, 1007]);
    expect(() => decodeBatch(b.slice(0, 60), true)).toThrow();
  });
});

describe("URL state", () => {
  it("round-trips and ignores what it cannot read", () => {
    const s = {
      volume: "demo",
      camera: { position: [1.25, -2, 3] as [number, number, number], target: [4, 5, 6] as [number, number, number] },
      navigation: "fly" as const,
      detail: 6,
      slice: { axis: "y" as const, position: 40 },
      iso: 90.5,
      colormap: "magma" as const,
    };
    const q = urlQuery(s);
    expect(q).toBe("?volume=demo&camera=1.3,-2,3&target=4,5,6&nav=fly&detail=6&slice=y:40&iso=90.5&cmap=magma");
    expect(readUrl(q)).toEqual({ ...s, camera: { position: [1.3, -2, 3], target: [4, 5, 6] } });
    expect(readUrl("?camera=1,2&nav=walk&slice=w:3&detail=-1&iso=x&cmap=rainbow")).toEqual({
      volume: null,
      camera: null,
      navigation: null,
      detail: null,
      slice: null,
      iso: null,
      colormap: null,
    });
  });
});

describe("colour maps and the Neuroglancer link", () => {
  it("has matplotlib's endpoints and grey in between", () => {
    // viridis(0) and viridis(1) in matplotlib: (0.267004, 0.004874, 0.329415), (0.993248,
    // 0.906157, 0.143936); magma(1): (0.987053, 0.991438, 0.749504).
    expect(colorAt("viridis", 0)).toEqual([68, 1, 84]);
    expect(colorAt("viridis", 1)).toEqual([253, 231, 37]);
    expect(colorAt("magma", 1)).toEqual([252, 253, 191]);
    expect(colorAt("grey", 0.5)).toEqual([128, 128, 128]);
    expect(colorAt("viridis", -3)).toEqual([68, 1, 84]);
    const l = lut("cividis");
    expect([...l.slice(0, 3)]).toEqual([0, 0x22, 0x4e]);
    expect([...l.slice(255 * 3)]).toEqual([0xfe, 0xe8, 0x38]);
  });

  it("links Neuroglancer to the volume's precomputed view", () => {
    const url = neuroglancerUrl("http://127.0.0.1:9000", "http://127.0.0.1:7070", "my scan", [10, 20, 30]);
    expect(url.startsWith("http://127.0.0.1:9000/#!")).toBe(true);
    const state = JSON.parse(decodeURIComponent(url.slice(url.indexOf("#!") + 2)));
    expect(state.layers).toEqual([
      { type: "image", source: "precomputed://http://127.0.0.1:7070/v1/volumes/my%20scan/precomputed", name: "my scan" },
    ]);
    expect(state.navigation.pose.position.voxelCoordinates).toEqual([10, 20, 30]);
  });
});
