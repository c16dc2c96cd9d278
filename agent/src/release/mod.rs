//! Release execution: fetch a release's manifest and missing blobs, assemble it, switch
//! `current` atomically, restart, health-check, roll back on failure, garbage-collect.
//!
//! Layout under the state directory:
//!
//! ```text
//! blobs/sha256/<hex>          content store, one file per blob (verified before it lands here)
//! blobs/tmp/<hex>.partial     downloads in progress, resumed with `Range` after a crash
//! releases/<version>/         complete releases only (hard links into the store, or copies)
//!   .lekiwi/manifest.json     the manifest, byte for byte as fetched
//!   .lekiwi/release.json      {"version": .., "digest": ..}
//! releases/.tmp-<version>-<rand>/   a release being assembled
//! current -> releases/<version>     switched by `current.new` + rename
//! deploy.json                 journal: the deployment in progress, recent command ids, history
//! ```
//!
//! Crash safety: the journal is written (atomically) before every irreversible step, releases
//! appear under their final name only when complete and fsync'd, and `current` is replaced by a
//! rename. An agent killed at any point therefore leaves `current` on a complete release, and
//! [`Releases::recover`] finishes or rolls back the interrupted deployment at the next start.
//!
//! Release files are hard links to the store: the robot's software must treat its release
//! directory as read-only. A store blob that was modified anyway fails verification and is
//! downloaded again.

mod activate;
mod error;
mod fetch;
mod hooks;
mod prepare;
mod progress;
mod store;
#[cfg(test)]
mod tests;

pub(crate) use hooks::kill_group;
use std::sync::Arc;

use futures::FutureExt;
use lekiwi_protocol::Release;
use lekiwi_protocol::release::{ManifestError, digest_hex};
use tokio::sync::mpsc::UnboundedSender;
use tracing::{info, warn};

use crate::config::Config;
use error::io;
pub use error::{Error, Result};
use fetch::Client;
pub use fetch::GatewayAccess;
/// The blob client, which the fleet simulator shares among its robots.
pub(crate) use fetch::{Caller, Client as BlobClient};
use hooks::Hooks;
use prepare::Wanted;
pub use progress::{Outcome, Phase, Progress};
use progress::{Reporter, Tally};
pub(crate) use store::sha256_digest;
use store::{Active, Finished, Journal, JournalPhase, Layout};

/// Runs blocking file system work off the (single-threaded) runtime.
///
/// The job is boxed so that tokio's task machinery is instantiated once rather than once per
/// call site (about 100 KB of the release binary).
async fn blocking<T: Send + 'static>(f: impl FnOnce() -> Result<T> + Send + 'static) -> Result<T> {
    let (tx, rx) = tokio::sync::oneshot::channel();
    let job: Box<dyn FnOnce() + Send> = Box::new(move || {
        let _ = tx.send(f());
    });
    drop(tokio::task::spawn_blocking(job));
    rx.await
        .map_err(|_| Error::Task("a blocking file system task panicked".into()))?
}

/// The robot's releases: the content store, the release directories and `current`.
///
/// Owned by one task at a time; `deploy`, `rollback` and `recover` take `&mut self` and their
/// futures are `Send`, so the run loop can move the whole value into a spawned task.
// shape: its methods by step of a deployment: here the store and what the gateway asked for,
// prepare.rs making the release complete on disk, activate.rs the switch, health check and
// rollback.
pub struct Releases {
    layout: Layout,
    client: Client,
    hooks: Hooks,
    keep: usize,
    /// Set to true by the holder of the matching sender to cancel the command running now
    /// (see [`Releases::cancel_handle`]).
    stop: tokio::sync::watch::Receiver<bool>,
}

impl Releases {
    /// Opens (and creates) the release store in the configured state directory.
    pub fn open(config: &Config, gateway: GatewayAccess) -> Result<Self> {
        let layout = Layout::new(&config.state_dir);
        layout.create()?;
        let mut client = Client::new(gateway)?;
        client.pace = fetch::Pace::new(config.release_download_rate_limit).map(Arc::new);
        Ok(Self {
            layout,
            client,
            hooks: Hooks::from_config(config),
            keep: (config.release_keep as usize).max(1),
            stop: tokio::sync::watch::channel(false).1,
        })
    }

    /// Replaces the gateway address and credentials, e.g. after enrollment.
    pub fn set_gateway(&mut self, gateway: GatewayAccess) -> Result<()> {
        let pace = self.client.pace.take();
        self.client = Client::new(gateway)?;
        self.client.pace = pace;
        Ok(())
    }

    /// A new handle that cancels the next command (`deploy` or `rollback`) and replaces the
    /// previous one: sending `true` stops a download, a verification, an assembly or the
    /// pre-switch command within moments and reports `cancelled` with the release that ran
    /// before untouched (downloaded blobs and partial files stay for a later resume); after the
    /// switch it switches back and reports `rolled_back`.
    pub fn cancel_handle(&mut self) -> tokio::sync::watch::Sender<bool> {
        let (tx, rx) = tokio::sync::watch::channel(false);
        self.stop = rx;
        tx
    }

    /// Replaces the robot's token only (it changes once, at enrollment).
    pub fn set_token(&mut self, token: impl Into<String>) {
        self.client.set_token(token.into());
    }

    /// The release `current` points at, if any.
    pub fn current(&self) -> Option<Release> {
        self.layout.current()
    }

    /// Downloads the blob `digest` (at most `limit` bytes) into memory and verifies its digest:
    /// an agent build for `lekiwi-agent`'s self-update (see [`crate::selfupdate`]).
    pub async fn fetch_verified(&self, url: &str, digest: &str, limit: usize) -> Result<Vec<u8>> {
        digest_hex(digest)?;
        let bytes = self.client.get_small(url, limit).await?;
        let actual = store::sha256_digest(&bytes);
        if actual != digest {
            return Err(Error::DigestMismatch {
                what: format!("agent build {url}"),
                expected: digest.to_owned(),
                actual,
            });
        }
        Ok(bytes)
    }

    /// Deploys `release`, whose manifest is at `manifest_url` (a path relative to the gateway's
    /// base URL). Reports progress on `progress`; the last report matches the outcome.
    pub async fn deploy(
        &mut self,
        command_id: &str,
        release: &Release,
        manifest_url: &str,
        progress: &UnboundedSender<Progress>,
    ) -> Outcome {
        self.run(command_id, release, Some(manifest_url), progress)
            .await
    }

    /// Switches back to `release`: instantly if it is still kept on disk, else by deploying it
    /// from its manifest blob (`/v1/blobs/<digest>`).
    pub async fn rollback(
        &mut self,
        command_id: &str,
        release: &Release,
        progress: &UnboundedSender<Progress>,
    ) -> Outcome {
        self.run(command_id, release, None, progress).await
    }

    /// Finishes what an interrupted deployment left: called once at agent start, before any
    /// command. `None` if nothing was interrupted.
    pub async fn recover(&mut self, progress: &UnboundedSender<Progress>) -> Option<Outcome> {
        let mut journal = self.load_journal().await;
        let layout = self.layout.clone();
        if let Err(e) = blocking(move || layout.clean_temporaries()).await {
            warn!(error = %e, "cannot clean temporary release files");
        }
        let active = journal.active.clone()?;
        let mut rep = Reporter::new(progress, &active.command_id);
        let current = self.current();
        let switched = current.as_ref() == Some(&active.target);
        info!(
            command_id = %active.command_id,
            phase = ?active.phase,
            release = %active.target.version,
            switched,
            "recovering an interrupted deployment"
        );
        let outcome = match active.phase {
            JournalPhase::Preparing | JournalPhase::Switching if !switched => {
                // The gateway resends the command, possibly with the same id: forget it.
                journal.active = None;
                self.save_journal(&journal).await;
                let message = "interrupted before the switch; the gateway will resend".to_owned();
                rep.phase(Phase::Failed, message.clone());
                return Some(Outcome {
                    phase: Phase::Failed,
                    message,
                    current,
                    bytes_downloaded: 0,
                    files_downloaded: 0,
                    files_reused: 0,
                });
            }
            JournalPhase::Preparing | JournalPhase::Switching => {
                self.activate(&mut journal, &active, &mut rep, true)
                    .boxed()
                    .await
            }
            JournalPhase::RollingBack => {
                let why = format!(
                    "{} (rollback finished after an agent restart)",
                    active.reason
                );
                self.revert(&mut journal, &active, &mut rep, why)
                    .boxed()
                    .await
            }
        };
        Some(
            self.finish(
                &mut journal,
                &active.command_id,
                outcome,
                Tally::default(),
                &mut rep,
            )
            .await,
        )
    }

    async fn run(
        &mut self,
        command_id: &str,
        release: &Release,
        manifest_url: Option<&str>,
        progress: &UnboundedSender<Progress>,
    ) -> Outcome {
        let mut journal = self.load_journal().await;
        if journal.active.is_some() {
            // The loop should have called `recover` at start; do it now rather than deploy on
            // top of an unfinished switch.
            self.recover(progress).await;
            journal = self.load_journal().await;
        }
        let mut rep = Reporter::new(progress, command_id);
        if let Some(done) = journal.recent.iter().find(|f| f.command_id == command_id) {
            let message = format!(
                "command {command_id} was already executed: {}",
                done.message
            );
            rep.send(done.phase, None, message.clone());
            return Outcome {
                phase: done.phase,
                message,
                current: self.current(),
                bytes_downloaded: 0,
                files_downloaded: 0,
                files_reused: 0,
            };
        }
        let mut tally = Tally::default();
        let outcome = self
            .execute(
                &mut journal,
                command_id,
                release,
                manifest_url,
                &mut rep,
                &mut tally,
            )
            .await;
        self.finish(&mut journal, command_id, outcome, tally, &mut rep)
            .await
    }

    /// Records the end of a command in the journal, collects garbage after a success, and
    /// sends the final report.
    async fn finish(
        &mut self,
        journal: &mut Journal,
        command_id: &str,
        (phase, message): (Phase, String),
        tally: Tally,
        rep: &mut Reporter<'_>,
    ) -> Outcome {
        journal.active = None;
        journal.remember(Finished {
            command_id: command_id.to_owned(),
            phase,
            message: message.clone(),
        });
        let current = self.current();
        if let Some(c) = &current {
            journal.touch(&c.version);
        }
        self.save_journal(journal).await;
        if phase == Phase::Done {
            let (layout, keep, history) = (self.layout.clone(), self.keep, journal.history.clone());
            match blocking(move || layout.collect_garbage(keep, &history)).await {
                Ok(gc) if gc.releases + gc.blobs > 0 => {
                    info!(
                        releases = gc.releases,
                        blobs = gc.blobs,
                        "old releases collected"
                    );
                }
                Ok(_) => {}
                Err(e) => warn!(error = %e, "garbage collection failed"),
            }
        }
        rep.bytes_downloaded = tally.bytes;
        let percent = (phase == Phase::Done).then_some(100.0);
        rep.send(phase, percent, message.clone());
        Outcome {
            phase,
            message,
            current,
            bytes_downloaded: tally.bytes,
            files_downloaded: tally.files_downloaded,
            files_reused: tally.files_reused,
        }
    }

    async fn execute(
        &mut self,
        journal: &mut Journal,
        command_id: &str,
        release: &Release,
        manifest_url: Option<&str>,
        rep: &mut Reporter<'_>,
        tally: &mut Tally,
    ) -> (Phase, String) {
        let failed = |e: Error| (Phase::Failed, e.to_string());
        if let Err(e) = validate_release(release) {
            return failed(e);
        }
        let previous = self.current();
        if previous.as_ref() == Some(release) {
            return (
                Phase::Done,
                format!("release {} is already current", release.version),
            );
        }
        let active = Active {
            command_id: command_id.to_owned(),
            target: release.clone(),
            previous,
            phase: JournalPhase::Preparing,
            reason: String::new(),
        };
        journal.active = Some(active.clone());
        if let Err(e) = self.write_journal(journal).await {
            return failed(e);
        }
        let mut stop = self.stop.clone();
        let prepared = cancellable(
            &mut stop,
            self.prepare(release, manifest_url, rep, tally).boxed(),
        )
        .await;
        if !matches!(prepared, Some(Ok(()))) {
            let layout = self.layout.clone();
            if let Err(e) = blocking(move || layout.clean_temporaries()).await {
                warn!(error = %e, "cannot clean temporary release files");
            }
        }
        match prepared {
            Some(Ok(())) => {}
            Some(Err(e)) => return failed(e),
            None => {
                let message = format!(
                    "cancelled before the switch to {}; {} bytes downloaded are kept for a later resume",
                    release.version, rep.bytes_downloaded
                );
                return (Phase::Cancelled, message);
            }
        }
        self.activate(journal, &active, rep, false).boxed().await
    }

    async fn load_journal(&self) -> Journal {
        let layout = self.layout.clone();
        match blocking(move || Journal::load(&layout)).await {
            Ok(j) => j,
            Err(e) => {
                warn!(error = %e, "cannot read the deploy journal; starting a new one");
                Journal::default()
            }
        }
    }

    async fn write_journal(&self, journal: &Journal) -> Result<()> {
        let layout = self.layout.clone();
        let journal = journal.clone();
        blocking(move || journal.save(&layout)).await
    }

    /// Saves the journal where a failure cannot change the outcome any more; logs it.
    async fn save_journal(&self, journal: &Journal) {
        if let Err(e) = self.write_journal(journal).await {
            warn!(error = %e, "cannot write the deploy journal");
        }
    }
}

/// Runs `work` unless `stop` turns true first (`None` then, and `work` is dropped where it
/// stands). A dropped sender never cancels.
pub(crate) async fn cancellable<T>(
    stop: &mut tokio::sync::watch::Receiver<bool>,
    work: impl Future<Output = T>,
) -> Option<T> {
    let stopped = async {
        if stop.wait_for(|s| *s).await.is_err() {
            std::future::pending::<()>().await;
        }
    };
    tokio::select! {
        out = work => Some(out),
        () = stopped => None,
    }
}

fn validate_release(release: &Release) -> Result<()> {
    digest_hex(&release.digest)?;
    // A leading dot would hide the release among the store's own temporary directories.
    if !lekiwi_protocol::release::valid_version(&release.version)
        || release.version.starts_with('.')
    {
        return Err(ManifestError::Version(release.version.clone()).into());
    }
    Ok(())
}
