//! Post-switch analysis (`spec.analysis`): a started robot that runs the release and reports
//! healthy counts as updated only once the gateway's window after its switch
//! (`status.analysis`) spans `windowSeconds`, and fails if a metric rose past its threshold
//! over the baseline before the switch.

use jiff::{SignedDuration, Timestamp};
use lekiwi_crds::analysis::{AnalysisReport, AnalysisSpec, MetricSummary};

use super::RobotView;
use super::draft::Rollout;

/// How a started robot's switch settled.
#[derive(Clone, Debug, PartialEq)]
pub(super) enum Settled {
    /// It runs the release healthy (and, with `spec.analysis`, its window passed within the
    /// thresholds).
    Updated,
    /// A metric rose past its threshold over the baseline: why.
    Failed(String),
}

/// How the switch of a started robot, told to switch at `since`, settled; `None`: not yet.
pub(super) fn switched(
    robot: &RobotView,
    since: Timestamp,
    rollout: &Rollout<'_>,
) -> Option<Settled> {
    if !(robot.runs(rollout.target) && robot.healthy) {
        return None;
    }
    let Some(spec) = rollout.analysis else {
        return Some(Settled::Updated);
    };
    let report = robot.analysis.as_ref()?;
    let start = report.window_start.as_ref()?.0;
    let end = report.window_end.as_ref()?.0;
    // Status times are whole seconds: a window opened in the second the robot was started
    // is this switch's.
    if report.release.as_ref() != Some(rollout.target) || start.as_second() < since.as_second() {
        return None;
    }
    let span = end.duration_since(start);
    if span < SignedDuration::from_secs(spec.window_seconds.max(1)) {
        return None;
    }
    let failed = judge(spec, report)
        .or_else(|| judge_events(spec, report, span))
        .or_else(|| judge_telemetry(spec, report));
    Some(match failed {
        Some(why) => Settled::Failed(why),
        None => Settled::Updated,
    })
}

/// A metric a threshold applies to: its name in status, the ratio's name in the spec, and
/// whether the window's highest reading (memory) or its mean (CPU) is compared.
struct Check<'a> {
    metric: &'static str,
    threshold: &'static str,
    max: Option<f64>,
    baseline: Option<&'a MetricSummary>,
    window: Option<&'a MetricSummary>,
    peak: bool,
}

/// Why the report fails `spec`, naming the first metric past its threshold; `None` if none
/// is. A metric missing before or after the switch, or with a zero baseline, is not judged.
fn judge(spec: &AnalysisSpec, report: &AnalysisReport) -> Option<String> {
    let (b, w) = (&report.baseline, &report.window);
    let checks = [
        Check {
            metric: "hostMemoryBytes",
            threshold: "maxHostMemoryRatio",
            max: spec.max_host_memory_ratio,
            baseline: b.host_memory_bytes.as_ref(),
            window: w.host_memory_bytes.as_ref(),
            peak: true,
        },
        Check {
            metric: "hostCpuPercent",
            threshold: "maxHostCpuRatio",
            max: spec.max_host_cpu_ratio,
            baseline: b.host_cpu_percent.as_ref(),
            window: w.host_cpu_percent.as_ref(),
            peak: false,
        },
        Check {
            metric: "memoryPercent",
            threshold: "maxRobotMemoryRatio",
            max: spec.max_robot_memory_ratio,
            baseline: b.memory_percent.as_ref(),
            window: w.memory_percent.as_ref(),
            peak: true,
        },
        Check {
            metric: "rttMs",
            threshold: "maxRttRatio",
            max: spec.max_rtt_ratio,
            baseline: b.rtt_ms.as_ref(),
            window: w.rtt_ms.as_ref(),
            peak: false,
        },
    ];
    checks.iter().find_map(|c| {
        let (max, base, win) = (c.max?, c.baseline?, c.window?);
        let observed = if c.peak { win.max } else { win.mean };
        if base.mean <= 0.0 {
            return None;
        }
        let ratio = observed / base.mean;
        (ratio > max).then(|| {
            let what = if c.peak { "highest" } else { "mean" };
            format!(
                "analysis failed: {} {what} {} after the switch is {ratio:.2}x the baseline \
                 mean {} ({} {max})",
                c.metric,
                number(observed),
                number(base.mean),
                c.threshold
            )
        })
    })
}

/// Why the window's `error` events fail `spec` (their share of the events, or their rate over
/// the window's `span`); `None` if they do not.
fn judge_events(
    spec: &AnalysisSpec,
    report: &AnalysisReport,
    span: SignedDuration,
) -> Option<String> {
    let counts = report.window.events.as_ref()?;
    let errors = f64::from(counts.errors);
    if let Some(max) = spec.max_error_event_fraction
        && counts.total > 0
    {
        let fraction = errors / f64::from(counts.total);
        if fraction > max {
            return Some(format!(
                "analysis failed: {} of {} events after the switch are errors ({fraction:.3}; \
                 maxErrorEventFraction {max})",
                counts.errors, counts.total
            ));
        }
    }
    let max = spec.max_error_events_per_minute?;
    let per_minute = errors * 60.0 / span.as_secs_f64().max(1.0);
    (per_minute > max).then(|| {
        format!(
            "analysis failed: {} error events in {}s after the switch, {per_minute:.2} a minute \
             (maxErrorEventsPerMinute {max})",
            counts.errors,
            span.as_secs()
        )
    })
}

/// Why the window's telemetry fails `spec`: the first metric whose highest reading is above
/// its ceiling; `None` if none is (a metric the robot did not send passes).
fn judge_telemetry(spec: &AnalysisSpec, report: &AnalysisReport) -> Option<String> {
    spec.telemetry.iter().find_map(|ceiling| {
        let seen = report
            .window
            .telemetry
            .iter()
            .find(|t| t.metric == ceiling.metric)?;
        (seen.max > ceiling.max).then(|| {
            format!(
                "analysis failed: telemetry {} reached {} after the switch (ceiling {})",
                ceiling.metric,
                number(seen.max),
                ceiling.max
            )
        })
    })
}

/// A reading for people: whole numbers from 100 up (bytes), two decimals below (percent).
fn number(x: f64) -> String {
    if x >= 100.0 {
        format!("{x:.0}")
    } else {
        format!("{x:.2}")
    }
}

#[cfg(test)]
mod tests {
    use lekiwi_crds::analysis::{EventCounts, MetricWindow, TelemetryCeiling};

    use super::*;

    fn ceiling(metric: &str, max: f64) -> TelemetryCeiling {
        TelemetryCeiling {
            metric: metric.into(),
            max,
        }
    }

    /// A telemetry ceiling fails the robot when the window's highest reading is above it; a
    /// metric the robot did not send passes.
    #[test]
    fn a_reading_above_its_ceiling_fails_the_robot() {
        let report = AnalysisReport {
            window: MetricWindow {
                telemetry: vec![ceiling("cpu_percent", 80.0)],
                ..MetricWindow::default()
            },
            ..AnalysisReport::default()
        };
        let spec = |c: Vec<TelemetryCeiling>| AnalysisSpec {
            telemetry: c,
            ..AnalysisSpec::default()
        };
        let pass = spec(vec![ceiling("cpu_percent", 80.0), ceiling("other", 0.0)]);
        assert_eq!(judge_telemetry(&pass, &report), None);
        let why = judge_telemetry(&spec(vec![ceiling("cpu_percent", 75.0)]), &report).unwrap();
        assert_eq!(
            why,
            "analysis failed: telemetry cpu_percent reached 80.00 after the switch (ceiling 75)"
        );
    }

    fn summary(mean: f64, max: f64) -> Option<MetricSummary> {
        Some(MetricSummary {
            samples: 3,
            mean,
            max,
        })
    }

    /// Memory is judged on the window's peak, CPU on its mean; the message names the metric,
    /// the value, the baseline and the threshold; an unset threshold or missing metric passes.
    #[test]
    fn the_first_metric_past_its_ratio_fails_the_robot() {
        let report = AnalysisReport {
            baseline: MetricWindow {
                host_memory_bytes: summary(100.0, 110.0),
                host_cpu_percent: summary(10.0, 50.0),
                memory_percent: None,
                ..MetricWindow::default()
            },
            window: MetricWindow {
                host_memory_bytes: summary(120.0, 200.0),
                host_cpu_percent: summary(15.0, 90.0),
                memory_percent: summary(90.0, 95.0),
                events: Some(EventCounts {
                    total: 10,
                    errors: 2,
                }),
                telemetry: vec![ceiling("cpu_percent", 80.0)],
                ..MetricWindow::default()
            },
            ..AnalysisReport::default()
        };
        let spec = |mem: Option<f64>, cpu: Option<f64>| AnalysisSpec {
            max_host_memory_ratio: mem,
            max_host_cpu_ratio: cpu,
            max_robot_memory_ratio: Some(1.0),
            ..AnalysisSpec::default()
        };
        assert_eq!(judge(&spec(None, None), &report), None);
        assert_eq!(judge(&spec(Some(2.0), Some(1.5)), &report), None);
        let why = judge(&spec(Some(1.5), Some(1.5)), &report).unwrap();
        assert_eq!(
            why,
            "analysis failed: hostMemoryBytes highest 200 after the switch is 2.00x the baseline \
             mean 100 (maxHostMemoryRatio 1.5)"
        );
        let why = judge(&spec(None, Some(1.4)), &report).unwrap();
        assert!(
            why.contains("hostCpuPercent mean 15.00 after the switch is 1.50x"),
            "{why}"
        );

        // Errors: 2 of 10 events, 2 in 60 s.
        let events = |fraction: Option<f64>, per_minute: Option<f64>| AnalysisSpec {
            max_error_event_fraction: fraction,
            max_error_events_per_minute: per_minute,
            ..AnalysisSpec::default()
        };
        let minute = SignedDuration::from_secs(60);
        assert_eq!(
            judge_events(&events(Some(0.2), Some(2.0)), &report, minute),
            None
        );
        let why = judge_events(&events(Some(0.1), None), &report, minute).unwrap();
        assert!(
            why.contains("2 of 10 events after the switch are errors"),
            "{why}"
        );
        let why = judge_events(&events(None, Some(1.5)), &report, minute).unwrap();
        assert!(
            why.contains("2 error events in 60s after the switch, 2.00 a minute"),
            "{why}"
        );
    }
}
