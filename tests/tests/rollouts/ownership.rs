//! Who owns a robot that two RobotDeployments select, against the real API server, the real
//! operator and a fleet of real agents (`lekiwi-fleet`): the newer deployment takes the robots
//! and the older, completed one shows them `Superseded` instead of hiding that they run another
//! release; a higher `spec.priority` (validated by the schema) takes them back.

use std::path::{Path, PathBuf};
use std::time::Duration;

use k8s_openapi::api::core::v1::Event;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
use kube::Api;
use kube::api::{ListParams, Patch, PatchParams, PostParams};
use lekiwi_crds::deployment::{RobotRolloutState, RolloutPhase};
use lekiwi_crds::{ReleaseRef, Robot, RobotDeployment, RobotDeploymentSpec};
use lekiwi_tests::{
    FleetProcess, FleetSpec, OperatorSite, gateway_url, test_strategy, wait_for, wait_online,
};
use serde_json::json;

const ROBOTS: usize = 4;

struct Site {
    base: OperatorSite,
    _fleet: FleetProcess,
}

lekiwi_tests::deref_to_operator_site!(Site);

impl Site {
    async fn new(prefix: &str) -> anyhow::Result<Self> {
        let base = OperatorSite::start(prefix).await?;
        let (dir, ns, op, token_file) = (&base.dir, &base.ns, &base.op, &base.token_file);
        let fleet = FleetProcess::start(FleetSpec {
            gateway: &gateway_url(op),
            token_file,
            namespace: ns,
            robots: ROBOTS,
            state_root: &dir.path().join("robots"),
            health_command: "true",
            report_every: "2",
            rust_log: "warn",
            extra: &[],
        })?;
        wait_online(&base.client, ns, ROBOTS, Duration::from_secs(120)).await?;
        Ok(Self {
            base,
            _fleet: fleet,
        })
    }

    fn push(&self, version: &str) -> anyhow::Result<ReleaseRef> {
        let dir = release_dir(self.dir.path(), version)?;
        self.base.push(&dir, version)
    }

    fn deployments(&self) -> Api<RobotDeployment> {
        Api::namespaced(self.client.clone(), &self.ns)
    }

    async fn deploy(
        &self,
        name: &str,
        release: &ReleaseRef,
        selector: LabelSelector,
    ) -> anyhow::Result<()> {
        let d = RobotDeployment::new(
            name,
            RobotDeploymentSpec {
                selector,
                release: Some(release.clone()),
                agent: None,
                strategy: test_strategy(ROBOTS as i32, 0),
                paused: false,
                priority: 0,
                analysis: None,
            },
        );
        self.deployments()
            .create(&PostParams::default(), &d)
            .await?;
        Ok(())
    }

    /// Waits until `name` is Completed with `updated` robots and `superseded` superseded ones.
    async fn completed(
        &self,
        name: &str,
        updated: i32,
        superseded: i32,
    ) -> anyhow::Result<RobotDeployment> {
        wait_for(
            &format!("{name} Completed {updated} + {superseded} superseded"),
            Duration::from_secs(120),
            || async {
                let d = self.deployments().get(name).await.ok()?;
                let st = d.status.as_ref()?;
                (st.phase == Some(RolloutPhase::Completed)
                    && st.updated == updated
                    && st.targeted == updated
                    && st.superseded == superseded)
                    .then_some(d)
            },
        )
        .await
    }

    /// Robots' reported releases, by robot name.
    async fn releases(&self) -> anyhow::Result<Vec<(String, String)>> {
        let robots = Api::<Robot>::namespaced(self.client.clone(), &self.ns)
            .list(&ListParams::default())
            .await?;
        let mut out: Vec<(String, String)> = robots
            .items
            .into_iter()
            .map(|r| {
                let v = r.status.and_then(|s| s.current_release);
                (
                    r.metadata.name.unwrap_or_default(),
                    v.map_or("-".into(), |v| v.version.to_string()),
                )
            })
            .collect();
        out.sort();
        Ok(out)
    }

    async fn events_of(&self, deployment: &str, reason: &str) -> anyhow::Result<Vec<String>> {
        let events = Api::<Event>::namespaced(self.client.clone(), &self.ns)
            .list(&ListParams::default())
            .await?;
        Ok(events
            .items
            .into_iter()
            .filter(|e| e.involved_object.name.as_deref() == Some(deployment))
            .filter(|e| e.reason.as_deref() == Some(reason))
            .filter_map(|e| e.message)
            .collect())
    }
}

fn release_dir(root: &Path, version: &str) -> anyhow::Result<PathBuf> {
    let dir = root.join(format!("release-{version}"));
    std::fs::create_dir_all(&dir)?;
    std::fs::write(dir.join("version.txt"), version)?;
    Ok(dir)
}

fn on(robots: &[(String, String)], version: &str) -> Vec<String> {
    robots
        .iter()
        .filter(|(_, v)| v == version)
        .map(|(n, _)| n.clone())
        .collect()
}

/// `demo-fleet` (every robot, Completed) and a newer `team-b` selecting two of them with another
/// release: team-b updates its two, demo-fleet shows them `Superseded` (status, count, rows, an
/// Event) and does not take them back; a higher priority on demo-fleet does.
#[tokio::test]
async fn the_newer_deployment_owns_shared_robots_and_the_older_shows_them_superseded()
-> anyhow::Result<()> {
    let site = Site::new("owner").await?;
    let v1 = site.push("1.0.0")?;
    let v2 = site.push("2.0.0")?;
    site.deploy("demo-fleet", &v1, LabelSelector::default())
        .await?;
    site.completed("demo-fleet", ROBOTS as i32, 0).await?;

    let robots = Api::<Robot>::namespaced(site.client.clone(), &site.ns);
    for name in ["kiwi-000", "kiwi-001"] {
        robots
            .patch(
                name,
                &PatchParams::default(),
                &Patch::Merge(&json!({"metadata": {"labels": {"team": "b"}}})),
            )
            .await?;
    }
    let team_b = LabelSelector {
        match_labels: Some([("team".to_owned(), "b".to_owned())].into()),
        ..LabelSelector::default()
    };
    site.deploy("team-b", &v2, team_b).await?;
    site.completed("team-b", 2, 0).await?;
    let demo = site.completed("demo-fleet", 2, 2).await?;
    let st = demo.status.unwrap();
    assert_eq!(st.progress.as_deref(), Some("2/2"));
    let superseded: Vec<(&str, Option<&str>)> = st
        .robots
        .iter()
        .filter(|r| r.state == RobotRolloutState::Superseded)
        .map(|r| (r.robot.as_str(), r.message.as_deref()))
        .collect();
    assert_eq!(
        superseded,
        [
            ("kiwi-000", Some("owned by deployment team-b")),
            ("kiwi-001", Some("owned by deployment team-b"))
        ]
    );
    let events = wait_for(
        "the RobotsSuperseded Event",
        Duration::from_secs(30),
        || async {
            let e = site
                .events_of("demo-fleet", "RobotsSuperseded")
                .await
                .ok()?;
            (!e.is_empty()).then_some(e)
        },
    )
    .await?;
    assert!(
        events[0].contains("team-b (kiwi-000, kiwi-001)"),
        "{events:?}"
    );
    // demo-fleet re-plans on its own change too and still leaves them alone.
    site.deployments()
        .patch(
            "demo-fleet",
            &PatchParams::default(),
            &Patch::Merge(&json!({"metadata": {"labels": {"touched": "yes"}}})),
        )
        .await?;
    tokio::time::sleep(Duration::from_secs(3)).await;
    let by = site.releases().await?;
    assert_eq!(on(&by, "2.0.0"), ["kiwi-000", "kiwi-001"], "{by:?}");
    assert_eq!(on(&by, "1.0.0"), ["kiwi-002", "kiwi-003"], "{by:?}");

    // The schema bounds the priority; a higher one takes the robots back.
    let refused = site
        .deployments()
        .patch(
            "demo-fleet",
            &PatchParams::default(),
            &Patch::Merge(&json!({"spec": {"priority": 5000}})),
        )
        .await;
    assert!(refused.is_err(), "priority 5000 accepted");
    site.deployments()
        .patch(
            "demo-fleet",
            &PatchParams::default(),
            &Patch::Merge(&json!({"spec": {"priority": 10}})),
        )
        .await?;
    site.completed("demo-fleet", ROBOTS as i32, 0).await?;
    site.completed("team-b", 0, 2).await?;
    wait_for("every robot on 1.0.0", Duration::from_secs(60), || async {
        let by = site.releases().await.ok()?;
        (on(&by, "1.0.0").len() == ROBOTS).then_some(())
    })
    .await?;
    Ok(())
}
