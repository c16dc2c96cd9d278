//! The gateway's periodic care of the blob store: every period (and after each push) it
//! collects garbage when this replica may, measures the store (gauges) and warns by a Warning
//! Event, once per crossing, when the volume's free space falls under the threshold.
//!
//! Replicas share the store's volume (ReadWriteMany), each knowing only its own downloads: only
//! the replica holding the leader Lease collects, so that one process decides and the others
//! never race it. A process without leader election (`--role gateway`) collects on its own.

use std::sync::Arc;
use std::time::Duration;

use k8s_openapi::api::coordination::v1::Lease;
use kube::Api;
use kube::runtime::events::{Event, EventType, Recorder, Reporter};
use tokio::sync::watch;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use super::Releases;
use lekiwi_metrics::GatewayMetrics;

/// Reason of the Warning Event about the volume.
pub const NEARLY_FULL: &str = "BlobStoreNearlyFull";

/// How the care runs.
pub struct Care {
    /// Between two rounds; `None`: no collection (the store is still measured every 5 min).
    pub period: Option<Duration>,
    /// Free space in percent of the volume under which to warn.
    pub warn_percent: u8,
    /// Whether this replica may collect now (the leader Lease).
    pub leader: watch::Receiver<bool>,
    /// The gateway's name: its Lease (in `namespace`) carries the Warning Event.
    pub gateway: String,
    /// The operator's namespace.
    pub namespace: String,
}

/// Starts the care of `releases` as `care` says; the releases (shared with the routes) and the
/// task.
pub fn start(
    releases: Releases,
    care: Care,
    client: &kube::Client,
    cancel: &CancellationToken,
) -> (Arc<Releases>, JoinHandle<()>) {
    let releases = Arc::new(releases);
    let metrics = releases.metrics.clone();
    let task = tokio::spawn(run(
        releases.clone(),
        care,
        client.clone(),
        metrics,
        cancel.clone(),
    ));
    (releases, task)
}

/// Runs the care until `cancel`.
pub async fn run(
    releases: Arc<Releases>,
    care: Care,
    client: kube::Client,
    metrics: GatewayMetrics,
    cancel: CancellationToken,
) {
    let every = care.period.unwrap_or(Duration::from_secs(300));
    let mut tick = tokio::time::interval(every);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut low = false;
    loop {
        tokio::select! {
            () = cancel.cancelled() => return,
            _ = tick.tick() => {}
            () = releases.pushed.notified() => {}
        }
        if care.period.is_some() && *care.leader.borrow() {
            collect(&releases).await;
        }
        let now_low = measure(&releases, &metrics, care.warn_percent).await;
        low = match now_low {
            // Warned once per crossing; an Event that could not be published is tried again.
            Some(note) if !low => warn_event(&client, &care, note).await,
            now_low => low && now_low.is_some(),
        };
    }
}

async fn collect(releases: &Releases) {
    match releases.collect().await {
        Ok((removed, plan)) => {
            if removed.releases > 0 || !plan.deferred.is_empty() {
                info!(
                    releases = removed.releases,
                    blobs = removed.blobs,
                    bytes = removed.bytes,
                    deferred = plan.deferred.len(),
                    "release garbage collection"
                );
            }
        }
        Err(e) => warn!(error = %e, "release garbage collection failed"),
    }
}

/// Sets the gauges; returns the warning note when the volume's free space is under
/// `warn_percent` of its size.
async fn measure(
    releases: &Releases,
    metrics: &GatewayMetrics,
    warn_percent: u8,
) -> Option<String> {
    let usage = match releases.store.usage().await {
        Ok(u) => u,
        Err(e) => {
            warn!(error = %e, "cannot measure the release blob store");
            return None;
        }
    };
    let gauge = |v: u64| i64::try_from(v).unwrap_or(i64::MAX);
    metrics.blob_store_bytes.set(gauge(usage.bytes));
    metrics.blob_store_blobs.set(gauge(usage.blobs));
    if let Ok(records) = releases.store.index().list(None).await {
        metrics.blob_store_releases.set(gauge(records.len() as u64));
    }
    let (free, size) = (usage.free?, usage.size?);
    metrics.blob_volume_free_bytes.set(gauge(free));
    metrics.blob_volume_size_bytes.set(gauge(size));
    low_space(free, size, warn_percent)
}

/// The warning when `free` is under `percent` of `size`.
fn low_space(free: u64, size: u64, percent: u8) -> Option<String> {
    (size > 0 && (free as u128) * 100 < (size as u128) * u128::from(percent)).then(|| {
        format!(
            "the release blob store's volume has {} MiB free of {} MiB (under {percent}%): delete releases (kubectl lekiwi release list, release delete), lower --release-retention or grow the volume",
            free >> 20,
            size >> 20
        )
    })
}

/// Publishes the Warning Event on the gateway's Lease; whether it went out.
async fn warn_event(client: &kube::Client, care: &Care, note: String) -> bool {
    warn!(%note, "blob store volume nearly full");
    let lease = match Api::<Lease>::namespaced(client.clone(), &care.namespace)
        .get(&care.gateway)
        .await
    {
        Ok(l) => l,
        Err(e) => {
            warn!(error = %e, "cannot read the gateway's Lease for the volume warning");
            return false;
        }
    };
    let recorder = Recorder::new(
        client.clone(),
        Reporter {
            controller: "lekiwi-gateway".into(),
            instance: Some(care.gateway.clone()),
        },
    );
    let event = Event {
        type_: EventType::Warning,
        reason: NEARLY_FULL.into(),
        note: Some(note),
        action: "MeasureBlobStore".into(),
        secondary: None,
    };
    use kube::Resource as _;
    match recorder.publish(&event, &lease.object_ref(&())).await {
        Ok(()) => true,
        Err(e) => {
            warn!(error = %e, "cannot publish the volume warning");
            false
        }
    }
}

#[cfg(test)]
mod tests {
    use super::low_space;

    #[test]
    fn warns_under_the_threshold_only() {
        assert!(low_space(5, 100, 10).is_some());
        assert!(low_space(10, 100, 10).is_none());
        assert!(low_space(0, 0, 10).is_none());
        assert!(low_space(1 << 30, 20 << 30, 10).is_some());
    }
}
