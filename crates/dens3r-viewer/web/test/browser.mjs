// Headless Chromium as this machine runs it (Debian's, or $CHROMIUM), shared by the page
// check and the README's pictures: no sandbox (CI runs as root), software WebGL, and no
// background connections (the machine's network is closed).
import { chromium } from 'playwright-core';

export function launch() {
  return chromium.launch({
    executablePath: process.env.CHROMIUM || '/usr/bin/chromium',
    args: [
      '--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader', '--disable-quic',
      '--no-first-run', '--disable-background-networking', '--disable-component-update', '--disable-sync',
    ],
  });
}
