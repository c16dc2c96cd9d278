//! The agent's run loop: one task on a single-threaded runtime that samples telemetry, checks
//! for teleoperation, keeps the outbox, and holds (or re-establishes) the gateway session.
//!
//! Everything durable goes through the [`Outbox`] first; the session only sends what the outbox
//! holds and deletes it when acknowledged, so a dead gateway or a killed agent loses nothing.

use std::collections::BTreeMap;
use std::future::Future;
use std::pin::Pin;
use std::time::Duration;

use futures::{SinkExt, StreamExt};
use lekiwi_protocol::{
    AgentMessage, ErrorCode, Health, MAX_FRAME_BYTES, PROTOCOL_VERSION, Release, Sample,
    ServerMessage, Severity, decode, encode,
};
use tokio::time::{Instant, sleep_until};
use tokio_tungstenite::tungstenite::Message;
use tracing::{debug, error, info, warn};

use crate::backoff::Backoff;
use crate::config::Config;
use crate::connection::{ConnectError, Credentials as ConnCredentials, Socket, Welcome};
use crate::discovery::{Advertiser, StatusSnapshot};
use crate::outbox::{Lane, Outbox};
use crate::release::{GatewayAccess, Outcome, Phase, Progress, Releases};
use crate::state::{self, Credentials};
use crate::telemetry::Telemetry;
use crate::teleop::{Detector, Verdict};

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
        /// The address.
        addr: std::net::SocketAddr,
        /// The cause.
        source: std::io::Error,
    },
    /// The release store is unusable.
    #[error(transparent)]
    Release(#[from] crate::release::Error),
    /// Neither saved credentials nor an enrollment token.
    #[error(
        "not enrolled: no credentials in {0} and no enrollment token \
         (set enrollmentTokenFile, --enrollment-token-file or LEKIWI_ENROLLMENT_TOKEN_FILE)"
    )]
    NotEnrolled(std::path::PathBuf),
}

/// Version of this agent.
pub const AGENT_VERSION: &str = env!("CARGO_PKG_VERSION");

/// Durable messages in flight beyond the window, reserved for the critical lane.
const CRITICAL_RESERVE: usize = 8;
/// Acknowledgements are deleted from the outbox in batches of at most this many...
const ACK_BATCH: usize = 128;
/// ...or after this long.
const ACK_FLUSH: Duration = Duration::from_millis(250);
/// The status endpoint's numbers are refreshed at most this often (and on (dis)connection).
const STATUS_EVERY: Duration = Duration::from_secs(1);
/// Missing heartbeat acks for this many intervals ends the session.
const DEAD_INTERVALS: u32 = 3;

/// WebSocket bytes of a client text frame carrying `len` payload bytes (header + mask key).
fn ws_frame_bytes(len: usize) -> u64 {
    let header = match len {
        0..=125 => 2,
        126..=65535 => 4,
        _ => 10,
    };
    (len + header + 4) as u64
}

type Connecting = Pin<Box<dyn Future<Output = Result<(Socket, Welcome), ConnectError>>>>;

/// A live session.
struct Session {
    ws: Socket,
    welcome: Welcome,
    started: Instant,
    last_rx: Instant,
    next_heartbeat: Instant,
    /// Highest sequence sent per lane (messages after it are next).
    cursor: [u64; 3],
    /// Sent, not yet acknowledged: seq and when it was sent.
    in_flight: BTreeMap<u64, Instant>,
    /// Send tokens (durable messages), refilled at `rate` per second.
    tokens: f64,
    rate: f64,
    last_refill: Instant,
    /// No durable sends before this (after the gateway refused one).
    hold_until: Option<Instant>,
}

impl Session {
    fn new(ws: Socket, welcome: Welcome) -> Self {
        let now = Instant::now();
        // Stay well under the gateway's limit: heartbeats and replays share it.
        let rate = (f64::from(welcome.max_messages_per_second) * 0.5).max(1.0);
        Self {
            ws,
            welcome,
            started: now,
            last_rx: now,
            next_heartbeat: now,
            cursor: [0; 3],
            in_flight: BTreeMap::new(),
            tokens: rate.min(32.0),
            rate,
            last_refill: now,
            hold_until: None,
        }
    }

    fn refill(&mut self, now: Instant) {
        let burst = self.rate.min(32.0);
        self.tokens = (self.tokens
            + now.duration_since(self.last_refill).as_secs_f64() * self.rate)
            .min(burst);
        self.last_refill = now;
    }
}

/// Takes back messages sent more than a heartbeat interval ago and still unacknowledged, so
/// they are sent again (PROTOCOL.md §6 rule 3).
fn resend_unacknowledged(session: &mut Session) {
    let stale_before = Instant::now() - session.welcome.heartbeat_interval;
    let stale: Vec<u64> = session
        .in_flight
        .iter()
        .filter(|(_, sent)| **sent < stale_before)
        .map(|(seq, _)| *seq)
        .collect();
    if let Some(first) = stale.first() {
        warn!(
            count = stale.len(),
            first, "no ack within a heartbeat interval; resending"
        );
        for seq in &stale {
            session.in_flight.remove(seq);
        }
        for c in &mut session.cursor {
            *c = (*c).min(first - 1);
        }
    }
}

/// The agent.
pub struct Agent {
    config: Config,
    outbox: Outbox,
    telemetry: Telemetry,
    detector: Detector,
    teleop: Verdict,
    status: tokio::sync::watch::Sender<StatusSnapshot>,
    advertiser: Option<Advertiser>,
    pending_samples: Vec<Sample>,
    pending_acks: Vec<u64>,
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
}

/// A deployment task and what it is for.
struct Deploying {
    task: tokio::task::JoinHandle<(Releases, Option<Outcome>)>,
    /// Its command id (empty for a recovery) and release.
    command_id: String,
    release: Option<Release>,
    /// Later command ids for the same release (a reconnect re-sends the command): they get the
    /// same final report.
    aliases: Vec<String>,
}

impl Agent {
    /// Opens the state directory and the outbox and starts the local status endpoint and the
    /// mDNS advertisement.
    pub async fn new(config: Config) -> Result<Self, Error> {
        state::ensure_dir(&config.state_dir)?;
        let enrollment_token = config.enrollment_token()?;
        if state::load_credentials(&config.state_dir)?.is_none() && enrollment_token.is_none() {
            return Err(Error::NotEnrolled(config.state_dir.clone()));
        }
        let outbox = Outbox::open(&config.state_dir, config.outbox_max_bytes)?;
        let saved = state::load_credentials(&config.state_dir)?;
        let releases = Releases::open(
            &config,
            GatewayAccess::from_gateway_url(
                &config.gateway,
                saved.as_ref().map(|c| c.token.clone()).unwrap_or_default(),
                saved
                    .as_ref()
                    .map_or(config.robot_name.clone(), |c| c.robot.clone()),
                config.ca_file.clone(),
            )?,
        )?;
        let current_release = releases.current();
        let (progress_tx, progress_rx) = tokio::sync::mpsc::unbounded_channel();
        let telemetry = Telemetry::new(&config);
        let mut detector = Detector::new(&config);
        let teleop = detector.check();
        let snapshot = StatusSnapshot {
            robot: config.robot_name.clone(),
            agent_version: AGENT_VERSION.to_owned(),
            release: current_release.clone(),
            gateway: config.gateway.clone(),
            connected: false,
            teleoperation: Some(teleop.to_wire()),
            outbox_pending: outbox.depth()?.messages,
            last_rtt_ms: None,
            bytes_sent: 0,
            started_at_ms: lekiwi_protocol::now_ms(),
        };
        let (status, status_rx) = tokio::sync::watch::channel(snapshot.clone());
        let mut status_port = 0;
        if let Some(addr) = config.status_addr() {
            let listener = tokio::net::TcpListener::bind(addr)
                .await
                .map_err(|source| Error::StatusListen { addr, source })?;
            status_port = listener.local_addr().map(|a| a.port()).unwrap_or_default();
            info!(addr = %listener.local_addr().map(|a| a.to_string()).unwrap_or_default(), "status endpoint listening");
            tokio::spawn(crate::discovery::serve_status(listener, status_rx));
        }
        let advertiser = if config.mdns {
            match Advertiser::start(&snapshot, status_port) {
                Ok(a) => Some(a),
                Err(e) => {
                    warn!(error = %e, "mDNS advertisement unavailable; going on without it");
                    None
                }
            }
        } else {
            None
        };
        Ok(Self {
            config,
            outbox,
            telemetry,
            detector,
            teleop,
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
        })
    }

    /// Follows what the agent publishes on its status endpoint.
    pub fn status(&self) -> tokio::sync::watch::Receiver<StatusSnapshot> {
        self.status.subscribe()
    }

    /// The robot's name as the gateway knows it, once enrolled.
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
            agent_version: AGENT_VERSION.to_owned(),
            system: crate::telemetry::system_facts(),
            current_release: self.current_release.clone(),
            last_acked_seq: (last > 0).then_some(last),
            health: Some(Health {
                healthy: true,
                message: None,
            }),
            teleoperation: Some(self.teleop.to_wire()),
        })
    }

    /// Queues an event durably.
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

    fn flush_samples(&mut self) -> Result<(), Error> {
        while !self.pending_samples.is_empty() {
            let n = self.pending_samples.len().min(1000);
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

    fn publish_status(&mut self, connected: bool) {
        let depth = self.outbox.depth().map(|d| d.messages).unwrap_or_default();
        let teleop = self.teleop.to_wire();
        let (bytes, rtt) = (self.bytes_sent, self.last_rtt_ms);
        self.status.send_modify(|s| {
            s.connected = connected;
            s.teleoperation = Some(teleop);
            s.outbox_pending = depth;
            s.bytes_sent = bytes;
            s.last_rtt_ms = rtt;
        });
    }

    async fn send(&mut self, session: &mut Session, frame: String) -> bool {
        let bytes = ws_frame_bytes(frame.len());
        match tokio::time::timeout(
            Duration::from_secs(10),
            session.ws.send(Message::text(frame)),
        )
        .await
        {
            Ok(Ok(())) => {
                self.bytes_sent += bytes;
                true
            }
            Ok(Err(e)) => {
                warn!(error = %e, "send failed");
                false
            }
            Err(_) => {
                warn!("send timed out");
                false
            }
        }
    }

    async fn send_heartbeat(&mut self, session: &mut Session) -> bool {
        let hb = AgentMessage::Heartbeat {
            sent_at_ms: lekiwi_protocol::now_ms(),
            rtt_ms: self.last_rtt_ms,
            vitals: self.telemetry.vitals(),
            current_release: self.current_release.clone(),
            health: Some(Health {
                healthy: true,
                message: None,
            }),
            teleoperation: Some(self.teleop.to_wire()),
        };
        session.next_heartbeat = Instant::now() + session.welcome.heartbeat_interval;
        self.send(session, encode(&hb)).await
    }

    /// Sends queued durable messages while the window and the rate allow; returns false when
    /// the connection failed.
    async fn pump(&mut self, session: &mut Session) -> Result<bool, Error> {
        let now = Instant::now();
        if session.hold_until.is_some_and(|t| now < t) {
            return Ok(true);
        }
        session.hold_until = None;
        session.refill(now);
        let window = self.config.outbox_window as usize;
        for lane in Lane::ALL {
            let limit = match lane {
                Lane::Critical => window + CRITICAL_RESERVE,
                _ => window,
            };
            while session.in_flight.len() < limit && session.tokens >= 1.0 {
                let want = (limit - session.in_flight.len()).min(session.tokens as usize);
                let batch = self
                    .outbox
                    .next_in_lane(lane, session.cursor[lane as usize], want)?;
                if batch.is_empty() {
                    break;
                }
                for entry in batch {
                    session.cursor[lane as usize] = entry.seq;
                    if session.in_flight.insert(entry.seq, now).is_some() {
                        continue;
                    }
                    session.tokens -= 1.0;
                    if !self.send(session, entry.frame).await {
                        return Ok(false);
                    }
                }
            }
        }
        Ok(true)
    }

    /// When the pump should run again, if it is waiting for tokens or a hold.
    fn pump_wake(&self, session: &Session) -> Option<Instant> {
        if let Some(t) = session.hold_until {
            return Some(t);
        }
        (session.tokens < 1.0)
            .then(|| session.last_refill + Duration::from_secs_f64(1.0 / session.rate))
    }

    fn on_welcome(&mut self, session: &Session, enrolling: bool) -> Result<(), Error> {
        let welcome = &session.welcome;
        if let Some(token) = &welcome.robot_token {
            state::save_credentials(
                &self.config.state_dir,
                &Credentials {
                    robot: welcome.robot.clone(),
                    token: token.clone(),
                },
            )?;
            info!(robot = %welcome.robot, "enrolled; the robot's own token is saved");
            let access = GatewayAccess::from_gateway_url(
                &self.config.gateway,
                token.clone(),
                welcome.robot.clone(),
                self.config.ca_file.clone(),
            )?;
            match self.releases.as_mut() {
                Some(r) => r.set_gateway(access)?,
                None => self.pending_access = Some(access),
            }
            self.reenroll = false;
        } else if enrolling {
            warn!("enrolled without a robot token in welcome; will enroll again next time");
        }
        if let Some(stored) = welcome.stored_seq
            && let Some(renumbered) = self.outbox.renumber_after(stored)?
        {
            warn!(
                stored,
                renumbered,
                "the gateway holds later sequence numbers than this state directory \
                 (lost or restored); queued messages renumbered after them"
            );
        }
        let dropped = self.outbox.take_dropped()?;
        if dropped.telemetry + dropped.events > 0 {
            self.event(
                Lane::Event,
                "outbox_overflow",
                Severity::Warning,
                format!(
                    "the outbox reached its bound of {} bytes while offline: dropped {} telemetry batches and {} events, oldest first",
                    self.config.outbox_max_bytes, dropped.telemetry, dropped.events
                ),
                serde_json::json!({"telemetry": dropped.telemetry, "events": dropped.events}),
            )?;
        }
        Ok(())
    }

    /// Handles one frame from the gateway; returns the code of a fatal error, which ends the
    /// session.
    fn on_frame(&mut self, session: &mut Session, text: &str) -> Result<Option<ErrorCode>, Error> {
        let msg = match decode::<ServerMessage>(text, MAX_FRAME_BYTES) {
            Ok(m) => m,
            Err(e) => {
                warn!(error = %e, "undecodable frame from the gateway; ignored");
                return Ok(None);
            }
        };
        match msg {
            ServerMessage::Ack { seq } => {
                if session.in_flight.remove(&seq).is_some() {
                    self.pending_acks.push(seq);
                }
            }
            ServerMessage::HeartbeatAck { sent_at_ms, .. } => {
                let rtt = (lekiwi_protocol::now_ms() - sent_at_ms).max(0) as f64;
                self.last_rtt_ms = Some(rtt);
                debug!(rtt_ms = rtt, "heartbeat acknowledged");
            }
            ServerMessage::Error {
                code,
                message,
                fatal,
                seq,
            } => {
                if let Some(seq) = seq
                    && session.in_flight.remove(&seq).is_some()
                {
                    // Resend it (and what follows in its lane) after a pause.
                    for c in &mut session.cursor {
                        if *c >= seq {
                            *c = seq - 1;
                        }
                    }
                    let pause = if code == ErrorCode::RateLimited {
                        Duration::from_secs(1)
                    } else {
                        Duration::from_secs(2)
                    };
                    session.hold_until = Some(Instant::now() + pause);
                }
                if fatal {
                    warn!(?code, %message, "the gateway ends the session");
                    return Ok(Some(code));
                }
                warn!(?code, %message, ?seq, "the gateway refused a frame");
            }
            ServerMessage::Command {
                command_id,
                command,
            } => self.on_command(command_id, command)?,
            ServerMessage::Welcome { .. } => {
                warn!("a second welcome; ignored");
            }
        }
        Ok(None)
    }

    /// A command from the gateway: start it, or queue it behind the one running.
    fn on_command(
        &mut self,
        command_id: String,
        command: lekiwi_protocol::Command,
    ) -> Result<(), Error> {
        use lekiwi_protocol::Command;
        let target = match &command {
            Command::Deploy { release, .. } | Command::Rollback { release } => {
                Some(release.clone())
            }
            Command::Cancel => None,
        };
        info!(%command_id, ?command, "command received");
        if let Some(running) = self.deploying.as_mut() {
            if target.is_some() && running.release == target {
                // The same release again (a reconnect re-sends it): report to both ids.
                running.aliases.push(command_id);
                return Ok(());
            }
            match command {
                Command::Cancel => {
                    if let Some((queued_id, _)) = self.queued.take() {
                        self.report_final(
                            &queued_id,
                            Phase::Failed,
                            "cancelled before it started".into(),
                        )?;
                    }
                    // A running deployment finishes or rolls back by itself; it is not torn
                    // down half-way.
                    self.report_final(
                        &command_id,
                        Phase::Failed,
                        "a deployment in progress is not interrupted; it finishes or rolls back"
                            .into(),
                    )?;
                }
                other => {
                    if let Some((old, _)) = self.queued.replace((command_id, other)) {
                        self.report_final(
                            &old,
                            Phase::Failed,
                            "superseded by a newer command".into(),
                        )?;
                    }
                }
            }
            return Ok(());
        }
        match command {
            Command::Cancel => {
                self.report_final(&command_id, Phase::Done, "nothing to cancel".into())?
            }
            other => self.start_command(command_id, other),
        }
        Ok(())
    }

    fn report_final(
        &mut self,
        command_id: &str,
        phase: Phase,
        message: String,
    ) -> Result<(), Error> {
        let ts = lekiwi_protocol::now_ms();
        self.outbox
            .push(Lane::Critical, ts, |seq| AgentMessage::Progress {
                seq,
                command_id: command_id.to_owned(),
                phase: phase.as_str().to_owned(),
                percent: None,
                message,
            })?;
        Ok(())
    }

    /// Moves the release store into a task that runs `command`.
    fn start_command(&mut self, command_id: String, command: lekiwi_protocol::Command) {
        use lekiwi_protocol::Command;
        let Some(mut releases) = self.releases.take() else {
            return;
        };
        let tx = self.progress_tx.clone();
        let id = command_id.clone();
        let (release, task) = match command {
            Command::Deploy {
                release,
                manifest_url,
            } => (
                Some(release.clone()),
                tokio::spawn(async move {
                    let o = releases.deploy(&id, &release, &manifest_url, &tx).await;
                    (releases, Some(o))
                }),
            ),
            Command::Rollback { release } => (
                Some(release.clone()),
                tokio::spawn(async move {
                    let o = releases.rollback(&id, &release, &tx).await;
                    (releases, Some(o))
                }),
            ),
            Command::Cancel => {
                self.releases = Some(releases);
                return;
            }
        };
        self.deploying = Some(Deploying {
            task,
            command_id,
            release,
            aliases: Vec::new(),
        });
    }

    /// Runs the recovery of an interrupted deployment, if the journal has one.
    fn start_recovery(&mut self) {
        let Some(mut releases) = self.releases.take() else {
            return;
        };
        let tx = self.progress_tx.clone();
        self.deploying = Some(Deploying {
            task: tokio::spawn(async move {
                let o = releases.recover(&tx).await;
                (releases, o)
            }),
            command_id: String::new(),
            release: None,
            aliases: Vec::new(),
        });
    }

    /// A deployment task ended: take the store back, report to aliases, start what is queued.
    fn on_deploy_done(
        &mut self,
        joined: Result<(Releases, Option<Outcome>), tokio::task::JoinError>,
    ) -> Result<(), Error> {
        let Some(done) = self.deploying.take() else {
            return Ok(());
        };
        let (mut releases, outcome) = match joined {
            Ok(x) => x,
            Err(e) => {
                // The task panicked: the store's journal makes the next start recover.
                error!(error = %e, "deployment task failed; restart the agent to recover");
                return Ok(());
            }
        };
        if let Some(access) = self.pending_access.take() {
            releases.set_gateway(access)?;
        }
        self.current_release = releases.current();
        self.releases = Some(releases);
        if let Some(o) = &outcome {
            info!(
                command_id = %done.command_id,
                phase = %o.phase,
                bytes = o.bytes_downloaded,
                files_downloaded = o.files_downloaded,
                files_reused = o.files_reused,
                message = %o.message,
                "deployment finished"
            );
            for alias in &done.aliases {
                self.report_final(alias, o.phase, o.message.clone())?;
            }
        }
        let release = self.current_release.clone();
        self.status.send_modify(|s| s.release = release);
        if let Some(adv) = self.advertiser.as_mut() {
            let snapshot = self.status.borrow().clone();
            if let Err(e) = adv.update(&snapshot) {
                warn!(error = %e, "cannot update the mDNS advertisement");
            }
        }
        if let Some((id, cmd)) = self.queued.take() {
            self.start_command(id, cmd);
        }
        Ok(())
    }

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

    /// Runs until `shutdown` completes; then queues what is pending and closes the session.
    pub async fn run(mut self, shutdown: impl Future<Output = ()>) -> Result<(), Error> {
        tokio::pin!(shutdown);
        self.event(
            Lane::Event,
            "agent_started",
            Severity::Info,
            format!("lekiwi-agent {AGENT_VERSION} started"),
            serde_json::json!({"version": AGENT_VERSION}),
        )?;
        self.start_recovery();
        let mut backoff = Backoff::new(
            Duration::from_millis(self.config.backoff_initial_ms),
            Duration::from_millis(self.config.backoff_max_ms),
        );
        let connect_timeout = Duration::from_secs(self.config.connect_timeout_s);
        let teleop_every = Duration::from_secs_f64(self.config.teleop_interval_s);
        let batch_every = Duration::from_secs(self.config.telemetry_batch_interval_s);
        let mut next_teleop = Instant::now() + teleop_every;
        let mut next_batch = Instant::now() + batch_every;
        let mut next_ack_flush: Option<Instant> = None;
        let mut reconnect_at = Instant::now();
        let mut connecting: Option<(Connecting, bool)> = None;
        let mut session: Option<Session> = None;
        let far = Duration::from_secs(86_400);
        let mut published_connected = false;
        let mut next_status = Instant::now();

        loop {
            let telemetry_due = self.telemetry.next_due();
            let heartbeat_due = session
                .as_ref()
                .map_or(Instant::now() + far, |s| s.next_heartbeat);
            let dead_at = session.as_ref().map_or(Instant::now() + far, |s| {
                s.last_rx + s.welcome.heartbeat_interval * DEAD_INTERVALS
            });
            let pump_due = session.as_ref().and_then(|s| self.pump_wake(s));
            let idle = session.is_none() && connecting.is_none();
            let ws_next = async {
                match session.as_mut() {
                    Some(s) => s.ws.next().await,
                    None => std::future::pending().await,
                }
            };
            let deploy_done = async {
                match self.deploying.as_mut() {
                    Some(d) => (&mut d.task).await,
                    None => std::future::pending().await,
                }
            };
            let connect_done = async {
                match connecting.as_mut() {
                    Some((fut, _)) => fut.await,
                    None => std::future::pending().await,
                }
            };
            enum Wake {
                Shutdown,
                Telemetry,
                Batch,
                Teleop,
                Reconnect,
                Connected(Box<Result<(Socket, Welcome), ConnectError>>),
                Frame(Option<Result<Message, tokio_tungstenite::tungstenite::Error>>),
                Heartbeat,
                Dead,
                Pump,
                AckFlush,
                Progress(Option<Progress>),
                Deployed(Box<Result<(Releases, Option<Outcome>), tokio::task::JoinError>>),
            }
            let wake = tokio::select! {
                biased;
                () = &mut shutdown => Wake::Shutdown,
                frame = ws_next => Wake::Frame(frame),
                p = self.progress_rx.recv() => Wake::Progress(p),
                r = deploy_done => Wake::Deployed(Box::new(r)),
                res = connect_done => Wake::Connected(Box::new(res)),
                () = sleep_until(heartbeat_due) => Wake::Heartbeat,
                () = sleep_until(next_teleop) => Wake::Teleop,
                () = sleep_until(telemetry_due) => Wake::Telemetry,
                () = sleep_until(next_batch) => Wake::Batch,
                () = sleep_until(dead_at) => Wake::Dead,
                () = sleep_until(pump_due.unwrap_or(Instant::now() + far)), if pump_due.is_some() => Wake::Pump,
                () = sleep_until(next_ack_flush.unwrap_or(Instant::now() + far)), if next_ack_flush.is_some() => Wake::AckFlush,
                () = sleep_until(reconnect_at), if idle => Wake::Reconnect,
            };
            let mut end_session: Option<&'static str> = None;
            let mut fatal_code: Option<ErrorCode> = None;
            match wake {
                Wake::Shutdown => break,
                Wake::Telemetry => {
                    let samples = self
                        .telemetry
                        .collect_due(Instant::now(), lekiwi_protocol::now_ms());
                    self.pending_samples.extend(samples);
                    if self.pending_samples.len() >= 1000 {
                        self.flush_samples()?;
                    }
                }
                Wake::Batch => {
                    next_batch = Instant::now() + batch_every;
                    self.flush_samples()?;
                }
                Wake::Teleop => {
                    next_teleop = Instant::now() + teleop_every;
                    if self.on_teleop_check()?
                        && let Some(s) = session.as_mut()
                        && !self.send_heartbeat(s).await
                    {
                        end_session = Some("send failed");
                    }
                }
                Wake::Reconnect => {
                    let (creds, enrolling) = self.credentials()?;
                    let hello = self.hello()?;
                    let url = self.config.gateway.clone();
                    let ca = self.config.ca_file.clone();
                    info!(
                        gateway = %url,
                        robot = %creds.robot,
                        enrolling,
                        attempt = backoff.attempts(),
                        "connecting"
                    );
                    connecting = Some((
                        Box::pin(async move {
                            crate::connection::connect_with_ca(
                                &url,
                                &creds,
                                &hello,
                                connect_timeout,
                                ca.as_deref(),
                            )
                            .await
                        }),
                        enrolling,
                    ));
                }
                Wake::Connected(res) => {
                    let enrolling = connecting.take().is_some_and(|(_, e)| e);
                    match *res {
                        Ok((ws, welcome)) => {
                            info!(
                                robot = %welcome.robot,
                                heartbeat_s = welcome.heartbeat_interval.as_secs(),
                                stored_seq = ?welcome.stored_seq,
                                "connected"
                            );
                            let mut s = Session::new(ws, welcome);
                            self.on_welcome(&s, enrolling)?;
                            self.status
                                .send_modify(|st| st.robot = s.welcome.robot.clone());
                            if !self.send_heartbeat(&mut s).await {
                                end_session = Some("send failed");
                            }
                            session = Some(s);
                        }
                        Err(e) => {
                            if matches!(e, ConnectError::Unauthorized(_)) {
                                if self.enrollment_token.is_some() && !enrolling {
                                    warn!(error = %e, "the robot's token was refused; enrolling again with the enrollment token");
                                    self.reenroll = true;
                                } else {
                                    error!(error = %e, "credentials refused; retrying at the slowest rate");
                                    backoff.saturate();
                                    reconnect_at = Instant::now() + backoff.ceiling();
                                }
                            } else if !e.retryable() {
                                error!(error = %e, "cannot connect; retrying at the slowest rate");
                                backoff.saturate();
                            }
                            let delay = backoff.next_delay();
                            warn!(error = %e, retry_in_ms = delay.as_millis() as u64, attempt = backoff.attempts(), "connection failed");
                            // A refused token waits at least the cap (set above).
                            reconnect_at = reconnect_at.max(Instant::now() + delay);
                        }
                    }
                }
                Wake::Frame(frame) => {
                    if let Some(s) = session.as_mut() {
                        s.last_rx = Instant::now();
                        match frame {
                            Some(Ok(Message::Text(t))) => {
                                if let Some(code) = self.on_frame(s, t.as_str())? {
                                    end_session = Some("the gateway ended the session");
                                    fatal_code = Some(code);
                                }
                                if self.pending_acks.len() >= ACK_BATCH {
                                    self.flush_acks()?;
                                    next_ack_flush = None;
                                } else if !self.pending_acks.is_empty() && next_ack_flush.is_none()
                                {
                                    next_ack_flush = Some(Instant::now() + ACK_FLUSH);
                                }
                            }
                            Some(Ok(Message::Close(_))) | None => {
                                end_session = Some("the gateway closed the connection");
                            }
                            Some(Ok(_)) => {}
                            Some(Err(e)) => {
                                warn!(error = %e, "connection error");
                                end_session = Some("connection error");
                            }
                        }
                    }
                }
                Wake::Heartbeat => {
                    if let Some(s) = session.as_mut() {
                        resend_unacknowledged(s);
                        if !self.send_heartbeat(s).await {
                            end_session = Some("send failed");
                        }
                    }
                }
                Wake::Dead => end_session = Some("no answer from the gateway"),
                Wake::Pump => {}
                Wake::Progress(p) => {
                    if let Some(p) = p {
                        let ts = lekiwi_protocol::now_ms();
                        self.outbox
                            .push(Lane::Critical, ts, |seq| p.to_message(seq))?;
                    }
                }
                Wake::Deployed(r) => {
                    // Progress sent before the end goes out first.
                    while let Ok(p) = self.progress_rx.try_recv() {
                        let ts = lekiwi_protocol::now_ms();
                        self.outbox
                            .push(Lane::Critical, ts, |seq| p.to_message(seq))?;
                    }
                    self.on_deploy_done(*r)?;
                    if let Some(s) = session.as_mut()
                        && !self.send_heartbeat(s).await
                    {
                        end_session = Some("send failed");
                    }
                }
                Wake::AckFlush => {
                    next_ack_flush = None;
                    self.flush_acks()?;
                }
            }
            if end_session.is_none()
                && let Some(s) = session.as_mut()
                && !self.pump(s).await?
            {
                end_session = Some("send failed");
            }
            if let Some(why) = end_session
                && let Some(mut s) = session.take()
            {
                self.flush_acks()?;
                next_ack_flush = None;
                let _ = tokio::time::timeout(Duration::from_secs(1), s.ws.close(None)).await;
                let lasted = s.started.elapsed();
                // A session that held for a heartbeat interval was a success (PROTOCOL.md §11).
                if lasted >= s.welcome.heartbeat_interval {
                    backoff.reset();
                }
                let delay = match fatal_code {
                    // Another replica takes over: come back soon, spread over 5 s.
                    Some(ErrorCode::ShuttingDown) => {
                        Duration::from_millis(rand::random_range(0..=5000))
                    }
                    // Retrying soon cannot help.
                    Some(ErrorCode::Replaced | ErrorCode::UnsupportedVersion) => {
                        backoff.saturate();
                        backoff.ceiling() + backoff.next_delay()
                    }
                    _ => backoff.next_delay(),
                };
                warn!(
                    reason = why,
                    lasted_s = lasted.as_secs(),
                    retry_in_ms = delay.as_millis() as u64,
                    "disconnected"
                );
                reconnect_at = Instant::now() + delay;
            }
            let connected = session.is_some();
            if connected != published_connected || Instant::now() >= next_status {
                self.publish_status(connected);
                published_connected = connected;
                next_status = Instant::now() + STATUS_EVERY;
            }
        }

        info!("shutting down");
        self.flush_samples()?;
        self.flush_acks()?;
        if let Some(mut s) = session {
            let _ = tokio::time::timeout(Duration::from_secs(2), s.ws.close(None)).await;
        }
        drop(self.advertiser.take());
        Ok(())
    }
}
