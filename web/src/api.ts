// The server's HTTP API as the viewer uses it: JSON types (`proto/src/api.rs`), requests, and
// errors (RFC 9457 problem details) put into words a person can act on.

import type { VoxelType } from "./voxels";

export type Vec3 = [number, number, number];

export interface LevelInfo {
  level: number;
  grid: Vec3;
  dims: Vec3;
}

export interface VolumeInfo {
  name: string;
  dims: Vec3;
  voxel_type: "u8" | "u16";
  low: number;
  high: number;
  surface: number;
  brick: number;
  levels: LevelInfo[];
  voxel_scale: Vec3;
  version: number;
  /** Attribute channels beside density (`docs/channels.md`); absent on volumes without. */
  channels?: ChannelInfo[];
}

/** A categorical channel: `material` (worlds) or `label` (segmentations). */
export interface ChannelInfo {
  name: string;
  /** Bytes per voxel 1, 2, 4 or 8 (`decodeVoxels` reads them). */
  type: VoxelType;
  /** Display colour per value ("#rrggbb", index = value), when the volume gives them. */
  palette?: string[];
  sparse?: boolean;
}

export interface LevelBrick {
  hash: string;
  min: number;
  max: number;
}

export interface LevelGrid {
  level: number;
  grid: Vec3;
  min: Vec3;
  max: Vec3;
  version: number;
  bricks: LevelBrick[];
}

/** Changed bricks per level, level 0 first. */
export type ChangedBricks = Vec3[][];

/** An edit's operation in a few words (`proto/src/history.rs` OpSummary). */
export interface OpSummary {
  op: string;
  leaves: string[];
  box: { min: Vec3; max: Vec3 };
}

/** What a commit did and who made it (`proto/src/history.rs` CommitInfo), all optional. */
export interface CommitInfo {
  author?: string;
  message?: string;
  kind?: "edit" | "undo" | "redo" | "revert" | "tag";
  op?: OpSummary;
  target?: number;
  replayed?: number;
  to?: number;
  tag?: string;
}

export interface ChangeEvent extends CommitInfo {
  version: number;
  timestamp_ms: number;
  changed: ChangedBricks;
  /**
   * What each brick of `changed` holds now (same levels, same order): hash and value range, as
   * the level grid lists them. Absent when the commit changed too many bricks to list.
   */
  bricks?: LevelBrick[][];
  /** Changed bricks of attribute channels, by channel: only channels that changed. */
  channels?: Record<string, ChangedBricks>;
}

/** One commit of `GET .../history`. */
export interface HistoryEntry extends CommitInfo {
  version: number;
  timestamp_ms: number;
  bricks_changed: number;
  /** For edits: taken back now (undone, or reverted away). */
  undone?: boolean;
}

export interface HistoryList {
  head: number;
  oldest: number;
  more: boolean;
  commits: HistoryEntry[];
}

/** Another user's whereabouts (`presence` events of the feed). */
export interface Presence {
  user: string;
  position: Vec3;
  looking?: Vec3;
  label?: string;
  at_ms: number;
  gone?: boolean;
}

/** `GET /v1/auth`: who the token is, and how to sign in. */
export interface AuthInfo {
  user: string | null;
  write: boolean;
  admin: boolean;
  private_reads: boolean;
  oidc: { issuer: string; client_id: string; audience: string } | null;
}

export interface ChangeList {
  since: number;
  head: number;
  oldest: number;
  more: boolean;
  changes: ChangeEvent[];
}

export interface EditResponse {
  version: number;
  /** For undo and redo: other edits applied again. */
  replayed?: number;
  previous: number;
  changed: ChangedBricks;
  evaluated: number;
  new_records: number;
  checkpoint: boolean;
  elapsed_us: number;
}

interface Problem {
  title?: string;
  status?: number;
  detail?: string;
  version?: number;
}

/** A failed request: the HTTP status (0 when the server could not be reached) and words. */
export class ApiError extends Error {
  readonly status: number;
  readonly detail: string;
  /** Seconds from `Retry-After`, when the server sent it. */
  readonly retryAfter: number | null;
  /** The volume's current version, on a 409. */
  readonly version: number | null;

  constructor(status: number, detail: string, retryAfter: number | null, version: number | null) {
    super(`${status}: ${detail}`);
    this.status = status;
    this.detail = detail;
    this.retryAfter = retryAfter;
    this.version = version;
  }
}

/** Whether an error is the cancellation of a request the viewer no longer needs. */
export function isAbort(e: unknown): boolean {
  return e instanceof DOMException && e.name === "AbortError";
}

async function failure(response: Response): Promise<ApiError> {
  let problem: Problem = {};
  try {
    problem = (await response.json()) as Problem;
  } catch {
    // Not JSON (a proxy's page, an empty body): the status says what there is to say.
  }
  const retry = Number(response.headers.get("retry-after"));
  return new ApiError(
    response.status,
    problem.detail ?? problem.title ?? response.statusText,
    Number.isFinite(retry) && retry > 0 ? retry : null,
    problem.version ?? null,
  );
}

/** The words shown to a person for a failed edit (the statuses of docs/editing.md). */
export function editErrorWords(e: unknown): string {
  if (!(e instanceof ApiError)) {
    return `The edit could not be sent: ${e instanceof Error ? e.message : String(e)}.`;
  }
  const retry = e.retryAfter === null ? "" : ` Try again in ${e.retryAfter} s.`;
  switch (e.status) {
    case 0:
      return "The server cannot be reached; the edit was not applied.";
    case 401:
      return "The server refused the write token (401 Unauthorized): nothing was changed. Enter the token from the server's token file (data/tokens).";
    case 403:
      return "This token may only read (403 Forbidden): nothing was changed.";
    case 409:
      return `Someone else edited first: the volume is now at version ${e.version ?? "?"} (409 Conflict). Nothing was changed; look again and retry.`;
    case 413:
      return "The edit is too large for the server (413 Payload Too Large): nothing was changed.";
    case 422:
      return `The server cannot apply this edit (422): ${e.detail}`;
    case 429:
      return `Too many edits from this token (429 Too Many Requests): nothing was changed.${retry}`;
    case 503:
      return `The server is busy with other edits (503 Service Unavailable): nothing was changed.${retry}`;
    default:
      return `The edit failed (${e.status}): ${e.detail}`;
  }
}

/**
 * The words shown to a person when the volume cannot be read: above all a server whose reads
 * are private (`isovox serve --private-reads`) answering 401, with or without a token sent.
 */
export function readErrorWords(e: unknown, tokenSent: boolean): string {
  if (!(e instanceof ApiError)) return `Cannot load: ${e instanceof Error ? e.message : String(e)}.`;
  if (e.status === 401) {
    return tokenSent
      ? "The server refused the token (401 Unauthorized): nothing can be shown. Enter a token from the server's token file (data/tokens)."
      : "This server's volumes are private (401 Unauthorized): enter a token from the server's token file (data/tokens) to see them.";
  }
  if (e.status === 0) return "The server cannot be reached.";
  return `Cannot load (${e.status}): ${e.detail}`;
}

/**
 * Requests to one server (`base` is its origin, empty for the page's own). When `token` gives
 * one, every request carries it (`Authorization: Bearer`): a server with private reads wants it
 * on reads too, the change feed included.
 */
/**
 * How a mesh is asked for: the iso value (null: the volume's default) and the channel whose
 * values its vertices carry (null: none; `docs/mesh-encoding.md`, the material section).
 */
export interface MeshLook {
  iso: number | null;
  channel: string | null;
}

/** The query parameters of `look` after `?version=`. */
function lookQuery(look: MeshLook): string {
  const iso = look.iso === null ? "" : `&iso=${look.iso}`;
  return look.channel === null ? iso : `${iso}&channel=${encodeURIComponent(look.channel)}`;
}

/**
 * A segment id as the server writes it: a number for u8, u16 and u32 channels, a decimal string
 * for u64 channels (a number holds integers exactly only to 2^53).
 */
export type SegmentId = number | string;

/** One segment of a channel (`GET .../channels/{channel}/segments`). */
export interface Segment {
  id: SegmentId;
  /** Level-0 voxels holding it. */
  voxels: number;
  /** Its level-0 box, [min, max) per axis as [[x0, y0, z0], [x1, y1, z1]]. */
  box: [Vec3, Vec3];
}

/** A page of a channel's segments. */
export interface SegmentList {
  version: number;
  channel: string;
  total?: number;
  segments: Segment[];
  /** The `after` of the next page, absent on the last. */
  next?: SegmentId;
}

export class Api {
  readonly base: string;
  private readonly token: () => string | null;

  constructor(base = "", token: () => string | null = () => null) {
    this.base = base;
    this.token = token;
  }

  private async send(path: string, init: RequestInit = {}): Promise<Response> {
    const headers = new Headers(init.headers);
    const token = this.token();
    if (token && !headers.has("authorization")) headers.set("authorization", `Bearer ${token}`);
    let response: Response;
    try {
      response = await fetch(this.base + path, { ...init, headers });
    } catch (e) {
      if (isAbort(e)) throw e;
      throw new ApiError(0, `cannot reach the server (${String(e)})`, null, null);
    }
    if (!response.ok) throw await failure(response);
    return response;
  }

  private async json<T>(path: string, signal?: AbortSignal): Promise<T> {
    const r = await this.send(path, signal ? { signal } : {});
    return (await r.json()) as T;
  }

  volumes(signal?: AbortSignal): Promise<{ volumes: VolumeInfo[] }> {
    return this.json("/v1/volumes", signal);
  }

  volume(name: string, signal?: AbortSignal): Promise<VolumeInfo> {
    return this.json(`/v1/volumes/${encodeURIComponent(name)}`, signal);
  }

  /** The brick grid of a box of `level` (brick coordinates, max exclusive) at `version`. */
  async levelGrid(
    name: string,
    level: number,
    min: Vec3,
    max: Vec3,
    version: number,
    signal?: AbortSignal,
  ): Promise<{ grid: LevelGrid; bytes: number }> {
    const region = [...min, ...max].join(",");
    const path = `/v1/volumes/${encodeURIComponent(name)}/levels/${level}?region=${region}&version=${version}`;
    const text = await (await this.send(path, signal ? { signal } : {})).text();
    return { grid: JSON.parse(text) as LevelGrid, bytes: text.length };
  }

  /** One mesh tile in the compact encoding (`proto/src/mesh.rs`). */
  async meshTile(
    name: string,
    key: { level: number; x: number; y: number; z: number },
    version: number,
    signal?: AbortSignal,
    look: MeshLook = { iso: null, channel: null },
  ): Promise<ArrayBuffer> {
    const path = `/v1/volumes/${encodeURIComponent(name)}/meshes/${key.level}/${key.x}/${key.y}/${key.z}?version=${version}${lookQuery(look)}`;
    const r = await this.send(path, signal ? { signal } : {});
    return r.arrayBuffer();
  }

  /**
   * The transition strip of face `face` (0..5: -x, +x, -y, +y, -z, +z) of a mesh tile: a plain
   * mesh in the compact encoding, version 1 (`docs/lod-meshes.md`).
   */
  async meshStrip(
    name: string,
    key: { level: number; x: number; y: number; z: number },
    face: number,
    version: number,
    signal?: AbortSignal,
    look: MeshLook = { iso: null, channel: null },
  ): Promise<ArrayBuffer> {
    const faceName = encodeURIComponent(["-x", "+x", "-y", "+y", "-z", "+z"][face] ?? "?");
    const path = `/v1/volumes/${encodeURIComponent(name)}/meshes/${key.level}/${key.x}/${key.y}/${key.z}/strips/${faceName}?version=${version}${lookQuery(look)}`;
    const r = await this.send(path, signal ? { signal } : {});
    return r.arrayBuffer();
  }

  /** One brick's voxels (raw, x fastest, little endian, of density's type or the channel's). */
  async brick(
    name: string,
    key: { level: number; x: number; y: number; z: number },
    signal?: AbortSignal,
    channel: string | null = null,
  ): Promise<ArrayBuffer> {
    const query = channel === null ? "" : `?channel=${encodeURIComponent(channel)}`;
    const path = `/v1/volumes/${encodeURIComponent(name)}/bricks/${key.level}/${key.x}/${key.y}/${key.z}${query}`;
    const r = await this.send(path, signal ? { signal } : {});
    return r.arrayBuffer();
  }

  /** The first `limit` segments of `channel` (ids ascending). */
  segments(name: string, channel: string, limit = 1000, signal?: AbortSignal): Promise<SegmentList> {
    return this.json(
      `/v1/volumes/${encodeURIComponent(name)}/channels/${encodeURIComponent(channel)}/segments?limit=${limit}`,
      signal,
    );
  }

  /**
   * Segment `id`'s closed mesh at `level` (compact encoding, version 1). The path takes the id in
   * decimal: a u64 id's string as it is, every digit kept.
   */
  async segmentMesh(name: string, channel: string, id: SegmentId, level: number, signal?: AbortSignal): Promise<ArrayBuffer> {
    const path = `/v1/volumes/${encodeURIComponent(name)}/channels/${encodeURIComponent(channel)}/segments/${encodeURIComponent(String(id))}/mesh?level=${level}&format=compact`;
    const r = await this.send(path, signal ? { signal } : {});
    return r.arrayBuffer();
  }

  /** Many bricks' voxels in one response (`proto/src/batch.rs`, encoding raw). */
  async batch(
    name: string,
    keys: Array<[number, number, number, number]>,
    version: number,
    signal?: AbortSignal,
  ): Promise<ArrayBuffer> {
    const r = await this.send(`/v1/volumes/${encodeURIComponent(name)}/batch`, {
      method: "POST",
      headers: { "content-type": "application/json" },
      body: JSON.stringify({ keys, version, encoding: "raw" }),
      ...(signal ? { signal } : {}),
    });
    return r.arrayBuffer();
  }

  /** The versions after `since` (410 when the history was compacted away). */
  changes(name: string, since: number, signal?: AbortSignal): Promise<ChangeList> {
    return this.json(`/v1/volumes/${encodeURIComponent(name)}/changes?since=${since}`, signal);
  }

  /** Applies an edit (`docs/editing.md`); `ifMatch` makes it conditional on a version. */
  async edit(
    name: string,
    request: unknown,
    token: string,
    ifMatch: number | null,
  ): Promise<EditResponse> {
    const headers: Record<string, string> = {
      "content-type": "application/json",
      authorization: `Bearer ${token}`,
    };
    if (ifMatch !== null) headers["if-match"] = String(ifMatch);
    const r = await this.send(`/v1/volumes/${encodeURIComponent(name)}/edits`, {
      method: "POST",
      headers,
      body: JSON.stringify(request),
    });
    return (await r.json()) as EditResponse;
  }

  /** Commits newest first (`before` a version when given). */
  history(name: string, limit = 100, before?: number): Promise<HistoryList> {
    const b = before === undefined ? "" : `&before=${before}`;
    return this.json(`/v1/volumes/${encodeURIComponent(name)}/history?limit=${limit}${b}`);
  }

  private async post<T>(path: string, body: unknown): Promise<T> {
    const r = await this.send(path, {
      method: "POST",
      headers: { "content-type": "application/json" },
      body: JSON.stringify(body),
    });
    return (r.status === 204 ? null : await r.json()) as T;
  }

  /** Takes back the edit of `version` (or, for an undo's version, makes its edit again). */
  undo(name: string, version: number): Promise<EditResponse> {
    return this.post(`/v1/volumes/${encodeURIComponent(name)}/undo`, { version });
  }

  /** Commits a version whose content is version `to`'s. */
  revert(name: string, to: number): Promise<EditResponse> {
    return this.post(`/v1/volumes/${encodeURIComponent(name)}/revert`, { to });
  }

  /** Tells the others where this page's camera is. */
  async presence(name: string, position: Vec3, looking: Vec3, label: string): Promise<void> {
    await this.post(`/v1/volumes/${encodeURIComponent(name)}/presence`, { position, looking, label });
  }

  /**
   * Who the token is (`user` null without one) and how to sign in; `anonymous` asks without the
   * token (how to sign in, when the token was refused).
   */
  async auth(anonymous = false): Promise<AuthInfo> {
    if (!anonymous) return this.json("/v1/auth");
    const r = await fetch(`${this.base}/v1/auth`);
    if (!r.ok) throw await failure(r);
    return (await r.json()) as AuthInfo;
  }

  /**
   * The change feed's server-sent events after `since`, as a byte stream. Read with `fetch`, not
   * `EventSource`: an `EventSource` cannot send the `Authorization` header private reads need.
   */
  async events(name: string, since: number, signal: AbortSignal): Promise<ReadableStream<Uint8Array>> {
    const r = await this.send(`/v1/volumes/${encodeURIComponent(name)}/events?since=${since}`, {
      headers: { accept: "text/event-stream" },
      cache: "no-store",
      signal,
    });
    if (!r.body) throw new ApiError(0, "the change feed has no body", null, null);
    return r.body;
  }
}
