//! `GET /api/v1/robots`, `/api/v1/namespaces/{namespace}/robots[/{name}]`: the fleet's Robots
//! from the gateway's cache, filtered by label selector, phase and release, a page at a time.

use std::sync::Arc;

use axum::Json;
use axum::extract::rejection::QueryRejection;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, header};
use axum::response::{IntoResponse, Response};
use jiff::Timestamp;
use lekiwi_crds::Robot;
use lekiwi_crds::robot::{RobotPhase, TelemetrySummary};
use serde::{Deserialize, Serialize};

use super::selector::Selector;
use super::{authorize, bad_query, check_names, continue_after, page_size, ready, resume_key};
use crate::kube_auth::Access;
use crate::{ApiError, FleetState};
use lekiwi_core::RobotKey;
use lekiwi_core::cache::{Found, Key};

static NO_LABELS: std::collections::BTreeMap<String, String> = std::collections::BTreeMap::new();

/// Query of the robot lists.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "camelCase")]
pub struct ListQuery {
    /// Label selector, as `kubectl get -l` takes it.
    #[serde(default, deserialize_with = "super::blank_is_none")]
    pub(crate) label_selector: Option<String>,
    /// Only robots in this phase.
    #[serde(default, deserialize_with = "super::blank_is_none")]
    pub(crate) phase: Option<String>,
    /// Only robots reporting that they run this release version.
    #[serde(default, deserialize_with = "super::blank_is_none")]
    pub(crate) release: Option<String>,
    /// Page size.
    #[serde(default, deserialize_with = "super::blank_is_none")]
    pub(crate) limit: Option<u32>,
    /// Token of the page to resume after.
    #[serde(default, deserialize_with = "super::blank_is_none")]
    pub(crate) r#continue: Option<String>,
}

/// A page of a list.
#[derive(Debug, Serialize)]
pub struct Page<T> {
    /// The objects, ordered by namespace and name.
    pub items: Vec<T>,
    /// Resumes after the last item; absent on the last page.
    #[serde(rename = "continue", skip_serializing_if = "Option::is_none")]
    pub next: Option<String>,
}

/// One robot and its latest vitals.
#[derive(Debug, Serialize)]
pub struct RobotView {
    /// The Robot as stored, without managed fields.
    robot: Arc<Robot>,
    /// Its latest telemetry summary (CPU, memory, temperature, battery).
    vitals: Option<TelemetrySummary>,
    /// When the gateway last recorded a heartbeat (the vitals are as of then).
    #[serde(rename = "vitalsTime")]
    vitals_time: Option<String>,
    /// When the robot was last heard from (see [`last_seen`]).
    #[serde(rename = "lastSeen", skip_serializing_if = "Option::is_none")]
    last_seen: Option<String>,
}

/// `GET /api/v1/robots`: robots of every namespace the gateway watches (`list robots` in all
/// namespaces).
pub async fn list_all(
    State(state): State<FleetState>,
    query: Result<Query<ListQuery>, QueryRejection>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    list(state, None, query, headers).await
}

/// `GET /api/v1/namespaces/{namespace}/robots` (`list robots` in that namespace).
pub async fn list_namespaced(
    State(state): State<FleetState>,
    Path(namespace): Path<String>,
    query: Result<Query<ListQuery>, QueryRejection>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    check_names(&namespace, None)?;
    list(state, Some(namespace), query, headers).await
}

async fn list(
    state: FleetState,
    namespace: Option<String>,
    query: Result<Query<ListQuery>, QueryRejection>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let Query(query) = query.map_err(bad_query)?;
    let access = Access::new("list", "robots", namespace.as_deref().unwrap_or_default());
    authorize(&state, &headers, Some(access)).await?;
    let filter = Filter::parse(&query)?;
    ready(&state.fleet.robots)?;
    let found = state.fleet.robots.page_json_objects(
        filter.place(namespace.as_deref()),
        filter.limit,
        |r| filter.keep(r),
    );
    let keys: Vec<RobotKey> = found.items.iter().map(|(r, _)| robot_key(r)).collect();
    let held = state.presence.last_heartbeats(&keys);
    let body = page_body(&found, held);
    Ok(([(header::CONTENT_TYPE, "application/json")], body).into_response())
}

/// The page as [`Page`] would serialize, from each robot's JSON kept in the cache, each with its
/// `lastSeen` (`held`: the live heartbeats, in the same order), which changes with every
/// heartbeat and so is not kept in that JSON.
fn page_body(found: &Found<(Arc<Robot>, Arc<str>)>, held: Vec<Option<Timestamp>>) -> String {
    let size = found.items.iter().map(|(_, j)| j.len() + 48).sum::<usize>();
    let mut body = String::with_capacity(size + 64);
    body.push_str(r#"{"items":["#);
    for (i, ((robot, json), held)) in found.items.iter().zip(held).enumerate() {
        if i > 0 {
            body.push(',');
        }
        let open = json.strip_suffix('}').filter(|o| o.len() > 1);
        match (open, last_seen(robot, held)) {
            (Some(open), Some(seen)) => {
                body.push_str(open);
                body.push_str(r#","lastSeen":""#);
                body.push_str(&rfc3339(seen));
                body.push_str(r#""}"#);
            }
            _ => body.push_str(json),
        }
    }
    body.push(']');
    if let Some(last) = found.last.as_ref().filter(|_| found.more) {
        body.push_str(r#","continue":""#);
        body.push_str(&continue_after(last));
        body.push('"');
    }
    body.push('}');
    body
}

/// When the robot was last heard from: the later of its live heartbeat in a session this
/// gateway holds (`held`) and the `status.lastHeartbeatTime` written last (by whichever gateway
/// holds it), which a steady robot's status refreshes only once per `--status-refresh-seconds`.
pub(crate) fn last_seen(robot: &Robot, held: Option<Timestamp>) -> Option<Timestamp> {
    let written = robot
        .status
        .as_ref()
        .and_then(|s| s.last_heartbeat_time.as_ref());
    held.max(written.map(|t| t.0))
}

/// `t` in RFC 3339, to the millisecond.
fn rfc3339(t: Timestamp) -> String {
    jiff::fmt::temporal::DateTimePrinter::new()
        .precision(Some(3))
        .timestamp_to_string(&t)
}

fn robot_key(robot: &Robot) -> RobotKey {
    RobotKey::new(
        robot.metadata.namespace.as_deref().unwrap_or_default(),
        robot.metadata.name.as_deref().unwrap_or_default(),
    )
}

/// A robot list's parsed query.
struct Filter {
    selector: Selector,
    phase: Option<RobotPhase>,
    release: Option<String>,
    after: Option<Key>,
    limit: usize,
}

impl Filter {
    fn parse(query: &ListQuery) -> Result<Self, ApiError> {
        Ok(Self {
            limit: page_size(query.limit)? as usize,
            selector: Selector::parse(query.label_selector.as_deref().unwrap_or_default())
                .map_err(ApiError::BadRequest)?,
            phase: query.phase.as_deref().map(parse_phase).transpose()?,
            release: query.release.clone(),
            after: resume_key(query.r#continue.as_deref())?,
        })
    }

    /// Where the list reads: the namespace, after the `continue` key, by a label the selector
    /// requires.
    fn place<'a>(
        &'a self,
        namespace: Option<&'a str>,
    ) -> (Option<&'a str>, Option<&'a Key>, Option<(&'a str, &'a str)>) {
        (namespace, self.after.as_ref(), self.selector.equality())
    }

    fn keep(&self, r: &Robot) -> bool {
        self.selector
            .matches(r.metadata.labels.as_ref().unwrap_or(&NO_LABELS))
            && self
                .phase
                .is_none_or(|p| r.status.as_ref().and_then(|s| s.phase) == Some(p))
            && self
                .release
                .as_deref()
                .is_none_or(|v| running(r) == Some(v))
    }
}

/// The page of robots `query` asks for in `namespace` (all if `None`), from the cache.
pub(crate) fn page(
    state: &FleetState,
    namespace: Option<&str>,
    query: &ListQuery,
) -> Result<Page<Arc<Robot>>, ApiError> {
    let filter = Filter::parse(query)?;
    ready(&state.fleet.robots)?;
    let found = state
        .fleet
        .robots
        .page_objects(filter.place(namespace), filter.limit, |r| filter.keep(r));
    let next = found
        .last
        .filter(|_| found.more)
        .map(|k| continue_after(&k));
    Ok(Page {
        items: found.items,
        next,
    })
}

/// `GET /api/v1/namespaces/{namespace}/robots/{name}` (`get robots`): the Robot and its vitals.
pub async fn one(
    State(state): State<FleetState>,
    Path((namespace, name)): Path<(String, String)>,
    headers: HeaderMap,
) -> Result<Json<RobotView>, ApiError> {
    check_names(&namespace, Some(&name))?;
    let access = Access {
        name: Some(name.clone()),
        ..Access::new("get", "robots", &namespace)
    };
    authorize(&state, &headers, Some(access)).await?;
    ready(&state.fleet.robots)?;
    let robot = state
        .fleet
        .robots
        .get(&namespace, &name)
        .ok_or_else(|| ApiError::NotFound(format!("robot {namespace}/{name} not found")))?;
    let status = robot.status.as_ref();
    let held = state.presence.last_heartbeats(&[robot_key(&robot)]);
    Ok(Json(RobotView {
        last_seen: last_seen(&robot, held.into_iter().next().flatten()).map(rfc3339),
        vitals: status.and_then(|s| s.telemetry.as_deref().cloned()),
        vitals_time: status
            .and_then(|s| s.last_heartbeat_time.as_ref())
            .map(|t| t.0.to_string()),
        robot,
    }))
}

/// The release version the robot reports it runs.
pub(crate) fn running(r: &Robot) -> Option<&str> {
    let status = r.status.as_ref()?;
    status.current_release.as_ref().map(|c| c.version.as_str())
}

pub(crate) fn parse_phase(text: &str) -> Result<RobotPhase, ApiError> {
    RobotPhase::ALL
        .into_iter()
        .find(|p| p.as_str() == text)
        .ok_or_else(|| {
            let all: Vec<_> = RobotPhase::ALL.iter().map(|p| p.as_str()).collect();
            ApiError::BadRequest(format!("unknown phase {text:?}; one of {}", all.join(", ")))
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use k8s_openapi::apimachinery::pkg::apis::meta::v1::Time;
    use lekiwi_core::cache::Cache;
    use lekiwi_crds::robot::RobotStatus;
    use lekiwi_crds::{Robot, RobotSpec};
    use serde_json::Value;

    fn robot(name: &str, written: Option<&str>) -> Robot {
        let mut r = Robot::new(name, RobotSpec::default());
        r.metadata.namespace = Some("lab".into());
        r.status = written.map(|t| RobotStatus {
            last_heartbeat_time: Some(Time(t.parse().unwrap())),
            ..RobotStatus::default()
        });
        r
    }

    /// Each item is the Robot plus `lastSeen`: the later of the live heartbeat and the written
    /// one; none when neither is known. The page stays valid JSON.
    #[test]
    fn a_page_adds_last_seen_to_each_robot() {
        let cache = Cache::listed([
            robot("held", Some("2026-12-05T08:00:00Z")),
            robot("elsewhere", Some("2026-12-05T08:01:00Z")),
            robot("never", None),
        ]);
        let found = cache.page_json_objects((Some("lab"), None, None), 10, |_| true);
        let live: Timestamp = "2026-12-05T08:04:59.123456Z".parse().unwrap();
        // In key order: elsewhere, held, never.
        let body = page_body(&found, vec![None, Some(live), None]);
        let page: Value = serde_json::from_str(&body).expect("valid JSON");
        let seen: Vec<(&str, Option<&str>)> = page["items"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| {
                (
                    r["metadata"]["name"].as_str().unwrap(),
                    r["lastSeen"].as_str(),
                )
            })
            .collect();
        assert_eq!(
            seen,
            [
                ("elsewhere", Some("2026-12-05T08:01:00.000Z")),
                ("held", Some("2026-12-05T08:04:59.123Z")),
                ("never", None),
            ]
        );
        assert_eq!(
            page["items"][1]["kind"], "Robot",
            "the resource is kept whole"
        );
        // A live heartbeat older than the written one (another gateway holds it now) loses.
        let old: Timestamp = "2026-12-05T07:00:00Z".parse().unwrap();
        let r = robot("held", Some("2026-12-05T08:00:00Z"));
        assert_eq!(
            last_seen(&r, Some(old)),
            Some("2026-12-05T08:00:00Z".parse().unwrap())
        );
    }
}
