//! Read-your-own-writes for the rollout planner: the marks, spec parts and statuses this
//! controller wrote, laid over shared stores that do not show them yet.
//!
//! The stores follow the API server through watches, which fall behind when the API server is
//! loaded (after its restart at 10,000 robots, by more than a minute). A plan made from a store
//! that lacks the marks of the batch it just started sees that batch empty and starts it again:
//! every member is written again with a new start time, its timeout starts over, and the writes
//! load the API server further. [`super::catch_up`] waits a few seconds for the stores; past
//! that the planner plans on, from the stores with these writes laid over them.
//!
//! A write is laid over an object whose stored resourceVersion is older than the write's, and
//! forgotten once the store shows that version or a later one (resourceVersions compare as
//! numbers, as an etcd-backed API server issues them; one that does not parse is never laid
//! over), or after [`KEEP`].

use std::borrow::Cow;
use std::collections::HashMap;
use std::sync::{Mutex, MutexGuard};
use std::time::Duration;

use kube::ResourceExt;
use lekiwi_crds::{Robot, RobotDeployment, RobotDeploymentStatus};
use tokio::time::Instant;

use super::apply::Written;
use lekiwi_core::apply::RobotSpecPart;

/// Longest a write is laid over a store that does not show it.
pub const KEEP: Duration = Duration::from_secs(600);

/// A robot (namespace, name) and the mark annotation of one rollout kind.
type RobotKey = (String, String, &'static str);
/// A deployment (namespace, name).
type DeploymentKey = (String, String);

/// One robot write: its resourceVersion, the mark text and the spec part it set.
struct RobotWrite {
    version: u64,
    mark: String,
    spec: Option<RobotSpecPart>,
    at: Instant,
}

/// The writes of this controller that the stores may not show yet.
#[derive(Default)]
pub struct OwnWrites {
    robots: Mutex<HashMap<RobotKey, RobotWrite>>,
    statuses: Mutex<HashMap<DeploymentKey, (u64, RobotDeploymentStatus, Instant)>>,
}

impl OwnWrites {
    /// Remembers the robots a reconcile wrote in `namespace`; forgets writes older than [`KEEP`].
    pub fn wrote_robots(&self, namespace: &str, written: &[Written]) {
        let now = Instant::now();
        let mut robots = lock(&self.robots);
        robots.retain(|_, w| now.duration_since(w.at) < KEEP);
        for w in written {
            let Some(version) = version(w.resource_version.as_deref()) else {
                continue;
            };
            robots.insert(
                (namespace.to_owned(), w.robot.clone(), w.key),
                RobotWrite {
                    version,
                    mark: w.mark.clone(),
                    spec: w.spec.clone(),
                    at: now,
                },
            );
        }
    }

    /// Remembers the status a reconcile wrote to a deployment, at `written_version`.
    pub fn wrote_status(
        &self,
        deployment: &RobotDeployment,
        written_version: Option<&str>,
        status: &RobotDeploymentStatus,
    ) {
        let Some(version) = version(written_version) else {
            return;
        };
        let now = Instant::now();
        let mut statuses = lock(&self.statuses);
        statuses.retain(|_, (_, _, at)| now.duration_since(*at) < KEEP);
        statuses.insert(key_of(deployment), (version, status.clone(), now));
    }

    /// `robot` as the store holds it, or with the mark (annotation `key`) and spec part this
    /// controller wrote when the store is older than that write.
    pub fn robot<'a>(&self, robot: &'a Robot, key: &'static str) -> Cow<'a, Robot> {
        let mut robots = lock(&self.robots);
        // Every robot of every plan passes here; with nothing remembered (the steady state),
        // no key is built.
        if robots.is_empty() {
            return Cow::Borrowed(robot);
        }
        let id = (robot.namespace().unwrap_or_default(), robot.name_any(), key);
        let Some(w) = robots.get(&id) else {
            return Cow::Borrowed(robot);
        };
        if !older(robot.resource_version().as_deref(), w.version) {
            robots.remove(&id);
            return Cow::Borrowed(robot);
        }
        let mut laid = robot.clone();
        laid.annotations_mut()
            .insert(key.to_owned(), w.mark.clone());
        if let Some(spec) = &w.spec {
            spec.set_on(&mut laid.spec);
        }
        Cow::Owned(laid)
    }

    /// The status this controller wrote to `deployment`, when the store's copy is older.
    pub fn status(&self, deployment: &RobotDeployment) -> Option<RobotDeploymentStatus> {
        let id = key_of(deployment);
        let mut statuses = lock(&self.statuses);
        let (version, status, _) = statuses.get(&id)?;
        if older(deployment.resource_version().as_deref(), *version) {
            return Some(status.clone());
        }
        statuses.remove(&id);
        None
    }
}

fn key_of(deployment: &RobotDeployment) -> DeploymentKey {
    (
        deployment.namespace().unwrap_or_default(),
        deployment.name_any(),
    )
}

/// A resourceVersion as a number, when it is one.
fn version(v: Option<&str>) -> Option<u64> {
    v?.parse().ok()
}

/// Whether the stored `version` is older than `written` (a store whose version does not parse
/// is taken as up to date: nothing is laid over it).
fn older(stored: Option<&str>, written: u64) -> bool {
    version(stored).is_some_and(|v| v < written)
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;
    use lekiwi_crds::{ReleaseRef, RobotSpec};

    const KEY: &str = "fleet.lekiwi.io/rollout";

    fn robot(version: &str) -> Robot {
        let mut r = Robot::new("kiwi", RobotSpec::default());
        r.metadata.namespace = Some("lab".into());
        r.metadata.resource_version = Some(version.into());
        r
    }

    fn release() -> ReleaseRef {
        serde_json::from_value(serde_json::json!({
            "version": "2.0.0",
            "digest": format!("sha256:{}", "b".repeat(64)),
        }))
        .unwrap()
    }

    fn written(version: &str) -> Written {
        Written {
            robot: "kiwi".into(),
            key: KEY,
            mark: "started".into(),
            spec: Some(RobotSpecPart {
                release: Some(release()),
                agent: None,
            }),
            resource_version: Some(version.into()),
        }
    }

    /// A store older than the write shows the write; one at it or later shows itself, and the
    /// write is forgotten then.
    #[tokio::test(start_paused = true)]
    async fn a_write_is_laid_over_an_older_store_only() {
        let own = OwnWrites::default();
        own.wrote_robots("lab", &[written("120")]);
        let stale = robot("100");
        let laid = own.robot(&stale, KEY);
        assert!(matches!(laid, Cow::Owned(_)));
        assert_eq!(laid.annotations()[KEY], "started");
        assert_eq!(laid.spec.release, Some(release()));
        assert_eq!(own.robot(&stale, "other/key").annotations().get(KEY), None);

        let caught_up = robot("121");
        assert!(matches!(own.robot(&caught_up, KEY), Cow::Borrowed(_)));
        assert!(
            matches!(own.robot(&stale, KEY), Cow::Borrowed(_)),
            "forgotten once the store showed it"
        );
    }

    #[tokio::test(start_paused = true)]
    async fn versions_that_do_not_parse_and_old_writes_are_never_laid_over() {
        let own = OwnWrites::default();
        own.wrote_robots("lab", &[written("abc")]);
        assert!(matches!(own.robot(&robot("1"), KEY), Cow::Borrowed(_)));
        own.wrote_robots("lab", &[written("120")]);
        assert!(matches!(own.robot(&robot("x"), KEY), Cow::Borrowed(_)));
        tokio::time::advance(KEEP + Duration::from_secs(1)).await;
        own.wrote_robots("lab", &[]);
        assert!(matches!(own.robot(&robot("100"), KEY), Cow::Borrowed(_)));
    }

    #[tokio::test(start_paused = true)]
    async fn a_status_written_is_read_back_until_the_store_shows_it() {
        let own = OwnWrites::default();
        let mut d: RobotDeployment = serde_json::from_value(serde_json::json!({
            "apiVersion": "fleet.lekiwi.io/v1alpha1",
            "kind": "RobotDeployment",
            "metadata": {"name": "roll", "namespace": "lab", "resourceVersion": "50"},
            "spec": {"selector": {}, "release": release()},
        }))
        .unwrap();
        let status = RobotDeploymentStatus {
            current_batch: Some(7),
            ..Default::default()
        };
        own.wrote_status(&d, Some("60"), &status);
        assert_eq!(own.status(&d), Some(status));
        d.metadata.resource_version = Some("61".into());
        assert_eq!(own.status(&d), None);
        d.metadata.resource_version = Some("50".into());
        assert_eq!(own.status(&d), None, "forgotten");
    }
}
