// Browser tests of the viewer: Debian's chromium (playwright-core, SwiftShader WebGL2) against a
// real `isovox serve` (the binary named by ISOVOX_BIN) on the demo world.
//
//   ISOVOX_BIN=target/debug/isovox node --test tests/browser.test.mjs     (in web/)
//
// `cargo test -p isovox-server --test web` runs this with the binary it built.

import { execFileSync } from "node:child_process";
import { copyFileSync, mkdtempSync, rmSync, writeFileSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";
import { after, before, test } from "node:test";
import assert from "node:assert/strict";
import { launch } from "./chromium.mjs";
import { decodePng, pixel } from "./png.mjs";
import { demoToken, startServer } from "./server.mjs";

const BIN = process.env.ISOVOX_BIN;
const VIEW = { width: 800, height: 500 };
/** The sky colour of scene.ts (0x9cc4e4). */
const SKY = [0x9c, 0xc4, 0xe4];
/** Where the overlay text and the control panel are: left out of pixel comparisons. */
const OVERLAY = { x: 0, y: 0, w: 520, h: 110 };
const PANEL_W = 270;
/** A pixel of the default view on the terrain in front (edits there are in plain sight). */
const FRONT = { x: Math.round((VIEW.width - PANEL_W) * 0.42), y: Math.round(VIEW.height * 0.72) };

let dataDir;
let server;
let browser;
let token;

before(async () => {
  assert.ok(BIN, "set ISOVOX_BIN to the isovox binary");
  dataDir = mkdtempSync(join(tmpdir(), "isovox-browser-"));
  // The first start generates the demo world and a write token; a u16 volume joins it after.
  const first = await startServer(BIN, dataDir);
  await first.kill();
  execFileSync(BIN, [
    "generate", "ellipsoid", "-o", join(dataDir, "ell16.vod"),
    "--dims", "96,80,64", "--brick", "16", "--type", "u16",
  ]);
  // A scan-like ball: u8 values falling off from the centre, 255 - 6 d (d in voxels from
  // (31.5, 31.5, 31.5)), so each iso value has its own sphere: radius (255 - iso) / 6.
  const ball = new Uint8Array(64 ** 3);
  for (let z = 0; z < 64; z++) for (let y = 0; y < 64; y++) for (let x = 0; x < 64; x++) {
    const d = Math.hypot(x - 31.5, y - 31.5, z - 31.5);
    ball[x + 64 * (y + 64 * z)] = Math.max(0, Math.min(255, Math.round(255 - 6 * d)));
  }
  writeFileSync(join(dataDir, "ball.raw"), ball);
  execFileSync(BIN, ["import", join(dataDir, "ball.raw"), "--dims", "64,64,64", "--brick", "16", "-o", join(dataDir, "ball.vod")]);
  rmSync(join(dataDir, "ball.raw"));
  server = await startServer(BIN, dataDir);
  token = demoToken(dataDir);
  browser = await launch();
});

after(async () => {
  await browser?.close();
  await server?.kill();
  if (dataDir) rmSync(dataDir, { recursive: true, force: true });
});

// --- helpers -------------------------------------------------------------------------------

/** A request to the API of `on` (the shared server by default), with `on.token` if given. */
async function api(path, init = {}, on = { base: server.base, token: null }) {
  const headers = { ...init.headers, ...(on.token ? { authorization: `Bearer ${on.token}` } : {}) };
  const r = await fetch(on.base + path, { ...init, headers });
  assert.ok(r.ok, `${path}: ${r.status} ${await r.clone().text()}`);
  return r;
}

/** A page of its own (own session storage) on `query`, with its console errors collected. */
async function openPage(query = "", base = server.base) {
  const context = await browser.newContext({ viewport: VIEW });
  const page = await context.newPage();
  const errors = [];
  page.on("console", (m) => {
    if (m.type() === "error") errors.push(m.text());
  });
  page.on("pageerror", (e) => errors.push(e.message));
  await page.goto(`${base}/${query}`);
  return { context, page, errors };
}

const stats = (page) => page.evaluate(() => window.isovox?.stats() ?? null);

async function waitFor(page, what, predicate, timeoutMs = 60_000) {
  const start = Date.now();
  let last = null;
  while (Date.now() - start < timeoutMs) {
    last = await stats(page);
    if (last && predicate(last)) return last;
    await page.waitForTimeout(100);
  }
  throw new Error(`timed out waiting for ${what}; last stats ${JSON.stringify(last)}`);
}

/**
 * Waits until every tile the camera needs shows its current content, and a frame drew it: no
 * frame is pending (one asked for soon after another waits out that one's pause, scene.ts
 * `requestRender`, so frames of the browser alone do not tell), then two more frames for the
 * browser to composite it.
 */
async function waitComplete(page, version = 0) {
  const s = await waitFor(
    page,
    `the view to be complete at version ${version} and drawn`,
    (s) => s.complete && s.completeMs !== null && s.version >= version && s.stale === 0 && !s.framePending,
  );
  await page.evaluate(() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r))));
  return s;
}

/** Waits until the view drew the last frame it asked for (see `waitComplete`), composited. */
async function waitDrawn(page) {
  await waitFor(page, "the view's last frame to be drawn", (s) => !s.framePending);
  await page.evaluate(() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r))));
}

let shots = 0;

/** The page as on screen; also written to ISOVOX_TEST_SHOTS/ when that is set (for a failure). */
async function screenshot(page) {
  const png = await page.screenshot();
  if (process.env.ISOVOX_TEST_SHOTS) {
    writeFileSync(join(process.env.ISOVOX_TEST_SHOTS, `shot-${String(++shots).padStart(2, "0")}.png`), png);
  }
  return decodePng(png);
}

const isSky = (p) => Math.abs(p[0] - SKY[0]) + Math.abs(p[1] - SKY[1]) + Math.abs(p[2] - SKY[2]) < 24;

function inUi(x, y) {
  const inOverlay = x < OVERLAY.x + OVERLAY.w && y < OVERLAY.y + OVERLAY.h;
  return inOverlay || x >= VIEW.width - PANEL_W || x < 0 || y < 0 || x >= VIEW.width || y >= VIEW.height;
}

/** Pixels of the 3D view (outside the overlay and panel) that differ by more than 24 in a channel. */
function changedPixels(a, b, inside) {
  let changed = 0;
  let total = 0;
  for (let y = 0; y < a.height; y++) {
    for (let x = 0; x < a.width; x++) {
      if (inUi(x, y) || !inside(x, y)) continue;
      total++;
      const p = pixel(a, x, y);
      const q = pixel(b, x, y);
      if (Math.max(...p.map((c, i) => Math.abs(c - q[i]))) > 24) changed++;
    }
  }
  return { changed, total };
}

/** A volume's voxels at a coarse level, from the API, to know where its surface is. */
async function surfaceTops(level, volume = "demo", on = undefined) {
  const info = await (await api(`/v1/volumes/${volume}`, {}, on)).json();
  const dims = info.levels[level].dims;
  const body = await (await api(`/v1/volumes/${volume}/levels/${level}?format=voxels`, {}, on)).arrayBuffer();
  const voxels = info.voxel_type === "u16" ? new Uint16Array(body) : new Uint8Array(body);
  const step = 2 ** level;
  const world = (i, a) => ((i + 0.5) * step - 0.5) * info.voxel_scale[a];
  /** The top surface voxel of column (i, k), as a world point, or null for an empty column. */
  const top = (i, k) => {
    for (let j = dims[1] - 1; j >= 0; j--) {
      if (voxels[i + dims[0] * (j + dims[1] * k)] >= info.surface) return [world(i, 0), world(j, 1), world(k, 2)];
    }
    return null;
  };
  return { info, dims, top };
}

/** Whether the ray (origin o, direction d) meets the box [[x0, x1], [y0, y1], [z0, z1]]. */
function hitsBox(o, d, box) {
  let near = -Infinity;
  let far = Infinity;
  for (let a = 0; a < 3; a++) {
    const [lo, hi] = box[a];
    if (Math.abs(d[a]) < 1e-12) {
      if (o[a] < lo || o[a] > hi) return false;
      continue;
    }
    const t1 = (lo - o[a]) / d[a];
    const t2 = (hi - o[a]) / d[a];
    near = Math.max(near, Math.min(t1, t2));
    far = Math.min(far, Math.max(t1, t2));
  }
  return near <= far && far >= 0;
}

/**
 * Asserts that screenshot `img` of `page` shows `volume` (read from `on`'s API): every sampled
 * point of its top surface (columns `first`, `first + stride`, ... of level `level`, from the
 * voxels, not from the page) is drawn, not sky; and wherever the ray through a pixel misses the
 * volume's box the pixel is sky: nothing is drawn where nothing is.
 */
async function assertShowsVolume(page, img, { volume, level, first, stride, on, minMisses = 50 }) {
  const { info, dims, top } = await surfaceTops(level, volume, on);
  let onScreen = 0;
  let drawn = 0;
  for (let i = first; i < dims[0]; i += stride) {
    for (let k = first; k < dims[2]; k += stride) {
      const p = top(i, k);
      if (!p) continue;
      // A little below the top: inside the surface, not on a silhouette edge.
      const at = await project(page, [p[0], p[1] - 3 * info.voxel_scale[1], p[2]]);
      if (inUi(at.x, at.y)) continue;
      onScreen++;
      if (!isSky(pixel(img, at.x, at.y))) drawn++;
    }
  }
  assert.ok(onScreen >= 20, `${onScreen} sampled surface points of ${volume} on screen`);
  assert.ok(drawn >= onScreen * 0.95, `${drawn} of ${onScreen} surface points of ${volume} drawn`);

  // The box is grown by a coarse voxel, where the outermost vertices may lie.
  const margin = 2 ** info.levels.length;
  const box = info.dims.map((d, a) => [-margin, d * info.voxel_scale[a] + margin]);
  let misses = 0;
  for (const r of await viewRays(page)) {
    if (hitsBox(r.origin, r.direction, box)) continue;
    misses++;
    assert.ok(isSky(pixel(img, r.x, r.y)), `pixel (${r.x}, ${r.y}) off ${volume} is ${pixel(img, r.x, r.y)}, not sky`);
  }
  assert.ok(misses > minMisses, `${misses} sampled pixels look past ${volume}`);
}

/** The rays through sampled pixels of the view (outside the overlay and panel). */
async function viewRays(page) {
  const rays = await page.evaluate(({ w, h }) => {
    const out = [];
    for (let y = 2; y < h; y += 6) for (let x = 2; x < w; x += 6) out.push({ x, y, ...window.isovox.ray(x, y) });
    return out;
  }, { w: VIEW.width - PANEL_W, h: VIEW.height });
  return rays.filter((r) => !inUi(r.x, r.y));
}

/** Whether the ray (origin o, direction d) meets the ellipsoid of centre c and radii r. */
function hitsEllipsoid(o, d, c, r) {
  const oo = o.map((v, a) => (v - c[a]) / r[a]);
  const dd = d.map((v, a) => v / r[a]);
  const A = dd.reduce((s, v) => s + v * v, 0);
  const B = 2 * dd.reduce((s, v, a) => s + v * oo[a], 0);
  const C = oo.reduce((s, v) => s + v * v, 0) - 1;
  const disc = B * B - 4 * A * C;
  return disc >= 0 && (-B + Math.sqrt(disc)) / (2 * A) >= 0;
}

const project = (page, p) => page.evaluate(([x, y, z]) => window.isovox.project(x, y, z), p);

/** The URLs the page requested after `since` (ms on its clock). */
const requestedUrls = (page, since) =>
  page.evaluate(
    (t) => performance.getEntriesByType("resource").filter((e) => e.startTime >= t).map((e) => e.name),
    since,
  );

/** Mesh tiles the page requested after `since` (ms on its clock), as [level, x, y, z]. */
async function meshRequests(page, since) {
  const names = await requestedUrls(page, since);
  return names
    .map((n) => /\/meshes\/(\d+)\/(\d+)\/(\d+)\/(\d+)(?:\?|$)/.exec(n))
    .filter(Boolean)
    .map((m) => m.slice(1).map(Number));
}

/** The transition strips requested since `since`: [l, x, y, z, face]. */
async function stripRequests(page, since) {
  const faces = ["-x", "+x", "-y", "+y", "-z", "+z"];
  const names = await requestedUrls(page, since);
  return names
    .map((n) => /\/meshes\/(\d+)\/(\d+)\/(\d+)\/(\d+)\/strips\/([^?]+)/.exec(n))
    .filter(Boolean)
    .map((m) => [...m.slice(1, 5).map(Number), faces.indexOf(decodeURIComponent(m[5]))]);
}

/** Whether tile [l, x, y, z] reads a brick that `changed` (per level) lists: its 3x3x3 inputs. */
function isStale(tile, changed) {
  const [l, x, y, z] = tile;
  return (changed[l] ?? []).some(([bx, by, bz]) => Math.abs(bx - x) <= 1 && Math.abs(by - y) <= 1 && Math.abs(bz - z) <= 1);
}

/**
 * Whether the strip of face f of tile [l, x, y, z] (brick edge b) reads a brick `changed` lists
 * (server/src/mesh/tile/): of level l, the lattice points of the layer of cells along the face
 * (b (t + 1) - 2 ..= b (t + 1) + 1 on a high face, b t - 1 ..= b t + 2 on a low one, the tile's
 * b t - 1 ..= b (t + 1) + 1 across, from -2 for a first tile); of level l + 1, the face's plane
 * P (b (t + 1) / 2 or b t / 2) with a point on either side, and across c = floor(lo / 2) - 1 ..=
 * d = b (t + 1) / 2 + 1; stored voxels of a level above 0 reach 2 below and 1 above a point.
 */
function isStripStale([l, x, y, z, f], changed, b) {
  const t = [x, y, z];
  const axis = f >> 1;
  const high = (f & 1) === 1;
  const reads = (level, lattice) =>
    (changed[level] ?? []).some((c) =>
      [0, 1, 2].every((a) => {
        let [lo, hi] = lattice(a);
        if (level > 0) [lo, hi] = [lo - 2, hi + 1];
        return Math.floor(lo / b) <= c[a] && c[a] <= Math.floor(hi / b);
      }),
    );
  const fine = (a) => {
    const lo = t[a] === 0 ? -1 : b * t[a];
    const hi = b * (t[a] + 1);
    if (a !== axis) return [lo - 1, hi + 1];
    return high ? [hi - 2, hi + 1] : [lo - 1, lo + 2];
  };
  const coarse = (a) => {
    const lo = t[a] === 0 ? -1 : b * t[a];
    const hi = b * (t[a] + 1);
    const [c, d] = [Math.floor(lo / 2) - 1, hi / 2 + 1];
    if (a !== axis) return [c, d];
    const p = high ? d - 1 : c + 1;
    return [p - 1, p + 1];
  };
  return reads(l, fine) || reads(l + 1, coarse);
}

/** Clicks the surface at screen point `at` in edit mode, giving `tokenText` when asked. */
async function editThroughUi(page, at, { op, primitive, size, tokenText, material }) {
  await page.check("#edit-mode");
  await page.selectOption("#op", op);
  await page.selectOption("#primitive", primitive);
  if (material !== undefined) await page.selectOption("#material", String(material));
  await page.fill("#size", String(size));
  await page.mouse.click(at.x, at.y);
  await page.waitForSelector("#token-form:not([hidden])");
  await page.fill("#token", tokenText);
  await page.click("#token-form button");
  await page.waitForFunction(() => !/^(Applying|Enter)/.test(document.querySelector("#edit-status").textContent) && document.querySelector("#edit-status").textContent !== "");
  return page.textContent("#edit-status");
}

// --- tests ---------------------------------------------------------------------------------

test("the page loads without console errors, with WebGL2, and shows the demo world", { timeout: 120_000 }, async () => {
  const { context, page, errors } = await openPage();
  const s = await waitComplete(page);
  assert.equal(s.webgl2, true, "WebGL2 context");
  assert.equal(s.volume, "demo");
  assert.ok(s.drawn > 0 && s.triangles > 10_000, `tiles drawn: ${JSON.stringify(s)}`);
  const img = await screenshot(page);
  await assertShowsVolume(page, img, { volume: "demo", level: 2, first: 4, stride: 12 });

  // The terrain fills a good part of the view, in its own colours.
  let ground = 0;
  let all = 0;
  for (let y = 0; y < img.height; y += 4) {
    for (let x = 0; x < img.width; x += 4) {
      if (inUi(x, y)) continue;
      all++;
      if (!isSky(pixel(img, x, y))) ground++;
    }
  }
  assert.ok(ground > all * 0.2 && ground < all * 0.95, `terrain covers ${ground} of ${all} samples`);
  assert.deepEqual(errors, [], "console errors");
  await context.close();
});

test("an edit in one page changes the picture in another page at the edited place", { timeout: 180_000 }, async () => {
  const a = await openPage();
  const b = await openPage();
  await waitComplete(a.page);
  const before = await waitComplete(b.page);
  const beforeImg = await screenshot(b.page);
  const since = await b.page.evaluate(() => performance.now());

  // A point of the terrain in front, where the edit's box shows.
  const at = FRONT;
  assert.ok(!isSky(pixel(beforeImg, at.x, at.y)), "the edit point is on the terrain");
  const nearAt = (x, y) => Math.hypot(x - at.x, y - at.y) < 20;
  // A draws its own edit at once: its request is held here until A's page has been looked at,
  // so the server has not even seen the edit when A shows it.
  const aBeforeImg = await screenshot(a.page);
  let release;
  const held = new Promise((r) => (release = r));
  await a.page.route("**/v1/volumes/demo/edits", async (route) => {
    await held;
    await route.continue();
  });
  const editing = editThroughUi(a.page, at, { op: "union", primitive: "cuboid", size: 24, tokenText: token });
  await waitFor(a.page, "A's preview of its edit", (s) => s.previews === 1 && s.editStatus === "Applying...");
  await a.page.evaluate(() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r))));
  const preview = changedPixels(aBeforeImg, await screenshot(a.page), nearAt);
  assert.ok(preview.changed > preview.total * 0.2, `A's preview changed ${preview.changed} of ${preview.total} pixels near the edit`);
  assert.equal((await stats(b.page)).version, before.version, "B has not seen the edit yet");
  release();
  const status = await editing;
  await a.page.unroute("**/v1/volumes/demo/edits");
  const m = /Applied as version (\d+)/.exec(status);
  assert.ok(m, `edit status: ${status}`);
  const version = Number(m[1]);
  assert.ok(version > before.version);

  const after = await waitComplete(b.page, version);
  const afterImg = await screenshot(b.page);
  const near = changedPixels(beforeImg, afterImg, nearAt);
  const far = changedPixels(beforeImg, afterImg, (x, y) => Math.hypot(x - at.x, y - at.y) > 150);
  assert.ok(near.changed > near.total * 0.2, `near the edit ${near.changed} of ${near.total} pixels changed`);
  assert.ok(far.changed <= far.total * 0.002, `far from the edit ${far.changed} of ${far.total} pixels changed`);

  // Page B fetched exactly tiles the edit made stale.
  const changes = await (await api(`/v1/volumes/demo/changes?since=${before.version}`)).json();
  // Changed bricks per level, over every version since.
  const changed = [];
  for (const c of changes.changes) c.changed.forEach((bricks, level) => (changed[level] = [...(changed[level] ?? []), ...bricks]));
  const fetched = await meshRequests(b.page, since);
  assert.ok(fetched.length > 0, "the stale tiles were fetched");
  for (const t of fetched) assert.ok(isStale(t, changed), `tile ${t} was fetched but not stale`);
  // And exactly strips the edit made stale.
  const info = await (await api(`/v1/volumes/demo`)).json();
  for (const s of await stripRequests(b.page, since)) {
    assert.ok(s[4] >= 0, `strip ${s}: a face name`);
    assert.ok(isStripStale(s, changed, info.brick), `strip ${s} was fetched but not stale`);
  }
  assert.equal(after.stale, 0);
  // Once A's own view shows the edit's tiles, the preview is gone.
  await waitComplete(a.page, version);
  await waitFor(a.page, "A's preview to be taken away", (s) => s.previews === 0);
  await a.context.close();
  await b.context.close();
});

/**
 * Per pixel of the 3D view sampled every 4th, the palette value whose colour it shows: light and
 * the textures scale a colour's channels alike, so its chromaticity (r, g, b over their sum)
 * names it; null for sky, or no value within 0.012. Rock and marble (both grey) count as one.
 */
function materialsShown(img, palette, inside = () => true) {
  const chroma = ([r, g, b]) => [r / (r + g + b + 1e-9), g / (r + g + b + 1e-9)];
  const known = palette.map((hex, value) => ({ value, c: chroma([1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16))) }));
  const counts = new Map();
  let ground = 0;
  for (let y = 0; y < img.height; y += 4) {
    for (let x = 0; x < img.width; x += 4) {
      if (inUi(x, y) || !inside(x, y)) continue;
      const p = pixel(img, x, y);
      if (isSky(p)) continue;
      ground++;
      const c = chroma(p);
      let best = null;
      for (const k of known.slice(1)) {
        const d = Math.hypot(c[0] - k.c[0], c[1] - k.c[1]);
        if (d < 0.012 && (best === null || d < best.d)) best = { value: k.value, d };
      }
      if (best === null) continue;
      const value = best.value === 6 ? 1 : best.value;
      counts.set(value, (counts.get(value) ?? 0) + 1);
    }
  }
  return { ground, counts };
}

test("materials: the demo world shows several, and a paint from page A changes the colour on page B there alone", { timeout: 180_000 }, async () => {
  const info = await (await api("/v1/volumes/demo")).json();
  const palette = info.channels.find((c) => c.name === "material").palette;
  const a = await openPage();
  const b = await openPage();
  await waitComplete(a.page);
  const before = await waitComplete(b.page);
  assert.equal(await b.page.inputValue("#colormap"), "materials", "a volume with materials is coloured by them");
  const beforeImg = await screenshot(b.page);
  const shown = materialsShown(beforeImg, palette);
  const many = [...shown.counts].filter(([, n]) => n >= shown.ground * 0.01);
  assert.ok(many.length >= 2, `materials on 1% of the ground or more: ${JSON.stringify([...shown.counts])} of ${shown.ground}`);

  // A paints ore (5, gold: nowhere on the surface before) where the terrain in front is; the
  // density does not change, the colour does.
  const at = FRONT;
  const nearAt = (x, y) => Math.hypot(x - at.x, y - at.y) < 14;
  const oreBefore = materialsShown(beforeImg, palette, nearAt).counts.get(5) ?? 0;
  assert.equal(oreBefore, 0, "no ore in front before");
  const status = await editThroughUi(a.page, at, { op: "paint", primitive: "ellipsoid", size: 16, tokenText: token, material: 5 });
  const m = /Applied as version (\d+)/.exec(status);
  assert.ok(m, `paint status: ${status}`);
  const version = Number(m[1]);
  const change = (await (await api(`/v1/volumes/demo/changes?since=${version - 1}`)).json()).changes[0];
  assert.ok(change.changed.every((bricks) => bricks.length === 0), "a paint changes no density brick");
  assert.ok(change.channels.material[0].length > 0, "a paint changes material bricks");

  await waitComplete(b.page, version);
  const afterImg = await screenshot(b.page);
  const near = materialsShown(afterImg, palette, nearAt);
  const ore = near.counts.get(5) ?? 0;
  assert.ok(ore > near.ground * 0.3, `ore on ${ore} of ${near.ground} samples in front after the paint`);
  const far = changedPixels(beforeImg, afterImg, (x, y) => Math.hypot(x - at.x, y - at.y) > 150);
  assert.ok(far.changed <= far.total * 0.002, `far from the paint ${far.changed} of ${far.total} pixels changed`);

  // The pointer over the surface says the voxel's material, as GET /bricks?channel= has it.
  await b.page.mouse.move(at.x, at.y - 5);
  await b.page.mouse.move(at.x, at.y);
  await b.page.waitForFunction(() => window.isovox.probe()?.where === "surface" && window.isovox.probe()?.channels);
  const probe = await b.page.evaluate(() => window.isovox.probe());
  const size = info.brick;
  const [px, py, pz] = probe.position;
  const brick = new Uint8Array(await (await api(`/v1/volumes/demo/bricks/0/${Math.floor(px / size)}/${Math.floor(py / size)}/${Math.floor(pz / size)}?channel=material`)).arrayBuffer());
  assert.equal(probe.channels.material, brick[(px % size) + size * ((py % size) + size * (pz % size))]);
  assert.match(await b.page.textContent("#probe"), new RegExp(`material ${probe.channels.material}`));

  // The segment list lists the materials in use, ore among them now; ticking ore shows its mesh.
  const listed = await (await api("/v1/volumes/demo/channels/material/segments")).json();
  await b.page.waitForFunction((n) => document.querySelectorAll("#segments input[data-segment]").length === n, listed.segments.length);
  assert.ok(listed.segments.some((s) => s.id === 5), `ore listed: ${JSON.stringify(listed.segments.map((s) => s.id))}`);
  await b.page.check('#segments input[data-segment="5"]');
  await waitFor(b.page, "ore's mesh to be shown", (s) => s.segments === 1);
  await b.page.uncheck('#segments input[data-segment="5"]');
  await waitFor(b.page, "ore's mesh to be hidden", (s) => s.segments === 0);
  assert.deepEqual(b.errors, [], "console errors");
  await a.context.close();
  await b.context.close();
});

test("the slice view's pixels are the voxels GET /bricks returns (u8, and u16 through window/level)", { timeout: 120_000 }, async () => {
  for (const { query, volume, window: wl } of [
    { query: "?volume=demo&slice=z:200", volume: "demo", window: null },
    { query: "?volume=ell16&slice=y:37", volume: "ell16", window: { width: 20000, center: 30000 } },
  ]) {
    const { context, page, errors } = await openPage(query);
    await page.waitForSelector("#slice[data-version]");
    if (wl) {
      await page.evaluate(({ width, center }) => {
        for (const [id, v] of [["slice-width", width], ["slice-center", center]]) {
          const input = document.getElementById(id);
          input.value = String(v);
          input.dispatchEvent(new Event("input"));
        }
      }, wl);
    }
    const shown = await page.evaluate(() => {
      const c = document.getElementById("slice");
      const d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
      return { ...c.dataset, w: c.width, h: c.height, red: Array.from(d.filter((_, i) => i % 4 === 0)) };
    });
    const info = await (await api(`/v1/volumes/${volume}`)).json();
    const level = Number(shown.level);
    const index = Number(shown.index);
    const axis = { x: 0, y: 1, z: 2 }[shown.axis];
    assert.equal(shown.axis, query.includes("slice=z") ? "z" : "y");
    const l = info.levels[level];
    // Columns and rows of the plane (see slice.ts): z: x right, y up; y: x right, z down.
    const [col, row, rowDown] = axis === 2 ? [0, 1, false] : [0, 2, true];
    assert.equal(shown.w, l.dims[col]);
    assert.equal(shown.h, l.dims[row]);
    const b = info.brick;
    const u16 = info.voxel_type === "u16";
    const grey = (v) => {
      const width = wl?.width ?? info.high - info.low;
      const center = wl?.center ?? info.low + (info.high - info.low) / 2;
      return Math.min(255, Math.max(0, Math.round(((v - (center - width / 2)) * 255) / width)));
    };
    let compared = 0;
    for (let bj = 0; bj < l.grid[row]; bj++) {
      for (let bi = 0; bi < l.grid[col]; bi++) {
        const key = [0, 0, 0];
        key[axis] = Math.floor(index / b);
        key[col] = bi;
        key[row] = bj;
        const body = await (await api(`/v1/volumes/${volume}/bricks/${level}/${key.join("/")}`)).arrayBuffer();
        const voxels = u16 ? new Uint16Array(body) : new Uint8Array(body);
        assert.equal(voxels.length, b ** 3);
        for (let v = 0; v < b; v++) {
          for (let u = 0; u < b; u++) {
            const cu = bi * b + u;
            const rv = bj * b + v;
            if (cu >= shown.w || rv >= shown.h) continue;
            const q = [0, 0, 0];
            q[axis] = index % b;
            q[col] = u;
            q[row] = v;
            const value = voxels[q[0] + b * (q[1] + b * q[2])];
            const y = rowDown ? rv : shown.h - 1 - rv;
            const got = shown.red[y * shown.w + cu];
            if (got !== grey(value)) {
              assert.fail(`${volume} pixel (${cu}, ${y}) is ${got}, voxel ${value} gives ${grey(value)}`);
            }
            compared++;
          }
        }
      }
    }
    assert.equal(compared, shown.w * shown.h);
    assert.deepEqual(errors, []);
    await context.close();
  }
});

/**
 * Before the page's scripts run: after every animation-frame callback that drew into the view
 * (WebGL2 draw calls or a clear), `window.__probe()` runs, while the frame just drawn is still in
 * the drawing buffer (it is cleared only when the browser composites the frame).
 */
function probeFrames() {
  // (Against the viewer before issue 36, which swapped tiles one by one, the burst below showed
  // up to 703 newly enclosed sky pixels in a frame.)
  const raf = window.requestAnimationFrame.bind(window);
  let dirty = false;
  const proto = WebGL2RenderingContext.prototype;
  for (const name of ["drawElements", "drawArrays", "clear"]) {
    const f = proto[name];
    proto[name] = function (...args) {
      dirty = true;
      return f.apply(this, args);
    };
  }
  window.requestAnimationFrame = (cb) =>
    raf((t) => {
      cb(t);
      if (dirty) {
        dirty = false;
        window.__probe?.();
      }
    });
}

/**
 * In the page: a probe that reads each frame's pixels and records which sky pixels the surface
 * encloses (not reached from the canvas's border through sky: a flood fill), as indices into the
 * frame, leaving out those `allowed` lists. `window.__frames` gets one entry per frame.
 */
function installHoleProbe({ sky, allowed }) {
  const canvas = document.getElementById("view");
  const gl = canvas.getContext("webgl2");
  const ok = new Set(allowed);
  window.__frames = [];
  window.__probe = () => {
    const w = gl.drawingBufferWidth;
    const h = gl.drawingBufferHeight;
    const px = new Uint8Array(w * h * 4);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
    const isSky = (i) =>
      Math.abs(px[i * 4] - sky[0]) + Math.abs(px[i * 4 + 1] - sky[1]) + Math.abs(px[i * 4 + 2] - sky[2]) < 24;
    const reached = new Uint8Array(w * h);
    const stack = [];
    const push = (i) => {
      if (!reached[i] && isSky(i)) {
        reached[i] = 1;
        stack.push(i);
      }
    };
    for (let x = 0; x < w; x++) {
      push(x);
      push((h - 1) * w + x);
    }
    for (let y = 0; y < h; y++) {
      push(y * w);
      push(y * w + w - 1);
    }
    while (stack.length) {
      const i = stack.pop();
      const x = i % w;
      if (x > 0) push(i - 1);
      if (x < w - 1) push(i + 1);
      if (i >= w) push(i - w);
      if (i < w * (h - 1)) push(i + w);
    }
    const enclosed = [];
    for (let i = 0; i < w * h; i++) if (!reached[i] && isSky(i) && !ok.has(i)) enclosed.push(i);
    const s = window.isovox?.stats();
    window.__frames.push({ version: s?.version ?? null, stale: s?.stale ?? null, enclosed });
  };
}

test("while a burst of edits lands, another page never shows sky through the terrain, and ends as a fresh page does", { timeout: 240_000 }, async () => {
  // The default view's camera, as its URL gives it, so that a fresh page can take the same one.
  const a = await openPage();
  await waitComplete(a.page);
  const view = await a.page.evaluate(() => location.search);
  await a.context.close();

  const context = await browser.newContext({ viewport: VIEW });
  await context.addInitScript(probeFrames);
  const page = await context.newPage();
  const errors = [];
  page.on("pageerror", (e) => errors.push(e.message));
  await page.goto(`${server.base}/${view}`);
  const before = await waitComplete(page);
  await waitFor(page, "the feed to be live", (s) => s.feed === "live");
  // The enclosed sky of the view before the burst (gaps under overhangs and the like) is allowed.
  await page.evaluate(installHoleProbe, { sky: SKY, allowed: [] });
  await page.evaluate(() => window.isovox && window.__probe());
  const start = await page.evaluate(() => window.__frames.at(-1));
  await page.evaluate(installHoleProbe, { sky: SKY, allowed: start.enclosed });

  // Ten edits in the terrain in front (below the horizon: ground, not sky, lies behind them),
  // alternately carved and raised, across the borders of tiles (multiples of 128 voxels: every
  // level's tiles meet there), where tiles of two versions would not meet. Sent at once.
  const p = await page.evaluate(({ x, y }) => window.isovox.pick(x, y), FRONT);
  assert.ok(p, "a surface point in front");
  const { top } = await surfaceTops(1);
  const [bx, bz] = [Math.round(p[0] / 128) * 128, Math.round(p[2] / 128) * 128];
  const points = [];
  for (let i = 0; i < 10; i++) {
    const d = (Math.floor(i / 2) - 2) * 20;
    const [x, z] = i % 2 === 0 ? [bx, p[2] + d] : [p[0] + d, bz];
    const t = top(Math.floor(x / 2), Math.floor(z / 2));
    assert.ok(t, `a surface at ${x}, ${z}`);
    points.push([Math.round(x), Math.round(t[1]), Math.round(z)]);
  }
  const sent = Date.now();
  const answers = await Promise.all(
    points.map((c, i) =>
      api("/v1/volumes/demo/edits", {
        method: "POST",
        headers: { "content-type": "application/json", authorization: `Bearer ${token}` },
        body: JSON.stringify({
          op: i % 2 === 0 ? "difference" : "union",
          term: { ellipsoid: { center: c, radii: i % 2 === 0 ? [24, 24, 24] : [16, 16, 16] } },
        }),
      }).then((r) => r.json()),
    ),
  );
  const burstMs = Date.now() - sent;
  const last = Math.max(...answers.map((r) => r.version));
  assert.equal(last, before.version + 10, "ten versions");
  await waitComplete(page, last);
  const frames = await page.evaluate(() => window.__frames);
  const afterImg = await screenshot(page);

  // A fresh page at the same camera: what the newest version looks like. Sky it encloses (a
  // carving may open a real gap) is allowed in the frames, as before.
  const fresh = await browser.newContext({ viewport: VIEW });
  await fresh.addInitScript(probeFrames);
  const freshPage = await fresh.newPage();
  await freshPage.goto(`${server.base}/${view}`);
  await waitComplete(freshPage, last);
  await freshPage.evaluate(installHoleProbe, { sky: SKY, allowed: start.enclosed });
  await freshPage.evaluate(() => window.__probe());
  const end = await freshPage.evaluate(() => window.__frames.at(-1));
  const freshImg = await screenshot(freshPage);
  await fresh.close();

  const allowed = new Set(end.enclosed);
  const holes = frames.map((f) => ({ ...f, enclosed: f.enclosed.filter((i) => !allowed.has(i)) }));
  const worst = holes.reduce((m, f) => (f.enclosed.length > m.enclosed.length ? f : m), { enclosed: [] });
  console.log(
    `burst of 10 edits sent in ${burstMs} ms; page B drew ${frames.length} frames meanwhile, versions ` +
      `${[...new Set(frames.map((f) => f.version))].join(",")}; most newly enclosed sky in a frame: ${worst.enclosed.length}`,
  );
  assert.ok(frames.length >= 1 && frames.at(-1).version === last, `the last of ${frames.length} frames shows version ${last}`);
  assert.equal(worst.enclosed.length, 0, `a frame of version ${worst.version} showed sky through the terrain in ${worst.enclosed.length} pixels`);

  // After the burst the page shows what a fresh page at the same camera shows.
  const diff = changedPixels(afterImg, freshImg, () => true);
  assert.ok(diff.changed <= diff.total * 0.0005, `${diff.changed} of ${diff.total} pixels differ from a fresh page`);
  assert.deepEqual(errors, []);
  await context.close();
});

/** Whether pixel p is grey (its channels within 3 of each other). */
const isGrey = (p) => Math.max(...p) - Math.min(...p) <= 3;

test("for scans: the iso value and the colour map change the pixels as chosen", { timeout: 180_000 }, async () => {
  const { context, page, errors } = await openPage("?volume=ball");
  await waitComplete(page);
  const ball = await (await api("/v1/volumes/ball")).json();
  const centre = ball.dims.map((d) => (d - 1) / 2);
  const rays = await viewRays(page);
  /** Rays that go through the sphere of radius r, and rays that miss the one of radius R. */
  const split = (r, R) => ({
    through: rays.filter((q) => hitsEllipsoid(q.origin, q.direction, centre, [r, r, r])),
    past: rays.filter((q) => !hitsEllipsoid(q.origin, q.direction, centre, [R, R, R])),
  });

  // The default iso value (S - 0.5 = 126.5): a sphere of radius 128.5 / 6 = 21.4 voxels.
  let img = await screenshot(page);
  const wide = split(20, 23);
  for (const q of wide.through) assert.ok(!isSky(pixel(img, q.x, q.y)), `(${q.x}, ${q.y}) through the ball is sky`);
  for (const q of wide.past) assert.ok(isSky(pixel(img, q.x, q.y)), `(${q.x}, ${q.y}) past the ball is not sky`);
  // Terrain colours, not grey.
  assert.ok(wide.through.filter((q) => !isGrey(pixel(img, q.x, q.y))).length > wide.through.length * 0.9);

  // Iso 200: radius 55 / 6 = 9.2 voxels; the tiles are asked for with ?iso=200.
  const since = await page.evaluate(() => performance.now());
  await page.fill("#iso", "200");
  await page.dispatchEvent("#iso", "change");
  await waitFor(page, "the new surface", (st) => st.complete && st.stale === 0);
  await waitComplete(page);
  const meshUrls = (await requestedUrls(page, since)).filter((u) => u.includes("/meshes/"));
  assert.ok(meshUrls.length > 0 && meshUrls.every((u) => u.includes("iso=200")), `mesh requests: ${meshUrls}`);
  assert.match(await page.evaluate(() => location.search), /iso=200/);
  img = await screenshot(page);
  const narrow = split(8, 10.5);
  assert.ok(narrow.through.length > 100 && narrow.past.length > 1000);
  for (const q of narrow.through) assert.ok(!isSky(pixel(img, q.x, q.y)), `(${q.x}, ${q.y}) through the iso-200 ball is sky`);
  for (const q of narrow.past) assert.ok(isSky(pixel(img, q.x, q.y)), `(${q.x}, ${q.y}) past the iso-200 ball is not sky`);

  // Colour map grey: the lit surface is grey. Viridis: it is not, and the slice's voxels map to
  // matplotlib's viridis ends through the window (values >= 200 to its top, <= 100 to its bottom).
  await page.selectOption("#colormap", "grey");
  await waitDrawn(page);
  img = await screenshot(page);
  for (const q of narrow.through) assert.ok(isGrey(pixel(img, q.x, q.y)), `(${q.x}, ${q.y}) is ${pixel(img, q.x, q.y)}, not grey`);
  await page.selectOption("#colormap", "viridis");
  await waitDrawn(page);
  const viridisImg = await screenshot(page);
  const coloured = narrow.through.filter((q) => !isGrey(pixel(viridisImg, q.x, q.y))).length;
  assert.ok(coloured > narrow.through.length * 0.9, `${coloured} of ${narrow.through.length} surface pixels coloured`);
  // (The slice and its plane in 3D come last: they would cover pixels looked at above.)
  await page.check("#slice-on");
  await page.waitForSelector("#slice[data-version]");
  await page.evaluate(() => {
    for (const [id, v] of [["slice-width", 100], ["slice-center", 150]]) {
      const input = document.getElementById(id);
      input.value = String(v);
      input.dispatchEvent(new Event("input"));
    }
  });
  const shown = await page.evaluate(() => {
    const c = document.getElementById("slice");
    return { w: c.width, h: c.height, index: Number(c.dataset.index), rgba: Array.from(c.getContext("2d").getImageData(0, 0, c.width, c.height).data) };
  });
  assert.equal(shown.w, 64);
  const plane = new Uint8Array(await (await api(`/v1/volumes/ball/levels/0?format=voxels&region=0,0,${shown.index},64,64,${shown.index + 1}`)).arrayBuffer());
  let ends = 0;
  for (let y = 0; y < 64; y++) {
    for (let x = 0; x < 64; x++) {
      const v = plane[x + 64 * y];
      const at = ((63 - y) * 64 + x) * 4; // z slice: y up
      const got = shown.rgba.slice(at, at + 3);
      if (v >= 200) assert.deepEqual(got, [253, 231, 37], `voxel (${x}, ${y}) = ${v}`);
      else if (v <= 100) assert.deepEqual(got, [68, 1, 84], `voxel (${x}, ${y}) = ${v}`);
      else continue;
      ends++;
    }
  }
  assert.ok(ends > 2000, `${ends} slice pixels at the map's ends`);
  assert.equal(shown.index, 32);
  assert.match(await page.evaluate(() => location.search), /cmap=viridis/);
  assert.deepEqual(errors, []);
  await context.close();
});

test("for scans: the voxel under the pointer, the slice's plane in 3D, resizing it, and the Neuroglancer link", { timeout: 180_000 }, async () => {
  const { context, page, errors } = await openPage("?volume=ball");
  await waitComplete(page);
  const ball = await (await api("/v1/volumes/ball")).json();
  const voxelOf = async (p) => {
    const b = ball.brick;
    const body = new Uint8Array(await (await api(`/v1/volumes/ball/bricks/0/${p.map((c) => Math.floor(c / b)).join("/")}`)).arrayBuffer());
    return body[(p[0] % b) + b * ((p[1] % b) + b * (p[2] % b))];
  };

  // Over the surface: the voxel nearest the point under the pointer, with its value.
  const at = await project(page, [31.5, 31.5 + 21.4, 31.5]);
  await page.mouse.move(at.x, at.y - 5);
  await page.mouse.move(at.x, at.y);
  await page.waitForFunction(() => window.isovox.probe()?.where === "surface");
  const surface = await page.evaluate(() => window.isovox.probe());
  const hit = await page.evaluate(({ x, y }) => window.isovox.pick(x, y), at);
  assert.ok(surface.position.every((c, a) => Math.abs(c - hit[a]) <= 0.5 + 1e-6), `${surface.position} is not the voxel at ${hit}`);
  assert.equal(surface.value, await voxelOf(surface.position));
  assert.match(await page.textContent("#probe"), new RegExp(`surface \\(${surface.position.join(", ")}\\): ${surface.value}`));

  // The slice: its plane appears in the 3D view where it cuts the volume.
  const before = await screenshot(page);
  await page.check("#slice-on");
  await page.waitForSelector("#slice[data-version]");
  await waitDrawn(page);
  const after = await screenshot(page);
  // A corner of the plane (z = 32, the volume's x and y ends, outside the ball) is drawn there:
  // one that neither the panel nor the slice's own box covers.
  const sliceBox = await page.locator("#slice-box").boundingBox();
  const underBox = (p) => p.x >= sliceBox.x - 8 && p.x <= sliceBox.x + sliceBox.width + 8 && p.y >= sliceBox.y - 8;
  let corner = null;
  for (const [x, y] of [[63.5, 0.5], [0.5, 0.5], [63.5, 63.5], [0.5, 63.5]]) {
    const p = await project(page, [x, y, 32]);
    if (!inUi(p.x, p.y) && !underBox(p)) {
      corner = p;
      break;
    }
  }
  assert.ok(corner, "a corner of the plane in sight");
  const near = changedPixels(before, after, (x, y) => Math.hypot(x - corner.x, y - corner.y) < 6);
  assert.ok(near.changed > 0, "the plane's corner is drawn");

  // Resizable: dragging the box's corner grows it, and the slice with it.
  const box = await page.locator("#slice-box").boundingBox();
  const canvasBefore = await page.locator("#slice").boundingBox();
  await page.mouse.move(box.x + box.width - 3, box.y + box.height - 3);
  await page.mouse.down();
  await page.mouse.move(box.x + box.width + 80, box.y + box.height + 0, { steps: 5 });
  await page.mouse.up();
  const grown = await page.locator("#slice-box").boundingBox();
  const canvasAfter = await page.locator("#slice").boundingBox();
  assert.ok(grown.width > box.width + 40, `the box is ${grown.width} wide, was ${box.width}`);
  assert.ok(canvasAfter.width >= canvasBefore.width, "the slice follows the box");

  // Over the slice: the voxel drawn under the pointer, equal to GET /bricks there.
  const c = await page.locator("#slice").boundingBox();
  await page.mouse.move(c.x + c.width * 0.3, c.y + c.height * 0.6);
  await page.waitForFunction(() => window.isovox.probe()?.where === "slice");
  const onSlice = await page.evaluate(() => window.isovox.probe());
  assert.equal(onSlice.level, 0);
  assert.equal(onSlice.position[2], 32);
  assert.equal(onSlice.value, await voxelOf(onSlice.position));

  // Open in Neuroglancer: the ball's precomputed view on this server, which answers.
  const href = await page.getAttribute("#neuroglancer", "href");
  const state = JSON.parse(decodeURIComponent(href.slice(href.indexOf("#!") + 2)));
  assert.equal(state.layers[0].source, `precomputed://${server.base}/v1/volumes/ball/precomputed`);
  const infoJson = await (await fetch(`${server.base}/v1/volumes/ball/precomputed/info`)).json();
  assert.equal(infoJson.type, "image");
  assert.deepEqual(infoJson.scales[0].size, [64, 64, 64]);
  assert.deepEqual(errors, []);
  await context.close();
});

test("a wrong token shows an error in words and changes nothing", { timeout: 120_000 }, async () => {
  const { context, page } = await openPage();
  const s = await waitComplete(page);
  const beforeImg = await screenshot(page);
  const at = FRONT;
  const status = await editThroughUi(page, at, {
    op: "difference",
    primitive: "ellipsoid",
    size: 20,
    tokenText: "not-the-write-token-0123456789",
  });
  assert.match(status, /refused the write token \(401 Unauthorized\): nothing was changed/);
  assert.equal(await page.getAttribute("#edit-status", "class"), "error");
  const info = await (await api("/v1/volumes/demo")).json();
  assert.equal(info.version, s.version, "the volume's version did not move");
  await page.waitForTimeout(500);
  const afterImg = await screenshot(page);
  const diff = changedPixels(beforeImg, afterImg, () => true);
  assert.equal(diff.changed, 0, `${diff.changed} pixels of the view changed`);
  // The refused token is forgotten: the next edit asks for one again.
  await page.mouse.click(at.x, at.y);
  await page.waitForSelector("#token-form:not([hidden])");
  await context.close();
});

test("the page survives a server restart and catches up with what changed meanwhile", { timeout: 180_000 }, async () => {
  const { context, page } = await openPage();
  const before = await waitComplete(page);
  const beforeImg = await screenshot(page);
  // The surface point under a pixel of the terrain in front, where the carving shows.
  const at = FRONT;
  const p = await page.evaluate(({ x, y }) => window.isovox.pick(x, y), at);
  assert.ok(p, "a surface point under the pixel");

  await server.kill();
  await waitFor(page, "the feed to notice", (s) => s.feed === "reconnecting");
  // While no server runs, an edit is committed to the file from the command line.
  const since = await page.evaluate(() => performance.now());
  execFileSync(BIN, [
    "edit", join(dataDir, "demo.vod"), "--op", "difference",
    "--ellipsoid", `${Math.round(p[0])},${Math.round(p[1])},${Math.round(p[2])},32,32,32`,
  ]);
  server = await startServer(BIN, dataDir, { addr: server.addr });

  const after = await waitComplete(page, before.version + 1);
  assert.equal(after.version, before.version + 1);
  assert.equal(after.feed, "live");
  const afterImg = await screenshot(page);
  const near = changedPixels(beforeImg, afterImg, (x, y) => Math.hypot(x - at.x, y - at.y) < 15);
  assert.ok(near.changed > near.total * 0.15, `near the carved place ${near.changed} of ${near.total} pixels changed`);
  const changes = await (await api(`/v1/volumes/demo/changes?since=${before.version}`)).json();
  const fetched = await meshRequests(page, since);
  assert.ok(fetched.length > 0);
  for (const t of fetched) assert.ok(isStale(t, changes.changes[0].changed), `tile ${t} was fetched but not stale`);
  await context.close();
});

test("over HTTPS the page loads with HTTP/2, its requests sharing one connection", { timeout: 120_000 }, async () => {
  // A server of its own on a copy of the demo world, with a self-signed certificate.
  const dir = mkdtempSync(join(tmpdir(), "isovox-tls-"));
  copyFileSync(join(dataDir, "demo.vod"), join(dir, "demo.vod"));
  const [cert, key] = [join(dir, "cert.pem"), join(dir, "key.pem")];
  execFileSync("openssl", [
    "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-days", "2",
    "-subj", "/CN=127.0.0.1", "-addext", "subjectAltName=IP:127.0.0.1", "-keyout", key, "-out", cert,
  ], { stdio: "ignore" });
  const tls = await startServer(BIN, dir, { extraArgs: ["--tls-cert", cert, "--tls-key", key] });
  const secure = await launch(["--ignore-certificate-errors"]);
  try {
    assert.match(tls.base, /^https:/);
    const context = await secure.newContext({ viewport: VIEW });
    const page = await context.newPage();
    await page.goto(`${tls.base}/`);
    const s = await waitComplete(page);
    assert.equal(s.protocol, "h2");
    assert.ok(s.triangles > 10_000 && s.webgl2);
    // Every answered API request (requests the viewer cancelled have no status and no protocol).
    const protocols = await page.evaluate(() =>
      performance
        .getEntriesByType("resource")
        .filter((e) => e.name.includes("/v1/") && e.responseStatus > 0)
        .map((e) => e.nextHopProtocol),
    );
    assert.ok(protocols.length > 10);
    assert.deepEqual([...new Set(protocols)], ["h2"]);
  } finally {
    await secure.close();
    await tls.kill();
    rmSync(dir, { recursive: true, force: true });
  }
});

test("fly navigation: keys move the camera, and tiles near where it went are fetched", { timeout: 180_000 }, async () => {
  const { context, page, errors } = await openPage();
  await waitComplete(page);
  const info = await (await api("/v1/volumes/demo")).json();
  const before = await page.evaluate(() => window.isovox.camera());
  const selectedBefore = new Set((await page.evaluate(() => window.isovox.selection())).map(String));
  assert.equal(before.navigation, "orbit");

  await page.selectOption("#navigation", "fly");
  // Keys go to the view, not to the select that has the focus.
  await page.mouse.click(FRONT.x, FRONT.y);
  const since = await page.evaluate(() => performance.now());
  // Forward (W) until the camera needs finest tiles it did not need before.
  const newFinest = () =>
    page.evaluate(
      (old) => window.isovox.selection().filter((k) => k[0] === 0 && !old.includes(String(k))).length,
      [...selectedBefore],
    );
  await page.keyboard.down("w");
  const start = Date.now();
  while ((await newFinest()) === 0 && Date.now() - start < 60_000) await page.waitForTimeout(100);
  await page.keyboard.up("w");
  const after = await page.evaluate(() => window.isovox.camera());
  assert.equal(after.navigation, "fly");
  // Let the last position's selection be planned (at most every 100 ms) and loaded.
  await page.waitForTimeout(300);
  await waitComplete(page);
  assert.deepEqual(await page.evaluate(() => window.isovox.camera().position), after.position, "the camera stays put without keys");

  // The camera went forward, along where it looked.
  const moved = after.position.map((c, a) => c - before.position[a]);
  const distance = Math.hypot(...moved);
  assert.ok(distance > 0, "the camera moved");
  const along = moved.reduce((sum, m, a) => sum + m * before.direction[a], 0) / distance;
  assert.ok(along > 0.99, `moved ${moved} is not forward along ${before.direction} (cos ${along})`);
  assert.match(await page.evaluate(() => location.search), /nav=fly/);

  // The finest tiles the camera needs now and did not before: level 0 is chosen where the
  // level-1 tile around it is within the finest radius, so that tile is nearer the new position
  // than the old one (box distances, as lod.ts measures them).
  const boxDistance = ([l, x, y, z], p) => {
    const span = info.brick * 2 ** l;
    return Math.hypot(...[x, y, z].map((c, a) => {
      const lo = c * span * info.voxel_scale[a];
      const hi = (c + 1) * span * info.voxel_scale[a];
      return p[a] < lo ? lo - p[a] : p[a] > hi ? p[a] - hi : 0;
    }));
  };
  const selected = await page.evaluate(() => window.isovox.selection());
  const fresh = selected.filter((k) => k[0] === 0 && !selectedBefore.has(String(k)));
  assert.ok(fresh.length > 0, "the camera needs new finest tiles");
  for (const [, x, y, z] of fresh) {
    const parent = [1, x >> 1, y >> 1, z >> 1];
    assert.ok(
      boxDistance(parent, after.position) < boxDistance(parent, before.position),
      `new finest tile ${[0, x, y, z]} is not nearer the new camera position`,
    );
  }
  // And those with a surface were requested after the move: the tile, or the transition strip
  // of a face touching a coarser tile (a tile whose own level holds no surface is not fetched,
  // its strips can be).
  const requested = new Set((await meshRequests(page, since)).map(String));
  for (const s of await stripRequests(page, since)) requested.add(String(s.slice(0, 4)));
  const fetched = fresh.filter((k) => requested.has(String(k)));
  assert.ok(fetched.length > 0, `none of the ${fresh.length} new finest tiles was requested`);
  assert.deepEqual(errors, []);
  await context.close();
});

test("the volume picker loads the chosen volume's tiles and shows it", { timeout: 180_000 }, async () => {
  const { context, page, errors } = await openPage();
  await waitComplete(page);
  const options = await page.$$eval("#volume option", (os) => os.map((o) => ({ value: o.value, text: o.textContent })));
  assert.deepEqual(options.map((o) => o.value).sort(), ["ball", "demo", "ell16"]);
  assert.match(options.find((o) => o.value === "ell16").text, /96x80x64 u16/);
  const since = await page.evaluate(() => performance.now());

  await page.selectOption("#volume", "ell16");
  await waitFor(page, "ell16 to be shown", (s) => s.volume === "ell16" && s.complete && s.drawn > 0);
  const s = await waitComplete(page);
  assert.equal(s.volume, "ell16");
  const urls = (await requestedUrls(page, since)).filter((u) => u.includes("/v1/"));
  const meshes = urls.filter((u) => u.includes("/meshes/"));
  assert.ok(meshes.length > 0, "mesh tiles were requested");
  for (const u of urls) assert.match(u, /\/v1\/volumes\/ell16(\/|$|\?)/, `a request after choosing ell16: ${u}`);
  assert.match(await page.textContent("#overlay"), /^ell16 {2}version/);
  assert.match(await page.evaluate(() => location.search), /volume=ell16/);

  const img = await screenshot(page);
  // The ellipsoid fills the view: few pixels look past its box.
  await assertShowsVolume(page, img, { volume: "ell16", level: 0, first: 4, stride: 8, minMisses: 10 });
  // So also: wherever a ray misses the ellipsoid itself (it fills the volume: centre and radii
  // (dims - 1) / 2 in whole voxels, grown by 4 voxels for coarse tiles' vertices), the pixel is
  // sky; and where a ray goes through its middle, it is not.
  const ell = await (await api("/v1/volumes/ell16")).json();
  const radii = ell.dims.map((d, a) => Math.floor((d - 1) / 2) * ell.voxel_scale[a]);
  const grown = radii.map((r, a) => r + 4 * ell.voxel_scale[a]);
  let past = 0;
  let through = 0;
  for (const r of await viewRays(page)) {
    const p = pixel(img, r.x, r.y);
    if (!hitsEllipsoid(r.origin, r.direction, radii, grown)) {
      past++;
      assert.ok(isSky(p), `pixel (${r.x}, ${r.y}) off the ellipsoid is ${p}, not sky`);
    } else if (hitsEllipsoid(r.origin, r.direction, radii, radii.map((x) => x * 0.8))) {
      through++;
      assert.ok(!isSky(p), `pixel (${r.x}, ${r.y}) through the ellipsoid is sky`);
    }
  }
  assert.ok(past > 500 && through > 500, `${past} pixels past the ellipsoid, ${through} through it`);
  assert.deepEqual(errors, []);
  await context.close();
});

test("with private reads the page asks for the token once, then shows and follows the volume; a wrong token shows an error and no tiles", { timeout: 180_000 }, async () => {
  // A server of its own on a copy of the demo world and its tokens, every read needing a token.
  const dir = mkdtempSync(join(tmpdir(), "isovox-private-"));
  copyFileSync(join(dataDir, "demo.vod"), join(dir, "demo.vod"));
  copyFileSync(join(dataDir, "tokens"), join(dir, "tokens"));
  const priv = await startServer(BIN, dir, { extraArgs: ["--private-reads"] });
  const on = { base: priv.base, token };
  try {
    assert.equal((await fetch(`${priv.base}/v1/volumes`)).status, 401, "reads need a token");

    const right = await openPage("", priv.base);
    await right.page.waitForSelector("#token-form:not([hidden])");
    assert.match(await right.page.textContent("#overlay"), /private \(401 Unauthorized\): enter a token/);
    await right.page.fill("#token", token);
    await right.page.click("#token-form button");
    const s = await waitComplete(right.page);
    assert.equal(s.volume, "demo");
    assert.ok(s.triangles > 10_000);
    assert.ok(await right.page.isHidden("#token-form"));
    await assertShowsVolume(right.page, await screenshot(right.page), { volume: "demo", level: 2, first: 4, stride: 12, on });

    // The change feed carries the token too: an edit made elsewhere reaches the page.
    await waitFor(right.page, "the feed to be live", (st) => st.feed === "live");
    const p = await right.page.evaluate(({ x, y }) => window.isovox.pick(x, y), FRONT);
    assert.ok(p, "a surface point under the pixel");
    const edit = await (await api("/v1/volumes/demo/edits", {
      method: "POST",
      headers: { "content-type": "application/json" },
      body: JSON.stringify({ op: "union", term: { ellipsoid: { center: p.map(Math.round), radii: [12, 12, 12] } } }),
    }, on)).json();
    const followed = await waitComplete(right.page, edit.version);
    assert.equal(followed.version, edit.version);
    assert.equal(followed.feed, "live");

    // Once per session: a reload of the page does not ask again.
    await right.page.reload();
    await waitComplete(right.page, edit.version);
    assert.ok(await right.page.isHidden("#token-form"));
    await right.context.close();

    const wrong = await openPage("", priv.base);
    await wrong.page.waitForSelector("#token-form:not([hidden])");
    await wrong.page.fill("#token", "not-the-token-0123456789abcdef");
    await wrong.page.click("#token-form button");
    await wrong.page.waitForFunction(() => /refused the token/.test(document.querySelector("#overlay").textContent));
    assert.match(
      await wrong.page.textContent("#overlay"),
      /The server refused the token \(401 Unauthorized\): nothing can be shown/,
    );
    // Asked again, and nothing drawn.
    await wrong.page.waitForSelector("#token-form:not([hidden])");
    const st = await stats(wrong.page);
    assert.equal(st.tilesOnScreen, 0);
    assert.equal(st.volume, null);
    const img = await screenshot(wrong.page);
    // The words may reach past the overlay's usual box: leave out where they are.
    const words = await wrong.page.locator("#overlay").boundingBox();
    const onWords = (x, y) => x <= words.x + words.width && y <= words.y + words.height;
    let notSky = 0;
    for (let y = 0; y < img.height; y += 4) {
      for (let x = 0; x < img.width; x += 4) if (!inUi(x, y) && !onWords(x, y) && !isSky(pixel(img, x, y))) notSky++;
    }
    assert.equal(notSky, 0, `${notSky} sampled pixels of the view are not sky`);
    await wrong.context.close();
  } finally {
    await priv.kill();
    rmSync(dir, { recursive: true, force: true });
  }
});
