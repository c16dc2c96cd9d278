//! The irreversible half of a deployment: pre-switch hook, the switch of `current`, restart and
//! health check, and the rollback to the previous release when any of them fails.

use futures::FutureExt;
use tracing::warn;

use super::hooks::HookEnv;
use super::progress::{Phase, Reporter};
use super::store::{Active, Journal, JournalPhase};
use super::{Releases, blocking, cancellable};

impl Releases {
    /// Pre-switch hook, switch, restart, health check; reverts on failure after the switch.
    /// `resume`: the switch already happened before an agent restart.
    pub(super) async fn activate(
        &mut self,
        journal: &mut Journal,
        active: &Active,
        rep: &mut Reporter<'_>,
        resume: bool,
    ) -> (Phase, String) {
        let target = &active.target;
        let mut stop = self.stop.clone();
        let env = HookEnv {
            dir: self.layout.release_dir(&target.version),
            release: target.clone(),
            previous: active.previous.as_ref().map(|p| p.version.clone()),
        };
        if !resume {
            if let Some(ended) = self.pre_switch(&env, rep, &mut stop).await {
                return ended;
            }
            let mut switching = active.clone();
            switching.phase = JournalPhase::Switching;
            journal.active = Some(switching);
            if let Err(e) = self.write_journal(journal).await {
                return (Phase::Failed, e.to_string());
            }
            rep.phase(
                Phase::Switching,
                format!("switching current to {}", target.version),
            );
            let layout = self.layout.clone();
            let version = target.version.clone();
            if let Err(e) = blocking(move || layout.switch(Some(&version))).await {
                // The rename did not happen (or did, and the fsync failed): put back what was.
                let why = format!("switch failed: {e}");
                return self.revert(journal, active, rep, why).boxed().await;
            }
        }
        if !self.hooks.restart.is_empty() {
            rep.phase(
                Phase::Restarting,
                format!("restarting on {}", target.version),
            );
            let run = self.hooks.run(&self.hooks.restart, &env).boxed();
            let result = cancellable(&mut stop, run).await.unwrap_or_else(cancelled);
            if let Err(why) = result {
                let why = format!("restart command failed on {}: {why}", target.version);
                return self.revert(journal, active, rep, why).boxed().await;
            }
        }
        if !self.hooks.health.is_empty() {
            rep.phase(
                Phase::HealthCheck,
                format!("checking the health of {}", target.version),
            );
            let check = self.hooks.health_check(&env).boxed();
            let result = cancellable(&mut stop, check)
                .await
                .unwrap_or_else(cancelled);
            if let Err(why) = result {
                let why = format!("health check of {} failed: {why}", target.version);
                return self.revert(journal, active, rep, why).boxed().await;
            }
        }
        let message = if resume {
            format!(
                "release {} runs (finished after an agent restart)",
                target.version
            )
        } else {
            format!("release {} runs", target.version)
        };
        (Phase::Done, message)
    }

    /// Runs the pre-switch command, if any; the outcome when it ends the deployment (it failed,
    /// or a cancel stopped it: nothing is switched either way).
    async fn pre_switch(
        &self,
        env: &HookEnv,
        rep: &mut Reporter<'_>,
        stop: &mut tokio::sync::watch::Receiver<bool>,
    ) -> Option<(Phase, String)> {
        if self.hooks.pre_switch.is_empty() {
            return None;
        }
        rep.phase(Phase::PreSwitch, "running the pre-switch command");
        let run = self.hooks.run(&self.hooks.pre_switch, env).boxed();
        match cancellable(stop, run).await {
            Some(Ok(())) => None,
            Some(Err(why)) => Some((
                Phase::Failed,
                format!("pre-switch command failed, nothing switched: {why}"),
            )),
            None => Some((
                Phase::Cancelled,
                "cancelled during the pre-switch command, nothing switched".to_owned(),
            )),
        }
    }

    /// Switches back to the previous release (or to none) and restarts it.
    pub(super) async fn revert(
        &mut self,
        journal: &mut Journal,
        active: &Active,
        rep: &mut Reporter<'_>,
        why: String,
    ) -> (Phase, String) {
        warn!(command_id = %active.command_id, reason = %why, "rolling back");
        let mut rolling = active.clone();
        rolling.phase = JournalPhase::RollingBack;
        rolling.reason = why.clone();
        journal.active = Some(rolling);
        if let Err(e) = self.write_journal(journal).await {
            warn!(error = %e, "cannot record the rollback in the journal; rolling back anyway");
        }
        let previous = active.previous.clone();
        let back_to = previous.as_ref().map_or_else(
            || "no release (there was none before; current removed)".to_owned(),
            |p| p.version.clone(),
        );
        rep.phase(
            Phase::Switching,
            format!("{why}; switching back to {back_to}"),
        );
        let layout = self.layout.clone();
        let version = previous.as_ref().map(|p| p.version.clone());
        if let Err(e) = blocking(move || layout.switch(version.as_deref())).await {
            return (
                Phase::Failed,
                format!("{why}; switching back to {back_to} failed too: {e}"),
            );
        }
        let mut message = format!("{why}; rolled back to {back_to}");
        if let Some(prev) = &previous
            && !self.hooks.restart.is_empty()
        {
            rep.phase(Phase::Restarting, format!("restarting on {}", prev.version));
            let env = HookEnv {
                dir: self.layout.release_dir(&prev.version),
                release: prev.clone(),
                previous: Some(active.target.version.clone()),
            };
            if let Err(e) = self.hooks.run(&self.hooks.restart, &env).boxed().await {
                message.push_str(&format!("; restarting {} failed too: {e}", prev.version));
            }
        }
        (Phase::RolledBack, message)
    }
}

/// The error of a hook that a `cancel` stopped after the switch: it rolls back like a failure.
fn cancelled() -> Result<(), String> {
    Err("cancelled by the gateway".to_owned())
}
