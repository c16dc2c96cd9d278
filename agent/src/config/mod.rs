//! Agent configuration: a YAML file and its drop-ins, overridden by flags and `LEKIWI_*`
//! environment variables.
//!
//! The lab's file (`/etc/lekiwi/agent.yaml`) comes first, then every `*.yaml` of the drop-in
//! directory beside it (`/etc/lekiwi/agent.d/`) in name order, a later file's keys replacing an
//! earlier one's: `lekiwi-agent join` writes its own drop-in and never the lab's file.
//!
//! Every key of the file is also a flag (`--kebab-case`) and an environment variable
//! (`LEKIWI_SCREAMING_CASE`); a test keeps the three in step. The file is flat on purpose, so
//! the mapping is obvious: `telemetryCpuIntervalS: 5` is `--telemetry-cpu-interval-s 5` is
//! `LEKIWI_TELEMETRY_CPU_INTERVAL_S=5`.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use lekiwi_protocol::transport::plaintext_remote_host;
use serde::{Deserialize, Serialize};

mod flags;

pub use flags::{Command, Flags, JoinArgs};

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
    /// The gateway URL is plain text to another host and plain text was not allowed.
    #[error(
        "gateway {gateway} is plain ws:// to {host}, not this machine: anyone on the path could read \
         the robot's token and send it deployments. Use wss:// (with --ca-file for a private CA), or \
         on a network you trust pass --insecure-allow-plaintext (LEKIWI_INSECURE_ALLOW_PLAINTEXT=true)"
    )]
    Plaintext { gateway: String, host: String },
    /// A required setting is missing everywhere.
    #[error("no gateway configured: set `gateway` in {path}, --gateway or LEKIWI_GATEWAY_URL")]
    MissingGateway { path: PathBuf },
}

/// The effective configuration. Field names are the config file's keys; each field's flag in
/// [`Flags`] has the full help text shown by `--help` and the book's generated reference.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase", deny_unknown_fields, default)]
pub struct Config {
    /// `ws://` or `wss://` URL of the gateway's agent endpoint (required).
    pub gateway: String,
    /// PEM CA that `wss://` trusts instead of the public web roots.
    pub ca_file: Option<PathBuf>,
    /// Allows a `ws://` gateway on another host (token and deployments readable and forgeable
    /// on the path); without it such a URL is refused at start.
    pub insecure_allow_plaintext: bool,
    /// Holds the robot's token, the outbox and the releases; must survive reboots.
    pub state_dir: PathBuf,
    /// `namespace/name` or `name`; empty means the host name.
    pub robot_name: String,
    /// Read once, when the state directory holds no token of the robot's own.
    pub enrollment_token_file: Option<PathBuf>,
    /// Takes precedence over the file; never printed.
    #[serde(skip_serializing)]
    pub enrollment_token: Option<String>,
    /// Upper bound of the first reconnect delay, ms (doubles per failure).
    pub backoff_initial_ms: u64,
    /// Upper bound of every reconnect delay, ms.
    pub backoff_max_ms: u64,
    /// Time for the connection and `welcome` together, s.
    pub connect_timeout_s: u64,
    /// Bytes of queued messages before the oldest telemetry (then events) is dropped.
    pub outbox_max_bytes: u64,
    /// Durable messages sent and not yet acknowledged, at most.
    pub outbox_window: u32,
    /// `host:port` of the local JSON status endpoint, or `off`.
    pub status_listen: String,
    /// Whether to advertise `_lekiwi._tcp.local` over mDNS.
    pub mdns: bool,
    /// `text` or `json` log lines.
    pub log_format: String,

    /// Seconds between CPU samples.
    pub telemetry_cpu_interval_s: u64,
    /// Seconds between memory samples.
    pub telemetry_memory_interval_s: u64,
    /// Seconds between network samples.
    pub telemetry_network_interval_s: u64,
    /// Seconds between temperature samples.
    pub telemetry_temperature_interval_s: u64,
    /// Seconds between disk samples.
    pub telemetry_disk_interval_s: u64,
    /// Seconds between samples sent whether or not they moved.
    pub telemetry_full_interval_s: u64,
    /// Seconds between telemetry messages (samples are batched).
    pub telemetry_batch_interval_s: u64,
    /// Percentage points the CPU must move to be sent.
    pub telemetry_cpu_delta: f64,
    /// Percentage points memory use must move to be sent.
    pub telemetry_memory_delta: f64,
    /// Fraction a network rate must move to be sent.
    pub telemetry_network_delta: f64,
    /// Degrees Celsius the temperature must move to be sent.
    pub telemetry_temperature_delta: f64,
    /// Percentage points disk use must move to be sent.
    pub telemetry_disk_delta: f64,

    /// Seconds between teleoperation checks.
    pub teleop_interval_s: f64,
    /// Sum of the weights of firing indicators from which the robot counts as teleoperated.
    pub teleop_threshold: f64,
    /// Substring of the LeKiwi host process's command line.
    pub teleop_process_pattern: String,
    /// Weight of "the host process runs" (0: indicator off).
    pub teleop_process_weight: f64,
    /// Host ports for commands; an ESTABLISHED connection on one is an indicator.
    pub teleop_command_ports: Vec<u16>,
    /// Weight of a command connection (0: indicator off).
    pub teleop_command_weight: f64,
    /// Host ports for video.
    pub teleop_video_ports: Vec<u16>,
    /// Weight of a video connection (0: indicator off).
    pub teleop_video_weight: f64,
    /// Video stream (e.g. RTSP) ports.
    pub teleop_stream_ports: Vec<u16>,
    /// Weight of a stream connection (0: indicator off).
    pub teleop_stream_weight: f64,
    /// Motor serial device; another process holding it open is an indicator.
    pub teleop_serial_device: PathBuf,
    /// Weight of the held serial device (0: indicator off).
    pub teleop_serial_weight: f64,

    /// Shell command run every health interval; exiting non-zero makes the robot unhealthy.
    pub health_command: String,
    /// Seconds between health checks (0.5 to 3600).
    pub health_interval_s: f64,
    /// Seconds `healthCommand` may run (0.1 to 300).
    pub health_timeout_s: f64,
    /// Substring of the command line of a process that must run; empty: not checked.
    pub host_process_pattern: String,
    /// Device (e.g. the motor serial port) that must exist; unset: not checked.
    pub health_serial_device: Option<PathBuf>,
    /// Use (percent) of the state directory's file system from which the robot is unhealthy;
    /// 0: not checked.
    pub health_disk_max_percent: f64,

    /// Shell command run in a new release before the switch; failing aborts the deployment.
    pub release_pre_switch_command: String,
    /// Shell command that restarts the robot's software after a switch.
    pub release_restart_command: String,
    /// Shell command that passes once the new release is healthy (retried until the timeout).
    pub release_health_command: String,
    /// Seconds the health command may take to pass.
    pub release_health_timeout_s: u64,
    /// Seconds the pre-switch and restart commands may each run.
    pub release_hook_timeout_s: u64,
    /// Releases kept on disk, the current one included (at least 2, for rollback).
    pub release_keep: u32,
    /// Cap on the download rate of release blobs, bytes per second, over all parallel
    /// downloads (0: no cap). For robots on a shared or metered link, and for tests.
    pub release_download_rate_limit: u64,
    /// Seconds a new agent build has to reach the gateway before the guard switches back.
    pub agent_update_deadline_s: u64,
    /// Starts of a new agent build without reaching the gateway before the guard switches back.
    pub agent_update_max_starts: u32,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            gateway: String::new(),
            ca_file: None,
            insecure_allow_plaintext: false,
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
            health_command: String::new(),
            health_interval_s: 10.0,
            health_timeout_s: 10.0,
            host_process_pattern: String::new(),
            health_serial_device: None,
            health_disk_max_percent: 95.0,
            release_pre_switch_command: String::new(),
            release_restart_command: String::new(),
            release_health_command: String::new(),
            release_health_timeout_s: 60,
            release_hook_timeout_s: 300,
            release_keep: 3,
            release_download_rate_limit: 0,
            agent_update_deadline_s: 300,
            agent_update_max_starts: 3,
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

    /// File, drop-ins, environment and flags merged, without checking that the gateway is set
    /// (for subcommands that work on the state directory only).
    pub fn merge(flags: &Flags) -> Result<Self, Error> {
        let mut merged = read_files(&flags.config)?;
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
        if let Some(host) = plaintext_remote_host(&self.gateway)
            && !self.insecure_allow_plaintext
        {
            return Err(Error::Plaintext {
                gateway: self.gateway.clone(),
                host: host.to_owned(),
            });
        }
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
        health_bounds(self)?;
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

    /// This configuration with sensors quiet: telemetry sampled hourly, teleoperation checked
    /// hourly with every indicator off, no health check (always healthy). For many agents on one machine (the fleet binary,
    /// tests), where vitals and processes say nothing about any one robot.
    pub fn without_sensors(self) -> Self {
        Self {
            telemetry_cpu_interval_s: 3600,
            telemetry_memory_interval_s: 3600,
            telemetry_network_interval_s: 3600,
            telemetry_temperature_interval_s: 3600,
            telemetry_disk_interval_s: 3600,
            telemetry_batch_interval_s: 3600,
            teleop_interval_s: 3600.0,
            teleop_process_weight: 0.0,
            teleop_command_weight: 0.0,
            teleop_video_weight: 0.0,
            teleop_stream_weight: 0.0,
            teleop_serial_weight: 0.0,
            health_command: String::new(),
            health_interval_s: 3600.0,
            host_process_pattern: String::new(),
            health_serial_device: None,
            health_disk_max_percent: 0.0,
            ..self
        }
    }

    /// This configuration with telemetry sampled every `every_s` seconds in the proportions of
    /// the defaults (CPU and network every `every_s`, memory every 2×, temperature 6×, disk
    /// 12×; 5 s gives exactly the defaults) and sent in batches every `batch_s` seconds: for
    /// simulated robots, whose readings come from [`crate::telemetry::Telemetry::synthetic`].
    pub fn with_telemetry_every(self, every_s: u64, batch_s: u64) -> Self {
        let every_s = every_s.max(1);
        Self {
            telemetry_cpu_interval_s: every_s,
            telemetry_memory_interval_s: every_s * 2,
            telemetry_network_interval_s: every_s,
            telemetry_temperature_interval_s: every_s * 6,
            telemetry_disk_interval_s: every_s * 12,
            telemetry_batch_interval_s: batch_s.max(1),
            ..self
        }
    }

    /// The warning to log at start when the gateway is plain text to another host (allowed by
    /// `insecureAllowPlaintext`, or [`Config::load`] would have refused it).
    pub fn plaintext_warning(&self) -> Option<String> {
        plaintext_remote_host(&self.gateway).map(|host| {
            format!(
                "INSECURE: the gateway {} is plain ws:// to {host}; anyone on the path can read this \
                 robot's token and send it deployments (code execution). Use wss://",
                self.gateway
            )
        })
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

/// The health check's timing and threshold stay within bounds: a check neither hammers the robot
/// nor hangs, and a disk threshold is a percentage.
fn health_bounds(c: &Config) -> Result<(), Error> {
    let within = |v: f64, lo: f64, hi: f64| v.is_finite() && (lo..=hi).contains(&v);
    if !within(c.health_interval_s, 0.5, 3600.0) {
        return Err(Error::Invalid(format!(
            "healthIntervalS ({}) must be 0.5 to 3600",
            c.health_interval_s
        )));
    }
    if !within(c.health_timeout_s, 0.1, 300.0) {
        return Err(Error::Invalid(format!(
            "healthTimeoutS ({}) must be 0.1 to 300",
            c.health_timeout_s
        )));
    }
    if !within(c.health_disk_max_percent, 0.0, 100.0) {
        return Err(Error::Invalid(format!(
            "healthDiskMaxPercent ({}) must be 0 (off) to 100",
            c.health_disk_max_percent
        )));
    }
    Ok(())
}

/// The drop-in directory of a config file: beside it, named after it with `.d`
/// (`/etc/lekiwi/agent.yaml` has `/etc/lekiwi/agent.d`).
pub fn drop_in_dir(config: &Path) -> PathBuf {
    let stem = config
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    config
        .parent()
        .unwrap_or(Path::new("/"))
        .join(format!("{stem}.d"))
}

/// The config file's keys, then each drop-in's (`*.yaml`, in name order) over them.
fn read_files(config: &Path) -> Result<serde_json::Map<String, serde_json::Value>, Error> {
    let mut merged = read_file(config)?;
    let dir = drop_in_dir(config);
    let entries = match std::fs::read_dir(&dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(merged),
        Err(source) => return Err(Error::ReadConfig { path: dir, source }),
    };
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "yaml") && p.is_file())
        .collect();
    files.sort();
    for file in files {
        merged.extend(read_file(&file)?);
    }
    Ok(merged)
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
mod tests;
