//! Scenario tests of the rollout planner: a small simulated fleet driven through plans.

use super::*;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::{LabelSelector, ObjectMeta};
use lekiwi_crds::ConditionStatus;
use lekiwi_crds::RobotDeploymentSpec;
use lekiwi_crds::deployment::{RobotRolloutState, RolloutPhase, RolloutStrategy};

fn rel(v: &str) -> ReleaseRef {
    ReleaseRef {
        version: v.into(),
        digest: format!(
            "sha256:{}",
            v.repeat(64).chars().take(64).collect::<String>()
        )
        .into(),
    }
}

fn deployment(batch: IntOrString, canary: i32) -> RobotDeployment {
    let mut d = RobotDeployment::new(
        "roll",
        RobotDeploymentSpec {
            selector: LabelSelector::default(),
            release: Some(rel("2")),
            agent: None,
            strategy: RolloutStrategy {
                batch_size: batch,
                canary,
                success_threshold: 0.8,
                robot_timeout_seconds: 60,
                pause_between_batches_seconds: 0,
                wait_timeout_seconds: 300,
                ..RolloutStrategy::default()
            },
            paused: false,
            analysis: None,
            priority: 0,
        },
    );
    d.metadata = ObjectMeta {
        name: Some("roll".into()),
        namespace: Some("lab".into()),
        generation: Some(1),
        ..ObjectMeta::default()
    };
    d
}

fn robot(i: usize) -> RobotView {
    RobotView {
        name: format!("kiwi-{i:02}"),
        maintenance: false,
        phase: Some(RobotPhase::Online),
        healthy: true,
        teleoperated: false,
        desired: Some(rel("1")),
        current: Some(rel("1")),
        last_update: None,
        mark: None,
        analysis: None,
        superseded_by: None,
        ..RobotView::default()
    }
}

struct Sim {
    d: RobotDeployment,
    robots: Vec<RobotView>,
    now: Timestamp,
    /// Robots whose health check fails on the new release (the agent switches back).
    failing: Vec<String>,
    events: Vec<&'static str>,
}

impl Sim {
    fn new(d: RobotDeployment, n: usize) -> Self {
        Self {
            d,
            robots: (0..n).map(robot).collect(),
            now: "2026-11-22T10:00:00Z".parse().unwrap(),
            failing: Vec::new(),
            events: Vec::new(),
        }
    }

    fn facts(&self) -> Facts {
        Facts {
            now: self.now,
            robots: self.robots.clone(),
            target: self.d.spec.release.clone().unwrap(),
            release: ReleaseCheck::Valid,
            overlaps: Vec::new(),
            active_deployments: vec!["roll".into()],
        }
    }

    /// One reconcile: plan, apply writes and status.
    fn step(&mut self) -> Plan {
        let plan = plan(&self.d, &self.facts());
        for w in &plan.writes {
            let r = self.robots.iter_mut().find(|r| r.name == w.robot).unwrap();
            r.mark = Some(w.mark.clone());
            if w.release.is_some() {
                r.desired = w.release.clone();
            }
        }
        // As the API server keeps it: times to the whole second.
        let stored = serde_json::to_value(&plan.status).unwrap();
        self.d.status = Some(serde_json::from_value(stored).unwrap());
        self.events.extend(plan.events.iter().map(|e| e.reason));
        plan
    }

    /// Agents act on their desired release.
    fn agents(&mut self) {
        for r in &mut self.robots {
            if r.desired != r.current && r.phase == Some(RobotPhase::Online) && !r.teleoperated {
                let want = r.desired.clone().unwrap();
                if self.failing.contains(&r.name) && want == rel("2") {
                    r.last_update = Some((
                        want,
                        "rolled_back".into(),
                        Some("health check failed".into()),
                        Some(self.now),
                    ));
                } else {
                    r.current = Some(want.clone());
                    r.last_update = Some((want, "done".into(), None, Some(self.now)));
                }
            }
        }
    }

    fn advance(&mut self, s: i64) {
        self.now += SignedDuration::from_secs(s);
    }

    fn phase(&self) -> RolloutPhase {
        self.d.status.as_ref().unwrap().phase.unwrap()
    }

    fn run_until_done(&mut self, max_steps: usize) -> usize {
        for i in 0..max_steps {
            self.step();
            if matches!(
                self.phase(),
                RolloutPhase::Completed
                    | RolloutPhase::RolledBack
                    | RolloutPhase::Failed
                    | RolloutPhase::Aborted
            ) {
                return i;
            }
            self.agents();
            self.advance(1);
        }
        panic!("no end after {max_steps} steps: {:?}", self.d.status);
    }
}

#[test]
fn batch_sizes_and_counts() {
    assert_eq!(batch_size(&IntOrString::String("25%".into()), 10), 3);
    assert_eq!(batch_size(&IntOrString::String("10%".into()), 200), 20);
    assert_eq!(batch_size(&IntOrString::Int(0), 10), 1);
    assert_eq!(total_batches(1, 3, 10), 4);
    assert_eq!(total_batches(0, 20, 200), 10);
    assert_eq!(total_batches(5, 3, 2), 1);
    assert_ne!(
        rollout_id(&rel("2"), None),
        rollout_id(&rel("2"), Some("2026"))
    );
}

#[test]
fn a_clean_rollout_goes_canary_first_then_in_batches() {
    let mut sim = Sim::new(deployment(IntOrString::Int(3), 1), 10);
    let first = sim.step();
    assert_eq!(first.writes.len(), 1, "canary batch of one");
    assert_eq!(first.writes[0].robot, "kiwi-00");
    assert_eq!(first.writes[0].release, Some(rel("2")));
    assert_eq!(first.writes[0].mark.previous, Some(rel("1")));
    assert_eq!(sim.phase(), RolloutPhase::Progressing);
    assert_eq!(sim.d.status.as_ref().unwrap().total_batches, Some(4));
    sim.run_until_done(50);
    let st = sim.d.status.clone().unwrap();
    assert_eq!(st.phase, Some(RolloutPhase::Completed));
    assert_eq!((st.updated, st.failed, st.targeted), (10, 0, 10));
    assert!(sim.robots.iter().all(|r| r.current == Some(rel("2"))));
    let batches = sim.events.iter().filter(|e| **e == "BatchStarted").count();
    assert_eq!(batches, 4);
    // Batches contain the robots in name order.
    let marks: Vec<i32> = sim
        .robots
        .iter()
        .map(|r| r.mark.as_ref().unwrap().batch)
        .collect();
    assert_eq!(marks, vec![0, 1, 1, 1, 2, 2, 2, 3, 3, 3]);
    // A finished rollout asks for nothing more.
    let again = sim.step();
    assert!(again.writes.is_empty() && again.requeue_after.is_none());
}

#[test]
fn a_failing_batch_rolls_every_updated_robot_back() {
    let mut sim = Sim::new(deployment(IntOrString::Int(10), 0), 20);
    // 3 of the second batch fail their health check: 70% < 80%.
    sim.failing = vec!["kiwi-10".into(), "kiwi-13".into(), "kiwi-17".into()];
    sim.run_until_done(50);
    let st = sim.d.status.clone().unwrap();
    assert_eq!(st.phase, Some(RolloutPhase::RolledBack), "{:?}", st.message);
    assert!(
        st.message.as_deref().unwrap().contains("3 of 10"),
        "{:?}",
        st.message
    );
    assert!(
        sim.robots.iter().all(|r| r.current == Some(rel("1"))),
        "every robot back on the previous release"
    );
    assert!(sim.events.contains(&"RollbackStarted") && sim.events.contains(&"RolledBack"));
    assert!(sim.events.contains(&"RobotUpdateFailed"));
    let rolled_back = st
        .robots
        .iter()
        .filter(|r| r.state == RobotRolloutState::RolledBack)
        .count();
    assert_eq!(rolled_back, 20);
    assert_eq!(st.failed, 3, "failures still counted after the rollback");
}

#[test]
fn teleoperated_robots_are_waited_for_and_never_interrupted() {
    let mut sim = Sim::new(deployment(IntOrString::Int(5), 0), 5);
    sim.robots[2].teleoperated = true;
    sim.step();
    let r2 = &sim.robots[2];
    assert_eq!(r2.mark.as_ref().unwrap().state, MarkState::Waiting);
    assert_eq!(
        r2.desired,
        Some(rel("1")),
        "not told to switch while teleoperated"
    );
    for _ in 0..5 {
        sim.agents();
        sim.advance(10);
        sim.step();
    }
    assert_eq!(sim.phase(), RolloutPhase::Progressing, "waits for it");
    assert_eq!(sim.robots[2].current, Some(rel("1")));
    sim.robots[2].teleoperated = false;
    sim.run_until_done(20);
    assert_eq!(sim.phase(), RolloutPhase::Completed);
    assert_eq!(sim.robots[2].current, Some(rel("2")));
}

#[test]
fn robots_waited_for_too_long_are_skipped_and_offline_ones_skipped_at_once() {
    let mut d = deployment(IntOrString::Int(5), 0);
    d.spec.strategy.wait_timeout_seconds = 100;
    let mut sim = Sim::new(d, 5);
    sim.robots[1].teleoperated = true;
    sim.robots[3].phase = Some(RobotPhase::Offline);
    sim.step();
    assert_eq!(
        sim.robots[3].mark.as_ref().unwrap().state,
        MarkState::Skipped,
        "unavailable: Skip by default"
    );
    sim.agents();
    sim.advance(101);
    sim.run_until_done(10);
    let st = sim.d.status.clone().unwrap();
    assert_eq!(st.phase, Some(RolloutPhase::Completed));
    assert_eq!((st.updated, st.skipped), (3, 2));
    assert_eq!(sim.robots[1].current, Some(rel("1")));
}

/// The rollout rolls back, and says a robot timed out.
fn assert_rolling_back_on_a_timeout(sim: &Sim) {
    assert_eq!(sim.phase(), RolloutPhase::RollingBack);
    let st = sim.d.status.as_ref().unwrap();
    assert!(
        st.message.as_deref().unwrap().contains("timed out"),
        "{:?}",
        st.message
    );
}

/// Two robots started in one batch that must all succeed; kiwi-01 goes offline mid-update and
/// never reports (kiwi-00 succeeds).
fn one_robot_silent() -> Sim {
    let mut d = deployment(IntOrString::Int(2), 0);
    d.spec.strategy.success_threshold = 1.0;
    let mut sim = Sim::new(d, 2);
    sim.step();
    sim.robots[1].phase = Some(RobotPhase::Offline);
    sim.agents();
    sim
}

#[test]
fn silent_robots_fail_after_the_timeout() {
    let mut sim = one_robot_silent();
    sim.advance(30);
    sim.step();
    assert_eq!(sim.phase(), RolloutPhase::Progressing);
    sim.advance(31);
    sim.step();
    assert_rolling_back_on_a_timeout(&sim);
}

/// The soak's canary that timed out on a store a minute behind: a robot past its timeout on a
/// view that was not read fresh (`unconfirmed`) stays in progress, and the plan looks again
/// within a second; on a fresh view that still shows it silent, it fails.
#[test]
fn a_timeout_waits_for_a_fresh_view_of_the_robot() {
    let mut sim = one_robot_silent();
    sim.advance(61);
    sim.robots[1].unconfirmed = true;
    let plan = sim.step();
    assert_eq!(sim.phase(), RolloutPhase::Progressing);
    assert_eq!(plan.requeue_after, Some(std::time::Duration::from_secs(1)));
    sim.robots[1].unconfirmed = false;
    sim.step();
    assert_rolling_back_on_a_timeout(&sim);
}

#[test]
fn an_offline_robot_that_comes_back_in_time_succeeds() {
    let mut sim = Sim::new(deployment(IntOrString::Int(2), 0), 2);
    sim.step();
    sim.robots[1].phase = Some(RobotPhase::Offline);
    sim.agents();
    sim.advance(20);
    sim.step();
    sim.robots[1].phase = Some(RobotPhase::Online);
    sim.run_until_done(10);
    assert_eq!(sim.phase(), RolloutPhase::Completed);
    assert_eq!(sim.d.status.as_ref().unwrap().updated, 2);
}

#[test]
fn a_restarted_controller_does_not_redeploy_finished_robots() {
    let mut sim = Sim::new(deployment(IntOrString::Int(2), 0), 6);
    sim.step(); // batch 0 formed
    sim.agents();
    sim.step(); // batch 0 done
    sim.step(); // batch 1 formed
    sim.agents(); // kiwi-00..03 run the release
    // A new leader starts from the objects only: status and marks are all it has.
    let plan = plan(&sim.d, &sim.facts());
    assert!(
        plan.writes
            .iter()
            .all(|w| !["kiwi-00", "kiwi-01", "kiwi-02", "kiwi-03"].contains(&w.robot.as_str())),
        "{:?}",
        plan.writes
    );
    sim.run_until_done(20);
    assert_eq!(sim.phase(), RolloutPhase::Completed);
}

#[test]
fn editing_the_release_starts_over_from_the_canary() {
    let mut sim = Sim::new(deployment(IntOrString::Int(2), 1), 5);
    sim.step();
    sim.agents();
    sim.step();
    sim.d.spec.release = Some(rel("3"));
    let p = sim.step();
    assert_eq!(
        p.writes.len(),
        1,
        "canary of the new rollout: {:?}",
        p.writes
    );
    assert_eq!(p.writes[0].release, Some(rel("3")));
    assert_eq!(p.writes[0].mark.previous, Some(rel("2")));
    assert!(sim.events.contains(&"RolloutRestarted"));
    sim.run_until_done(30);
    assert!(sim.robots.iter().all(|r| r.current == Some(rel("3"))));
}

#[test]
fn paused_rollouts_start_no_new_robot() {
    let mut sim = Sim::new(deployment(IntOrString::Int(2), 0), 4);
    sim.step();
    sim.d.spec.paused = true;
    sim.agents();
    for _ in 0..3 {
        let p = sim.step();
        assert!(p.writes.iter().all(|w| w.release.is_none()));
        sim.agents();
        sim.advance(5);
    }
    assert_eq!(sim.phase(), RolloutPhase::Paused);
    assert_eq!(sim.d.status.as_ref().unwrap().updated, 2);
    sim.d.spec.paused = false;
    sim.run_until_done(10);
    assert_eq!(sim.d.status.as_ref().unwrap().updated, 4);
}

#[test]
fn a_pause_sends_robots_not_yet_switched_back_and_a_resume_starts_them_again() {
    let mut sim = Sim::new(deployment(IntOrString::Int(2), 0), 4);
    sim.step();
    sim.d.spec.paused = true;
    let p = sim.step();
    let held: Vec<_> = p
        .writes
        .iter()
        .map(|w| (w.robot.as_str(), w.release.clone()))
        .collect();
    assert_eq!(
        held,
        [("kiwi-00", Some(rel("1"))), ("kiwi-01", Some(rel("1")))],
        "their spec goes back to the release they run, which cancels the download"
    );
    assert!(p.writes.iter().all(|w| w.mark.state == MarkState::Waiting));
    sim.agents();
    sim.advance(1000);
    let p = sim.step();
    assert!(
        p.writes.is_empty(),
        "a pause longer than the wait timeout skips nobody"
    );
    assert_eq!(sim.phase(), RolloutPhase::Paused);
    sim.d.spec.paused = false;
    let p = sim.step();
    assert!(
        p.writes.iter().all(|w| w.release == Some(rel("2"))),
        "{:?}",
        p.writes
    );
    assert_eq!(p.writes.len(), 2);
    sim.run_until_done(10);
    assert_eq!(sim.d.status.as_ref().unwrap().updated, 4);
}

#[test]
fn robots_another_deployment_owns_are_left_alone_and_shown_superseded() {
    let mut sim = Sim::new(deployment(IntOrString::Int(5), 0), 4);
    sim.run_until_done(10);
    assert_eq!(sim.phase(), RolloutPhase::Completed);
    for r in &mut sim.robots[2..] {
        r.superseded_by = Some("team-b".into());
        r.current = Some(rel("9"));
    }
    sim.d.spec.release = Some(rel("2"));
    let p = sim.step();
    assert!(
        p.writes.is_empty(),
        "a superseded robot is not taken back: {:?}",
        p.writes
    );
    let st = sim.d.status.clone().unwrap();
    assert_eq!(st.phase, Some(RolloutPhase::Completed));
    assert_eq!((st.targeted, st.updated, st.superseded), (2, 2, 2));
    assert_eq!(st.progress.as_deref(), Some("2/2"));
    let rows: Vec<_> = st
        .robots
        .iter()
        .filter(|r| r.state == RobotRolloutState::Superseded)
        .collect();
    assert_eq!(rows.len(), 2);
    assert_eq!(
        rows[0].message.as_deref(),
        Some("owned by deployment team-b")
    );
    let event = p
        .events
        .iter()
        .find(|e| e.reason == "RobotsSuperseded")
        .unwrap();
    assert!(
        event.note.contains("team-b (kiwi-02, kiwi-03)"),
        "{}",
        event.note
    );
    assert!(
        !sim.step()
            .events
            .iter()
            .any(|e| e.reason == "RobotsSuperseded"),
        "once"
    );
}

#[test]
fn an_invalid_release_fails_clearly_and_a_younger_overlap_waits() {
    let sim = Sim::new(deployment(IntOrString::Int(2), 0), 2);
    let mut facts = sim.facts();
    facts.release = ReleaseCheck::Invalid("release sha256:22… not found in the blob store".into());
    let p = plan(&sim.d, &facts);
    assert!(p.writes.is_empty());
    assert_eq!(p.status.phase, Some(RolloutPhase::Failed));
    assert!(p.status.message.as_deref().unwrap().contains("not found"));
    let c = lekiwi_crds::condition::find(&p.status.conditions, CONDITION_RELEASE_VALID).unwrap();
    assert_eq!(c.status, ConditionStatus::False);

    let mut facts = sim.facts();
    facts.overlaps = vec![Overlap {
        deployment: "older".into(),
        earlier: true,
        robots: vec!["kiwi-00".into()],
    }];
    let p = plan(&sim.d, &facts);
    assert!(p.writes.is_empty());
    let c = lekiwi_crds::condition::find(&p.status.conditions, CONDITION_CONFLICT).unwrap();
    assert_eq!(c.status, ConditionStatus::True);
    assert!(c.message.contains("older"));
}

#[test]
fn robots_held_by_another_deployment_are_not_touched() {
    let mut sim = Sim::new(deployment(IntOrString::Int(5), 0), 3);
    sim.robots[0].mark = Some(Mark {
        deployment: "other".into(),
        rollout_id: "x".into(),
        batch: 0,
        state: MarkState::Started,
        since: sim.now,
        previous: None,
        message: None,
        failed: false,
    });
    let mut facts = sim.facts();
    facts.active_deployments.push("other".into());
    let p = plan(&sim.d, &facts);
    assert!(p.writes.iter().all(|w| w.robot != "kiwi-00"));
    assert_eq!(p.writes.len(), 2);
}

#[test]
fn undo_rolls_back_a_completed_rollout_and_new_robots_join_a_completed_one() {
    let mut sim = Sim::new(deployment(IntOrString::Int(5), 0), 3);
    sim.run_until_done(10);
    sim.robots.push(robot(7));
    sim.agents();
    sim.advance(1);
    let p = sim.step();
    assert_eq!(p.writes.len(), 1, "the new robot is updated");
    sim.run_until_done(10);
    assert_eq!(sim.d.status.as_ref().unwrap().updated, 4);

    sim.advance(5);
    let at = sim.now.to_string();
    sim.d
        .metadata
        .annotations
        .get_or_insert_default()
        .insert(UNDO_ANNOTATION.into(), at);
    sim.advance(1);
    sim.run_until_done(10);
    assert_eq!(sim.phase(), RolloutPhase::RolledBack);
    assert!(sim.robots.iter().all(|r| r.current == Some(rel("1"))));
}

#[test]
fn an_undo_in_the_second_a_new_rollout_starts_is_of_the_old_rollout() {
    let mut sim = Sim::new(deployment(IntOrString::Int(5), 0), 3);
    sim.run_until_done(10);
    assert_eq!(sim.phase(), RolloutPhase::Completed);
    // An undo at .2 s rolls 2 back; a new release at .5 s of the same second (the status
    // keeps whole seconds) is a new rollout the undo is older than.
    sim.now += SignedDuration::from_millis(200);
    let at = sim.now.to_string();
    sim.d
        .metadata
        .annotations
        .get_or_insert_default()
        .insert(UNDO_ANNOTATION.into(), at);
    for _ in 0..10 {
        sim.step();
        if sim.phase() == RolloutPhase::RolledBack {
            break;
        }
        sim.agents();
    }
    assert_eq!(sim.phase(), RolloutPhase::RolledBack);
    sim.now += SignedDuration::from_millis(300);
    sim.d.spec.release = Some(rel("3"));
    let p = sim.step();
    assert_ne!(p.status.phase, Some(RolloutPhase::RollingBack), "{p:#?}");
    sim.run_until_done(10);
    assert_eq!(sim.phase(), RolloutPhase::Completed);
    assert!(sim.robots.iter().all(|r| r.current == Some(rel("3"))));
}

#[test]
fn rolling_a_release_out_again_ignores_the_marks_of_its_earlier_rollout() {
    let mut sim = Sim::new(deployment(IntOrString::Int(4), 0), 4);
    // 2 fails on one robot of four: rolled back; the robots keep marks of that rollout.
    sim.failing = vec!["kiwi-01".into()];
    sim.run_until_done(10);
    assert_eq!(sim.phase(), RolloutPhase::RolledBack);
    // Back to 1, which every robot runs: done at once, no robot written.
    sim.d.spec.release = Some(rel("1"));
    sim.advance(1);
    sim.run_until_done(10);
    assert_eq!(sim.phase(), RolloutPhase::Completed);
    // 2 again, now healthy: a new rollout that updates everyone.
    sim.failing.clear();
    sim.d.spec.release = Some(rel("2"));
    sim.advance(1);
    sim.run_until_done(10);
    assert_eq!(sim.phase(), RolloutPhase::Completed);
    assert!(sim.robots.iter().all(|r| r.current == Some(rel("2"))));
    assert_eq!(sim.d.status.as_ref().unwrap().updated, 4);
}

/// 2 rolled out to four robots and rolling back (kiwi-01 fails its health check), kiwi-02 taken
/// over by a teleoperator before it applied the rollback (agents do not act while teleoperated).
fn rolling_back_without_kiwi_02() -> Sim {
    let mut sim = Sim::new(deployment(IntOrString::Int(4), 0), 4);
    sim.failing = vec!["kiwi-01".into()];
    sim.step();
    sim.agents();
    sim.advance(1);
    sim.step();
    assert_eq!(sim.phase(), RolloutPhase::RollingBack);
    sim.robots[2].teleoperated = true;
    sim
}

/// [`rolling_back_without_kiwi_02`] to its end: RolledBack on kiwi-02's timeout while it still
/// runs 2, its `spec.release` back on 1; then 3 asked for.
fn rolled_back_without_kiwi_02() -> Sim {
    let mut sim = rolling_back_without_kiwi_02();
    sim.run_until_done(120);
    assert_eq!(sim.phase(), RolloutPhase::RolledBack);
    let message = sim.d.status.as_ref().unwrap().message.clone().unwrap();
    assert!(
        message.starts_with(
            "1 updated robot(s) did not run their previous release within 60s of being told to \
             switch back (first: kiwi-02)"
        ),
        "{message}"
    );
    let kiwi_02 = &sim.robots[2];
    assert_eq!(
        (&kiwi_02.current, &kiwi_02.desired),
        (&Some(rel("2")), &Some(rel("1")))
    );
    sim.failing.clear();
    sim.d.spec.release = Some(rel("3"));
    sim.advance(1);
    sim
}

/// A rollback gives a robot up (the rollout ends RolledBack without it) only on a fresh view:
/// past its timeout on a store not read fresh, it is waited for.
#[test]
fn a_rollback_gives_a_robot_up_only_on_a_fresh_view() {
    let mut sim = rolling_back_without_kiwi_02();
    sim.agents();
    sim.advance(61);
    sim.robots[2].unconfirmed = true;
    let plan = sim.step();
    assert_eq!(sim.phase(), RolloutPhase::RollingBack);
    assert_eq!(plan.requeue_after, Some(std::time::Duration::from_secs(1)));
    sim.robots[2].unconfirmed = false;
    sim.step();
    assert_eq!(sim.phase(), RolloutPhase::RolledBack);
}

#[test]
fn a_robot_still_rolling_back_is_started_with_the_release_it_returns_to_as_previous() {
    let mut sim = rolled_back_without_kiwi_02();
    // Free, but its rollback not yet done (or not yet seen): it still runs the release left.
    sim.robots[2].teleoperated = false;
    let plan = sim.step();
    let kiwi_02 = plan.writes.iter().find(|w| w.robot == "kiwi-02").unwrap();
    assert_eq!(kiwi_02.mark.state, MarkState::Started);
    assert_eq!(kiwi_02.mark.previous, Some(rel("1")), "not 2, rolled back");
    assert_eq!(plan.writes.len(), 4);
    assert!(
        plan.writes
            .iter()
            .all(|w| w.mark.previous == Some(rel("1")))
    );
}

#[test]
fn a_robot_waited_for_while_rolling_back_keeps_the_release_it_returns_to_as_previous() {
    let mut sim = rolled_back_without_kiwi_02();
    let plan = sim.step();
    let kiwi_02 = plan.writes.iter().find(|w| w.robot == "kiwi-02").unwrap();
    assert_eq!(kiwi_02.mark.state, MarkState::Waiting);
    assert_eq!(kiwi_02.mark.previous, Some(rel("1")));
    // Free again, still on 2: started from its wait with 1 to return to.
    sim.robots[2].teleoperated = false;
    sim.advance(1);
    let plan = sim.step();
    let kiwi_02 = plan.writes.iter().find(|w| w.robot == "kiwi-02").unwrap();
    assert_eq!(kiwi_02.mark.state, MarkState::Started);
    assert_eq!(kiwi_02.mark.previous, Some(rel("1")), "not 2, rolled back");
    // Its spec no longer asks for 1 (written by hand meanwhile): what it runs is recorded.
    let mut sim = rolled_back_without_kiwi_02();
    sim.robots[2].current = Some(rel("5"));
    sim.robots[2].desired = Some(rel("5"));
    sim.robots[2].teleoperated = false;
    let plan = sim.step();
    let kiwi_02 = plan.writes.iter().find(|w| w.robot == "kiwi-02").unwrap();
    assert_eq!(
        kiwi_02.mark.previous,
        Some(rel("5")),
        "it runs what it was told"
    );
}

#[test]
fn a_robot_that_vanishes_mid_update_leaves_a_consistent_rollout() {
    let mut sim = Sim::new(deployment(IntOrString::Int(3), 0), 9);
    let first = sim.step();
    assert_eq!(first.writes.len(), 3);
    // kiwi-01, told to switch, is deleted (or loses its label) before it reports; its batch
    // is judged on the robots that remain, and no later robot is pulled forward into batch 0.
    sim.robots.retain(|r| r.name != "kiwi-01");
    sim.agents();
    sim.advance(1);
    let plan = sim.step();
    let st = sim.d.status.clone().unwrap();
    assert_eq!(st.targeted, 8);
    assert!(
        plan.writes.iter().all(|w| w.mark.batch != 0),
        "nobody joins a formed batch: {:?}",
        plan.writes
    );
    sim.run_until_done(50);
    let st = sim.d.status.clone().unwrap();
    assert_eq!(st.phase, Some(RolloutPhase::Completed), "{:?}", st.message);
    assert_eq!((st.updated, st.failed, st.targeted), (8, 0, 8));
    assert!(sim.robots.iter().all(|r| r.current == Some(rel("2"))));
    // Batch membership never changed for the robots that stayed.
    let marks: Vec<(String, i32)> = sim
        .robots
        .iter()
        .map(|r| (r.name.clone(), r.mark.as_ref().unwrap().batch))
        .collect();
    assert_eq!(marks[..2], [("kiwi-00".into(), 0), ("kiwi-02".into(), 0)]);
    assert!(marks[2..5].iter().all(|(_, b)| *b == 1), "{marks:?}");
}

#[test]
fn a_rollback_the_marks_record_goes_on_under_an_older_status() {
    let mut sim = Sim::new(deployment(IntOrString::Int(10), 0), 30);
    sim.failing = vec!["kiwi-10".into(), "kiwi-13".into(), "kiwi-17".into()];
    // Run until the plan that decides the rollback; keep the status from before it, as a
    // controller that stopped between its robot writes and its status write would leave it.
    let before = loop {
        let before = sim.d.status.clone();
        sim.step();
        if sim.phase() == RolloutPhase::RollingBack {
            break before;
        }
        sim.agents();
        sim.advance(1);
    };
    sim.d.status = before;
    assert_ne!(sim.phase(), RolloutPhase::RollingBack);
    let plan = sim.step();
    assert_eq!(sim.phase(), RolloutPhase::RollingBack, "{:?}", plan.status);
    assert!(
        plan.writes.iter().all(|w| w.release != Some(rel("2"))),
        "no robot is started: {:?}",
        plan.writes
    );
    sim.run_until_done(50);
    assert_eq!(sim.phase(), RolloutPhase::RolledBack);
    assert!(
        sim.robots
            .iter()
            .all(|r| r.desired.as_ref().is_none_or(|d| *d == rel("1"))),
        "every robot's spec is back on 1"
    );
    assert!(sim.robots.iter().all(|r| r.current == Some(rel("1"))));
}

/// A robot that runs the release healthy but whose switch no gateway saw (so no analysis
/// window) fails at the timeout with that reason, not as "unhealthy".
#[test]
fn a_switch_without_an_analysis_window_times_out_naming_it() {
    let mut d = deployment(IntOrString::Int(1), 0);
    d.spec.analysis = Some(lekiwi_crds::analysis::AnalysisSpec {
        window_seconds: 30,
        ..lekiwi_crds::analysis::AnalysisSpec::default()
    });
    let mut sim = Sim::new(d, 1);
    sim.step();
    sim.agents();
    sim.advance(61);
    sim.step();
    let st = sim.d.status.as_ref().unwrap();
    let why = st.robots[0].message.as_deref().unwrap_or_default();
    assert!(
        why.contains("runs 2 healthy, but no analysis window of its switch"),
        "{st:?}"
    );
}

impl Sim {
    /// Sets `annotation` to the current time, as `kubectl lekiwi rollout undo|abort|restart` do.
    fn stamp(&mut self, annotation: &str) {
        let at = self.now.to_string();
        self.d
            .metadata
            .annotations
            .get_or_insert_default()
            .insert(annotation.into(), at);
    }

    fn running(&self, release: &str) -> Vec<&str> {
        self.robots
            .iter()
            .filter(|r| r.current == Some(rel(release)))
            .map(|r| r.name.as_str())
            .collect()
    }
}

/// Batch 0 (kiwi-00, 01) done; batch 1 started: kiwi-02 switched, kiwi-03 still downloading.
fn aborted_mid_batch() -> Sim {
    let mut sim = Sim::new(deployment(IntOrString::Int(2), 0), 6);
    sim.step();
    sim.agents();
    sim.advance(1);
    let p = sim.step();
    let started: Vec<_> = p.writes.iter().map(|w| w.robot.as_str()).collect();
    assert_eq!(started, ["kiwi-02", "kiwi-03"], "{:?}", sim.d.status);
    sim.robots[2].current = Some(rel("2"));
    sim.advance(1);
    sim.stamp(ABORT_ANNOTATION);
    sim.advance(1);
    sim
}

#[test]
fn an_abort_keeps_switched_robots_cancels_downloads_and_starts_nobody() {
    let mut sim = aborted_mid_batch();
    let p = sim.step();
    let writes: Vec<_> = p
        .writes
        .iter()
        .map(|w| (w.robot.as_str(), w.mark.state, w.release.clone()))
        .collect();
    assert_eq!(
        writes,
        [("kiwi-03", MarkState::Skipped, Some(rel("1")))],
        "only the robot not yet switched is told to stay, which cancels its download"
    );
    assert!(p.finished);
    assert_eq!(p.status.phase, Some(RolloutPhase::Aborted));
    assert!(sim.events.contains(&"RolloutAborted"), "{:?}", sim.events);
    let progressing = p
        .status
        .conditions
        .iter()
        .find(|c| c.r#type == "Progressing");
    assert_eq!(
        progressing.map(|c| (c.status, c.reason.as_str())),
        Some((ConditionStatus::False, "Aborted"))
    );
    for _ in 0..5 {
        sim.agents();
        sim.advance(100);
        let p = sim.step();
        assert!(p.writes.is_empty(), "nothing starts after an abort: {p:?}");
        assert_eq!(sim.phase(), RolloutPhase::Aborted);
    }
    assert_eq!(sim.running("2"), ["kiwi-00", "kiwi-01", "kiwi-02"]);
    assert_eq!(sim.running("1"), ["kiwi-03", "kiwi-04", "kiwi-05"]);
    let st = sim.d.status.as_ref().unwrap();
    assert_eq!((st.updated, st.pending), (3, 2), "{st:?}");

    // A restart goes on from where the abort stopped.
    sim.stamp(RESTART_ANNOTATION);
    sim.advance(1);
    sim.run_until_done(20);
    assert_eq!(sim.phase(), RolloutPhase::Completed);
    assert_eq!(sim.running("2").len(), 6);
}

#[test]
fn an_undo_after_an_abort_rolls_the_switched_robots_back() {
    let mut sim = aborted_mid_batch();
    sim.step();
    sim.agents();
    sim.advance(5);
    sim.stamp(UNDO_ANNOTATION);
    sim.advance(1);
    sim.run_until_done(10);
    assert_eq!(sim.phase(), RolloutPhase::RolledBack);
    assert_eq!(sim.running("1").len(), 6);
}

#[test]
fn an_abort_of_a_finished_or_earlier_rollout_changes_nothing() {
    let mut sim = Sim::new(deployment(IntOrString::Int(5), 0), 3);
    sim.run_until_done(10);
    sim.advance(1);
    sim.stamp(ABORT_ANNOTATION);
    sim.advance(1);
    let p = sim.step();
    assert!(p.writes.is_empty() && p.events.is_empty(), "{p:?}");
    assert_eq!(sim.phase(), RolloutPhase::Completed);
    // The next release is a new rollout the abort is older than.
    sim.advance(1);
    sim.d.spec.release = Some(rel("3"));
    sim.run_until_done(10);
    assert_eq!(sim.phase(), RolloutPhase::Completed);
    assert_eq!(sim.running("3").len(), 3);
}

/// With no pause between batches, the plan that closes a batch opens the next: a batch costs
/// one status write and one reconcile. With a pause, the next batch waits for it.
#[test]
fn a_batch_that_succeeds_opens_the_next_in_the_same_plan_unless_a_pause_is_asked() {
    let mut sim = Sim::new(deployment(IntOrString::Int(2), 0), 6);
    sim.step();
    sim.agents();
    sim.advance(1);
    let p = sim.step();
    let started: Vec<_> = p.writes.iter().map(|w| w.robot.as_str()).collect();
    assert_eq!(started, ["kiwi-02", "kiwi-03"]);
    assert_eq!(p.batch_result.map(|(b, _)| b), Some(0));
    assert_eq!(p.status.current_batch, Some(1));
    let reasons: Vec<_> = p.events.iter().map(|e| e.reason).collect();
    assert_eq!(reasons, ["BatchSucceeded", "BatchStarted"]);
    // Every batch is one plan: 3 batches, 3 plans to the last one's success, which completes.
    sim.agents();
    sim.advance(1);
    sim.step();
    sim.agents();
    sim.advance(1);
    assert!(sim.step().finished);
    assert_eq!(sim.phase(), RolloutPhase::Completed);

    let mut paced = deployment(IntOrString::Int(2), 0);
    paced.spec.strategy.pause_between_batches_seconds = 30;
    let mut sim = Sim::new(paced, 6);
    sim.step();
    sim.agents();
    sim.advance(1);
    let p = sim.step();
    assert!(p.writes.is_empty(), "{p:?}");
    assert_eq!(
        p.status.message.as_deref(),
        Some("batch 0 succeeded; next batch after the pause")
    );
}

/// A status older than the robots' marks (a leader that stopped after writing robots, before
/// its status write) does not open a batch twice: the batch the marks show started is resolved.
#[test]
fn a_status_older_than_the_marks_does_not_open_the_next_batch_twice() {
    let mut sim = Sim::new(deployment(IntOrString::Int(2), 0), 6);
    sim.step();
    sim.agents();
    sim.advance(1);
    let before = sim.d.status.clone();
    let p = sim.step();
    let started: Vec<_> = p.writes.iter().map(|w| w.robot.as_str()).collect();
    assert_eq!(started, ["kiwi-02", "kiwi-03"]);
    // The status write is lost; the marks of kiwi-02 and kiwi-03 are not.
    sim.d.status = before;
    sim.advance(1);
    let p = sim.step();
    assert!(p.writes.is_empty(), "nobody else starts: {:?}", p.writes);
    sim.agents();
    sim.advance(1);
    sim.run_until_done(10);
    assert_eq!(sim.phase(), RolloutPhase::Completed);
    assert_eq!(sim.running("2").len(), 6);
}

/// The canary of a one-robot-canary rollout started at 10:00:00.400, whose agent then reports
/// `phase` with `message` for the target release, received by its gateway at `at`: the status a
/// second later, and the canary's row in it.
fn canary_reported(
    at: &str,
    phase: &str,
    message: &str,
) -> (
    lekiwi_crds::RobotDeploymentStatus,
    lekiwi_crds::deployment::RobotResult,
) {
    let mut sim = Sim::new(deployment(IntOrString::Int(1), 1), 2);
    sim.now = "2026-11-22T10:00:00.400Z".parse().unwrap();
    let first = sim.step();
    assert_eq!(first.writes.len(), 1, "the canary starts");
    let canary = first.writes[0].robot.clone();
    let r = sim.robots.iter_mut().find(|r| r.name == canary).unwrap();
    let at: Timestamp = at.parse().unwrap();
    r.last_update = Some((rel("2"), phase.into(), Some(message.into()), Some(at)));
    sim.advance(1);
    sim.step();
    let st = sim.d.status.clone().unwrap();
    let row = st
        .robots
        .iter()
        .find(|r| r.robot == canary)
        .unwrap()
        .clone();
    (st, row)
}

/// A failure the agent reports in the second its robot was started, after the start, fails
/// the robot at once, not after its timeout (a canary in the soak, refused a release its
/// gateway did not know yet, held a rollout 180 s when such reports were compared by the
/// whole second).
#[test]
fn a_failure_reported_in_the_second_of_the_start_fails_the_robot_at_once() {
    // As the gateway writes it: to the microsecond, 50 ms after the start.
    let (st, result) = canary_reported(
        "2026-11-22T10:00:00.450Z",
        "failed",
        "release unknown to the gateway",
    );
    // Its batch rolls back (the robot never left its release, so it is back on it at once).
    assert_eq!(st.phase, Some(RolloutPhase::RollingBack), "{st:#?}");
    assert_eq!(result.state, RobotRolloutState::RolledBack, "{st:#?}");
    assert!(
        result
            .message
            .as_deref()
            .is_some_and(|m| m.contains("the agent reported failed")),
        "{st:#?}"
    );
}

/// A pause cancels the canary's update and a resume starts it again within one second; the
/// agent's report of the cancelled update came 50 ms before the new start. It is the old
/// update's outcome, not the new one's failure.
#[test]
fn an_outcome_reported_just_before_the_start_in_the_same_second_is_not_this_starts() {
    let (st, result) = canary_reported(
        "2026-11-22T10:00:00.350Z",
        "rolled_back",
        "health check of 2 failed: cancelled by the gateway",
    );
    assert_eq!(st.phase, Some(RolloutPhase::Progressing), "{st:#?}");
    assert_eq!(result.state, RobotRolloutState::Updating, "{st:#?}");
}

/// A batch whose robots all fail at once plans at most `EVENTS_PER_REASON` RobotUpdateFailed
/// Events and one that counts the rest: each Event is an API request the reconcile makes before
/// the rollout goes on, and the hour at 10,000 robots saw a batch of 990 timed-out robots hold
/// its deployment for minutes while their Events went out one by one.
#[test]
fn a_batch_failing_at_once_plans_a_bounded_number_of_events() {
    let mut sim = Sim::new(deployment(IntOrString::Int(60), 0), 60);
    sim.failing = (0..60).map(|i| robot(i).name).collect();
    let mut most = 0;
    let mut summaries = Vec::new();
    for _ in 0..20 {
        let plan = sim.step();
        let failed: Vec<_> = plan
            .events
            .iter()
            .filter(|e| e.reason == "RobotUpdateFailed")
            .collect();
        most = most.max(failed.len());
        summaries.extend(
            failed
                .iter()
                .filter(|e| e.note.starts_with("and "))
                .map(|e| e.note.clone()),
        );
        sim.agents();
        sim.now += SignedDuration::from_secs(5);
    }
    let st = sim.d.status.clone().unwrap();
    assert_eq!(
        st.failed, 60,
        "every failure is still counted: {:?}",
        st.message
    );
    assert_eq!(
        most,
        super::draft::EVENTS_PER_REASON + 1,
        "ten Events and a summary"
    );
    assert_eq!(
        summaries,
        vec![
            "and 50 more RobotUpdateFailed in this step, left out of Events: the \
             RobotDeployment's status and each Robot's rollout mark say which robots"
                .to_owned()
        ]
    );
}
