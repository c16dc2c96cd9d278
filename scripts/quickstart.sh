#!/usr/bin/env bash
#! The main job on a fresh Debian 12 machine: installs what is needed, starts a local control
#! plane (etcd + kube-apiserver), installs the CRDs, runs the operator and applies the example
#! robots, then shows them with `kubectl get rb`. `quickstart.sh down` stops it all again.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT="$PWD"
STATE="${LEKIWI_CACHE:-$HOME/.cache/lekiwi}/quickstart"
NS="${LEKIWI_DEMO_NAMESPACE:-lekiwi-demo}"
SYSTEM_NS=lekiwi-system
mkdir -p "$STATE"

log() { printf '\033[1;34m[quickstart]\033[0m %s\n' "$*" >&2; }

stop_operator() {
  if [ -f "$STATE/operator.pid" ] && kill -0 "$(cat "$STATE/operator.pid")" 2>/dev/null; then
    kill -TERM "$(cat "$STATE/operator.pid")" && log "operator stopped"
  fi
  rm -f "$STATE/operator.pid"
}

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
PORT="${LEKIWI_HTTP_PORT:-8080}"
if python3 -c "import socket,sys; s=socket.socket(); s.bind(('127.0.0.1', $PORT))" 2>/dev/null; then :; else
  PORT=$(python3 -c "import socket; s=socket.socket(); s.bind(('127.0.0.1',0)); print(s.getsockname()[1])")
fi
log "starting lekiwi-operator (metrics on http://127.0.0.1:$PORT/metrics, log in $STATE/operator.log)"
setsid nohup target/debug/lekiwi-operator --namespace "$SYSTEM_NS" --http-addr "127.0.0.1:$PORT" \
  >"$STATE/operator.log" 2>&1 </dev/null &
echo $! >"$STATE/operator.pid"
for _ in $(seq 1 100); do
  curl -fsS "http://127.0.0.1:$PORT/readyz" >/dev/null 2>&1 && break
  kill -0 "$(cat "$STATE/operator.pid")" 2>/dev/null || { tail -20 "$STATE/operator.log"; exit 1; }
  sleep 0.2
done

log "applying the example robots and deployment to namespace $NS"
kubectl apply -n "$NS" -f manifests/examples/
for _ in $(seq 1 50); do
  [ "$(kubectl get rb -n "$NS" -o jsonpath='{.items[*].status.phase}' | wc -w)" -ge 3 ] && break
  sleep 0.2
done
echo
kubectl get rb -n "$NS"
echo
kubectl lekiwi robots -n "$NS" -o wide
cat <<MSG

The control plane and operator keep running. Try:
  eval "\$(scripts/control-plane.sh env)"; export PATH="$ROOT/target/debug:\$PATH"
  kubectl get lekiwi -n $NS                      # robots and deployments
  kubectl explain robot.spec                    # the resource documentation
  kubectl describe rb kiwi-03 -n $NS            # conditions and events
  curl -s http://127.0.0.1:$PORT/metrics | grep lekiwi_robots
  scripts/quickstart.sh down                    # stop everything
MSG
