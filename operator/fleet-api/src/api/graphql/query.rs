//! Queries and mutations: robots (filtered, paged; one with its vitals, events and telemetry)
//! and rollouts with their per-robot progress, from the same caches and event store as the REST
//! routes, and the rollout actions. Each field checks the caller's permission first, as the
//! matching REST route does.

use std::collections::BTreeMap;
use std::sync::Arc;

use async_graphql::{Context, Json, Object, Result, SimpleObject};
use kube::ResourceExt;
use lekiwi_crds::deployment::{ABORT_ANNOTATION, RESTART_ANNOTATION, UNDO_ANNOTATION};
use lekiwi_crds::robot::TelemetrySummary;
use lekiwi_crds::{Robot, RobotDeployment};
use serde_json::{Value, json};

use super::scalar::BigInt;
use super::{allowed, refusal};
use crate::api::history::{self, HistoryQuery};
use crate::api::{DEFAULT_LIMIT, check_names, robots, rollouts};
use crate::kube_auth::Access;
use lekiwi_core::RobotKey;

/// A paged field's cost: 1, plus the page size asked for times what is selected in it (its
/// `items` with their fields, and `continue`), so that a query costs at least 1 per field.
fn page_cost(limit: Option<i32>, child: usize) -> usize {
    let n = limit.map_or(DEFAULT_LIMIT as usize, |n| n.clamp(1, 1000) as usize);
    n.saturating_mul(child).saturating_add(1)
}

/// A GraphQL `limit` as the REST routes take it (out of range is refused there).
fn limit(n: Option<i32>) -> Option<u32> {
    n.map(|n| u32::try_from(n).unwrap_or(0))
}

/// `namespace` (and `name`) valid, as a GraphQL error otherwise.
fn names(namespace: Option<&str>, name: Option<&str>) -> Result<()> {
    match namespace {
        Some(ns) => check_names(ns, name).map_err(refusal),
        None => Ok(()),
    }
}

/// A robot's latest vitals (its last heartbeat's telemetry summary).
#[derive(SimpleObject)]
pub struct Vitals {
    cpu_percent: Option<f64>,
    memory_percent: Option<f64>,
    temperature_celsius: Option<f64>,
    battery_percent: Option<f64>,
}

impl From<&TelemetrySummary> for Vitals {
    fn from(t: &TelemetrySummary) -> Self {
        Self {
            cpu_percent: t.cpu_percent,
            memory_percent: t.memory_percent,
            temperature_celsius: t.temperature_celsius,
            battery_percent: t.battery_percent,
        }
    }
}

/// A Robot as the gateway's cache holds it.
pub struct RobotObject(pub Arc<Robot>);

#[Object(name = "Robot")]
impl RobotObject {
    async fn namespace(&self) -> String {
        self.0.namespace().unwrap_or_default()
    }
    async fn name(&self) -> String {
        self.0.name_any()
    }
    /// The Robot's labels, as a JSON object.
    async fn labels(&self) -> Json<BTreeMap<String, String>> {
        Json(self.0.labels().clone())
    }
    /// `Pending`, `Online`, `Offline`, ...
    async fn phase(&self) -> Option<&'static str> {
        self.0.status.as_ref()?.phase.map(|p| p.as_str())
    }
    /// The release version the robot reports it runs.
    async fn release(&self) -> Option<&str> {
        robots::running(&self.0)
    }
    /// When the gateway last recorded a heartbeat (RFC 3339); the vitals are as of then.
    async fn last_heartbeat_time(&self) -> Option<String> {
        let status = self.0.status.as_ref()?;
        status.last_heartbeat_time.as_ref().map(|t| t.0.to_string())
    }
    async fn vitals(&self) -> Option<Vitals> {
        self.0
            .status
            .as_ref()?
            .telemetry
            .as_deref()
            .map(Vitals::from)
    }
    /// The whole status, as the API server holds it.
    async fn status(&self) -> Json<Value> {
        Json(serde_json::to_value(&self.0.status).unwrap_or_default())
    }
    /// Stored events the gateway received within a time range (RFC 3339, its clock, not
    /// `tsMs`; default the last hour), oldest first; needs `get robots/events`.
    #[graphql(complexity = "page_cost(limit, child_complexity)")]
    async fn events(
        &self,
        ctx: &Context<'_>,
        since: Option<String>,
        until: Option<String>,
        limit: Option<i32>,
        after: Option<String>,
    ) -> Result<EventPage> {
        let query = HistoryQuery {
            since,
            until,
            metric: None,
            limit: self::limit(limit),
            r#continue: after,
        };
        let (state, robot) = self.history(ctx, "events").await?;
        let page = history::read_events(state, &robot, &query)
            .await
            .map_err(refusal)?;
        Ok(EventPage {
            items: page
                .items
                .into_iter()
                .map(|e| Event {
                    seq: e.seq.into(),
                    ts_ms: e.ts_ms.into(),
                    kind: e.kind,
                    severity: e.severity,
                    message: e.message,
                    data: Json(e.data),
                })
                .collect(),
            next: page.next,
        })
    }
    /// Stored telemetry samples (of one `metric` if given) within a time range, oldest first;
    /// needs `get robots/telemetry`.
    #[graphql(complexity = "page_cost(limit, child_complexity)")]
    async fn telemetry(
        &self,
        ctx: &Context<'_>,
        metric: Option<String>,
        since: Option<String>,
        until: Option<String>,
        limit: Option<i32>,
        after: Option<String>,
    ) -> Result<SamplePage> {
        let query = HistoryQuery {
            since,
            until,
            metric,
            limit: self::limit(limit),
            r#continue: after,
        };
        let (state, robot) = self.history(ctx, "telemetry").await?;
        let page = history::read_telemetry(state, &robot, &query)
            .await
            .map_err(refusal)?;
        Ok(SamplePage {
            items: page
                .items
                .into_iter()
                .map(|s| Sample {
                    seq: s.seq.into(),
                    metric: s.metric,
                    ts_ms: s.ts_ms.into(),
                    value: s.value,
                })
                .collect(),
            next: page.next,
        })
    }
}

impl RobotObject {
    /// The caller's state and this robot's key once it may `get` its `subresource`.
    async fn history<'a>(
        &self,
        ctx: &Context<'a>,
        subresource: &'static str,
    ) -> Result<(&'a crate::FleetState, RobotKey)> {
        let (ns, name) = (self.0.namespace().unwrap_or_default(), self.0.name_any());
        let access = Access {
            subresource: Some(subresource),
            name: Some(name.clone()),
            ..Access::new("get", "robots", &ns)
        };
        let (state, _) = allowed(ctx, access).await?;
        Ok((state, RobotKey::new(ns, name)))
    }
}

/// One stored event of a robot.
#[derive(SimpleObject)]
pub struct Event {
    /// The robot's sequence number, shared with telemetry.
    seq: BigInt,
    /// When it happened on the robot: Unix time in milliseconds.
    ts_ms: BigInt,
    kind: String,
    severity: String,
    message: String,
    data: Json<Value>,
}

/// One stored telemetry sample.
#[derive(SimpleObject)]
pub struct Sample {
    /// The sequence number of the robot's telemetry message that carried it.
    seq: BigInt,
    metric: String,
    /// When it was measured on the robot: Unix time in milliseconds.
    ts_ms: BigInt,
    value: f64,
}

/// A page of robots; `continue` resumes after its last one.
#[derive(SimpleObject)]
pub struct RobotPage {
    items: Vec<RobotObject>,
    #[graphql(name = "continue")]
    next: Option<String>,
}

/// A page of events.
#[derive(SimpleObject)]
pub struct EventPage {
    items: Vec<Event>,
    #[graphql(name = "continue")]
    next: Option<String>,
}

/// A page of telemetry samples.
#[derive(SimpleObject)]
pub struct SamplePage {
    items: Vec<Sample>,
    #[graphql(name = "continue")]
    next: Option<String>,
}

/// A RobotDeployment (a rollout) with its per-robot progress.
pub struct RolloutObject(pub Arc<RobotDeployment>);

#[Object(name = "Rollout")]
impl RolloutObject {
    async fn namespace(&self) -> String {
        self.0.namespace().unwrap_or_default()
    }
    async fn name(&self) -> String {
        self.0.name_any()
    }
    /// The release version it rolls out (null for an agent rollout).
    async fn release(&self) -> Option<&str> {
        self.0.spec.release.as_ref().map(|r| r.version.as_str())
    }
    /// The `lekiwi-agent` version it rolls out (null for a release rollout).
    async fn agent(&self) -> Option<&str> {
        self.0.spec.agent.as_ref().map(|a| a.version.as_str())
    }
    async fn paused(&self) -> bool {
        self.0.spec.paused
    }
    /// `Progressing`, `Paused`, `Complete`, ...
    async fn phase(&self) -> Option<String> {
        let phase = self.0.status.as_ref()?.phase.as_ref()?;
        serde_json::to_value(phase)
            .ok()?
            .as_str()
            .map(str::to_owned)
    }
    async fn targeted(&self) -> i32 {
        self.0.status.as_ref().map_or(0, |s| s.targeted)
    }
    async fn updated(&self) -> i32 {
        self.0.status.as_ref().map_or(0, |s| s.updated)
    }
    async fn failed(&self) -> i32 {
        self.0.status.as_ref().map_or(0, |s| s.failed)
    }
    async fn pending(&self) -> i32 {
        self.0.status.as_ref().map_or(0, |s| s.pending)
    }
    /// Per-robot outcomes (`status.robots`): `{robot, batch, state, reason}`.
    async fn robots(&self) -> Json<Value> {
        let robots = self.0.status.as_ref().map(|s| &s.robots);
        Json(serde_json::to_value(robots).unwrap_or_default())
    }
    /// The whole status, as the API server holds it.
    async fn status(&self) -> Json<Value> {
        Json(serde_json::to_value(&self.0.status).unwrap_or_default())
    }
}

/// A page of rollouts.
#[derive(SimpleObject)]
pub struct RolloutPage {
    items: Vec<RolloutObject>,
    #[graphql(name = "continue")]
    next: Option<String>,
}

/// The queries.
pub struct QueryRoot;

#[Object]
impl QueryRoot {
    /// Robots of `namespace` (every namespace when absent: needs `list robots` cluster-wide),
    /// filtered by label selector, phase and running release, ordered by namespace and name.
    #[graphql(complexity = "page_cost(limit, child_complexity)")]
    #[allow(clippy::too_many_arguments)]
    async fn robots(
        &self,
        ctx: &Context<'_>,
        namespace: Option<String>,
        label_selector: Option<String>,
        phase: Option<String>,
        release: Option<String>,
        limit: Option<i32>,
        after: Option<String>,
    ) -> Result<RobotPage> {
        names(namespace.as_deref(), None)?;
        let ns = namespace.as_deref().unwrap_or_default();
        let (state, _) = allowed(ctx, Access::new("list", "robots", ns)).await?;
        let query = robots::ListQuery {
            label_selector,
            phase,
            release,
            limit: self::limit(limit),
            r#continue: after,
        };
        let page = robots::page(state, namespace.as_deref(), &query).map_err(refusal)?;
        Ok(RobotPage {
            items: page.items.into_iter().map(RobotObject).collect(),
            next: page.next,
        })
    }

    /// One robot (`get robots`); null when there is none.
    async fn robot(
        &self,
        ctx: &Context<'_>,
        namespace: String,
        name: String,
    ) -> Result<Option<RobotObject>> {
        names(Some(&namespace), Some(&name))?;
        let access = Access {
            name: Some(name.clone()),
            ..Access::new("get", "robots", &namespace)
        };
        let (state, _) = allowed(ctx, access).await?;
        crate::api::ready(&state.fleet.robots).map_err(refusal)?;
        Ok(state.fleet.robots.get(&namespace, &name).map(RobotObject))
    }

    /// Rollouts of `namespace` (every namespace when absent).
    #[graphql(complexity = "page_cost(limit, child_complexity)")]
    async fn rollouts(
        &self,
        ctx: &Context<'_>,
        namespace: Option<String>,
        limit: Option<i32>,
        after: Option<String>,
    ) -> Result<RolloutPage> {
        names(namespace.as_deref(), None)?;
        let ns = namespace.as_deref().unwrap_or_default();
        let (state, _) = allowed(ctx, Access::new("list", "robotdeployments", ns)).await?;
        let query = rollouts::ListQuery {
            limit: self::limit(limit),
            r#continue: after,
        };
        let page = rollouts::page(state, namespace.as_deref(), &query).map_err(refusal)?;
        Ok(RolloutPage {
            items: page.items.into_iter().map(RolloutObject).collect(),
            next: page.next,
        })
    }

    /// One rollout (`get robotdeployments`); null when there is none.
    async fn rollout(
        &self,
        ctx: &Context<'_>,
        namespace: String,
        name: String,
    ) -> Result<Option<RolloutObject>> {
        names(Some(&namespace), Some(&name))?;
        let access = Access {
            name: Some(name.clone()),
            ..Access::new("get", "robotdeployments", &namespace)
        };
        let (state, _) = allowed(ctx, access).await?;
        crate::api::ready(&state.fleet.rollouts).map_err(refusal)?;
        Ok(state
            .fleet
            .rollouts
            .get(&namespace, &name)
            .map(RolloutObject))
    }
}

/// The rollout actions: `patch robotdeployments` in the namespace, writing what
/// `kubectl lekiwi rollout pause|resume|abort|undo|restart` writes.
pub struct MutationRoot;

#[Object]
impl MutationRoot {
    /// Sets `spec.paused`.
    async fn pause_rollout(
        &self,
        ctx: &Context<'_>,
        namespace: String,
        name: String,
    ) -> Result<RolloutObject> {
        act(ctx, namespace, name, json!({"spec": {"paused": true}})).await
    }
    /// Clears `spec.paused`.
    async fn resume_rollout(
        &self,
        ctx: &Context<'_>,
        namespace: String,
        name: String,
    ) -> Result<RolloutObject> {
        act(ctx, namespace, name, json!({"spec": {"paused": false}})).await
    }
    /// Stamps the abort annotation with now: the rollout stops where it stands, ends Aborted.
    async fn abort_rollout(
        &self,
        ctx: &Context<'_>,
        namespace: String,
        name: String,
    ) -> Result<RolloutObject> {
        act(ctx, namespace, name, rollouts::stamp(ABORT_ANNOTATION)).await
    }
    /// Stamps the undo annotation with now.
    async fn undo_rollout(
        &self,
        ctx: &Context<'_>,
        namespace: String,
        name: String,
    ) -> Result<RolloutObject> {
        act(ctx, namespace, name, rollouts::stamp(UNDO_ANNOTATION)).await
    }
    /// Stamps the restart annotation with now.
    async fn restart_rollout(
        &self,
        ctx: &Context<'_>,
        namespace: String,
        name: String,
    ) -> Result<RolloutObject> {
        act(ctx, namespace, name, rollouts::stamp(RESTART_ANNOTATION)).await
    }
}

async fn act(
    ctx: &Context<'_>,
    namespace: String,
    name: String,
    patch: Value,
) -> Result<RolloutObject> {
    names(Some(&namespace), Some(&name))?;
    let access = Access {
        name: Some(name.clone()),
        ..Access::new("patch", "robotdeployments", &namespace)
    };
    let (state, caller) = allowed(ctx, access).await?;
    let patched = rollouts::patch_rollout(state, &caller.user, &namespace, &name, &patch)
        .await
        .map_err(refusal)?;
    Ok(RolloutObject(Arc::new(patched)))
}
