//! The single-node cluster whose Pods really run (`scripts/testbed/cluster.sh`): started once per test
//! process and reused across runs, images built with `scripts/lib/oci.py` and imported into its
//! containerd, and plain HTTP to the addresses of its network namespace (ClusterIPs, NodePorts).

use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::OnceLock;

use anyhow::{Context as _, Result, bail};
use ipnet::IpNet;
use kube::Client;
use kube::config::{KubeConfigOptions, Kubeconfig};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

use crate::netns::NetView;
use crate::{repo_root, tool};

/// A running cluster managed by `scripts/testbed/cluster.sh`, described by its `env` output.
pub struct Cluster {
    /// State directory (`LEKIWI_CLUSTER_DIR`).
    pub dir: PathBuf,
    /// Admin kubeconfig.
    pub kubeconfig: PathBuf,
    /// The node's IP, in its network namespace: the API server, the kubelet and NodePorts
    /// listen there.
    pub node_ip: String,
    /// The host's end of the veth pair to the node: Pods reach the host at this address.
    pub host_ip: String,
    /// The node's network namespace (`ip netns` name).
    pub netns: String,
    /// The CNI bridge in the node's namespace.
    pub bridge: String,
    /// The Pod range.
    pub pod_cidr: IpNet,
    /// The Service (ClusterIP) range.
    pub service_cidr: IpNet,
    /// containerd's socket, for `ctr images import`.
    pub containerd: PathBuf,
}

impl Cluster {
    /// The cluster shared by every test (`cluster.sh up`: a no-op when it is already healthy).
    /// A failed `up` is printed and tried once more (it resumes where it stopped: a first start
    /// on a CI machine that restored a stopped cluster's state once failed and left a cluster
    /// the next test found healthy). Panics with the script's output when the node still cannot
    /// run: a test never skips silently.
    pub fn shared() -> &'static Cluster {
        static SHARED: OnceLock<Cluster> = OnceLock::new();
        SHARED.get_or_init(|| {
            if let Err(first) = script(&["up"]) {
                eprintln!("{first:#}\nscripts/testbed/cluster.sh up failed once; trying again");
                script(&["up"]).expect("scripts/testbed/cluster.sh up, the second time");
            }
            let env = String::from_utf8_lossy(&script(&["env"]).expect("cluster.sh env").stdout)
                .into_owned();
            let var = |name: &str| {
                env.lines()
                    .find_map(|l| l.strip_prefix(&format!("export {name}=")))
                    .map(|v| v.trim_matches(['\'', '"']).to_owned())
                    .unwrap_or_else(|| panic!("cluster.sh env prints no {name}:\n{env}"))
            };
            let net = |name: &str| {
                var(name)
                    .parse()
                    .unwrap_or_else(|e| panic!("{name} from cluster.sh env: {e}"))
            };
            Cluster {
                dir: var("LEKIWI_CLUSTER_DIR").into(),
                kubeconfig: var("KUBECONFIG").into(),
                node_ip: var("LEKIWI_NODE_IP"),
                host_ip: var("LEKIWI_HOST_IP"),
                netns: var("LEKIWI_NODE_NETNS"),
                bridge: var("LEKIWI_NODE_BRIDGE"),
                pod_cidr: net("LEKIWI_POD_CIDR"),
                service_cidr: net("LEKIWI_SERVICE_CIDR"),
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

    /// Runs helm from the cache against this cluster, in the repository root (so
    /// `charts/lekiwi-operator` names the chart); fails with its output unless it succeeds.
    pub fn helm(&self, args: &[&str]) -> Result<String> {
        let out = Command::new(tool("helm"))
            .args(args)
            .env("KUBECONFIG", &self.kubeconfig)
            .current_dir(repo_root())
            .stdin(Stdio::null())
            .output()?;
        checked(out, &format!("helm {args:?}"))
    }

    /// The operator image built by `scripts/image.sh` (release build, cached) and imported into
    /// the node's containerd, once per test process, also tagged as `<reference>-next` for
    /// upgrades. Returns the reference, `ghcr.io/lekiwi-fleet/lekiwi-operator:<appVersion>`.
    pub fn operator_image(&self) -> &'static str {
        static IMAGE: OnceLock<String> = OnceLock::new();
        IMAGE.get_or_init(|| {
            let started = std::time::Instant::now();
            let out = Command::new("bash")
                .arg(repo_root().join("scripts/image.sh"))
                .args(["operator", "--load", "ctr", "--address"])
                .arg(&self.containerd)
                .stdin(Stdio::null())
                .output()
                .expect("run scripts/image.sh");
            checked(out, "scripts/image.sh operator --load ctr").expect("build the operator image");
            eprintln!(
                "operator image built and imported in {:?}",
                started.elapsed()
            );
            let version =
                std::fs::read_to_string(repo_root().join("charts/lekiwi-operator/Chart.yaml"))
                    .expect("Chart.yaml")
                    .lines()
                    .find_map(|l| l.strip_prefix("appVersion:"))
                    .map(|v| v.trim().trim_matches('"').to_owned())
                    .expect("appVersion in Chart.yaml");
            let reference = format!("ghcr.io/lekiwi-fleet/lekiwi-operator:{version}");
            let out = Command::new("ctr")
                .arg("--address")
                .arg(&self.containerd)
                .args(["-n", "k8s.io", "images", "tag", "--force", &reference])
                .arg(format!("{reference}-next"))
                .output()
                .expect("run ctr images tag");
            checked(out, "ctr images tag").expect("tag the operator image");
            reference
        })
    }

    /// The PID, on the host, of the main process of the container with this `containerd://ID`
    /// (from a Pod's status), as containerd's task list shows it.
    pub fn container_pid(&self, container_id: &str) -> Result<u32> {
        let id = container_id.trim_start_matches("containerd://");
        let out = Command::new("ctr")
            .arg("--address")
            .arg(&self.containerd)
            .args(["-n", "k8s.io", "tasks", "ls"])
            .output()?;
        let list = checked(out, "ctr tasks ls")?;
        list.lines()
            .find_map(|l| {
                let mut f = l.split_whitespace();
                (f.next() == Some(id)).then(|| f.next()?.parse().ok())?
            })
            .with_context(|| format!("no task {id} in:\n{list}"))
    }

    /// What of this node `view` shows: its bridge, an address that is the node IP or in the Pod
    /// or Service range, a route into those ranges other than through the node IP, an iptables
    /// chain named `KUBE-*` (kube-proxy, the kubelet) or `CNI-*` (the CNI plugins). Empty for the
    /// host's own namespace: the node keeps all of these in its own.
    pub fn traces_in(&self, view: &NetView) -> Vec<String> {
        let node_ip: Option<IpAddr> = self.node_ip.parse().ok();
        let ranges = [self.pod_cidr, self.service_cidr];
        let ours = |addr: IpAddr| Some(addr) == node_ip || ranges.iter().any(|r| r.contains(&addr));
        let overlaps = |net: &IpNet| ranges.iter().any(|r| r.contains(net) || net.contains(r));
        let bridges = view.bridges.iter().filter(|b| **b == self.bridge);
        let addresses = view.addresses.iter().filter(|(a, _)| ours(a.addr()));
        let routes = view.routes.iter();
        let chains = view.chains.iter();
        bridges
            .map(|b| format!("bridge {b}"))
            .chain(addresses.map(|(a, link)| format!("address {a} on {link}")))
            .chain(
                routes
                    .filter(|r| overlaps(&r.dst) && r.via != node_ip)
                    .map(|r| format!("route to {} on {}", r.dst, r.dev)),
            )
            .chain(
                chains
                    .filter(|c| c.starts_with("KUBE-") || c.starts_with("CNI-"))
                    .map(|c| format!("iptables chain {c}")),
            )
            .collect()
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
        .arg(repo_root().join("scripts/testbed/cluster.sh"))
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
/// 65532:65532) plus `files` (`SRC:DEST`), with `scripts/lib/oci.py`.
pub fn busybox_image(out: &Path, reference: &str, files: &[String]) -> Result<()> {
    let mut cmd = Command::new("python3");
    cmd.arg(repo_root().join("scripts/lib/oci.py"))
        .arg("--out")
        .arg(out)
        .args(["--ref", reference, "--file", "/bin/busybox:/bin/busybox"])
        .args(["--user", "65532:65532"]);
    for file in files {
        cmd.args(["--file", file]);
    }
    checked(cmd.output().context("run scripts/lib/oci.py")?, "oci.py").map(|_| ())
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

/// Forwards TCP connections to a new port on `listen_ip` (e.g. the host's end of the veth pair,
/// [`Cluster::host_ip`], which Pods reach) to `to` (e.g. a server on the host's loopback), for as
/// long as the caller's Tokio runtime runs. Returns the listening address.
pub async fn forward(listen_ip: &str, to: SocketAddr) -> Result<SocketAddr> {
    let listener = tokio::net::TcpListener::bind((listen_ip, 0)).await?;
    let addr = listener.local_addr()?;
    tokio::spawn(async move {
        while let Ok((mut inbound, _)) = listener.accept().await {
            tokio::spawn(async move {
                if let Ok(mut outbound) = tokio::net::TcpStream::connect(to).await {
                    let _ = tokio::io::copy_bidirectional(&mut inbound, &mut outbound).await;
                }
            });
        }
    });
    Ok(addr)
}
