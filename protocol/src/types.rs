//! The facts messages carry: releases, the robot's computer, health, teleoperation, readings,
//! events and telemetry samples.

use serde::{Deserialize, Serialize};

/// A release as the agent reports or is told to run it.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, Eq, Hash)]
pub struct Release {
    /// Version name.
    pub version: String,
    /// `sha256:<hex>` digest of the release manifest.
    pub digest: String,
}

/// Facts about the robot's computer, sent once in `hello`.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct SystemFacts {
    /// Host name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hostname: Option<String>,
    /// Operating system name and version.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub os: Option<String>,
    /// Kernel version.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kernel: Option<String>,
    /// CPU architecture, e.g. `aarch64`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub arch: Option<String>,
    /// Logical CPUs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cpus: Option<u32>,
    /// Total memory in bytes.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub memory_bytes: Option<u64>,
}

/// The agent's health verdict.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, Eq)]
pub struct Health {
    /// Whether every check passes.
    pub healthy: bool,
    /// Why not, for people.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
    /// Why not, for machines: one CamelCase word naming the first failed check, e.g.
    /// `HostProcessNotRunning`. Optional (agents before it send only `message`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
}

impl Health {
    /// Every check passes.
    pub fn ok() -> Self {
        Self {
            healthy: true,
            message: None,
            reason: None,
        }
    }
}

/// The agent's teleoperation verdict.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Teleoperation {
    /// Whether somebody operates the robot.
    pub active: bool,
    /// Weighted indicator score, 0 to 1.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub score: Option<f64>,
}

/// Current readings sent with every heartbeat; all optional.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct Vitals {
    /// Seconds since boot.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub uptime_s: Option<u64>,
    /// CPU use, percent of all cores.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cpu_percent: Option<f64>,
    /// Memory in use, percent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub memory_percent: Option<f64>,
    /// One-minute load average.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub load1: Option<f64>,
    /// Root file system use, percent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub disk_percent: Option<f64>,
    /// SoC temperature, degrees Celsius.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub temperature_c: Option<f64>,
    /// Battery charge, percent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub battery_percent: Option<f64>,
    /// Resident memory of the LeKiwi host process (the agent's `hostProcessPattern`), bytes.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub host_rss_bytes: Option<u64>,
    /// CPU use of the LeKiwi host process since the previous reading, percent of all cores.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub host_cpu_percent: Option<f64>,
}

/// One stored agent event as the gateway's events endpoint answers it (and as its store keeps
/// it): durable `event` frames, and `progress` frames with kind `progress`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoredEvent {
    /// The robot's sequence number, shared with telemetry.
    pub seq: u64,
    /// When it happened on the robot, Unix milliseconds.
    pub ts_ms: i64,
    /// What happened, e.g. `teleoperation_started` or `progress`.
    pub kind: String,
    /// `info`, `warning` or `error`.
    pub severity: String,
    /// Human-readable text.
    pub message: String,
    /// Structured details; `null` when there are none.
    #[serde(default)]
    pub data: serde_json::Value,
}

/// Milliseconds since the Unix epoch by this machine's clock (0 before 1970; saturates).
pub fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
        .unwrap_or_default()
}

/// Severity of an agent event.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq, Hash)]
#[serde(rename_all = "snake_case")]
pub enum Severity {
    /// Routine.
    Info,
    /// Worth a look.
    Warning,
    /// Something failed.
    Error,
    /// A severity this version does not know (from a newer agent); stored as `unknown`.
    #[serde(other)]
    Unknown,
}

/// One telemetry sample.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Sample {
    /// Metric name, e.g. `cpu_percent`.
    pub metric: String,
    /// When it was taken, Unix milliseconds.
    pub ts_ms: i64,
    /// The reading, in the unit the metric name says.
    pub value: f64,
}
