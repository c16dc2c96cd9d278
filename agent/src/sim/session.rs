//! One simulated robot: connects (enrolling the first time), heartbeats, sends durable events
//! at `--events-per-minute` and telemetry batches as the agent does (its own collector, reading
//! a synthetic world: see `Telemetry::synthetic`) from an in-memory outbox (resent after a
//! reconnect until acknowledged, exactly like the agent's durable outbox), and reconnects with
//! backoff. Telemetry is sampled while connected only.

use std::collections::BTreeMap;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use futures::{SinkExt, StreamExt};
use lekiwi_protocol::{
    AgentMessage, ErrorCode, Health, PROTOCOL_VERSION, Release, Sample, ServerMessage, Severity,
    SystemFacts, Teleoperation, Vitals, decode, encode,
};
use rand::Rng;
use tokio_tungstenite::tungstenite::Message;

use super::{Fleet, Stats, lock};
use crate::connection::{ConnectError, Credentials, connect_with_ca};
use crate::telemetry::Telemetry;

/// A durable message not acknowledged yet: what its frame is made from.
pub(super) enum Durable {
    /// An event made at this time (Unix milliseconds).
    Event(i64),
    /// A batch of telemetry samples.
    Telemetry(Vec<Sample>),
}

/// The durable messages of one robot not yet acknowledged, by `seq` (one sequence for every
/// kind, PROTOCOL.md §6), and the next `seq` to use. It lives as long as the robot's task,
/// across sessions, as the agent's outbox does on disk.
#[derive(Default)]
pub(super) struct Outbox {
    next_seq: u64,
    unacked: BTreeMap<u64, Durable>,
}

impl Outbox {
    /// A new event: its `seq` and time, kept until acknowledged.
    fn push(&mut self, stats: &Stats) -> (u64, i64) {
        self.next_seq += 1;
        let ts_ms = lekiwi_protocol::now_ms();
        self.unacked.insert(self.next_seq, Durable::Event(ts_ms));
        stats.events_generated.fetch_add(1, Ordering::Relaxed);
        (self.next_seq, ts_ms)
    }

    /// A new telemetry batch: its `seq`, kept until acknowledged.
    fn push_telemetry(&mut self, samples: Vec<Sample>, stats: &Stats) -> u64 {
        self.next_seq += 1;
        stats.telemetry_generated.fetch_add(1, Ordering::Relaxed);
        stats
            .samples_generated
            .fetch_add(samples.len() as u64, Ordering::Relaxed);
        self.unacked
            .insert(self.next_seq, Durable::Telemetry(samples));
        self.next_seq
    }

    /// The gateway stored `seq`.
    fn ack(&mut self, seq: u64, stats: &Stats) {
        if let Some(done) = self.unacked.remove(&seq) {
            count_acked(&done, stats);
        }
    }

    /// `welcome.stored_seq`: everything up to it is stored already.
    fn stored_through(&mut self, stored: Option<u64>, stats: &Stats) {
        let Some(stored) = stored else { return };
        let keep = self.unacked.split_off(&(stored + 1));
        for done in std::mem::replace(&mut self.unacked, keep).values() {
            count_acked(done, stats);
        }
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

fn count_acked(done: &Durable, stats: &Stats) {
    let counter = match done {
        Durable::Event(_) => &stats.events_acked,
        Durable::Telemetry(_) => &stats.telemetry_acked,
    };
    counter.fetch_add(1, Ordering::Relaxed);
}

/// The frame of the durable message `seq`.
fn frame(name: &str, seq: u64, durable: &Durable) -> Message {
    Message::text(encode(&match durable {
        &Durable::Event(ts_ms) => AgentMessage::Event {
            seq,
            ts_ms,
            kind: "sim_tick".into(),
            severity: Severity::Info,
            message: format!("{name} event {seq}"),
            data: serde_json::Value::Null,
        },
        Durable::Telemetry(samples) => AgentMessage::Telemetry {
            seq,
            samples: samples.clone(),
        },
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

/// One robot's telemetry: the agent's collector over the robot's synthetic world, and the
/// samples collected since the last batch.
pub(super) struct Sampler {
    telemetry: Telemetry,
    pending: Vec<Sample>,
    batch_every: Duration,
}

impl Sampler {
    /// The sampler of robot `name` as `--telemetry-interval-s` asks (none for 0).
    fn new(args: &super::Args, name: &str) -> Option<Self> {
        if args.telemetry_interval_s == 0 {
            return None;
        }
        let config = crate::config::Config::default()
            .with_telemetry_every(args.telemetry_interval_s, args.telemetry_batch_interval_s);
        Some(Self {
            telemetry: Telemetry::synthetic(&config, name),
            pending: Vec::new(),
            batch_every: Duration::from_secs(config.telemetry_batch_interval_s),
        })
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
    let mut sampler = Sampler::new(args, &name);
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
                        sampler: sampler.as_mut(),
                        pending_rtt: None,
                        last_rtt: None,
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
    sampler: Option<&'a mut Sampler>,
    /// The heartbeat awaiting its ack: its `sent_at_ms` and when it was sent.
    pending_rtt: Option<(i64, Instant)>,
    /// The round trip of the last acknowledged heartbeat, ms, sent with the next.
    last_rtt: Option<f64>,
}

/// A far-off instant, for a timer that must not fire.
fn far_future() -> tokio::time::Instant {
    tokio::time::Instant::now() + Duration::from_secs(86_400)
}

impl Session<'_> {
    /// Resends the unacknowledged messages, then heartbeats and sends new events and telemetry
    /// until the session ends.
    async fn run(mut self, ws: crate::connection::Socket) {
        let (mut tx, mut rx) = ws.split();
        for (&seq, durable) in self.outbox.unacked.iter() {
            if let Durable::Event(_) = durable {
                let resent = &self.fleet.stats.events_resent;
                resent.fetch_add(1, Ordering::Relaxed);
            }
            if tx.send(frame(self.name, seq, durable)).await.is_err() {
                return;
            }
        }
        // Spread the first heartbeat, event and batch over one period each.
        let mut tick = spread_interval(self.interval);
        let event_period = self
            .fleet
            .args
            .events_per_minute
            .filter(|r| *r > 0.0)
            .map(|r| Duration::from_secs_f64(60.0 / r));
        let mut events = spread_interval(event_period.unwrap_or(Duration::from_secs(3600)));
        let batch_period = self.sampler.as_ref().map(|s| s.batch_every);
        let mut batches = spread_interval(batch_period.unwrap_or(Duration::from_secs(3600)));
        loop {
            let sample_due = self.sampler.as_ref().map(|s| s.telemetry.next_due());
            let making = self.fleet.generating();
            let sent = tokio::select! {
                _ = tick.tick() => {
                    let heartbeat = self.heartbeat();
                    tx.send(heartbeat).await
                }
                _ = events.tick(), if event_period.is_some() && making => {
                    let (seq, ts_ms) = self.outbox.push(&self.fleet.stats);
                    tx.send(frame(self.name, seq, &Durable::Event(ts_ms))).await
                }
                _ = tokio::time::sleep_until(sample_due.unwrap_or_else(far_future)),
                    if sample_due.is_some() => {
                    self.collect();
                    Ok(())
                }
                _ = batches.tick(), if batch_period.is_some() && making => {
                    match self.batch() {
                        Some(message) => tx.send(message).await,
                        None => Ok(()),
                    }
                }
                frame = rx.next() => {
                    let Some(Ok(frame)) = frame else { return };
                    if !self.on_frame(frame) {
                        return;
                    }
                    Ok(())
                }
            };
            if sent.is_err() {
                return;
            }
        }
    }

    /// A heartbeat: the telemetry's latest readings, or fixed vitals without telemetry.
    fn heartbeat(&mut self) -> Message {
        let sent_at_ms = lekiwi_protocol::now_ms();
        self.pending_rtt = Some((sent_at_ms, Instant::now()));
        let vitals = match self.sampler.as_mut() {
            Some(s) => s.telemetry.vitals(),
            None => Vitals {
                cpu_percent: Some(12.0),
                memory_percent: Some(30.0),
                temperature_c: Some(50.0),
                ..Vitals::default()
            },
        };
        Message::text(encode(&AgentMessage::Heartbeat {
            sent_at_ms,
            rtt_ms: self.last_rtt,
            vitals,
            current_release: None,
            health: None,
            teleoperation: None,
        }))
    }

    /// Runs the telemetry samplers that are due; what passes their filters waits for the batch.
    fn collect(&mut self) {
        if let Some(s) = self.sampler.as_mut() {
            let samples = s
                .telemetry
                .collect_due(tokio::time::Instant::now(), lekiwi_protocol::now_ms());
            s.pending.extend(samples);
        }
    }

    /// The telemetry batch of the samples collected since the last, if any, kept in the
    /// outbox until acknowledged.
    fn batch(&mut self) -> Option<Message> {
        let s = self.sampler.as_mut()?;
        if s.pending.is_empty() {
            return None;
        }
        let samples = std::mem::take(&mut s.pending);
        let seq = self
            .outbox
            .push_telemetry(samples.clone(), &self.fleet.stats);
        Some(frame(self.name, seq, &Durable::Telemetry(samples)))
    }

    /// Handles a frame from the gateway; false when the session is over.
    fn on_frame(&mut self, frame: Message) -> bool {
        let stats = &*self.fleet.stats;
        let Message::Text(text) = frame else {
            return !matches!(frame, Message::Close(_));
        };
        match decode::<ServerMessage>(text.as_str(), usize::MAX) {
            Ok(ServerMessage::HeartbeatAck { sent_at_ms, .. }) => {
                if let Some((_, at)) = self.pending_rtt.take_if(|(s, _)| *s == sent_at_ms) {
                    self.last_rtt = Some(stats.record_rtt(at.elapsed()));
                }
            }
            Ok(ServerMessage::Ack { seq }) => self.outbox.ack(seq, stats),
            Ok(ServerMessage::Error { code, fatal, .. }) => {
                stats.error_frames.fetch_add(1, Ordering::Relaxed);
                if fatal || code == ErrorCode::Replaced {
                    return false;
                }
            }
            _ => {}
        }
        true
    }
}

/// A ticker of `period` whose first tick falls at a random point of the first period.
fn spread_interval(period: Duration) -> tokio::time::Interval {
    let offset = rand::rng().random_range(Duration::ZERO..=period);
    tokio::time::interval_at(tokio::time::Instant::now() + offset, period)
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
        // Telemetry batches share the sequence and are counted apart from events.
        let sample = |v| Sample {
            metric: "cpu_percent".into(),
            ts_ms: 1,
            value: v,
        };
        assert_eq!(
            outbox.push_telemetry(vec![sample(1.0), sample(2.0)], &stats),
            6
        );
        outbox.push(&stats);
        outbox.push_telemetry(vec![sample(3.0)], &stats);
        outbox.stored_through(Some(7), &stats);
        assert_eq!(outbox.unacked.keys().copied().collect::<Vec<_>>(), [8]);
        outbox.ack(8, &stats);
        let load = |c: &std::sync::atomic::AtomicU64| c.load(Ordering::Relaxed);
        assert_eq!(load(&stats.events_acked), 6);
        assert_eq!(load(&stats.telemetry_generated), 2);
        assert_eq!(load(&stats.telemetry_acked), 2);
        assert_eq!(load(&stats.samples_generated), 3);
    }
}
