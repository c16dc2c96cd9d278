//! Two gateway replicas whose Robot watches are out of step, as behind one Service: the replica
//! holding a robot's session sees the robot's new release and tells the robot, whose download
//! reaches the other replica before that one's watch has the change. The download waits for the
//! lagging replica's cache (bounded) and is served, not answered "unknown digest"; when the
//! watch lags longer than that wait, the replica reads the robot's Robot from the API server
//! once and serves it then.
//!
//! The lagging replica reaches the API server through a proxy that, once the robot and its token
//! are known to both, hands on every byte the server sends 2 s late, so its watch events (and
//! every answer) arrive 2 s after the other's.

use std::time::{Duration, Instant};

use kube::Api;
use kube::api::{Patch, PatchParams};
use lekiwi_crds::Robot;
use lekiwi_tests::blobs::{OneFileRelease, get_bytes as get};
use lekiwi_tests::lag_proxy::LagProxy;
use lekiwi_tests::{ControlPlane, OperatorProcess, create_robot, namespace, robot_token};
use serde_json::json;

/// How late the lagging replica sees the API server's answers and watch events.
const LAG: Duration = Duration::from_secs(2);

#[tokio::test]
async fn a_download_on_a_replica_whose_watch_lags_waits_for_it_and_is_served() -> anyhow::Result<()>
{
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "bloblag").await?;
    let blobs = tempfile::tempdir()?;
    let blob_dir = blobs.path().to_str().expect("utf-8 path");
    let gateway = ["--role", "gateway", "--blob-dir", blob_dir];

    let mut ahead = OperatorProcess::start(cp, &ns, "ahead", &gateway)?;
    let proxy = LagProxy::start(cp.api_server_addr()?).await?;
    let kubeconfig = blobs.path().join("lagging-kubeconfig");
    cp.kubeconfig_via(&format!("https://{}", proxy.addr), &kubeconfig)?;
    let mut lagging =
        OperatorProcess::start_with_kubeconfig(&kubeconfig, &ns, "lagging", &gateway)?;
    ahead.wait_ready().await?;
    lagging.wait_ready().await?;

    create_robot(&client, &ns, "kiwi", &[]).await?;
    let token = format!("Bearer {}", robot_token(&client, &ns, "kiwi").await?);
    let robot = format!("{ns}/kiwi");
    let as_robot = [
        ("authorization", token.as_str()),
        ("x-lekiwi-robot", robot.as_str()),
    ];

    // A release of one file, pushed by a Kubernetes user to the replicas' shared blob store.
    let release = OneFileRelease::new("1.0.0", b"the lagging replica's policy");
    let admin = format!("Bearer {}", cp.admin_token()?);
    release.push(ahead.gateway_port, &admin, &ns).await?;
    let (file, manifest) = (&release.file, &release.manifest);
    // Before the robot is told of it, the replica does not let it read the release (after
    // waiting its bounded while for a change that does not come); the robot's token is known
    // to it (a 404, not a 401). From now on that replica's watch lags.
    let blob = format!("/v1/blobs/{file}");
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let (code, body) = get(lagging.gateway_port, &blob, &as_robot).await;
        if code == 404 {
            break;
        }
        assert_eq!(code, 401, "{}", String::from_utf8_lossy(&body));
        assert!(
            Instant::now() < deadline,
            "the robot's token never reached the replica"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    proxy.set_lag(LAG);

    // The rollout names the release in the robot's spec; the replica ahead sees it first.
    let patch = json!({"spec": {"release": {"version": "1.0.0", "digest": manifest}}});
    Api::<Robot>::namespaced(client.clone(), &ns)
        .patch("kiwi", &PatchParams::default(), &Patch::Merge(&patch))
        .await?;
    let changed = Instant::now();
    let (code, body) = get(ahead.gateway_port, &blob, &as_robot).await;
    assert_eq!(
        (code, body),
        (200, release.content.clone()),
        "the replica ahead serves it"
    );
    let ahead_after = changed.elapsed();
    assert!(
        ahead_after < LAG,
        "the replica ahead took {ahead_after:?} to see the change: it does not lead"
    );

    // The download reaching the lagging replica now: its cache does not have the release yet,
    // so the read waits for the watch and is then served.
    let asked = Instant::now();
    let (code, body) = get(lagging.gateway_port, &blob, &as_robot).await;
    let waited = asked.elapsed();
    eprintln!(
        "replica ahead served the file {ahead_after:?} after the change; the lagging one \
         answered {code} {waited:?} after being asked"
    );
    assert_eq!(
        (code, body),
        (200, release.content.clone()),
        "the lagging replica serves the release once its watch has it"
    );
    assert!(
        waited >= LAG / 4,
        "the lagging replica answered in {waited:?}: its watch was not behind, so this run \
         tested nothing"
    );
    assert!(
        waited < Duration::from_secs(3) + LAG / 2,
        "the wait is bounded (3 s): {waited:?}"
    );
    // The manifest too (the agent fetches it first).
    let (code, body) = get(
        lagging.gateway_port,
        &format!("/v1/blobs/{manifest}"),
        &as_robot,
    )
    .await;
    assert_eq!((code, body), (200, release.manifest_bytes));
    drop(proxy);
    Ok(())
}

/// How late the lagging replica's watch runs in the second test: past the 3 s a read waits for
/// the cache.
const LONG_LAG: Duration = Duration::from_secs(6);

#[tokio::test]
async fn a_download_on_a_replica_whose_watch_lags_past_the_wait_reads_the_robot_and_is_served()
-> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "bloblate").await?;
    let blobs = tempfile::tempdir()?;
    let blob_dir = blobs.path().to_str().expect("utf-8 path");
    let gateway = ["--role", "gateway", "--blob-dir", blob_dir];

    let mut ahead = OperatorProcess::start(cp, &ns, "ahead", &gateway)?;
    let proxy = LagProxy::start(cp.api_server_addr()?).await?;
    let kubeconfig = blobs.path().join("lagging-kubeconfig");
    cp.kubeconfig_via(&format!("https://{}", proxy.addr), &kubeconfig)?;
    let mut lagging =
        OperatorProcess::start_with_kubeconfig(&kubeconfig, &ns, "lagging", &gateway)?;
    ahead.wait_ready().await?;
    lagging.wait_ready().await?;

    create_robot(&client, &ns, "kiwi", &[]).await?;
    let token = format!("Bearer {}", robot_token(&client, &ns, "kiwi").await?);
    let robot = format!("{ns}/kiwi");
    let as_robot = [
        ("authorization", token.as_str()),
        ("x-lekiwi-robot", robot.as_str()),
    ];
    let release = OneFileRelease::new("1.0.0", b"a watch later than the wait");
    let admin = format!("Bearer {}", cp.admin_token()?);
    release.push(ahead.gateway_port, &admin, &ns).await?;
    let manifest_path = format!("/v1/blobs/{}", release.manifest);
    // Once the robot's token is known to the lagging replica (a 404, not a 401), its watch
    // and every answer it gets run LONG_LAG late. (The file, not the manifest: a read the
    // replica refused is remembered for a few seconds for that robot and blob.)
    let file_path = format!("/v1/blobs/{}", release.file);
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let (code, body) = get(lagging.gateway_port, &file_path, &as_robot).await;
        if code == 404 {
            break;
        }
        assert_eq!(code, 401, "{}", String::from_utf8_lossy(&body));
        assert!(
            Instant::now() < deadline,
            "the robot's token never reached the replica"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    proxy.set_lag(LONG_LAG);

    let patch = json!({"spec": {"release": {"version": "1.0.0", "digest": release.manifest}}});
    Api::<Robot>::namespaced(client.clone(), &ns)
        .patch("kiwi", &PatchParams::default(), &Patch::Merge(&patch))
        .await?;
    let (code, _) = get(ahead.gateway_port, &manifest_path, &as_robot).await;
    assert_eq!(code, 200, "the replica ahead serves the manifest");

    // The lagging replica's cache does not show the release within its 3 s wait; it then
    // reads the Robot (LONG_LAG late too) and serves the manifest, not a 404.
    let asked = Instant::now();
    let (code, body) = get(lagging.gateway_port, &manifest_path, &as_robot).await;
    let waited = asked.elapsed();
    eprintln!("the lagging replica answered {code} {waited:?} after being asked");
    assert_eq!(
        (code, body),
        (200, release.manifest_bytes.clone()),
        "the lagging replica serves the release once it has read the robot"
    );
    assert!(
        waited >= Duration::from_secs(3),
        "answered in {waited:?}: the cache was not behind past the wait, so this run tested nothing"
    );
    drop(proxy);
    Ok(())
}
