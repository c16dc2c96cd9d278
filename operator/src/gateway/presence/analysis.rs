//! Per-robot metrics before and after a release switch, for rollouts with `spec.analysis`: the
//! gateway folds every heartbeat into a baseline (since the switch before, or since it first saw
//! the robot) and, once the agent reports a switch `done`, into that switch's window too. A few
//! numbers per metric, whatever the number of heartbeats: memory is bounded per robot.

use jiff::{SignedDuration, Timestamp};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::Time;
use lekiwi_crds::analysis::{
    AnalysisReport, EventCounts, MAX_TELEMETRY_METRICS, MAX_WINDOW_SECONDS, MetricSummary,
    MetricWindow, TelemetryCeiling,
};
use lekiwi_crds::{ReleaseRef, RobotStatus};
use lekiwi_protocol::{Release, Sample, Vitals, rules};

/// A robot whose switch is younger than [`MAX_WINDOW_SECONDS`] has its status refreshed at
/// least this often, so that rollouts see its window without waiting for the routine refresh.
pub const WINDOW_REFRESH: std::time::Duration = std::time::Duration::from_secs(5);

/// Count, sum and highest of one metric's readings.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Acc {
    n: u32,
    sum: f64,
    max: f64,
}

impl Acc {
    fn add(&mut self, x: Option<f64>) {
        let Some(x) = x.filter(|x| x.is_finite() && *x >= 0.0) else {
            return;
        };
        if self.n == u32::MAX {
            return;
        }
        self.max = if self.n == 0 { x } else { self.max.max(x) };
        self.n += 1;
        self.sum += x;
    }

    fn summary(&self) -> Option<MetricSummary> {
        (self.n > 0).then(|| MetricSummary {
            samples: self.n,
            mean: self.sum / f64::from(self.n),
            max: self.max,
        })
    }
}

/// The metrics analysis compares.
#[derive(Clone, Debug, Default, PartialEq)]
struct Metrics {
    host_memory: Acc,
    host_cpu: Acc,
    memory_percent: Acc,
    rtt_ms: Acc,
    events: u32,
    error_events: u32,
    /// Highest reading of each telemetry metric, the first [`MAX_TELEMETRY_METRICS`] seen.
    telemetry: Vec<(String, f64)>,
}

impl Metrics {
    fn telemetry(&mut self, samples: &[Sample]) {
        for s in samples.iter().filter(|s| s.value.is_finite()) {
            if let Some((_, max)) = self.telemetry.iter_mut().find(|(m, _)| *m == s.metric) {
                *max = max.max(s.value);
            } else if self.telemetry.len() < MAX_TELEMETRY_METRICS && s.metric.len() <= 64 {
                self.telemetry.push((s.metric.clone(), s.value));
            }
        }
    }

    fn add(&mut self, v: &Vitals, rtt_ms: Option<f64>) {
        let rss = v.host_rss_bytes.filter(|&b| b <= rules::MAX_MEMORY_BYTES);
        self.host_memory.add(rss.map(|b| b as f64));
        self.host_cpu.add(v.host_cpu_percent);
        self.memory_percent.add(v.memory_percent);
        self.rtt_ms.add(rtt_ms);
    }

    /// The accumulators a written summary stands for.
    fn resume(w: &MetricWindow) -> Self {
        let acc = |s: &Option<MetricSummary>| {
            s.as_ref().map_or(Acc::default(), |s| Acc {
                n: s.samples,
                sum: s.mean * f64::from(s.samples),
                max: s.max,
            })
        };
        let events = w.events.clone().unwrap_or_default();
        Self {
            host_memory: acc(&w.host_memory_bytes),
            host_cpu: acc(&w.host_cpu_percent),
            memory_percent: acc(&w.memory_percent),
            rtt_ms: acc(&w.rtt_ms),
            events: events.total,
            error_events: events.errors,
            telemetry: w
                .telemetry
                .iter()
                .map(|t| (t.metric.clone(), t.max))
                .collect(),
        }
    }

    fn event(&mut self, error: bool) {
        self.events = self.events.saturating_add(1);
        if error {
            self.error_events = self.error_events.saturating_add(1);
        }
    }

    fn window(&self) -> MetricWindow {
        MetricWindow {
            host_memory_bytes: self.host_memory.summary(),
            host_cpu_percent: self.host_cpu.summary(),
            memory_percent: self.memory_percent.summary(),
            rtt_ms: self.rtt_ms.summary(),
            events: (self.events > 0).then_some(EventCounts {
                total: self.events,
                errors: self.error_events,
            }),
            telemetry: self
                .telemetry
                .iter()
                .map(|(metric, max)| TelemetryCeiling {
                    metric: metric.clone(),
                    max: *max,
                })
                .collect(),
        }
    }
}

/// One switch: the release, when it was reported done, the baseline before it and the
/// readings since.
#[derive(Clone, Debug, PartialEq)]
struct Window {
    release: Release,
    start: Timestamp,
    end: Option<Timestamp>,
    baseline_start: Option<Timestamp>,
    baseline: Metrics,
    observed: Metrics,
}

/// What the gateway keeps of one robot for analysis.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Tracker {
    /// Readings since the last switch (or since the robot was first seen): the next baseline.
    since_switch: Metrics,
    /// When the first of `since_switch` arrived.
    since_switch_start: Option<Timestamp>,
    /// The last switch, if the gateway saw one (boxed: most robots have none, and every
    /// connected robot's presence entry holds a tracker).
    last: Option<Box<Window>>,
}

impl Tracker {
    /// Folds a heartbeat's vitals and round-trip time, received at `now`, in.
    pub fn record(&mut self, vitals: &Vitals, rtt_ms: Option<f64>, now: Timestamp) {
        self.since_switch.add(vitals, rtt_ms);
        self.since_switch_start.get_or_insert(now);
        if let Some(w) = self.last.as_mut() {
            w.observed.add(vitals, rtt_ms);
            w.end = Some(now);
        }
    }

    /// Folds a batch of telemetry samples in (their highest reading per metric).
    pub fn telemetry(&mut self, samples: &[Sample]) {
        self.since_switch.telemetry(samples);
        if let Some(w) = self.last.as_mut() {
            w.observed.telemetry(samples);
        }
    }

    /// Counts an event the robot sent, `error` if of that severity.
    pub fn event(&mut self, error: bool) {
        self.since_switch.event(error);
        if let Some(w) = self.last.as_mut() {
            w.observed.event(error);
        }
    }

    /// The robot switched to `release` at `at` (the agent's `done`, or a heartbeat or hello
    /// that first shows it): a new window opens, with the readings since the previous switch
    /// as its baseline. Nothing changes when the last window is already of `release` (the
    /// heartbeat and the `done` of one switch).
    pub fn switched(&mut self, release: Release, at: Timestamp) {
        if self.last.as_ref().is_some_and(|w| w.release == release) {
            return;
        }
        self.last = Some(Box::new(Window {
            release,
            start: at,
            end: None,
            baseline_start: self.since_switch_start.take(),
            baseline: std::mem::take(&mut self.since_switch),
            observed: Metrics::default(),
        }));
    }

    /// The tracker another gateway (or this one before a restart) left in `report`: the window
    /// goes on from its summary, and its readings are the next baseline so far. `None` when the
    /// report lacks its release or start.
    pub fn resume(report: &AnalysisReport) -> Option<Self> {
        let release = report.release.as_ref()?;
        let observed = Metrics::resume(&report.window);
        Some(Self {
            since_switch: observed.clone(),
            since_switch_start: report.window_start.as_ref().map(|t| t.0),
            last: Some(Box::new(Window {
                release: Release::from(release),
                start: report.window_start.as_ref()?.0,
                end: report.window_end.as_ref().map(|t| t.0),
                baseline_start: report.baseline_start.as_ref().map(|t| t.0),
                baseline: Metrics::resume(&report.baseline),
                observed,
            })),
        })
    }

    /// The tracker a new session of a robot that runs `running` starts from: this gateway's
    /// own (`ours`, with the release it last saw), else the one the Robot's `stored` status
    /// holds. If the robot runs another release than this gateway and its status (when a
    /// gateway wrote it: it has a heartbeat time; the controller alone writes only a phase)
    /// last saw, it switched while no gateway saw its `done` (a restart, a move), and that
    /// switch's window opens `now`. A robot's first connection is no switch: opening a window
    /// there would refresh every new robot's status every few seconds for ten minutes.
    pub fn at_connect(
        ours: Option<(&Tracker, Option<&Release>)>,
        stored: Option<&RobotStatus>,
        running: Option<&Release>,
        now: Timestamp,
    ) -> Self {
        let mut tracker = match ours {
            Some((t, _)) => t.clone(),
            None => stored
                .and_then(|s| s.analysis.as_deref())
                // A window that closed is not resumed: the status then drops it.
                .filter(|a| window_open(a))
                .and_then(Self::resume)
                .unwrap_or_default(),
        };
        let seen_here = ours.and_then(|(_, r)| r);
        let seen_stored = stored
            .filter(|s| s.last_heartbeat_time.is_some())
            .map(|s| s.current_release.as_ref().map(Release::from));
        if let Some(release) = running
            && (ours.is_none() || seen_here != Some(release))
            && seen_stored.is_some_and(|r| r.as_ref() != Some(release))
        {
            tracker.switched(release.clone(), now);
        }
        tracker
    }

    /// Whether the last switch is recent enough for its window to matter to a rollout.
    pub fn window_open(&self, now: Timestamp) -> bool {
        self.last.as_ref().is_some_and(|w| {
            now.duration_since(w.start) <= SignedDuration::from_secs(MAX_WINDOW_SECONDS)
        })
    }

    /// The summary written to `status.analysis`; `None` before any switch.
    pub fn report(&self) -> Option<AnalysisReport> {
        let w = self.last.as_ref()?;
        Some(AnalysisReport {
            release: Some(ReleaseRef::from(&w.release)),
            baseline_start: w.baseline_start.map(Time),
            window_start: Some(Time(w.start)),
            window_end: w.end.map(Time),
            baseline: w.baseline.window(),
            window: w.observed.window(),
        })
    }
}

impl super::Presence {
    /// The session `session` of `key` sent an event (`error` if of that severity): counted for
    /// analysis, written with the next status write.
    pub fn event(&self, key: &crate::gateway::event_store::RobotKey, session: u64, error: bool) {
        self.with_state(|s| {
            if let Some(e) = s.live_session(key, session) {
                e.analysis.event(error);
            }
        });
    }

    /// The session `session` of `key` sent telemetry: the highest reading per metric is kept
    /// for analysis.
    pub fn telemetry(
        &self,
        key: &crate::gateway::event_store::RobotKey,
        session: u64,
        samples: &[Sample],
    ) {
        self.with_state(|s| {
            if let Some(e) = s.live_session(key, session) {
                e.analysis.telemetry(samples);
            }
        });
    }
}

/// Whether `report`'s window is recent enough to matter to a rollout (see [`Tracker::window_open`]).
pub fn window_open(report: &AnalysisReport) -> bool {
    report.window_start.as_ref().is_some_and(|t| {
        Timestamp::now().duration_since(t.0) <= SignedDuration::from_secs(MAX_WINDOW_SECONDS)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn vitals(rss: u64, cpu: f64) -> Vitals {
        Vitals {
            host_rss_bytes: Some(rss),
            host_cpu_percent: Some(cpu),
            ..Vitals::default()
        }
    }

    /// Readings before a switch are its baseline (mean and highest), readings after it its
    /// window; the next switch's baseline is what came after the one before; NaN and absent
    /// readings are left out.
    #[test]
    fn a_switch_splits_baseline_from_window() {
        let t0 = Timestamp::from_second(1_000).unwrap();
        let mut t = Tracker::default();
        assert_eq!(t.report(), None);
        t.record(&vitals(100, 1.0), Some(2.0), t0);
        t.event(true);
        t.record(&vitals(300, f64::NAN), None, t0);
        let rel = |v: &str| Release {
            version: v.into(),
            digest: format!("sha256:{v}"),
        };
        t.switched(rel("2"), t0);
        t.record(
            &vitals(400, 4.0),
            Some(-1.0),
            t0 + SignedDuration::from_secs(1),
        );
        t.event(false);
        let sample = |metric: &str, value: f64| Sample {
            metric: metric.into(),
            ts_ms: 0,
            value,
        };
        t.telemetry(&[sample("cpu_percent", 30.0), sample("cpu_percent", 70.0)]);
        t.telemetry(&[sample("cpu_percent", 50.0), sample("x", f64::NAN)]);
        let r = t.report().unwrap();
        let ceiling = TelemetryCeiling {
            metric: "cpu_percent".into(),
            max: 70.0,
        };
        assert_eq!(r.window.telemetry, vec![ceiling]);
        // Another gateway resumes from the written summary and writes the same one.
        let resumed = Tracker::resume(&r).unwrap();
        assert_eq!(resumed.report(), Some(r.clone()));
        // A second sign of the same switch (the heartbeat, then the `done`) changes nothing.
        let mut again = t.clone();
        again.switched(rel("2"), t0 + SignedDuration::from_secs(5));
        assert_eq!(again.report(), Some(r.clone()));

        let base = r.baseline.host_memory_bytes.unwrap();
        assert_eq!((base.samples, base.mean, base.max), (2, 200.0, 300.0));
        assert_eq!(r.baseline.host_cpu_percent.unwrap().samples, 1);
        assert_eq!(r.baseline.memory_percent, None);
        assert_eq!(r.baseline.rtt_ms.unwrap().mean, 2.0);
        assert_eq!(r.window.rtt_ms, None, "negative round trips are left out");
        let counts = |total, errors| Some(EventCounts { total, errors });
        assert_eq!(r.baseline.events, counts(1, 1));
        assert_eq!(r.window.events, counts(1, 0));
        assert_eq!(r.baseline_start, Some(Time(t0)));
        assert_eq!(r.window.host_memory_bytes.unwrap().max, 400.0);
        assert_eq!(r.window_end, Some(Time(t0 + SignedDuration::from_secs(1))));
        assert!(t.window_open(t0 + SignedDuration::from_secs(MAX_WINDOW_SECONDS)));
        assert!(!t.window_open(t0 + SignedDuration::from_secs(MAX_WINDOW_SECONDS + 1)));

        t.switched(rel("3"), t0 + SignedDuration::from_secs(2));
        let r = t.report().unwrap();
        assert_eq!(r.baseline.host_memory_bytes.unwrap().mean, 400.0);
        assert_eq!(r.window, MetricWindow::default());
    }
}
