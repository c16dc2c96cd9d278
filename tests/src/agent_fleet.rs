//! Real `lekiwi-agent` processes under the supervisor ([`crate::supervisor`]) against a private
//! control plane and operator, with agent builds pushed by `kubectl-lekiwi agent push`: the
//! setup of the agent self-update tests (`agent_update`, `agent_rollout`).
//!
//! Agent A is the workspace's `lekiwi-agent` (the "package binary"). B is A under another version
//! name: a wrapper script that sets `LEKIWI_AGENT_VERSION_OVERRIDE` and execs A. D is A with a
//! wrong gateway URL baked in: it runs but never connects.

use std::path::PathBuf;
use std::time::Duration;

use kube::Api;
use lekiwi_crds::{AgentArch, Robot};
use serde_json::Value;

use crate::supervisor::{SuperviseSpec, Supervised};
use crate::{
    ControlPlane, OperatorProcess, bin, enrollment_token_file, gateway_url, log_dir, namespace,
};

/// How long most steps may take.
pub const T: Duration = Duration::from_secs(60);
/// `agentUpdateDeadlineS` of the test agents.
pub const DEADLINE_S: u64 = 20;

/// The architecture name of this machine's builds.
pub fn arch() -> &'static str {
    AgentArch::of_machine(std::env::consts::ARCH)
        .expect("a machine with agent builds")
        .as_str()
}

/// A private control plane (CRDs of this tree: the shared one is re-applied with other
/// worktrees' CRDs, which prune `spec.agent`), an operator, and the robots' state.
pub struct AgentFleet {
    /// Admin client of the private control plane.
    pub client: kube::Client,
    /// The robots' namespace.
    pub ns: String,
    /// The operator (gateway and controllers).
    pub op: OperatorProcess,
    /// The robots' state directories and the pushed builds.
    pub dir: tempfile::TempDir,
    token_file: PathBuf,
    /// Last: dropped after the operator.
    pub cp: ControlPlane,
}

/// A private control plane with this tree's CRDs, an operator (identity `identity`) and a
/// namespace named after `prefix`.
pub async fn agent_fleet(prefix: &str, identity: &str) -> anyhow::Result<AgentFleet> {
    let cp = ControlPlane::private()?;
    cp.install_crds()?;
    let client = cp.client().await?;
    let ns = namespace(&client, prefix).await?;
    let mut op = OperatorProcess::start(&cp, &ns, identity, &["--heartbeat-grace-seconds", "60"])?;
    op.wait_ready().await?;
    let dir = tempfile::tempdir()?;
    let token_file = dir.path().join("enroll");
    enrollment_token_file(&client, &ns, &token_file).await?;
    Ok(AgentFleet {
        cp,
        client,
        ns,
        op,
        dir,
        token_file,
    })
}

impl AgentFleet {
    /// Robot `name` under the supervisor, on agent A.
    pub fn robot(&self, name: &str) -> Supervised {
        let state = self.dir.path().join(name);
        let args: Vec<String> = [
            "--config",
            "/nonexistent/lekiwi-agent.yaml",
            "--state-dir",
            state.to_str().unwrap(),
            "--gateway",
            &gateway_url(&self.op),
            "--robot-name",
            &format!("{}/{name}", self.ns),
            "--enrollment-token-file",
            self.token_file.to_str().unwrap(),
            "--status-listen",
            "off",
            "--agent-update-deadline-s",
            &DEADLINE_S.to_string(),
            "--agent-update-max-starts",
            "3",
        ]
        .iter()
        .chain(crate::agent::QUICK_AGENT_FLAGS.iter())
        .map(|s| s.to_string())
        .collect();
        Supervised::start(SuperviseSpec {
            args,
            state_dir: state,
            log: log_dir().join(format!("agent-update-{}-{name}.log", self.ns)),
            restart_delay: Duration::from_millis(300),
            check_every: Duration::from_secs(1),
        })
    }

    /// Writes a build (a script) and pushes it with `kubectl-lekiwi agent push`; its digest.
    pub fn push(&self, name: &str, version: &str, script: &str) -> anyhow::Result<String> {
        use std::os::unix::fs::PermissionsExt as _;
        let path = self.dir.path().join(name);
        std::fs::write(&path, script)?;
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755))?;
        let server = format!("http://127.0.0.1:{}", self.op.gateway_port);
        crate::push_agent(
            &self.cp.kubeconfig(),
            &self.ns,
            &server,
            None,
            &path,
            version,
            arch(),
        )
    }

    /// Sets `spec.agent` of robot `name`.
    pub async fn desire(
        &self,
        name: &str,
        version: &str,
        arch: &str,
        digest: &str,
    ) -> anyhow::Result<()> {
        crate::set_agent(&self.client, &self.ns, name, version, arch, digest).await
    }

    /// `status.agentDigest` of robot `name`.
    pub async fn agent_digest(&self, name: &str) -> Option<String> {
        let robot = Api::<Robot>::namespaced(self.client.clone(), &self.ns)
            .get(name)
            .await
            .ok()?;
        robot.status?.agent_digest.map(String::from)
    }

    /// `status.agentVersion` and `status.agentUpdate` of robot `name`.
    pub async fn agent_status(&self, name: &str) -> Option<(String, Value)> {
        let robot = Api::<Robot>::namespaced(self.client.clone(), &self.ns)
            .get(name)
            .await
            .ok()?;
        let status = serde_json::to_value(robot.status?).ok()?;
        Some((
            status["agentVersion"]
                .as_str()
                .unwrap_or_default()
                .to_owned(),
            status["agentUpdate"].clone(),
        ))
    }
}

/// Wrapper B/D: A under another version name (D also with a wrong gateway baked in).
pub fn wrapper(version: &str, wrong_gateway: bool) -> String {
    let a = bin("lekiwi-agent");
    let rewrite = if wrong_gateway {
        "for i in \"${!args[@]}\"; do [ \"${args[$i]}\" = --gateway ] && args[$((i+1))]=ws://127.0.0.1:9/v1/agent; done\n"
    } else {
        ""
    };
    format!(
        "#!/bin/bash\nargs=(\"$@\")\n{rewrite}LEKIWI_AGENT_VERSION_OVERRIDE={version} exec {} \"${{args[@]}}\"\n",
        a.display()
    )
}
