//! Teleoperation detection: a weighted score from indicators read in `/proc`.
//!
//! Interface the agent loop uses (keep these signatures):
//! - `Detector::new(config: &crate::config::Config) -> Detector`
//! - `Detector::check(&mut self) -> Verdict`
//! - `Verdict { active: bool, score: f64, indicators: Vec<String> }`, `Verdict::to_wire()`
