#!/usr/bin/env bash
# The Python package's tests (python/tests, pytest): links the `dens3r._native` extension from
# the test build that `cargo test --workspace` leaves (same profile and features, so only the
# extension itself is linked), stages it beside python/dens3r/ in target/python/, and runs pytest
# in .cache/py-venv (numpy, pytest, tqdm and Ray from PyPI). Users install with `pip install ./python`.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
cargo build --workspace --profile test --locked
stage=target/python
rm -rf "$stage" && mkdir -p "$stage/dens3r"
cp python/dens3r/*.py "$stage/dens3r/"
cp target/debug/lib_native.so "$stage/dens3r/_native.abi3.so"
venv=.cache/py-venv
if ! "$venv/bin/python" -c "import numpy, pytest, tqdm" 2>/dev/null; then
  python3 -m venv "$venv"
  "$venv/bin/pip" install -q numpy pytest tqdm
fi
# Ray (PyPI) for the executor test's local cluster; without it that test says so and skips.
if ! "$venv/bin/python" -c "import ray" 2>/dev/null; then
  "$venv/bin/pip" install -q "ray>=2.9" || echo "warning: Ray could not be installed; the Ray executor test will skip"
fi
# The CLI of the same build: the tests compare the module's arrays with its outputs.
export DENS3R_BIN="$PWD/target/debug/dens3r"
PYTHONPATH="$PWD/$stage" "$venv/bin/python" -m pytest -q python/tests "$@"
