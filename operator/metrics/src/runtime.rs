//! Metrics of the process's async runtime, read when `/metrics` is scraped: a task that is
//! spawned and never ends shows here long before it shows in memory.

use prometheus_client::metrics::gauge::Gauge;

use super::{Registrar, Registry};

/// What the runtime exports.
#[derive(Clone)]
pub struct RuntimeMetrics {
    /// Tasks spawned and not yet finished, at the last scrape.
    pub tasks: Gauge,
}

impl RuntimeMetrics {
    pub(crate) fn register(registry: &mut Registry) -> Self {
        let mut r = Registrar(registry);
        Self {
            tasks: r.add(
                "lekiwi_runtime_tasks",
                "Tokio tasks alive in this process (spawned and not yet finished), read at each scrape",
            ),
        }
    }

    /// Reads the runtime the caller runs on; outside a runtime it leaves the gauges as they are.
    pub fn observe(&self) {
        if let Ok(handle) = tokio::runtime::Handle::try_current() {
            let alive = handle.metrics().num_alive_tasks();
            self.tasks.set(i64::try_from(alive).unwrap_or(i64::MAX));
        }
    }
}
