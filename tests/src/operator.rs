//! A `lekiwi-operator` process of a test's own: its ports, store, log and metrics.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Result, bail};

use crate::control_plane::ControlPlane;
use crate::http::{http_get, sample};
use crate::process::{ChildProcess, Launch};
use crate::{free_ports, log_dir};

/// A `lekiwi-operator` process; SIGKILLed when dropped.
pub struct OperatorProcess {
    process: ChildProcess,
    /// Port of its HTTP endpoints (`/readyz`, `/metrics`, the API).
    pub http_port: u16,
    /// Port of its agent gateway.
    pub gateway_port: u16,
    /// Its SQLite event store (removed before the first start).
    pub store_path: PathBuf,
    /// Its log file, appended to across restarts.
    pub log: PathBuf,
}

/// What a test chose for one operator: the rest (ports, store, blob dir, quick Lease timings)
/// the harness fills in.
struct OperatorSpec<'a> {
    kubeconfig: &'a Path,
    namespace: &'a str,
    identity: &'a str,
    extra: &'a [&'a str],
    env: &'a [(&'a str, &'a str)],
    /// Watch every namespace (no `--watch-namespace`): only on a private control plane, where
    /// no other test's robots live.
    cluster_wide: bool,
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
        Self::spawn(OperatorSpec {
            kubeconfig: &cp.kubeconfig(),
            namespace,
            identity,
            extra,
            env,
            cluster_wide: false,
        })
    }

    /// As [`Self::start`], with other credentials.
    pub fn start_with_kubeconfig(
        kubeconfig: &Path,
        namespace: &str,
        identity: &str,
        extra: &[&str],
    ) -> Result<Self> {
        Self::spawn(OperatorSpec {
            kubeconfig,
            namespace,
            identity,
            extra,
            env: &[],
            cluster_wide: false,
        })
    }

    /// As [`Self::start`], watching every namespace (its Leases still live in `namespace`).
    /// Only for a [`ControlPlane::private`]: on the shared one it would act on other tests'
    /// robots.
    pub fn start_cluster_wide(
        cp: &ControlPlane,
        namespace: &str,
        identity: &str,
        extra: &[&str],
    ) -> Result<Self> {
        Self::spawn(OperatorSpec {
            kubeconfig: &cp.kubeconfig(),
            namespace,
            identity,
            extra,
            env: &[],
            cluster_wide: true,
        })
    }

    fn spawn(spec: OperatorSpec<'_>) -> Result<Self> {
        let (namespace, identity) = (spec.namespace, spec.identity);
        let [http_port, gateway_port] = free_ports(2)[..] else {
            unreachable!("free_ports returns as many as asked")
        };
        let log = log_dir().join(format!("{namespace}-{identity}.log"));
        let store_path = log_dir().join(format!("{namespace}-{identity}.db"));
        let _ = std::fs::remove_file(&store_path);
        std::fs::File::create(&log)?;
        let args = operator_args(&spec, http_port, gateway_port, &store_path);
        let process = ChildProcess::spawn(Launch {
            binary: "lekiwi-operator",
            what: "operator",
            rust_log: "info,kube=warn,lekiwi_operator=debug,lekiwi_gateway=debug,lekiwi_presence=debug",
            args,
            env: spec
                .env
                .iter()
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect(),
            log: log.clone(),
            term_deadline: Duration::from_secs(20),
            term_poll: Duration::from_millis(50),
        })?;
        Ok(Self {
            process,
            http_port,
            gateway_port,
            store_path,
            log,
        })
    }

    /// Opens this operator's SQLite event store beside it, to check what the gateway stored.
    pub async fn event_store(&self) -> Result<lekiwi_event_store::Store> {
        let url = format!("sqlite://{}", self.store_path.display());
        Ok(lekiwi_event_store::Store::connect(&url).await?)
    }

    /// Starts it again with the same ports, store and flags (after [`Self::kill`] or
    /// [`Self::terminate`]); the log is appended to.
    pub fn restart(&mut self) -> Result<()> {
        self.process.restart()
    }

    /// Waits until `/readyz` answers 200.
    pub async fn wait_ready(&mut self) -> Result<()> {
        let port = self.http_port;
        let start = Instant::now();
        loop {
            if let Some(status) = self.process.exited()? {
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
        self.process.log_text()
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
        self.process.kill();
    }

    /// SIGTERM, then waits (up to 20 s) for the exit.
    pub fn terminate(&mut self) -> Result<std::process::ExitStatus> {
        self.process.terminate()
    }

    /// Its process id (for reading `/proc/<pid>/status`).
    pub fn pid(&self) -> u32 {
        self.process.pid()
    }

    /// Whether the process is still running.
    pub fn running(&mut self) -> bool {
        self.process.running()
    }
}

/// The operator's flags: scoped to the test's namespace, on its own ports and store, with Lease
/// timings short enough for tests, then the test's `extra` flags.
fn operator_args(
    spec: &OperatorSpec<'_>,
    http_port: u16,
    gateway_port: u16,
    store_path: &Path,
) -> Vec<String> {
    let (namespace, identity, extra) = (spec.namespace, spec.identity, spec.extra);
    let mut args: Vec<String> = Vec::new();
    let mut push = |a: &[&str]| args.extend(a.iter().map(|s| s.to_string()));
    push(&["--kubeconfig", spec.kubeconfig.to_str().unwrap()]);
    push(&["--namespace", namespace, "--identity", identity]);
    if !spec.cluster_wide {
        push(&["--watch-namespace", namespace]);
    }
    push(&["--http-addr", &format!("127.0.0.1:{http_port}")]);
    push(&["--gateway-addr", &format!("127.0.0.1:{gateway_port}")]);
    push(&["--gateway-name", &format!("gw-{identity}")]);
    if !extra.iter().any(|a| a.starts_with("--store-url")) {
        // Its own SQLite store beside the log, unless the test names one (e.g. PostgreSQL
        // shared between replicas).
        push(&["--store-url", &format!("sqlite://{}", store_path.display())]);
    }
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
    args
}

/// A ready operator for gateway tests: robots stay Online through a minute of silence
/// (`--heartbeat-grace-seconds 60`), so only what a test does changes their phase.
pub async fn gateway_operator(
    cp: &ControlPlane,
    namespace: &str,
    identity: &str,
    extra: &[&str],
) -> Result<OperatorProcess> {
    let mut args = vec!["--heartbeat-grace-seconds", "60"];
    args.extend_from_slice(extra);
    let mut op = OperatorProcess::start(cp, namespace, identity, &args)?;
    op.wait_ready().await?;
    Ok(op)
}
