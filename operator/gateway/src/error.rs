//! The gateway's error type: what stops a gateway from starting or serving.

/// Why the gateway stopped.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A listener could not start.
    #[error("cannot serve HTTP on {addr}: {source}")]
    Serve {
        addr: std::net::SocketAddr,
        source: std::io::Error,
    },
    /// A long-running task ended unexpectedly.
    #[error("task {0} stopped unexpectedly")]
    TaskStopped(&'static str),
}

/// Result with the gateway's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;
