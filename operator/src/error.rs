//! The operator's error type.

/// Everything that can fail in the operator.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// No usable Kubernetes client configuration.
    #[error("cannot configure the Kubernetes client: {0}")]
    KubeConfig(String),
    /// A CRD this operator needs is not installed.
    #[error(
        "the CustomResourceDefinition {0} is not installed; run `kubectl apply -f manifests/crds/` or start with --install-crds"
    )]
    CrdMissing(String),
    /// Reading or installing CRDs failed.
    #[error("cannot check or install CRD {name}: {source}")]
    Crd { name: String, source: kube::Error },
    /// A CRD did not become Established in time.
    #[error("CRD {0} did not become Established")]
    CrdNotEstablished(String),
    /// The leader-election Lease could not be read or written.
    #[error("leader election Lease {name}: {source}")]
    Lease { name: String, source: kube::Error },
    /// The HTTP server could not start.
    #[error("cannot serve HTTP on {addr}: {source}")]
    Serve {
        addr: std::net::SocketAddr,
        source: std::io::Error,
    },
    /// A long-running task ended unexpectedly.
    #[error("task {0} stopped unexpectedly")]
    TaskStopped(&'static str),
    /// A controller failed.
    #[error(transparent)]
    Controllers(#[from] lekiwi_controllers::Error),
    /// The agent gateway failed.
    #[error(transparent)]
    Gateway(#[from] lekiwi_gateway::Error),
    /// The durable event store failed.
    #[error("event store: {0}")]
    Store(#[from] lekiwi_event_store::Error),
}

/// Result with the operator's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    use super::*;

    /// What `lekiwi-operator` prints when it cannot start: the failing part and its reason.
    #[tokio::test]
    async fn start_up_errors_name_the_part_that_failed() {
        let err: Error = lekiwi_event_store::Store::connect("nope://x")
            .await
            .unwrap_err()
            .into();
        assert!(
            err.to_string()
                .starts_with("event store: unsupported event store URL"),
            "{err}"
        );
        let err: Error = lekiwi_controllers::Error::TaskStopped("robot reflector").into();
        assert_eq!(err.to_string(), "task robot reflector stopped unexpectedly");
    }
}
