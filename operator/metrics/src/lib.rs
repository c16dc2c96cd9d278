//! The operator's Prometheus registry (`lekiwi_*`, bounded label sets only). Each subsystem
//! defines and registers its own metrics: [`ControllerMetrics`], [`RolloutMetrics`],
//! [`LeaderMetrics`], [`GatewayMetrics`], [`RuntimeMetrics`] and the opt-in per-robot
//! [`RobotMetrics`].

use std::sync::Arc;

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::registry::Metric;

mod controller;
mod gateway;
mod leader;
mod rollout;
mod runtime;

pub use controller::{
    ControllerLabels, ControllerMetrics, ControllerName, ErrorLabels, PhaseLabels, ReconcileTimer,
};
pub use gateway::{
    AgentUpdateLabels, GatewayMetrics, PriorityLabels, ReasonLabels, ReviewLabels, RobotLabels,
    RobotMetrics, RobotReleaseLabels, WriteLabels,
};
pub use leader::LeaderMetrics;
pub use rollout::{DeploymentLabels, DeploymentPhaseLabels, OutcomeLabels, RolloutMetrics};
pub use runtime::RuntimeMetrics;

/// A bounded label with one value from a fixed set.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct KindLabels {
    /// The kind (frame type, error code, refusal reason, ...).
    pub kind: &'static str,
}

/// One registered metric, as the reference documentation lists it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct MetricInfo {
    /// The name as registered (a counter is exported with `_total` after it).
    pub name: String,
    /// `counter`, `gauge`, `histogram`, ...
    pub kind: String,
    /// The help text.
    pub help: String,
}

/// The operator's registry: prometheus-client's, which encodes only metrics that have series,
/// plus a catalogue of every metric registered, series or not (the book's metrics reference is
/// generated from it). Subsystems register through it with the same call as prometheus-client's.
#[derive(Default)]
pub struct Registry {
    inner: prometheus_client::registry::Registry,
    catalogue: Vec<MetricInfo>,
}

impl Registry {
    /// Registers `metric` as `name` and notes it in the catalogue.
    pub fn register<N: Into<String>, H: Into<String>>(
        &mut self,
        name: N,
        help: H,
        metric: impl Metric,
    ) {
        let (name, help) = (name.into(), help.into());
        self.catalogue.push(MetricInfo {
            name: name.clone(),
            kind: metric.metric_type().as_str().to_owned(),
            help: help.clone(),
        });
        self.inner.register(name, help, metric);
    }
}

/// Registers a subsystem's metrics and hands each back, so that its struct names every metric
/// once, with its exported name and help beside it. Metrics are encoded in registration order.
pub(crate) struct Registrar<'a>(pub(crate) &'a mut Registry);

impl Registrar<'_> {
    /// A new metric of its default shape, registered as `name`.
    pub(crate) fn add<M: Metric + Clone + Default>(&mut self, name: &str, help: &str) -> M {
        self.with(name, help, M::default())
    }

    /// `metric`, registered as `name`.
    pub(crate) fn with<M: Metric + Clone>(&mut self, name: &str, help: &str, metric: M) -> M {
        self.0.register(name, help, metric.clone());
        metric
    }
}

/// All metrics, cheap to clone.
#[derive(Clone)]
pub struct Metrics {
    registry: Arc<prometheus_client::registry::Registry>,
    catalogue: Arc<Vec<MetricInfo>>,
    /// The controllers' reconciles and the fleet as the leader sees it.
    pub controllers: ControllerMetrics,
    /// Leader election.
    pub leader: LeaderMetrics,
    /// The agent gateway.
    pub gateway: GatewayMetrics,
    /// Rollouts of RobotDeployments.
    pub rollouts: RolloutMetrics,
    /// Per-robot vitals and release (empty unless `--per-robot-metrics`).
    pub per_robot: RobotMetrics,
    /// The async runtime's tasks.
    pub runtime: RuntimeMetrics,
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
        let gateway = GatewayMetrics::register(&mut registry);
        let controllers = ControllerMetrics::register(&mut registry);
        let leader = LeaderMetrics::register(&mut registry);
        let rollouts = RolloutMetrics::register(&mut registry);
        let per_robot = RobotMetrics::register(&mut registry, per_robot);
        let runtime = RuntimeMetrics::register(&mut registry);
        Self {
            registry: Arc::new(registry.inner),
            catalogue: Arc::new(registry.catalogue),
            controllers,
            leader,
            gateway,
            rollouts,
            per_robot,
            runtime,
        }
    }

    /// Every metric registered, in registration order, whether or not it has series yet.
    pub fn catalogue(&self) -> &[MetricInfo] {
        &self.catalogue
    }

    /// Renders every metric in the OpenMetrics text format.
    pub fn encode(&self) -> String {
        let mut out = String::new();
        // Writing into a String cannot fail.
        let _ = prometheus_client::encoding::text::encode(&mut out, &self.registry);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_follow_the_lekiwi_convention() {
        let m = Metrics::default();
        drop(m.controllers.reconcile_started(ControllerName::robot));
        m.controllers
            .robots
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

    /// The catalogue holds every metric, also those without series (which the encoding
    /// leaves out), with the type the encoding gives it.
    #[test]
    fn the_catalogue_lists_every_metric_with_its_type() {
        let m = Metrics::new(true);
        let names: Vec<&str> = m.catalogue().iter().map(|i| i.name.as_str()).collect();
        for name in [
            "lekiwi_robots",
            "lekiwi_gateway_refused",
            "lekiwi_robot_cpu_percent",
        ] {
            assert!(names.contains(&name), "{name} missing from {names:?}");
        }
        m.controllers
            .robots
            .get_or_create(&PhaseLabels { phase: "Online" })
            .set(1);
        let text = m.encode();
        for info in m.catalogue() {
            let typed = format!("# TYPE {} {}", info.name, info.kind);
            assert!(
                !text.contains(&format!("# TYPE {} ", info.name)) || text.contains(&typed),
                "{typed}"
            );
        }
        assert!(text.contains("# TYPE lekiwi_robots gauge"), "{text}");
        let mut unique = names.clone();
        unique.sort_unstable();
        unique.dedup();
        assert_eq!(unique.len(), names.len(), "a name registered twice");
    }
}
