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

mod fetch;
mod hooks;
mod store;
#[cfg(test)]
mod tests;

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use futures::stream::FuturesUnordered;
use futures::{FutureExt, StreamExt};
use lekiwi_protocol::release::{ManifestError, ReleaseManifest, blob_path, digest_hex};
use lekiwi_protocol::{AgentMessage, Release};
use tokio::sync::mpsc::UnboundedSender;
use tracing::{info, warn};

use crate::config::Config;
pub use fetch::GatewayAccess;
use fetch::{Client, Fetched};
use hooks::{HookEnv, Hooks};
use store::{Active, Finished, Journal, JournalPhase, Layout};

/// Blobs downloaded at the same time.
const DOWNLOAD_CONCURRENCY: usize = 4;
/// Attempts per blob within one deployment (each resumes where the previous stopped).
const DOWNLOAD_ATTEMPTS: u32 = 3;
/// Least time between two progress reports of the same phase.
const PROGRESS_EVERY: Duration = Duration::from_millis(500);

/// Errors of the release machinery; most end a deployment as `failed` with this text.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file or directory of the release store could not be read or written.
    #[error("release store: {path}: {source}")]
    Io {
        /// The path.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The gateway's URL, the CA file or a header value is unusable.
    #[error("gateway access: {0}")]
    Access(String),
    /// The gateway could not be reached or the transfer broke off.
    #[error("fetching {url}: {message}")]
    Transport {
        /// What was fetched.
        url: String,
        /// Why it failed.
        message: String,
    },
    /// The gateway refused the robot's token (HTTP 401).
    #[error("the gateway refused the robot's token for {url}: {message}")]
    Unauthorized {
        /// What was fetched.
        url: String,
        /// The gateway's message.
        message: String,
    },
    /// The release's manifest is not on the gateway (HTTP 404).
    #[error("release {0} unknown to the gateway")]
    UnknownRelease(String),
    /// A blob of the manifest is not on the gateway (HTTP 404).
    #[error("blob {digest} of {path} unknown to the gateway")]
    UnknownBlob {
        /// Its digest.
        digest: String,
        /// The first file that has this content.
        path: String,
    },
    /// Another HTTP status.
    #[error("fetching {url}: HTTP {status}: {message}")]
    Status {
        /// What was fetched.
        url: String,
        /// The status code.
        status: u16,
        /// The gateway's message.
        message: String,
    },
    /// Content does not hash to its digest.
    #[error("{what}: digest mismatch: expected {expected}, got {actual}")]
    DigestMismatch {
        /// The file or manifest.
        what: String,
        /// The digest asked for.
        expected: String,
        /// The digest of what arrived.
        actual: String,
    },
    /// More bytes than the manifest announced.
    #[error("{what}: more than the {size} bytes the manifest announces")]
    TooLarge {
        /// The file or manifest.
        what: String,
        /// The announced size.
        size: u64,
    },
    /// The manifest is invalid.
    #[error("invalid manifest: {0}")]
    Manifest(#[from] ManifestError),
    /// The command itself is unusable (bad digest, version, URL or a manifest that does not
    /// fit the release).
    #[error("{0}")]
    Invalid(String),
    /// A blocking task died.
    #[error("release task failed: {0}")]
    Task(String),
}

/// Result of this module.
pub type Result<T, E = Error> = std::result::Result<T, E>;

fn io(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> Error {
    let path = path.into();
    move |source| Error::Io { path, source }
}

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

/// Phase of a command, as reported in `progress.phase` (the protocol's own type).
pub use lekiwi_protocol::ProgressPhase as Phase;

/// One progress report of a command; the last one of a command has phase `done`, `failed` or
/// `rolled_back` and matches the [`Outcome`].
#[derive(Clone, Debug, PartialEq)]
pub struct Progress {
    /// The command reported on.
    pub command_id: String,
    /// Its phase.
    pub phase: Phase,
    /// Percent done, while downloading and at the end.
    pub percent: Option<f64>,
    /// Details.
    pub message: String,
    /// Bytes received so far.
    pub bytes_downloaded: u64,
    /// Bytes to receive in all (the blobs missing from the store).
    pub bytes_total: u64,
}

impl Progress {
    /// The durable wire message for this report.
    pub fn to_message(&self, seq: u64) -> AgentMessage {
        AgentMessage::Progress {
            seq,
            command_id: self.command_id.clone(),
            phase: self.phase.as_str().to_owned(),
            percent: self.percent,
            message: self.message.clone(),
        }
    }
}

/// How a command ended.
#[derive(Clone, Debug, PartialEq)]
pub struct Outcome {
    /// `done`, `failed` or `rolled_back`.
    pub phase: Phase,
    /// Why, or what happened.
    pub message: String,
    /// The release `current` points at now.
    pub current: Option<Release>,
    /// Bytes received from the gateway (manifest included).
    pub bytes_downloaded: u64,
    /// Blobs downloaded.
    pub files_downloaded: usize,
    /// Files of the release whose content was already in the store.
    pub files_reused: usize,
}

/// Sends progress: every phase change, and within a phase at most every [`PROGRESS_EVERY`].
struct Reporter<'a> {
    tx: &'a UnboundedSender<Progress>,
    command_id: String,
    phase: Option<Phase>,
    last: Option<Instant>,
    bytes_downloaded: u64,
    bytes_total: u64,
}

impl<'a> Reporter<'a> {
    fn new(tx: &'a UnboundedSender<Progress>, command_id: &str) -> Self {
        Self {
            tx,
            command_id: command_id.to_owned(),
            phase: None,
            last: None,
            bytes_downloaded: 0,
            bytes_total: 0,
        }
    }

    fn send(&mut self, phase: Phase, percent: Option<f64>, message: String) {
        info!(command_id = %self.command_id, phase = %phase, %message, "release progress");
        self.phase = Some(phase);
        self.last = Some(Instant::now());
        // A closed channel means nobody listens any more; the work goes on regardless.
        let _ = self.tx.send(Progress {
            command_id: self.command_id.clone(),
            phase,
            percent,
            message,
            bytes_downloaded: self.bytes_downloaded,
            bytes_total: self.bytes_total,
        });
    }

    /// A phase change: always sent.
    fn phase(&mut self, phase: Phase, message: impl Into<String>) {
        self.send(phase, None, message.into());
    }

    /// Download progress: sent unless the last report is younger than [`PROGRESS_EVERY`].
    fn downloaded(&mut self, bytes: u64, message: impl FnOnce() -> String) {
        self.bytes_downloaded = bytes;
        if self.last.is_some_and(|t| t.elapsed() < PROGRESS_EVERY) {
            return;
        }
        let percent = if self.bytes_total == 0 {
            100.0
        } else {
            (bytes as f64 * 100.0 / self.bytes_total as f64).min(100.0)
        };
        self.send(Phase::Downloading, Some(percent), message());
    }
}

/// Counters of one deployment.
#[derive(Default)]
struct Tally {
    bytes: u64,
    files_downloaded: usize,
    files_reused: usize,
}

/// The robot's releases: the content store, the release directories and `current`.
///
/// Owned by one task at a time; `deploy`, `rollback` and `recover` take `&mut self` and their
/// futures are `Send`, so the run loop can move the whole value into a spawned task.
pub struct Releases {
    layout: Layout,
    client: Client,
    hooks: Hooks,
    keep: usize,
}

impl Releases {
    /// Opens (and creates) the release store in the configured state directory.
    pub fn open(config: &Config, gateway: GatewayAccess) -> Result<Self> {
        let layout = Layout::new(&config.state_dir);
        layout.create()?;
        Ok(Self {
            layout,
            client: Client::new(gateway)?,
            hooks: Hooks::from_config(config),
            keep: (config.release_keep as usize).max(1),
        })
    }

    /// Replaces the gateway address and credentials, e.g. after enrollment.
    pub fn set_gateway(&mut self, gateway: GatewayAccess) -> Result<()> {
        self.client = Client::new(gateway)?;
        Ok(())
    }

    /// Replaces the robot's token only (it changes once, at enrollment).
    pub fn set_token(&mut self, token: impl Into<String>) {
        self.client.set_token(token.into());
    }

    /// The release `current` points at, if any.
    pub fn current(&self) -> Option<Release> {
        self.layout.current()
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
        if let Err(e) = self
            .prepare(release, manifest_url, rep, tally)
            .boxed()
            .await
        {
            let layout = self.layout.clone();
            if let Err(e) = blocking(move || layout.clean_temporaries()).await {
                warn!(error = %e, "cannot clean temporary release files");
            }
            return failed(e);
        }
        self.activate(journal, &active, rep, false).boxed().await
    }

    /// Makes `releases/<version>/` exist and be complete.
    async fn prepare(
        &mut self,
        release: &Release,
        manifest_url: Option<&str>,
        rep: &mut Reporter<'_>,
        tally: &mut Tally,
    ) -> Result<()> {
        let layout = self.layout.clone();
        let r = release.clone();
        if blocking(move || Ok(layout.installed(&r))).await? {
            rep.phase(
                Phase::Assembling,
                format!(
                    "release {} is kept on disk; nothing to download",
                    release.version
                ),
            );
            return Ok(());
        }
        let url = manifest_url.map_or_else(|| blob_path(&release.digest), str::to_owned);
        rep.phase(
            Phase::Downloading,
            format!("fetching the manifest of {}", release.version),
        );
        let (bytes, manifest) = self.manifest(release, &url, tally).boxed().await?;
        if manifest.version != release.version {
            return Err(Error::Invalid(format!(
                "the manifest names version {:?}, the command {:?}",
                manifest.version, release.version
            )));
        }
        if let Some(f) = manifest.files.iter().find(|f| {
            f.path == store::META_DIR || f.path.starts_with(&format!("{}/", store::META_DIR))
        }) {
            return Err(Error::Invalid(format!(
                "the manifest has {:?}: {}/ is reserved for the agent",
                f.path,
                store::META_DIR
            )));
        }

        // One entry per distinct blob, named by its first file for messages.
        let mut blobs: BTreeMap<&str, (&str, u64)> = BTreeMap::new();
        for f in &manifest.files {
            blobs
                .entry(f.digest.as_str())
                .or_insert((f.path.as_str(), f.size));
        }
        let layout = self.layout.clone();
        let digests: Vec<String> = blobs.keys().map(|d| (*d).to_owned()).collect();
        let held = blocking(move || Ok(layout.held(&digests))).await?;
        let missing: Vec<Wanted> = blobs
            .iter()
            .filter(|(d, _)| !held.contains(**d))
            .map(|(d, (p, s))| Wanted {
                digest: (*d).to_owned(),
                path: (*p).to_owned(),
                size: *s,
            })
            .collect();
        tally.files_reused = manifest
            .files
            .iter()
            .filter(|f| held.contains(&f.digest))
            .count();
        self.download(&missing, rep, tally).boxed().await?;

        rep.phase(
            Phase::Verifying,
            format!("verifying {} files already held", tally.files_reused),
        );
        let layout = self.layout.clone();
        let reused: Vec<Wanted> = blobs
            .iter()
            .filter(|(d, _)| held.contains(**d))
            .map(|(d, (p, s))| Wanted {
                digest: (*d).to_owned(),
                path: (*p).to_owned(),
                size: *s,
            })
            .collect();
        let corrupt = blocking(move || layout.verify(reused)).await?;
        if !corrupt.is_empty() {
            warn!(
                count = corrupt.len(),
                "held blobs failed verification; downloading them again"
            );
            tally.files_reused -= manifest
                .files
                .iter()
                .filter(|f| corrupt.iter().any(|c| c.digest == f.digest))
                .count();
            self.download(&corrupt, rep, tally).boxed().await?;
        }

        rep.phase(
            Phase::Assembling,
            format!("assembling {} files", manifest.files.len()),
        );
        let layout = self.layout.clone();
        let r = release.clone();
        blocking(move || layout.assemble(&r, &bytes, &manifest)).await
    }

    /// The manifest's bytes (from the store, else the gateway) and its parsed form.
    async fn manifest(
        &mut self,
        release: &Release,
        url: &str,
        tally: &mut Tally,
    ) -> Result<(Vec<u8>, ReleaseManifest)> {
        let layout = self.layout.clone();
        let digest = release.digest.clone();
        let bytes = match blocking(move || layout.read_blob(&digest)).await? {
            Some(b) => b,
            None => {
                let mut attempt = 0;
                let fetched = loop {
                    attempt += 1;
                    match self
                        .client
                        .get_small(url, lekiwi_protocol::release::MAX_MANIFEST_BYTES)
                        .await
                    {
                        Err(e @ Error::Transport { .. }) if attempt < DOWNLOAD_ATTEMPTS => {
                            warn!(error = %e, attempt, "manifest download failed; retrying");
                            tokio::time::sleep(Duration::from_millis(200 * u64::from(attempt)))
                                .await;
                        }
                        r => break r,
                    }
                };
                let bytes = match fetched {
                    Err(Error::Status { status: 404, .. }) => {
                        return Err(Error::UnknownRelease(release.digest.clone()));
                    }
                    r => r?,
                };
                tally.bytes += bytes.len() as u64;
                let actual = store::sha256_digest(&bytes);
                if actual != release.digest {
                    return Err(Error::DigestMismatch {
                        what: format!("manifest of {}", release.version),
                        expected: release.digest.clone(),
                        actual,
                    });
                }
                let layout = self.layout.clone();
                let (digest, b) = (release.digest.clone(), bytes.clone());
                blocking(move || layout.put_blob(&digest, &b)).await?;
                bytes
            }
        };
        let manifest = ReleaseManifest::parse(&bytes)?;
        Ok((bytes, manifest))
    }

    /// Downloads `wanted` into the store, [`DOWNLOAD_CONCURRENCY`] at a time.
    async fn download(
        &mut self,
        wanted: &[Wanted],
        rep: &mut Reporter<'_>,
        tally: &mut Tally,
    ) -> Result<()> {
        if wanted.is_empty() {
            return Ok(());
        }
        let total: u64 = wanted.iter().map(|w| w.size).sum();
        rep.bytes_total += total;
        let base = tally.bytes;
        rep.phase(
            Phase::Downloading,
            format!("downloading {} files, {total} bytes", wanted.len()),
        );
        let counter = AtomicU64::new(0);
        let (client, layout) = (&self.client, &self.layout);
        let mut queue = wanted.iter();
        let mut downloads = FuturesUnordered::new();
        for w in queue.by_ref().take(DOWNLOAD_CONCURRENCY) {
            downloads.push(fetch_blob(client, layout, w, &counter));
        }
        let mut ticker = tokio::time::interval(PROGRESS_EVERY);
        ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut done = 0;
        let result = loop {
            tokio::select! {
                next = downloads.next() => match next {
                    None => break Ok(()),
                    Some(Ok(())) => {
                        done += 1;
                        if let Some(w) = queue.next() {
                            downloads.push(fetch_blob(client, layout, w, &counter));
                        }
                    }
                    Some(Err(e)) => break Err(e),
                },
                _ = ticker.tick() => {
                    let bytes = base + counter.load(Ordering::Relaxed);
                    rep.downloaded(bytes, || format!("{done} of {} files", wanted.len()));
                }
            }
        };
        drop(downloads);
        tally.bytes = base + counter.load(Ordering::Relaxed);
        tally.files_downloaded += done;
        rep.bytes_downloaded = tally.bytes;
        result?;
        let layout = self.layout.clone();
        blocking(move || layout.sync_store()).await
    }

    /// Pre-switch hook, switch, restart, health check; reverts on failure after the switch.
    /// `resume`: the switch already happened before an agent restart.
    async fn activate(
        &mut self,
        journal: &mut Journal,
        active: &Active,
        rep: &mut Reporter<'_>,
        resume: bool,
    ) -> (Phase, String) {
        let target = &active.target;
        let env = HookEnv {
            dir: self.layout.release_dir(&target.version),
            release: target.clone(),
            previous: active.previous.as_ref().map(|p| p.version.clone()),
        };
        if !resume {
            if !self.hooks.pre_switch.is_empty() {
                rep.phase(Phase::PreSwitch, "running the pre-switch command");
                if let Err(why) = self.hooks.run(&self.hooks.pre_switch, &env).boxed().await {
                    return (
                        Phase::Failed,
                        format!("pre-switch command failed, nothing switched: {why}"),
                    );
                }
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
            if let Err(why) = self.hooks.run(&self.hooks.restart, &env).boxed().await {
                let why = format!("restart command failed on {}: {why}", target.version);
                return self.revert(journal, active, rep, why).boxed().await;
            }
        }
        if !self.hooks.health.is_empty() {
            rep.phase(
                Phase::HealthCheck,
                format!("checking the health of {}", target.version),
            );
            if let Err(why) = self.hooks.health_check(&env).boxed().await {
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

    /// Switches back to the previous release (or to none) and restarts it.
    async fn revert(
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

    async fn load_journal(&self) -> Journal {
        let layout = self.layout.clone();
        match blocking(move || layout.load_journal()).await {
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
        blocking(move || layout.save_journal(&journal)).await
    }

    /// Saves the journal where a failure cannot change the outcome any more; logs it.
    async fn save_journal(&self, journal: &Journal) {
        if let Err(e) = self.write_journal(journal).await {
            warn!(error = %e, "cannot write the deploy journal");
        }
    }
}

/// A blob to download.
#[derive(Clone, Debug)]
struct Wanted {
    digest: String,
    /// The first file with this content, for messages.
    path: String,
    size: u64,
}

/// Downloads one blob with up to [`DOWNLOAD_ATTEMPTS`] attempts, each resuming the partial file.
async fn fetch_blob(
    client: &Client,
    layout: &Layout,
    w: &Wanted,
    counter: &AtomicU64,
) -> Result<()> {
    let mut attempt = 0;
    loop {
        attempt += 1;
        match client.fetch_blob(layout, w, counter).await {
            Ok(Fetched) => return Ok(()),
            Err(Error::Status { status: 404, .. }) => {
                return Err(Error::UnknownBlob {
                    digest: w.digest.clone(),
                    path: w.path.clone(),
                });
            }
            Err(e @ (Error::Transport { .. } | Error::Status { .. }))
                if attempt < DOWNLOAD_ATTEMPTS =>
            {
                warn!(digest = %w.digest, attempt, error = %e, "download interrupted; resuming");
                tokio::time::sleep(Duration::from_millis(200 * u64::from(attempt))).await;
            }
            Err(e) => return Err(e),
        }
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
