import { describe, expect, it } from "vitest";
import { meshLevel, segmentColor } from "../src/segments";

describe("segment colours", () => {
  it("take the palette's colour where it gives one", () => {
    expect(segmentColor(3, ["#000000", "#77736e", "#7a5634", "#4f8a35"])).toEqual([0x4f, 0x8a, 0x35]);
    // Past the palette's end, or a malformed entry: hashed.
    expect(segmentColor(9, ["#000000"])).toEqual(segmentColor(9));
    expect(segmentColor(1, ["#000000", "red"])).toEqual(segmentColor(1));
  });

  it("are stable, in range, readable, and far apart for neighbouring ids", () => {
    for (let id = 1; id <= 500; id++) {
      const c = segmentColor(id);
      expect(c).toEqual(segmentColor(id));
      for (const v of c) {
        expect(Number.isInteger(v) && v >= 0 && v <= 255).toBe(true);
      }
      // Lightness 0.55, saturation 0.65: never near black or white.
      expect(Math.max(...c)).toBeGreaterThan(150);
      expect(Math.min(...c)).toBeLessThan(110);
      const next = segmentColor(id + 1);
      expect(Math.max(...c.map((v, i) => Math.abs(v - next[i]!)))).toBeGreaterThan(20);
    }
    // Large ids (u16 labels) too.
    expect(segmentColor(65535)).toEqual(segmentColor(65535));
  });
});

describe("the level a segment's mesh is asked at", () => {
  it("is the finest whose padded box holds at most the cap", () => {
    // 10 x 10 x 10 voxels from 0: padded 12^3 = 1728 at level 0.
    expect(meshLevel([[0, 0, 0], [10, 10, 10]], 5, 1728)).toBe(0);
    expect(meshLevel([[0, 0, 0], [10, 10, 10]], 5, 1727)).toBe(1);
    // 256^3 from 0 with the default cap (2^21): level 0 is 258^3, level 1 130^3 = 2,197,000,
    // level 2 66^3 = 287,496.
    expect(meshLevel([[0, 0, 0], [256, 256, 256]], 5)).toBe(2);
    // A box off the grid: level 1 of x 3..9 is voxels 1..4 (floor 3/2 to ceil 9/2): 4 + 2.
    expect(meshLevel([[3, 0, 0], [9, 2, 2]], 3, 6 * 3 * 3)).toBe(1);
    // Nothing fits: the coarsest level.
    expect(meshLevel([[0, 0, 0], [64, 64, 64]], 3, 1)).toBe(2);
  });
});
