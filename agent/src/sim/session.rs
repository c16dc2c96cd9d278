//! One simulated robot: connects (enrolling the first time), heartbeats, sends durable events
//! at `--events-per-minute` from an in-memory outbox (resent after a reconnect until
//! acknowledged, exactly like the agent's durable outbox), and reconnects with backoff.

use std::collections::BTreeMap;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use futures::{SinkExt, StreamExt};
use lekiwi_protocol::{
    AgentMessage, ErrorCode, Health, PROTOCOL_VERSION, Release, ServerMessage, Severity,
    SystemFacts, Teleoperation, Vitals, decode, encode,
};
use rand::Rng;
use tokio_tungstenite::tungstenite::Message;

use super::{Fleet, Stats, lock};
use crate::connection::{ConnectError, Credentials, connect_with_ca};

/// The durable events of one robot not yet acknowledged, by `seq`, and the next `seq` to use.
/// It lives as long as the robot's task, across sessions, as the agent's outbox does on disk.
#[derive(Default)]
pub(super) struct Outbox {
    next_seq: u64,
    unacked: BTreeMap<u64, i64>,
}

impl Outbox {
    /// A new event: its `seq` and time, kept until acknowledged.
    fn push(&mut self, stats: &Stats) -> (u64, i64) {
        self.next_seq += 1;
        let ts_ms = lekiwi_protocol::now_ms();
        self.unacked.insert(self.next_seq, ts_ms);
        stats.events_generated.fetch_add(1, Ordering::Relaxed);
        (self.next_seq, ts_ms)
    }

    /// The gateway stored `seq`.
    fn ack(&mut self, seq: u64, stats: &Stats) {
        if self.unacked.remove(&seq).is_some() {
            stats.events_acked.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// `welcome.stored_seq`: everything up to it is stored already.
    fn stored_through(&mut self, stored: Option<u64>, stats: &Stats) {
        let Some(stored) = stored else { return };
        let keep = self.unacked.split_off(&(stored + 1));
        let dropped = std::mem::replace(&mut self.unacked, keep).len();
        stats
            .events_acked
            .fetch_add(dropped as u64, Ordering::Relaxed);
    }

    /// The highest `seq` acknowledged, for `hello.last_acked_seq`.
    fn last_acked(&self) -> Option<u64> {
        let below = self
            .unacked
            .keys()
            .next()
            .map_or(self.next_seq, |first| first - 1);
        (below > 0).then_some(below)
    }
}

/// The event frame for `seq`.
fn event(name: &str, seq: u64, ts_ms: i64) -> Message {
    Message::text(encode(&AgentMessage::Event {
        seq,
        ts_ms,
        kind: "sim_tick".into(),
        severity: Severity::Info,
        message: format!("{name} event {seq}"),
        data: serde_json::Value::Null,
    }))
}

/// The `hello` of a simulated robot: a Raspberry Pi running the fleet's release.
fn hello(name: &str, release: &Release, last_acked_seq: Option<u64>) -> AgentMessage {
    AgentMessage::Hello {
        protocol_version: PROTOCOL_VERSION,
        agent_version: concat!("sim-", env!("CARGO_PKG_VERSION")).to_owned(),
        agent_digest: None,
        system: SystemFacts {
            hostname: Some(name.to_owned()),
            os: Some("Debian GNU/Linux 12 (bookworm)".into()),
            arch: Some("aarch64".into()),
            cpus: Some(4),
            memory_bytes: Some(8 << 30),
            kernel: None,
        },
        current_release: Some(release.clone()),
        last_acked_seq,
        health: Some(Health {
            healthy: true,
            message: None,
            reason: None,
        }),
        teleoperation: Some(Teleoperation {
            active: false,
            score: Some(0.0),
        }),
        features: Vec::new(),
    }
}

/// One simulated robot, forever: connect, run the session, back off, again.
pub(super) async fn robot(fleet: Fleet, name: String, url: String) {
    let args = &fleet.args;
    let own = lock(&fleet.tokens).get(&name).cloned();
    let mut creds = Credentials {
        token: own.unwrap_or_else(|| args.enrollment_token.clone()),
        robot: format!("{}/{}", args.namespace, name),
    };
    let mut outbox = Outbox::default();
    let mut first = true;
    let mut backoff =
        crate::backoff::Backoff::new(Duration::from_millis(500), Duration::from_secs(30));
    let timeout = Duration::from_secs_f64(args.connect_timeout);
    loop {
        let hello = hello(&name, &fleet.release, outbox.last_acked());
        let floor =
            match connect_with_ca(&url, &creds, &hello, timeout, args.ca_file.as_deref()).await {
                Ok((ws, welcome)) => {
                    backoff.reset();
                    if let Some(token) = welcome.robot_token.clone() {
                        lock(&fleet.tokens).insert(name.clone(), token.clone());
                        creds.token = token;
                    }
                    creds.robot = welcome.robot.clone();
                    outbox.stored_through(welcome.stored_seq, &fleet.stats);
                    fleet.count_session(std::mem::take(&mut first));
                    let interval = args
                        .heartbeat_interval
                        .map(Duration::from_secs_f64)
                        .unwrap_or(welcome.heartbeat_interval);
                    Session {
                        fleet: &fleet,
                        name: &name,
                        interval,
                        outbox: &mut outbox,
                    }
                    .run(ws)
                    .await;
                    fleet.stats.connected.fetch_sub(1, Ordering::Relaxed);
                    args.late_delay_of(&name)
                }
                Err(e) => {
                    fleet.stats.connect_errors.fetch_add(1, Ordering::Relaxed);
                    if matches!(e, ConnectError::Unauthorized(_)) {
                        eprintln!("{name}: {e}");
                        // A stale token (rotated elsewhere): enroll again.
                        creds.token = args.enrollment_token.clone();
                    }
                    e.retry_after().unwrap_or_default()
                }
            };
        // A server's Retry-After first, then full jitter, so a fleet does not come back in
        // lockstep (PROTOCOL.md §11).
        tokio::time::sleep(floor + backoff.next_delay()).await;
    }
}

/// One established session of a simulated robot.
struct Session<'a> {
    fleet: &'a Fleet,
    name: &'a str,
    interval: Duration,
    outbox: &'a mut Outbox,
}

impl Session<'_> {
    /// Resends the unacknowledged events, then heartbeats and sends new events until the session
    /// ends.
    async fn run(self, ws: crate::connection::Socket) {
        let Session {
            fleet,
            name,
            interval,
            outbox,
        } = self;
        let stats = &*fleet.stats;
        let (mut tx, mut rx) = ws.split();
        for (&seq, &ts_ms) in &outbox.unacked {
            stats.events_resent.fetch_add(1, Ordering::Relaxed);
            if tx.send(event(name, seq, ts_ms)).await.is_err() {
                return;
            }
        }
        // Spread the first heartbeat and the first event over one period each.
        let mut tick = spread_interval(interval);
        let event_period = fleet
            .args
            .events_per_minute
            .filter(|r| *r > 0.0)
            .map(|r| Duration::from_secs_f64(60.0 / r));
        let mut events = spread_interval(event_period.unwrap_or(Duration::from_secs(3600)));
        let mut pending: Option<(i64, Instant)> = None;
        let mut last_rtt: Option<f64> = None;
        loop {
            tokio::select! {
                _ = tick.tick() => {
                    let sent_at_ms = lekiwi_protocol::now_ms();
                    pending = Some((sent_at_ms, Instant::now()));
                    if tx.send(heartbeat(sent_at_ms, last_rtt)).await.is_err() {
                        return;
                    }
                }
                _ = events.tick(), if event_period.is_some() && fleet.generating() => {
                    let (seq, ts_ms) = outbox.push(stats);
                    if tx.send(event(name, seq, ts_ms)).await.is_err() {
                        return;
                    }
                }
                frame = rx.next() => {
                    let Some(Ok(frame)) = frame else { return };
                    let Message::Text(text) = frame else {
                        if matches!(frame, Message::Close(_)) { return; }
                        continue;
                    };
                    match decode::<ServerMessage>(text.as_str(), usize::MAX) {
                        Ok(ServerMessage::HeartbeatAck { sent_at_ms, .. }) => {
                            if let Some((_, at)) = pending.take_if(|(s, _)| *s == sent_at_ms) {
                                last_rtt = Some(stats.record_rtt(at.elapsed()));
                            }
                        }
                        Ok(ServerMessage::Ack { seq }) => outbox.ack(seq, stats),
                        Ok(ServerMessage::Error { code, fatal, .. }) => {
                            stats.error_frames.fetch_add(1, Ordering::Relaxed);
                            if fatal || code == ErrorCode::Replaced {
                                return;
                            }
                        }
                        _ => {}
                    }
                }
            }
        }
    }
}

/// A ticker of `period` whose first tick falls at a random point of the first period.
fn spread_interval(period: Duration) -> tokio::time::Interval {
    let offset = rand::rng().random_range(Duration::ZERO..=period);
    tokio::time::interval_at(tokio::time::Instant::now() + offset, period)
}

/// A heartbeat with fixed vitals.
fn heartbeat(sent_at_ms: i64, rtt_ms: Option<f64>) -> Message {
    Message::text(encode(&AgentMessage::Heartbeat {
        sent_at_ms,
        rtt_ms,
        vitals: Vitals {
            cpu_percent: Some(12.0),
            memory_percent: Some(30.0),
            temperature_c: Some(50.0),
            ..Vitals::default()
        },
        current_release: None,
        health: None,
        teleoperation: None,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    /// `--late-share` picks about that share of the robots, the same ones each time; none by
    /// default.
    #[test]
    fn late_robots_are_a_stable_share() {
        let args = |extra: &[&str]| {
            let base = ["lekiwi-sim", "--enrollment-token", "t"];
            super::super::Args::parse_from(base.iter().chain(extra))
        };
        let names: Vec<String> = (1..=10_000).map(|i| format!("bench-{i:05}")).collect();
        let late = |a: &super::super::Args| -> Vec<&String> {
            names
                .iter()
                .filter(|n| !a.late_delay_of(n).is_zero())
                .collect()
        };
        assert!(late(&args(&[])).is_empty());
        let some = args(&["--late-share", "0.01", "--late-delay", "25"]);
        let picked = late(&some);
        assert!((70..=130).contains(&picked.len()), "{}", picked.len());
        assert_eq!(picked, late(&some), "the same robots again");
        assert_eq!(some.late_delay_of(picked[0]), Duration::from_secs(25));
    }

    #[test]
    fn the_outbox_keeps_what_is_not_acknowledged_and_counts_each_event_once() {
        let stats = Stats::default();
        let mut outbox = Outbox::default();
        assert_eq!(outbox.last_acked(), None);
        for _ in 0..5 {
            outbox.push(&stats);
        }
        outbox.ack(2, &stats);
        outbox.ack(2, &stats);
        assert_eq!(outbox.last_acked(), None, "seq 1 is still unacknowledged");
        outbox.ack(1, &stats);
        assert_eq!(outbox.last_acked(), Some(2));
        // A new session's welcome says 4 is stored: 3 and 4 count as acknowledged, 5 stays.
        outbox.stored_through(Some(4), &stats);
        assert_eq!(outbox.unacked.keys().copied().collect::<Vec<_>>(), [5]);
        assert_eq!(outbox.last_acked(), Some(4));
        assert_eq!(stats.events_generated.load(Ordering::Relaxed), 5);
        assert_eq!(stats.events_acked.load(Ordering::Relaxed), 4);
        outbox.ack(5, &stats);
        assert_eq!(outbox.last_acked(), Some(5));
        assert_eq!(stats.events_acked.load(Ordering::Relaxed), 5);
    }
}
