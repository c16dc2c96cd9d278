//! The status writer: takes robots off the queues under a rate limit (adaptive, see
//! [`super::adapt`]) and a concurrency cap, applies their latest status, and retries failed
//! writes with backoff.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use jiff::Timestamp;
use k8s_openapi::api::core::v1::ObjectReference;
use kube::api::{Patch, PatchParams};
use kube::runtime::events::{Event, EventType, Recorder, Reporter};
use kube::{Api, Resource};
use lekiwi_crds::Robot;
use lekiwi_crds::contract::managers;
use tokio::sync::Semaphore;
use tokio_util::sync::CancellationToken;
use tracing::{debug, warn};

use super::adapt::AdaptiveRate;
use super::{Entry, Presence, Priority};
use crate::watched::WatchedRobots;
use lekiwi_core::RobotKey;
use lekiwi_core::api_client::is_missing;
use lekiwi_core::apply::Metadata;
use lekiwi_core::rate::TokenBucket;
use lekiwi_core::watch::version_of;
use lekiwi_liveness::holder::{Holder, newest_holder};

/// Why a status write did not happen.
enum WriteError {
    /// The Robot was deleted (the API server said so of it; see [`is_missing`]).
    Gone,
    /// A later session (of another gateway) holds the robot: our write would undo its.
    Superseded,
    /// The Robot changed since the version the write was fenced with; read again.
    Conflict,
    /// The API server refused the status as invalid (400 or 422), with its explanation;
    /// retrying the same status cannot help.
    Refused(String),
    /// The API server refused or failed; retried.
    Api(kube::Error),
}

/// A write that landed: the Robot's `resourceVersion` after it (0 when not a number).
type Written = u64;

/// Whether a write's outcome says the API server is overloaded: a 429, a 5xx, or no answer.
fn throttled(result: &Result<Written, WriteError>) -> bool {
    match result {
        Err(WriteError::Api(kube::Error::Api(s))) => s.code == 429 || s.code >= 500,
        Err(WriteError::Api(_)) => true,
        _ => false,
    }
}

fn lock(rate: &Mutex<AdaptiveRate>) -> std::sync::MutexGuard<'_, AdaptiveRate> {
    rate.lock().unwrap_or_else(|p| p.into_inner())
}

/// Longest note of the Warning Event on a refused status (the API server's reason), in bytes.
const MAX_EVENT_NOTE_BYTES: usize = 1024;

/// Reads of the Robot (and writes against it) one status write tries while other writers keep
/// changing it, before it queues the robot again.
const FRESH_ATTEMPTS: usize = 3;

/// A failed write is retried after 400 ms, doubling per failure up to this.
const MAX_RETRY_DELAY: Duration = Duration::from_secs(60);

impl Presence {
    /// Writes queued robots until cancelled; `holders` is the Robot watch's cache, which
    /// saves a read per write (see [`Presence::write`]).
    pub async fn run_writer(
        self,
        client: kube::Client,
        holders: Option<WatchedRobots>,
        cancel: CancellationToken,
    ) {
        let slots = Arc::new(Semaphore::new(self.config.concurrency.max(1)));
        let mut bucket = TokenBucket::new(self.config.qps, self.config.burst);
        let adaptive = self.adaptive_rate();
        let recorder = Recorder::new(
            client.clone(),
            Reporter {
                controller: "lekiwi-gateway".into(),
                instance: Some(self.config.gateway.clone()),
            },
        );
        loop {
            let next = self.with_state(|s| s.pop());
            let Some((key, priority)) = next else {
                tokio::select! {
                    () = cancel.cancelled() => return,
                    () = self.notify.notified() => continue,
                    // A periodic look even without a wake-up: cheap insurance against a lost notify.
                    () = tokio::time::sleep(Duration::from_secs(1)) => continue,
                }
            };
            if let Some(a) = &adaptive {
                bucket.set_rate(lock(a).rate());
            }
            if !self.with_state(|s| s.begin_write(&key, priority)) {
                continue;
            }
            tokio::select! {
                () = cancel.cancelled() => return,
                () = bucket.take() => {}
            }
            let Ok(permit) = slots.clone().acquire_owned().await else {
                return;
            };
            let Some(entry) = self.with_state(|s| s.take_for_write(&key)) else {
                self.with_state(|s| s.end_write(&key));
                continue;
            };
            let me = self.clone();
            let client = client.clone();
            let recorder = recorder.clone();
            let holders = holders.clone();
            let adaptive = adaptive.clone();
            tokio::spawn(async move {
                let holders = holders.as_ref();
                let started = Instant::now();
                let mut result = me.write(&client, holders, &key, &entry).await;
                if let Some(a) = &adaptive {
                    me.adapt(a, started.elapsed(), throttled(&result));
                }
                if let Err(WriteError::Refused(why)) = &result
                    && !entry.presence_only
                {
                    me.refused(&recorder, &key, &entry, why).await;
                    let bare = Entry {
                        presence_only: true,
                        ..entry.clone()
                    };
                    result = me.write(&client, holders, &key, &bare).await;
                }
                drop(permit);
                let outcome = me.settle(key.clone(), priority, &entry, result);
                me.with_state(|s| s.end_write(&key));
                me.wake();
                me.metrics
                    .gateway
                    .status_writes
                    .get_or_create(&lekiwi_metrics::WriteLabels {
                        priority: priority.label(),
                        result: outcome,
                    })
                    .inc();
            });
        }
    }

    /// The adaptive rate, unless the rate is fixed; exports the starting rate.
    fn adaptive_rate(&self) -> Option<Arc<Mutex<AdaptiveRate>>> {
        let adaptive = self
            .config
            .adaptive
            .map(|b| Arc::new(Mutex::new(AdaptiveRate::new(self.config.qps, b))));
        let rate = adaptive
            .as_ref()
            .map_or(self.config.qps, |a| lock(a).rate());
        self.metrics.gateway.status_rate.set(rate);
        adaptive
    }

    /// Feeds how a write was answered into the adaptive rate, and exports the new rate.
    fn adapt(&self, adaptive: &Mutex<AdaptiveRate>, took: Duration, throttled: bool) {
        let backlog = self.queued() > 0;
        let mut a = lock(adaptive);
        let answer = a.classify(took, throttled);
        let rate = a.observe(answer, backlog, Instant::now());
        self.metrics.gateway.status_rate.set(rate);
    }

    /// Brings the presence state up to date with how the write of `entry` went, and returns
    /// the `result` label of the write.
    fn settle(
        &self,
        key: RobotKey,
        priority: Priority,
        entry: &Entry,
        result: Result<Written, WriteError>,
    ) -> &'static str {
        match result {
            Ok(version) => {
                self.written(&key, entry, version);
                "ok"
            }
            Err(WriteError::Gone) => {
                warn!(robot = %key.name, namespace = %key.namespace, "Robot no longer exists; dropping its presence");
                self.with_state(|s| s.robots.remove(&key));
                "gone"
            }
            Err(WriteError::Superseded) => {
                // Not ours any more: the Robot watch closes the session, if it still runs.
                self.with_state(|s| {
                    if s.robots
                        .get(&key)
                        .is_some_and(|e| e.session == entry.session)
                    {
                        s.robots.remove(&key);
                        s.queued.remove(&key);
                    }
                });
                "superseded"
            }
            Err(WriteError::Refused(why)) => {
                // Even presence alone was refused: nothing this gateway sends can help.
                warn!(robot = %key.name, namespace = %key.namespace, error = %why, "status write refused; not retrying");
                "refused"
            }
            Err(WriteError::Api(e)) => {
                self.retry_later(key, priority, Some(&e));
                "error"
            }
            Err(WriteError::Conflict) => {
                // Other writers were busy with this Robot; nothing failed.
                self.retry_later(key, priority, None);
                "conflict"
            }
        }
    }

    /// `entry` is in the API server now, the Robot at `version`: its heartbeat counts as
    /// written, and a disconnected robot written as such is forgotten.
    pub(super) fn written(&self, key: &RobotKey, entry: &Entry, version: Written) {
        self.with_state(|s| {
            if let Some(e) = s.robots.get_mut(key) {
                e.retries = 0;
                if e.session == entry.session {
                    e.written_version = e.written_version.max(version);
                    e.written_heartbeat = Some(entry.last_heartbeat);
                    e.written_at = Some(Timestamp::now());
                    e.analysis.written(&entry.analysis);
                    // A claim stays until this gateway's Robot watch shows the write
                    // (`Presence::write_seen`): the Robot controller's watch is seldom ahead of it.
                }
                // A disconnected robot written as such needs no memory any more, except that
                // the status says so.
                if !e.connected && !entry.connected && e.session == entry.session {
                    s.robots.remove(key);
                    s.known_offline.insert(key.clone());
                }
            }
            if entry.connected {
                s.known_offline.remove(key);
            }
        });
    }

    /// Queues the robot again after a backoff that doubles with each failure in a row; an
    /// `error` is logged as a warning, a retry without one (conflicts) at debug level.
    fn retry_later(
        &self,
        key: RobotKey,
        priority: Priority,
        error: Option<&dyn std::fmt::Display>,
    ) {
        let retries = self.with_state(|s| {
            s.robots.get_mut(&key).map(|e| {
                e.retries += 1;
                e.retries
            })
        });
        let delay =
            Duration::from_millis(200 * (1u64 << retries.unwrap_or(1).min(8))).min(MAX_RETRY_DELAY);
        match error {
            Some(error) => {
                warn!(robot = %key.name, namespace = %key.namespace, error = %error, retry_in = ?delay, "status write failed")
            }
            None => {
                debug!(robot = %key.name, namespace = %key.namespace, retry_in = ?delay, "the Robot kept changing while writing its status; retrying")
            }
        }
        let again = self.clone();
        tokio::spawn(async move {
            tokio::time::sleep(delay).await;
            again.with_state(|s| {
                if s.robots.contains_key(&key) {
                    s.enqueue(&key, priority);
                }
            });
            again.wake();
        });
    }

    /// The API server refused the status of `entry`: the rest of its session writes presence
    /// only, and a Warning Event on the Robot quotes the server's reason (which names the field).
    async fn refused(&self, recorder: &Recorder, key: &RobotKey, entry: &Entry, why: &str) {
        warn!(robot = %key.name, namespace = %key.namespace, error = %why, "status refused; writing presence only");
        self.with_state(|s| {
            if let Some(e) = s.robots.get_mut(key).filter(|e| e.session == entry.session) {
                e.presence_only = true;
            }
        });
        let event = Event {
            type_: EventType::Warning,
            reason: "StatusFieldRefused".into(),
            note: Some(lekiwi_protocol::truncate_utf8(why, MAX_EVENT_NOTE_BYTES).to_owned()),
            action: "WriteStatus".into(),
            secondary: None,
        };
        let robot = ObjectReference {
            api_version: Some(Robot::api_version(&()).into_owned()),
            kind: Some(Robot::kind(&()).into_owned()),
            name: Some(key.name.clone()),
            namespace: Some(key.namespace.clone()),
            ..ObjectReference::default()
        };
        if let Err(e) = recorder.publish(&event, &robot).await {
            warn!(robot = %key.name, error = %e, "cannot publish Event");
        }
    }

    /// Applies the status of `e`, fenced: only while no later session holds the robot (see
    /// [`lekiwi_liveness::holder`]), with the `resourceVersion` that showed it as a precondition.
    /// The newer of the Robot watch's cache (`holders`) and this session's own last write
    /// answers first (see [`newest_holder`]); after a conflict, or for a robot missing there,
    /// the Robot is read from the API server, up to [`FRESH_ATTEMPTS`] times.
    async fn write(
        &self,
        client: &kube::Client,
        holders: Option<&WatchedRobots>,
        key: &RobotKey,
        e: &Entry,
    ) -> Result<Written, WriteError> {
        let api: Api<Robot> = Api::namespaced(client.clone(), &key.namespace);
        let own = self.with_state(|s| {
            s.robots
                .get(key)
                .filter(|held| held.session == e.session)
                .map_or(0, |held| held.written_version)
        });
        let cached = holders.and_then(|h| h.holder(key));
        if let Some(holder) = newest_holder(cached, own, &self.config.gateway, e.epoch) {
            match self.apply(&api, key, e, &holder, None).await {
                Err(WriteError::Conflict) => {
                    self.metrics.gateway.status_write_conflicts.inc();
                }
                done => return done,
            }
        }
        for _ in 0..FRESH_ATTEMPTS {
            let fresh = match api.get(&key.name).await {
                Ok(r) => r,
                Err(kube::Error::Api(s)) if is_missing(&s, &key.name) => {
                    return Err(WriteError::Gone);
                }
                Err(err) => return Err(WriteError::Api(err)),
            };
            match self
                .apply(&api, key, e, &Holder::of(&fresh), Some(&fresh))
                .await
            {
                Err(WriteError::Conflict) => {
                    self.metrics.gateway.status_write_conflicts.inc();
                }
                done => return done,
            }
        }
        Err(WriteError::Conflict)
    }

    /// Applies the status of `e` against the Robot as `holder` shows it (read from `fresh`,
    /// when the Robot was just read, which the phase is then planned from too): `Superseded`
    /// without a request when a later session holds it, `Conflict` when it changed since.
    async fn apply(
        &self,
        api: &Api<Robot>,
        key: &RobotKey,
        e: &Entry,
        holder: &Holder,
        fresh: Option<&Robot>,
    ) -> Result<Written, WriteError> {
        if holder.supersedes(&self.config.gateway, e.epoch, e.connected) {
            debug!(robot = %key.name, holder = ?holder.gateway, "a later session holds the robot; not writing");
            return Err(WriteError::Superseded);
        }
        let precondition = Metadata::fence(holder.resource_version.clone());
        let patch = self.patch(key, e, Some(precondition), fresh);
        match api
            .patch_status(
                &key.name,
                &PatchParams::apply(managers::GATEWAY).force(),
                &Patch::Apply(&patch),
            )
            .await
        {
            Ok(robot) => Ok(version_of(&robot).unwrap_or(0)),
            Err(kube::Error::Api(s)) if is_missing(&s, &key.name) => Err(WriteError::Gone),
            Err(kube::Error::Api(s)) if s.code == 409 => Err(WriteError::Conflict),
            Err(kube::Error::Api(s)) if s.code == 400 || s.code == 422 => {
                Err(WriteError::Refused(s.message))
            }
            Err(err) => Err(WriteError::Api(err)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ConnectInfo;
    use crate::tests::entry;
    use axum::http::StatusCode;

    /// A stand-in API server that answers every request with `status` and `body`.
    async fn answering(status: StatusCode, body: &'static str) -> kube::Client {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let app = axum::Router::new().fallback(move || async move { (status, body) });
        tokio::spawn(async move { axum::serve(listener, app).await });
        kube::Client::try_from(kube::Config::new(url.parse().unwrap())).unwrap()
    }

    /// A restarting API server answers "404 page not found" for a custom resource it has not
    /// loaded yet: the write is retried, the robot's presence kept. Only a 404 naming the Robot
    /// drops it.
    #[tokio::test]
    async fn a_404_that_does_not_name_the_robot_is_retried_not_taken_for_a_deletion() {
        let presence = crate::tests::presence();
        let key = RobotKey::new("fleet", "kiwi");
        let e = entry(true, ConnectInfo::default());
        let unserved = answering(StatusCode::NOT_FOUND, "404 page not found").await;
        let outcome = presence.write(&unserved, None, &key, &e).await;
        assert!(matches!(outcome, Err(WriteError::Api(_))), "not retried");

        let deleted = answering(
            StatusCode::NOT_FOUND,
            r#"{"kind":"Status","apiVersion":"v1","status":"Failure","reason":"NotFound","message":"robots.fleet.lekiwi.io \"kiwi\" not found","details":{"name":"kiwi","group":"fleet.lekiwi.io","kind":"robots"},"code":404}"#,
        )
        .await;
        let outcome = presence.write(&deleted, None, &key, &e).await;
        assert!(
            matches!(outcome, Err(WriteError::Gone)),
            "a deleted Robot not seen as gone"
        );
    }
}
