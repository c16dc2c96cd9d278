//! The downloading half of a simulated deploy: the manifest (held, or fetched and verified)
//! and the blobs the robot lacks, one after the other over the shared blob client, each
//! verified as it streams and counted into the robot's disk chunk by chunk, so that a cancel
//! or a cut keeps what arrived and the next attempt resumes it with `Range`.

use std::sync::Arc;
use std::time::Duration;

use lekiwi_protocol::Release;
use lekiwi_protocol::release::blob_path;

use super::Report;
use super::args::Fault;
use super::disk::Disk;
use super::shared::Known;
use super::task::{Reporter, Tally, Task};
use crate::release::{Error, Phase, sha256_digest};

/// Attempts per blob within one deployment (each resumes where the previous stopped).
const DOWNLOAD_ATTEMPTS: u32 = 3;

/// A blob to download.
pub(super) struct Wanted<'a> {
    pub(super) digest: &'a str,
    /// The first file with this content, for messages.
    pub(super) path: &'a str,
    pub(super) size: u64,
}

/// The release's manifest: held (the fleet parsed it already), or downloaded and verified.
pub(super) async fn manifest(
    task: &Task,
    disk: &mut Disk,
    release: &Release,
    url: &str,
    tally: &mut Tally,
) -> Result<Arc<Known>, String> {
    let digest = &release.digest;
    if disk.held().contains(digest.as_str())
        && let Some(known) = task.shared.cached(digest)
    {
        return Ok(known);
    }
    let limit = lekiwi_protocol::release::MAX_MANIFEST_BYTES;
    let client = task.shared.client(task.robot.gateway);
    let mut attempt = 0;
    let fetched = loop {
        attempt += 1;
        let permit = task.shared.permits.acquire().await;
        let got = client.get_small_as(url, limit, task.robot.caller()).await;
        drop(permit);
        match got {
            Err(Error::Transport { .. }) if attempt < DOWNLOAD_ATTEMPTS => {
                tokio::time::sleep(Duration::from_millis(200 * u64::from(attempt))).await;
            }
            r => break r,
        }
    };
    let bytes = match fetched {
        Err(Error::Status { status: 404, .. }) => {
            return Err(Error::UnknownRelease(digest.clone()).to_string());
        }
        r => r.map_err(|e| e.to_string())?,
    };
    tally.bytes += bytes.len() as u64;
    task.shared.counters.bytes(bytes.len() as u64);
    let actual = sha256_digest(&bytes);
    if actual != *digest {
        return Err(Error::DigestMismatch {
            what: format!("manifest of {}", release.version),
            expected: digest.clone(),
            actual,
        }
        .to_string());
    }
    disk.put_manifest(digest, bytes.len() as u64);
    task.shared
        .known(digest, &bytes)
        .map_err(|e| Error::from(e).to_string())
}

/// How one blob's download ended.
#[derive(Debug, PartialEq)]
enum Fetched {
    /// Whole and verified.
    Whole,
    /// Cut off halfway because the robot goes offline (`Fault::Offline`).
    Cut,
}

/// Downloads the `missing` blobs one after the other. A robot of `Fault::Timeout` stalls
/// until cancelled; one of `Fault::Offline` goes offline halfway through a download that
/// starts afresh (a resumed one completes).
pub(super) async fn download(
    task: &Task,
    disk: &mut Disk,
    missing: &[Wanted<'_>],
    fault: Fault,
    rep: &mut Reporter<'_>,
    tally: &mut Tally,
) -> Result<(), String> {
    if missing.is_empty() {
        return Ok(());
    }
    let total: u64 = missing.iter().map(|w| w.size).sum();
    rep.total += total;
    rep.phase(
        Phase::Downloading,
        format!("downloading {} files, {total} bytes", missing.len()),
    );
    if fault == Fault::Timeout {
        return std::future::pending().await;
    }
    let fresh = missing.iter().all(|w| disk.partial(w.digest) == 0);
    let cut_at =
        (fault == Fault::Offline && fresh && total > 0).then(|| tally.bytes + total.div_ceil(2));
    for (done, w) in missing.iter().enumerate() {
        let progress = (done, missing.len());
        if fetch_blob(task, disk, w, rep, tally, cut_at, progress).await? == Fetched::Cut {
            let offline = task.shared.args.offline_for();
            let _ = task.tx.send(Report::Offline(offline));
            return Err(Error::Transport {
                url: blob_path(w.digest),
                message: "transfer broke off: the robot went offline".into(),
            }
            .to_string());
        }
        tally.files_downloaded += 1;
    }
    Ok(())
}

/// One blob, with up to [`DOWNLOAD_ATTEMPTS`] attempts, each resuming the last.
async fn fetch_blob(
    task: &Task,
    disk: &mut Disk,
    w: &Wanted<'_>,
    rep: &mut Reporter<'_>,
    tally: &mut Tally,
    cut_at: Option<u64>,
    progress: (usize, usize),
) -> Result<Fetched, String> {
    let mut attempt = 0;
    loop {
        attempt += 1;
        match transfer(task, disk, w, rep, tally, cut_at, progress).await {
            Ok(f) => return Ok(f),
            Err(Error::Status { status: 404, .. }) => {
                let (digest, path) = (w.digest.to_owned(), w.path.to_owned());
                return Err(Error::UnknownBlob { digest, path }.to_string());
            }
            Err(Error::Transport { .. } | Error::Status { .. }) if attempt < DOWNLOAD_ATTEMPTS => {
                tokio::time::sleep(Duration::from_millis(200 * u64::from(attempt))).await;
            }
            Err(e) => return Err(e.to_string()),
        }
    }
}

/// One attempt at one blob: from what the disk holds of it on, counted into the disk as the
/// chunks arrive (so a cancel or a cut keeps them), then verified.
async fn transfer(
    task: &Task,
    disk: &mut Disk,
    w: &Wanted<'_>,
    rep: &mut Reporter<'_>,
    tally: &mut Tally,
    cut_at: Option<u64>,
    progress: (usize, usize),
) -> Result<Fetched, Error> {
    let from = disk.partial(w.digest);
    let resumed = from > 0;
    let what = || format!("blob {} of {}", w.digest, w.path);
    if w.size > 0 && from < w.size {
        let _permit = task.shared.permits.acquire().await;
        let client = task.shared.client(task.robot.gateway);
        let path = blob_path(w.digest);
        let mut stream = client.open_stream(&path, from, task.robot.caller()).await?;
        if stream.from == 0 {
            disk.loose(w.digest, w.size).reset();
        }
        while let Some(chunk) = stream.chunk().await? {
            let blob = disk.loose(w.digest, w.size);
            if blob.have + chunk.len() as u64 > w.size {
                blob.reset();
                return Err(Error::TooLarge {
                    what: what(),
                    size: w.size,
                });
            }
            blob.add(&chunk);
            tally.bytes += chunk.len() as u64;
            task.shared.counters.bytes(chunk.len() as u64);
            rep.downloaded(tally.bytes, progress);
            if cut_at.is_some_and(|at| tally.bytes >= at) {
                return Ok(Fetched::Cut);
            }
        }
        let have = disk.partial(w.digest);
        if have < w.size {
            let message = format!("the body ended after {have} of {} bytes", w.size);
            return Err(Error::Transport { url: path, message });
        }
        stream.finish(client);
    }
    match disk.loose(w.digest, w.size).verify() {
        Ok(()) => Ok(Fetched::Whole),
        // The partial bytes from before may be what is wrong: one more try from scratch.
        Err(_) if resumed => Err(Error::Transport {
            url: blob_path(w.digest),
            message: format!(
                "the resumed download of {} did not verify; starting over",
                what()
            ),
        }),
        Err(actual) => Err(Error::DigestMismatch {
            what: what(),
            expected: w.digest.to_owned(),
            actual,
        }),
    }
}
