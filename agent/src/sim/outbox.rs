//! A simulated robot's durable outbox: the events, command reports and telemetry batches not
//! yet acknowledged, by `seq` (one sequence for every kind, PROTOCOL.md §6), kept across
//! sessions in memory as the agent keeps its outbox on disk.

use std::collections::BTreeMap;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use lekiwi_protocol::{AgentMessage, Sample, Severity, encode};
use tokio_tungstenite::tungstenite::Message;

use super::Stats;

/// The durable messages of one robot not yet acknowledged, by `seq`, and the next `seq` to use.
/// It lives as long as the robot's task, across sessions, as the agent's outbox does on disk.
#[derive(Default)]
pub(super) struct Outbox {
    next_seq: u64,
    pub(super) unacked: BTreeMap<u64, Pending>,
    /// When each unacknowledged message was last sent.
    sent: BTreeMap<u64, Instant>,
}

/// A durable message kept until acknowledged.
pub(super) enum Pending {
    /// A generated event, made again from its time when resent.
    Tick(i64),
    /// A message of the robot's commands, kept as sent.
    Frame(Box<str>),
    /// A batch of telemetry samples.
    Telemetry(Vec<Sample>),
}

impl Pending {
    /// Counts `self` as acknowledged.
    fn count_acked(&self, stats: &Stats) {
        let counter = match self {
            Pending::Tick(_) | Pending::Frame(_) => &stats.events_acked,
            Pending::Telemetry(_) => &stats.telemetry_acked,
        };
        counter.fetch_add(1, Ordering::Relaxed);
    }
}

impl Outbox {
    /// A new event made at `ts_ms` by the robot's clock: its `seq` and time, kept until
    /// acknowledged.
    pub(super) fn push_at(&mut self, ts_ms: i64, stats: &Stats) -> (u64, i64) {
        self.next_seq += 1;
        self.unacked.insert(self.next_seq, Pending::Tick(ts_ms));
        self.sent.insert(self.next_seq, Instant::now());
        stats.events_generated.fetch_add(1, Ordering::Relaxed);
        (self.next_seq, ts_ms)
    }

    /// A new durable message made by `make` from its `seq`, kept until acknowledged; its frame.
    pub(super) fn push_message(
        &mut self,
        make: impl FnOnce(u64) -> AgentMessage,
        stats: &Stats,
    ) -> Message {
        self.next_seq += 1;
        let frame = encode(&make(self.next_seq));
        self.unacked.insert(
            self.next_seq,
            Pending::Frame(frame.clone().into_boxed_str()),
        );
        self.sent.insert(self.next_seq, Instant::now());
        stats.events_generated.fetch_add(1, Ordering::Relaxed);
        Message::text(frame)
    }

    /// A new telemetry batch: its `seq`, kept until acknowledged.
    pub(super) fn push_telemetry(&mut self, samples: Vec<Sample>, stats: &Stats) -> u64 {
        self.next_seq += 1;
        stats.telemetry_generated.fetch_add(1, Ordering::Relaxed);
        stats
            .samples_generated
            .fetch_add(samples.len() as u64, Ordering::Relaxed);
        self.unacked
            .insert(self.next_seq, Pending::Telemetry(samples));
        self.sent.insert(self.next_seq, Instant::now());
        self.next_seq
    }

    /// The gateway stored `seq`.
    pub(super) fn ack(&mut self, seq: u64, stats: &Stats) {
        self.sent.remove(&seq);
        if let Some(done) = self.unacked.remove(&seq) {
            done.count_acked(stats);
        }
    }

    /// `seq` was (re)sent now.
    pub(super) fn mark_sent(&mut self, seq: u64) {
        if self.unacked.contains_key(&seq) {
            self.sent.insert(seq, Instant::now());
        }
    }

    /// The unacknowledged messages last sent at least `age` ago, in ascending `seq`: refused
    /// (`store_unavailable`, `rate_limited`) or their ack lost, they go again (PROTOCOL.md §6
    /// rule 3).
    pub(super) fn due(&self, age: Duration) -> Vec<u64> {
        let now = Instant::now();
        self.unacked
            .keys()
            .filter(|seq| {
                self.sent
                    .get(seq)
                    .is_none_or(|at| now.duration_since(*at) >= age)
            })
            .copied()
            .collect()
    }

    /// The highest `seq` acknowledged, for `hello.last_acked_seq`.
    pub(super) fn last_acked(&self) -> Option<u64> {
        let below = self
            .unacked
            .keys()
            .next()
            .map_or(self.next_seq, |first| first - 1);
        (below > 0).then_some(below)
    }

    /// The frame of the unacknowledged message `seq` of robot `name`, to send again.
    pub(super) fn frame(name: &str, seq: u64, pending: &Pending) -> Message {
        match pending {
            Pending::Tick(ts_ms) => event(name, seq, *ts_ms),
            Pending::Frame(frame) => Message::text(&**frame),
            Pending::Telemetry(samples) => Message::text(encode(&AgentMessage::Telemetry {
                seq,
                samples: samples.clone(),
            })),
        }
    }
}

/// The event frame for `seq`.
pub(super) fn event(name: &str, seq: u64, ts_ms: i64) -> Message {
    Message::text(encode(&AgentMessage::Event {
        seq,
        ts_ms,
        kind: "sim_tick".into(),
        severity: Severity::Info,
        message: format!("{name} event {seq}"),
        data: serde_json::Value::Null,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A message the gateway refused or whose ack was lost goes again once it has waited;
    /// an acknowledged one never.
    #[test]
    fn unacknowledged_messages_are_due_again_after_a_while() {
        let stats = Stats::default();
        let mut outbox = Outbox::default();
        for _ in 0..3 {
            outbox.push_at(1, &stats);
        }
        assert!(outbox.due(Duration::from_secs(60)).is_empty(), "just sent");
        outbox.ack(2, &stats);
        assert_eq!(outbox.due(Duration::ZERO), [1, 3]);
        outbox.mark_sent(1);
        assert_eq!(outbox.due(Duration::from_millis(50)), Vec::<u64>::new());
        std::thread::sleep(Duration::from_millis(60));
        assert_eq!(outbox.due(Duration::from_millis(50)), [1, 3]);
    }

    #[test]
    fn the_outbox_keeps_what_is_not_acknowledged_and_counts_each_event_once() {
        let stats = Stats::default();
        let mut outbox = Outbox::default();
        assert_eq!(outbox.last_acked(), None);
        for _ in 0..5 {
            outbox.push_at(1, &stats);
        }
        outbox.ack(2, &stats);
        outbox.ack(2, &stats);
        assert_eq!(outbox.last_acked(), None, "seq 1 is still unacknowledged");
        outbox.ack(1, &stats);
        assert_eq!(outbox.last_acked(), Some(2));
        // Replays of 3 and 4 after a reconnect are acknowledged; 5 stays.
        outbox.ack(3, &stats);
        outbox.ack(4, &stats);
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
        outbox.push_at(1, &stats);
        outbox.push_telemetry(vec![sample(3.0)], &stats);
        for seq in [6, 7] {
            outbox.ack(seq, &stats);
        }
        assert_eq!(outbox.unacked.keys().copied().collect::<Vec<_>>(), [8]);
        outbox.ack(8, &stats);
        let load = |c: &std::sync::atomic::AtomicU64| c.load(Ordering::Relaxed);
        assert_eq!(load(&stats.events_acked), 6);
        assert_eq!(load(&stats.telemetry_generated), 2);
        assert_eq!(load(&stats.telemetry_acked), 2);
        assert_eq!(load(&stats.samples_generated), 3);
    }
}
