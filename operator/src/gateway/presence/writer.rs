//! The status writer: takes robots off the queues under a rate limit and a concurrency cap,
//! applies their latest status, and retries failed writes with backoff.

use std::sync::Arc;
use std::time::Duration;

use k8s_openapi::api::core::v1::ObjectReference;
use kube::api::{Patch, PatchParams};
use kube::runtime::events::{Event, EventType, Recorder, Reporter};
use kube::{Api, Resource};
use lekiwi_crds::Robot;
use lekiwi_crds::contract::managers;
use tokio::sync::Semaphore;
use tokio_util::sync::CancellationToken;
use tracing::{debug, warn};

use super::patch::Precondition;
use super::{Entry, Presence, Priority};
use crate::gateway::event_store::RobotKey;
use crate::gateway::rate::TokenBucket;

/// Why a status write did not happen.
enum WriteError {
    /// The Robot was deleted.
    Gone,
    /// Another gateway holds the robot now; our disconnect would undo its connect.
    Superseded,
    /// The API server refused the status as invalid (400 or 422), with its explanation;
    /// retrying the same status cannot help.
    Refused(String),
    /// The API server refused or failed; retried.
    Api(kube::Error),
}

/// Longest note of the Warning Event on a refused status (the API server's reason), in bytes.
const MAX_EVENT_NOTE_BYTES: usize = 1024;

/// A failed write is retried after 400 ms, doubling per failure up to this.
const MAX_RETRY_DELAY: Duration = Duration::from_secs(60);

impl Presence {
    /// Writes queued robots until cancelled.
    pub async fn run_writer(self, client: kube::Client, cancel: CancellationToken) {
        let slots = Arc::new(Semaphore::new(self.config.concurrency.max(1)));
        let mut bucket = TokenBucket::new(self.config.qps, self.config.burst);
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
            tokio::select! {
                () = cancel.cancelled() => return,
                () = bucket.take() => {}
            }
            let Ok(permit) = slots.clone().acquire_owned().await else {
                return;
            };
            let Some(entry) = self.with_state(|s| s.take_for_write(&key)) else {
                continue;
            };
            let me = self.clone();
            let client = client.clone();
            let recorder = recorder.clone();
            tokio::spawn(async move {
                let mut result = me.write(&client, &key, &entry).await;
                if let Err(WriteError::Refused(why)) = &result
                    && !entry.presence_only
                {
                    me.refused(&recorder, &key, &entry, why).await;
                    let bare = Entry {
                        presence_only: true,
                        ..entry.clone()
                    };
                    result = me.write(&client, &key, &bare).await;
                }
                drop(permit);
                let outcome = me.settle(key, priority, &entry, result);
                me.metrics
                    .gateway
                    .status_writes
                    .get_or_create(&crate::metrics::WriteLabels {
                        priority: priority.label(),
                        result: outcome,
                    })
                    .inc();
            });
        }
    }

    /// Brings the presence state up to date with how the write of `entry` went, and returns
    /// the `result` label of the write.
    fn settle(
        &self,
        key: RobotKey,
        priority: Priority,
        entry: &Entry,
        result: Result<(), WriteError>,
    ) -> &'static str {
        match result {
            Ok(()) => {
                self.written(&key, entry);
                "ok"
            }
            Err(WriteError::Gone) => {
                warn!(robot = %key.name, namespace = %key.namespace, "Robot no longer exists; dropping its presence");
                self.with_state(|s| s.robots.remove(&key));
                "gone"
            }
            Err(WriteError::Superseded) => "superseded",
            Err(WriteError::Refused(why)) => {
                // Even presence alone was refused: nothing this gateway sends can help.
                warn!(robot = %key.name, namespace = %key.namespace, error = %why, "status write refused; not retrying");
                "refused"
            }
            Err(WriteError::Api(e)) => {
                self.retry_later(key, priority, &e);
                "error"
            }
        }
    }

    /// `entry` is in the API server now: its heartbeat counts as written, and a disconnected
    /// robot written as such is forgotten.
    fn written(&self, key: &RobotKey, entry: &Entry) {
        self.with_state(|s| {
            if let Some(e) = s.robots.get_mut(key) {
                e.retries = 0;
                if e.session == entry.session {
                    e.written_heartbeat = Some(entry.last_heartbeat);
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

    /// Queues the robot again after a backoff that doubles with each failure in a row.
    fn retry_later(&self, key: RobotKey, priority: Priority, error: &kube::Error) {
        let retries = self.with_state(|s| {
            s.robots.get_mut(&key).map(|e| {
                e.retries += 1;
                e.retries
            })
        });
        let delay =
            Duration::from_millis(200 * (1u64 << retries.unwrap_or(1).min(8))).min(MAX_RETRY_DELAY);
        warn!(robot = %key.name, namespace = %key.namespace, error = %error, retry_in = ?delay, "status write failed");
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

    /// Applies the status of `e`; a disconnect only while the robot is still ours.
    async fn write(
        &self,
        client: &kube::Client,
        key: &RobotKey,
        e: &Entry,
    ) -> Result<(), WriteError> {
        let api: Api<Robot> = Api::namespaced(client.clone(), &key.namespace);
        let precondition = if e.connected {
            None
        } else {
            Some(self.disconnect_precondition(&api, key, e).await?)
        };
        let patch = self.patch(key, e, precondition);
        match api
            .patch_status(
                &key.name,
                &PatchParams::apply(managers::GATEWAY).force(),
                &Patch::Apply(&patch),
            )
            .await
        {
            Ok(_) => Ok(()),
            Err(kube::Error::Api(s)) if s.code == 404 => Err(WriteError::Gone),
            Err(kube::Error::Api(s)) if s.code == 400 || s.code == 422 => {
                Err(WriteError::Refused(s.message))
            }
            Err(err) => Err(WriteError::Api(err)),
        }
    }

    /// A disconnect must not undo a newer connection through another gateway: it is written
    /// only if the robot is still ours, with the version we read as a precondition.
    async fn disconnect_precondition(
        &self,
        api: &Api<Robot>,
        key: &RobotKey,
        e: &Entry,
    ) -> Result<Precondition, WriteError> {
        let robot = match api.get_opt(&key.name).await {
            Ok(Some(r)) => r,
            Ok(None) => return Err(WriteError::Gone),
            Err(err) => return Err(WriteError::Api(err)),
        };
        let status = robot.status.unwrap_or_default();
        let ours = status.gateway.as_deref() == Some(self.config.gateway.as_str());
        let newer = status
            .connected_since
            .is_some_and(|t| t.0 > e.connected_since);
        if status.gateway.is_some() && (!ours || newer) {
            debug!(robot = %key.name, "robot moved to another gateway; not writing the disconnect");
            return Err(WriteError::Superseded);
        }
        Ok(Precondition {
            resource_version: robot.metadata.resource_version,
        })
    }
}
