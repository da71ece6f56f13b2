// The segment list: a categorical channel's ids (`GET .../channels/{channel}/segments`), each
// with its colour and voxel count, and a checkbox that shows or hides its closed mesh (`.../
// segments/{id}/mesh`) in the 3D view. Colours are the channel's palette where it gives one,
// else a function of the id alone, so an id keeps its colour across pages, sessions and viewers.
// Ids are kept as decimal strings (`segmentKey`) from the list to the mesh request and the 3D
// view: a u64 channel's ids go past 2^53, where a number would drop their last digits.

import type { Api, ChangeEvent, ChannelInfo, Segment, SegmentId, VolumeInfo } from "./api";
import { decodeStrip, type TriangleSet } from "./mesh";

/** Voxels (with the padding) a segment mesh is asked for at most: the level follows from it. */
export const MESH_VOXELS = 1 << 21;

/** The golden ratio's fraction: the hue step from one id to the next. */
const GOLDEN = 0.618033988749895;
/** The hue step of a large id's high 32 bits: sqrt(2) - 1, irrational and unrelated to GOLDEN. */
const HIGH_STEP = Math.SQRT2 - 1;

/** The key of segment `id` in the panel, the 3D view and URLs: its exact decimal digits. */
export function segmentKey(id: SegmentId): string {
  return String(id);
}

/** `id` as a number where a number holds it exactly (below 2^53), else as a bigint. */
function exactId(id: SegmentId | bigint): number | bigint {
  if (typeof id === "number") return id;
  const v = BigInt(id);
  return v <= BigInt(Number.MAX_SAFE_INTEGER) ? Number(v) : v;
}

/**
 * The hue (0..1) of an id from its exact value. Below 2^53, `id` times the golden ratio (mod 1):
 * neighbouring ids are 0.38 of the circle apart and no two of a run of ids coincide. Above, the
 * product of a float would have lost the low digits (all such ids would share a few hues): the
 * low 32 bits times the golden ratio plus the high 32 bits times sqrt(2) - 1 (mod 1), computed
 * from the bigint, so ids differing in their last digits differ in hue as small ids do.
 */
function hueOf(id: number | bigint): number {
  if (typeof id === "number") return (id * GOLDEN) % 1;
  const low = Number(id & 0xffffffffn);
  const high = Number((id >> 32n) & 0xffffffffn);
  return (((low * GOLDEN) % 1) + ((high * HIGH_STEP) % 1)) % 1;
}

/**
 * The display colour of value `id` (0..255 per channel): the palette's ("#rrggbb") when it has
 * one for `id` (ids below the palette's length), else a colour of its own: the hue `hueOf` the
 * exact id (ids below 2^53 keep the colours they always had; a u64 id as a string or a bigint
 * gets the same colour as the number when below 2^53), saturation and lightness fixed to stay
 * readable.
 */
export function segmentColor(id: SegmentId | bigint, palette: readonly string[] = []): [number, number, number] {
  const v = exactId(id);
  const m = typeof v === "number" ? /^#([0-9a-f]{6})$/i.exec(palette[v] ?? "") : null;
  if (m) {
    const rgb = parseInt(m[1]!, 16);
    return [rgb >> 16, (rgb >> 8) & 255, rgb & 255];
  }
  const hue = hueOf(v) * 6;
  const s = 0.65;
  const l = 0.55;
  const c = (1 - Math.abs(2 * l - 1)) * s;
  const x = c * (1 - Math.abs((hue % 2) - 1));
  const [r, g, b] =
    hue < 1 ? [c, x, 0] : hue < 2 ? [x, c, 0] : hue < 3 ? [0, c, x] : hue < 4 ? [0, x, c] : hue < 5 ? [x, 0, c] : [c, 0, x];
  const o = l - c / 2;
  return [r, g, b].map((v) => Math.round((v + o) * 255)) as [number, number, number];
}

/**
 * The finest level at which segment box `box` (level-0 voxels, max exclusive), one voxel of
 * padding on each side, holds at most `cap` voxels.
 */
export function meshLevel(box: Segment["box"], levels: number, cap = MESH_VOXELS): number {
  for (let level = 0; level < levels; level++) {
    const f = 2 ** level;
    const n = [0, 1, 2].reduce((p, a) => p * (Math.ceil(box[1][a]! / f) - Math.floor(box[0][a]! / f) + 2), 1);
    if (n <= cap) return level;
  }
  return Math.max(0, levels - 1);
}

/** Where the segment meshes are drawn (the 3D view). */
export interface SegmentSink {
  /** `id`: the segment's key (`segmentKey`), exact for u64 ids. */
  showSegment(id: string, mesh: TriangleSet, color: [number, number, number]): void;
  hideSegment(id: string): void;
}

/** The panel: its channel, its list, and the meshes it shows. */
export class SegmentPanel {
  private info: VolumeInfo | null = null;
  private channel: ChannelInfo | null = null;
  /** Shown segments, by key, with the version their mesh is of. */
  private readonly shown = new Map<string, number>();
  private refresh: ReturnType<typeof setTimeout> | null = null;
  private version = 0;

  constructor(
    private readonly api: Api,
    private readonly sink: SegmentSink,
    private readonly el: {
      section: HTMLElement;
      channel: HTMLSelectElement;
      status: HTMLElement;
      list: HTMLElement;
    },
  ) {
    el.channel.addEventListener("change", () => {
      this.channel = this.info?.channels?.find((c) => c.name === el.channel.value) ?? null;
      this.hideAll();
      void this.load();
    });
  }

  /** Segments shown now (keys: decimal ids). */
  get showing(): string[] {
    return [...this.shown.keys()];
  }

  /** A new volume: its categorical channels in the picker (the panel hidden without any). */
  open(info: VolumeInfo): void {
    this.hideAll();
    this.info = info;
    this.version = info.version;
    const channels = info.channels ?? [];
    this.el.section.hidden = channels.length === 0;
    this.el.channel.replaceChildren(...channels.map((c) => new Option(c.name, c.name)));
    // A segmentation's labels first, when the volume has one.
    this.channel = channels.find((c) => c.name === "label") ?? channels[0] ?? null;
    if (this.channel) this.el.channel.value = this.channel.name;
    void this.load();
  }

  /** A commit: when it changed the channel, the list (and the meshes shown) are asked again. */
  commit(ev: ChangeEvent): void {
    this.version = ev.version;
    const name = this.channel?.name;
    if (!name || !(ev.channels?.[name] ?? []).some((bricks) => bricks.length > 0)) return;
    if (this.refresh !== null) clearTimeout(this.refresh);
    // A burst of paints refreshes once.
    this.refresh = setTimeout(() => {
      this.refresh = null;
      void this.load();
      for (const id of this.shown.keys()) void this.showMesh(id);
    }, 200);
  }

  private async load(): Promise<void> {
    const info = this.info;
    const channel = this.channel;
    if (!info || !channel) return;
    this.el.status.textContent = "Loading...";
    try {
      const page = await this.api.segments(info.name, channel.name);
      if (this.info !== info || this.channel !== channel) return;
      const more = page.next !== undefined ? ` (the first ${page.segments.length})` : "";
      this.el.status.textContent = `${page.total ?? page.segments.length} segments at version ${page.version}${more}`;
      this.el.list.replaceChildren(...page.segments.map((s) => this.item(s)));
    } catch (e) {
      this.el.status.textContent = `The segments could not be listed: ${String(e instanceof Error ? e.message : e)}`;
    }
  }

  private item(s: Segment): HTMLElement {
    const key = segmentKey(s.id);
    const li = document.createElement("li");
    const box = document.createElement("input");
    box.type = "checkbox";
    box.checked = this.shown.has(key);
    box.dataset["segment"] = key;
    box.addEventListener("change", () => {
      if (box.checked) void this.showMesh(key, s.box);
      else this.hide(key);
    });
    const swatch = document.createElement("span");
    swatch.className = "swatch";
    swatch.style.background = `rgb(${segmentColor(key, this.channel?.palette).join(",")})`;
    const label = document.createElement("label");
    label.append(box, swatch, ` ${key} (${s.voxels.toLocaleString("en")} voxels)`);
    li.append(label);
    return li;
  }

  private async showMesh(id: string, box?: Segment["box"]): Promise<void> {
    const info = this.info;
    const channel = this.channel;
    if (!info || !channel) return;
    this.shown.set(id, this.version);
    const level = box ? meshLevel(box, info.levels.length) : (this.levelOf.get(id) ?? 0);
    if (box) this.levelOf.set(id, level);
    try {
      const mesh = decodeStrip(await this.api.segmentMesh(info.name, channel.name, id, level));
      if (!this.shown.has(id) || this.info !== info) return;
      this.sink.showSegment(id, mesh, segmentColor(id, channel.palette));
    } catch (e) {
      this.shown.delete(id);
      this.el.status.textContent = `Segment ${id}: ${String(e instanceof Error ? e.message : e)}`;
    }
  }

  /** The level each shown segment's mesh was asked for at. */
  private readonly levelOf = new Map<string, number>();

  private hide(id: string): void {
    this.shown.delete(id);
    this.sink.hideSegment(id);
  }

  private hideAll(): void {
    for (const id of [...this.shown.keys()]) this.hide(id);
  }
}
