//! The `update_agent` command on the robot: download and verify the build, install it into the
//! inactive slot (or, for a build the robot keeps already, its inactive slot or the package
//! binary, none of that: a rollback downloads nothing), write the pending-update record, flip
//! `current` (all in a task that holds the
//! release store, like a deployment), then end the run loop so that `main` exits with
//! [`EXIT_UPDATED`](crate::selfupdate::EXIT_UPDATED). Also the two ends of an update: the new
//! agent commits once a gateway welcomed it, and the agent after a fallback reports it.
//!
//! Events (durable, critical lane): `agent_update_started` (the old agent, just before it
//! exits), `agent_update_succeeded` (the new agent, at commit), `agent_update_failed` (nothing
//! switched: download, digest or disk), `agent_update_fallen_back` (the guard undid it; sent by
//! the agent that runs afterwards). Each carries `{"version", "from", "digest", "command_id"}`
//! and, for the last two, `"reason"`.

use lekiwi_protocol::Severity;
use tracing::{info, warn};

use super::commands::{AgentTarget, Deploying};
use super::{Agent, Error};
use crate::outbox::Lane;
use crate::release::{Outcome, Phase, Releases};
use crate::selfupdate::local::LocalBuild;
use crate::selfupdate::{self, Pending, Slots};

/// Largest agent build downloaded, in bytes (it is held in memory while verified).
const MAX_AGENT_BYTES: usize = 128 * 1024 * 1024;

impl Agent {
    /// Why an `update_agent` for `digest` is not even started, if it is not.
    fn refuse_agent_update(&self, version: &str, digest: &str) -> Option<String> {
        if version == selfupdate::version() {
            return Some(format!("agent {version} runs already"));
        }
        let slots = Slots::new(&self.config.state_dir);
        if let Some(fb) = slots.fallen_back().filter(|f| f.digest == digest) {
            return Some(format!(
                "agent {version} ({digest}) was undone on this robot before: {}",
                fb.reason
            ));
        }
        slots
            .pending()
            .map(|p| format!("agent update to {} is not committed yet", p.version))
    }

    /// Starts the task that installs and switches to `version`; `None` (the store given back)
    /// when it is refused.
    pub(super) fn start_agent_update(
        &mut self,
        releases: Releases,
        command_id: String,
        target: AgentTarget,
        url: String,
    ) -> Option<Deploying> {
        if let Some(why) = self.refuse_agent_update(&target.version, &target.digest) {
            info!(%command_id, version = %target.version, %why, "agent update not started");
            self.releases = Some(releases);
            return None;
        }
        let pending = Pending {
            command_id: command_id.clone(),
            version: target.version.clone(),
            digest: target.digest.clone(),
            from_version: selfupdate::version().to_owned(),
            previous: None,
            slot: String::new(),
            deadline_ms: lekiwi_protocol::now_ms()
                + i64::try_from(self.config.agent_update_deadline_s.saturating_mul(1000))
                    .unwrap_or(i64::MAX / 2),
            starts: 0,
            max_starts: self.config.agent_update_max_starts,
        };
        let slots = Slots::new(&self.config.state_dir);
        let task = tokio::spawn(install(releases, slots, pending, url));
        Some(Deploying::agent(task, command_id, target))
    }

    /// The install task ended: on a switch, report it and end the run loop; else report why not.
    pub(super) fn agent_update_done(
        &mut self,
        command_id: &str,
        target: &AgentTarget,
        outcome: &Outcome,
    ) -> Result<(), Error> {
        let data = serde_json::json!({
            "version": target.version,
            "from": selfupdate::version(),
            "digest": target.digest,
            "command_id": command_id,
            "bytes": outcome.bytes_downloaded,
        });
        if outcome.phase == Phase::Done {
            self.event(
                Lane::Critical,
                "agent_update_started",
                Severity::Info,
                format!(
                    "switching from agent {} to {}; restarting",
                    selfupdate::version(),
                    target.version
                ),
                data,
            )?;
            self.restart_for_update = true;
        } else {
            let mut data = data;
            data["reason"] = outcome.message.clone().into();
            self.event(
                Lane::Critical,
                "agent_update_failed",
                Severity::Error,
                format!(
                    "agent update to {} failed: {}",
                    target.version, outcome.message
                ),
                data,
            )?;
        }
        Ok(())
    }

    /// After a gateway welcomed this agent: commits the pending update that installed it.
    pub(super) fn commit_agent_update(&mut self) -> Result<(), Error> {
        let slots = Slots::new(&self.config.state_dir);
        let Some(p) = slots
            .pending()
            .filter(|p| p.version == selfupdate::version())
        else {
            return Ok(());
        };
        slots.clear_pending().map_err(selfupdate_error)?;
        info!(version = %p.version, from = %p.from_version, "agent update committed");
        self.event(
            Lane::Critical,
            "agent_update_succeeded",
            Severity::Info,
            format!("agent {} replaced {}", p.version, p.from_version),
            serde_json::json!({
                "version": p.version, "from": p.from_version,
                "digest": p.digest, "command_id": p.command_id,
            }),
        )?;
        Ok(())
    }

    /// At start: queues the report of an update the guard undid, once.
    pub(super) fn report_fallen_back(&mut self) -> Result<(), Error> {
        let slots = Slots::new(&self.config.state_dir);
        let Some(mut fb) = slots.fallen_back().filter(|f| !f.reported) else {
            return Ok(());
        };
        warn!(version = %fb.version, reason = %fb.reason, "an agent update was undone");
        self.event(
            Lane::Critical,
            "agent_update_fallen_back",
            Severity::Error,
            format!(
                "agent update to {} was undone, back on {}: {}",
                fb.version,
                selfupdate::version(),
                fb.reason
            ),
            serde_json::json!({
                "version": fb.version, "from": selfupdate::version(),
                "digest": fb.digest, "command_id": fb.command_id, "reason": fb.reason,
            }),
        )?;
        fb.reported = true;
        slots.set_fallen_back(&fb).map_err(selfupdate_error)
    }
}

fn selfupdate_error(e: selfupdate::Error) -> Error {
    Error::State(crate::state::Error::Io {
        path: e.path,
        source: e.source,
    })
}

/// Downloads, verifies, installs and switches; gives the store back with the outcome.
async fn install(
    releases: Releases,
    slots: Slots,
    mut pending: Pending,
    url: String,
) -> (Releases, Option<Outcome>) {
    let current = releases.current();
    let outcome = |phase, message, bytes| Outcome {
        phase,
        message,
        current: current.clone(),
        bytes_downloaded: bytes,
        files_downloaded: usize::from(bytes > 0),
        files_reused: 0,
    };
    let local = {
        let (slots, digest) = (slots.clone(), pending.digest.clone());
        tokio::task::spawn_blocking(move || slots.find_local(&digest))
            .await
            .ok()
            .flatten()
    };
    if let Some(local) = local {
        let o = match switch_local(slots, pending, local).await {
            Ok(message) => outcome(Phase::Done, message, 0),
            Err(message) => outcome(Phase::Failed, message, 0),
        };
        return (releases, Some(o));
    }
    let bytes = match releases
        .fetch_verified(&url, &pending.digest, MAX_AGENT_BYTES)
        .await
    {
        Ok(b) => b,
        Err(e) => return (releases, Some(outcome(Phase::Failed, e.to_string(), 0))),
    };
    let size = bytes.len() as u64;
    let switched = tokio::task::spawn_blocking(move || {
        let slot = slots.inactive();
        pending.previous = slots.current();
        pending.slot = slot.to_owned();
        slots.install(slot, &bytes)?;
        slots.set_pending(&pending)?;
        slots.switch(Some(slot))
    })
    .await;
    let o = match switched {
        Ok(Ok(())) => outcome(Phase::Done, "switched".into(), size),
        Ok(Err(e)) => outcome(Phase::Failed, e.to_string(), size),
        Err(e) => outcome(Phase::Failed, e.to_string(), size),
    };
    (releases, Some(o))
}

/// Switches to a build kept on this robot (a rollback, mostly): no download.
async fn switch_local(
    slots: Slots,
    mut pending: Pending,
    local: LocalBuild,
) -> Result<String, String> {
    let message = format!(
        "switched to the build kept as {} (no download)",
        local.describe()
    );
    tokio::task::spawn_blocking(move || {
        pending.previous = slots.current();
        pending.slot = local.slot().unwrap_or_default().to_owned();
        slots.set_pending(&pending)?;
        slots.switch(local.slot())
    })
    .await
    .map_err(|e| e.to_string())?
    .map_err(|e| e.to_string())?;
    Ok(message)
}
