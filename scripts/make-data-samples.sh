#!/usr/bin/env bash
# Regenerates data-samples/ (deterministic: same seeds, same files). Small on purpose:
# 160x120 images, 8 views per scene, a few MB in all.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
cargo build --release -q -p dens3r-cli
bin=target/release/dens3r
rm -rf data-samples/orbit data-samples/room
$bin render --procedural blob --seed 0 --views 8 --width 160 --height 120 -o data-samples/orbit
$bin render --procedural room --seed 0 --views 8 --width 160 --height 120 -o data-samples/room
du -sh data-samples/*
