#!/usr/bin/env bash
# Installs the benchmark peers from PyPI into .cache/bench-venv (git-ignored): torch,
# safetensors, numpy (backbone), open3d 0.20 and pillow (fusion, and the mesh-file cross-check
# in the tests). Open3D's wheel needs libusb from Debian. COLMAP 3.8 (Debian `colmap`) is the
# peer of `bench sfm`. Then:
#   target/release/dens3r bench backbone
#   target/release/dens3r bench fusion
#   target/release/dens3r bench sfm     (after scripts/fetch-data.sh: scanned meshes, photos)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0.so.0; then
    if [ "$(id -u)" = 0 ]; then
        apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null
    else
        echo "note: install Debian's libusb-1.0-0 for open3d (sudo apt-get install libusb-1.0-0)" >&2
    fi
fi
if ! command -v colmap >/dev/null 2>&1; then
    if [ "$(id -u)" = 0 ]; then
        apt-get update -qq && apt-get install -y -qq colmap >/dev/null
    else
        echo "note: install Debian's colmap for bench sfm (sudo apt-get install colmap)" >&2
    fi
fi
python3 -m venv .cache/bench-venv
.cache/bench-venv/bin/pip install -q torch safetensors numpy "open3d==0.20.*" pillow pycolmap
.cache/bench-venv/bin/python3 -c "import torch, open3d; print('torch', torch.__version__, 'open3d', open3d.__version__)"
