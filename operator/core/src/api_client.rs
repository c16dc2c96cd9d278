//! How long the operator waits on the Kubernetes API server: every answer within a read timeout,
//! every watch closed by the server well before it.
//!
//! An API server that restarts can take a request in while it starts and never answer it. A watch
//! is guarded by the watcher's own idle timeout, but the list a watcher starts with (and any other
//! request) is not: a Robot watch of the rollout controller once waited on such a list for good,
//! and the rollout planned from a Robot store that stopped in the minute of the restart. With a
//! read timeout the request fails, the watcher retries it, and the store catches up.

use std::time::Duration;

use kube::runtime::watcher;

/// Longest the client waits for the API server to send anything on a request.
pub const READ_TIMEOUT: Duration = Duration::from_secs(60);

/// Seconds after which the API server ends a watch (the watcher then resumes it from its last
/// resource version). Shorter than [`READ_TIMEOUT`]: a watch of an object that does not change
/// receives nothing until the server ends it, so the server must end it before the read timeout
/// would.
pub const WATCH_TIMEOUT_SECS: u32 = 50;

/// Whether the API server said that the object `name` does not exist: a 404 whose details name
/// it. A 404 without them comes from a path the server does not serve (yet): a restarting API
/// server answers so for custom resources until it has loaded their definitions, and a gateway
/// that took that for a deleted Robot stopped writing the status of a robot still connected.
pub fn is_missing(status: &kube::core::Status, name: &str) -> bool {
    status.code == 404 && status.details.as_ref().is_some_and(|d| d.name == name)
}

/// Sets the read timeout on the configuration every operator client is built from.
pub fn with_timeouts(mut config: kube::Config) -> kube::Config {
    config.read_timeout = Some(READ_TIMEOUT);
    // The timeout counts from the request, not from when its pooled connection went idle.
    config.reset_reader_on_write = true;
    config
}

/// A watcher configuration whose watches the server ends within [`WATCH_TIMEOUT_SECS`].
pub fn watch_config() -> watcher::Config {
    watcher::Config::default().timeout(WATCH_TIMEOUT_SECS)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::AsyncReadExt;

    /// Only a 404 that names the object says it is missing; the plain "404 page not found" of
    /// a path not served yet does not.
    #[test]
    fn only_a_not_found_naming_the_object_says_it_is_missing() {
        let missing: kube::core::Status = serde_json::from_value(serde_json::json!({
            "kind": "Status", "apiVersion": "v1", "status": "Failure", "reason": "NotFound",
            "message": "robots.fleet.lekiwi.io \"kiwi\" not found", "code": 404,
            "details": {"name": "kiwi", "group": "fleet.lekiwi.io", "kind": "robots"},
        }))
        .unwrap();
        assert!(is_missing(&missing, "kiwi"));
        assert!(!is_missing(&missing, "other"));
        let unserved =
            kube::core::Status::failure("404 page not found", "Failed to parse error data")
                .with_code(404);
        assert!(!is_missing(&unserved, "kiwi"));
        let conflict = kube::core::Status::failure("changed", "Conflict").with_code(409);
        assert!(!is_missing(&conflict, "kiwi"));
    }

    /// A server that takes the connection and the request in and never answers: the request
    /// fails once the read timeout passed, rather than waiting for good.
    #[tokio::test]
    async fn a_request_the_server_never_answers_fails_after_the_read_timeout() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        tokio::spawn(async move {
            while let Ok((mut conn, _)) = listener.accept().await {
                tokio::spawn(async move {
                    let mut buf = [0u8; 4096];
                    while matches!(conn.read(&mut buf).await, Ok(n) if n > 0) {}
                });
            }
        });
        let url = format!("http://{addr}").parse().unwrap();
        let client = kube::Client::try_from(with_timeouts(kube::Config::new(url))).unwrap();
        let started = tokio::time::Instant::now();
        let waited = tokio::time::timeout(READ_TIMEOUT * 2, client.apiserver_version()).await;
        let answer = waited.expect("the request still waited at twice the read timeout");
        assert!(answer.is_err(), "{answer:?}");
        assert!(started.elapsed() >= READ_TIMEOUT - Duration::from_secs(1));
    }

    #[test]
    fn a_watch_ends_before_the_read_timeout_would_cut_it() {
        let config = with_timeouts(kube::Config::new("https://127.0.0.1:6443".parse().unwrap()));
        assert_eq!(config.read_timeout, Some(READ_TIMEOUT));
        assert!(config.reset_reader_on_write);
        let watch = watch_config().timeout.expect("a server-side timeout");
        assert!(Duration::from_secs(u64::from(watch)) + Duration::from_secs(5) < READ_TIMEOUT);
    }
}
