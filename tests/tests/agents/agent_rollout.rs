//! Agent rollouts (issue 19): a RobotDeployment with `spec.agent` moves ten real `lekiwi-agent`
//! processes (under the supervisor that plays systemd's part) from agent A to B in a canary and
//! two batches; then a build that exits at start (C) and one that never connects (D) each cost
//! the canary robot alone: it falls back to B by itself, the batch fails, the rollout is
//! `RolledBack` with the reason, and no other robot restarted.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
use k8s_openapi::apimachinery::pkg::util::intstr::IntOrString;
use kube::Api;
use kube::api::{Patch, PatchParams, PostParams};
use lekiwi_core::RobotKey;
use lekiwi_crds::deployment::{AGENT_MARK_ANNOTATION, RolloutPhase, RolloutStrategy};
use lekiwi_crds::{AgentArch, AgentBuild, AgentRef, Robot, RobotDeployment, RobotDeploymentSpec};
use lekiwi_tests::agent_fleet::{AgentFleet, DEADLINE_S, T, agent_fleet, arch, wrapper};
use lekiwi_tests::supervisor::Supervised;
use lekiwi_tests::{bin, wait_for, wait_online};
use serde_json::{Value, json};

const DEPLOYMENT: &str = "agents";

fn agent(version: &str, digest: &str) -> AgentRef {
    AgentRef {
        version: version.to_owned(),
        builds: vec![AgentBuild {
            arch: AgentArch::of_machine(arch()).unwrap(),
            digest: digest.to_owned(),
        }],
    }
}

/// The deployment's status once `done` says it is, or the last status in the error.
async fn wait_rollout(
    api: &Api<RobotDeployment>,
    what: &str,
    timeout: Duration,
    done: impl Fn(&lekiwi_crds::RobotDeploymentStatus) -> bool,
) -> anyhow::Result<lekiwi_crds::RobotDeploymentStatus> {
    let got = wait_for(what, timeout, || async {
        let status = api.get(DEPLOYMENT).await.ok()?.status?;
        done(&status).then_some(status)
    })
    .await;
    match got {
        Ok(s) => Ok(s),
        Err(e) => {
            let last = api.get(DEPLOYMENT).await.ok().and_then(|d| d.status);
            anyhow::bail!("{e}; last status: {last:#?}")
        }
    }
}

/// Each robot's agent rollout mark (batch and state) and its `spec.agent.version`.
async fn marks(f: &AgentFleet) -> anyhow::Result<BTreeMap<String, (Value, Option<String>)>> {
    let robots = Api::<Robot>::namespaced(f.client.clone(), &f.ns)
        .list(&Default::default())
        .await?;
    Ok(robots
        .items
        .into_iter()
        .map(|r| {
            let mark = r
                .metadata
                .annotations
                .as_ref()
                .and_then(|a| a.get(AGENT_MARK_ANNOTATION))
                .and_then(|m| serde_json::from_str(m).ok())
                .unwrap_or(Value::Null);
            let name = r.metadata.name.clone().unwrap_or_default();
            (name, (mark, r.spec.agent.map(|a| a.version)))
        })
        .collect())
}

/// Points the deployment at agent `version` and waits until the new rollout ends; its status
/// and how long that took.
async fn retarget(
    api: &Api<RobotDeployment>,
    version: &str,
    digest: &str,
) -> anyhow::Result<(lekiwi_crds::RobotDeploymentStatus, Duration)> {
    let t0 = Instant::now();
    let patched = api
        .patch(
            DEPLOYMENT,
            &PatchParams::default(),
            &Patch::Merge(json!({"spec": {"agent": agent(version, digest)}})),
        )
        .await?;
    let generation = patched.metadata.generation;
    let status = wait_rollout(
        api,
        &format!("the rollout of {version} ended"),
        2 * T + Duration::from_secs(DEADLINE_S),
        |s| {
            s.observed_generation >= generation
                && matches!(
                    s.phase,
                    Some(RolloutPhase::RolledBack | RolloutPhase::Completed | RolloutPhase::Failed)
                )
        },
    )
    .await?;
    Ok((status, t0.elapsed()))
}

fn starts(r: &Supervised) -> usize {
    r.history.lock().unwrap().starts.len()
}

#[tokio::test]
async fn a_deployment_moves_agents_in_batches_and_a_broken_build_costs_only_the_canary()
-> anyhow::Result<()> {
    let f = agent_fleet("agentroll", "agro").await?;
    let names: Vec<String> = (0..10).map(|i| format!("kiwi-{i}")).collect();
    let robots: Vec<Supervised> = names.iter().map(|n| f.robot(n)).collect();
    wait_online(&f.client, &f.ns, names.len(), 2 * T).await?;
    let b = f.push("agent-b", "9.0.0-b", &wrapper("9.0.0-b", false))?;
    let api: Api<RobotDeployment> = Api::namespaced(f.client.clone(), &f.ns);

    // A -> B: canary 1, then batches of 5 and 4.
    let mut d = RobotDeployment::new(
        DEPLOYMENT,
        RobotDeploymentSpec {
            selector: LabelSelector::default(),
            release: None,
            agent: Some(agent("9.0.0-b", &b)),
            strategy: RolloutStrategy {
                canary: 1,
                batch_size: IntOrString::Int(5),
                success_threshold: 1.0,
                robot_timeout_seconds: 90,
                ..RolloutStrategy::default()
            },
            paused: false,
            analysis: None,
            priority: 0,
        },
    );
    d.metadata.namespace = Some(f.ns.clone());
    let t0 = Instant::now();
    api.create(&PostParams::default(), &d).await?;
    let status = wait_rollout(&api, "A -> B Completed", 3 * T, |s| {
        matches!(
            s.phase,
            Some(RolloutPhase::Completed | RolloutPhase::RolledBack | RolloutPhase::Failed)
        )
    })
    .await?;
    let took = t0.elapsed();
    assert_eq!(status.phase, Some(RolloutPhase::Completed), "{status:#?}");
    assert_eq!(
        (status.updated, status.failed, status.targeted),
        (10, 0, 10),
        "{status:#?}"
    );
    assert_eq!(status.total_batches, Some(3));
    let marks_b = marks(&f).await?;
    let mut per_batch = BTreeMap::<i64, usize>::new();
    for name in &names {
        let (version, _) = f.agent_status(name).await.unwrap_or_default();
        assert_eq!(version, "9.0.0-b", "{name} runs B");
        let (mark, desired) = &marks_b[name];
        assert_eq!(desired.as_deref(), Some("9.0.0-b"), "{name}: spec.agent");
        *per_batch
            .entry(mark["batch"].as_i64().unwrap_or(-1))
            .or_default() += 1;
    }
    assert_eq!(
        per_batch,
        BTreeMap::from([(0, 1), (1, 5), (2, 4)]),
        "canary, 5, 4"
    );
    eprintln!("A -> B: ten robots in a canary and two batches in {took:?}");

    // B -> C (exits at start) and then B -> D (never connects): the canary falls back by
    // itself, the batch is below the threshold, the rollout rolls back; no other robot moves.
    let c = f.push(
        "agent-c",
        "9.0.0-c",
        "#!/bin/sh\necho 'agent C: exits at start' >&2\nexit 1\n",
    )?;
    let dd = f.push("agent-d", "9.0.0-d", &wrapper("9.0.0-d", true))?;
    for (version, digest, why) in [
        ("9.0.0-c", &c, "crash at start"),
        ("9.0.0-d", &dd, "no connection"),
    ] {
        let before: Vec<usize> = robots.iter().map(starts).collect();
        let (status, took) = retarget(&api, version, digest).await?;
        assert_eq!(
            status.phase,
            Some(RolloutPhase::RolledBack),
            "{version}: {status:#?}"
        );
        let rolled_back = status
            .conditions
            .iter()
            .find(|c| c.r#type == "RolledBack")
            .map(|c| c.message.clone())
            .unwrap_or_default();
        assert!(
            rolled_back.contains("kiwi-0") && rolled_back.contains(why),
            "{version}: the reason names the canary and why: {rolled_back:?}"
        );
        let (back_on, update) = f.agent_status("kiwi-0").await.unwrap_or_default();
        assert_eq!(back_on, "9.0.0-b", "{version}: the canary is back on B");
        assert_eq!(update["phase"], "FallenBack", "{update}");
        let now_marks = marks(&f).await?;
        for (i, name) in names.iter().enumerate() {
            let (_, desired) = &now_marks[name];
            assert_eq!(
                desired.as_deref(),
                Some("9.0.0-b"),
                "{version}: {name}'s spec.agent"
            );
            if i > 0 {
                assert_eq!(
                    starts(&robots[i]),
                    before[i],
                    "{version}: {name} never restarted"
                );
                assert_eq!(
                    now_marks[name].0, marks_b[name].0,
                    "{version}: {name} untouched"
                );
            }
        }
        eprintln!("B -> {version}: rolled back after {took:?} ({rolled_back})");
    }
    // The plugin reports an agent rollout as users watch it.
    let out = std::process::Command::new(bin("kubectl-lekiwi"))
        .arg("--kubeconfig")
        .arg(f.cp.kubeconfig())
        .args([
            "-n",
            &f.ns,
            "rollout",
            "status",
            DEPLOYMENT,
            "--watch=false",
        ])
        .env_remove("LEKIWI_SERVER")
        .output()?;
    let report = String::from_utf8_lossy(&out.stdout);
    assert!(
        report.contains(&format!(
            "robotdeployment/{DEPLOYMENT}: agent 9.0.0-d → {} {dd}",
            arch()
        )) && report.contains("RolledBack")
            && report.contains("kiwi-0"),
        "{report}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(
        f.op.metric(r#"lekiwi_gateway_agent_updates_total{kind="fallen_back",version="9.0.0-c"}"#)
            .await,
        Some(1.0)
    );
    one_failure_in_a_batch_returns_the_updated_robots(&f, &api, &robots).await
}

/// B -> E, a build that exits at start on kiwi-3 only: the canary (kiwi-0) and four robots of
/// batch 1 run E, kiwi-3 falls back, 4 of 5 is below the threshold: every robot on E returns to
/// B from its own disk (nothing downloaded), batch 2 is never started.
async fn one_failure_in_a_batch_returns_the_updated_robots(
    f: &AgentFleet,
    api: &Api<RobotDeployment>,
    robots: &[Supervised],
) -> anyhow::Result<()> {
    let script = wrapper("9.0.0-e", false).replacen(
        "\n",
        "\ncase \"$*\" in */kiwi-3\\ *) echo 'agent E: exits on kiwi-3' >&2; exit 1;; esac\n",
        1,
    );
    let e = f.push("agent-e", "9.0.0-e", &script)?;
    let before: Vec<usize> = robots.iter().map(starts).collect();
    let (status, took) = retarget(api, "9.0.0-e", &e).await?;
    assert_eq!(status.phase, Some(RolloutPhase::RolledBack), "{status:#?}");
    let now_marks = marks(f).await?;
    for (i, r) in robots.iter().enumerate() {
        let name = format!("kiwi-{i}");
        let (version, _) = f.agent_status(&name).await.unwrap_or_default();
        assert_eq!(version, "9.0.0-b", "{name} is on B again");
        if i <= 5 {
            assert!(starts(r) > before[i], "{name} switched");
            assert_eq!(now_marks[&name].1.as_deref(), Some("9.0.0-b"), "{name}");
        } else {
            assert_eq!(starts(r), before[i], "{name} (batch 2) never restarted");
            assert_ne!(
                now_marks[&name].0["rolloutId"].as_str(),
                status.rollout_id.as_deref(),
                "{name} was never started in this rollout"
            );
        }
    }
    let back = |name: &str| {
        status
            .robots
            .iter()
            .find(|r| r.robot == name)
            .map(|r| (r.state, r.previous_release.clone()))
    };
    let (state, previous) = back("kiwi-1").expect("kiwi-1 in the status");
    assert_eq!(
        state,
        lekiwi_crds::deployment::RobotRolloutState::RolledBack,
        "{status:#?}"
    );
    assert_eq!(previous.map(|p| p.version).as_deref(), Some("9.0.0-b"));
    // The return to B came from the robots' own disks.
    let store = f.op.event_store().await?;
    let key = RobotKey::new(f.ns.clone(), "kiwi-1".to_owned());
    let returned = wait_for("kiwi-1's switch back to B stored", T, || async {
        let events = store.events(&key, None, 10_000).await.ok()?;
        events
            .into_iter()
            .rev()
            .find(|e| e.kind == "agent_update_started")
            .filter(|e| e.data["version"] == "9.0.0-b" && e.data["from"] == "9.0.0-e")
    })
    .await?;
    assert_eq!(returned.data["bytes"], 0, "{:?}", returned.data);
    eprintln!(
        "B -> E: kiwi-3 fell back, the five robots on E returned to B; rolled back after {took:?}"
    );
    Ok(())
}
