//! Telemetry collector: one `sysinfo` sampler per metric, each on its own interval, with delta
//! compression (a value is sent only when it moved past its threshold, plus a periodic full
//! sample). Filled in by the telemetry work; see the interface below.
//!
//! Interface the agent loop uses (keep these signatures):
//! - `Telemetry::new(config: &crate::config::Config) -> Telemetry`
//! - `Telemetry::next_due(&self) -> tokio::time::Instant` — when the next sampler is due
//! - `Telemetry::collect_due(&mut self, now: tokio::time::Instant, ts_ms: i64) -> Vec<Sample>`
//! - `Telemetry::vitals(&mut self) -> lekiwi_protocol::Vitals` — for heartbeats
//! - `system_facts() -> lekiwi_protocol::SystemFacts` — for `hello`
