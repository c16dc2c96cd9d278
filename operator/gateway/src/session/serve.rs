//! A session's main loop after `welcome`: it waits for shutdown, a control message, silence or
//! the agent's next frame, paces the agent's frames, and hands each message to its handler.

use std::time::Duration;

use crate::mailbox::Receiver;
use axum::extract::ws::Message;
use futures::{Sink, Stream, StreamExt};
use lekiwi_protocol::{AgentMessage, ErrorCode, Release, ServerMessage, decode};
use tokio::time::Instant;
use tracing::{debug, info, warn};

use super::Limits;
use super::Session;
use super::conn::{CLOSE_AWAY, CLOSE_POLICY, End, Flow};
use crate::registry::Control;
use lekiwi_core::rate::TokenBucket;
use lekiwi_metrics::KindLabels;

/// What woke the session up.
enum Wake<E> {
    /// The gateway is shutting down.
    Shutdown,
    /// The registry's message, or `None` when the registry dropped this session.
    Control(Option<Control>),
    /// No frame arrived within the missed-heartbeat limit.
    Silence,
    /// The socket's next item; `None` when it ended.
    Socket(Option<Result<Message, E>>),
}

/// How the agent's frames are paced: when silence ends the session, and the rate limit with
/// its tally of refusals.
struct Pace {
    /// Time without a frame after which the session is closed.
    silence: Duration,
    /// When the current silence reaches `silence`.
    deadline: Instant,
    bucket: TokenBucket,
    /// Net refused frames: each refusal adds one, each accepted frame takes one away.
    strikes: u32,
}

impl Pace {
    fn new(limits: &Limits) -> Self {
        let silence = limits.heartbeat_interval * limits.missed_heartbeats.max(1);
        Self {
            silence,
            deadline: Instant::now() + silence,
            bucket: TokenBucket::new(f64::from(limits.rate.max(1)), limits.burst),
            strikes: 0,
        }
    }

    /// A frame arrived: the silence starts over.
    fn heard(&mut self) {
        self.deadline = Instant::now() + self.silence;
    }

    /// Whether the rate limit lets this frame in; counts the strike either way.
    fn admit(&mut self) -> bool {
        if self.bucket.try_take() {
            self.strikes = self.strikes.saturating_sub(1);
            true
        } else {
            self.strikes += 1;
            false
        }
    }
}

impl<W> Session<'_, W>
where
    W: Sink<Message> + Unpin + Send,
{
    /// Serves the agent until the session ends, and says why it ended.
    pub(super) async fn serve<R, E>(
        &mut self,
        stream: &mut R,
        control: &mut Receiver<Control>,
    ) -> End
    where
        R: Stream<Item = Result<Message, E>> + Unpin + Send,
        E: std::fmt::Display,
    {
        let mut pace = Pace::new(&self.shared.limits);
        if let Err(end) = Box::pin(self.send_commands()).await {
            return end;
        }
        if let Err(end) = Box::pin(self.send_agent_update()).await {
            return end;
        }
        loop {
            let wake = tokio::select! {
                () = self.shared.cancel.cancelled() => Wake::Shutdown,
                ctl = control.recv() => Wake::Control(ctl),
                () = tokio::time::sleep_until(pace.deadline) => Wake::Silence,
                frame = stream.next() => Wake::Socket(frame),
            };
            // Each handler's future is boxed: it lives only while it handles this wake-up, and
            // inline it would add its size to this loop's future, which lives (and holds its
            // memory) as long as the connection.
            let flow = match wake {
                Wake::Shutdown => Box::pin(self.shut_down()).await,
                Wake::Control(ctl) => Box::pin(self.on_control(ctl)).await,
                Wake::Silence => Box::pin(self.silent(pace.silence)).await,
                Wake::Socket(frame) => Box::pin(self.on_socket(frame, &mut pace)).await,
            };
            if let Err(end) = flow {
                return end;
            }
        }
    }

    /// Sends the commands the ledger says are due (cancel, rollback, deploy), if any.
    pub(super) async fn send_commands(&mut self) -> Flow {
        for cmd in self.commands.next_commands(&self.shared.gateway, self.id) {
            if let ServerMessage::Command {
                command,
                command_id,
            } = &cmd
            {
                info!(%command_id, ?command, "sending command");
            }
            self.conn.send(&cmd).await?;
        }
        Ok(())
    }

    /// Cancels a download of `release` in flight, when a user's abort or undo stopped its
    /// rollout.
    async fn halt(&mut self, release: Release) -> Flow {
        let version = release.version.clone();
        let Some(cmd) = self.commands.halt(release, &self.shared.gateway, self.id) else {
            return Ok(());
        };
        if let ServerMessage::Command {
            command_id,
            command,
        } = &cmd
        {
            info!(%command_id, ?command, %version, "sending command: a user stopped the rollout");
        }
        self.conn.send(&cmd).await
    }

    async fn shut_down(&mut self) -> Flow {
        self.conn
            .fail(
                ErrorCode::ShuttingDown,
                "gateway shutting down; reconnect",
                (CLOSE_AWAY, "gateway shutting down"),
            )
            .await;
        Err(End::Shutdown)
    }

    async fn on_control(&mut self, control: Option<Control>) -> Flow {
        match control {
            Some(Control::Send(msg)) => self.conn.send(&msg).await,
            Some(Control::Desired { release, held }) => {
                let release = release.map(|r| *r);
                self.commands.set_desired(release.clone());
                if let Some(release) = release.filter(|_| held) {
                    self.halt(release).await?;
                }
                self.send_commands().await
            }
            Some(Control::Halt(release)) => self.halt(*release).await,
            Some(Control::DesiredAgent(agent)) => {
                self.agent.set_desired(agent.map(|a| *a));
                self.send_agent_update().await
            }
            Some(Control::Credentials { deleted }) => self.check_credentials(deleted).await,
            Some(Control::Replaced) | None => {
                self.replaced().await;
                Err(End::Replaced)
            }
            Some(Control::Moved) => {
                info!("a later session of this robot on another gateway took over; closing");
                self.replaced().await;
                Err(End::Moved)
            }
        }
    }

    /// Tells the agent that a newer connection of its robot replaced this one, and closes.
    async fn replaced(&mut self) {
        self.conn
            .fail(
                ErrorCode::Replaced,
                "a newer connection of this robot replaced this one",
                (CLOSE_POLICY, "replaced by a newer connection"),
            )
            .await;
    }

    /// The robot's token Secret changed: the session ends (close 1008 `token revoked`, no
    /// `error` frame) unless the token it speaks with still counts.
    async fn check_credentials(&mut self, deleted: bool) -> Flow {
        if !deleted && self.shared.auth.still_counts(self.key, &self.token_hash) {
            return Ok(());
        }
        warn!("the robot's token was rotated or revoked; closing its session");
        self.conn.close(CLOSE_POLICY, "token revoked").await;
        Err(End::Revoked)
    }

    async fn silent(&mut self, silence: Duration) -> Flow {
        warn!(
            ?silence,
            "no frame within the missed-heartbeat limit; closing"
        );
        self.conn.close(CLOSE_AWAY, "heartbeat timeout").await;
        Err(End::HeartbeatTimeout)
    }

    /// Takes the socket's next item: paces it, decodes it, applies it and sends the reply.
    async fn on_socket<E: std::fmt::Display>(
        &mut self,
        frame: Option<Result<Message, E>>,
        pace: &mut Pace,
    ) -> Flow {
        let text = match frame {
            None => return Err(End::Closed),
            Some(Ok(Message::Close(_))) => {
                self.conn.answer_close().await;
                return Err(End::Closed);
            }
            Some(Err(e)) => {
                debug!(error = %e, "socket error");
                return Err(End::Closed);
            }
            // Pings keep the socket open but are no heartbeat: they do not reset the deadline.
            Some(Ok(Message::Ping(_) | Message::Pong(_))) => return Ok(()),
            Some(Ok(Message::Binary(_))) => None,
            Some(Ok(Message::Text(t))) => Some(t),
        };
        pace.heard();
        if !pace.admit() {
            return self.rate_limited(pace.strikes).await;
        }
        let Some(text) = text else {
            return self
                .conn
                .error(
                    ErrorCode::Malformed,
                    "binary frames are not part of the protocol; send JSON text",
                    false,
                )
                .await;
        };
        let msg = match decode::<AgentMessage>(text.as_str(), self.shared.limits.max_frame_bytes) {
            Ok(m) => m,
            Err(e) => return self.conn.error(e.code(), e.to_string(), false).await,
        };
        self.shared
            .metrics
            .gateway
            .frames
            .get_or_create(&KindLabels {
                kind: frame_label(&msg),
            })
            .inc();
        // Boxed: a message's handling lives only while it runs; inline, its largest handler
        // would grow every idle session's future, held for the connection's whole life.
        let reply = Box::pin(self.apply(msg)).await?;
        self.reply(reply).await
    }

    /// Refuses a frame over the rate limit; past the abuse threshold, ends the session.
    async fn rate_limited(&mut self, strikes: u32) -> Flow {
        let limits = &self.shared.limits;
        if strikes > limits.abuse_threshold {
            self.conn
                .fail(
                    ErrorCode::RateLimited,
                    "sustained message rate above the limit; closing",
                    (CLOSE_POLICY, "rate limit exceeded"),
                )
                .await;
            return Err(End::Abuse);
        }
        let message = format!(
            "more than {} messages per second; message dropped, resend later",
            limits.rate
        );
        self.conn
            .error(ErrorCode::RateLimited, message, false)
            .await
    }
}

/// The bounded `frames` metric label of an agent message.
fn frame_label(msg: &AgentMessage) -> &'static str {
    match msg {
        AgentMessage::Hello { .. } => "hello",
        AgentMessage::Heartbeat { .. } => "heartbeat",
        AgentMessage::Event { .. } => "event",
        AgentMessage::Telemetry { .. } => "telemetry",
        AgentMessage::Progress { .. } => "progress",
    }
}
