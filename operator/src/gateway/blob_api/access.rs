//! Which blobs a robot may read: the release manifests that Robots of its own namespace name in
//! `spec.release` (as the gateway's Robot watch last saw them), and the files those manifests
//! list. A Kubernetes user RBAC allowed `get releases` reads every blob.
//!
//! A check costs no API request: the namespace's releases come from the Robot watch's cache and
//! a manifest's file list is read from the blob store once, then kept (a manifest never changes:
//! its name is its content's digest). A rollout reaches a robot only through its Robot's
//! `spec.release`, so a RobotDeployment's release is readable exactly for the robots it has
//! started to update.

use std::collections::{BTreeSet, HashMap};
use std::sync::{Arc, Mutex};

use tracing::debug;

use super::Caller;
use crate::gateway::AppState;
use lekiwi_blob_store::BlobStore;

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
    let blobs = &state.blobs;
    let Some(desired) = state.shared.desired.as_ref() else {
        return refuse(state, robot, digest);
    };
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
    if blobs
        .manifests
        .referenced(&blobs.store, &releases, digest)
        .await
    {
        return true;
    }
    refuse(state, robot, digest)
}

/// Counts and logs a refused read; always `false`.
fn refuse(state: &AppState, robot: &lekiwi_core::RobotKey, digest: &str) -> bool {
    state.count_refusal("blob_not_referenced");
    debug!(%robot, %digest, "refused a blob no release of the robot's namespace references");
    false
}
