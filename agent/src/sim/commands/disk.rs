//! A simulated robot's "disk", in memory: the releases it keeps (a pointer each to a manifest
//! the fleet shares), the one `current` points at, and the blobs of an unfinished download with
//! how much of each it holds. So a second deploy fetches only the files that changed, a
//! rollback to a kept release fetches nothing, and a download cut off resumes where it stopped,
//! as on a real agent's content store.

use std::collections::HashSet;
use std::sync::Arc;

use lekiwi_protocol::Release;

use super::shared::Known;

/// Releases kept after a successful deploy, `current` included (the agent's `releaseKeep`).
pub(in crate::sim) const KEEP: usize = 3;

/// See the module docs.
#[derive(Debug, Default)]
pub(in crate::sim) struct Disk {
    /// The release `current` points at.
    current: Option<Arc<Known>>,
    /// Releases assembled, the most recently current first.
    kept: Vec<Arc<Known>>,
    /// Blobs held outside the kept releases.
    loose: Vec<Loose>,
}

/// A blob in the store that no kept release holds (yet): the manifest or a file of a release
/// being downloaded, whole or in part.
pub(in crate::sim) struct Loose {
    digest: String,
    size: u64,
    /// Bytes of it held.
    pub(in crate::sim) have: u64,
    /// The hash of those bytes, while it is incomplete.
    hasher: Option<ring::digest::Context>,
}

impl std::fmt::Debug for Loose {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} {}/{}", self.digest, self.have, self.size)
    }
}

impl Loose {
    /// Appends `chunk`.
    pub(in crate::sim) fn add(&mut self, chunk: &[u8]) {
        self.have += chunk.len() as u64;
        if let Some(h) = self.hasher.as_mut() {
            h.update(chunk);
        }
    }

    /// Forgets what it held (the gateway sent the whole blob again).
    pub(in crate::sim) fn reset(&mut self) {
        self.have = 0;
        self.hasher = Some(ring::digest::Context::new(&ring::digest::SHA256));
    }

    /// Once all of it is held: its digest matches (`Ok`), or the digest it has instead.
    pub(in crate::sim) fn verify(&mut self) -> Result<(), String> {
        let Some(h) = self.hasher.take() else {
            return Ok(());
        };
        let actual = format!("sha256:{}", hex(h.finish().as_ref()));
        if actual == self.digest {
            Ok(())
        } else {
            self.reset();
            Err(actual)
        }
    }

    /// Whether all of it is held.
    pub(in crate::sim) fn complete(&self) -> bool {
        self.have == self.size && self.hasher.is_none()
    }
}

/// Lowercase hex digits of `bytes`.
pub(super) fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

impl Disk {
    /// A robot that runs `factory` (kept, with no files), or nothing.
    pub(in crate::sim) fn new(factory: Option<Arc<Known>>) -> Self {
        Self {
            kept: factory.iter().cloned().collect(),
            current: factory,
            loose: Vec::new(),
        }
    }

    /// The release `current` points at.
    pub(in crate::sim) fn current(&self) -> Option<&Arc<Known>> {
        self.current.as_ref()
    }

    /// The kept release `release`, if it is one.
    pub(in crate::sim) fn kept(&self, release: &Release) -> Option<Arc<Known>> {
        self.kept.iter().find(|k| k.release == *release).cloned()
    }

    /// The digests of every blob held whole: the kept releases' files and manifests, and the
    /// complete loose blobs.
    pub(in crate::sim) fn held(&self) -> HashSet<&str> {
        let kept = self.kept.iter().flat_map(|k| {
            std::iter::once(k.release.digest.as_str())
                .chain(k.manifest.files.iter().map(|f| f.digest.as_str()))
        });
        let loose = self
            .loose
            .iter()
            .filter(|l| l.complete())
            .map(|l| l.digest.as_str());
        kept.chain(loose).collect()
    }

    /// The loose blob `digest` of `size` bytes, added (empty) if the store has none of it.
    pub(in crate::sim) fn loose(&mut self, digest: &str, size: u64) -> &mut Loose {
        let i = match self.loose.iter().position(|l| l.digest == digest) {
            Some(i) => i,
            None => {
                let mut l = Loose {
                    digest: digest.to_owned(),
                    size,
                    have: 0,
                    hasher: None,
                };
                l.reset();
                self.loose.push(l);
                self.loose.len() - 1
            }
        };
        &mut self.loose[i]
    }

    /// Bytes held of blob `digest` outside the kept releases.
    pub(in crate::sim) fn partial(&self, digest: &str) -> u64 {
        self.loose
            .iter()
            .find(|l| l.digest == digest)
            .map_or(0, |l| l.have)
    }

    /// Records a verified manifest of `size` bytes.
    pub(in crate::sim) fn put_manifest(&mut self, digest: &str, size: u64) {
        let l = self.loose(digest, size);
        l.have = size;
        l.hasher = None;
    }

    /// `releases/<version>/` is complete: the release is kept, and its blobs belong to it.
    pub(in crate::sim) fn assemble(&mut self, known: Arc<Known>) {
        let files: HashSet<&str> = known
            .manifest
            .files
            .iter()
            .map(|f| f.digest.as_str())
            .chain(std::iter::once(known.release.digest.as_str()))
            .collect();
        self.loose.retain(|l| !files.contains(l.digest.as_str()));
        if self.kept(&known.release).is_none() {
            let at = usize::from(self.current.is_some()).min(self.kept.len());
            self.kept.insert(at, known);
        }
    }

    /// Points `current` at `to` (a kept release) or at nothing.
    pub(in crate::sim) fn switch(&mut self, to: Option<Arc<Known>>) {
        if let Some(k) = &to
            && let Some(i) = self.kept.iter().position(|x| Arc::ptr_eq(x, k))
        {
            let k = self.kept.remove(i);
            self.kept.insert(0, k);
        }
        self.current = to;
    }

    /// After a successful deploy: keeps [`KEEP`] releases, the current one first, and drops
    /// every loose blob (partial downloads included).
    pub(in crate::sim) fn collect_garbage(&mut self) {
        self.kept.truncate(KEEP);
        self.loose.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lekiwi_protocol::release::{ManifestFile, ReleaseManifest};

    fn digest(content: &[u8]) -> String {
        crate::release::sha256_digest(content)
    }

    fn release(version: &str, contents: &[&str]) -> Arc<Known> {
        let files = contents
            .iter()
            .enumerate()
            .map(|(i, c)| ManifestFile {
                path: format!("f{i}"),
                digest: digest(c.as_bytes()),
                size: c.len() as u64,
                mode: 0o644,
            })
            .collect();
        Arc::new(Known {
            release: Release {
                version: version.into(),
                digest: digest(version.as_bytes()),
            },
            manifest: ReleaseManifest::new(version, files),
        })
    }

    #[test]
    fn a_deployed_release_makes_only_changed_files_missing() {
        let v1 = release("1", &["a", "b", "c"]);
        let v2 = release("2", &["a", "b", "changed"]);
        let mut disk = Disk::new(None);
        assert!(disk.held().is_empty());
        disk.assemble(v1.clone());
        disk.switch(Some(v1.clone()));
        let held = disk.held();
        let missing: Vec<_> = v2
            .manifest
            .files
            .iter()
            .filter(|f| !held.contains(f.digest.as_str()))
            .map(|f| f.path.as_str())
            .collect();
        assert_eq!(missing, ["f2"]);
        assert_eq!(
            disk.kept(&v1.release).map(|k| k.release.clone()),
            Some(v1.release.clone())
        );
        assert!(disk.kept(&v2.release).is_none());
    }

    #[test]
    fn a_partial_blob_resumes_and_is_verified_whole() {
        let mut disk = Disk::new(None);
        let content = b"hello, robot";
        let d = digest(content);
        disk.loose(&d, content.len() as u64).add(&content[..5]);
        assert_eq!(disk.partial(&d), 5);
        assert!(!disk.held().contains(d.as_str()));
        let l = disk.loose(&d, content.len() as u64);
        l.add(&content[5..]);
        assert_eq!(l.verify(), Ok(()));
        assert!(disk.held().contains(d.as_str()));
        // Wrong bytes fail verification and are forgotten.
        let other = digest(b"other");
        let l = disk.loose(&other, 5);
        l.add(b"wrong");
        assert!(l.verify().is_err());
        assert_eq!(disk.partial(&other), 0);
    }

    #[test]
    fn assembling_switching_and_collecting_keep_the_latest_releases() {
        let factory = release("0", &[]);
        let mut disk = Disk::new(Some(factory.clone()));
        let versions: Vec<_> = (1..=4).map(|i| release(&i.to_string(), &["x"])).collect();
        for v in &versions {
            disk.put_manifest(&v.release.digest, 10);
            disk.loose("sha256:partial", 100).add(b"abc");
            disk.assemble(v.clone());
            assert!(
                disk.partial(&v.release.digest) == 0,
                "the manifest belongs to it"
            );
            disk.switch(Some(v.clone()));
            disk.collect_garbage();
            assert_eq!(disk.partial("sha256:partial"), 0, "partials are collected");
        }
        let kept: Vec<_> = disk
            .kept
            .iter()
            .map(|k| k.release.version.as_str())
            .collect();
        assert_eq!(kept, ["4", "3", "2"]);
        // A rollback to a kept release, then one back to nothing.
        disk.switch(disk.kept(&versions[1].release));
        assert_eq!(
            disk.current().map(|k| k.release.version.as_str()),
            Some("2")
        );
        disk.switch(None);
        assert!(disk.current().is_none());
    }
}
