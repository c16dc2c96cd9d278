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

/// How late the lagging replica's watch runs in the second test: past the 3 s a read waits for
/// the cache.
const LONG_LAG: Duration = Duration::from_secs(6);

/// Two gateway replicas sharing a blob store, one reaching the API server through a
/// [`LagProxy`]; a robot whose token both know; a release of one file pushed but not yet told
/// to the robot.
struct Replicas {
    client: kube::Client,
    ns: String,
    ahead: OperatorProcess,
    lagging: OperatorProcess,
    proxy: LagProxy,
    token: String,
    robot: String,
    release: OneFileRelease,
    _blobs: tempfile::TempDir,
}

impl Replicas {
    /// Starts both replicas in a new namespace `prefix`-…, pushes a release of `content` and
    /// waits until the lagging replica knows the robot's token: a read of the release's file is
    /// a 404 there (refused after its bounded wait, the robot not told of it), not a 401. The
    /// proxy does not lag yet.
    async fn start(prefix: &str, content: &[u8]) -> anyhow::Result<Self> {
        let cp = ControlPlane::shared();
        let client = cp.client().await?;
        let ns = namespace(&client, prefix).await?;
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
        // Pushed by a Kubernetes user to the replicas' shared blob store.
        let release = OneFileRelease::new("1.0.0", content);
        let admin = format!("Bearer {}", cp.admin_token()?);
        release.push(ahead.gateway_port, &admin, &ns).await?;
        let replicas = Self {
            client,
            robot: format!("{ns}/kiwi"),
            ns,
            ahead,
            lagging,
            proxy,
            token,
            release,
            _blobs: blobs,
        };
        let file = replicas.path(&replicas.release.file);
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            let (code, body) = replicas.get(replicas.lagging.gateway_port, &file).await;
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
        Ok(replicas)
    }

    fn path(&self, digest: &str) -> String {
        format!("/v1/blobs/{digest}")
    }

    /// A GET of `path` from the replica at `port`, as the robot.
    async fn get(&self, port: u16, path: &str) -> (u16, Vec<u8>) {
        let as_robot = [
            ("authorization", self.token.as_str()),
            ("x-lekiwi-robot", self.robot.as_str()),
        ];
        get(port, path, &as_robot).await
    }

    /// The rollout's write: the release in the robot's spec.
    async fn tell_robot(&self) -> anyhow::Result<()> {
        let patch =
            json!({"spec": {"release": {"version": "1.0.0", "digest": self.release.manifest}}});
        Api::<Robot>::namespaced(self.client.clone(), &self.ns)
            .patch("kiwi", &PatchParams::default(), &Patch::Merge(&patch))
            .await?;
        Ok(())
    }
}

#[tokio::test]
async fn a_download_on_a_replica_whose_watch_lags_waits_for_it_and_is_served() -> anyhow::Result<()>
{
    let r = Replicas::start("bloblag", b"the lagging replica's policy").await?;
    let (blob, manifest) = (r.path(&r.release.file), r.path(&r.release.manifest));
    // From now on the lagging replica's watch (and every answer it gets) runs LAG late.
    r.proxy.set_lag(LAG);

    // The rollout names the release in the robot's spec; the replica ahead sees it first.
    r.tell_robot().await?;
    let changed = Instant::now();
    let (code, body) = r.get(r.ahead.gateway_port, &blob).await;
    assert_eq!(
        (code, body),
        (200, r.release.content.clone()),
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
    let (code, body) = r.get(r.lagging.gateway_port, &blob).await;
    let waited = asked.elapsed();
    eprintln!(
        "replica ahead served the file {ahead_after:?} after the change; the lagging one \
         answered {code} {waited:?} after being asked"
    );
    assert_eq!(
        (code, body),
        (200, r.release.content.clone()),
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
    let (code, body) = r.get(r.lagging.gateway_port, &manifest).await;
    assert_eq!((code, body), (200, r.release.manifest_bytes.clone()));
    Ok(())
}

#[tokio::test]
async fn a_download_on_a_replica_whose_watch_lags_past_the_wait_reads_the_robot_and_is_served()
-> anyhow::Result<()> {
    // The token check reads the file, not the manifest: a read the replica refused is
    // remembered for a few seconds for that robot and blob.
    let r = Replicas::start("bloblate", b"a watch later than the wait").await?;
    let manifest = r.path(&r.release.manifest);
    r.proxy.set_lag(LONG_LAG);

    r.tell_robot().await?;
    let (code, _) = r.get(r.ahead.gateway_port, &manifest).await;
    assert_eq!(code, 200, "the replica ahead serves the manifest");

    // The lagging replica's cache does not show the release within its 3 s wait; it then
    // reads the Robot (LONG_LAG late too) and serves the manifest, not a 404.
    let asked = Instant::now();
    let (code, body) = r.get(r.lagging.gateway_port, &manifest).await;
    let waited = asked.elapsed();
    eprintln!("the lagging replica answered {code} {waited:?} after being asked");
    assert_eq!(
        (code, body),
        (200, r.release.manifest_bytes.clone()),
        "the lagging replica serves the release once it has read the robot"
    );
    assert!(
        waited >= Duration::from_secs(3),
        "answered in {waited:?}: the cache was not behind past the wait, so this run tested nothing"
    );
    Ok(())
}
