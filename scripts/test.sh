#!/usr/bin/env bash
# The test command: sets up what is missing, then runs the whole test suite.
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$repo/scripts/setup.sh"
# The browser viewer, which the browser test opens in headless Chromium.
bash "$repo/scripts/build-web.sh"
cd "$repo"
# Incremental caches only pay off on rebuilds and cost gigabytes on a clean clone.
export CARGO_INCREMENTAL="${CARGO_INCREMENTAL:-0}"
# Property tests draw their cases from a fixed seed, so a run is reproducible and a
# failure can be replayed; set PROPTEST_RNG_SEED to another number to explore new cases
# (failures are saved in the *.proptest-regressions files beside the tests).
export PROPTEST_RNG_SEED="${PROPTEST_RNG_SEED:-20261123}"
cargo test --workspace --locked
