//! The release store on disk: content-addressed blobs, assembled releases, the `current`
//! symlink and the deploy journal. Blocking file system code, run via `spawn_blocking`.

use std::collections::{BTreeSet, HashSet};
use std::io::Write;
use std::os::unix::fs::{MetadataExt, PermissionsExt};
use std::path::{Path, PathBuf};

use lekiwi_protocol::Release;
use lekiwi_protocol::release::{ReleaseManifest, digest_hex};
use tracing::warn;

use super::{Error, Result, Wanted, io};

mod journal;

pub(super) use journal::{Active, Finished, Journal, JournalPhase};

/// Directory inside each release that holds the agent's own files.
pub(super) const META_DIR: &str = ".lekiwi";
/// `sha256:<hex>` of `bytes`.
pub(crate) fn sha256_digest(bytes: &[u8]) -> String {
    let mut h = Hasher::new();
    h.update(bytes);
    h.finish()
}

/// Incremental SHA-256 (ring's, which uses the CPU's SHA instructions on the Pi).
#[derive(Clone)]
pub(super) struct Hasher(ring::digest::Context);

impl Hasher {
    pub(super) fn new() -> Self {
        Self(ring::digest::Context::new(&ring::digest::SHA256))
    }

    pub(super) fn update(&mut self, bytes: &[u8]) {
        self.0.update(bytes);
    }

    /// `sha256:<hex>`.
    pub(super) fn finish(self) -> String {
        use std::fmt::Write as _;
        let mut s = String::with_capacity(71);
        s.push_str("sha256:");
        for b in self.0.finish().as_ref() {
            let _ = write!(s, "{b:02x}");
        }
        s
    }
}

impl Write for Hasher {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.update(buf);
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// Releases and blobs deleted by garbage collection.
#[derive(Debug, Default)]
pub(super) struct Collected {
    pub releases: usize,
    pub blobs: usize,
}

/// Paths of the store.
#[derive(Clone, Debug)]
pub(super) struct Layout {
    root: PathBuf,
}

fn fsync_dir(dir: &Path) -> Result<()> {
    std::fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(io(dir))
}

fn remove_if_exists(path: &Path) -> Result<()> {
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(io(path)(e)),
        _ => Ok(()),
    }
}

/// Writes `bytes` to `path` durably: temporary file, fsync, rename, fsync of the directory.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut tmp_name = path.file_name().unwrap_or_default().to_owned();
    tmp_name.push(".tmp");
    let tmp = dir.join(tmp_name);
    let mut file = std::fs::File::create(&tmp).map_err(io(&tmp))?;
    file.write_all(bytes).map_err(io(&tmp))?;
    file.sync_all().map_err(io(&tmp))?;
    drop(file);
    std::fs::rename(&tmp, path).map_err(io(path))?;
    fsync_dir(dir)
}

impl Layout {
    pub(super) fn new(state_dir: &Path) -> Self {
        Self {
            root: state_dir.to_owned(),
        }
    }

    fn store(&self) -> PathBuf {
        self.root.join("blobs").join("sha256")
    }

    fn tmp(&self) -> PathBuf {
        self.root.join("blobs").join("tmp")
    }

    fn releases(&self) -> PathBuf {
        self.root.join("releases")
    }

    fn journal(&self) -> PathBuf {
        self.root.join("deploy.json")
    }

    /// The `current` symlink.
    pub(super) fn current_link(&self) -> PathBuf {
        self.root.join("current")
    }

    pub(super) fn release_dir(&self, version: &str) -> PathBuf {
        self.releases().join(version)
    }

    pub(super) fn blob_path(&self, digest: &str) -> Result<PathBuf> {
        Ok(self.store().join(digest_hex(digest)?))
    }

    pub(super) fn partial_path(&self, digest: &str) -> Result<PathBuf> {
        Ok(self.tmp().join(format!("{}.partial", digest_hex(digest)?)))
    }

    pub(super) fn create(&self) -> Result<()> {
        for dir in [self.store(), self.tmp(), self.releases()] {
            std::fs::create_dir_all(&dir).map_err(io(&dir))?;
        }
        Ok(())
    }

    /// The release `current` points at: its `.lekiwi/release.json`.
    pub(super) fn current(&self) -> Option<Release> {
        let link = self.current_link();
        let target = std::fs::read_link(&link).ok()?;
        let dir = self.root.join(target);
        match read_release(&dir) {
            Some(r) => Some(r),
            None => {
                warn!(dir = %dir.display(), "current points at no complete release");
                None
            }
        }
    }

    /// Whether `releases/<version>/` holds exactly this release.
    pub(super) fn installed(&self, release: &Release) -> bool {
        read_release(&self.release_dir(&release.version)).as_ref() == Some(release)
    }

    /// The digests (of `wanted`) present in the store.
    pub(super) fn held(&self, wanted: &[String]) -> HashSet<String> {
        wanted
            .iter()
            .filter(|d| self.blob_path(d).is_ok_and(|p| p.is_file()))
            .cloned()
            .collect()
    }

    /// Re-hashes held blobs; deletes and returns those that do not match.
    pub(super) fn verify(&self, blobs: Vec<Wanted>) -> Result<Vec<Wanted>> {
        let mut corrupt = Vec::new();
        for w in blobs {
            let path = self.blob_path(&w.digest)?;
            let mut hasher = Hasher::new();
            let ok = match std::fs::File::open(&path) {
                Ok(mut f) => {
                    let n = std::io::copy(&mut f, &mut hasher).map_err(io(&path))?;
                    n == w.size && hasher.finish() == w.digest
                }
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => false,
                Err(e) => return Err(io(&path)(e)),
            };
            if !ok {
                warn!(digest = %w.digest, path = %w.path, "held blob does not match its digest");
                remove_if_exists(&path)?;
                corrupt.push(w);
            }
        }
        Ok(corrupt)
    }

    /// A blob's content if the store holds it and it matches its digest.
    pub(super) fn read_blob(&self, digest: &str) -> Result<Option<Vec<u8>>> {
        let path = self.blob_path(digest)?;
        match std::fs::read(&path) {
            Ok(bytes) if sha256_digest(&bytes) == digest => Ok(Some(bytes)),
            Ok(_) => {
                warn!(%digest, "held blob does not match its digest; fetching it again");
                remove_if_exists(&path)?;
                Ok(None)
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(io(&path)(e)),
        }
    }

    /// Stores verified bytes as a blob.
    pub(super) fn put_blob(&self, digest: &str, bytes: &[u8]) -> Result<()> {
        let partial = self.partial_path(digest)?;
        let mut file = std::fs::File::create(&partial).map_err(io(&partial))?;
        file.write_all(bytes).map_err(io(&partial))?;
        file.sync_all().map_err(io(&partial))?;
        let blob = self.blob_path(digest)?;
        std::fs::rename(&partial, &blob).map_err(io(&blob))?;
        self.sync_store()
    }

    /// Makes the store's directory entries durable (after blobs were moved in).
    pub(super) fn sync_store(&self) -> Result<()> {
        fsync_dir(&self.store())
    }

    /// Builds `releases/<version>/` from the store: in a temporary directory, then renamed.
    pub(super) fn assemble(
        &self,
        release: &Release,
        manifest_bytes: &[u8],
        manifest: &ReleaseManifest,
    ) -> Result<()> {
        let releases = self.releases();
        let dest = self.release_dir(&release.version);
        if read_release(&dest).as_ref() == Some(release) {
            return Ok(());
        }
        if dest.exists() {
            // The same version with other content (re-uploaded). Never touch a running one.
            if self.current().is_some_and(|c| c.version == release.version) {
                return Err(Error::Invalid(format!(
                    "version {} runs now with another digest; give the new release its own version",
                    release.version
                )));
            }
            let aside = releases.join(format!(
                ".tmp-{}-old-{:08x}",
                release.version,
                rand::random::<u32>()
            ));
            std::fs::rename(&dest, &aside).map_err(io(&dest))?;
            std::fs::remove_dir_all(&aside).map_err(io(&aside))?;
        }
        let tmp = releases.join(format!(
            ".tmp-{}-{:08x}",
            release.version,
            rand::random::<u32>()
        ));
        std::fs::create_dir(&tmp).map_err(io(&tmp))?;
        let mut dirs = BTreeSet::new();
        for f in &manifest.files {
            let path = tmp.join(&f.path);
            if let Some(parent) = path.parent()
                && parent != tmp
                && dirs.insert(parent.to_owned())
            {
                std::fs::create_dir_all(parent).map_err(io(parent))?;
            }
            self.place(&self.blob_path(&f.digest)?, &path, f.mode)?;
        }
        let meta = tmp.join(META_DIR);
        std::fs::create_dir(&meta).map_err(io(&meta))?;
        for (name, bytes) in [
            ("manifest.json", manifest_bytes.to_vec()),
            (
                "release.json",
                serde_json::to_vec(release).unwrap_or_default(),
            ),
        ] {
            let path = meta.join(name);
            let mut file = std::fs::File::create(&path).map_err(io(&path))?;
            file.write_all(&bytes).map_err(io(&path))?;
            file.sync_all().map_err(io(&path))?;
        }
        // Every directory entry made above must be durable before the release "exists";
        // `create_dir_all` made the parents of nested directories too.
        let mut all_dirs = BTreeSet::new();
        for dir in &dirs {
            let mut d = dir.as_path();
            while d.starts_with(&tmp) && d != tmp && all_dirs.insert(d.to_owned()) {
                d = d.parent().unwrap_or(&tmp);
            }
        }
        for dir in &all_dirs {
            fsync_dir(dir)?;
        }
        fsync_dir(&meta)?;
        fsync_dir(&tmp)?;
        std::fs::rename(&tmp, &dest).map_err(io(&dest))?;
        fsync_dir(&releases)
    }

    /// Hard-links a blob to `dest` with `mode`, or copies it: across file systems, or when the
    /// blob is linked elsewhere with another mode (links share the mode).
    fn place(&self, blob: &Path, dest: &Path, mode: u32) -> Result<()> {
        let meta = std::fs::metadata(blob).map_err(io(blob))?;
        let mut link = true;
        if meta.mode() & 0o7777 != mode {
            if meta.nlink() == 1 {
                std::fs::set_permissions(blob, std::fs::Permissions::from_mode(mode))
                    .map_err(io(blob))?;
            } else {
                link = false;
            }
        }
        if link {
            match std::fs::hard_link(blob, dest) {
                Ok(()) => return Ok(()),
                Err(e) => warn!(error = %e, blob = %blob.display(), "cannot hard-link; copying"),
            }
        }
        std::fs::copy(blob, dest).map_err(io(dest))?;
        std::fs::set_permissions(dest, std::fs::Permissions::from_mode(mode)).map_err(io(dest))?;
        std::fs::File::open(dest)
            .and_then(|f| f.sync_all())
            .map_err(io(dest))
    }

    /// Points `current` at `releases/<version>` (or removes it): `current.new` + rename, then
    /// fsync of the state directory.
    pub(super) fn switch(&self, version: Option<&str>) -> Result<()> {
        let current = self.current_link();
        match version {
            Some(v) => {
                let new = self.root.join("current.new");
                remove_if_exists(&new)?;
                std::os::unix::fs::symlink(Path::new("releases").join(v), &new)
                    .map_err(io(&new))?;
                std::fs::rename(&new, &current).map_err(io(&current))?;
            }
            None => remove_if_exists(&current)?,
        }
        fsync_dir(&self.root)
    }

    /// Deletes what an interrupted deployment left: releases being assembled and
    /// `current.new`. Partial downloads stay, to be resumed.
    pub(super) fn clean_temporaries(&self) -> Result<()> {
        let releases = self.releases();
        for entry in std::fs::read_dir(&releases).map_err(io(&releases))? {
            let entry = entry.map_err(io(&releases))?;
            if entry.file_name().to_string_lossy().starts_with(".tmp-") {
                let path = entry.path();
                std::fs::remove_dir_all(&path).map_err(io(&path))?;
            }
        }
        remove_if_exists(&self.root.join("current.new"))
    }

    /// Keeps `keep` releases (current and the most recently current others), deletes older
    /// release directories, partial downloads and blobs no kept release references.
    pub(super) fn collect_garbage(&self, keep: usize, history: &[String]) -> Result<Collected> {
        let mut collected = Collected::default();
        self.clean_temporaries()?;
        let releases = self.releases();
        let mut present: Vec<(String, std::time::SystemTime)> = Vec::new();
        for entry in std::fs::read_dir(&releases).map_err(io(&releases))? {
            let entry = entry.map_err(io(&releases))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            if name.starts_with('.') {
                continue;
            }
            let mtime = entry
                .metadata()
                .and_then(|m| m.modified())
                .unwrap_or(std::time::UNIX_EPOCH);
            present.push((name, mtime));
        }
        // Most recently current first; releases never current after them, newest first.
        let rank = |v: &str| history.iter().position(|h| h == v);
        present.sort_by(|(a, at), (b, bt)| rank(b).cmp(&rank(a)).then(bt.cmp(at)));
        let current = self.current().map(|c| c.version);
        let mut kept: Vec<String> = current.iter().cloned().collect();
        for (name, _) in &present {
            if kept.len() >= keep {
                break;
            }
            if !kept.contains(name) {
                kept.push(name.clone());
            }
        }
        for (name, _) in &present {
            if !kept.contains(name) {
                let dir = releases.join(name);
                // Out of the way first, so that a crash never leaves a half-deleted release
                // under its real name.
                let aside = releases.join(format!(".tmp-{name}-gc"));
                std::fs::rename(&dir, &aside).map_err(io(&dir))?;
                std::fs::remove_dir_all(&aside).map_err(io(&aside))?;
                collected.releases += 1;
            }
        }
        // Blobs referenced by a kept release, the manifests included.
        let mut referenced = HashSet::new();
        for name in &kept {
            let dir = releases.join(name);
            let Some(release) = read_release(&dir) else {
                continue;
            };
            let manifest_path = dir.join(META_DIR).join("manifest.json");
            let bytes = std::fs::read(&manifest_path).map_err(io(&manifest_path))?;
            let manifest = ReleaseManifest::parse(&bytes)?;
            referenced.insert(digest_hex(&release.digest)?.to_owned());
            for f in &manifest.files {
                referenced.insert(digest_hex(&f.digest)?.to_owned());
            }
        }
        let store = self.store();
        for entry in std::fs::read_dir(&store).map_err(io(&store))? {
            let entry = entry.map_err(io(&store))?;
            if !referenced.contains(entry.file_name().to_string_lossy().as_ref()) {
                remove_if_exists(&entry.path())?;
                collected.blobs += 1;
            }
        }
        let tmp = self.tmp();
        for entry in std::fs::read_dir(&tmp).map_err(io(&tmp))? {
            let entry = entry.map_err(io(&tmp))?;
            remove_if_exists(&entry.path())?;
        }
        Ok(collected)
    }
}

/// The `.lekiwi/release.json` of a release directory.
fn read_release(dir: &Path) -> Option<Release> {
    let bytes = std::fs::read(dir.join(META_DIR).join("release.json")).ok()?;
    serde_json::from_slice(&bytes).ok()
}
