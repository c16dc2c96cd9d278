//! `release push`: upload the blobs the gateway lacks a few at a time with a progress line, then
//! the manifest (always: storing it records the release in the namespace, for `release list`
//! and garbage collection), then confirm that the gateway holds the whole release.

use std::collections::{BTreeMap, BTreeSet};
use std::io::{IsTerminal, Write};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use anyhow::bail;
use futures::{StreamExt, TryStreamExt};
use lekiwi_protocol::release::ReleaseManifest;
use sha2::{Digest, Sha256};

use super::files::HashedFile;
use super::gateway::Gateway;
use super::upload::{Blob, Progress, Source, Upload};

/// How a push uploads: blobs at once and bytes per request (each at least 1).
#[derive(Clone, Copy, Debug)]
pub(super) struct PushOptions {
    pub(super) parallel: usize,
    pub(super) chunk_bytes: u64,
}

/// What a push did.
#[derive(Debug, PartialEq, Eq)]
pub struct Pushed {
    /// Digest of the manifest.
    pub digest: String,
    /// Bytes uploaded, manifest included.
    pub bytes: u64,
    /// Files whose content the gateway already had.
    pub present_files: usize,
    /// Blobs this push stored (the manifest not counted).
    pub new_blobs: usize,
    /// Whether this push stored the manifest.
    pub manifest_uploaded: bool,
}

impl Pushed {
    /// The summary line, e.g. `release 1.2.0: 0 B uploaded, 50 files already present (0 new
    /// blobs, manifest already present)`.
    pub fn summary(&self, version: &str) -> String {
        let manifest = if self.manifest_uploaded {
            " + manifest"
        } else {
            ", manifest already present"
        };
        format!(
            "release {version}: {} uploaded, {} files already present ({} new blobs{manifest})",
            human(self.bytes),
            self.present_files,
            self.new_blobs
        )
    }
}

/// Bytes for people: `0 B`, `512 B`, `1.5 KiB`, `3.2 GiB`.
pub fn human(bytes: u64) -> String {
    const UNITS: [&str; 4] = ["KiB", "MiB", "GiB", "TiB"];
    if bytes < 1024 {
        return format!("{bytes} B");
    }
    let mut value = bytes as f64 / 1024.0;
    let mut unit = 0;
    while value >= 1024.0 && unit < UNITS.len() - 1 {
        value /= 1024.0;
        unit += 1;
    }
    format!("{value:.1} {}", UNITS[unit])
}

/// Pushes a hashed release: the missing blobs, then the manifest, then a check that the gateway
/// lacks nothing.
pub(super) async fn push(
    gateway: &Gateway,
    manifest: &ReleaseManifest,
    files: &[HashedFile],
    options: PushOptions,
) -> anyhow::Result<Pushed> {
    let blobs = distinct_blobs(files);
    let present = present_blobs(gateway, &blobs).await?;
    let missing: Vec<Blob> = blobs
        .into_values()
        .filter(|b| !present.contains(&b.digest))
        .collect();
    let present_files = files
        .iter()
        .filter(|f| present.contains(&f.manifest.digest))
        .count();

    let progress = Arc::new(Progress::default());
    let uploaded = upload_all(gateway, missing, options, &progress).await?;
    let mut bytes: u64 = uploaded.iter().map(|(b, _)| b).sum();
    let new_blobs = uploaded.iter().filter(|(_, stored)| *stored).count();

    // The manifest last: once it is stored, every blob it names is too.
    let (digest, sent, manifest_uploaded) =
        push_manifest(gateway, manifest, options.chunk_bytes, &progress).await?;
    bytes += sent;
    let info = gateway.release(&digest).await?;
    if !info.missing.is_empty() {
        bail!(
            "the gateway lacks {} blobs of release {digest} after the push: {}",
            info.missing.len(),
            info.missing.join(", ")
        );
    }
    Ok(Pushed {
        digest,
        bytes,
        present_files,
        new_blobs,
        manifest_uploaded,
    })
}

/// One blob per distinct content, by digest, named after the first file that has it.
fn distinct_blobs(files: &[HashedFile]) -> BTreeMap<String, Blob> {
    let mut blobs: BTreeMap<String, Blob> = BTreeMap::new();
    for f in files {
        blobs
            .entry(f.manifest.digest.clone())
            .or_insert_with(|| Blob {
                digest: f.manifest.digest.clone(),
                size: f.manifest.size,
                name: f.manifest.path.clone(),
                source: Source::File(f.source.clone()),
            });
    }
    blobs
}

/// The digests among `blobs` that the gateway already stores, asked 8 at a time.
async fn present_blobs(
    gateway: &Gateway,
    blobs: &BTreeMap<String, Blob>,
) -> anyhow::Result<BTreeSet<String>> {
    futures::stream::iter(blobs.keys().cloned())
        .map(|d| async move { Ok::<_, anyhow::Error>(gateway.has_blob(&d).await?.then_some(d)) })
        .buffer_unordered(8)
        .try_filter_map(|d| async move { Ok(d) })
        .try_collect()
        .await
}

/// Uploads `missing`, `options.parallel` at a time, with a progress line on a terminal; returns
/// per blob the bytes sent and whether this push stored it.
async fn upload_all(
    gateway: &Gateway,
    missing: Vec<Blob>,
    options: PushOptions,
    progress: &Arc<Progress>,
) -> anyhow::Result<Vec<(u64, bool)>> {
    let total_bytes: u64 = missing.iter().map(|b| b.size).sum();
    let total_blobs = missing.len() as u64;
    let ticker = std::io::stderr().is_terminal().then(|| {
        let progress = progress.clone();
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(Duration::from_secs(1));
            loop {
                tick.tick().await;
                eprint!(
                    "\ruploading: {} / {}, {} / {total_blobs} files   ",
                    human(progress.bytes.load(Ordering::Relaxed)),
                    human(total_bytes),
                    progress.blobs.load(Ordering::Relaxed)
                );
                let _ = std::io::stderr().flush();
            }
        })
    });
    let uploaded = futures::stream::iter(missing)
        .map(|blob| {
            let progress = progress.clone();
            async move {
                let upload = Upload {
                    gateway,
                    blob: &blob,
                };
                let done = upload.run(options.chunk_bytes, &progress).await;
                progress.blobs.fetch_add(1, Ordering::Relaxed);
                done
            }
        })
        .buffer_unordered(options.parallel)
        .try_collect::<Vec<(u64, bool)>>()
        .await;
    if let Some(t) = ticker {
        t.abort();
        eprint!("\r\x1b[2K");
    }
    uploaded
}

/// Uploads the manifest unless the gateway has it: its digest, the bytes sent and whether this
/// push stored it.
async fn push_manifest(
    gateway: &Gateway,
    manifest: &ReleaseManifest,
    chunk_bytes: u64,
    progress: &Progress,
) -> anyhow::Result<(String, u64, bool)> {
    let manifest_bytes = manifest.to_bytes();
    let digest = format!("sha256:{}", hex::encode(Sha256::digest(&manifest_bytes)));
    if gateway.has_blob(&digest).await? {
        // Sent anyway (it is small): the gateway records it as a release of this namespace.
        gateway.put_whole(&digest, manifest_bytes).await?;
        return Ok((digest, 0, false));
    }
    let blob = Blob {
        digest: digest.clone(),
        size: manifest_bytes.len() as u64,
        name: "the manifest".into(),
        source: Source::Memory(Arc::new(manifest_bytes)),
    };
    let (sent, stored) = Upload {
        gateway,
        blob: &blob,
    }
    .run(chunk_bytes, progress)
    .await?;
    Ok((digest, sent, stored))
}
