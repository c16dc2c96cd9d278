//! Per-robot metrics before and after a release switch, for rollouts with `spec.analysis`: the
//! gateway folds every heartbeat into a baseline (since the switch before, or since it first saw
//! the robot) and, once the agent reports a switch `done`, into that switch's window too. A few
//! numbers per metric, whatever the number of heartbeats: memory is bounded per robot.
//!
//! The summary goes out with the robot's status writes. A switch that a rollout with analysis
//! asked for (the Robot's [`WINDOW_ANNOTATION`]) costs one write more: the one after its window
//! has spanned what the rollout asked ([`Tracker::outcome_due`]), which the rollout judges. Any
//! other switch costs nothing beyond its own write.

use jiff::{SignedDuration, Timestamp};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::Time;
use kube::ResourceExt;
use lekiwi_crds::analysis::{
    AnalysisReport, EventCounts, MAX_TELEMETRY_METRICS, MAX_WINDOW_SECONDS, MetricSummary,
    MetricWindow, TelemetryCeiling, WINDOW_ANNOTATION,
};
use lekiwi_crds::{ReleaseRef, Robot, RobotStatus};
use lekiwi_protocol::{Release, Sample, Vitals, rules};

/// The analysis window a rollout asked for a robot's switch to `release`: read from the Robot
/// the rollout wrote (its `spec.release` and [`WINDOW_ANNOTATION`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Asked {
    release: Release,
    window: SignedDuration,
}

impl Asked {
    /// What `robot` asks of a switch to its `spec.release`; `None` without the annotation (no
    /// rollout with analysis set that release) or with one that is not a number of seconds.
    /// The window is cut to [`MAX_WINDOW_SECONDS`], as the deployment's schema cuts it.
    pub fn of(robot: &Robot) -> Option<Self> {
        let release = robot.spec.release.as_ref()?;
        let seconds: i64 = robot
            .annotations()
            .get(WINDOW_ANNOTATION)?
            .trim()
            .parse()
            .ok()?;
        Some(Self {
            release: Release::from(release),
            window: SignedDuration::from_secs(seconds.clamp(1, MAX_WINDOW_SECONDS)),
        })
    }

    /// The window asked for a switch to `release`, if this is it.
    fn window_of(asked: Option<&Self>, release: &Release) -> Option<SignedDuration> {
        asked.filter(|a| a.release == *release).map(|a| a.window)
    }
}

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
    /// How long the rollout that asked for the switch watches it; `None`: none asked.
    asked: Option<SignedDuration>,
    /// A status write holding the window as long as `asked` landed: its outcome is written.
    reported: bool,
}

impl Window {
    /// Whether the readings span the window the rollout asked for (never, if none asked).
    fn complete(&self) -> bool {
        match (self.asked, self.end) {
            (Some(asked), Some(end)) => end.duration_since(self.start) >= asked,
            _ => false,
        }
    }
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
    /// as its baseline, watched as long as `asked` says if it asks for this switch. Nothing
    /// changes when the last window is already of `release` (the heartbeat and the `done` of
    /// one switch).
    pub fn switched(&mut self, release: Release, at: Timestamp, asked: Option<&Asked>) {
        if self.last.as_ref().is_some_and(|w| w.release == release) {
            return;
        }
        self.last = Some(Box::new(Window {
            asked: Asked::window_of(asked, &release),
            release,
            start: at,
            end: None,
            baseline_start: self.since_switch_start.take(),
            baseline: std::mem::take(&mut self.since_switch),
            observed: Metrics::default(),
            reported: false,
        }));
    }

    /// The tracker another gateway (or this one before a restart) left in `report`: the window
    /// goes on from its summary, and its readings are the next baseline so far; watched as
    /// long as `asked` says, its outcome already written if the summary spans that. `None`
    /// when the report lacks its release or start.
    pub fn resume(report: &AnalysisReport, asked: Option<&Asked>) -> Option<Self> {
        let release = Release::from(report.release.as_ref()?);
        let observed = Metrics::resume(&report.window);
        let mut window = Window {
            asked: Asked::window_of(asked, &release),
            release,
            start: report.window_start.as_ref()?.0,
            end: report.window_end.as_ref().map(|t| t.0),
            baseline_start: report.baseline_start.as_ref().map(|t| t.0),
            baseline: Metrics::resume(&report.baseline),
            observed: observed.clone(),
            reported: false,
        };
        window.reported = window.complete();
        Some(Self {
            since_switch: observed,
            since_switch_start: report.window_start.as_ref().map(|t| t.0),
            last: Some(Box::new(window)),
        })
    }

    /// Whether the window's outcome is due to be written: a rollout asked for it, its readings
    /// span what it asked, and no status write holding that has landed yet.
    pub fn outcome_due(&self) -> bool {
        self.last
            .as_ref()
            .is_some_and(|w| w.complete() && !w.reported)
    }

    /// A status write of `sent` (this tracker as it was when the write was made) landed: if it
    /// held the complete window of the same switch, that window's outcome is written.
    pub fn written(&mut self, sent: &Tracker) {
        let (Some(w), Some(sent)) = (self.last.as_mut(), sent.last.as_ref()) else {
            return;
        };
        if sent.release == w.release && sent.start == w.start && sent.complete() {
            w.reported = true;
        }
    }

    /// The tracker a new session of a robot that runs `running` starts from: this gateway's
    /// own (`ours`, with the release it last saw), else the one the Robot's `stored` status
    /// holds. If the robot runs another release than this gateway and its status (when a
    /// gateway wrote it: it has a heartbeat time; the controller alone writes only a phase)
    /// last saw, it switched while no gateway saw its `done` (a restart, a move), and that
    /// switch's window opens `now`. A robot's first connection is no switch. `asked` is what
    /// the Robot asks of a switch (see [`Asked::of`]).
    pub fn at_connect(
        ours: Option<(&Tracker, Option<&Release>)>,
        stored: Option<&RobotStatus>,
        running: Option<&Release>,
        asked: Option<&Asked>,
        now: Timestamp,
    ) -> Self {
        let mut tracker = match ours {
            Some((t, _)) => t.clone(),
            None => stored
                .and_then(|s| s.analysis.as_deref())
                // A window that closed is not resumed: the status then drops it.
                .filter(|a| window_open(a))
                .and_then(|a| Self::resume(a, asked))
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
            tracker.switched(release.clone(), now, asked);
        }
        tracker
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
    /// What the Robot of `key`, as the gateway's cache holds it, asks of a switch.
    pub(super) fn asked(&self, key: &lekiwi_core::RobotKey) -> Option<Asked> {
        self.cached_robot(key).as_deref().and_then(Asked::of)
    }

    /// The session `session` of `key` sent an event (`error` if of that severity): counted for
    /// analysis, written with the next status write.
    pub fn event(&self, key: &lekiwi_core::RobotKey, session: u64, error: bool) {
        self.with_state(|s| {
            if let Some(e) = s.live_session(key, session) {
                e.analysis.event(error);
            }
        });
    }

    /// The session `session` of `key` sent telemetry: the highest reading per metric is kept
    /// for analysis.
    pub fn telemetry(&self, key: &lekiwi_core::RobotKey, session: u64, samples: &[Sample]) {
        self.with_state(|s| {
            if let Some(e) = s.live_session(key, session) {
                e.analysis.telemetry(samples);
            }
        });
    }
}

/// Whether `report`'s window is recent enough to matter to a rollout: its switch is at most
/// [`MAX_WINDOW_SECONDS`] old.
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
        t.switched(rel("2"), t0, None);
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
        let resumed = Tracker::resume(&r, None).unwrap();
        assert_eq!(resumed.report(), Some(r.clone()));
        // A second sign of the same switch (the heartbeat, then the `done`) changes nothing.
        let mut again = t.clone();
        again.switched(rel("2"), t0 + SignedDuration::from_secs(5), None);
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
        assert!(!t.outcome_due(), "no rollout asked for this window");

        t.switched(rel("3"), t0 + SignedDuration::from_secs(2), None);
        let r = t.report().unwrap();
        assert_eq!(r.baseline.host_memory_bytes.unwrap().mean, 400.0);
        assert_eq!(r.window, MetricWindow::default());
    }
}
