// The view in the page's URL, so a link reproduces it: volume, camera, navigation, detail and
// slice, iso value and colour map, e.g.
// `?volume=demo&camera=-30,300,700&target=256,90,256&nav=orbit&detail=12&slice=z:256&iso=90.5&cmap=viridis`.

import type { Navigation } from "./scene";
import type { Axis } from "./slice";
import { COLORMAPS, type Colormap } from "./colormap";

type V3 = [number, number, number];

export interface UrlState {
  volume: string | null;
  camera: { position: V3; target: V3 } | null;
  navigation: Navigation | null;
  detail: number | null;
  slice: { axis: Axis; position: number } | null;
  /** The iso value (null: the volume's own). */
  iso?: number | null;
  colormap?: Colormap | null;
}

function vec(s: string | null): V3 | null {
  const v = s?.split(",").map(Number);
  return v && v.length === 3 && v.every(Number.isFinite) ? (v as V3) : null;
}

/** Reads the state from `search` (the page's own by default); absent or malformed parts are null. */
export function readUrl(search = location.search): UrlState {
  const q = new URLSearchParams(search);
  const position = vec(q.get("camera"));
  const target = vec(q.get("target"));
  const nav = q.get("nav");
  const detail = Number(q.get("detail"));
  const [axis, pos] = (q.get("slice") ?? "").split(":");
  const iso = q.get("iso");
  const cmap = q.get("cmap");
  return {
    iso: iso !== null && iso !== "" && Number.isFinite(Number(iso)) ? Number(iso) : null,
    colormap: COLORMAPS.find((m) => m === cmap) ?? null,
    volume: q.get("volume"),
    camera: position && target ? { position, target } : null,
    navigation: nav === "orbit" || nav === "fly" ? nav : null,
    detail: Number.isFinite(detail) && detail > 0 ? detail : null,
    slice:
      (axis === "x" || axis === "y" || axis === "z") && Number.isFinite(Number(pos)) && pos !== ""
        ? { axis, position: Number(pos) }
        : null,
  };
}

/** The query string for a state (camera rounded to a tenth of a unit). */
export function urlQuery(s: UrlState): string {
  const q = new URLSearchParams();
  const v = (p: V3) => p.map((c) => Math.round(c * 10) / 10).join(",");
  if (s.volume) q.set("volume", s.volume);
  if (s.camera) {
    q.set("camera", v(s.camera.position));
    q.set("target", v(s.camera.target));
  }
  if (s.navigation) q.set("nav", s.navigation);
  if (s.detail) q.set("detail", String(s.detail));
  if (s.slice) q.set("slice", `${s.slice.axis}:${s.slice.position}`);
  if (s.iso != null) q.set("iso", String(s.iso));
  if (s.colormap && s.colormap !== "terrain") q.set("cmap", s.colormap);
  return `?${q.toString().replaceAll("%2C", ",").replaceAll("%3A", ":")}`;
}

/** Replaces the page's URL (no history entry per camera move). */
export function writeUrl(s: UrlState): void {
  const search = urlQuery(s);
  if (search !== location.search) history.replaceState(null, "", search + location.hash);
}
