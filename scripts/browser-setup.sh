#!/usr/bin/env bash
# Headless Chromium for the page test (Debian's `chromium`), installed when missing, and the
# viewer's npm packages (playwright-core drives it). Exit status 0 only when both are ready.
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
chromium="${CHROMIUM:-/usr/bin/chromium}"
if [ ! -x "$chromium" ]; then
  if command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
    apt-get install -y -qq chromium >/dev/null 2>&1 || { apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq chromium >/dev/null 2>&1; }
  fi
fi
if [ ! -x "$chromium" ]; then
  echo "browser-setup: no Chromium at $chromium (Debian: apt-get install chromium, or set CHROMIUM); the page test will skip" >&2
  exit 1
fi
bash scripts/build-viewer.sh || exit 1
echo "browser-setup: $("$chromium" --version 2>/dev/null | head -1)"
