//! One handler per agent message type (as mini-redis has one `apply` per command): each does
//! what its message asks and answers with the frame to send back.

use axum::extract::ws::Message;
use futures::Sink;
use jiff::Timestamp;
use lekiwi_protocol::rules::{self, FieldError};
use lekiwi_protocol::{AgentMessage, ErrorCode, MAX_SEQ, ProgressPhase, Sample, ServerMessage};
use tracing::{debug, info, warn};

use super::Session;
use super::conn::{End, Flow, wire_name};
use lekiwi_event_store::{self as event_store, Quota, QuotaLimit, StoredEvent};
use lekiwi_metrics::KindLabels;
use lekiwi_metrics::ReasonLabels;
use lekiwi_presence::{HeartbeatInfo, UpdateOutcome};

impl<W> Session<'_, W>
where
    W: Sink<Message> + Unpin + Send,
{
    /// Applies one agent message; `Err` when the session ended meanwhile.
    pub(super) async fn apply(&mut self, mut msg: AgentMessage) -> Result<ServerMessage, End> {
        if let Some(seq) = msg.seq().filter(|s| *s > MAX_SEQ) {
            return Ok(seq_out_of_range(seq));
        }
        if matches!(msg, AgentMessage::Heartbeat { .. }) {
            let refused = rules::sanitize(&mut msg);
            self.invalid_fields(refused).await?;
        }
        Ok(match msg {
            AgentMessage::Hello { .. } => ServerMessage::Error {
                code: ErrorCode::UnexpectedMessage,
                message: "hello was already received".into(),
                fatal: false,
                seq: None,
            },
            AgentMessage::Heartbeat {
                sent_at_ms,
                rtt_ms,
                vitals,
                current_release,
                health,
                teleoperation,
            } => {
                let info = HeartbeatInfo {
                    release: current_release,
                    health,
                    teleoperation,
                    vitals,
                    rtt_ms,
                };
                self.heartbeat(sent_at_ms, rtt_ms, info).await?
            }
            AgentMessage::Event {
                seq,
                ts_ms,
                kind,
                severity,
                message,
                data,
            } => {
                let ev = StoredEvent {
                    seq,
                    ts_ms,
                    kind,
                    severity: wire_name(&severity),
                    message,
                    data,
                };
                let stored = Box::pin(self.shared.store.insert_event(self.key, &ev)).await;
                // Stored before too (`Ok(false)`): a resend of an event whose first session
                // ended, or whose store answer failed, before presence was told; an update step
                // it carries counts now (presence ignores a step it has already).
                if let Ok(newly) = stored {
                    self.agent_event(&ev, newly);
                }
                self.durable(ev.seq, stored)
            }
            AgentMessage::Telemetry { seq, samples } => self.telemetry(seq, &samples).await,
            AgentMessage::Progress {
                seq,
                command_id,
                phase,
                percent,
                message,
            } => {
                self.progress(seq, command_id, phase, percent, message)
                    .await
            }
        })
    }

    /// Names each field the status rules refused in a non-fatal `invalid_field` error (the rest
    /// of its message still takes effect).
    pub(super) async fn invalid_fields(&mut self, refused: Vec<FieldError>) -> Flow {
        for e in refused {
            // Counted in `error_frames_total{kind="invalid_field"}`; a log line per heartbeat
            // would flood the log.
            tracing::debug!(robot = %self.key.name, namespace = %self.key.namespace, field = e.field, reason = %e.reason, "refused a status field");
            self.conn
                .refuse(ErrorCode::InvalidField, e.to_string(), None)
                .await?;
        }
        Ok(())
    }

    /// Sends a handler's answer: an error frame is a refusal (counted by [`super::conn::Conn::refuse`]).
    pub(super) async fn reply(&mut self, reply: ServerMessage) -> Flow {
        match reply {
            ServerMessage::Error {
                code, message, seq, ..
            } => self.conn.refuse(code, message, seq).await,
            other => self.conn.send(&other).await,
        }
    }

    /// A heartbeat: round-trip time, the release the robot runs (a deploy may be due again),
    /// presence; answered with an ack carrying the server's clock.
    async fn heartbeat(
        &mut self,
        sent_at_ms: i64,
        rtt_ms: Option<f64>,
        info: HeartbeatInfo,
    ) -> Result<ServerMessage, End> {
        if let Some(rtt) = rtt_ms.filter(|r| r.is_finite() && *r >= 0.0) {
            self.shared
                .metrics
                .gateway
                .heartbeat_rtt
                .observe(rtt / 1000.0);
        }
        // A deploy goes out once per desired release and session (PROTOCOL.md §12): a robot
        // that switched away from it is asked again only for a release not yet sent.
        if self.commands.reported(&info.release) {
            self.send_commands().await?;
        }
        self.shared.presence.heartbeat(self.key, self.id, info);
        Ok(ServerMessage::HeartbeatAck {
            sent_at_ms,
            server_time_ms: Timestamp::now().as_millisecond(),
        })
    }

    /// A durable event: stored, then acked.
    async fn event(&self, ev: &StoredEvent) -> ServerMessage {
        self.shared
            .presence
            .event(self.key, self.id, ev.severity == "error");
        let stored = Box::pin(self.shared.store.insert_event(self.key, ev)).await;
        self.durable(ev.seq, stored)
    }

    /// A durable batch of telemetry samples: stored, then acked.
    async fn telemetry(&self, seq: u64, samples: &[Sample]) -> ServerMessage {
        self.shared.presence.telemetry(self.key, self.id, samples);
        let stored = Box::pin(self.shared.store.insert_telemetry(self.key, seq, samples)).await;
        self.durable(seq, stored)
    }

    /// A deploy command's progress: a final phase of the command this session sent tells
    /// presence how the update ended; every report is stored as a durable `progress` event.
    async fn progress(
        &mut self,
        seq: u64,
        command_id: String,
        phase: String,
        percent: Option<f64>,
        message: String,
    ) -> ServerMessage {
        let known = ProgressPhase::parse(&phase);
        if let Some((release, cancelled)) = self.commands.finished(&command_id, known) {
            info!(%phase, release = %release.version, %message, cancelled, "update finished");
            self.shared.presence.update_finished(
                self.key,
                self.id,
                UpdateOutcome {
                    release,
                    phase: outcome_phase(&phase, known, cancelled),
                    message: (!message.is_empty()).then(|| message.clone()),
                    time: Timestamp::now(),
                },
            );
        }
        let ev = StoredEvent {
            seq,
            ts_ms: Timestamp::now().as_millisecond(),
            kind: "progress".into(),
            severity: if known == Some(ProgressPhase::Failed) {
                "error".into()
            } else {
                "info".into()
            },
            message,
            data: serde_json::json!({ "command_id": command_id, "phase": phase, "percent": percent }),
        };
        self.event(&ev).await
    }

    /// The answer to a durable message: an ack once stored (or already stored), else an error
    /// so the agent keeps it and resends.
    fn durable(&self, seq: u64, stored: event_store::Result<bool>) -> ServerMessage {
        match stored {
            Ok(new) => {
                self.shared
                    .metrics
                    .gateway
                    .durable
                    .get_or_create(&KindLabels {
                        kind: if new { "stored" } else { "replay" },
                    })
                    .inc();
                ServerMessage::Ack { seq }
            }
            // A sequence number the store cannot hold will never be stored: say so, do not
            // ask for a resend.
            Err(event_store::Error::SeqOutOfRange(_)) => seq_out_of_range(seq),
            Err(event_store::Error::QuotaExceeded { limit, quota, .. }) => {
                self.over_quota(seq, limit, quota)
            }
            Err(e) => {
                self.shared.metrics.gateway.event_store_error("write");
                if e.is_unavailable() {
                    // The store logged the outage once; every message refused meanwhile
                    // would flood the log.
                    debug!(seq, error = %e, "durable message refused: event store out of reach");
                } else {
                    warn!(seq, error = %e, "cannot store a durable message");
                }
                ServerMessage::Error {
                    code: ErrorCode::StoreUnavailable,
                    message: format!("message {seq} was not stored; resend it later"),
                    fatal: false,
                    seq: Some(seq),
                }
            }
        }
    }
}

impl<W> Session<'_, W>
where
    W: Sink<Message> + Unpin + Send,
{
    /// A durable message refused because the robot is over its quota: counted, reported on the
    /// Robot (rate-limited), and answered `quota_exceeded` naming it so the agent drops it.
    fn over_quota(&self, seq: u64, limit: QuotaLimit, quota: Quota) -> ServerMessage {
        let reason = match limit {
            QuotaLimit::Rows => "quota_rows",
            QuotaLimit::Bytes => "quota_bytes",
        };
        self.shared
            .metrics
            .gateway
            .events_refused
            .get_or_create(&ReasonLabels { reason })
            .inc();
        // Logged once per interval with the Warning Event, not per message of a flood.
        debug!(
            seq,
            limit = limit.as_str(),
            "robot over its event store quota; message refused"
        );
        self.shared
            .quota_warnings
            .refused(self.key, seq, quota, limit.as_str());
        ServerMessage::Error {
            code: ErrorCode::QuotaExceeded,
            message: format!(
                "message {seq} was not stored: this robot keeps at most {} rows and {} bytes in the event store ({} exceeded); drop it",
                quota.rows,
                quota.bytes,
                limit.as_str()
            ),
            fatal: false,
            seq: Some(seq),
        }
    }
}

/// The refusal of a durable message whose `seq` is above [`MAX_SEQ`]: `malformed` naming it, so
/// the agent drops it instead of resending it (PROTOCOL.md §6 rule 2).
fn seq_out_of_range(seq: u64) -> ServerMessage {
    ServerMessage::Error {
        code: ErrorCode::Malformed,
        message: format!(
            "sequence number {seq} is out of range (at most 2^53-1 = {MAX_SEQ}); this message cannot be stored"
        ),
        fatal: false,
        seq: Some(seq),
    }
}

/// The phase recorded for an update that ended with `phase`: a command this gateway cancelled
/// (the robot should no longer run its release: a pause, an undo, a rollback) that did not end
/// `done` ended because of the cancel, whether before the switch (`cancelled`) or after it (the
/// agent switched back: `rolled_back`), so it is recorded `cancelled`, never as a failure a
/// rollout that starts the robot again could take for its own.
fn outcome_phase(phase: &str, known: Option<ProgressPhase>, cancelled: bool) -> String {
    if cancelled && known != Some(ProgressPhase::Done) {
        ProgressPhase::Cancelled.as_str().to_owned()
    } else {
        phase.to_owned()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cancelled_commands_end_is_recorded_cancelled_unless_it_switched_for_good() {
        use ProgressPhase::{Cancelled, Done, Failed, RolledBack};
        // The pause's cancel reached the agent in its health check: it switched back.
        assert_eq!(
            outcome_phase("rolled_back", Some(RolledBack), true),
            "cancelled"
        );
        assert_eq!(outcome_phase("failed", Some(Failed), true), "cancelled");
        assert_eq!(
            outcome_phase("cancelled", Some(Cancelled), true),
            "cancelled"
        );
        // It finished before the cancel arrived: the robot runs the release.
        assert_eq!(outcome_phase("done", Some(Done), true), "done");
        // A command not cancelled keeps the agent's word.
        assert_eq!(
            outcome_phase("rolled_back", Some(RolledBack), false),
            "rolled_back"
        );
        assert_eq!(outcome_phase("failed", Some(Failed), false), "failed");
    }
}
