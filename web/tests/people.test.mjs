// Browser tests of editing together (issue 34): two pages signed in as two users of the token
// file. Debian's chromium (playwright-core, SwiftShader WebGL2) against a real `isovox serve`
// (the binary named by ISOVOX_BIN) on the demo world.
//
//   ISOVOX_BIN=target/debug/isovox node --test tests/people.test.mjs     (in web/)

import { createHash, generateKeyPairSync, sign } from "node:crypto";
import { appendFileSync, mkdtempSync, rmSync, writeFileSync } from "node:fs";
import { createServer } from "node:http";
import { tmpdir } from "node:os";
import { join } from "node:path";
import { after, before, test } from "node:test";
import assert from "node:assert/strict";
import { launch } from "./chromium.mjs";
import { decodePng, pixel } from "./png.mjs";
import { startServer } from "./server.mjs";

const BIN = process.env.ISOVOX_BIN;
const VIEW = { width: 800, height: 500 };
const PANEL_W = 270;
/** The overlay text (top left): left out of pixel comparisons. */
const OVERLAY = { w: 520, h: 110 };
/** A pixel of the default view on the terrain in front. */
const FRONT = { x: Math.round((VIEW.width - PANEL_W) * 0.42), y: Math.round(VIEW.height * 0.72) };
const ALICE = "a11ce0000000000000000000000000a1";
const BOB = "b0b00000000000000000000000000b0b";

let dataDir;
let server;
let browser;

before(async () => {
  assert.ok(BIN, "set ISOVOX_BIN to the isovox binary");
  dataDir = mkdtempSync(join(tmpdir(), "isovox-people-"));
  // The first start generates the demo world and the token file; two users join it.
  const first = await startServer(BIN, dataDir);
  await first.kill();
  appendFileSync(join(dataDir, "tokens"), `alice ${ALICE} write\nbob ${BOB} write\n`);
  server = await startServer(BIN, dataDir);
  browser = await launch();
});

after(async () => {
  await browser?.close();
  await server?.kill();
  if (dataDir) rmSync(dataDir, { recursive: true, force: true });
});

async function openPage(query = "") {
  const context = await browser.newContext({ viewport: VIEW });
  const page = await context.newPage();
  const errors = [];
  page.on("console", (m) => {
    if (m.type() === "error") errors.push(m.text());
  });
  page.on("pageerror", (e) => errors.push(e.message));
  await page.goto(`${server.base}/${query}`);
  return { context, page, errors };
}

async function until(page, what, fn, arg, timeoutMs = 60_000) {
  const start = Date.now();
  let last = null;
  while (Date.now() - start < timeoutMs) {
    last = await page.evaluate(fn, arg);
    if (last) return last;
    await page.waitForTimeout(100);
  }
  throw new Error(`timed out waiting for ${what}`);
}

/**
 * Waits until every tile the camera needs shows version `version` or later, and a frame drew it:
 * no frame is pending (one asked for soon after another waits out that one's pause, scene.ts
 * `requestRender`, so frames of the browser alone do not tell), then two more frames for the
 * browser to composite it.
 */
async function waitComplete(page, version = 0) {
  await until(
    page,
    `the view to be complete at version ${version} and drawn`,
    (v) => {
      const s = window.isovox?.stats();
      return s && s.complete && s.completeMs !== null && s.version >= v && s.stale === 0 && !s.framePending;
    },
    version,
  );
  await page.evaluate(() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r))));
}

const people = (page) => page.evaluate(() => window.isovox.people());

/** Signs in with a pasted token through the panel's button and prompt. */
async function signIn(page, token, user) {
  await page.click("#sign-in");
  await page.fill("#token", token);
  await page.click("#token-form button");
  await until(page, `signed in as ${user}`, (u) => window.isovox.people().me === u, user);
  assert.match(await page.textContent("#who"), new RegExp(`Signed in as ${user}`));
}

let shots = 0;

/** The page's screenshot (also written to ISOVOX_TEST_SHOTS/ when that is set), and the boxes of what lies over the 3D view (markers, notes). */
async function shot(page) {
  const covered = await page.evaluate(() =>
    [...document.querySelectorAll("#cursors .cursor:not([hidden]), #note:not([hidden]), #viewing:not([hidden])")].map((el) => {
      // A marker's dot and name lie around its own (zero-size) box.
      const r = el.getBoundingClientRect();
      const spread = el.classList.contains("cursor") ? 120 : 4;
      return { x0: r.left - 12, y0: r.top - 16, x1: r.right + spread, y1: r.bottom + 16 };
    }),
  );
  const png = await page.screenshot();
  if (process.env.ISOVOX_TEST_SHOTS) {
    writeFileSync(join(process.env.ISOVOX_TEST_SHOTS, `people-${String(++shots).padStart(2, "0")}.png`), png);
  }
  return { img: decodePng(png), covered };
}

/** Pixels of the 3D view (outside the overlay, panel and anything over the view in either shot) differing by more than 24. */
function changedPixels(a, b, inside = () => true) {
  const covered = [...a.covered, ...b.covered];
  let changed = 0;
  let total = 0;
  for (let y = 0; y < a.img.height; y++) {
    for (let x = 0; x < VIEW.width - PANEL_W; x++) {
      if ((x < OVERLAY.w && y < OVERLAY.h) || !inside(x, y)) continue;
      if (covered.some((c) => x >= c.x0 && x <= c.x1 && y >= c.y0 && y <= c.y1)) continue;
      total++;
      const p = pixel(a.img, x, y);
      const q = pixel(b.img, x, y);
      if (Math.max(...p.map((c, i) => Math.abs(c - q[i]))) > 24) changed++;
    }
  }
  return { changed, total };
}

/** FNV-1a 32 of a string (presence.ts gives each user the hue FNV-1a mod 360). */
function fnv1a(s) {
  let h = 0x811c9dc5;
  for (const c of s) h = Math.imul(h ^ c.charCodeAt(0), 0x01000193) >>> 0;
  return h;
}

test("A's edit reaches B with A's name and A's cursor; Ctrl+Z in A gives both pages the surface from before; B views the edit's version read-only and reverts to it; A's redo is then refused in words", { timeout: 300_000 }, async (t) => {
  const b = await openPage();
  await waitComplete(b.page);
  // A stands 40% of the way from B's camera to the point B looks at: A's cursor is in B's view.
  const q = new URL(b.page.url()).searchParams;
  const camB = q.get("camera").split(",").map(Number);
  const target = q.get("target").split(",").map(Number);
  const camA = camB.map((v, i) => v + 0.4 * (target[i] - v));
  const a = await openPage(`?volume=demo&camera=${camA.join(",")}&target=${target.join(",")}`);
  await signIn(b.page, BOB, "bob");
  await signIn(a.page, ALICE, "alice");

  // B draws alice's marker, in her colour, where her camera is.
  const marker = await b.page.waitForSelector('#cursors .cursor[data-user="alice"]:not([hidden])', { state: "attached", timeout: 30_000 });
  assert.match(await marker.textContent(), /alice/);
  const label = await (await marker.$("span")).boundingBox();
  assert.ok(label && label.width > 10 && label.x >= 0 && label.x < VIEW.width - PANEL_W, `alice's name on screen: ${JSON.stringify(label)}`);
  const colour = await marker.evaluate((el) => el.style.getPropertyValue("--colour"));
  assert.equal(colour, `hsl(${fnv1a("alice") % 360}, 70%, 45%)`);
  const box = await marker.boundingBox();
  const expected = await b.page.evaluate(([x, y, z]) => window.isovox.project(x, y, z), camA);
  assert.ok(Math.hypot(box.x - expected.x, box.y - expected.y) < 3, `marker at ${JSON.stringify(box)}, A's camera at ${JSON.stringify(expected)}`);
  assert.ok((await people(b.page)).cursors.includes("alice"));
  assert.ok(!(await people(b.page)).cursors.includes("bob"), "a page draws no marker for its own user");

  await waitComplete(a.page);
  await waitComplete(b.page);
  const beforeA = await shot(a.page);
  const beforeB = await shot(b.page);

  // A carves through the panel (the session's token is alice's already: no prompt).
  assert.ok(await a.page.evaluate(({ x, y }) => window.isovox.pick(x, y), FRONT), "terrain under the edit point");
  await a.page.check("#edit-mode");
  await a.page.selectOption("#op", "union");
  await a.page.selectOption("#primitive", "cuboid");
  await a.page.fill("#size", "24");
  await a.page.mouse.click(FRONT.x, FRONT.y);
  const applied = await until(a.page, "the edit's answer", () => {
    const t = document.querySelector("#edit-status").textContent;
    return /Applied as version|failed|refused|cannot/.test(t) ? t : null;
  });
  const m = /Applied as version (\d+)/.exec(applied);
  assert.ok(m, `edit status: ${applied}`);
  const version = Number(m[1]);
  assert.equal((await people(a.page)).nextUndo, version);

  // B: the change with alice's name in the history panel, and on screen.
  await waitComplete(b.page, version);
  const row = await b.page.waitForSelector(`#history li[data-version="${version}"]`, { timeout: 30_000 });
  const rowText = await row.textContent();
  assert.match(rowText, /alice/);
  assert.match(rowText, /added \(union: cuboid\)/);
  const entry = (await people(b.page)).history.find((e) => e.version === version);
  assert.deepEqual([entry.author, entry.kind, entry.undone], ["alice", "edit", false]);
  const afterB = await shot(b.page);
  const info = await (await fetch(`${server.base}/v1/volumes/demo`)).json();
  const history = await (await fetch(`${server.base}/v1/volumes/demo/history?limit=1`)).json();
  assert.equal(history.commits[0].version, version);
  const opBox = history.commits[0].op.box;
  const centre = opBox.min.map((v, i) => ((v + opBox.max[i]) / 2) * info.voxel_scale[i]);
  const at = await b.page.evaluate(([x, y, z]) => window.isovox.project(x, y, z), centre);
  const near = changedPixels(beforeB, afterB, (x, y) => Math.hypot(x - at.x, y - at.y) < 15);
  t.diagnostic(`B near the edit: ${near.changed} of ${near.total} pixels changed`);
  assert.ok(near.total > 100 && near.changed > near.total * 0.2, `B sees the edit: ${near.changed} of ${near.total} pixels near it changed`);

  // A presses Ctrl+Z: the edit is undone, and both pages show the surface from before it.
  // (Keys typed in the size field are the field's: the person has left it.)
  await a.page.evaluate(() => document.activeElement?.blur());
  await a.page.keyboard.press("Control+z");
  const undone = await until(a.page, "the undo's answer", () => {
    const t = document.querySelector("#edit-status").textContent;
    return /Undone|undo|cannot/.test(t) && !/Undoing/.test(t) ? t : null;
  });
  const u = /^Undone as version (\d+); no later edit over it\.$/.exec(undone);
  assert.ok(u, `undo status: ${undone}`);
  const undoVersion = Number(u[1]);
  assert.ok(undoVersion > version);
  await waitComplete(a.page, undoVersion);
  await waitComplete(b.page, undoVersion);
  for (const [name, page, beforeShot] of [["A", a.page, beforeA], ["B", b.page, beforeB]]) {
    const now = await shot(page);
    const diff = changedPixels(beforeShot, now);
    t.diagnostic(`${name} after the undo: ${diff.changed} of ${diff.total} pixels differ from before the edit`);
    assert.ok(diff.total > 100_000, `${name}: ${diff.total} pixels compared`);
    assert.ok(diff.changed <= diff.total * 0.001, `${name}: ${diff.changed} of ${diff.total} pixels differ from before the edit`);
  }
  // B's history marks the edit undone, by alice's undo.
  await b.page.waitForSelector(`#history li.undone[data-version="${version}"]`, { timeout: 30_000 });
  const undoRow = await b.page.textContent(`#history li[data-version="${undoVersion}"]`);
  assert.match(undoRow, new RegExp(`alice undid version ${version}`));
  assert.equal((await people(a.page)).nextRedo, undoVersion);

  // B looks at the edit's version read-only: the cuboid again, under a banner; then live again.
  await b.page.click(`#history li[data-version="${version}"] button.view`);
  assert.match(await b.page.textContent("#viewing"), new RegExp(`Viewing version ${version}, read-only`));
  await until(b.page, "B at the edit's version", (v) => window.isovox.stats().version === v, version);
  await waitComplete(b.page, version);
  const viewed = await shot(b.page);
  const same = changedPixels(afterB, viewed);
  t.diagnostic(`B viewing version ${version}: ${same.changed} of ${same.total} pixels differ from live after the edit`);
  assert.ok(same.changed <= same.total * 0.001, `viewing version ${version}: ${same.changed} of ${same.total} pixels differ`);
  await b.page.check("#edit-mode");
  await b.page.mouse.click(FRONT.x, FRONT.y);
  assert.match(await b.page.textContent("#edit-status"), /read-only: go back to live to edit/);
  await b.page.uncheck("#edit-mode");
  await b.page.click("#live");
  assert.ok(await b.page.isHidden("#viewing"));
  await until(b.page, "B live again", (v) => window.isovox.stats().version === v, undoVersion);
  await waitComplete(b.page, undoVersion);
  const live = changedPixels(beforeB, await shot(b.page));
  assert.ok(live.changed <= live.total * 0.001, `live again: ${live.changed} of ${live.total} pixels differ from before the edit`);

  // B reverts to the edit's version: the cuboid is back on both pages.
  b.page.once("dialog", (d) => void d.accept());
  await b.page.click(`#history li[data-version="${version}"] button.revert`);
  const reverted = await until(b.page, "the revert's answer", () => {
    const t = document.querySelector("#edit-status").textContent;
    return /Reverted|revert/.test(t) ? t : null;
  });
  const r = new RegExp(`^Reverted to version ${version} as version (\\d+)\\.$`).exec(reverted);
  assert.ok(r, `revert status: ${reverted}`);
  await waitComplete(a.page, Number(r[1]));
  await waitComplete(b.page, Number(r[1]));
  const back = changedPixels(afterB, await shot(b.page));
  assert.ok(back.changed <= back.total * 0.001, `after the revert: ${back.changed} of ${back.total} pixels differ from after the edit`);
  await b.page.waitForSelector(`#history li[data-version="${r[1]}"]`);
  assert.match(await b.page.textContent(`#history li[data-version="${r[1]}"]`), new RegExp(`bob reverted to version ${version}`));

  // A's Ctrl+Shift+Z would make the edit again, but the revert did: the server's 409 in words.
  await a.page.keyboard.press("Control+Shift+Z");
  const refused = await until(a.page, "the redo's answer", () => {
    const t = document.querySelector("#edit-status").textContent;
    return /Redo|redo|Redone/.test(t) && !/Redoing/.test(t) ? t : null;
  });
  assert.match(refused, new RegExp(`^Version ${undoVersion} cannot be redone \\(409 Conflict\\): .+ It was taken off the list\\.$`));
  assert.equal((await people(a.page)).nextRedo, null);

  // Chromium logs every failed request; the refused redo's 409 is the one expected.
  const conflict = /^Failed to load resource: the server responded with a status of 409/;
  assert.deepEqual(a.errors.filter((e) => !conflict.test(e)), [], "A's console errors");
  assert.equal(a.errors.length, 1, "one refused request, the redo");
  assert.deepEqual(b.errors, [], "B's console errors");
  await a.context.close();
  await b.context.close();
});

// --- sign-in at an OpenID Connect provider -----------------------------------------------------

const b64url = (buf) => Buffer.from(buf).toString("base64url");

/**
 * A provider on 127.0.0.1 that signs in anyone at once: discovery, an authorization endpoint
 * that redirects back with a code, and a token endpoint that checks the code, the redirect URI,
 * the client and the PKCE verifier against the S256 challenge before it answers an opaque access
 * token and an ID token (RS256) for `user` with `roles`. CORS open, as providers allow the
 * origins registered for a client.
 */
async function startProvider({ clientId, user, roles }) {
  const { privateKey, publicKey } = generateKeyPairSync("rsa", { modulusLength: 2048 });
  const jwk = { ...publicKey.export({ format: "jwk" }), kid: "k1", alg: "RS256", use: "sig" };
  const codes = new Map();
  const seen = { authorize: [], token: [] };
  const server = createServer((req, res) => {
    const u = new URL(req.url, base);
    const cors = { "access-control-allow-origin": "*", "access-control-allow-headers": "content-type" };
    const json = (status, body) => {
      res.writeHead(status, { ...cors, "content-type": "application/json" });
      res.end(JSON.stringify(body));
    };
    if (req.method === "OPTIONS") return res.writeHead(204, cors), res.end();
    if (u.pathname === "/.well-known/openid-configuration") {
      return json(200, { issuer: base, authorization_endpoint: `${base}/auth`, token_endpoint: `${base}/token`, jwks_uri: `${base}/jwks` });
    }
    if (u.pathname === "/auth") {
      const p = Object.fromEntries(u.searchParams);
      seen.authorize.push(p);
      const code = `code-${codes.size + 1}`;
      codes.set(code, p);
      const back = new URL(p.redirect_uri);
      back.searchParams.set("code", code);
      back.searchParams.set("state", p.state);
      return res.writeHead(302, { location: back.toString() }), res.end();
    }
    if (u.pathname === "/token" && req.method === "POST") {
      let body = "";
      req.on("data", (c) => (body += c));
      req.on("end", () => {
        const f = Object.fromEntries(new URLSearchParams(body));
        seen.token.push(f);
        const asked = codes.get(f.code);
        codes.delete(f.code);
        const ok =
          asked &&
          f.grant_type === "authorization_code" &&
          f.client_id === clientId &&
          asked.client_id === clientId &&
          f.redirect_uri === asked.redirect_uri &&
          asked.code_challenge_method === "S256" &&
          b64url(createHash("sha256").update(f.code_verifier ?? "").digest()) === asked.code_challenge;
        if (!ok) return json(400, { error: "invalid_grant" });
        const now = Math.floor(Date.now() / 1000);
        const claims = { iss: base, aud: clientId, sub: `id-${user}`, preferred_username: user, iat: now, exp: now + 600, isovox_roles: roles };
        const input = `${b64url(JSON.stringify({ alg: "RS256", kid: "k1", typ: "JWT" }))}.${b64url(JSON.stringify(claims))}`;
        const jwt = `${input}.${b64url(sign("sha256", Buffer.from(input), privateKey))}`;
        json(200, { access_token: "opaque-access-token", token_type: "Bearer", id_token: jwt, expires_in: 600 });
      });
      return;
    }
    json(404, { error: "not_found" });
  });
  await new Promise((r) => server.listen(0, "127.0.0.1", r));
  const base = `http://127.0.0.1:${server.address().port}`;
  return { base, jwks: { keys: [jwk] }, seen, close: () => new Promise((r) => server.close(r)) };
}

test("sign-in at the server's OIDC provider: authorization code with PKCE, in the page", { timeout: 180_000 }, async () => {
  const provider = await startProvider({ clientId: "isovox-web", user: "carol", roles: ["write:*"] });
  const jwksFile = join(dataDir, "jwks.json");
  writeFileSync(jwksFile, JSON.stringify(provider.jwks));
  await server.kill();
  server = await startServer(BIN, dataDir, {
    extraArgs: ["--oidc-issuer", provider.base, "--oidc-audience", "isovox-web", "--oidc-jwks", jwksFile],
  });
  try {
    const { context, page, errors } = await openPage("?volume=demo&detail=12");
    await page.waitForSelector("#sign-in-oidc:not([hidden])");
    assert.match(await page.textContent("#who"), /Not signed in/);
    await Promise.all([page.waitForURL((u) => u.searchParams.has("code")), page.click("#sign-in-oidc")]);
    await until(page, "signed in as carol", () => window.isovox?.people().me === "carol");
    assert.match(await page.textContent("#who"), /^Signed in as carol$/);
    // The provider was asked for a code with an S256 challenge and the page's own address, and
    // the page traded it with the verifier (the provider checked them); the page's query is back.
    assert.equal(provider.seen.authorize.length, 1);
    const asked = provider.seen.authorize[0];
    assert.equal(asked.client_id, "isovox-web");
    assert.equal(asked.redirect_uri, `${server.base}/`);
    assert.equal(asked.code_challenge_method, "S256");
    assert.equal(provider.seen.token.length, 1);
    const back = new URL(page.url()).searchParams;
    assert.deepEqual([back.has("code"), back.has("state"), back.get("volume"), back.get("detail")], [false, false, "demo", "12"]);
    // The session's token is the ID token (the access token is opaque): the server takes it.
    const token = await page.evaluate(() => sessionStorage.getItem("isovox-token"));
    const who = await (await fetch(`${server.base}/v1/auth`, { headers: { authorization: `Bearer ${token}` } })).json();
    assert.deepEqual([who.user, who.write], ["carol", true]);
    assert.deepEqual(errors, [], "console errors");
    await context.close();
  } finally {
    await provider.close();
  }
});
