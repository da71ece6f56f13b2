// The surface textures of materials, made here from noise (no image files: they are ours, under
// the project's licence). Each is a tileable 64x64 pattern of brightness around 1, one layer per
// material value 0..7 of a texture array; the shader multiplies it with the material's palette
// colour and maps it onto the surface by triplanar mapping (`scene.ts`), so any palette gets
// textured surfaces. Layers follow the demo world's materials: 1 rock (cracked), 2 soil
// (pebbles), 3 grass (blades), 4 sand (fine grain), 5 ore (rock with bright flecks), 6 marble
// (veins); 0 and 7 are plain noise.

export const TEXTURE_SIZE = 64;
export const TEXTURE_LAYERS = 8;

/** A hash of integer lattice point (x, y) and seed to [0, 1). */
function hash(x: number, y: number, seed: number): number {
  let h = (x * 374761393 + y * 668265263 + seed * 2246822519) | 0;
  h = Math.imul(h ^ (h >>> 13), 1274126177);
  h ^= h >>> 16;
  return (h >>> 0) / 4294967296;
}

/**
 * Value noise with `cells` lattice cells across the texture (`across` of them along v, `cells`
 * by default), periodic over it (the lattice wraps), so the pattern tiles without a seam.
 */
function noise(u: number, v: number, cells: number, seed: number, across = cells): number {
  const x = u * cells;
  const y = v * across;
  const x0 = Math.floor(x);
  const y0 = Math.floor(y);
  const fx = x - x0;
  const fy = y - y0;
  const sx = fx * fx * (3 - 2 * fx);
  const sy = fy * fy * (3 - 2 * fy);
  const w = (i: number, n: number) => ((i % n) + n) % n;
  const a = hash(w(x0, cells), w(y0, across), seed);
  const b = hash(w(x0 + 1, cells), w(y0, across), seed);
  const c = hash(w(x0, cells), w(y0 + 1, across), seed);
  const d = hash(w(x0 + 1, cells), w(y0 + 1, across), seed);
  return a + (b - a) * sx + (c - a) * sy + (a - b - c + d) * sx * sy;
}

/** Four octaves of `noise`, in [0, 1). */
function fbm(u: number, v: number, cells: number, seed: number, across = cells): number {
  let sum = 0;
  let amp = 0.5;
  for (let o = 0; o < 4; o++, cells *= 2, across *= 2, amp /= 2) sum += amp * noise(u, v, cells, seed + o, across);
  return sum / 0.9375;
}

/** Brightness of layer `layer` at (u, v), periodic with period 1 along both. */
export function brightness(layer: number, u: number, v: number): number {
  switch (layer) {
    case 1: {
      // Rock: broad variation, darker ridges where the noise crosses its middle (cracks).
      const n = fbm(u, v, 4, 11);
      const crack = Math.abs(noise(u, v, 6, 12) - 0.5) < 0.03 ? 0.7 : 1;
      return (0.75 + 0.45 * n) * crack;
    }
    case 2: {
      // Soil: fine grain with round pebbles.
      const pebble = noise(u, v, 16, 21) > 0.78 ? 1.18 : 1;
      return (0.82 + 0.3 * fbm(u, v, 8, 22)) * pebble;
    }
    case 3: {
      // Grass: blades along v (noise with 8 times the cells across), slightly bent.
      return 0.75 + 0.45 * fbm(u + 0.01 * Math.sin(2 * Math.PI * v * 2), v, 32, 31, 4);
    }
    case 4:
      // Sand: fine, low-contrast grain.
      return 0.9 + 0.2 * noise(u, v, 32, 41);
    case 5: {
      // Ore: rock with bright flecks.
      const fleck = noise(u, v, 12, 51) > 0.82 ? 1.45 : 1;
      return (0.72 + 0.4 * fbm(u, v, 4, 52)) * fleck;
    }
    case 6: {
      // Marble: veins along a turbulent sine.
      const t = Math.sin(2 * Math.PI * (u + v) * 2 + 7 * fbm(u, v, 4, 61));
      return 0.8 + 0.3 * Math.pow(Math.abs(t), 0.3);
    }
    default:
      return 0.85 + 0.3 * fbm(u, v, 4, 71 + layer);
  }
}

/**
 * The layers as RGBA bytes, layer after layer, row after row: grey (r = g = b), brightness
 * times 200 (so 1 is 200 and the brightest flecks stay below 255), alpha 255.
 */
export function materialTextures(): Uint8Array {
  const n = TEXTURE_SIZE;
  const out = new Uint8Array(TEXTURE_LAYERS * n * n * 4);
  for (let layer = 0; layer < TEXTURE_LAYERS; layer++) {
    for (let y = 0; y < n; y++) {
      for (let x = 0; x < n; x++) {
        const g = Math.max(0, Math.min(255, Math.round(200 * brightness(layer, x / n, y / n))));
        const at = 4 * (x + n * (y + n * layer));
        out[at] = g;
        out[at + 1] = g;
        out[at + 2] = g;
        out[at + 3] = 255;
      }
    }
  }
  return out;
}
