//! Test harness: the shared local control plane and private ones for disruptive tests
//! ([`control_plane`]), the single-node cluster whose Pods really run ([`cluster`]), our operator, agent and `lekiwi-fleet` processes ([`operator`],
//! [`agent`], [`fleet_process`], [`sim_process`]), a stand-in for the gateway's cluster writes ([`stand_in`]),
//! fleet fixtures and waits ([`fleet`]), RBAC'd users ([`users`]) and bare HTTP helpers
//! ([`http`]), re-exported here so tests import them from the crate root; robots on other hosts
//! made of network namespaces are in [`netns`]; a GraphQL WebSocket client is [`graphql`]; a stand-in for systemd is [`supervisor`];
//! a headless browser is [`browser`]; emulated Raspberry Pi 5s running the arm64 agent are in
//! [`pi`].

pub mod agent;
pub mod agent_fleet;
pub mod blobs;
pub mod browser;
pub mod cluster;
pub mod control_plane;
pub mod fleet;
pub mod fleet_process;
pub mod graphql;
pub mod http;
pub mod lag_proxy;
pub mod markdown;
pub mod netns;
pub mod operator;
pub mod pi;
pub mod postgres;
mod process;
pub mod sim_process;
mod site;
pub mod stand_in;
pub mod supervisor;
pub mod users;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use anyhow::{Result, bail};
use jiff::Timestamp;

pub use agent::{AgentProcess, connect_agent, heartbeat, hello, recv};
pub use control_plane::{ControlPlane, namespace};
pub use fleet::{
    create_robot, enrollment_token, enrollment_token_file, gateway_url, get_robot, robot_token,
    rollout_finished, set_agent, set_release, test_strategy, wait_online, wait_phase,
};
pub use fleet_process::{FleetProcess, FleetSpec};
pub use http::{http_get, http_get_with, http_request, sample, test_ca};
pub use operator::{OperatorProcess, gateway_operator};
pub use sim_process::{SimProcess, SimSpec};
pub use site::OperatorSite;
pub use stand_in::{GATEWAY_FIELD_MANAGER, GatewayStandIn};
pub use users::{account, chart_roles, chart_roles_named};

/// The repository root.
pub fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .canonicalize()
        .expect("repo root")
}

/// The cache `scripts/setup.sh` fills: `$LEKIWI_CACHE`, by default `~/.cache/lekiwi`.
pub fn cache_dir() -> PathBuf {
    let home = std::env::var("HOME").unwrap_or_else(|_| "/root".into());
    let cache = std::env::var("LEKIWI_CACHE").unwrap_or_else(|_| format!("{home}/.cache/lekiwi"));
    PathBuf::from(cache)
}

/// The items of a `List` as `kubectl lekiwi -o json` prints one (as kubectl does), checked
/// to be a `List`.
pub fn list_items<T: serde::de::DeserializeOwned>(
    json: impl AsRef<[u8]>,
) -> anyhow::Result<Vec<T>> {
    let mut list: serde_json::Value = serde_json::from_slice(json.as_ref())?;
    anyhow::ensure!(
        list["apiVersion"] == "v1" && list["kind"] == "List",
        "not a List: {list}"
    );
    Ok(serde_json::from_value(list["items"].take())?)
}

/// kubectl and helm as installed by `scripts/setup.sh`.
pub fn tool(name: &str) -> PathBuf {
    cache_dir().join("bin").join(name)
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

/// Pushes `dir` as release `version` with the real `kubectl lekiwi release push` to `server`
/// (`http://` or `https://`, trusting `ca` when given), as `kubeconfig`'s user; the release it
/// printed.
pub fn push_release(
    kubeconfig: &Path,
    namespace: &str,
    server: &str,
    ca: Option<&Path>,
    dir: &Path,
    version: &str,
) -> Result<lekiwi_crds::ReleaseRef> {
    let mut cmd = Command::new(bin("kubectl-lekiwi"));
    cmd.arg("--kubeconfig")
        .arg(kubeconfig)
        .args(["-n", namespace, "release", "push"])
        .arg(dir)
        .args(["--version", version, "--server", server])
        .env_remove("LEKIWI_SERVER");
    if let Some(ca) = ca {
        cmd.arg("--certificate-authority").arg(ca);
    }
    let out = cmd.output()?;
    if !out.status.success() {
        bail!(
            "release push of {version} failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(lekiwi_crds::ReleaseRef {
        version: version.into(),
        digest: String::from_utf8_lossy(&out.stdout).trim().into(),
    })
}

/// Pushes the agent build `file` as `version` for `arch` with `kubectl lekiwi agent push`
/// (over https:// when `ca` is given); its digest.
pub fn push_agent(
    kubeconfig: &Path,
    namespace: &str,
    server: &str,
    ca: Option<&Path>,
    file: &Path,
    version: &str,
    arch: &str,
) -> Result<String> {
    let mut cmd = Command::new(bin("kubectl-lekiwi"));
    cmd.arg("--kubeconfig")
        .arg(kubeconfig)
        .args([
            "-n",
            namespace,
            "agent",
            "push",
            "--version",
            version,
            "--arch",
            arch,
        ])
        .arg(file)
        .args(["--server", server])
        .env_remove("LEKIWI_SERVER");
    if let Some(ca) = ca {
        cmd.arg("--certificate-authority").arg(ca);
    }
    let out = cmd.output()?;
    let digest = String::from_utf8_lossy(&out.stdout).trim().to_owned();
    if !out.status.success() || !digest.starts_with("sha256:") {
        bail!(
            "agent push of {version} failed: {digest}\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(digest)
}

/// A directory for logs of processes a test starts, kept after the run for debugging.
pub fn log_dir() -> PathBuf {
    let dir = repo_root().join("target/test-logs");
    std::fs::create_dir_all(&dir).expect("create log dir");
    dir
}

/// `count` distinct free loopback ports from `scripts/lib/free-ports.py`, which picks them outside
/// the kernel's ephemeral range: a port the kernel may give a client socket can be taken by any
/// of the many connections parallel tests open between the pick and the server's bind (a CI
/// flake: an operator's "Address already in use").
pub fn free_ports(count: usize) -> Vec<u16> {
    let out = Command::new("python3")
        .arg(repo_root().join("scripts/lib/free-ports.py"))
        .arg(count.to_string())
        .output()
        .expect("run scripts/lib/free-ports.py");
    assert!(out.status.success(), "scripts/lib/free-ports.py: {out:?}");
    let ports: Vec<u16> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| l.trim().parse().expect("a port number"))
        .collect();
    assert_eq!(ports.len(), count, "scripts/lib/free-ports.py {count}");
    ports
}

/// One free loopback port (see [`free_ports`]).
pub fn free_port() -> u16 {
    free_ports(1)[0]
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

/// Now, as a Kubernetes `Time` string (second precision).
pub fn now() -> String {
    Timestamp::now()
        .round(jiff::Unit::Second)
        .unwrap_or_else(|_| Timestamp::now())
        .strftime("%Y-%m-%dT%H:%M:%SZ")
        .to_string()
}

/// Reads a file under the repository root.
pub fn repo_file(path: impl AsRef<Path>) -> String {
    std::fs::read_to_string(repo_root().join(path)).expect("read repo file")
}
