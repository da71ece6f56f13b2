// Loads the demo world in headless Chromium from a cold cache, over HTTP/1.1 and over HTTP/2
// with TLS, and reports time to first frame, time until every tile the camera needs is on
// screen, requests and bytes. `scripts/bench-web.sh` builds the server and a certificate and
// runs this; by hand:
//
//   node bench/load.mjs --bin target/release/isovox --cert cert.pem --key key.pem [--runs 5]
//       [--width 1280 --height 720] [--screenshot docs/viewer.png]

import { mkdtempSync, rmSync, writeFileSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";
import { parseArgs } from "node:util";
import { launch } from "../tests/chromium.mjs";
import { startServer } from "../tests/server.mjs";

const { values: opt } = parseArgs({
  options: {
    bin: { type: "string" },
    cert: { type: "string" },
    key: { type: "string" },
    runs: { type: "string", default: "5" },
    width: { type: "string", default: "1280" },
    height: { type: "string", default: "720" },
    screenshot: { type: "string" },
  },
});
if (!opt.bin || !opt.cert || !opt.key) {
  console.error("usage: load.mjs --bin ISOVOX --cert CERT.pem --key KEY.pem [--runs N]");
  process.exit(2);
}
const runs = Number(opt.runs);
const viewport = { width: Number(opt.width), height: Number(opt.height) };

/** One cold load: a new browser (empty cache, no connections), the page until complete. */
async function load(base, tls) {
  const browser = await launch(tls ? ["--ignore-certificate-errors"] : []);
  try {
    const context = await browser.newContext({ viewport });
    const page = await context.newPage();
    // Requests and bytes on the wire are the page's own count of its API requests (resource
    // timing), and the page is polled in the page itself: a DevTools session watching the
    // network, or asking every few milliseconds, takes CPU from the page on this 2-core machine.
    // A new browser has an empty cache.
    const errors = [];
    page.on("pageerror", (e) => errors.push(e.message));
    await page.goto(`${base}/`);
    let s;
    try {
      const done = () => {
        const st = window.isovox?.stats();
        return st?.completeMs != null ? st : null;
      };
      s = await (await page.waitForFunction(done, null, { polling: 20, timeout: 60_000 })).jsonValue();
    } catch (e) {
      const now = await page.evaluate(() => window.isovox?.stats() ?? null);
      throw new Error(`not complete after 60 s: ${JSON.stringify(now)} (${e.message})`);
    }
    if (errors.length) throw new Error(`page errors: ${errors.join("; ")}`);
    const result = {
      firstFrameMs: s.firstFrameMs,
      completeMs: s.completeMs,
      requests: s.wireRequests,
      bytes: s.wireBytes,
      tiles: s.desired,
      triangles: s.triangles,
      protocol: s.protocol,
      decodedBytes: s.bytes,
    };
    if (opt.screenshot && !tls) {
      await page.evaluate(() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r))));
      writeFileSync(opt.screenshot, await page.screenshot());
    }
    return result;
  } finally {
    await browser.close();
  }
}

const median = (xs) => [...xs].sort((a, b) => a - b)[Math.floor(xs.length / 2)];

const dataDir = mkdtempSync(join(tmpdir(), "isovox-bench-web-"));
const rows = [];
try {
  for (const [label, tls] of [["HTTP/1.1", false], ["HTTP/2 + TLS", true]]) {
    const server = await startServer(opt.bin, dataDir, {
      extraArgs: tls ? ["--tls-cert", opt.cert, "--tls-key", opt.key] : [],
    });
    try {
      await load(server.base, tls); // warms the server's page cache and mesh cache, not the browser's
      const results = [];
      for (let i = 0; i < runs; i++) results.push(await load(server.base, tls));
      rows.push({ label, results });
    } finally {
      await server.kill();
    }
  }
} finally {
  rmSync(dataDir, { recursive: true, force: true });
}

const r0 = rows[0].results[0];
console.log(
  `demo world 512x256x512 (brick 32), viewport ${viewport.width}x${viewport.height}, ` +
    `${r0.tiles} tiles in view (${r0.triangles.toLocaleString("en")} triangles), ${runs} cold loads each, median (min-max)`,
);
console.log("| protocol | first frame | every tile on screen | requests | bytes on the wire | tile bytes decoded |");
console.log("|---|---:|---:|---:|---:|---:|");
for (const { label, results } of rows) {
  const f = (k, d = 0) => {
    const xs = results.map((r) => r[k]);
    return `${median(xs).toFixed(d)} (${Math.min(...xs).toFixed(d)}-${Math.max(...xs).toFixed(d)})`;
  };
  const proto = [...new Set(results.map((r) => r.protocol))].join(",");
  console.log(
    `| ${label} (${proto}) | ${f("firstFrameMs")} ms | ${f("completeMs")} ms | ${median(results.map((r) => r.requests))} | ` +
      `${(median(results.map((r) => r.bytes)) / 1e6).toFixed(2)} MB | ${(median(results.map((r) => r.decodedBytes)) / 1e6).toFixed(2)} MB |`,
  );
}
const goals = rows.map(({ label, results }) => {
  const ff = median(results.map((r) => r.firstFrameMs));
  const c = median(results.map((r) => r.completeMs));
  return `${label}: first frame ${ff < 1000 ? "under" : "OVER"} 1 s, complete ${c < 3000 ? "under" : "OVER"} 3 s`;
});
console.log(`goals: ${goals.join("; ")}`);
