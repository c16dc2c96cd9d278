//! The agent's run loop: one task on a single-threaded runtime that samples telemetry, checks
//! for teleoperation, hears the health checks' verdict, keeps the outbox, and holds (or re-establishes) the gateway session.
//!
//! Everything durable goes through the [`Outbox`] first; the session only sends what the outbox
//! holds and deletes it when acknowledged, so a dead gateway or a killed agent loses nothing.
//! The loop ([`driver`]) wakes up for one thing at a time and hands it to a named step: the
//! connection's life ([`link`]), one connected session ([`session`]), commands and deployments
//! ([`commands`]), the local status endpoint ([`status`]).

mod agent_update;
mod commands;
mod driver;
mod link;
mod session;
mod status;
#[cfg(test)]
mod tests;

use std::future::Future;

use lekiwi_protocol::{AgentMessage, Health, PROTOCOL_VERSION, Release, Sample, Severity};
use tracing::info;

use crate::config::Config;
use crate::connection::Credentials as ConnCredentials;
use crate::discovery::{Advertiser, StatusSnapshot};
use crate::outbox::{Lane, Outbox};
use crate::release::{GatewayAccess, Progress, Releases};
use crate::state::{self, Credentials};
use crate::telemetry::Telemetry;
use crate::teleop::{Detector, Verdict};

use commands::Deploying;

/// Why the agent stopped.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The state directory is unusable.
    #[error(transparent)]
    State(#[from] state::Error),
    /// The outbox is unusable.
    #[error(transparent)]
    Outbox(#[from] crate::outbox::Error),
    /// The configuration is unusable.
    #[error(transparent)]
    Config(#[from] crate::config::Error),
    /// The status endpoint cannot listen.
    #[error("status endpoint {addr}: {source}")]
    StatusListen {
        /// The configured `statusListen` address.
        addr: std::net::SocketAddr,
        /// Why binding it failed (in use, no permission).
        source: std::io::Error,
    },
    /// The release store is unusable.
    #[error(transparent)]
    Release(#[from] crate::release::Error),
    /// Neither saved credentials nor an enrollment token.
    #[error(
        "not enrolled: no credentials in {0} and no enrollment token \
         (set enrollmentTokenFile, --enrollment-token-file or LEKIWI_ENROLLMENT_TOKEN_FILE; \
         or give it a robot's own token with `lekiwi-agent adopt`)"
    )]
    NotEnrolled(std::path::PathBuf),
}

/// Version of this agent, as sent in `hello` and shown on the status endpoint.
pub const AGENT_VERSION: &str = env!("CARGO_PKG_VERSION");

/// Telemetry samples per durable message at most; more are split into several.
const SAMPLES_PER_MESSAGE: usize = 1000;

/// The agent: its state directory (credentials, outbox, releases), its sensors, and what it
/// publishes locally. [`Agent::run`] drives it.
// shape: one run loop's state, its methods by concern: driver.rs the loop, link.rs the connection,
// session.rs a session, commands.rs and agent_update.rs the commands, status.rs what it publishes
// locally.
pub struct Agent {
    config: Config,
    outbox: Outbox,
    telemetry: Telemetry,
    detector: Detector,
    teleop: Verdict,
    /// The latest health verdict of the periodic checks ([`crate::health`]); `None` once their
    /// task is gone (the last verdict is then kept in `last_health`).
    health: Option<tokio::sync::watch::Receiver<Health>>,
    last_health: Health,
    /// The host process's latest reading, for heartbeat vitals.
    host_stats: tokio::sync::watch::Receiver<Option<crate::health::HostStats>>,
    status: tokio::sync::watch::Sender<StatusSnapshot>,
    advertiser: Option<Advertiser>,
    /// Samples collected since the last telemetry message was queued.
    pending_samples: Vec<Sample>,
    /// Acknowledged sequence numbers not yet deleted from the outbox (deleted in batches).
    pending_acks: Vec<u64>,
    /// WebSocket bytes sent since the start, for the status endpoint.
    bytes_sent: u64,
    last_rtt_ms: Option<f64>,
    enrollment_token: Option<String>,
    /// Use the enrollment token next time (the robot's own token was refused).
    reenroll: bool,
    /// The release store, while no deployment task holds it.
    releases: Option<Releases>,
    /// The release `current` points at.
    current_release: Option<Release>,
    /// The deployment (or recovery) running now.
    deploying: Option<Deploying>,
    /// The next command, received while one was running (the latest wins).
    queued: Option<(String, lekiwi_protocol::Command)>,
    progress_tx: tokio::sync::mpsc::UnboundedSender<Progress>,
    progress_rx: tokio::sync::mpsc::UnboundedReceiver<Progress>,
    /// New credentials for the release store, while a task holds it.
    pending_access: Option<GatewayAccess>,
    /// An agent update switched `current`: the run loop ends so that the new build starts.
    restart_for_update: bool,
    /// `sha256:` digest of the build that runs (sent in `hello`), if it could be read.
    agent_digest: Option<String>,
}

/// The digest of the build that runs, from the state directory `state_dir` (see
/// [`Slots::identify_running`](crate::selfupdate::Slots::identify_running)); `None`, logged,
/// when it cannot be read.
async fn running_build(state_dir: &std::path::Path) -> Option<String> {
    let slots = crate::selfupdate::Slots::new(state_dir);
    let exe = match std::env::current_exe() {
        Ok(exe) => exe,
        Err(e) => {
            tracing::warn!(error = %e, "cannot tell which binary runs; hello carries no agent digest");
            return None;
        }
    };
    let version = crate::selfupdate::version();
    let digest = tokio::task::spawn_blocking(move || slots.identify_running(&exe, version))
        .await
        .ok()
        .flatten();
    if digest.is_none() {
        tracing::warn!("cannot read the running agent build; hello carries no agent digest");
    }
    digest
}

/// How [`Agent::run`] ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stopped {
    /// Shutdown was asked for.
    Shutdown,
    /// An agent update switched `current`: exit with
    /// [`EXIT_UPDATED`](crate::selfupdate::EXIT_UPDATED) so the service manager starts it.
    Updated,
}

impl Agent {
    /// This agent with `telemetry` as its sampler instead of this machine's (the fleet
    /// simulator's robots, see [`Telemetry::synthetic`]).
    pub fn with_telemetry(mut self, telemetry: Telemetry) -> Self {
        self.telemetry = telemetry;
        self
    }

    /// Opens the state directory and the outbox and starts the local status endpoint and the
    /// mDNS advertisement.
    pub async fn new(config: Config) -> Result<Self, Error> {
        state::ensure_dir(&config.state_dir)?;
        let enrollment_token = config.enrollment_token()?;
        let saved = state::load_credentials(&config.state_dir)?;
        if saved.is_none() && enrollment_token.is_none() {
            return Err(Error::NotEnrolled(config.state_dir.clone()));
        }
        let outbox = Outbox::open(&config.state_dir, config.outbox_max_bytes)?;
        let releases = open_releases(&config, saved.as_ref())?;
        let current_release = releases.current();
        let (progress_tx, progress_rx) = tokio::sync::mpsc::unbounded_channel();
        let telemetry = Telemetry::new(&config);
        let mut detector = Detector::new(&config);
        let teleop = detector.check();
        let checks = crate::health::spawn(&config);
        let last_health = checks.health.borrow().clone();
        let snapshot = StatusSnapshot {
            robot: config.robot_name.clone(),
            agent_version: crate::selfupdate::version().to_owned(),
            release: current_release.clone(),
            gateway: config.gateway.clone(),
            connected: false,
            teleoperation: Some(teleop.to_wire()),
            outbox_pending: outbox.depth()?.messages,
            last_rtt_ms: None,
            bytes_sent: 0,
            started_at_ms: lekiwi_protocol::now_ms(),
        };
        let (status, advertiser) = status::start(&config, snapshot).await?;
        let agent_digest = running_build(&config.state_dir).await;
        Ok(Self {
            config,
            outbox,
            telemetry,
            detector,
            teleop,
            health: Some(checks.health),
            last_health,
            host_stats: checks.host,
            status,
            advertiser,
            pending_samples: Vec::new(),
            pending_acks: Vec::new(),
            bytes_sent: 0,
            last_rtt_ms: None,
            enrollment_token,
            reenroll: false,
            releases: Some(releases),
            current_release,
            deploying: None,
            queued: None,
            progress_tx,
            progress_rx,
            pending_access: None,
            restart_for_update: false,
            agent_digest,
        })
    }

    /// Follows what the agent publishes on its status endpoint.
    pub fn status(&self) -> tokio::sync::watch::Receiver<StatusSnapshot> {
        self.status.subscribe()
    }

    /// Runs until `shutdown` completes; then queues what is pending and closes the session.
    pub async fn run(self, shutdown: impl Future<Output = ()>) -> Result<Stopped, Error> {
        let connect = link::websocket(&self.config);
        self.run_with(shutdown, connect).await
    }

    /// The credentials for the next connection, and whether they are the enrollment token.
    fn credentials(&self) -> Result<(ConnCredentials, bool), Error> {
        let saved = state::load_credentials(&self.config.state_dir)?;
        let own = |c: Credentials| {
            Ok((
                ConnCredentials {
                    token: c.token,
                    robot: c.robot,
                },
                false,
            ))
        };
        match (saved, &self.enrollment_token) {
            (Some(c), None) => own(c),
            (Some(c), Some(_)) if !self.reenroll => own(c),
            (_, Some(token)) => Ok((
                ConnCredentials {
                    token: token.clone(),
                    robot: self.config.robot_name.clone(),
                },
                true,
            )),
            (None, None) => Err(Error::NotEnrolled(self.config.state_dir.clone())),
        }
    }

    fn hello(&mut self) -> Result<AgentMessage, Error> {
        let last = self.outbox.last_acked_seq()?;
        Ok(AgentMessage::Hello {
            protocol_version: PROTOCOL_VERSION,
            agent_version: crate::selfupdate::version().to_owned(),
            agent_digest: self.agent_digest.clone(),
            system: crate::telemetry::system_facts(),
            current_release: self.current_release.clone(),
            last_acked_seq: (last > 0).then_some(last),
            health: Some(self.health_now()),
            teleoperation: Some(self.teleop.to_wire()),
            features: vec![lekiwi_protocol::FEATURE_UPDATE_AGENT.to_owned()],
        })
    }

    /// The latest health verdict.
    fn health_now(&mut self) -> Health {
        if let Some(rx) = &self.health {
            self.last_health = rx.borrow().clone();
        }
        self.last_health.clone()
    }

    /// The readings for a heartbeat: the machine's, and the host process's when it runs.
    fn vitals(&mut self) -> lekiwi_protocol::Vitals {
        let host = *self.host_stats.borrow();
        lekiwi_protocol::Vitals {
            host_rss_bytes: host.map(|h| h.rss_bytes),
            host_cpu_percent: host.and_then(|h| h.cpu_percent),
            ..self.telemetry.vitals()
        }
    }

    /// Queues an event durably; returns its sequence number.
    pub fn event(
        &mut self,
        lane: Lane,
        kind: &str,
        severity: Severity,
        message: String,
        data: serde_json::Value,
    ) -> Result<u64, Error> {
        let ts_ms = lekiwi_protocol::now_ms();
        Ok(self.outbox.push(lane, ts_ms, |seq| AgentMessage::Event {
            seq,
            ts_ms,
            kind: kind.to_owned(),
            severity,
            message,
            data,
        })?)
    }

    /// Queues a deployment progress report durably, on the critical lane.
    fn queue_progress(&mut self, p: &Progress) -> Result<(), Error> {
        let ts = lekiwi_protocol::now_ms();
        self.outbox
            .push(Lane::Critical, ts, |seq| p.to_message(seq))?;
        Ok(())
    }

    fn flush_samples(&mut self) -> Result<(), Error> {
        while !self.pending_samples.is_empty() {
            let n = self.pending_samples.len().min(SAMPLES_PER_MESSAGE);
            let samples: Vec<Sample> = self.pending_samples.drain(..n).collect();
            self.outbox
                .push(Lane::Telemetry, lekiwi_protocol::now_ms(), |seq| {
                    AgentMessage::Telemetry { seq, samples }
                })?;
        }
        Ok(())
    }

    fn flush_acks(&mut self) -> Result<(), Error> {
        if !self.pending_acks.is_empty() {
            let acks = std::mem::take(&mut self.pending_acks);
            self.outbox.ack(&acks)?;
        }
        Ok(())
    }

    /// Runs the teleoperation detector; a change is queued as a critical event. Returns
    /// whether the verdict changed (the gateway then hears it in a heartbeat at once).
    fn on_teleop_check(&mut self) -> Result<bool, Error> {
        let verdict = self.detector.check();
        let changed = verdict.active != self.teleop.active;
        if changed {
            let kind = if verdict.active {
                "teleoperation_started"
            } else {
                "teleoperation_stopped"
            };
            info!(score = verdict.score, indicators = ?verdict.indicators, "{kind}");
            let data = serde_json::to_value(&verdict).unwrap_or_default();
            let message = format!(
                "score {:.2} ({})",
                verdict.score,
                verdict.indicators.join(", ")
            );
            self.teleop = verdict;
            self.event(Lane::Critical, kind, Severity::Info, message, data)?;
        } else {
            self.teleop = verdict;
        }
        Ok(changed)
    }
}

/// Opens the release store with the saved credentials (or none yet, before enrollment).
fn open_releases(config: &Config, saved: Option<&Credentials>) -> Result<Releases, Error> {
    let access = GatewayAccess::from_gateway_url(
        &config.gateway,
        saved.map(|c| c.token.clone()).unwrap_or_default(),
        saved.map_or(config.robot_name.clone(), |c| c.robot.clone()),
        config.ca_file.clone(),
    )?;
    Ok(Releases::open(config, access)?)
}
