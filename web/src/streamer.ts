// The camera-distance streamer of the viewer: which mesh tiles the camera needs (`lod.ts`, the
// same selection as the server and the Rust client), in which order to fetch them, what is on
// screen meanwhile, and what an edit made stale.
//
// Selection. Tiles of neighbouring levels are stitched where they meet, so the selection is
// balanced (`lod.ts` `balancedTiles`: tiles that touch differ by at most one level) and the
// renderer draws each tile with its face mask (`stitchMasks`, `mesh.ts` `stitch`).
//
// Content keys. A mesh tile reads the bricks around it at its level (its cells reach into the +1
// neighbours, its normals one sample further on every side; `tile.ts` `meshTileReads`, as
// `server/src/mesh/tile/` reads them); the transition strip of a face, fetched only while the
// face touches a coarser tile (the tile's mask, `stitchMasks`), reads the tile's level along the
// face and the next coarser level around it (`stripReads`). A content key is the position (and
// face) and the content hashes of those bricks, learnt from the levels' brick grids (`GET
// .../levels/{l}?region=`, in chunks of 8x8x8 bricks). Tiles and strips are cached by content
// key, so one whose inputs did not change is never fetched again (a neighbour's level change
// fetches the newly needed strips, not the tile), and the bricks' value ranges tell, without a
// request, which tiles and strips no surface crosses (most of a terrain's air and rock).
//
// Order. Requests go coarse first, then nearest first: every tile of the selection's coarsest
// level that covers a selected tile is fetched first (a stand-in for the finer tiles under it
// until they are all there), then the selection by level, coarse to fine, and within a level by
// distance from the camera. At most `maxInFlight` requests run at once (`inFlightBudget` in
// main.ts), and a request no tile needs any more (the camera moved on) is aborted.
//
// Edits. `applyCommit` takes the changed bricks' new hashes from the event (`bricks`; when it
// does not list them, it forgets them and the chunks holding them are fetched at the new
// version), aborts the requests they make stale, and plans again: the tiles whose inputs
// changed get a new content key and are refetched, ahead of everything else. Not
// all of them: a commit says which level-0 voxels it can have changed (`changeBoxes`: an edit's
// `op.box` within its changed level-0 bricks), and a tile or strip none of whose stored voxels is
// made of those (`tile.ts` `reachedBy`: the stencil of its reads, 2^k level-0 voxels per voxel of
// level k) has the same mesh at the new version: it keeps its content key ("carried") and is
// neither refetched nor waited for. A radius-5 edit changes a brick on every level, read by up to
// 27 tiles a level (and their strips); its box reaches one to a few of them.
//
// Versions swap whole. A tile whose drawing changed (new content, or new strips) is "pending";
// pending tiles that touch (by a face, an edge or a corner, across levels too) form a region,
// and a region keeps showing its old drawings until every one of its new drawings has arrived,
// then swaps them all in one plan (one frame). So a tile never meets a neighbour of another
// version: a tile whose drawing did not change read none of the changed bricks, so its border
// agrees with both versions of its neighbours. Commits that land while a region waits collapse
// into the newest: the region waits for the newest drawings, and requests for older ones are
// cancelled (their content keys are no longer wanted).

import { Api, ApiError, isAbort, type ChangeEvent, type MeshLook, type LevelBrick, type LevelGrid, type Vec3, type VolumeInfo } from "./api";
import { balancedTiles, keyText, Layout, stitchMasks, tileDistance, type TileKey } from "./lod";
import { decodeStrip, decodeTile, stitchedTriangles, type TileMesh } from "./mesh";
import { hasStrip, meshTileReads, reachedBy, stripReads, valueRange, type TileRead, type VoxelBox } from "./tile";
import { InFlightLimit } from "./limit";

/** Bricks per axis of the grid chunks fetched to learn content hashes. */
const CHUNK = 8;
const RETRY_MIN_MS = 250;
const RETRY_MAX_MS = 10_000;
/** Commits remembered to check answers that started at an older version. */
const COMMIT_LOG = 256;

/**
 * Where the streamer puts what is to be drawn: a tile, its face mask and the strips of the faces
 * in the mask (`mesh.ts` `stitch` draws them together).
 */
export interface TileSink {
  show(id: string, key: TileKey, mesh: TileMesh, mask: number, strips: ReadonlyArray<TileMesh | null>): void;
  hide(id: string): void;
}

/** What a tile shows: its content, mask and strips, named by `content`. */
interface Drawing {
  content: string;
  mesh: TileMesh;
  mask: number;
  strips: Array<TileMesh | null>;
}

/** A tile no surface crosses, drawn only for its strips. */
const EMPTY: TileMesh = {
  positions: new Float32Array(0),
  normals: new Int16Array(0),
  indices: new Uint16Array(0),
  min: [0, 0, 0],
  max: [0, 0, 0],
  moves: null,
  bytes: 0,
};

export interface StreamerStats {
  version: number;
  /** Tiles of the camera's selection, and how many of them show their current content. */
  desired: number;
  ready: number;
  /** Tiles drawn, and triangles in them. */
  drawn: number;
  triangles: number;
  /** Triangles of the tiles drawn in the view frustum. */
  trianglesInView: number;
  inFlight: number;
  /** Requests allowed in flight now: the maximum, less after the server refused some. */
  inFlightLimit: number;
  requests: number;
  /** Response bytes received (decoded). */
  bytes: number;
  /** Every tile of the selection shows its current content; nothing is in flight for it. */
  complete: boolean;
  /** The same for the tiles in the view frustum (those outside may still be loading). */
  completeInView: boolean;
  /** Tiles showing an older drawing, waiting for their region's new drawings to arrive. */
  stale: number;
  lastError: string | null;
}

/**
 * Request priority, smallest first: [class, -level, distance]. Class 0: a tile on screen whose
 * drawing a commit made stale (what others just edited jumps the queue); 1: in the view
 * frustum; 2: out of it.
 */
type Priority = [number, number, number];

/** A request a plan wants: how urgent, and what starts it. */
interface Wanted {
  priority: Priority;
  start: () => void;
}

/** When a commit's changes reached the page and the screen (performance.now() milliseconds). */
export interface CommitTrace {
  version: number;
  /** The change feed delivered it. */
  feed: number;
  /** The last response of a request started at this version arrived. */
  fetched: number | null;
  /** Requests started at this version, and the time spent decoding their answers. */
  requests: number;
  decodeMs: number;
  /** Every tile of the view shows its drawing of this version (or a later one). */
  shown: number | null;
  /** The first frame drawn after `shown` (set by the renderer's owner, `main.ts`). */
  frame: number | null;
}

/** Commit traces kept (the newest). */
const TRACES = 256;

interface Job {
  id: string;
  priority: Priority;
  controller: AbortController;
  version: number;
  /** When it started (performance.now()), to tell which overload a refusal belongs to. */
  started: number;
}

type BrickState = LevelBrick | "absent" | undefined;

export interface StreamerOptions {
  api: Api;
  info: VolumeInfo;
  sink: TileSink;
  radii: number[];
  maxInFlight: number;
  cacheBytes?: number;
  onChange?: () => void;
  /**
   * Whether a box (world units: voxel coordinates times the voxel scale) is in the view
   * frustum; by default everything is.
   */
  inView?: (min: [number, number, number], max: [number, number, number]) => boolean;
  /**
   * After a plan that took t ms, a response plans again only once `planPause` x t ms have
   * passed (meanwhile the next requests of the last plan's queue start at once): a plan walks
   * every selected tile, and with hundreds selected, planning after each response took 30% of
   * the page's main thread in a close view's load (half of it late in the load). 0 (the
   * default): every response plans at once.
   */
  planPause?: number;
}

export class Streamer {
  private readonly api: Api;
  private info: VolumeInfo;
  private layout: Layout;
  private readonly sink: TileSink;
  private readonly onChange: () => void;
  radii: number[];
  version: number;
  private readonly limit: InFlightLimit;
  /** The iso value meshed at: null for the volume's default (S - 0.5). */
  private isoValue: number | null = null;
  /** The channel whose values the meshes' vertices carry (materials), or null. */
  private channelName: string | null = null;
  /**
   * With a channel: per brick (`level/x/y/z`), the version of the last commit that changed the
   * channel's brick there since the page loaded the volume. The grids give density's hashes
   * only, and a paint changes the channel alone: these stamps, part of the content keys, are
   * what tells a mesh with the old materials from one with the new.
   */
  private stamps = new Map<string, number>();

  private camera: [number, number, number] = [0, 0, 0];
  /** Per level: brick index -> what the grid said. */
  private hashes: Array<Map<number, LevelBrick>> = [];
  /**
   * Content keys computed since the hashes last changed (a plan after each response would
   * otherwise compute every selected tile's and strip's key again: most of a plan's time).
   */
  private keys = new Map<string, string | null>();
  /**
   * Content keys that do not come from the hashes, by name (as `keys`): for tiles and strips of
   * the selection, what they were before the last commits that did not reach them (their meshes
   * did not change), or, for those the last commit that did reach them, `NAME#E.V`: their
   * meshes at version V (and at every later one until a commit reaches them again), asked for
   * at once, without waiting for the changed bricks' new hashes.
   */
  private carried = new Map<string, string>();
  /** Told apart in `NAME#E.V` keys: a reload or another iso value starts a new epoch E. */
  private epoch = 0;
  private readonly cache = new Map<string, TileMesh | null>();
  private cacheBytes = 0;
  private readonly cacheLimit: number;
  private readonly jobs = new Map<string, Job>();
  private readonly retryAt = new Map<string, { at: number; delay: number }>();
  private readonly commitLog: Array<{ version: number; bricks: Set<string> }> = [];
  private readonly displayed = new Map<string, Drawing>();
  /** Per tile of the selection: what it last showed. */
  private readonly lastShown = new Map<string, Drawing | null>();
  /** Per tile of the selection: its face mask. */
  private masks = new Map<string, number>();
  private readyCount = 0;
  private staleCount = 0;
  private readyInView = 0;
  private desiredInView = 0;
  private inView: (min: [number, number, number], max: [number, number, number]) => boolean;
  /** Per selected tile: whether it is in the view frustum. */
  private visible = new Map<string, boolean>();
  /** Tiles showing an older drawing than their current one (the last plan's pending regions). */
  private pendingIds = new Set<string>();
  /** Per recent commit: when it reached the page and the screen. */
  readonly traces = new Map<number, CommitTrace>();
  private desired: TileKey[] = [];
  private selectionKey = "";
  /** Counts `setView` calls: the view frustum is part of what the selection depends on. */
  private viewCount = 0;
  private planned = false;
  private retryTimer: ReturnType<typeof setTimeout> | null = null;
  private readonly planPause: number;
  /** A plan put off by `planPause`, and when the last plan ended and how long it took. */
  private planTimer: ReturnType<typeof setTimeout> | null = null;
  private lastPlanEnd = -Infinity;
  private lastPlanCost = 0;
  /** The last plan's requests not started yet, most urgent first. */
  private queue: Array<[string, Wanted]> = [];
  private stopped = false;
  private readonly counters = { requests: 0, bytes: 0 };
  private lastError: string | null = null;
  private statsCache: StreamerStats | null = null;

  constructor(o: StreamerOptions) {
    this.api = o.api;
    this.info = o.info;
    this.layout = new Layout(o.info.dims, o.info.brick);
    this.sink = o.sink;
    this.radii = o.radii;
    this.limit = new InFlightLimit(o.maxInFlight);
    this.cacheLimit = o.cacheBytes ?? 256 << 20;
    this.version = o.info.version;
    this.onChange = o.onChange ?? (() => {});
    this.inView = o.inView ?? (() => true);
    this.planPause = o.planPause ?? 0;
    this.hashes = this.layout.grids.map(() => new Map());
  }

  /** Requests in flight now. */
  get inFlight(): number {
    return this.jobs.size;
  }

  /** The most requests in flight at once; fewer while the server refuses some (503, 429). */
  get maxInFlight(): number {
    return this.limit.max;
  }

  set maxInFlight(max: number) {
    this.limit.max = max;
  }

  get volume(): VolumeInfo {
    return this.info;
  }

  /** The tiles the camera needs now (sorted as `balancedTiles` returns them). */
  selection(): readonly TileKey[] {
    return this.desired;
  }

  setCamera(camera: [number, number, number]): void {
    this.camera = camera;
    this.plan();
  }

  /** The iso value meshed at (null: the volume's default, S - 0.5). */
  get iso(): number | null {
    return this.isoValue;
  }

  /**
   * Meshes at another iso value: every tile gets a new content key; the view keeps the old
   * surface until the new one has arrived (one region), then swaps.
   */
  setIso(iso: number | null): void {
    if (iso === this.isoValue) return;
    this.isoValue = iso;
    this.keys.clear();
    this.carried.clear();
    this.epoch++;
    this.plan();
  }

  /** The camera moved or turned: its position, and what is in its view frustum now. */
  setView(
    camera: [number, number, number],
    inView: (min: [number, number, number], max: [number, number, number]) => boolean,
  ): void {
    this.camera = camera;
    this.inView = inView;
    this.visible = new Map();
    // Tiles out of the view frustum are selected coarser: a turn changes the selection too.
    this.viewCount++;
    this.plan();
  }

  setRadii(radii: number[]): void {
    this.radii = radii;
    this.plan();
  }

  /** Applies one committed version of the change feed (versions in order, each once). */
  applyCommit(ev: ChangeEvent): void {
    if (ev.version <= this.version) return;
    this.carry(changeBoxes(ev, this.layout.brick, this.channelName), ev.version);
    if (this.channelName !== null) {
      ev.channels?.[this.channelName]?.forEach((bricks, level) => {
        for (const [x, y, z] of bricks) this.stamps.set(`${level}/${x}/${y}/${z}`, ev.version);
        if (bricks.length > 0) this.keys.clear();
      });
    }
    const changed = new Set<string>();
    // The event says what the changed bricks hold now when it lists them: the grids are
    // up to date without asking the server (the chunks are asked again otherwise).
    const listed = ev.bricks?.length === ev.changed.length && ev.changed.every((b, l) => ev.bricks?.[l]?.length === b.length);
    ev.changed.forEach((bricks, level) => {
      const known = this.hashes[level];
      bricks.forEach(([x, y, z], i) => {
        changed.add(`${level}/${x}/${y}/${z}`);
        const index = this.brickIndex(level, x, y, z);
        const now = listed ? ev.bricks?.[level]?.[i] : undefined;
        if (now && known?.has(index)) known.set(index, now);
        else known?.delete(index);
        this.keys.clear();
      });
    });
    this.commitLog.push({ version: ev.version, bricks: changed });
    if (this.commitLog.length > COMMIT_LOG) this.commitLog.shift();
    this.traces.set(ev.version, {
      version: ev.version,
      feed: performance.now(),
      fetched: null,
      requests: 0,
      decodeMs: 0,
      shown: null,
      frame: null,
    });
    for (const v of this.traces.keys()) {
      if (this.traces.size <= TRACES) break;
      this.traces.delete(v);
    }
    this.version = ev.version;
    // Chunk requests still running answer for the old version; the chunks holding changed
    // bricks are asked again at the new one (mesh requests are by content key: still valid).
    for (const job of this.jobs.values()) {
      if (job.id.startsWith("g:")) this.abort(job);
    }
    this.plan();
  }

  /** Starts over from new metadata (the history was compacted, or the server went back). */
  reload(info: VolumeInfo): void {
    for (const job of this.jobs.values()) this.abort(job);
    this.info = info;
    this.layout = new Layout(info.dims, info.brick);
    this.selectionKey = "";
    this.hashes = this.layout.grids.map(() => new Map());
    this.keys.clear();
    this.carried.clear();
    this.epoch++;
    this.commitLog.length = 0;
    if (this.channelName !== null) {
      // The stamps start again from this version, and the content keys without them name
      // density only: a cached mesh may carry values the channel no longer has.
      this.stamps.clear();
      this.cache.clear();
      this.cacheBytes = 0;
    }
    this.version = info.version;
    this.plan();
  }

  stop(): void {
    this.stopped = true;
    for (const job of this.jobs.values()) this.abort(job);
    if (this.retryTimer !== null) clearTimeout(this.retryTimer);
    if (this.planTimer !== null) clearTimeout(this.planTimer);
    for (const id of this.displayed.keys()) this.sink.hide(id);
    this.displayed.clear();
  }

  stats(): StreamerStats {
    if (this.statsCache) return this.statsCache;
    let triangles = 0;
    let trianglesInView = 0;
    for (const [id, d] of this.displayed) {
      const n = stitchedTriangles(d.mesh, d.mask, d.strips);
      triangles += n;
      if (this.visible.get(id.startsWith("s:") ? id.slice(2) : id) !== false) trianglesInView += n;
    }
    this.statsCache = {
      version: this.version,
      desired: this.desired.length,
      ready: this.readyCount,
      drawn: this.displayed.size,
      triangles,
      trianglesInView,
      inFlight: this.jobs.size,
      inFlightLimit: this.limit.get(),
      requests: this.counters.requests,
      bytes: this.counters.bytes,
      complete:
        this.planned && this.readyCount === this.desired.length && this.jobs.size === 0,
      completeInView: this.planned && this.readyInView === this.desiredInView,
      stale: this.staleCount,
      lastError: this.lastError,
    };
    return this.statsCache;
  }

  // --- planning ---------------------------------------------------------------------------

  private brickIndex(level: number, x: number, y: number, z: number): number {
    const g = this.layout.grid(level);
    return x + g[0] * (y + g[1] * z);
  }

  private brick(level: number, x: number, y: number, z: number): BrickState {
    if (!this.layout.contains({ level, x, y, z })) return "absent";
    return this.hashes[level]?.get(this.brickIndex(level, x, y, z));
  }

  /**
   * A content key (`name` and the hashes of the bricks `reads` reads), or null while a hash is
   * unknown; "" when no surface can cross what they decide (`tile_inputs`'s and
   * `strip_inputs`'s `may_cross` rule: the voxels read, bounded through the coarser levels'
   * interpolation; outside the volume every voxel is L = 0).
   */
  private keyOf(name: string, reads: TileRead[]): string | null {
    const iso = this.isoValue ?? this.info.surface - 0.5;
    let low = Infinity;
    let high = -Infinity;
    const parts: string[] = [this.isoValue === null ? name : `${name}@${iso}`];
    if (this.channelName !== null) parts.push(`~${this.channelName}`);
    for (const read of reads) {
      const [lo, hi] = read.bricks;
      const [clo, chi] = read.crossing;
      let min = Infinity;
      let max = -Infinity;
      for (let z = lo[2]; z <= hi[2]; z++) {
        for (let y = lo[1]; y <= hi[1]; y++) {
          for (let x = lo[0]; x <= hi[0]; x++) {
            const b = this.brick(read.level, x, y, z);
            if (b === undefined) return null;
            parts.push(b === "absent" ? "-" : b.hash);
            if (this.channelName !== null) {
              const stamp = this.stamps.get(`${read.level}/${x}/${y}/${z}`);
              if (stamp !== undefined) parts.push(`@${stamp}`);
            }
            const crossing =
              x >= clo[0] && x <= chi[0] && y >= clo[1] && y <= chi[1] && z >= clo[2] && z <= chi[2];
            if (crossing) {
              min = Math.min(min, b === "absent" ? 0 : b.min);
              max = Math.max(max, b === "absent" ? 0 : b.max);
            }
          }
        }
      }
      const [l, h] = valueRange(read.level, min, max);
      low = Math.min(low, l);
      high = Math.max(high, h);
    }
    return low < iso && high >= iso ? parts.join(":") : "";
  }

  /** The channel whose values the meshes' vertices carry (null: none). */
  get channel(): string | null {
    return this.channelName;
  }

  /**
   * Meshes with (or without) the values of `channel` on their vertices: every tile gets a new
   * content key, and the view keeps the old surface until the new one has arrived.
   */
  setChannel(channel: string | null): void {
    if (channel === this.channelName) return;
    this.channelName = channel;
    this.stamps.clear();
    this.keys.clear();
    this.carried.clear();
    this.epoch++;
    this.plan();
  }

  /** The tile's content key (`keyOf` of what it reads). */
  private contentKey(k: TileKey): string | null {
    const name = keyText(k);
    let key = this.keys.get(name);
    if (key === undefined) {
      key = this.carried.get(name) ?? this.keyOf(name, meshTileReads(this.layout, k));
      this.keys.set(name, key);
    }
    return key;
  }

  /** The content key of the strip of face `face` of tile `k`. */
  private stripKey(k: TileKey, face: number): string | null {
    const name = `${keyText(k)}/${face}`;
    let key = this.keys.get(name);
    if (key === undefined) {
      key = this.carried.get(name) ?? this.keyOf(name, stripReads(this.layout, k, face));
      this.keys.set(name, key);
    }
    return key;
  }

  /**
   * Before the hashes of commit `version`'s bricks are forgotten: every tile of the selection
   * and strip of its masks whose voxels `boxes` (the commit's changed level-0 voxels) do not
   * reach keeps its content key, so it is neither refetched nor waited for; those it reaches
   * get the key of their meshes at `version`, fetched at once (no grid chunk first: the mesh of
   * a version needs no hash to be asked for). When `boxes` is null (the commit did not say
   * what it changed), every tile reading a changed brick gets a new key once the new hashes
   * are known. Tiles out of the selection lose what they carried (nobody checks them against
   * the commit).
   */
  private carry(boxes: VoxelBox[] | null, version: number): void {
    const next = new Map<string, string>();
    if (boxes !== null) {
      const keep = (name: string, key: string | null, reads: TileRead[]) => {
        if (reachedBy(reads, boxes)) next.set(name, `${name}#${this.epoch}.${version}`);
        else if (key !== null) next.set(name, key);
      };
      for (const k of this.desired) {
        keep(keyText(k), this.contentKey(k), meshTileReads(this.layout, k));
        for (const face of this.maskFaces(k)) {
          if (hasStrip(this.layout, k, face)) {
            keep(`${keyText(k)}/${face}`, this.stripKey(k, face), stripReads(this.layout, k, face));
          }
        }
      }
    }
    this.carried = next;
    this.keys.clear();
  }

  /** The faces of tile `k`'s mask. */
  private maskFaces(k: TileKey): number[] {
    const mask = this.masks.get(keyText(k)) ?? 0;
    return [0, 1, 2, 3, 4, 5].filter((f) => (mask & (1 << f)) !== 0);
  }

  /** The grid chunks whose hashes `reads` needs and does not have. */
  private missingChunks(reads: TileRead[], out: Set<string>): void {
    for (const { level, bricks } of reads) {
      const [lo, hi] = bricks;
      for (let z = lo[2]; z <= hi[2]; z++) {
        for (let y = lo[1]; y <= hi[1]; y++) {
          for (let x = lo[0]; x <= hi[0]; x++) {
            if (this.brick(level, x, y, z) === undefined) {
              out.add(
                `${level}/${Math.floor(x / CHUNK)}/${Math.floor(y / CHUNK)}/${Math.floor(z / CHUNK)}`,
              );
            }
          }
        }
      }
    }
  }

  /**
   * Tile `k` drawn with its current content and the strips of its mask, when all are there
   * (null: nothing to draw); undefined while something is missing.
   */
  private current(k: TileKey, mask: number): Drawing | null | undefined {
    const available = (c: string | null) => (c === "" ? null : c ? this.cache.get(c) : undefined);
    const content = this.contentKey(k);
    const mesh = available(content);
    if (content === null || mesh === undefined) return undefined;
    const keys = [content, String(mask)];
    const strips: Array<TileMesh | null> = [null, null, null, null, null, null];
    for (let f = 0; f < 6; f++) {
      if ((mask & (1 << f)) === 0) continue;
      const key = this.stripKey(k, f);
      const strip = available(key);
      if (key === null || strip === undefined) return undefined;
      strips[f] = strip;
      keys.push(key);
    }
    if (mesh === null && strips.every((s) => s === null)) return null;
    return { content: keys.join("|"), mesh: mesh ?? EMPTY, mask, strips };
  }

  /** What tile `k` can show now: its current drawing, else what it showed before. */
  private showable(k: TileKey, mask: number): { drawing: Drawing | null; current: boolean } | undefined {
    const now = this.current(k, mask);
    if (now !== undefined) return { drawing: now, current: true };
    const old = this.lastShown.get(keyText(k));
    if (old !== undefined) return { drawing: old, current: false };
    return undefined;
  }

  /** Tile `k`'s box in world units. */
  private box(k: TileKey): [[number, number, number], [number, number, number]] {
    const span = this.layout.brick * 2 ** k.level;
    const s = this.info.voxel_scale;
    const p = [k.x, k.y, k.z];
    const min = [0, 1, 2].map((a) => (p[a] ?? 0) * span * (s[a] ?? 1)) as [number, number, number];
    const max = [0, 1, 2].map((a) => ((p[a] ?? 0) + 1) * span * (s[a] ?? 1)) as [number, number, number];
    return [min, max];
  }

  /** Whether tile `k` is in the view frustum (remembered per selection). */
  private isVisible(k: TileKey): boolean {
    const id = keyText(k);
    let v = this.visible.get(id);
    if (v === undefined) {
      const [min, max] = this.box(k);
      v = this.inView(min, max);
      this.visible.set(id, v);
    }
    return v;
  }

  /** Plans again: the selection, what is drawn, and which requests run. */
  plan(): void {
    if (this.stopped) return;
    const began = performance.now();
    if (this.planTimer !== null) {
      clearTimeout(this.planTimer);
      this.planTimer = null;
    }
    this.planned = true;
    this.statsCache = null;
    const scale = this.info.voxel_scale;
    // The selection depends on the camera, its view frustum, the radii and the layout only.
    const selectionKey = `${this.camera.join(",")}|${this.viewCount}|${this.radii.join(",")}|${this.layout.grids.length}`;
    if (selectionKey !== this.selectionKey) {
      this.selectionKey = selectionKey;
      this.visible = new Map();
      this.desired = balancedTiles(this.layout, scale, this.camera, this.radii, (k) => this.isVisible(k));
      this.masks = stitchMasks(this.layout, this.desired);
    }
    // Stand-ins: the tiles of the selection's coarsest level over selected tiles in the view
    // frustum that have nothing to show yet (out of it, nothing shows either way: they must not
    // keep the tiles in view under a stand-in).
    const coarsest = this.desired.reduce((a, k) => Math.max(a, k.level), 0);
    const standIns = new Map<string, TileKey>();
    for (const k of this.desired) {
      if (
        k.level < coarsest &&
        this.isVisible(k) &&
        this.showable(k, this.masks.get(keyText(k)) ?? 0) === undefined
      ) {
        const a = this.layout.ancestor(k, coarsest);
        standIns.set(keyText(a), a);
      }
    }

    // What is on screen (first: it tells which tiles are pending).
    this.draw(standIns);

    // What each tile needs, with its priority: stale tiles on screen first, then those in the
    // view frustum, then the rest; within each, coarse first, then nearest.
    const wanted = new Map<string, Wanted>();
    const want = (id: string, priority: Priority, start: () => void) => {
      const w = wanted.get(id);
      if (!w || compare(priority, w.priority) < 0) wanted.set(id, { priority, start });
    };
    const need = (k: TileKey, faces: number[]) => {
      const id = keyText(k);
      const urgency = this.pendingIds.has(id) ? 0 : this.isVisible(k) ? 1 : 2;
      const priority: Priority = [urgency, -k.level, tileDistance(this.layout, scale, k, this.camera)];
      const content = this.contentKey(k);
      const chunks = new Set<string>();
      if (content === null) {
        this.missingChunks(meshTileReads(this.layout, k), chunks);
      } else if (content !== "" && !this.cache.has(content)) {
        want(`m:${content}`, priority, () => this.fetchMesh(k, content));
      }
      for (const face of faces) {
        const strip = this.stripKey(k, face);
        if (strip === null) this.missingChunks(stripReads(this.layout, k, face), chunks);
        else if (strip !== "" && !this.cache.has(strip)) {
          want(`s:${strip}`, priority, () => this.fetchStrip(k, face, strip));
        }
      }
      for (const c of chunks) want(`g:${c}`, priority, () => this.fetchChunk(c));
    };
    for (const a of standIns.values()) need(a, []);
    for (const k of this.desired) need(k, this.maskFaces(k));

    // Cancel what nobody needs any more; start the most urgent of the rest.
    for (const job of this.jobs.values()) {
      const w = wanted.get(job.id);
      if (w) job.priority = w.priority;
      else this.abort(job);
    }
    const now = performance.now();
    let nextRetry = Infinity;
    const queue = [...wanted.entries()]
      .filter(([id]) => !this.jobs.has(id))
      .filter(([id]) => {
        const r = this.retryAt.get(id);
        if (r && r.at > now) {
          nextRetry = Math.min(nextRetry, r.at);
          return false;
        }
        return true;
      })
      .sort((a, b) => compare(a[1].priority, b[1].priority));
    this.queue = queue;
    this.startQueued(now, true);
    if (this.retryTimer !== null) clearTimeout(this.retryTimer);
    this.retryTimer =
      nextRetry < Infinity ? setTimeout(() => this.plan(), nextRetry - now + 1) : null;
    this.onChange();
    this.lastPlanEnd = performance.now();
    this.lastPlanCost = this.lastPlanEnd - began;
  }

  /**
   * Starts the most urgent requests of the last plan's queue while there is room. Between
   * plans (`fresh` false), those started, answered or waiting to retry since are passed over,
   * and so are grid chunks (an answered one is not told apart from one still needed without
   * walking its bricks): they wait for the next plan.
   */
  private startQueued(now: number, fresh: boolean): void {
    let i = 0;
    for (; i < this.queue.length; i++) {
      const [id, w] = this.queue[i]!;
      if (!fresh) {
        const passed = this.jobs.has(id) || id.startsWith("g:") || this.cache.has(id.slice(2));
        if (passed || (this.retryAt.get(id)?.at ?? 0) > now) continue;
      }
      // Stale tiles on screen may take one place beyond the limit, so an edit is never queued
      // behind a long load.
      const room = this.limit.get() + (w.priority[0] === 0 ? 1 : 0);
      if (this.jobs.size >= room) break;
      this.jobs.set(id, {
        id,
        priority: w.priority,
        controller: new AbortController(),
        version: this.version,
        started: now,
      });
      this.trace(this.version, (t) => t.requests++);
      w.start();
    }
    this.queue = this.queue.slice(i);
    this.statsCache = null;
  }

  /**
   * Plans after a response: at once when nothing else is in flight, when the answer was for a
   * stale tile on screen (an edit's), or when the last plan's pause is over; otherwise the next
   * queued requests start now and the plan waits for the end of the pause (`planPause`).
   */
  private planAfterResponse(job: Job): void {
    const now = performance.now();
    const wait = this.lastPlanEnd + this.planPause * this.lastPlanCost - now;
    if (wait <= 0 || this.jobs.size === 0 || job.priority[0] === 0) {
      this.plan();
      return;
    }
    this.startQueued(now, false);
    if (this.planTimer === null) this.planTimer = setTimeout(() => this.plan(), wait);
  }

  /**
   * What is on screen: each selected tile that has something to show, except under a stand-in:
   * where a selected tile has nothing yet, the stand-in over it is drawn instead of every
   * selected tile under it (they would overlap). A tile whose drawing changed swaps only with
   * every other changed tile it touches (its region), when all their new drawings are there.
   */
  private draw(standIns: Map<string, TileKey>): void {
    const coarsest = this.desired.reduce((a, k) => Math.max(a, k.level), 0);
    const covering = new Map<string, { key: TileKey; drawing: Drawing | null }>();
    for (const [id, s] of standIns) {
      const m = this.showable(s, 0);
      if (m) covering.set(id, { key: s, drawing: m.drawing });
    }
    const next = new Map<string, { key: TileKey; drawing: Drawing }>();
    const desiredIds = new Set<string>();
    let ready = 0;
    let readyInView = 0;
    let inView = 0;
    const put = (id: string, k: TileKey, d: Drawing | null, current: boolean) => {
      this.lastShown.set(id, d);
      if (d) next.set(id, { key: k, drawing: d });
      if (current) {
        ready++;
        if (this.isVisible(k)) readyInView++;
      }
    };
    const pending: Array<{ id: string; key: TileKey; now: Drawing | null | undefined; old: Drawing | null }> = [];
    for (const k of this.desired) {
      const id = keyText(k);
      desiredIds.add(id);
      if (this.isVisible(k)) inView++;
      if (k.level < coarsest && covering.has(keyText(this.layout.ancestor(k, coarsest)))) continue;
      const now = this.current(k, this.masks.get(id) ?? 0);
      const old = this.lastShown.get(id);
      if (old === undefined) {
        // Never shown: nothing to keep; shown once it is there.
        if (now !== undefined) put(id, k, now, true);
        continue;
      }
      if (now !== undefined && (now?.content ?? "") === (old?.content ?? "")) put(id, k, now, true);
      else pending.push({ id, key: k, now, old });
    }

    // Regions: pending tiles that touch, joined (union-find).
    const parent = pending.map((_, i) => i);
    const root = (i: number): number => {
      while (parent[i] !== i) i = parent[i] = parent[parent[i]!]!;
      return i;
    };
    // A sweep along x: only boxes whose x ranges meet are compared (an iso change makes every
    // tile pending; all pairs would be too many to check on every plan).
    const boxes = pending.map((p) => this.voxelBox(p.key));
    const byX = boxes.map((_, i) => i).sort((i, j) => boxes[i]![0]! - boxes[j]![0]!);
    for (let a = 0; a < byX.length; a++) {
      const i = byX[a]!;
      for (let b = a + 1; b < byX.length; b++) {
        const j = byX[b]!;
        if (boxes[j]![0]! > boxes[i]![1]!) break;
        if (touches(boxes[i]!, boxes[j]!)) parent[root(i)] = root(j);
      }
    }
    const waiting = new Set<number>();
    pending.forEach((p, i) => {
      if (p.now === undefined) waiting.add(root(i));
    });
    this.pendingIds = new Set();
    let stale = 0;
    pending.forEach((p, i) => {
      if (waiting.has(root(i))) {
        put(p.id, p.key, p.old, false);
        // Urgent when a commit changed it (its mask, which only the camera changes, is the same).
        if (p.old === null || p.old.mask === (this.masks.get(p.id) ?? 0)) this.pendingIds.add(p.id);
        stale++;
      } else {
        put(p.id, p.key, p.now ?? null, true);
      }
    });

    for (const [id, c] of covering) {
      if (c.drawing) next.set(`s:${id}`, { key: c.key, drawing: c.drawing });
    }
    for (const id of this.lastShown.keys()) {
      if (!desiredIds.has(id)) this.lastShown.delete(id);
    }
    for (const [id, drawing] of this.displayed) {
      if (next.get(id)?.drawing.content !== drawing.content) {
        this.sink.hide(id);
        this.displayed.delete(id);
      }
    }
    for (const [id, { key, drawing }] of next) {
      if (!this.displayed.has(id)) {
        this.sink.show(id, key, drawing.mesh, drawing.mask, drawing.strips);
        this.displayed.set(id, drawing);
      }
    }
    this.readyCount = ready;
    this.staleCount = stale;
    this.readyInView = readyInView;
    this.desiredInView = inView;
    if (stale === 0) {
      const now = performance.now();
      for (const t of this.traces.values()) {
        if (t.shown === null && t.version <= this.version) t.shown = now;
      }
    }
  }

  /** Tile `k`'s box in level-0 voxels, [min, max] per axis. */
  private voxelBox(k: TileKey): number[] {
    const span = this.layout.brick * 2 ** k.level;
    return [k.x * span, (k.x + 1) * span, k.y * span, (k.y + 1) * span, k.z * span, (k.z + 1) * span];
  }

  /** Applies `f` to the trace of `version`, if one is kept. */
  private trace(version: number, f: (t: CommitTrace) => void): void {
    const t = this.traces.get(version);
    if (t) f(t);
  }

  // --- requests ---------------------------------------------------------------------------

  private abort(job: Job): void {
    job.controller.abort();
    this.jobs.delete(job.id);
  }

  private finish(id: string, job: Job | undefined, error: unknown): void {
    if (!job || this.jobs.get(id) !== job) return;
    this.jobs.delete(id);
    if (error !== null) {
      if (isAbort(error)) return;
      const now = performance.now();
      const refused = error instanceof ApiError && (error.status === 503 || error.status === 429);
      if (refused) this.limit.overloaded(job.started, now);
      const r = this.retryAt.get(id);
      const backoff = r ? Math.min(r.delay * 2, RETRY_MAX_MS) : RETRY_MIN_MS;
      // The server's Retry-After is when it expects room again: never ask sooner.
      const asked = error instanceof ApiError && error.retryAfter !== null ? error.retryAfter * 1000 : 0;
      const delay = Math.max(backoff, asked);
      this.retryAt.set(id, { at: now + delay, delay: backoff });
      this.lastError = error instanceof ApiError ? error.message : String(error);
    } else {
      this.limit.succeeded();
      this.retryAt.delete(id);
    }
    this.planAfterResponse(job);
  }

  private fetchChunk(chunk: string): void {
    const id = `g:${chunk}`;
    const job = this.jobs.get(id);
    if (!job) return;
    const [level, cx, cy, cz] = chunk.split("/").map(Number) as [number, number, number, number];
    const g = this.layout.grid(level);
    const min: [number, number, number] = [cx * CHUNK, cy * CHUNK, cz * CHUNK];
    const max: [number, number, number] = [
      Math.min(g[0], min[0] + CHUNK),
      Math.min(g[1], min[1] + CHUNK),
      Math.min(g[2], min[2] + CHUNK),
    ];
    this.counters.requests++;
    this.api
      .levelGrid(this.info.name, level, min, max, job.version, job.controller.signal)
      .then(({ grid, bytes }) => {
        if (this.jobs.get(id) !== job) return;
        this.counters.bytes += bytes;
        this.trace(job.version, (t) => (t.fetched = performance.now()));
        this.learn(grid, job.version);
        this.finish(id, job, null);
      })
      .catch((e: unknown) => this.finish(id, job, e));
  }

  /** Takes a grid answer for `version`, but not the bricks a later commit changed. */
  private learn(grid: LevelGrid, version: number): void {
    const later = this.commitLog.filter((c) => c.version > version);
    if (version < this.version && later.length < this.version - version) return; // log too short
    const known = this.hashes[grid.level];
    if (!known) return;
    let i = 0;
    for (let z = grid.min[2]; z < grid.max[2]; z++) {
      for (let y = grid.min[1]; y < grid.max[1]; y++) {
        for (let x = grid.min[0]; x < grid.max[0]; x++) {
          const b = grid.bricks[i++];
          const text = `${grid.level}/${x}/${y}/${z}`;
          if (b && !later.some((c) => c.bricks.has(text))) {
            known.set(this.brickIndex(grid.level, x, y, z), b);
            this.keys.clear();
          }
        }
      }
    }
  }

  private look(): MeshLook {
    return { iso: this.isoValue, channel: this.channelName };
  }

  private fetchMesh(k: TileKey, content: string): void {
    const id = `m:${content}`;
    const job = this.jobs.get(id);
    if (!job) return;
    this.counters.requests++;
    this.api
      .meshTile(this.info.name, k, job.version, job.controller.signal, this.look())
      .then((buffer) => {
        if (this.jobs.get(id) !== job) return;
        this.counters.bytes += buffer.byteLength;
        const t0 = performance.now();
        const mesh = decodeTile(buffer);
        this.decoded(job.version, t0);
        this.remember(content, mesh.indices.length === 0 ? null : mesh);
        this.finish(id, job, null);
      })
      .catch((e: unknown) => this.finish(id, job, e));
  }

  private fetchStrip(k: TileKey, face: number, content: string): void {
    const id = `s:${content}`;
    const job = this.jobs.get(id);
    if (!job) return;
    this.counters.requests++;
    this.api
      .meshStrip(this.info.name, k, face, job.version, job.controller.signal, this.look())
      .then((buffer) => {
        if (this.jobs.get(id) !== job) return;
        this.counters.bytes += buffer.byteLength;
        const t0 = performance.now();
        const strip = decodeStrip(buffer);
        this.decoded(job.version, t0);
        this.remember(content, strip.indices.length === 0 ? null : strip);
        this.finish(id, job, null);
      })
      .catch((e: unknown) => this.finish(id, job, e));
  }

  /** Notes in `version`'s trace a response that arrived at `t0` and was decoded until now. */
  private decoded(version: number, t0: number): void {
    const now = performance.now();
    this.trace(version, (t) => {
      t.fetched = t0;
      t.decodeMs += now - t0;
    });
  }

  /** Keeps a tile's mesh by content key, least recently stored first out past the budget. */
  private remember(content: string, mesh: TileMesh | null): void {
    this.cache.set(content, mesh);
    this.cacheBytes += mesh?.bytes ?? 0;
    if (this.cacheBytes <= this.cacheLimit) return;
    const inUse = new Set<TileMesh>();
    for (const d of this.displayed.values()) {
      inUse.add(d.mesh);
      for (const s of d.strips) if (s) inUse.add(s);
    }
    for (const [key, m] of this.cache) {
      if (this.cacheBytes <= this.cacheLimit) break;
      if (m && inUse.has(m)) continue;
      this.cache.delete(key);
      this.cacheBytes -= m?.bytes ?? 0;
    }
  }
}

/**
 * The level-0 voxels a commit can have changed, as boxes (max exclusive), or null when it does
 * not say. An edit's `op.box` bounds the voxels it changes, and each changed voxel lies in a
 * changed level-0 brick: so the box within each of those bricks. An undo, redo or revert says
 * no box of its own that bounds what it changed (an undo applies later edits again over the
 * bricks it recomputes), so the changed level-0 bricks whole; a commit that did not record its
 * kind, or changed coarser bricks without a level-0 one, is taken to change everything its
 * bricks hold (null).
 */
export function changeBoxes(ev: ChangeEvent, brick: number, channel: string | null = null): VoxelBox[] | null {
  if (ev.kind === undefined) return null;
  // With a channel drawn, its changes are changes of the meshes too (a paint changes it alone).
  const streams = [ev.changed, ...(channel !== null && ev.channels?.[channel] ? [ev.channels[channel]] : [])];
  const level0 = streams.flatMap((changed) => changed[0] ?? []);
  if (level0.length === 0 && streams.some((changed) => changed.some((bricks) => bricks.length > 0))) return null;
  const op = ev.kind === "edit" ? ev.op?.box : undefined;
  const boxes: VoxelBox[] = [];
  for (const b of level0) {
    const min = b.map((c, a) => Math.max(c * brick, op?.min[a] ?? -Infinity)) as Vec3;
    const max = b.map((c, a) => Math.min((c + 1) * brick, op?.max[a] ?? Infinity)) as Vec3;
    if ([0, 1, 2].every((a) => min[a]! < max[a]!)) boxes.push({ min, max });
  }
  return boxes;
}

function compare(a: Priority, b: Priority): number {
  return a[0] - b[0] || a[1] - b[1] || a[2] - b[2];
}

/** Whether two boxes ([min, max] per axis) share at least a point. */
function touches(a: number[], b: number[]): boolean {
  for (let i = 0; i < 6; i += 2) {
    if ((a[i] ?? 0) > (b[i + 1] ?? 0) || (b[i] ?? 0) > (a[i + 1] ?? 0)) return false;
  }
  return true;
}
