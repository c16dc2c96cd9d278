//! The reference to a software release that robots run and deployments roll out.

use lekiwi_protocol::rules;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::text::Text;

/// A software release: a version name plus the digest of its file manifest.
#[derive(Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq, Eq, Hash)]
#[serde(rename_all = "camelCase")]
pub struct ReleaseRef {
    /// Human-readable version of the release, for example `1.4.2` or `2026-11-01-nightly`.
    /// Letters, digits, `.`, `_`, `+` and `-`; 1 to 128 characters.
    #[schemars(
        length(min = 1, max = rules::MAX_VERSION_CHARS),
        regex(pattern = rules::VERSION_PATTERN)
    )]
    pub version: Text,

    /// Digest of the release's file manifest, as printed by `kubectl lekiwi release push`:
    /// `sha256:` followed by 64 lowercase hex digits. The manifest lists every file of the
    /// release with its own digest, so two robots with the same digest run the same bytes.
    #[schemars(regex(pattern = rules::DIGEST_PATTERN))]
    pub digest: Text,
}

impl std::fmt::Display for ReleaseRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let short = self.digest.strip_prefix("sha256:").unwrap_or(&self.digest);
        write!(f, "{} ({})", self.version, &short[..short.len().min(12)])
    }
}

impl From<&lekiwi_protocol::Release> for ReleaseRef {
    fn from(release: &lekiwi_protocol::Release) -> Self {
        ReleaseRef {
            version: release.version.as_str().into(),
            digest: release.digest.as_str().into(),
        }
    }
}

impl From<&ReleaseRef> for lekiwi_protocol::Release {
    fn from(release: &ReleaseRef) -> Self {
        lekiwi_protocol::Release {
            version: release.version.to_string(),
            digest: release.digest.to_string(),
        }
    }
}
