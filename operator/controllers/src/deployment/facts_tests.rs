//! Unit tests of how an agent rollout sees a robot ([`super::facts`]): what it runs, its update
//! report, a missing build, and the checks of an agent deployment's spec.

use k8s_openapi::apimachinery::pkg::apis::meta::v1::{LabelSelector, MicroTime};
use lekiwi_crds::agent::AgentUpdateReport;
use lekiwi_crds::robot::SystemInfo;
use lekiwi_crds::{
    AgentArch, AgentBuild, AgentRef, ReleaseRef, Robot, RobotDeploymentSpec, RobotSpec, RobotStatus,
};

use super::facts::{agent_view, check_spec, target};
use super::plan::{ReleaseCheck, RobotView};

fn digest(c: char) -> String {
    format!("sha256:{}", c.to_string().repeat(64))
}

fn agent_b() -> AgentRef {
    AgentRef {
        version: "0.3.0".into(),
        builds: vec![AgentBuild {
            arch: AgentArch::Arm64,
            digest: digest('b'),
        }],
    }
}

fn spec(release: Option<ReleaseRef>, agent: Option<AgentRef>) -> RobotDeploymentSpec {
    RobotDeploymentSpec {
        selector: LabelSelector::default(),
        release,
        agent,
        strategy: Default::default(),
        paused: false,
        analysis: None,
        priority: 0,
    }
}

fn robot(version: &str, arch: &str, update: Option<(&str, &str)>) -> Robot {
    let mut r = Robot::new("kiwi-1", RobotSpec::default());
    r.status = Some(RobotStatus {
        agent_version: Some(version.into()),
        agent_digest: Some(digest('a').into()),
        system: Some(Box::new(SystemInfo {
            arch: Some(arch.into()),
            ..SystemInfo::default()
        })),
        agent_update: update.map(|(version, phase)| {
            Box::new(AgentUpdateReport {
                version: Some(version.into()),
                phase: Some(phase.into()),
                message: Some("crash at start".into()),
                time: Some(MicroTime("2026-11-25T10:00:00Z".parse().unwrap())),
            })
        }),
        ..RobotStatus::default()
    });
    r
}

#[test]
fn a_robot_on_another_agent_runs_its_own_version_and_digest_and_one_on_the_target_runs_it() {
    let b = agent_b();
    let t = target(&spec(None, Some(b.clone())));
    assert_eq!(t.version, "0.3.0");
    assert!(
        t.digest.starts_with("sha256:") && t.digest.len() == 71,
        "{t:?}"
    );
    let old = agent_view(
        RobotView::default(),
        &robot("0.2.0", "aarch64", None),
        &b,
        &t,
    );
    assert_eq!(
        old.current,
        Some(ReleaseRef {
            version: "0.2.0".into(),
            digest: digest('a').into()
        }),
        "the rollback target is what it runs"
    );
    assert_eq!(old.arch, Some(AgentArch::Arm64));
    assert_eq!(old.no_build, None);
    let new = agent_view(
        RobotView::default(),
        &robot("0.3.0", "aarch64", None),
        &b,
        &t,
    );
    assert_eq!(
        new.current,
        Some(t.clone()),
        "the gateway's rule: the version"
    );
    // Other builds of the same version are another rollout.
    let mut b2 = b.clone();
    b2.builds[0].digest = digest('c');
    assert_ne!(target(&spec(None, Some(b2))), t);
}

#[test]
fn update_reports_of_the_target_version_count_and_failures_are_failures() {
    let b = agent_b();
    let t = target(&spec(None, Some(b.clone())));
    for (phase, wire) in [
        ("FallenBack", "failed"),
        ("Failed", "failed"),
        ("Unsupported", "failed"),
        ("Succeeded", "done"),
        ("Sent", "switching"),
    ] {
        let r = robot("0.2.0", "aarch64", Some(("0.3.0", phase)));
        let v = agent_view(RobotView::default(), &r, &b, &t);
        let (release, got, message, _) = v.last_update.expect(phase);
        assert_eq!((release, got.as_str()), (t.clone(), wire), "{phase}");
        assert_eq!(message.as_deref(), Some("crash at start"));
    }
    // A report about another version is not this rollout's.
    let r = robot("0.2.0", "aarch64", Some(("0.2.5", "FallenBack")));
    assert_eq!(
        agent_view(RobotView::default(), &r, &b, &t).last_update,
        None
    );
}

#[test]
fn a_robot_without_a_build_for_its_architecture_is_left_out_with_the_reason() {
    let b = agent_b();
    let t = target(&spec(None, Some(b.clone())));
    let amd = agent_view(
        RobotView::default(),
        &robot("0.2.0", "x86_64", None),
        &b,
        &t,
    );
    assert_eq!(
        amd.no_build.as_deref(),
        Some("skipped: agent 0.3.0 has no amd64 build")
    );
    let riscv = agent_view(
        RobotView::default(),
        &robot("0.2.0", "riscv64", None),
        &b,
        &t,
    );
    assert!(riscv.no_build.unwrap().contains("\"riscv64\""));
    // A robot's long or odd architecture text is quoted and cut before it reaches the status.
    let odd = "\u{1b}[2J".repeat(500);
    let why = agent_view(RobotView::default(), &robot("0.2.0", &odd, None), &b, &t)
        .no_build
        .unwrap();
    assert!(why.len() < 200 && !why.contains('\u{1b}'), "{why}");
}

#[test]
fn an_agent_deployment_needs_its_builds_and_no_analysis_and_exactly_one_target() {
    let dir = tempfile::tempdir().unwrap();
    let b = agent_b();
    let check = |s: &RobotDeploymentSpec| check_spec(Some(dir.path()), s);
    let ReleaseCheck::Invalid(why) = check(&spec(None, Some(b.clone()))) else {
        panic!("a missing build passed");
    };
    assert!(
        why.contains("arm64 build of agent 0.3.0") && why.contains("agent push"),
        "{why}"
    );
    std::fs::create_dir_all(dir.path().join("sha256")).unwrap();
    std::fs::write(dir.path().join("sha256").join("b".repeat(64)), b"bin").unwrap();
    assert_eq!(check(&spec(None, Some(b.clone()))), ReleaseCheck::Valid);
    let mut with_analysis = spec(None, Some(b.clone()));
    with_analysis.analysis = Some(Default::default());
    assert!(matches!(check(&with_analysis), ReleaseCheck::Invalid(w) if w.contains("analysis")));
    let both = spec(Some(ReleaseRef::default()), Some(b));
    assert!(matches!(check(&both), ReleaseCheck::Invalid(w) if w.contains("exactly one")));
    assert!(matches!(check(&spec(None, None)), ReleaseCheck::Invalid(_)));
}
