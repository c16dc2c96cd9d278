//! The connection's life: a connection attempt with the right credentials, the session that
//! follows, and the wait before the next attempt (backoff with full jitter, longer when retrying
//! soon cannot help).

use std::time::Duration;

use futures::SinkExt;
use lekiwi_protocol::ErrorCode;
use tokio::time::Instant;
use tokio_tungstenite::tungstenite::Message;
use tracing::{error, info, warn};

use super::driver::{Ending, Loop};
use super::session::Session;
use super::{Agent, Error};
use crate::backoff::Backoff;
use crate::config::Config;
use crate::connection::{ConnectError, Connector, Socket, Transport, Welcome};

/// Connects over a real WebSocket to the configured gateway.
pub(super) fn websocket(config: &Config) -> Connector<Socket> {
    let url = config.gateway.clone();
    let ca = config.ca_file.clone();
    let timeout = Duration::from_secs(config.connect_timeout_s);
    Box::new(move |creds, hello| {
        let (url, ca) = (url.clone(), ca.clone());
        Box::pin(async move {
            crate::connection::connect_with_ca(&url, &creds, &hello, timeout, ca.as_deref()).await
        })
    })
}

impl Agent {
    /// Starts a connection attempt, with the robot's own token or the enrollment token.
    pub(super) fn start_connecting<S>(&mut self, lp: &mut Loop<S>) -> Result<(), Error> {
        let (creds, enrolling) = self.credentials()?;
        let hello = self.hello()?;
        info!(
            gateway = %self.config.gateway,
            robot = %creds.robot,
            enrolling,
            attempt = lp.backoff.attempts(),
            "connecting"
        );
        lp.connecting = Some(((lp.connect)(creds, hello), enrolling));
        Ok(())
    }

    /// A connection attempt ended: the session starts, or the next attempt is scheduled.
    pub(super) async fn on_connected<S: Transport>(
        &mut self,
        lp: &mut Loop<S>,
        res: Result<(S, Welcome), ConnectError>,
    ) -> Result<Option<Ending>, Error> {
        let enrolling = lp.connecting.take().is_some_and(|(_, e)| e);
        match res {
            Ok((ws, welcome)) => self.start_session(lp, ws, welcome, enrolling).await,
            Err(e) => {
                self.on_connect_failed(lp, &e, enrolling);
                Ok(None)
            }
        }
    }

    /// The gateway welcomed us: apply the welcome and send the first heartbeat.
    async fn start_session<S: Transport>(
        &mut self,
        lp: &mut Loop<S>,
        ws: S,
        welcome: Welcome,
        enrolling: bool,
    ) -> Result<Option<Ending>, Error> {
        info!(
            robot = %welcome.robot,
            heartbeat_s = welcome.heartbeat_interval.as_secs(),
            stored_seq = ?welcome.stored_seq,
            "connected"
        );
        let mut s = Session::new(ws, welcome);
        self.on_welcome(&s.welcome, enrolling)?;
        self.commit_agent_update()?;
        self.status
            .send_modify(|st| st.robot = s.welcome.robot.clone());
        let ending = (!self.send_heartbeat(&mut s).await).then(Ending::send_failed);
        lp.session = Some(s);
        Ok(ending)
    }

    /// Schedules the next attempt; a refused robot token switches to the enrollment token
    /// once, other refusals retry at the slowest rate. A refused enrollment goes back to the
    /// robot's own token, if it has one: the gateway never lets an enrollment token take over an
    /// enrolled robot, so the two alternate at the slowest rate until one is accepted.
    fn on_connect_failed<S>(&mut self, lp: &mut Loop<S>, e: &ConnectError, enrolling: bool) {
        let backoff = &mut lp.backoff;
        if enrolling && matches!(e, ConnectError::Forbidden(_)) {
            error!(error = %e, "enrollment refused: this robot is enrolled already; retrying at the slowest rate");
            self.reenroll = false;
            backoff.saturate();
            lp.reconnect_at = Instant::now() + backoff.ceiling();
        } else if matches!(
            e,
            ConnectError::Unauthorized(_) | ConnectError::Forbidden(_)
        ) {
            if self.enrollment_token.is_some() && !enrolling {
                warn!(error = %e, "the robot's token was refused; enrolling again with the enrollment token");
                self.reenroll = true;
            } else {
                error!(error = %e, "credentials refused; retrying at the slowest rate");
                backoff.saturate();
                lp.reconnect_at = Instant::now() + backoff.ceiling();
            }
        } else if !e.retryable() {
            error!(error = %e, "cannot connect; retrying at the slowest rate");
            backoff.saturate();
        }
        // A gateway's `Retry-After` is the least wait; the jittered backoff comes on top, so
        // robots told the same second do not all come back in it together.
        let delay = backoff.next_delay() + e.retry_after().unwrap_or_default();
        warn!(error = %e, retry_in_ms = delay.as_millis() as u64, attempt = backoff.attempts(), "connection failed");
        // A refused token waits at least the cap (set above).
        lp.reconnect_at = lp.reconnect_at.max(Instant::now() + delay);
    }

    /// Ends the session: deletes what was acknowledged, closes the socket, and schedules the
    /// next attempt.
    pub(super) async fn end_session<S: Transport>(
        &mut self,
        lp: &mut Loop<S>,
        mut s: Session<S>,
        ending: Ending,
    ) -> Result<(), Error> {
        self.flush_acks()?;
        lp.next_ack_flush = None;
        let _ = tokio::time::timeout(Duration::from_secs(1), s.ws.send(Message::Close(None))).await;
        let lasted = s.started.elapsed();
        // A session that held for a heartbeat interval was a success (PROTOCOL.md §11).
        if lasted >= s.welcome.heartbeat_interval {
            lp.backoff.reset();
        }
        let delay = retry_delay(&mut lp.backoff, ending.code);
        warn!(
            reason = ending.why,
            lasted_s = lasted.as_secs(),
            retry_in_ms = delay.as_millis() as u64,
            "disconnected"
        );
        lp.reconnect_at = Instant::now() + delay;
        Ok(())
    }
}

/// The window over which a robot whose held session was lost without a word (its gateway
/// crashed, a network path broke) comes back: the gateway's whole fleet lost it at the same
/// moment, and the first retries of 10,000 robots spread over 10 s reach the surviving gateway
/// at about 1,000 a second instead of all within the backoff's first 0.5 s.
const LOST_SESSION_SPREAD: Duration = Duration::from_secs(10);

/// How long to wait before reconnecting after a session the gateway ended with `code`.
fn retry_delay(backoff: &mut Backoff, code: Option<ErrorCode>) -> Duration {
    match code {
        // Another replica takes over: come back soon, spread over 5 s.
        Some(ErrorCode::ShuttingDown) => Duration::from_millis(rand::random_range(0..=5000)),
        // A held session lost abruptly: uniform over the spread (never beyond the backoff's
        // cap); a failure after it continues the backoff.
        None if backoff.attempts() == 0 => {
            backoff.next_delay();
            let spread = LOST_SESSION_SPREAD.min(backoff.cap());
            let ms = u64::try_from(spread.as_millis()).unwrap_or(u64::MAX);
            Duration::from_millis(rand::random_range(0..=ms))
        }
        // Retrying soon cannot help.
        Some(ErrorCode::Replaced | ErrorCode::UnsupportedVersion) => {
            backoff.saturate();
            backoff.ceiling() + backoff.next_delay()
        }
        _ => backoff.next_delay(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 10,000 robots lose their gateway at the same moment, each after a session that held:
    /// their first reconnects, counted per second, never exceed twice the mean rate over the
    /// spread (before the spread, all 10,000 came within the first 0.5 s).
    #[test]
    fn a_fleet_that_lost_its_gateway_comes_back_spread_out() {
        const ROBOTS: usize = 10_000;
        // The agent's defaults: backoff from 500 ms up to 60 s.
        let mut per_second = [0usize; 11];
        for _ in 0..ROBOTS {
            let mut backoff = Backoff::new(Duration::from_millis(500), Duration::from_secs(60));
            let delay = retry_delay(&mut backoff, None);
            assert!(delay <= LOST_SESSION_SPREAD, "{delay:?}");
            per_second[delay.as_secs() as usize] += 1;
            assert_eq!(
                backoff.attempts(),
                1,
                "a failure next continues the backoff"
            );
        }
        let mean = ROBOTS / LOST_SESSION_SPREAD.as_secs() as usize;
        let peak = per_second.iter().copied().max().unwrap_or_default();
        assert!(peak <= 2 * mean, "{per_second:?}");
    }

    /// The spread never exceeds the configured cap (tests and impatient robots set it low),
    /// and a robot already backing off keeps its backoff.
    #[test]
    fn the_spread_respects_the_cap_and_an_ongoing_backoff() {
        let mut quick = Backoff::new(Duration::from_millis(200), Duration::from_secs(2));
        assert!(retry_delay(&mut quick, None) <= Duration::from_secs(2));
        let mut failing = Backoff::new(Duration::from_millis(100), Duration::from_secs(60));
        failing.next_delay();
        assert!(retry_delay(&mut failing, None) <= Duration::from_millis(200));
    }
}
