#!/usr/bin/env bash
#! Builds the operator image (linux/amd64 and linux/arm64, or the test bed's pause image) as a
#! reproducible OCI archive, offline, from this checkout and the host's Debian 12 files, and
#! optionally loads the host's platform into containerd or podman. The same commit gives the same
#! digest: see docs/src/install/image.md.
set -euo pipefail

usage() {
  cat <<'EOF'
Usage: scripts/image.sh [operator|pause] [--out FILE] [--arch LIST] [--load ctr|podman]
                        [--address SOCK] [--arm64-profile NAME]

  operator (default)  ghcr.io/lekiwi-fleet/lekiwi-operator:<Chart.yaml appVersion> for linux/amd64
                      and linux/arm64; for each, the release binary (cargo build --release
                      --locked; for arm64 cross-built with Debian's rustc), the shared libraries
                      it loads, the CA bundle, /etc/passwd and /etc/group with user 65532, /tmp
                      (1777). No shell, no package manager; runs as 65532:65532.
                      Default output: target/image/lekiwi-operator-<tag>.oci.tar (an OCI image
                      index of both platforms), and beside it each platform's own archive,
                      target/image/lekiwi-operator-<tag>-<arch>.oci.tar
  pause               lekiwi.local/pause:3.2 from Debian's busybox-static, the test bed's sandbox
                      image (amd64). Default output: ~/.cache/lekiwi/images/pause.oci.tar

  --out FILE          where to write the archive; with two platforms their own archives go beside
                      it, named FILE without .tar (and .oci) plus -<arch>.oci.tar
  --arch LIST         amd64,arm64 (the operator's default) or one of them: a single-platform
                      archive (--arch amd64 skips the arm64 cross-build, for quick local work)
  --load ctr          import the host's platform (amd64) into containerd (ctr -n k8s.io images
                      import) at --address
  --load podman       podman load (the host's platform)
  --address SOCK      containerd socket for --load ctr (default /run/containerd/containerd.sock)
  --arm64-profile NAME
                      the cargo profile of the arm64 cross-build (default release, what a lab
                      runs; also LEKIWI_IMAGE_ARM64_PROFILE). The test suite builds `image-check`
                      (Cargo.toml: release at opt-level 0), a fraction of release's cold build
                      time; either way the image's label fleet.lekiwi.io/cargo-profile names it

Environment: LEKIWI_IMAGE_TARGET (cargo target dir, default ~/.cache/lekiwi/image-target, kept
so later builds are incremental), LEKIWI_IMAGE_TARGET_ARM64 (the aarch64 build's, with Debian's
rustc: default ~/.cache/lekiwi/image-target-arm64), SOURCE_DATE_EPOCH (default: the commit time
of HEAD).
Prints the archive's path last, after its digest and size.
EOF
}

log() { printf '\033[1;34m[image]\033[0m %s\n' "$*" >&2; }
die() { printf '\033[1;31m[image]\033[0m %s\n' "$*" >&2; exit 1; }

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/lib/cache-build.sh
source "$REPO/scripts/lib/cache-build.sh"
CACHE="${LEKIWI_CACHE:-$HOME/.cache/lekiwi}"
KIND=operator OUT="" ARCHES="" LOAD="" ADDRESS=/run/containerd/containerd.sock
ARM64_PROFILE="${LEKIWI_IMAGE_ARM64_PROFILE:-release}"
HOST_ARCH=amd64
while [ $# -gt 0 ]; do
  case "$1" in
    operator|pause) KIND="$1" ;;
    --out) OUT="$2"; shift ;;
    --arch) ARCHES="$2"; shift ;;
    --load) LOAD="$2"; shift ;;
    --address) ADDRESS="$2"; shift ;;
    --arm64-profile) ARM64_PROFILE="$2"; shift ;;
    -h|--help) usage; exit 0 ;;
    *) usage >&2; die "unknown argument: $1" ;;
  esac
  shift
done
case "$LOAD" in ""|ctr|podman) ;; *) die "--load: ctr or podman, not $LOAD" ;; esac
grep -q "^\[profile\.$ARM64_PROFILE\]\$" "$REPO/Cargo.toml" || [ "$ARM64_PROFILE" = release ] ||
  die "--arm64-profile $ARM64_PROFILE: no such profile in Cargo.toml (release or image-check)"
[ "$(dpkg --print-architecture)" = "$HOST_ARCH" ] || die "this script runs on an amd64 host"
case "$KIND:${ARCHES:-default}" in
  pause:default|pause:amd64) ARCHES=amd64 ;;
  pause:*) die "--arch $ARCHES: the pause image is built for amd64 only" ;;
  operator:default) ARCHES=amd64,arm64 ;;
  operator:amd64|operator:arm64|operator:amd64,arm64) ;;
  operator:arm64,amd64) ARCHES=amd64,arm64 ;;
  *) die "--arch $ARCHES: amd64, arm64 or amd64,arm64" ;;
esac
IFS=, read -r -a ARCH_LIST <<<"$ARCHES"
[ -z "$LOAD" ] || [[ ",$ARCHES," == *",$HOST_ARCH,"* ]] ||
  die "--load loads the host's platform: build $HOST_ARCH too"
export SOURCE_DATE_EPOCH="${SOURCE_DATE_EPOCH:-$(git -C "$REPO" log -1 --format=%ct)}"

# We write the OCI layout ourselves (scripts/lib/oci.py, ~300 lines of standard-library Python) rather
# than use buildah: buildah needs a storage driver, user namespaces or root, and its archives carry
# timestamps and history we would have to scrub, while an image of a few host files needs none of
# that; writing the tar ourselves makes sorted entries, owners 0:0 and fixed mtimes (the same
# digest twice) a property of the code instead of a set of flags.
pack() { python3 "$REPO/scripts/lib/oci.py" "$@" >&2; }

build_pause() {
  [ -x /bin/busybox ] && /bin/busybox --list >/dev/null 2>&1 ||
    die "/bin/busybox is missing: run scripts/setup.sh (Debian package busybox-static)"
  REF=lekiwi.local/pause:3.2
  OUT="${OUT:-$CACHE/images/pause.oci.tar}"
  LOAD_FILE="$OUT"
  # PID 1 in a PID namespace ignores signals it has no handler for, so a bare `sleep` would sit out
  # the whole grace period and be killed. This shell traps TERM and INT and exits at once (like
  # the real pause), and, as PID 1, reaps whatever orphans a shared PID namespace hands it.
  pack --out "$OUT" --ref "$REF" --arch amd64 --epoch 0 --file /bin/busybox:/bin/busybox:0755 \
    --entrypoint '["/bin/busybox","sh","-c","trap \"exit 0\" TERM INT; while :; do /bin/busybox sleep 2147483647 & wait $!; done"]' \
    --user 65535:65535 --label org.opencontainers.image.source=scripts/image.sh
}

# The shared libraries the amd64 binary $1 loads, as ldd prints them (absolute paths, host's
# glibc), as oci.py's SRC:DEST pairs.
amd64_libraries() {
  ldd "$1" | awk '$2 == "=>" && $3 ~ /^\// {print $3 ":" $3} $1 ~ /^\// {print $1 ":" $1}' | sort -u
}

# The same for the aarch64 binary $1, which ldd cannot run: its ELF interpreter and its NEEDED
# libraries (and theirs), where Debian arm64 has them. They come from the host's libc6:arm64 and
# libgcc-s1:arm64 (dpkg multiarch, dependencies of libstd-rust-web-dev:arm64), which apt keeps at
# the same version as amd64's, security updates included; the cross sysroot's may lag behind.
arm64_libraries() {
  local sysroot=/lib/aarch64-linux-gnu interp f lib seen=" " todo=("$1")
  interp="$(aarch64-linux-gnu-readelf -l "$1" | sed -nE 's/.*program interpreter: ([^]]+)\]/\1/p')"
  [ -n "$interp" ] || die "$1 has no ELF interpreter"
  seen+="$(basename "$interp") "
  {
    echo "$sysroot/$(basename "$interp"):$interp"
    while [ ${#todo[@]} -gt 0 ]; do
      f="${todo[0]}" && todo=("${todo[@]:1}")
      for lib in $(aarch64-linux-gnu-readelf -d "$f" | sed -nE 's/.*\(NEEDED\).*\[(.*)\]/\1/p'); do
        case "$seen" in *" $lib "*) continue ;; esac
        seen+="$lib "
        [ -e "$sysroot/$lib" ] || die "$lib (needed by $f) is not in $sysroot (run scripts/setup.sh)"
        echo "$sysroot/$lib:/lib/aarch64-linux-gnu/$lib"
        todo+=("$sysroot/$lib")
      done
    done
  } | sort -u
}

# Builds the operator for $1 (amd64, or arm64 with Debian's rustc, as scripts/testbed/pi.sh builds the
# agent) from the source copy $2; sets BIN to the binary and PROFILE to its cargo profile (amd64:
# release; arm64: $ARM64_PROFILE). The binary must not depend on where the sources, the cargo home
# or the target dir are. SOURCE_DATE_EPOCH is fixed for cargo: ring's build script reruns when it
# changes (at every commit, with the commit time), rebuilding the whole TLS stack; nothing embeds
# a build date.
cargo_build() {
  local arch="$1" src="$2" target cross=()
  target="${LEKIWI_IMAGE_TARGET:-$CACHE/image-target}"
  PROFILE=release
  if [ "$arch" = arm64 ]; then
    # Its own target dir: Debian's rustc 1.96 and rustup's would otherwise rebuild each other's
    # build scripts; and not scripts/testbed/pi.sh's: different sources path and RUSTFLAGS rebuild all.
    target="${LEKIWI_IMAGE_TARGET_ARM64:-$CACHE/image-target-arm64}"
    PROFILE="$ARM64_PROFILE"
    [ -x /usr/bin/rustc ] && command -v aarch64-linux-gnu-gcc >/dev/null ||
      die "the arm64 toolchain is missing: run scripts/setup.sh (or build with --arch amd64)"
    cross=(RUSTC=/usr/bin/rustc CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_LINKER=aarch64-linux-gnu-gcc
      CC_aarch64_unknown_linux_gnu=aarch64-linux-gnu-gcc)
  fi
  local cargo=cargo triple=() bin="$target/$PROFILE/lekiwi-operator"
  [ "$arch" = amd64 ] || { cargo=/usr/bin/cargo triple=(--target aarch64-unknown-linux-gnu)
    bin="$target/aarch64-unknown-linux-gnu/$PROFILE/lekiwi-operator"; }
  log "cargo build --profile $PROFILE --locked -p lekiwi-operator ${triple[*]} (target dir $target)"
  clean_env
  local t0=$SECONDS
  ( cd "$src" && env "${CLEAN_ENV[@]}" "${cross[@]}" CARGO_TARGET_DIR="$target" SOURCE_DATE_EPOCH=0 \
      RUSTFLAGS="--remap-path-prefix=$src=/src --remap-path-prefix=${CARGO_HOME:-$HOME/.cargo}=/cargo --remap-path-prefix=$target=/target" \
      "$cargo" build --profile "$PROFILE" --locked -p lekiwi-operator --bin lekiwi-operator "${triple[@]}" )
  log "$arch build ($PROFILE): $((SECONDS - t0)) s"
  BIN="$bin"
}

# Packs the operator image for $1 from BIN into archive $2 (files shared by all platforms in
# $STAGE).
pack_operator() {
  local arch="$1" out="$2" args=() lib libs
  libs="$("${arch}_libraries" "$BIN")" || die "listing the libraries of $BIN failed"
  for lib in $libs; do args+=(--file "$lib"); done
  pack --out "$out" --ref "$REF" --arch "$arch" \
    --file "$BIN:/usr/bin/lekiwi-operator:0755" "${args[@]}" \
    --file /etc/ssl/certs/ca-certificates.crt:/etc/ssl/certs/ca-certificates.crt:0644 \
    --file "$STAGE/passwd:/etc/passwd:0644" --file "$STAGE/group:/etc/group:0644" \
    --file "$STAGE/nsswitch.conf:/etc/nsswitch.conf:0644" \
    --dir /tmp:1777 --dir /var/lib/lekiwi:0755 --dir /home/nonroot:0755 \
    --entrypoint '["/usr/bin/lekiwi-operator"]' --user 65532:65532 --workdir /home/nonroot \
    --env SSL_CERT_FILE=/etc/ssl/certs/ca-certificates.crt \
    --label "org.opencontainers.image.version=$TAG" --label "fleet.lekiwi.io/cargo-profile=$PROFILE" \
    --label org.opencontainers.image.source=https://github.com/lekiwi-fleet/lekiwi-fleet \
    --label "org.opencontainers.image.revision=$(git -C "$REPO" rev-parse HEAD)"
}

build_operator() {
  TAG="$(awk -F'"' '/^appVersion:/ {print $2}' "$REPO/charts/lekiwi-operator/Chart.yaml")"
  [ -n "$TAG" ] || die "no appVersion in charts/lekiwi-operator/Chart.yaml"
  REF="ghcr.io/lekiwi-fleet/lekiwi-operator:$TAG"
  local arch base out merge=()
  if [ ${#ARCH_LIST[@]} = 1 ]; then
    OUT="${OUT:-$REPO/target/image/lekiwi-operator-$TAG-$ARCHES.oci.tar}"
  else
    OUT="${OUT:-$REPO/target/image/lekiwi-operator-$TAG.oci.tar}"
  fi
  base="${OUT%.tar}" && base="${base%.oci}"
  STAGE="$(mktemp -d)"
  trap 'rm -rf "$STAGE"' EXIT
  printf 'root:x:0:0:root:/root:/sbin/nologin\nnonroot:x:65532:65532:nonroot:/home/nonroot:/sbin/nologin\n' >"$STAGE/passwd"
  printf 'root:x:0:\nnonroot:x:65532:\n' >"$STAGE/group"
  # /etc/hosts (which Kubernetes writes) before DNS, as glibc does not without this file.
  printf 'hosts: files dns\n' >"$STAGE/nsswitch.conf"
  # One build at a time: the source copy and the target dirs are shared by every checkout.
  mkdir -p "$CACHE"
  exec 9>"$CACHE/.image.lock"
  flock 9
  # The build runs in a copy of the sources at a fixed path (scripts/lib/cache-build.sh says why).
  local src="$CACHE/image-src"
  src_copy "$src"
  for arch in "${ARCH_LIST[@]}"; do
    cargo_build "$arch" "$src"
    out="$OUT"
    [ ${#ARCH_LIST[@]} = 1 ] || out="$base-$arch.oci.tar"
    pack_operator "$arch" "$out"
    merge+=(--merge "$out")
    [ "$arch" != "$HOST_ARCH" ] || LOAD_FILE="$out"
  done
  [ ${#ARCH_LIST[@]} = 1 ] || pack --out "$OUT" --ref "$REF" "${merge[@]}"
}

LOAD_FILE=""
case "$KIND" in
  pause) build_pause ;;
  operator) build_operator ;;
esac

case "$LOAD" in
  ctr) log "ctr -n k8s.io images import $LOAD_FILE ($ADDRESS)"
       ctr --address "$ADDRESS" -n k8s.io images import "$LOAD_FILE" >&2 ;;
  podman) log "podman load $LOAD_FILE"; podman load -i "$LOAD_FILE" >&2 ;;
esac
echo "$OUT"
