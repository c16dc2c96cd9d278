//! Making a release complete on disk: its manifest (from the store or the gateway), the blobs
//! the store lacks (downloaded a few at a time, each resumable), a re-check of the blobs it
//! holds, and the assembly of `releases/<version>/`.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use futures::stream::FuturesUnordered;
use futures::{FutureExt, StreamExt};
use lekiwi_protocol::Release;
use lekiwi_protocol::release::{ReleaseManifest, blob_path};
use tracing::warn;

use super::fetch::{Client, Fetched};
use super::progress::{PROGRESS_EVERY, Phase, Reporter, Tally};
use super::store::{self, Layout};
use super::{Error, Releases, Result, blocking};

/// Blobs downloaded at the same time.
const DOWNLOAD_CONCURRENCY: usize = 4;
/// Attempts per blob within one deployment (each resumes where the previous stopped).
const DOWNLOAD_ATTEMPTS: u32 = 3;

impl Releases {
    /// Makes `releases/<version>/` exist and be complete.
    pub(super) async fn prepare(
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
        check_manifest(release, &manifest)?;
        let blobs = self.sort_blobs(&manifest).await?;
        tally.files_reused = blobs.files_reused;
        self.download(&blobs.missing, rep, tally).boxed().await?;
        self.verify_held(&manifest, blobs.held, rep, tally)
            .boxed()
            .await?;

        rep.phase(
            Phase::Assembling,
            format!("assembling {} files", manifest.files.len()),
        );
        let layout = self.layout.clone();
        let r = release.clone();
        blocking(move || layout.assemble(&r, &bytes, &manifest)).await
    }

    /// The manifest's distinct blobs, split by whether the store holds them.
    async fn sort_blobs(&self, manifest: &ReleaseManifest) -> Result<Blobs> {
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
        let (held_blobs, missing) = blobs
            .iter()
            .map(|(d, (p, s))| Wanted {
                digest: (*d).to_owned(),
                path: (*p).to_owned(),
                size: *s,
            })
            .partition(|w| held.contains(&w.digest));
        let files_reused = manifest
            .files
            .iter()
            .filter(|f| held.contains(&f.digest))
            .count();
        Ok(Blobs {
            missing,
            held: held_blobs,
            files_reused,
        })
    }

    /// Verifies the blobs the store already held and downloads again those that fail (a
    /// release file modified in place changes its store blob, which is a hard link).
    async fn verify_held(
        &mut self,
        manifest: &ReleaseManifest,
        held: Vec<Wanted>,
        rep: &mut Reporter<'_>,
        tally: &mut Tally,
    ) -> Result<()> {
        rep.phase(
            Phase::Verifying,
            format!("verifying {} files already held", tally.files_reused),
        );
        let layout = self.layout.clone();
        let corrupt = blocking(move || layout.verify(held)).await?;
        if corrupt.is_empty() {
            return Ok(());
        }
        warn!(
            count = corrupt.len(),
            "held blobs failed verification; downloading them again"
        );
        tally.files_reused -= manifest
            .files
            .iter()
            .filter(|f| corrupt.iter().any(|c| c.digest == f.digest))
            .count();
        self.download(&corrupt, rep, tally).boxed().await
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
}

/// The distinct blobs of a manifest, by whether the store already holds them.
struct Blobs {
    /// Not in the store: to download.
    missing: Vec<Wanted>,
    /// In the store: to verify before they are linked into the release.
    held: Vec<Wanted>,
    /// Files of the manifest (not blobs: two files may share one) whose content is held.
    files_reused: usize,
}

/// A check that the manifest fits the command: same version, and no file in the directory the
/// agent keeps for itself inside every release.
fn check_manifest(release: &Release, manifest: &ReleaseManifest) -> Result<()> {
    if manifest.version != release.version {
        return Err(Error::Invalid(format!(
            "the manifest names version {:?}, the command {:?}",
            manifest.version, release.version
        )));
    }
    if let Some(f) = manifest
        .files
        .iter()
        .find(|f| f.path == store::META_DIR || f.path.starts_with(&format!("{}/", store::META_DIR)))
    {
        return Err(Error::Invalid(format!(
            "the manifest has {:?}: {}/ is reserved for the agent",
            f.path,
            store::META_DIR
        )));
    }
    Ok(())
}

/// A blob to download.
#[derive(Clone, Debug)]
pub(super) struct Wanted {
    pub(super) digest: String,
    /// The first file with this content, for messages.
    pub(super) path: String,
    pub(super) size: u64,
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
