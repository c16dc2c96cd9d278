//! Post-switch analysis: what a `RobotDeployment` asks of a robot after it switched
//! (`spec.analysis`), and what the gateway measured before and after the switch
//! (`Robot.status.analysis`).

use k8s_openapi::apimachinery::pkg::apis::meta::v1::Time;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::release::ReleaseRef;

/// Longest analysis window, seconds (the most `windowSeconds` allows): a gateway that takes a
/// robot over goes on from the window summary in its status for this long after its switch.
pub const MAX_WINDOW_SECONDS: i64 = 600;

/// Annotation on a Robot: the `windowSeconds` of the `spec.analysis` of the RobotDeployment that
/// set its `spec.release` (written by the rollout together with `spec.release`, removed by a
/// write without analysis). The gateway holding the robot writes its status once more when the
/// window of its switch to that release has spanned this long: the write the rollout judges. A
/// switch without it costs no status write beyond the switch's own.
pub const WINDOW_ANNOTATION: &str = "fleet.lekiwi.io/analysis-window-seconds";

/// Most telemetry metrics a window keeps the highest reading of (the first ones seen).
pub const MAX_TELEMETRY_METRICS: usize = 16;

/// Watches each updated robot for a while after its switch and fails it when its telemetry got
/// worse than before the switch by more than the given ratios. A failed robot counts against
/// the batch's `successThreshold` like any other failure (and so can roll the fleet back).
/// Every threshold is optional; a metric the robot does not report is not judged.
#[derive(Clone, Debug, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct AnalysisSpec {
    /// How long to watch a robot after it reported the switch `done`, seconds, from 1 to 600.
    /// Default 120. The robot counts as updated only once the window has passed.
    #[serde(default = "default_window")]
    #[schemars(range(min = 1, max = 600))]
    pub window_seconds: i64,

    /// Largest allowed ratio of the host process's resident memory after the switch (the
    /// highest reading in the window) to before it (the mean reading), e.g. 1.5.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 0.0))]
    pub max_host_memory_ratio: Option<f64>,

    /// Largest allowed ratio of the host process's mean CPU use after the switch to before
    /// it, e.g. 2.0.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 0.0))]
    pub max_host_cpu_ratio: Option<f64>,

    /// Largest allowed ratio of the robot's memory use (percent of total; the highest reading
    /// in the window) after the switch to before it (the mean reading), e.g. 1.5.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 0.0))]
    pub max_robot_memory_ratio: Option<f64>,

    /// Largest allowed ratio of the mean heartbeat round-trip time after the switch to before
    /// it, e.g. 2.0.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 0.0))]
    pub max_rtt_ratio: Option<f64>,

    /// Largest allowed share, from 0 to 1, of `error` events among the events the robot sent in
    /// the window, e.g. 0.05. Judged only when it sent some.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 0.0, max = 1.0))]
    pub max_error_event_fraction: Option<f64>,

    /// Largest allowed number of `error` events per minute of the window.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 0.0))]
    pub max_error_events_per_minute: Option<f64>,

    /// Absolute ceilings on telemetry the robot sends (`telemetry` frames), by metric name: the
    /// robot fails if a reading in the window is above its ceiling. At most 16.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    #[schemars(length(max = 16))]
    pub telemetry: Vec<TelemetryCeiling>,
}

/// An absolute ceiling on one telemetry metric.
#[derive(Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct TelemetryCeiling {
    /// The metric's name as the agent sends it, e.g. `cpu_percent`.
    #[schemars(length(min = 1, max = 64))]
    pub metric: String,
    /// Highest allowed reading, in the metric's unit.
    pub max: f64,
}

fn default_window() -> i64 {
    120
}

impl Default for AnalysisSpec {
    fn default() -> Self {
        Self {
            window_seconds: default_window(),
            max_host_memory_ratio: None,
            max_host_cpu_ratio: None,
            max_robot_memory_ratio: None,
            max_rtt_ratio: None,
            max_error_event_fraction: None,
            max_error_events_per_minute: None,
            telemetry: Vec::new(),
        }
    }
}

/// Readings of one metric over a stretch of time: how many, their mean and their highest.
#[derive(Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct MetricSummary {
    /// Number of readings.
    pub samples: u32,
    /// Their mean.
    pub mean: f64,
    /// The highest.
    pub max: f64,
}

/// One robot's metrics before and after a switch, as the gateway holding its connection saw
/// them in its heartbeats.
#[derive(Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct MetricWindow {
    /// `host_rss_bytes`: the host process's resident memory, bytes.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub host_memory_bytes: Option<MetricSummary>,
    /// `host_cpu_percent`: the host process's CPU use, percent of all cores.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub host_cpu_percent: Option<MetricSummary>,
    /// `memory_percent`: the robot's memory use, percent of total.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub memory_percent: Option<MetricSummary>,
    /// `rtt_ms`: the heartbeat round-trip time the agent measured, milliseconds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rtt_ms: Option<MetricSummary>,
    /// Events the robot sent (`event` frames), all and `error` ones.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub events: Option<EventCounts>,
    /// The highest reading of each telemetry metric the robot sent (at most 16 metrics, the
    /// first seen).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    #[schemars(length(max = 16))]
    pub telemetry: Vec<TelemetryCeiling>,
}

/// Events received over a stretch of time.
#[derive(Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct EventCounts {
    /// Every event.
    pub total: u32,
    /// Those of severity `error`.
    pub errors: u32,
}

/// The gateway's summary of a robot's last switch: the baseline (heartbeats since the switch
/// before it, or since the gateway first saw the robot) and the window after it (heartbeats
/// since the agent reported the switch `done`). Rollouts with `spec.analysis` judge it.
#[derive(Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct AnalysisReport {
    /// When the baseline's first reading arrived.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub baseline_start: Option<Time>,
    /// The release switched to.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub release: Option<ReleaseRef>,
    /// When the gateway received the `done` report: the window's start.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub window_start: Option<Time>,
    /// When the last heartbeat counted in `window` arrived.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub window_end: Option<Time>,
    /// Readings before the switch.
    #[serde(default)]
    pub baseline: MetricWindow,
    /// Readings since the switch.
    #[serde(default)]
    pub window: MetricWindow,
}
