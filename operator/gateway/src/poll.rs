//! The legacy polling endpoint: old agents `GET /v1/poll` with their robot and version and learn
//! whether an update is available. Answers come from `Robot.spec.release` as the gateway's Robot
//! watch holds it, stay the same for up to 60 s and carry an ETag so unchanged answers cost a
//! 304; a poll counts as a heartbeat.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

use axum::extract::{ConnectInfo as PeerAddr, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use kube::Api;
use lekiwi_crds::Robot;
use lekiwi_protocol::Release;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use super::auth::{Grant, Refusal};
use super::session::Limits;
use super::{ApiError, AppState, bearer};
use lekiwi_core::RobotKey;
use lekiwi_metrics::KindLabels;
use lekiwi_presence::ConnectInfo;
use lekiwi_presence::watched::WatchedRobots;

/// How long a poll answer stays the same after the robot's desired release changed.
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

/// The answer; its JSON is the response body and, hashed, its ETag.
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

/// The release each robot's polls were last answered with, and when: an answer stays the same
/// for up to [`CACHE_TTL`] after the Robot changed, as legacy agents have always been answered.
/// Its source is the gateway's Robot watch
/// ([`WatchedRobots`]); the API server is read only for a
/// robot the watch does not hold.
#[derive(Default)]
pub struct PollMemo {
    entries: Mutex<HashMap<RobotKey, (Instant, Option<Release>)>>,
}

impl PollMemo {
    /// The release `key` should run, as its polls are answered now.
    async fn desired(
        &self,
        watch: Option<&WatchedRobots>,
        client: &kube::Client,
        key: &RobotKey,
    ) -> Result<Option<Release>, ApiError> {
        if let Some(release) = self.answered(key) {
            return Ok(release);
        }
        let release = match watch.and_then(|d| d.lookup(key)) {
            Some(release) => release,
            // Not in the watch's cache: a Robot created a moment ago may not have arrived yet,
            // and the API server also tells a robot that does not exist.
            None => read_release(client, key).await?,
        };
        self.lock()
            .insert(key.clone(), (Instant::now(), release.clone()));
        Ok(release)
    }

    /// What `key`'s polls were answered with, if that was less than [`CACHE_TTL`] ago.
    fn answered(&self, key: &RobotKey) -> Option<Option<Release>> {
        self.lock()
            .get(key)
            .filter(|(at, _)| at.elapsed() < CACHE_TTL)
            .map(|(_, release)| release.clone())
    }

    fn lock(&self) -> MutexGuard<'_, HashMap<RobotKey, (Instant, Option<Release>)>> {
        self.entries.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// A robot's `spec.release` read from the API server; `NotFound` when the robot does not exist.
async fn read_release(client: &kube::Client, key: &RobotKey) -> Result<Option<Release>, ApiError> {
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
    Ok(robot.spec.release.as_ref().map(Release::from))
}

/// `GET /v1/poll?robot=ns/name&version=V`.
pub async fn poll(
    State(state): State<AppState>,
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
    // Only the robot's own token may speak for it: an enrollment token would fake presence.
    let Grant::Robot(key) = grant else {
        return Err(state.refused(Refusal::EnrollmentToken));
    };
    let desired = state
        .poll_memo
        .desired(state.shared.desired.as_ref(), &state.client, &key)
        .await?;
    let answer = PollAnswer::new(&q, desired.as_ref(), &state.shared.limits);
    // The robot's release is known exactly when it runs the desired version.
    let release = desired.filter(|r| r.version == q.version);
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
    Ok(respond(&state, &headers, body))
}

impl PollAnswer {
    /// The answer to a robot that runs `q.version` and should run `desired`.
    fn new(q: &PollQuery, desired: Option<&Release>, limits: &Limits) -> Self {
        PollAnswer {
            update_available: desired.is_some_and(|r| r.version != q.version),
            current_version: q.version.clone(),
            target_version: desired.map(|r| r.version.clone()),
            target_digest: desired.map(|r| r.digest.clone()),
            manifest_url: desired.map(|r| lekiwi_protocol::release::blob_path(&r.digest)),
            poll_interval_seconds: limits.heartbeat_interval.as_secs().max(1),
        }
    }
}

/// The answer `body` with its ETag, or a bodiless 304 when the client holds that ETag already.
fn respond(state: &AppState, headers: &HeaderMap, body: String) -> Response {
    let etag = format!(
        "\"{}\"",
        &hex::encode(Sha256::digest(body.as_bytes()))[..32]
    );
    let unchanged = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        == Some(etag.as_str());
    state
        .shared
        .metrics
        .gateway
        .polls
        .get_or_create(&KindLabels {
            kind: if unchanged { "304" } else { "200" },
        })
        .inc();
    let mut response = if unchanged {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        ([(header::CONTENT_TYPE, "application/json")], body).into_response()
    };
    let h = response.headers_mut();
    if let Ok(v) = HeaderValue::from_str(&etag) {
        h.insert(header::ETAG, v);
    }
    // Clients revalidate every poll (a 304 costs nothing); an answer stays the same for up to
    // 60 s (see `PollMemo`), and its source is the gateway's Robot watch, so polls cost the API
    // server no reads for robots the watch holds.
    h.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static("private, no-cache"),
    );
    response
}
