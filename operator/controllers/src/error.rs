//! The controllers' error type, and what a reconcile can do about each error ([`Category`]).

/// Everything that can fail in a controller.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Writing a Robot's spec or annotations failed.
    #[error("cannot patch {object}: {source}")]
    PatchRobot { object: String, source: kube::Error },
    /// Reading a Robot from the API server (not the store) failed.
    #[error("cannot read {object}: {source}")]
    ReadRobot { object: String, source: kube::Error },
    /// Writing a Robot's or RobotDeployment's status failed.
    #[error("cannot patch status of {object}: {source}")]
    PatchStatus { object: String, source: kube::Error },
    /// A task a controller needs (a watch, a reflector, the release check) stopped.
    #[error("task {0} stopped unexpectedly")]
    TaskStopped(&'static str),
}

/// What the caller of a failed operation can do about it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Category {
    /// The object changed since it was read (409): plan again from the newer version, which
    /// the watch brings; nothing is wrong.
    Conflict,
    /// The API server is unreachable, overloaded or timed out (network errors, 429, 5xx): the
    /// same call can succeed later; back off and retry.
    Transient,
    /// Retrying the same call cannot help (a refused or invalid write, a missing permission):
    /// retry rarely, and say so loudly.
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
            | Error::ReadRobot { source, .. }
            | Error::PatchStatus { source, .. } => kube_category(source),
            Error::TaskStopped(_) => Category::Transient,
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
            Error::PatchStatus { .. } => "patch_status",
            Error::PatchRobot { .. } => "patch_robot",
            Error::ReadRobot { .. } => "read_robot",
            Error::TaskStopped(_) => "task_stopped",
        }
    }
}

/// Result with the controllers' [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// The API server's answer `code` as the client reports it, for tests.
#[cfg(test)]
pub(crate) fn api(code: u16) -> kube::Error {
    let status: kube::core::Status =
        serde_json::from_value(serde_json::json!({ "code": code })).unwrap();
    kube::Error::Api(Box::new(status))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn patch(code: u16) -> Error {
        Error::PatchStatus {
            object: "lab/kiwi".into(),
            source: api(code),
        }
    }

    #[test]
    fn api_answers_are_sorted_by_what_a_retry_can_do() {
        assert_eq!(patch(409).category(), Category::Conflict);
        assert!(patch(409).is_conflict());
        for code in [408, 429, 500, 503, 504] {
            assert_eq!(patch(code).category(), Category::Transient, "{code}");
        }
        for code in [400, 403, 404, 422] {
            assert_eq!(patch(code).category(), Category::Permanent, "{code}");
        }
        let robot = Error::PatchRobot {
            object: "lab/kiwi".into(),
            source: api(503),
        };
        assert_eq!(robot.category(), Category::Transient);
        assert_eq!(
            Error::TaskStopped("robot reflector").category(),
            Category::Transient
        );
    }
}
