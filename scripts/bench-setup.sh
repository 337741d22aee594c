#!/usr/bin/env bash
# Installs the benchmark peers from PyPI into .cache/bench-venv (git-ignored): torch,
# safetensors, numpy. Then: target/release/dens3r bench backbone
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
python3 -m venv .cache/bench-venv
.cache/bench-venv/bin/pip install -q torch safetensors numpy
.cache/bench-venv/bin/python3 -c "import torch; print('torch', torch.__version__)"
