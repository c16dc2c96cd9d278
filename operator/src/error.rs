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
    /// Writing a Robot's spec or annotations failed.
    #[error("cannot patch {object}: {source}")]
    PatchRobot { object: String, source: kube::Error },
    /// Writing a Robot's status failed.
    #[error("cannot patch status of {object}: {source}")]
    PatchStatus { object: String, source: kube::Error },
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
    /// The durable event store failed.
    #[error("event store: {0}")]
    Store(#[from] lekiwi_event_store::Error),
}

/// What the caller of a failed operation can do about it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Category {
    /// The object changed since it was read (409): plan again from the newer version, which
    /// the watch brings; nothing is wrong.
    Conflict,
    /// The API server or the database is unreachable, overloaded or timed out (network errors,
    /// 429, 5xx): the same call can succeed later; back off and retry.
    Transient,
    /// Retrying the same call cannot help (a refused or invalid write, a missing CRD or
    /// permission, bad configuration): retry rarely, and say so loudly.
    Permanent,
}

/// The category of a failed Kubernetes API call.
fn kube_category(e: &kube::Error) -> Category {
    match e {
        kube::Error::Api(status) => match status.code {
            409 => Category::Conflict,
            408 | 429 | 500..=599 => Category::Transient,
            _ => Category::Permanent,
        },
        // The request never got an answer: connection refused or reset, TLS, timeouts.
        _ => Category::Transient,
    }
}

impl Error {
    /// What a caller can do about this error (see [`Category`]).
    pub fn category(&self) -> Category {
        match self {
            Error::PatchRobot { source, .. }
            | Error::PatchStatus { source, .. }
            | Error::Lease { source, .. }
            | Error::Crd { source, .. } => kube_category(source),
            Error::CrdNotEstablished(_) | Error::TaskStopped(_) => Category::Transient,
            Error::KubeConfig(_) | Error::CrdMissing(_) | Error::Serve { .. } => {
                Category::Permanent
            }
            Error::Store(e) if e.is_transient() => Category::Transient,
            Error::Store(_) => Category::Permanent,
        }
    }

    /// Whether the API server refused a write because the object changed since it was read
    /// (409 Conflict: a `resourceVersion` precondition failed).
    pub fn is_conflict(&self) -> bool {
        matches!(
            self,
            Error::PatchStatus {
                source: kube::Error::Api(status),
                ..
            } if status.code == 409
        )
    }

    /// A bounded label for the `reason` of the error metric.
    pub fn metric_reason(&self) -> &'static str {
        match self {
            Error::KubeConfig(_) => "kube_config",
            Error::CrdMissing(_) | Error::Crd { .. } | Error::CrdNotEstablished(_) => "crd",
            Error::PatchStatus { .. } => "patch_status",
            Error::PatchRobot { .. } => "patch_robot",
            Error::Lease { .. } => "lease",
            Error::Serve { .. } => "serve",
            Error::TaskStopped(_) => "task_stopped",
            Error::Store(_) => "store",
        }
    }
}

/// Result with the operator's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    use super::*;

    fn api(code: u16) -> kube::Error {
        let status: kube::core::Status =
            serde_json::from_value(serde_json::json!({ "code": code })).unwrap();
        kube::Error::Api(Box::new(status))
    }

    fn patch(code: u16) -> Error {
        Error::PatchStatus {
            object: "lab/kiwi".into(),
            source: api(code),
        }
    }

    #[test]
    fn api_answers_are_sorted_by_what_a_retry_can_do() {
        assert_eq!(patch(409).category(), Category::Conflict);
        for code in [408, 429, 500, 503, 504] {
            assert_eq!(patch(code).category(), Category::Transient, "{code}");
        }
        for code in [400, 403, 404, 422] {
            assert_eq!(patch(code).category(), Category::Permanent, "{code}");
        }
        let lease = Error::Lease {
            name: "leader".into(),
            source: api(503),
        };
        assert_eq!(lease.category(), Category::Transient);
    }

    #[test]
    fn setup_and_store_errors_are_sorted_too() {
        assert_eq!(
            Error::CrdMissing("robots.fleet.lekiwi.io".into()).category(),
            Category::Permanent
        );
        assert_eq!(
            Error::CrdNotEstablished("robots.fleet.lekiwi.io".into()).category(),
            Category::Transient
        );
        assert_eq!(
            Error::Store(lekiwi_event_store::Error::Closed).category(),
            Category::Transient
        );
        assert_eq!(
            Error::Store(lekiwi_event_store::Error::SeqOutOfRange(u64::MAX)).category(),
            Category::Permanent
        );
    }

    #[tokio::test]
    async fn store_errors_are_wrapped_with_their_reason() {
        let err: Error = lekiwi_event_store::Store::connect("nope://x")
            .await
            .unwrap_err()
            .into();
        assert_eq!(err.metric_reason(), "store");
        assert!(
            err.to_string()
                .starts_with("event store: unsupported event store URL")
        );
    }
}
