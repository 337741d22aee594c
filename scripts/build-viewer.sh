#!/usr/bin/env bash
# The 3-D viewer of the pages dens3r writes (OUT/index.html): three.js from npm (pinned by
# crates/dens3r-viewer/web/package-lock.json, its licence shipped beside it) and the page's
# code, bundled by esbuild into crates/dens3r-viewer/web/dist/app.js, which the next cargo
# build puts into the binary. Nothing is fetched at run time. Skips work already done.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../crates/dens3r-viewer/web"
if ! command -v npm >/dev/null; then
  echo "build-viewer: npm not found: install Node.js 18 or later (Debian: apt-get install nodejs npm); until then dens3r's pages have no 3-D view" >&2
  exit 1
fi
if [ ! -f node_modules/.package-lock.json ] || [ package-lock.json -nt node_modules/.package-lock.json ]; then
  npm ci --no-audit --no-fund --loglevel=error
fi
if [ ! -f dist/app.js ] || [ -n "$(find src package-lock.json -newer dist/app.js -print -quit)" ]; then
  npx --no-install esbuild src/main.js --bundle --minify --format=iife --legal-comments=eof \
    --target=es2020 --outfile=dist/app.js --log-level=warning
  echo "build-viewer: $(wc -c < dist/app.js) bytes in crates/dens3r-viewer/web/dist/app.js"
fi
