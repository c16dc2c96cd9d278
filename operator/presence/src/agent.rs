//! The robot's latest agent update (`status.agentUpdate`): what the gateway did about
//! `spec.agent` and what the agent reported back in its `agent_update_*` events.

use jiff::Timestamp;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::MicroTime;
use lekiwi_crds::AgentUpdateReport;

use super::{Entry, Presence, Priority, State};
use lekiwi_core::RobotKey;

/// Longest message written to `status.agentUpdate.message`, in characters.
const MAX_MESSAGE_CHARS: usize = 1024;

/// One step of an agent update, as written to `status.agentUpdate`.
#[derive(Clone, Debug, PartialEq)]
pub struct AgentUpdateOutcome {
    /// The agent version it is about.
    pub version: String,
    /// `Sent`, `Started`, `Succeeded`, `Failed`, `FallenBack`, `Unavailable` or `Unsupported`.
    pub phase: &'static str,
    /// Why, in words.
    pub message: String,
    /// When the gateway saw it.
    pub time: Timestamp,
}

impl Presence {
    /// A step of the agent update of `key` in session `session`, kept if it differs from the
    /// last one (time aside); `true` if it did. An outcome is written at once; a step in
    /// progress (`Sent`, `Started`) goes with the robot's next write (the outcome's, or the
    /// session's end as the agent restarts into the new build), one status write per robot of
    /// an agent rollout fewer each.
    pub fn agent_update(&self, key: &RobotKey, session: u64, outcome: AgentUpdateOutcome) -> bool {
        let changed = self.with_state(|s| {
            let Some(e) = s.robots.get_mut(key).filter(|e| e.session == session) else {
                return false;
            };
            let same = e.agent_update.as_ref().is_some_and(|old| {
                old.version == outcome.version
                    && old.phase == outcome.phase
                    && old.message == outcome.message
            });
            if same {
                return false;
            }
            let in_progress = matches!(outcome.phase, "Sent" | "Started");
            e.agent_update = Some(Box::new(outcome));
            if !in_progress {
                s.enqueue(key, Priority::High);
            }
            true
        });
        if changed {
            self.wake();
        }
        changed
    }
}

impl Presence {
    /// Whether the latest agent update of `key` to `version` fell back (the robot refuses that
    /// build from then on; the gateway does not send it again).
    pub fn agent_update_fell_back(&self, key: &RobotKey, version: &str) -> bool {
        self.with_state(|s| {
            s.robots
                .get(key)
                .and_then(|e| e.agent_update.as_ref())
                .is_some_and(|o| o.version == version && o.phase == "FallenBack")
        })
    }
}

/// How long, in seconds, the end of a session whose agent restarts into its update waits for
/// the agent's next session before it is written: an update then costs the robot one status
/// write (the new session's, with the new version), not two (the end, then the new start).
pub const RESTART_GRACE_SECONDS: u8 = 15;

/// Whether the session of `key` that ended now ended as its agent restarts into the update in
/// progress: then its end waits for the next session (see [`RESTART_GRACE_SECONDS`]).
pub(super) fn wait_for_restart(s: &mut State, key: &RobotKey) -> bool {
    let Some(e) = s.robots.get_mut(key) else {
        return false;
    };
    let restarting = in_progress(e);
    if restarting {
        e.restart_grace = RESTART_GRACE_SECONDS;
    }
    restarting
}

/// How long, in seconds, the first session after an agent restarted into its update waits to
/// be written for the agent's `agent_update_*` report, which it sends as soon as it is
/// welcomed: the new session and the update's outcome then cost the robot one status write.
pub const REPORT_WAIT_SECONDS: u8 = 2;

/// Whether `old`, the entry a new session of its robot replaces, is the session of an agent
/// that restarted into its update: a session's end held back for it (see
/// [`wait_for_restart`]), or a session still open with an update in progress, whose end this
/// gateway had not noticed yet when the restarted agent connected again (a busy gateway reads
/// a closed socket late). The new session is then written with the agent's report of the
/// update, or after [`REPORT_WAIT_SECONDS`].
pub(super) fn restarted_into_update(old: &Entry) -> bool {
    if old.connected {
        in_progress(old)
    } else {
        old.restart_grace > 0
    }
}

/// Whether the latest agent update of `e` is under way (`Sent` or `Started`).
fn in_progress(e: &Entry) -> bool {
    e.agent_update
        .as_ref()
        .is_some_and(|u| matches!(u.phase, "Sent" | "Started"))
}

/// One second of the restart grace of `e` (see [`RESTART_GRACE_SECONDS`]) went by: whether it
/// ran out just now, and the session's end is written.
pub(super) fn grace_ran_out(e: &mut Entry) -> bool {
    if e.restart_grace == 0 {
        return false;
    }
    e.restart_grace -= 1;
    e.restart_grace == 0
}

/// The status field of an outcome.
pub(super) fn report(o: &AgentUpdateOutcome) -> AgentUpdateReport {
    AgentUpdateReport {
        version: Some(o.version.clone()),
        phase: Some(o.phase.to_owned()),
        message: Some(o.message.chars().take(MAX_MESSAGE_CHARS).collect()),
        time: Some(MicroTime(o.time)),
    }
}
