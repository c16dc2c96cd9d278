//! Telemetry collector: one cheap `sysinfo` sampler per concern, each on its own interval, with
//! delta compression (a value is sent only when it moved past its threshold, plus a periodic
//! full sample), and the current readings for heartbeats.
//!
//! # Metrics
//!
//! Config keys without their `telemetry` prefix; a change must exceed the threshold.
//!
//! | Metric               | Unit         | Interval               | Sent on a change over        |
//! |----------------------|--------------|------------------------|------------------------------|
//! | `cpu_percent`        | %, all cores | `CpuIntervalS`         | `CpuDelta` points            |
//! | `memory_percent`     | %, RAM used  | `MemoryIntervalS`      | `MemoryDelta` points         |
//! | `memory_used_bytes`  | bytes        | `MemoryIntervalS`      | (sent with `memory_percent`) |
//! | `net_rx_bytes_per_s` | bytes/s      | `NetworkIntervalS`     | `NetworkDelta` × last sent   |
//! | `net_tx_bytes_per_s` | bytes/s      | `NetworkIntervalS`     | `NetworkDelta` × last sent   |
//! | `temperature_c`      | °C           | `TemperatureIntervalS` | `TemperatureDelta` °C        |
//! | `disk_percent`       | %, `/` used  | `DiskIntervalS`        | `DiskDelta` points           |
//!
//! Network rates also ignore changes under 1 KiB/s ([`NETWORK_DELTA_FLOOR_BYTES_PER_S`]). Every
//! metric is also sent when `telemetryFullIntervalS` passed since it was last sent, so
//! the fleet sees each metric at least that often, and its first reading is always sent.
//!
//! - CPU is the average over the sampler's interval (from `/proc/stat` counters).
//! - Memory in use is total minus available (what the kernel could not hand out without
//!   swapping).
//! - Network rates are summed over every interface but loopback, from the kernel's byte counters
//!   over the time since the previous network sample.
//! - Temperature is the hottest CPU/SoC sensor (`cpu_thermal` on a Raspberry Pi), else the
//!   hottest sensor; not reported on machines without sensors (e.g. in a container).
//! - Disk is the file system mounted at `/` (else the largest), counting the blocks reserved for
//!   root as used: 100 % means ordinary processes cannot write.
//!
//! Percent and °C values are rounded to 0.1, bytes to whole numbers, which keeps the frames short.
//! The agent runs on a Raspberry Pi next to the robot's own software, so each sampler refreshes
//! only what it reads (never `System::new_all()`), and all samplers share one time grid: with the
//! default intervals the agent wakes once every 5 s for telemetry.

use std::fmt;
use std::time::Duration;

use lekiwi_protocol::{Sample, Vitals};
use tokio::time::Instant;
use tracing::{debug, info, warn};

use crate::config::Config;

mod delta;
mod probe;
mod synthetic;
mod thermal;

pub use delta::{
    CompressionStats, DeltaFilter, Metric, MetricStats, NETWORK_DELTA_FLOOR_BYTES_PER_S, Threshold,
};
use probe::{Probe, SystemProbe};
pub use probe::{fs_use_percent, system_facts};

/// Delay from [`Telemetry::new`] to the first collection: long enough for a meaningful first CPU
/// reading (it needs two counter snapshots), short enough that the fleet sees the robot's state
/// right after start.
pub const FIRST_SAMPLE_DELAY: Duration = Duration::from_secs(1);

/// A group of metrics read together by one refresh, on one interval.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Sampler {
    Cpu,
    Memory,
    Network,
    Temperature,
    Disk,
}

impl Sampler {
    const ALL: [Sampler; 5] = [
        Sampler::Cpu,
        Sampler::Memory,
        Sampler::Network,
        Sampler::Temperature,
        Sampler::Disk,
    ];

    fn name(self) -> &'static str {
        match self {
            Sampler::Cpu => "cpu",
            Sampler::Memory => "memory",
            Sampler::Network => "network",
            Sampler::Temperature => "temperature",
            Sampler::Disk => "disk",
        }
    }

    fn interval_s(self, config: &Config) -> u64 {
        match self {
            Sampler::Cpu => config.telemetry_cpu_interval_s,
            Sampler::Memory => config.telemetry_memory_interval_s,
            Sampler::Network => config.telemetry_network_interval_s,
            Sampler::Temperature => config.telemetry_temperature_interval_s,
            Sampler::Disk => config.telemetry_disk_interval_s,
        }
    }
}

/// One sampler's schedule.
#[derive(Debug)]
struct Slot {
    sampler: Sampler,
    interval: Duration,
    next: Instant,
    /// Whether the last run gave a reading; `None` before the first run.
    available: Option<bool>,
}

/// One metric's compression state and counters.
#[derive(Debug)]
struct MetricState {
    /// `None` for a metric sent exactly when its sampler's leading metric is
    /// (`memory_used_bytes` follows `memory_percent`: both describe the same reading).
    filter: Option<DeltaFilter>,
    latest: Option<f64>,
    taken: u64,
    emitted: u64,
}

/// The telemetry collector the agent's run loop drives: sleep until [`Telemetry::next_due`],
/// then call [`Telemetry::collect_due`] and queue what it returns.
pub struct Telemetry {
    probe: Box<dyn Probe>,
    slots: Vec<Slot>,
    metrics: Vec<MetricState>,
}

impl fmt::Debug for Telemetry {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Telemetry")
            .field("slots", &self.slots)
            .field("stats", &self.stats())
            .finish_non_exhaustive()
    }
}

impl Telemetry {
    /// Samplers with the configured intervals and thresholds, reading this machine. The first
    /// collection is due [`FIRST_SAMPLE_DELAY`] from now.
    pub fn new(config: &Config) -> Telemetry {
        Self::with_probe(config, Box::new(SystemProbe::new()), Instant::now())
    }

    /// Samplers with the configured intervals and thresholds, reading the synthetic world of
    /// the simulated robot `name` (see [`synthetic`]) instead of this machine.
    pub fn synthetic(config: &Config, name: &str) -> Telemetry {
        let probe = synthetic::SyntheticProbe::new(name);
        Self::with_probe(config, Box::new(probe), Instant::now())
    }

    fn with_probe(config: &Config, probe: Box<dyn Probe>, start: Instant) -> Telemetry {
        let first = start + FIRST_SAMPLE_DELAY;
        let slots = Sampler::ALL
            .into_iter()
            .map(|sampler| Slot {
                sampler,
                // Validation rejects 0; guard anyway, as 0 would make the run loop spin.
                interval: Duration::from_secs(sampler.interval_s(config).max(1)),
                next: first,
                available: None,
            })
            .collect();
        let full = Duration::from_secs(config.telemetry_full_interval_s.max(1));
        let metrics = Metric::ALL
            .into_iter()
            .map(|metric| {
                let threshold = match metric {
                    Metric::CpuPercent => Some(Threshold::Absolute(config.telemetry_cpu_delta)),
                    Metric::MemoryPercent => {
                        Some(Threshold::Absolute(config.telemetry_memory_delta))
                    }
                    Metric::MemoryUsedBytes => None,
                    Metric::NetRxBytesPerS | Metric::NetTxBytesPerS => Some(Threshold::Relative {
                        fraction: config.telemetry_network_delta,
                        floor: NETWORK_DELTA_FLOOR_BYTES_PER_S,
                    }),
                    Metric::TemperatureC => {
                        Some(Threshold::Absolute(config.telemetry_temperature_delta))
                    }
                    Metric::DiskPercent => Some(Threshold::Absolute(config.telemetry_disk_delta)),
                };
                MetricState {
                    filter: threshold.map(|t| DeltaFilter::new(t, full)),
                    latest: None,
                    taken: 0,
                    emitted: 0,
                }
            })
            .collect();
        Telemetry {
            probe,
            slots,
            metrics,
        }
    }

    /// When the next sampler is due.
    pub fn next_due(&self) -> Instant {
        self.slots
            .iter()
            .map(|slot| slot.next)
            .min()
            .unwrap_or_else(|| Instant::now() + FIRST_SAMPLE_DELAY)
    }

    /// Runs every sampler due at `now` and returns the readings worth sending, stamped `ts_ms`.
    ///
    /// Each sampler that ran is next due one interval after its previous due time (so samplers
    /// stay on a common grid), or one interval after `now` if the agent fell further behind
    /// than that (no burst of catch-up samples after a suspend).
    pub fn collect_due(&mut self, now: Instant, ts_ms: i64) -> Vec<Sample> {
        let mut out = Vec::new();
        let mut ran = 0usize;
        for i in 0..self.slots.len() {
            let slot = &mut self.slots[i];
            if slot.next > now {
                continue;
            }
            slot.next += slot.interval;
            if slot.next <= now {
                slot.next = now + slot.interval;
            }
            let sampler = slot.sampler;
            let available = self.sample(sampler, now, ts_ms, &mut out);
            self.note_availability(i, available);
            ran += 1;
        }
        debug!(samplers = ran, emitted = out.len(), "telemetry collected");
        out
    }

    /// Current readings for a heartbeat: the latest reading of each sampler (whether or not it
    /// was sent), plus uptime and load read now.
    pub fn vitals(&mut self) -> Vitals {
        Vitals {
            uptime_s: self.probe.uptime_s(),
            cpu_percent: self.latest(Metric::CpuPercent),
            memory_percent: self.latest(Metric::MemoryPercent),
            load1: self.probe.load1(),
            disk_percent: self.latest(Metric::DiskPercent),
            temperature_c: self.latest(Metric::TemperatureC),
            battery_percent: None,
            // The health checks read the host process (`crate::health`).
            host_rss_bytes: None,
            host_cpu_percent: None,
        }
    }

    /// Readings taken and sent since start, in total and per metric.
    pub fn stats(&self) -> CompressionStats {
        let metrics: Vec<MetricStats> = Metric::ALL
            .into_iter()
            .zip(&self.metrics)
            .map(|(metric, state)| MetricStats {
                metric: metric.as_str(),
                taken: state.taken,
                emitted: state.emitted,
            })
            .collect();
        CompressionStats {
            taken: metrics.iter().map(|m| m.taken).sum(),
            emitted: metrics.iter().map(|m| m.emitted).sum(),
            metrics,
        }
    }

    fn latest(&self, metric: Metric) -> Option<f64> {
        self.metrics[metric.index()].latest
    }

    /// Runs one sampler; returns whether it produced a reading.
    fn sample(
        &mut self,
        sampler: Sampler,
        now: Instant,
        ts_ms: i64,
        out: &mut Vec<Sample>,
    ) -> bool {
        let at = (now, ts_ms);
        match sampler {
            Sampler::Cpu => {
                let value = self.probe.cpu_percent();
                self.record(Metric::CpuPercent, value, None, at, out);
                value.is_some()
            }
            Sampler::Memory => {
                let reading = self.probe.memory();
                let sent = self.record(
                    Metric::MemoryPercent,
                    reading.map(|r| r.percent),
                    None,
                    at,
                    out,
                );
                let used = reading.map(|r| r.used_bytes as f64);
                self.record(Metric::MemoryUsedBytes, used, Some(sent), at, out);
                reading.is_some()
            }
            Sampler::Network => {
                let reading = self.probe.network();
                let rx = reading.map(|r| r.rx_bytes_per_s);
                let tx = reading.map(|r| r.tx_bytes_per_s);
                self.record(Metric::NetRxBytesPerS, rx, None, at, out);
                self.record(Metric::NetTxBytesPerS, tx, None, at, out);
                reading.is_some()
            }
            Sampler::Temperature => {
                let value = self.probe.temperature_c();
                self.record(Metric::TemperatureC, value, None, at, out);
                value.is_some()
            }
            Sampler::Disk => {
                let value = self.probe.disk_percent();
                self.record(Metric::DiskPercent, value, None, at, out);
                value.is_some()
            }
        }
    }

    /// Records a reading (or its absence) and queues it if it passes the metric's filter, or,
    /// for a follower metric, if `follow` says its leader was sent. Returns whether it was
    /// sent.
    fn record(
        &mut self,
        metric: Metric,
        value: Option<f64>,
        follow: Option<bool>,
        (now, ts_ms): (Instant, i64),
        out: &mut Vec<Sample>,
    ) -> bool {
        let state = &mut self.metrics[metric.index()];
        let Some(value) = value.filter(|v| v.is_finite()).map(|v| metric.round(v)) else {
            state.latest = None;
            return false;
        };
        state.latest = Some(value);
        state.taken += 1;
        let send = match (&mut state.filter, follow) {
            (Some(filter), _) => filter.offer(value, now),
            (None, follow) => follow.unwrap_or(true),
        };
        if send {
            state.emitted += 1;
            out.push(Sample {
                metric: metric.as_str().to_owned(),
                ts_ms,
                value,
            });
        }
        send
    }

    /// Logs when a sampler starts or stops giving readings, once per change.
    fn note_availability(&mut self, slot: usize, available: bool) {
        let slot = &mut self.slots[slot];
        let sampler = slot.sampler.name();
        match (slot.available, available) {
            (None, false) => info!(sampler, "no reading on this machine; not reported"),
            (Some(true), false) => warn!(sampler, "sampler stopped giving readings"),
            (Some(false), true) => info!(sampler, "sampler gives readings again"),
            _ => {}
        }
        slot.available = Some(available);
    }
}

#[cfg(test)]
mod tests {
    use std::sync::{Arc, Mutex};

    use lekiwi_protocol::{AgentMessage, encode};

    use super::probe::{MemoryReading, NetworkReading, pick_sensors, use_percent};
    use super::*;

    fn secs(s: u64) -> Duration {
        Duration::from_secs(s)
    }

    // ---- DeltaFilter -------------------------------------------------------------------------

    #[test]
    fn first_value_is_always_sent() {
        let t0 = Instant::now();
        let mut f = DeltaFilter::new(Threshold::Absolute(5.0), secs(600));
        assert_eq!(f.last_sent(), None);
        assert!(f.offer(0.0, t0));
        assert_eq!(f.last_sent(), Some(0.0));
    }

    #[test]
    fn absolute_threshold_is_strict_and_measured_from_the_last_sent_value() {
        let t0 = Instant::now();
        let mut f = DeltaFilter::new(Threshold::Absolute(5.0), secs(600));
        assert!(f.offer(10.0, t0));
        assert!(
            !f.offer(15.0, t0 + secs(5)),
            "exactly the threshold is not enough"
        );
        assert!(!f.offer(5.0, t0 + secs(10)));
        assert!(f.offer(15.1, t0 + secs(15)));
        // A slow drift is sent once it adds up, because the reference is the last sent value.
        assert!(!f.offer(17.0, t0 + secs(20)));
        assert!(!f.offer(19.0, t0 + secs(25)));
        assert!(f.offer(20.2, t0 + secs(30)));
        assert_eq!(f.last_sent(), Some(20.2));
        // Downwards counts too.
        assert!(f.offer(2.0, t0 + secs(35)));
    }

    #[test]
    fn relative_threshold_scales_with_the_value_and_has_a_floor() {
        let t0 = Instant::now();
        let threshold = Threshold::Relative {
            fraction: 0.25,
            floor: 1024.0,
        };
        let mut f = DeltaFilter::new(threshold, secs(600));
        assert!(f.offer(1_000_000.0, t0));
        assert!(!f.offer(1_200_000.0, t0 + secs(5)), "+20 % < 25 %");
        assert!(!f.offer(760_000.0, t0 + secs(10)), "-24 %");
        assert!(f.offer(1_300_000.0, t0 + secs(15)), "+30 %");
        assert!(f.offer(100.0, t0 + secs(20)), "a drop to idle");
        // Near zero, the floor keeps idle chatter quiet although it doubles in relative terms.
        assert!(!f.offer(900.0, t0 + secs(25)));
        assert!(!f.offer(0.0, t0 + secs(30)));
        assert!(f.offer(5_000.0, t0 + secs(35)));
        assert!(!threshold.exceeded(0.0, 1024.0));
        assert!(threshold.exceeded(0.0, 1025.0));
    }

    #[test]
    fn full_interval_resends_an_unchanged_value() {
        let t0 = Instant::now();
        let mut f = DeltaFilter::new(Threshold::Absolute(1.0), secs(600));
        assert!(f.offer(42.0, t0));
        for s in (60..600).step_by(60) {
            assert!(!f.offer(42.0, t0 + secs(s)), "at {s} s");
        }
        assert!(f.offer(42.0, t0 + secs(600)));
        // The clock restarts at each send, also a send caused by a change.
        assert!(f.offer(50.0, t0 + secs(900)));
        assert!(!f.offer(50.0, t0 + secs(1440)));
        assert!(f.offer(50.0, t0 + secs(1500)));
    }

    #[test]
    fn values_that_are_not_finite_are_never_sent() {
        let t0 = Instant::now();
        let mut f = DeltaFilter::new(Threshold::Absolute(1.0), secs(600));
        assert!(!f.offer(f64::NAN, t0));
        assert!(!f.offer(f64::INFINITY, t0));
        assert_eq!(f.last_sent(), None);
    }

    /// Deterministic noise for the synthetic series (xorshift64*), uniform in [-1, 1).
    struct Noise(u64);

    impl Noise {
        fn next(&mut self) -> f64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            let x = self.0.wrapping_mul(0x2545_f491_4f6c_dd1d);
            (x >> 11) as f64 / (1u64 << 52) as f64 - 1.0
        }
    }

    /// CPU of an idle robot with three real changes (a teleoperation session, a burst of full
    /// load, back to idle), noise of ±2 points on top.
    fn cpu_truth(t_s: u64) -> f64 {
        match t_s {
            900..1200 => 60.0,
            2400..2460 => 95.0,
            _ => 8.0,
        }
    }

    #[test]
    fn an_hour_of_noisy_cpu_is_cut_at_least_fivefold_and_keeps_every_real_change() {
        let config = Config::default();
        let t0 = Instant::now();
        let mut filter = DeltaFilter::new(
            Threshold::Absolute(config.telemetry_cpu_delta),
            secs(config.telemetry_full_interval_s),
        );
        let mut noise = Noise(0x9e37_79b9_7f4a_7c15);
        let (mut taken, mut sent) = (0u32, 0u32);
        let mut max_error: f64 = 0.0;
        for t_s in (0..3600).step_by(config.telemetry_cpu_interval_s as usize) {
            let value = Metric::CpuPercent.round(cpu_truth(t_s) + 2.0 * noise.next());
            taken += 1;
            let emitted = filter.offer(value, t0 + secs(t_s));
            sent += u32::from(emitted);
            if t_s > 0 && cpu_truth(t_s) != cpu_truth(t_s - 5) {
                assert!(emitted, "the change at {t_s} s was not sent");
            }
            let seen = filter.last_sent().unwrap_or(f64::NAN);
            max_error = max_error.max((seen - value).abs());
        }
        println!(
            "cpu, 1 h at 5 s: {taken} readings, {sent} sent ({:.1}x fewer), \
             receiver off by at most {max_error:.1} points",
            f64::from(taken) / f64::from(sent)
        );
        assert_eq!(taken, 720);
        assert!(sent * 5 <= taken, "only {taken}/{sent}");
        assert!(max_error <= config.telemetry_cpu_delta);
    }

    // ---- Telemetry with a synthetic world -----------------------------------------------------

    /// A robot over an hour: idle, a teleoperation session at 15-20 min (CPU, memory and video
    /// traffic up, the SoC warms), a release download at 40-41 min (full CPU, 5 MB/s in, a bit
    /// more disk). Noise on everything.
    struct World {
        t_s: f64,
        noise: Noise,
        /// Every reading handed out, for the "send everything" baseline.
        log: Vec<(Metric, f64)>,
        temperature: f64,
        has_temperature: bool,
    }

    impl World {
        fn new() -> Self {
            Self {
                t_s: 0.0,
                noise: Noise(0x2545_f491_4f6c_dd1d),
                log: Vec::new(),
                temperature: 48.0,
                has_temperature: true,
            }
        }

        fn phase(&self) -> Phase {
            match self.t_s as u64 {
                900..1200 => Phase::Teleop,
                2400..2460 => Phase::Download,
                _ => Phase::Idle,
            }
        }

        fn jitter(&mut self, value: f64, fraction: f64) -> f64 {
            (value * (1.0 + fraction * self.noise.next())).max(0.0)
        }

        fn log(&mut self, metric: Metric, value: f64) -> f64 {
            self.log.push((metric, value));
            value
        }
    }

    #[derive(Clone, Copy, PartialEq)]
    enum Phase {
        Idle,
        Teleop,
        Download,
    }

    #[derive(Clone)]
    struct FakeProbe(Arc<Mutex<World>>);

    impl FakeProbe {
        fn world(&self) -> std::sync::MutexGuard<'_, World> {
            self.0.lock().unwrap()
        }
    }

    impl Probe for FakeProbe {
        fn cpu_percent(&mut self) -> Option<f64> {
            let mut w = self.world();
            let base = match w.phase() {
                Phase::Idle => 8.0,
                Phase::Teleop => 60.0,
                Phase::Download => 95.0,
            };
            let v = (base + 2.0 * w.noise.next()).clamp(0.0, 100.0);
            Some(w.log(Metric::CpuPercent, v))
        }

        fn memory(&mut self) -> Option<MemoryReading> {
            let mut w = self.world();
            let base = if w.phase() == Phase::Teleop {
                45.0
            } else {
                31.0
            };
            let percent = base + 0.3 * w.noise.next();
            let used_bytes = (percent / 100.0 * 8.0 * 1024.0 * 1024.0 * 1024.0) as u64;
            w.log(Metric::MemoryPercent, percent);
            w.log(Metric::MemoryUsedBytes, used_bytes as f64);
            Some(MemoryReading {
                percent,
                used_bytes,
            })
        }

        fn network(&mut self) -> Option<NetworkReading> {
            let mut w = self.world();
            let (rx, tx) = match w.phase() {
                Phase::Idle => (600.0, 900.0),
                Phase::Teleop => (40_000.0, 2_500_000.0),
                Phase::Download => (5_000_000.0, 60_000.0),
            };
            let rx = w.jitter(rx, 0.4);
            let tx = w.jitter(tx, 0.4);
            w.log(Metric::NetRxBytesPerS, rx);
            w.log(Metric::NetTxBytesPerS, tx);
            Some(NetworkReading {
                rx_bytes_per_s: rx,
                tx_bytes_per_s: tx,
            })
        }

        fn temperature_c(&mut self) -> Option<f64> {
            let mut w = self.world();
            if !w.has_temperature {
                return None;
            }
            let target = match w.phase() {
                Phase::Idle => 48.0,
                Phase::Teleop => 62.0,
                Phase::Download => 66.0,
            };
            // The SoC heats and cools with a lag.
            w.temperature += (target - w.temperature) * 0.3;
            let v = w.temperature + 0.3 * w.noise.next();
            Some(w.log(Metric::TemperatureC, v))
        }

        fn disk_percent(&mut self) -> Option<f64> {
            let mut w = self.world();
            let v = if w.t_s >= 2460.0 { 38.0 } else { 37.2 };
            Some(w.log(Metric::DiskPercent, v))
        }

        fn uptime_s(&self) -> Option<u64> {
            Some(1000 + self.world().t_s as u64)
        }

        fn load1(&self) -> Option<f64> {
            Some(0.25)
        }
    }

    fn fake(config: &Config, start: Instant) -> (Telemetry, FakeProbe) {
        let probe = FakeProbe(Arc::new(Mutex::new(World::new())));
        let telemetry = Telemetry::with_probe(config, Box::new(probe.clone()), start);
        (telemetry, probe)
    }

    fn taken(telemetry: &Telemetry, metric: Metric) -> u64 {
        telemetry.stats().metrics[metric.index()].taken
    }

    fn names(samples: &[Sample]) -> Vec<&str> {
        samples.iter().map(|s| s.metric.as_str()).collect()
    }

    #[test]
    fn samplers_run_on_their_own_intervals_on_one_grid() {
        let config = Config::default();
        let start = Instant::now();
        let (mut telemetry, _probe) = fake(&config, start);
        let first = start + FIRST_SAMPLE_DELAY;
        assert_eq!(telemetry.next_due(), first);
        assert!(
            telemetry.collect_due(start, 1).is_empty(),
            "nothing due yet"
        );

        let samples = telemetry.collect_due(first, 1_000);
        assert_eq!(
            names(&samples),
            Metric::ALL.map(Metric::as_str),
            "every sampler runs first and its first value is sent"
        );
        assert!(samples.iter().all(|s| s.ts_ms == 1_000));
        assert_eq!(telemetry.next_due(), first + secs(5));
        assert!(telemetry.collect_due(first, 1_000).is_empty(), "not twice");

        // Ten minutes later (less than the full interval since the first send), on the grid.
        let mut now = telemetry.next_due();
        while now < first + secs(599) {
            telemetry.collect_due(now, 0);
            now = telemetry.next_due();
        }
        assert_eq!(now, first + secs(600));
        assert_eq!(taken(&telemetry, Metric::CpuPercent), 120);
        assert_eq!(taken(&telemetry, Metric::NetRxBytesPerS), 120);
        assert_eq!(taken(&telemetry, Metric::MemoryPercent), 60);
        assert_eq!(taken(&telemetry, Metric::MemoryUsedBytes), 60);
        assert_eq!(taken(&telemetry, Metric::TemperatureC), 20);
        assert_eq!(taken(&telemetry, Metric::DiskPercent), 10);
        // Idle disk and memory did not move: only the first value was sent.
        let stats = telemetry.stats();
        assert_eq!(stats.metrics[Metric::DiskPercent.index()].emitted, 1);
        assert_eq!(stats.metrics[Metric::MemoryPercent.index()].emitted, 1);
        // At 600 s the full sample sends everything again.
        let samples = telemetry.collect_due(now, 0);
        assert_eq!(names(&samples), Metric::ALL.map(Metric::as_str));
    }

    #[test]
    fn a_late_wake_runs_each_sampler_once_and_reschedules_from_now() {
        let config = Config::default();
        let start = Instant::now();
        let (mut telemetry, _probe) = fake(&config, start);
        let late = start + secs(3600);
        telemetry.collect_due(late, 0);
        let stats = telemetry.stats();
        assert!(stats.metrics.iter().all(|m| m.taken == 1), "{stats:?}");
        assert_eq!(telemetry.next_due(), late + secs(5));
    }

    #[test]
    fn memory_used_bytes_is_sent_exactly_with_memory_percent() {
        let config = Config::default();
        let start = Instant::now();
        let (mut telemetry, probe) = fake(&config, start);
        let mut now = telemetry.next_due();
        while now < start + secs(3600) {
            probe.world().t_s = (now - start).as_secs_f64();
            let samples = telemetry.collect_due(now, 0);
            let names = names(&samples);
            assert_eq!(
                names.contains(&"memory_percent"),
                names.contains(&"memory_used_bytes")
            );
            now = telemetry.next_due();
        }
        let stats = telemetry.stats();
        let percent = &stats.metrics[Metric::MemoryPercent.index()];
        let bytes = &stats.metrics[Metric::MemoryUsedBytes.index()];
        assert_eq!(
            (percent.taken, percent.emitted),
            (bytes.taken, bytes.emitted)
        );
        assert!(percent.emitted >= 3, "the teleop session's jump in and out");
    }

    #[test]
    fn vitals_hold_the_latest_readings_and_a_missing_sensor_stays_none() {
        let config = Config::default();
        let start = Instant::now();
        let (mut telemetry, probe) = fake(&config, start);
        probe.world().has_temperature = false;
        let before = telemetry.vitals();
        assert_eq!(before.cpu_percent, None);
        assert_eq!(before.uptime_s, Some(1000));

        let samples = telemetry.collect_due(telemetry.next_due(), 0);
        assert!(!names(&samples).contains(&"temperature_c"));
        let vitals = telemetry.vitals();
        let log = probe.world().log.clone();
        let reading = |metric| {
            log.iter()
                .rev()
                .find(|(m, _)| *m == metric)
                .map(|&(_, v)| metric.round(v))
        };
        assert_eq!(vitals.cpu_percent, reading(Metric::CpuPercent));
        assert_eq!(vitals.memory_percent, reading(Metric::MemoryPercent));
        assert_eq!(vitals.disk_percent, Some(37.2));
        assert_eq!(vitals.temperature_c, None);
        assert_eq!(vitals.load1, Some(0.25));
        assert_eq!(vitals.battery_percent, None);
        assert_eq!(
            telemetry.stats().metrics[Metric::TemperatureC.index()].taken,
            0
        );
    }

    /// What the agent puts on the wire over an hour, with delta compression and without: the
    /// samples batched every `telemetryBatchIntervalS` into `telemetry` frames, as the run loop
    /// does (an empty batch sends nothing).
    #[test]
    fn an_hour_of_telemetry_costs_at_least_five_times_fewer_bytes_with_compression() {
        let config = Config::default();
        let start = Instant::now();
        let (mut telemetry, probe) = fake(&config, start);
        let batch_every = secs(config.telemetry_batch_interval_s);
        let base_ms: i64 = 1_763_800_000_000;

        let mut frames = [0usize; 2];
        let mut bytes = [0usize; 2];
        let mut seq = [0u64; 2];
        let mut pending: [Vec<Sample>; 2] = [Vec::new(), Vec::new()];
        let mut flush = |pending: &mut [Vec<Sample>; 2]| {
            for i in 0..2 {
                if pending[i].is_empty() {
                    continue;
                }
                seq[i] += 1;
                let frame = encode(&AgentMessage::Telemetry {
                    seq: seq[i],
                    samples: std::mem::take(&mut pending[i]),
                });
                frames[i] += 1;
                bytes[i] += frame.len();
            }
        };

        let end = start + secs(3600);
        let mut next_batch = start + batch_every;
        loop {
            let due = telemetry.next_due();
            while next_batch <= due.min(end) {
                flush(&mut pending);
                next_batch += batch_every;
            }
            if due > end {
                break;
            }
            let t = due - start;
            probe.world().t_s = t.as_secs_f64();
            let ts_ms = base_ms + t.as_millis() as i64;
            let sent = telemetry.collect_due(due, ts_ms);
            pending[0].extend(sent);
            pending[1].extend(probe.world().log.drain(..).map(|(metric, value)| Sample {
                metric: metric.as_str().to_owned(),
                ts_ms,
                value: metric.round(value),
            }));
        }
        flush(&mut pending);

        let stats = telemetry.stats();
        let [compressed, everything] = bytes;
        println!(
            "1 h of telemetry at the default settings: {} readings, {} sent ({:.1}x fewer)",
            stats.taken,
            stats.emitted,
            stats.ratio().unwrap_or_default()
        );
        for m in &stats.metrics {
            println!(
                "  {:<20} {:>4} taken {:>4} sent",
                m.metric, m.taken, m.emitted
            );
        }
        println!(
            "  every reading: {everything} bytes/h in {} frames; \
             delta-compressed: {compressed} bytes/h in {} frames ({:.1}x fewer bytes)",
            frames[1],
            frames[0],
            everything as f64 / compressed as f64
        );
        assert_eq!(stats.taken, 720 + 360 * 2 + 720 * 2 + 120 + 60);
        assert!(compressed * 5 <= everything, "{compressed} vs {everything}");
        // The cost on the wire of an hour of telemetry stays small on a metered link.
        assert!(compressed < 64 * 1024, "{compressed} bytes/h");
    }

    // ---- Helpers -----------------------------------------------------------------------------

    #[test]
    fn cpu_sensors_win_over_others_and_any_sensor_beats_none() {
        let pi = ["cpu_thermal temp1", "rp1_adc temp1", "nvme Composite"];
        assert_eq!(pick_sensors(pi.into_iter()), vec![0]);
        let amd = [
            "nvme Composite",
            "k10temp Tctl",
            "k10temp Tccd1",
            "amdgpu edge",
        ];
        assert_eq!(pick_sensors(amd.into_iter()), vec![1, 2]);
        let other = ["acpitz temp1", "nvme Composite"];
        assert_eq!(pick_sensors(other.into_iter()), vec![0, 1]);
        assert!(pick_sensors(std::iter::empty()).is_empty());
    }

    #[test]
    fn disk_use_is_what_df_shows_and_an_empty_file_system_has_none() {
        // 1000 blocks, 600 free, 100 of them usable without root: 400 used of 500 usable.
        assert_eq!(use_percent(1000, 600, 100), Some(80.0));
        // Nothing reserved: used over total.
        assert_eq!(use_percent(1000, 250, 250), Some(75.0));
        assert_eq!(use_percent(1000, 1000, 1000), Some(0.0));
        assert_eq!(use_percent(1000, 1000, 0), None);
        assert_eq!(use_percent(0, 0, 0), None);
    }

    #[test]
    fn values_are_rounded_for_the_wire() {
        assert_eq!(Metric::CpuPercent.round(12.345_678), 12.3);
        assert_eq!(Metric::TemperatureC.round(51.96), 52.0);
        assert_eq!(Metric::NetRxBytesPerS.round(1234.56), 1235.0);
        let names: Vec<_> = Metric::ALL.iter().map(ToString::to_string).collect();
        assert_eq!(
            names,
            [
                "cpu_percent",
                "memory_percent",
                "memory_used_bytes",
                "net_rx_bytes_per_s",
                "net_tx_bytes_per_s",
                "temperature_c",
                "disk_percent"
            ]
        );
    }

    #[test]
    fn telemetry_can_move_between_threads() {
        fn assert_send_sync<T: Send + Sync>() {}
        assert_send_sync::<Telemetry>();
    }

    // ---- This machine ------------------------------------------------------------------------

    #[test]
    fn this_machine_gives_cpu_memory_and_disk_samples_and_vitals() {
        let mut telemetry = Telemetry::new(&Config::default());
        let due = telemetry.next_due();
        std::thread::sleep(due.saturating_duration_since(Instant::now()));
        let samples = telemetry.collect_due(due, 42);
        let value = |name: &str| {
            samples
                .iter()
                .find(|s| s.metric == name)
                .map(|s| s.value)
                .unwrap_or_else(|| panic!("no {name} in {samples:?}"))
        };
        assert!((0.0..=100.0).contains(&value("cpu_percent")));
        assert!((0.0..=100.0).contains(&value("memory_percent")));
        assert!(value("memory_used_bytes") > 0.0);
        assert!((0.0..=100.0).contains(&value("disk_percent")));
        assert!(value("net_rx_bytes_per_s") >= 0.0);
        assert!(samples.iter().all(|s| s.ts_ms == 42));

        let vitals = telemetry.vitals();
        println!("{samples:?}\n{vitals:?}");
        assert!(vitals.uptime_s.is_some_and(|s| s > 0));
        assert!(vitals.load1.is_some_and(|l| l >= 0.0));
        assert_eq!(vitals.memory_percent, Some(value("memory_percent")));
        assert_eq!(vitals.cpu_percent, Some(value("cpu_percent")));
        assert_eq!(vitals.disk_percent, Some(value("disk_percent")));
        assert_eq!(vitals.battery_percent, None);
        if let Some(t) = vitals.temperature_c {
            assert!((-40.0..150.0).contains(&t), "{t}");
        }
    }

    #[test]
    fn this_machine_has_system_facts() {
        let facts = system_facts();
        println!("{facts:?}");
        assert!(facts.cpus.is_some_and(|n| n >= 1));
        assert!(facts.memory_bytes.is_some_and(|b| b > 0));
        assert_eq!(facts.arch.as_deref(), Some(std::env::consts::ARCH));
        assert!(facts.kernel.is_some());
        assert!(facts.os.is_some());
    }
}
