//! Which blobs a robot may read: the release manifests that Robots of its own namespace name in
//! `spec.release` (as the gateway's Robot watch last saw them), and the files those manifests
//! list. A Kubernetes user RBAC allowed `get releases` reads every blob.
//!
//! A check costs no API request: the namespace's releases come from the Robot watch's cache and
//! a manifest's file list is read from the blob store once, then kept (a manifest never changes:
//! its name is its content's digest). A rollout reaches a robot only through its Robot's
//! `spec.release`, so a RobotDeployment's release is readable exactly for the robots it has
//! started to update. A read refused at first waits up to 3 s for the cache to show a release
//! another gateway replica has already told the robot of; if it still does not, the robot's own
//! Robot is read from the API server once, within a small budget of such reads (a miss is
//! remembered for a few seconds), so a replica whose watch runs late under load does not fail
//! a robot's update.

use std::collections::{BTreeSet, HashMap};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::sync::broadcast::error::RecvError;
use tracing::debug;

use kube::Api;

use super::Caller;
use crate::AppState;
use crate::lookup::Subject;
use lekiwi_blob_store::BlobStore;
use lekiwi_core::cache::Cache;
use lekiwi_crds::Robot;
use lekiwi_presence::watched::WatchedRobots;

/// How long a robot's read of a blob no release references yet waits for this gateway's Robot
/// cache to catch up with another replica's (bounded: a refusal costs at most this).
const CATCH_UP: Duration = Duration::from_secs(3);

/// Manifests whose file lists are kept; past this many the cache starts over.
const MAX_CACHED_MANIFESTS: usize = 1024;

/// The file digests of the release manifests checked so far, by manifest digest.
#[derive(Default)]
pub(super) struct ManifestFiles {
    cache: Mutex<HashMap<String, Arc<BTreeSet<String>>>>,
}

impl ManifestFiles {
    /// The digests `manifest` lists; `None` when it is not stored or not a manifest (not
    /// remembered: it may be pushed later).
    async fn files(&self, store: &BlobStore, manifest: &str) -> Option<Arc<BTreeSet<String>>> {
        if let Some(files) = self.lock().get(manifest) {
            return Some(files.clone());
        }
        let parsed = match store.manifest(manifest).await {
            Ok(m) => m,
            Err(e) => {
                debug!(%manifest, error = %e, "a robot's release manifest cannot be read");
                return None;
            }
        };
        let files: Arc<BTreeSet<String>> =
            Arc::new(parsed.files.into_iter().map(|f| f.digest).collect());
        let mut cache = self.lock();
        if cache.len() >= MAX_CACHED_MANIFESTS {
            cache.clear();
        }
        cache.insert(manifest.to_owned(), files.clone());
        Some(files)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<String, Arc<BTreeSet<String>>>> {
        self.cache.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Whether `digest` is one of `releases` (manifest digests) or a file one of them lists.
    pub(super) async fn referenced(
        &self,
        store: &BlobStore,
        releases: &BTreeSet<String>,
        digest: &str,
    ) -> bool {
        if releases.contains(digest) {
            return true;
        }
        for manifest in releases {
            if let Some(files) = self.files(store, manifest).await
                && files.contains(digest)
            {
                return true;
            }
        }
        false
    }
}

/// Whether `caller` may read `digest`: an allowed Kubernetes user always, a robot when a release
/// of its namespace references the blob. A refusal is counted as
/// `lekiwi_gateway_refused_total{kind="blob_not_referenced"}`; the caller answers it as an
/// unknown digest (404), so a robot learns nothing of other namespaces' blobs.
pub(super) async fn may_read(state: &AppState, caller: &Caller, digest: &str) -> bool {
    let Caller::Robot(robot) = caller else {
        return true;
    };
    let Some(desired) = state.shared.desired.as_ref() else {
        return refuse(state, robot, digest);
    };
    if referenced(state, desired, robot, digest).await {
        return true;
    }
    // Behind one Service, the gateway holding the robot's session may have seen the new
    // release first and told the robot, whose download reached this replica before this
    // replica's watch brought the change: follow the cache's changes for a moment.
    if caught_up(&desired.0, CATCH_UP, || {
        referenced(state, desired, robot, digest)
    })
    .await
    {
        return true;
    }
    if read_live(state, robot, digest).await {
        return true;
    }
    refuse(state, robot, digest)
}

/// Whether `robot`'s Robot, read from the API server now, references `digest` in its
/// `spec.release` (the manifest or a file it lists) or `spec.agent`. Within the budget of
/// [`Lookups`](crate::lookup::Lookups): a read that does not find the blob is
/// remembered (for this robot and blob), and a failed, throttled or remembered one answers
/// `false`.
async fn read_live(state: &AppState, robot: &lekiwi_core::RobotKey, digest: &str) -> bool {
    let subject = Subject::Spec(&robot.namespace, &robot.name, digest);
    if state.blobs.reads.admit(subject).is_err() {
        return false;
    }
    let api: Api<Robot> = Api::namespaced(state.client.clone(), &robot.namespace);
    let found = match api.get_opt(&robot.name).await {
        Ok(Some(r)) => r,
        Ok(None) => {
            state.blobs.reads.missed(subject);
            return false;
        }
        Err(e) => {
            debug!(%robot, error = %e, "cannot read a robot to check its blob read");
            return false;
        }
    };
    let blobs = &state.blobs;
    let release: BTreeSet<String> = found
        .spec
        .release
        .iter()
        .map(|r| r.digest.to_string())
        .collect();
    let agent = found
        .spec
        .agent
        .iter()
        .flat_map(|a| a.builds.iter())
        .any(|b| b.digest == digest);
    let allowed = agent
        || blobs
            .manifests
            .referenced(&blobs.store, &release, digest)
            .await;
    if !allowed {
        state.blobs.reads.missed(subject);
    }
    allowed
}

/// Runs `check` again at every change of `cache` until it passes (`true`) or `wait` is over
/// (`false`); also once right after subscribing, for a change that came in just before.
pub(super) async fn caught_up<F, Fut>(cache: &Cache<Robot>, wait: Duration, mut check: F) -> bool
where
    F: FnMut() -> Fut,
    Fut: Future<Output = bool>,
{
    let mut changes = cache.subscribe();
    let deadline = tokio::time::Instant::now() + wait;
    loop {
        if check().await {
            return true;
        }
        match tokio::time::timeout_at(deadline, changes.recv()).await {
            Ok(Ok(_) | Err(RecvError::Lagged(_))) => {}
            Ok(Err(RecvError::Closed)) | Err(_) => return false,
        }
    }
}

/// Whether a release of `robot`'s namespace references `digest` now.
async fn referenced(
    state: &AppState,
    desired: &WatchedRobots,
    robot: &lekiwi_core::RobotKey,
    digest: &str,
) -> bool {
    let blobs = &state.blobs;
    // The robot's own release first: one cache lookup, the case of every normal download. Only
    // a miss scans the namespace's Robots.
    let own: BTreeSet<String> = desired.get(robot).map(|r| r.digest).into_iter().collect();
    if blobs.manifests.referenced(&blobs.store, &own, digest).await {
        return true;
    }
    // An agent build that a Robot of the namespace names in `spec.agent`.
    if desired.agent_digests_in(&robot.namespace).contains(digest) {
        return true;
    }
    let releases = desired.digests_in(&robot.namespace);
    blobs
        .manifests
        .referenced(&blobs.store, &releases, digest)
        .await
}

/// Counts and logs a refused read; always `false`.
fn refuse(state: &AppState, robot: &lekiwi_core::RobotKey, digest: &str) -> bool {
    state.count_refusal("blob_not_referenced");
    debug!(%robot, %digest, "refused a blob no release of the robot's namespace references");
    false
}
