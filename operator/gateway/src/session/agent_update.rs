//! A session's agent-update bookkeeping (`spec.agent`, PROTOCOL.md §12.1): the `update_agent`
//! command for the build of the robot's architecture, sent once per desired version and
//! session; the status message when there is no such build or the agent cannot update itself;
//! and the agent's `agent_update_*` events, which move `status.agentUpdate` and the
//! `lekiwi_gateway_agent_updates_total{kind, version}` counter.

use axum::extract::ws::Message;
use futures::Sink;
use jiff::Timestamp;
use lekiwi_crds::{AgentArch, AgentRef};
use lekiwi_protocol::{Command, FEATURE_UPDATE_AGENT, ServerMessage};
use tracing::info;

use super::Session;
use super::conn::Flow;
use lekiwi_event_store::StoredEvent;
use lekiwi_metrics::AgentUpdateLabels;
use lekiwi_presence::AgentUpdateOutcome;

/// What the session knows about the robot's agent and the `update_agent` it sent.
pub(super) struct AgentLedger {
    /// The agent version the robot's `hello` reported.
    running: String,
    /// The architecture the robot's `hello` reported (`uname -m`).
    arch: Option<String>,
    /// Whether the agent listed the `update_agent` feature.
    capable: bool,
    /// The robot's `spec.agent` as the gateway's Robot watch last saw it.
    desired: Option<AgentRef>,
    /// The desired version already acted on in this session (command sent or status given).
    handled: Option<String>,
    /// `update_agent` commands made in this session, numbering their ids.
    counter: u32,
}

/// What to do about the desired agent now.
#[derive(Debug, PartialEq)]
pub(super) enum Step {
    /// Send this command; the status says `Sent`.
    Send(ServerMessage, String),
    /// Send nothing; the status says this (phase, message).
    Report(&'static str, String),
}

impl AgentLedger {
    /// A ledger for an agent whose `hello` said `running`, `arch` and `features`.
    pub(super) fn new(
        running: String,
        arch: Option<String>,
        features: &[String],
        desired: Option<AgentRef>,
    ) -> Self {
        Self {
            running,
            arch,
            capable: features.iter().any(|f| f == FEATURE_UPDATE_AGENT),
            desired,
            handled: None,
            counter: 0,
        }
    }

    /// The version `spec.agent` names, if any.
    pub(super) fn desired_version(&self) -> Option<&str> {
        self.desired.as_ref().map(|d| d.version.as_str())
    }

    /// Records a new `spec.agent`.
    pub(super) fn set_desired(&mut self, desired: Option<AgentRef>) {
        self.desired = desired;
    }

    /// The step due now, with the version it is about; `None` when the robot runs the desired
    /// agent, none is desired, or this version was acted on in this session already.
    pub(super) fn next(&mut self, gateway: &str, session: u64) -> Option<(String, Step)> {
        let desired = self.desired.as_ref()?;
        let version = desired.version.clone();
        if version == self.running || self.handled.as_ref() == Some(&version) {
            return None;
        }
        self.handled = Some(version.clone());
        if !self.capable {
            let why = format!(
                "agent {} cannot update itself (no `{FEATURE_UPDATE_AGENT}` in its hello): \
                 install lekiwi-agent {version} on the robot by hand",
                self.running
            );
            return Some((version, Step::Report("Unsupported", why)));
        }
        let machine = self.arch.clone().unwrap_or_default();
        let Some(arch) = AgentArch::of_machine(&machine) else {
            let why = format!("no agent builds exist for architecture {machine:?} of this robot");
            return Some((version, Step::Report("Unavailable", why)));
        };
        let Some(digest) = desired.build_for(arch).map(str::to_owned) else {
            let have: Vec<&str> = desired.builds.iter().map(|b| b.arch.as_str()).collect();
            let why = format!(
                "agent {version} has no build for {} (this robot is {machine}); builds: {}",
                arch.as_str(),
                have.join(", ")
            );
            return Some((version, Step::Report("Unavailable", why)));
        };
        self.counter += 1;
        let command_id = format!(
            "{gateway}-{}-{session}-agent-{}",
            super::commands::boot_id(),
            self.counter
        );
        let why = format!("update_agent sent: {} build {digest}", arch.as_str());
        let command = ServerMessage::Command {
            command_id,
            command: Command::UpdateAgent {
                version: version.clone(),
                url: lekiwi_protocol::release::blob_path(&digest),
                digest,
            },
        };
        Some((version, Step::Send(command, why)))
    }
}

/// The `version` label of a step about `version`: itself when it is the version `spec.agent`
/// names (`desired`), else `other` (robot-reported text never makes a series of its own).
fn metric_version(version: &str, desired: Option<&str>) -> String {
    if desired == Some(version) {
        version.to_owned()
    } else {
        "other".to_owned()
    }
}

/// The counter kind of what the gateway did (`Sent`, `Unavailable`, `Unsupported`).
fn own_kind(phase: &str) -> &'static str {
    match phase {
        "Sent" => "sent",
        "Unavailable" => "unavailable",
        _ => "unsupported",
    }
}

/// The status phase and counter kind of an agent's `agent_update_*` event.
fn event_phase(kind: &str) -> Option<(&'static str, &'static str)> {
    Some(match kind {
        "agent_update_started" => ("Started", "started"),
        "agent_update_succeeded" => ("Succeeded", "succeeded"),
        "agent_update_failed" => ("Failed", "failed"),
        "agent_update_fallen_back" => ("FallenBack", "fallen_back"),
        _ => return None,
    })
}

impl<W> Session<'_, W>
where
    W: Sink<Message> + Unpin + Send,
{
    /// Sends the `update_agent` command due, or writes why none goes out. A version that fell
    /// back on this robot is not sent again (the agent would refuse it): `status.agentUpdate`
    /// keeps saying `FallenBack` until `spec.agent` names another version.
    pub(super) async fn send_agent_update(&mut self) -> Flow {
        let fell_back = |v: &str| self.shared.presence.agent_update_fell_back(self.key, v);
        if self.agent.desired_version().is_some_and(fell_back) {
            return Ok(());
        }
        let Some((version, step)) = self.agent.next(&self.shared.gateway, self.id) else {
            return Ok(());
        };
        let (phase, message) = match step {
            Step::Send(cmd, why) => {
                info!(%version, "sending update_agent");
                self.conn.send(&cmd).await?;
                ("Sent", why)
            }
            Step::Report(phase, why) => {
                info!(%version, %phase, %why, "no update_agent for this robot");
                (phase, why)
            }
        };
        self.agent_step(version, phase, own_kind(phase), message, true);
        Ok(())
    }

    /// An event of the agent now in the store: an `agent_update_*` one is a step of its
    /// update. `newly` when the store did not hold it before; a resend (its first session ended
    /// before presence was told) is counted only if its step is new to presence.
    pub(super) fn agent_event(&self, ev: &StoredEvent, newly: bool) {
        let Some((phase, kind)) = event_phase(&ev.kind) else {
            return;
        };
        let version = ev.data["version"].as_str().unwrap_or_default().to_owned();
        self.agent_step(version, phase, kind, ev.message.clone(), newly);
    }

    /// Writes a step to `status.agentUpdate` and counts it (when `always`, else only if it is
    /// new to presence).
    fn agent_step(
        &self,
        version: String,
        phase: &'static str,
        kind: &'static str,
        message: String,
        always: bool,
    ) {
        let labels = AgentUpdateLabels {
            kind,
            version: metric_version(&version, self.agent.desired_version()),
        };
        let outcome = AgentUpdateOutcome {
            version,
            phase,
            message,
            time: Timestamp::now(),
        };
        let changed = self
            .shared
            .presence
            .agent_update(self.key, self.id, outcome);
        if always || changed {
            self.shared
                .metrics
                .gateway
                .agent_updates
                .get_or_create(&labels)
                .inc();
        }
    }
}

#[cfg(test)]
mod tests {
    use lekiwi_crds::AgentBuild;

    use super::*;

    fn desired(version: &str, arch: AgentArch) -> Option<AgentRef> {
        Some(AgentRef {
            version: version.into(),
            builds: vec![AgentBuild {
                arch,
                digest: format!("sha256:{}", "c".repeat(64)),
            }],
        })
    }

    fn features() -> Vec<String> {
        vec![FEATURE_UPDATE_AGENT.into()]
    }

    #[test]
    fn the_build_of_the_robots_architecture_goes_out_once() {
        let mut l = AgentLedger::new(
            "1".into(),
            Some("x86_64".into()),
            &features(),
            desired("1", AgentArch::Amd64),
        );
        assert_eq!(l.next("gw", 1), None, "runs it already");
        l.set_desired(desired("2", AgentArch::Amd64));
        let Some((v, Step::Send(ServerMessage::Command { command, .. }, _))) = l.next("gw", 1)
        else {
            panic!("no command");
        };
        assert_eq!(v, "2");
        assert!(
            matches!(command, Command::UpdateAgent { ref url, .. } if url.starts_with("/v1/blobs/sha256:")),
            "{command:?}"
        );
        assert_eq!(l.next("gw", 1), None, "once per session");
    }

    #[test]
    fn only_a_desired_version_labels_the_metric() {
        assert_eq!(metric_version("0.2.0", Some("0.2.0")), "0.2.0");
        assert_eq!(metric_version("0.2.0", Some("0.3.0")), "other");
        assert_eq!(metric_version(&"x".repeat(10_000), None), "other");
    }

    #[test]
    fn no_build_or_no_feature_is_said_once_not_failed() {
        let mut l = AgentLedger::new(
            "1".into(),
            Some("x86_64".into()),
            &features(),
            desired("2", AgentArch::Arm64),
        );
        let (_, step) = l.next("gw", 1).unwrap();
        assert!(
            matches!(&step, Step::Report("Unavailable", why) if why.contains("no build for amd64")),
            "{step:?}"
        );
        assert_eq!(l.next("gw", 1), None);
        let mut old = AgentLedger::new("1".into(), None, &[], desired("2", AgentArch::Amd64));
        assert!(matches!(
            old.next("gw", 1),
            Some((_, Step::Report("Unsupported", _)))
        ));
    }
}
