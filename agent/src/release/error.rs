//! The release machinery's one error type, and the helper that attaches a path to I/O errors.

use std::path::PathBuf;

use lekiwi_protocol::release::ManifestError;

/// Errors of the release machinery; most end a deployment as `failed` with this text.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file or directory of the release store could not be read or written.
    #[error("release store: {path}: {source}")]
    Io {
        /// The file or directory the operation was on.
        path: PathBuf,
        /// What the operating system said.
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
        /// The digest the manifest names for it (`sha256:<hex>`).
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

/// `Result` with the release [`Error`] as the default error.
pub type Result<T, E = Error> = std::result::Result<T, E>;

pub(super) fn io(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> Error {
    let path = path.into();
    move |source| Error::Io { path, source }
}
