// Opens a page in Debian's Chromium (headless, software WebGL) and keeps it open until this
// process's standard input closes or 180 s pass, printing the page's errors on stderr. The
// Neuroglancer test drives the page through Neuroglancer's own Python side meanwhile.
// Usage: node open_page.mjs URL WIDTH HEIGHT
import { chromium } from 'playwright-core';

const [url, width, height] = process.argv.slice(2);
const browser = await chromium.launch({
  executablePath: '/usr/bin/chromium',
  args: [
    '--use-angle=swiftshader', '--enable-unsafe-swiftshader', '--headless', '--no-sandbox',
    '--disable-gpu', '--disable-background-networking', '--disable-component-update',
    '--disable-sync', '--no-first-run',
  ],
});
try {
  const page = await browser.newPage({ viewport: { width: Number(width), height: Number(height) } });
  page.on('pageerror', (e) => console.error(`page error: ${e.message}`));
  page.on('console', (m) => { if (m.type() === 'error') console.error(`console: ${m.text()}`); });
  await page.goto(url);
  console.log('opened');
  await new Promise((resolve) => {
    // The timer is cleared once stdin ends: a pending timer keeps node running after the
    // browser closed, and the caller would wait for it (30 s per page in the Neuroglancer test).
    const timer = setTimeout(resolve, 180_000);
    const done = () => { clearTimeout(timer); resolve(); };
    process.stdin.on('end', done);
    process.stdin.on('close', done);
    process.stdin.resume();
  });
} finally {
  await browser.close();
}
