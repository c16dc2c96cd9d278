#!/usr/bin/env bash
#! Builds the operator image (or the test bed's pause image) as a reproducible OCI archive, offline,
#! from this checkout and the host's Debian 12 files, and optionally loads it into containerd or
#! podman. The same commit gives the same digest: see "The operator image" in README.md.
set -euo pipefail

usage() {
  cat <<'EOF'
Usage: scripts/image.sh [operator|pause] [--out FILE] [--arch amd64] [--load ctr|podman]
                        [--address SOCK]

  operator (default)  ghcr.io/lekiwi-fleet/lekiwi-operator:<Chart.yaml appVersion>: the release
                      binary (cargo build --release --locked), the shared libraries ldd lists, the
                      CA bundle, /etc/passwd and /etc/group with user 65532, /tmp (1777). No
                      shell, no package manager; runs as 65532:65532.
                      Default output: target/image/lekiwi-operator-<tag>-<arch>.oci.tar
  pause               lekiwi.local/pause:3.2 from Debian's busybox-static, the test bed's sandbox
                      image. Default output: ~/.cache/lekiwi/images/pause.oci.tar

  --out FILE          where to write the archive
  --arch ARCH         amd64 (arm64: see README.md, "The operator image")
  --load ctr          import into containerd (ctr -n k8s.io images import) at --address
  --load podman       podman load
  --address SOCK      containerd socket for --load ctr (default /run/containerd/containerd.sock)

Environment: LEKIWI_IMAGE_TARGET (cargo target dir, default ~/.cache/lekiwi/image-target, kept
so later builds are incremental), SOURCE_DATE_EPOCH (default: the commit time of HEAD).
Prints the archive's path last, after its digest and size.
EOF
}

log() { printf '\033[1;34m[image]\033[0m %s\n' "$*" >&2; }
die() { printf '\033[1;31m[image]\033[0m %s\n' "$*" >&2; exit 1; }

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/cache-build.sh
source "$REPO/scripts/cache-build.sh"
CACHE="${LEKIWI_CACHE:-$HOME/.cache/lekiwi}"
KIND=operator OUT="" ARCH=amd64 LOAD="" ADDRESS=/run/containerd/containerd.sock
while [ $# -gt 0 ]; do
  case "$1" in
    operator|pause) KIND="$1" ;;
    --out) OUT="$2"; shift ;;
    --arch) ARCH="$2"; shift ;;
    --load) LOAD="$2"; shift ;;
    --address) ADDRESS="$2"; shift ;;
    -h|--help) usage; exit 0 ;;
    *) usage >&2; die "unknown argument: $1" ;;
  esac
  shift
done
case "$LOAD" in ""|ctr|podman) ;; *) die "--load: ctr or podman, not $LOAD" ;; esac
[ "$ARCH" = amd64 ] || die "--arch $ARCH: only amd64 is built here; README.md says how arm64 is built"
export SOURCE_DATE_EPOCH="${SOURCE_DATE_EPOCH:-$(git -C "$REPO" log -1 --format=%ct)}"

# We write the OCI layout ourselves (scripts/oci.py, ~250 lines of standard-library Python) rather
# than use buildah: buildah needs a storage driver, user namespaces or root, and its archives carry
# timestamps and history we would have to scrub, while an image of a few host files needs none of
# that; writing the tar ourselves makes sorted entries, owners 0:0 and fixed mtimes (the same
# digest twice) a property of the code instead of a set of flags.
pack() { python3 "$REPO/scripts/oci.py" --arch "$ARCH" "$@" >&2; }

build_pause() {
  [ -x /bin/busybox ] && /bin/busybox --list >/dev/null 2>&1 ||
    die "/bin/busybox is missing: run scripts/setup.sh (Debian package busybox-static)"
  REF=lekiwi.local/pause:3.2
  OUT="${OUT:-$CACHE/images/pause.oci.tar}"
  # PID 1 in a PID namespace ignores signals it has no handler for, so a bare `sleep` would sit out
  # the whole grace period and be killed. This shell traps TERM and INT and exits at once (like
  # the real pause), and, as PID 1, reaps whatever orphans a shared PID namespace hands it.
  pack --out "$OUT" --ref "$REF" --epoch 0 --file /bin/busybox:/bin/busybox:0755 \
    --entrypoint '["/bin/busybox","sh","-c","trap \"exit 0\" TERM INT; while :; do /bin/busybox sleep 2147483647 & wait $!; done"]' \
    --user 65535:65535 --label org.opencontainers.image.source=scripts/image.sh
}

# The shared libraries the binary loads, as ldd prints them (absolute paths, host's glibc).
libraries() {
  ldd "$1" | awk '$2 == "=>" && $3 ~ /^\// {print $3} $1 ~ /^\// {print $1}' | sort -u
}

build_operator() {
  local tag target bin
  tag="$(awk -F'"' '/^appVersion:/ {print $2}' "$REPO/charts/lekiwi-operator/Chart.yaml")"
  [ -n "$tag" ] || die "no appVersion in charts/lekiwi-operator/Chart.yaml"
  REF="ghcr.io/lekiwi-fleet/lekiwi-operator:$tag"
  OUT="${OUT:-$REPO/target/image/lekiwi-operator-$tag-$ARCH.oci.tar}"
  target="${LEKIWI_IMAGE_TARGET:-$CACHE/image-target}"
  # The build runs in a copy of the sources at a fixed path (scripts/cache-build.sh says why).
  local src="$CACHE/image-src"
  src_copy "$src"
  log "cargo build --release --locked -p lekiwi-operator (target dir $target)"
  # The binary must not depend on where the sources, the cargo home or the target dir are.
  # SOURCE_DATE_EPOCH is fixed for cargo: ring's build script reruns when it changes (at every
  # commit, with the commit time), rebuilding the whole TLS stack; nothing embeds a build date.
  clean_env
  ( cd "$src" && env "${CLEAN_ENV[@]}" CARGO_TARGET_DIR="$target" SOURCE_DATE_EPOCH=0 \
      RUSTFLAGS="--remap-path-prefix=$src=/src --remap-path-prefix=${CARGO_HOME:-$HOME/.cargo}=/cargo --remap-path-prefix=$target=/target" \
      cargo build --release --locked -p lekiwi-operator --bin lekiwi-operator )
  bin="$target/release/lekiwi-operator"
  local args=() lib stage
  stage="$(mktemp -d)"
  STAGE="$stage"
  trap 'rm -rf "$STAGE"' EXIT
  printf 'root:x:0:0:root:/root:/sbin/nologin\nnonroot:x:65532:65532:nonroot:/home/nonroot:/sbin/nologin\n' >"$stage/passwd"
  printf 'root:x:0:\nnonroot:x:65532:\n' >"$stage/group"
  # /etc/hosts (which Kubernetes writes) before DNS, as glibc does not without this file.
  printf 'hosts: files dns\n' >"$stage/nsswitch.conf"
  for lib in $(libraries "$bin"); do args+=(--file "$lib:$lib"); done
  pack --out "$OUT" --ref "$REF" \
    --file "$bin:/usr/bin/lekiwi-operator:0755" "${args[@]}" \
    --file /etc/ssl/certs/ca-certificates.crt:/etc/ssl/certs/ca-certificates.crt:0644 \
    --file "$stage/passwd:/etc/passwd:0644" --file "$stage/group:/etc/group:0644" \
    --file "$stage/nsswitch.conf:/etc/nsswitch.conf:0644" \
    --dir /tmp:1777 --dir /var/lib/lekiwi:0755 --dir /home/nonroot:0755 \
    --entrypoint '["/usr/bin/lekiwi-operator"]' --user 65532:65532 --workdir /home/nonroot \
    --env SSL_CERT_FILE=/etc/ssl/certs/ca-certificates.crt \
    --label "org.opencontainers.image.version=$tag" \
    --label org.opencontainers.image.source=https://github.com/lekiwi-fleet/lekiwi-fleet \
    --label "org.opencontainers.image.revision=$(git -C "$REPO" rev-parse HEAD)"
}

case "$KIND" in
  pause) build_pause ;;
  operator) build_operator ;;
esac

case "$LOAD" in
  ctr) log "ctr -n k8s.io images import ($ADDRESS)"
       ctr --address "$ADDRESS" -n k8s.io images import "$OUT" >&2 ;;
  podman) log "podman load"; podman load -i "$OUT" >&2 ;;
esac
echo "$OUT"
