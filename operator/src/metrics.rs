//! Prometheus metrics of the operator (`lekiwi_*`), with bounded label sets only.

use std::collections::HashMap;
use std::sync::atomic::AtomicU64;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use lekiwi_protocol::{Release, Vitals};

use prometheus_client::encoding::{EncodeLabelSet, EncodeLabelValue};
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;

/// Which controller a series belongs to.
#[derive(Clone, Copy, Debug, Hash, PartialEq, Eq, EncodeLabelValue)]
#[allow(non_camel_case_types)]
pub enum ControllerName {
    /// The Robot controller.
    robot,
    /// The RobotDeployment controller.
    deployment,
}

/// Labels of per-controller series.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct ControllerLabels {
    /// The controller.
    pub controller: ControllerName,
}

/// Labels of per-controller error series.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct ErrorLabels {
    /// The controller.
    pub controller: ControllerName,
    /// Bounded error category.
    pub reason: &'static str,
}

/// Labels of per-phase series.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct PhaseLabels {
    /// A `Robot` phase.
    pub phase: &'static str,
}

/// Labels of gateway status-queue series.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct PriorityLabels {
    /// `high` or `low`.
    pub priority: &'static str,
}

/// Labels of gateway status writes.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct WriteLabels {
    /// `high` or `low`.
    pub priority: &'static str,
    /// `ok`, `error`, `gone` or `superseded`.
    pub result: &'static str,
}

/// A bounded label with one value from a fixed set.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct KindLabels {
    /// The kind (frame type, error code, refusal reason, ...).
    pub kind: &'static str,
}

/// All metrics, cheap to clone.
#[derive(Clone)]
pub struct Metrics {
    registry: Arc<Registry>,
    /// Reconciles started.
    pub reconciliations: Family<ControllerLabels, Counter>,
    /// Reconciles that failed.
    pub reconcile_errors: Family<ErrorLabels, Counter>,
    /// Reconcile latency.
    pub reconcile_duration: Family<ControllerLabels, Histogram>,
    /// Robots by phase, as the leader last saw them.
    pub robots: Family<PhaseLabels, Gauge>,
    /// Robots whose agent reports teleoperation, as the leader last saw them.
    pub robots_teleoperating: Gauge,
    /// Robot phase transitions, by the phase entered.
    pub robot_transitions: Family<PhaseLabels, Counter>,
    /// 1 while this replica holds the leader Lease.
    pub is_leader: Gauge,
    /// Times this replica became leader.
    pub leader_acquisitions: Counter,
    /// Agent connections open now.
    pub gateway_connections: Gauge,
    /// Sessions ended, by how (`closed`, `replaced`, `heartbeat_timeout`, `error`, ...).
    pub gateway_sessions_ended: Family<KindLabels, Counter>,
    /// Upgrade requests refused, by reason.
    pub gateway_refused: Family<KindLabels, Counter>,
    /// Frames received, by message type.
    pub gateway_frames: Family<KindLabels, Counter>,
    /// Error frames sent, by code.
    pub gateway_errors: Family<KindLabels, Counter>,
    /// Durable messages acknowledged, `stored` or `replay`.
    pub gateway_durable: Family<KindLabels, Counter>,
    /// Heartbeat round-trip time the agents report.
    pub gateway_heartbeat_rtt: Histogram,
    /// Robots waiting for a status write, by priority.
    pub gateway_status_queue: Family<PriorityLabels, Gauge>,
    /// Status writes, by priority and result.
    pub gateway_status_writes: Family<WriteLabels, Counter>,
    /// Legacy polls answered, `200` or `304`.
    pub gateway_polls: Family<KindLabels, Counter>,
    /// Blob bytes sent to robots and clients (no per-robot label: robots are unbounded).
    pub gateway_blob_bytes_served: Counter,
    /// Blob bytes received in uploads.
    pub gateway_blob_bytes_received: Counter,
    /// Blob upload requests, by outcome (`created`, `partial`, `exists`, `conflict`, ...).
    pub gateway_blob_uploads: Family<KindLabels, Counter>,
    /// Rollout metrics.
    pub rollouts: RolloutMetrics,
    /// Per-robot vitals and release (empty unless `--per-robot-metrics`).
    pub per_robot: RobotMetrics,
}

impl Default for Metrics {
    /// Without per-robot series.
    fn default() -> Self {
        Self::new(false)
    }
}

impl Metrics {
    /// All metrics; per-robot series only when `per_robot` is set.
    pub fn new(per_robot: bool) -> Self {
        let mut registry = Registry::default();
        let reconciliations = Family::<ControllerLabels, Counter>::default();
        let reconcile_errors = Family::<ErrorLabels, Counter>::default();
        let reconcile_duration =
            Family::<ControllerLabels, Histogram>::new_with_constructor(|| {
                Histogram::new(exponential_buckets(0.001, 2.0, 14))
            });
        let robots = Family::<PhaseLabels, Gauge>::default();
        let robot_transitions = Family::<PhaseLabels, Counter>::default();
        let robots_teleoperating = Gauge::default();
        let is_leader = Gauge::default();
        let leader_acquisitions = Counter::default();
        let gateway_connections = Gauge::default();
        let gateway_sessions_ended = Family::<KindLabels, Counter>::default();
        let gateway_refused = Family::<KindLabels, Counter>::default();
        let gateway_frames = Family::<KindLabels, Counter>::default();
        let gateway_errors = Family::<KindLabels, Counter>::default();
        let gateway_durable = Family::<KindLabels, Counter>::default();
        let gateway_heartbeat_rtt = Histogram::new(exponential_buckets(0.0005, 2.0, 14));
        let gateway_status_queue = Family::<PriorityLabels, Gauge>::default();
        let gateway_status_writes = Family::<WriteLabels, Counter>::default();
        let gateway_polls = Family::<KindLabels, Counter>::default();
        let gateway_blob_bytes_served = Counter::default();
        let gateway_blob_bytes_received = Counter::default();
        let gateway_blob_uploads = Family::<KindLabels, Counter>::default();
        let rollouts = RolloutMetrics::register(&mut registry);
        let per_robot = RobotMetrics::register(&mut registry, per_robot);
        registry.register(
            "lekiwi_gateway_connections",
            "Agent connections open now",
            gateway_connections.clone(),
        );
        registry.register(
            "lekiwi_gateway_sessions_ended",
            "Agent sessions ended, by how",
            gateway_sessions_ended.clone(),
        );
        registry.register(
            "lekiwi_gateway_refused",
            "Agent upgrade requests refused, by reason",
            gateway_refused.clone(),
        );
        registry.register(
            "lekiwi_gateway_frames",
            "Frames received from agents, by message type",
            gateway_frames.clone(),
        );
        registry.register(
            "lekiwi_gateway_error_frames",
            "Error frames sent to agents, by code",
            gateway_errors.clone(),
        );
        registry.register(
            "lekiwi_gateway_durable_messages",
            "Durable agent messages acknowledged, stored or replay",
            gateway_durable.clone(),
        );
        registry.register(
            "lekiwi_gateway_heartbeat_rtt_seconds",
            "Heartbeat round-trip time as reported by agents",
            gateway_heartbeat_rtt.clone(),
        );
        registry.register(
            "lekiwi_gateway_status_queue",
            "Robots waiting for a status write, by priority",
            gateway_status_queue.clone(),
        );
        registry.register(
            "lekiwi_gateway_status_writes",
            "Robot status writes, by priority and result",
            gateway_status_writes.clone(),
        );
        registry.register(
            "lekiwi_gateway_polls",
            "Legacy polls answered, by status code",
            gateway_polls.clone(),
        );
        registry.register(
            "lekiwi_gateway_blob_bytes_served",
            "Release blob bytes sent to robots and clients",
            gateway_blob_bytes_served.clone(),
        );
        registry.register(
            "lekiwi_gateway_blob_bytes_received",
            "Release blob bytes received in uploads",
            gateway_blob_bytes_received.clone(),
        );
        registry.register(
            "lekiwi_gateway_blob_uploads",
            "Release blob upload requests, by outcome",
            gateway_blob_uploads.clone(),
        );
        registry.register(
            "lekiwi_controller_reconciliations",
            "Reconciles started, by controller",
            reconciliations.clone(),
        );
        registry.register(
            "lekiwi_controller_reconcile_errors",
            "Reconciles that failed, by controller and error category",
            reconcile_errors.clone(),
        );
        registry.register(
            "lekiwi_controller_reconcile_duration_seconds",
            "Time one reconcile took, by controller",
            reconcile_duration.clone(),
        );
        registry.register(
            "lekiwi_robots",
            "Robots by phase, as the leader sees them",
            robots.clone(),
        );
        registry.register(
            "lekiwi_robots_teleoperating",
            "Robots whose agent reports teleoperation active, as the leader sees them (no \
             per-robot label)",
            robots_teleoperating.clone(),
        );
        registry.register(
            "lekiwi_robot_phase_transitions",
            "Robot phase transitions, by the phase entered",
            robot_transitions.clone(),
        );
        registry.register(
            "lekiwi_leader_election_is_leader",
            "1 while this replica holds the leader Lease, else 0",
            is_leader.clone(),
        );
        registry.register(
            "lekiwi_leader_election_acquisitions",
            "Times this replica became leader",
            leader_acquisitions.clone(),
        );
        Self {
            registry: Arc::new(registry),
            reconciliations,
            reconcile_errors,
            reconcile_duration,
            robots,
            robot_transitions,
            robots_teleoperating,
            is_leader,
            leader_acquisitions,
            gateway_connections,
            gateway_sessions_ended,
            gateway_refused,
            gateway_frames,
            gateway_errors,
            gateway_durable,
            gateway_heartbeat_rtt,
            gateway_status_queue,
            gateway_status_writes,
            gateway_polls,
            gateway_blob_bytes_served,
            gateway_blob_bytes_received,
            gateway_blob_uploads,
            rollouts,
            per_robot,
        }
    }

    /// Renders every metric in the OpenMetrics text format.
    pub fn encode(&self) -> String {
        let mut out = String::new();
        // Writing into a String cannot fail.
        let _ = prometheus_client::encoding::text::encode(&mut out, &self.registry);
        out
    }

    /// Counts a reconcile and returns a guard that records its duration when dropped.
    pub fn reconcile_started(&self, controller: ControllerName) -> ReconcileTimer {
        let labels = ControllerLabels { controller };
        self.reconciliations.get_or_create(&labels).inc();
        ReconcileTimer {
            histogram: self.reconcile_duration.get_or_create(&labels).clone(),
            start: Instant::now(),
        }
    }
}

/// Records a reconcile's duration on drop.
pub struct ReconcileTimer {
    histogram: Histogram,
    start: Instant,
}

impl Drop for ReconcileTimer {
    fn drop(&mut self) {
        self.histogram.observe(self.start.elapsed().as_secs_f64());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_follow_the_lekiwi_convention() {
        let m = Metrics::default();
        drop(m.reconcile_started(ControllerName::robot));
        m.robots
            .get_or_create(&PhaseLabels { phase: "Online" })
            .set(3);
        let text = m.encode();
        assert!(
            text.contains("lekiwi_controller_reconciliations_total{controller=\"robot\"} 1"),
            "{text}"
        );
        assert!(text.contains(
            "lekiwi_controller_reconcile_duration_seconds_count{controller=\"robot\"} 1"
        ));
        assert!(text.contains("lekiwi_robots{phase=\"Online\"} 3"));
        assert!(text.ends_with("# EOF\n"));
    }
}

/// Labels of per-deployment series (bounded by the number of RobotDeployments, which people
/// create by hand).
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct DeploymentLabels {
    /// Namespace.
    pub namespace: String,
    /// RobotDeployment name.
    pub deployment: String,
}

/// Labels of rollout outcome series.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct OutcomeLabels {
    /// `completed`, `rolled_back` or `failed` (rollouts); `succeeded` or `failed` (batches).
    pub outcome: &'static str,
}

/// Labels of per-deployment phase series.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct DeploymentPhaseLabels {
    /// Namespace.
    pub namespace: String,
    /// RobotDeployment name.
    pub deployment: String,
    /// Its phase.
    pub phase: &'static str,
}

/// What the RobotDeployment controller exports.
#[derive(Clone)]
pub struct RolloutMetrics {
    /// 1 for the phase each deployment is in, 0 for the others.
    pub phase: Family<DeploymentPhaseLabels, Gauge>,
    /// Targeted, updated and failed robots per deployment.
    pub targeted: Family<DeploymentLabels, Gauge>,
    /// Robots running the release.
    pub updated: Family<DeploymentLabels, Gauge>,
    /// Robots that failed.
    pub failed: Family<DeploymentLabels, Gauge>,
    /// Index of the batch being rolled out.
    pub current_batch: Family<DeploymentLabels, Gauge>,
    /// Finished rollouts, by outcome.
    pub finished: Family<OutcomeLabels, Counter>,
    /// How long finished rollouts took, by outcome.
    pub duration: Family<OutcomeLabels, Histogram>,
    /// Finished batches, by outcome.
    pub batches: Family<OutcomeLabels, Counter>,
    /// Success ratio of finished batches.
    pub batch_success: Histogram,
}

impl RolloutMetrics {
    fn register(registry: &mut Registry) -> Self {
        let m = Self {
            phase: Family::default(),
            targeted: Family::default(),
            updated: Family::default(),
            failed: Family::default(),
            current_batch: Family::default(),
            finished: Family::default(),
            duration: Family::new_with_constructor(|| {
                Histogram::new(exponential_buckets(1.0, 2.0, 16))
            }),
            batches: Family::default(),
            batch_success: Histogram::new([0.0, 0.5, 0.7, 0.8, 0.9, 0.95, 0.99, 1.0]),
        };
        registry.register(
            "lekiwi_rollout_phase",
            "1 for the phase each RobotDeployment is in",
            m.phase.clone(),
        );
        registry.register(
            "lekiwi_rollout_targeted_robots",
            "Robots a RobotDeployment targets",
            m.targeted.clone(),
        );
        registry.register(
            "lekiwi_rollout_updated_robots",
            "Robots of a RobotDeployment running its release",
            m.updated.clone(),
        );
        registry.register(
            "lekiwi_rollout_failed_robots",
            "Robots of a RobotDeployment that failed to update",
            m.failed.clone(),
        );
        registry.register(
            "lekiwi_rollout_current_batch",
            "Index of the batch a RobotDeployment is rolling out",
            m.current_batch.clone(),
        );
        registry.register(
            "lekiwi_rollouts_finished",
            "Rollouts finished, by outcome",
            m.finished.clone(),
        );
        registry.register(
            "lekiwi_rollout_duration_seconds",
            "Duration of finished rollouts, by outcome",
            m.duration.clone(),
        );
        registry.register(
            "lekiwi_rollout_batches",
            "Rollout batches finished, by outcome",
            m.batches.clone(),
        );
        registry.register(
            "lekiwi_rollout_batch_success_ratio",
            "Share of a finished batch's robots that updated",
            m.batch_success.clone(),
        );
        m
    }
}

/// Labels of per-robot series: one set per robot connected to this gateway.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct RobotLabels {
    /// Namespace of the Robot.
    pub namespace: String,
    /// Robot name.
    pub robot: String,
}

/// Labels of the per-robot release series: one version per robot at a time.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct RobotReleaseLabels {
    /// Namespace of the Robot.
    pub namespace: String,
    /// Robot name.
    pub robot: String,
    /// Release version the robot runs.
    pub version: String,
}

/// Per-robot gauges from heartbeats, behind `--per-robot-metrics`. Cost: about five series per
/// connected robot (a 10 000-robot fleet adds 50 000 series to every gateway's scrape), removed
/// when the robot disconnects; off by default.
#[derive(Clone)]
pub struct RobotMetrics {
    enabled: bool,
    /// CPU use, percent of all cores.
    pub cpu: Family<RobotLabels, Gauge<f64, AtomicU64>>,
    /// Memory in use, percent.
    pub memory: Family<RobotLabels, Gauge<f64, AtomicU64>>,
    /// SoC temperature.
    pub temperature: Family<RobotLabels, Gauge<f64, AtomicU64>>,
    /// 1 for the release version each robot runs.
    pub release: Family<RobotReleaseLabels, Gauge>,
    /// The version each robot's release series carries, to drop it when the version changes.
    versions: Arc<Mutex<HashMap<RobotLabels, String>>>,
}

impl RobotMetrics {
    fn register(registry: &mut Registry, enabled: bool) -> Self {
        let m = Self {
            enabled,
            cpu: Family::default(),
            memory: Family::default(),
            temperature: Family::default(),
            release: Family::default(),
            versions: Arc::default(),
        };
        registry.register(
            "lekiwi_robot_cpu_percent",
            "CPU use of each connected robot, percent of all cores, from its last heartbeat \
             (only with --per-robot-metrics; one series per connected robot)",
            m.cpu.clone(),
        );
        registry.register(
            "lekiwi_robot_memory_percent",
            "Memory in use on each connected robot, percent, from its last heartbeat (only with \
             --per-robot-metrics; one series per connected robot)",
            m.memory.clone(),
        );
        registry.register(
            "lekiwi_robot_temperature_celsius",
            "SoC temperature of each connected robot, from its last heartbeat (only with \
             --per-robot-metrics; one series per connected robot)",
            m.temperature.clone(),
        );
        registry.register(
            "lekiwi_robot_release_info",
            "1 for the release version each connected robot runs (only with \
             --per-robot-metrics; one series per connected robot, its version label changes \
             with each update)",
            m.release.clone(),
        );
        m
    }

    /// Records a heartbeat's vitals and the release the robot runs; nothing when disabled.
    pub fn record(&self, namespace: &str, robot: &str, vitals: &Vitals, release: Option<&Release>) {
        if !self.enabled {
            return;
        }
        let labels = RobotLabels {
            namespace: namespace.to_owned(),
            robot: robot.to_owned(),
        };
        for (family, value) in [
            (&self.cpu, vitals.cpu_percent),
            (&self.memory, vitals.memory_percent),
            (&self.temperature, vitals.temperature_c),
        ] {
            match value.filter(|v| v.is_finite()) {
                Some(v) => {
                    family.get_or_create(&labels).set(v);
                }
                None => {
                    family.remove(&labels);
                }
            }
        }
        let mut versions = self.versions.lock().unwrap_or_else(|p| p.into_inner());
        let new = release.map(|r| r.version.clone());
        if versions.get(&labels) == new.as_ref() {
            return;
        }
        if let Some(old) = versions.remove(&labels) {
            self.release.remove(&release_labels(&labels, old));
        }
        if let Some(version) = new {
            self.release
                .get_or_create(&release_labels(&labels, version.clone()))
                .set(1);
            versions.insert(labels, version);
        }
    }

    /// Drops every series of a robot that disconnected.
    pub fn forget(&self, namespace: &str, robot: &str) {
        if !self.enabled {
            return;
        }
        let labels = RobotLabels {
            namespace: namespace.to_owned(),
            robot: robot.to_owned(),
        };
        self.cpu.remove(&labels);
        self.memory.remove(&labels);
        self.temperature.remove(&labels);
        let old = self
            .versions
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .remove(&labels);
        if let Some(old) = old {
            self.release.remove(&release_labels(&labels, old));
        }
    }
}

fn release_labels(robot: &RobotLabels, version: String) -> RobotReleaseLabels {
    RobotReleaseLabels {
        namespace: robot.namespace.clone(),
        robot: robot.robot.clone(),
        version,
    }
}

#[cfg(test)]
mod robot_tests {
    use super::*;

    #[test]
    fn per_robot_series_follow_heartbeats_and_disconnects() {
        let release = |v: &str| Release {
            version: v.into(),
            digest: "sha256:00".into(),
        };
        let vitals = Vitals {
            cpu_percent: Some(12.5),
            temperature_c: Some(51.0),
            ..Vitals::default()
        };
        let off = Metrics::default();
        off.per_robot
            .record("ns", "r2d2", &vitals, Some(&release("1.0.0")));
        assert!(!off.encode().contains("r2d2\""), "disabled by default");

        let m = Metrics::new(true);
        m.per_robot
            .record("ns", "r2d2", &vitals, Some(&release("1.0.0")));
        m.per_robot
            .record("ns", "r2d2", &vitals, Some(&release("2.0.0")));
        let text = m.encode();
        assert!(
            text.contains("lekiwi_robot_cpu_percent{namespace=\"ns\",robot=\"r2d2\"} 12.5"),
            "{text}"
        );
        assert!(
            text.contains("lekiwi_robot_temperature_celsius{namespace=\"ns\",robot=\"r2d2\"} 51.0"),
            "{text}"
        );
        assert!(
            !text.contains("lekiwi_robot_memory_percent{"),
            "no reading, no series: {text}"
        );
        assert!(
            text.contains(
                "lekiwi_robot_release_info{namespace=\"ns\",robot=\"r2d2\",version=\"2.0.0\"} 1"
            ),
            "{text}"
        );
        assert!(
            !text.contains("version=\"1.0.0\""),
            "the old version's series is gone: {text}"
        );
        m.per_robot.forget("ns", "r2d2");
        assert!(!m.encode().contains("r2d2\""), "{}", m.encode());
    }
}
