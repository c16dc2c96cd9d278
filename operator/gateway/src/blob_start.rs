//! The release blob store and the Fleet API as the gateway process starts them: the blob
//! routes' state, the releases of the store, the Fleet API's state, and the tasks that care for
//! the store (garbage collection, stale uploads).

use std::sync::Arc;
use std::time::Duration;

use tokio::sync::watch;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use super::blob_api;
use super::lookup::{LookupConfig, Lookups};
use crate::config::Config;
use lekiwi_blob_store::BlobStore;
use lekiwi_core::RobotKey;
use lekiwi_event_store::Store;
use lekiwi_fleet_api::api::FleetApi;
use lekiwi_fleet_api::kube_auth::KubeAuth;
use lekiwi_fleet_api::releases::{self, Releases};
use lekiwi_fleet_api::{FleetState, Heartbeats};
use lekiwi_metrics::Metrics;
use lekiwi_presence::Presence;

/// The live heartbeats the Fleet API answers each Robot with: those of the sessions this
/// gateway's presence holds.
pub(super) struct LiveHeartbeats(pub(super) Presence);

impl Heartbeats for LiveHeartbeats {
    fn last_heartbeats(&self, keys: &[RobotKey]) -> Vec<Option<jiff::Timestamp>> {
        self.0.last_heartbeats(keys)
    }
}

/// The blob routes' state: the store's directories are made now when possible; if not, the
/// gateway still serves agents and uploads answer 500 until they can be made.
async fn blob_api_state(config: &Config, cancel: CancellationToken) -> blob_api::BlobApi {
    let store = BlobStore::new(&config.flags.blob_dir, config.flags.max_blob_bytes)
        .with_read_grace(Duration::from_secs(config.flags.blob_read_grace_seconds));
    match store.ensure_dirs().await {
        Ok(()) => info!(dir = %config.flags.blob_dir.display(), "release blob store ready"),
        Err(e) => warn!(error = %e, "cannot prepare the release blob store"),
    }
    tokio::spawn(remove_stale_uploads(
        store.clone(),
        Duration::from_secs(config.flags.stale_upload_hours.saturating_mul(3600)),
        cancel,
    ));
    blob_api::BlobApi::new(store)
}

/// The blob routes' state, the Fleet API's state (`fleet`'s caches, the releases of the store
/// as its Robots and RobotDeployments use them, the event store, the live heartbeats), and the
/// task that cares for the store.
pub(super) async fn blob_state(
    config: &Config,
    (client, metrics): (&kube::Client, &Metrics),
    (fleet, store, presence): (FleetApi, &Store, Arc<dyn Heartbeats>),
    leader: watch::Receiver<bool>,
    cancel: &CancellationToken,
) -> (blob_api::BlobApi, FleetState, JoinHandle<()>) {
    let reads = Lookups::new(
        LookupConfig::of(config),
        metrics.gateway.auth_lookups.clone(),
    );
    let blobs = blob_api_state(config, cancel.clone())
        .await
        .with_reads(reads);
    let releases = Releases::new(
        blobs.store.clone(),
        (fleet.robots.clone(), fleet.rollouts.clone()),
        config.flags.release_retention,
        metrics.gateway.clone(),
    );
    let care = releases::task::Care {
        period: (config.flags.release_gc_seconds > 0)
            .then(|| Duration::from_secs(config.flags.release_gc_seconds)),
        warn_percent: config.flags.blob_free_warn_percent,
        leader,
        gateway: config.name.clone(),
        namespace: config.namespace.clone(),
    };
    let (releases, task) = releases::task::start(releases, care, client, cancel);
    let kube_auth = KubeAuth::new(
        client.clone(),
        metrics.gateway.clone(),
        config.flags.auth_lookup_qps,
        config.flags.auth_lookup_burst,
    );
    let api = FleetState {
        fleet: Arc::new(fleet),
        kube_auth: Arc::new(kube_auth),
        releases,
        store: store.clone(),
        presence,
        metrics: metrics.gateway.clone(),
    };
    (blobs, api, task)
}

/// Deletes the blob uploads nobody resumed for `max_age`, now and every hour, until `cancel`.
async fn remove_stale_uploads(store: BlobStore, max_age: Duration, cancel: CancellationToken) {
    let mut every = tokio::time::interval(Duration::from_secs(3600));
    loop {
        tokio::select! {
            _ = cancel.cancelled() => return,
            _ = every.tick() => {}
        }
        match store.remove_stale_uploads(max_age).await {
            Ok((0, _)) => {}
            Ok((files, bytes)) => info!(files, bytes, "removed interrupted blob uploads"),
            Err(e) => warn!(error = %e, "cannot remove interrupted blob uploads"),
        }
    }
}
