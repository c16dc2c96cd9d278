//! The etcd + kube-apiserver pair the tests run against (`scripts/testbed/control-plane.sh`): the shared
//! one, private ones for tests that restart it, and a namespace per test.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::OnceLock;

use anyhow::{Context as _, Result, bail};
use k8s_openapi::api::core::v1::Namespace;
use kube::api::{ObjectMeta, PostParams};
use kube::config::{KubeConfigOptions, Kubeconfig};
use kube::{Api, Client};

use crate::{repo_root, tool};

/// A running etcd + kube-apiserver managed by `scripts/testbed/control-plane.sh`.
pub struct ControlPlane {
    /// State directory of the instance (`LEKIWI_CP_DIR`).
    pub dir: PathBuf,
    /// Set for a private instance: purged when dropped.
    private: Option<tempfile::TempDir>,
}

impl ControlPlane {
    /// The control plane shared by the whole test run (started once, reused), with our CRDs.
    pub fn shared() -> &'static ControlPlane {
        static SHARED: OnceLock<ControlPlane> = OnceLock::new();
        SHARED.get_or_init(|| {
            let dir = std::env::var("LEKIWI_CP_DIR")
                .map(PathBuf::from)
                // Not the quickstart's control plane: an operator left running there watches
                // every namespace and would fight the tests' own operators.
                .unwrap_or_else(|_| crate::cache_dir().join("test-control-plane"));
            let cp = ControlPlane { dir, private: None };
            cp.prune_kubectl_caches();
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
            .arg(repo_root().join("scripts/testbed/control-plane.sh"))
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

    /// SIGKILLs kube-apiserver alone; etcd keeps running (and can be changed behind the API
    /// server's back with [`ControlPlane::etcd_delete`]).
    pub fn kill_apiserver(&self) -> Result<()> {
        self.script(&["kill", "kube-apiserver"]).map(|_| ())
    }

    /// Deletes `key` (e.g. `/registry/secrets/NS/NAME`) in etcd directly, through etcd's JSON
    /// gateway: what a watcher that was disconnected meanwhile can only learn from a relist.
    pub async fn etcd_delete(&self, key: &str) -> Result<u64> {
        use base64::Engine as _;
        let ports = std::fs::read_to_string(self.dir.join("ports.env"))?;
        let port = ports
            .lines()
            .find_map(|l| l.strip_prefix("ETCD_PORT="))
            .ok_or_else(|| anyhow::anyhow!("no ETCD_PORT in ports.env"))?;
        let body = serde_json::json!({
            "key": base64::engine::general_purpose::STANDARD.encode(key),
        });
        let answer: serde_json::Value = reqwest::Client::new()
            .post(format!("http://127.0.0.1:{port}/v3/kv/deleterange"))
            .json(&body)
            .send()
            .await?
            .error_for_status()?
            .json()
            .await?;
        Ok(answer["deleted"]
            .as_str()
            .and_then(|n| n.parse().ok())
            .unwrap_or(0))
    }

    /// Path of the admin kubeconfig.
    pub fn kubeconfig(&self) -> PathBuf {
        self.dir.join("kubeconfig")
    }

    /// The admin user's bearer token (group system:masters), as a Kubernetes user presents it
    /// to the gateway's HTTP API.
    pub fn admin_token(&self) -> Result<String> {
        Ok(std::fs::read_to_string(self.dir.join("admin-token"))?
            .trim()
            .to_owned())
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
        self.write_kubeconfig(path, |kc| {
            let users = kc["users"]
                .as_sequence_mut()
                .context("kubeconfig has no users")?;
            for user in users.iter_mut() {
                user["user"] =
                    serde_yaml::to_value(std::collections::BTreeMap::from([("token", token)]))?;
            }
            Ok(())
        })
    }

    /// A kubeconfig for the same server and user, reached at `server` (`https://host:port`,
    /// a proxy in front of the API server), written to `path`.
    pub fn kubeconfig_via(&self, server: &str, path: &Path) -> Result<()> {
        self.write_kubeconfig(path, |kc| {
            let clusters = kc["clusters"]
                .as_sequence_mut()
                .context("kubeconfig has no clusters")?;
            for cluster in clusters.iter_mut() {
                cluster["cluster"]["server"] = serde_yaml::Value::from(server);
            }
            Ok(())
        })
    }

    /// The admin kubeconfig as YAML.
    fn kubeconfig_yaml(&self) -> Result<serde_yaml::Value> {
        Ok(serde_yaml::from_str(&std::fs::read_to_string(
            self.kubeconfig(),
        )?)?)
    }

    /// The admin kubeconfig, changed by `edit`, written to `path`.
    fn write_kubeconfig(
        &self,
        path: &Path,
        edit: impl FnOnce(&mut serde_yaml::Value) -> Result<()>,
    ) -> Result<()> {
        let mut kc = self.kubeconfig_yaml()?;
        edit(&mut kc)?;
        std::fs::write(path, serde_yaml::to_string(&kc)?)?;
        Ok(())
    }

    /// The API server's address, from the kubeconfig's server URL.
    pub fn api_server_addr(&self) -> Result<std::net::SocketAddr> {
        let kc = self.kubeconfig_yaml()?;
        let server = kc["clusters"][0]["cluster"]["server"]
            .as_str()
            .context("kubeconfig has no server")?;
        let hostport = server.trim_start_matches("https://").trim_end_matches('/');
        Ok(hostport.parse()?)
    }

    /// Removes the kubectl discovery caches of test processes that have ended (one per
    /// process, a few MiB each: without this they pile up run after run).
    fn prune_kubectl_caches(&self) {
        let Ok(entries) = std::fs::read_dir(&self.dir) else {
            return;
        };
        for entry in entries.flatten() {
            let name = entry.file_name();
            let Some(pid) = name.to_str().and_then(|n| n.strip_prefix("kubectl-cache-")) else {
                continue;
            };
            if !Path::new("/proc").join(pid).exists() {
                let _ = std::fs::remove_dir_all(entry.path());
            }
        }
    }

    /// A command for a tool from the cache, pointed at this control plane.
    fn command(&self, name: &str) -> Command {
        let mut cmd = Command::new(tool(name));
        cmd.env("KUBECONFIG", self.kubeconfig())
            // A fresh discovery cache: a stale one hides CRDs installed a moment ago.
            .env(
                "KUBECACHEDIR",
                self.dir
                    .join(format!("kubectl-cache-{}", std::process::id())),
            )
            .current_dir(repo_root());
        cmd
    }

    /// Runs a tool from the cache (`kubectl`, `helm`) against this control plane.
    pub fn tool(&self, name: &str, args: &[&str]) -> Output {
        self.command(name).args(args).output().expect("run tool")
    }

    /// Runs kubectl against this control plane, with the cache's `bin` directory first on
    /// `PATH`.
    pub fn kubectl(&self, args: &[&str]) -> Output {
        let path = format!(
            "{}:{}",
            tool("kubectl").parent().unwrap().display(),
            std::env::var("PATH").unwrap_or_default()
        );
        self.command("kubectl")
            .args(args)
            .env("PATH", path)
            .output()
            .expect("run kubectl")
    }

    /// Write requests (POST, PUT, PATCH, APPLY, DELETE) the API server has served since it
    /// started, from its own `/metrics` (`apiserver_request_total`), by resource and
    /// subresource (`robots`, `robots/status`): on a private control plane, what a test's
    /// processes cost it.
    pub fn writes(&self) -> Result<std::collections::BTreeMap<String, f64>> {
        self.requests(&["POST", "PUT", "PATCH", "APPLY", "DELETE"])
    }

    /// The API server's requests of `verbs` so far (`apiserver_request_total`), by resource
    /// (`robots`, `robots/status`, ...).
    pub fn requests(&self, verbs: &[&str]) -> Result<std::collections::BTreeMap<String, f64>> {
        let out = self.kubectl(&["get", "--raw", "/metrics"]);
        anyhow::ensure!(out.status.success(), "kubectl get --raw /metrics failed");
        let text = String::from_utf8(out.stdout)?;
        let mut by = std::collections::BTreeMap::new();
        for line in text.lines() {
            let Some(rest) = line.strip_prefix("apiserver_request_total{") else {
                continue;
            };
            let Some((labels, value)) = rest.rsplit_once("} ") else {
                continue;
            };
            let label = |name: &str| {
                labels
                    .split(',')
                    .find_map(|kv| kv.strip_prefix(&format!("{name}=\"")))
                    .map(|v| v.trim_end_matches('"').to_owned())
                    .unwrap_or_default()
            };
            if !verbs.contains(&label("verb").as_str()) {
                continue;
            }
            let (resource, sub) = (label("resource"), label("subresource"));
            let key = if sub.is_empty() {
                resource
            } else {
                format!("{resource}/{sub}")
            };
            *by.entry(key).or_default() += value.trim().parse::<f64>().unwrap_or(0.0);
        }
        Ok(by)
    }

    /// Server-side applies our CRDs and waits until they are served
    /// (`scripts/testbed/control-plane.sh crds`).
    pub fn install_crds(&self) -> Result<()> {
        self.script(&["crds"]).map(drop)
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
