//! Metrics of leader election: whether this replica leads, and how often it became leader.

use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::gauge::Gauge;

use super::Registry;

/// What leader election exports.
#[derive(Clone)]
pub struct LeaderMetrics {
    /// 1 while this replica holds the leader Lease.
    pub is_leader: Gauge,
    /// Times this replica became leader.
    pub acquisitions: Counter,
}

impl LeaderMetrics {
    pub(crate) fn register(registry: &mut Registry) -> Self {
        let m = Self {
            is_leader: Gauge::default(),
            acquisitions: Counter::default(),
        };
        registry.register(
            "lekiwi_leader_election_is_leader",
            "1 while this replica holds the leader Lease, else 0",
            m.is_leader.clone(),
        );
        registry.register(
            "lekiwi_leader_election_acquisitions",
            "Times this replica became leader",
            m.acquisitions.clone(),
        );
        m
    }
}
