// The viewer's page: wires the API, the streamer, the change feed, the 3D view, editing, the
// slice view, the overlay and the URL together.

import "./style.css";
import * as THREE from "three";
import { Api, ApiError, editErrorWords, readErrorWords, type ChannelInfo, type VolumeInfo } from "./api";
import { editRequest, OPERATORS, previewOf, PRIMITIVES, TokenStore, type Preview, type Primitive } from "./edit";
import { Feed, type FeedState } from "./feed";
import { radiiForScreenError } from "./lod";
import { Viewport, type Navigation } from "./scene";
import { AXIS, SliceView, type Axis } from "./slice";
import { Streamer } from "./streamer";
import { COLORMAPS, neuroglancerUrl, type Colormap } from "./colormap";
import { readUrl, writeUrl, type UrlState } from "./url";
import "./people.css";
import { People } from "./people";
import { SegmentPanel } from "./segments";
import { decodeVoxels, voxelValue, type VoxelType, type Voxels } from "./voxels";

const $ = <T extends HTMLElement>(id: string) => document.getElementById(id) as T;

const tokens = new TokenStore();
// Every request carries the session's token once there is one (private reads need it).
const api = new Api("", () => tokens.get());
const viewport = new Viewport($<HTMLCanvasElement>("view"));
const slice = new SliceView(api, $<HTMLCanvasElement>("slice"));
const overlay = $<HTMLPreElement>("overlay");
const editStatus = $<HTMLParagraphElement>("edit-status");
const segments = new SegmentPanel(api, viewport, {
  section: $("segments-section"),
  channel: $<HTMLSelectElement>("segment-channel"),
  status: $("segments-status"),
  list: $("segments"),
});

let info: VolumeInfo | null = null;
let streamer: Streamer | null = null;
let feed: Feed | null = null;
let feedState: FeedState = "connecting";
let protocol = "http/1.1";
let frames = 0;
let firstFrameMs: number | null = null;
let completeMs: number | null = null;
let completeInViewMs: number | null = null;
let lastEdit: { version: number; sent: number; answerMs: number; screenMs: number | null } | null =
  null;
const wire = { requests: 0, bytes: 0 };

// Bytes on the wire and requests, as the browser counts them (headers and compression
// included, cached answers as 0).
performance.setResourceTimingBufferSize(100_000);
new PerformanceObserver((list) => {
  for (const e of list.getEntries() as PerformanceResourceTiming[]) {
    if (!e.name.includes("/v1/")) continue;
    wire.requests++;
    wire.bytes += e.transferSize;
    if (e.nextHopProtocol && e.nextHopProtocol !== protocol) {
      protocol = e.nextHopProtocol;
      if (streamer) {
        streamer.maxInFlight = inFlightBudget();
        streamer.plan();
      }
    }
  }
}).observe({ type: "resource", buffered: true });

// --- the volume --------------------------------------------------------------------------

/**
 * Requests the streamer keeps in flight. Over HTTP/1.1 a browser opens six connections per
 * host and the change feed holds one: five carry tiles and the sixth request waits in the
 * browser's queue, which starts it the moment a connection frees instead of when the page's
 * main thread next runs (with software rendering it may be drawing a frame for hundreds of
 * milliseconds). An edit or a slice then waits behind that one request. Many more share one
 * HTTP/2 connection.
 */
function inFlightBudget(): number {
  return protocol === "h2" || protocol === "h3" ? 16 : 6;
}

/**
 * A plan after a response waits out three times the last plan's cost (`StreamerOptions`
 * `planPause`): plans after responses then take about a quarter of the main thread at most
 * while tiles stream in.
 */
const PLAN_PAUSE = 3;

function radii(v: VolumeInfo): number[] {
  const detail = Number($<HTMLInputElement>("detail").value);
  const h = viewport.renderer.domElement.clientHeight || 720;
  return radiiForScreenError(v.levels.length, v.voxel_scale, (viewport.camera.fov * Math.PI) / 180, h, detail);
}

function cameraPosition(): [number, number, number] {
  const p = viewport.camera.position;
  return [p.x, p.y, p.z];
}

/** Whether a box (world units) is in the camera's view frustum now. */
function inViewNow(): (min: [number, number, number], max: [number, number, number]) => boolean {
  const camera = viewport.camera;
  camera.updateMatrixWorld();
  const frustum = new THREE.Frustum().setFromProjectionMatrix(
    new THREE.Matrix4().multiplyMatrices(camera.projectionMatrix, camera.matrixWorldInverse),
  );
  const box = new THREE.Box3();
  return (min, max) => frustum.intersectsBox(box.set(new THREE.Vector3(...min), new THREE.Vector3(...max)));
}

async function openVolume(name: string, state: UrlState | null): Promise<void> {
  streamer?.stop();
  feed?.close();
  for (const p of previews.splice(0)) viewport.removePreview(p.id);
  const v = await api.volume(name);
  info = v;
  const view = state?.camera && {
    position: new THREE.Vector3(...state.camera.position),
    target: new THREE.Vector3(...state.camera.target),
  };
  viewport.setVolume(v, view ?? undefined);
  if (state?.detail) $<HTMLInputElement>("detail").value = String(state.detail);
  $<HTMLInputElement>("iso").value = state?.iso != null ? String(state.iso) : "";
  $<HTMLInputElement>("iso").min = String(v.low);
  $<HTMLInputElement>("iso").max = String(v.high);
  showMaterials(v);
  segments.open(v);
  const materials = materialChannel(v);
  const map = state?.colormap ?? (materials ? "materials" : "terrain");
  setColormap(map === "materials" && !materials ? "terrain" : map);
  if (state?.navigation) setNavigation(state.navigation);
  const s = new Streamer({
    api,
    info: v,
    sink: viewport,
    radii: radii(v),
    maxInFlight: inFlightBudget(),
    planPause: PLAN_PAUSE,
    onChange: changed,
    inView: inViewNow(),
  });
  streamer = s;
  s.setIso(chosenIso());
  s.setChannel(meshChannel());
  s.setCamera(cameraPosition());
  updateNeuroglancer();
  feed = new Feed(api, name, v.version, {
    commit: (ev) => {
      // While an older version is shown, the live one is caught up when the page returns.
      if (people.viewing === null) s.applyCommit(ev);
      if (slice.touches(ev.changed)) void loadSlice();
      people.commit(ev);
      segments.commit(ev);
    },
    presence: (p) => people.presence(p),
    reload: async () => {
      const fresh = await api.volume(name);
      s.reload(fresh);
      void loadSlice();
      return fresh.version;
    },
    state: (st) => {
      feedState = st;
      updateOverlay();
    },
  });
  setupSlice(v, state);
  people.open(v);
  writeUrl(urlState());
}

let changePending = false;
/** Whether the view was complete (every tile, every tile in view) at the last change. */
let wasComplete = false;
let wasCompleteInView = false;

/** The streamer changed what it shows or knows: update the rest once per frame. */
function changed(): void {
  if (changePending) return;
  changePending = true;
  requestAnimationFrame(() => {
    changePending = false;
    afterChange();
  });
}

/**
 * The page's own edits drawn at once, until its view shows them: the preview's id in the view,
 * and the edit's version once the server answered (null before).
 */
const previews: Array<{ id: number; version: number | null }> = [];

/** Takes away the previews of the edits the view shows now (or of `failed`, an edit refused). */
function clearPreviews(failed?: number): void {
  const st = streamer?.stats();
  for (let i = previews.length - 1; i >= 0; i--) {
    const p = previews[i]!;
    const shown = p.version !== null && st !== undefined && st.version >= p.version && st.stale === 0;
    if (p.id === failed || shown) {
      viewport.removePreview(p.id);
      previews.splice(i, 1);
    }
  }
}

function afterChange(): void {
  const s = streamer;
  if (!s) return;
  clearPreviews();
  if (lastEdit && lastEdit.screenMs === null) {
    const st = s.stats();
    if (st.version >= lastEdit.version && st.stale === 0) {
      // Drawn with the next frame.
      const edit = lastEdit;
      requestAnimationFrame(() => {
        edit.screenMs = performance.now() - edit.sent;
        updateOverlay();
      });
    }
  }
  // The frame that completes the view (every tile in it, or every tile) is drawn at once, not
  // after the last frame's pause; when the last tiles were out of the view frustum, which draws
  // no frame by itself, it marks the view complete.
  const st = s.stats();
  if ((st.complete && !wasComplete) || (st.completeInView && !wasCompleteInView)) viewport.requestRender(true);
  wasComplete = st.complete;
  wasCompleteInView = st.completeInView;
  // No frame otherwise: the view draws a frame when a tile comes or goes (and swiftshader takes
  // about 100 ms for one of the default view, time the requests after it would wait for).
  updateOverlay();
}

// Frames wait for the last one's pause only while tiles are on their way (scene.ts).
viewport.busy = () => (streamer?.inFlight ?? 0) > 0;

viewport.onFrame = (tiles) => {
  frames++;
  const now = performance.now();
  if (firstFrameMs === null && tiles > 0) {
    firstFrameMs = now;
    performance.mark("isovox:first-frame");
  }
  const st = streamer?.stats();
  if (completeInViewMs === null && st?.completeInView && tiles > 0) completeInViewMs = now;
  if (completeMs === null && st?.complete) {
    completeMs = now;
    performance.mark("isovox:complete");
  }
  // Commits whose tiles were all swapped in before this frame: on screen now.
  for (const t of streamer?.traces.values() ?? []) {
    if (t.shown !== null && t.frame === null) t.frame = now;
  }
  updateOverlay();
};

// The radii follow the canvas's height (the screen-space error is in its pixels), and the view
// frustum its shape.
new ResizeObserver(() => {
  if (!info || !streamer) return;
  streamer.radii = radii(info);
  streamer.setView(cameraPosition(), inViewNow());
}).observe(viewport.renderer.domElement);

let cameraTimer: ReturnType<typeof setTimeout> | null = null;
viewport.onCameraChange = () => {
  // The selection is planned again at most every 100 ms while the camera moves.
  if (cameraTimer !== null) return;
  cameraTimer = setTimeout(() => {
    cameraTimer = null;
    streamer?.setView(cameraPosition(), inViewNow());
    writeUrl(urlState());
    updateNeuroglancer();
  }, 100);
};

// --- overlay -----------------------------------------------------------------------------

function mb(bytes: number): string {
  return `${(bytes / 1e6).toFixed(2)} MB`;
}

function updateOverlay(): void {
  const s = streamer?.stats();
  if (!s || !info) return;
  const lines = [
    `${info.name}  version ${s.version}  feed ${feedState}`,
    `tiles ${s.ready}/${s.desired} ready, ${s.drawn} drawn, ${s.triangles.toLocaleString("en")} triangles`,
    `in flight ${s.inFlight} of ${s.inFlightLimit}` +
      (s.inFlightLimit < (streamer?.maxInFlight ?? 0) ? ` (server busy; at most ${streamer?.maxInFlight})` : "") +
      ` (${protocol})`,
    `${mb(s.bytes)} received in ${s.requests} requests, ${mb(wire.bytes)} on the wire`,
  ];
  if (lastEdit) {
    const screen = lastEdit.screenMs === null ? "..." : `${lastEdit.screenMs.toFixed(0)} ms`;
    lines.push(`last edit: answered in ${lastEdit.answerMs.toFixed(0)} ms, on screen in ${screen}`);
  }
  if (s.lastError) lines.push(`last error: ${s.lastError}`);
  overlay.textContent = lines.join("\n");
}

// --- URL ---------------------------------------------------------------------------------

function urlState(): UrlState {
  return {
    volume: info?.name ?? null,
    camera: {
      position: cameraPosition(),
      target: [viewport.target.x, viewport.target.y, viewport.target.z],
    },
    navigation: viewport.navigation,
    detail: Number($<HTMLInputElement>("detail").value),
    slice: $<HTMLInputElement>("slice-on").checked
      ? { axis: slice.state.axis, position: slice.state.position }
      : null,
    iso: chosenIso(),
    colormap: $<HTMLSelectElement>("colormap").value as Colormap,
  };
}

// --- controls ----------------------------------------------------------------------------

function setNavigation(n: Navigation): void {
  $<HTMLSelectElement>("navigation").value = n;
  viewport.setNavigation(n);
}

$<HTMLSelectElement>("navigation").addEventListener("change", (e) => {
  setNavigation((e.target as HTMLSelectElement).value as Navigation);
  writeUrl(urlState());
});
$<HTMLInputElement>("detail").addEventListener("change", () => {
  if (info) streamer?.setRadii(radii(info));
  writeUrl(urlState());
});
$<HTMLSelectElement>("volume").addEventListener("change", (e) => {
  void openVolume((e.target as HTMLSelectElement).value, null);
});

// --- editing -----------------------------------------------------------------------------

for (const { op, label } of OPERATORS) $<HTMLSelectElement>("op").add(new Option(label, op));
for (const p of PRIMITIVES) $<HTMLSelectElement>("primitive").add(new Option(p, p));
$<HTMLSelectElement>("op").value = "difference";
$<HTMLSelectElement>("op").addEventListener("change", (e) => {
  $("overwrite-label").hidden = (e.target as HTMLSelectElement).value !== "paint";
});

/** The volume's material channel (u8, named `material`), which meshes can carry. */
function materialChannel(v: VolumeInfo): ChannelInfo | null {
  return v.channels?.find((c) => c.name === "material" && c.type === "u8") ?? null;
}

/**
 * The material controls for volume `v`: the picker (none, or one of the palette's values,
 * each on its colour), paint as an operation, the "materials" colouring; hidden without a
 * material channel.
 */
function showMaterials(v: VolumeInfo): void {
  const channel = materialChannel(v);
  const picker = $<HTMLSelectElement>("material");
  picker.replaceChildren(new Option("as it is (none given)", ""));
  for (const [value, color] of (channel?.palette ?? []).entries()) {
    if (value === 0) continue;
    const option = new Option(`material ${value}`, String(value));
    option.style.background = color;
    picker.add(option);
  }
  $("material-label").hidden = channel === null;
  const op = $<HTMLSelectElement>("op");
  for (const option of op.options) {
    if (option.value === "paint") option.hidden = option.disabled = channel === null;
  }
  if (channel === null && op.value === "paint") op.value = "difference";
  $("overwrite-label").hidden = op.value !== "paint";
  for (const option of $<HTMLSelectElement>("colormap").options) {
    if (option.value === "materials") option.hidden = option.disabled = channel === null;
  }
  viewport.setPalette(channel?.palette ?? []);
}

/** The channel the meshes carry: the material channel while the surface is coloured by it. */
function meshChannel(): string | null {
  const map = $<HTMLSelectElement>("colormap").value;
  return map === "materials" && info && materialChannel(info) ? "material" : null;
}

let pendingEdit: { request: Record<string, unknown>; preview: Preview | null } | null = null;
/** The server refused to read without a (right) token: the page starts once one is given. */
let awaitingReadToken = false;
/** The session's token may only read (403): the next edit asks for a write token. */
let writeRefused = false;

/** Shows the token prompt (one token per session, for reads and edits alike). */
function askToken(): void {
  $<HTMLFormElement>("token-form").hidden = false;
  $<HTMLInputElement>("token").focus();
}

function say(text: string, error = false): void {
  editStatus.textContent = text;
  editStatus.classList.toggle("error", error);
}

async function sendEdit(request: Record<string, unknown>, preview: Preview | null = null): Promise<void> {
  if (!info || !streamer) return;
  if (people.viewing !== null) {
    say(`Viewing version ${people.viewing}, read-only: go back to live to edit.`, true);
    return;
  }
  const token = tokens.get();
  if (!token || writeRefused) {
    pendingEdit = { request, preview };
    askToken();
    say("Enter the write token (asked once for this session).");
    return;
  }
  const ifMatch = $<HTMLInputElement>("if-match").checked ? streamer.version : null;
  const sent = performance.now();
  say("Applying...");
  // Drawn at once, while the server applies the edit and the view fetches its tiles.
  const shown = preview ? { id: viewport.addPreview(preview, info.voxel_scale), version: null as number | null } : null;
  if (shown) previews.push(shown);
  try {
    const r = await api.edit(info.name, request, token, ifMatch);
    lastEdit = { version: r.version, sent, answerMs: performance.now() - sent, screenMs: null };
    if (shown) shown.version = r.version;
    say(`Applied as version ${r.version}.`);
    people.edited(r.version);
    changed();
  } catch (e) {
    if (shown) clearPreviews(shown.id);
    // A wrong token is forgotten. A read-only one still serves the page's reads until a write
    // token replaces it.
    if (e instanceof ApiError && e.status === 401) tokens.forget();
    if (e instanceof ApiError && e.status === 403) writeRefused = true;
    say(editErrorWords(e), true);
  }
}

$<HTMLFormElement>("token-form").addEventListener("submit", (e) => {
  e.preventDefault();
  const input = $<HTMLInputElement>("token");
  if (!input.value.trim()) return;
  tokens.set(input.value);
  writeRefused = false;
  input.value = "";
  $<HTMLFormElement>("token-form").hidden = true;
  void people.whoAmI();
  if (awaitingReadToken) {
    awaitingReadToken = false;
    begin();
  }
  const r = pendingEdit;
  pendingEdit = null;
  if (r) void sendEdit(r.request, r.preview);
});

/** Edits at canvas pixel (x, y): picks the surface and sends the edit. */
function editAt(x: number, y: number): void {
  if (!info) return;
  const p = viewport.pick(x, y);
  if (!p) {
    say("No surface under the pointer.", true);
    return;
  }
  const s = info.voxel_scale;
  const op = $<HTMLSelectElement>("op").value;
  const primitive = $<HTMLSelectElement>("primitive").value as Primitive;
  const center: [number, number, number] = [p.x / s[0], p.y / s[1], p.z / s[2]];
  const size = Number($<HTMLInputElement>("size").value);
  const chosen = $<HTMLSelectElement>("material").value;
  const material = chosen === "" || !materialChannel(info) ? null : Number(chosen);
  if (op === "paint" && material === null) {
    say("Choose a material to paint with.", true);
    return;
  }
  const overwrite = $<HTMLSelectElement>("overwrite").value === "empty" ? "empty" : "all";
  const request = editRequest(op, primitive, center, size, info.dims, { material, overwrite });
  if (!request) {
    say("The shape lies outside the volume.", true);
    return;
  }
  void sendEdit(request, previewOf(op, primitive, center, size));
}

{
  const canvas = viewport.renderer.domElement;
  let down: { x: number; y: number; t: number } | null = null;
  canvas.addEventListener("pointerdown", (e) => (down = { x: e.clientX, y: e.clientY, t: e.timeStamp }));
  canvas.addEventListener("pointerup", (e) => {
    const d = down;
    down = null;
    if (!d || !$<HTMLInputElement>("edit-mode").checked) return;
    // A click, not the end of a drag that moved the camera.
    if (Math.hypot(e.clientX - d.x, e.clientY - d.y) > 4 || e.timeStamp - d.t > 600) return;
    const r = canvas.getBoundingClientRect();
    editAt(e.clientX - r.left, e.clientY - r.top);
  });
}

// --- people: undo, history, cursors, sign-in (people.ts) ----------------------------------

const people = new People({
  api,
  tokens,
  volume: () => info,
  camera: () => {
    const c = viewport.camera;
    const d = c.position.distanceTo(viewport.target);
    const looking = c.position.clone().addScaledVector(c.getWorldDirection(new THREE.Vector3()), d);
    return { position: cameraPosition(), looking: [looking.x, looking.y, looking.z] };
  },
  project: (p) => {
    const v = new THREE.Vector3(...p).project(viewport.camera);
    // Behind the camera (or on it): not drawn.
    if (!(v.z > -1 && v.z < 1)) return null;
    return viewport.project(new THREE.Vector3(...p));
  },
  show: (version) => {
    if (streamer && info) streamer.reload({ ...info, version: version ?? feed?.version ?? info.version });
  },
  say,
  askToken,
});

// Markers follow every camera move and frame; the others are told (throttled, presence.ts).
{
  const cameraChanged = viewport.onCameraChange;
  viewport.onCameraChange = () => {
    cameraChanged();
    people.cameraMoved();
  };
  const frameDrawn = viewport.onFrame;
  viewport.onFrame = (tiles) => {
    frameDrawn(tiles);
    people.frame();
  };
}

// --- slice -------------------------------------------------------------------------------

async function loadSlice(): Promise<void> {
  if (!$<HTMLInputElement>("slice-on").checked || !streamer) return;
  try {
    await slice.load(streamer.version);
  } catch (e) {
    if (!(e instanceof DOMException && e.name === "AbortError")) say(`Slice: ${String(e)}`, true);
  }
}

function setupSlice(v: VolumeInfo, state: UrlState | null): void {
  slice.setVolume(v, state?.slice ?? undefined);
  $<HTMLInputElement>("slice-on").checked = state?.slice != null;
  const levels = $<HTMLSelectElement>("slice-level");
  levels.replaceChildren(new Option("auto", "auto"), ...v.levels.map((l) => new Option(String(l.level))));
  const width = $<HTMLInputElement>("slice-width");
  const center = $<HTMLInputElement>("slice-center");
  for (const input of [width, center]) input.max = String(v.high - v.low);
  width.min = "1";
  center.min = String(v.low);
  width.value = String(slice.state.width);
  center.value = String(slice.state.center);
  $<HTMLSelectElement>("slice-axis").value = slice.state.axis;
  syncSlicePosition();
  $<HTMLDivElement>("slice-box").hidden = !$<HTMLInputElement>("slice-on").checked;
  showSlicePlane();
  void loadSlice();
}

function syncSlicePosition(): void {
  if (!info) return;
  const pos = $<HTMLInputElement>("slice-pos");
  pos.max = String(info.dims[AXIS[slice.state.axis]] - 1);
  pos.value = String(slice.state.position);
}

$<HTMLInputElement>("slice-on").addEventListener("change", (e) => {
  const on = (e.target as HTMLInputElement).checked;
  $<HTMLDivElement>("slice-box").hidden = !on;
  showSlicePlane();
  void loadSlice();
  writeUrl(urlState());
});
$<HTMLSelectElement>("slice-axis").addEventListener("change", (e) => {
  slice.state.axis = (e.target as HTMLSelectElement).value as Axis;
  if (info) slice.state.position = Math.floor(info.dims[AXIS[slice.state.axis]] / 2);
  syncSlicePosition();
  showSlicePlane();
  void loadSlice();
  writeUrl(urlState());
});
$<HTMLInputElement>("slice-pos").addEventListener("change", (e) => {
  slice.state.position = Number((e.target as HTMLInputElement).value);
  showSlicePlane();
  void loadSlice();
  writeUrl(urlState());
});
$<HTMLSelectElement>("slice-level").addEventListener("change", (e) => {
  const v = (e.target as HTMLSelectElement).value;
  slice.state.level = v === "auto" ? "auto" : Number(v);
  void loadSlice();
});
for (const id of ["slice-width", "slice-center"]) {
  $<HTMLInputElement>(id).addEventListener("input", () => {
    slice.state.width = Number($<HTMLInputElement>("slice-width").value);
    slice.state.center = Number($<HTMLInputElement>("slice-center").value);
    slice.draw();
  });
}

/** The slice's plane in the 3D view, while the slice is shown. */
function showSlicePlane(): void {
  if (!info || !$<HTMLInputElement>("slice-on").checked) {
    viewport.setSlicePlane(null);
    return;
  }
  const a = AXIS[slice.state.axis];
  const s = info.voxel_scale;
  const size = new THREE.Vector3(info.dims[0] * s[0], info.dims[1] * s[1], info.dims[2] * s[2]);
  // Voxel i's sample sits at i (the surface's coordinates), so the plane too.
  viewport.setSlicePlane({ axis: slice.state.axis, position: slice.state.position * (s[a] ?? 1), size });
}

// --- for scans: colour map, iso value, the voxel under the pointer, Neuroglancer ----------

for (const m of COLORMAPS) $<HTMLSelectElement>("colormap").add(new Option(m, m));

function setColormap(map: Colormap): void {
  $<HTMLSelectElement>("colormap").value = map;
  viewport.setColormap(map);
  slice.setColormap(map);
  streamer?.setChannel(meshChannel());
}

$<HTMLSelectElement>("colormap").addEventListener("change", (e) => {
  setColormap((e.target as HTMLSelectElement).value as Colormap);
  writeUrl(urlState());
});

/** The iso value chosen, or null for the volume's default (empty or out of its range). */
function chosenIso(): number | null {
  const text = $<HTMLInputElement>("iso").value.trim();
  const v = Number(text);
  if (!info || text === "" || !Number.isFinite(v) || v < info.low || v > info.high) return null;
  return v;
}

$<HTMLInputElement>("iso").addEventListener("change", () => {
  streamer?.setIso(chosenIso());
  writeUrl(urlState());
});

function updateNeuroglancer(): void {
  if (!info) return;
  const t = viewport.target;
  const s = info.voxel_scale;
  const center: [number, number, number] = [t.x / s[0], t.y / s[1], t.z / s[2]].map(Math.round) as [number, number, number];
  const base = new URLSearchParams(location.search).get("neuroglancer") ?? "https://neuroglancer-demo.appspot.com/";
  $<HTMLAnchorElement>("neuroglancer").href = neuroglancerUrl(base, location.origin, info.name, center);
}

/** What the pointer is over: a voxel's position and value, or nothing. */
let probe: {
  where: string;
  position: [number, number, number];
  level: number;
  value: number;
  /**
   * Over the surface: the channels' values at the voxel (material, label, ...), exact: u64
   * values as decimal strings, as the segment list writes their ids.
   */
  channels?: Record<string, number | string>;
} | null = null;

function showProbe(): void {
  $<HTMLParagraphElement>("probe").textContent = probe
    ? `${probe.where} (${probe.position.join(", ")})${probe.level > 0 ? ` level ${probe.level}` : ""}: ${probe.value}` +
      Object.entries(probe.channels ?? {})
        .map(([name, value]) => `, ${name} ${value}`)
        .join("")
    : "pointer: -";
}

{
  // Over the slice: the voxel shown under the pointer (from the loaded slice, as drawn).
  const canvas = $<HTMLCanvasElement>("slice");
  canvas.addEventListener("pointermove", (e) => {
    const r = canvas.getBoundingClientRect();
    // The canvas is drawn with object-fit: contain: find the drawn image's box.
    const scale = Math.min(r.width / canvas.width, r.height / canvas.height);
    const x0 = r.left + (r.width - canvas.width * scale) / 2;
    const y0 = r.top + (r.height - canvas.height * scale) / 2;
    const v = slice.voxelAt((e.clientX - x0) / scale, (e.clientY - y0) / scale);
    probe = v && { where: "slice", ...v };
    showProbe();
  });
}

{
  // Over the 3D view: the level-0 voxel nearest the surface point under the pointer, its value
  // read from its brick (one request per brick and version, at most every 100 ms).
  const canvas = viewport.renderer.domElement;
  const bricks = new Map<string, Promise<Voxels>>();
  let timer: ReturnType<typeof setTimeout> | null = null;
  let last: { x: number; y: number } | null = null;
  const look = async () => {
    timer = null;
    const v = info;
    if (!last || !v || !streamer) return;
    const p = viewport.pick(last.x, last.y);
    if (!p) {
      probe = null;
      showProbe();
      return;
    }
    const s = v.voxel_scale;
    const pos = [p.x / s[0], p.y / s[1], p.z / s[2]].map((c, a) =>
      Math.min(v.dims[a]! - 1, Math.max(0, Math.round(c))),
    ) as [number, number, number];
    const b = v.brick;
    const key = { level: 0, x: Math.floor(pos[0] / b), y: Math.floor(pos[1] / b), z: Math.floor(pos[2] / b) };
    const version = streamer.version;
    // The brick's voxels of density (channel null) or of a channel, each once per version.
    const voxelsOf = (channel: string | null, type: VoxelType) => {
      const id = `${v.name}/${version}/${channel ?? ""}/${key.x}/${key.y}/${key.z}`;
      let voxels = bricks.get(id);
      if (!voxels) {
        if (bricks.size > 64) bricks.clear();
        voxels = api.brick(v.name, key, undefined, channel).then((buf) => decodeVoxels(buf, type));
        bricks.set(id, voxels);
        voxels.catch(() => bricks.delete(id));
      }
      return voxels;
    };
    const l = [pos[0] % b, pos[1] % b, pos[2] % b];
    const at = l[0]! + b * (l[1]! + b * l[2]!);
    const data = await voxelsOf(null, v.voxel_type);
    const channels = await Promise.all(
      (v.channels ?? []).map(async (c) => [c.name, voxelValue(await voxelsOf(c.name, c.type), at)] as const),
    );
    // The pointer left the view meanwhile: what is under it now (the slice, or nothing) stands.
    if (!last) return;
    // Density is u8 or u16: always a number.
    probe = { where: "surface", position: pos, level: 0, value: Number(data[at] ?? 0), channels: Object.fromEntries(channels) };
    showProbe();
  };
  canvas.addEventListener("pointermove", (e) => {
    const r = canvas.getBoundingClientRect();
    last = { x: e.clientX - r.left, y: e.clientY - r.top };
    if (timer === null) timer = setTimeout(() => void look().catch(() => {}), 100);
  });
  // Off the view (onto the slice box, which lies over it, or the panel): a look still to come
  // would put the voxel under the pointer's last place in the view over what it is on now.
  canvas.addEventListener("pointerleave", () => {
    last = null;
    if (timer !== null) clearTimeout(timer);
    timer = null;
  });
}

// --- start -------------------------------------------------------------------------------

/** For the browser tests and the benchmark: what the page shows, read without scraping. */
const hook = {
  stats: () => ({
    ...(streamer?.stats() ?? null),
    volume: info?.name ?? null,
    feed: feedState,
    protocol,
    webgl2: viewport.webgl2,
    frames,
    tilesOnScreen: viewport.tileCount,
    framePending: viewport.framePending,
    /** The page's own edits drawn as previews, waiting for their tiles. */
    previews: viewport.previewCount,
    /** Segment meshes shown from the segment list. */
    segments: viewport.segmentCount,
    firstFrameMs,
    completeMs,
    completeInViewMs,
    wireRequests: wire.requests,
    wireBytes: wire.bytes,
    lastEdit,
    editStatus: editStatus.textContent,
  }),
  /** Where world point (x, y, z) appears on the canvas, in CSS pixels. */
  project: (x: number, y: number, z: number) => viewport.project(new THREE.Vector3(x, y, z)),
  /** The ray from the camera through canvas pixel (x, y): origin and unit direction. */
  ray: (x: number, y: number) => {
    const r = viewport.ray(x, y).ray;
    return { origin: r.origin.toArray(), direction: r.direction.toArray() };
  },
  /** The surface point under canvas pixel (x, y), or null. */
  pick: (x: number, y: number) => viewport.pick(x, y)?.toArray() ?? null,
  /** The camera: where it is, where it looks (a unit vector), and how it is steered. */
  camera: () => ({
    position: cameraPosition(),
    direction: viewport.camera.getWorldDirection(new THREE.Vector3()).toArray(),
    navigation: viewport.navigation,
  }),
  /** When recent commits reached the page and the screen (performance.now() milliseconds). */
  traces: () => [...(streamer?.traces.values() ?? [])].map((t) => ({ ...t })),
  /** The voxel under the pointer (3D view or slice), as the panel shows it. */
  probe: () => probe,
  /** The tiles the camera needs now, as [level, x, y, z]. */
  selection: () => (streamer?.selection() ?? []).map((k) => [k.level, k.x, k.y, k.z]),
  /** Who the page is, the others' cursors, the history panel's rows, the undo stacks. */
  people: () => people.state(),
};
(window as unknown as { isovox: typeof hook }).isovox = hook;

async function start(): Promise<void> {
  const state = readUrl();
  const tokenSent = tokens.get() !== null;
  let volumes: VolumeInfo[];
  try {
    ({ volumes } = await api.volumes());
  } catch (e) {
    overlay.textContent = readErrorWords(e, tokenSent);
    if (e instanceof ApiError && e.status === 401) {
      // Private reads: ask for the token, and start again when it is given.
      if (tokenSent) tokens.forget();
      awaitingReadToken = true;
      askToken();
    }
    return;
  }
  const picker = $<HTMLSelectElement>("volume");
  picker.replaceChildren();
  for (const v of volumes) picker.add(new Option(`${v.name} (${v.dims.join("x")} ${v.voxel_type})`, v.name));
  const name =
    volumes.find((v) => v.name === state.volume)?.name ??
    volumes.find((v) => v.name === "demo")?.name ??
    volumes[0]?.name;
  if (!name) {
    overlay.textContent = "The server serves no volume.";
    return;
  }
  picker.value = name;
  await openVolume(name, state);
}

function begin(): void {
  people
    .start()
    .then(start)
    .catch((e: unknown) => {
      overlay.textContent = readErrorWords(e, tokens.get() !== null);
    });
}

begin();
