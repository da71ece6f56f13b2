// How fast others' edits reach the screen, and how fast a close view loads: headless Chromium
// with two pages on the demo world, page A editing, page B watching. `scripts/bench-web.sh
// --live` builds the server and runs this; by hand:
//
//   node bench/live.mjs --bin target/release/isovox [--edits 50] [--width 1280 --height 720]
//
// For each view (the default one, and CLOSE below: near the ground at the default detail):
//
// - B's cold load (empty cache): first frame, every tile in the view frustum on screen, every
//   tile of the selection on screen, tiles, triangles, requests, bytes on the wire and decoded.
// - Then EDITS edits, one at a time, each a small ellipsoid added or carved near the view's
//   centre (in sight in both views), sent by page A with `fetch`, and the time from A sending it
//   to the first animation frame of B in which B shows the version and no tile waits for a newer
//   drawing (read in B's own animation-frame callbacks, so it is measured the same way for any
//   version of the viewer). Where the page keeps commit traces (`isovox.traces()`), the time is
//   split into: server (A's request answered), feed (B's change feed delivered the commit),
//   fetch (the last response of B's requests for it), decode, and draw (until the first frame
//   after B swapped the tiles in). Clocks: performance.timeOrigin + performance.now() of each
//   page (the same machine clock).

import { mkdtempSync, rmSync } from "node:fs";
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
    edits: { type: "string", default: "50" },
    width: { type: "string", default: "1280" },
    height: { type: "string", default: "720" },
    views: { type: "string", default: "default,close" },
    json: { type: "boolean", default: false },
  },
});
if (!opt.bin && !opt.base) {
  console.error("usage: live.mjs --bin ISOVOX | --base URL --token TOKEN [--edits N] [--views default,close]");
  process.exit(2);
}
const viewport = { width: Number(opt.width), height: Number(opt.height) };
const edits = Number(opt.edits);

const epoch = (page) => page.evaluate(() => performance.timeOrigin + performance.now());

async function waitPage(page, what, predicate, arg, timeoutMs = 120_000) {
  const start = Date.now();
  for (;;) {
    const v = await page.evaluate(predicate, arg);
    if (v) return v;
    if (Date.now() - start > timeoutMs) throw new Error(`timed out waiting for ${what}`);
    await page.waitForTimeout(10);
  }
}

/** The top surface height of the demo world at (x, z), from level 1's voxels. */
async function surface(base) {
  const info = await (await fetch(`${base}/v1/volumes/demo`)).json();
  const l = info.levels[1].dims;
  const voxels = new Uint8Array(await (await fetch(`${base}/v1/volumes/demo/levels/1?format=voxels`)).arrayBuffer());
  return (x, z) => {
    const [i, k] = [Math.floor(x / 2), Math.floor(z / 2)];
    for (let j = l[1] - 1; j >= 0; j--) if (voxels[i + l[0] * (j + l[1] * k)] >= info.surface) return 2 * j + 1;
    return 0;
  };
}

async function runView(base, token, name, top) {
  const query = name === "close" ? `?camera=${CLOSE.camera.join(",")}&target=${CLOSE.target.join(",")}` : "";
  const browser = await launch();
  try {
    const open = async () => {
      const context = await browser.newContext({ viewport });
      const page = await context.newPage();
      const errors = [];
      page.on("pageerror", (e) => errors.push(e.message));
      return { context, page, errors };
    };
    const a = await open();
    const b = await open();
    const cdp = await b.context.newCDPSession(b.page);
    await cdp.send("Network.enable");
    await cdp.send("Network.setCacheDisabled", { cacheDisabled: true });
    let wireBytes = 0;
    let requests = 0;
    cdp.on("Network.requestWillBeSent", () => requests++);
    cdp.on("Network.loadingFinished", (e) => (wireBytes += e.encodedDataLength));
    await b.page.goto(`${base}/${query}`);
    const load = await waitPage(b.page, "B's view to be complete", () => {
      const s = window.isovox?.stats();
      return s?.completeMs != null ? s : null;
    });
    const loaded = {
      firstFrameMs: load.firstFrameMs,
      completeInViewMs: load.completeInViewMs ?? null,
      completeMs: load.completeMs,
      tiles: load.desired,
      drawn: load.drawn,
      triangles: load.triangles,
      requests,
      wireBytes,
      decodedBytes: load.bytes,
    };
    await a.page.goto(`${base}/${query}`);
    await waitPage(a.page, "A's view to be complete", () => window.isovox?.stats()?.completeMs != null);
    await waitPage(b.page, "B's feed to be live", () => window.isovox?.stats()?.feed === "live");

    // B: in each animation frame, the first time it shows a version with nothing waiting.
    await b.page.evaluate(() => {
      window.__shown = {};
      const tick = () => {
        const s = window.isovox.stats();
        if (s.stale === 0 && !(s.version in window.__shown)) {
          window.__shown[s.version] = performance.timeOrigin + performance.now();
        }
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
      const trace = await b.page.evaluate(
        (v) => {
          const t = window.isovox.traces?.().find((t) => t.version === v);
          return t ? { ...t, origin: performance.timeOrigin } : null;
        },
        sent.version,
      );
      const row = { total: seen - sent.t0, server: sent.t1 - sent.t0 };
      if (trace) {
        const e = (ms) => (ms === null ? null : trace.origin + ms);
        row.feed = e(trace.feed) - sent.t0;
        row.fetch = trace.fetched === null ? 0 : trace.fetched - trace.feed;
        row.decode = trace.decodeMs;
        row.requests = trace.requests;
        row.draw = trace.frame === null || trace.shown === null ? null : trace.frame - Math.max(trace.shown, trace.fetched ?? trace.feed);
      }
      rows.push(row);
      // Let both pages settle before the next edit.
      await b.page.waitForTimeout(50);
    }
    const errors = [...a.errors, ...b.errors];
    if (errors.length) throw new Error(`page errors: ${errors.join("; ")}`);
    await a.context.close();
    await b.context.close();
    return { name, loaded, rows };
  } finally {
    await browser.close();
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
    server = await startServer(opt.bin, dataDir);
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
  console.log("| view | first frame | in view complete | complete | tiles | triangles | requests | on the wire | decoded |");
  console.log("|---|---:|---:|---:|---:|---:|---:|---:|---:|");
  for (const { name, loaded: l } of results) {
    console.log(
      `| ${name} | ${ms(l.firstFrameMs)} | ${ms(l.completeInViewMs)} | ${ms(l.completeMs)} | ${l.tiles} | ` +
        `${l.triangles.toLocaleString("en")} | ${l.requests} | ${(l.wireBytes / 1e6).toFixed(1)} MB | ${(l.bytes ?? l.decodedBytes) / 1e6 > 0 ? ((l.decodedBytes) / 1e6).toFixed(1) : "-"} MB |`,
    );
  }
  console.log(`\nedit on page A to the first frame of page B showing it, ${edits} edits, p50 / p99:`);
  console.log("| view | A to B's screen | server (A answered) | feed (B told) | fetch (after feed) | decode | draw (swap to frame) | requests per edit |");
  console.log("|---|---:|---:|---:|---:|---:|---:|---:|");
  for (const { name, rows } of results) {
    const col = (k) => `${ms(pct(rows.map((r) => r[k]), 50))} / ${ms(pct(rows.map((r) => r[k]), 99))}`;
    const req = pct(rows.map((r) => r.requests), 50);
    console.log(
      `| ${name} | ${col("total")} | ${col("server")} | ${col("feed")} | ${col("fetch")} | ${col("decode")} | ${col("draw")} | ${req ?? "-"} |`,
    );
  }
} finally {
  await server?.kill();
  if (dataDir) rmSync(dataDir, { recursive: true, force: true });
}
