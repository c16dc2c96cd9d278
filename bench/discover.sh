#!/usr/bin/env bash
#! Discovery benchmark: how long `kubectl lekiwi discover` needs to find every robot
#! of a lab, per method. The lab is N network namespaces on a bridge (10.79.0.0/24), each running
#! a real `lekiwi-agent` (status endpoint on :9477, mDNS on); a dnsmasq-format lease file lists
#! them all. Once the agents have had 15 s to start up, for each method alone (mDNS; probe of the /24; ARP sweep of the bridge; DHCP lease
#! file) it runs discover once with each window (--timeout) of 100, 200, 300, 500, 750, 1000 and
#! 1500 ms and reports how many robots it found in each, and the shortest window from which on it
#! found all N. Runs as the ignored test `discover_time_to_find_per_method` of
#! tests/tests/agents/discover_methods.rs, against the shared test control plane.
#!
#! Usage: bash bench/discover.sh [options]
#!   --robots N   robots in the lab (default 50; at most 200)
#!   -h, --help   this text
#!
#! Needs root (network namespaces, the ARP sweep's raw socket). Writes the table to
#! bench/results/discover-<date>.txt and bench/results/discover-latest.txt. Takes about a minute
#! once built; the lab is removed when the test ends.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
RESULTS="$ROOT/bench/results"
ROBOTS=50
COMMAND="bash bench/discover.sh $*"

# shellcheck source=bench/lib.sh
source "$ROOT/bench/lib.sh"

while [ $# -gt 0 ]; do
  case "$1" in
    --robots)
      [[ "${2:-}" =~ ^[1-9][0-9]*$ ]] && [ "$2" -le 200 ] || die "--robots needs a count from 1 to 200"
      ROBOTS="$2"; shift 2 ;;
    -h|--help) usage; exit 0 ;;
    *) usage >&2; die "unknown option: $1" ;;
  esac
done
[ "$(id -u)" = 0 ] || die "needs root: network namespaces and a raw socket for the ARP sweep"
command -v ip >/dev/null || die "needs ip (iproute2)"

cd "$ROOT"
export LEKIWI_CP_DIR="${LEKIWI_CP_DIR:-$HOME/.cache/lekiwi/test-control-plane}"
log "shared test control plane"
bash scripts/testbed/control-plane.sh up >&2
eval "$(bash scripts/testbed/control-plane.sh env)"
log "building"
cargo build --workspace --bins >&2
OUT="$ROOT/target/test-logs/discover-bench.log"
mkdir -p "$(dirname "$OUT")"
log "discovering $ROBOTS robots by each method"
LEKIWI_DISCOVER_ROBOTS="$ROBOTS" cargo test -p lekiwi-tests --test agents -- \
  --ignored --exact discover_methods::discover_time_to_find_per_method --nocapture >"$OUT" \
  || die "the benchmark test failed (its output: $OUT)"
grep -q '^| mdns' "$OUT" || die "no table in the test's output (skipped? see above)"

mkdir -p "$RESULTS"
STAMP="$(date -u +%Y%m%d-%H%M%S)"
{
  echo "# $COMMAND, $(date -u +%FT%TZ), $(nproc) cores, load average $(cut -d' ' -f1-3 /proc/loadavg), debug build"
  echo "# agents: real lekiwi-agent processes, one per network namespace"
  grep '^|' "$OUT"
} | tee "$RESULTS/discover-$STAMP.txt" >"$RESULTS/discover-latest.txt"
cat "$RESULTS/discover-latest.txt"
