#!/usr/bin/env bash
#! The agent on an emulated Raspberry Pi 5, next to prometheus-node-exporter: boots the Debian
#! arm64 root filesystem of `scripts/testbed/pi.sh rootfs` (systemd as PID 1; prometheus-node-exporter
#! installed and started by its own package), installs our arm64 .deb (`scripts/deb.sh`) with
#! `dpkg -i` and starts lekiwi-agent.service with its DEFAULT settings (only the gateway, its CA,
#! the enrollment token and the robot's name set) against the operator (`--role all`, defaults:
#! 30 s heartbeats) on the host over wss://, with a private control plane. The host scrapes
#! node-exporter's /metrics every 15 s through a forwarded port, as a Prometheus would.
#!
#! Inside the guest a script reads utime+stime (/proc/PID/stat) and VmRSS of both services every
#! 10 s and prints them on the serial console; the window starts at the first reading after the
#! Robot is Online and lasts --minutes. Prints one table: CPU seconds per hour of each over the
#! window, their ratio, RSS of each at the end, and boot-to-Online (QEMU's start to the Robot's
#! phase Online: kernel, systemd, dpkg -i, enable, enrollment). Emulated CPU time is not a Pi's
#! (QEMU's TCG): compare the two as a ratio only.
#!
#! Usage: bash bench/pi.sh [options]
#!   --minutes N    length of the window (default 10)
#!   --no-build     use the operator as it is (the .deb and the root filesystem are built or
#!                  taken from the cache either way)
#!   --operator P   the operator binary (default: the release build in $CARGO_TARGET_DIR or
#!                  target/; its build does not change the guest's figures)
#!   --deb PATH     install this arm64 .deb instead of building one with scripts/deb.sh
#!   --keep         keep the work directory (console log, operator log, scrapes)
#!   -h, --help     this text
#!
#! Writes the table to bench/results/pi-<date>.txt and bench/results/pi-latest.txt. Takes
#! --minutes plus about 3 minutes once built (the root filesystem's first build: a few minutes
#! more); cleans up on exit, failure and Ctrl-C; shares the lock of the other benchmarks.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
OPERATOR="${CARGO_TARGET_DIR:-$ROOT/target}/release/lekiwi-operator"
RESULTS="$ROOT/bench/results"
MINUTES=10
DEB=""
BUILD=1
KEEP=0
COMMAND="bash bench/pi.sh $*"
SCRAPE_EVERY=15

# shellcheck source=bench/lib.sh
source "$ROOT/bench/lib.sh"

while [ $# -gt 0 ]; do
  case "$1" in
    --minutes) positive_int "$1" "${2:-}"; MINUTES="$2"; shift 2 ;;
    --no-build) BUILD=0; shift ;;
    --operator) OPERATOR="$(realpath "$2")"; BUILD=0; shift 2 ;;
    --deb) DEB="$(realpath "$2")"; shift 2 ;;
    --keep) KEEP=1; shift ;;
    -h | --help) usage; exit 0 ;;
    *) usage >&2; die "unknown option: $1" ;;
  esac
done

WORK="$(mktemp -d "${TMPDIR:-/tmp}/lekiwi-bench-pi.XXXXXX")"
CP_DIR="$WORK/control-plane"
CP_UP=0
PIDS=()
CLEANUP_GRACE=2
trap_cleanup
take_bench_lock
log "work directory: $WORK"

# ---- builds: the operator (x86_64), the arm64 .deb, the root filesystem ----------------------
if [ $BUILD = 1 ]; then
  log "building the operator (release)"
  (cd "$ROOT" && cargo build --release -p lekiwi-operator) >"$WORK/build.log" 2>&1 \
    || { tail -30 "$WORK/build.log" >&2; die "build failed"; }
fi
[ -x "$OPERATOR" ] || die "$OPERATOR is missing (run without --no-build)"
log "the arm64 .deb (scripts/deb.sh) and the root filesystem (scripts/testbed/pi.sh rootfs)"
[ -n "$DEB" ] || DEB="$(bash "$ROOT/scripts/deb.sh" --arch arm64 --out "$WORK/deb" 2>"$WORK/deb.log" | tail -1)" \
  || { tail -20 "$WORK/deb.log" >&2; die "scripts/deb.sh failed"; }
[ -f "$DEB" ] || die "no .deb at $DEB"
bash "$ROOT/scripts/testbed/pi.sh" rootfs 2>"$WORK/rootfs.log" || { tail -20 "$WORK/rootfs.log" >&2; die "pi.sh rootfs failed"; }

fact date "$(date -Is)"
fact host "$(nproc) CPUs ($(awk -F': ' '/^model name/ { print $2; exit }' /proc/cpuinfo)), kernel $(uname -r), load average at start $(cut -d' ' -f1-3 /proc/loadavg)"
fact_source
fact command "$COMMAND"
fact deb "$(basename "$DEB") ($(du -k "$DEB" | cut -f1) kB)"
fact minutes "$MINUTES"
fact operator "$OPERATOR"

# ---- control plane, a CA for 10.0.2.2 (the host as the guest sees it), the operator ------------
start_control_plane
NS=bench
ROBOT=kiwi-pi
kubectl create namespace lekiwi-system >/dev/null
kubectl create namespace "$NS" >/dev/null
PAYLOAD="$WORK/payload"
mkdir -p "$PAYLOAD"
enrollment_token "$NS" "$PAYLOAD/enroll"
(
  cd "$WORK"
  printf 'subjectAltName=IP:127.0.0.1,IP:10.0.2.2\nbasicConstraints=CA:FALSE\n' >ext
  openssl req -x509 -newkey rsa:2048 -nodes -days 1 -subj /CN=lekiwi-bench-ca -keyout ca.key -out ca.crt
  openssl req -newkey rsa:2048 -nodes -subj /CN=lekiwi-gateway -keyout tls.key -out tls.csr
  openssl x509 -req -in tls.csr -CA ca.crt -CAkey ca.key -CAcreateserial -days 1 -extfile ext -out tls.crt
) >"$WORK/ca.log" 2>&1 || die "making the CA failed: $(tail -5 "$WORK/ca.log")"
cp "$WORK/ca.crt" "$PAYLOAD/ca.crt"

HTTP_PORT="$(free_port)"
GW_PORT="$(free_port)"
log "starting the operator (--role all, defaults; gateway wss :$GW_PORT)"
start operator "$OPERATOR" --role all --kubeconfig "$KUBECONFIG" \
  --namespace lekiwi-system --identity bench-operator --gateway-name bench-gateway \
  --gateway-addr "127.0.0.1:$GW_PORT" --http-addr "127.0.0.1:$HTTP_PORT" \
  --store-url "sqlite://$WORK/events.db" --tls-cert "$WORK/tls.crt" --tls-key "$WORK/tls.key"
OP_PID=$LAST_PID
operator_ready() {
  alive "$OP_PID" || die "operator exited: $(tail -5 "$WORK/operator.log")"
  curl -fsS --max-time 2 "http://127.0.0.1:$HTTP_PORT/readyz" >/dev/null 2>&1
}
wait_for operator 60 operator_ready

# ---- the guest ------------------------------------------------------------------------------
cp "$DEB" "$PAYLOAD/lekiwi-agent.deb"
cat >"$PAYLOAD/agent.yaml" <<EOF
gateway: wss://10.0.2.2:$GW_PORT/v1/agent
caFile: /etc/lekiwi/ca.crt
enrollmentTokenFile: /etc/lekiwi/enroll
robotName: $NS/$ROBOT
EOF
# At the first boot: install and start the agent. Then every 10 s, with shell builtins only (no
# process the readings would have to leave out): uptime, then utime+stime ticks, VmRSS kB and
# start tick of the agent, then of node-exporter.
cat >"$PAYLOAD/run.sh" <<'EOF'
[ -n "${BASH_VERSION:-}" ] || exec /bin/bash "$0" "$@"
P=/payload
dpkg -i "$P/lekiwi-agent.deb" >/dev/null && echo "LEKIWI-DPKG ok"
install -m 0644 "$P/agent.yaml" /etc/lekiwi/agent.yaml
install -m 0644 "$P/ca.crt" /etc/lekiwi/ca.crt
install -m 0600 "$P/enroll" /etc/lekiwi/enroll
systemctl enable --now lekiwi-agent 2>/dev/null && echo "LEKIWI-ENABLED"
pid_of() { systemctl show -p MainPID --value "$1"; }
fig() { # pid
  local st k v rss=-
  [ "$1" != 0 ] && read -r -a st <"/proc/$1/stat" 2>/dev/null || { echo "- - -"; return; }
  while read -r k v _; do [ "$k" = VmRSS: ] && rss=$v; done <"/proc/$1/status"
  echo "$((st[13] + st[14])) $rss ${st[21]}"
}
a=0 n=0
while :; do
  [ -d "/proc/$a" ] && [ "$a" != 0 ] || a="$(pid_of lekiwi-agent)"
  [ -d "/proc/$n" ] && [ "$n" != 0 ] || n="$(pid_of prometheus-node-exporter)"
  read -r up _ </proc/uptime
  echo "LEKIWI-FIG $up $a $(fig "$a") $n $(fig "$n")"
  sleep 10
done
EOF

NE_PORT="$(free_port)"
log "booting the emulated Pi 5 (node-exporter forwarded to 127.0.0.1:$NE_PORT)"
T0="$(now)"
start guest env LEKIWI_PI_RUN="$WORK/pi" bash "$ROOT/scripts/testbed/pi.sh" boot --rootfs --foreground \
  --name bench-pi --memory 768 --payload "$PAYLOAD" --forward "$NE_PORT:9100"
GUEST_PID=$LAST_PID
CONSOLE="$WORK/pi/bench-pi/console.log"
online() {
  alive "$GUEST_PID" || die "the guest stopped: $(tail -20 "$CONSOLE" 2>/dev/null)"
  [ "$(kubectl -n "$NS" get robot "$ROBOT" -o jsonpath='{.status.phase}' 2>/dev/null)" = Online ]
}
wait_for "Robot $NS/$ROBOT Online" 600 online
fact boot_to_online "$(elapsed "$T0")"
grep -q "LEKIWI-DPKG ok" "$CONSOLE" || die "dpkg -i did not succeed: $(tail -20 "$CONSOLE")"
log "Online after $(elapsed "$T0") s; window of $MINUTES min from the next reading"

# The window: from the first reading after Online to the first one --minutes later, scraping
# node-exporter every 15 s meanwhile.
figs() { sed 's/\r$//' "$CONSOLE" | grep -a '^LEKIWI-FIG ' || true; }
seen="$(figs | wc -l)"
wait_for "a reading" 60 bash -c "[ \$(sed 's/\r\$//' '$CONSOLE' | grep -ac '^LEKIWI-FIG ') -gt $seen ]"
FIRST="$(figs | tail -1)"
first_up="$(echo "$FIRST" | cut -d' ' -f2)"
scrapes=0 failed=0
until [ "$(figs | tail -1 | awk -v u="$first_up" -v m="$MINUTES" '{ print ($2 - u >= m * 60) }')" = 1 ]; do
  alive "$GUEST_PID" || die "the guest stopped: $(tail -20 "$CONSOLE")"
  if curl -fsS --max-time 10 "http://127.0.0.1:$NE_PORT/metrics" -o "$WORK/node-exporter-metrics.txt"; then
    scrapes=$((scrapes + 1))
  else
    failed=$((failed + 1))
  fi
  sleep "$SCRAPE_EVERY"
done
LAST="$(figs | tail -1)"
fact first "$FIRST"
fact last "$LAST"
fact scrapes "$scrapes ok, $failed failed, $(stat -c %s "$WORK/node-exporter-metrics.txt" 2>/dev/null || echo 0) bytes each"
fact robot_phase "$(kubectl -n "$NS" get robot "$ROBOT" -o jsonpath='{.status.phase}' 2>/dev/null || echo '?')"
fact kernel "$(cut -d' ' -f2 "${LEKIWI_CACHE:-$HOME/.cache/lekiwi}/pi/base.stamp" 2>/dev/null || echo '?')"

# ---- report ---------------------------------------------------------------------------------
mkdir -p "$RESULTS"
STAMP="$(date +%Y%m%d-%H%M%S)"
python3 - "$WORK/facts.env" >"$WORK/table.txt" <<'PY'
import sys
f = dict(l.rstrip("\n").split("=", 1) for l in open(sys.argv[1]) if "=" in l)
first, last = f["first"].split(), f["last"].split()
window = float(last[1]) - float(first[1])
def proc(i):  # fields of one service on a LEKIWI-FIG line: pid ticks rss start
    return {"pid": last[i], "cpu": (int(last[i + 1]) - int(first[i + 1])) / 100, "rss": int(last[i + 2]),
            "same": first[i] == last[i]}
a, n = proc(2), proc(6)
per_h = lambda p: p["cpu"] / window * 3600
print(f"LeKiwi agent on an emulated Raspberry Pi 5, {f['date']}")
print(f"host: {f['host']}")
print(f"source: {f['source']}")
print(f"command: {f['command']}")
print("guest: QEMU virt, 2 x Cortex-A76 (TCG), 768 MB, Debian bookworm arm64 root filesystem of "
      f"scripts/testbed/pi.sh rootfs with systemd, kernel {f['kernel']}")
print(f"agent: {f['deb']} installed with dpkg -i, lekiwi-agent.service, default settings "
      "(gateway, CA, enrollment token and robot name set); the operator --role all on the host, "
      f"defaults (heartbeat 30 s), over wss:// ({f['operator']})")
print("reference: prometheus-node-exporter (Debian bookworm arm64) as its package starts it, "
      f"/metrics scraped every 15 s from the host: {f['scrapes']}")
print(f"window: {window:.0f} s (guest uptime {float(first[1]):.0f} to {float(last[1]):.0f} s) from the "
      "first reading after Online; CPU = utime + stime, 100 ticks/s; emulated CPU time: compare as a ratio")
print()
print(f"{'':40}{'agent':>16}{'node-exporter':>18}")
print(f"{'CPU per hour':40}{per_h(a):>14.1f} s{per_h(n):>16.1f} s")
print(f"{'CPU in the window':40}{a['cpu']:>14.2f} s{n['cpu']:>16.2f} s")
print(f"{'CPU ratio agent / node-exporter':40}{per_h(a) / max(per_h(n), 1e-9):>15.2f}x")
print(f"{'RSS at the end (MB = 10^6 bytes)':40}{a['rss'] * 1024 / 1e6:>13.2f} MB{n['rss'] * 1024 / 1e6:>15.2f} MB")
print(f"{'RSS ratio agent / node-exporter':40}{a['rss'] / max(n['rss'], 1):>15.2f}x")
print(f"{'same process all along':40}{str(a['same']):>16}{str(n['same']):>18}")
print(f"{'boot to Online (QEMU start to Robot Online)':44}{float(f['boot_to_online']):>10.1f} s")
print(f"{'Robot phase at the end':40}{f['robot_phase']:>16}")
PY
cp "$WORK/table.txt" "$RESULTS/pi-$STAMP.txt"
cp "$WORK/table.txt" "$RESULTS/pi-latest.txt"
echo
cat "$WORK/table.txt"
echo
log "written to bench/results/pi-$STAMP.txt and bench/results/pi-latest.txt"
