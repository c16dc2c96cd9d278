//! Release manifests: what a release is made of, as the CLI uploads it and agents fetch it.
//!
//! A release is a directory of files. Each file is stored once, content-addressed by its SHA-256
//! (a *blob*); the manifest lists path, digest, size and mode of every file and is itself a blob.
//! The manifest's digest names the release (`RobotDeployment.spec.release.digest`).

use serde::{Deserialize, Serialize};

/// URL path of the blob API, relative to the gateway's base URL; a blob is at
/// `{BLOBS_PATH}/sha256:<hex>`.
pub const BLOBS_PATH: &str = "/v1/blobs";

/// Media type of a manifest.
pub const MANIFEST_MEDIA_TYPE: &str = "application/vnd.lekiwi.release.manifest.v1+json";

/// Largest manifest accepted, bytes (about 20,000 files).
pub const MAX_MANIFEST_BYTES: usize = 4 * 1024 * 1024;

/// Errors validating a manifest or a digest.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum ManifestError {
    /// Not `sha256:` followed by 64 lowercase hex digits.
    #[error("invalid digest {0:?}: expected sha256: followed by 64 lowercase hex digits")]
    Digest(String),
    /// A path that is absolute, empty, has `.`/`..` components or odd characters.
    #[error(
        "invalid path {0:?}: must be relative, without `.` or `..` components, NUL or backslash"
    )]
    Path(String),
    /// The same path twice.
    #[error("duplicate path {0:?}")]
    Duplicate(String),
    /// The version is empty or not a safe directory name.
    #[error("invalid version {0:?}: 1-128 characters of letters, digits, `.`, `_`, `+`, `-`")]
    Version(String),
    /// A mode with bits other than permissions.
    #[error("invalid mode {mode:o} of {path:?}: only permission bits (0o7777 at most)")]
    Mode {
        /// Path of the file in the manifest.
        path: String,
        /// Its mode.
        mode: u32,
    },
    /// Not JSON of this shape.
    #[error("not a release manifest: {0}")]
    Json(String),
}

/// One file of a release.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ManifestFile {
    /// Relative path inside the release, `/`-separated.
    pub path: String,
    /// `sha256:<hex>` of the content.
    pub digest: String,
    /// Size in bytes.
    pub size: u64,
    /// Unix permission bits, e.g. `0o644` (written as a decimal number in JSON).
    pub mode: u32,
}

/// A release's manifest.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ReleaseManifest {
    /// Media type, [`MANIFEST_MEDIA_TYPE`].
    #[serde(rename = "mediaType")]
    pub media_type: String,
    /// Version name.
    pub version: String,
    /// The files, sorted by path.
    pub files: Vec<ManifestFile>,
}

/// Checks a `sha256:<hex>` digest and returns the hex part.
pub fn digest_hex(digest: &str) -> Result<&str, ManifestError> {
    match digest.strip_prefix("sha256:") {
        Some(hex)
            if hex.len() == 64
                && hex
                    .bytes()
                    .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b)) =>
        {
            Ok(hex)
        }
        _ => Err(ManifestError::Digest(digest.to_owned())),
    }
}

/// The blob URL path of a digest.
pub fn blob_path(digest: &str) -> String {
    format!("{BLOBS_PATH}/{digest}")
}

/// Whether a version is usable as a directory name.
pub fn valid_version(version: &str) -> bool {
    !version.is_empty()
        && version.len() <= 128
        && version != "."
        && version != ".."
        && version
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'+' | b'-'))
}

fn valid_path(path: &str) -> bool {
    !path.is_empty()
        && !path.starts_with('/')
        && !path.contains('\0')
        && !path.contains('\\')
        && path
            .split('/')
            .all(|c| !c.is_empty() && c != "." && c != "..")
}

impl ReleaseManifest {
    /// A manifest of `files` (sorted here).
    pub fn new(version: impl Into<String>, mut files: Vec<ManifestFile>) -> Self {
        files.sort_by(|a, b| a.path.cmp(&b.path));
        Self {
            media_type: MANIFEST_MEDIA_TYPE.to_owned(),
            version: version.into(),
            files,
        }
    }

    /// Parses and validates a manifest.
    pub fn parse(bytes: &[u8]) -> Result<Self, ManifestError> {
        if bytes.len() > MAX_MANIFEST_BYTES {
            return Err(ManifestError::Json(format!(
                "{} bytes, more than the limit of {MAX_MANIFEST_BYTES}",
                bytes.len()
            )));
        }
        let m: Self =
            serde_json::from_slice(bytes).map_err(|e| ManifestError::Json(e.to_string()))?;
        m.validate()?;
        Ok(m)
    }

    /// Checks version, paths (relative, unique, no prefix of another), digests and modes.
    pub fn validate(&self) -> Result<(), ManifestError> {
        if self.media_type != MANIFEST_MEDIA_TYPE {
            return Err(ManifestError::Json(format!(
                "mediaType {:?}, expected {MANIFEST_MEDIA_TYPE}",
                self.media_type
            )));
        }
        if !valid_version(&self.version) {
            return Err(ManifestError::Version(self.version.clone()));
        }
        let mut paths = std::collections::BTreeSet::new();
        for f in &self.files {
            if !valid_path(&f.path) {
                return Err(ManifestError::Path(f.path.clone()));
            }
            digest_hex(&f.digest)?;
            if f.mode > 0o7777 {
                return Err(ManifestError::Mode {
                    path: f.path.clone(),
                    mode: f.mode,
                });
            }
            if !paths.insert(f.path.as_str()) {
                return Err(ManifestError::Duplicate(f.path.clone()));
            }
        }
        // A file may not also be a directory of another file (`a` and `a/b`).
        for p in &paths {
            let mut prefix = String::new();
            for comp in p.split('/').collect::<Vec<_>>().iter().rev().skip(1).rev() {
                if !prefix.is_empty() {
                    prefix.push('/');
                }
                prefix.push_str(comp);
                if paths.contains(prefix.as_str()) {
                    return Err(ManifestError::Duplicate(prefix));
                }
            }
        }
        Ok(())
    }

    /// Canonical bytes: what is uploaded and hashed.
    pub fn to_bytes(&self) -> Vec<u8> {
        serde_json::to_vec(self).unwrap_or_default()
    }

    /// Sum of the files' sizes.
    pub fn total_bytes(&self) -> u64 {
        self.files.iter().map(|f| f.size).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file(path: &str) -> ManifestFile {
        ManifestFile {
            path: path.into(),
            digest: format!("sha256:{}", "a".repeat(64)),
            size: 3,
            mode: 0o644,
        }
    }

    #[test]
    fn valid_manifests_round_trip_sorted() {
        let m = ReleaseManifest::new("1.2.0", vec![file("b/c.py"), file("a.txt")]);
        assert_eq!(m.files[0].path, "a.txt");
        let parsed = ReleaseManifest::parse(&m.to_bytes()).unwrap();
        assert_eq!(parsed, m);
        assert_eq!(parsed.total_bytes(), 6);
    }

    #[test]
    fn bad_manifests_are_refused_with_the_reason() {
        for (files, want) in [
            (vec![file("/etc/passwd")], "invalid path"),
            (vec![file("a/../../x")], "invalid path"),
            (vec![file("a//b")], "invalid path"),
            (vec![file("a"), file("a")], "duplicate"),
            (vec![file("a"), file("a/b")], "duplicate"),
        ] {
            let err = ReleaseManifest::new("1", files).validate().unwrap_err();
            assert!(err.to_string().contains(want), "{err}");
        }
        let mut bad = file("x");
        bad.digest = "sha256:XYZ".into();
        assert!(matches!(
            ReleaseManifest::new("1", vec![bad]).validate(),
            Err(ManifestError::Digest(_))
        ));
        let mut bad = file("x");
        bad.mode = 0o100644;
        assert!(ReleaseManifest::new("1", vec![bad]).validate().is_err());
        assert!(matches!(
            ReleaseManifest::new("../x", vec![]).validate(),
            Err(ManifestError::Version(_))
        ));
        assert!(ReleaseManifest::parse(b"{}").is_err());
    }

    #[test]
    fn digests_are_checked() {
        let hex = "0123456789abcdef".repeat(4);
        assert_eq!(digest_hex(&format!("sha256:{hex}")).unwrap(), hex);
        assert!(digest_hex("sha256:abc").is_err());
        assert!(digest_hex(&format!("md5:{hex}")).is_err());
        assert_eq!(blob_path("sha256:ab"), "/v1/blobs/sha256:ab");
    }
}
