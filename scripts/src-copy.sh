#!/usr/bin/env bash
#! Sourced by the scripts that build into a cache shared across checkouts (scripts/image.sh,
#! scripts/pi.sh): `src_copy DEST` mirrors this checkout's sources (tracked and untracked, not
#! ignored, no .git or target) to DEST, copying only files whose content changed. A build from a
#! fixed DEST is incremental whichever path the checkout is at (a fresh CI clone, a worktree),
#! where building in the checkout itself would rebuild everything when its path changes (the path
#! is in --remap-path-prefix and in the crates' package ids) and bake that path into test binaries.

src_copy() {
  local repo dest="$1"
  repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
  mkdir -p "$dest"
  rsync -rlc --delete --exclude=/.git --exclude=/target --filter=':- .gitignore' "$repo/" "$dest/"
}
