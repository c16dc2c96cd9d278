#!/bin/sh
# Moves a robot that polls the legacy endpoint (GET /v1/poll) to the LeKiwi agent, keeping its
# identity (its Robot, its token, its history): put this script and the agent in a release,
# point the robot's spec.release at it, and have the legacy poller run it, as root, from the
# directory it downloaded the release into. The book: Robots, "Moving off
# legacy polling" (docs/src/robots/legacy-polling.md).
#
# Environment (what the poller knows; the first three are required):
#   LEKIWI_ROBOT           namespace/name, as in the poll's robot= parameter
#   LEKIWI_TOKEN_FILE      a file holding the robot's token (the poll's Bearer token, lkr_...)
#   LEKIWI_GATEWAY_URL     the agent endpoint: the poller's base URL with wss:// and /v1/agent
#   LEKIWI_CA_FILE         the gateway's CA certificate, when it is not a public one
#   LEKIWI_INSECURE_ALLOW_PLAINTEXT  true to allow a ws:// gateway on another host (the token
#                          and the deployments are then readable on the way; avoid)
#   LEKIWI_LEGACY_SERVICE  the poller's systemd unit: disabled, then stopped, as the last step
#   LEKIWI_CONFIG          the agent's config file (default /etc/lekiwi/agent.yaml)
#   LEKIWI_STATE_DIR       the agent's state directory (default /var/lib/lekiwi)
#   LEKIWI_BIN_DIR         where a bare agent binary goes (default /usr/local/bin)
#   LEKIWI_START_COMMAND   how to start the agent where systemd is not running (a container);
#                          default: systemctl enable --now lekiwi-agent
#
# The agent comes from the release: lekiwi-agent_*_<dpkg architecture>.deb, installed with
# dpkg -i (with its systemd unit and guard timer), or, where there is no such package or no dpkg,
# a bare binary lekiwi-agent-<uname -m> copied to $LEKIWI_BIN_DIR (start it with
# LEKIWI_START_COMMAND). The token is handed over with `lekiwi-agent adopt`: no enrollment token
# is needed and the robot keeps its name. Every step is idempotent: after a failure, run it again.
# Exit status 0 only when the agent is installed, holds the robot's token and was started; the
# poller must then stop polling (its unit is disabled here when LEKIWI_LEGACY_SERVICE is set).
set -eu

say() { printf 'migrate-to-agent: %s\n' "$*"; }
die() { say "error: $*" >&2; exit 1; }

here="$(cd "$(dirname "$0")" && pwd)"
robot="${LEKIWI_ROBOT:-}"
token_file="${LEKIWI_TOKEN_FILE:-}"
gateway="${LEKIWI_GATEWAY_URL:-}"
config="${LEKIWI_CONFIG:-/etc/lekiwi/agent.yaml}"
state="${LEKIWI_STATE_DIR:-/var/lib/lekiwi}"
bin_dir="${LEKIWI_BIN_DIR:-/usr/local/bin}"

[ -n "$robot" ] || die "LEKIWI_ROBOT (namespace/name) is not set"
[ -r "$token_file" ] || die "LEKIWI_TOKEN_FILE ('$token_file') is not a readable file"
case "$gateway" in
  wss://*/v1/agent | ws://*/v1/agent) ;;
  *) die "LEKIWI_GATEWAY_URL ('$gateway') must be wss://HOST[:PORT]/v1/agent" ;;
esac
[ -z "${LEKIWI_CA_FILE:-}" ] || [ -r "$LEKIWI_CA_FILE" ] || die "LEKIWI_CA_FILE is not readable"

# 1. The agent binary: the package for this architecture, else the bare binary.
agent=""
if command -v dpkg >/dev/null 2>&1; then
  arch="$(dpkg --print-architecture)"
  for deb in "$here"/lekiwi-agent_*_"$arch".deb; do
    [ -f "$deb" ] || continue
    say "installing $(basename "$deb")"
    dpkg -i "$deb"
    agent=/usr/bin/lekiwi-agent
  done
fi
if [ -z "$agent" ]; then
  bare="$here/lekiwi-agent-$(uname -m)"
  [ -f "$bare" ] || die "the release has neither lekiwi-agent_*_${arch:-?}.deb nor lekiwi-agent-$(uname -m)"
  mkdir -p "$bin_dir"
  # Copy beside, then rename: a running agent's binary is never overwritten in place.
  cp "$bare" "$bin_dir/.lekiwi-agent.new"
  chmod 0755 "$bin_dir/.lekiwi-agent.new"
  mv -f "$bin_dir/.lekiwi-agent.new" "$bin_dir/lekiwi-agent"
  agent="$bin_dir/lekiwi-agent"
  say "installed $agent ($("$agent" --version))"
fi

# 2. Its configuration: the gateway and the robot's name. A config that names a gateway
#    already is somebody's choice and is kept.
if [ -f "$config" ] && grep -q '^gateway:' "$config"; then
  say "keeping $config (it names a gateway)"
else
  mkdir -p "$(dirname "$config")"
  {
    echo "# Written by migrate-to-agent.sh when this robot left the legacy polling endpoint."
    echo "gateway: $gateway"
    echo "robotName: $robot"
    [ -z "${LEKIWI_CA_FILE:-}" ] || echo "caFile: $LEKIWI_CA_FILE"
    [ "${LEKIWI_INSECURE_ALLOW_PLAINTEXT:-}" != true ] || echo "insecureAllowPlaintext: true"
  } >"$config.new"
  mv -f "$config.new" "$config"
  say "wrote $config"
fi

"$agent" --config "$config" --state-dir "$state" --print-config >/dev/null ||
  die "the agent refuses $config (see above); nothing was started"

# 3. The robot's own token, handed over (never printed).
"$agent" --config "$config" --state-dir "$state" adopt --robot "$robot" --token-file "$token_file"

# 4. Start the agent.
if [ -n "${LEKIWI_START_COMMAND:-}" ]; then
  say "starting the agent: $LEKIWI_START_COMMAND"
  sh -c "$LEKIWI_START_COMMAND"
elif [ "$agent" = /usr/bin/lekiwi-agent ] && [ -d /run/systemd/system ]; then
  systemctl enable --now lekiwi-agent
  say "lekiwi-agent.service enabled and started"
else
  die "cannot start the agent: no systemd with the package's unit here; set LEKIWI_START_COMMAND"
fi

# 5. The poller's service goes last: stopping it may end this script's own process group.
if [ -n "${LEKIWI_LEGACY_SERVICE:-}" ]; then
  systemctl disable "$LEKIWI_LEGACY_SERVICE"
  say "disabled $LEKIWI_LEGACY_SERVICE; stopping it"
  systemctl stop --no-block "$LEKIWI_LEGACY_SERVICE"
fi
say "done: $robot now connects with the agent"
