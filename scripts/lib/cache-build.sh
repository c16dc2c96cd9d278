#!/usr/bin/env bash
#! Sourced by the scripts that build into a cache shared across checkouts and callers
#! (scripts/image.sh, scripts/testbed/pi.sh), so that a build is incremental and the same whoever starts it:
#!   src_copy DEST   mirrors this checkout's sources (tracked and untracked, not ignored, no .git or
#!                   target) to DEST, copying only files whose content changed. Building in the
#!                   checkout itself would rebuild everything whenever its path changes (a fresh CI
#!                   clone, a worktree: the path is in --remap-path-prefix and in the crates' package
#!                   ids) and bake that path into test binaries.
#!   clean_env       sets CLEAN_ENV to the `env -u` arguments that drop what a calling cargo or test
#!                   runner exports (CARGO_*, RUSTUP_*, RUSTC*, RUSTFLAGS, ...): ring's build script
#!                   reruns when those change, so a build started from `cargo test` would otherwise
#!                   undo the cache of one started by hand, and the other way round.

src_copy() {
  local repo dest="$1"
  repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
  mkdir -p "$dest"
  rsync -rlc --delete --exclude=/.git --exclude=/target --filter=':- .gitignore' "$repo/" "$dest/"
}

clean_env() {
  CLEAN_ENV=()
  local v
  for v in $(compgen -e); do
    case "$v" in
      CARGO_HOME) ;;
      CARGO_* | RUSTUP_* | RUSTC* | RUSTDOC* | RUSTFLAGS | OUT_DIR | RUST_RECURSION_COUNT) CLEAN_ENV+=(-u "$v") ;;
    esac
  done
}
