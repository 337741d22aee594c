#!/usr/bin/env bash
# Reproduces a segmentation row of the docs/heads.md's "Heads on scenes they never saw": a DPT head and
# the linear probe, trained the same way on DINOv2-S features of ROOMS rendered rooms for EPOCHS
# epochs, scored on rooms never trained on (seed 97001, 64 rooms; seeds 95001 + 96001, 32 rooms,
# as the second check). Rooms: `dens3r synth --kind rooms --size 320x240 --views 6`, training
# seeds 5001 (100 rooms), 5002 (200 more), 5003 (700 more) and 5004 (1000 more).
# Every part resumes: rerun after an interruption and it continues where it stopped (synth keeps
# finished scenes, the feature cache keeps computed features, train-head resumes from its
# checkpoint). Work goes to $DENS3R_HEADS_DIR (default .cache/heads, git-ignored): about 2 GB
# per 100 rooms with their features. Both heads read the same feature cache.
#
#   bash scripts/heads-rooms.sh                      # 2000 rooms, 4 epochs (about 2 hours on 2 CPU cores, both heads at once)
#   ROOMS=1000 EPOCHS=6 bash scripts/heads-rooms.sh  # another row: ROOMS = 100, 300, 1000 or 2000
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
start=$(date +%s)
rooms="${ROOMS:-2000}"
epochs="${EPOCHS:-4}"
case "$rooms" in
  100) n=1 ;; 300) n=2 ;; 1000) n=3 ;; 2000) n=4 ;;
  *) echo "heads-rooms: ROOMS must be 100, 300, 1000 or 2000 (got $rooms)" >&2; exit 2 ;;
esac

cargo build --release --locked -p dens3r-cli
bash scripts/fetch-data.sh
B="$PWD/target/release/dens3r"
onnx="$PWD/.cache/data/dinov2/vit_s_focus.onnx"
if [ ! -f "$onnx" ]; then
  echo "heads-rooms: $onnx is missing; run bash scripts/fetch-data.sh (it needs PyPI)" >&2
  exit 1
fi
export DENS3R_DATA="${DENS3R_DATA:-$PWD/.cache/data}"
work="${DENS3R_HEADS_DIR:-.cache/heads}"
mkdir -p "$work/runs"
cd "$work"

S=(synth --kind rooms --size 320x240 --views 6)
seeds=(5001 5002 5003 5004)
counts=(100 200 700 1000)
sets=()
for i in $(seq 0 $((n - 1))); do
  $B "${S[@]}" --scenes "${counts[$i]}" --seed "${seeds[$i]}" -o "s${seeds[$i]}"
  sets+=("s${seeds[$i]}")
done
$B "${S[@]}" --scenes 64 --seed 97001 -o held64
$B "${S[@]}" --scenes 16 --seed 95001 -o val
$B "${S[@]}" --scenes 16 --seed 96001 -o test

# The two heads side by side: the linear probe's small steps fill the cores the DPT leaves idle.
T=(train-head --backbone "dinov2:$onnx" --kind seg --data "${sets[@]}" --val held64 --epochs "$epochs"
  --balance --cache feat-dino)
dpt="runs/clip-dpt-$rooms-ep$epochs"
lin="runs/clip-lin-$rooms-ep$epochs"
pids=()
[ -f "$dpt.json" ] || { $B "${T[@]}" --head dpt -o "$dpt" > "$dpt.log" 2>&1 & pids+=($!); }
# The linear probe starts once the DPT's run has every feature in the cache (it says how many
# training images it has then), so the two never compute the same features.
if [ ! -f "$lin.json" ]; then
  while [ ${#pids[@]} -gt 0 ] && kill -0 "${pids[0]}" 2>/dev/null && ! grep -q " training / " "$dpt.log"; do
    sleep 10
  done
  $B "${T[@]}" --head linear -o "$lin" > "$lin.log" 2>&1 & pids+=($!)
fi
for p in "${pids[@]}"; do
  wait "$p" || { echo "heads-rooms: a training run failed; its log:" >&2; tail -n 3 "$dpt.log" "$lin.log" >&2; exit 1; }
done

miou() { $B eval head "$1.json" --backbone "dinov2:$onnx" --data "${@:2}" --cache feat-dino --json | grep -o '"miou":[0-9.]*' | cut -d: -f2; }
l1=$(miou "$lin" held64); d1=$(miou "$dpt" held64)
l2=$(miou "$lin" val test); d2=$(miou "$dpt" val test)
python3 - "$rooms" "$epochs" "$l1" "$d1" "$l2" "$d2" <<'EOF'
import sys
rooms, epochs, l1, d1, l2, d2 = sys.argv[1], sys.argv[2], *map(float, sys.argv[3:])
print(f"{rooms} rooms, {epochs} epochs, held-out mIoU (last epoch's heads):")
print(f"  64 rooms (seed 97001):  linear {l1:.3f}  DPT {d1:.3f}  DPT - linear {d1 - l1:+.3f}")
print(f"  32 rooms (95001+96001): linear {l2:.3f}  DPT {d2:.3f}  DPT - linear {d2 - l2:+.3f}")
EOF
echo "wall time: $(( ($(date +%s) - start) / 60 )) min"
