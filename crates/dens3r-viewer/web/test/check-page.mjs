// Opens a page dens3r wrote (OUT/index.html, from the file system) in headless Chromium and
// prints what a person would see, as JSON: console errors, how much of the 3-D canvas differs
// from the background (mesh and points), and how many pixels moving the confidence slider
// changed. `--screenshot FILE` also saves the page. Used by the browser test and by
// scripts/make-readme-images.sh.
//   node check-page.mjs OUT/index.html [--screenshot FILE] [--width W --height H]
import { launch } from './browser.mjs';
import { pathToFileURL } from 'node:url';
import path from 'node:path';

const args = process.argv.slice(2);
const opt = (name, dflt) => {
  const i = args.indexOf(name);
  return i >= 0 ? args[i + 1] : dflt;
};
const index = args[0];
if (!index) {
  console.error('usage: node check-page.mjs OUT/index.html [--screenshot FILE]');
  process.exit(2);
}
const BACKGROUND = [0x1d, 0x20, 0x24];

const browser = await launch();
try {
  const page = await browser.newPage({ viewport: { width: Number(opt('--width', 1280)), height: Number(opt('--height', 800)) } });
  const errors = [];
  page.on('console', (m) => { if (m.type() === 'error') errors.push(m.text()); });
  page.on('pageerror', (e) => errors.push(String(e)));
  page.on('requestfailed', (r) => errors.push(`failed to load ${r.url()}`));
  const t0 = Date.now();
  await page.goto(pathToFileURL(path.resolve(index)).href);
  await page.waitForFunction(() => window.dens3rViewer && window.dens3rViewer.ready, null, { timeout: 120000 });
  const readySeconds = (Date.now() - t0) / 1000;
  const grab = async () => {
    const p = await page.evaluate(() => window.dens3rViewer.pixels());
    return { ...p, rgba: Buffer.from(p.rgba, 'base64') };
  };
  const nonBackground = (p) => {
    let n = 0;
    for (let i = 0; i < p.rgba.length; i += 4) {
      if (Math.abs(p.rgba[i] - BACKGROUND[0]) + Math.abs(p.rgba[i + 1] - BACKGROUND[1]) + Math.abs(p.rgba[i + 2] - BACKGROUND[2]) > 12) n++;
    }
    return n / (p.rgba.length / 4);
  };
  const differing = (a, b) => {
    let n = 0;
    for (let i = 0; i < a.rgba.length; i += 4) {
      if (a.rgba[i] !== b.rgba[i] || a.rgba[i + 1] !== b.rgba[i + 1] || a.rgba[i + 2] !== b.rgba[i + 2]) n++;
    }
    return n / (a.rgba.length / 4);
  };
  const modes = await page.$$eval('#mode option', (os) => os.map((o) => o.value));
  const report = { ready_seconds: readySeconds, errors, modes, viewer: await page.evaluate(() => !document.getElementById('status').textContent) };
  const startMode = await page.inputValue('#mode');
  if (modes.includes('mesh')) {
    await page.selectOption('#mode', 'mesh');
    report.mesh_drawn = nonBackground(await grab());
  }
  if (modes.includes('points')) {
    await page.selectOption('#mode', 'points');
    await page.locator('#conf').fill('0');
    const low = await grab();
    report.points_drawn = nonBackground(low);
    report.label_low = await page.textContent('#conf-label');
    await page.locator('#conf').fill('700');
    const high = await grab();
    report.points_drawn_high = nonBackground(high);
    report.label_high = await page.textContent('#conf-label');
    report.changed_by_slider = differing(low, high);
  }
  // Clicking a view's picture looks from that camera.
  const cards = await page.$$('#gallery figure');
  if (cards.length > 1) {
    const before = await grab();
    await cards[Math.floor(cards.length / 2)].click();
    report.changed_by_view_click = differing(before, await grab());
  }
  report.pictures = await page.$$eval('#gallery img', (is) => is.length);
  // Pictures load lazily as they scroll into view: ask for them all now.
  report.pictures_loaded = await page.$$eval('#gallery img', (is) =>
    Promise.all(is.map((i) => { i.loading = 'eager'; return i.decode().then(() => true, () => false); })).then((r) => r.filter(Boolean).length));
  report.summary_rows = await page.$$eval('#summary tr', (r) => r.length);
  report.match_pictures = await page.$$eval('#matches img', (is) => is.length);
  report.score_tables = await page.$$eval('#scores table', (t) => t.length);
  const shot = opt('--screenshot');
  if (shot) {
    await page.click('#home');
    await page.evaluate(() => { document.getElementById('gallery').scrollLeft = 0; });
    await page.locator('#conf').fill(String(await page.evaluate(() => window.dens3rViewer.startSlider)));
    await page.selectOption('#mode', startMode);
    await page.screenshot({ path: shot });
  }
  console.log(JSON.stringify(report));
} finally {
  await browser.close();
}
