#!/usr/bin/env bash
#! Runs a local Kubernetes control plane (etcd + kube-apiserver v1.20.2, no scheduler, no
#! controller-manager, no kubelet) as background processes on free 127.0.0.1 ports, for tests and
#! local development of the LeKiwi fleet control plane.
#!
#! Usage: scripts/testbed/control-plane.sh <command>
#!   up            start etcd + kube-apiserver and wait for /readyz (idempotent; a healthy instance is
#!                 left alone; a stopped or crashed one is restarted on the SAME ports with the same
#!                 data, certificates and tokens)
#!   down          stop both processes (SIGTERM, then SIGKILL), keep the data
#!   down --purge  stop and delete the state directory (alias: clean)
#!   kill [NAME]   SIGKILL both processes at once (simulates a crash), keep the data; with NAME
#!                 (etcd or kube-apiserver) only that one
#!   status        print state, ports and pids; exit 0 if healthy, 1 otherwise
#!   env           print `export KUBECONFIG=...` and `export PATH=...` lines, for
#!                 eval "$(scripts/testbed/control-plane.sh env)"
#!   crds          server-side apply manifests/crds/ and wait (60 s at most) until each is
#!                 Established; a CRD created a moment ago has no status.conditions yet, which
#!                 `kubectl wait --for=condition=Established` takes for an error at once
#!   help          this text
#!
#! Environment:
#!   LEKIWI_CP_DIR       state directory (default ~/.cache/lekiwi/control-plane); use different
#!                       directories to run several independent control planes side by side
#!   KUBEBUILDER_ASSETS  directory with `etcd` and `kube-apiserver` to use instead of the cached
#!                       v1.20.2 build (envtest convention)
#!   LEKIWI_CP_TIMEOUT   seconds `up` waits for /readyz (default 90)
#!   LEKIWI_APISERVER_ARGS  more kube-apiserver flags, split on spaces (e.g. the benchmarks'
#!                       --audit-policy-file and --audit-log-path)
#!
#! State directory layout: ports.env, kubeconfig (admin, system:masters), kubeconfig-user and
#! user-token (non-admin user `lekiwi-user`, no RBAC bindings), admin-token, tokens.csv, pki/
#! (ca.crt signs the apiserver's serving cert for 127.0.0.1/localhost), sa.key/sa.pub, etcd/ (data),
#! *.pid and *.log per process, .lock (flock serialising up/down/kill).
set -euo pipefail

SCRIPT_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
CACHE="${LEKIWI_CACHE:-$HOME/.cache/lekiwi}"
STATE="$(realpath -m "${LEKIWI_CP_DIR:-$CACHE/control-plane}")"
TIMEOUT="${LEKIWI_CP_TIMEOUT:-90}"
BIN_DIR="$CACHE/bin"

log() { printf '[control-plane] %s\n' "$*" >&2; }
die() { printf '[control-plane] error: %s\n' "$*" >&2; exit 1; }
usage() { sed -n 's/^#!\( \|$\)//p' "${BASH_SOURCE[0]}"; }

# ---- binaries -------------------------------------------------------------------------------
resolve_binaries() {
  if [ -n "${KUBEBUILDER_ASSETS:-}" ] && [ -x "$KUBEBUILDER_ASSETS/etcd" ] \
      && [ -x "$KUBEBUILDER_ASSETS/kube-apiserver" ]; then
    ETCD_BIN="$KUBEBUILDER_ASSETS/etcd"
    APISERVER_BIN="$KUBEBUILDER_ASSETS/kube-apiserver"
    return
  fi
  local dir="$CACHE/k8s/v1.20.2"
  if [ ! -x "$dir/kube-apiserver" ] || [ ! -x "$dir/etcd" ]; then
    log "kube-apiserver/etcd not found in $dir; running scripts/setup.sh"
    "$SCRIPT_DIR/../setup.sh" >&2
  fi
  [ -x "$dir/kube-apiserver" ] || die "setup.sh did not produce $dir/kube-apiserver"
  [ -x "$dir/etcd" ] || die "setup.sh did not produce $dir/etcd"
  ETCD_BIN="$dir/etcd"
  APISERVER_BIN="$dir/kube-apiserver"
}

# ---- processes ------------------------------------------------------------------------------
# Each process is identified by its pid file AND by a marker argument in its command line (so a
# recycled pid never makes us signal or trust an unrelated process).
marker() {
  case "$1" in
    etcd) printf -- '--data-dir=%s/etcd' "$STATE" ;;
    kube-apiserver) printf -- '--cert-dir=%s/pki/generated' "$STATE" ;;
  esac
}

# shellcheck source=scripts/lib/procs.sh
source "$(dirname "${BASH_SOURCE[0]}")/../lib/procs.sh"

# ---- state (created once, reused across restarts) -------------------------------------------
load_ports() {
  # shellcheck disable=SC1091
  [ -f "$STATE/ports.env" ] && . "$STATE/ports.env"
}

port_free() {
  python3 - "$1" <<'PY'
import socket, sys
s = socket.socket()
s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
try:
    s.bind(("127.0.0.1", int(sys.argv[1])))
except OSError:
    sys.exit(1)
PY
}

pick_ports() {
  local ports
  mapfile -t ports < <(python3 "$SCRIPT_DIR/../lib/free-ports.py" 3)
  printf 'ETCD_PORT=%d\nETCD_PEER_PORT=%d\nAPISERVER_PORT=%d\n' "${ports[@]}"
}

write_kubeconfig() { # file user token
  local tmp="$1.tmp.$$"
  cat >"$tmp" <<EOF
apiVersion: v1
kind: Config
clusters:
- name: lekiwi
  cluster:
    server: https://127.0.0.1:$APISERVER_PORT
    certificate-authority-data: $(base64 -w0 "$STATE/pki/ca.crt")
users:
- name: $2
  user:
    token: $3
contexts:
- name: lekiwi-$2
  context:
    cluster: lekiwi
    user: $2
    namespace: default
current-context: lekiwi-$2
EOF
  chmod 600 "$tmp"
  mv -f "$tmp" "$1"
}

init_state() {
  mkdir -p "$STATE/pki/generated"
  mkdir -p -m 700 "$STATE/etcd"
  if [ ! -s "$STATE/ports.env" ]; then
    pick_ports >"$STATE/ports.env.tmp" && mv -f "$STATE/ports.env.tmp" "$STATE/ports.env"
  fi
  load_ports

  local pki="$STATE/pki"
  if [ ! -s "$pki/ca.crt" ] || [ ! -s "$pki/apiserver.crt" ]; then
    log "generating CA and serving certificate"
    openssl req -x509 -newkey rsa:2048 -nodes -days 3650 -subj "/CN=lekiwi-control-plane-ca" \
      -keyout "$pki/ca.key" -out "$pki/ca.crt" \
      -addext "basicConstraints=critical,CA:TRUE" \
      -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null
    openssl req -newkey rsa:2048 -nodes -subj "/CN=kube-apiserver" \
      -keyout "$pki/apiserver.key" -out "$pki/apiserver.csr" 2>/dev/null
    cat >"$pki/apiserver.ext" <<'EOF'
basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature,keyEncipherment
extendedKeyUsage=serverAuth
subjectKeyIdentifier=hash
authorityKeyIdentifier=keyid,issuer
subjectAltName=IP:127.0.0.1,IP:10.0.0.1,DNS:localhost,DNS:kubernetes,DNS:kubernetes.default,DNS:kubernetes.default.svc,DNS:kubernetes.default.svc.cluster.local
EOF
    openssl x509 -req -days 3650 -in "$pki/apiserver.csr" -CA "$pki/ca.crt" -CAkey "$pki/ca.key" \
      -CAcreateserial -extfile "$pki/apiserver.ext" -out "$pki/apiserver.crt" 2>/dev/null
    chmod 600 "$pki"/*.key
  fi
  if [ ! -s "$STATE/sa.pub" ]; then
    openssl genrsa -out "$STATE/sa.key" 2048 2>/dev/null
    openssl rsa -in "$STATE/sa.key" -pubout -out "$STATE/sa.pub" 2>/dev/null
    chmod 600 "$STATE/sa.key"
  fi
  if [ ! -s "$STATE/tokens.csv" ]; then
    openssl rand -hex 24 >"$STATE/admin-token"
    openssl rand -hex 24 >"$STATE/user-token"
    chmod 600 "$STATE/admin-token" "$STATE/user-token"
    printf '%s,admin,admin,system:masters\n%s,lekiwi-user,lekiwi-user\n' \
      "$(cat "$STATE/admin-token")" "$(cat "$STATE/user-token")" >"$STATE/tokens.csv"
    chmod 600 "$STATE/tokens.csv"
  fi
  [ -s "$STATE/kubeconfig" ] || write_kubeconfig "$STATE/kubeconfig" admin "$(cat "$STATE/admin-token")"
  [ -s "$STATE/kubeconfig-user" ] \
    || write_kubeconfig "$STATE/kubeconfig-user" lekiwi-user "$(cat "$STATE/user-token")"
}

# ---- health ---------------------------------------------------------------------------------
etcd_healthy() {
  curl -fsS --max-time 2 "http://127.0.0.1:$ETCD_PORT/health" 2>/dev/null | grep -q '"health":"true"'
}

apiserver_ready() {
  [ -n "${APISERVER_PORT:-}" ] && [ -s "$STATE/admin-token" ] || return 1
  [ "$(curl -sS --max-time 3 --cacert "$STATE/pki/ca.crt" \
        -H "Authorization: Bearer $(cat "$STATE/admin-token")" \
        "https://127.0.0.1:$APISERVER_PORT/readyz" 2>/dev/null)" = ok ]
}

healthy() {
  load_ports || return 1
  live_pid etcd >/dev/null && live_pid kube-apiserver >/dev/null && apiserver_ready
}

# ---- commands -------------------------------------------------------------------------------
take_lock() {
  mkdir -p "$STATE"
  exec 9>"$STATE/.lock"
  flock -w 300 9 || die "timed out waiting for the lock $STATE/.lock"
}

start_etcd() {
  local extra=()
  # Tests do not need durability across machine crashes; a killed process loses nothing (the flag
  # exists in etcd >= 3.4.14 but is not listed in `etcd --help`). A single member elects itself, so
  # short raft timers only make (re)starts faster: ~0.3s instead of up to ~2s to become leader.
  grep -qa -- unsafe-no-fsync "$ETCD_BIN" && extra+=(--unsafe-no-fsync)
  port_free "$ETCD_PORT" && port_free "$ETCD_PEER_PORT" \
    || die "etcd ports $ETCD_PORT/$ETCD_PEER_PORT are taken by another process"
  spawn etcd "$ETCD_BIN" --name=default "$(marker etcd)" \
    --listen-client-urls="http://127.0.0.1:$ETCD_PORT" \
    --advertise-client-urls="http://127.0.0.1:$ETCD_PORT" \
    --listen-peer-urls="http://127.0.0.1:$ETCD_PEER_PORT" \
    --initial-advertise-peer-urls="http://127.0.0.1:$ETCD_PEER_PORT" \
    --initial-cluster="default=http://127.0.0.1:$ETCD_PEER_PORT" \
    --heartbeat-interval=50 --election-timeout=500 \
    --logger=zap --log-outputs=stderr "${extra[@]}"
  local deadline=$((SECONDS + 30))
  until etcd_healthy; do
    still_running etcd || { tail_log etcd; die "etcd exited during startup"; }
    [ $SECONDS -lt $deadline ] || { tail_log etcd; die "etcd not healthy after 30s"; }
    sleep 0.1
  done
}

# --advertise-address=127.0.0.1 keeps the apiserver off the host's interfaces; the `kubernetes`
# Endpoints object cannot hold a loopback address, hence --endpoint-reconciler-type=none (otherwise it
# logs "may not be in the loopback range" every 10s). Nothing runs in-cluster here anyway.
start_apiserver() {
  port_free "$APISERVER_PORT" || die "apiserver port $APISERVER_PORT is taken by another process"
  local extra=()
  read -ra extra <<<"${LEKIWI_APISERVER_ARGS:-}"
  spawn kube-apiserver "$APISERVER_BIN" "$(marker kube-apiserver)" \
    --etcd-servers="http://127.0.0.1:$ETCD_PORT" \
    --secure-port="$APISERVER_PORT" \
    --bind-address=127.0.0.1 \
    --advertise-address=127.0.0.1 \
    --endpoint-reconciler-type=none \
    --tls-cert-file="$STATE/pki/apiserver.crt" \
    --tls-private-key-file="$STATE/pki/apiserver.key" \
    --service-account-issuer=https://kubernetes.default.svc \
    --service-account-key-file="$STATE/sa.pub" \
    --service-account-signing-key-file="$STATE/sa.key" \
    --authorization-mode=RBAC \
    --service-cluster-ip-range=10.0.0.0/24 \
    --allow-privileged=true \
    --disable-admission-plugins=ServiceAccount \
    --token-auth-file="$STATE/tokens.csv" \
    "${extra[@]}"
}

cmd_up() {
  # Fast path without the lock: nothing to do.
  healthy && return 0
  take_lock
  healthy && return 0            # another `up` finished while we waited for the lock
  local t0=$SECONDS
  resolve_binaries
  init_state
  live_pid etcd >/dev/null || { log "starting etcd on 127.0.0.1:$ETCD_PORT"; start_etcd; }
  if ! live_pid kube-apiserver >/dev/null; then
    log "starting kube-apiserver on https://127.0.0.1:$APISERVER_PORT"
    start_apiserver
  fi
  local deadline=$((SECONDS + TIMEOUT))
  until apiserver_ready; do
    still_running etcd || { tail_log etcd; die "etcd exited"; }
    still_running kube-apiserver \
      || { tail_log kube-apiserver 40; die "kube-apiserver exited during startup"; }
    if [ $SECONDS -ge $deadline ]; then
      tail_log kube-apiserver 40
      die "kube-apiserver not ready after ${TIMEOUT}s (https://127.0.0.1:$APISERVER_PORT/readyz)"
    fi
    sleep 0.2
  done
  log "ready in $((SECONDS - t0))s: https://127.0.0.1:$APISERVER_PORT, KUBECONFIG=$STATE/kubeconfig"
}

cmd_down() {
  local purge=0
  case "${1:-}" in
    --purge) purge=1 ;;
    "") ;;
    *) die "unknown option for down: $1" ;;
  esac
  [ -d "$STATE" ] || return 0
  take_lock
  local name
  for name in kube-apiserver etcd; do
    stop_proc "$name" TERM 5 || stop_proc "$name" KILL 5 || die "could not stop $name"
  done
  rm -f "$STATE/etcd.pid" "$STATE/kube-apiserver.pid"
  if [ $purge = 1 ]; then
    rm -rf "$STATE"
    log "stopped and removed $STATE"
  else
    log "stopped (data kept in $STATE)"
  fi
}

cmd_kill() {
  local names=(etcd kube-apiserver)
  case "${1:-}" in
    "") ;;
    etcd|kube-apiserver) names=("$1") ;;
    *) die "unknown process for kill: $1 (etcd or kube-apiserver)" ;;
  esac
  [ -d "$STATE" ] || return 0
  take_lock
  local name
  for name in "${names[@]}"; do
    stop_proc "$name" KILL 5 || die "could not kill $name"
  done
  log "killed ${names[*]} (data kept in $STATE)"
}

cmd_status() {
  if ! load_ports 2>/dev/null; then
    echo "down (no state in $STATE)"
    return 1
  fi
  local epid apid state=down
  epid="$(live_pid etcd || echo -)"
  apid="$(live_pid kube-apiserver || echo -)"
  healthy && state=up
  echo "$state"
  echo "state dir:  $STATE"
  echo "apiserver:  https://127.0.0.1:$APISERVER_PORT (pid $apid)"
  echo "etcd:       http://127.0.0.1:$ETCD_PORT, peer $ETCD_PEER_PORT (pid $epid)"
  echo "kubeconfig: $STATE/kubeconfig (admin), $STATE/kubeconfig-user (lekiwi-user)"
  [ $state = up ]
}

cmd_env() {
  printf 'export KUBECONFIG=%q\n' "$STATE/kubeconfig"
  printf 'export PATH=%q:"$PATH"\n' "$BIN_DIR"
}

cmd_crds() {
  local kubectl=("$BIN_DIR/kubectl" --kubeconfig "$STATE/kubeconfig") crd deadline=$((SECONDS + 60))
  "${kubectl[@]}" apply --server-side --force-conflicts -f "$SCRIPT_DIR/../../manifests/crds/" >/dev/null
  for crd in robots.fleet.lekiwi.io robotdeployments.fleet.lekiwi.io; do
    until [ "$("${kubectl[@]}" get crd "$crd" \
             -o 'jsonpath={.status.conditions[?(@.type=="Established")].status}')" = True ]; do
      [ $SECONDS -lt $deadline ] || die "CRD $crd not Established within 60 s"
      sleep 0.2
    done
  done
}

case "${1:-help}" in
  up) cmd_up ;;
  down) shift; cmd_down "$@" ;;
  clean) cmd_down --purge ;;
  kill) shift; cmd_kill "$@" ;;
  status) cmd_status ;;
  env) cmd_env ;;
  crds) cmd_crds ;;
  help|-h|--help) usage ;;
  *) usage >&2; exit 2 ;;
esac
