#!/usr/bin/env bash
#! Runs the property tests (frame decoder, manifest parser, status rules, status mapping against the
#! CRD schema) with many cases: at least --cases in total (default 1000000), split evenly over the
#! properties, each bounded by --timeout seconds (default 900). Prints a table (property, cases,
#! time, failures) and writes it to bench/results/fuzz-latest.txt. Needs no cluster.
#!
#! Usage: bench/fuzz.sh [--cases N] [--timeout SECONDS] [--profile release|dev]
#!
#! CI runs the same properties with proptest's default (256 cases each) as ordinary tests.
set -euo pipefail

ROOT="$(cd "$(dirname "$0")/.." && pwd)"
# shellcheck source=bench/lib.sh
source "$ROOT/bench/lib.sh"

TOTAL=1000000 TIMEOUT=900 PROFILE=release
while [ $# -gt 0 ]; do
  case "$1" in
    --cases) TOTAL="${2:?}"; shift 2 ;;
    --timeout) TIMEOUT="${2:?}"; shift 2 ;;
    --profile) PROFILE="${2:?}"; shift 2 ;;
    -h|--help) usage; exit 0 ;;
    *) die "unknown option $1 (see --help)" ;;
  esac
done
[[ "$TOTAL" =~ ^[1-9][0-9]*$ ]] || die "--cases needs a positive integer"
[[ "$TIMEOUT" =~ ^[1-9][0-9]*$ ]] || die "--timeout needs a positive integer"

# package, test target (--lib or --test NAME), test name
PROPERTIES=(
  "lekiwi-protocol|--test properties|arbitrary_text_never_panics_the_frame_decoder"
  "lekiwi-protocol|--test properties|frame_like_text_never_panics_the_frame_decoder"
  "lekiwi-protocol|--test properties|arbitrary_bytes_never_panic_the_manifest_parser"
  "lekiwi-protocol|--test properties|manifest_like_text_never_panics_the_manifest_parser"
  "lekiwi-protocol|--test properties|the_rule_checks_agree_with_the_crd_patterns"
  "lekiwi-presence|--lib|properties_tests::every_report_maps_to_a_status_the_crd_accepts"
)
PER=$(( (TOTAL + ${#PROPERTIES[@]} - 1) / ${#PROPERTIES[@]} ))

cd "$ROOT"
printf '[fuzz] building the test binaries (%s profile)\n' "$PROFILE" >&2
cargo test --profile "$PROFILE" -p lekiwi-protocol -p lekiwi-presence --no-run -q 2>&1 | tail -3 >&2

mkdir -p bench/results
OUT="bench/results/fuzz-latest.txt"
TABLE=$(mktemp)
trap 'rm -f "$TABLE"' EXIT
printf '%-70s %10s %9s %s\n' property cases seconds failures >"$TABLE"
sum=0 failed=0
for entry in "${PROPERTIES[@]}"; do
  IFS='|' read -r pkg target name <<<"$entry"
  start=$(date +%s.%N)
  # shellcheck disable=SC2086 # $target is two words on purpose
  if PROPTEST_CASES="$PER" timeout "$TIMEOUT" cargo test --profile "$PROFILE" -q -p "$pkg" $target \
      -- --exact "$name" >"$TABLE.log" 2>&1; then
    result=0
  elif [ $? -eq 124 ]; then
    result="timeout"; failed=$((failed + 1))
  else
    result=1; failed=$((failed + 1))
    grep -E 'minimal failing input|panicked' "$TABLE.log" | head -3 >&2 || true
  fi
  secs=$(echo "$(date +%s.%N) - $start" | bc)
  [ "$result" = 0 ] && sum=$((sum + PER))
  printf '%-70s %10d %9.1f %s\n' "${name##*::}" "$PER" "$secs" "$result" >>"$TABLE"
done
rm -f "$TABLE.log"
printf '%-70s %10d\n' "total (passed)" "$sum" >>"$TABLE"
{ echo "# bench/fuzz.sh $(date -u +%FT%TZ), $(git rev-parse --short HEAD 2>/dev/null || echo '?'), profile $PROFILE"; cat "$TABLE"; } | tee "$OUT"
[ "$failed" -eq 0 ]
