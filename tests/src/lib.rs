//! Test harness: the shared local control plane, private ones for disruptive tests, operator
//! processes, and a stand-in that plays the gateway's part in Robot status.

pub mod postgres;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use anyhow::{Context as _, Result, bail};
use jiff::Timestamp;
use k8s_openapi::api::coordination::v1::{Lease, LeaseSpec};
use k8s_openapi::api::core::v1::Namespace;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::MicroTime;
use kube::api::{ObjectMeta, Patch, PatchParams, PostParams};
use kube::config::{KubeConfigOptions, Kubeconfig};
use kube::{Api, Client};
use lekiwi_crds::Robot;
use serde_json::{Value, json};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// The repository root.
pub fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .canonicalize()
        .expect("repo root")
}

/// kubectl and helm as installed by `scripts/setup.sh`.
pub fn tool(name: &str) -> PathBuf {
    let home = std::env::var("HOME").unwrap_or_else(|_| "/root".into());
    let cache = std::env::var("LEKIWI_CACHE").unwrap_or_else(|_| format!("{home}/.cache/lekiwi"));
    PathBuf::from(cache).join("bin").join(name)
}

/// Path of one of our binaries, built once per test process.
pub fn bin(name: &str) -> PathBuf {
    static BUILT: OnceLock<()> = OnceLock::new();
    BUILT.get_or_init(|| {
        // The same command as scripts/test.sh runs first, in the same environment: the test
        // runner's CARGO_PKG_* variables would make ring's build script, and so the whole TLS
        // stack, rebuild.
        let mut cmd = Command::new("cargo");
        for (key, _) in std::env::vars_os() {
            let key = key.to_string_lossy().into_owned();
            let keep = matches!(key.as_str(), "CARGO_HOME" | "CARGO_TARGET_DIR");
            if !keep
                && (key.starts_with("CARGO")
                    || key.starts_with("RUSTUP_TOOLCHAIN")
                    || key == "OUT_DIR"
                    || key == "RUST_RECURSION_COUNT")
            {
                cmd.env_remove(&key);
            }
        }
        let status = cmd
            .args(["build", "--quiet", "--workspace", "--bins"])
            .current_dir(repo_root())
            .status()
            .expect("run cargo build");
        assert!(status.success(), "building the binaries failed");
    });
    let target = std::env::var("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|_| repo_root().join("target"));
    target.join("debug").join(name)
}

/// A directory for logs of processes a test starts, kept after the run for debugging.
pub fn log_dir() -> PathBuf {
    let dir = repo_root().join("target/test-logs");
    std::fs::create_dir_all(&dir).expect("create log dir");
    dir
}

/// A running etcd + kube-apiserver managed by `scripts/control-plane.sh`.
pub struct ControlPlane {
    /// State directory of the instance.
    pub dir: PathBuf,
    private: Option<tempfile::TempDir>,
}

impl ControlPlane {
    /// The control plane shared by the whole test run (started once, reused), with our CRDs.
    pub fn shared() -> &'static ControlPlane {
        static SHARED: OnceLock<ControlPlane> = OnceLock::new();
        SHARED.get_or_init(|| {
            let dir = std::env::var("LEKIWI_CP_DIR")
                .map(PathBuf::from)
                .unwrap_or_else(|_| {
                    let home = std::env::var("HOME").unwrap_or_else(|_| "/root".into());
                    // Not the quickstart's control plane: an operator left running there watches
                    // every namespace and would fight the tests' own operators.
                    PathBuf::from(home).join(".cache/lekiwi/test-control-plane")
                });
            let cp = ControlPlane { dir, private: None };
            cp.up().expect("start the shared control plane");
            cp.install_crds().expect("install CRDs");
            cp
        })
    }

    /// A second control plane of this test's own, on its own ports, for tests that restart it.
    pub fn private() -> Result<ControlPlane> {
        let tmp = tempfile::Builder::new().prefix("lekiwi-cp-").tempdir()?;
        let cp = ControlPlane {
            dir: tmp.path().to_owned(),
            private: Some(tmp),
        };
        cp.up()?;
        Ok(cp)
    }

    fn script(&self, args: &[&str]) -> Result<Output> {
        let out = Command::new("bash")
            .arg(repo_root().join("scripts/control-plane.sh"))
            .args(args)
            .env("LEKIWI_CP_DIR", &self.dir)
            .stdin(Stdio::null())
            .output()?;
        if !out.status.success() {
            bail!(
                "control-plane.sh {args:?} failed: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        Ok(out)
    }

    /// Starts (or restarts, on the same ports and data) the processes.
    pub fn up(&self) -> Result<()> {
        self.script(&["up"]).map(|_| ())
    }

    /// SIGKILLs etcd and kube-apiserver, keeping their data.
    pub fn kill(&self) -> Result<()> {
        self.script(&["kill"]).map(|_| ())
    }

    /// The admin kubeconfig.
    pub fn kubeconfig(&self) -> PathBuf {
        self.dir.join("kubeconfig")
    }

    /// A client with admin rights.
    pub async fn client(&self) -> Result<Client> {
        let kc = Kubeconfig::read_from(self.kubeconfig())?;
        let config =
            kube::Config::from_custom_kubeconfig(kc, &KubeConfigOptions::default()).await?;
        Ok(Client::try_from(config)?)
    }

    /// A kubeconfig for the same server with another bearer token.
    pub fn kubeconfig_with_token(&self, token: &str, path: &Path) -> Result<()> {
        let mut kc: serde_yaml::Value =
            serde_yaml::from_str(&std::fs::read_to_string(self.kubeconfig())?)?;
        let users = kc["users"]
            .as_sequence_mut()
            .context("kubeconfig has no users")?;
        for user in users.iter_mut() {
            user["user"] =
                serde_yaml::to_value(std::collections::BTreeMap::from([("token", token)]))?;
        }
        std::fs::write(path, serde_yaml::to_string(&kc)?)?;
        Ok(())
    }

    /// Runs a tool from the cache (`kubectl`, `helm`) against this control plane.
    pub fn tool(&self, name: &str, args: &[&str]) -> Output {
        Command::new(tool(name))
            .args(args)
            .env("KUBECONFIG", self.kubeconfig())
            .env(
                "KUBECACHEDIR",
                self.dir
                    .join(format!("kubectl-cache-{}", std::process::id())),
            )
            .current_dir(repo_root())
            .output()
            .expect("run tool")
    }

    /// Runs kubectl against this control plane.
    pub fn kubectl(&self, args: &[&str]) -> Output {
        let path = format!(
            "{}:{}",
            tool("kubectl").parent().unwrap().display(),
            std::env::var("PATH").unwrap_or_default()
        );
        Command::new(tool("kubectl"))
            .args(args)
            .env("KUBECONFIG", self.kubeconfig())
            // A fresh discovery cache: a stale one hides CRDs installed a moment ago.
            .env(
                "KUBECACHEDIR",
                self.dir
                    .join(format!("kubectl-cache-{}", std::process::id())),
            )
            .env("PATH", path)
            .current_dir(repo_root())
            .output()
            .expect("run kubectl")
    }

    /// Server-side applies our CRDs and waits until they are served.
    pub fn install_crds(&self) -> Result<()> {
        let out = self.kubectl(&[
            "apply",
            "--server-side",
            "--force-conflicts",
            "-f",
            "manifests/crds/",
        ]);
        if !out.status.success() {
            bail!(
                "kubectl apply crds: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        let out = self.kubectl(&[
            "wait",
            "--for=condition=Established",
            "--timeout=60s",
            "crd/robots.fleet.lekiwi.io",
            "crd/robotdeployments.fleet.lekiwi.io",
        ]);
        if !out.status.success() {
            bail!(
                "CRDs not established: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        Ok(())
    }
}

impl Drop for ControlPlane {
    fn drop(&mut self) {
        if self.private.is_some() {
            let _ = self.script(&["down", "--purge"]);
        }
    }
}

/// Creates a namespace of the test's own. Namespaces are not deleted: without a
/// controller-manager they would stay Terminating anyway, and `down --purge` removes all.
pub async fn namespace(client: &Client, prefix: &str) -> Result<String> {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)?
        .subsec_nanos();
    let name = format!(
        "{prefix}-{:x}{:x}",
        std::process::id() % 4096,
        nanos % 65536
    );
    let ns = Namespace {
        metadata: ObjectMeta {
            name: Some(name.clone()),
            ..ObjectMeta::default()
        },
        ..Namespace::default()
    };
    Api::<Namespace>::all(client.clone())
        .create(&PostParams::default(), &ns)
        .await?;
    Ok(name)
}

/// A free loopback port.
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("free port")
}

/// Polls `f` every 100 ms until it returns `Some`, or fails after `timeout` with `what`.
pub async fn wait_for<T, F, Fut>(what: &str, timeout: Duration, mut f: F) -> Result<T>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Option<T>>,
{
    let start = Instant::now();
    loop {
        if let Some(v) = f().await {
            return Ok(v);
        }
        if start.elapsed() > timeout {
            bail!("timed out after {timeout:?} waiting for {what}");
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// A `lekiwi-operator` process; SIGKILLed when dropped.
pub struct OperatorProcess {
    child: Child,
    /// Address of its HTTP endpoints.
    pub http_port: u16,
    /// Port of its agent gateway.
    pub gateway_port: u16,
    /// Its SQLite event store.
    pub store_path: PathBuf,
    /// Its log file.
    pub log: PathBuf,
    args: Vec<String>,
    env: Vec<(String, String)>,
}

impl OperatorProcess {
    /// Starts an operator that watches only `namespace` and keeps its Leases there.
    pub fn start(
        cp: &ControlPlane,
        namespace: &str,
        identity: &str,
        extra: &[&str],
    ) -> Result<Self> {
        Self::start_with_kubeconfig(&cp.kubeconfig(), namespace, identity, extra)
    }

    /// As [`Self::start`], with extra environment variables.
    pub fn start_with_env(
        cp: &ControlPlane,
        namespace: &str,
        identity: &str,
        extra: &[&str],
        env: &[(&str, &str)],
    ) -> Result<Self> {
        Self::spawn(&cp.kubeconfig(), namespace, identity, extra, env)
    }

    /// As [`Self::start`], with other credentials.
    pub fn start_with_kubeconfig(
        kubeconfig: &Path,
        namespace: &str,
        identity: &str,
        extra: &[&str],
    ) -> Result<Self> {
        Self::spawn(kubeconfig, namespace, identity, extra, &[])
    }

    fn spawn(
        kubeconfig: &Path,
        namespace: &str,
        identity: &str,
        extra: &[&str],
        env: &[(&str, &str)],
    ) -> Result<Self> {
        let env: Vec<(String, String)> = env
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        let http_port = free_port();
        let gateway_port = free_port();
        let log = log_dir().join(format!("{namespace}-{identity}.log"));
        let store_path = log_dir().join(format!("{namespace}-{identity}.db"));
        let _ = std::fs::remove_file(&store_path);
        std::fs::File::create(&log)?;
        let mut args: Vec<String> = Vec::new();
        let mut push = |a: &[&str]| args.extend(a.iter().map(|s| s.to_string()));
        push(&["--kubeconfig", kubeconfig.to_str().unwrap()]);
        push(&[
            "--namespace",
            namespace,
            "--watch-namespace",
            namespace,
            "--identity",
            identity,
        ]);
        push(&["--http-addr", &format!("127.0.0.1:{http_port}")]);
        push(&["--gateway-addr", &format!("127.0.0.1:{gateway_port}")]);
        push(&["--gateway-name", &format!("gw-{identity}")]);
        push(&["--store-url", &format!("sqlite://{}", store_path.display())]);
        push(&[
            "--lease-duration-seconds",
            "4",
            "--lease-retry-seconds",
            "1",
        ]);
        if !extra.contains(&"--blob-dir") {
            // Never the machine's /var/lib/lekiwi: each operator gets its own blob store.
            let blobs = log_dir().join(format!("{namespace}-{identity}-blobs"));
            push(&["--blob-dir", blobs.to_str().unwrap()]);
        }
        push(extra);
        let child = spawn_operator(&args, &env, &log)?;
        Ok(Self {
            child,
            http_port,
            gateway_port,
            store_path,
            log,
            args,
            env,
        })
    }

    /// Starts it again with the same ports, store and flags (after [`Self::kill`] or
    /// [`Self::terminate`]); the log is appended to.
    pub fn restart(&mut self) -> Result<()> {
        self.kill();
        self.child = spawn_operator(&self.args, &self.env, &self.log)?;
        Ok(())
    }

    /// Waits until `/readyz` answers 200.
    pub async fn wait_ready(&mut self) -> Result<()> {
        let port = self.http_port;
        let start = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait()? {
                bail!(
                    "operator exited with {status} before it was ready; log:\n{}",
                    self.log_text()
                );
            }
            if let Ok((200, _)) = http_get(port, "/readyz").await {
                return Ok(());
            }
            if start.elapsed() > Duration::from_secs(30) {
                bail!("operator not ready in 30s; log:\n{}", self.log_text());
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    /// The process's output so far.
    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// The raw `/metrics` text.
    pub async fn metrics(&self) -> Result<String> {
        let (code, body) = http_get(self.http_port, "/metrics").await?;
        if code != 200 {
            bail!("/metrics answered {code}");
        }
        Ok(body)
    }

    /// One sample's value from `/metrics`, by its full series name, e.g. `x_total{a="b"}`.
    pub async fn metric(&self, series: &str) -> Option<f64> {
        let text = self.metrics().await.ok()?;
        sample(&text, series)
    }

    /// SIGKILL: a crash, nothing is cleaned up.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// SIGTERM, then waits for the exit.
    pub fn terminate(&mut self) -> Result<std::process::ExitStatus> {
        Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status()?;
        let start = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait()? {
                return Ok(status);
            }
            if start.elapsed() > Duration::from_secs(20) {
                bail!("operator did not exit within 20s of SIGTERM");
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Whether the process is still running.
    pub fn running(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }
}

fn spawn_operator(args: &[String], env: &[(String, String)], log: &Path) -> Result<Child> {
    let file = std::fs::OpenOptions::new()
        .append(true)
        .create(true)
        .open(log)?;
    Command::new(bin("lekiwi-operator"))
        .args(args)
        .env("RUST_LOG", "info,kube=warn,lekiwi_operator=debug")
        .envs(env.iter().map(|(k, v)| (k, v)))
        .stdin(Stdio::null())
        .stdout(file.try_clone()?)
        .stderr(file)
        .spawn()
        .context("spawn lekiwi-operator")
}

impl Drop for OperatorProcess {
    fn drop(&mut self) {
        self.kill();
    }
}

/// Finds one sample in Prometheus text by its exact series name.
pub fn sample(text: &str, series: &str) -> Option<f64> {
    text.lines().find_map(|l| {
        l.strip_prefix(series)
            .and_then(|rest| rest.strip_prefix(' '))
            .and_then(|v| v.trim().parse().ok())
    })
}

/// A minimal HTTP/1.0 GET against 127.0.0.1: status code and body.
pub async fn http_get(port: u16, path: &str) -> Result<(u16, String)> {
    let mut stream = tokio::net::TcpStream::connect(("127.0.0.1", port)).await?;
    stream
        .write_all(format!("GET {path} HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n").as_bytes())
        .await?;
    let mut buf = Vec::new();
    stream.read_to_end(&mut buf).await?;
    let text = String::from_utf8_lossy(&buf).into_owned();
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let code = head
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    Ok((code, body.to_owned()))
}

/// Field manager the real gateway uses for the presence fields of Robot status.
pub const GATEWAY_FIELD_MANAGER: &str = lekiwi_crds::contract::managers::GATEWAY;

/// Plays the gateway's part until the gateway exists: renews a gateway Lease and writes the
/// presence fields of Robot status by server-side apply under the gateway's field manager,
/// always the whole set, as the real gateway will.
pub struct GatewayStandIn {
    /// The gateway's identity (and Lease name).
    pub name: String,
    robots: Api<Robot>,
    leases: Api<Lease>,
    renew: Option<tokio::task::JoinHandle<()>>,
    presence: std::collections::HashMap<String, Value>,
}

impl GatewayStandIn {
    /// Creates the gateway's Lease in `namespace` and renews it every second.
    pub async fn start(
        client: &Client,
        namespace: &str,
        name: &str,
        lease_seconds: i32,
    ) -> Result<Self> {
        let leases: Api<Lease> = Api::namespaced(client.clone(), namespace);
        let mut me = Self {
            name: name.to_owned(),
            robots: Api::namespaced(client.clone(), namespace),
            leases,
            renew: None,
            presence: Default::default(),
        };
        me.renew_lease(lease_seconds).await?;
        me.resume_renewing(lease_seconds);
        Ok(me)
    }

    async fn renew_lease(&self, lease_seconds: i32) -> Result<()> {
        renew(&self.leases, &self.name, lease_seconds).await
    }

    /// Starts renewing again after [`Self::stop_renewing`].
    pub fn resume_renewing(&mut self, lease_seconds: i32) {
        let (leases, name) = (self.leases.clone(), self.name.clone());
        self.renew = Some(tokio::spawn(async move {
            loop {
                let _ = renew(&leases, &name, lease_seconds).await;
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        }));
    }

    /// Stops renewing the Lease, as a crashed gateway would.
    pub fn stop_renewing(&mut self) {
        if let Some(t) = self.renew.take() {
            t.abort();
        }
    }

    async fn write(&mut self, robot: &str, fields: Value) -> Result<()> {
        let entry = self
            .presence
            .entry(robot.to_owned())
            .or_insert_with(|| json!({}));
        for (k, v) in fields.as_object().cloned().unwrap_or_default() {
            entry[k] = v;
        }
        let patch = json!({ "apiVersion": "fleet.lekiwi.io/v1alpha1", "kind": "Robot", "status": entry.clone() });
        self.robots
            .patch_status(
                robot,
                &PatchParams::apply(GATEWAY_FIELD_MANAGER).force(),
                &Patch::Apply(&patch),
            )
            .await
            .with_context(|| format!("gateway stand-in: patch status of {robot}"))?;
        Ok(())
    }

    /// An agent connects: presence facts as the gateway would record them.
    pub async fn connect(&mut self, robot: &str) -> Result<()> {
        let now = now();
        let gateway = self.name.clone();
        self.write(
            robot,
            json!({
                "connected": true,
                "gateway": gateway,
                "protocol": "websocket",
                "connectedSince": now,
                "lastHeartbeatTime": now,
                "agentVersion": "0.1.0",
                "address": "127.0.0.1",
                "health": { "healthy": true },
                "teleoperation": { "active": false },
                "system": { "os": "Debian GNU/Linux 12 (bookworm)", "arch": "aarch64", "cpus": 4, "memoryBytes": 8_589_934_592u64 },
                "telemetry": { "cpuPercent": 12.5, "memoryPercent": 31.0, "temperatureCelsius": 48.2 }
            }),
        )
        .await
    }

    /// A heartbeat worth recording.
    pub async fn heartbeat(&mut self, robot: &str) -> Result<()> {
        self.write(robot, json!({ "lastHeartbeatTime": now() }))
            .await
    }

    /// Any other presence fields, e.g. `{"teleoperation": {"active": true}}`.
    pub async fn report(&mut self, robot: &str, fields: Value) -> Result<()> {
        self.write(robot, fields).await
    }

    /// The agent's connection closed.
    pub async fn disconnect(&mut self, robot: &str) -> Result<()> {
        self.write(robot, json!({ "connected": false })).await
    }
}

impl Drop for GatewayStandIn {
    fn drop(&mut self) {
        self.stop_renewing();
    }
}

async fn renew(leases: &Api<Lease>, name: &str, lease_seconds: i32) -> Result<()> {
    let lease = Lease {
        metadata: ObjectMeta {
            name: Some(name.to_owned()),
            ..ObjectMeta::default()
        },
        spec: Some(LeaseSpec {
            holder_identity: Some(name.to_owned()),
            lease_duration_seconds: Some(lease_seconds),
            renew_time: Some(MicroTime(Timestamp::now())),
            ..LeaseSpec::default()
        }),
    };
    leases
        .patch(
            name,
            &PatchParams::apply(GATEWAY_FIELD_MANAGER).force(),
            &Patch::Apply(&lease),
        )
        .await?;
    Ok(())
}

/// Now, as a Kubernetes `Time` string (second precision).
pub fn now() -> String {
    Timestamp::now()
        .round(jiff::Unit::Second)
        .unwrap_or_else(|_| Timestamp::now())
        .strftime("%Y-%m-%dT%H:%M:%SZ")
        .to_string()
}

/// Reads a robot.
pub async fn get_robot(client: &Client, namespace: &str, name: &str) -> Result<Robot> {
    Ok(Api::<Robot>::namespaced(client.clone(), namespace)
        .get(name)
        .await?)
}

/// Creates a robot from a minimal spec.
pub async fn create_robot(
    client: &Client,
    namespace: &str,
    name: &str,
    labels: &[(&str, &str)],
) -> Result<Robot> {
    let labels: serde_json::Map<String, Value> = labels
        .iter()
        .map(|(k, v)| (k.to_string(), json!(v)))
        .collect();
    let robot: Robot = serde_json::from_value(json!({
        "apiVersion": "fleet.lekiwi.io/v1alpha1",
        "kind": "Robot",
        "metadata": { "name": name, "labels": labels },
        "spec": { "displayName": format!("Test robot {name}") }
    }))?;
    Ok(Api::<Robot>::namespaced(client.clone(), namespace)
        .create(&PostParams::default(), &robot)
        .await?)
}

/// Reads a file under the repository root.
pub fn repo_file(path: impl AsRef<Path>) -> String {
    std::fs::read_to_string(repo_root().join(path)).expect("read repo file")
}

/// The gateway's WebSocket URL of an operator process.
pub fn gateway_url(op: &OperatorProcess) -> String {
    format!(
        "ws://127.0.0.1:{}{}",
        op.gateway_port,
        lekiwi_protocol::AGENT_PATH
    )
}

/// Creates a fleet enrollment token for `namespace` (stored as a hash) and returns it.
pub async fn enrollment_token(client: &Client, namespace: &str) -> Result<String> {
    use k8s_openapi::api::core::v1::Secret;
    let token = lekiwi_crds::contract::new_token("lke_");
    let secret = lekiwi_crds::contract::enrollment_token_secret(&token);
    Api::<Secret>::namespaced(client.clone(), namespace)
        .create(&PostParams::default(), &secret)
        .await?;
    Ok(token)
}

/// A `hello` as a real agent sends it.
pub fn hello() -> lekiwi_protocol::AgentMessage {
    lekiwi_protocol::AgentMessage::Hello {
        protocol_version: lekiwi_protocol::PROTOCOL_VERSION,
        agent_version: "0.1.0-test".into(),
        system: lekiwi_protocol::SystemFacts {
            arch: Some("aarch64".into()),
            cpus: Some(4),
            ..Default::default()
        },
        current_release: None,
        last_acked_seq: None,
        health: Some(lekiwi_protocol::Health {
            healthy: true,
            message: None,
        }),
        teleoperation: Some(lekiwi_protocol::Teleoperation {
            active: false,
            score: Some(0.0),
        }),
    }
}

/// A plain HTTP/1.1 GET with headers: status, response headers (lowercase names) and body.
pub async fn http_get_with(
    port: u16,
    path: &str,
    headers: &[(&str, &str)],
) -> Result<(u16, Vec<(String, String)>, String)> {
    let mut stream = tokio::net::TcpStream::connect(("127.0.0.1", port)).await?;
    let mut req = format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n");
    for (k, v) in headers {
        req.push_str(&format!("{k}: {v}\r\n"));
    }
    req.push_str("\r\n");
    stream.write_all(req.as_bytes()).await?;
    let mut buf = Vec::new();
    stream.read_to_end(&mut buf).await?;
    let text = String::from_utf8_lossy(&buf).into_owned();
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let mut lines = head.lines();
    let code = lines
        .next()
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let hdrs = lines
        .filter_map(|l| {
            l.split_once(':')
                .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_owned()))
        })
        .collect();
    Ok((code, hdrs, body.to_owned()))
}

/// Makes, with openssl, a self-signed CA (`ca.crt`) and a server certificate it signed for
/// 127.0.0.1 and localhost (`tls.crt`, `tls.key`) in `dir`.
pub fn test_ca(dir: &Path) -> Result<()> {
    let d = dir.display();
    let sh = |cmd: String| -> Result<()> {
        let out = Command::new("bash").arg("-c").arg(&cmd).output()?;
        if !out.status.success() {
            bail!("{cmd}: {}", String::from_utf8_lossy(&out.stderr));
        }
        Ok(())
    };
    sh(format!(
        "openssl req -x509 -newkey rsa:2048 -nodes -days 1 -subj /CN=lekiwi-test-ca -keyout {d}/ca.key -out {d}/ca.crt"
    ))?;
    sh(format!(
        "openssl req -newkey rsa:2048 -nodes -subj /CN=127.0.0.1 -keyout {d}/tls.key -out {d}/tls.csr"
    ))?;
    std::fs::write(
        dir.join("ext"),
        "subjectAltName=IP:127.0.0.1,DNS:localhost\nbasicConstraints=CA:FALSE\n",
    )?;
    sh(format!(
        "openssl x509 -req -in {d}/tls.csr -CA {d}/ca.crt -CAkey {d}/ca.key -CAcreateserial -days 1 -extfile {d}/ext -out {d}/tls.crt"
    ))
}

/// A real `lekiwi-agent` process with its own state directory, for tests.
pub struct AgentProcess {
    child: Child,
    /// Its state directory (token, outbox).
    pub state_dir: PathBuf,
    /// Port of its local status endpoint.
    pub status_port: u16,
    /// Its log file (JSON lines).
    pub log: PathBuf,
    args: Vec<String>,
}

impl AgentProcess {
    /// Starts an agent for `robot` (`namespace/name`) against `gateway`, enrolling with the
    /// token in `enrollment_token_file` when its state directory has no credentials yet. Quick
    /// test settings: backoff 200 ms to 2 s, teleoperation checks every 0.5 s, no mDNS; `extra`
    /// flags are appended and must not repeat one of these (the agent refuses repeated flags).
    pub fn start(
        gateway: &str,
        robot: &str,
        enrollment_token_file: &Path,
        state_dir: &Path,
        extra: &[&str],
    ) -> Result<Self> {
        let status_port = free_port();
        let safe = robot.replace('/', "_");
        let log = log_dir().join(format!(
            "agent-{safe}-{}.log",
            state_dir
                .file_name()
                .and_then(|n| n.to_str())
                .unwrap_or("state")
        ));
        std::fs::File::create(&log)?;
        let mut args: Vec<String> = [
            "--config",
            "/nonexistent/lekiwi-agent.yaml",
            "--gateway",
            gateway,
            "--robot-name",
            robot,
            "--enrollment-token-file",
            enrollment_token_file.to_str().unwrap(),
            "--state-dir",
            state_dir.to_str().unwrap(),
            "--status-listen",
            &format!("127.0.0.1:{status_port}"),
            "--mdns",
            "false",
            "--backoff-initial-ms",
            "200",
            "--backoff-max-ms",
            "2000",
            "--connect-timeout-s",
            "5",
            "--teleop-interval-s",
            "0.5",
            "--log-format",
            "json",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        args.extend(extra.iter().map(|s| s.to_string()));
        let child = spawn_agent(&args, &log)?;
        Ok(Self {
            child,
            state_dir: state_dir.to_owned(),
            status_port,
            log,
            args,
        })
    }

    /// SIGKILL: a crash or a power cut, nothing is cleaned up.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// SIGTERM and wait for the exit status.
    pub fn terminate(&mut self) -> Result<std::process::ExitStatus> {
        Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status()?;
        let start = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait()? {
                return Ok(status);
            }
            if start.elapsed() > Duration::from_secs(10) {
                bail!("agent did not exit within 10s of SIGTERM");
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Starts it again with the same flags and state directory (log appended).
    pub fn restart(&mut self) -> Result<()> {
        self.kill();
        self.child = spawn_agent(&self.args, &self.log)?;
        Ok(())
    }

    /// Its process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The JSON log lines so far.
    pub fn log_lines(&self) -> Vec<Value> {
        std::fs::read_to_string(&self.log)
            .unwrap_or_default()
            .lines()
            .filter_map(|l| serde_json::from_str(l).ok())
            .collect()
    }

    /// The log as text, for failure messages.
    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// `GET /status` of its local endpoint.
    pub async fn status(&self) -> Result<Value> {
        let (code, body) = http_get(self.status_port, "/status").await?;
        if code != 200 {
            bail!("/status answered {code}: {body}");
        }
        Ok(serde_json::from_str(&body)?)
    }

    /// Queues an event with `lekiwi-agent event` (works whether or not the agent runs) and
    /// returns its sequence number.
    pub fn emit(&self, kind: &str, message: &str, data: &Value) -> Result<u64> {
        let out = Command::new(bin("lekiwi-agent"))
            .args(["--config", "/nonexistent/lekiwi-agent.yaml"])
            .args(["--state-dir", self.state_dir.to_str().unwrap()])
            .args(["event", "--kind", kind, "--message", message])
            .args(["--data", &data.to_string()])
            .output()?;
        if !out.status.success() {
            bail!(
                "lekiwi-agent event failed: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        Ok(String::from_utf8_lossy(&out.stdout).trim().parse()?)
    }
}

fn spawn_agent(args: &[String], log: &Path) -> Result<Child> {
    let file = std::fs::OpenOptions::new()
        .append(true)
        .create(true)
        .open(log)?;
    Command::new(bin("lekiwi-agent"))
        .args(args)
        .env("RUST_LOG", "info,lekiwi_agent=debug")
        .stdin(Stdio::null())
        .stdout(file.try_clone()?)
        .stderr(file)
        .spawn()
        .context("spawn lekiwi-agent")
}

impl Drop for AgentProcess {
    fn drop(&mut self) {
        self.kill();
    }
}
