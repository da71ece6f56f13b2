import { describe, expect, it } from "vitest";
import { brightness, materialTextures, TEXTURE_LAYERS, TEXTURE_SIZE } from "../src/textures";

describe("material textures", () => {
  it("tile without a seam: every layer's pattern repeats with period 1 along u and v", () => {
    for (let layer = 0; layer < TEXTURE_LAYERS; layer++) {
      for (let i = 0; i < 64; i++) {
        const u = ((i * 37) % 64) / 64;
        const v = ((i * 11) % 64) / 64;
        const b = brightness(layer, u, v);
        expect(brightness(layer, u + 1, v)).toBeCloseTo(b, 9);
        expect(brightness(layer, u, v + 1)).toBeCloseTo(b, 9);
      }
    }
  });

  it("are grey, opaque, not flat, and bright around 1 (200) so the palette colour shows", () => {
    const t = materialTextures();
    const n = TEXTURE_SIZE * TEXTURE_SIZE;
    expect(t.length).toBe(TEXTURE_LAYERS * n * 4);
    for (let layer = 0; layer < TEXTURE_LAYERS; layer++) {
      let sum = 0;
      let lo = 255;
      let hi = 0;
      for (let i = 0; i < n; i++) {
        const at = 4 * (layer * n + i);
        expect(t[at + 1]).toBe(t[at]);
        expect(t[at + 2]).toBe(t[at]);
        expect(t[at + 3]).toBe(255);
        sum += t[at]!;
        lo = Math.min(lo, t[at]!);
        hi = Math.max(hi, t[at]!);
      }
      const mean = sum / n;
      expect(mean, `layer ${layer}`).toBeGreaterThan(150);
      expect(mean, `layer ${layer}`).toBeLessThan(240);
      expect(hi - lo, `layer ${layer}`).toBeGreaterThan(10);
    }
  });
});
