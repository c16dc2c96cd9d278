//! The Helm chart on a real node (`scripts/testbed/cluster.sh`) with the operator image from
//! `scripts/image.sh`: the operator Pod becomes Ready through its real probes under the chart's
//! securityContext as the kernel enforces it (non-root, read-only root filesystem, no
//! capabilities, seccomp) and writes only to its volumes; agents on the host enroll through the
//! gateway Service's NodePort over wss:// trusting the chart's generated CA, a release pushed
//! through the NodePort rolls out and a failing one rolls back; `helm upgrade` to a new image
//! tag replaces the Pod, the robots reconnect and every stored event is still there; `helm
//! uninstall` leaves the CRDs and the robots. The install page walked as written (issue #41):
//! from an empty cluster to a first rollout, a certificate rotation, a second rollout and a
//! release deleted, with no gateway address, port-forward or CA file typed (module `walk`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use k8s_openapi::api::coordination::v1::Lease;
use k8s_openapi::api::core::v1::{ConfigMap, Event, PersistentVolume, PersistentVolumeClaim};
use k8s_openapi::api::core::v1::{Pod, Secret, Service};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
use kube::api::{ListParams, Patch, PatchParams, PostParams};
use kube::{Api, Client};
use lekiwi_crds::deployment::RolloutPhase;
use lekiwi_crds::{ReleaseRef, Robot, RobotDeployment, RobotDeploymentSpec};
use lekiwi_tests::cluster::{Cluster, forward, http_get_at};

use crate::walk;
use lekiwi_tests::postgres::Postgres;
use lekiwi_tests::{
    FleetProcess, FleetSpec, bin, enrollment_token_file, namespace, rollout_finished,
    test_strategy, wait_for, wait_online,
};
use serde_json::{Value, json};

const CHART: &str = "charts/lekiwi-operator";
const ROBOTS: usize = 6;
const HEALTH: &str = r#"test ! -e "$LEKIWI_RELEASE_DIR/../../fail-health""#;

/// One release of the chart in its own namespace (release name = namespace), with the files
/// agents and the CLI need: the gateway's CA and an enrollment token.
struct Install {
    cluster: &'static Cluster,
    client: Client,
    ns: String,
    full: String,
    dir: tempfile::TempDir,
    ca: PathBuf,
    /// `https://<node IP>:<NodePort>` of the gateway Service.
    server: String,
}

impl Install {
    /// `helm install` with the image from the node's containerd, the gateway as a NodePort on
    /// the node's IP (in the generated certificate), and a claim the node's 1Gi PVs can hold.
    async fn new(cluster: &'static Cluster, prefix: &str, extra: &[&str]) -> anyhow::Result<Self> {
        let client = cluster.client().await?;
        let ns = namespace(&client, prefix).await?;
        Self::install(cluster, client, ns, extra).await
    }

    /// `helm install` into the existing namespace `ns` (as [`Install::new`]).
    async fn install(
        cluster: &'static Cluster,
        client: Client,
        ns: String,
        extra: &[&str],
    ) -> anyhow::Result<Self> {
        let ip = format!("gateway.tls.extraIpAddresses={{{}}}", cluster.node_ip);
        let mut args = vec!["install", &ns, CHART, "-n", &ns, "--set", &ip];
        for set in [
            "image.pullPolicy=Never",
            "rbac.userRoles=false",
            "persistence.size=200Mi",
            "gateway.service.type=NodePort",
            "operator.logFormat=text",
        ] {
            args.extend(["--set", set]);
        }
        args.extend_from_slice(extra);
        cluster.helm(&args)?;
        let full = format!("{ns}-lekiwi-operator");
        let dir = tempfile::tempdir()?;
        let cm = Api::<ConfigMap>::namespaced(client.clone(), &ns)
            .get(&format!("{full}-gateway-ca"))
            .await?;
        let ca = dir.path().join("ca.crt");
        std::fs::write(&ca, &cm.data.unwrap_or_default()["ca.crt"])?;
        let svc = Api::<Service>::namespaced(client.clone(), &ns)
            .get(&format!("{full}-gateway"))
            .await?;
        let port = svc.spec.and_then(|s| s.ports?.first()?.node_port);
        let server = format!("https://{}:{}", cluster.node_ip, port.context("nodePort")?);
        Ok(Self {
            cluster,
            client,
            ns,
            full,
            dir,
            ca,
            server,
        })
    }

    fn ws_url(&self) -> String {
        format!(
            "{}{}",
            self.server.replacen("https", "wss", 1),
            lekiwi_protocol::AGENT_PATH
        )
    }

    fn kubectl(&self, args: &[&str]) -> String {
        let mut all = vec!["-n", &self.ns];
        all.extend_from_slice(args);
        self.cluster.kubectl(&all).unwrap_or_else(|e| e.to_string())
    }

    /// What to read when a wait fails: the Pods, their description and the operator's log.
    fn diagnose(&self) -> String {
        let pods = "app.kubernetes.io/component=operator";
        format!(
            "{}\n{}\n{}",
            self.kubectl(&["get", "pods,events", "-o", "wide"]),
            self.kubectl(&["describe", "pods", "-l", pods]),
            self.kubectl(&["logs", "-l", pods, "--tail", "60"]),
        )
    }

    /// Waits for `n` operator Pods Ready (and no others); returns them.
    async fn ready_pods(&self, n: usize, within: Duration) -> anyhow::Result<Vec<Pod>> {
        let api = Api::<Pod>::namespaced(self.client.clone(), &self.ns);
        let lp = ListParams::default().labels("app.kubernetes.io/component=operator");
        let found = wait_for("the operator Pods Ready", within, || async {
            let pods = api.list(&lp).await.ok()?.items;
            let ready = pods.iter().filter(|p| is_ready(p)).count();
            (pods.len() == n && ready == n).then_some(pods)
        })
        .await;
        found.map_err(|e| anyhow::anyhow!("{e}\n{}", self.diagnose()))
    }

    /// `kubectl lekiwi ARGS... -n NS` against the cluster, through the NodePort for the
    /// commands that talk to the gateway.
    fn cli(&self, args: &[&str]) -> anyhow::Result<String> {
        let out = Command::new(bin("kubectl-lekiwi"))
            .arg("--kubeconfig")
            .arg(&self.cluster.kubeconfig)
            .args(["-n", &self.ns])
            .args(args)
            .args(["--server", &self.server, "--certificate-authority"])
            .arg(&self.ca)
            .env_remove("LEKIWI_SERVER")
            .output()?;
        if !out.status.success() {
            bail!(
                "kubectl lekiwi {args:?}: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        Ok(String::from_utf8_lossy(&out.stdout).into_owned())
    }

    fn push(&self, dir: &Path, version: &str) -> anyhow::Result<ReleaseRef> {
        let out = self.cli(&[
            "release",
            "push",
            dir.to_str().unwrap(),
            "--version",
            version,
        ])?;
        Ok(ReleaseRef {
            version: version.into(),
            digest: out.trim().into(),
        })
    }

    /// A robot's stored events, from the gateway's event store through the NodePort.
    /// Tried up to three times, 5 s apart: right after a `helm upgrade` a connect through the
    /// NodePort once timed out in CI while kube-proxy moved it to the new Pod.
    fn events(&self, robot: &str) -> anyhow::Result<Vec<Value>> {
        let args = [
            "events", robot, "-o", "json", "--since", "2h", "--limit", "1000",
        ];
        let mut last = None;
        for _ in 0..3 {
            match self.cli(&args) {
                Ok(out) => return lekiwi_tests::list_items(&out),
                Err(e) => {
                    eprintln!("{e:#}; trying again");
                    last = Some(e);
                    std::thread::sleep(std::time::Duration::from_secs(5));
                }
            }
        }
        Err(last.expect("three attempts"))
    }

    fn fleet(&self, robots: usize, extra: &[&str]) -> anyhow::Result<FleetProcess> {
        let token = self.dir.path().join("enroll");
        let ca = self.ca.to_str().unwrap().to_owned();
        FleetProcess::start(FleetSpec {
            gateway: &self.ws_url(),
            token_file: &token,
            namespace: &self.ns,
            robots,
            state_root: &self.dir.path().join("robots"),
            health_command: HEALTH,
            report_every: "5",
            rust_log: "warn,lekiwi_agent::release=info",
            extra: &[&["--ca-file", &ca], extra].concat(),
        })
    }

    async fn robots(&self) -> anyhow::Result<Vec<Robot>> {
        let api = Api::<Robot>::namespaced(self.client.clone(), &self.ns);
        Ok(api.list(&ListParams::default()).await?.items)
    }

    async fn wait_online(&self, n: usize) -> anyhow::Result<()> {
        wait_online(&self.client, &self.ns, n, Duration::from_secs(90)).await
    }

    /// Creates or retargets RobotDeployment `name` to `release`; waits for its end; its phase.
    async fn roll(&self, name: &str, release: &ReleaseRef) -> anyhow::Result<RolloutPhase> {
        self.start_roll(name, release).await?;
        self.roll_end(name).await
    }

    /// Creates or retargets RobotDeployment `name` to `release` (batches of 2 after a canary).
    async fn start_roll(&self, name: &str, release: &ReleaseRef) -> anyhow::Result<()> {
        let api = Api::<RobotDeployment>::namespaced(self.client.clone(), &self.ns);
        if api.get_opt(name).await?.is_some() {
            let patch = json!({"spec": {"release": release}});
            api.patch(name, &PatchParams::default(), &Patch::Merge(&patch))
                .await?;
        } else {
            let spec = RobotDeploymentSpec {
                selector: LabelSelector::default(),
                release: Some(release.clone()),
                agent: None,
                strategy: test_strategy(2, 1),
                paused: false,
                analysis: None,
                priority: 0,
            };
            api.create(&PostParams::default(), &RobotDeployment::new(name, spec))
                .await?;
        }
        Ok(())
    }

    /// Waits for RobotDeployment `name` to end; returns its phase.
    async fn roll_end(&self, name: &str) -> anyhow::Result<RolloutPhase> {
        let api = Api::<RobotDeployment>::namespaced(self.client.clone(), &self.ns);
        let d = rollout_finished(&api, name, Duration::from_secs(120))
            .await
            .map_err(|e| anyhow::anyhow!("{e}\n{}", self.diagnose()))?;
        let st = d.status.unwrap_or_default();
        eprintln!("{name}: {:?} {:?}", st.phase, st.message);
        st.phase.context("no phase")
    }
}

/// Deletes the namespace however the test ends (the claim releases its PV; the next
/// `cluster.sh up` makes it Available again).
impl Drop for Install {
    fn drop(&mut self) {
        let _ = self
            .cluster
            .helm(&["uninstall", &self.ns, "-n", &self.ns, "--wait=false"]);
        let _ = self
            .cluster
            .kubectl(&["delete", "namespace", &self.ns, "--wait=false"]);
    }
}

fn is_ready(pod: &Pod) -> bool {
    let conditions = pod.status.as_ref().and_then(|s| s.conditions.as_ref());
    conditions.is_some_and(|c| c.iter().any(|c| c.type_ == "Ready" && c.status == "True"))
}

fn release_dir(root: &Path, tag: &str) -> anyhow::Result<PathBuf> {
    let dir = root.join(format!("release-{tag}"));
    std::fs::create_dir_all(dir.join("lekiwi"))?;
    for i in 0..10 {
        let text = format!("file {i} of release {tag}\n").repeat(100);
        std::fs::write(dir.join("lekiwi").join(format!("f{i}.py")), text)?;
    }
    Ok(dir)
}

/// Reads `/proc/<pid>/{status,mountinfo}` of the operator's container process on the host:
/// what the kernel enforces, whatever the Pod spec says.
fn assert_locked_down(pid: u32) {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("status");
    let field = |name: &str| {
        status
            .lines()
            .find_map(|l| l.strip_prefix(&format!("{name}:")))
            .map(|v| v.split_whitespace().collect::<Vec<_>>().join(" "))
            .unwrap_or_default()
    };
    assert_eq!(field("Uid"), "65532 65532 65532 65532", "{status}");
    assert_eq!(field("Gid"), "65532 65532 65532 65532", "{status}");
    assert_eq!(field("CapEff"), "0000000000000000", "{status}");
    assert_eq!(field("CapPrm"), "0000000000000000", "{status}");
    assert_eq!(field("CapBnd"), "0000000000000000", "{status}");
    assert_eq!(field("NoNewPrivs"), "1", "{status}");
    assert_eq!(field("Seccomp"), "2", "a seccomp filter: {status}");
    // mountinfo: ID PARENT MAJ:MIN ROOT MOUNTPOINT OPTIONS ...; writable mounts are only the
    // volumes (and the kernel's own /dev/shm, /proc, ... which hold no files of ours).
    let mounts = std::fs::read_to_string(format!("/proc/{pid}/mountinfo")).expect("mountinfo");
    let mut writable = Vec::new();
    for line in mounts.lines() {
        let f: Vec<&str> = line.split_whitespace().collect();
        let (point, opts) = (f[4], f[5]);
        if point == "/" {
            assert!(
                opts.split(',').any(|o| o == "ro"),
                "root filesystem: {line}"
            );
        }
        if opts.split(',').any(|o| o == "rw") {
            writable.push(point);
        }
    }
    for point in ["/var/lib/lekiwi", "/tmp"] {
        assert!(writable.contains(&point), "{point} writable: {writable:?}");
    }
    let unexpected: Vec<_> = writable
        .iter()
        .filter(|p| !["/var/lib/lekiwi", "/tmp", "/dev", "/dev/shm", "/dev/mqueue"].contains(p))
        .filter(|p| !p.starts_with("/proc") && !p.starts_with("/sys") && !p.starts_with("/dev/"))
        .filter(|p| !["/etc/hosts", "/etc/hostname", "/etc/resolv.conf"].contains(p))
        .collect();
    assert!(
        unexpected.is_empty(),
        "writable beyond the volumes: {unexpected:?}"
    );
}

/// The Pod IP's `port`, from the host (the bridge routes to it).
fn pod_addr(pod: &Pod, port: u16) -> std::net::SocketAddr {
    let ip = pod.status.as_ref().and_then(|s| s.pod_ip.clone());
    format!("{}:{port}", ip.expect("Pod IP")).parse().unwrap()
}

/// A gauge's value from the operator's `/metrics` on the Pod IP.
async fn gauge(pod: &Pod, name: &str) -> Option<f64> {
    let (_, body) = http_get_at(pod_addr(pod, 8080), "/metrics").await.ok()?;
    body.lines()
        .find_map(|l| l.strip_prefix(&format!("{name} ")))
        .and_then(|v| v.trim().parse().ok())
}

/// The kubelet's own count of probe results for the operator container (its /metrics/probes
/// through the API server's node proxy), e.g. `("Liveness", "successful")`.
fn kubelet_probes(cluster: &Cluster, ns: &str, kind: &str, result: &str) -> f64 {
    let path = "/api/v1/nodes/lekiwi-node/proxy/metrics/probes";
    let metrics = cluster.kubectl(&["get", "--raw", path]).unwrap_or_default();
    let labels = [
        format!("namespace=\"{ns}\""),
        "container=\"operator\"".into(),
        format!("probe_type=\"{kind}\""),
        format!("result=\"{result}\""),
    ];
    metrics
        .lines()
        .filter(|l| l.starts_with("prober_probe_total{") && labels.iter().all(|x| l.contains(x)))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum()
}

/// Memory and CPU time of the container (cgroup v1 `memory` and `cpuacct` of `pid`), read on
/// the host, for the report.
fn cgroup_usage(pid: u32) -> String {
    let cgroups = std::fs::read_to_string(format!("/proc/{pid}/cgroup")).unwrap_or_default();
    let read = |controller: &str, file: &str| {
        let path = cgroups.lines().find_map(|l| {
            let (_, rest) = l.split_once(':')?;
            let (names, path) = rest.split_once(':')?;
            names.split(',').any(|n| n == controller).then_some(path)
        })?;
        let text = std::fs::read_to_string(format!("/sys/fs/cgroup/{controller}{path}/{file}"));
        text.ok()?.trim().parse::<u64>().ok()
    };
    let mib = |b: Option<u64>| b.map_or("?".into(), |b| format!("{:.1} MiB", b as f64 / 1048576.0));
    let cpu =
        read("cpuacct", "cpuacct.usage").map_or("?".into(), |n| format!("{:.2} s", n as f64 / 1e9));
    format!(
        "memory {} (max {}), CPU {cpu}",
        mib(read("memory", "memory.usage_in_bytes")),
        mib(read("memory", "memory.max_usage_in_bytes"))
    )
}

/// The host directory of the PV bound to the operator's claim.
async fn volume_dir(site: &Install) -> anyhow::Result<PathBuf> {
    let claim = Api::<PersistentVolumeClaim>::namespaced(site.client.clone(), &site.ns)
        .get(&format!("{}-data", site.full))
        .await?;
    let volume = claim.spec.and_then(|s| s.volume_name).context("unbound")?;
    let pv = Api::<PersistentVolume>::all(site.client.clone())
        .get(&volume)
        .await?;
    Ok(pv
        .spec
        .and_then(|s| s.host_path)
        .context("hostPath")?
        .path
        .into())
}

/// Point 1: probes answered by the real endpoints (the kubelet counts its successes, no
/// Unhealthy event), the locked-down process, and the store written on the volume.
async fn probed_and_locked_down(site: &Install, pod: &Pod) -> anyhow::Result<()> {
    for path in ["/healthz", "/readyz"] {
        let (code, body) = http_get_at(pod_addr(pod, 8080), path).await?;
        assert_eq!(code, 200, "{path}: {body}");
    }
    let (cluster, ns) = (site.cluster, site.ns.as_str());
    wait_for(
        "the kubelet's successful liveness and readiness probes",
        Duration::from_secs(40),
        || async {
            // Liveness every 10 s, readiness every 5 s (the chart's periods).
            let live = kubelet_probes(cluster, ns, "Liveness", "successful");
            let ready = kubelet_probes(cluster, ns, "Readiness", "successful");
            if live < 1.0 {
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
            (live >= 1.0 && ready >= 1.0).then_some(())
        },
    )
    .await
    .map_err(|e| anyhow::anyhow!("{e}\n{}", site.diagnose()))?;
    for kind in ["Liveness", "Readiness"] {
        assert_eq!(kubelet_probes(cluster, ns, kind, "failed"), 0.0, "{kind}");
    }
    let events = Api::<Event>::namespaced(site.client.clone(), ns)
        .list(&ListParams::default())
        .await?;
    let unhealthy: Vec<_> = events
        .items
        .iter()
        .filter(|e| e.reason.as_deref() == Some("Unhealthy"))
        .map(|e| e.message.clone())
        .collect();
    assert!(unhealthy.is_empty(), "probe failures: {unhealthy:?}");
    let status = pod.status.as_ref().unwrap();
    let container = &status.container_statuses.as_ref().unwrap()[0];
    assert_eq!(container.restart_count, 0);
    let pid = cluster.container_pid(container.container_id.as_deref().unwrap())?;
    assert_locked_down(pid);
    eprintln!("idle: {}", cgroup_usage(pid));
    let dir = volume_dir(site).await?;
    assert!(dir.join("events.db").exists(), "events.db on the PV");
    Ok(())
}

/// Each robot's `progress` events with phase `done`: completed deploys.
fn deploys_done(site: &Install, robot: &str) -> anyhow::Result<usize> {
    let events = site.events(robot)?;
    Ok(events
        .iter()
        .filter(|e| e["kind"] == "progress" && e["data"]["phase"] == "done")
        .count())
}

/// Point 2: agents on the host through the NodePort (wss://, the chart's CA) enroll and go
/// Online; a release pushed through the NodePort completes; a failing one rolls back.
async fn agents_through_the_node_port(site: &Install) -> anyhow::Result<FleetProcess> {
    enrollment_token_file(&site.client, &site.ns, &site.dir.path().join("enroll")).await?;
    let t = Instant::now();
    let fleet = site.fleet(ROBOTS, &[])?;
    site.wait_online(ROBOTS).await?;
    eprintln!(
        "{ROBOTS} robots Online through the NodePort in {:?}",
        t.elapsed()
    );
    let v1 = site.push(&release_dir(site.dir.path(), "1")?, "1.0.0")?;
    let t = Instant::now();
    assert_eq!(site.roll("fleet", &v1).await?, RolloutPhase::Completed);
    eprintln!("rollout of 1.0.0 completed in {:?}", t.elapsed());
    let blobs = volume_dir(site).await?.join("blobs");
    assert!(
        std::fs::read_dir(&blobs)?.next().is_some(),
        "the pushed release is on the PV"
    );
    // Every robot fails its health check with the next release.
    for i in 0..ROBOTS {
        std::fs::write(fleet.state(&format!("kiwi-{i:03}")).join("fail-health"), "")?;
    }
    let v2 = site.push(&release_dir(site.dir.path(), "2")?, "2.0.0")?;
    assert_eq!(site.roll("fleet", &v2).await?, RolloutPhase::RolledBack);
    for i in 0..ROBOTS {
        std::fs::remove_file(fleet.state(&format!("kiwi-{i:03}")).join("fail-health"))?;
    }
    let by = releases(site).await?;
    assert_eq!(by.get("1.0.0"), Some(&ROBOTS), "{by:?}");
    Ok(fleet)
}

/// Robots by the release they report.
async fn releases(site: &Install) -> anyhow::Result<BTreeMap<String, usize>> {
    let mut by = BTreeMap::new();
    for r in site.robots().await? {
        let v = r.status.and_then(|s| s.current_release);
        *by.entry(v.map_or("-".to_owned(), |r| r.version.to_string()))
            .or_default() += 1;
    }
    Ok(by)
}

/// Every robot's stored events, by robot.
fn all_events(site: &Install) -> anyhow::Result<BTreeMap<String, Vec<Value>>> {
    (0..ROBOTS)
        .map(|i| {
            let name = format!("kiwi-{i:03}");
            Ok((name.clone(), site.events(&name)?))
        })
        .collect()
}

/// Point 4: `helm upgrade` to another image tag replaces the Pod; every robot reconnects to
/// the new one within its backoff; every event stored before is still there (SQLite on the PV).
async fn upgrade_keeps_robots_and_events(site: &Install, image: &str) -> anyhow::Result<()> {
    let before = all_events(site)?;
    let old = site.ready_pods(1, Duration::from_secs(5)).await?;
    let old_name = old[0].metadata.name.clone();
    let tag = format!("image.tag={}-next", image.rsplit(':').next().unwrap());
    let t = Instant::now();
    site.cluster.helm(&[
        "upgrade",
        &site.ns,
        CHART,
        "-n",
        &site.ns,
        "--reuse-values",
        "--set",
        &tag,
    ])?;
    let new = wait_for("the upgraded Pod", Duration::from_secs(120), || async {
        let pods = site.ready_pods(1, Duration::from_secs(1)).await.ok()?;
        let spec = pods[0].spec.as_ref()?;
        let upgraded = pods[0].metadata.name != old_name
            && spec.containers[0].image.as_deref()?.ends_with("-next");
        upgraded.then(|| pods[0].clone())
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\n{}", site.diagnose()))?;
    let ready = t.elapsed();
    // The agents retry every 2 s at most (FleetSpec); kube-proxy needs a moment for the new
    // endpoint.
    wait_for(
        "every robot reconnected",
        Duration::from_secs(20),
        || async {
            (gauge(&new, "lekiwi_gateway_connections").await? >= ROBOTS as f64).then_some(())
        },
    )
    .await
    .map_err(|e| anyhow::anyhow!("{e}\n{}", site.diagnose()))?;
    eprintln!(
        "helm upgrade: new Pod Ready after {ready:?}, {ROBOTS} robots reconnected after {:?}",
        t.elapsed()
    );
    let container = new
        .status
        .as_ref()
        .and_then(|s| s.container_statuses.clone());
    let id = container
        .and_then(|c| c[0].container_id.clone())
        .context("container")?;
    let usage = cgroup_usage(site.cluster.container_pid(&id)?);
    eprintln!("after the reconnects: {usage}");
    let after = all_events(site)?;
    for (robot, events) in &before {
        let seqs = |v: &[Value]| v.iter().map(|e| e["seq"].clone()).collect::<Vec<_>>();
        let kept = seqs(&after[robot]);
        let lost: Vec<_> = seqs(events)
            .into_iter()
            .filter(|s| !kept.contains(s))
            .collect();
        assert!(
            lost.is_empty(),
            "{robot}: events {lost:?} lost in the upgrade"
        );
    }
    let v3 = site.push(&release_dir(site.dir.path(), "3")?, "3.0.0")?;
    assert_eq!(site.roll("fleet", &v3).await?, RolloutPhase::Completed);
    for robot in before.keys() {
        // 1.0.0, the rollback to 1.0.0 and 3.0.0: each deploy finished once.
        assert!(deploys_done(site, robot)? >= 2, "{robot}");
    }
    Ok(())
}

/// Point 5: `helm uninstall` removes the operator but leaves the CRDs and the robots.
async fn uninstall_keeps_crds_and_robots(site: &Install) -> anyhow::Result<()> {
    site.cluster
        .helm(&["uninstall", &site.ns, "-n", &site.ns])?;
    let left = || site.kubectl(&["get", "deployments,pods", "-o", "name"]);
    let pods = left();
    // The 1.20 kubelet deletes a stopped Pod's object only once its sandbox is removed, which
    // its container GC may leave to its next round, once a minute: a cold run here saw the
    // operator Pod's sandbox stopped at once and removed 59 s later (another, 46 s). So the
    // bound is two GC rounds, not one.
    wait_for("the operator gone", Duration::from_secs(150), || async {
        left().trim().is_empty().then_some(())
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}: before {pods}; left {}", left()))?;
    for crd in ["robots.fleet.lekiwi.io", "robotdeployments.fleet.lekiwi.io"] {
        site.cluster.kubectl(&["get", "crd", crd])?;
    }
    assert_eq!(site.robots().await?.len(), ROBOTS, "the robots stay");
    let api = Api::<RobotDeployment>::namespaced(site.client.clone(), &site.ns);
    api.get("fleet")
        .await
        .context("the RobotDeployment stays")?;
    Ok(())
}

#[tokio::test(flavor = "multi_thread")]
async fn chart_on_a_real_node_serves_agents_upgrades_and_uninstalls() -> anyhow::Result<()> {
    let cluster = Cluster::shared();
    let image = cluster.operator_image();
    let t = Instant::now();
    let site = Install::new(cluster, "helm", &[]).await?;
    let pods = site.ready_pods(1, Duration::from_secs(120)).await?;
    eprintln!("helm install: operator Pod Ready after {:?}", t.elapsed());
    probed_and_locked_down(&site, &pods[0]).await?;
    let _fleet = agents_through_the_node_port(&site).await?;
    upgrade_keeps_robots_and_events(&site, image).await?;
    uninstall_keeps_crds_and_robots(&site).await?;
    Ok(())
}

/// A ReadWriteMany claim `blobs` in `ns` on a hostPath PV of the test's own (the node is one
/// machine, so every replica mounts the same directory).
async fn rwx_claim(client: &Client, ns: &str, dir: &Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir)?;
    std::fs::set_permissions(dir, std::os::unix::fs::PermissionsExt::from_mode(0o777))?;
    let pv: PersistentVolume = serde_json::from_value(json!({
        "metadata": {"name": format!("{ns}-blobs")},
        "spec": {
            "capacity": {"storage": "1Gi"},
            "accessModes": ["ReadWriteMany"],
            "persistentVolumeReclaimPolicy": "Delete",
            "storageClassName": "",
            "hostPath": {"path": dir, "type": "Directory"},
            "claimRef": {"namespace": ns, "name": "blobs"},
        },
    }))?;
    Api::<PersistentVolume>::all(client.clone())
        .create(&PostParams::default(), &pv)
        .await?;
    let claim: PersistentVolumeClaim = serde_json::from_value(json!({
        "metadata": {"name": "blobs"},
        "spec": {
            "accessModes": ["ReadWriteMany"],
            "storageClassName": "",
            "volumeName": format!("{ns}-blobs"),
            "resources": {"requests": {"storage": "1Gi"}},
        },
    }))?;
    Api::<PersistentVolumeClaim>::namespaced(client.clone(), ns)
        .create(&PostParams::default(), &claim)
        .await?;
    Ok(())
}

/// The leader Lease's holder.
async fn leader(site: &Install) -> Option<String> {
    let api = Api::<Lease>::namespaced(site.client.clone(), &site.ns);
    api.get("lekiwi-operator").await.ok()?.spec?.holder_identity
}

/// Point 3: two replicas on PostgreSQL (the host's, reached by the Pods through a forwarder on
/// the host's end of the veth pair to the node) and a ReadWriteMany blob volume. The leader Pod is deleted mid-rollout: the
/// other replica takes the Lease within its duration, the rollout completes, and no robot is
/// deployed twice.
#[tokio::test(flavor = "multi_thread")]
async fn two_replicas_hand_leadership_over_mid_rollout() -> anyhow::Result<()> {
    let cluster = Cluster::shared();
    cluster.operator_image();
    let pg = Postgres::start()?;
    pg.create_database("lekiwi")?;
    let to = format!("127.0.0.1:{}", pg.port()).parse()?;
    let addr = forward(&cluster.host_ip, to).await?;
    let client = cluster.client().await?;
    let ns = namespace(&client, "ha").await?;
    let url = format!("postgres://postgres@{addr}/lekiwi");
    let secret: Secret = serde_json::from_value(json!({
        "metadata": {"name": "pg"}, "stringData": {"url": url},
    }))?;
    Api::<Secret>::namespaced(client.clone(), &ns)
        .create(&PostParams::default(), &secret)
        .await?;
    let blob_dir = tempfile::tempdir()?;
    rwx_claim(&client, &ns, &blob_dir.path().join("blobs")).await?;
    let sets = [
        "--set",
        "replicaCount=2",
        "--set",
        "store.postgres.existingSecret=pg",
        "--set",
        "persistence.existingClaim=blobs",
    ];
    let site = Install::install(cluster, client, ns, &sets).await?;
    site.ready_pods(2, Duration::from_secs(120)).await?;
    enrollment_token_file(&site.client, &site.ns, &site.dir.path().join("enroll")).await?;
    let _fleet = site.fleet(ROBOTS, &["--restart-command", "sleep 5"])?;
    site.wait_online(ROBOTS).await?;
    let v1 = site.push(&release_dir(site.dir.path(), "1")?, "1.0.0")?;
    site.start_roll("ha", &v1).await?;
    let api = Api::<RobotDeployment>::namespaced(site.client.clone(), &site.ns);
    wait_for("batch 1 started", Duration::from_secs(60), || async {
        let st = api.get("ha").await.ok()?.status?;
        let progressing = st.phase == Some(RolloutPhase::Progressing);
        (progressing && st.current_batch? >= 1).then_some(())
    })
    .await?;
    let old = leader(&site).await.context("a leader")?;
    // The chart's replicas hold the Lease as their Pod's name.
    let pod = old.clone();
    let t = Instant::now();
    eprintln!("{}", site.kubectl(&["delete", "pod", &pod, "--wait=false"]));
    let new = wait_for("a new leader", Duration::from_secs(30), || async {
        leader(&site).await.filter(|h| !h.starts_with(&pod))
    })
    .await
    .map_err(|e| {
        let lease = site.kubectl(&["get", "lease", "-o", "yaml"]);
        anyhow::anyhow!("{e} (was {old})\n{lease}\n{}", site.diagnose())
    })?;
    let handover = t.elapsed();
    eprintln!("leader {old} deleted; {new} leads after {handover:?}");
    assert!(
        handover < Duration::from_secs(15),
        "within the lease duration"
    );
    assert_eq!(site.roll_end("ha").await?, RolloutPhase::Completed);
    for i in 0..ROBOTS {
        let robot = format!("kiwi-{i:03}");
        let events = site.events(&robot)?;
        let phase = |p: &str| {
            let of = |e: &&Value| e["kind"] == "progress" && e["data"]["phase"] == p;
            events.iter().filter(of).count()
        };
        // Updated once: one download, one switch, one restart. A robot that reconnects to the
        // other replica while its deploy is still running may be sent the same release again
        // (the replicas do not share which commands are running); its agent then answers
        // `done` at once without touching anything, which is counted but allowed.
        for p in ["switching", "restarting"] {
            assert_eq!(phase(p), 1, "{robot}: {p} once: {events:#?}");
        }
        assert!(phase("done") >= 1, "{robot}: done: {events:#?}");
        if phase("done") > 1 {
            eprintln!("{robot}: sent the same release again, answered done without an update");
        }
    }
    Ok(())
}

/// `kubectl lekiwi` from the kubeconfig alone (issue #41): with no --server and no CA file it
/// finds the chart's gateway in --gateway-namespace, reaches it through a port-forward it opens
/// itself through the API server, trusts the chart's CA from its ConfigMap and presents the
/// kubeconfig user's token; `robot add` prints a join command with the gateway's NodePort
/// address and its CA's pin.
#[tokio::test(flavor = "multi_thread")]
async fn the_plugin_reaches_the_gateway_from_the_kubeconfig_alone() -> anyhow::Result<()> {
    let cluster = Cluster::shared();
    cluster.operator_image();
    // Its operator minds its own namespace: tests that follow must not meet it reconciling
    // their deployments while its Pod terminates.
    let client = cluster.client().await?;
    let ns = namespace(&client, "plugin").await?;
    let watch = format!("operator.watchNamespace={ns}");
    let site = Install::install(cluster, client, ns, &["--set", &watch]).await?;
    site.ready_pods(1, Duration::from_secs(120)).await?;
    let plugin = |args: &[&str]| -> anyhow::Result<String> {
        let out = Command::new(bin("kubectl-lekiwi"))
            .arg("--kubeconfig")
            .arg(&cluster.kubeconfig)
            .args(["-n", &site.ns, "--gateway-namespace", &site.ns])
            .args(args)
            .env_remove("LEKIWI_SERVER")
            .env_remove("LEKIWI_GATEWAY_URL")
            .output()?;
        if !out.status.success() {
            bail!(
                "kubectl lekiwi {args:?}: {}\n{}",
                String::from_utf8_lossy(&out.stderr),
                site.diagnose()
            );
        }
        Ok(String::from_utf8_lossy(&out.stdout).into_owned())
    };
    let rel = release_dir(site.dir.path(), "1.0.0")?;
    let push = [
        "release",
        "push",
        rel.to_str().unwrap(),
        "--version",
        "1.0.0",
    ];
    let digest = plugin(&push)?.trim().to_owned();
    assert!(digest.starts_with("sha256:"), "{digest}");
    let inspected: Value =
        serde_json::from_str(&plugin(&["release", "inspect", &digest, "-o", "json"])?)?;
    assert_eq!(inspected["version"], "1.0.0");
    assert_eq!(inspected["missing"], json!([]));

    let ca = std::fs::read(&site.ca)?;
    let der = rustls_pki_types::pem::PemObject::from_pem_slice(&ca)
        .map(|c: rustls_pki_types::CertificateDer<'static>| c)?;
    let pin = lekiwi_protocol::join::ca_cert_hash(&der)?;
    let line = plugin(&["robot", "add", "kiwi-plugin"])?;
    assert!(
        line.contains(&format!("--gateway {}", site.ws_url())),
        "{line}"
    );
    assert!(line.contains(&format!("--ca-cert-hash {pin}")), "{line}");
    Ok(())
}

/// Writes the robot's code for `version` in the lab's `~/kiwi-app`: one file the same in every
/// version, one of its own; returns the SHA-256 (hex) of the latter.
fn kiwi_app(lab: &walk::Lab, version: &str) -> anyhow::Result<String> {
    use sha2::Digest as _;
    let dir = lab.home.path().join("kiwi-app/lekiwi");
    std::fs::create_dir_all(&dir)?;
    std::fs::write(dir.join("drive.py"), "print('the same in every version')\n")?;
    let own = format!("VERSION = {version:?}\n").repeat(50);
    std::fs::write(dir.join("version.py"), &own)?;
    Ok(hex::encode(sha2::Sha256::digest(own.as_bytes())))
}

/// The release robot `name` of the lab's namespace reports.
async fn current_release(lab: &walk::Lab, name: &str) -> anyhow::Result<String> {
    let robot = Api::<Robot>::namespaced(lab.client.clone(), &lab.ns)
        .get(name)
        .await?;
    let current = robot.status.and_then(|s| s.current_release);
    Ok(current.map(|r| r.version.to_string()).unwrap_or_default())
}

/// The chart's operator Pod (Ready) and the gateway's NodePort, in the page's release.
async fn walked_install(lab: &walk::Lab) -> anyhow::Result<(Pod, u16)> {
    let pods = Api::<Pod>::namespaced(lab.client.clone(), walk::RELEASE_NS);
    let lp = ListParams::default().labels("app.kubernetes.io/component=operator");
    let pod = wait_for(
        "the operator Pod Ready",
        Duration::from_secs(60),
        || async {
            let list = pods.list(&lp).await.ok()?.items;
            (list.len() == 1 && is_ready(&list[0])).then(|| list[0].clone())
        },
    )
    .await?;
    let svc = Api::<Service>::namespaced(lab.client.clone(), walk::RELEASE_NS)
        .get(&format!("{}-gateway", walk::FULL))
        .await?;
    let port = svc.spec.and_then(|s| s.ports?.first()?.node_port);
    Ok((pod, u16::try_from(port.context("nodePort")?)?))
}

/// The page's join: `robot add` prints one line shaped as the page's `sh robot` block (the
/// same words up to the values), naming the gateway by the node's address and NodePort; run on
/// the robot host it joins, and the robot is Online.
async fn walked_join(
    lab: &mut walk::Lab,
    robot: &mut walk::RobotHost,
    node_port: u16,
) -> anyhow::Result<()> {
    let line = lab.run("add")?;
    assert_eq!(line.lines().count(), 1, "{line}");
    let flags = |l: &str| {
        let words: Vec<String> = l.split_whitespace().map(str::to_owned).collect();
        let mut shape: Vec<String> = words[..3].to_vec();
        shape.extend(words.into_iter().filter(|w| w.starts_with("--")));
        shape
    };
    assert_eq!(flags(&line), flags(&lab.page().robot), "{line}");
    let gateway = format!(
        "--gateway wss://{}:{node_port}/v1/agent",
        lab.cluster.node_ip
    );
    assert!(line.contains(&gateway), "{line}");
    let said = robot.join(line.trim()).await?;
    eprintln!("join: {said}");
    let name = format!("{}/kiwi-1", lab.ns);
    assert!(
        said.contains(&format!("robot {name} joined: Online")),
        "{said}"
    );
    // Join returns once the gateway has welcomed the agent; the Robot's phase is the gateway's
    // status write.
    let joined = Instant::now();
    wait_online(&lab.client, &lab.ns, 1, Duration::from_secs(30)).await?;
    eprintln!(
        "the Robot Online in the API {:?} after join returned",
        joined.elapsed()
    );
    Ok(())
}

/// The page's rotation: `helm upgrade` with another validity; new connections to the NodePort
/// get a new certificate, the expiry gauge moves to it, the robot stays Online.
async fn walked_rotation(lab: &mut walk::Lab, pod: &Pod, node_port: u16) -> anyhow::Result<()> {
    const EXPIRY: &str = "lekiwi_gateway_tls_certificate_expiry_timestamp_seconds";
    let addr = format!("{}:{node_port}", lab.cluster.node_ip);
    let before = walk::served_serial(&addr)?;
    let expiry = gauge(pod, EXPIRY).await.context("the expiry gauge")?;
    let t = Instant::now();
    lab.run("rotate")?;
    // The kubelet updates a Secret volume on its next sync of the Pod (up to a minute and its
    // cache's TTL), the gateway reads the files every 10 s.
    wait_for(
        "the new certificate served",
        Duration::from_secs(240),
        || async {
            let now = walk::served_serial(&addr).ok()?;
            (now != before).then_some(())
        },
    )
    .await?;
    let served = t.elapsed();
    let after = wait_for(
        "the expiry gauge moved",
        Duration::from_secs(30),
        || async { gauge(pod, EXPIRY).await.filter(|e| *e != expiry) },
    )
    .await?;
    let days = (after - jiff::Timestamp::now().as_second() as f64) / 86_400.0;
    eprintln!(
        "rotation: new certificate served {served:?} after helm upgrade; {days:.1} days left (was {:.1})",
        (expiry - jiff::Timestamp::now().as_second() as f64) / 86_400.0
    );
    assert!((729.0..=730.1).contains(&days), "{days} days");
    let connections = gauge(pod, "lekiwi_gateway_connections").await;
    assert_eq!(connections, Some(1.0), "the robot's session");
    Ok(())
}

/// Issue #41 part 6: docs/src/install/first-rollout.md walked as written, on the node: the
/// image loaded and the chart installed with its defaults (a NodePort and the node's address
/// in the certificate), a robot on a host of its own joined with the one command `robot add`
/// prints, a release pushed and rolled out, the gateway's certificate rotated, the next
/// release rolled out with `set-release`, and an unused release deleted with its blobs, with
/// no gateway address, port-forward or CA file typed.
#[tokio::test(flavor = "multi_thread")]
async fn the_first_rollout_page_walked_as_written() -> anyhow::Result<()> {
    let cluster = Cluster::shared();
    // Builds target/image/lekiwi-operator-*.oci.tar, which the page's first block imports.
    cluster.operator_image();
    let mut lab = walk::Lab::new(cluster).await?;
    // What a lab types to its first completed rollout: the page's commands and the join on the
    // robot, without the image import (only where nodes cannot pull it) and `rollout status`
    // (it watches).
    let typed: Vec<String> = lab
        .page()
        .commands_until("first")
        .into_iter()
        .filter(|c| !c.starts_with("ctr ") && !c.starts_with("kubectl lekiwi rollout status"))
        .chain(["sudo lekiwi-agent join ... (on the robot)".to_owned()])
        .collect();
    eprintln!(
        "{} commands to the first completed rollout:\n{}",
        typed.len(),
        typed.join("\n")
    );
    assert_eq!(typed.len(), 5, "the page says five");
    lab.run("image")?;
    let t = Instant::now();
    lab.run("install")?;
    eprintln!("helm install --wait returned after {:?}", t.elapsed());
    let (pod, node_port) = walked_install(&lab).await?;
    let mut robot = walk::RobotHost::new(cluster)?;
    walked_join(&mut lab, &mut robot, node_port).await?;
    kiwi_app(&lab, "1.0.0")?;
    let status = lab.run("first")?;
    eprintln!(
        "first rollout completed {:?} after helm install began: {status}",
        t.elapsed()
    );
    let current = current_release(&lab, "kiwi-1").await?;
    assert_eq!(current, "1.0.0", "{}", lab.diagnose());
    walked_rotation(&mut lab, &pod, node_port).await?;
    let next = kiwi_app(&lab, "1.1.0")?;
    lab.run("next")?;
    let current = current_release(&lab, "kiwi-1").await?;
    assert_eq!(current, "1.1.0", "{}", lab.diagnose());
    let rc = kiwi_app(&lab, "1.2.0-rc.1")?;
    let deleted = lab.run("delete")?;
    let digest = deleted
        .split(['(', ')'])
        .find(|w| w.starts_with("sha256:"))
        .context("the deleted release's digest")?;
    let blobs = lab.blobs();
    assert!(!blobs.join(&digest[7..]).exists(), "its manifest is gone");
    assert!(!blobs.join(&rc).exists(), "its own file is gone");
    assert!(blobs.join(&next).exists(), "1.1.0's file stays");
    lab.all_ran()?;
    drop(robot);
    Ok(())
}
