#!/usr/bin/env bash
# The test command: fetch real test material (cached; tests say so when it is absent), then
# run every test of the workspace.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
bash scripts/fetch-data.sh || echo "warning: some test data could not be fetched; the tests that need it will say so"
# GPU tests (wgpu) run on any Vulkan driver, lavapipe included: with one present they must run,
# not skip.
if bash scripts/gpu-setup.sh; then
  export DENS3R_REQUIRE_GPU="${DENS3R_REQUIRE_GPU:-1}"
fi
# The pages' 3-D viewer (three.js from npm) goes into the build; headless Chromium opens a
# reconstruction's page in the CLI's tests: with both ready, that test must run, not skip.
if bash scripts/browser-setup.sh; then
  export DENS3R_REQUIRE_BROWSER="${DENS3R_REQUIRE_BROWSER:-1}"
else
  bash scripts/build-viewer.sh || echo "warning: the viewer was not bundled; pages will have no 3-D view"
fi
cargo test --workspace --locked
# The Python package (python/): its extension linked from the same test build, then pytest.
bash scripts/python-test.sh
