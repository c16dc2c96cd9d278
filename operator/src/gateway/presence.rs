//! Presence: what each connected robot last said, kept in memory, and the one writer that turns
//! meaningful changes into `Robot` status by server-side apply without flooding the API server.
//!
//! Every robot has at most one entry in one of two queues: transitions (connect, disconnect,
//! release, health or teleoperation change) go to the high-priority queue, routine heartbeat
//! refreshes (at most every `status_refresh`) to the low one. The writer takes high before low,
//! writes the *latest* state of the robot when its turn comes (so bursts coalesce), respects a
//! rate limit, and retries failures with backoff; nothing is dropped and memory is bounded by
//! the number of robots.

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use jiff::Timestamp;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::Time;
use kube::Api;
use kube::api::{Patch, PatchParams};
use lekiwi_crds::Robot;
use lekiwi_protocol::{Health, Release, SystemFacts, Teleoperation, Vitals};
use serde_json::{Value, json};
use tokio::sync::{Notify, Semaphore};
use tokio_util::sync::CancellationToken;
use tracing::{debug, warn};

use crate::gateway::event_store::RobotKey;
use crate::metrics::Metrics;
use lekiwi_crds::contract::managers;

/// Write priority.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Priority {
    /// Connects, disconnects and other transitions.
    High,
    /// Routine `lastHeartbeatTime` refreshes.
    Low,
}

impl Priority {
    fn label(self) -> &'static str {
        match self {
            Priority::High => "high",
            Priority::Low => "low",
        }
    }
}

/// What a robot told us at connect time.
#[derive(Clone, Debug, Default)]
pub struct ConnectInfo {
    /// `websocket` or `poll`.
    pub protocol: &'static str,
    /// Agent software version.
    pub agent_version: String,
    /// Release it runs.
    pub release: Option<Release>,
    /// Health.
    pub health: Option<Health>,
    /// Teleoperation.
    pub teleoperation: Option<Teleoperation>,
    /// System facts.
    pub system: SystemFacts,
    /// Peer address.
    pub address: Option<String>,
}

/// What a heartbeat carries that matters for status.
#[derive(Clone, Debug, Default)]
pub struct HeartbeatInfo {
    /// Release it runs.
    pub release: Option<Release>,
    /// Health.
    pub health: Option<Health>,
    /// Teleoperation.
    pub teleoperation: Option<Teleoperation>,
    /// Readings.
    pub vitals: Vitals,
}

/// How an agent's release update ended, as it reported it.
#[derive(Clone, Debug, PartialEq)]
pub struct UpdateOutcome {
    /// The release it was told to run.
    pub release: Release,
    /// `done`, `failed` or `rolled_back`.
    pub phase: String,
    /// Its explanation.
    pub message: Option<String>,
    /// When the gateway got it.
    pub time: Timestamp,
}

#[derive(Clone, Debug)]
struct Entry {
    session: u64,
    connected: bool,
    info: ConnectInfo,
    connected_since: Timestamp,
    last_heartbeat: Timestamp,
    written_heartbeat: Option<Timestamp>,
    teleoperation_since: Option<Timestamp>,
    vitals: Vitals,
    retries: u32,
    last_update: Option<UpdateOutcome>,
}

#[derive(Default)]
struct State {
    robots: HashMap<RobotKey, Entry>,
    queued: HashMap<RobotKey, Priority>,
    high: VecDeque<RobotKey>,
    low: VecDeque<RobotKey>,
}

impl State {
    fn enqueue(&mut self, key: &RobotKey, priority: Priority) {
        match self.queued.get(key) {
            Some(Priority::High) => {}
            Some(Priority::Low) if priority == Priority::Low => {}
            _ => {
                // A robot waiting as Low is promoted: it stays in `low` too, but is skipped
                // there because `queued` says High.
                self.queued.insert(key.clone(), priority);
                match priority {
                    Priority::High => self.high.push_back(key.clone()),
                    Priority::Low => self.low.push_back(key.clone()),
                }
            }
        }
    }

    fn pop(&mut self) -> Option<(RobotKey, Priority)> {
        while let Some(key) = self.high.pop_front() {
            if self.queued.get(&key) == Some(&Priority::High) {
                self.queued.remove(&key);
                return Some((key, Priority::High));
            }
        }
        while let Some(key) = self.low.pop_front() {
            if self.queued.get(&key) == Some(&Priority::Low) {
                self.queued.remove(&key);
                return Some((key, Priority::Low));
            }
        }
        None
    }
}

/// Settings of the presence tracker and its writer.
#[derive(Clone, Debug)]
pub struct PresenceConfig {
    /// This gateway's name (also its Lease's name), written to `status.gateway`.
    pub gateway: String,
    /// Refresh `lastHeartbeatTime` at most this often when nothing else changes.
    pub status_refresh: Duration,
    /// A polling robot that has not polled for this long is Offline.
    pub poll_grace: Duration,
    /// Sustained status writes per second.
    pub qps: f64,
    /// Burst of status writes.
    pub burst: u32,
    /// Writes in flight at once.
    pub concurrency: usize,
}

/// The presence tracker; cheap to clone.
#[derive(Clone)]
pub struct Presence {
    state: Arc<Mutex<State>>,
    notify: Arc<Notify>,
    config: Arc<PresenceConfig>,
    metrics: Metrics,
}

impl Presence {
    /// An empty tracker.
    pub fn new(config: PresenceConfig, metrics: Metrics) -> Self {
        Self {
            state: Arc::default(),
            notify: Arc::default(),
            config: Arc::new(config),
            metrics,
        }
    }

    fn with_state<T>(&self, f: impl FnOnce(&mut State) -> T) -> T {
        let mut state = self.state.lock().unwrap_or_else(|p| p.into_inner());
        let out = f(&mut state);
        self.metrics
            .gateway
            .status_queue
            .get_or_create(&crate::metrics::PriorityLabels { priority: "high" })
            .set(state.high.len() as i64);
        self.metrics
            .gateway
            .status_queue
            .get_or_create(&crate::metrics::PriorityLabels { priority: "low" })
            .set(state.low.len() as i64);
        out
    }

    fn wake(&self) {
        self.notify.notify_one();
    }

    /// A session of `key` started.
    pub fn connect(&self, key: &RobotKey, session: u64, info: ConnectInfo) {
        let now = Timestamp::now();
        self.with_state(|s| {
            let teleoperation_since = info.teleoperation.as_ref().map(|_| now);
            // Keep the last update's outcome: rollouts read it, and a manager that stops
            // sending a field makes server-side apply drop it.
            let last_update = s.robots.get(key).and_then(|e| e.last_update.clone());
            s.robots.insert(
                key.clone(),
                Entry {
                    session,
                    connected: true,
                    info,
                    connected_since: now,
                    last_heartbeat: now,
                    written_heartbeat: None,
                    teleoperation_since,
                    vitals: Vitals::default(),
                    retries: 0,
                    last_update,
                },
            );
            s.enqueue(key, Priority::High);
        });
        self.wake();
    }

    /// A heartbeat of the session `session`: kept in memory; written at once only if the
    /// release, health or teleoperation changed.
    pub fn heartbeat(&self, key: &RobotKey, session: u64, hb: HeartbeatInfo) {
        let now = Timestamp::now();
        let changed = self.with_state(|s| {
            let Some(e) = s
                .robots
                .get_mut(key)
                .filter(|e| e.session == session && e.connected)
            else {
                return false;
            };
            e.last_heartbeat = now;
            e.vitals = hb.vitals;
            let mut changed = false;
            if hb.release.is_some() && hb.release != e.info.release {
                e.info.release = hb.release;
                changed = true;
            }
            if hb.health.is_some() && hb.health != e.info.health {
                e.info.health = hb.health;
                changed = true;
            }
            if let Some(t) = hb.teleoperation {
                let was = e.info.teleoperation.as_ref().map(|t| t.active);
                if was != Some(t.active) {
                    e.teleoperation_since = Some(now);
                    changed = true;
                }
                e.info.teleoperation = Some(t);
            }
            self.metrics.per_robot.record(
                &key.namespace,
                &key.name,
                &e.vitals,
                e.info.release.as_ref(),
            );
            if changed {
                s.enqueue(key, Priority::High);
            }
            changed
        });
        if changed {
            self.wake();
        }
    }

    /// An update commanded in session `session` ended; written at once.
    pub fn update_finished(&self, key: &RobotKey, session: u64, outcome: UpdateOutcome) {
        let done = self.with_state(|s| {
            let Some(e) = s.robots.get_mut(key).filter(|e| e.session == session) else {
                return false;
            };
            if outcome.phase == lekiwi_protocol::ProgressPhase::Done.as_str() {
                e.info.release = Some(outcome.release.clone());
            }
            e.last_update = Some(outcome);
            s.enqueue(key, Priority::High);
            true
        });
        if done {
            self.wake();
        }
    }

    /// A poll from a legacy agent counts as a heartbeat (and as a connect the first time).
    pub fn poll(&self, key: &RobotKey, info: ConnectInfo) {
        enum Act {
            Connect,
            Wake,
            Nothing,
        }
        let act = self.with_state(|s| match s.robots.get_mut(key) {
            Some(e) if e.connected && e.info.protocol == "poll" => {
                e.last_heartbeat = Timestamp::now();
                if info.release != e.info.release || info.agent_version != e.info.agent_version {
                    e.info.release = info.release.clone();
                    e.info.agent_version = info.agent_version.clone();
                    s.enqueue(key, Priority::High);
                    Act::Wake
                } else {
                    Act::Nothing
                }
            }
            // Connected over WebSocket: the session is the authority; the poll changes nothing.
            Some(e) if e.connected => Act::Nothing,
            _ => Act::Connect,
        });
        match act {
            Act::Connect => self.connect(key, 0, info),
            Act::Wake => self.wake(),
            Act::Nothing => {}
        }
    }

    /// The session `session` ended; ignored if a newer session already took over.
    pub fn disconnect(&self, key: &RobotKey, session: u64) {
        let done = self.with_state(|s| {
            let Some(e) = s
                .robots
                .get_mut(key)
                .filter(|e| e.session == session && e.connected)
            else {
                return false;
            };
            e.connected = false;
            self.metrics.per_robot.forget(&key.namespace, &key.name);
            s.enqueue(key, Priority::High);
            true
        });
        if done {
            self.wake();
        }
    }

    /// Robots waiting for a write.
    pub fn queued(&self) -> usize {
        self.with_state(|s| s.queued.len())
    }

    /// Number of robots connected right now.
    pub fn connected(&self) -> usize {
        self.with_state(|s| s.robots.values().filter(|e| e.connected).count())
    }

    /// Queues routine refreshes and ends silent polling sessions; call every second.
    pub fn tick(&self) {
        let now = Timestamp::now();
        let refresh =
            jiff::SignedDuration::try_from(self.config.status_refresh).unwrap_or_default();
        let poll_grace = jiff::SignedDuration::try_from(self.config.poll_grace).unwrap_or_default();
        let queued = self.with_state(|s| {
            let mut due = Vec::new();
            for (key, e) in s.robots.iter_mut() {
                if !e.connected {
                    continue;
                }
                if e.info.protocol == "poll" && now.duration_since(e.last_heartbeat) > poll_grace {
                    e.connected = false;
                    due.push((key.clone(), Priority::High));
                } else if e
                    .written_heartbeat
                    .is_some_and(|w| now.duration_since(w) >= refresh && e.last_heartbeat > w)
                {
                    due.push((key.clone(), Priority::Low));
                }
            }
            for (key, p) in &due {
                s.enqueue(key, *p);
            }
            !due.is_empty()
        });
        if queued {
            self.wake();
        }
    }

    /// The status patch for one robot's current state.
    fn patch_for(&self, e: &Entry) -> Value {
        let time = |t: Timestamp| serde_json::to_value(Time(t)).unwrap_or(Value::Null);
        let mut status = json!({
            "connected": e.connected,
            "gateway": self.config.gateway,
            "protocol": e.info.protocol,
            "connectedSince": time(e.connected_since),
            "lastHeartbeatTime": time(e.last_heartbeat),
        });
        if !e.info.agent_version.is_empty() {
            status["agentVersion"] = json!(e.info.agent_version);
        }
        if let Some(r) = &e.info.release {
            status["currentRelease"] = json!({ "version": r.version, "digest": r.digest });
        }
        if let Some(a) = &e.info.address {
            status["address"] = json!(a);
        }
        if let Some(h) = &e.info.health {
            status["health"] = json!(h);
            if h.message.is_none() {
                status["health"] = json!({ "healthy": h.healthy });
            }
        }
        if let Some(t) = &e.info.teleoperation {
            let mut v = json!({ "active": t.active });
            if let Some(score) = t.score {
                v["score"] = json!(score.clamp(0.0, 1.0));
            }
            if let Some(since) = e.teleoperation_since {
                v["since"] = time(since);
            }
            status["teleoperation"] = v;
        }
        let sys = &e.info.system;
        let mut system = serde_json::Map::new();
        for (k, v) in [
            ("hostname", sys.hostname.as_ref().map(|x| json!(x))),
            ("os", sys.os.as_ref().map(|x| json!(x))),
            ("kernel", sys.kernel.as_ref().map(|x| json!(x))),
            ("arch", sys.arch.as_ref().map(|x| json!(x))),
            ("cpus", sys.cpus.map(|x| json!(x))),
            ("memoryBytes", sys.memory_bytes.map(|x| json!(x))),
        ] {
            if let Some(v) = v {
                system.insert(k.to_owned(), v);
            }
        }
        if !system.is_empty() {
            status["system"] = Value::Object(system);
        }
        let v = &e.vitals;
        let mut telemetry = serde_json::Map::new();
        for (k, x) in [
            ("cpuPercent", v.cpu_percent),
            ("memoryPercent", v.memory_percent),
            ("temperatureCelsius", v.temperature_c),
            ("batteryPercent", v.battery_percent),
        ] {
            if let Some(x) = x.filter(|x| x.is_finite()) {
                telemetry.insert(k.to_owned(), json!(x));
            }
        }
        if !telemetry.is_empty() {
            status["telemetry"] = Value::Object(telemetry);
        }
        if let Some(u) = &e.last_update {
            let mut v = json!({
                "release": { "version": u.release.version, "digest": u.release.digest },
                "phase": u.phase,
                "time": time(u.time),
            });
            if let Some(m) = &u.message {
                v["message"] = json!(m.chars().take(1024).collect::<String>());
            }
            status["lastUpdate"] = v;
        }
        json!({ "apiVersion": "fleet.lekiwi.io/v1alpha1", "kind": "Robot", "status": status })
    }

    /// Writes queued robots until cancelled.
    pub async fn run_writer(self, client: kube::Client, cancel: CancellationToken) {
        let slots = Arc::new(Semaphore::new(self.config.concurrency.max(1)));
        let mut bucket = super::rate::TokenBucket::new(self.config.qps, self.config.burst);
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
            let Some(entry) = self.with_state(|s| s.robots.get(&key).cloned()) else {
                continue;
            };
            let me = self.clone();
            let client = client.clone();
            tokio::spawn(async move {
                let result = me.write(&client, &key, &entry).await;
                drop(permit);
                let outcome = match result {
                    Ok(()) => {
                        me.with_state(|s| {
                            if let Some(e) = s.robots.get_mut(&key) {
                                e.retries = 0;
                                if e.session == entry.session {
                                    e.written_heartbeat = Some(entry.last_heartbeat);
                                }
                                // A disconnected robot written as such needs no memory any more.
                                if !e.connected && !entry.connected && e.session == entry.session {
                                    s.robots.remove(&key);
                                }
                            }
                        });
                        "ok"
                    }
                    Err(WriteError::Gone) => {
                        warn!(robot = %key.name, namespace = %key.namespace, "Robot no longer exists; dropping its presence");
                        me.with_state(|s| s.robots.remove(&key));
                        "gone"
                    }
                    Err(WriteError::Superseded) => "superseded",
                    Err(WriteError::Api(e)) => {
                        let retries = me.with_state(|s| {
                            s.robots.get_mut(&key).map(|e| {
                                e.retries += 1;
                                e.retries
                            })
                        });
                        let delay =
                            Duration::from_millis(200 * (1u64 << retries.unwrap_or(1).min(8)))
                                .min(Duration::from_secs(60));
                        warn!(robot = %key.name, namespace = %key.namespace, error = %e, retry_in = ?delay, "status write failed");
                        let again = me.clone();
                        tokio::spawn(async move {
                            tokio::time::sleep(delay).await;
                            again.with_state(|s| {
                                if s.robots.contains_key(&key) {
                                    s.enqueue(&key, priority);
                                }
                            });
                            again.wake();
                        });
                        "error"
                    }
                };
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

    async fn write(
        &self,
        client: &kube::Client,
        key: &RobotKey,
        e: &Entry,
    ) -> Result<(), WriteError> {
        let api: Api<Robot> = Api::namespaced(client.clone(), &key.namespace);
        let mut patch = self.patch_for(e);
        if !e.connected {
            // A disconnect must not undo a newer connection through another gateway: write it
            // only if the robot is still ours, with the version we read as a precondition.
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
            patch["metadata"] = json!({ "resourceVersion": robot.metadata.resource_version });
        }
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
            Err(err) => Err(WriteError::Api(err)),
        }
    }
}

enum WriteError {
    Gone,
    Superseded,
    Api(kube::Error),
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(n: &str) -> RobotKey {
        RobotKey {
            namespace: "lab".into(),
            name: n.into(),
        }
    }

    fn presence() -> Presence {
        Presence::new(
            PresenceConfig {
                gateway: "gw".into(),
                status_refresh: Duration::from_secs(300),
                poll_grace: Duration::from_secs(180),
                qps: 10.0,
                burst: 10,
                concurrency: 2,
            },
            Metrics::default(),
        )
    }

    #[test]
    fn transitions_jump_the_queue_and_bursts_coalesce() {
        let p = presence();
        p.with_state(|s| {
            s.robots.insert(
                key("a"),
                Entry {
                    session: 1,
                    connected: true,
                    info: ConnectInfo::default(),
                    connected_since: Timestamp::now(),
                    last_heartbeat: Timestamp::now(),
                    written_heartbeat: None,
                    teleoperation_since: None,
                    vitals: Vitals::default(),
                    retries: 0,
                    last_update: None,
                },
            );
            s.enqueue(&key("a"), Priority::Low);
        });
        p.connect(&key("b"), 2, ConnectInfo::default());
        p.connect(&key("b"), 3, ConnectInfo::default());
        p.disconnect(&key("b"), 2); // stale session: ignored
        p.with_state(|s| {
            assert_eq!(
                s.pop(),
                Some((key("b"), Priority::High)),
                "high first, once"
            );
            assert_eq!(s.pop(), Some((key("a"), Priority::Low)));
            assert_eq!(s.pop(), None);
            assert!(s.robots[&key("b")].connected);
        });
    }

    #[test]
    fn routine_heartbeats_write_nothing_until_refresh_but_changes_do() {
        let p = presence();
        p.connect(
            &key("a"),
            1,
            ConnectInfo {
                teleoperation: Some(Teleoperation {
                    active: false,
                    score: None,
                }),
                ..ConnectInfo::default()
            },
        );
        p.with_state(|s| {
            s.pop();
            s.robots.get_mut(&key("a")).unwrap().written_heartbeat = Some(Timestamp::now());
        });
        for _ in 0..100 {
            p.heartbeat(
                &key("a"),
                1,
                HeartbeatInfo {
                    teleoperation: Some(Teleoperation {
                        active: false,
                        score: None,
                    }),
                    ..Default::default()
                },
            );
        }
        p.tick();
        assert_eq!(
            p.with_state(|s| s.pop()),
            None,
            "unchanged heartbeats within the refresh period"
        );
        p.heartbeat(
            &key("a"),
            1,
            HeartbeatInfo {
                teleoperation: Some(Teleoperation {
                    active: true,
                    score: Some(0.9),
                }),
                ..Default::default()
            },
        );
        assert_eq!(p.with_state(|s| s.pop()), Some((key("a"), Priority::High)));
        let patch = p.with_state(|s| p.patch_for(&s.robots[&key("a")]));
        assert_eq!(patch["status"]["teleoperation"]["active"], json!(true));
        assert_eq!(patch["status"]["gateway"], json!("gw"));
    }
}
