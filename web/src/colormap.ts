// Colour maps for scans: grey, and matplotlib's perceptually uniform viridis, magma, inferno and
// cividis (ten samples each, at i / 9, interpolated linearly in between: endpoints exact, the rest
// within a few levels of the 256-entry tables). The slice view maps the window/level's 0..255
// through one; the 3D view colours the surface by height through it.

export const COLORMAPS = ["terrain", "materials", "grey", "viridis", "magma", "inferno", "cividis"] as const;
export type Colormap = (typeof COLORMAPS)[number];

const STOPS: Record<Exclude<Colormap, "terrain" | "materials">, string[]> = {
  grey: ["000000", "ffffff"],
  viridis: ["440154", "482878", "3e4989", "31688e", "26828e", "1f9e89", "35b779", "6ece58", "b5de2b", "fde725"],
  magma: ["000004", "180f3d", "440f76", "721f81", "9e2f7f", "cd4071", "f1605d", "fd9668", "feca8d", "fcfdbf"],
  inferno: ["000004", "1b0c41", "4a0c6b", "781c6d", "a52c60", "cf4446", "ed6925", "fb9b06", "f7d13d", "fcffa4"],
  cividis: ["00224e", "123570", "3b496c", "575d6d", "707173", "8a8678", "a59c74", "c3b369", "e1cc55", "fee838"],
};

const rgb = (hex: string): [number, number, number] => [
  parseInt(hex.slice(0, 2), 16),
  parseInt(hex.slice(2, 4), 16),
  parseInt(hex.slice(4, 6), 16),
];

/**
 * The map's colour at t in [0, 1] (clamped), 0..255 per channel; "terrain" and "materials"
 * (surface colourings) are grey here.
 */
export function colorAt(map: Colormap, t: number): [number, number, number] {
  const stops = STOPS[map === "terrain" || map === "materials" ? "grey" : map].map(rgb);
  const x = Math.min(1, Math.max(0, Number.isFinite(t) ? t : 0)) * (stops.length - 1);
  const i = Math.min(stops.length - 2, Math.floor(x));
  const f = x - i;
  const a = stops[i]!;
  const b = stops[i + 1]!;
  return [0, 1, 2].map((c) => Math.round(a[c]! + (b[c]! - a[c]!) * f)) as [number, number, number];
}

/** 256 colours (r, g, b, r, g, b, ...) for grey levels 0..255. */
export function lut(map: Colormap): Uint8Array {
  const out = new Uint8Array(256 * 3);
  for (let g = 0; g < 256; g++) out.set(colorAt(map, g / 255), g * 3);
  return out;
}

/**
 * A Neuroglancer link to the volume `name` served at `origin`: its precomputed view as an image
 * layer (grey through the map's window), the four-panel layout, centred on `center` (voxels).
 * `neuroglancer` is the client's address (hosted Neuroglancer reads http://127.0.0.1 and any
 * CORS-open https:// origin).
 */
export function neuroglancerUrl(
  neuroglancer: string,
  origin: string,
  name: string,
  center: [number, number, number],
): string {
  const state = {
    layers: [
      {
        type: "image",
        source: `precomputed://${origin}/v1/volumes/${encodeURIComponent(name)}/precomputed`,
        name,
      },
    ],
    navigation: { pose: { position: { voxelCoordinates: center } }, zoomFactor: 1 },
    layout: "4panel",
  };
  const base = neuroglancer.endsWith("/") ? neuroglancer : `${neuroglancer}/`;
  return `${base}#!${encodeURIComponent(JSON.stringify(state))}`;
}
