//! The agent's command line: one flag (and environment variable) per config file key, plus the
//! subcommands that work on the state directory without running the agent.

use std::path::PathBuf;

use clap::Parser;
use serde::Serialize;

/// Command-line flags; each also reads an environment variable and overrides the file.
///
/// Field names match [`Config`]'s exactly; a flag left unset keeps the file's value or the
/// default.
#[derive(Debug, Default, Parser, Serialize)]
#[command(
    name = "lekiwi-agent",
    version,
    about = "Connects a LeKiwi robot to its fleet's gateway: heartbeats, telemetry, a durable \
             event outbox, teleoperation detection, mDNS discovery and release updates",
    long_about = None,
    after_help = "Every flag is also a key of the config file (camelCase, e.g. `stateDir`) and an \
                  environment variable (shown above). Precedence: flag, environment, file, default."
)]
#[serde(rename_all = "camelCase")]
pub struct Flags {
    /// Config file to read (a missing file is fine; flags and environment suffice), then the
    /// `*.yaml` drop-ins of the directory beside it named after it with `.d`
    /// (`/etc/lekiwi/agent.d/`), in name order, each overriding the files before it.
    #[arg(long, env = "LEKIWI_CONFIG", default_value = "/etc/lekiwi/agent.yaml")]
    #[serde(skip)]
    pub config: PathBuf,
    /// Print the effective configuration as YAML and exit.
    #[arg(long)]
    #[serde(skip)]
    pub print_config: bool,
    /// Something to do instead of running the agent.
    #[command(subcommand)]
    #[serde(skip)]
    pub command: Option<Command>,

    /// WebSocket URL of the gateway, e.g. wss://fleet.example.com/v1/agent.
    #[arg(long, env = "LEKIWI_GATEWAY_URL")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gateway: Option<String>,
    /// PEM file of the CA that signs the gateway's certificate (default: the public web roots).
    #[arg(long, env = "LEKIWI_CA_FILE")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ca_file: Option<PathBuf>,
    /// Allow a plain ws:// gateway on another host (anyone on the path can read the token and
    /// forge deployments); without it such a URL is refused at start.
    #[arg(
        long,
        env = "LEKIWI_INSECURE_ALLOW_PLAINTEXT",
        num_args = 0..=1,
        default_missing_value = "true"
    )]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub insecure_allow_plaintext: Option<bool>,
    /// Directory for the token, the outbox and releases.
    #[arg(long, env = "LEKIWI_STATE_DIR")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub state_dir: Option<PathBuf>,
    /// Robot as `namespace/name` (or `name`); default: the host name.
    #[arg(long, env = "LEKIWI_ROBOT_NAME")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub robot_name: Option<String>,
    /// File holding the fleet enrollment token, used once when the state dir has no token.
    #[arg(long, env = "LEKIWI_ENROLLMENT_TOKEN_FILE")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub enrollment_token_file: Option<PathBuf>,
    /// Fleet enrollment token itself (prefer the file: environments leak).
    #[arg(long, env = "LEKIWI_ENROLLMENT_TOKEN", hide_env_values = true)]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub enrollment_token: Option<String>,
    /// First reconnect delay's upper bound, milliseconds (doubles per failure; full jitter).
    #[arg(long, env = "LEKIWI_BACKOFF_INITIAL_MS")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub backoff_initial_ms: Option<u64>,
    /// Cap of the reconnect delay, milliseconds.
    #[arg(long, env = "LEKIWI_BACKOFF_MAX_MS")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub backoff_max_ms: Option<u64>,
    /// Seconds to wait for the connection and `welcome`.
    #[arg(long, env = "LEKIWI_CONNECT_TIMEOUT_S")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub connect_timeout_s: Option<u64>,
    /// Bound of the on-disk outbox, bytes of queued messages; oldest telemetry goes first.
    #[arg(long, env = "LEKIWI_OUTBOX_MAX_BYTES")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub outbox_max_bytes: Option<u64>,
    /// Durable messages in flight (sent, not yet acknowledged) at most.
    #[arg(long, env = "LEKIWI_OUTBOX_WINDOW")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub outbox_window: Option<u32>,
    /// Address of the local JSON status endpoint, or `off`.
    #[arg(long, env = "LEKIWI_STATUS_LISTEN")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub status_listen: Option<String>,
    /// Advertise `_lekiwi._tcp.local` over mDNS.
    #[arg(long, env = "LEKIWI_MDNS")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mdns: Option<bool>,
    /// Log format: text or json.
    #[arg(long, env = "LEKIWI_LOG_FORMAT")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub log_format: Option<String>,

    /// Seconds between CPU samples.
    #[arg(long, env = "LEKIWI_TELEMETRY_CPU_INTERVAL_S")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telemetry_cpu_interval_s: Option<u64>,
    /// Seconds between memory samples.
    #[arg(long, env = "LEKIWI_TELEMETRY_MEMORY_INTERVAL_S")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telemetry_memory_interval_s: Option<u64>,
    /// Seconds between network samples.
    #[arg(long, env = "LEKIWI_TELEMETRY_NETWORK_INTERVAL_S")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telemetry_network_interval_s: Option<u64>,
    /// Seconds between temperature samples.
    #[arg(long, env = "LEKIWI_TELEMETRY_TEMPERATURE_INTERVAL_S")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telemetry_temperature_interval_s: Option<u64>,
    /// Seconds between disk samples.
    #[arg(long, env = "LEKIWI_TELEMETRY_DISK_INTERVAL_S")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telemetry_disk_interval_s: Option<u64>,
    /// Seconds between full samples (every metric sent even if it did not move).
    #[arg(long, env = "LEKIWI_TELEMETRY_FULL_INTERVAL_S")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telemetry_full_interval_s: Option<u64>,
    /// Seconds between telemetry batches (samples are collected, then sent as one message).
    #[arg(long, env = "LEKIWI_TELEMETRY_BATCH_INTERVAL_S")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telemetry_batch_interval_s: Option<u64>,
    /// CPU percent must move by more than this to be sent.
    #[arg(long, env = "LEKIWI_TELEMETRY_CPU_DELTA")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telemetry_cpu_delta: Option<f64>,
    /// Memory percent must move by more than this to be sent.
    #[arg(long, env = "LEKIWI_TELEMETRY_MEMORY_DELTA")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telemetry_memory_delta: Option<f64>,
    /// Network rate (bytes/s, each direction) must move by more than this fraction to be sent.
    #[arg(long, env = "LEKIWI_TELEMETRY_NETWORK_DELTA")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telemetry_network_delta: Option<f64>,
    /// Temperature (°C) must move by more than this to be sent.
    #[arg(long, env = "LEKIWI_TELEMETRY_TEMPERATURE_DELTA")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telemetry_temperature_delta: Option<f64>,
    /// Disk percent must move by more than this to be sent.
    #[arg(long, env = "LEKIWI_TELEMETRY_DISK_DELTA")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telemetry_disk_delta: Option<f64>,

    /// Seconds between teleoperation checks.
    #[arg(long, env = "LEKIWI_TELEOP_INTERVAL_S")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub teleop_interval_s: Option<f64>,
    /// Score (sum of the weights of the indicators that fire) at which the robot counts as
    /// teleoperated.
    #[arg(long, env = "LEKIWI_TELEOP_THRESHOLD")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub teleop_threshold: Option<f64>,
    /// Substring of the LeKiwi host process's command line.
    #[arg(long, env = "LEKIWI_TELEOP_PROCESS_PATTERN")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub teleop_process_pattern: Option<String>,
    /// Weight of "the host process runs" (0 turns the indicator off).
    #[arg(long, env = "LEKIWI_TELEOP_PROCESS_WEIGHT")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub teleop_process_weight: Option<f64>,
    /// Command ports of the host (comma-separated); an ESTABLISHED connection counts.
    #[arg(long, env = "LEKIWI_TELEOP_COMMAND_PORTS", value_delimiter = ',')]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub teleop_command_ports: Option<Vec<u16>>,
    /// Weight of an ESTABLISHED connection on a command port (0 turns it off).
    #[arg(long, env = "LEKIWI_TELEOP_COMMAND_WEIGHT")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub teleop_command_weight: Option<f64>,
    /// Video ports of the host (comma-separated).
    #[arg(long, env = "LEKIWI_TELEOP_VIDEO_PORTS", value_delimiter = ',')]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub teleop_video_ports: Option<Vec<u16>>,
    /// Weight of an ESTABLISHED connection on a video port (0 turns it off).
    #[arg(long, env = "LEKIWI_TELEOP_VIDEO_WEIGHT")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub teleop_video_weight: Option<f64>,
    /// Video stream ports (e.g. RTSP; comma-separated).
    #[arg(long, env = "LEKIWI_TELEOP_STREAM_PORTS", value_delimiter = ',')]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub teleop_stream_ports: Option<Vec<u16>>,
    /// Weight of an ESTABLISHED connection on a stream port (0 turns it off).
    #[arg(long, env = "LEKIWI_TELEOP_STREAM_WEIGHT")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub teleop_stream_weight: Option<f64>,
    /// Motor serial device; held open by a process other than the agent counts.
    #[arg(long, env = "LEKIWI_TELEOP_SERIAL_DEVICE")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub teleop_serial_device: Option<PathBuf>,
    /// Weight of "the serial device is held open" (0 turns it off).
    #[arg(long, env = "LEKIWI_TELEOP_SERIAL_WEIGHT")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub teleop_serial_weight: Option<f64>,

    /// Shell command run every health interval in the current release directory; exiting
    /// non-zero (or outliving the health timeout) makes the robot unhealthy. Empty: none.
    #[arg(long, env = "LEKIWI_HEALTH_COMMAND")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub health_command: Option<String>,
    /// Seconds between health checks (0.5 to 3600); a change is sent to the gateway at once.
    #[arg(long, env = "LEKIWI_HEALTH_INTERVAL_S")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub health_interval_s: Option<f64>,
    /// Seconds the health command may run before it counts as failed and is killed (0.1 to
    /// 300).
    #[arg(long, env = "LEKIWI_HEALTH_TIMEOUT_S")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub health_timeout_s: Option<f64>,
    /// Substring of the command line of the LeKiwi host process, which must run for the robot
    /// to be healthy (e.g. lerobot.robots.lekiwi.lekiwi_host). Empty: not checked.
    #[arg(long, env = "LEKIWI_HOST_PROCESS_PATTERN")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub host_process_pattern: Option<String>,
    /// Device that must exist for the robot to be healthy (e.g. /dev/ttyACM0, the motor serial
    /// port). Unset: not checked.
    #[arg(long, env = "LEKIWI_HEALTH_SERIAL_DEVICE")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub health_serial_device: Option<PathBuf>,
    /// Use of the state directory's file system, percent as `df` shows it, from which the robot
    /// is unhealthy (0 turns the check off).
    #[arg(long, env = "LEKIWI_HEALTH_DISK_MAX_PERCENT")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub health_disk_max_percent: Option<f64>,

    /// Shell command run in the new release directory before the switch; failing it aborts
    /// the deployment (the old release keeps running). Empty: none.
    #[arg(long, env = "LEKIWI_RELEASE_PRE_SWITCH_COMMAND")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub release_pre_switch_command: Option<String>,
    /// Shell command that restarts the robot's software after a switch (e.g.
    /// `systemctl restart lekiwi-host`). Empty: none.
    #[arg(long, env = "LEKIWI_RELEASE_RESTART_COMMAND")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub release_restart_command: Option<String>,
    /// Shell command that exits 0 when the new release is healthy; retried until it passes or
    /// the health timeout ends. Empty: healthy once restarted.
    #[arg(long, env = "LEKIWI_RELEASE_HEALTH_COMMAND")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub release_health_command: Option<String>,
    /// Seconds the health command may take to pass after a switch.
    #[arg(long, env = "LEKIWI_RELEASE_HEALTH_TIMEOUT_S")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub release_health_timeout_s: Option<u64>,
    /// Seconds the pre-switch and the restart command may each run before they count as
    /// failed (and are killed).
    #[arg(long, env = "LEKIWI_RELEASE_HOOK_TIMEOUT_S")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub release_hook_timeout_s: Option<u64>,
    /// Releases kept on disk (the current one included) for instant rollback.
    #[arg(long, env = "LEKIWI_RELEASE_KEEP")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub release_keep: Option<u32>,
    /// Cap on the download rate of release blobs, bytes per second, over all parallel
    /// downloads (0: no cap).
    #[arg(long, env = "LEKIWI_RELEASE_DOWNLOAD_RATE_LIMIT")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub release_download_rate_limit: Option<u64>,
    /// Seconds a new agent build (installed by an `update_agent` command) has to reach the
    /// gateway; past it, `lekiwi-agent guard` switches back to the previous build.
    #[arg(long, env = "LEKIWI_AGENT_UPDATE_DEADLINE_S")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub agent_update_deadline_s: Option<u64>,
    /// Starts a new agent build may take without reaching the gateway before
    /// `lekiwi-agent guard` switches back (it crashes at start).
    #[arg(long, env = "LEKIWI_AGENT_UPDATE_MAX_STARTS")]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub agent_update_max_starts: Option<u32>,
}

/// Arguments of `lekiwi-agent join` (printed by `kubectl lekiwi robot add` and `kubectl lekiwi
/// enroll-token`).
#[derive(Debug, clap::Args)]
pub struct JoinArgs {
    /// The gateway's agent URL, wss://HOST:PORT/v1/agent.
    #[arg(long)]
    pub gateway: String,
    /// Pin of the gateway's CA: `sha256:` and the hex SHA-256 of the CA certificate's DER
    /// SubjectPublicKeyInfo. The CA the gateway presents must have it, or join refuses.
    #[arg(long)]
    pub ca_cert_hash: String,
    /// A fleet enrollment token (lke_...) or the robot's own token (lkr_..., from `kubectl
    /// lekiwi robot add`, which then needs --name).
    #[arg(long, env = "LEKIWI_JOIN_TOKEN", hide_env_values = true)]
    pub token: String,
    /// The robot, `namespace/name` (default: named after the host, in the token's namespace).
    #[arg(long)]
    pub name: Option<String>,
    /// Join another gateway than the one this robot joined before (its files are replaced,
    /// and with another CA the robot's own token is forgotten).
    #[arg(long)]
    pub force: bool,
    /// Write the files but do not run `systemctl enable --now lekiwi-agent` (containers,
    /// tests: start the agent yourself; join still waits for it).
    #[arg(long)]
    pub no_start: bool,
    /// Seconds to keep trying a gateway that refuses or does not answer connections (or their
    /// TLS handshake), then to wait for the agent to reach it (0: try once, do not wait).
    #[arg(long, default_value_t = 120)]
    pub wait_s: u64,
    /// Directory that stands for `/`: files are written under it, and the paths written into
    /// them name it (for tests and images).
    #[arg(long, default_value = "/")]
    pub root: PathBuf,
}

/// Subcommands.
#[derive(Debug, clap::Subcommand)]
pub enum Command {
    /// Join the fleet with one command (`kubectl lekiwi robot add` and `enroll-token` print
    /// it): fetches the gateway's CA and checks it against --ca-cert-hash, writes
    /// /etc/lekiwi/agent.d/50-join.yaml (never /etc/lekiwi/agent.yaml), /etc/lekiwi/ca.crt (0644)
    /// and /etc/lekiwi/enrollment-token (0600) or the robot's token in
    /// /var/lib/lekiwi/credentials.json (0600), runs `systemctl enable --now lekiwi-agent` and
    /// waits until the agent is connected. Run again, it changes nothing; another gateway needs
    /// --force.
    Join(JoinArgs),
    /// Queue an event for the fleet (e.g. from a lekiwi_host hook); it is stored in the outbox
    /// at once and sent by the running agent, also if the gateway is unreachable right now.
    Event {
        /// Machine-readable kind, e.g. `calibration_done`.
        #[arg(long)]
        kind: String,
        /// Human-readable text.
        #[arg(long, default_value = "")]
        message: String,
        /// info, warning or error.
        #[arg(long, default_value = "info", value_parser = ["info", "warning", "error"])]
        severity: String,
        /// Details as a JSON value.
        #[arg(long)]
        data: Option<String>,
        /// Send ahead of telemetry and other events and never drop it.
        #[arg(long)]
        critical: bool,
    },
    /// Undo an agent update that did not come back: run by the service manager from the
    /// package's binary before every start of the agent and (with --check) periodically. Switches
    /// `<state-dir>/agent/current` back to the previous build when the new one has not reached
    /// the gateway by its deadline, has started too often, or is for another CPU. Exit status 0;
    /// with --check, 3 when it switched back (restart the agent then).
    Guard {
        /// Periodic check while the agent runs: only the deadline counts, no start is counted.
        #[arg(long)]
        check: bool,
    },
    /// Take over a robot's existing token instead of enrolling: a robot moving from the legacy
    /// polling endpoint to the agent, or a reinstalled robot whose token was kept. Writes
    /// `<state-dir>/credentials.json` (mode 0600); the agent then connects as that robot. Refuses
    /// an enrollment token, and credentials of another robot already in the state directory.
    Adopt {
        /// The robot, as `namespace/name`.
        #[arg(long)]
        robot: String,
        /// File holding the robot's own token (`lkr_...`, from `kubectl lekiwi robot add`);
        /// `-` reads standard input. Surrounding whitespace is ignored.
        #[arg(long)]
        token_file: PathBuf,
    },
}
