//! The install page walked literally (issue #41): the `sh walk=ID` blocks of
//! docs/src/install/first-rollout.md, run as written by bash on a lab's computer (a home of its
//! own, a kubeconfig whose current namespace holds the robots, kubectl, helm and the plugin on
//! the `PATH`), and the join command `robot add` prints, run on a robot host of its own: a
//! network namespace linked to the node's as a second network of the node, reaching the node's
//! address and the gateway's NodePort as a robot on the lab's network does.

use std::collections::BTreeSet;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use anyhow::{Context as _, bail, ensure};
use k8s_openapi::api::core::v1::PersistentVolume;
use kube::api::PostParams;
use kube::{Api, Client};
use lekiwi_tests::cluster::Cluster;
use lekiwi_tests::markdown::code_blocks;
use lekiwi_tests::netns::ip;
use lekiwi_tests::{bin, log_dir, namespace, repo_root, tool};
use serde_json::json;

/// The page the test walks.
pub const PAGE: &str = "docs/src/install/first-rollout.md";
/// The chart's release and namespace, as the page installs it.
pub const RELEASE_NS: &str = "lekiwi-system";
/// The chart's full name for release `lekiwi`.
pub const FULL: &str = "lekiwi-lekiwi-operator";

/// The page's blocks: `sh walk=ID` (what the lab types, in order) and the one `sh robot`
/// block (the shape of the join command the plugin prints). Any other block is an error:
/// nothing a reader is told to run escapes the test.
pub struct Page {
    pub walk: Vec<(String, String)>,
    pub robot: String,
}

impl Page {
    pub fn read() -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(repo_root().join(PAGE))?;
        let (mut walk, mut robot) = (Vec::new(), Vec::new());
        for (info, code) in code_blocks(&text) {
            let mut words = info.split_whitespace();
            ensure!(
                words.next() == Some("sh"),
                "{PAGE}: a block not `sh`: {code}"
            );
            match words.next() {
                Some("robot") => robot.push(code),
                Some(w) if w.starts_with("walk=") => walk.push((w[5..].to_owned(), code)),
                _ => bail!("{PAGE}: a block neither `sh walk=ID` nor `sh robot`: {code}"),
            }
        }
        ensure!(robot.len() == 1, "{PAGE}: one `sh robot` block");
        Ok(Self {
            walk,
            robot: robot.remove(0),
        })
    }

    /// The commands of the walk blocks up to and including block `last`: lines that start a
    /// command (not continuations, here-document bodies or comments).
    pub fn commands_until(&self, last: &str) -> Vec<String> {
        let mut out = Vec::new();
        for (id, code) in &self.walk {
            let mut heredoc: Option<String> = None;
            let mut continued = false;
            for line in code.lines() {
                let line = line.trim();
                if let Some(end) = &heredoc {
                    if line == end {
                        heredoc = None;
                    }
                    continue;
                }
                if !continued && !line.is_empty() && !line.starts_with('#') {
                    out.push(line.to_owned());
                }
                continued = line.ends_with('\\');
                heredoc = line.split_once("<<").map(|(_, w)| w.trim().to_owned());
            }
            if id == last {
                break;
            }
        }
        out
    }
}

/// A lab's computer: a home of its own, a kubeconfig whose current namespace `ns` holds the
/// robots, and a PersistentVolume for the chart's default claim (what a cluster's storage
/// provisioner would give it). Uninstalls the chart and deletes what it made when dropped.
pub struct Lab {
    pub cluster: &'static Cluster,
    pub client: Client,
    pub ns: String,
    pub home: tempfile::TempDir,
    kubeconfig: PathBuf,
    page: Page,
    ran: BTreeSet<String>,
    data: tempfile::TempDir,
}

impl Lab {
    pub async fn new(cluster: &'static Cluster) -> anyhow::Result<Self> {
        let client = cluster.client().await?;
        let ns = namespace(&client, "walk").await?;
        let home = tempfile::tempdir()?;
        let kubeconfig = home.path().join(".kube/config");
        std::fs::create_dir_all(kubeconfig.parent().unwrap())?;
        std::fs::copy(&cluster.kubeconfig, &kubeconfig)?;
        let out = Command::new(tool("kubectl"))
            .arg("--kubeconfig")
            .arg(&kubeconfig)
            .args(["config", "set-context", "--current", "--namespace", &ns])
            .output()?;
        ensure!(out.status.success(), "kubectl config set-context: {out:?}");
        let data = tempfile::tempdir()?;
        let lab = Self {
            cluster,
            client,
            ns,
            home,
            kubeconfig,
            page: Page::read()?,
            ran: BTreeSet::new(),
            data,
        };
        lab.volume().await?;
        Ok(lab)
    }

    /// A 10Gi hostPath PV (the chart's default `persistence.size`) bound ahead to the chart's
    /// claim: the node's own PVs are 1Gi.
    async fn volume(&self) -> anyhow::Result<()> {
        let dir = self.data.path();
        std::fs::set_permissions(dir, std::os::unix::fs::PermissionsExt::from_mode(0o777))?;
        let pv: PersistentVolume = serde_json::from_value(json!({
            "metadata": {"name": self.pv_name()},
            "spec": {
                "capacity": {"storage": "10Gi"},
                "accessModes": ["ReadWriteOnce"],
                "persistentVolumeReclaimPolicy": "Retain",
                "storageClassName": "standard",
                "hostPath": {"path": dir, "type": "Directory"},
                "claimRef": {"namespace": RELEASE_NS, "name": format!("{FULL}-data")},
            },
        }))?;
        Api::<PersistentVolume>::all(self.client.clone())
            .create(&PostParams::default(), &pv)
            .await?;
        Ok(())
    }

    fn pv_name(&self) -> String {
        format!("{}-data", self.ns)
    }

    /// The blob store's directory (on the PV).
    pub fn blobs(&self) -> PathBuf {
        self.data.path().join("blobs/sha256")
    }

    /// Runs the page's block `id` with bash (`-euo pipefail`) in the repository (the chart and
    /// the image archive are named from there); its standard output.
    pub fn run(&mut self, id: &str) -> anyhow::Result<String> {
        let code = self
            .page
            .walk
            .iter()
            .find(|(i, _)| i == id)
            .map(|(_, c)| c.clone())
            .with_context(|| format!("no block `sh walk={id}` in {PAGE}"))?;
        eprintln!("walk={id}:\n{code}");
        let path = [
            bin("kubectl-lekiwi").parent().unwrap().to_owned(),
            tool("kubectl").parent().unwrap().to_owned(),
        ];
        let path = std::env::join_paths(path.iter().cloned().chain(std::env::split_paths(
            &std::env::var_os("PATH").unwrap_or_default(),
        )))?;
        let out = Command::new("bash")
            .args(["-euo", "pipefail", "-c", &code])
            .current_dir(repo_root())
            .env("HOME", self.home.path())
            .env("KUBECONFIG", &self.kubeconfig)
            .env("PATH", path)
            .env("NODE_IP", &self.cluster.node_ip)
            .env("CONTAINERD_ADDRESS", &self.cluster.containerd)
            .env_remove("LEKIWI_SERVER")
            .env_remove("LEKIWI_GATEWAY_URL")
            .env_remove("LEKIWI_GATEWAY_NAMESPACE")
            .stdin(Stdio::null())
            .output()?;
        let (stdout, stderr) = (
            String::from_utf8_lossy(&out.stdout).into_owned(),
            String::from_utf8_lossy(&out.stderr),
        );
        eprintln!("{stdout}{stderr}");
        ensure!(out.status.success(), "walk={id} failed: {stderr}");
        self.ran.insert(id.to_owned());
        Ok(stdout)
    }

    /// The page's blocks, each run once.
    pub fn all_ran(&self) -> anyhow::Result<()> {
        let left: Vec<_> = self
            .page
            .walk
            .iter()
            .filter(|(id, _)| !self.ran.contains(id))
            .map(|(id, _)| id.clone())
            .collect();
        ensure!(left.is_empty(), "blocks of {PAGE} not run: {left:?}");
        Ok(())
    }

    /// What to read when a step fails: the lab's robots and rollouts, the operator's log.
    pub fn diagnose(&self) -> String {
        let ns = self.ns.as_str();
        let get = [
            "get",
            "robots,robotdeployments,events",
            "-o",
            "yaml",
            "-n",
            ns,
        ];
        let logs = [
            "logs",
            "-n",
            RELEASE_NS,
            "-l",
            "app.kubernetes.io/component=operator",
            "--tail",
            "80",
        ];
        let run = |args: &[&str]| self.cluster.kubectl(args).unwrap_or_else(|e| e.to_string());
        format!("{}\n{}", run(&get), run(&logs))
    }

    pub fn page(&self) -> &Page {
        &self.page
    }
}

impl Drop for Lab {
    fn drop(&mut self) {
        let _ = self.cluster.helm(&[
            "uninstall",
            "lekiwi",
            "-n",
            RELEASE_NS,
            "--wait",
            "--timeout",
            "60s",
        ]);
        for ns in [RELEASE_NS, self.ns.as_str()] {
            let _ = self
                .cluster
                .kubectl(&["delete", "namespace", ns, "--wait=false"]);
        }
        let _ = self
            .cluster
            .kubectl(&["delete", "pv", &self.pv_name(), "--wait=false"]);
    }
}

/// A robot on a host of its own: network namespace `lkw-robot-PID`, linked by a veth pair to
/// the node's namespace as a second network of the node (`198.18.214.0/30`: the node `.1`, the
/// robot `.2`, its default route through the node). `/` of the robot is a directory (join's
/// `--root`) on a disk of its own (a tmpfs) and the agent runs as its unit would, from `/etc/lekiwi/agent.yaml` and the
/// drop-ins beside it. All removed when dropped.
pub struct RobotHost {
    netns: String,
    pub root: tempfile::TempDir,
    agent: Option<Child>,
    log: PathBuf,
    mounted: bool,
}

const ROBOT_NET_NODE: &str = "198.18.214.1";
const ROBOT_NET_ROBOT: &str = "198.18.214.2";

impl RobotHost {
    pub fn new(cluster: &Cluster) -> anyhow::Result<Self> {
        let id = std::process::id() % 100_000;
        let netns = format!("lkw-robot-{id}");
        let (robot_end, node_end) = (format!("lkw{id}r"), format!("lkw{id}n"));
        ip(&["netns", "add", &netns])?;
        let host = Self {
            netns: netns.clone(),
            root: tempfile::tempdir()?,
            agent: None,
            log: log_dir().join(format!("walk-agent-{netns}.log")),
            mounted: false,
        };
        let mut host = host;
        host.mount_disk()?;
        ip(&[
            "link", "add", &robot_end, "type", "veth", "peer", "name", &node_end,
        ])?;
        ip(&["link", "set", &robot_end, "netns", &netns])?;
        ip(&["link", "set", &node_end, "netns", &cluster.netns])?;
        let node_addr = format!("{ROBOT_NET_NODE}/30");
        ip(&[
            "-n",
            &cluster.netns,
            "addr",
            "add",
            &node_addr,
            "dev",
            &node_end,
        ])?;
        ip(&["-n", &cluster.netns, "link", "set", &node_end, "up"])?;
        let robot_addr = format!("{ROBOT_NET_ROBOT}/30");
        ip(&["-n", &netns, "addr", "add", &robot_addr, "dev", &robot_end])?;
        ip(&["-n", &netns, "link", "set", &robot_end, "up"])?;
        ip(&["-n", &netns, "link", "set", "lo", "up"])?;
        ip(&[
            "-n",
            &netns,
            "route",
            "add",
            "default",
            "via",
            ROBOT_NET_NODE,
        ])?;
        // The package's configuration file, as installing the .deb leaves it.
        let etc = host.root.path().join("etc/lekiwi");
        std::fs::create_dir_all(&etc)?;
        std::fs::copy(
            repo_root().join("agent/debian/agent.yaml"),
            etc.join("agent.yaml"),
        )?;
        Ok(host)
    }

    /// The robot's own disk: a 256 MiB tmpfs on its root, so that the agent's disk check sees
    /// the robot's file system, not the test machine's.
    fn mount_disk(&mut self) -> anyhow::Result<()> {
        let out = Command::new("mount")
            .args(["-t", "tmpfs", "-o", "size=256m", "tmpfs"])
            .arg(self.root.path())
            .output()?;
        ensure!(out.status.success(), "mount tmpfs: {out:?}");
        self.mounted = true;
        Ok(())
    }

    /// Runs `line`, the join command as printed (`sudo lekiwi-agent join ...`), on the robot:
    /// under its root, with `--no-start` (no systemd here) and the agent started as its unit
    /// does once join has written its drop-in. Returns what join printed.
    pub async fn join(&mut self, line: &str) -> anyhow::Result<String> {
        let words: Vec<&str> = line.split_whitespace().collect();
        ensure!(
            words.len() > 3 && words[..3] == ["sudo", "lekiwi-agent", "join"],
            "not a join command: {line}"
        );
        let root = self.root.path().to_str().unwrap().to_owned();
        let joining = tokio::process::Command::new("ip")
            .args(["netns", "exec", &self.netns])
            .arg(bin("lekiwi-agent"))
            .args(&words[2..])
            .args(["--root", &root, "--no-start"])
            .stdin(Stdio::null())
            .output();
        let mut joining = tokio::spawn(joining);
        let drop_in = self.root.path().join("etc/lekiwi/agent.d/50-join.yaml");
        // Join writes its drop-in once the gateway's CA matched the pin, then waits for the
        // agent; one that ends before has failed.
        let ended = tokio::time::timeout(Duration::from_secs(30), async {
            loop {
                tokio::select! {
                    out = &mut joining => return Some(out),
                    () = tokio::time::sleep(Duration::from_millis(50)) => {}
                }
                if drop_in.exists() {
                    return None;
                }
            }
        })
        .await
        .context("join wrote no drop-in within 30 s")?;
        let out = match ended {
            Some(out) => out??,
            None => {
                self.start_agent()?;
                joining.await??
            }
        };
        let said = format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        ensure!(
            out.status.success(),
            "join: {said}\nagent log:\n{}",
            std::fs::read_to_string(&self.log).unwrap_or_default()
        );
        Ok(said)
    }

    /// `lekiwi-agent --config /etc/lekiwi/agent.yaml` in the robot's namespace (the unit's
    /// command; its state directory is join's drop-in's under the root), retrying quickly.
    fn start_agent(&mut self) -> anyhow::Result<()> {
        let config = self.root.path().join("etc/lekiwi/agent.yaml");
        let file = std::fs::File::create(&self.log)?;
        let child = Command::new("ip")
            .args(["netns", "exec", &self.netns])
            .arg(bin("lekiwi-agent"))
            .arg("--config")
            .arg(&config)
            .args(["--mdns", "false", "--backoff-initial-ms", "200"])
            .args(["--backoff-max-ms", "2000"])
            .env("RUST_LOG", "info")
            .stdin(Stdio::null())
            .stdout(file.try_clone()?)
            .stderr(file)
            .spawn()?;
        self.agent = Some(child);
        Ok(())
    }
}

impl Drop for RobotHost {
    fn drop(&mut self) {
        if let Some(agent) = &mut self.agent {
            let _ = agent.kill();
            let _ = agent.wait();
        }
        // Deleting the namespace deletes the veth end inside it and so its peer in the node's.
        let _ = ip(&["netns", "del", &self.netns]);
        if self.mounted {
            let _ = Command::new("umount").arg(self.root.path()).status();
        }
    }
}

/// The serial of the certificate a new TLS connection to `addr` (from the host) is given.
pub fn served_serial(addr: &str) -> anyhow::Result<String> {
    let out = Command::new("bash")
        .arg("-c")
        .arg(format!(
            "openssl s_client -connect {addr} </dev/null 2>/dev/null | openssl x509 -noout -serial"
        ))
        .output()?;
    ensure!(out.status.success(), "openssl s_client {addr}: {out:?}");
    Ok(String::from_utf8_lossy(&out.stdout).trim().to_owned())
}
