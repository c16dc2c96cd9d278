//! The gateway's server-side-apply patch of a `Robot` status, built from the `crds` types
//! ([`lekiwi_core::apply::StatusApply`], as the controllers' writes are) so that a renamed or retyped
//! status field fails to compile here instead of silently writing a key the CRD schema does not
//! know.
//!
//! The patch holds exactly the fields the gateway owns, plus the phase and conditions they
//! imply when the gateway can plan them ([`super::phase`]): server-side apply drops a field its
//! manager stops sending, so an unset fact is left out (every `RobotStatus` field is skipped
//! when `None`), never sent as `null`.

use k8s_openapi::apimachinery::pkg::apis::meta::v1::{MicroTime, Time};
use lekiwi_crds::release::ReleaseRef;
use lekiwi_crds::robot::{
    HealthReport, Robot, RobotStatus, SystemInfo, TelemetrySummary, TeleoperationReport,
    UpdateReport,
};
use lekiwi_protocol::{SystemFacts, Vitals, rules};
use serde_json::Value;

use super::{Entry, UpdateOutcome};
use lekiwi_core::apply::{Metadata, StatusApply};

/// The agent's explanation of an update outcome is cut to this many characters.
const MAX_UPDATE_MESSAGE_CHARS: usize = 1024;

/// The apply patch of the robot's status as `gateway` sees it in `e`; with a `precondition`,
/// the write only succeeds against that version of the robot.
#[cfg(test)]
pub(super) fn status_patch(gateway: &str, e: &Entry, precondition: Option<Metadata>) -> Value {
    planned_status_patch(gateway, e, precondition, |_| {})
}

/// The apply patch as `status_patch` builds it, with `plan` adding the phase and conditions the facts imply (see
/// [`super::phase`]).
pub(super) fn planned_status_patch(
    gateway: &str,
    e: &Entry,
    precondition: Option<Metadata>,
    plan: impl FnOnce(&mut RobotStatus),
) -> Value {
    let mut status = gateway_status(gateway, e);
    plan(&mut status);
    let patch = StatusApply::new::<Robot>(status).with_metadata(precondition);
    // A `Value` keeps the keys sorted, as the hand-written patch had them on the wire.
    serde_json::to_value(patch).unwrap_or(Value::Null)
}

/// The status fields the gateway owns. Every field is named, none defaulted, so that a field
/// added to `RobotStatus` must be placed here or explicitly left to the controller. With
/// `presence_only`, just the facts of the connection itself.
pub(super) fn gateway_status(gateway: &str, e: &Entry) -> RobotStatus {
    let info = &e.info;
    if e.presence_only {
        return RobotStatus {
            connected: Some(e.connected),
            gateway: Some(gateway.into()),
            protocol: Some(info.protocol.into()),
            last_heartbeat_time: Some(Time(e.last_heartbeat)),
            connected_since: Some(Time(e.connected_since)),
            session_epoch: Some(e.epoch),
            ..RobotStatus::default()
        };
    }
    RobotStatus {
        // Planned by `super::phase` (shared with the Robot controller), not a gateway fact.
        phase: None,
        conditions: Vec::new(),
        observed_generation: None,
        // Owned by the gateway.
        connected: Some(e.connected),
        gateway: Some(gateway.into()),
        protocol: Some(info.protocol.into()),
        last_heartbeat_time: Some(Time(e.last_heartbeat)),
        connected_since: Some(Time(e.connected_since)),
        session_epoch: Some(e.epoch),
        agent_version: Some(rules::cut_text(&info.agent_version, rules::MAX_TEXT_CHARS))
            .filter(|v| !v.is_empty())
            .map(Into::into),
        agent_digest: info.agent_digest.clone().map(Into::into),
        current_release: info.release.as_ref().map(ReleaseRef::from),
        address: info.address.clone(),
        health: info.health.as_ref().map(|h| HealthReport {
            healthy: h.healthy,
            message: h.message.clone(),
            reason: h.reason.clone(),
        }),
        teleoperation: info.teleoperation.as_ref().map(|t| TeleoperationReport {
            active: t.active,
            score: t.score.map(|s| s.clamp(0.0, 1.0)),
            since: e.teleoperation_since.map(Time),
        }),
        system: system_info(&info.system).map(Box::new),
        telemetry: telemetry_summary(&e.vitals).map(Box::new),
        last_update: e.last_update.as_ref().map(|u| Box::new(update_report(u))),
        analysis: e.analysis.report().map(Box::new),
        agent_update: e
            .agent_update
            .as_ref()
            .map(|u| Box::new(super::agent::report(u))),
    }
}

/// The system facts the agent sent, or `None` when it sent none (no empty object).
fn system_info(sys: &SystemFacts) -> Option<SystemInfo> {
    let info = SystemInfo {
        hostname: sys.hostname.clone(),
        os: sys.os.clone().map(Into::into),
        kernel: sys.kernel.clone().map(Into::into),
        arch: sys.arch.clone().map(Into::into),
        cpus: sys.cpus,
        memory_bytes: sys.memory_bytes,
    };
    (info != SystemInfo::default()).then_some(info)
}

/// The finite readings of the last heartbeat, or `None` when there is none: JSON has no NaN.
fn telemetry_summary(v: &Vitals) -> Option<TelemetrySummary> {
    let finite = |x: Option<f64>| x.filter(|x| x.is_finite());
    let summary = TelemetrySummary {
        cpu_percent: finite(v.cpu_percent),
        memory_percent: finite(v.memory_percent),
        temperature_celsius: finite(v.temperature_c),
        battery_percent: finite(v.battery_percent),
        host_memory_bytes: v.host_rss_bytes.filter(|&b| b <= rules::MAX_MEMORY_BYTES),
        host_cpu_percent: finite(v.host_cpu_percent),
    };
    (summary != TelemetrySummary::default()).then_some(summary)
}

fn update_report(u: &UpdateOutcome) -> UpdateReport {
    UpdateReport {
        release: Some(ReleaseRef::from(&u.release)),
        phase: Some(u.phase.clone()),
        message: u
            .message
            .as_ref()
            .map(|m| m.chars().take(MAX_UPDATE_MESSAGE_CHARS).collect()),
        time: Some(MicroTime(u.time)),
    }
}
