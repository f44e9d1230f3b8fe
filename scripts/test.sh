#!/usr/bin/env bash
# The test command: sets up what is missing, then runs the whole test suite.
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$repo/scripts/setup.sh"
cd "$repo"
cargo test --workspace --locked
