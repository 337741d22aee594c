#!/usr/bin/env bash
# The test command: fetch real test material (cached; tests say so when it is absent), then
# run every test of the workspace.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
bash scripts/fetch-data.sh || echo "warning: some test data could not be fetched; the tests that need it will say so"
cargo test --workspace --locked
