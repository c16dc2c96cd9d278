//! Releases have a lifecycle: a real operator (controller + gateway) with a short garbage
//! collection period and a retention of 3, real agents (`lekiwi-fleet`) and the real CLI. Twelve
//! releases pushed, three rolled out, one rolled back automatically: collection keeps exactly
//! the releases something references plus the newest three, a file shared by two releases stays
//! while either does, `release delete` is refused while a release is used, and a download in
//! progress keeps its release.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
use kube::Api;
use kube::api::{ListParams, Patch, PatchParams, PostParams};
use lekiwi_crds::deployment::RolloutPhase;
use lekiwi_crds::{ReleaseRef, Robot, RobotDeployment, RobotDeploymentSpec};
use lekiwi_tests::{
    FleetProcess, FleetSpec, OperatorSite, bin, connect_agent, gateway_url, rollout_finished,
    set_release, test_strategy, wait_for, wait_online,
};
use serde_json::{Value, json};
use sha2::{Digest, Sha256};

const HEALTH: &str = r#"test ! -e "$LEKIWI_RELEASE_DIR/../../fail-health""#;
const RETENTION: usize = 3;

fn cli(site: &OperatorSite, args: &[&str]) -> anyhow::Result<std::process::Output> {
    Ok(Command::new(bin("kubectl-lekiwi"))
        .arg("--kubeconfig")
        .arg(site.cp.kubeconfig())
        .args(["-n", &site.ns])
        .args(args)
        .args([
            "--server",
            &format!("http://127.0.0.1:{}", site.op.gateway_port),
        ])
        .env_remove("LEKIWI_SERVER")
        .output()?)
}

/// The releases `release list -o json` shows, by version.
fn listed(site: &OperatorSite) -> anyhow::Result<Vec<Value>> {
    let out = cli(site, &["release", "list", "-o", "json"])?;
    anyhow::ensure!(
        out.status.success(),
        "release list: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_slice(&out.stdout)?;
    Ok(v["items"].as_array().cloned().unwrap_or_default())
}

fn versions(items: &[Value]) -> BTreeSet<String> {
    items
        .iter()
        .filter_map(|i| i["version"].as_str().map(str::to_owned))
        .collect()
}

fn blobs(dir: &Path) -> BTreeSet<String> {
    std::fs::read_dir(dir.join("sha256"))
        .map(|e| {
            e.filter_map(Result::ok)
                .map(|e| format!("sha256:{}", e.file_name().to_string_lossy()))
                .collect()
        })
        .unwrap_or_default()
}

fn digest(bytes: &[u8]) -> String {
    format!("sha256:{}", hex::encode(Sha256::digest(bytes)))
}

/// Release `n`: a file every release shares, one that releases 1 and 2 share, and its own.
fn release_dir(root: &Path, n: usize, big: usize) -> anyhow::Result<PathBuf> {
    let dir = root.join(format!("release-{n:02}"));
    std::fs::create_dir_all(&dir)?;
    std::fs::write(dir.join("common.py"), "COMMON = 1\n".repeat(100))?;
    if n <= 2 {
        std::fs::write(dir.join("pair.py"), "PAIR = 1\n".repeat(100))?;
    }
    let own: Vec<u8> = format!("release {n}\n").bytes().cycle().take(big).collect();
    std::fs::write(dir.join("own.bin"), own)?;
    Ok(dir)
}

/// The versions Robots and RobotDeployments of the namespace reference, as the gateway counts.
async fn referenced(site: &OperatorSite) -> anyhow::Result<BTreeSet<String>> {
    let mut out = BTreeSet::new();
    let robots = Api::<Robot>::namespaced(site.client.clone(), &site.ns);
    for r in robots.list(&ListParams::default()).await?.items {
        out.extend(r.spec.release.map(|r| r.version.to_string()));
        out.extend(
            r.status
                .and_then(|s| s.current_release)
                .map(|r| r.version.to_string()),
        );
    }
    let deployments = Api::<RobotDeployment>::namespaced(site.client.clone(), &site.ns);
    for d in deployments.list(&ListParams::default()).await?.items {
        out.extend(d.spec.release.map(|r| r.version.to_string()));
        for r in d.status.into_iter().flat_map(|s| s.robots) {
            out.extend(r.previous_release.map(|p| p.version.to_string()));
        }
    }
    Ok(out)
}

fn newest(n: usize) -> BTreeSet<String> {
    (13 - n..=12).map(|i| format!("{i:02}.0")).collect()
}

/// Waits until the listed releases are exactly `want`, after the read grace and a collection
/// period have passed (a release robots read a moment ago is only deferred until then).
async fn collected(site: &OperatorSite, want: &BTreeSet<String>) -> anyhow::Result<()> {
    tokio::time::sleep(Duration::from_secs(4)).await;
    let got = wait_for("garbage collection", Duration::from_secs(30), || async {
        let now = versions(&listed(site).ok()?);
        (now == *want).then_some(now)
    })
    .await;
    if got.is_err() {
        anyhow::bail!("listed {:?}, want {want:?}", versions(&listed(site)?));
    }
    Ok(())
}

async fn rollout(
    site: &OperatorSite,
    release: &ReleaseRef,
    create: bool,
) -> anyhow::Result<RobotDeployment> {
    let api = Api::<RobotDeployment>::namespaced(site.client.clone(), &site.ns);
    if create {
        let d = RobotDeployment::new(
            "fleet",
            RobotDeploymentSpec {
                selector: LabelSelector::default(),
                release: Some(release.clone()),
                agent: None,
                strategy: test_strategy(1, 1),
                paused: false,
                analysis: None,
                priority: 0,
            },
        );
        api.create(&PostParams::default(), &d).await?;
    } else {
        let patch = json!({"spec": {"release": release}});
        api.patch("fleet", &PatchParams::default(), &Patch::Merge(&patch))
            .await?;
    }
    rollout_finished(&api, "fleet", Duration::from_secs(120)).await
}

#[tokio::test]
async fn collection_keeps_what_is_referenced_plus_the_newest_and_rollbacks_work()
-> anyhow::Result<()> {
    let site = OperatorSite::start_with(
        "relgc",
        &[
            "--release-retention",
            "3",
            "--release-gc-seconds",
            "1",
            "--blob-read-grace-seconds",
            "2",
        ],
    )
    .await?;
    let blob_dir = site.dir.path().join("blobs");
    let fleet = FleetProcess::start(FleetSpec {
        gateway: &gateway_url(&site.op),
        token_file: &site.token_file,
        namespace: &site.ns,
        robots: 3,
        state_root: &site.dir.path().join("robots"),
        health_command: HEALTH,
        report_every: "2",
        rust_log: "warn",
        extra: &[],
    })?;
    wait_online(&site.client, &site.ns, 3, Duration::from_secs(60)).await?;

    // Three releases, rolled out one after the other.
    let mut releases = Vec::new();
    for n in 1..=3 {
        releases.push(site.push(
            &release_dir(site.dir.path(), n, 64 * 1024)?,
            &format!("{n:02}.0"),
        )?);
        let d = rollout(&site, &releases[n - 1], n == 1).await?;
        let st = d.status.unwrap();
        assert_eq!(st.phase, Some(RolloutPhase::Completed), "{:?}", st.message);
    }
    // Nine more: twelve pushed. 3 is desired, current and the deployment's release, 2 every
    // robot's rollback target; 10, 11 and 12 are the newest three.
    for n in 4..=12 {
        releases.push(site.push(
            &release_dir(site.dir.path(), n, 64 * 1024)?,
            &format!("{n:02}.0"),
        )?);
    }
    let refs = referenced(&site).await?;
    assert_eq!(refs, ["02.0", "03.0"].map(String::from).into(), "{refs:?}");
    let mut want = refs.clone();
    want.extend(newest(RETENTION));
    collected(&site, &want).await?;
    let items = listed(&site)?;
    eprintln!(
        "after 12 pushes and 3 rollouts, kept: {:?}",
        versions(&items)
    );
    assert_eq!(items[0]["version"], "12.0", "newest first");
    assert!(items[0]["size"].as_u64().unwrap() > 64 * 1024);
    let three = items.iter().find(|i| i["version"] == "03.0").unwrap();
    assert_eq!(
        three["robots"],
        json!({"desired": 3, "current": 3, "previous": 0})
    );
    assert_eq!(
        three["deployments"],
        json!({"release": 1, "rollbackTarget": 0})
    );
    let two = items.iter().find(|i| i["version"] == "02.0").unwrap();
    assert_eq!(two["robots"]["previous"], 3);
    assert_eq!(two["deployments"]["rollbackTarget"], 1);
    let pair = digest("PAIR = 1\n".repeat(100).as_bytes());
    let on_disk = blobs(&blob_dir);
    assert!(
        on_disk.contains(&pair),
        "release 1 is gone, 2 keeps the file they share"
    );
    assert!(
        !on_disk.contains(&releases[0].digest.to_string()),
        "release 1's manifest is gone"
    );
    assert!(
        !on_disk.contains(&releases[4].digest.to_string()),
        "release 5's manifest is gone"
    );

    // Delete is refused while a release is used, and works when it is not.
    let out = cli(&site, &["release", "delete", "03.0"])?;
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("in use") && err.contains("3 desired"),
        "{err}"
    );
    let out = cli(&site, &["release", "delete", "10.0"])?;
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    want.remove("10.0");
    assert_eq!(versions(&listed(&site)?), want);

    // A rollback: 12 fails its health check on the canary; the robots stay on or go back to 3.
    for robot in ["kiwi-000", "kiwi-001", "kiwi-002"] {
        std::fs::write(fleet.state(robot).join("fail-health"), "")?;
    }
    let d = rollout(&site, &releases[11], false).await?;
    let st = d.status.unwrap();
    assert_eq!(st.phase, Some(RolloutPhase::RolledBack), "{:?}", st.message);
    wait_for("robots back on 03.0", Duration::from_secs(60), || async {
        let robots = Api::<Robot>::namespaced(site.client.clone(), &site.ns)
            .list(&ListParams::default())
            .await
            .ok()?;
        robots
            .items
            .iter()
            .all(|r| {
                r.status.as_ref().and_then(|s| s.current_release.as_ref()) == Some(&releases[2])
                    && r.spec.release.as_ref() == Some(&releases[2])
            })
            .then_some(())
    })
    .await?;
    // 2 is nobody's rollback target any more: it goes, and the file it shared with 1 with it.
    let refs = referenced(&site).await?;
    assert!(!refs.contains("02.0"), "{refs:?}");
    let mut want = refs;
    want.extend(["11.0", "12.0"].map(String::from));
    collected(&site, &want).await?;
    let on_disk = blobs(&blob_dir);
    assert!(
        !on_disk.contains(&pair),
        "the file shared by 1 and 2 went with the last of them"
    );
    let common = digest("COMMON = 1\n".repeat(100).as_bytes());
    assert!(
        on_disk.contains(&common),
        "the file every release shares stays"
    );
    eprintln!(
        "after the rollback, kept: {:?}; {} blobs on disk",
        versions(&listed(&site)?),
        on_disk.len()
    );
    drop(fleet);
    Ok(())
}

#[tokio::test]
async fn a_download_in_progress_keeps_its_release() -> anyhow::Result<()> {
    // Every volume has less than 100% free: the gateway warns at once.
    let site = OperatorSite::start_with(
        "reldl-gc",
        &[
            "--release-retention",
            "1",
            "--release-gc-seconds",
            "1",
            "--blob-free-warn-percent",
            "100",
        ],
    )
    .await?;
    let enroll = std::fs::read_to_string(&site.token_file)?;
    let enroll = enroll.trim();
    let robot = format!("{}/slow", site.ns);
    let (ws, welcome) = connect_agent(&site.op, enroll, &robot).await?;
    let robot_token = welcome.robot_token.expect("a robot token");
    let big = 48 * 1024 * 1024;
    let v1 = site.push(&release_dir(site.dir.path(), 1, big)?, "01.0")?;
    set_release(&site.client, &site.ns, "slow", &serde_json::to_value(&v1)?).await?;
    // The robot starts downloading release 1's big file and reads only its first bytes.
    let own: Vec<u8> = "release 1\n".bytes().cycle().take(big).collect();
    let url = format!(
        "http://127.0.0.1:{}/v1/blobs/{}",
        site.op.gateway_port,
        digest(&own)
    );
    let http = reqwest::Client::new();
    let mut resp = wait_for("the blob is readable", Duration::from_secs(10), || async {
        let resp = http
            .get(&url)
            .bearer_auth(&robot_token)
            .header("x-lekiwi-robot", &robot)
            .send()
            .await
            .ok()?;
        (resp.status() == 200).then_some(resp)
    })
    .await?;
    let mut body = resp.chunk().await?.expect("a first chunk").to_vec();
    // Nothing references release 1 now, and 2 and 3 are newer: only the download keeps it.
    let v2 = site.push(&release_dir(site.dir.path(), 2, 1024)?, "02.0")?;
    let v3 = site.push(&release_dir(site.dir.path(), 3, 1024)?, "03.0")?;
    set_release(&site.client, &site.ns, "slow", &serde_json::to_value(&v3)?).await?;
    collected(&site, &["01.0", "03.0"].map(String::from).into()).await?;
    assert_ne!(v2.digest, v3.digest);
    while let Some(chunk) = resp.chunk().await? {
        body.extend_from_slice(&chunk);
    }
    assert_eq!(body.len(), big);
    assert_eq!(digest(&body), digest(&own), "the download completed intact");
    let items = listed(&site)?;
    assert!(
        versions(&items).contains("01.0"),
        "kept while downloaded: {items:?}"
    );
    drop(ws);

    // The store's gauges, and one Warning Event on the gateway's Lease for the crossing.
    let metrics = site.op.metrics().await?;
    for series in [
        "lekiwi_gateway_blob_store_releases 2",
        "lekiwi_gateway_blob_volume_free_bytes ",
        "lekiwi_gateway_blob_volume_size_bytes ",
        "lekiwi_gateway_releases_removed_total{kind=\"gc\"} 1",
    ] {
        assert!(metrics.contains(series), "no {series} in\n{metrics}");
    }
    let events =
        Api::<k8s_openapi::api::core::v1::Event>::namespaced(site.client.clone(), &site.ns);
    let warned = wait_for("the volume warning", Duration::from_secs(20), || async {
        let list = events.list(&ListParams::default()).await.ok()?;
        let found: Vec<_> = list
            .items
            .into_iter()
            .filter(|e| e.reason.as_deref() == Some("BlobStoreNearlyFull"))
            .collect();
        (!found.is_empty()).then_some(found)
    })
    .await?;
    assert_eq!(warned.len(), 1, "one Event per crossing: {warned:?}");
    assert_eq!(warned[0].type_.as_deref(), Some("Warning"));
    assert_eq!(warned[0].involved_object.kind.as_deref(), Some("Lease"));
    assert_eq!(
        warned[0].count.unwrap_or(1),
        1,
        "published once: {warned:?}"
    );
    Ok(())
}
