#!/usr/bin/env bash
#! Runs the whole test suite: installs what is missing (scripts/setup.sh test), checks formatting
#! and lints, builds, starts the shared local control plane and runs every unit and integration
#! test with nextest. Among them: the book under docs/ is built with mdBook and its internal links
#! checked, the generated reference pages compared with the code, and the tour run against a
#! quickstart of its own.
set -euo pipefail
cd "$(dirname "$0")/.."

log() { printf '\033[1;34m[test]\033[0m %s\n' "$*" >&2; }
start=$(date +%s)

bash scripts/setup.sh test
# cargo-nextest and mdbook, built by setup.sh from crates.io.
export PATH="${LEKIWI_CACHE:-$HOME/.cache/lekiwi}/cargo-tools/bin:$PATH"
log "cargo fmt --check"
cargo fmt --all -- --check
log "cargo clippy --all-targets -- -D warnings"
cargo clippy --quiet --workspace --all-targets -- -D warnings
log "code shape: no fn over 80 lines, no module over 400 without a written reason"
python3 scripts/checks/shape.py --check
log "building binaries"
cargo build --quiet --workspace --bins
# The operator image for amd64 and arm64 (cached in ~/.cache/lekiwi/image-target and
# image-target-arm64) before the tests, so no test waits minutes for it while others run on
# its timers.
# The arm64 binary with Cargo.toml's image-check profile (it says why); image.sh alone: release.
export LEKIWI_IMAGE_ARM64_PROFILE="${LEKIWI_IMAGE_ARM64_PROFILE:-image-check}"
log "building the operator image (arm64: profile $LEKIWI_IMAGE_ARM64_PROFILE)"
bash scripts/image.sh >/dev/null
# The tests' own control plane, apart from the quickstart's (whose operator watches everything).
export LEKIWI_CP_DIR="${LEKIWI_CP_DIR:-${LEKIWI_CACHE:-$HOME/.cache/lekiwi}/test-control-plane}"
log "starting the shared control plane ($LEKIWI_CP_DIR)"
bash scripts/testbed/control-plane.sh up
eval "$(bash scripts/testbed/control-plane.sh env)"

log "running tests"
# A failing test ends its output with its own message (a cluster.sh failure prints the script's
# log there), not with pages of stack frames that push the message out of CI's excerpt. Set
# LEKIWI_TEST_BACKTRACE=1 for frames.
export RUST_BACKTRACE="${LEKIWI_TEST_BACKTRACE:-0}" RUST_LIB_BACKTRACE=0
# Tests that keep the CPU busy for long (emulated Pis, a whole cluster with Pods, image builds)
# run after the others, one at a time, so they never starve the timing of the rest.
HEAVY='binary_id(lekiwi-tests::testbed)'
if cargo nextest --version >/dev/null 2>&1; then
  if [ $# -gt 0 ]; then
    cargo nextest run --workspace --no-fail-fast "$@"
  else
    rc=0
    cargo nextest run --workspace --no-fail-fast -E "not ($HEAVY)" || rc=$?
    log "heavy tests, one at a time"
    cargo nextest run --workspace --no-fail-fast --test-threads 1 -E "$HEAVY" || rc=$?
    [ $rc = 0 ] || { log "tests failed"; exit $rc; }
  fi
else
  log "cargo-nextest not found; falling back to cargo test"
  cargo test --workspace --no-fail-fast "$@"
fi
log "all tests passed in $(( $(date +%s) - start ))s"
