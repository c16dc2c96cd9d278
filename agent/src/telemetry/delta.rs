//! Delta compression of telemetry: the metrics, the threshold a change must exceed to be
//! sent, the filter that applies it (with a periodic full sample), and the counters of what it
//! saved.

use std::fmt;
use std::time::Duration;

use serde::Serialize;
use tokio::time::Instant;

/// Network rate changes smaller than this many bytes/s are never sent (except in full samples):
/// an idle link carries a few hundred bytes/s of heartbeats and mDNS whose relative jitter would
/// otherwise beat any fractional threshold.
pub const NETWORK_DELTA_FLOOR_BYTES_PER_S: f64 = 1024.0;

/// A telemetry metric; its wire name is [`Metric::as_str`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Metric {
    /// `cpu_percent`: CPU use, percent of all cores, averaged over the sampling interval.
    CpuPercent,
    /// `memory_percent`: memory in use, percent of RAM.
    MemoryPercent,
    /// `memory_used_bytes`: memory in use, bytes.
    MemoryUsedBytes,
    /// `net_rx_bytes_per_s`: bytes received per second, all interfaces but loopback.
    NetRxBytesPerS,
    /// `net_tx_bytes_per_s`: bytes sent per second, all interfaces but loopback.
    NetTxBytesPerS,
    /// `temperature_c`: hottest CPU/SoC sensor, degrees Celsius.
    TemperatureC,
    /// `disk_percent`: root file system use, percent.
    DiskPercent,
}

impl Metric {
    /// Every metric, in the order samples and stats list them.
    pub const ALL: [Metric; 7] = [
        Metric::CpuPercent,
        Metric::MemoryPercent,
        Metric::MemoryUsedBytes,
        Metric::NetRxBytesPerS,
        Metric::NetTxBytesPerS,
        Metric::TemperatureC,
        Metric::DiskPercent,
    ];

    /// The metric's name on the wire (`Sample::metric`).
    pub fn as_str(self) -> &'static str {
        match self {
            Metric::CpuPercent => "cpu_percent",
            Metric::MemoryPercent => "memory_percent",
            Metric::MemoryUsedBytes => "memory_used_bytes",
            Metric::NetRxBytesPerS => "net_rx_bytes_per_s",
            Metric::NetTxBytesPerS => "net_tx_bytes_per_s",
            Metric::TemperatureC => "temperature_c",
            Metric::DiskPercent => "disk_percent",
        }
    }

    /// The value as sent: 0.1 resolution for percent and °C, whole bytes otherwise. Finer
    /// digits are sensor noise and would only lengthen the frames.
    pub(super) fn round(self, value: f64) -> f64 {
        match self {
            Metric::CpuPercent
            | Metric::MemoryPercent
            | Metric::TemperatureC
            | Metric::DiskPercent => (value * 10.0).round() / 10.0,
            Metric::MemoryUsedBytes | Metric::NetRxBytesPerS | Metric::NetTxBytesPerS => {
                value.round()
            }
        }
    }

    pub(super) fn index(self) -> usize {
        self as usize
    }
}

impl fmt::Display for Metric {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// How far a value must move from the last sent one to be sent again.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Threshold {
    /// By more than this many units (percentage points, °C).
    Absolute(f64),
    /// By more than `fraction` of the last sent value's magnitude, and by more than `floor`
    /// units (so that values near zero do not count every wobble as a large relative change).
    Relative {
        /// Fraction of the last sent value, e.g. 0.25.
        fraction: f64,
        /// Smallest change that counts, in the metric's unit.
        floor: f64,
    },
}

impl Threshold {
    /// Whether moving from `last_sent` to `value` crosses the threshold.
    pub fn exceeded(self, last_sent: f64, value: f64) -> bool {
        let delta = (value - last_sent).abs();
        match self {
            Threshold::Absolute(limit) => delta > limit,
            Threshold::Relative { fraction, floor } => {
                delta > (fraction * last_sent.abs()).max(floor)
            }
        }
    }
}

/// Delta compression of one metric: remembers the last value sent and decides whether a new
/// reading is worth sending.
///
/// A reading is sent when it is the first, when it differs from the last *sent* value (not the
/// last reading, so a slow drift is sent once it adds up) by more than the [`Threshold`], or when
/// `full_interval` has passed since the metric was last sent. The receiver's picture therefore
/// never deviates from the truth by more than the threshold, and is never older than the full
/// interval plus one sampling interval.
#[derive(Clone, Debug)]
pub struct DeltaFilter {
    threshold: Threshold,
    full_interval: Duration,
    last_sent: Option<(f64, Instant)>,
}

impl DeltaFilter {
    /// A filter that has sent nothing yet.
    pub fn new(threshold: Threshold, full_interval: Duration) -> Self {
        Self {
            threshold,
            full_interval,
            last_sent: None,
        }
    }

    /// Offers a reading taken at `now`; returns whether to send it (and if so, remembers it as
    /// sent). A value that is not finite is never sent.
    pub fn offer(&mut self, value: f64, now: Instant) -> bool {
        if !value.is_finite() {
            return false;
        }
        let send = match self.last_sent {
            None => true,
            Some((last, at)) => {
                self.threshold.exceeded(last, value)
                    || now.saturating_duration_since(at) >= self.full_interval
            }
        };
        if send {
            self.last_sent = Some((value, now));
        }
        send
    }

    /// The last value sent, if any.
    pub fn last_sent(&self) -> Option<f64> {
        self.last_sent.map(|(value, _)| value)
    }
}

/// Samples taken and sent for one metric.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct MetricStats {
    /// The metric's wire name ([`Metric::as_str`]).
    pub metric: &'static str,
    /// Readings taken.
    pub taken: u64,
    /// Readings sent (passed delta compression or were part of a full sample).
    pub emitted: u64,
}

/// How much delta compression saved since the agent started.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct CompressionStats {
    /// Readings taken, all metrics.
    pub taken: u64,
    /// Readings sent, all metrics.
    pub emitted: u64,
    /// Per metric, in [`Metric::ALL`] order.
    pub metrics: Vec<MetricStats>,
}

impl CompressionStats {
    /// Readings taken per reading sent (e.g. 8.0 means 8× fewer samples on the wire), or `None`
    /// before anything was sent.
    pub fn ratio(&self) -> Option<f64> {
        (self.emitted > 0).then(|| self.taken as f64 / self.emitted as f64)
    }
}
