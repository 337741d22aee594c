#!/usr/bin/env bash
# The README's pictures (docs/images/), made from the demo's outputs so they show what the
# current code writes: a photo with its predicted depth and normals, the reconstruction's page
# (OUT/index.html) as a browser shows it, and a match picture. Runs scripts/demo.sh first when
# its outputs are missing; needs headless Chromium (scripts/browser-setup.sh installs it).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
out="${1:-out}"
if [ ! -f "$out/recon/index.html" ] || [ ! -f "$out/photos/index.html" ]; then
  bash scripts/demo.sh "$out"
fi
bash scripts/browser-setup.sh
web=crates/dens3r-viewer/web
mkdir -p docs/images
node "$web/test/compose.mjs" docs/images/photo-depth-normals.png 240 \
  "$out/photos/images/chelsea.png" "$out/photos/viz/chelsea_depth.png" "$out/photos/viz/chelsea_normal.png"
node "$web/test/check-page.mjs" "$out/recon/index.html" --width 1100 --height 640 \
  --screenshot docs/images/viewer.png > /dev/null
match=$(ls "$out"/recon/matches/*.png | head -1)
node "$web/test/compose.mjs" docs/images/matches.png 220 "$match"
ls -l docs/images/
