//! Agent configuration: a YAML file, overridden by flags and `LEKIWI_*` environment variables.
//!
//! Every key of the file is also a flag (`--kebab-case`) and an environment variable
//! (`LEKIWI_SCREAMING_CASE`); a test keeps the three in step. The file is flat on purpose, so
//! the mapping is obvious: `telemetryCpuIntervalS: 5` is `--telemetry-cpu-interval-s 5` is
//! `LEKIWI_TELEMETRY_CPU_INTERVAL_S=5`.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use clap::Parser;
use serde::{Deserialize, Serialize};

/// Errors loading the configuration.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The config file exists but cannot be read.
    #[error("cannot read config file {path}: {source}")]
    ReadConfig {
        path: PathBuf,
        source: std::io::Error,
    },
    /// The config file is not valid YAML of the expected shape.
    #[error("invalid config file {path}: {source}")]
    ParseConfig {
        path: PathBuf,
        source: serde_yaml::Error,
    },
    /// A flag or environment value does not fit its key.
    #[error("invalid setting: {0}")]
    Invalid(String),
    /// A required setting is missing everywhere.
    #[error("no gateway configured: set `gateway` in {path}, --gateway or LEKIWI_GATEWAY_URL")]
    MissingGateway { path: PathBuf },
}

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
    /// Config file to read (a missing file is fine; flags and environment suffice).
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
}

/// Subcommands.
#[derive(Debug, clap::Subcommand)]
pub enum Command {
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
}

/// The effective configuration. Field names are the config file's keys.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase", deny_unknown_fields, default)]
pub struct Config {
    /// Gateway WebSocket URL.
    pub gateway: String,
    /// CA for `wss://`.
    pub ca_file: Option<PathBuf>,
    /// State directory.
    pub state_dir: PathBuf,
    /// Robot, `namespace/name` or `name`.
    pub robot_name: String,
    /// Enrollment token file.
    pub enrollment_token_file: Option<PathBuf>,
    /// Enrollment token.
    #[serde(skip_serializing)]
    pub enrollment_token: Option<String>,
    /// First backoff bound, ms.
    pub backoff_initial_ms: u64,
    /// Backoff cap, ms.
    pub backoff_max_ms: u64,
    /// Connect + welcome timeout, s.
    pub connect_timeout_s: u64,
    /// Outbox bound, bytes.
    pub outbox_max_bytes: u64,
    /// Messages in flight.
    pub outbox_window: u32,
    /// Status endpoint address or `off`.
    pub status_listen: String,
    /// mDNS advertisement on or off.
    pub mdns: bool,
    /// `text` or `json`.
    pub log_format: String,

    /// CPU sampling interval, s.
    pub telemetry_cpu_interval_s: u64,
    /// Memory sampling interval, s.
    pub telemetry_memory_interval_s: u64,
    /// Network sampling interval, s.
    pub telemetry_network_interval_s: u64,
    /// Temperature sampling interval, s.
    pub telemetry_temperature_interval_s: u64,
    /// Disk sampling interval, s.
    pub telemetry_disk_interval_s: u64,
    /// Full sample interval, s.
    pub telemetry_full_interval_s: u64,
    /// Batch interval, s.
    pub telemetry_batch_interval_s: u64,
    /// CPU threshold, percentage points.
    pub telemetry_cpu_delta: f64,
    /// Memory threshold, percentage points.
    pub telemetry_memory_delta: f64,
    /// Network threshold, relative change.
    pub telemetry_network_delta: f64,
    /// Temperature threshold, °C.
    pub telemetry_temperature_delta: f64,
    /// Disk threshold, percentage points.
    pub telemetry_disk_delta: f64,

    /// Teleoperation check interval, s.
    pub teleop_interval_s: f64,
    /// Score threshold.
    pub teleop_threshold: f64,
    /// Host process command-line substring.
    pub teleop_process_pattern: String,
    /// Host process weight.
    pub teleop_process_weight: f64,
    /// Command ports.
    pub teleop_command_ports: Vec<u16>,
    /// Command connection weight.
    pub teleop_command_weight: f64,
    /// Video ports.
    pub teleop_video_ports: Vec<u16>,
    /// Video connection weight.
    pub teleop_video_weight: f64,
    /// Stream ports.
    pub teleop_stream_ports: Vec<u16>,
    /// Stream connection weight.
    pub teleop_stream_weight: f64,
    /// Serial device.
    pub teleop_serial_device: PathBuf,
    /// Serial weight.
    pub teleop_serial_weight: f64,

    /// Pre-switch command.
    pub release_pre_switch_command: String,
    /// Restart command.
    pub release_restart_command: String,
    /// Health command.
    pub release_health_command: String,
    /// Health timeout, s.
    pub release_health_timeout_s: u64,
    /// Pre-switch and restart command timeout, s.
    pub release_hook_timeout_s: u64,
    /// Releases kept.
    pub release_keep: u32,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            gateway: String::new(),
            ca_file: None,
            state_dir: PathBuf::from("/var/lib/lekiwi"),
            robot_name: String::new(),
            enrollment_token_file: None,
            enrollment_token: None,
            backoff_initial_ms: 500,
            backoff_max_ms: 60_000,
            connect_timeout_s: 15,
            outbox_max_bytes: 64 * 1024 * 1024,
            outbox_window: 32,
            status_listen: "127.0.0.1:9477".into(),
            mdns: true,
            log_format: "text".into(),
            telemetry_cpu_interval_s: 5,
            telemetry_memory_interval_s: 10,
            telemetry_network_interval_s: 5,
            telemetry_temperature_interval_s: 30,
            telemetry_disk_interval_s: 60,
            telemetry_full_interval_s: 600,
            telemetry_batch_interval_s: 60,
            telemetry_cpu_delta: 5.0,
            telemetry_memory_delta: 2.0,
            telemetry_network_delta: 0.25,
            telemetry_temperature_delta: 1.0,
            telemetry_disk_delta: 1.0,
            teleop_interval_s: 2.0,
            teleop_threshold: 0.5,
            teleop_process_pattern: "lerobot.robots.lekiwi.lekiwi_host".into(),
            teleop_process_weight: 0.1,
            teleop_command_ports: vec![5555],
            teleop_command_weight: 0.6,
            teleop_video_ports: vec![5556],
            teleop_video_weight: 0.3,
            teleop_stream_ports: vec![8554],
            teleop_stream_weight: 0.3,
            teleop_serial_device: PathBuf::from("/dev/ttyACM0"),
            teleop_serial_weight: 0.2,
            release_pre_switch_command: String::new(),
            release_restart_command: String::new(),
            release_health_command: String::new(),
            release_health_timeout_s: 60,
            release_hook_timeout_s: 300,
            release_keep: 3,
        }
    }
}

impl Config {
    /// Merges the file (if present) with flags and environment; flags win.
    pub fn load(flags: &Flags, hostname: &str) -> Result<Self, Error> {
        let mut config = Self::merge(flags)?;
        if config.gateway.is_empty() {
            return Err(Error::MissingGateway {
                path: flags.config.clone(),
            });
        }
        if config.robot_name.is_empty() {
            config.robot_name = hostname.to_owned();
        }
        config.validate()?;
        Ok(config)
    }

    /// File, environment and flags merged, without checking that the gateway is set (for
    /// subcommands that work on the state directory only).
    pub fn merge(flags: &Flags) -> Result<Self, Error> {
        let mut merged = read_file(&flags.config)?;
        let overrides = serde_json::to_value(flags).map_err(|e| Error::Invalid(e.to_string()))?;
        if let serde_json::Value::Object(overrides) = overrides {
            merged.extend(overrides);
        }
        serde_json::from_value(serde_json::Value::Object(merged)).map_err(|source| {
            Error::ParseConfig {
                path: flags.config.clone(),
                source: serde::de::Error::custom(source),
            }
        })
    }

    fn validate(&self) -> Result<(), Error> {
        let bad = |msg: String| Err(Error::Invalid(msg));
        if self.robot_name.is_empty() {
            return bad("robotName is empty and the host has no name".into());
        }
        if self.backoff_initial_ms == 0 || self.backoff_max_ms < self.backoff_initial_ms {
            return bad(format!(
                "backoffInitialMs ({}) must be > 0 and <= backoffMaxMs ({})",
                self.backoff_initial_ms, self.backoff_max_ms
            ));
        }
        if self.release_keep < 2 {
            return bad(format!(
                "releaseKeep ({}) must be at least 2: the current release and the one to roll back to",
                self.release_keep
            ));
        }
        if self.release_hook_timeout_s == 0 {
            return bad("releaseHookTimeoutS must be at least 1".into());
        }
        if self.outbox_window == 0 {
            return bad("outboxWindow must be at least 1".into());
        }
        if self.outbox_max_bytes < 64 * 1024 {
            return bad(format!(
                "outboxMaxBytes ({}) must be at least 65536",
                self.outbox_max_bytes
            ));
        }
        for (key, v) in [
            ("telemetryCpuIntervalS", self.telemetry_cpu_interval_s),
            ("telemetryMemoryIntervalS", self.telemetry_memory_interval_s),
            (
                "telemetryNetworkIntervalS",
                self.telemetry_network_interval_s,
            ),
            (
                "telemetryTemperatureIntervalS",
                self.telemetry_temperature_interval_s,
            ),
            ("telemetryDiskIntervalS", self.telemetry_disk_interval_s),
            ("telemetryFullIntervalS", self.telemetry_full_interval_s),
            ("telemetryBatchIntervalS", self.telemetry_batch_interval_s),
        ] {
            if v == 0 {
                return bad(format!("{key} must be at least 1 second"));
            }
        }
        if self.teleop_interval_s.is_nan() || self.teleop_interval_s <= 0.0 {
            return bad("teleopIntervalS must be > 0".into());
        }
        if self.status_listen != "off" && self.status_listen.parse::<SocketAddr>().is_err() {
            return bad(format!(
                "statusListen {:?} is neither host:port nor `off`",
                self.status_listen
            ));
        }
        if !matches!(self.log_format.as_str(), "text" | "json") {
            return bad(format!(
                "logFormat {:?} must be text or json",
                self.log_format
            ));
        }
        Ok(())
    }

    /// The status endpoint address, unless turned off.
    pub fn status_addr(&self) -> Option<SocketAddr> {
        self.status_listen.parse().ok()
    }

    /// The enrollment token from the config or its file, if any.
    pub fn enrollment_token(&self) -> Result<Option<String>, Error> {
        if let Some(t) = &self.enrollment_token {
            return Ok(Some(t.trim().to_owned()));
        }
        match &self.enrollment_token_file {
            None => Ok(None),
            Some(path) => std::fs::read_to_string(path)
                .map(|t| Some(t.trim().to_owned()))
                .map_err(|source| Error::ReadConfig {
                    path: path.clone(),
                    source,
                }),
        }
    }
}

fn read_file(path: &Path) -> Result<serde_json::Map<String, serde_json::Value>, Error> {
    match std::fs::read_to_string(path) {
        Ok(text) if text.trim().is_empty() => Ok(Default::default()),
        Ok(text) => serde_yaml::from_str(&text).map_err(|source| Error::ParseConfig {
            path: path.to_owned(),
            source,
        }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Default::default()),
        Err(source) => Err(Error::ReadConfig {
            path: path.to_owned(),
            source,
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flags_override_file_and_file_overrides_defaults() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("agent.yaml");
        std::fs::write(
            &path,
            "gateway: wss://file/agent\nrobotName: from-file\ntelemetryCpuIntervalS: 7\nteleopCommandPorts: [6000, 6001]\n",
        )
        .unwrap();
        let flags = Flags::parse_from([
            "lekiwi-agent",
            "--config",
            path.to_str().unwrap(),
            "--robot-name",
            "kiwi-9",
            "--teleop-video-ports",
            "7000,7001",
            "--mdns",
            "false",
        ]);
        let cfg = Config::load(&flags, "host").unwrap();
        assert_eq!(cfg.gateway, "wss://file/agent");
        assert_eq!(cfg.robot_name, "kiwi-9");
        assert_eq!(cfg.state_dir, PathBuf::from("/var/lib/lekiwi"));
        assert_eq!(cfg.telemetry_cpu_interval_s, 7);
        assert_eq!(cfg.teleop_command_ports, vec![6000, 6001]);
        assert_eq!(cfg.teleop_video_ports, vec![7000, 7001]);
        assert!(!cfg.mdns);
        assert_eq!(cfg.telemetry_memory_interval_s, 10);
    }

    #[test]
    fn bad_file_and_missing_gateway_are_clear_errors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("agent.yaml");
        std::fs::write(&path, "gatewy: typo\n").unwrap();
        let flags = Flags::parse_from(["lekiwi-agent", "--config", path.to_str().unwrap()]);
        let err = Config::load(&flags, "h").unwrap_err().to_string();
        assert!(err.contains("unknown field `gatewy`"), "{err}");

        std::fs::write(&path, "gateway: ws://x\ntelemetryCpuIntervalS: fast\n").unwrap();
        let err = Config::load(&flags, "h").unwrap_err().to_string();
        assert!(err.contains("invalid type"), "{err}");

        std::fs::write(&path, "gateway: ws://x\nstatusListen: nowhere\n").unwrap();
        let err = Config::load(&flags, "h").unwrap_err().to_string();
        assert!(err.contains("statusListen"), "{err}");

        let flags = Flags::parse_from(["lekiwi-agent", "--config", "/nonexistent/agent.yaml"]);
        let err = Config::load(&flags, "h").unwrap_err().to_string();
        assert!(err.contains("LEKIWI_GATEWAY_URL"), "{err}");
    }

    /// Every file key (camelCase) with the flag of the same name in kebab case; panics when a
    /// key has no flag.
    fn keys_and_flags() -> Vec<(String, clap::Arg)> {
        use clap::CommandFactory;
        let cmd = Flags::command();
        let serde_json::Value::Object(keys) = serde_json::to_value(Config::default()).unwrap()
        else {
            unreachable!()
        };
        // The token itself is never printed, so it is not serialized.
        keys.keys()
            .cloned()
            .chain(["enrollmentToken".to_owned()])
            .map(|key| {
                let kebab: String = key
                    .chars()
                    .flat_map(|c| {
                        if c.is_ascii_uppercase() {
                            vec!['-', c.to_ascii_lowercase()]
                        } else {
                            vec![c]
                        }
                    })
                    .collect();
                let arg = cmd
                    .get_arguments()
                    .find(|a| a.get_long() == Some(kebab.as_str()))
                    .unwrap_or_else(|| panic!("no flag --{kebab} for key {key}"));
                (key, arg.clone())
            })
            .collect()
    }

    /// Every file key has a flag of the same name in kebab case and an env var; and back.
    #[test]
    fn every_key_is_a_flag_and_an_env_var() {
        use clap::CommandFactory;
        let keys = keys_and_flags();
        for (key, arg) in &keys {
            let kebab = arg.get_long().unwrap();
            let env = arg
                .get_env()
                .unwrap_or_else(|| panic!("--{kebab} has no env var"));
            let want = if key == "gateway" {
                "LEKIWI_GATEWAY_URL".to_owned()
            } else {
                format!("LEKIWI_{}", kebab.replace('-', "_").to_ascii_uppercase())
            };
            assert_eq!(env.to_str().unwrap(), want, "env var of --{kebab}");
        }
        let flag_count = Flags::command()
            .get_arguments()
            .filter(|a| a.get_long().is_some())
            .count();
        // config and print-config (and clap's help/version, which have no long here) aside.
        assert_eq!(flag_count - 2, keys.len(), "a flag without a file key");
    }

    /// The README's configuration table has one row per key, with its flag, environment
    /// variable, default and help text as the agent has them.
    #[test]
    fn the_readme_table_matches_the_flags() {
        let readme =
            std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../README.md")).unwrap();
        let rows: Vec<Vec<&str>> = readme
            .lines()
            .filter(|l| l.starts_with("| `") && l.contains("` | `--"))
            .map(|l| l.trim_matches('|').split(" | ").map(str::trim).collect())
            .collect();
        let defaults = serde_json::to_value(Config::default()).unwrap();
        let keys = keys_and_flags();
        for (key, arg) in &keys {
            let long = arg.get_long().unwrap();
            let row = rows
                .iter()
                .find(|r| r[0] == format!("`{key}`"))
                .unwrap_or_else(|| panic!("README: no row for `{key}`"));
            assert_eq!(row[1], format!("`--{long}`"), "{key}");
            let env = arg.get_env().unwrap().to_str().unwrap();
            assert_eq!(row[2], format!("`{env}`"), "{key}");
            let default = match (key.as_str(), &defaults[key]) {
                ("gateway", _) => "(required)".to_owned(),
                ("robotName", _) => "`host name`".to_owned(),
                (_, serde_json::Value::Null) => "—".to_owned(),
                (_, serde_json::Value::String(s)) if s.is_empty() => "`(none)`".to_owned(),
                (_, serde_json::Value::String(s)) => format!("`{s}`"),
                (_, serde_json::Value::Array(a)) => format!(
                    "`{}`",
                    a.iter()
                        .map(|v| v.to_string())
                        .collect::<Vec<_>>()
                        .join(",")
                ),
                (_, v) => format!("`{v}`"),
            };
            assert_eq!(row[3], default, "default of {key}");
            let help = arg.get_help().unwrap().to_string();
            assert_eq!(row[4], help.trim_end_matches('.'), "help of {key}");
        }
        assert_eq!(keys.len(), rows.len(), "README rows without a flag");
    }
}
