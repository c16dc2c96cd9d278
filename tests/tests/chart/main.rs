//! The Helm chart rendered and linted offline, and its PrometheusRule under promtool.
//!
//! One test binary per group, a module per file: the harness is linked once per group.

mod chart;
mod chart_alerts;
