//! Leader election by a `coordination.k8s.io` Lease: every replica serves, only the leader
//! reconciles. A standby takes over once the Lease has not changed for its whole duration.

use std::time::{Duration, Instant};

use jiff::Timestamp;
use k8s_openapi::api::coordination::v1::{Lease, LeaseSpec};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::MicroTime;
use kube::Api;
use kube::api::{ObjectMeta, PostParams};
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::error::{Error, Result};
use lekiwi_metrics::Metrics;

/// One replica's view of the election.
pub struct LeaderElector {
    api: Api<Lease>,
    name: String,
    identity: String,
    duration: Duration,
    retry: Duration,
    /// The Lease record last seen and when this replica first saw it (local clock), so expiry
    /// does not depend on clocks agreeing between replicas.
    observed: Option<(LeaseSpec, Instant)>,
}

impl LeaderElector {
    /// An elector for the Lease `namespace/name`.
    pub fn new(
        client: kube::Client,
        namespace: &str,
        name: &str,
        identity: String,
        duration: Duration,
        retry: Duration,
    ) -> Self {
        Self {
            api: Api::namespaced(client, namespace),
            name: name.to_owned(),
            identity,
            duration,
            retry,
            observed: None,
        }
    }

    /// Campaigns and renews until cancelled, publishing leadership on `leader`; releases the
    /// Lease on the way out so a standby takes over at once.
    pub async fn run(
        mut self,
        leader: watch::Sender<bool>,
        metrics: Metrics,
        cancel: CancellationToken,
    ) {
        let mut last_renew = Instant::now();
        loop {
            let is_leader = *leader.borrow();
            match self.try_acquire_or_renew().await {
                Ok(true) => {
                    last_renew = Instant::now();
                    if !is_leader {
                        info!(identity = %self.identity, lease = %self.name, "became leader");
                        metrics.leader.acquisitions.inc();
                        metrics.leader.is_leader.set(1);
                        leader.send_replace(true);
                    }
                }
                Ok(false) => {
                    if is_leader {
                        warn!(identity = %self.identity, "lost the leader Lease to another replica");
                    }
                    metrics.leader.is_leader.set(0);
                    leader.send_replace(false);
                }
                Err(e) => {
                    warn!(error = %e, "leader election attempt failed");
                    // Keep leading through short API outages, but never past our own Lease.
                    if is_leader && last_renew.elapsed() >= self.duration.saturating_sub(self.retry)
                    {
                        warn!("cannot renew the leader Lease in time; stepping down");
                        metrics.leader.is_leader.set(0);
                        leader.send_replace(false);
                    }
                }
            }
            tokio::select! {
                () = cancel.cancelled() => break,
                () = tokio::time::sleep(self.retry) => {}
            }
        }
        if *leader.borrow() {
            leader.send_replace(false);
            metrics.leader.is_leader.set(0);
            match self.release().await {
                Ok(()) => info!("released the leader Lease"),
                Err(e) => warn!(error = %e, "could not release the leader Lease"),
            }
        }
    }

    fn lease_error(&self, source: kube::Error) -> Error {
        Error::Lease {
            name: self.name.clone(),
            source,
        }
    }

    /// The Lease as stored now, if it exists.
    async fn read(&self) -> Result<Option<Lease>> {
        self.api
            .get_opt(&self.name)
            .await
            .map_err(|e| self.lease_error(e))
    }

    /// One round: true when this replica holds the Lease afterwards.
    async fn try_acquire_or_renew(&mut self) -> Result<bool> {
        let now = MicroTime(Timestamp::now());
        let Some(mut lease) = self.read().await? else {
            let lease = Lease {
                metadata: ObjectMeta {
                    name: Some(self.name.clone()),
                    ..ObjectMeta::default()
                },
                spec: Some(self.spec_for_me(now, 0)),
            };
            return match self.api.create(&PostParams::default(), &lease).await {
                Ok(_) => Ok(true),
                Err(kube::Error::Api(s)) if s.code == 409 => Ok(false),
                Err(e) => Err(self.lease_error(e)),
            };
        };
        let spec = lease.spec.clone().unwrap_or_default();
        let holder = spec.holder_identity.clone().unwrap_or_default();
        if self.observed.as_ref().map(|(s, _)| s) != Some(&spec) {
            self.observed = Some((spec.clone(), Instant::now()));
        }
        let observed_at = self
            .observed
            .as_ref()
            .map(|(_, t)| *t)
            .unwrap_or_else(Instant::now);
        let held_duration = spec
            .lease_duration_seconds
            .map(|s| Duration::from_secs(s.max(0) as u64))
            .unwrap_or(self.duration);
        let expired = observed_at.elapsed() >= held_duration;
        let new_spec = if holder == self.identity {
            LeaseSpec {
                renew_time: Some(now),
                ..spec
            }
        } else if holder.is_empty() || expired {
            if !holder.is_empty() {
                info!(previous = %holder, "leader Lease expired; taking over");
            }
            self.spec_for_me(now, spec.lease_transitions.unwrap_or(0) + 1)
        } else {
            return Ok(false);
        };
        lease.spec = Some(new_spec);
        // `replace` carries the resourceVersion we read: a concurrent writer makes it fail with
        // 409 instead of both replicas believing they lead.
        match self
            .api
            .replace(&self.name, &PostParams::default(), &lease)
            .await
        {
            Ok(_) => Ok(true),
            Err(kube::Error::Api(s)) if s.code == 409 => Ok(false),
            Err(e) => Err(self.lease_error(e)),
        }
    }

    fn spec_for_me(&self, now: MicroTime, transitions: i32) -> LeaseSpec {
        LeaseSpec {
            holder_identity: Some(self.identity.clone()),
            lease_duration_seconds: Some(self.duration.as_secs() as i32),
            acquire_time: Some(now.clone()),
            renew_time: Some(now),
            lease_transitions: Some(transitions),
            ..LeaseSpec::default()
        }
    }

    async fn release(&self) -> Result<()> {
        let Some(mut lease) = self.read().await? else {
            return Ok(());
        };
        let Some(spec) = lease.spec.as_mut() else {
            return Ok(());
        };
        if spec.holder_identity.as_deref() != Some(self.identity.as_str()) {
            return Ok(());
        }
        spec.holder_identity = None;
        spec.lease_duration_seconds = Some(1);
        spec.renew_time = Some(MicroTime(Timestamp::now()));
        self.api
            .replace(&self.name, &PostParams::default(), &lease)
            .await
            .map_err(|e| self.lease_error(e))?;
        Ok(())
    }
}
