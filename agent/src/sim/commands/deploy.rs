//! A `deploy` or `rollback` on a simulated robot, step by step as the agent's release code
//! (`crate::release`) goes: the manifest and the blobs the robot lacks over the real blob API
//! (really transferred, verified and discarded, resumed with `Range` after a cut), then the
//! simulated pre-switch, switch, restart and health check, reporting the same phases with the
//! same messages, and the robot's fault (`--*-share`) where it strikes.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use lekiwi_protocol::Release;
use lekiwi_protocol::release::{blob_path, digest_hex, valid_version};
use tokio::sync::watch;

use super::args::Fault;
use super::disk::Disk;
use super::download::{Wanted, download, manifest};
use super::shared::Known;
use super::task::{Reporter, Tally, Task};
use crate::release::{Error, Outcome, Phase, cancellable};

/// Deploys `release` (its manifest at `manifest_url`, or, for a rollback, at its blob path)
/// on `disk`; the last report sent matches the outcome.
pub(super) async fn run(
    task: &Task,
    disk: &mut Disk,
    command_id: &str,
    release: &Release,
    manifest_url: Option<&str>,
) -> Outcome {
    let mut rep = Reporter::new(&task.tx, command_id);
    let mut tally = Tally::default();
    let (phase, message) = execute(task, disk, release, manifest_url, &mut rep, &mut tally).await;
    task.shared.counters.ended(phase);
    if phase == Phase::Done {
        disk.collect_garbage();
    }
    rep.bytes = tally.bytes;
    rep.send(
        phase,
        (phase == Phase::Done).then_some(100.0),
        message.clone(),
    );
    Outcome {
        phase,
        message,
        current: disk.current().map(|k| k.release.clone()),
        bytes_downloaded: tally.bytes,
        files_downloaded: tally.files_downloaded,
        files_reused: tally.files_reused,
    }
}

async fn execute(
    task: &Task,
    disk: &mut Disk,
    release: &Release,
    manifest_url: Option<&str>,
    rep: &mut Reporter<'_>,
    tally: &mut Tally,
) -> (Phase, String) {
    if let Err(e) = validate_release(release) {
        return (Phase::Failed, e);
    }
    if disk.current().is_some_and(|k| k.release == *release) {
        let message = format!("release {} is already current", release.version);
        return (Phase::Done, message);
    }
    let previous = disk.current().cloned();
    let fault = task
        .shared
        .args
        .fault_of(&task.robot.name, &release.version);
    let mut stop = task.stop.clone();
    let prepare = prepare(task, disk, release, manifest_url, fault, rep, tally);
    let known = match cancellable(&mut stop, prepare).await {
        Some(Ok(known)) => known,
        Some(Err(e)) => return (Phase::Failed, e),
        None => {
            let message = format!(
                "cancelled before the switch to {}; {} bytes downloaded are kept for a later resume",
                release.version, rep.bytes
            );
            return (Phase::Cancelled, message);
        }
    };
    let steps = Activation {
        task,
        previous,
        target: known,
        fault,
    };
    steps.run(disk, rep, &mut stop).await
}

/// A digest and a version the agent would accept.
fn validate_release(release: &Release) -> Result<(), String> {
    digest_hex(&release.digest).map_err(|e| Error::from(e).to_string())?;
    if !valid_version(&release.version) || release.version.starts_with('.') {
        let e = lekiwi_protocol::release::ManifestError::Version(release.version.clone());
        return Err(Error::from(e).to_string());
    }
    Ok(())
}

/// Makes the release "complete on disk": kept already, or its manifest and missing blobs
/// downloaded; the release.
async fn prepare(
    task: &Task,
    disk: &mut Disk,
    release: &Release,
    manifest_url: Option<&str>,
    fault: Fault,
    rep: &mut Reporter<'_>,
    tally: &mut Tally,
) -> Result<Arc<Known>, String> {
    if let Some(known) = disk.kept(release) {
        let message = format!(
            "release {} is kept on disk; nothing to download",
            release.version
        );
        rep.phase(Phase::Assembling, message);
        return Ok(known);
    }
    let url = manifest_url.map_or_else(|| blob_path(&release.digest), str::to_owned);
    rep.phase(
        Phase::Downloading,
        format!("fetching the manifest of {}", release.version),
    );
    let known = manifest(task, disk, release, &url, tally).await?;
    check_manifest(release, &known)?;
    // One entry per distinct blob, named by its first file.
    let mut blobs: BTreeMap<&str, (&str, u64)> = BTreeMap::new();
    for f in &known.manifest.files {
        blobs.entry(&f.digest).or_insert((&f.path, f.size));
    }
    let missing: Vec<Wanted<'_>> = {
        let held = disk.held();
        tally.files_reused = known
            .manifest
            .files
            .iter()
            .filter(|f| held.contains(f.digest.as_str()))
            .count();
        blobs
            .iter()
            .filter(|(d, _)| !held.contains(**d))
            .map(|(d, (path, size))| Wanted {
                digest: d,
                path,
                size: *size,
            })
            .collect()
    };
    download(task, disk, &missing, fault, rep, tally).await?;
    let reused = tally.files_reused;
    rep.phase(
        Phase::Verifying,
        format!("verifying {reused} files already held"),
    );
    let files = known.manifest.files.len();
    rep.phase(Phase::Assembling, format!("assembling {files} files"));
    disk.assemble(known.clone());
    Ok(known)
}

/// The agent's checks of a manifest against its command.
fn check_manifest(release: &Release, known: &Known) -> Result<(), String> {
    let manifest = &known.manifest;
    if manifest.version != release.version {
        return Err(format!(
            "the manifest names version {:?}, the command {:?}",
            manifest.version, release.version
        ));
    }
    if let Some(f) = manifest
        .files
        .iter()
        .find(|f| f.path == ".lekiwi" || f.path.starts_with(".lekiwi/"))
    {
        return Err(format!(
            "the manifest has {:?}: .lekiwi/ is reserved for the agent",
            f.path
        ));
    }
    Ok(())
}

/// The irreversible half: pre-switch, switch, restart, health check, and the switch back when
/// one fails after the switch.
struct Activation<'a> {
    task: &'a Task,
    previous: Option<Arc<Known>>,
    target: Arc<Known>,
    fault: Fault,
}

/// Waits out a simulated hook of `d`; false if a `cancel` came first.
async fn hook(stop: &mut watch::Receiver<bool>, d: Duration) -> bool {
    cancellable(stop, tokio::time::sleep(d)).await.is_some()
}

impl Activation<'_> {
    async fn run(
        self,
        disk: &mut Disk,
        rep: &mut Reporter<'_>,
        stop: &mut watch::Receiver<bool>,
    ) -> (Phase, String) {
        let args = &self.task.shared.args;
        let version = self.target.release.version.clone();
        if let Some(d) = args.pre_switch_seconds.0 {
            rep.phase(Phase::PreSwitch, "running the pre-switch command");
            if !hook(stop, d).await {
                let message = "cancelled during the pre-switch command, nothing switched";
                return (Phase::Cancelled, message.to_owned());
            }
        }
        rep.phase(Phase::Switching, format!("switching current to {version}"));
        disk.switch(Some(self.target.clone()));
        if let Some(d) = args.restart_seconds.0 {
            rep.phase(Phase::Restarting, format!("restarting on {version}"));
            if !hook(stop, d).await {
                let why = format!("restart command failed on {version}: cancelled by the gateway");
                return self.revert(disk, rep, why).await;
            }
        }
        if let Some(d) = args.health_check_seconds.0 {
            rep.phase(
                Phase::HealthCheck,
                format!("checking the health of {version}"),
            );
            let failing = self.fault == Fault::FailHealth;
            let wait = if failing { args.health_timeout() } else { d };
            let why = if !hook(stop, wait).await {
                Some("cancelled by the gateway".to_owned())
            } else {
                failing.then(|| {
                    let secs = wait.as_secs_f64();
                    format!("not healthy within {secs}s; last: the simulated health check failed")
                })
            };
            if let Some(why) = why {
                let why = format!("health check of {version} failed: {why}");
                return self.revert(disk, rep, why).await;
            }
        }
        (Phase::Done, format!("release {version} runs"))
    }

    /// Switches back to the previous release (or to none) and restarts it.
    async fn revert(self, disk: &mut Disk, rep: &mut Reporter<'_>, why: String) -> (Phase, String) {
        let back_to = self.previous.as_ref().map_or_else(
            || "no release (there was none before; current removed)".to_owned(),
            |p| p.release.version.clone(),
        );
        rep.phase(
            Phase::Switching,
            format!("{why}; switching back to {back_to}"),
        );
        disk.switch(self.previous.clone());
        if let (Some(prev), Some(d)) = (&self.previous, self.task.shared.args.restart_seconds.0) {
            rep.phase(
                Phase::Restarting,
                format!("restarting on {}", prev.release.version),
            );
            tokio::time::sleep(d).await;
        }
        (
            Phase::RolledBack,
            format!("{why}; rolled back to {back_to}"),
        )
    }
}
