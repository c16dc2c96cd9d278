//! The release blob store: files named by their SHA-256 under one directory (a PersistentVolume
//! in the chart), with verified, resumable and idempotent uploads.
//!
//! Layout under the root: complete blobs at `sha256/<hex>`, uploads in progress at
//! `uploads/<hex>.partial`, the releases each namespace pushed at `releases/<ns>/<hex>.json`
//! ([`index`]); [`gc`] plans and makes their removal, never of a blob a download reads
//! ([`readers`]). A blob appears under `sha256/` only by an atomic rename after its
//! content was hashed and found equal to its name, so readers never see a partial or wrong blob.
//! Uploads of one digest are serialized by an in-process lock; replicas sharing the directory
//! could interleave bytes of one partial, which the final verification catches (the partial is
//! deleted and the client starts over), never corrupting a stored blob.

pub mod gc;
pub mod index;
pub mod readers;
#[cfg(test)]
mod tests;
mod upload;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use lekiwi_protocol::release::{MAX_MANIFEST_BYTES, ManifestError, ReleaseManifest, digest_hex};
use serde::Serialize;

use self::index::ReleaseIndex;
use self::readers::{ReadGuard, Readers};

/// What can go wrong storing or reading blobs.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The digest is not `sha256:` and 64 lowercase hex digits.
    #[error(transparent)]
    Digest(ManifestError),
    /// A chunk does not start where the upload stands.
    #[error("the upload of {digest} is at offset {current}, not {given}: resume from {current}")]
    OffsetMismatch {
        /// Digest of the blob being uploaded.
        digest: String,
        /// Offset the client sent.
        given: u64,
        /// Bytes the partial upload holds.
        current: u64,
    },
    /// The uploaded content hashes to another digest; the partial upload was deleted.
    #[error("digest mismatch: expected {expected}, the uploaded content is {actual}")]
    DigestMismatch {
        /// The digest the upload was for.
        expected: String,
        /// The digest of what arrived.
        actual: String,
    },
    /// The blob is larger than the store accepts.
    #[error("the blob is larger than the limit of {limit} bytes")]
    TooLarge {
        /// The store's limit in bytes, which the client can compare with its file.
        limit: u64,
    },
    /// A chunk that does not fit its declared range or total.
    #[error("bad chunk: {0}")]
    BadChunk(String),
    /// The request body broke off; what arrived before is kept for resuming.
    #[error("reading the upload body failed after {received} bytes: {message}")]
    Body {
        /// Bytes written before the failure.
        received: u64,
        /// What failed.
        message: String,
    },
    /// No blob with this digest.
    #[error("blob {0} not found")]
    NotFound(String),
    /// The blob exists but is not a release manifest.
    #[error("{digest} is not a valid release manifest: {source}")]
    Manifest {
        /// Digest of the blob read as a manifest.
        digest: String,
        /// What in its content is not a valid manifest.
        source: ManifestError,
    },
    /// The file system failed.
    #[error("blob store {}: {source}", path.display())]
    Io {
        /// The file or directory it failed on (empty when a blocking task died).
        path: PathBuf,
        /// The operating system's error.
        source: std::io::Error,
    },
}

/// Result with the blob store's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> Error + '_ {
    move |source| Error::Io {
        path: path.to_owned(),
        source,
    }
}

/// Where an upload stands after a write.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UploadState {
    /// The blob was already stored; nothing was written.
    Exists {
        /// Size of the stored blob in bytes.
        size: u64,
    },
    /// This write completed the blob, which is verified and stored now.
    Complete {
        /// Size of the stored blob in bytes.
        size: u64,
    },
    /// The chunk was accepted; the blob is not complete yet.
    Partial {
        /// Bytes received so far: where the next chunk starts.
        offset: u64,
    },
}

/// A release manifest as stored, with the blobs it references that the store lacks.
#[derive(Clone, Debug, Serialize)]
pub struct ReleaseInfo {
    /// Digest of the manifest.
    pub digest: String,
    /// The manifest's version and files, inlined in the JSON answer.
    #[serde(flatten)]
    pub manifest: ReleaseManifest,
    /// Digests of referenced blobs that are not stored, sorted, each once.
    pub missing: Vec<String>,
}

/// Content-addressed blobs in a directory.
#[derive(Clone)]
// shape: reads here; upload.rs verified, resumable uploads; gc.rs garbage collection.
pub struct BlobStore {
    root: PathBuf,
    max_blob_bytes: u64,
    /// One lock per digest with an upload in flight, so two uploads never write one partial.
    locks: Arc<Mutex<HashMap<String, Arc<tokio::sync::Mutex<()>>>>>,
    /// Downloads reading each blob now (and lately), which garbage collection leaves alone.
    readers: Readers,
}

/// The bytes and count of the blobs stored, and the room on their volume.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Usage {
    /// Complete blobs stored.
    pub blobs: u64,
    /// Their bytes.
    pub bytes: u64,
    /// Bytes the volume has free for the gateway (`None` when the file system cannot say).
    pub free: Option<u64>,
    /// The volume's size in bytes (`None` when the file system cannot say).
    pub size: Option<u64>,
}

impl BlobStore {
    /// A store under `root` accepting blobs of at most `max_blob_bytes`. Touches nothing on
    /// disk: directories are made by [`Self::ensure_dirs`] or the first upload.
    pub fn new(root: impl Into<PathBuf>, max_blob_bytes: u64) -> Self {
        Self {
            root: root.into(),
            max_blob_bytes,
            locks: Arc::default(),
            readers: Readers::default(),
        }
    }

    /// The same store, a blob counting as read for `grace` after its last download ended.
    pub fn with_read_grace(mut self, grace: std::time::Duration) -> Self {
        self.readers = Readers::new(grace);
        self
    }

    /// The per-namespace release records of this store.
    pub fn index(&self) -> ReleaseIndex {
        ReleaseIndex::new(&self.root)
    }

    /// The downloads reading blobs now.
    pub fn readers(&self) -> &Readers {
        &self.readers
    }

    /// The directory holding `sha256/` and `uploads/`.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The largest blob accepted.
    pub fn max_blob_bytes(&self) -> u64 {
        self.max_blob_bytes
    }

    /// Creates the store's directories if they do not exist.
    pub async fn ensure_dirs(&self) -> Result<()> {
        for dir in [self.blob_dir(), self.upload_dir()] {
            tokio::fs::create_dir_all(&dir).await.map_err(io(&dir))?;
        }
        Ok(())
    }

    fn blob_dir(&self) -> PathBuf {
        self.root.join("sha256")
    }

    fn upload_dir(&self) -> PathBuf {
        self.root.join("uploads")
    }

    /// Path of a stored blob, from a validated digest.
    fn blob_path(&self, hex: &str) -> PathBuf {
        self.blob_dir().join(hex)
    }

    fn partial_path(&self, hex: &str) -> PathBuf {
        self.upload_dir().join(format!("{hex}.partial"))
    }

    /// Size of a stored blob, `None` if it is not stored.
    pub async fn stat(&self, digest: &str) -> Result<Option<u64>> {
        let hex = digest_hex(digest).map_err(Error::Digest)?;
        file_size(&self.blob_path(hex)).await
    }

    /// Bytes received so far of an incomplete upload (0 if none).
    pub async fn partial_offset(&self, digest: &str) -> Result<u64> {
        let hex = digest_hex(digest).map_err(Error::Digest)?;
        Ok(file_size(&self.partial_path(hex)).await?.unwrap_or(0))
    }

    /// Opens a stored blob for reading (seek for ranges), with its size; `None` if not stored.
    pub async fn open(&self, digest: &str) -> Result<Option<(tokio::fs::File, u64)>> {
        let hex = digest_hex(digest).map_err(Error::Digest)?;
        let path = self.blob_path(hex);
        let file = match tokio::fs::File::open(&path).await {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(io(&path)(e)),
        };
        let size = file.metadata().await.map_err(io(&path))?.len();
        Ok(Some((file, size)))
    }

    /// Like [`Self::open`], the blob marked as read (safe from garbage collection) until the
    /// guard drops.
    pub async fn open_read(
        &self,
        digest: &str,
    ) -> Result<Option<(tokio::fs::File, u64, ReadGuard)>> {
        // Marked before it is opened: a collection deciding now sees the read.
        let guard = self.readers.begin(digest);
        Ok(self
            .open(digest)
            .await?
            .map(|(file, size)| (file, size, guard)))
    }

    /// Deletes the blob `digest` unless a download reads it; its size when it was deleted.
    fn remove_blob(&self, digest: &str) -> Result<Option<u64>> {
        let hex = digest_hex(digest).map_err(Error::Digest)?;
        let path = self.blob_path(hex);
        let removed = self.readers.unless_busy(digest, || {
            let size = std::fs::metadata(&path).map(|m| m.len()).ok();
            match std::fs::remove_file(&path) {
                Ok(()) => Ok(size),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
                Err(e) => Err(io(&path)(e)),
            }
        });
        removed.unwrap_or(Ok(None))
    }

    /// The blobs stored, their bytes, and the room on the store's volume.
    pub async fn usage(&self) -> Result<Usage> {
        let dir = self.blob_dir();
        let mut usage = Usage::default();
        let mut entries = match tokio::fs::read_dir(&dir).await {
            Ok(e) => Some(e),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(e) => return Err(io(&dir)(e)),
        };
        while let Some(entries) = entries.as_mut()
            && let Some(entry) = entries.next_entry().await.map_err(io(&dir))?
        {
            if let Ok(meta) = entry.metadata().await
                && meta.is_file()
            {
                usage.blobs += 1;
                usage.bytes += meta.len();
            }
        }
        if let Ok(vfs) = rustix::fs::statvfs(&self.root) {
            usage.free = Some(vfs.f_bavail.saturating_mul(vfs.f_frsize));
            usage.size = Some(vfs.f_blocks.saturating_mul(vfs.f_frsize));
        }
        Ok(usage)
    }

    async fn lock(&self, hex: &str) -> tokio::sync::OwnedMutexGuard<()> {
        let lock = {
            let mut locks = self.locks.lock().unwrap_or_else(|p| p.into_inner());
            // Forget locks nobody holds or waits for; the map stays as small as the uploads
            // in flight.
            locks.retain(|_, l| Arc::strong_count(l) > 1);
            locks.entry(hex.to_owned()).or_default().clone()
        };
        lock.lock_owned().await
    }

    /// Deletes the interrupted uploads nobody resumed for `max_age` (by the partial file's
    /// modification time); an upload in flight is never touched. Returns how many partials
    /// went and their bytes.
    pub async fn remove_stale_uploads(&self, max_age: std::time::Duration) -> Result<(usize, u64)> {
        let dir = self.upload_dir();
        let mut entries = match tokio::fs::read_dir(&dir).await {
            Ok(e) => e,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok((0, 0)),
            Err(e) => return Err(io(&dir)(e)),
        };
        let (mut files, mut bytes) = (0, 0);
        while let Some(entry) = entries.next_entry().await.map_err(io(&dir))? {
            let name = entry.file_name();
            let Some(hex) = name.to_str().and_then(|n| n.strip_suffix(".partial")) else {
                continue;
            };
            let path = entry.path();
            let stale = |meta: &std::fs::Metadata| {
                meta.modified()
                    .ok()
                    .and_then(|m| m.elapsed().ok())
                    .is_some_and(|age| age > max_age)
            };
            match tokio::fs::metadata(&path).await {
                Ok(meta) if stale(&meta) => {}
                _ => continue,
            }
            // Held while deciding, so that no upload writes the partial in between.
            let _guard = self.lock(hex).await;
            let Ok(meta) = tokio::fs::metadata(&path).await else {
                continue;
            };
            if stale(&meta) {
                remove_if_exists(&path).await?;
                files += 1;
                bytes += meta.len();
            }
        }
        Ok((files, bytes))
    }

    /// Reads and validates the release manifest stored as `digest`.
    pub async fn manifest(&self, digest: &str) -> Result<ReleaseManifest> {
        let hex = digest_hex(digest).map_err(Error::Digest)?;
        let path = self.blob_path(hex);
        let size = file_size(&path)
            .await?
            .ok_or_else(|| Error::NotFound(digest.to_owned()))?;
        let manifest_error = |source| Error::Manifest {
            digest: digest.to_owned(),
            source,
        };
        if size > MAX_MANIFEST_BYTES as u64 {
            return Err(manifest_error(ManifestError::Json(format!(
                "{size} bytes, more than the limit of {MAX_MANIFEST_BYTES}"
            ))));
        }
        let bytes = tokio::fs::read(&path).await.map_err(io(&path))?;
        ReleaseManifest::parse(&bytes).map_err(manifest_error)
    }

    /// Reads and validates the release manifest stored as `digest` and lists the blobs it
    /// references that the store lacks.
    pub async fn release(&self, digest: &str) -> Result<ReleaseInfo> {
        let manifest = self.manifest(digest).await?;
        let mut missing = Vec::new();
        let wanted: std::collections::BTreeSet<&str> =
            manifest.files.iter().map(|f| f.digest.as_str()).collect();
        for d in wanted {
            if self.stat(d).await?.is_none() {
                missing.push(d.to_owned());
            }
        }
        Ok(ReleaseInfo {
            digest: digest.to_owned(),
            manifest,
            missing,
        })
    }
}

async fn file_size(path: &Path) -> Result<Option<u64>> {
    match tokio::fs::metadata(path).await {
        Ok(m) => Ok(Some(m.len())),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(io(path)(e)),
    }
}

async fn remove_if_exists(path: &Path) -> Result<()> {
    match tokio::fs::remove_file(path).await {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(io(path)(e)),
    }
}
