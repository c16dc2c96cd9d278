#!/usr/bin/env bash
#! The main job on a fresh Debian 12 machine: installs what is needed, starts a local control
#! plane (etcd + kube-apiserver), installs the CRDs, runs the operator (controllers + gateway),
#! applies the example robots, starts a fleet of 20 real agents (one process, one state directory
#! per robot) that enroll over real WebSockets, pushes a demo release and rolls it out to the fleet
#! while you watch `kubectl lekiwi rollout status`. `quickstart.sh down` stops it all again.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT="$PWD"
STATE="${LEKIWI_CACHE:-$HOME/.cache/lekiwi}/quickstart"
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

case "${1:-up}" in
  down)
    stop_operator
    bash scripts/control-plane.sh down
    exit 0 ;;
  up) ;;
  -h|--help)
    echo "Usage: scripts/quickstart.sh [up|down]"
    echo "  up    install everything, start control plane + operator, apply the example robots (default)"
    echo "  down  stop the operator and the control plane (data is kept)"
    exit 0 ;;
  *) echo "unknown command: $1 (try --help)" >&2; exit 2 ;;
esac

bash scripts/setup.sh
log "building (debug) lekiwi-operator, kubectl-lekiwi, lekiwi-agent"
cargo build --quiet --workspace --bins
bash scripts/control-plane.sh up
eval "$(bash scripts/control-plane.sh env)"
export PATH="$ROOT/target/debug:$PATH"   # so `kubectl lekiwi` finds the plugin

log "installing the CRDs"
bash scripts/control-plane.sh crds
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
cat <<MSG

The control plane and operator keep running. Try:
  eval "\$(scripts/control-plane.sh env)"; export PATH="$ROOT/target/debug:\$PATH"
  kubectl get lekiwi -n $NS                      # robots and deployments
  kubectl explain robot.spec                    # the resource documentation
  kubectl describe rb kiwi-03 -n $NS            # conditions and events
  curl -s http://127.0.0.1:$PORT/metrics | grep -E 'lekiwi_(robots|gateway_connections) '
  kubectl lekiwi rollout status demo-fleet -n $NS --watch=false
  # A new release, then a rollback: 3 robots of the second batch fail their health check.
  d=\$(mkdir -p /tmp/demo-1.1.0 && cp -r $STATE/releases/1.0.0/. /tmp/demo-1.1.0 && echo tuned >>/tmp/demo-1.1.0/lekiwi/config.yaml && \\
      kubectl lekiwi release push /tmp/demo-1.1.0 --version 1.1.0 --server http://127.0.0.1:$GW_PORT -n $NS)
  touch $STATE/fleet/kiwi-00{2,3,4}/fail-health
  kubectl patch rdeploy demo-fleet -n $NS --type merge -p "{\\"spec\\":{\\"release\\":{\\"version\\":\\"1.1.0\\",\\"digest\\":\\"\$d\\"},\\"strategy\\":{\\"batchSize\\":5}}}"
  kubectl lekiwi rollout status demo-fleet -n $NS   # canary, then batch 1 fails: RolledBack
  kill -STOP \$(cat $STATE/fleet.pid)            # freeze the fleet: robots turn Offline in ~30 s
  kill -CONT \$(cat $STATE/fleet.pid)            # ...and come back
  scripts/quickstart.sh down                    # stop everything
MSG
