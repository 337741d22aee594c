#!/usr/bin/env bash
# Regenerates docs/cli.md (the full command-line reference) from the commands' own help;
# crates/dens3r-cli/tests/cli.rs fails when it is out of date.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
cargo run --release --quiet --bin dens3r -- cli-reference > docs/cli.md.tmp
mv docs/cli.md.tmp docs/cli.md
echo "docs/cli.md: $(wc -l < docs/cli.md) lines"
