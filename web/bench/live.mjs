// How fast others' edits reach the screen, and how fast a close view loads: headless Chromium
// with two pages on the demo world, page A editing, page B watching, each in a browser of its own
// (pages of one browser share its GPU process: with SwiftShader, A's frames would hold up B's).
// `scripts/bench-web.sh` builds the server and runs this; by hand:
//
//   node bench/live.mjs --bin target/release/isovox [--edits 50] [--width 1280 --height 720]
//       [--cert cert.pem --key key.pem]     (HTTPS with HTTP/2: chromium takes any certificate)
//       [--settle MS]                       (between edits, after B drew the last one: 1000)
//   node bench/live.mjs --base URL --token TOKEN [--tls]   (a server already running)
//
// For each view (the default one, and CLOSE below: near the ground at the default detail):
//
// - B's cold load (empty cache): first frame, every tile in the view frustum on screen, every
//   tile of the selection on screen, tiles, triangles, requests, bytes on the wire and decoded.
// - Then EDITS edits, one at a time, each a small ellipsoid added or carved near the view's
//   centre (in sight in both views), sent by page A with `fetch`, and the time from A sending it
//   to the first animation frame of B in which B shows the version and no tile waits for a newer
//   drawing (read in B's own animation-frame callbacks, so it is measured the same way for any
//   version of the viewer), or, where the page keeps commit traces (`isovox.traces()`), to the
//   frame B drew the swap in, if later (a frame is paced after the one before it). The time is
//   then split into: server (A's request answered), feed (B's change feed delivered the
//   commit), fetch (the last response of B's requests for it), decode, and draw (until the
//   first frame after B swapped the tiles in); raster is the time from that frame to B's next
//   animation frame, which runs once the frame's pixels are composited (with SwiftShader, once
//   they are rasterized: not counted in the total, which a GPU would make a few milliseconds).
//   After each edit the bench waits `--settle` ms, so that B has finished drawing (and its pause
//   after a frame, twice the frame's cost) and each edit is timed on its own. Clocks:
//   performance.timeOrigin + performance.now() of each page (the same machine clock).

import { mkdtempSync, readFileSync, rmSync } from "node:fs";
import { get as httpsGet } from "node:https";
import { tmpdir } from "node:os";
import { join } from "node:path";
import { parseArgs } from "node:util";
import { launch } from "../tests/chromium.mjs";
import { demoToken, startServer } from "../tests/server.mjs";

/** The close view: a camera about 100 voxels from a gently rolling part of the demo world. */
export const CLOSE = { camera: [220, 175, 420], target: [250, 125, 340] };

const { values: opt } = parseArgs({
  options: {
    bin: { type: "string" },
    base: { type: "string" },
    token: { type: "string" },
    cert: { type: "string" },
    key: { type: "string" },
    tls: { type: "boolean", default: false },
    edits: { type: "string", default: "50" },
    settle: { type: "string", default: "1000" },
    width: { type: "string", default: "1280" },
    height: { type: "string", default: "720" },
    views: { type: "string", default: "default,close" },
    json: { type: "boolean", default: false },
  },
});
if ((!opt.bin && !opt.base) || Boolean(opt.cert) !== Boolean(opt.key)) {
  console.error(
    "usage: live.mjs --bin ISOVOX [--cert CERT.pem --key KEY.pem] | --base URL --token TOKEN [--tls] " +
      "[--edits N] [--views default,close]",
  );
  process.exit(2);
}
const viewport = { width: Number(opt.width), height: Number(opt.height) };
const edits = Number(opt.edits);
const settle = Number(opt.settle);
/** HTTPS (with HTTP/2): a self-signed certificate, so chromium is told to take any. */
const tls = opt.tls || Boolean(opt.cert);

/** GET `url` as bytes; over HTTPS trusting the bench's own certificate (or any, with --tls). */
async function download(url) {
  if (!url.startsWith("https:")) return new Uint8Array(await (await fetch(url)).arrayBuffer());
  const options = opt.cert ? { ca: readFileSync(opt.cert) } : { rejectUnauthorized: false };
  return new Promise((resolve, reject) => {
    httpsGet(url, options, (res) => {
      const chunks = [];
      res.on("data", (c) => chunks.push(c));
      res.on("end", () => resolve(new Uint8Array(Buffer.concat(chunks))));
      res.on("error", reject);
    }).on("error", reject);
  });
}

const epoch = (page) => page.evaluate(() => performance.timeOrigin + performance.now());

/**
 * Waits until `predicate(arg)` is truthy in the page and returns its value. It is polled in
 * the page itself (not a DevTools round trip every few milliseconds, which on this 2-core
 * machine takes CPU from the page being measured).
 */
async function waitPage(page, what, predicate, arg, timeoutMs = 120_000) {
  try {
    const handle = await page.waitForFunction(predicate, arg, { polling: 10, timeout: timeoutMs });
    return await handle.jsonValue();
  } catch (e) {
    throw new Error(`timed out waiting for ${what}: ${e.message}`);
  }
}

/** The top surface height of the demo world at (x, z), from level 1's voxels. */
async function surface(base) {
  const info = JSON.parse(new TextDecoder().decode(await download(`${base}/v1/volumes/demo`)));
  const l = info.levels[1].dims;
  const voxels = await download(`${base}/v1/volumes/demo/levels/1?format=voxels`);
  return (x, z) => {
    const [i, k] = [Math.floor(x / 2), Math.floor(z / 2)];
    for (let j = l[1] - 1; j >= 0; j--) if (voxels[i + l[0] * (j + l[1] * k)] >= info.surface) return 2 * j + 1;
    return 0;
  };
}

async function runView(base, token, name, top) {
  const query = name === "close" ? `?camera=${CLOSE.camera.join(",")}&target=${CLOSE.target.join(",")}` : "";
  // A browser each: pages of one browser share its GPU process, and with SwiftShader A's
  // frames would hold up B's (two people editing together have a GPU each).
  const browsers = [];
  try {
    const open = async () => {
      const browser = await launch(tls ? ["--ignore-certificate-errors"] : []);
      browsers.push(browser);
      const context = await browser.newContext({ viewport });
      const page = await context.newPage();
      const errors = [];
      page.on("pageerror", (e) => errors.push(e.message));
      return { context, page, errors };
    };
    const a = await open();
    const b = await open();
    // Requests and bytes on the wire are the page's own count of its API requests (resource
    // timing): a DevTools session watching the network slowed the close view's load by about
    // a tenth. A new browser has an empty cache.
    await b.page.goto(`${base}/${query}`);
    const load = await waitPage(b.page, "B's view to be complete", () => {
      const s = window.isovox?.stats();
      return s?.completeMs != null ? s : null;
    });
    const loaded = {
      protocol: load.protocol,
      firstFrameMs: load.firstFrameMs,
      completeInViewMs: load.completeInViewMs ?? null,
      completeMs: load.completeMs,
      tiles: load.desired,
      drawn: load.drawn,
      triangles: load.triangles,
      requests: load.wireRequests,
      wireBytes: load.wireBytes,
      decodedBytes: load.bytes,
    };
    await a.page.goto(`${base}/${query}`);
    await waitPage(a.page, "A's view to be complete", () => window.isovox?.stats()?.completeMs != null);
    await waitPage(b.page, "B's feed to be live", () => window.isovox?.stats()?.feed === "live");

    // B: in each animation frame, the first time it shows a version with nothing waiting, and
    // when its animation frames ran (the one after a frame B drew runs once that frame's pixels
    // are composited: with SwiftShader, once they are rasterized).
    await b.page.evaluate(() => {
      window.__shown = {};
      window.__ticks = [];
      const tick = () => {
        const now = performance.timeOrigin + performance.now();
        const s = window.isovox.stats();
        if (s.stale === 0 && !(s.version in window.__shown)) window.__shown[s.version] = now;
        window.__ticks.push(now);
        if (window.__ticks.length > 1000) window.__ticks.splice(0, 500);
        requestAnimationFrame(tick);
      };
      requestAnimationFrame(tick);
    });

    const rows = [];
    for (let i = 0; i < edits; i++) {
      // Points on a 5x5 grid around the view's target, 8 voxels apart.
      const x = CLOSE.target[0] + ((i % 5) - 2) * 8;
      const z = CLOSE.target[2] + ((Math.floor(i / 5) % 5) - 2) * 8;
      const y = top(x, z);
      const op = i % 2 === 0 ? "union" : "difference";
      const r = 5;
      const request = {
        op,
        term: { ellipsoid: { center: [x, y, z], radii: [r, r, r] } },
        region: { min: [x - r - 2, y - r - 2, z - r - 2], max: [x + r + 3, y + r + 3, z + r + 3] },
      };
      const sent = await a.page.evaluate(
        async ({ request, token }) => {
          const t0 = performance.timeOrigin + performance.now();
          const res = await fetch("/v1/volumes/demo/edits", {
            method: "POST",
            headers: { "content-type": "application/json", authorization: `Bearer ${token}` },
            body: JSON.stringify(request),
          });
          const t1 = performance.timeOrigin + performance.now();
          if (!res.ok) throw new Error(`edit: ${res.status} ${await res.text()}`);
          return { t0, t1, version: (await res.json()).version };
        },
        { request, token },
      );
      const seen = await waitPage(b.page, `B to show version ${sent.version}`, (v) => {
        const at = Object.entries(window.__shown).find(([k]) => Number(k) >= v);
        return at ? at[1] : null;
      }, sent.version, 60_000);
      // Where the page keeps commit traces, the frame B drew the swap in (it may come after the
      // animation frame above: a frame is paced after the one before); waited for, at most 3 s
      // (an edit that changed nothing in view draws no frame).
      const traceOf = (v) => {
        const t = window.isovox.traces?.().find((t) => t.version === v);
        return t ? { ...t, origin: performance.timeOrigin } : null;
      };
      let trace = await b.page.evaluate(traceOf, sent.version);
      for (const start = Date.now(); trace && trace.frame === null && Date.now() - start < 3000; ) {
        await b.page.waitForTimeout(10);
        trace = await b.page.evaluate(traceOf, sent.version);
      }
      const row = { total: seen - sent.t0, server: sent.t1 - sent.t0 };
      if (trace) {
        const e = (ms) => (ms === null ? null : trace.origin + ms);
        if (trace.frame !== null) row.total = Math.max(seen, e(trace.frame)) - sent.t0;
        row.feed = e(trace.feed) - sent.t0;
        row.fetch = trace.fetched === null ? 0 : trace.fetched - trace.feed;
        row.decode = trace.decodeMs;
        row.requests = trace.requests;
        row.draw = trace.frame === null || trace.shown === null ? null : trace.frame - Math.max(trace.shown, trace.fetched ?? trace.feed);
        if (trace.frame !== null) {
          // Its pixels: the next animation frame of B after it.
          const at = e(trace.frame);
          const next = await waitPage(b.page, "B's next animation frame", (t) => window.__ticks.find((x) => x > t) ?? null, at, 10_000);
          row.raster = next - at;
        }
      }
      rows.push(row);
      // Let B finish drawing (and its pause after a frame: twice the frame's cost) before the
      // next edit, so that each edit is timed on its own and not behind the last one's frame.
      await b.page.waitForTimeout(settle);
    }
    const errors = [...a.errors, ...b.errors];
    if (errors.length) throw new Error(`page errors: ${errors.join("; ")}`);
    await a.context.close();
    await b.context.close();
    return { name, loaded, rows };
  } finally {
    for (const browser of browsers) await browser.close();
  }
}

const pct = (xs, p) => {
  const s = xs.filter((x) => x !== null && x !== undefined).sort((a, b) => a - b);
  if (!s.length) return null;
  return s[Math.min(s.length - 1, Math.ceil((p / 100) * s.length) - 1)];
};
const ms = (x) => (x === null ? "-" : `${x.toFixed(0)} ms`);

let server = null;
let dataDir = null;
try {
  let base = opt.base;
  let token = opt.token;
  if (opt.bin) {
    dataDir = mkdtempSync(join(tmpdir(), "isovox-bench-live-"));
    server = await startServer(opt.bin, dataDir, {
      extraArgs: opt.cert ? ["--tls-cert", opt.cert, "--tls-key", opt.key] : [],
    });
    base = server.base;
    token = demoToken(dataDir);
  }
  const top = await surface(base);
  const results = [];
  for (const name of opt.views.split(",")) results.push(await runView(base, token, name, top));
  if (opt.json) console.log(JSON.stringify(results, null, 1));
  console.log(
    `demo world 512x256x512, viewport ${viewport.width}x${viewport.height}, close view camera ` +
      `${CLOSE.camera.join(",")} target ${CLOSE.target.join(",")}`,
  );
  console.log("| view | protocol | first frame | in view complete | complete | tiles | triangles | requests | on the wire | decoded |");
  console.log("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|");
  for (const { name, loaded: l } of results) {
    console.log(
      `| ${name} | ${l.protocol} | ${ms(l.firstFrameMs)} | ${ms(l.completeInViewMs)} | ${ms(l.completeMs)} | ${l.tiles} | ` +
        `${l.triangles.toLocaleString("en")} | ${l.requests} | ${(l.wireBytes / 1e6).toFixed(1)} MB | ${(l.bytes ?? l.decodedBytes) / 1e6 > 0 ? ((l.decodedBytes) / 1e6).toFixed(1) : "-"} MB |`,
    );
  }
  console.log(`\nedit on page A to the first frame of page B showing it, ${edits} edits, p50 / p99:`);
  console.log(
    "| view | A to B's screen | server (A answered) | feed (B told) | fetch (after feed) | decode | draw (swap to frame) " +
      "| requests per edit | raster (frame to pixels) |",
  );
  console.log("|---|---:|---:|---:|---:|---:|---:|---:|---:|");
  for (const { name, rows } of results) {
    const col = (k) => `${ms(pct(rows.map((r) => r[k]), 50))} / ${ms(pct(rows.map((r) => r[k]), 99))}`;
    const req = pct(rows.map((r) => r.requests), 50);
    console.log(
      `| ${name} | ${col("total")} | ${col("server")} | ${col("feed")} | ${col("fetch")} | ${col("decode")} | ${col("draw")} | ` +
        `${req ?? "-"} | ${col("raster")} |`,
    );
  }
} finally {
  await server?.kill();
  if (dataDir) rmSync(dataDir, { recursive: true, force: true });
}
