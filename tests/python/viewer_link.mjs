// Prints the "Open in Neuroglancer" link of Isovox's own viewer page for a volume: the page is
// opened in Debian's Chromium (headless, software WebGL) and the link read once the page set it.
// Usage: node viewer_link.mjs ORIGIN VOLUME
import { chromium } from 'playwright-core';

const [origin, volume] = process.argv.slice(2);
const browser = await chromium.launch({
  executablePath: '/usr/bin/chromium',
  args: ['--use-angle=swiftshader', '--enable-unsafe-swiftshader', '--headless', '--no-sandbox', '--disable-gpu'],
});
try {
  const page = await browser.newPage({ viewport: { width: 800, height: 500 } });
  await page.goto(`${origin}/?volume=${encodeURIComponent(volume)}`);
  await page.waitForFunction(() => window.isovox?.stats()?.volume && document.querySelector('#neuroglancer')?.href, null, { timeout: 60_000 });
  console.log(await page.getAttribute('#neuroglancer', 'href'));
} finally {
  await browser.close();
}
