// The slice view: a cross-section of the volume along x, y or z, drawn from the bricks (one
// batch request for every brick the plane cuts, `proto/src/batch.rs`), one canvas pixel per
// voxel of the chosen level, grey = the voxel through window/level.
//
// Orientation (the browser tests rely on it): a z slice has x to the right and y up (row 0 is
// the largest y); an x slice has z to the right and y up; a y slice, seen from above, has x to
// the right and z down (row 0 is z = 0).

import type { Api, VolumeInfo } from "./api";
import { lut, type Colormap } from "./colormap";

export type Axis = "x" | "y" | "z";

type Index = 0 | 1 | 2;
export const AXIS: Record<Axis, Index> = { x: 0, y: 1, z: 2 };
/** Batches stay under the server's 64 MiB and 4,096-brick limits. */
const BATCH_BYTES = 32 << 20;
const BATCH_KEYS = 4096;
/** The automatic level keeps a slice within about this many pixels. */
const AUTO_PIXELS = 512 * 512;

/** The plane's axes on screen: [columns, rows], and whether rows run against their axis. */
export function planeAxes(axis: Axis): { col: Index; row: Index; rowDown: boolean } {
  if (axis === "z") return { col: 0, row: 1, rowDown: false };
  if (axis === "x") return { col: 2, row: 1, rowDown: false };
  return { col: 0, row: 2, rowDown: true };
}

/** Grey 0..255 for value `v` through a window of `width` centred on `center`. */
export function windowLevel(v: number, center: number, width: number): number {
  const lo = center - width / 2;
  const g = Math.round(((v - lo) * 255) / Math.max(width, 1e-9));
  return g < 0 ? 0 : g > 255 ? 255 : g;
}

/** The decoded entries of a raw batch response: key and voxels per brick. */
export function decodeBatch(
  buffer: ArrayBuffer,
  u16: boolean,
): Array<{ level: number; x: number; y: number; z: number; voxels: Uint8Array | Uint16Array }> {
  const view = new DataView(buffer);
  if (buffer.byteLength < 8 || view.getUint32(0, true) !== 0x42425649) {
    throw new Error("brick batch: bad magic");
  }
  const n = view.getUint32(4, true);
  if (8 + n * 28 > buffer.byteLength) throw new Error(`brick batch: ${n} entries do not fit`);
  let at = 8 + n * 28;
  const out = [];
  for (let i = 0; i < n; i++) {
    const e = 8 + i * 28;
    const codec = view.getUint8(e + 1);
    const len = view.getUint32(e + 24, true);
    if (codec !== 0) throw new Error(`brick batch: codec ${codec} where raw voxels were asked`);
    if (at + len > buffer.byteLength) throw new Error("brick batch: payload beyond the end");
    const bytes = buffer.slice(at, at + len);
    out.push({
      level: view.getUint8(e),
      x: view.getUint32(e + 4, true),
      y: view.getUint32(e + 8, true),
      z: view.getUint32(e + 12, true),
      voxels: u16 ? new Uint16Array(bytes) : new Uint8Array(bytes),
    });
    at += len;
  }
  return out;
}

export interface SliceState {
  axis: Axis;
  /** Position along the axis, in level-0 voxels. */
  position: number;
  /** Level shown, or "auto". */
  level: number | "auto";
  center: number;
  width: number;
}

export class SliceView {
  readonly canvas: HTMLCanvasElement;
  state: SliceState;
  private info: VolumeInfo | null = null;
  private values: Uint16Array | null = null;
  private size = { w: 0, h: 0, level: 0, index: 0 };
  private controller: AbortController | null = null;
  private colors = lut("grey");
  /** Called when the slice was drawn (after each load). */
  onDrawn: () => void = () => {};

  constructor(
    private readonly api: Api,
    canvas: HTMLCanvasElement,
  ) {
    this.canvas = canvas;
    this.state = { axis: "z", position: 0, level: "auto", center: 127.5, width: 255 };
  }

  setVolume(info: VolumeInfo, state?: Partial<SliceState>): void {
    this.info = info;
    const range = info.high - info.low;
    this.state = {
      axis: "z",
      position: Math.floor(info.dims[2] / 2),
      level: "auto",
      center: info.low + range / 2,
      width: range,
      ...state,
    };
  }

  /** The level drawn: the chosen one, or the finest whose slice fits about 512x512 pixels. */
  level(): number {
    const info = this.info;
    if (!info) return 0;
    if (this.state.level !== "auto") {
      return Math.min(Math.max(0, this.state.level), info.levels.length - 1);
    }
    const { col, row } = planeAxes(this.state.axis);
    for (const l of info.levels) {
      if (l.dims[col] * l.dims[row] <= AUTO_PIXELS) return l.level;
    }
    return info.levels.length - 1;
  }

  /** Whether a commit's changed bricks cut the plane shown. */
  touches(changed: Array<Array<[number, number, number]>>): boolean {
    const info = this.info;
    if (!info || !this.values) return false;
    const a = AXIS[this.state.axis];
    const b = Math.floor(this.size.index / info.brick);
    return (changed[this.size.level] ?? []).some((p) => p[a] === b);
  }

  /** Loads the plane's bricks at `version` and draws them. */
  async load(version: number): Promise<void> {
    const info = this.info;
    if (!info) return;
    this.controller?.abort();
    const controller = new AbortController();
    this.controller = controller;
    const level = this.level();
    const l = info.levels[level];
    if (!l) return;
    const a = AXIS[this.state.axis];
    const { col, row, rowDown } = planeAxes(this.state.axis);
    const index = Math.min(l.dims[a] - 1, Math.max(0, Math.floor(this.state.position / 2 ** level)));
    const b = info.brick;
    const brickPlane = Math.floor(index / b);
    const local = index % b;
    const keys: Array<[number, number, number, number]> = [];
    for (let j = 0; j < l.grid[row]; j++) {
      for (let i = 0; i < l.grid[col]; i++) {
        const p = [0, 0, 0];
        p[a] = brickPlane;
        p[col] = i;
        p[row] = j;
        keys.push([level, p[0] ?? 0, p[1] ?? 0, p[2] ?? 0]);
      }
    }
    const u16 = info.voxel_type === "u16";
    const brickBytes = b ** 3 * (u16 ? 2 : 1);
    const perBatch = Math.max(1, Math.min(BATCH_KEYS, Math.floor(BATCH_BYTES / brickBytes)));
    const w = l.dims[col];
    const h = l.dims[row];
    const values = new Uint16Array(w * h);
    for (let start = 0; start < keys.length; start += perBatch) {
      const buffer = await this.api.batch(
        info.name,
        keys.slice(start, start + perBatch),
        version,
        controller.signal,
      );
      for (const e of decodeBatch(buffer, u16)) {
        const origin = [e.x * b, e.y * b, e.z * b];
        for (let v = 0; v < b; v++) {
          const rv = (origin[row] ?? 0) + v;
          if (rv >= h) break;
          for (let u = 0; u < b; u++) {
            const cu = (origin[col] ?? 0) + u;
            if (cu >= w) break;
            const q = [0, 0, 0];
            q[a] = local;
            q[col] = u;
            q[row] = v;
            const src = (q[0] ?? 0) + b * ((q[1] ?? 0) + b * (q[2] ?? 0));
            const y = rowDown ? rv : h - 1 - rv;
            values[y * w + cu] = e.voxels[src] ?? 0;
          }
        }
      }
    }
    if (this.controller !== controller) return;
    this.values = values;
    this.size = { w, h, level, index };
    this.canvas.dataset["axis"] = this.state.axis;
    this.canvas.dataset["level"] = String(level);
    this.canvas.dataset["index"] = String(index);
    this.canvas.dataset["version"] = String(version);
    this.draw();
  }

  /** Maps the window/level's grey levels through `map` ("terrain" draws grey). */
  setColormap(map: Colormap): void {
    this.colors = lut(map);
    this.draw();
  }

  /**
   * The voxel under canvas pixel (px, py) (canvas pixels, one per voxel of the level shown): its
   * level, its position in that level's voxels and its value; null off the slice.
   */
  voxelAt(px: number, py: number): { level: number; position: [number, number, number]; value: number } | null {
    const values = this.values;
    if (!values) return null;
    const { w, h, level, index } = this.size;
    const cu = Math.floor(px);
    const y = Math.floor(py);
    if (cu < 0 || y < 0 || cu >= w || y >= h) return null;
    const { col, row, rowDown } = planeAxes(this.state.axis);
    const p: [number, number, number] = [0, 0, 0];
    p[AXIS[this.state.axis]] = index;
    p[col] = cu;
    p[row] = rowDown ? y : h - 1 - y;
    return { level, position: p, value: values[y * w + cu] ?? 0 };
  }

  /** Draws the loaded values through the current window/level and colour map. */
  draw(): void {
    const values = this.values;
    if (!values) return;
    const { w, h } = this.size;
    this.canvas.width = w;
    this.canvas.height = h;
    const ctx = this.canvas.getContext("2d", { willReadFrequently: true });
    if (!ctx) return;
    const img = ctx.createImageData(w, h);
    const { center, width } = this.state;
    const colors = this.colors;
    for (let i = 0; i < values.length; i++) {
      const g = windowLevel(values[i] ?? 0, center, width);
      img.data[i * 4] = colors[g * 3] ?? 0;
      img.data[i * 4 + 1] = colors[g * 3 + 1] ?? 0;
      img.data[i * 4 + 2] = colors[g * 3 + 2] ?? 0;
      img.data[i * 4 + 3] = 255;
    }
    ctx.putImageData(img, 0, 0);
    this.onDrawn();
  }
}
