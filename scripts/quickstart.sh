#!/usr/bin/env bash
#! The main job on a fresh Debian 12 machine: installs what it needs (scripts/setup.sh main),
#! starts a local control plane (etcd + kube-apiserver), installs the CRDs, runs the operator
#! (controllers + gateway), applies the example robots, starts a fleet of 20 real agents (one
#! process, one state directory per robot) that enroll over real WebSockets, pushes a demo release
#! and rolls it out to the fleet while you watch `kubectl lekiwi rollout status`.
#!
#! Usage: scripts/quickstart.sh [up|env|down]
#!   up    (the default) install, start everything, roll the demo release out
#!   env   print the shell lines that point kubectl and the tour at the running quickstart:
#!         eval "$(bash scripts/quickstart.sh env)" sets KUBECONFIG, PATH (kubectl, helm, the
#!         workspace's binaries) and NS (its namespace), GW (the gateway's HTTP address), WS
#!         (the agents' WebSocket URL), METRICS (the operator's /metrics) and QS (its state)
#!   down  stop the fleet, the operator and the control plane (data is kept)
#!
#! Environment: LEKIWI_QUICKSTART_DIR (its state: logs, event store, blobs, the fleet's state
#! directories; default ~/.cache/lekiwi/quickstart), LEKIWI_CP_DIR (the control plane's, default
#! ~/.cache/lekiwi/control-plane), LEKIWI_HTTP_PORT and LEKIWI_GATEWAY_PORT (8080 and 8081 when
#! free), LEKIWI_SIM_ROBOTS (20), LEKIWI_DEMO_NAMESPACE (lekiwi-demo).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT="$PWD"
STATE="$(realpath -m "${LEKIWI_QUICKSTART_DIR:-${LEKIWI_CACHE:-$HOME/.cache/lekiwi}/quickstart}")"
NS="${LEKIWI_DEMO_NAMESPACE:-lekiwi-demo}"
SYSTEM_NS=lekiwi-system
mkdir -p "$STATE"

log() { printf '\033[1;34m[quickstart]\033[0m %s\n' "$*" >&2; }

SIM_ROBOTS="${LEKIWI_SIM_ROBOTS:-20}"

stop_pid() {
  if [ -f "$STATE/$1.pid" ] && kill -0 "$(cat "$STATE/$1.pid")" 2>/dev/null; then
    kill -TERM "$(cat "$STATE/$1.pid")" && log "$1 stopped"
  fi
  rm -f "$STATE/$1.pid"
}
stop_operator() { stop_pid fleet; stop_pid simulator; stop_pid operator; }

print_env() {
  [ -s "$STATE/ports.env" ] || { echo "no quickstart in $STATE: run bash scripts/quickstart.sh" >&2; exit 1; }
  # shellcheck source=/dev/null
  . "$STATE/ports.env"
  bash scripts/testbed/control-plane.sh env
  printf 'export PATH=%q:"$PATH"\n' "$ROOT/target/debug"
  printf 'export NS=%q GW=%q WS=%q METRICS=%q QS=%q\n' "$NS" "http://127.0.0.1:$GW_PORT" \
    "ws://127.0.0.1:$GW_PORT/v1/agent" "http://127.0.0.1:$PORT/metrics" "$STATE"
}

case "${1:-up}" in
  down)
    stop_operator
    bash scripts/testbed/control-plane.sh down
    exit 0 ;;
  env) print_env; exit 0 ;;
  up) ;;
  -h|--help) sed -n 's/^#!\( \|$\)//p' "$0"; exit 0 ;;
  *) echo "unknown command: $1 (try --help)" >&2; exit 2 ;;
esac

t0=$SECONDS
# etcd, kube-apiserver, kubectl, and the workspace's binaries (built while the rest installs).
bash scripts/setup.sh main
bash scripts/testbed/control-plane.sh up
eval "$(bash scripts/testbed/control-plane.sh env)"
export PATH="$ROOT/target/debug:$PATH"   # so `kubectl lekiwi` finds the plugin

log "installing the CRDs"
bash scripts/testbed/control-plane.sh crds
for ns in "$SYSTEM_NS" "$NS"; do
  kubectl get namespace "$ns" >/dev/null 2>&1 || kubectl create namespace "$ns" >/dev/null
done

stop_operator
free_port() {
  if python3 -c "import socket,sys; s=socket.socket(); s.bind(('127.0.0.1', $1))" 2>/dev/null; then echo "$1"; else
    python3 -c "import socket; s=socket.socket(); s.bind(('127.0.0.1',0)); print(s.getsockname()[1])"
  fi
}
PORT=$(free_port "${LEKIWI_HTTP_PORT:-8080}")
GW_PORT=$(free_port "${LEKIWI_GATEWAY_PORT:-8081}")
printf 'PORT=%s\nGW_PORT=%s\n' "$PORT" "$GW_PORT" >"$STATE/ports.env"
log "starting lekiwi-operator (metrics on http://127.0.0.1:$PORT/metrics, gateway ws://127.0.0.1:$GW_PORT/v1/agent, log in $STATE/operator.log)"
setsid nohup target/debug/lekiwi-operator --namespace "$SYSTEM_NS" --http-addr "127.0.0.1:$PORT" \
  --gateway-addr "127.0.0.1:$GW_PORT" --gateway-name quickstart-gateway \
  --store-url "sqlite://$STATE/events.db" --heartbeat-interval-seconds 10 --blob-dir "$STATE/blobs" \
  >"$STATE/operator.log" 2>&1 </dev/null &
echo $! >"$STATE/operator.pid"
for _ in $(seq 1 100); do
  curl -fsS "http://127.0.0.1:$PORT/readyz" >/dev/null 2>&1 && break
  kill -0 "$(cat "$STATE/operator.pid")" 2>/dev/null || { tail -20 "$STATE/operator.log"; exit 1; }
  sleep 0.2
done

log "applying the example robots and deployment to namespace $NS"
kubectl apply -n "$NS" -f manifests/examples/

# A fleet enrollment token: the Secret keeps only its SHA-256; the token itself stays here.
if [ ! -s "$STATE/enrollment-token" ] || ! kubectl get secret fleet-enrollment -n "$NS" >/dev/null 2>&1; then
  echo "lke_$(openssl rand -hex 32)" >"$STATE/enrollment-token"
  chmod 600 "$STATE/enrollment-token"
  kubectl delete secret fleet-enrollment -n "$NS" --ignore-not-found >/dev/null
  kubectl create secret generic fleet-enrollment -n "$NS" \
    --from-literal=sha256="$(tr -d '\n' <"$STATE/enrollment-token" | sha256sum | cut -d' ' -f1)" >/dev/null
  kubectl label secret fleet-enrollment -n "$NS" fleet.lekiwi.io/token=enrollment >/dev/null
fi
log "starting a fleet of $SIM_ROBOTS real agents (lekiwi-fleet; state in $STATE/fleet, log in $STATE/fleet.log)"
# Each robot's health check fails while its state directory holds a file named fail-health.
setsid nohup target/debug/lekiwi-fleet --gateway "ws://127.0.0.1:$GW_PORT/v1/agent" \
  --enrollment-token-file "$STATE/enrollment-token" --namespace "$NS" --robots "$SIM_ROBOTS" \
  --prefix kiwi --state-root "$STATE/fleet" --report-every 30 --health-timeout-s 3 \
  --health-command 'test ! -e "$LEKIWI_RELEASE_DIR/../../fail-health"' \
  >"$STATE/fleet.log" 2>&1 </dev/null &
echo $! >"$STATE/fleet.pid"
FLEET=$(for i in $(seq 0 $((SIM_ROBOTS - 1))); do printf 'kiwi-%03d\n' "$i"; done)
for _ in $(seq 1 300); do
  online=$(kubectl get rb -n "$NS" -o jsonpath='{range .items[*]}{.metadata.name} {.status.phase}{"\n"}{end}' \
    | grep -E '^kiwi-[0-9]{3} Online$' | cut -d' ' -f1 | grep -cxF "$FLEET" || true)
  [ "$online" -ge "$SIM_ROBOTS" ] && break
  sleep 0.2
done
# The demo deployment selects the fleet by this label.
# shellcheck disable=SC2086 # one robot name per word
kubectl label rb -n "$NS" --overwrite $FLEET fleet.lekiwi.io/group=quickstart >/dev/null
echo
kubectl get rb -n "$NS" -l fleet.lekiwi.io/group=quickstart

# A demo release: a directory of files, pushed to the operator's blob store.
demo_release() {
  local dir="$STATE/releases/$1"
  mkdir -p "$dir/lekiwi" "$dir/policy"
  printf 'robot_type: lekiwi\nversion: %s\n' "$1" >"$dir/lekiwi/config.yaml"
  printf 'print("lekiwi host %s")\n' "$1" >"$dir/lekiwi/host.py"
  head -c 262144 /dev/zero | tr '\0' 'w' >"$dir/policy/act.safetensors"
  echo "$dir"
}
log "pushing demo release 1.0.0 (kubectl lekiwi release push)"
DIGEST=$(kubectl lekiwi release push "$(demo_release 1.0.0)" --version 1.0.0 \
  --server "http://127.0.0.1:$GW_PORT" -n "$NS")
log "rolling 1.0.0 out to the fleet: a canary robot, then batches of 25%"
kubectl apply -n "$NS" -f - <<YAML
apiVersion: fleet.lekiwi.io/v1alpha1
kind: RobotDeployment
metadata:
  name: demo-fleet
spec:
  selector:
    matchLabels: {fleet.lekiwi.io/group: quickstart}
  release: {version: 1.0.0, digest: $DIGEST}
  strategy: {batchSize: 25%, canary: 1, successThreshold: 0.8, robotTimeoutSeconds: 120, unavailable: Skip}
YAML
kubectl lekiwi rollout status demo-fleet -n "$NS" --timeout 300
echo
kubectl get rb -n "$NS"
echo
kubectl lekiwi robots -n "$NS" -o wide | head -8
log "ready in $((SECONDS - t0)) s; the control plane, the operator and the fleet keep running"
cat <<MSG

Next: the 10-minute tour (README.md, or the book's Getting started). It starts with
  eval "\$(bash scripts/quickstart.sh env)"   # KUBECONFIG, PATH, NS, GW, WS, METRICS, QS
and ends with
  bash scripts/quickstart.sh down             # stop everything (data is kept)
MSG
