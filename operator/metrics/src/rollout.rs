//! Metrics of the RobotDeployment controller: rollout phases, progress, outcomes and durations,
//! one series set per RobotDeployment.

use jiff::Timestamp;
use kube::ResourceExt;
use lekiwi_crds::RobotDeployment;
use lekiwi_crds::deployment::RobotDeploymentStatus;
use lekiwi_crds::deployment::RolloutPhase;
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};

use super::Registry;

/// Labels of per-deployment series (bounded by the number of RobotDeployments, which people
/// create by hand).
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct DeploymentLabels {
    /// The deployment's namespace.
    pub namespace: String,
    /// The deployment's name (unique within the namespace).
    pub deployment: String,
}

/// Labels of rollout outcome series.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct OutcomeLabels {
    /// `completed`, `rolled_back`, `aborted` or `failed` (rollouts); `succeeded` or `failed` (batches).
    pub outcome: &'static str,
}

/// Labels of per-deployment phase series.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct DeploymentPhaseLabels {
    /// Namespace.
    pub namespace: String,
    /// RobotDeployment name.
    pub deployment: String,
    /// One of the seven rollout phases; the series of the current one is 1, the others 0.
    pub phase: &'static str,
}

/// What the RobotDeployment controller exports.
#[derive(Clone)]
pub struct RolloutMetrics {
    /// 1 for the phase each deployment is in, 0 for the others.
    pub phase: Family<DeploymentPhaseLabels, Gauge>,
    /// Robots a deployment targets (selected, not in maintenance).
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
    pub(crate) fn register(registry: &mut Registry) -> Self {
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

impl RolloutMetrics {
    /// Records what one plan of `deployment` says: gauges from the `status` it writes always;
    /// a batch's success ratio only in the plan that judged the batch (`batch_result`), the
    /// rollout's outcome only in the plan that ended it (`finished`).
    pub fn record(
        &self,
        deployment: &RobotDeployment,
        status: &RobotDeploymentStatus,
        (batch_result, finished): (Option<f64>, bool),
        now: Timestamp,
    ) {
        let (namespace, name) = (
            deployment.namespace().unwrap_or_default(),
            deployment.name_any(),
        );
        let labels = DeploymentLabels {
            namespace: namespace.clone(),
            deployment: name.clone(),
        };
        self.targeted
            .get_or_create(&labels)
            .set(i64::from(status.targeted));
        self.updated
            .get_or_create(&labels)
            .set(i64::from(status.updated));
        self.failed
            .get_or_create(&labels)
            .set(i64::from(status.failed));
        self.current_batch
            .get_or_create(&labels)
            .set(i64::from(status.current_batch.unwrap_or(0)));
        for phase in PHASES {
            self.phase
                .get_or_create(&DeploymentPhaseLabels {
                    namespace: namespace.clone(),
                    deployment: name.clone(),
                    phase: phase_str(phase),
                })
                .set(i64::from(status.phase == Some(phase)));
        }
        if let Some(ratio) = batch_result {
            self.batch_success.observe(ratio);
            let outcome = if ratio >= deployment.spec.strategy.success_threshold {
                "succeeded"
            } else {
                "failed"
            };
            self.batches.get_or_create(&OutcomeLabels { outcome }).inc();
        }
        if finished {
            let outcome = match status.phase {
                Some(RolloutPhase::Completed) => "completed",
                Some(RolloutPhase::RolledBack) => "rolled_back",
                Some(RolloutPhase::Aborted) => "aborted",
                _ => "failed",
            };
            let labels = OutcomeLabels { outcome };
            self.finished.get_or_create(&labels).inc();
            if let Some(start) = &status.start_time {
                let secs = now.duration_since(start.0).as_secs_f64().max(0.0);
                self.duration.get_or_create(&labels).observe(secs);
            }
        }
    }
}

/// Every phase, so the gauge of the phases a deployment left drops to 0.
const PHASES: [RolloutPhase; 8] = [
    RolloutPhase::Pending,
    RolloutPhase::Progressing,
    RolloutPhase::Paused,
    RolloutPhase::Completed,
    RolloutPhase::RollingBack,
    RolloutPhase::RolledBack,
    RolloutPhase::Failed,
    RolloutPhase::Aborted,
];

fn phase_str(p: RolloutPhase) -> &'static str {
    match p {
        RolloutPhase::Pending => "Pending",
        RolloutPhase::Progressing => "Progressing",
        RolloutPhase::Paused => "Paused",
        RolloutPhase::Completed => "Completed",
        RolloutPhase::RollingBack => "RollingBack",
        RolloutPhase::RolledBack => "RolledBack",
        RolloutPhase::Failed => "Failed",
        RolloutPhase::Aborted => "Aborted",
    }
}
