#!/usr/bin/env bash
#! Sourced by scripts/testbed/control-plane.sh and scripts/testbed/cluster.sh: the background processes they own.
#! Each process NAME has $STATE/NAME.pid and $STATE/NAME.log, and is recognised by its pid file AND
#! by the argument `marker NAME` prints (the caller defines `marker`, `log` and `die`), so a
#! recycled pid never makes us signal or trust an unrelated process.

# Prints the pid of a live process $1 belonging to this state dir.
live_pid() {
  local pid
  pid="$(cat "$STATE/$1.pid" 2>/dev/null)" || return 1
  [[ "$pid" =~ ^[0-9]+$ ]] || return 1
  # A zombie has an empty cmdline, so it counts as dead.
  { tr '\0' '\n' <"/proc/$pid/cmdline"; } 2>/dev/null | grep -qxF -- "$(marker "$1")" || return 1
  echo "$pid"
}

# Whether process $1, started by `spawn`, still runs: during the exec right after its pid file is
# written its command line can read empty for a moment, so a missing marker is believed only
# when it is still missing a moment later (a process that really exited stays gone).
still_running() { live_pid "$1" >/dev/null || { sleep 0.3; live_pid "$1" >/dev/null; }; }

# Starts "$@" as process $1, detached from the caller: new session, stdin closed, output to
# $STATE/$1.log, and without the lock file descriptor (fd 9), so it outlives the calling shell.
spawn() {
  local name="$1" i
  shift
  printf '\n==== %s starting %s\n' "$(date -Is)" "$name" >>"$STATE/$name.log"
  rm -f "$STATE/$name.pid"
  setsid bash -c 'echo $$ >"$0"; exec "$@"' "$STATE/$name.pid" "$@" \
    </dev/null >>"$STATE/$name.log" 2>&1 9>&- &
  # Wait until the child has written its own pid (it execs right after).
  for i in $(seq 50); do
    [ -s "$STATE/$name.pid" ] && return 0
    sleep 0.05
  done
  die "$name did not start (see $STATE/$name.log)"
}

# Signals process $1 with $2 and waits up to $3 seconds for it to exit. Returns 1 if still alive.
stop_proc() {
  local name="$1" sig="$2" wait_s="$3" pid i
  pid="$(live_pid "$name")" || return 0
  kill "-$sig" "$pid" 2>/dev/null || true
  for i in $(seq $((wait_s * 10))); do
    live_pid "$name" >/dev/null || return 0
    sleep 0.1
  done
  return 1
}

tail_log() { log "last lines of $STATE/$1.log:"; tail -n "${2:-25}" "$STATE/$1.log" >&2 || true; }
