// Pictures side by side, each scaled to one height, saved as one PNG (headless Chromium draws
// them): the README's pictures (scripts/make-readme-images.sh).
//   node compose.mjs OUT.png HEIGHT IMG [IMG ...]
import { launch } from './browser.mjs';
import { pathToFileURL } from 'node:url';
import path from 'node:path';
import fs from 'node:fs';
import os from 'node:os';

const [out, height, ...images] = process.argv.slice(2);
if (!out || !height || !images.length) {
  console.error('usage: node compose.mjs OUT.png HEIGHT IMG [IMG ...]');
  process.exit(2);
}
const browser = await launch();
try {
  const page = await browser.newPage({ viewport: { width: 4000, height: Number(height) } });
  const tags = images.map((i) => `<img src="${pathToFileURL(path.resolve(i)).href}" style="height:${height}px;display:block">`).join('');
  // A page on the file system may show pictures from it (about:blank may not).
  const html = path.join(fs.mkdtempSync(path.join(os.tmpdir(), 'compose-')), 'row.html');
  fs.writeFileSync(html, `<body style="margin:0;background:#fff"><div id="row" style="display:inline-flex;gap:4px">${tags}</div></body>`);
  await page.goto(pathToFileURL(html).href);
  await page.evaluate(() => Promise.all([...document.images].map((i) => i.decode())));
  await page.locator('#row').screenshot({ path: out });
} finally {
  await browser.close();
}
