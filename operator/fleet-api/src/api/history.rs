//! `GET /api/v1/namespaces/{namespace}/robots/{name}/events` and `.../telemetry`: a robot's
//! stored events and telemetry samples within a time range, a page at a time, from the event
//! store (SQLite or PostgreSQL). Allowed by `get` on the `robots/events` and
//! `robots/telemetry` subresources.

use axum::Json;
use axum::extract::rejection::QueryRejection;
use axum::extract::{Path, Query, State};
use axum::http::HeaderMap;
use jiff::{SignedDuration, Timestamp};
use serde::Deserialize;

use super::robots::Page;
use super::{authorize, bad_query, check_names, page_size, ready};
use crate::kube_auth::Access;
use crate::{ApiError, FleetState};
use lekiwi_core::RobotKey;
use lekiwi_event_store::{SampleCursor, StoredEvent, StoredSample, TimeRange};

/// How far back a range reaches when the query gives no `since`.
const DEFAULT_SPAN: SignedDuration = SignedDuration::from_hours(1);

/// Query of the history routes.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HistoryQuery {
    /// Start of the range (RFC 3339, included); default one hour before `until` or now.
    #[serde(default, deserialize_with = "super::blank_is_none")]
    pub(crate) since: Option<String>,
    /// End of the range (RFC 3339, excluded); default: no end.
    #[serde(default, deserialize_with = "super::blank_is_none")]
    pub(crate) until: Option<String>,
    /// Only samples of this metric (telemetry only).
    #[serde(default, deserialize_with = "super::blank_is_none")]
    pub(crate) metric: Option<String>,
    /// Page size.
    #[serde(default, deserialize_with = "super::blank_is_none")]
    pub(crate) limit: Option<u32>,
    /// Token of the page to resume after.
    #[serde(default, deserialize_with = "super::blank_is_none")]
    pub(crate) r#continue: Option<String>,
}

impl HistoryQuery {
    /// The `continue` token, if any: an empty one asks for the first page.
    fn resume(&self) -> Option<&str> {
        self.r#continue.as_deref().filter(|t| !t.is_empty())
    }

    fn range(&self) -> Result<TimeRange, ApiError> {
        let until = self
            .until
            .as_deref()
            .map(|t| timestamp("until", t))
            .transpose()?;
        let since = match self.since.as_deref() {
            Some(t) => timestamp("since", t)?,
            None => until.unwrap_or_else(Timestamp::now) - DEFAULT_SPAN,
        };
        let range = TimeRange {
            since_ms: since.as_millisecond(),
            until_ms: until.map_or(i64::MAX, |u| u.as_millisecond()),
        };
        if range.since_ms >= range.until_ms {
            return Err(ApiError::BadRequest("since must be before until".into()));
        }
        Ok(range)
    }
}

fn timestamp(param: &str, text: &str) -> Result<Timestamp, ApiError> {
    text.parse().map_err(|e| {
        ApiError::BadRequest(format!(
            "{param} must be an RFC 3339 time such as 2026-01-31T08:00:00Z: {e}"
        ))
    })
}

/// The robot named by the path, once the caller may `get` its `subresource`; 404 when the
/// gateway holds no such Robot (checked after the permission, so a 404 tells nothing to someone
/// who may not read it), whatever the store still keeps of it.
async fn allowed_robot(
    state: &FleetState,
    headers: &HeaderMap,
    (namespace, name): (String, String),
    subresource: &'static str,
) -> Result<RobotKey, ApiError> {
    check_names(&namespace, Some(&name))?;
    let access = Access {
        subresource: Some(subresource),
        name: Some(name.clone()),
        ..Access::new("get", "robots", &namespace)
    };
    authorize(state, headers, Some(access)).await?;
    ready(&state.fleet.robots)?;
    if state.fleet.robots.get(&namespace, &name).is_none() {
        return Err(ApiError::NotFound(format!(
            "robot {namespace}/{name} not found"
        )));
    }
    Ok(RobotKey::new(namespace, name))
}

/// `GET .../robots/{name}/events?since=&until=&limit=&continue=`: events the gateway received
/// within the range (its clock, whatever the robot's said), in ascending sequence order.
pub async fn events(
    State(state): State<FleetState>,
    Path(path): Path<(String, String)>,
    query: Result<Query<HistoryQuery>, QueryRejection>,
    headers: HeaderMap,
) -> Result<Json<Page<StoredEvent>>, ApiError> {
    let Query(query) = query.map_err(bad_query)?;
    let robot = allowed_robot(&state, &headers, path, "events").await?;
    read_events(&state, &robot, &query).await.map(Json)
}

/// The page of `robot`'s stored events `query` asks for.
pub(crate) async fn read_events(
    state: &FleetState,
    robot: &RobotKey,
    query: &HistoryQuery,
) -> Result<Page<StoredEvent>, ApiError> {
    if query.metric.is_some() {
        return Err(ApiError::BadRequest(
            "metric applies to telemetry only".into(),
        ));
    }
    let (range, limit) = (query.range()?, page_size(query.limit)?);
    let after = match query.resume() {
        None => None,
        Some(t) => Some(t.parse::<u64>().map_err(|_| invalid_continue())?),
    };
    let mut items = state
        .store
        .events_in_range(robot, after, range, limit + 1)
        .await
        .map_err(|e| ApiError::Internal(format!("reading events of {robot}: {e}")))?;
    let next = (items.len() > limit as usize).then(|| {
        items.truncate(limit as usize);
        items.last().map(|e| e.seq.to_string())
    });
    Ok(Page {
        items,
        next: next.flatten(),
    })
}

/// `GET .../robots/{name}/telemetry?metric=&since=&until=&limit=&continue=`: samples, oldest
/// first.
pub async fn telemetry(
    State(state): State<FleetState>,
    Path(path): Path<(String, String)>,
    query: Result<Query<HistoryQuery>, QueryRejection>,
    headers: HeaderMap,
) -> Result<Json<Page<StoredSample>>, ApiError> {
    let Query(query) = query.map_err(bad_query)?;
    let robot = allowed_robot(&state, &headers, path, "telemetry").await?;
    read_telemetry(&state, &robot, &query).await.map(Json)
}

/// The page of `robot`'s stored telemetry samples `query` asks for.
pub(crate) async fn read_telemetry(
    state: &FleetState,
    robot: &RobotKey,
    query: &HistoryQuery,
) -> Result<Page<StoredSample>, ApiError> {
    let (range, limit) = (query.range()?, page_size(query.limit)?);
    let after = query.resume().map(sample_cursor).transpose()?;
    let mut rows = state
        .store
        .samples_in_range(robot, query.metric.as_deref(), range, after, limit + 1)
        .await
        .map_err(|e| ApiError::Internal(format!("reading telemetry of {robot}: {e}")))?;
    let next = (rows.len() > limit as usize).then(|| {
        rows.truncate(limit as usize);
        rows.last()
            .map(|r| format!("{}.{}", r.cursor.ts_ms, r.cursor.id))
    });
    Ok(Page {
        items: rows.into_iter().map(|r| r.sample).collect(),
        next: next.flatten(),
    })
}

fn sample_cursor(token: &str) -> Result<SampleCursor, ApiError> {
    let (ts, id) = token.split_once('.').ok_or_else(invalid_continue)?;
    Ok(SampleCursor {
        ts_ms: ts.parse().map_err(|_| invalid_continue())?,
        id: id.parse().map_err(|_| invalid_continue())?,
    })
}

fn invalid_continue() -> ApiError {
    ApiError::BadRequest("invalid continue token".into())
}
