//! One simulated robot: connects (enrolling the first time), heartbeats, sends durable events
//! at `--events-per-minute` and telemetry batches as the agent does (its own collector, reading
//! a synthetic world: see `Telemetry::synthetic`) from an in-memory outbox (resent after a
//! reconnect until acknowledged, exactly like the agent's durable outbox), carries out the
//! gateway's commands ([`super::commands`]) and reconnects with backoff. Telemetry is sampled
//! while connected only.

use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use futures::stream::SplitSink;
use futures::{SinkExt, StreamExt};
use lekiwi_protocol::{
    AgentMessage, ErrorCode, FEATURE_UPDATE_AGENT, Health, PROTOCOL_VERSION, Sample, ServerMessage,
    SystemFacts, Teleoperation, Vitals, decode, encode,
};
use rand::Rng;
use tokio_tungstenite::tungstenite::Message;

use super::commands::{Commands, Handled, RobotId};
use super::outbox::{Outbox, Pending, event};
use super::{Fleet, Stats, lock};
use crate::connection::{ConnectError, Credentials, Socket, connect_with_ca};
use crate::telemetry::Telemetry;

/// How long a robot whose agent restarts (`update_agent`) stays away, at most: the service
/// manager's restart delay.
const RESTART_DELAY: Duration = Duration::from_millis(500);

/// The `hello` of a simulated robot: a Raspberry Pi running the release and agent build its
/// commands left it on.
fn hello(name: &str, commands: &Commands, last_acked_seq: Option<u64>) -> AgentMessage {
    let (agent_version, agent_digest) = commands.agent();
    AgentMessage::Hello {
        protocol_version: PROTOCOL_VERSION,
        agent_version: agent_version.to_owned(),
        agent_digest: Some(agent_digest.to_owned()),
        system: SystemFacts {
            hostname: Some(name.to_owned()),
            os: Some("Debian GNU/Linux 12 (bookworm)".into()),
            arch: Some("aarch64".into()),
            cpus: Some(4),
            memory_bytes: Some(8 << 30),
            kernel: None,
        },
        current_release: commands.current().cloned(),
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
        features: vec![FEATURE_UPDATE_AGENT.to_owned()],
    }
}

/// How a session ended, which says when to connect again.
enum Ended {
    /// Lost or closed: after the backoff (and the robot's `--late-delay`).
    Lost,
    /// The robot went offline for this long.
    Offline(Duration),
    /// The agent restarts as another build.
    Restart,
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
pub(super) async fn robot(fleet: Fleet, name: String, gateway: usize) {
    let args = &fleet.args;
    let url = &args.gateway[gateway % args.gateway.len()];
    let own = lock(&fleet.tokens).get(&name).cloned();
    let mut creds = Credentials {
        token: own.unwrap_or_else(|| args.enrollment_token.clone()),
        robot: format!("{}/{}", args.namespace, name),
    };
    let mut outbox = Outbox::default();
    let mut commands = Commands::new(fleet.commands.clone());
    let mut sampler = Sampler::new(args, &name);
    let mut first = true;
    let mut backoff =
        crate::backoff::Backoff::new(Duration::from_millis(500), Duration::from_secs(30));
    let timeout = Duration::from_secs_f64(args.connect_timeout);
    loop {
        let id = RobotId {
            name: name.clone(),
            robot: creds.robot.clone(),
            token: creds.token.clone(),
            gateway,
        };
        settle_offline(&mut commands, &id, &mut outbox, &fleet.stats);
        let hello = hello(&name, &commands, outbox.last_acked());
        let floor =
            match connect_with_ca(url, &creds, &hello, timeout, args.ca_file.as_deref()).await {
                Ok((ws, welcome)) => {
                    backoff.reset();
                    if let Some(token) = welcome.robot_token.clone() {
                        lock(&fleet.tokens).insert(name.clone(), token.clone());
                        creds.token = token;
                    }
                    creds.robot = welcome.robot.clone();
                    // Nothing dropped by stored_seq: we pipeline (PROTOCOL.md §6 rule 4).
                    fleet.count_session(std::mem::take(&mut first));
                    let interval = args
                        .heartbeat_interval
                        .map(Duration::from_secs_f64)
                        .unwrap_or(welcome.heartbeat_interval);
                    let robot = RobotId {
                        robot: creds.robot.clone(),
                        token: creds.token.clone(),
                        ..id
                    };
                    let ended = Session {
                        fleet: &fleet,
                        name: &name,
                        interval,
                        outbox: &mut outbox,
                        commands: &mut commands,
                        robot,
                        sampler: sampler.as_mut(),
                        pending: None,
                        last_rtt: None,
                    }
                    .run(ws)
                    .await;
                    fleet.stats.connected.fetch_sub(1, Ordering::Relaxed);
                    match ended {
                        Ended::Lost => args.late_delay_of(&name),
                        Ended::Offline(d) => d,
                        Ended::Restart => RESTART_DELAY,
                    }
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

/// Takes in what the robot's commands reported while it had no session: durable messages
/// into the outbox (sent when it connects), ended tasks (so `hello` names the release now
/// current).
fn settle_offline(commands: &mut Commands, robot: &RobotId, outbox: &mut Outbox, stats: &Stats) {
    while let Some(report) = commands.try_next() {
        if let Handled::Durable(d) = commands.handle(robot, report)
            && !stats.draining.load(Ordering::Relaxed)
        {
            outbox.push_message(|seq| d.message(seq), stats);
        }
    }
}

type Tx = SplitSink<Socket, Message>;

/// What woke a session.
enum Wake {
    Heartbeat,
    Event,
    Sample,
    Batch,
    Report(super::commands::Report),
    Frame(Option<Result<Message, tokio_tungstenite::tungstenite::Error>>),
}

/// What a session does after a wake-up.
enum Step {
    Go,
    /// Send a heartbeat now (a deploy ended: the gateway hears the release at once).
    Heartbeat,
    End(Ended),
}

/// One established session of a simulated robot.
struct Session<'a> {
    fleet: &'a Fleet,
    name: &'a str,
    interval: Duration,
    outbox: &'a mut Outbox,
    commands: &'a mut Commands,
    robot: RobotId,
    sampler: Option<&'a mut Sampler>,
    /// The heartbeat awaiting its ack: its `sent_at_ms` and when it left.
    pending: Option<(i64, Instant)>,
    last_rtt: Option<f64>,
}

impl Session<'_> {
    /// Resends the unacknowledged messages, then heartbeats, sends new events and carries out
    /// commands until the session ends.
    async fn run(mut self, ws: Socket) -> Ended {
        let (mut tx, mut rx) = ws.split();
        self.commands.welcomed();
        let stats = &*self.fleet.stats;
        if !self.resend(&mut tx, Duration::ZERO).await {
            return Ended::Lost;
        }
        // Spread the first heartbeat, event and telemetry batch over one period each.
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
            let wake = tokio::select! {
                _ = tick.tick() => Wake::Heartbeat,
                _ = events.tick(), if event_period.is_some() && making => Wake::Event,
                _ = tokio::time::sleep_until(sample_due.unwrap_or_else(far_future)),
                    if sample_due.is_some() => Wake::Sample,
                _ = batches.tick(), if batch_period.is_some() && making => Wake::Batch,
                report = self.commands.next() => Wake::Report(report),
                frame = rx.next() => Wake::Frame(frame),
            };
            let step = match wake {
                Wake::Heartbeat => Step::Heartbeat,
                // The run began to drain since the wait began: nothing new.
                Wake::Event if !self.fleet.generating() => Step::Go,
                Wake::Event => {
                    let (seq, ts_ms) = self.outbox.push_at(self.clock_ms(), stats);
                    match tx.send(event(self.name, seq, ts_ms)).await {
                        Ok(()) => Step::Go,
                        Err(_) => Step::End(Ended::Lost),
                    }
                }
                Wake::Sample => {
                    self.collect();
                    Step::Go
                }
                Wake::Batch => match self.batch() {
                    Some(frame) => match tx.send(frame).await {
                        Ok(()) => Step::Go,
                        Err(_) => Step::End(Ended::Lost),
                    },
                    None => Step::Go,
                },
                Wake::Report(report) => self.on_report(report, &mut tx).await,
                Wake::Frame(frame) => self.on_frame(frame),
            };
            match step {
                Step::Go => {}
                Step::Heartbeat => {
                    let interval = self.interval;
                    if !self.heartbeat(&mut tx).await || !self.resend(&mut tx, interval).await {
                        return Ended::Lost;
                    }
                }
                Step::End(ended) => return ended,
            }
        }
    }

    /// Sends again, in ascending `seq`, the unacknowledged messages last sent at least `age`
    /// ago; false if the connection failed.
    async fn resend(&mut self, tx: &mut Tx, age: Duration) -> bool {
        let stats = &*self.fleet.stats;
        for seq in self.outbox.due(age) {
            let Some(pending) = self.outbox.unacked.get(&seq) else {
                continue;
            };
            if !matches!(pending, Pending::Telemetry(_)) {
                stats.events_resent.fetch_add(1, Ordering::Relaxed);
            }
            if tx
                .send(Outbox::frame(self.name, seq, pending))
                .await
                .is_err()
            {
                return false;
            }
            self.outbox.mark_sent(seq);
        }
        true
    }

    /// Sends a heartbeat; false if the connection failed.
    async fn heartbeat(&mut self, tx: &mut Tx) -> bool {
        let sent_at_ms = lekiwi_protocol::now_ms();
        self.pending = Some((sent_at_ms, Instant::now()));
        let current = self.commands.current().cloned();
        let vitals = match self.sampler.as_mut() {
            Some(s) => s.telemetry.vitals(),
            None => Vitals {
                cpu_percent: Some(12.0),
                memory_percent: Some(30.0),
                temperature_c: Some(50.0),
                ..Vitals::default()
            },
        };
        let heartbeat = AgentMessage::Heartbeat {
            sent_at_ms,
            rtt_ms: self.last_rtt,
            vitals,
            current_release: current,
            health: None,
            teleoperation: None,
        };
        tx.send(Message::text(encode(&heartbeat))).await.is_ok()
    }

    /// The robot's clock, Unix milliseconds: the real time plus `--clock-offset-seconds`.
    fn clock_ms(&self) -> i64 {
        lekiwi_protocol::now_ms() + self.fleet.args.clock_offset_seconds * 1000
    }

    /// Runs the telemetry samplers that are due; what passes their filters waits for the batch.
    fn collect(&mut self) {
        let clock_ms = self.clock_ms();
        if let Some(s) = self.sampler.as_mut() {
            let samples = s
                .telemetry
                .collect_due(tokio::time::Instant::now(), clock_ms);
            s.pending.extend(samples);
        }
    }

    /// The telemetry batch of the samples collected since the last, if any, kept in the
    /// outbox until acknowledged.
    fn batch(&mut self) -> Option<Message> {
        let s = self.sampler.as_mut()?;
        if s.pending.is_empty() || !self.fleet.generating() {
            return None;
        }
        let samples = std::mem::take(&mut s.pending);
        let seq = self.outbox.push_telemetry(samples, &self.fleet.stats);
        let pending = &self.outbox.unacked[&seq];
        Some(Outbox::frame(self.name, seq, pending))
    }

    /// Something the robot's commands have for the gateway.
    async fn on_report(&mut self, report: super::commands::Report, tx: &mut Tx) -> Step {
        match self.commands.handle(&self.robot, report) {
            // A draining run makes nothing new: every message made is acknowledged or counted.
            Handled::Durable(_) if !self.fleet.generating() => Step::Go,
            Handled::Durable(d) => {
                let stats = &*self.fleet.stats;
                let frame = self.outbox.push_message(|seq| d.message(seq), stats);
                match tx.send(frame).await {
                    Ok(()) => Step::Go,
                    Err(_) => Step::End(Ended::Lost),
                }
            }
            Handled::Finished => Step::Heartbeat,
            // Gone without a word, as a robot that lost its network.
            Handled::Offline(d) => Step::End(Ended::Offline(d)),
            Handled::Restart => {
                let _ = tx.send(Message::Close(None)).await;
                Step::End(Ended::Restart)
            }
        }
    }

    /// A frame from the gateway, or the end of the connection.
    fn on_frame(
        &mut self,
        frame: Option<Result<Message, tokio_tungstenite::tungstenite::Error>>,
    ) -> Step {
        let stats = &*self.fleet.stats;
        let Some(Ok(frame)) = frame else {
            return Step::End(Ended::Lost);
        };
        let Message::Text(text) = frame else {
            if matches!(frame, Message::Close(_)) {
                return Step::End(Ended::Lost);
            }
            return Step::Go;
        };
        match decode::<ServerMessage>(text.as_str(), usize::MAX) {
            Ok(ServerMessage::HeartbeatAck { sent_at_ms, .. }) => {
                if let Some((_, at)) = self.pending.take_if(|(s, _)| *s == sent_at_ms) {
                    self.last_rtt = Some(stats.record_rtt(at.elapsed()));
                }
            }
            Ok(ServerMessage::Ack { seq }) => self.outbox.ack(seq, stats),
            Ok(ServerMessage::Error { code, fatal, .. }) => {
                stats.error_frames.fetch_add(1, Ordering::Relaxed);
                if fatal || code == ErrorCode::Replaced {
                    return Step::End(Ended::Lost);
                }
            }
            Ok(ServerMessage::Command {
                command_id,
                command,
            }) => self.commands.on_command(&self.robot, command_id, command),
            _ => {}
        }
        Step::Go
    }
}

/// A ticker of `period` whose first tick falls at a random point of the first period.
fn spread_interval(period: Duration) -> tokio::time::Interval {
    let offset = rand::rng().random_range(Duration::ZERO..=period);
    tokio::time::interval_at(tokio::time::Instant::now() + offset, period)
}

/// A far-off instant, for a timer that must not fire.
fn far_future() -> tokio::time::Instant {
    tokio::time::Instant::now() + Duration::from_secs(86_400)
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
}
