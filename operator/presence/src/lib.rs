//! The gateway's status writer: what each connected robot last said (its presence), kept in
//! memory, and the one writer that turns meaningful changes into `Robot` status by server-side
//! apply without flooding the API server. The robot-facing gateway (transport, sessions) feeds it;
//! the phase rules it applies are `lekiwi_liveness`'s, shared with the Robot controller.
//!
//! Every robot has at most one entry in one of two queues: transitions (connect, disconnect,
//! release, health or teleoperation change) go to the high-priority queue, routine heartbeat
//! refreshes (at most every `status_refresh`) and the outcome of an analysis window a rollout
//! asked for (once per switch) to the low one. The writer takes high before low,
//! writes the *latest* state of the robot when its turn comes (so bursts coalesce), respects a
//! rate limit, and retries failures with backoff; nothing is dropped and memory is bounded by
//! the number of robots. A status the API server refuses as invalid is not retried: the writer
//! falls back to presence alone for the rest of the session and says why in a Warning Event.

mod adapt;
mod agent;
pub(crate) mod analysis;

#[cfg(test)]
mod analysis_tests;
pub mod claims;
/// The session epochs and the fence of a gateway's writes: rules of [`lekiwi_liveness`].
pub use lekiwi_liveness::holder;
mod lag;
pub mod lease;
mod patch;
pub mod peers;
mod phase;
#[cfg(test)]
mod properties_tests;
mod queue;
mod refresh;
#[cfg(test)]
mod tests;
pub mod watched;
mod writer;

use std::sync::{Arc, Mutex};
use std::time::Duration;

use jiff::Timestamp;
use lekiwi_protocol::{Health, Release, SystemFacts, Teleoperation, Vitals};
use tokio::sync::Notify;

pub use self::adapt::RateBounds;
pub use self::agent::AgentUpdateOutcome;
pub use self::analysis::window_open as analysis_window_open;
pub use self::lag::status_lag_annotation;
pub use self::phase::PhasePlanner;
pub use self::queue::Priority;
use self::queue::State;
use self::refresh::{refresh_due, refresh_hash};
use lekiwi_core::RobotKey;
use lekiwi_liveness::holder::next_epoch;
use lekiwi_metrics::Metrics;

/// What a robot told us at connect time.
#[derive(Clone, Debug, Default)]
pub struct ConnectInfo {
    /// `websocket` or `poll`.
    pub protocol: &'static str,
    /// Agent software version.
    pub agent_version: String,
    /// Digest of the agent build (validated by `rules::sanitize`), `status.agentDigest`.
    pub agent_digest: Option<String>,
    /// Release it runs, written to `status.currentRelease`.
    pub release: Option<Release>,
    /// Its health verdict at connect, if it sent one.
    pub health: Option<Health>,
    /// Its teleoperation verdict at connect, if it sent one.
    pub teleoperation: Option<Teleoperation>,
    /// Hostname, OS, kernel, CPUs and memory, written to `status.system`.
    pub system: SystemFacts,
    /// The peer address the connection came from, written to `status.address`.
    pub address: Option<String>,
}

/// What a heartbeat carries that matters for status.
#[derive(Clone, Debug, Default)]
pub struct HeartbeatInfo {
    /// Release it runs now; a change is written at once.
    pub release: Option<Release>,
    /// Its health verdict; a change is written at once.
    pub health: Option<Health>,
    /// Its teleoperation verdict; a change of `active` is written at once.
    pub teleoperation: Option<Teleoperation>,
    /// CPU, memory, temperature and battery readings, written with the next status refresh.
    pub vitals: Vitals,
    /// Round-trip time of the previous heartbeat, ms, as the agent measured it (analysis only).
    pub rtt_ms: Option<f64>,
}

/// How an agent's release update ended, as it reported it.
#[derive(Clone, Debug, PartialEq)]
pub struct UpdateOutcome {
    /// The release it was told to run.
    pub release: Release,
    /// `done`, `failed`, `rolled_back` or `cancelled`.
    pub phase: String,
    /// Its explanation.
    pub message: Option<String>,
    /// When the gateway got it.
    pub time: Timestamp,
}

/// What the gateway knows of one robot, and how far its status write has caught up.
#[derive(Clone, Debug)]
struct Entry {
    session: u64,
    /// The session's epoch (see [`lekiwi_liveness::holder`]), written to `status.sessionEpoch`.
    epoch: i64,
    connected: bool,
    info: ConnectInfo,
    connected_since: Timestamp,
    last_heartbeat: Timestamp,
    written_heartbeat: Option<Timestamp>,
    /// When the last write of this session landed: routine refreshes count their period from
    /// it (`written_heartbeat` is the heartbeat's own time, up to an interval earlier).
    written_at: Option<Timestamp>,
    /// The Robot's `resourceVersion` after this session's last write (0: none); see `writer`.
    written_version: u64,
    /// A hash of the robot's name fixing its point in each refresh period ([`refresh_due`]).
    refresh_hash: u64,
    teleoperation_since: Option<Timestamp>,
    vitals: Vitals,
    retries: u32,
    last_update: Option<Box<UpdateOutcome>>,
    /// Metrics before and after the last switch (kept across sessions, like `last_update`).
    analysis: analysis::Tracker,
    /// How the latest agent update went (kept across sessions, like `last_update`).
    agent_update: Option<Box<AgentUpdateOutcome>>,
    /// The API server refused this session's full status: write presence facts only.
    presence_only: bool,
    /// A session of a robot last written as disconnected, not written yet: its first write
    /// waits until it has lasted [`SETTLE`] (or something else must be written).
    settling: bool,
    /// The robot's status named another gateway when this session opened, and this gateway's
    /// Robot watch has not shown a write of this session yet: the gateway claims it in its
    /// Lease (see [`claims`]).
    moved: bool,
    /// Seconds left before this session's end is written (see [`agent::wait_for_restart`]),
    /// or, connected, before the session that followed such an end is written without the
    /// agent's report of its update (see [`agent::restarted_into_update`]).
    restart_grace: u8,
}

/// How long a new session of a robot shown as disconnected must last before it is written as
/// connected (see `State::known_offline`).
pub const SETTLE: std::time::Duration = std::time::Duration::from_secs(1);

/// Settings of the presence tracker and its writer.
#[derive(Clone, Debug)]
pub struct PresenceConfig {
    /// This gateway's name (also its Lease's name), written to `status.gateway`.
    pub gateway: String,
    /// Refresh `lastHeartbeatTime` at most this often when nothing else changes.
    pub status_refresh: Duration,
    /// A polling robot that has not polled for this long is Offline.
    pub poll_grace: Duration,
    /// Sustained status writes per second (the start, when `adaptive`).
    pub qps: f64,
    /// Bounds within which the rate adapts to the API server's answers; `None`: fixed at `qps`.
    pub adaptive: Option<RateBounds>,
    /// Burst of status writes.
    pub burst: u32,
    /// Writes in flight at once.
    pub concurrency: usize,
}

/// The presence tracker; cheap to clone.
#[derive(Clone)]
// shape: what sessions tell it here; writer.rs the status writer, phase.rs the phase it writes,
// claims.rs the robots it claims, agent.rs agent updates, lag.rs how late its writes run.
pub struct Presence {
    state: Arc<Mutex<State>>,
    notify: Arc<Notify>,
    /// Wakes the Lease renewal when a robot moved here (see [`Presence::claims`]).
    claims_changed: Arc<Notify>,
    config: Arc<PresenceConfig>,
    metrics: Metrics,
    /// Set once the gateway's Robot cache is ready: status writes then carry the phase too.
    planner: Arc<std::sync::OnceLock<Arc<PhasePlanner>>>,
    /// The robots other gateways' Leases list as marked `Unknown` (see [`claims`]); empty until
    /// their watch ([`crate::peers::watch`]) fills it.
    peers: crate::peers::Peers,
}

impl Presence {
    /// An empty tracker.
    pub fn new(config: PresenceConfig, metrics: Metrics) -> Self {
        Self {
            state: Arc::default(),
            notify: Arc::default(),
            claims_changed: Arc::default(),
            config: Arc::new(config),
            metrics,
            planner: Arc::default(),
            peers: crate::peers::Peers::default(),
        }
    }

    fn with_state<T>(&self, f: impl FnOnce(&mut State) -> T) -> T {
        let mut state = self.state.lock().unwrap_or_else(|p| p.into_inner());
        let out = f(&mut state);
        for priority in Priority::ALL {
            let len = state.queues[priority.index()].len();
            let priority = priority.label();
            let labels = lekiwi_metrics::PriorityLabels { priority };
            self.metrics
                .gateway
                .status_queue
                .get_or_create(&labels)
                .set(len as i64);
        }
        out
    }

    fn wake(&self) {
        self.notify.notify_one();
    }

    /// A session of `key` with session epoch `epoch` started.
    pub fn connect(&self, key: &RobotKey, session: u64, epoch: i64, info: ConnectInfo) {
        self.connect_moved(key, session, epoch, info, false);
    }

    /// A session of `key` started; `moved` when the robot's status names another gateway: its
    /// write then goes before every other transition (first of all when the status shows the
    /// robot `Unknown` or `Offline`), and the gateway's Lease claims the robot until then.
    pub fn connect_moved(
        &self,
        key: &RobotKey,
        session: u64,
        epoch: i64,
        info: ConnectInfo,
        moved: bool,
    ) {
        let now = Timestamp::now();
        let queue = self.with_state(|s| {
            let teleoperation_since = info.teleoperation.as_ref().map(|_| now);
            // Keep the last update's outcome: rollouts read it, and a manager that stops
            // sending a field makes server-side apply drop it.
            let old = s.robots.get(key);
            let restarted = old.is_some_and(|e| agent::restarted_into_update(e));
            let last_update = old.and_then(|e| e.last_update.clone());
            let cached = self.cached_robot(key);
            // Shown gone although it connected: its write goes first (see `shown_gone`).
            let gone = moved && cached.as_ref().is_some_and(|r| self.gone_or_marked(key, r));
            let analysis = analysis::Tracker::at_connect(
                old.map(|e| (&e.analysis, e.info.release.as_ref())),
                cached.as_ref().and_then(|r| r.status.as_ref()),
                info.release.as_ref(),
                cached.as_deref().and_then(analysis::Asked::of).as_ref(),
                now,
            );
            s.robots.insert(
                key.clone(),
                Box::new(Entry {
                    session,
                    epoch,
                    connected: true,
                    info,
                    connected_since: now,
                    last_heartbeat: now,
                    written_heartbeat: None,
                    written_at: None,
                    written_version: 0,
                    refresh_hash: refresh_hash(key),
                    teleoperation_since,
                    vitals: Vitals::default(),
                    retries: 0,
                    last_update,
                    analysis,
                    agent_update: old.and_then(|e| e.agent_update.clone()),
                    presence_only: false,
                    settling: s.known_offline.contains(key) && !moved,
                    moved,
                    restart_grace: if restarted {
                        agent::REPORT_WAIT_SECONDS
                    } else {
                        0
                    },
                }),
            );
            let queue = if gone {
                Some(Priority::Gone)
            } else if moved {
                Some(Priority::Move)
            } else if restarted {
                // Written with the agent's report of its update, which follows at once.
                None
            } else {
                (!s.known_offline.contains(key)).then_some(Priority::High)
            };
            if let Some(priority) = queue {
                s.enqueue(key, priority);
            }
            queue
        });
        if moved {
            // Which queue a moved robot starts in is what decides how soon it is written.
            let queue = queue.map(Priority::label);
            tracing::debug!(robot = %key, ?queue, "the robot moved here; claiming it");
            self.claims_changed.notify_one();
        }
        self.wake();
    }

    /// A heartbeat of the session `session`: kept in memory; written at once only if the
    /// release, health or teleoperation changed.
    pub fn heartbeat(&self, key: &RobotKey, session: u64, hb: HeartbeatInfo) {
        let now = Timestamp::now();
        let changed = self.with_state(|s| {
            let Some(e) = s.live_session(key, session) else {
                return false;
            };
            e.last_heartbeat = now;
            e.vitals = hb.vitals;
            e.analysis.record(&e.vitals, hb.rtt_ms, now);
            let mut changed = false;
            if hb.release.is_some() && hb.release != e.info.release {
                // A switch within the session: its window opens now unless the `done` of a
                // command opened it already (a command of an earlier session, or none).
                if let (Some(_), Some(release)) = (&e.info.release, &hb.release) {
                    let asked = self.asked(key);
                    e.analysis.switched(release.clone(), now, asked.as_ref());
                }
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
                let asked = self.asked(key);
                e.analysis
                    .switched(outcome.release.clone(), outcome.time, asked.as_ref());
            }
            e.last_update = Some(Box::new(outcome));
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
            // A poll is no session the Robot watch can end: its epoch is just its time.
            Act::Connect => self.connect(key, 0, next_epoch(Timestamp::now(), None), info),
            Act::Wake => self.wake(),
            Act::Nothing => {}
        }
    }

    /// The session `session` ended; ignored if a newer session already took over.
    pub fn disconnect(&self, key: &RobotKey, session: u64) {
        let done = self.with_state(|s| {
            let Some(e) = s.live_session(key, session) else {
                return false;
            };
            e.connected = false;
            let unwritten = e.settling && !s.queued.contains_key(key);
            self.metrics.per_robot.forget(&key.namespace, &key.name);
            if unwritten {
                // Never written as connected, and the status still says disconnected.
                s.robots.remove(key);
                return false;
            }
            if !s.queued.contains_key(key) && agent::wait_for_restart(s, key) {
                return false;
            }
            s.enqueue(key, Priority::High);
            true
        });
        if done {
            self.wake();
        }
    }

    /// The session `session` ended because another gateway's later session holds the robot
    /// now: its entry goes without a write, the status is that gateway's.
    pub fn forget(&self, key: &RobotKey, session: u64) {
        self.with_state(|s| {
            if s.robots.get(key).is_some_and(|e| e.session == session) {
                s.robots.remove(key);
                s.queued.remove(key);
                self.metrics.per_robot.forget(&key.namespace, &key.name);
            }
        });
    }

    /// Robots waiting for a write.
    pub fn queued(&self) -> usize {
        self.with_state(|s| s.queued.len())
    }

    /// When each of `keys` last sent a heartbeat (or a legacy poll) in a session this gateway
    /// holds now, in the same order; `None` for a robot it does not hold. Its status carries
    /// that time only once per refresh period (see [`refresh_due`]); this is the live one. One
    /// lock for the whole list.
    pub fn last_heartbeats<'a>(
        &self,
        keys: impl IntoIterator<Item = &'a RobotKey>,
    ) -> Vec<Option<Timestamp>> {
        let state = self.state.lock().unwrap_or_else(|p| p.into_inner());
        keys.into_iter()
            .map(|k| {
                let e = state.robots.get(k).filter(|e| e.connected)?;
                Some(e.last_heartbeat)
            })
            .collect()
    }

    /// Number of robots connected right now.
    pub fn connected(&self) -> usize {
        self.with_state(|s| s.robots.values().filter(|e| e.connected).count())
    }

    /// Queues routine refreshes and the outcomes of analysis windows, ends silent polling
    /// sessions and stale claims, and every [`claims::GONE_SWEEP`] puts first the robots the
    /// Robot cache shows gone under their live session here; call every second.
    pub fn tick(&self) {
        let now = Timestamp::now();
        let refresh =
            jiff::SignedDuration::try_from(self.config.status_refresh).unwrap_or_default();
        let poll_grace = jiff::SignedDuration::try_from(self.config.poll_grace).unwrap_or_default();
        let settle = jiff::SignedDuration::try_from(SETTLE).unwrap_or_default();
        let queued = self.with_state(|s| {
            let mut due = Vec::new();
            for (key, e) in s.robots.iter_mut() {
                claims::end_stale_claim(e, now);
                if agent::grace_ran_out(e) {
                    due.push((key.clone(), Priority::High));
                    continue;
                }
                if !e.connected {
                    continue;
                }
                if e.settling && now.duration_since(e.connected_since) >= settle {
                    e.settling = false;
                    due.push((key.clone(), Priority::High));
                    continue;
                }
                if e.info.protocol == "poll" && now.duration_since(e.last_heartbeat) > poll_grace {
                    e.connected = false;
                    due.push((key.clone(), Priority::High));
                } else if e.written_heartbeat.is_some_and(|w| e.last_heartbeat > w)
                    && e.written_at
                        .is_some_and(|at| refresh_due(e, at, now, refresh))
                {
                    due.push((key.clone(), Priority::Low));
                } else if e.analysis.outcome_due()
                    && !s.queued.contains_key(key)
                    && !s.writing.contains_key(key)
                {
                    // The write a rollout judges; one in flight or waiting may hold it already
                    // (`Presence::written` tells).
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
        self.sweep_shown_gone_when_due();
    }
}
