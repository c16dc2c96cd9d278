//! Second step of the rollout planner: what may stop or turn the rollout regardless of its
//! robots (an invalid release, an older overlapping deployment, a user's undo or abort), each
//! reported as a condition.

use lekiwi_crds::{Condition, ConditionStatus};

use super::draft::{Draft, Rollout};
use super::{CONDITION_CONFLICT, CONDITION_RELEASE_VALID, Overlap, ReleaseCheck};

/// The verdicts of the gates.
pub(super) struct Gates<'a> {
    /// The release may be rolled out (valid, or not checked in this process).
    pub release_ok: bool,
    /// The first older active deployment that selects some of our robots: ours waits for it.
    pub older_overlap: Option<&'a Overlap>,
    /// A user asked for `rollout undo` after this rollout started.
    pub undo_requested: bool,
    /// A user asked for `rollout abort` after this rollout started.
    pub abort_requested: bool,
}

impl<'a> Gates<'a> {
    /// Checks the gates and adds the ReleaseValid and Conflict conditions to the draft.
    pub fn check(rollout: &Rollout<'a>, draft: &mut Draft) -> Self {
        let release_ok = check_release(rollout, draft);
        let older_overlap = rollout.overlaps.iter().find(|o| o.earlier);
        draft
            .conditions
            .push(conflict_condition(older_overlap, rollout.generation));
        let started = rollout
            .started
            .or_else(|| draft.status.start_time.as_ref().map(|t| t.0));
        // An undo or abort asked for before this rollout started was of an earlier one.
        let since_start =
            |at: Option<jiff::Timestamp>| at.is_some_and(|at| started.is_none_or(|s| at > s));
        Self {
            release_ok,
            older_overlap,
            undo_requested: since_start(rollout.undo_at),
            abort_requested: since_start(rollout.abort_at),
        }
    }
}

/// The ReleaseValid condition (none when the release was not checked).
fn check_release(rollout: &Rollout<'_>, draft: &mut Draft) -> bool {
    match rollout.release {
        ReleaseCheck::Invalid(why) => {
            draft.conditions.push(Condition::new(
                CONDITION_RELEASE_VALID,
                ConditionStatus::False,
                "InvalidRelease",
                why.clone(),
                rollout.generation,
            ));
            false
        }
        ReleaseCheck::Valid => {
            draft.conditions.push(Condition::new(
                CONDITION_RELEASE_VALID,
                ConditionStatus::True,
                "ManifestComplete",
                format!("{}: manifest and every file present", rollout.target),
                rollout.generation,
            ));
            true
        }
        ReleaseCheck::Unchecked => true,
    }
}

fn conflict_condition(older: Option<&Overlap>, generation: Option<i64>) -> Condition {
    match older {
        Some(o) => Condition::new(
            CONDITION_CONFLICT,
            ConditionStatus::True,
            "SelectorOverlap",
            format!(
                "{} robot(s) (e.g. {}) are also selected by the older active deployment {}; waiting for it to finish",
                o.robots.len(),
                o.robots.first().cloned().unwrap_or_default(),
                o.deployment
            ),
            generation,
        ),
        None => Condition::new(
            CONDITION_CONFLICT,
            ConditionStatus::False,
            "NoOverlap",
            "",
            generation,
        ),
    }
}
