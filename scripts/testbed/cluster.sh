#!/usr/bin/env bash
#! Runs a local single-node Kubernetes v1.20.2 cluster whose Pods really run: etcd, kube-apiserver,
#! kube-controller-manager, kube-scheduler, containerd (+ runc, CNI bridge), kubelet and kube-proxy
#! as background processes owned by this script, for tests of the LeKiwi fleet control plane.
#! Needs root (network namespace, iptables, mounts, cgroups). Nothing can be pulled: images are
#! imported with `ctr -n k8s.io images import` (the pause image from scripts/image.sh is imported
#! by `up`).
#!
#! Usage: scripts/testbed/cluster.sh <command>
#!   up            start everything, wait until the node is Ready and the basics work (idempotent: a
#!                 healthy cluster is left alone, Released PVs are made Available again)
#!   down          delete every Pod, stop every process, unmount every mount under the directory,
#!                 delete the node's network namespace (its bridge, addresses, routes, iptables
#!                 rules and network sysctls go with it) and the host's end of the veth pair,
#!                 restore the kernel-wide sysctls the kubelet changed; keeps certificates, etcd
#!                 data and imported images
#!   down --purge  the same, then delete the directory (alias: clean)
#!   status        print state, addresses and pids; exit 0 if healthy, 1 otherwise
#!   env           print export lines for eval "$(scripts/testbed/cluster.sh env)": KUBECONFIG, PATH,
#!                 LEKIWI_NODE_IP (the API server and NodePorts listen there), LEKIWI_HOST_IP (the
#!                 host as Pods reach it), LEKIWI_NODE_NETNS, LEKIWI_NODE_BRIDGE, LEKIWI_POD_CIDR,
#!                 LEKIWI_SERVICE_CIDR, CONTAINERD_ADDRESS (for `ctr -n k8s.io images import`),
#!                 LEKIWI_CLUSTER_DIR
#!   help          this text
#!
#! Environment:
#!   LEKIWI_CLUSTER_DIR      state directory (default ~/.cache/lekiwi/test-cluster)
#!   LEKIWI_CLUSTER_TIMEOUT  seconds `up` waits for each readiness step (default 120)
#!
#! Network: every process of the cluster runs in the network namespace `lekiwi-node`, linked to
#! the host by a veth pair: `lekiwi-veth` = 198.18.213.1/30 on the host, `eth0` = 198.18.213.2/30
#! in the namespace, which is the node IP (the API server, the kubelet and NodePorts listen there
#! and nowhere else). Inside the namespace only: the bridge `lekiwi0` = 198.19.213.1/25, Pods from
#! 198.19.213.0/25, Services from 198.19.213.128/25, kube-proxy's, the kubelet's and the CNI's
#! iptables rules, and the network sysctls they set. The host gains its end of the veth pair and
#! one route, 198.19.213.0/24 (Pods and Services) through the node IP; Pods reach the host at
#! 198.18.213.1. Every address is in 198.18.0.0/15 (RFC 2544: reserved for benchmarking, not a
#! private range a real network uses). etcd and the components' other ports are on the
#! namespace's loopback. StorageClass `standard` (default) has four pre-made 1Gi hostPath PVs under
#! the directory. One such cluster per machine: the namespace's and links' names, the kubelet's
#! cgroups and /var/log/pods are machine-wide.
set -euo pipefail

SCRIPT_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
CACHE="${LEKIWI_CACHE:-$HOME/.cache/lekiwi}"
STATE="$(realpath -m "${LEKIWI_CLUSTER_DIR:-$CACHE/test-cluster}")"
TIMEOUT="${LEKIWI_CLUSTER_TIMEOUT:-120}"
K8S_DIR="$CACHE/k8s/v1.20.2"
BIN_DIR="$CACHE/bin"
PAUSE_TAR="$CACHE/images/pause.oci.tar"
PAUSE_REF="lekiwi.local/pause:3.2"
# The node's network namespace and its veth pair to the host (see the help above for the plan).
NETNS=lekiwi-node
NETNS_PATH="/run/netns/$NETNS"
HOST_LINK=lekiwi-veth
NODE_LINK=eth0
HOST_IP=198.18.213.1
NODE_IP=198.18.213.2
BRIDGE=lekiwi0
# The node's ranges, the host's one route to the node: Pods in its lower half, Services above.
NODE_NET=198.19.213.0/24
BRIDGE_IP=198.19.213.1
POD_CIDR=198.19.213.0/25
SERVICE_CIDR=198.19.213.128/25
KUBERNETES_IP=198.19.213.129 # the `kubernetes` Service: the first address of the Service range
# What `up` writes to $STATE/network: state made for another plan (certificates, kubeconfigs,
# Service IPs in etcd) is not reused.
LAYOUT="netns=$NETNS node=$NODE_IP pods=$POD_CIDR services=$SERVICE_CIDR"
NODE_NAME=lekiwi-node
SOCK="$STATE/containerd/containerd.sock"
# Kernel-wide settings the kubelet changes (the network ones it and kube-proxy write belong to the
# node's namespace and go with it); `down` puts back the values saved before the first `up`.
SYSCTLS=(vm.overcommit_memory vm.panic_on_oom kernel.panic kernel.panic_on_oops
  kernel.keys.root_maxkeys kernel.keys.root_maxbytes)
PROCS=(etcd kube-apiserver containerd kubelet kube-controller-manager kube-scheduler kube-proxy)

log() { printf '[cluster] %s\n' "$*" >&2; }
die() { printf '[cluster] error: %s\n' "$*" >&2; exit 1; }
usage() { sed -n 's/^#!\( \|$\)//p' "${BASH_SOURCE[0]}"; }
kc() { "$BIN_DIR/kubectl" --kubeconfig "$STATE/kubeconfig" "$@"; }

# ---- processes (the same pid-file + marker scheme as scripts/testbed/control-plane.sh) ---------------
# Each process is identified by its pid file AND by a marker argument naming this directory, so a
# recycled pid never makes us signal or trust an unrelated process.
marker() {
  case "$1" in
    etcd) printf -- '--data-dir=%s/etcd' "$STATE" ;;
    kube-apiserver) printf -- '--cert-dir=%s/pki/generated' "$STATE" ;;
    containerd) printf -- '--config=%s/containerd/config.toml' "$STATE" ;;
    kubelet) printf -- '--root-dir=%s/kubelet' "$STATE" ;;
    kube-controller-manager) printf -- '--kubeconfig=%s/kubeconfigs/controller-manager' "$STATE" ;;
    kube-scheduler) printf -- '--kubeconfig=%s/kubeconfigs/scheduler' "$STATE" ;;
    kube-proxy) printf -- '--config=%s/kube-proxy.yaml' "$STATE" ;;
  esac
}

# shellcheck source=scripts/lib/procs.sh
source "$(dirname "${BASH_SOURCE[0]}")/../lib/procs.sh"

# Waits until "$@" succeeds; dies naming $what (and the log of $proc) after $TIMEOUT seconds.
# The last attempt's own output is printed too, and each step's time is logged (a slow step is
# the first thing to look at when a CI machine's `up` fails).
wait_for() {
  local what="$1" proc="$2" t0=$SECONDS deadline=$((SECONDS + TIMEOUT)) out
  shift 2
  until out=$("$@" 2>&1); do
    [ -z "$proc" ] || still_running "$proc" || { tail_log "$proc" 40; die "$proc exited (waiting for: $what)"; }
    if [ $SECONDS -ge $deadline ]; then
      [ -z "$proc" ] || tail_log "$proc" 40
      printf '[cluster] the last attempt printed:\n%s\n' "$(tail -n 20 <<<"$out")" >&2
      die "$what: not after ${TIMEOUT}s"
    fi
    sleep 0.3
  done
  log "$what (at ${SECONDS}s, this step $((SECONDS - t0))s)"
}

# ---- state: ports, certificates, tokens, kubeconfigs (created once) -------------------------
load_ports() {
  # shellcheck disable=SC1091
  [ -f "$STATE/ports.env" ] && . "$STATE/ports.env"
}

gen_cert() { # name subject extensions
  local pki="$STATE/pki"
  openssl req -newkey rsa:2048 -nodes -subj "$2" -keyout "$pki/$1.key" -out "$pki/$1.csr" 2>/dev/null
  printf 'basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature,keyEncipherment\n%s\n' \
    "$3" >"$pki/$1.ext"
  openssl x509 -req -days 3650 -in "$pki/$1.csr" -CA "$pki/ca.crt" -CAkey "$pki/ca.key" \
    -CAcreateserial -extfile "$pki/$1.ext" -out "$pki/$1.crt" 2>/dev/null
  chmod 600 "$pki/$1.key"
}

init_pki() {
  local pki="$STATE/pki"
  [ -s "$pki/kubelet.crt" ] && return 0
  log "generating the CA and certificates"
  mkdir -p "$pki/generated"
  openssl req -x509 -newkey rsa:2048 -nodes -days 3650 -subj "/CN=lekiwi-cluster-ca" \
    -keyout "$pki/ca.key" -out "$pki/ca.crt" -addext "basicConstraints=critical,CA:TRUE" \
    -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null
  gen_cert apiserver /CN=kube-apiserver "extendedKeyUsage=serverAuth
subjectAltName=IP:$NODE_IP,IP:127.0.0.1,IP:$KUBERNETES_IP,DNS:localhost,DNS:kubernetes,DNS:kubernetes.default,DNS:kubernetes.default.svc,DNS:kubernetes.default.svc.cluster.local"
  gen_cert apiserver-kubelet-client "/O=system:masters/CN=kube-apiserver-kubelet-client" \
    "extendedKeyUsage=clientAuth"
  gen_cert kubelet "/CN=$NODE_NAME" "extendedKeyUsage=serverAuth
subjectAltName=IP:$NODE_IP,DNS:$NODE_NAME"
  openssl genrsa -out "$STATE/sa.key" 2048 2>/dev/null
  openssl rsa -in "$STATE/sa.key" -pubout -out "$STATE/sa.pub" 2>/dev/null
  chmod 600 "$STATE/sa.key" "$pki/ca.key"
}

write_kubeconfig() { # name token
  mkdir -p "$STATE/kubeconfigs"
  local file="$STATE/kubeconfigs/$1"
  [ "$1" = admin ] && file="$STATE/kubeconfig"
  cat >"$file.tmp" <<EOF
apiVersion: v1
kind: Config
clusters:
- name: lekiwi
  cluster:
    server: https://$NODE_IP:$APISERVER_PORT
    certificate-authority-data: $(base64 -w0 "$STATE/pki/ca.crt")
users:
- name: $1
  user:
    token: $2
contexts:
- name: $1
  context: {cluster: lekiwi, user: $1, namespace: default}
current-context: $1
EOF
  chmod 600 "$file.tmp"
  mv -f "$file.tmp" "$file"
}

# One bearer token per identity; the kubelet is a real node identity (Node authorizer), the
# others are the users the RBAC bootstrap policy binds.
init_tokens() {
  [ -s "$STATE/tokens.csv" ] && return 0
  local line name user groups tok
  : >"$STATE/tokens.csv.tmp"
  for line in "admin admin system:masters" "kubelet system:node:$NODE_NAME system:nodes" \
      "controller-manager system:kube-controller-manager -" "scheduler system:kube-scheduler -" \
      "kube-proxy system:kube-proxy -"; do
    read -r name user groups <<<"$line"
    tok="$(openssl rand -hex 24)"
    if [ "$groups" = - ]; then
      printf '%s,%s,%s\n' "$tok" "$user" "$user" >>"$STATE/tokens.csv.tmp"
    else
      printf '%s,%s,%s,"%s"\n' "$tok" "$user" "$user" "$groups" >>"$STATE/tokens.csv.tmp"
    fi
    write_kubeconfig "$name" "$tok"
  done
  chmod 600 "$STATE/tokens.csv.tmp"
  mv -f "$STATE/tokens.csv.tmp" "$STATE/tokens.csv"
}

init_state() {
  mkdir -p "$STATE" "$STATE/kubelet" "$STATE/cni/net.d" "$STATE/containerd"
  mkdir -p -m 700 "$STATE/etcd"
  printf '%s\n' "$LAYOUT" >"$STATE/network"
  if [ ! -s "$STATE/ports.env" ]; then
    mapfile -t p < <(python3 "$SCRIPT_DIR/../lib/free-ports.py" 9)
    printf 'ETCD_PORT=%d\nETCD_PEER_PORT=%d\nAPISERVER_PORT=%d\nKUBELET_PORT=%d\nKUBELET_HEALTHZ_PORT=%d\nPROXY_HEALTHZ_PORT=%d\nPROXY_METRICS_PORT=%d\nCM_PORT=%d\nSCHED_PORT=%d\n' \
      "${p[@]}" >"$STATE/ports.env.tmp"
    mv -f "$STATE/ports.env.tmp" "$STATE/ports.env"
  fi
  load_ports
  init_pki
  init_tokens
  if [ ! -s "$STATE/sysctl.orig" ]; then
    local k
    for k in "${SYSCTLS[@]}"; do
      printf '%s=%s\n' "$k" "$(sysctl -n "$k" 2>/dev/null || echo -)"
    done >"$STATE/sysctl.orig"
  fi
}

restore_sysctls() {
  [ -s "$STATE/sysctl.orig" ] || return 0
  local k v
  while IFS='=' read -r k v; do
    [ "$v" = - ] || sysctl -qw "$k=$v" 2>/dev/null || log "could not restore $k=$v"
  done <"$STATE/sysctl.orig"
}

# ---- network --------------------------------------------------------------------------------
# Runs "$@" in the node's network namespace. nsenter, not `ip netns exec`: that one also gives the
# command a mount namespace of its own with a fresh /sys (no cgroup hierarchy for the kubelet and
# runc, and mounts the host's `down` could not see).
innet() { nsenter --net="$NETNS_PATH" -- "$@"; }

# The namespace, its veth pair and its bridge exist before anything starts: the node IP is the
# address the API server binds. br_netfilter's bridge-nf-call-iptables (a setting of each network
# namespace) makes bridged Pod-to-Service traffic see kube-proxy's rules.
setup_network() {
  # Kernels with loadable modules (CI runners) may not have loaded these yet; this one has them
  # built in and no /lib/modules, hence the `|| true`.
  [ -e /proc/sys/net/bridge ] || modprobe br_netfilter 2>/dev/null || true
  grep -qw overlay /proc/filesystems || modprobe overlay 2>/dev/null || true
  if [ ! -e "$NETNS_PATH" ]; then
    [ -e /run/netns ] || touch "$STATE/run-netns.created"
    ip netns add "$NETNS"
  fi
  if ! ip -n "$NETNS" link show "$NODE_LINK" >/dev/null 2>&1; then
    ip link del "$HOST_LINK" 2>/dev/null || true
    ip link add "$HOST_LINK" type veth peer name "$NODE_LINK" netns "$NETNS"
  fi
  ip addr replace "$HOST_IP/30" dev "$HOST_LINK"
  ip link set "$HOST_LINK" up
  ip -n "$NETNS" addr replace "$NODE_IP/30" dev "$NODE_LINK"
  ip -n "$NETNS" link set "$NODE_LINK" up
  ip -n "$NETNS" link set lo up
  ip route replace "$NODE_NET" via "$NODE_IP" dev "$HOST_LINK"
  ip -n "$NETNS" link show "$BRIDGE" >/dev/null 2>&1 || ip -n "$NETNS" link add "$BRIDGE" type bridge
  ip -n "$NETNS" addr replace "$BRIDGE_IP/${POD_CIDR#*/}" dev "$BRIDGE"
  ip -n "$NETNS" link set "$BRIDGE" up
  innet sysctl -qw net.ipv4.ip_forward=1
  innet sysctl -qw net.bridge.bridge-nf-call-iptables=1 2>/dev/null \
    || log "no br_netfilter: Pod-to-Service traffic between Pods on the bridge will not be NATed"
  bind_pod_logs
  cat >"$STATE/cni/net.d/10-lekiwi.conflist" <<EOF
{
  "cniVersion": "0.4.0",
  "name": "lekiwi",
  "plugins": [
    {
      "type": "bridge", "bridge": "$BRIDGE", "isGateway": true, "ipMasq": false,
      "hairpinMode": true,
      "ipam": {
        "type": "host-local", "dataDir": "$STATE/cni/ipam",
        "ranges": [[{"subnet": "$POD_CIDR", "gateway": "$BRIDGE_IP"}]],
        "routes": [{"dst": "0.0.0.0/0"}]
      }
    },
    {"type": "portmap", "capabilities": {"portMappings": true}}
  ]
}
EOF
}

# Deleting the namespace deletes everything in it (bridge, addresses, routes, iptables rules,
# sysctls) and the veth pair, whose host end carries the host's address and route.
teardown_network() {
  [ ! -e "$NETNS_PATH" ] || ip netns del "$NETNS"
  ip link del "$HOST_LINK" 2>/dev/null || true
  if [ -e "$STATE/run-netns.created" ]; then
    if [ -z "$(ls -A /run/netns 2>/dev/null)" ]; then
      ! mountpoint -q /run/netns || umount /run/netns
      rmdir /run/netns 2>/dev/null || true
    fi
    rm -f "$STATE/run-netns.created"
  fi
}

# The kubelet v1.20 writes container logs to /var/log/pods and links them from /var/log/containers
# (fixed paths). Both are bind mounts of directories under $STATE while the node runs, so `down`
# leaves no log behind; a directory `up` had to create is removed again by `down`.
bind_pod_logs() {
  local d
  for d in pods containers; do
    mkdir -p "$STATE/var-log/$d"
    mountpoint -q "/var/log/$d" && continue
    if [ ! -e "/var/log/$d" ]; then
      mkdir -p "/var/log/$d"
      touch "$STATE/var-log/$d.created"
    fi
    if [ -n "$(ls -A "/var/log/$d")" ]; then
      log "/var/log/$d is not empty (another kubelet?): our Pods' logs go there too"
      continue
    fi
    mount --bind "$STATE/var-log/$d" "/var/log/$d"
  done
}

unbind_pod_logs() {
  local d
  for d in pods containers; do
    if mountpoint -q "/var/log/$d" \
        && [ "$(findmnt -no FSROOT "/var/log/$d")" = "$STATE/var-log/$d" ]; then
      umount "/var/log/$d" || umount -l "/var/log/$d"
    fi
    if [ -e "$STATE/var-log/$d.created" ]; then
      rmdir "/var/log/$d" 2>/dev/null || log "/var/log/$d is not empty; left in place"
    fi
  done
  rm -rf "$STATE/var-log"
}

# A cluster made by this script before the node had a network namespace of its own ran in the
# host's: this deletes every iptables/ip6tables rule there that jumps to a KUBE-* or CNI-* chain,
# then those chains, as that version's `down` did.
clean_legacy_iptables() {
  local cmd
  for cmd in iptables ip6tables; do
    command -v "$cmd-save" >/dev/null || continue
    "$cmd-save" 2>/dev/null | python3 -c '
import re, shlex, subprocess, sys
cmd = sys.argv[1]
ours = re.compile(r"^(KUBE|CNI)-")
table, chains = None, []
for line in sys.stdin:
    line = line.rstrip("\n")
    if line.startswith("*"):
        table = line[1:]
    elif line.startswith(":"):
        name = line[1:].split()[0]
        if ours.match(name):
            chains.append((table, name))
    elif line.startswith("-A "):
        args = shlex.split(line)
        target = args[args.index("-j") + 1] if "-j" in args else ""
        if not ours.match(args[1]) and ours.match(target):
            subprocess.run([cmd, "-w", "-t", table, "-D"] + args[1:], check=False)
for table, name in chains:
    subprocess.run([cmd, "-w", "-t", table, "-F", name], check=False)
for table, name in chains:
    subprocess.run([cmd, "-w", "-t", table, "-X", name], check=False)
' "$cmd"
  done
}

# ---- configuration files --------------------------------------------------------------------
# This VM's kernel refuses writes to /proc/self/oom_score_adj; then runc needs scripts/testbed/runc-wrapper,
# copied into the state directory: the cluster outlives the checkout that started it (a deleted
# CI clone left containerd with "fork/exec .../scripts/testbed/runc-wrapper: no such file").
runc_binary() {
  if (echo -999 >/proc/self/oom_score_adj) 2>/dev/null; then
    command -v runc
  else
    install -m 0755 "$SCRIPT_DIR/runc-wrapper" "$STATE/runc-wrapper"
    echo "$STATE/runc-wrapper"
  fi
}

write_containerd_config() {
  mkdir -p "$STATE/containerd/opt"
  cat >"$STATE/containerd/config.toml" <<EOF
version = 2
root = "$STATE/containerd/root"
state = "$STATE/containerd/state"
disabled_plugins = ["io.containerd.snapshotter.v1.aufs", "io.containerd.snapshotter.v1.btrfs",
  "io.containerd.snapshotter.v1.devmapper", "io.containerd.snapshotter.v1.zfs"]
[grpc]
  address = "$SOCK"
[ttrpc]
  address = "$SOCK.ttrpc"
[debug]
  address = ""
[metrics]
  address = ""
[plugins."io.containerd.internal.v1.opt"]
  path = "$STATE/containerd/opt"
[plugins."io.containerd.grpc.v1.cri"]
  sandbox_image = "$PAUSE_REF"
  stream_server_address = "127.0.0.1"
  stream_server_port = "0"
  netns_mounts_under_state_dir = true
  [plugins."io.containerd.grpc.v1.cri".cni]
    bin_dir = "/usr/lib/cni"
    conf_dir = "$STATE/cni/net.d"
    max_conf_num = 1
  [plugins."io.containerd.grpc.v1.cri".containerd]
    snapshotter = "overlayfs"
    default_runtime_name = "runc"
    [plugins."io.containerd.grpc.v1.cri".containerd.runtimes.runc]
      runtime_type = "io.containerd.runc.v2"
      [plugins."io.containerd.grpc.v1.cri".containerd.runtimes.runc.options]
        BinaryName = "$(runc_binary)"
        SystemdCgroup = false
EOF
}

# Eviction thresholds are near zero: the test machine's disk is often fuller than the defaults
# allow, and no image evicted by GC could be pulled again.
write_kubelet_config() {
  cat >"$STATE/kubelet.yaml" <<EOF
apiVersion: kubelet.config.k8s.io/v1beta1
kind: KubeletConfiguration
address: $NODE_IP
port: $KUBELET_PORT
readOnlyPort: 0
healthzBindAddress: 127.0.0.1
healthzPort: $KUBELET_HEALTHZ_PORT
tlsCertFile: $STATE/pki/kubelet.crt
tlsPrivateKeyFile: $STATE/pki/kubelet.key
authentication:
  anonymous: {enabled: false}
  webhook: {enabled: true}
  x509: {clientCAFile: $STATE/pki/ca.crt}
authorization: {mode: Webhook}
cgroupDriver: cgroupfs
failSwapOn: false
clusterDomain: cluster.local
evictionHard: {memory.available: 50Mi, nodefs.available: 1%, imagefs.available: 1%, nodefs.inodesFree: 1%}
imageGCHighThresholdPercent: 100
imageGCLowThresholdPercent: 99
serializeImagePulls: false
EOF
  cat >"$STATE/kube-proxy.yaml" <<EOF
apiVersion: kubeproxy.config.k8s.io/v1alpha1
kind: KubeProxyConfiguration
clientConnection: {kubeconfig: $STATE/kubeconfigs/kube-proxy}
mode: iptables
hostnameOverride: $NODE_NAME
bindAddress: $NODE_IP
clusterCIDR: $POD_CIDR
nodePortAddresses: ["$NODE_IP/32"]
healthzBindAddress: 127.0.0.1:$PROXY_HEALTHZ_PORT
metricsBindAddress: 127.0.0.1:$PROXY_METRICS_PORT
conntrack: {maxPerCore: 0, min: 0, tcpEstablishedTimeout: 0s, tcpCloseWaitTimeout: 0s}
EOF
}

# ---- starting -------------------------------------------------------------------------------
# Every process of the cluster runs in the node's network namespace (nsenter execs it: the pid
# file names the process itself).
spawn_node() {
  local name="$1"
  shift
  spawn "$name" nsenter --net="$NETNS_PATH" -- "$@"
}

start_etcd() {
  spawn_node etcd "$K8S_DIR/etcd" --name=default "$(marker etcd)" \
    --listen-client-urls="http://127.0.0.1:$ETCD_PORT" \
    --advertise-client-urls="http://127.0.0.1:$ETCD_PORT" \
    --listen-peer-urls="http://127.0.0.1:$ETCD_PEER_PORT" \
    --initial-advertise-peer-urls="http://127.0.0.1:$ETCD_PEER_PORT" \
    --initial-cluster="default=http://127.0.0.1:$ETCD_PEER_PORT" \
    --heartbeat-interval=50 --election-timeout=500 --unsafe-no-fsync \
    --logger=zap --log-outputs=stderr
}

start_apiserver() {
  spawn_node kube-apiserver "$K8S_DIR/kube-apiserver" "$(marker kube-apiserver)" \
    --etcd-servers="http://127.0.0.1:$ETCD_PORT" \
    --secure-port="$APISERVER_PORT" --bind-address="$NODE_IP" --advertise-address="$NODE_IP" \
    --tls-cert-file="$STATE/pki/apiserver.crt" --tls-private-key-file="$STATE/pki/apiserver.key" \
    --client-ca-file="$STATE/pki/ca.crt" \
    --service-account-issuer=https://kubernetes.default.svc \
    --service-account-key-file="$STATE/sa.pub" \
    --service-account-signing-key-file="$STATE/sa.key" \
    --authorization-mode=Node,RBAC --enable-admission-plugins=NodeRestriction \
    --service-cluster-ip-range="$SERVICE_CIDR" --allow-privileged=true \
    --token-auth-file="$STATE/tokens.csv" \
    --kubelet-preferred-address-types=InternalIP \
    --kubelet-certificate-authority="$STATE/pki/ca.crt" \
    --kubelet-client-certificate="$STATE/pki/apiserver-kubelet-client.crt" \
    --kubelet-client-key="$STATE/pki/apiserver-kubelet-client.key"
}

start_controllers() {
  spawn_node kube-controller-manager "$K8S_DIR/kube-controller-manager" \
    "$(marker kube-controller-manager)" --controllers='*' --leader-elect=false \
    --use-service-account-credentials=true \
    --service-account-private-key-file="$STATE/sa.key" --root-ca-file="$STATE/pki/ca.crt" \
    --cluster-signing-cert-file="$STATE/pki/ca.crt" --cluster-signing-key-file="$STATE/pki/ca.key" \
    --port=0 --bind-address=127.0.0.1 --secure-port="$CM_PORT"
  spawn_node kube-scheduler "$K8S_DIR/kube-scheduler" "$(marker kube-scheduler)" \
    --leader-elect=false --port=0 --bind-address=127.0.0.1 --secure-port="$SCHED_PORT"
}

start_node() {
  write_containerd_config
  spawn_node containerd /usr/bin/containerd "$(marker containerd)"
  wait_for "containerd at $SOCK" containerd ctr --address "$SOCK" version
  [ -s "$PAUSE_TAR" ] || "$SCRIPT_DIR/../image.sh" pause >&2 || die "no pause image at $PAUSE_TAR"
  # containerd answers `version` before every plugin (content store, snapshotter) is loaded.
  wait_for "pause image imported into containerd" containerd \
    ctr --address "$SOCK" -n k8s.io images import "$PAUSE_TAR"
  write_kubelet_config
  spawn_node kubelet "$K8S_DIR/kubelet" "$(marker kubelet)" --config="$STATE/kubelet.yaml" \
    --kubeconfig="$STATE/kubeconfigs/kubelet" --container-runtime=remote \
    --container-runtime-endpoint="unix://$SOCK" --hostname-override="$NODE_NAME" \
    --node-ip="$NODE_IP"
  spawn_node kube-proxy "$K8S_DIR/kube-proxy" "$(marker kube-proxy)"
}

# ---- storage: StorageClass `standard` (default) with pre-made hostPath PVs ------------------
apply_storage() {
  local i docs=""
  for i in 0 1 2 3; do
    mkdir -p "$STATE/pv/pv-$i"
    chmod 0777 "$STATE/pv/pv-$i" # Pods run as non-root users
    docs+="---
apiVersion: v1
kind: PersistentVolume
metadata: {name: lekiwi-pv-$i, labels: {lekiwi.dev/test-cluster: \"true\"}}
spec:
  capacity: {storage: 1Gi}
  accessModes: [ReadWriteOnce]
  persistentVolumeReclaimPolicy: Retain
  storageClassName: standard
  hostPath: {path: $STATE/pv/pv-$i, type: Directory}
"
  done
  kc apply -f - >/dev/null <<EOF
apiVersion: storage.k8s.io/v1
kind: StorageClass
metadata:
  name: standard
  annotations: {storageclass.kubernetes.io/is-default-class: "true"}
provisioner: kubernetes.io/no-provisioner
volumeBindingMode: Immediate
reclaimPolicy: Retain
$docs
EOF
}

# A Released PV (its claim was deleted) is wiped and made Available again, so the four PVs last.
# Phase and claim come from one read of the PV, and the patch only applies while the claimRef is
# still that deleted claim's: a concurrent `up` or a claim bound meanwhile is never disturbed.
recycle_pvs() {
  local pv uid i
  while IFS=: read -r pv uid; do
    i="${pv#lekiwi-pv-}"
    [[ "$i" =~ ^[0-9]+$ ]] && [ -n "$uid" ] || continue
    find "$STATE/pv/pv-$i" -mindepth 1 -delete
    kc patch pv "$pv" --type=json -p "[{\"op\":\"test\",\"path\":\"/spec/claimRef/uid\",\"value\":\"$uid\"},
      {\"op\":\"remove\",\"path\":\"/spec/claimRef\"}]" >/dev/null 2>&1 || true
  done < <(kc get pv -l lekiwi.dev/test-cluster=true -o jsonpath='{range .items[?(@.status.phase=="Released")]}{.metadata.name}{":"}{.spec.claimRef.uid}{"\n"}{end}')
}

# ---- health ---------------------------------------------------------------------------------
apiserver_ready() {
  [ -n "${APISERVER_PORT:-}" ] || return 1
  [ "$(kc get --raw /readyz 2>/dev/null)" = ok ]
}

node_ready() {
  [ "$(kc get node "$NODE_NAME" \
    -o jsonpath='{.status.conditions[?(@.type=="Ready")].status}' 2>/dev/null)" = True ]
}

# The basics that need no DNS: the controller-manager made the default ServiceAccount's token,
# kube-proxy synced its rules, the StorageClass exists.
basics_ready() {
  [ -n "$(kc -n default get serviceaccount default -o jsonpath='{.secrets[0].name}' 2>/dev/null)" ] \
    && innet curl -fsS --max-time 2 "http://127.0.0.1:$PROXY_HEALTHZ_PORT/healthz" >/dev/null \
    && kc get storageclass standard >/dev/null 2>&1
}

# Whether process $1 of this directory is live and runs in the node's network namespace.
in_node() {
  local pid
  pid="$(live_pid "$1")" || return 1
  [ "$(stat -Lc %d:%i "/proc/$pid/ns/net" 2>/dev/null)" = "$(stat -Lc %d:%i "$NETNS_PATH" 2>/dev/null)" ]
}

all_live() {
  local name
  for name in "${PROCS[@]}"; do in_node "$name" || return 1; done
}

# Healthy = what `up` waits for, all of it: a cluster an interrupted `up` left half ready (the node
# Ready, the basics not yet) is finished by the next `up`, never taken as done.
healthy() {
  load_ports 2>/dev/null || return 1
  [ "$(cat "$STATE/network" 2>/dev/null)" = "$LAYOUT" ] && all_live && apiserver_ready && node_ready && basics_ready
}

# ---- up -------------------------------------------------------------------------------------
take_lock() {
  mkdir -p "$STATE"
  exec 9>"$STATE/.lock"
  flock -w 600 9 || die "timed out waiting for the lock $STATE/.lock"
}

resolve_binaries() {
  local b missing=0
  for b in etcd kube-apiserver kubelet kube-controller-manager kube-scheduler kube-proxy; do
    [ -x "$K8S_DIR/$b" ] || missing=1
  done
  for b in containerd ctr runc iptables conntrack ip; do
    command -v "$b" >/dev/null || missing=1
  done
  [ -x "$BIN_DIR/kubectl" ] && [ -d /usr/lib/cni ] || missing=1
  if [ $missing = 1 ]; then
    log "binaries missing; running scripts/setup.sh"
    LEKIWI_BUILD_NODE=1 "$SCRIPT_DIR/../setup.sh" >&2
  fi
  for b in etcd kube-apiserver kubelet kube-controller-manager kube-scheduler kube-proxy; do
    [ -x "$K8S_DIR/$b" ] || die "setup.sh did not produce $K8S_DIR/$b"
  done
}

# State made for another network plan is not reused (its certificates name other addresses, its
# etcd holds Service IPs of another range): what runs of it is stopped, what an older version of
# this script put in the host's namespace is removed, and the directory emptied (images are
# imported again when needed).
forget_other_layout() {
  [ -s "$STATE/ports.env" ] && [ "$(cat "$STATE/network" 2>/dev/null)" != "$LAYOUT" ] || return 0
  log "$STATE was made for another network plan: stopping it and starting afresh"
  load_ports
  stop_node
  teardown_network
  clean_legacy_host
  restore_sysctls
  find "$STATE" -mindepth 1 -maxdepth 1 ! -name .lock -exec rm -rf {} +
}

# A process that runs but not in the node's namespace (the namespace was deleted under it) has
# an address nobody reaches: the whole node starts again.
stop_strays() {
  local name
  for name in "${PROCS[@]}"; do
    if live_pid "$name" >/dev/null && ! in_node "$name"; then
      log "$name runs outside the namespace $NETNS: stopping every process of the node"
      stop_node
      return 0
    fi
  done
}

cmd_up() {
  [ "$(id -u)" = 0 ] || die "the node needs root (network namespace, iptables, mounts, cgroups)"
  if healthy; then recycle_pvs; return 0; fi
  take_lock
  if healthy; then recycle_pvs; return 0; fi
  local t0=$SECONDS
  resolve_binaries
  forget_other_layout
  init_state
  stop_strays
  setup_network
  live_pid etcd >/dev/null || { log "starting etcd on 127.0.0.1:$ETCD_PORT"; start_etcd; }
  wait_for "etcd healthy" etcd innet curl -fsS --max-time 2 "http://127.0.0.1:$ETCD_PORT/health"
  live_pid kube-apiserver >/dev/null || { log "starting kube-apiserver on https://$NODE_IP:$APISERVER_PORT"; start_apiserver; }
  wait_for "kube-apiserver ready" kube-apiserver apiserver_ready
  live_pid kube-controller-manager >/dev/null && live_pid kube-scheduler >/dev/null \
    || { stop_all_named kube-controller-manager kube-scheduler; log "starting controller-manager and scheduler"; start_controllers; }
  if ! live_pid containerd >/dev/null || ! live_pid kubelet >/dev/null || ! live_pid kube-proxy >/dev/null; then
    stop_all_named kube-proxy kubelet containerd
    log "starting containerd, kubelet and kube-proxy (node $NODE_NAME, $NODE_IP)"
    start_node
  fi
  # Retried like a readiness step: /readyz can answer ok before every resource is served.
  wait_for "StorageClass and PVs applied" kube-apiserver apply_storage
  wait_for "node $NODE_NAME Ready" kubelet node_ready
  wait_for "ServiceAccount token, kube-proxy sync, StorageClass" kube-proxy basics_ready
  recycle_pvs
  log "ready in $((SECONDS - t0))s: https://$NODE_IP:$APISERVER_PORT, KUBECONFIG=$STATE/kubeconfig"
}

# SIGTERM, then SIGKILL after 5 s (1 s for kube-apiserver, whose graceful shutdown waits ~10 s for
# watches that nobody needs at this point; its state is in etcd).
stop_all_named() {
  local name wait_s
  for name in "$@"; do
    wait_s=5
    [ "$name" = kube-apiserver ] && wait_s=1
    stop_proc "$name" TERM "$wait_s" || stop_proc "$name" KILL 5 || die "could not stop $name"
  done
}

# ---- down -----------------------------------------------------------------------------------
# With the controllers stopped (nothing recreates Pods), force-deleting every Pod lets the kubelet
# tear each down properly: CNI DEL (veth, IPAM, portmap rules), volume unmounts, log directories.
drain_pods() {
  live_pid kubelet >/dev/null && apiserver_ready || return 0
  stop_all_named kube-controller-manager kube-scheduler
  kc delete pods --all --all-namespaces --force --grace-period=0 --wait=false >/dev/null 2>&1 || true
  local deadline=$((SECONDS + 40)) t0=$SECONDS
  while [ $SECONDS -lt $deadline ]; do
    [ -z "$(ls -A "$STATE/kubelet/pods" 2>/dev/null)" ] \
      && [ -z "$(ctr --address "$SOCK" -n k8s.io tasks ls -q 2>/dev/null)" ] \
      && { log "the kubelet tore every Pod down in $((SECONDS - t0))s"; return 0; }
    sleep 0.5
  done
  log "the kubelet did not tear every Pod down in 40s; cleaning up by force"
}

# Whatever the kubelet left: container processes (every pid in a kubepods cgroup), the shims
# of this containerd, then the cgroups themselves.
kill_leftovers() {
  local f pid
  for f in /sys/fs/cgroup/*/kubepods /sys/fs/cgroup/kubepods; do
    [ -d "$f" ] || continue
    find "$f" -name cgroup.procs -exec cat {} + 2>/dev/null | xargs -r kill -9 2>/dev/null || true
  done
  for f in /proc/[0-9]*/cmdline; do
    pid="${f#/proc/}"; pid="${pid%/cmdline}"
    { tr '\0' '\n' <"$f"; } 2>/dev/null | grep -qxF -- "$SOCK" && kill -9 "$pid" 2>/dev/null || true
  done
  # A killed shim leaves its socket: /run/containerd/s/sha256("<containerd address>/<ns>/<id>").
  for f in "$STATE"/containerd/state/io.containerd.runtime.v2.task/*/*; do
    [ -d "$f" ] || continue
    rm -f "/run/containerd/s/$(printf '%s' "$SOCK/${f#"$STATE"/containerd/state/io.containerd.runtime.v2.task/}" \
      | sha256sum | cut -d' ' -f1)"
  done
  sleep 0.3
  for f in /sys/fs/cgroup/*/kubepods /sys/fs/cgroup/kubepods; do
    [ -d "$f" ] && find "$f" -depth -type d -exec rmdir {} + 2>/dev/null || true
  done
}

# Unmounts everything mounted under the state directory, deepest first.
unmount_all() {
  local m i
  for i in 1 2 3; do
    mapfile -t mounts < <(awk -v d="$STATE/" 'index($5, d) == 1 { print $5 }' /proc/self/mountinfo \
      | sort -r)
    [ ${#mounts[@]} = 0 ] && return 0
    for m in "${mounts[@]}"; do
      m="$(printf '%b' "$m")" # mountinfo escapes spaces as \040
      umount "$m" 2>/dev/null || umount -l "$m" 2>/dev/null || true
    done
  done
  [ -z "$(awk -v d="$STATE/" 'index($5, d) == 1' /proc/self/mountinfo)" ] \
    || die "mounts left under $STATE: $(awk -v d="$STATE/" 'index($5, d) == 1 { print $5 }' /proc/self/mountinfo)"
}

# Stops every process of the node and removes what they leave behind but the network.
stop_node() {
  drain_pods
  stop_all_named kube-proxy kubelet kube-scheduler kube-controller-manager
  local t
  if live_pid containerd >/dev/null; then
    for t in $(ctr --address "$SOCK" -n k8s.io tasks ls -q 2>/dev/null); do
      ctr --address "$SOCK" -n k8s.io tasks kill -s SIGKILL "$t" >/dev/null 2>&1 || true
    done
  fi
  stop_all_named containerd
  kill_leftovers
  unbind_pod_logs
  unmount_all
  rm -rf "$STATE/kubelet/pods" "$STATE/containerd/state" "$STATE/cni/ipam"
  stop_all_named kube-apiserver etcd
  for t in "${PROCS[@]}"; do rm -f "$STATE/$t.pid"; done
}

# What a version of this script from before the node's namespace left in the host's namespace
# (state without $STATE/network): its bridge and its KUBE-*/CNI-* chains.
clean_legacy_host() {
  [ -s "$STATE/ports.env" ] && [ ! -e "$STATE/network" ] || return 0
  ip link del "$BRIDGE" 2>/dev/null || true
  clean_legacy_iptables
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
  load_ports || true
  local t0=$SECONDS
  stop_node
  teardown_network
  clean_legacy_host
  restore_sysctls
  if [ $purge = 1 ]; then
    rm -rf "$STATE"
    log "stopped and removed $STATE in $((SECONDS - t0))s"
  else
    log "stopped in $((SECONDS - t0))s (certificates, etcd data and images kept in $STATE)"
  fi
}

# ---- status, env ----------------------------------------------------------------------------
cmd_status() {
  if ! load_ports 2>/dev/null; then
    echo "down (no state in $STATE)"
    return 1
  fi
  local state=down name
  healthy && state=up
  echo "$state"
  echo "state dir:  $STATE"
  echo "apiserver:  https://$NODE_IP:$APISERVER_PORT"
  echo "node:       $NODE_NAME, $NODE_IP in the network namespace $NETNS"
  echo "            (bridge $BRIDGE $BRIDGE_IP, Pods $POD_CIDR, Services $SERVICE_CIDR)"
  echo "host:       $HOST_IP on $HOST_LINK, a route to $NODE_NET via $NODE_IP"
  echo "containerd: $SOCK"
  for name in "${PROCS[@]}"; do
    printf '%-24s pid %s\n' "$name:" "$(live_pid "$name" || echo -)"
  done
  [ $state = up ]
}

cmd_env() {
  printf 'export KUBECONFIG=%q\n' "$STATE/kubeconfig"
  printf 'export PATH=%q:"$PATH"\n' "$BIN_DIR"
  printf 'export LEKIWI_NODE_IP=%q\n' "$NODE_IP"
  printf 'export LEKIWI_HOST_IP=%q\n' "$HOST_IP"
  printf 'export LEKIWI_NODE_NETNS=%q\n' "$NETNS"
  printf 'export LEKIWI_NODE_BRIDGE=%q\n' "$BRIDGE"
  printf 'export LEKIWI_POD_CIDR=%q\n' "$POD_CIDR"
  printf 'export LEKIWI_SERVICE_CIDR=%q\n' "$SERVICE_CIDR"
  printf 'export CONTAINERD_ADDRESS=%q\n' "$SOCK"
  printf 'export LEKIWI_CLUSTER_DIR=%q\n' "$STATE"
}

case "${1:-help}" in
  up) cmd_up ;;
  down) shift; cmd_down "$@" ;;
  clean) cmd_down --purge ;;
  status) cmd_status ;;
  env) cmd_env ;;
  help | -h | --help) usage ;;
  *) usage >&2; exit 2 ;;
esac
