//! Last step of the rollout planner: the status from where every robot ends up after this
//! plan's writes (per-robot results, counts, outcome conditions) and when to look again.

use std::collections::BTreeMap;
use std::time::Duration;

use lekiwi_crds::condition::merge_conditions;
use lekiwi_crds::deployment::{MAX_ROBOT_RESULTS, RobotResult, RobotRolloutState, RolloutPhase};
use lekiwi_crds::{Condition, ConditionStatus};

use super::classify::{Fleet, RobotState};
use super::draft::{Draft, Rollout};
use super::{
    CONDITION_COMPLETE, CONDITION_PROGRESSING, CONDITION_ROLLED_BACK, MarkState, Plan, RobotView,
    RobotWrite, time,
};

/// Targeted robots by outcome.
#[derive(Default)]
struct Counts {
    updated: i32,
    failed: i32,
    skipped: i32,
    /// Not targeted: owned by another deployment.
    superseded: i32,
}

/// How one robot counts and shows in `status.robots`.
struct Entry {
    /// Its row (state, batch, message), if it shows.
    row: Option<(RobotRolloutState, i32, Option<String>)>,
    /// It counts as updated.
    updated: bool,
    /// It failed before it was rolled back (its row says rolled back, the count says failed).
    failed_before_rollback: bool,
}

impl Entry {
    fn row(state: RobotRolloutState, batch: i32, message: Option<String>) -> Self {
        Self {
            row: Some((state, batch, message)),
            updated: false,
            failed_before_rollback: false,
        }
    }

    fn hidden(updated: bool) -> Self {
        Self {
            row: None,
            updated,
            failed_before_rollback: false,
        }
    }
}

/// Fills in the status and turns the draft into the plan.
pub(super) fn finish(rollout: &Rollout<'_>, fleet: &Fleet<'_>, mut draft: Draft) -> Plan {
    let (results, counts) = robot_results(rollout, fleet, &draft.writes);
    let targeted = fleet.targeted as i32;
    let total = fleet.total_batches;
    let (phase, batch) = (draft.phase, draft.current_batch);
    let status = &mut draft.status;
    status.robots = results;
    status.updated = counts.updated;
    status.failed = counts.failed;
    status.skipped = counts.skipped;
    status.superseded = counts.superseded;
    status.pending = (targeted - counts.updated - counts.failed - counts.skipped).max(0);
    status.progress = Some(format!("{}/{targeted}", counts.updated));
    status.current_batch = Some(batch);
    status.batch_progress = Some(format!(
        "{}/{}",
        (batch + 1).min(total.max(1) as i32),
        total
    ));
    status.phase = Some(phase);
    status.message = Some(draft.message.clone());
    outcome_conditions(rollout, &counts, targeted, &mut draft);
    superseded_event(rollout, fleet, &mut draft);
    // Kubernetes 1.20's server-side apply turns "" into null, which the schema refuses.
    for c in &mut draft.conditions {
        if c.message.is_empty() {
            c.message = c.reason.clone();
        }
    }
    if draft.status.message.as_deref() == Some("") {
        draft.status.message = None;
    }
    let events = draft.take_events();
    draft.status.conditions = merge_conditions(&rollout.previous.conditions, draft.conditions);
    let finished = rollout.was_active
        && matches!(
            phase,
            RolloutPhase::Completed
                | RolloutPhase::RolledBack
                | RolloutPhase::Failed
                | RolloutPhase::Aborted
        );
    Plan {
        writes: draft.writes,
        status: draft.status,
        events,
        requeue_after: requeue_after(rollout, phase, draft.wake),
        batch_result: draft.batch_result,
        finished,
    }
}

/// An Event when robots became superseded since the last status: how many, and by whom.
fn superseded_event(rollout: &Rollout<'_>, fleet: &Fleet<'_>, draft: &mut Draft) {
    let now = draft.status.superseded;
    if now <= rollout.previous.superseded {
        return;
    }
    let mut owners: BTreeMap<&str, Vec<&str>> = BTreeMap::new();
    for (robot, state) in &fleet.robots {
        if let RobotState::Superseded(owner) = state {
            owners.entry(owner).or_default().push(&robot.name);
        }
    }
    let by: Vec<String> = owners
        .iter_mut()
        .map(|(owner, robots)| {
            robots.sort_unstable();
            format!("{owner} ({})", robots.join(", "))
        })
        .collect();
    draft.warning(
        "RobotsSuperseded",
        format!(
            "{now} robot(s) are owned by another deployment and left alone: {}",
            by.join("; ")
        ),
    );
}

fn is_active(phase: RolloutPhase) -> bool {
    matches!(
        phase,
        RolloutPhase::Pending
            | RolloutPhase::Progressing
            | RolloutPhase::Paused
            | RolloutPhase::RollingBack
    )
}

/// An active rollout looks again when something is due, at least every 30 s and at most every
/// second; a finished one waits for a change.
fn requeue_after(
    rollout: &Rollout<'_>,
    phase: RolloutPhase,
    wake: Option<jiff::Timestamp>,
) -> Option<Duration> {
    if !is_active(phase) {
        return None;
    }
    let due = wake.map(|w| {
        Duration::try_from(w.duration_since(rollout.now)).unwrap_or(Duration::from_secs(1))
    });
    Some(
        due.unwrap_or(Duration::from_secs(30))
            .clamp(Duration::from_secs(1), Duration::from_secs(30)),
    )
}

/// The Progressing, Complete and RolledBack conditions, from the phase and the counts.
fn outcome_conditions(rollout: &Rollout<'_>, counts: &Counts, targeted: i32, draft: &mut Draft) {
    let (phase, generation) = (draft.phase, rollout.generation);
    let status = |yes: bool| {
        if yes {
            ConditionStatus::True
        } else {
            ConditionStatus::False
        }
    };
    let progressing_reason = match phase {
        RolloutPhase::Paused => "Paused",
        RolloutPhase::RollingBack => "RollingBack",
        RolloutPhase::Completed => "RolloutCompleted",
        RolloutPhase::RolledBack => "RolledBack",
        RolloutPhase::Failed => "Failed",
        RolloutPhase::Aborted => "Aborted",
        _ => "Updating",
    };
    let complete = phase == RolloutPhase::Completed;
    let rolled_back = matches!(phase, RolloutPhase::RolledBack | RolloutPhase::RollingBack);
    let Counts {
        updated,
        failed,
        skipped,
        ..
    } = counts;
    draft.conditions.extend([
        Condition::new(
            CONDITION_PROGRESSING,
            status(is_active(phase)),
            progressing_reason,
            draft.message.clone(),
            generation,
        ),
        Condition::new(
            CONDITION_COMPLETE,
            status(complete),
            if complete {
                "AllRobotsDone"
            } else {
                "InProgress"
            },
            format!("{updated} updated, {failed} failed, {skipped} skipped of {targeted}"),
            generation,
        ),
        Condition::new(
            CONDITION_ROLLED_BACK,
            status(rolled_back),
            if rolled_back {
                "BatchBelowThreshold"
            } else {
                "NotRolledBack"
            },
            if rolled_back {
                draft.message.clone()
            } else {
                String::new()
            },
            generation,
        ),
    ]);
}

/// The rows of `status.robots` (in progress and failures first, then by batch and name;
/// bounded) and the counts, from the robots' states and the writes this plan makes.
fn robot_results(
    rollout: &Rollout<'_>,
    fleet: &Fleet<'_>,
    writes: &[RobotWrite],
) -> (Vec<RobotResult>, Counts) {
    let written: BTreeMap<&str, &RobotWrite> =
        writes.iter().map(|w| (w.robot.as_str(), w)).collect();
    let mut results = Vec::new();
    let mut counts = Counts::default();
    for (robot, state) in &fleet.robots {
        let write = written.get(robot.name.as_str()).copied();
        let entry = entry(robot, state, write);
        counts.updated += i32::from(entry.updated);
        counts.failed += i32::from(entry.failed_before_rollback);
        let Some((state, batch, message)) = entry.row else {
            continue;
        };
        match state {
            RobotRolloutState::Failed => counts.failed += 1,
            RobotRolloutState::Skipped => counts.skipped += 1,
            RobotRolloutState::Superseded => counts.superseded += 1,
            _ => {}
        }
        let mark = write.map(|w| &w.mark).or(robot.mark.as_ref());
        results.push(RobotResult {
            robot: robot.name.clone(),
            batch,
            state,
            previous_release: mark.and_then(|m| m.previous.clone()),
            message,
            started_at: mark
                .filter(|m| m.state != MarkState::Waiting)
                .map(|m| time(m.since)),
            finished_at: None,
        });
    }
    let rank = |s: RobotRolloutState| match s {
        RobotRolloutState::Updating | RobotRolloutState::Waiting => 0,
        RobotRolloutState::Failed => 1,
        RobotRolloutState::RolledBack
        | RobotRolloutState::Skipped
        | RobotRolloutState::Superseded => 2,
        _ => 3,
    };
    results.sort_by(|a, b| {
        (rank(a.state), a.batch, &a.robot).cmp(&(rank(b.state), b.batch, &b.robot))
    });
    results.truncate(MAX_ROBOT_RESULTS);
    keep_finish_times(rollout, &mut results);
    (results, counts)
}

/// Keeps `finishedAt` stable across reconciles: a row in the same state as before keeps its
/// time; a row that just reached a final state gets the current time.
fn keep_finish_times(rollout: &Rollout<'_>, results: &mut [RobotResult]) {
    for r in results {
        if let Some(old) = rollout
            .previous
            .robots
            .iter()
            .find(|o| o.robot == r.robot && o.state == r.state)
        {
            r.finished_at = old.finished_at.clone();
        } else if matches!(
            r.state,
            RobotRolloutState::Updated
                | RobotRolloutState::Failed
                | RobotRolloutState::Skipped
                | RobotRolloutState::RolledBack
        ) {
            r.finished_at = Some(time(rollout.now));
        }
    }
}

/// How one robot shows: a write of this plan wins over the state it was classified in.
fn entry(robot: &RobotView, state: &RobotState, write: Option<&RobotWrite>) -> Entry {
    let mark = write.map(|w| &w.mark).or(robot.mark.as_ref());
    let written_batch = write.map_or(0, |w| w.mark.batch);
    match (state, write.map(|w| w.mark.state)) {
        (RobotState::Maintenance, _) => Entry::hidden(false),
        (RobotState::Superseded(owner), _) => Entry::row(
            RobotRolloutState::Superseded,
            -1,
            Some(format!("owned by deployment {owner}")),
        ),
        (_, Some(MarkState::Started)) => {
            Entry::row(RobotRolloutState::Updating, written_batch, None)
        }
        (_, Some(MarkState::Skipped)) => Entry::row(
            RobotRolloutState::Skipped,
            written_batch,
            write.and_then(|w| w.mark.message.clone()),
        ),
        (_, Some(MarkState::RollingBack)) | (RobotState::RollingBack(..), _) => {
            rolling_back(robot, mark)
        }
        (_, Some(MarkState::Waiting)) | (RobotState::Waiting(..), _) => Entry::row(
            RobotRolloutState::Waiting,
            mark.map_or(0, |m| m.batch),
            Some(robot.waiting_reason()),
        ),
        (RobotState::HeldBy(other), _) => Entry::row(
            RobotRolloutState::Pending,
            -1,
            Some(format!("held by deployment {other}")),
        ),
        (RobotState::Updated, _) => Entry::hidden(true),
        (RobotState::Succeeded(b), _) => Entry {
            updated: true,
            ..Entry::row(RobotRolloutState::Updated, *b, None)
        },
        (RobotState::Pending, _) => Entry::hidden(false),
        (RobotState::Updating(b, _), _) => Entry::row(RobotRolloutState::Updating, *b, None),
        (RobotState::Failed(b, why), _) => {
            Entry::row(RobotRolloutState::Failed, *b, Some(why.clone()))
        }
        (RobotState::Skipped(b, why), _) => {
            Entry::row(RobotRolloutState::Skipped, *b, Some(why.clone()))
        }
    }
}

/// A robot told to switch back: rolled back once it runs its previous release (or had none).
fn rolling_back(robot: &RobotView, mark: Option<&super::Mark>) -> Entry {
    let back = mark
        .and_then(|m| m.previous.as_ref())
        .is_none_or(|p| robot.runs(p));
    let failed = mark.filter(|m| m.failed);
    let why = match failed {
        Some(m) => format!(
            "failed ({}); ",
            m.message.as_deref().unwrap_or("no details")
        ),
        None => String::new(),
    };
    let (state, message) = if back {
        (
            RobotRolloutState::RolledBack,
            format!("{why}back on its previous release"),
        )
    } else {
        (
            RobotRolloutState::Updating,
            format!("{why}switching back to its previous release"),
        )
    };
    Entry {
        failed_before_rollback: failed.is_some(),
        ..Entry::row(state, mark.map_or(0, |m| m.batch), Some(message))
    }
}
