#!/usr/bin/env bash
#! The main job on a fresh Debian 12 machine: installs what is needed, starts a local control
#! plane (etcd + kube-apiserver), installs the CRDs, runs the operator (controllers + gateway),
#! applies the example robots, enrolls a simulated fleet of 20 robots over real WebSockets and
#! shows them coming Online with `kubectl get rb`. `quickstart.sh down` stops it all again.
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
stop_operator() { stop_pid simulator; stop_pid operator; }

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
kubectl apply --server-side --force-conflicts -f manifests/crds/ >/dev/null
kubectl wait --for=condition=Established --timeout=60s crd/robots.fleet.lekiwi.io crd/robotdeployments.fleet.lekiwi.io >/dev/null
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
  --store-url "sqlite://$STATE/events.db" --heartbeat-interval-seconds 10 \
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
log "starting a simulated fleet of $SIM_ROBOTS robots (real WebSocket agents; log in $STATE/simulator.log)"
setsid nohup target/debug/lekiwi-sim --gateway "ws://127.0.0.1:$GW_PORT/v1/agent" \
  --enrollment-token "$(cat "$STATE/enrollment-token")" --namespace "$NS" --robots "$SIM_ROBOTS" \
  --prefix kiwi-sim --report-every 30 >"$STATE/simulator.log" 2>&1 </dev/null &
echo $! >"$STATE/simulator.pid"
for _ in $(seq 1 150); do
  online=$(kubectl get rb -n "$NS" -o jsonpath='{range .items[*]}{.status.phase}{"\n"}{end}' | grep -c '^Online$' || true)
  [ "$online" -ge "$SIM_ROBOTS" ] && break
  sleep 0.2
done
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
  kill -STOP \$(cat $STATE/simulator.pid)        # freeze the fleet: robots turn Offline in ~30 s
  kill -CONT \$(cat $STATE/simulator.pid)        # ...and come back
  scripts/quickstart.sh down                    # stop everything
MSG
