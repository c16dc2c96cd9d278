//! The release blob store: files named by their SHA-256 under one directory (a PersistentVolume
//! in the chart), with verified, resumable and idempotent uploads.
//!
//! Layout under the root: complete blobs at `sha256/<hex>`, uploads in progress at
//! `uploads/<hex>.partial`. A blob appears under `sha256/` only by an atomic rename after its
//! content was hashed and found equal to its name, so readers never see a partial or wrong blob.
//! Uploads of one digest are serialized by an in-process lock; replicas sharing the directory
//! could interleave bytes of one partial, which the final verification catches (the partial is
//! deleted and the client starts over), never corrupting a stored blob.

use std::collections::HashMap;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use futures::{Stream, StreamExt};
use lekiwi_protocol::release::{MAX_MANIFEST_BYTES, ManifestError, ReleaseManifest, digest_hex};
use serde::Serialize;
use sha2::{Digest, Sha256};
use tokio::io::{AsyncSeekExt, AsyncWriteExt};

/// What can go wrong storing or reading blobs.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The digest is not `sha256:` and 64 lowercase hex digits.
    #[error(transparent)]
    Digest(ManifestError),
    /// A chunk does not start where the upload stands.
    #[error("the upload of {digest} is at offset {current}, not {given}: resume from {current}")]
    OffsetMismatch {
        /// The blob.
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
        /// The limit.
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
        /// The blob.
        digest: String,
        /// Why.
        source: ManifestError,
    },
    /// The file system failed.
    #[error("blob store {}: {source}", path.display())]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The error.
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
        /// Its size.
        size: u64,
    },
    /// This write completed the blob, which is verified and stored now.
    Complete {
        /// Its size.
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
    /// The manifest.
    #[serde(flatten)]
    pub manifest: ReleaseManifest,
    /// Digests of referenced blobs that are not stored, sorted, each once.
    pub missing: Vec<String>,
}

/// Content-addressed blobs in a directory.
#[derive(Clone)]
pub struct BlobStore {
    root: PathBuf,
    max_blob_bytes: u64,
    /// One lock per digest with an upload in flight, so two uploads never write one partial.
    locks: Arc<Mutex<HashMap<String, Arc<tokio::sync::Mutex<()>>>>>,
}

impl BlobStore {
    /// A store under `root` accepting blobs of at most `max_blob_bytes`. Touches nothing on
    /// disk: directories are made by [`Self::ensure_dirs`] or the first upload.
    pub fn new(root: impl Into<PathBuf>, max_blob_bytes: u64) -> Self {
        Self {
            root: root.into(),
            max_blob_bytes,
            locks: Arc::default(),
        }
    }

    /// The root directory.
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

    /// Writes `body` into the upload of `digest` at `offset`.
    ///
    /// With `total`, the body is a chunk of a blob of `total` bytes: `offset` must equal the
    /// bytes received so far (else [`Error::OffsetMismatch`] with the current offset), and the
    /// blob is verified and stored once the upload reaches `total` (an empty body at
    /// `offset == total` finishes an upload whose bytes all arrived but whose verification was
    /// cut short). A partial longer than `total` is discarded. Without `total`, the body is
    /// the whole blob: `offset` must be 0, any earlier partial upload is discarded, and the blob
    /// is verified and stored at the body's end. If the body breaks off, what arrived is kept
    /// for resuming. A blob already stored is not written again ([`UploadState::Exists`]); the
    /// body is then not read at all.
    pub async fn write_at<S, B, E>(
        &self,
        digest: &str,
        offset: u64,
        total: Option<u64>,
        body: S,
    ) -> Result<UploadState>
    where
        S: Stream<Item = Result<B, E>>,
        B: AsRef<[u8]>,
        E: std::fmt::Display,
    {
        let hex = digest_hex(digest).map_err(Error::Digest)?.to_owned();
        let limit = self.max_blob_bytes;
        if total.is_some_and(|t| t > limit) {
            return Err(Error::TooLarge { limit });
        }
        if let Some(size) = self.stat(digest).await? {
            return Ok(UploadState::Exists { size });
        }
        let guard = self.lock(&hex).await;
        // Another upload of the same blob may have finished while this one waited.
        if let Some(size) = self.stat(digest).await? {
            return Ok(UploadState::Exists { size });
        }
        let whole = total.is_none();
        if whole && offset != 0 {
            return Err(Error::BadChunk(
                "an upload without a range must start at offset 0".into(),
            ));
        }
        if let Some(t) = total
            && offset > t
        {
            return Err(Error::BadChunk(format!(
                "offset {offset} lies beyond the total of {t} bytes"
            )));
        }
        let upload_dir = self.upload_dir();
        tokio::fs::create_dir_all(&upload_dir)
            .await
            .map_err(io(&upload_dir))?;
        let partial = self.partial_path(&hex);
        let mut current = file_size(&partial).await?.unwrap_or(0);
        if let Some(t) = total
            && current > t
        {
            // Left by an upload that declared another size: useless for this one.
            remove_if_exists(&partial).await?;
            current = 0;
        }
        if !whole && offset != current {
            return Err(Error::OffsetMismatch {
                digest: digest.to_owned(),
                given: offset,
                current,
            });
        }
        let mut file = tokio::fs::OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(whole)
            .open(&partial)
            .await
            .map_err(io(&partial))?;
        file.seek(std::io::SeekFrom::Start(offset))
            .await
            .map_err(io(&partial))?;

        let end = total.unwrap_or(limit);
        let mut pos = offset;
        let mut failed = None;
        let mut body = std::pin::pin!(body);
        while let Some(chunk) = body.next().await {
            let chunk = match chunk {
                Ok(c) => c,
                Err(e) => {
                    failed = Some(Error::Body {
                        received: pos - offset,
                        message: e.to_string(),
                    });
                    break;
                }
            };
            let bytes = chunk.as_ref();
            let len = bytes.len() as u64;
            if pos + len > end {
                failed = Some(if whole {
                    Error::TooLarge { limit }
                } else {
                    Error::BadChunk(format!(
                        "the body runs past the declared total of {end} bytes"
                    ))
                });
                break;
            }
            file.write_all(bytes).await.map_err(io(&partial))?;
            pos += len;
        }
        // Let every write land before anyone measures the partial's size.
        file.flush().await.map_err(io(&partial))?;
        match failed {
            // Kept: the client resumes from what arrived.
            Some(e @ Error::Body { .. }) if !whole => return Err(e),
            Some(e) => {
                if whole {
                    drop(file);
                    remove_if_exists(&partial).await?;
                } else {
                    // Undo this chunk so the partial stays at a boundary the client knows.
                    file.set_len(offset).await.map_err(io(&partial))?;
                }
                return Err(e);
            }
            None => {}
        }
        if total.is_some_and(|t| pos < t) {
            return Ok(UploadState::Partial { offset: pos });
        }
        file.sync_all().await.map_err(io(&partial))?;
        drop(file);
        // Verification of a large blob takes a while: it runs to the end, holding the lock,
        // even if the client goes away meanwhile, so the next request finds the blob stored.
        let store = self.clone();
        let digest = digest.to_owned();
        let finish = tokio::spawn(async move {
            let finished = store.finish(&hex, &digest, &partial).await;
            drop(guard);
            finished
        });
        finish
            .await
            .unwrap_or_else(|e| {
                Err(Error::Io {
                    path: PathBuf::new(),
                    source: std::io::Error::other(e),
                })
            })
            .map(|()| UploadState::Complete { size: pos })
    }

    /// Hashes a complete partial upload and moves it into place, or deletes it on a mismatch.
    async fn finish(&self, hex: &str, digest: &str, partial: &Path) -> Result<()> {
        let actual = hash_file(partial.to_owned()).await?;
        if actual != hex {
            remove_if_exists(partial).await?;
            return Err(Error::DigestMismatch {
                expected: digest.to_owned(),
                actual: format!("sha256:{actual}"),
            });
        }
        let blob_dir = self.blob_dir();
        tokio::fs::create_dir_all(&blob_dir)
            .await
            .map_err(io(&blob_dir))?;
        let path = self.blob_path(hex);
        tokio::fs::rename(partial, &path).await.map_err(io(&path))
    }

    /// Reads and validates the release manifest stored as `digest` and lists the blobs it
    /// references that the store lacks.
    pub async fn release(&self, digest: &str) -> Result<ReleaseInfo> {
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
        let manifest = ReleaseManifest::parse(&bytes).map_err(manifest_error)?;
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

/// Hex SHA-256 of a file, read on the blocking pool (a 4 GiB blob takes seconds).
async fn hash_file(path: PathBuf) -> Result<String> {
    let hashed = tokio::task::spawn_blocking(move || {
        let mut file = std::fs::File::open(&path).map_err(io(&path))?;
        let mut hasher = Sha256::new();
        let mut buf = vec![0u8; 1024 * 1024];
        loop {
            let n = file.read(&mut buf).map_err(io(&path))?;
            if n == 0 {
                return Ok(hex::encode(hasher.finalize()));
            }
            hasher.update(&buf[..n]);
        }
    })
    .await;
    hashed.unwrap_or_else(|e| {
        Err(Error::Io {
            path: PathBuf::new(),
            source: std::io::Error::other(e),
        })
    })
}

#[cfg(test)]
mod tests {
    use lekiwi_protocol::release::ManifestFile;

    use super::*;

    fn digest(bytes: &[u8]) -> String {
        format!("sha256:{}", hex::encode(Sha256::digest(bytes)))
    }

    fn body(parts: &[&[u8]]) -> impl Stream<Item = Result<Vec<u8>, std::io::Error>> + use<> {
        let parts: Vec<_> = parts.iter().map(|p| Ok(p.to_vec())).collect();
        futures::stream::iter(parts)
    }

    fn store(max: u64) -> (tempfile::TempDir, BlobStore) {
        let dir = tempfile::tempdir().unwrap();
        let store = BlobStore::new(dir.path().join("blobs"), max);
        (dir, store)
    }

    #[tokio::test]
    async fn whole_uploads_are_verified_stored_and_idempotent() {
        let (_dir, store) = store(1024);
        let content = b"hello, kiwi";
        let d = digest(content);
        assert_eq!(store.stat(&d).await.unwrap(), None);
        let state = store
            .write_at(&d, 0, None, body(&[b"hello, ", b"kiwi"]))
            .await;
        assert_eq!(state.unwrap(), UploadState::Complete { size: 11 });
        assert_eq!(store.stat(&d).await.unwrap(), Some(11));
        let on_disk = store.root().join("sha256").join(&d[7..]);
        assert_eq!(std::fs::read(&on_disk).unwrap(), content);
        let mtime = std::fs::metadata(&on_disk).unwrap().modified().unwrap();

        // Again: nothing is read or written.
        let again = store.write_at(&d, 0, None, body(&[b"garbage"])).await;
        assert_eq!(again.unwrap(), UploadState::Exists { size: 11 });
        assert_eq!(
            std::fs::metadata(&on_disk).unwrap().modified().unwrap(),
            mtime
        );
        let (_, size) = store.open(&d).await.unwrap().unwrap();
        assert_eq!(size, 11);

        // The empty blob is a blob too.
        let empty = digest(b"");
        let state = store.write_at(&empty, 0, None, body(&[])).await.unwrap();
        assert_eq!(state, UploadState::Complete { size: 0 });
    }

    /// Interrupted uploads older than the limit go; fresh ones, stored blobs and other files stay.
    #[tokio::test]
    async fn stale_partial_uploads_are_removed() {
        let (_dir, store) = store(1024);
        let content: Vec<u8> = (0..100u8).collect();
        let (old, fresh) = (digest(&content), digest(&content[..50]));
        for d in [&old, &fresh] {
            let state = store
                .write_at(d, 0, Some(100), body(&[&content[..10]]))
                .await;
            assert_eq!(state.unwrap(), UploadState::Partial { offset: 10 });
        }
        let stored = digest(b"kept");
        store
            .write_at(&stored, 0, None, body(&[b"kept"]))
            .await
            .unwrap();
        let uploads = store.root().join("uploads");
        std::fs::write(uploads.join("notes.txt"), "not a partial").unwrap();
        let two_days_ago =
            std::time::SystemTime::now() - std::time::Duration::from_secs(2 * 86_400);
        std::fs::File::options()
            .write(true)
            .open(uploads.join(format!("{}.partial", &old[7..])))
            .unwrap()
            .set_modified(two_days_ago)
            .unwrap();

        let day = std::time::Duration::from_secs(86_400);
        assert_eq!(store.remove_stale_uploads(day).await.unwrap(), (1, 10));
        assert_eq!(store.partial_offset(&old).await.unwrap(), 0);
        assert_eq!(store.partial_offset(&fresh).await.unwrap(), 10);
        assert_eq!(store.stat(&stored).await.unwrap(), Some(4));
        assert!(uploads.join("notes.txt").exists());
        assert_eq!(store.remove_stale_uploads(day).await.unwrap(), (0, 0));
    }

    #[tokio::test]
    async fn chunks_resume_at_the_right_offset_only() {
        let (_dir, store) = store(1024);
        let content: Vec<u8> = (0..100u8).collect();
        let d = digest(&content);
        let state = store
            .write_at(&d, 0, Some(100), body(&[&content[..40]]))
            .await
            .unwrap();
        assert_eq!(state, UploadState::Partial { offset: 40 });
        assert_eq!(store.partial_offset(&d).await.unwrap(), 40);
        assert_eq!(store.stat(&d).await.unwrap(), None);

        match store
            .write_at(&d, 30, Some(100), body(&[&content[30..]]))
            .await
        {
            Err(Error::OffsetMismatch {
                current: 40,
                given: 30,
                ..
            }) => {}
            other => panic!("expected an offset mismatch, got {other:?}"),
        }
        // A body running past the total is refused and leaves the partial as it was.
        let too_long = [&content[40..], b"extra".as_slice()].concat();
        assert!(matches!(
            store.write_at(&d, 40, Some(100), body(&[&too_long])).await,
            Err(Error::BadChunk(_))
        ));
        assert_eq!(store.partial_offset(&d).await.unwrap(), 40);

        let state = store
            .write_at(&d, 40, Some(100), body(&[&content[40..70], &content[70..]]))
            .await
            .unwrap();
        assert_eq!(state, UploadState::Complete { size: 100 });
        assert_eq!(store.partial_offset(&d).await.unwrap(), 0);
        let mut read = Vec::new();
        let (mut file, _) = store.open(&d).await.unwrap().unwrap();
        tokio::io::AsyncReadExt::read_to_end(&mut file, &mut read)
            .await
            .unwrap();
        assert_eq!(read, content);
    }

    #[tokio::test]
    async fn a_complete_partial_is_finished_by_an_empty_chunk() {
        let (_dir, store) = store(1024);
        let content = vec![3u8; 50];
        let d = digest(&content);
        store.ensure_dirs().await.unwrap();
        // All bytes arrived, but the gateway stopped before verifying them.
        let partial = store
            .root()
            .join("uploads")
            .join(format!("{}.partial", &d[7..]));
        std::fs::write(&partial, &content).unwrap();
        assert_eq!(store.partial_offset(&d).await.unwrap(), 50);
        let state = store.write_at(&d, 50, Some(50), body(&[])).await.unwrap();
        assert_eq!(state, UploadState::Complete { size: 50 });

        // A partial longer than the declared total is discarded: start again from 0.
        let other = digest(b"short");
        let partial = store
            .root()
            .join("uploads")
            .join(format!("{}.partial", &other[7..]));
        std::fs::write(&partial, b"much too long").unwrap();
        assert!(matches!(
            store.write_at(&other, 13, Some(5), body(&[])).await,
            Err(Error::BadChunk(_))
        ));
        match store.write_at(&other, 5, Some(5), body(&[])).await {
            Err(Error::OffsetMismatch { current: 0, .. }) => {}
            other => panic!("{other:?}"),
        }
        let state = store.write_at(&other, 0, Some(5), body(&[b"short"])).await;
        assert_eq!(state.unwrap(), UploadState::Complete { size: 5 });
    }

    #[tokio::test]
    async fn a_broken_body_keeps_what_arrived() {
        let (_dir, store) = store(1024);
        let content = vec![7u8; 64];
        let d = digest(&content);
        let broken = futures::stream::iter(vec![
            Ok(content[..20].to_vec()),
            Err(std::io::Error::other("connection reset")),
        ]);
        match store.write_at(&d, 0, Some(64), broken).await {
            Err(Error::Body { received: 20, .. }) => {}
            other => panic!("{other:?}"),
        }
        assert_eq!(store.partial_offset(&d).await.unwrap(), 20);
        let state = store
            .write_at(&d, 20, Some(64), body(&[&content[20..]]))
            .await
            .unwrap();
        assert_eq!(state, UploadState::Complete { size: 64 });
    }

    #[tokio::test]
    async fn wrong_content_is_refused_and_not_stored() {
        let (_dir, store) = store(1024);
        let d = digest(b"the real thing");
        match store.write_at(&d, 0, None, body(&[b"a forgery"])).await {
            Err(Error::DigestMismatch { expected, actual }) => {
                assert_eq!(expected, d);
                assert_eq!(actual, digest(b"a forgery"));
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(store.stat(&d).await.unwrap(), None);
        assert_eq!(store.partial_offset(&d).await.unwrap(), 0);
        // Chunked too: the mismatch shows at the last chunk and discards the partial.
        assert!(matches!(
            store.write_at(&d, 0, Some(9), body(&[b"a forgery"])).await,
            Err(Error::DigestMismatch { .. })
        ));
        assert_eq!(store.partial_offset(&d).await.unwrap(), 0);
        assert!(matches!(
            store.stat("sha256:XYZ").await,
            Err(Error::Digest(_))
        ));
    }

    #[tokio::test]
    async fn size_limits_hold() {
        let (_dir, store) = store(8);
        let content = b"0123456789";
        let d = digest(content);
        assert!(matches!(
            store.write_at(&d, 0, Some(10), body(&[content])).await,
            Err(Error::TooLarge { limit: 8 })
        ));
        assert!(matches!(
            store.write_at(&d, 0, None, body(&[content])).await,
            Err(Error::TooLarge { limit: 8 })
        ));
        assert_eq!(store.partial_offset(&d).await.unwrap(), 0);
    }

    #[tokio::test]
    async fn concurrent_uploads_of_one_blob_do_not_corrupt_it() {
        let (_dir, store) = store(1 << 20);
        let content: Vec<u8> = (0..200_000u32).map(|i| (i % 251) as u8).collect();
        let d = digest(&content);
        let chunks: Vec<Vec<u8>> = content.chunks(4096).map(<[u8]>::to_vec).collect();
        let mut tasks = Vec::new();
        for _ in 0..8 {
            let (store, d, chunks) = (store.clone(), d.clone(), chunks.clone());
            tasks.push(tokio::spawn(async move {
                let parts = futures::stream::iter(chunks.into_iter().map(Ok::<_, std::io::Error>));
                store.write_at(&d, 0, None, parts).await
            }));
        }
        let mut complete = 0;
        for t in tasks {
            match t.await.unwrap().unwrap() {
                UploadState::Complete { .. } => complete += 1,
                UploadState::Exists { size } => assert_eq!(size, content.len() as u64),
                other => panic!("{other:?}"),
            }
        }
        assert_eq!(complete, 1, "exactly one upload writes the blob");
        let stored = std::fs::read(store.root().join("sha256").join(&d[7..])).unwrap();
        assert_eq!(stored, content);
    }

    #[tokio::test]
    async fn releases_list_missing_blobs_and_refuse_non_manifests() {
        let (_dir, store) = store(1 << 20);
        let present = b"print('hi')\n";
        let pd = digest(present);
        store
            .write_at(&pd, 0, None, body(&[present]))
            .await
            .unwrap();
        let absent = digest(b"policy weights");
        let manifest = ReleaseManifest::new(
            "1.0.0",
            vec![
                ManifestFile {
                    path: "main.py".into(),
                    digest: pd.clone(),
                    size: present.len() as u64,
                    mode: 0o755,
                },
                ManifestFile {
                    path: "policy/model.bin".into(),
                    digest: absent.clone(),
                    size: 14,
                    mode: 0o644,
                },
            ],
        );
        let bytes = manifest.to_bytes();
        let md = digest(&bytes);
        store.write_at(&md, 0, None, body(&[&bytes])).await.unwrap();
        let info = store.release(&md).await.unwrap();
        assert_eq!(info.manifest, manifest);
        assert_eq!(info.missing, vec![absent]);
        let json = serde_json::to_value(&info).unwrap();
        assert_eq!(json["version"], "1.0.0");
        assert_eq!(json["files"][0]["mode"], 0o755);

        assert!(matches!(
            store.release(&digest(b"nothing")).await,
            Err(Error::NotFound(_))
        ));
        match store.release(&pd).await {
            Err(e @ Error::Manifest { .. }) => {
                assert!(
                    e.to_string().contains("not a valid release manifest"),
                    "{e}"
                )
            }
            other => panic!("{other:?}"),
        }
    }
}
