//! The single-node cluster whose Pods really run (`scripts/cluster.sh`): started once per test
//! process and reused across runs, images built with `scripts/oci.py` and imported into its
//! containerd, and plain HTTP to the in-machine addresses (Pod IPs, ClusterIPs, NodePorts).

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::OnceLock;

use anyhow::{Context as _, Result, bail};
use kube::Client;
use kube::config::{KubeConfigOptions, Kubeconfig};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

use crate::{repo_root, tool};

/// A running cluster managed by `scripts/cluster.sh`, described by its `env` output.
pub struct Cluster {
    /// State directory (`LEKIWI_CLUSTER_DIR`).
    pub dir: PathBuf,
    /// Admin kubeconfig.
    pub kubeconfig: PathBuf,
    /// The node's IP: the API server, the kubelet and NodePorts listen there.
    pub node_ip: String,
    /// containerd's socket, for `ctr images import`.
    pub containerd: PathBuf,
}

impl Cluster {
    /// The cluster shared by every test (`cluster.sh up`: a no-op when it is already healthy).
    /// Panics with the script's output when the node cannot run: a test never skips silently.
    pub fn shared() -> &'static Cluster {
        static SHARED: OnceLock<Cluster> = OnceLock::new();
        SHARED.get_or_init(|| {
            script(&["up"]).expect("scripts/cluster.sh up");
            let env = String::from_utf8_lossy(&script(&["env"]).expect("cluster.sh env").stdout)
                .into_owned();
            let var = |name: &str| {
                env.lines()
                    .find_map(|l| l.strip_prefix(&format!("export {name}=")))
                    .map(|v| v.trim_matches(['\'', '"']).to_owned())
                    .unwrap_or_else(|| panic!("cluster.sh env prints no {name}:\n{env}"))
            };
            Cluster {
                dir: var("LEKIWI_CLUSTER_DIR").into(),
                kubeconfig: var("KUBECONFIG").into(),
                node_ip: var("LEKIWI_NODE_IP"),
                containerd: var("CONTAINERD_ADDRESS").into(),
            }
        })
    }

    /// A client with admin rights.
    pub async fn client(&self) -> Result<Client> {
        let kc = Kubeconfig::read_from(&self.kubeconfig)?;
        let config =
            kube::Config::from_custom_kubeconfig(kc, &KubeConfigOptions::default()).await?;
        Ok(Client::try_from(config)?)
    }

    /// Runs kubectl from the cache against this cluster; fails with its output unless it
    /// succeeds, else returns its stdout.
    pub fn kubectl(&self, args: &[&str]) -> Result<String> {
        let out = Command::new(tool("kubectl"))
            .args(args)
            .env("KUBECONFIG", &self.kubeconfig)
            .stdin(Stdio::null())
            .output()?;
        checked(out, &format!("kubectl {args:?}"))
    }

    /// Imports an OCI archive into the node's containerd (namespace `k8s.io`, where the kubelet
    /// looks), so Pods can use it with `imagePullPolicy: Never`.
    pub fn import_image(&self, archive: &Path) -> Result<()> {
        let out = Command::new("ctr")
            .arg("--address")
            .arg(&self.containerd)
            .args(["-n", "k8s.io", "images", "import"])
            .arg(archive)
            .output()?;
        checked(out, "ctr images import").map(|_| ())
    }
}

fn script(args: &[&str]) -> Result<Output> {
    let out = Command::new("bash")
        .arg(repo_root().join("scripts/cluster.sh"))
        .args(args)
        .stdin(Stdio::null())
        .output()?;
    if !out.status.success() {
        bail!(
            "cluster.sh {args:?} failed (the node cannot run here):\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(out)
}

fn checked(out: Output, what: &str) -> Result<String> {
    if !out.status.success() {
        bail!(
            "{what} failed: {}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// Writes an image `reference` holding Debian's static busybox at `/bin/busybox` (user
/// 65532:65532) plus `files` (`SRC:DEST`), with `scripts/oci.py`.
pub fn busybox_image(out: &Path, reference: &str, files: &[String]) -> Result<()> {
    let mut cmd = Command::new("python3");
    cmd.arg(repo_root().join("scripts/oci.py"))
        .arg("--out")
        .arg(out)
        .args(["--ref", reference, "--file", "/bin/busybox:/bin/busybox"])
        .args(["--user", "65532:65532"]);
    for file in files {
        cmd.args(["--file", file]);
    }
    checked(cmd.output().context("run scripts/oci.py")?, "oci.py").map(|_| ())
}

/// `GET path` over HTTP/1.0 to `addr`: the status code and the body.
pub async fn http_get_at(addr: SocketAddr, path: &str) -> Result<(u16, String)> {
    let mut stream = tokio::net::TcpStream::connect(addr).await?;
    stream
        .write_all(format!("GET {path} HTTP/1.0\r\nHost: {addr}\r\n\r\n").as_bytes())
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
