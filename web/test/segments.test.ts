import { afterEach, describe, expect, it, vi } from "vitest";
import { Api, type VolumeInfo } from "../src/api";
import { meshLevel, segmentColor, SegmentPanel, type SegmentSink } from "../src/segments";
import { triangle } from "./compact";

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

  it("keep the colours they always had for ids below 2^53", () => {
    // HSL with hue frac(id * 0.618033988749895), saturation 0.65, lightness 0.55, each channel
    // rounded from 0..255; worked out apart from the code (Python's colorsys). By hand for 1:
    // hue 0.618 * 6 = 3.708 (blue-cyan sextant), chroma 0.9 * 0.65 = 0.585, x = 0.585 * (1 -
    // 0.708) = 0.1707, base 0.55 - 0.2925 = 0.2575: (0.2575, 0.4282, 0.8425) * 255 = 66, 109, 215.
    const expected: Array<[number, [number, number, number]]> = [
      [0, [215, 66, 66]],
      [1, [66, 109, 215]],
      [2, [153, 215, 66]],
      [3, [215, 66, 196]],
      [7, [72, 215, 66]],
      [255, [66, 127, 215]],
      [1000, [215, 96, 66]],
      [65535, [215, 66, 193]],
      [4294967295, [215, 66, 174]],
    ];
    for (const [id, color] of expected) {
      expect(segmentColor(id), `id ${id}`).toEqual(color);
      // The same id as a u64 channel writes it (a string), or as a bigint: the same colour.
      expect(segmentColor(String(id)), `id "${id}"`).toEqual(color);
      expect(segmentColor(BigInt(id)), `id ${id}n`).toEqual(color);
    }
    // The palette applies to string ids too.
    expect(segmentColor("3", ["#000000", "#77736e", "#7a5634", "#4f8a35"])).toEqual([0x4f, 0x8a, 0x35]);
  });

  it("tell apart ids past 2^53 that differ only in their last digits, stably", () => {
    const a = "9007199254740993"; // 2^53 + 1
    const b = "9007199254740994"; // 2^53 + 2
    expect(segmentColor(a)).not.toEqual(segmentColor(b));
    expect(segmentColor(a)).toEqual(segmentColor(a));
    expect(segmentColor(a)).toEqual(segmentColor(2n ** 53n + 1n));
    // The documented rule, worked out apart from the code (exact decimals, Python's colorsys):
    // hue = frac(low32 * golden + high32 * (sqrt 2 - 1)). 2^53 + 1: low 1, high 2^21, hue 0.4188;
    // 2^53 + 2: low 2, hue 0.0368; 2^64 - 1: low and high 2^32 - 1, hue 0.4171.
    expect(segmentColor(a)).toEqual([66, 215, 142]);
    expect(segmentColor(b)).toEqual([215, 99, 66]);
    expect(segmentColor("18446744073709551615")).toEqual([66, 215, 141]);
    // No palette has that many entries: hashed.
    expect(segmentColor(a, ["#000000", "#ffffff"])).toEqual(segmentColor(a));
    // Runs of neighbouring large ids are as far apart as small ones.
    for (const start of [2n ** 53n + 1n, 2n ** 64n - 501n]) {
      for (let id = start; id < start + 500n; id++) {
        const c = segmentColor(id);
        const next = segmentColor(id + 1n);
        expect(Math.max(...c.map((v, i) => Math.abs(v - next[i]!))), `id ${id}`).toBeGreaterThan(20);
      }
    }
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

/** Just enough of a DOM element for the segment panel (vitest runs without a DOM). */
class FakeElement {
  hidden = false;
  textContent = "";
  value = "";
  type = "";
  checked = false;
  className = "";
  readonly dataset: Record<string, string> = {};
  readonly style: Record<string, string> = {};
  children: unknown[] = [];
  private readonly listeners = new Map<string, Array<() => void>>();

  addEventListener(type: string, listener: () => void): void {
    this.listeners.set(type, [...(this.listeners.get(type) ?? []), listener]);
  }
  dispatch(type: string): void {
    for (const listener of this.listeners.get(type) ?? []) listener();
  }
  append(...children: unknown[]): void {
    this.children.push(...children);
  }
  replaceChildren(...children: unknown[]): void {
    this.children = children;
  }
  /** The checkboxes under this element, depth first. */
  boxes(): FakeElement[] {
    const mine = this.type === "checkbox" ? [this] : [];
    return [...mine, ...this.children.flatMap((c) => (c instanceof FakeElement ? c.boxes() : []))];
  }
  /** The text under this element. */
  text(): string {
    return this.children.map((c) => (c instanceof FakeElement ? c.text() : String(c))).join("");
  }
}

describe("the segment panel of a u64 channel", () => {
  afterEach(() => vi.unstubAllGlobals());

  // Ids as the server writes them for u64 channels: decimal strings, here past 2^53 where a
  // number would round 2^53 + 1 to 2^53.
  const LIST = `{"version": 4, "channel": "label", "total": 3, "segments": [
    {"id": "9007199254740993", "voxels": 10, "box": [[0, 0, 0], [4, 4, 4]]},
    {"id": "18446744073709551615", "voxels": 20, "box": [[0, 0, 0], [4, 4, 4]]}
  ], "next": "18446744073709551615"}`;

  const info: VolumeInfo = {
    name: "cells",
    dims: [64, 64, 64],
    voxel_type: "u8",
    low: 0,
    high: 255,
    surface: 128,
    brick: 32,
    levels: [{ level: 0, grid: [2, 2, 2], dims: [64, 64, 64] }],
    voxel_scale: [1, 1, 1],
    version: 4,
    channels: [{ name: "label", type: "u64", sparse: true }],
  };

  it("lists, shows, fetches and hides segments by their exact ids", async () => {
    const urls: string[] = [];
    vi.stubGlobal("fetch", (url: string) => {
      urls.push(url);
      return Promise.resolve(url.includes("/mesh?") ? new Response(triangle()) : new Response(LIST));
    });
    vi.stubGlobal("document", { createElement: () => new FakeElement() });
    vi.stubGlobal(
      "Option",
      class {
        constructor(
          readonly text: string,
          readonly value: string,
        ) {}
      },
    );
    const calls: string[] = [];
    const sink: SegmentSink = {
      showSegment: (id, mesh, color) => {
        calls.push(`show ${id}`);
        expect(mesh.indices.length).toBe(3);
        expect(color).toEqual(segmentColor(id));
      },
      hideSegment: (id) => calls.push(`hide ${id}`),
    };
    const el = { section: new FakeElement(), channel: new FakeElement(), status: new FakeElement(), list: new FakeElement() };
    const panel = new SegmentPanel(new Api(), sink, el as unknown as ConstructorParameters<typeof SegmentPanel>[2]);
    panel.open(info);
    await vi.waitFor(() => expect(el.list.children.length).toBe(2));
    expect(el.status.textContent).toBe("3 segments at version 4 (the first 2)");
    const boxes = el.list.boxes();
    expect(boxes.map((b) => b.dataset["segment"])).toEqual(["9007199254740993", "18446744073709551615"]);
    expect(el.list.text()).toContain(" 18446744073709551615 (20 voxels)");

    boxes[1]!.checked = true;
    boxes[1]!.dispatch("change");
    await vi.waitFor(() => expect(calls).toEqual(["show 18446744073709551615"]));
    expect(urls.at(-1)).toBe("/v1/volumes/cells/channels/label/segments/18446744073709551615/mesh?level=0&format=compact");
    expect(panel.showing).toEqual(["18446744073709551615"]);

    boxes[0]!.checked = true;
    boxes[0]!.dispatch("change");
    await vi.waitFor(() => expect(calls.length).toBe(2));
    expect(urls.at(-1)).toContain("/segments/9007199254740993/mesh?");
    boxes[1]!.checked = false;
    boxes[1]!.dispatch("change");
    expect(calls.at(-1)).toBe("hide 18446744073709551615");
    expect(panel.showing).toEqual(["9007199254740993"]);
  });

  it("asks a u32 channel's meshes by their numeric ids as before", async () => {
    const urls: string[] = [];
    vi.stubGlobal("fetch", (url: string) => {
      urls.push(url);
      return Promise.resolve(new Response(triangle()));
    });
    await new Api().segmentMesh("cells", "label", 4294967295, 2);
    expect(urls).toEqual(["/v1/volumes/cells/channels/label/segments/4294967295/mesh?level=2&format=compact"]);
  });
});
