#!/usr/bin/env bash
#! The lekiwi-agent Debian package for a robot: builds the agent and packs
#! target/deb/lekiwi-agent_<version>_<arch>.deb with dpkg-deb from a staging directory.
#!
#! Usage: scripts/deb.sh [--arch arm64|amd64] [--out DIR]
#!   --arch arm64   (default) the Raspberry Pi 5 (Raspberry Pi OS 64-bit, Debian bookworm arm64):
#!                  cross-built with scripts/testbed/pi.sh's toolchain (Debian's rustc, in
#!                  $LEKIWI_CACHE/arm64-target, shared with `scripts/testbed/pi.sh build`)
#!   --arch amd64   this machine's architecture, built with the workspace's cargo
#!                  ($CARGO_TARGET_DIR or target/)
#!   --out DIR      where the .deb goes (default: target/deb in the checkout)
#!
#! The package holds
#!   /usr/bin/lekiwi-agent                     the stripped release binary
#!   /lib/systemd/system/lekiwi-agent.service  manifests/systemd/lekiwi-agent.service (hardened)
#!   /lib/systemd/system/lekiwi-agent-guard.{service,timer}  the agent update guard's periodic
#!                                             check (enabled with lekiwi-agent.service)
#!   /etc/lekiwi/agent.yaml                    the configuration the unit reads (a conffile:
#!                                             upgrades keep a lab's edits)
#!   /usr/share/doc/lekiwi-agent/copyright
#! and maintainer scripts (agent/debian/postinst, prerm, postrm: systemd's reload, and on purge
#! the state in /var/lib/lekiwi). The service is neither enabled nor started by the install:
#! `lekiwi-agent join ...` (printed by `kubectl lekiwi enroll-token --print-join-command`) writes
#! /etc/lekiwi/agent.d/50-join.yaml, /etc/lekiwi/ca.crt, /etc/lekiwi/enrollment-token and starts it.
#!
#! The build is the release profile, not the size-optimised `agent` profile: the aarch64 release
#! build is the one scripts/testbed/pi.sh and the tests already make (warm), while the `agent` profile's
#! fat LTO would add a second cold aarch64 build of several minutes to the test suite.
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
CACHE="${LEKIWI_CACHE:-$HOME/.cache/lekiwi}"

log() { printf '\033[1;34m[deb]\033[0m %s\n' "$*" >&2; }
die() { printf '\033[1;31m[deb]\033[0m error: %s\n' "$*" >&2; exit 1; }
usage() { sed -n 's/^#!\( \|$\)//p' "${BASH_SOURCE[0]}"; }

# dpkg-deb rather than cargo-deb: dpkg-deb is on every Debian machine, while cargo-deb would be one
# more tool to install and cache, and it cannot use Debian's rustc for the cross build as pi.sh does.
arch=arm64 out="$REPO/target/deb"
while [ $# -gt 0 ]; do
  case "$1" in
    --arch) arch="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    -h | --help | help) usage; exit 0 ;;
    *) usage >&2; exit 2 ;;
  esac
done

t0=$(date +%s)
case "$arch" in
  arm64)
    # `pi.sh build` cross-builds the release agent (and the initramfs the tests boot; cached).
    bash "$REPO/scripts/testbed/pi.sh" build
    bin="${LEKIWI_ARM64_TARGET:-$CACHE/arm64-target}/aarch64-unknown-linux-gnu/release/lekiwi-agent"
    strip=aarch64-linux-gnu-strip
    ;;
  amd64)
    log "building lekiwi-agent (release)"
    (cd "$REPO" && cargo build --quiet --release -p lekiwi-agent)
    bin="${CARGO_TARGET_DIR:-$REPO/target}/release/lekiwi-agent"
    strip=strip
    ;;
  *) die "--arch must be arm64 or amd64" ;;
esac
[ -x "$bin" ] || die "no binary at $bin"

version="$(sed -nE 's/^version = "([^"]+)"/\1/p' "$REPO/Cargo.toml" | head -1)"
stage="$(mktemp -d)"
trap 'rm -rf "$stage"' EXIT
chmod 0755 "$stage"
install -d "$stage/DEBIAN" "$stage/usr/bin" "$stage/lib/systemd/system" "$stage/etc/lekiwi" \
  "$stage/usr/share/doc/lekiwi-agent"
$strip -o "$stage/usr/bin/lekiwi-agent" "$bin"
chmod 0755 "$stage/usr/bin/lekiwi-agent"
install -m 0644 "$REPO/manifests/systemd/lekiwi-agent.service" \
  "$REPO/manifests/systemd/lekiwi-agent-guard.service" \
  "$REPO/manifests/systemd/lekiwi-agent-guard.timer" "$stage/lib/systemd/system/"
install -m 0644 "$REPO/agent/debian/agent.yaml" "$stage/etc/lekiwi/agent.yaml"
install -m 0644 "$REPO/agent/debian/copyright" "$stage/usr/share/doc/lekiwi-agent/copyright"
for s in postinst prerm postrm; do
  [ ! -e "$REPO/agent/debian/$s" ] || install -m 0755 "$REPO/agent/debian/$s" "$stage/DEBIAN/$s"
done
echo /etc/lekiwi/agent.yaml >"$stage/DEBIAN/conffiles"
cat >"$stage/DEBIAN/control" <<EOF
Package: lekiwi-agent
Version: $version
Architecture: $arch
Maintainer: LeKiwi fleet maintainers
Installed-Size: $(du -sk --exclude=DEBIAN "$stage" | cut -f1)
Depends: libc6 (>= 2.34), libgcc-s1
Section: utils
Priority: optional
Description: LeKiwi fleet agent
 Connects a LeKiwi robot to its fleet's gateway: heartbeats, telemetry, teleoperation detection
 and release updates. Runs as the hardened systemd unit lekiwi-agent.service.
EOF
mkdir -p "$out"
deb="$out/lekiwi-agent_${version}_${arch}.deb"
# Reproducible: the files' mtimes are the commit's time.
export SOURCE_DATE_EPOCH="${SOURCE_DATE_EPOCH:-$(git -C "$REPO" log -1 --format=%ct 2>/dev/null || date +%s)}"
find "$stage" -exec touch -h -d "@$SOURCE_DATE_EPOCH" {} +
dpkg-deb --root-owner-group -Zxz --build "$stage" "$deb" >/dev/null
log "$deb ($(du -h "$deb" | cut -f1); binary $(stat -c %s "$stage/usr/bin/lekiwi-agent") bytes stripped) in $(( $(date +%s) - t0 ))s"
echo "$deb"
