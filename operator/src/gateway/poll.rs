//! The legacy polling endpoint: old agents `GET /v1/poll` with their robot and version and learn
//! whether an update is available. Answers come from `Robot.spec.release`, cached for up to
//! 60 s and served with an ETag so unchanged answers cost a 304; a poll counts as a heartbeat.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::extract::{ConnectInfo as PeerAddr, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use kube::Api;
use lekiwi_crds::{ReleaseRef, Robot};
use lekiwi_protocol::Release;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use super::presence::ConnectInfo;
use super::{ApiError, GatewayState, bearer};
use crate::gateway::event_store::RobotKey;
use crate::metrics::KindLabels;

/// How long an answer may be served from the cache.
pub const CACHE_TTL: Duration = Duration::from_secs(60);

/// Query of a poll.
#[derive(Debug, Deserialize)]
pub struct PollQuery {
    /// `namespace/name` of the robot.
    pub robot: String,
    /// Version the robot runs now.
    #[serde(default)]
    pub version: String,
    /// Version of the polling agent, if it says.
    #[serde(default)]
    pub agent: Option<String>,
}

/// The answer.
#[derive(Debug, Serialize)]
pub struct PollAnswer {
    /// Whether the robot should switch to `target_version`.
    pub update_available: bool,
    /// The version the robot reported.
    pub current_version: String,
    /// The version it should run, if one is set.
    pub target_version: Option<String>,
    /// Digest of the target release's manifest.
    pub target_digest: Option<String>,
    /// Where to fetch the target release's manifest.
    pub manifest_url: Option<String>,
    /// Seconds until the next poll.
    pub poll_interval_seconds: u64,
}

/// Desired releases read from the API server, per robot, with when they were read.
#[derive(Default)]
pub struct ReleaseCache {
    entries: Mutex<HashMap<RobotKey, (Instant, Option<ReleaseRef>)>>,
}

impl ReleaseCache {
    async fn desired(
        &self,
        client: &kube::Client,
        key: &RobotKey,
    ) -> Result<Option<ReleaseRef>, ApiError> {
        if let Some((at, release)) = self
            .entries
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .get(key)
            && at.elapsed() < CACHE_TTL
        {
            return Ok(release.clone());
        }
        let api: Api<Robot> = Api::namespaced(client.clone(), &key.namespace);
        let robot = api
            .get_opt(&key.name)
            .await
            .map_err(|e| ApiError::Internal(format!("read robot: {e}")))?;
        let robot = robot.ok_or_else(|| {
            ApiError::NotFound(format!(
                "robot {}/{} does not exist",
                key.namespace, key.name
            ))
        })?;
        let release = robot.spec.release;
        self.entries
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .insert(key.clone(), (Instant::now(), release.clone()));
        Ok(release)
    }
}

/// `GET /v1/poll?robot=ns/name&version=V`.
pub async fn poll(
    State(state): State<GatewayState>,
    PeerAddr(peer): PeerAddr<SocketAddr>,
    Query(q): Query<PollQuery>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let grant = state
        .shared
        .auth
        .authenticate(bearer(&headers), Some(&q.robot))
        .await
        .map_err(|r| state.refused(r))?;
    let key = grant.robot().clone();
    if !q.robot.contains('/') {
        return Err(ApiError::BadRequest(
            "robot must be given as namespace/name".into(),
        ));
    }
    let desired = state.releases.desired(&state.client, &key).await?;
    let answer = PollAnswer {
        update_available: desired.as_ref().is_some_and(|r| r.version != q.version),
        current_version: q.version.clone(),
        target_version: desired.as_ref().map(|r| r.version.clone()),
        target_digest: desired.as_ref().map(|r| r.digest.clone()),
        manifest_url: desired
            .as_ref()
            .map(|r| lekiwi_protocol::release::blob_path(&r.digest)),
        poll_interval_seconds: state.shared.limits.heartbeat_interval.as_secs().max(1),
    };
    // The robot's release is known exactly when it runs the desired version.
    let release = desired
        .filter(|r| r.version == q.version)
        .map(|r| Release::from(&r));
    state.shared.presence.poll(
        &key,
        ConnectInfo {
            protocol: "poll",
            agent_version: q.agent.clone().unwrap_or_default(),
            release,
            address: Some(peer.ip().to_string()),
            ..ConnectInfo::default()
        },
    );

    let body = serde_json::to_string(&answer).map_err(|e| ApiError::Internal(e.to_string()))?;
    let etag = format!(
        "\"{}\"",
        &hex::encode(Sha256::digest(body.as_bytes()))[..32]
    );
    let mut response = if headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        == Some(etag.as_str())
    {
        state
            .shared
            .metrics
            .gateway
            .polls
            .get_or_create(&KindLabels { kind: "304" })
            .inc();
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        state
            .shared
            .metrics
            .gateway
            .polls
            .get_or_create(&KindLabels { kind: "200" })
            .inc();
        ([(header::CONTENT_TYPE, "application/json")], body).into_response()
    };
    let h = response.headers_mut();
    if let Ok(v) = HeaderValue::from_str(&etag) {
        h.insert(header::ETAG, v);
    }
    // Clients revalidate every poll (a 304 costs nothing); the gateway caches the answer's
    // source for up to 60 s, so a polling fleet costs the API server at most one read per robot
    // per minute.
    h.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static("private, no-cache"),
    );
    Ok(response)
}

/// Shared cache handle.
pub type SharedCache = Arc<ReleaseCache>;
