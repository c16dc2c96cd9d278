//! Metrics of the controllers (`lekiwi_controller_*`) and of the fleet as the leader sees it
//! (`lekiwi_robots*`).

use std::time::Instant;

use prometheus_client::encoding::{EncodeLabelSet, EncodeLabelValue};
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};

use super::Registry;

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
    /// Which controller the series is of (`robot` or `deployment`).
    pub controller: ControllerName,
}

/// Labels of per-controller error series.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct ErrorLabels {
    /// Which controller failed (`robot` or `deployment`).
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

/// What the controllers export.
#[derive(Clone)]
pub struct ControllerMetrics {
    /// Reconciles started, whether they succeed or fail.
    pub reconciliations: Family<ControllerLabels, Counter>,
    /// Reconciles that failed.
    pub reconcile_errors: Family<ErrorLabels, Counter>,
    /// Seconds from the start to the end of a reconcile, including its API writes.
    pub reconcile_duration: Family<ControllerLabels, Histogram>,
    /// Robots by phase, as the leader last saw them.
    pub robots: Family<PhaseLabels, Gauge>,
    /// Robots whose agent reports teleoperation, as the leader last saw them.
    pub robots_teleoperating: Gauge,
    /// Robot phase transitions, by the phase entered.
    pub robot_transitions: Family<PhaseLabels, Counter>,
}

impl ControllerMetrics {
    pub(crate) fn register(registry: &mut Registry) -> Self {
        let m = Self {
            reconciliations: Family::default(),
            reconcile_errors: Family::default(),
            reconcile_duration: Family::new_with_constructor(|| {
                Histogram::new(exponential_buckets(0.001, 2.0, 14))
            }),
            robots: Family::default(),
            robots_teleoperating: Gauge::default(),
            robot_transitions: Family::default(),
        };
        registry.register(
            "lekiwi_controller_reconciliations",
            "Reconciles started, by controller",
            m.reconciliations.clone(),
        );
        registry.register(
            "lekiwi_controller_reconcile_errors",
            "Reconciles that failed, by controller and error category",
            m.reconcile_errors.clone(),
        );
        registry.register(
            "lekiwi_controller_reconcile_duration_seconds",
            "Time one reconcile took, by controller",
            m.reconcile_duration.clone(),
        );
        registry.register(
            "lekiwi_robots",
            "Robots by phase, as the leader sees them",
            m.robots.clone(),
        );
        registry.register(
            "lekiwi_robots_teleoperating",
            "Robots whose agent reports teleoperation active, as the leader sees them (no \
             per-robot label)",
            m.robots_teleoperating.clone(),
        );
        registry.register(
            "lekiwi_robot_phase_transitions",
            "Robot phase transitions, by the phase entered",
            m.robot_transitions.clone(),
        );
        m
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
