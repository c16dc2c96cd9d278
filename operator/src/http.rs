//! The operator's HTTP endpoints: `/metrics`, `/healthz` and `/readyz`.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use axum::Router;
use axum::extract::State;
use axum::http::{StatusCode, header};
use axum::response::IntoResponse;
use axum::routing::get;

use lekiwi_metrics::Metrics;

/// What the endpoints read.
#[derive(Clone)]
pub struct HttpState {
    /// Metrics to render.
    pub metrics: Metrics,
    /// Set once the operator has checked its CRDs and started its tasks.
    pub ready: Arc<AtomicBool>,
    /// Whether this replica leads right now (reported by `/readyz`).
    pub leader: tokio::sync::watch::Receiver<bool>,
    /// Set once the gateway listens, when this process runs one.
    pub gateway_ready: Option<Arc<AtomicBool>>,
}

/// The router, separate from serving so tests can call it directly.
pub fn router(state: HttpState) -> Router {
    Router::new()
        .route("/metrics", get(metrics))
        .route("/healthz", get(|| async { "ok\n" }))
        .route("/readyz", get(readyz))
        .with_state(state)
}

async fn metrics(State(state): State<HttpState>) -> impl IntoResponse {
    state.metrics.runtime.observe();
    (
        [(
            header::CONTENT_TYPE,
            "application/openmetrics-text; version=1.0.0; charset=utf-8",
        )],
        state.metrics.encode(),
    )
}

async fn readyz(State(state): State<HttpState>) -> impl IntoResponse {
    let gateway_ready = state
        .gateway_ready
        .as_ref()
        .is_none_or(|g| g.load(Ordering::Acquire));
    if state.ready.load(Ordering::Acquire) && gateway_ready {
        let role = if *state.leader.borrow() {
            "leader"
        } else {
            "standby"
        };
        (StatusCode::OK, format!("ok ({role})\n"))
    } else {
        (StatusCode::SERVICE_UNAVAILABLE, "starting\n".to_owned())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::body::Body;
    use axum::http::Request;
    use http_body_util::BodyExt;
    use tower::ServiceExt;

    #[tokio::test]
    async fn readyz_reflects_startup_and_metrics_render() {
        let ready = Arc::new(AtomicBool::new(false));
        let (_tx, leader) = tokio::sync::watch::channel(true);
        let app = router(HttpState {
            metrics: Metrics::default(),
            ready: ready.clone(),
            leader,
            gateway_ready: None,
        });
        let get = |path: &str| Request::get(path).body(Body::empty()).unwrap();

        let res = app.clone().oneshot(get("/readyz")).await.unwrap();
        assert_eq!(res.status(), StatusCode::SERVICE_UNAVAILABLE);
        ready.store(true, Ordering::Release);
        let res = app.clone().oneshot(get("/readyz")).await.unwrap();
        assert_eq!(res.status(), StatusCode::OK);
        let body = res.into_body().collect().await.unwrap().to_bytes();
        assert_eq!(&body[..], b"ok (leader)\n");

        let res = app.oneshot(get("/metrics")).await.unwrap();
        let body = res.into_body().collect().await.unwrap().to_bytes();
        assert!(
            std::str::from_utf8(&body)
                .unwrap()
                .contains("lekiwi_leader_election_is_leader")
        );
    }

    /// Each scrape reads the runtime's live tasks: three tasks kept waiting count, and no longer
    /// count once they ended.
    #[tokio::test]
    async fn a_scrape_counts_the_tasks_alive() {
        let (_tx, leader) = tokio::sync::watch::channel(false);
        let app = router(HttpState {
            metrics: Metrics::default(),
            ready: Arc::new(AtomicBool::new(true)),
            leader,
            gateway_ready: None,
        });
        let tasks = || async {
            let res = app
                .clone()
                .oneshot(Request::get("/metrics").body(Body::empty()).unwrap())
                .await
                .unwrap();
            let body = res.into_body().collect().await.unwrap().to_bytes();
            let text = String::from_utf8(body.to_vec()).unwrap();
            let line = text
                .lines()
                .find(|l| l.starts_with("lekiwi_runtime_tasks "))
                .unwrap_or_else(|| panic!("no lekiwi_runtime_tasks in {text}"));
            line.rsplit(' ').next().unwrap().parse::<i64>().unwrap()
        };
        let before = tasks().await;
        let (go, _) = tokio::sync::broadcast::channel::<()>(1);
        let waiting: Vec<_> = (0..3)
            .map(|_| {
                let mut go = go.subscribe();
                tokio::spawn(async move {
                    let _ = go.recv().await;
                })
            })
            .collect();
        assert_eq!(tasks().await, before + 3);
        go.send(()).unwrap();
        for task in waiting {
            task.await.unwrap();
        }
        assert_eq!(tasks().await, before);
    }
}
