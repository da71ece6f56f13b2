// Edits from the viewer: a primitive of a chosen size placed at a picked point, combined with
// the volume by a chosen operator (docs/icvg.md), applied only within the primitive's box (the
// edit's `region`), so that operators which change everything outside their term (intersection,
// modulate, ...) act as a local brush instead of clearing the rest of the volume.

export const OPERATORS: ReadonlyArray<{ op: string; label: string }> = [
  { op: "union", label: "union (add)" },
  { op: "difference", label: "difference (carve)" },
  { op: "intersection", label: "intersection (keep inside)" },
  { op: "add", label: "add (densify)" },
  { op: "difference_a", label: "difference_a" },
  { op: "difference_b", label: "difference_b" },
  { op: "trim", label: "trim" },
  { op: "cap", label: "cap" },
  { op: "modulate", label: "modulate" },
  { op: "product", label: "product" },
  { op: "divide_a", label: "divide_a" },
  { op: "divide", label: "divide (s_l 0.5)" },
  { op: "paint", label: "paint (material only)" },
];

/**
 * What the shape is made of (`"material": N` on its leaf; null: nothing said, the volume keeps
 * its materials) and, for `paint`, which voxels it writes (`docs/channels.md`).
 */
export interface Attributes {
  material: number | null;
  overwrite: "all" | "empty";
}

export const PRIMITIVES = [
  "ellipsoid",
  "cuboid",
  "cylinder",
  "cone",
  "torus",
  "capsule",
  "prism",
  "pyramid",
] as const;
export type Primitive = (typeof PRIMITIVES)[number];

type V3 = [number, number, number];

/**
 * The leaf for `primitive` of size `s` (voxels, >= 2; about its half extent) centred on `c`
 * (level-0 voxel indices), within the limits docs/icvg.md states (cuboid sides > 2, prism and
 * pyramid sides >= 4, cylinder and cone heights >= 3).
 */
export function primitiveTerm(primitive: Primitive, c: V3, s: number): Record<string, unknown> {
  const r = Math.max(2, Math.round(s));
  const side = 2 * r + 1;
  const corner: V3 = [c[0] - r, c[1] - r, c[2] - r];
  switch (primitive) {
    case "ellipsoid":
      return { ellipsoid: { center: c, radii: [r, r, r] } };
    case "cuboid":
      return { cuboid: { origin: corner, size: [side, side, side] } };
    case "prism":
      return { prism: { origin: corner, size: [side, side, side] } };
    case "pyramid":
      return { pyramid: { origin: corner, size: [side, side, side] } };
    case "cylinder":
      return { cylinder: { base: [c[0], c[1] - r, c[2]], radii: [r, r], height: side } };
    case "cone":
      return { cone: { base: [c[0], c[1] - r, c[2]], radii: [r, r], height: side } };
    case "torus": {
      const minor = Math.max(1, Math.round(r / 3));
      return { torus: { center: c, major: Math.max(1, r - minor), minor } };
    }
    case "capsule": {
      const radius = Math.max(1, Math.round(r / 2));
      return { capsule: { center: c, radius, length: Math.max(1, 2 * (r - radius)) } };
    }
  }
}

/**
 * The edit request: `op(volume, primitive)` within the primitive's box grown by two voxels and
 * clipped to the volume; null when that box misses the volume. With a material the leaf carries
 * it; `paint` writes the material channel where the primitive is inside, density untouched.
 */
export function editRequest(
  op: string,
  primitive: Primitive,
  center: V3,
  size: number,
  dims: V3,
  attributes: Attributes = { material: null, overwrite: "all" },
): Record<string, unknown> | null {
  const c = center.map(Math.round) as V3;
  const r = Math.max(2, Math.round(size));
  const min = c.map((v, a) => Math.min(dims[a] ?? 0, Math.max(0, v - r - 2)));
  const max = c.map((v, a) => Math.min(dims[a] ?? 0, Math.max(0, v + r + 3)));
  if (min.some((v, a) => v >= (max[a] ?? 0))) return null;
  const term = primitiveTerm(primitive, c, r);
  if (attributes.material !== null) {
    const leaf = term[primitive] as Record<string, unknown>;
    leaf["material"] = attributes.material;
  }
  const request: Record<string, unknown> = { op, term, region: { min, max } };
  if (op === "divide") request["s_l"] = 0.5;
  if (op === "paint") {
    request["channel"] = "material";
    request["overwrite"] = attributes.overwrite;
  }
  return request;
}

const TOKEN_KEY = "isovox-token";

/**
 * The token, asked once per browser session and kept in its session storage: the write token
 * for edits, and on a server with private reads the token every request carries.
 */
export class TokenStore {
  get(): string | null {
    return sessionStorage.getItem(TOKEN_KEY);
  }

  set(token: string): void {
    sessionStorage.setItem(TOKEN_KEY, token.trim());
  }

  /** Forgets a token the server refused, so that it is asked for again. */
  forget(): void {
    sessionStorage.removeItem(TOKEN_KEY);
  }
}

/**
 * What the page draws at once for its own edit, until the server's tiles show it: the
 * primitive's surface, roughly (level-0 voxel coordinates). `effect` says how it is drawn:
 * "add" (union, add) as the terrain would draw it, "carve" (the differences) as a translucent
 * red shell where material goes away, "other" (operators whose result depends on both sides)
 * as a translucent grey shell.
 */
export interface Preview {
  primitive: Primitive;
  effect: "add" | "carve" | "other";
  /** The centre of the primitive's extension space. */
  center: V3;
  /** Half the extent of its surface along x, y and z. */
  half: V3;
  /** The torus's tube radius, the capsule's radius. */
  minor?: number;
}

/** The preview of `editRequest(op, primitive, center, size, ...)`'s shape. */
export function previewOf(op: string, primitive: Primitive, center: V3, size: number): Preview {
  const c = center.map(Math.round) as V3;
  const r = Math.max(2, Math.round(size));
  const effect = op === "union" || op === "add" ? "add" : op.startsWith("difference") ? "carve" : "other";
  const cube = (h: number): V3 => [h, h, h];
  switch (primitive) {
    case "ellipsoid":
      return { primitive, effect, center: c, half: cube(r) };
    // The surface of the cuboid and its cut forms lies on the S layer, one voxel in from the
    // extension space's faces; the cylinder's and the cone's ends too.
    case "cuboid":
    case "prism":
    case "pyramid":
      return { primitive, effect, center: c, half: cube(r - 1) };
    case "cylinder":
    case "cone":
      return { primitive, effect, center: c, half: [r, r - 1, r] };
    case "torus": {
      const minor = Math.max(1, Math.round(r / 3));
      const major = Math.max(1, r - minor);
      return { primitive, effect, center: c, half: [major + minor, minor, major + minor], minor };
    }
    case "capsule": {
      const radius = Math.max(1, Math.round(r / 2));
      const length = Math.max(1, 2 * (r - radius));
      return { primitive, effect, center: c, half: [radius, length / 2 + radius, radius], minor: radius };
    }
  }
}
