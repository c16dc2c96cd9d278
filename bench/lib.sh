# Shared by every benchmark driver in bench/ (sourced, never run): messages, option checks,
# the processes a benchmark starts and their cleanup, ports, waiting, the lock that
# keeps two benchmarks from running at once.
#
# The sourcing script sets ROOT, WORK, CP_DIR, KEEP, CP_UP=0 and PIDS=() first, and may set
# CLEANUP_GRACE (seconds of SIGTERM before SIGKILL at exit; 0, the default: SIGKILL at once),
# STOP_GRACE (the same for `stop`) and redefine keep_or_remove_work.

# The script's header (the `#!` lines after the shebang) as its help text.
usage() { sed -n 's/^#!\( \|$\)//p' "$0"; }
log() { printf '[bench %s] %s\n' "$(date +%T)" "$*" >&2; }
die() { log "error: $*"; exit 1; }

positive_int() { [[ "$2" =~ ^[1-9][0-9]*$ ]] || die "$1 needs a positive integer, not '$2'"; }

# ---- processes ------------------------------------------------------------------------------
# Starts "$@" in the background with its output in $WORK/<name>.log; sets LAST_PID. The lock's
# file descriptor stays with this script.
start() {
  local name="$1"; shift
  "$@" >"$WORK/$name.log" 2>&1 8>&- </dev/null &
  LAST_PID=$!
  PIDS+=("$LAST_PID")
}

# Forgets the pid of a process that has ended, so cleanup can never signal a reused pid.
forget() {
  local rest=() pid
  for pid in "${PIDS[@]}"; do [ "$pid" = "$1" ] || rest+=("$pid"); done
  PIDS=("${rest[@]}")
}

# Ends processes we started: with a grace of $1 s, SIGTERM to all first and SIGKILL to those
# still running when it is over; with none, SIGKILL at once. Reaps them.
end_processes() {
  local grace="$1" pid deadline; shift
  if [ "$grace" -gt 0 ]; then
    for pid in "$@"; do kill -TERM "$pid" 2>/dev/null; done
    deadline=$((SECONDS + grace))
    for pid in "$@"; do
      while kill -0 "$pid" 2>/dev/null && [ $SECONDS -lt $deadline ]; do sleep 0.1; done
    done
  fi
  for pid in "$@"; do
    kill -KILL "$pid" 2>/dev/null
    wait "$pid" 2>/dev/null
  done
  return 0
}

# Stops one process we started (see STOP_GRACE), reaps it and forgets it.
stop() {
  end_processes "${STOP_GRACE:-0}" "$1" || true
  forget "$1"
}

alive() { kill -0 "$1" 2>/dev/null; }

# Keeps the work directory when asked to or after a failure (for the post-mortem).
keep_or_remove_work() { # exit status
  if [ "$KEEP" = 1 ] || [ "$1" != 0 ]; then
    log "work directory kept: $WORK"
  else
    rm -rf "$WORK"
  fi
}

cleanup() {
  local rc=$?
  trap - EXIT INT TERM
  set +e
  end_processes "${CLEANUP_GRACE:-0}" "${PIDS[@]}"
  # A script's own last step (e.g. restoring a system setting it changed), if it set one.
  [ -n "${ON_EXIT:-}" ] && eval "$ON_EXIT"
  if [ "$CP_UP" = 1 ]; then
    # A kept work directory keeps the control plane's logs too (the purge removes its state).
    [ "${KEEP:-0}" = 1 ] && cp "$CP_DIR"/*.log "$WORK/" 2>/dev/null
    LEKIWI_CP_DIR="$CP_DIR" "$ROOT/scripts/testbed/control-plane.sh" down --purge >/dev/null 2>&1
  fi
  keep_or_remove_work "$rc"
  exit $rc
}

# Cleans up on exit, failure and Ctrl-C.
trap_cleanup() {
  trap cleanup EXIT
  trap 'log "interrupted"; exit 130' INT
  trap 'log "terminated"; exit 143' TERM
}

# scripts/setup.sh without its arm64 part (the cross-built agent and the emulated Pi's root
# filesystem): no x86_64 benchmark needs it, and building it cold would take most of an hour.
run_setup() {
  log "scripts/setup.sh (LEKIWI_SKIP_ARM64=1)"
  LEKIWI_SKIP_ARM64=1 bash "$ROOT/scripts/setup.sh" >"$WORK/setup.log" 2>&1 \
    || { tail -30 "$WORK/setup.log" >&2; die "setup failed"; }
}

# ---- measuring and waiting ------------------------------------------------------------------
fact() { printf '%s=%s\n' "$1" "$2" >>"$WORK/facts.env"; }

now() { date +%s.%N; }
# Seconds since $1 (a `now`), one decimal.
elapsed() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.1f", b - a }'; }

# A free 127.0.0.1 port below the ephemeral range, so outgoing connections (the gateway
# simulator's 10,000 client sockets among them) can never take it.
free_port() { python3 "$ROOT/scripts/lib/free-ports.py" 1; }

wait_for() { # what timeout_s command...
  local what="$1" timeout="$2"; shift 2
  local deadline=$((SECONDS + timeout))
  until "$@"; do
    [ $SECONDS -lt $deadline ] || die "$what not ready after ${timeout}s"
    sleep 0.5
  done
}

# The commit measured, and how many files differ from it.
# The tree the binaries were built from: read when release_binaries starts the build (an edit
# made while a long run goes on is not in its binaries), else now.
source_rev() {
  echo "$(git -C "$ROOT" rev-parse --short HEAD 2>/dev/null || echo unknown)$(n="$(git -C "$ROOT" status --porcelain 2>/dev/null | wc -l)"; [ "$n" = 0 ] || echo " + $n uncommitted changes")"
}
fact_source() { fact source "${BUILT_FROM:-$(source_rev)}"; }

# ---- metrics, memory and CPU of the processes a benchmark starts -----------------------------
# (scrape_apiserver needs CP_DIR and APISERVER_PORT, set by start_control_plane.)
scrape() { curl -fsS --max-time 10 "$1" -o "$2" 2>/dev/null; }

scrape_apiserver() {
  curl -fsS --max-time 30 --cacert "$CP_DIR/pki/ca.crt" \
    -H "Authorization: Bearer $(cat "$CP_DIR/admin-token")" \
    "https://127.0.0.1:$APISERVER_PORT/metrics" -o "$1"
}

# Current value of series $2 at URL $1 (integer part), or -1.
current() {
  local v
  v="$(curl -fsS --max-time 5 "$1" 2>/dev/null | awk -v s="$2" 'index($0, s " ") == 1 { print $2; exit }')"
  v="${v%%.*}"
  echo "${v:--1}"
}

rss_kib() { awk '/^VmRSS:/ { print $2 }' "/proc/$1/status"; }

# CPU seconds (user + system) a process and its live descendants have used so far (PostgreSQL
# is a postmaster with a backend per connection, under runuser).
cpu_seconds() {
  local pids=("$1") ticks=0 i=0 child
  while [ "$i" -lt "${#pids[@]}" ]; do
    for child in $(cat /proc/"${pids[$i]}"/task/*/children 2>/dev/null); do pids+=("$child"); done
    i=$((i + 1))
  done
  for i in "${pids[@]}"; do
    ticks=$((ticks + $(awk '{ print $14 + $15 }' "/proc/$i/stat" 2>/dev/null || echo 0)))
  done
  awk -v t="$ticks" -v hz="$(getconf CLK_TCK)" 'BEGIN { printf "%.2f", t / hz }'
}

# Busy CPU seconds of the whole machine so far (all cores).
machine_busy() {
  awk -v hz="$(getconf CLK_TCK)" '/^cpu / { printf "%.2f", ($2 + $3 + $4 + $7 + $8) / hz }' /proc/stat
}

# Records CPU use of the named processes over a window: cpu_snapshot NAME:PID... ; later
# cpu_report PHASE SECONDS.
declare -A CPU0=()
cpu_snapshot() {
  CPU0=()
  local item
  for item in "$@"; do CPU0["$item"]="$(cpu_seconds "${item#*:}")"; done
  CPU0["machine:0"]="$(machine_busy)"
}
cpu_report() {
  local phase="$1" seconds="$2" item now_s
  for item in "${!CPU0[@]}"; do
    if [ "$item" = machine:0 ]; then now_s="$(machine_busy)"; else now_s="$(cpu_seconds "${item#*:}")"; fi
    fact "cpu_${phase}_window_${item%%:*}" \
      "$(awk -v a="${CPU0[$item]}" -v b="$now_s" -v s="$seconds" 'BEGIN { printf "%.2f", (b - a) / s }')"
  done
}

# ---- the cluster ----------------------------------------------------------------------------
# A private control plane in $CP_DIR (taken down by cleanup) with our CRDs established; exports
# its environment (KUBECONFIG, PATH) and reads its ports (APISERVER_PORT, ...).
# make_tls DIR: a CA of the run's own (DIR/ca.crt) and a certificate for 127.0.0.1 it signed
# (DIR/tls.crt, DIR/tls.key), ECDSA P-256 as a cert-manager default would issue.
make_tls() {
  (cd "$1" \
    && openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days 1 \
         -subj /CN=lekiwi-bench-ca -keyout ca.key -out ca.crt \
    && openssl req -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -subj /CN=lekiwi-gateway \
         -keyout tls.key -out tls.csr \
    && printf 'subjectAltName=IP:127.0.0.1\n' >ext \
    && openssl x509 -req -in tls.csr -CA ca.crt -CAkey ca.key -CAcreateserial -days 1 \
         -extfile ext -out tls.crt) >"$1/openssl.log" 2>&1 || die "openssl failed: $(tail -3 "$1/openssl.log")"
}

start_control_plane() {
  log "starting a private control plane in $CP_DIR"
  export LEKIWI_CP_DIR="$CP_DIR"
  CP_UP=1
  "$ROOT/scripts/testbed/control-plane.sh" up 2>"$WORK/control-plane.log" 8>&- \
    || { tail -20 "$WORK/control-plane.log" >&2; die "control plane did not start"; }
  eval "$("$ROOT/scripts/testbed/control-plane.sh" env)"
  # shellcheck disable=SC1091
  . "$CP_DIR/ports.env"
  "$ROOT/scripts/testbed/control-plane.sh" crds 8>&-
}

# Writes a new fleet enrollment token to file $2 (mode 600) and its hash to the Secret
# `fleet-enrollment` in namespace $1, labelled as the gateway looks for it.
enrollment_token() { # namespace file
  echo "lke_$(openssl rand -hex 32)" >"$2"
  chmod 600 "$2"
  kubectl -n "$1" create secret generic fleet-enrollment \
    --from-literal=sha256="$(tr -d '\n' <"$2" | sha256sum | cut -d' ' -f1)" >/dev/null
  kubectl -n "$1" label secret fleet-enrollment fleet.lekiwi.io/token=enrollment >/dev/null
}

# Creates COUNT Robots PREFIX-00001... (PREFIX: sim unless given) in NAMESPACE and their token Secrets, labels and hash exactly
# as the gateway's enrollment writes them (all robots share the simulator's one token, of which
# HASH is the sha256 hex), by four parallel kubectl processes: a fleet that is already enrolled.
provision_robots() { # namespace count hash [prefix]
  local ns="$1" count="$2" hash="$3" part pid pids=()
  rm -f "$WORK"/provision-*.json
  python3 - "$count" "$hash" "$WORK/provision" 4 "${4:-sim}" <<'PY'
import base64, json, sys
robots, digest, prefix, parts = int(sys.argv[1]), sys.argv[2], sys.argv[3], int(sys.argv[4])
robot_prefix = sys.argv[5]
data = base64.b64encode(digest.encode()).decode()
for part in range(parts):
    items = []
    for i in range(part, robots, parts):
        name = f"{robot_prefix}-{i + 1:05d}"
        items.append({"apiVersion": "fleet.lekiwi.io/v1alpha1", "kind": "Robot",
                      "metadata": {"name": name}, "spec": {}})
        items.append({"apiVersion": "v1", "kind": "Secret", "type": "Opaque",
                      "metadata": {"name": f"{name}-agent-token",
                                   "labels": {"fleet.lekiwi.io/token": "robot",
                                              "fleet.lekiwi.io/robot": name}},
                      "data": {"sha256": data}})
    if not items:
        continue
    with open(f"{prefix}-{part}.json", "w") as out:
        json.dump({"apiVersion": "v1", "kind": "List", "items": items}, out)
PY
  # A loaded API server can refuse some creates (a 50,000-robot run met "resource quota
  # evaluation timed out"): up to three tries, the later ones refused only AlreadyExists for
  # what the earlier created.
  for part in 0 1 2 3; do
    [ -f "$WORK/provision-$part.json" ] || continue  # fewer robots than parts
    (
      : >"$WORK/provision-$part.log"
      for _ in 1 2 3; do
        out="$(kubectl -n "$ns" create -f "$WORK/provision-$part.json" 2>&1)" && exit 0
        errors="$(printf '%s\n' "$out" | grep -v ' created$' || true)"
        printf '%s\n' "$errors" >>"$WORK/provision-$part.log"
        # Done when every error is an AlreadyExists (no grep -q: with pipefail, its early
        # exit would fail the pipe).
        printf '%s\n' "$errors" | grep -v AlreadyExists >/dev/null || exit 0
        sleep 5
      done
      exit 1
    ) &
    pids+=($!)
    PIDS+=($!)
  done
  for pid in "${pids[@]}"; do
    wait "$pid" || die "provisioning failed: $(tail -qn 3 "$WORK"/provision-*.log)"
    forget "$pid"
  done
}

# ---- one benchmark at a time ----------------------------------------------------------------
# Two benchmarks would share the 2 cores and disturb each other: takes the machine's benchmark
# lock on file descriptor 8, waiting at most 15 minutes for another run to finish.
# Builds the release binaries of the packages in $1 (unless the run says --no-build: BUILD=0),
# then checks that each binary named after it is in $BIN.
# Usage: release_binaries "lekiwi-operator lekiwi-agent" lekiwi-operator lekiwi-sim
release_binaries() {
  local packages=() p b
  for p in $1; do packages+=(-p "$p"); done
  shift
  if [ "$BUILD" = 1 ]; then
    BUILT_FROM="$(source_rev)"
    log "building release binaries"
    (cd "$ROOT" && cargo build --release --bins "${packages[@]}") \
      >"$WORK/build.log" 2>&1 || { tail -30 "$WORK/build.log" >&2; die "build failed"; }
  fi
  for b in "$@"; do
    [ -x "$BIN/$b" ] || die "$BIN/$b is missing (run without --no-build)"
  done
}

take_bench_lock() {
  LOCK="${TMPDIR:-/tmp}/lekiwi-bench.lock"
  exec 8>>"$LOCK"
  if ! flock -n 8; then
    log "another benchmark run holds $LOCK; waiting for it (at most 15 minutes)"
    flock -w 900 8 || die "another benchmark run still holds $LOCK after 15 minutes"
  fi
}
