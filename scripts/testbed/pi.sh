#!/usr/bin/env bash
#! Emulated Raspberry Pi 5s for the arm64 agent: cross-builds the agent (and its unit-test binary)
#! for aarch64 with Debian's rustc, builds an initramfs around it (Debian's arm64 cloud kernel,
#! busybox-static, the cross sysroot's glibc) and boots it on QEMU's `virt` machine with a
#! Cortex-A76, the Pi 5's core. The guest reaches the host's loopback as 10.0.2.2.
#!
#! Usage: scripts/testbed/pi.sh <command> [options]
#!   build                 cross-build and assemble; heavy artefacts cached under $LEKIWI_CACHE/pi
#!                         (default ~/.cache/lekiwi/pi); a warm run only asks cargo whether
#!                         anything changed. Needs what scripts/setup.sh installs.
#!   boot [options] [-- AGENT-ARGS...]
#!                         boot guests (daemonised; see `stop`). Each has its own directory
#!                         $LEKIWI_PI_RUN/NAME (default $LEKIWI_CACHE/pi/run/NAME) with console.log
#!                         (the serial console) and qemu.pid. AGENT-ARGS go to the agent, one
#!                         argument each, exactly as given.
#!     --name NAME         guest name (default pi); with --count N the names are NAME-0..NAME-(N-1)
#!     --count N           how many guests (default 1)
#!     --run WHAT          agent (default): run /bin/lekiwi-agent AGENT-ARGS; unit-tests: run the
#!                         agent crate's unit-test binary; script: run /lekiwi/run.sh from the
#!                         payload; shell: a shell on the console
#!     --payload DIR       files put into the guest under /lekiwi (token, CA, ...); optional
#!     --status-port P     host port forwarded to guest port 9477 (the agent's status endpoint:
#!                         pass --status-listen 0.0.0.0:9477); with --count, P, P+1, ...
#!     --memory MB         guest memory (default 512)
#!     --forward H:G       with --rootfs: also forward host port 127.0.0.1:H to guest port G
#!                         (repeatable; e.g. prometheus-node-exporter's 9100)
#!     --foreground        one guest, not daemonised: this process becomes QEMU and ends when
#!                         the guest powers off (for tests)
#!     --rootfs            boot the Debian root filesystem (see `rootfs`) with systemd as PID 1,
#!                         on a copy-on-write overlay of the cached image; --payload DIR is then a
#!                         second disk mounted at /payload whose run.sh lekiwi-payload.service
#!                         runs at every boot (output on the console); no AGENT-ARGS. The guest's
#!                         `systemctl reboot` reboots it in the same QEMU process
#!   rootfs                build, once, a Debian bookworm arm64 root filesystem with systemd, dpkg
#!                         and prometheus-node-exporter into $LEKIWI_CACHE/pi/debian-arm64.qcow2:
#!                         `debootstrap --foreign` downloads, this machine's dpkg unpacks, the
#!                         emulated Pi only configures; rebuilt only when its recipe (this
#!                         script's rootfs functions) changes. Needs `build` first (and gcc)
#!   stop [NAME...]        kill the named guests (default: all) and delete their directories
#!   status                list running guests
#!   help                  this text
#!
#! The guest's /init prints, on the serial console:
#!   LEKIWI-CPU <the first "CPU part" line of /proc/cpuinfo>
#!   LEKIWI-RSS <the agent's VmRSS line>          (every 10 s while the agent runs)
#!   LEKIWI-EXIT run=<what> status=<exit status>  (then it powers the guest off)
#!
#! Environment: LEKIWI_CACHE, LEKIWI_PI_RUN, LEKIWI_ARM64_TARGET (the aarch64 target directory,
#! default $LEKIWI_CACHE/arm64-target: Debian's rustc 1.96 builds there, apart from rustup's).
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
# shellcheck source=scripts/lib/cache-build.sh
source "$REPO/scripts/lib/cache-build.sh"
CACHE="${LEKIWI_CACHE:-$HOME/.cache/lekiwi}"
PI="$CACHE/pi"
RUN="${LEKIWI_PI_RUN:-$PI/run}"
TARGET_DIR="${LEKIWI_ARM64_TARGET:-$CACHE/arm64-target}"
TRIPLE=aarch64-unknown-linux-gnu
MODULES=(virtio_ring virtio virtio_mmio virtio_blk failover net_failover virtio_net) # in load order
LIBS=(ld-linux-aarch64.so.1 libc.so.6 libm.so.6 libgcc_s.so.1 libpthread.so.0 libdl.so.2 librt.so.1)

log() { printf '\033[1;34m[pi]\033[0m %s\n' "$*" >&2; }
die() { printf '\033[1;31m[pi]\033[0m error: %s\n' "$*" >&2; exit 1; }
usage() { sed -n 's/^#!\( \|$\)//p' "${BASH_SOURCE[0]}"; }

# Debian's cargo and rustc for the aarch64 build, without what a calling `cargo test` exported
# (its CARGO_PKG_* variables would make build scripts, and so ring, rebuild).
cross_cargo() {
  clean_env
  env "${CLEAN_ENV[@]}" CARGO_TARGET_DIR="$TARGET_DIR" RUSTC=/usr/bin/rustc \
    CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_LINKER=aarch64-linux-gnu-gcc \
    CC_aarch64_unknown_linux_gnu=aarch64-linux-gnu-gcc \
    /usr/bin/cargo "$@"
}

# Downloads arm64 package $1 once (kept in $PI/debs) and unpacks it into directory $2.
unpack_pkg() {
  local deb
  deb="$(ls "$PI/debs/$1"_*_arm64.deb 2>/dev/null | head -1 || true)"
  if [ -z "$deb" ]; then
    log "fetching $1:arm64"
    mkdir -p "$PI/debs"
    ( cd "$PI/debs" && apt-get download -q -o APT::Sandbox::User=root "$1:arm64" >/dev/null ) || die "apt-get download $1:arm64 failed"
    deb="$(ls "$PI/debs/$1"_*_arm64.deb | head -1)"
  fi
  dpkg-deb -x "$deb" "$2"
}

# The kernel package linux-image-cloud-arm64 currently points at.
kernel_pkg() {
  apt-cache depends linux-image-cloud-arm64:arm64 2>/dev/null \
    | sed -nE 's/^ *Depends: (linux-image-[0-9][^:]*)(:arm64)?$/\1/p' | head -1
}

# The guest's /init (busybox sh).
write_init() {
  cat >"$1" <<'INIT'
#!/bin/busybox sh
# /init of the emulated Raspberry Pi 5 (written by scripts/testbed/pi.sh).
/bin/busybox --install -s /bin
export PATH=/bin:/sbin HOME=/root
mount -t proc proc /proc
mount -t sysfs sys /sys
mount -t devtmpfs dev /dev
mkdir -p /tmp /run /root /var/lib/lekiwi
mount -t tmpfs tmp /tmp
mount -t tmpfs run /run
for m in $(cat /lib/modules/order); do insmod "/lib/modules/$m.ko"; done
# The robot's SD card: an ext4 disk for the agent's state (release store, outbox, token).
[ -b /dev/vda ] && mount -t ext4 /dev/vda /var/lib/lekiwi
arg() { for w in $(cat /proc/cmdline); do case "$w" in "lekiwi.$1="*) echo "${w#*=}" ;; esac; done; }
# No RTC the kernel reads: the host's clock at boot plus the time the kernel took.
t="$(arg time)"
up="$(cut -d. -f1 /proc/uptime)"
[ -n "$t" ] && date -s "@$((t + up))" >/dev/null
hostname "$(arg name)"
ip link set lo up
ip link set eth0 up
ip addr add 10.0.2.15/24 dev eth0
ip route add default via 10.0.2.2
echo "LEKIWI-CPU $(grep -m1 'CPU part' /proc/cpuinfo)"
run="$(arg run)"
rc=0
case "$run" in
  agent)
    set --
    [ -e /lekiwi/args ] && while IFS= read -r a; do set -- "$@" "$a"; done </lekiwi/args
    /bin/lekiwi-agent "$@" &
    pid=$!
    ( while sleep 10; do echo "LEKIWI-RSS $(grep VmRSS /proc/$pid/status)"; done ) &
    wait "$pid" || rc=$?
    ;;
  unit-tests)
    cd /tmp
    for t in /tests/*; do "$t" --test-threads=2 || rc=$?; done
    ;;
  script) sh /lekiwi/run.sh || rc=$? ;;
  shell) setsid cttyhack sh || rc=$? ;;
  *) echo "unknown lekiwi.run=$run"; rc=2 ;;
esac
echo "LEKIWI-EXIT run=$run status=$rc"
sync
poweroff -f
INIT
  chmod 0755 "$1"
}

# Packs directory $1 into the gzipped newc cpio $2.
pack() { ( cd "$1" && find . -mindepth 1 | LC_ALL=C sort | cpio -o -H newc --quiet -R 0:0 ) | gzip -1 >"$2"; }

build_base() {
  local kpkg kdir bbdir root
  kpkg="$(kernel_pkg)"
  [ -n "$kpkg" ] || die "no linux-image-cloud-arm64:arm64 in apt's lists (run scripts/setup.sh)"
  kdir="$(mktemp -d)" bbdir="$(mktemp -d)"
  find "$PI/debs" -name 'linux-image-*.deb' ! -name "${kpkg}_*" -delete 2>/dev/null || true # older kernels
  unpack_pkg "$kpkg" "$kdir"
  unpack_pkg busybox-static "$bbdir"
  cp "$(ls "$kdir"/boot/vmlinuz-* | head -1)" "$PI/vmlinuz"
  root="$(mktemp -d)"
  mkdir -p "$root"/{bin,sbin,lib/modules,proc,sys,dev,tmp,run,etc,lekiwi,tests}
  cp "$bbdir/bin/busybox" "$root/bin/busybox"
  local m f
  for m in "${MODULES[@]}"; do
    f="$(find "$kdir/lib/modules" -name "$m.ko*" | head -1)"
    [ -n "$f" ] || continue # built in
    echo "$m" >>"$root/lib/modules/order"
    case "$f" in
      *.xz) xz -dc "$f" >"$root/lib/modules/$m.ko" ;;
      *) cp "$f" "$root/lib/modules/$m.ko" ;;
    esac
  done
  for f in "${LIBS[@]}"; do cp -L "/usr/aarch64-linux-gnu/lib/$f" "$root/lib/$f"; done
  echo "root:x:0:0:root:/root:/bin/sh" >"$root/etc/passwd"
  write_init "$root/init"
  ln -sf busybox "$root/bin/sh" # the other applets: `busybox --install` in /init
  pack "$root" "$PI/base.cpio.gz"
  rm -rf "$root" "$kdir" "$bbdir"
  base_stamp >"$PI/base.stamp"
}

# What the base is made from: this script (its /init, modules, libraries) and the kernel package.
base_stamp() { echo "$(sha256sum "${BASH_SOURCE[0]}" | cut -d' ' -f1) $(kernel_pkg)"; }

# The agent's test executables (lib and bins) from cargo's JSON messages.
test_executables() {
  cross_cargo test --release --no-run --quiet -p lekiwi-agent --target "$TRIPLE" --message-format=json \
    | python3 -c '
import json, sys
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and m.get("profile", {}).get("test") and m.get("executable"):
        if m["package_id"].find("agent") >= 0 and set(m["target"]["kind"]) & {"lib", "bin"}:
            print(m["target"]["name"] + " " + m["executable"])'
}

cmd_build() {
  mkdir -p "$PI"
  exec 9>"$PI/.build.lock" # tests build from parallel processes
  flock 9
  local t0 stamp
  t0=$(date +%s)
  [ -x /usr/bin/rustc ] && command -v aarch64-linux-gnu-gcc >/dev/null && command -v qemu-system-aarch64 >/dev/null \
    || die "the arm64 toolchain or qemu-system-arm is missing: run scripts/setup.sh"
  log "cross-building lekiwi-agent for $TRIPLE (release) into $TARGET_DIR"
  # From a copy of the sources at a fixed path (scripts/lib/cache-build.sh says why).
  local src="$PI/src"
  src_copy "$src"
  ( cd "$src" && cross_cargo build --quiet --release -p lekiwi-agent --target "$TRIPLE" )
  log "cross-building the agent's unit tests"
  local tests
  tests="$(cd "$src" && test_executables)"
  [ -n "$tests" ] || die "cargo reported no test executable for lekiwi-agent"
  # The base (kernel, busybox, glibc, /init) follows this script's version.
  [ "$(cat "$PI/base.stamp" 2>/dev/null)" = "$(base_stamp)" ] || build_base
  local agent="$TARGET_DIR/$TRIPLE/release/lekiwi-agent"
  stamp="$(stat -c %Y "$agent" | tr '\n' ' ')$(find "$src/agent/tests/fixtures" -type f -printf '%T@ ' | sha256sum | cut -c1-16) $(echo "$tests" | while read -r _ e; do stat -c %Y "$e"; done | tr '\n' ' ')"
  if [ "$(cat "$PI/payload.stamp" 2>/dev/null)" != "$stamp" ]; then
    local root
    root="$(mktemp -d)"
    mkdir -p "$root/bin" "$root/tests"
    aarch64-linux-gnu-strip -o "$root/bin/lekiwi-agent" "$agent"
    echo "$tests" | while read -r name exe; do aarch64-linux-gnu-strip --strip-debug -o "$root/tests/$name" "$exe"; done
    # Unit tests read the agent's fixtures (the Pi 5's /sys and /proc), where the test binary
    # looks for them.
    mkdir -p "$root$src/agent/tests"
    cp -a "$src/agent/tests/fixtures" "$root$src/agent/tests/"
    pack "$root" "$PI/agent.cpio.gz"
    rm -rf "$root"
    echo "$stamp" >"$PI/payload.stamp"
  fi
  log "ready in $(( $(date +%s) - t0 ))s: kernel $PI/vmlinuz, initramfs $PI/base.cpio.gz + $PI/agent.cpio.gz"
}

# Writes guest NAME's directory (initrd = base + agent + its payload) and prints QEMU's arguments.
prepare_guest() {
  local name="$1" run="$2" payload="$3" port="$4" mem="$5" dir="$RUN/$1"
  shift 5
  [ -e "$PI/agent.cpio.gz" ] || die "nothing built yet: run scripts/testbed/pi.sh build"
  rm -rf "$dir" && mkdir -p "$dir/payload/lekiwi"
  [ -z "$payload" ] || cp -a "$payload/." "$dir/payload/lekiwi/"
  : >"$dir/payload/lekiwi/args"
  local a
  for a in "$@"; do printf '%s\n' "$a" >>"$dir/payload/lekiwi/args"; done
  pack "$dir/payload" "$dir/payload.cpio.gz"
  cat "$PI/base.cpio.gz" "$PI/agent.cpio.gz" "$dir/payload.cpio.gz" >"$dir/initrd"
  rm -rf "$dir/payload" "$dir/payload.cpio.gz"
  truncate -s 256M "$dir/disk.img"
  mkfs.ext4 -q -F -L lekiwi "$dir/disk.img"
  local fwd=""
  [ -z "$port" ] || fwd=",hostfwd=tcp:127.0.0.1:$port-:9477"
  printf '%s\n' -M virt -cpu cortex-a76 -smp 2 -m "$mem" -display none -monitor none -no-reboot \
    -serial "file:$dir/console.log" -netdev "user,id=n0$fwd" -device virtio-net-device,netdev=n0 \
    -drive "file=$dir/disk.img,format=raw,if=none,id=d0" -device virtio-blk-device,drive=d0 \
    -kernel "$PI/vmlinuz" -initrd "$dir/initrd" \
    -append "console=ttyAMA0 rdinit=/init panic=-1 quiet lekiwi.run=$run lekiwi.name=$name lekiwi.time=$(date +%s)"
}

# Like prepare_guest, for the Debian root filesystem (`boot --rootfs`): a copy-on-write overlay of
# the cached image, and DIR of --payload as a second disk (/dev/vdb, mounted at /payload).
prepare_rootfs_guest() {
  local name="$1" payload="$2" port="$3" mem="$4" forwards="$5" dir="$RUN/$1"
  [ -e "$ROOTFS" ] && [ -e "$PI/rootinit.cpio.gz" ] || die "no root filesystem yet: run scripts/testbed/pi.sh rootfs"
  rm -rf "$dir" && mkdir -p "$dir"
  qemu-img create -q -f qcow2 -F qcow2 -b "$ROOTFS" "$dir/disk.qcow2"
  cat "$PI/base.cpio.gz" "$PI/rootinit.cpio.gz" >"$dir/initrd"
  local extra=()
  if [ -n "$payload" ]; then
    mkfs.ext4 -q -F -L payload -d "$payload" "$dir/payload.img" "$(( $(du -sm "$payload" | cut -f1) + 16 ))M" >/dev/null
    extra=(-drive "file=$dir/payload.img,format=raw,if=none,id=d1,readonly=on" -device virtio-blk-device,drive=d1)
  fi
  local fwd="" f
  [ -z "$port" ] || fwd=",hostfwd=tcp:127.0.0.1:$port-:9477"
  for f in $forwards; do fwd="$fwd,hostfwd=tcp:127.0.0.1:${f%%:*}-:${f#*:}"; done
  # No -no-reboot: the guest's `systemctl reboot` restarts it in the same QEMU process.
  printf '%s\n' -M virt -cpu cortex-a76 -smp 2 -m "$mem" -display none -monitor none \
    -serial "file:$dir/console.log" -netdev "user,id=n0$fwd" -device virtio-net-device,netdev=n0 \
    "${extra[@]}" -drive "file=$dir/disk.qcow2,format=qcow2,if=none,id=d0" -device virtio-blk-device,drive=d0 \
    -kernel "$PI/vmlinuz" -initrd "$dir/initrd" \
    -append "console=ttyAMA0 rdinit=/rootinit panic=-1 quiet lekiwi.name=$name lekiwi.time=$(date +%s)"
}

cmd_boot() {
  local name=pi count=1 run=agent payload="" port="" mem=512 fg=0 rootfs=0 forwards=""
  while [ $# -gt 0 ]; do
    case "$1" in
      --name) name="$2"; shift 2 ;;
      --count) count="$2"; shift 2 ;;
      --run) run="$2"; shift 2 ;;
      --payload) payload="$(realpath "$2")"; shift 2 ;;
      --status-port) port="$2"; shift 2 ;;
      --memory) mem="$2"; shift 2 ;;
      --forward)
        [[ "$2" =~ ^[0-9]+:[0-9]+$ ]] || die "--forward takes HOSTPORT:GUESTPORT, not '$2'"
        forwards="$forwards $2"; shift 2 ;;
      --foreground) fg=1; shift ;;
      --rootfs) rootfs=1; shift ;;
      --) shift; break ;;
      *) die "boot: unknown option $1 (see --help)" ;;
    esac
  done
  mkdir -p "$RUN"
  if [ "$rootfs" = 1 ]; then
    [ "$count" = 1 ] && [ $# = 0 ] || die "--rootfs boots one guest and takes no agent arguments"
    mapfile -t qargs < <(prepare_rootfs_guest "$name" "$payload" "$port" "$mem" "$forwards")
    [ "${#qargs[@]}" -gt 0 ] || die "preparing $name failed"
    if [ "$fg" = 1 ]; then
      echo $$ >"$RUN/$name/qemu.pid"
      exec qemu-system-aarch64 "${qargs[@]}"
    fi
    qemu-system-aarch64 "${qargs[@]}" -daemonize -pidfile "$RUN/$name/qemu.pid"
    log "booted $name (Debian, systemd): console $RUN/$name/console.log"
    return
  fi
  [ -z "$forwards" ] || die "--forward is for --rootfs guests"
  if [ "$fg" = 1 ]; then
    [ "$count" = 1 ] || die "--foreground boots one guest"
    mapfile -t qargs < <(prepare_guest "$name" "$run" "$payload" "$port" "$mem" "$@")
    echo $$ >"$RUN/$name/qemu.pid"
    exec qemu-system-aarch64 "${qargs[@]}"
  fi
  local i n p
  for ((i = 0; i < count; i++)); do
    n="$name"; p="$port"
    [ "$count" = 1 ] || { n="$name-$i"; [ -z "$port" ] || p=$((port + i)); }
    mapfile -t qargs < <(prepare_guest "$n" "$run" "$payload" "$p" "$mem" "$@")
    qemu-system-aarch64 "${qargs[@]}" -daemonize -pidfile "$RUN/$n/qemu.pid"
    log "booted $n: console $RUN/$n/console.log${p:+, status http://127.0.0.1:$p/status}"
  done
}

# ---- A Debian bookworm arm64 root filesystem with systemd (for the .deb; see scripts/deb.sh) ----
# (Not rootfs.qcow2: the image debootstrap's second stage made before, with other packages.)
ROOTFS="$PI/debian-arm64.qcow2" ROOTFS_STAMP="$PI/debian-arm64.stamp"
# Only what the .deb test and bench/pi.sh use: systemd as PID 1 (dpkg comes with minbase) and
# prometheus-node-exporter (the figures' yardstick). The network is set with busybox's `ip`, not
# iproute2's; no ca-certificates (the agent trusts the CA file it is given). Left out of minbase's
# "required" set because nothing here uses them and each costs the emulated dpkg time: apt (and
# its TLS stack), tzdata (the guest runs on UTC), e2fsprogs.
ROOTFS_PKGS=systemd,systemd-sysv,prometheus-node-exporter
ROOTFS_EXCLUDE=apt,tzdata,e2fsprogs

# The Debian mirror of the machine's apt sources (as scripts/setup.sh finds it).
debian_mirror() {
  local m
  m="$(cat /etc/apt/sources.list.d/*.sources /etc/apt/sources.list 2>/dev/null \
    | sed -nE 's,^(URIs:|deb)[[:space:]]+(\[[^]]*\][[:space:]]+)?(https?://[^ ]+/debian)/?([[:space:]].*)?$,\3,p' | head -1 || true)"
  echo "${m:-http://deb.debian.org/debian}"
}

# The initramfs's second /init for the disk: loads the modules (from the base initramfs), sets the
# clock, then either configures the packages unpacked on the host (lekiwi.root=configure, see
# unpack_on_host) or hands over to systemd.
write_rootinit() {
  cat >"$1" <<'INIT'
#!/bin/busybox sh
/bin/busybox --install -s /bin
export PATH=/bin:/sbin
mount -t proc proc /proc
mount -t sysfs sys /sys
mount -t devtmpfs dev /dev
for m in $(cat /lib/modules/order); do insmod "/lib/modules/$m.ko"; done
arg() { for w in $(cat /proc/cmdline); do case "$w" in "lekiwi.$1="*) echo "${w#*=}" ;; esac; done; }
t="$(arg time)"
[ -n "$t" ] && date -s "@$((t + $(cut -d. -f1 /proc/uptime)))" >/dev/null
mkdir -p /newroot
mount -t ext4 /dev/vda /newroot || { echo "LEKIWI-EXIT run=root status=99"; poweroff -f; }
if [ "$(arg root)" = configure ]; then
  mount --bind /proc /newroot/proc
  mount --bind /sys /newroot/sys
  mount --bind /dev /newroot/dev
  rc=0
  t0="$(cut -d. -f1 /proc/uptime)"
  chroot /newroot /usr/bin/env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin LC_ALL=C.UTF-8 \
    DEBIAN_FRONTEND=noninteractive DEBCONF_NONINTERACTIVE_SEEN=true /bin/sh /lekiwi-configure || rc=$?
  echo "LEKIWI-CONFIGURE $(( $(cut -d. -f1 /proc/uptime) - t0 ))s"
  rm -f /newroot/lekiwi-configure
  umount /newroot/dev /newroot/sys /newroot/proc
  sync
  umount /newroot
  echo "LEKIWI-EXIT run=configure status=$rc"
  poweroff -f
fi
umount /proc /sys /dev
exec switch_root /newroot /sbin/init
INIT
  chmod 0755 "$1"
}

# Files the guest's root gets on top of Debian's: the network (QEMU's user network, static), the
# host name, and lekiwi-payload.service: at each boot it mounts the second disk (/dev/vdb, if
# any) and runs its run.sh with the output on the console: how tests install and drive the guest.
rootfs_overlay() {
  local r="$1"
  echo pi >"$r/etc/hostname"
  printf '127.0.0.1 localhost\n127.0.1.1 pi\n' >"$r/etc/hosts"
  : >"$r/etc/fstab"
  cat >"$r/etc/systemd/system/lekiwi-net.service" <<'UNIT'
[Unit]
Description=QEMU user network (10.0.2.15/24 via 10.0.2.2)
DefaultDependencies=no
Before=network-online.target network.target
Wants=network.target
[Service]
Type=oneshot
RemainAfterExit=yes
ExecStart=/usr/local/sbin/busybox ip link set lo up
ExecStart=/usr/local/sbin/busybox ip link set eth0 up
ExecStart=/usr/local/sbin/busybox ip addr add 10.0.2.15/24 dev eth0
ExecStart=/usr/local/sbin/busybox ip route add default via 10.0.2.2
[Install]
WantedBy=network-online.target
UNIT
  cat >"$r/etc/systemd/system/lekiwi-payload.service" <<'UNIT'
[Unit]
Description=Run run.sh from the payload disk (/dev/vdb)
After=lekiwi-net.service local-fs.target
Wants=lekiwi-net.service
ConditionPathExists=/dev/vdb
[Service]
Type=simple
ExecStart=/bin/sh -c 'mkdir -p /payload && mount -o ro /dev/vdb /payload && exec /bin/sh /payload/run.sh'
StandardOutput=tty
StandardError=tty
TTYPath=/dev/ttyAMA0
[Install]
WantedBy=multi-user.target
UNIT
  mkdir -p "$r/etc/systemd/system/multi-user.target.wants" "$r/etc/systemd/system/network-online.target.wants"
  # busybox-static (cached for the initramfs) for `ip`.
  local bb
  bb="$(mktemp -d)"
  unpack_pkg busybox-static "$bb"
  install -D -m 0755 "$bb/bin/busybox" "$r/usr/local/sbin/busybox"
  rm -rf "$bb"
  ln -sf ../lekiwi-payload.service "$r/etc/systemd/system/multi-user.target.wants/"
  ln -sf ../lekiwi-net.service "$r/etc/systemd/system/network-online.target.wants/"
  ln -sf ../lekiwi-net.service "$r/etc/systemd/system/multi-user.target.wants/"
}

# What the root filesystem is made from: the functions above and the package list.
rootfs_stamp() {
  { declare -f write_rootinit rootfs_overlay unpack_on_host write_configure build_rootfs; echo "$ROOTFS_PKGS $ROOTFS_EXCLUDE"; } \
    | sha256sum | cut -d' ' -f1
}

# Unpacks every package debootstrap's first stage downloaded with this machine's dpkg (--root:
# the files, dpkg's database, conffiles, trigger interests), so that the emulated Pi only has to
# configure them: unpacking inside it (debootstrap's second stage) was most of its 13 minutes.
# A package's preinst would run in a chroot of arm64 programs this machine cannot execute: while
# dpkg unpacks, the stage's /bin/sh is a static x86_64 program that does nothing, and the guest
# runs the preinsts before configuring (see write_configure). dash, which ships /bin/sh and has
# no preinst, goes last, after /bin/sh is restored. No documentation, manual pages or translations.
unpack_on_host() {
  local r="$1" noop debs=() d
  command -v gcc >/dev/null || die "gcc is missing (the x86_64 no-op /bin/sh of the unpack)"
  noop="$(mktemp -d)"
  printf 'int main(void) { return 0; }\n' | gcc -static -Os -x c -o "$noop/sh" -
  for d in "$r"/var/cache/apt/archives/*.deb; do [[ "$(basename "$d")" = dash_* ]] || debs+=("$d"); done
  local dpkg=(dpkg --root="$r" --force-architecture --force-depends --force-unsafe-io
    --path-exclude='/usr/share/doc/*' --path-exclude='/usr/share/man/*' --path-exclude='/usr/share/info/*'
    --path-exclude='/usr/share/locale/*' --path-exclude='/usr/share/lintian/*')
  cp --remove-destination "$noop/sh" "$r/usr/bin/sh"
  "${dpkg[@]}" --unpack "${debs[@]}" >"$PI/unpack.log" 2>&1 || { tail -20 "$PI/unpack.log" >&2; die "dpkg --unpack failed (log: $PI/unpack.log)"; }
  ln -sf dash "$r/usr/bin/sh"
  "${dpkg[@]}" --unpack "$r"/var/cache/apt/archives/dash_*.deb >>"$PI/unpack.log" 2>&1 \
    || { tail -20 "$PI/unpack.log" >&2; die "dpkg --unpack dash failed (log: $PI/unpack.log)"; }
  rm -rf "$noop" "$r/debootstrap" "$r"/var/cache/apt/archives/*.deb "$r"/usr/share/{doc,man,info,locale,lintian}/*
  # The first stage leaves /proc a symlink to the host's /proc (its second stage would replace it).
  if [ -L "$r/proc" ]; then rm "$r/proc" && mkdir -m 0555 "$r/proc"; fi
}

# The guest's part (/lekiwi-configure, run in a chroot by /rootinit): the preinsts the host could
# not run (base-passwd's first: it writes /etc/passwd and /etc/group), with the environment dpkg
# gives them, then `dpkg --configure -a`, which orders the packages and runs their postinsts and
# the pending triggers (ldconfig among them).
write_configure() {
  cat >"$1" <<'SH'
set -e
cd /var/lib/dpkg/info
for f in base-passwd.preinst $(ls *.preinst | grep -v '^base-passwd\.preinst$'); do
  p="${f%.preinst}"
  echo "preinst ${p%:*}"
  DPKG_MAINTSCRIPT_NAME=preinst DPKG_MAINTSCRIPT_PACKAGE="${p%:*}" DPKG_MAINTSCRIPT_ARCH=arm64 \
    DPKG_MAINTSCRIPT_PACKAGE_REFCOUNT=1 DPKG_ROOT= DPKG_ADMINDIR=/var/lib/dpkg "./$f" install
done
cd /
dpkg --force-unsafe-io --configure -a
SH
}

build_rootfs() {
  local stage img t0 rc
  t0=$(date +%s)
  stage="$PI/rootfs.stage" img="$PI/rootfs.raw"
  rm -rf "$stage" "$img" && mkdir -p "$stage"
  log "debootstrap --foreign bookworm arm64 ($ROOTFS_PKGS) from $(debian_mirror)"
  debootstrap --foreign --arch arm64 --variant=minbase --include="$ROOTFS_PKGS" --exclude="$ROOTFS_EXCLUDE" \
    bookworm "$stage" "$(debian_mirror)" >"$PI/debootstrap.log" 2>&1 \
    || { tail -20 "$PI/debootstrap.log" >&2; die "debootstrap --foreign failed (log: $PI/debootstrap.log)"; }
  rootfs_overlay "$stage"
  log "first stage in $(( $(date +%s) - t0 ))s; unpacking with this machine's dpkg"
  unpack_on_host "$stage"
  write_configure "$stage/lekiwi-configure"
  log "unpacked at $(( $(date +%s) - t0 ))s; making the disk"
  mkfs.ext4 -q -F -L root -d "$stage" "$img" 2G
  rm -rf "$stage"
  local ri
  ri="$(mktemp -d)"
  write_rootinit "$ri/rootinit"
  pack "$ri" "$PI/rootinit.cpio.gz"
  rm -rf "$ri"
  log "configuring inside the emulated Pi (console: $PI/stage2.log)"
  cat "$PI/base.cpio.gz" "$PI/rootinit.cpio.gz" >"$PI/rootfs.initrd"
  # cache=unsafe: the guest's flushes stop at QEMU (the image is rebuilt if anything fails).
  timeout 1800 qemu-system-aarch64 -M virt -cpu cortex-a76 -smp 2 -m 1024 -display none -monitor none \
    -no-reboot -nic none -serial "file:$PI/stage2.log" -drive "file=$img,format=raw,if=none,id=d0,cache=unsafe" \
    -device virtio-blk-device,drive=d0 -kernel "$PI/vmlinuz" -initrd "$PI/rootfs.initrd" \
    -append "console=ttyAMA0 rdinit=/rootinit panic=-1 quiet lekiwi.root=configure lekiwi.time=$(date +%s)" || true
  rc="$(sed -nE 's/.*LEKIWI-EXIT run=configure status=([0-9]+).*/\1/p' "$PI/stage2.log")"
  [ "$rc" = 0 ] || { tail -30 "$PI/stage2.log" >&2; rm -f "$img"; die "configuring in the guest failed (status ${rc:-none})"; }
  log "configured at $(( $(date +%s) - t0 ))s ($(sed -n 's/.*LEKIWI-CONFIGURE //p' "$PI/stage2.log" | tr -d '\r') in the guest); compressing"
  qemu-img convert -c -O qcow2 "$img" "$ROOTFS"
  rm -f "$img"
  rootfs_stamp >"$ROOTFS_STAMP"
  log "root filesystem $ROOTFS ($(du -h "$ROOTFS" | cut -f1)) in $(( $(date +%s) - t0 ))s"
}

cmd_rootfs() {
  mkdir -p "$PI"
  exec 8>"$PI/.rootfs.lock"
  flock 8
  [ -e "$PI/base.cpio.gz" ] || die "run scripts/testbed/pi.sh build first"
  command -v debootstrap >/dev/null || die "debootstrap is missing: run scripts/setup.sh"
  [ -e "$ROOTFS" ] && [ "$(cat "$ROOTFS_STAMP" 2>/dev/null)" = "$(rootfs_stamp)" ] && return 0
  build_rootfs
  rm -f "$PI/rootfs.initrd" # the build's; guests get their own
}

cmd_stop() {
  local names=("$@") n pid
  [ ${#names[@]} -gt 0 ] || mapfile -t names < <(ls "$RUN" 2>/dev/null)
  for n in "${names[@]}"; do
    [ -d "$RUN/$n" ] || continue
    pid="$(cat "$RUN/$n/qemu.pid" 2>/dev/null || true)"
    if [ -n "$pid" ] && grep -qs qemu-system "/proc/$pid/cmdline"; then
      kill "$pid" 2>/dev/null || true
      for _ in $(seq 50); do [ -e "/proc/$pid" ] || break; sleep 0.1; done
      kill -9 "$pid" 2>/dev/null || true
    fi
    rm -rf "${RUN:?}/$n"
    log "stopped $n"
  done
}

cmd_status() {
  local n pid
  for n in $(ls "$RUN" 2>/dev/null); do
    pid="$(cat "$RUN/$n/qemu.pid" 2>/dev/null || true)"
    if [ -n "$pid" ] && grep -qs qemu-system "/proc/$pid/cmdline"; then
      echo "$n running pid=$pid console=$RUN/$n/console.log"
    else
      echo "$n stopped console=$RUN/$n/console.log"
    fi
  done
}

case "${1:-help}" in
  build) shift; cmd_build "$@" ;;
  boot) shift; cmd_boot "$@" ;;
  stop) shift; cmd_stop "$@" ;;
  rootfs) shift; cmd_rootfs "$@" ;;
  status) cmd_status ;;
  help | -h | --help) usage ;;
  *) usage >&2; exit 2 ;;
esac
