#!/usr/bin/env bash
# The main job on the bundled data-samples/: build, render fuse-ready scenes from the bundled
# ground truth, inspect them, and evaluate. Outputs go to ${1:-out}/.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
out="${1:-out}"
cargo build --release -p dens3r-cli
bin=target/release/dens3r
set -x
# The bundled scenes are valid scene folders.
$bin info data-samples/orbit
# Render the bundled object mesh along an orbit, and a procedural room along a walk (640x480, 30 views).
$bin render --mesh data-samples/orbit/gt_mesh.ply --views 30 -o "$out/orbit"
$bin render --procedural room --views 30 -o "$out/room"
$bin info "$out/room"
# Normals derived from the rendered depth against the rendered normals (angles in degrees).
$bin eval normals --from-depth "$out/orbit" "$out/orbit"
$bin eval normals --from-depth "$out/room" "$out/room"
# Depth of the bundled scene against itself, scale-aligned (a prediction goes first).
$bin eval depth --align median data-samples/room data-samples/room
# The re-rendered ground-truth mesh against the bundled one: Chamfer 0, F-score 1.
$bin eval mesh "$out/orbit/gt_mesh.ply" data-samples/orbit/gt_mesh.ply --threshold 0.01
# Meshes of the bundled orbit: TSDF fusion, and a short neural-SDF run (300 iterations), each
# against the ground truth.
$bin fuse data-samples/orbit -o "$out/orbit_tsdf.ply" --voxel 0.02
$bin eval mesh "$out/orbit_tsdf.ply" data-samples/orbit/gt_mesh.ply
$bin nsdf data-samples/orbit -o "$out/orbit_nsdf.ply" --iters 300 --voxel 0.02 --restart
$bin eval mesh "$out/orbit_nsdf.ply" data-samples/orbit/gt_mesh.ply
# The backbone: parity with the official PyTorch code on a dumped case (bundled in
# tests/fixtures/), then predict on the bundled room images. The parity fixture holds a tiny
# random-weight model: the predictions exercise the pipeline only. With real weights:
# --weights dens3r.safetensors --size 512.
fixture=tests/fixtures/parity/A_shared_dec_48x64
$bin verify "$fixture"
$bin predict --weights "$fixture/weights.safetensors" --config "$fixture/config.json" --size 160 \
  data-samples/room/images/0000.png data-samples/room/images/0004.png -o "$out/predict"
$bin info "$out/predict"
