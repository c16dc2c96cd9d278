//! One connected session: heartbeats, the durable send window (rate, in-flight limit, resends)
//! and the frames the gateway sends. Generic over the [`Transport`], so unit tests drive it
//! with channels.

use std::collections::BTreeMap;
use std::time::Duration;

use futures::SinkExt;
use lekiwi_protocol::{
    AgentMessage, ErrorCode, MAX_FRAME_BYTES, MAX_SEQ, ServerMessage, Severity, decode, encode,
};
use tokio::time::Instant;
use tokio_tungstenite::tungstenite::Message;
use tracing::{debug, info, warn};

use super::{Agent, Error};
use crate::connection::{Transport, Welcome};
use crate::outbox::Lane;
use crate::release::GatewayAccess;
use crate::state::{self, Credentials};

/// Durable messages in flight beyond the window, reserved for the critical lane.
const CRITICAL_RESERVE: usize = 8;
/// A send that takes longer than this counts as a dead connection.
const SEND_TIMEOUT: Duration = Duration::from_secs(10);
/// Most send tokens saved up while idle: the burst after a pause.
const MAX_BURST: f64 = 32.0;

/// WebSocket bytes of a client text frame carrying `len` payload bytes (header + mask key).
fn ws_frame_bytes(len: usize) -> u64 {
    let header = match len {
        0..=125 => 2,
        126..=65535 => 4,
        _ => 10,
    };
    (len + header + 4) as u64
}

/// A live session.
pub(super) struct Session<S> {
    pub(super) ws: S,
    pub(super) welcome: Welcome,
    pub(super) started: Instant,
    /// When the gateway last sent anything; silence for long ends the session.
    pub(super) last_rx: Instant,
    pub(super) next_heartbeat: Instant,
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

impl<S: Transport> Session<S> {
    pub(super) fn new(ws: S, welcome: Welcome) -> Self {
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
            tokens: rate.min(MAX_BURST),
            rate,
            last_refill: now,
            hold_until: None,
        }
    }

    fn refill(&mut self, now: Instant) {
        let burst = self.rate.min(MAX_BURST);
        self.tokens = (self.tokens
            + now.duration_since(self.last_refill).as_secs_f64() * self.rate)
            .min(burst);
        self.last_refill = now;
    }

    /// When the pump should run again, if it is waiting for tokens or a hold.
    pub(super) fn pump_wake(&self) -> Option<Instant> {
        if let Some(t) = self.hold_until {
            return Some(t);
        }
        (self.tokens < 1.0).then(|| self.last_refill + Duration::from_secs_f64(1.0 / self.rate))
    }

    /// Takes back messages sent more than a heartbeat interval ago and still unacknowledged,
    /// so they are sent again (PROTOCOL.md §6 rule 3).
    pub(super) fn resend_unacknowledged(&mut self) {
        let stale_before = Instant::now() - self.welcome.heartbeat_interval;
        let stale: Vec<u64> = self
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
                self.in_flight.remove(seq);
            }
            for c in &mut self.cursor {
                *c = (*c).min(first - 1);
            }
        }
    }

    /// The gateway refused durable message `seq`: send it (and what follows in its lane) again
    /// after a pause.
    fn retry_refused(&mut self, seq: u64, code: ErrorCode) {
        if self.in_flight.remove(&seq).is_none() {
            return;
        }
        for c in &mut self.cursor {
            if *c >= seq {
                *c = seq - 1;
            }
        }
        let pause = if code == ErrorCode::RateLimited {
            Duration::from_secs(1)
        } else {
            Duration::from_secs(2)
        };
        self.hold_until = Some(Instant::now() + pause);
    }
}

impl Agent {
    /// Sends one frame, counting its bytes; false when the connection failed.
    async fn send<S: Transport>(&mut self, session: &mut Session<S>, frame: String) -> bool {
        let bytes = ws_frame_bytes(frame.len());
        match tokio::time::timeout(SEND_TIMEOUT, session.ws.send(Message::text(frame))).await {
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

    /// Sends a heartbeat with the latest vitals and verdicts, and schedules the next.
    pub(super) async fn send_heartbeat<S: Transport>(&mut self, session: &mut Session<S>) -> bool {
        let hb = AgentMessage::Heartbeat {
            sent_at_ms: lekiwi_protocol::now_ms(),
            rtt_ms: self.last_rtt_ms,
            vitals: self.vitals(),
            current_release: self.current_release.clone(),
            health: Some(self.health_now()),
            teleoperation: Some(self.teleop.to_wire()),
        };
        session.next_heartbeat = Instant::now() + session.welcome.heartbeat_interval;
        self.send(session, encode(&hb)).await
    }

    /// Sends queued durable messages while the window and the rate allow; returns false when
    /// the connection failed.
    pub(super) async fn pump<S: Transport>(
        &mut self,
        session: &mut Session<S>,
    ) -> Result<bool, Error> {
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
                    if entry.frame.len() > session.welcome.max_frame_bytes {
                        self.discard(entry.seq, "larger than the gateway accepts")?;
                        continue;
                    }
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

    /// The session is up: keep a token issued at enrollment, renumber the outbox if the
    /// gateway is ahead of it, and report what the outbox dropped while offline.
    pub(super) fn on_welcome(&mut self, welcome: &Welcome, enrolling: bool) -> Result<(), Error> {
        if let Some(token) = &welcome.robot_token {
            self.save_robot_token(welcome, token)?;
        } else if enrolling {
            warn!("enrolled without a robot token in welcome; will enroll again next time");
        }
        if let Some(stored) = welcome.stored_seq.filter(|s| *s > MAX_SEQ) {
            warn!(
                stored,
                max = MAX_SEQ,
                "protocol error: welcome.stored_seq is above the protocol's maximum; ignored"
            );
        } else if let Some(stored) = welcome.stored_seq
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

    /// Drops a queued durable message the gateway will never store, with a log saying why.
    fn discard(&mut self, seq: u64, why: &str) -> Result<(), Error> {
        if self.outbox.discard(seq)? {
            warn!(
                seq,
                why, "durable message dropped: the gateway cannot store it"
            );
        }
        Ok(())
    }

    /// Saves the robot's own token from `welcome` and gives it to the release store.
    fn save_robot_token(&mut self, welcome: &Welcome, token: &str) -> Result<(), Error> {
        state::save_credentials(
            &self.config.state_dir,
            &Credentials {
                robot: welcome.robot.clone(),
                token: token.to_owned(),
            },
        )?;
        info!(robot = %welcome.robot, "enrolled; the robot's own token is saved");
        let access = GatewayAccess::from_gateway_url(
            &self.config.gateway,
            token.to_owned(),
            welcome.robot.clone(),
            self.config.ca_file.clone(),
        )?;
        match self.releases.as_mut() {
            Some(r) => r.set_gateway(access)?,
            None => self.pending_access = Some(access),
        }
        self.reenroll = false;
        Ok(())
    }

    /// Handles one frame from the gateway; returns the code of a fatal error, which ends the
    /// session. An undecodable frame is logged and ignored.
    pub(super) fn on_frame<S: Transport>(
        &mut self,
        session: &mut Session<S>,
        text: &str,
    ) -> Result<Option<ErrorCode>, Error> {
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
                match seq {
                    // Never storable (PROTOCOL.md §6 rule 2): dropped, not resent.
                    Some(seq)
                        if matches!(code, ErrorCode::Malformed | ErrorCode::QuotaExceeded) =>
                    {
                        session.in_flight.remove(&seq);
                        self.discard(seq, &message)?;
                    }
                    Some(seq) => session.retry_refused(seq, code),
                    None => {}
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
}
