//! Controllers and the state they share.

pub mod deployment;
pub mod metrics;
pub mod robot;

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use k8s_openapi::api::coordination::v1::Lease;
use kube::runtime::events::Recorder;
use kube::runtime::reflector::Store;

use crate::config::Config;
use crate::metrics::Metrics;

/// What every reconcile gets.
#[derive(Clone)]
pub struct Context {
    /// The Kubernetes client.
    pub client: kube::Client,
    /// The one Event recorder of this process.
    pub recorder: Recorder,
    /// Metrics.
    pub metrics: Metrics,
    /// Operator configuration.
    pub config: Arc<Config>,
    /// Leases of the gateways, once the Robot controller has started watching them.
    pub gateway_leases: Option<Store<Lease>>,
    /// Consecutive failures per object, for exponential backoff.
    failures: Arc<Mutex<HashMap<(String, String), u32>>>,
}

impl Context {
    /// A context with no failures recorded.
    pub fn new(
        client: kube::Client,
        recorder: Recorder,
        metrics: Metrics,
        config: Arc<Config>,
    ) -> Self {
        Self {
            client,
            recorder,
            metrics,
            config,
            gateway_leases: None,
            failures: Arc::default(),
        }
    }

    /// Delay before retrying an object that just failed: 1 s, doubling, at most 5 minutes.
    pub fn next_backoff(&self, name: &str, namespace: &str) -> Duration {
        let mut failures = self.failures.lock().unwrap_or_else(|p| p.into_inner());
        let n = failures
            .entry((namespace.to_owned(), name.to_owned()))
            .or_insert(0);
        *n = n.saturating_add(1);
        Duration::from_secs(1u64 << (*n - 1).min(8)).min(Duration::from_secs(300))
    }

    /// Forgets an object's failures after a successful reconcile.
    pub fn reset_backoff(&self, name: &str, namespace: &str) {
        let mut failures = self.failures.lock().unwrap_or_else(|p| p.into_inner());
        failures.remove(&(namespace.to_owned(), name.to_owned()));
    }
}
