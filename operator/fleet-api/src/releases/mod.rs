//! The releases of the blob store as the fleet uses them: who references each release (Robots'
//! desired and current releases, the previous release RobotDeployments recorded per robot, the
//! deployments' own release), listing them with that count, deleting one that nothing
//! references, and garbage collection of those beyond the retention ([`task`] runs it).

pub mod task;

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use jiff::Timestamp;
use lekiwi_crds::{Robot, RobotDeployment};
use serde::Serialize;
use tokio::sync::Notify;

use lekiwi_blob_store::gc::{self, Inputs, Plan, Removed};
use lekiwi_blob_store::index::ReleaseRecord;
use lekiwi_blob_store::{BlobStore, Result};
use lekiwi_core::cache::Cache;
use lekiwi_metrics::{GatewayMetrics, KindLabels};

/// How many robots reference a release, by how.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct RobotUses {
    /// Robots whose `spec.release` it is.
    pub desired: u32,
    /// Robots whose `status.currentRelease` it is.
    pub current: u32,
    /// Robots a RobotDeployment would roll back to it (`status.robots[].previousRelease`).
    pub previous: u32,
}

/// How many RobotDeployments reference a release, by how.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct DeploymentUses {
    /// Deployments whose `spec.release` it is.
    pub release: u32,
    /// Deployments that would roll some robot back to it.
    pub rollback_target: u32,
}

/// Who references one release.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Uses {
    /// Robots.
    pub robots: RobotUses,
    /// RobotDeployments.
    pub deployments: DeploymentUses,
}

impl Uses {
    /// Whether anything references the release.
    pub fn any(&self) -> bool {
        *self != Self::default()
    }
}

/// `(namespace, manifest digest)`.
pub type ReleaseKey = (String, String);

/// Who references which release, from the gateway's caches of Robots and RobotDeployments,
/// and the agent builds Robots name or run.
#[derive(Debug, Default)]
pub struct References {
    /// Per release.
    pub uses: BTreeMap<ReleaseKey, Uses>,
    /// Agent build digests in `spec.agent.builds` or `status.agentDigest`.
    pub agent_builds: BTreeSet<String>,
}

impl References {
    /// Reads the caches.
    pub fn of(robots: &Cache<Robot>, rollouts: &Cache<RobotDeployment>) -> Self {
        let mut refs = Self::default();
        for r in robots.page(None, None, usize::MAX, |_| true).0 {
            refs.add_robot(&r);
        }
        for d in rollouts.page(None, None, usize::MAX, |_| true).0 {
            refs.add_deployment(&d);
        }
        refs
    }

    fn bump(&mut self, ns: Option<&String>, digest: &str, f: impl FnOnce(&mut Uses)) {
        if let Some(ns) = ns {
            f(self
                .uses
                .entry((ns.clone(), digest.to_owned()))
                .or_default());
        }
    }

    fn add_robot(&mut self, r: &Robot) {
        let ns = r.metadata.namespace.as_ref();
        if let Some(rel) = &r.spec.release {
            self.bump(ns, &rel.digest, |u| u.robots.desired += 1);
        }
        let status = r.status.as_ref();
        if let Some(rel) = status.and_then(|s| s.current_release.as_ref()) {
            self.bump(ns, &rel.digest, |u| u.robots.current += 1);
        }
        let builds = r.spec.agent.iter().flat_map(|a| &a.builds);
        self.agent_builds
            .extend(builds.map(|b| b.digest.to_string()));
        if let Some(d) = status.and_then(|s| s.agent_digest.as_ref()) {
            self.agent_builds.insert(d.to_string());
        }
    }

    fn add_deployment(&mut self, d: &RobotDeployment) {
        let ns = d.metadata.namespace.as_ref();
        if let Some(rel) = &d.spec.release {
            self.bump(ns, &rel.digest, |u| u.deployments.release += 1);
        }
        let previous: Vec<String> = d
            .status
            .iter()
            .flat_map(|s| &s.robots)
            .filter_map(|r| r.previous_release.as_ref().map(|p| p.digest.to_string()))
            .collect();
        for digest in &previous {
            self.bump(ns, digest, |u| u.robots.previous += 1);
        }
        for digest in previous.iter().collect::<BTreeSet<_>>() {
            self.bump(ns, digest, |u| u.deployments.rollback_target += 1);
        }
    }

    /// Who references release `digest` of `namespace`.
    pub fn of_release(&self, namespace: &str, digest: &str) -> Uses {
        self.uses
            .get(&(namespace.to_owned(), digest.to_owned()))
            .copied()
            .unwrap_or_default()
    }
}

/// One release of a namespace as the list shows it.
#[derive(Clone, Debug, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct ReleaseItem {
    /// The namespace it was pushed to.
    pub namespace: String,
    /// Its version.
    pub version: String,
    /// The manifest's digest.
    pub digest: String,
    /// Bytes of its files (`None` when the manifest cannot be read).
    pub size: Option<u64>,
    /// Its files.
    pub files: Option<usize>,
    /// When it was first pushed to the namespace.
    pub pushed: Timestamp,
    /// Who references it.
    #[serde(flatten)]
    pub uses: Uses,
}

/// The fleet's view of the blob store: what the release routes and garbage collection share.
pub struct Releases {
    /// The store.
    pub store: BlobStore,
    robots: Arc<Cache<Robot>>,
    rollouts: Arc<Cache<RobotDeployment>>,
    /// The newest releases of each namespace kept besides those in use.
    pub retention: usize,
    pub(crate) metrics: GatewayMetrics,
    /// Wakes the collector (after a push).
    pub pushed: Notify,
    /// Serializes collections and deletions in this process.
    busy: tokio::sync::Mutex<()>,
}

impl Releases {
    /// Releases of `store`, referenced by the Robots and RobotDeployments of the caches.
    pub fn new(
        store: BlobStore,
        (robots, rollouts): (Arc<Cache<Robot>>, Arc<Cache<RobotDeployment>>),
        retention: usize,
        metrics: GatewayMetrics,
    ) -> Self {
        Self {
            store,
            robots,
            rollouts,
            retention,
            metrics,
            pushed: Notify::new(),
            busy: tokio::sync::Mutex::new(()),
        }
    }

    /// Whether the caches hold their first list (before, nothing is known to be unused).
    pub fn ready(&self) -> bool {
        self.robots.is_ready() && self.rollouts.is_ready()
    }

    /// Who references what now.
    pub fn references(&self) -> References {
        References::of(&self.robots, &self.rollouts)
    }

    /// The releases of `namespace`, newest push first, with their size and users.
    pub async fn list(&self, namespace: &str) -> Result<Vec<ReleaseItem>> {
        let refs = self.references();
        let mut items = Vec::new();
        for r in self
            .store
            .index()
            .list(Some(namespace))
            .await?
            .into_iter()
            .rev()
        {
            let manifest = self.store.manifest(&r.digest).await.ok();
            items.push(ReleaseItem {
                uses: refs.of_release(&r.namespace, &r.digest),
                size: manifest.as_ref().map(|m| m.total_bytes()),
                files: manifest.as_ref().map(|m| m.files.len()),
                namespace: r.namespace,
                version: r.version,
                digest: r.digest,
                pushed: r.pushed,
            });
        }
        Ok(items)
    }

    /// The file lists of the manifests recorded or referenced (one that cannot be read is
    /// left out), and the blobs that stay whatever happens: referenced manifests, their files
    /// and agent builds in use.
    async fn inputs(
        &self,
        records: &[ReleaseRecord],
        refs: &References,
    ) -> (BTreeMap<String, BTreeSet<String>>, BTreeSet<String>) {
        let referenced: BTreeSet<&str> = refs.uses.keys().map(|(_, d)| d.as_str()).collect();
        let manifests: BTreeSet<&str> = records
            .iter()
            .map(|r| r.digest.as_str())
            .chain(referenced.iter().copied())
            .collect();
        let mut files = BTreeMap::new();
        for m in manifests {
            if let Ok(manifest) = self.store.manifest(m).await {
                let listed = manifest.files.into_iter().map(|f| f.digest).collect();
                files.insert(m.to_owned(), listed);
            }
        }
        let mut pinned = refs.agent_builds.clone();
        for m in referenced {
            pinned.insert(m.to_owned());
            pinned.extend(files.get(m).into_iter().flatten().cloned());
        }
        (files, pinned)
    }

    /// Plans against the current records and references; `stays` says which records must stay
    /// besides the referenced ones.
    async fn plan(
        &self,
        records: &[ReleaseRecord],
        refs: &References,
        stays: impl Fn(&ReleaseRecord) -> bool,
    ) -> Plan {
        let (files, pinned) = self.inputs(records, refs).await;
        let inputs = Inputs {
            records,
            pinned: &pinned,
            files: &files,
        };
        let readers = self.store.readers();
        gc::plan(
            &inputs,
            |r| stays(r) || refs.of_release(&r.namespace, &r.digest).any(),
            |b| readers.busy(b),
        )
    }

    /// One garbage collection: removes every release no Robot or RobotDeployment references
    /// that is not among the newest [`Self::retention`] of its namespace, with the blobs only
    /// such releases list. Nothing happens before the caches hold their first list.
    pub async fn collect(&self) -> Result<(Removed, Plan)> {
        let _one = self.busy.lock().await;
        if !self.ready() {
            return Ok((Removed::default(), Plan::default()));
        }
        let records = self.store.index().list(None).await?;
        let refs = self.references();
        let newest = gc::newest(&records, self.retention);
        let plan = self
            .plan(&records, &refs, |r| {
                newest.contains(&(r.namespace.clone(), r.digest.clone()))
            })
            .await;
        let removed = self.store.remove(&plan).await?;
        self.count(removed, "gc");
        Ok((removed, plan))
    }

    /// Deletes the release of `namespace` that `reference` names (its digest, or a version
    /// only one release there has), with the blobs no other release lists.
    pub async fn delete(&self, namespace: &str, reference: &str) -> Result<Deleted, Refused> {
        let _one = self.busy.lock().await;
        if !self.ready() {
            return Err(Refused::NotReady);
        }
        let records = self
            .store
            .index()
            .list(None)
            .await
            .map_err(Refused::Store)?;
        let matching: Vec<&ReleaseRecord> = records
            .iter()
            .filter(|r| {
                r.namespace == namespace && (r.digest == reference || r.version == reference)
            })
            .collect();
        let target = match matching.as_slice() {
            [] => return Err(Refused::NotFound),
            [one] => (*one).clone(),
            many => {
                return Err(Refused::Ambiguous(
                    many.iter().map(|r| r.digest.clone()).collect(),
                ));
            }
        };
        let refs = self.references();
        let uses = refs.of_release(namespace, &target.digest);
        if uses.any() {
            return Err(Refused::InUse(Box::new((target, uses))));
        }
        let plan = self.plan(&records, &refs, |r| *r != target).await;
        if !plan.deferred.is_empty() {
            return Err(Refused::Downloading);
        }
        let removed = self.store.remove(&plan).await.map_err(Refused::Store)?;
        self.count(removed, "delete");
        Ok(Deleted {
            release: target,
            blobs: removed.blobs,
            bytes: removed.bytes,
        })
    }

    fn count(&self, removed: Removed, kind: &'static str) {
        self.metrics
            .releases_removed
            .get_or_create(&KindLabels { kind })
            .inc_by(removed.releases as u64);
        self.metrics.blob_bytes_removed.inc_by(removed.bytes);
    }
}

/// What a deletion removed.
#[derive(Clone, Debug, Serialize)]
pub struct Deleted {
    /// The release.
    #[serde(flatten)]
    pub release: ReleaseRecord,
    /// Blobs deleted with it (shared ones stay).
    pub blobs: usize,
    /// Their bytes.
    pub bytes: u64,
}

/// Why a release was not deleted.
#[derive(Debug)]
pub enum Refused {
    /// The namespace has no such release.
    NotFound,
    /// The version names several releases (their digests).
    Ambiguous(Vec<String>),
    /// Robots or deployments reference it.
    InUse(Box<(ReleaseRecord, Uses)>),
    /// A download reads one of its blobs now.
    Downloading,
    /// The gateway has not read the fleet yet.
    NotReady,
    /// The store failed.
    Store(lekiwi_blob_store::Error),
}

impl Refused {
    /// The message for the user.
    pub fn message(&self, namespace: &str, reference: &str) -> String {
        match self {
            Refused::NotFound => format!(
                "no release {reference} in namespace {namespace}: see kubectl lekiwi release list -n {namespace}"
            ),
            Refused::Ambiguous(digests) => format!(
                "version {reference} names {} releases in namespace {namespace} ({}): delete one by its digest",
                digests.len(),
                digests.join(", ")
            ),
            Refused::InUse(found) => {
                let (r, u) = found.as_ref();
                format!(
                    "release {} ({}) is in use: robots: {} desired, {} current, {} previous; deployments: {} release, {} rollback target. Move them to another release first",
                    r.version,
                    r.digest,
                    u.robots.desired,
                    u.robots.current,
                    u.robots.previous,
                    u.deployments.release,
                    u.deployments.rollback_target
                )
            }
            Refused::Downloading => {
                "a robot is downloading this release now; retry in a few minutes".into()
            }
            Refused::NotReady => "the gateway is still reading the fleet; retry in a moment".into(),
            Refused::Store(e) => e.to_string(),
        }
    }
}
