//! The run loop itself: it sleeps until one thing is due (a frame, a timer, a finished
//! connection attempt or deployment, shutdown), hands it to the step for it, then sends what
//! the outbox holds and publishes the status.

use std::future::Future;
use std::pin::Pin;
use std::time::Duration;

use lekiwi_protocol::{ErrorCode, Severity};
use tokio::time::{Instant, sleep_until};
use tokio_tungstenite::tungstenite::{Error as WsError, Message};
use tracing::warn;

use super::commands::Joined;
use super::session::Session;
use super::status::STATUS_EVERY;
use super::{Agent, Error, SAMPLES_PER_MESSAGE, Stopped};
use crate::backoff::Backoff;
use crate::config::Config;
use crate::connection::{ConnectError, Transport, Welcome};
use crate::connection::{Connecting, Connector};
use crate::outbox::Lane;
use crate::release::Progress;

/// Acknowledgements are deleted from the outbox in batches of at most this many...
const ACK_BATCH: usize = 128;
/// ...or after this long.
const ACK_FLUSH: Duration = Duration::from_millis(250);
/// Missing heartbeat acks for this many intervals ends the session.
const DEAD_INTERVALS: u32 = 3;
/// How far ahead a timer lies while it has nothing to wait for.
const FAR: Duration = Duration::from_secs(86_400);

/// What woke the loop.
enum Wake<S> {
    Shutdown,
    Telemetry,
    Batch,
    Teleop,
    /// The health verdict changed (or, `false`, its task is gone).
    Health(bool),
    Reconnect,
    Connected(Box<Result<(S, Welcome), ConnectError>>),
    Frame(Option<Result<Message, WsError>>),
    Heartbeat,
    Dead,
    Pump,
    AckFlush,
    Progress(Option<Progress>),
    Deployed(Box<Joined>),
}

/// Why the session ends, and the gateway's code when the gateway ended it.
pub(super) struct Ending {
    pub(super) why: &'static str,
    pub(super) code: Option<ErrorCode>,
}

impl Ending {
    pub(super) fn because(why: &'static str) -> Self {
        Self { why, code: None }
    }

    pub(super) fn send_failed() -> Self {
        Self::because("send failed")
    }
}

/// What the loop keeps between wake-ups besides the agent: the connection (attempt or session),
/// its backoff, and the timers.
pub(super) struct Loop<S> {
    /// Opens a connection and runs the handshake.
    pub(super) connect: Connector<S>,
    pub(super) backoff: Backoff,
    teleop_every: Duration,
    batch_every: Duration,
    next_teleop: Instant,
    next_batch: Instant,
    /// When pending acknowledgements are deleted from the outbox, if any are pending.
    pub(super) next_ack_flush: Option<Instant>,
    /// No connection attempt before this.
    pub(super) reconnect_at: Instant,
    /// The connection attempt under way, and whether it enrolls.
    pub(super) connecting: Option<(Connecting<S>, bool)>,
    pub(super) session: Option<Session<S>>,
    /// The `connected` the status endpoint shows.
    published_connected: bool,
    next_status: Instant,
}

impl<S: Transport> Loop<S> {
    fn new(config: &Config, connect: Connector<S>) -> Self {
        let teleop_every = Duration::from_secs_f64(config.teleop_interval_s);
        let batch_every = Duration::from_secs(config.telemetry_batch_interval_s);
        let now = Instant::now();
        Self {
            connect,
            backoff: Backoff::new(
                Duration::from_millis(config.backoff_initial_ms),
                Duration::from_millis(config.backoff_max_ms),
            ),
            teleop_every,
            batch_every,
            next_teleop: now + teleop_every,
            next_batch: now + batch_every,
            next_ack_flush: None,
            reconnect_at: now,
            connecting: None,
            session: None,
            published_connected: false,
            next_status: now,
        }
    }
}

impl Agent {
    /// [`Agent::run`] over connections that `connect` opens.
    pub(super) async fn run_with<S: Transport>(
        mut self,
        shutdown: impl Future<Output = ()>,
        connect: Connector<S>,
    ) -> Result<Stopped, Error> {
        tokio::pin!(shutdown);
        let version = crate::selfupdate::version();
        self.event(
            Lane::Event,
            "agent_started",
            Severity::Info,
            format!("lekiwi-agent {version} started"),
            serde_json::json!({"version": version}),
        )?;
        self.report_fallen_back()?;
        self.start_recovery();
        let mut lp = Loop::new(&self.config, connect);
        loop {
            let wake = self.next_wake(&mut lp, shutdown.as_mut()).await;
            if matches!(wake, Wake::Shutdown) {
                break;
            }
            let ending = self.on_wake(&mut lp, wake).await?;
            self.settle(&mut lp, ending).await?;
            if self.restart_for_update {
                self.shut_down(lp.session.take()).await?;
                return Ok(Stopped::Updated);
            }
        }
        self.shut_down(lp.session.take()).await?;
        Ok(Stopped::Shutdown)
    }

    /// Sleeps until the first thing due; `biased`, so shutdown and the gateway's frames come
    /// before timers.
    async fn next_wake<S: Transport>(
        &mut self,
        lp: &mut Loop<S>,
        shutdown: Pin<&mut impl Future<Output = ()>>,
    ) -> Wake<S> {
        let telemetry_due = self.telemetry.next_due();
        let heartbeat_due = lp
            .session
            .as_ref()
            .map_or(Instant::now() + FAR, |s| s.next_heartbeat);
        let dead_at = lp.session.as_ref().map_or(Instant::now() + FAR, |s| {
            s.last_rx + s.welcome.heartbeat_interval * DEAD_INTERVALS
        });
        let pump_due = lp.session.as_ref().and_then(Session::pump_wake);
        let ack_flush_due = lp.next_ack_flush;
        let idle = lp.session.is_none() && lp.connecting.is_none();
        let (next_teleop, next_batch, reconnect_at) =
            (lp.next_teleop, lp.next_batch, lp.reconnect_at);
        let ws_next = async {
            match lp.session.as_mut() {
                Some(s) => futures::StreamExt::next(&mut s.ws).await,
                None => std::future::pending().await,
            }
        };
        let deploy_done = async {
            match self.deploying.as_mut() {
                Some(d) => (&mut d.task).await,
                None => std::future::pending().await,
            }
        };
        let health_changed = async {
            match self.health.as_mut() {
                Some(rx) => rx.changed().await.is_ok(),
                None => std::future::pending().await,
            }
        };
        let connect_done = async {
            match lp.connecting.as_mut() {
                Some((fut, _)) => fut.await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            biased;
            () = shutdown => Wake::Shutdown,
            frame = ws_next => Wake::Frame(frame),
            p = self.progress_rx.recv() => Wake::Progress(p),
            r = deploy_done => Wake::Deployed(Box::new(r)),
            res = connect_done => Wake::Connected(Box::new(res)),
            () = sleep_until(heartbeat_due) => Wake::Heartbeat,
            () = sleep_until(next_teleop) => Wake::Teleop,
            alive = health_changed => Wake::Health(alive),
            () = sleep_until(telemetry_due) => Wake::Telemetry,
            () = sleep_until(next_batch) => Wake::Batch,
            () = sleep_until(dead_at) => Wake::Dead,
            () = sleep_until(pump_due.unwrap_or(Instant::now() + FAR)), if pump_due.is_some() => Wake::Pump,
            () = sleep_until(ack_flush_due.unwrap_or(Instant::now() + FAR)), if ack_flush_due.is_some() => Wake::AckFlush,
            () = sleep_until(reconnect_at), if idle => Wake::Reconnect,
        }
    }

    /// Hands one wake-up to its step; returns why the session must end, if it must.
    async fn on_wake<S: Transport>(
        &mut self,
        lp: &mut Loop<S>,
        wake: Wake<S>,
    ) -> Result<Option<Ending>, Error> {
        match wake {
            Wake::Shutdown | Wake::Pump => {}
            Wake::Telemetry => self.on_telemetry_due()?,
            Wake::Batch => {
                lp.next_batch = Instant::now() + lp.batch_every;
                self.flush_samples()?;
            }
            Wake::Teleop => {
                lp.next_teleop = Instant::now() + lp.teleop_every;
                if self.on_teleop_check()? {
                    return Ok(self.heartbeat_now(lp).await);
                }
            }
            Wake::Health(alive) => {
                if !alive {
                    warn!("the health checks stopped; the last verdict stands");
                    self.health = None;
                }
                return Ok(self.heartbeat_now(lp).await);
            }
            Wake::Reconnect => self.start_connecting(lp)?,
            Wake::Connected(res) => return self.on_connected(lp, *res).await,
            Wake::Frame(frame) => return self.on_socket_frame(lp, frame),
            Wake::Heartbeat => {
                if let Some(s) = lp.session.as_mut() {
                    s.resend_unacknowledged();
                }
                return Ok(self.heartbeat_now(lp).await);
            }
            Wake::Dead => return Ok(Some(Ending::because("no answer from the gateway"))),
            Wake::Progress(p) => {
                if let Some(p) = p {
                    self.queue_progress(&p)?;
                }
            }
            Wake::Deployed(r) => {
                // Progress sent before the end goes out first.
                while let Ok(p) = self.progress_rx.try_recv() {
                    self.queue_progress(&p)?;
                }
                self.on_deploy_done(*r)?;
                return Ok(self.heartbeat_now(lp).await);
            }
            Wake::AckFlush => {
                lp.next_ack_flush = None;
                self.flush_acks()?;
            }
        }
        Ok(None)
    }

    /// Collects the samples due; a full message's worth is queued at once.
    fn on_telemetry_due(&mut self) -> Result<(), Error> {
        let samples = self
            .telemetry
            .collect_due(Instant::now(), lekiwi_protocol::now_ms());
        self.pending_samples.extend(samples);
        if self.pending_samples.len() >= SAMPLES_PER_MESSAGE {
            self.flush_samples()?;
        }
        Ok(())
    }

    /// Sends a heartbeat now, if connected (the gateway hears a change without waiting).
    async fn heartbeat_now<S: Transport>(&mut self, lp: &mut Loop<S>) -> Option<Ending> {
        let s = lp.session.as_mut()?;
        (!self.send_heartbeat(s).await).then(Ending::send_failed)
    }

    /// Something arrived on the session's socket: a frame to handle, or its end.
    fn on_socket_frame<S: Transport>(
        &mut self,
        lp: &mut Loop<S>,
        frame: Option<Result<Message, WsError>>,
    ) -> Result<Option<Ending>, Error> {
        let Some(s) = lp.session.as_mut() else {
            return Ok(None);
        };
        s.last_rx = Instant::now();
        match frame {
            Some(Ok(Message::Text(t))) => {
                let ending = self.on_frame(s, t.as_str())?.map(|code| Ending {
                    why: "the gateway ended the session",
                    code: Some(code),
                });
                self.schedule_ack_flush(lp)?;
                Ok(ending)
            }
            Some(Ok(Message::Close(_))) | None => {
                Ok(Some(Ending::because("the gateway closed the connection")))
            }
            Some(Ok(_)) => Ok(None),
            Some(Err(e)) => {
                warn!(error = %e, "connection error");
                Ok(Some(Ending::because("connection error")))
            }
        }
    }

    /// Deletes acknowledged messages from the outbox once a batch is full, or arms the timer
    /// that deletes a partial batch.
    fn schedule_ack_flush<S>(&mut self, lp: &mut Loop<S>) -> Result<(), Error> {
        if self.pending_acks.len() >= ACK_BATCH {
            self.flush_acks()?;
            lp.next_ack_flush = None;
        } else if !self.pending_acks.is_empty() && lp.next_ack_flush.is_none() {
            lp.next_ack_flush = Some(Instant::now() + ACK_FLUSH);
        }
        Ok(())
    }

    /// After every wake-up: send what the outbox holds, end the session if it must end, and
    /// refresh the status endpoint when due.
    async fn settle<S: Transport>(
        &mut self,
        lp: &mut Loop<S>,
        mut ending: Option<Ending>,
    ) -> Result<(), Error> {
        if ending.is_none()
            && let Some(s) = lp.session.as_mut()
            && !self.pump(s).await?
        {
            ending = Some(Ending::send_failed());
        }
        if let Some(ending) = ending
            && let Some(s) = lp.session.take()
        {
            self.end_session(lp, s, ending).await?;
        }
        let connected = lp.session.is_some();
        if connected != lp.published_connected || Instant::now() >= lp.next_status {
            self.publish_status(connected);
            lp.published_connected = connected;
            lp.next_status = Instant::now() + STATUS_EVERY;
        }
        Ok(())
    }

    /// Queues what is pending and closes the session.
    async fn shut_down<S: Transport>(&mut self, session: Option<Session<S>>) -> Result<(), Error> {
        tracing::info!("shutting down");
        self.flush_samples()?;
        self.flush_acks()?;
        if let Some(mut s) = session {
            let _ = tokio::time::timeout(
                Duration::from_secs(2),
                futures::SinkExt::send(&mut s.ws, Message::Close(None)),
            )
            .await;
        }
        drop(self.advertiser.take());
        Ok(())
    }
}
