//! The Fleet API's OpenAPI 3 document, served at [`paths::OPENAPI`]. The router is built from
//! the same [`paths`] constants, and a test checks that every route is documented (and the
//! integration test that every documented route answers).

use std::sync::LazyLock;

use axum::Json;
use axum::extract::State;
use axum::http::HeaderMap;
use serde_json::{Value, json};

use super::{DEFAULT_LIMIT, MAX_LIMIT, authorize};
use crate::{ApiError, FleetState};

/// Every route of the Fleet API, as axum spells it (`{param}`, as OpenAPI does too).
pub mod paths {
    /// This document.
    pub const OPENAPI: &str = "/api/v1/openapi.json";
    /// What the caller may do in a namespace.
    pub const ACCESS: &str = "/api/v1/namespaces/{namespace}/access";
    /// Robots of every namespace.
    pub const ROBOTS: &str = "/api/v1/robots";
    /// The robots of one namespace, counted.
    pub const SUMMARY: &str = "/api/v1/namespaces/{namespace}/summary";
    /// Robots of one namespace.
    pub const NAMESPACED_ROBOTS: &str = "/api/v1/namespaces/{namespace}/robots";
    /// One robot.
    pub const ROBOT: &str = "/api/v1/namespaces/{namespace}/robots/{name}";
    /// A robot's stored events.
    pub const ROBOT_EVENTS: &str = "/api/v1/namespaces/{namespace}/robots/{name}/events";
    /// A robot's stored telemetry.
    pub const ROBOT_TELEMETRY: &str = "/api/v1/namespaces/{namespace}/robots/{name}/telemetry";
    /// RobotDeployments of every namespace.
    pub const ROLLOUTS: &str = "/api/v1/rollouts";
    /// RobotDeployments of one namespace.
    pub const NAMESPACED_ROLLOUTS: &str = "/api/v1/namespaces/{namespace}/rollouts";
    /// One RobotDeployment.
    pub const ROLLOUT: &str = "/api/v1/namespaces/{namespace}/rollouts/{name}";
    /// Pause a rollout.
    pub const ROLLOUT_PAUSE: &str = "/api/v1/namespaces/{namespace}/rollouts/{name}/pause";
    /// Resume a rollout.
    pub const ROLLOUT_RESUME: &str = "/api/v1/namespaces/{namespace}/rollouts/{name}/resume";
    /// Abort a rollout.
    pub const ROLLOUT_ABORT: &str = "/api/v1/namespaces/{namespace}/rollouts/{name}/abort";
    /// Undo a rollout.
    pub const ROLLOUT_UNDO: &str = "/api/v1/namespaces/{namespace}/rollouts/{name}/undo";
    /// Restart a rollout.
    pub const ROLLOUT_RESTART: &str = "/api/v1/namespaces/{namespace}/rollouts/{name}/restart";
    /// The releases pushed to one namespace.
    pub const RELEASES: &str = "/api/v1/namespaces/{namespace}/releases";
    /// One release, by digest or version.
    pub const RELEASE: &str = "/api/v1/namespaces/{namespace}/releases/{release}";
    /// GraphQL: `POST` for queries and mutations, `GET` for the subscriptions' WebSocket.
    pub const GRAPHQL: &str = "/api/v1/graphql";
}

/// Every route with its method, the list the router and the document are checked against.
pub const ROUTES: [(&str, &str); 20] = [
    ("get", paths::OPENAPI),
    ("get", paths::ACCESS),
    ("get", paths::ROBOTS),
    ("get", paths::SUMMARY),
    ("get", paths::NAMESPACED_ROBOTS),
    ("get", paths::ROBOT),
    ("get", paths::ROBOT_EVENTS),
    ("get", paths::ROBOT_TELEMETRY),
    ("get", paths::ROLLOUTS),
    ("get", paths::NAMESPACED_ROLLOUTS),
    ("get", paths::ROLLOUT),
    ("post", paths::ROLLOUT_PAUSE),
    ("post", paths::ROLLOUT_RESUME),
    ("post", paths::ROLLOUT_ABORT),
    ("post", paths::ROLLOUT_UNDO),
    ("post", paths::ROLLOUT_RESTART),
    ("get", paths::RELEASES),
    ("delete", paths::RELEASE),
    ("post", paths::GRAPHQL),
    ("get", paths::GRAPHQL),
];

/// `GET /api/v1/openapi.json`: the document, to any authenticated user.
pub async fn document(
    State(state): State<FleetState>,
    headers: HeaderMap,
) -> Result<Json<Value>, ApiError> {
    authorize(&state, &headers, None).await?;
    Ok(Json(DOCUMENT.clone()))
}

/// The document, built once.
pub static DOCUMENT: LazyLock<Value> = LazyLock::new(build);

fn param(name: &str, place: &str, description: &str, schema: Value) -> Value {
    json!({"name": name, "in": place, "required": place == "path",
           "description": description, "schema": schema})
}

fn path_params(named: bool) -> Vec<Value> {
    let mut params = vec![param(
        "namespace",
        "path",
        "Namespace.",
        json!({"type": "string"}),
    )];
    if named {
        params.push(param(
            "name",
            "path",
            "Object name.",
            json!({"type": "string"}),
        ));
    }
    params
}

fn page_params() -> Vec<Value> {
    vec![
        param(
            "limit",
            "query",
            &format!("Items per page, 1 to {MAX_LIMIT} (default {DEFAULT_LIMIT})."),
            json!({"type": "integer", "minimum": 1, "maximum": MAX_LIMIT}),
        ),
        param(
            "continue",
            "query",
            "The `continue` token of the previous page (same filters); empty or absent: the first page.",
            json!({"type": "string"}),
        ),
    ]
}

fn robot_filters() -> Vec<Value> {
    vec![
        param(
            "labelSelector",
            "query",
            "Label selector as `kubectl get -l` takes it.",
            json!({"type": "string"}),
        ),
        param(
            "phase",
            "query",
            "Only robots in this phase.",
            json!({"enum": ["Pending", "Online", "Offline", "Unknown", "Maintenance"]}),
        ),
        param(
            "release",
            "query",
            "Only robots reporting they run this release version (`status.currentRelease.version`).",
            json!({"type": "string"}),
        ),
    ]
}

fn history_params(metric: bool) -> Vec<Value> {
    let mut params = vec![
        param(
            "since",
            "query",
            "Start of the range, RFC 3339, included (default: one hour before `until`, or before now). Events are selected by when the gateway received them, samples by their `ts_ms`.",
            json!({"type": "string", "format": "date-time"}),
        ),
        param(
            "until",
            "query",
            "End of the range, RFC 3339, excluded (default: no end).",
            json!({"type": "string", "format": "date-time"}),
        ),
    ];
    if metric {
        params.push(param(
            "metric",
            "query",
            "Only samples of this metric, e.g. `cpu_percent`.",
            json!({"type": "string"}),
        ));
    }
    params
}

/// One operation: summary, the RBAC permission it needs, parameters, the 200 schema.
fn op(summary: &str, rbac: &str, params: Vec<Value>, ok: Value) -> Value {
    let error = |d: &str| json!({"description": d, "content": {"application/json": {"schema": {"$ref": "#/components/schemas/Error"}}}});
    json!({
        "summary": summary,
        "description": format!("Needs {rbac}."),
        "x-kubernetes-rbac": rbac,
        "parameters": params,
        "responses": {
            "200": {"description": "OK", "content": {"application/json": {"schema": ok}}},
            "400": error("A malformed parameter; the message says which."),
            "401": error("No bearer token, or one the API server does not accept."),
            "403": error("RBAC does not allow the user this; the message names the permission."),
            "404": error("No such object."),
            "429": error("The user's request budget is spent; retry after `Retry-After` seconds."),
            "503": error("The gateway is starting, or cannot review tokens now; retry after `Retry-After`."),
        }
    })
}

fn page_of(schema: &str) -> Value {
    json!({"type": "object", "required": ["items"], "properties": {
        "items": {"type": "array", "items": {"$ref": format!("#/components/schemas/{schema}")}},
        "continue": {"type": "string", "description": "Present when more items follow: pass it as `continue`."}}})
}

fn schema(name: &str) -> Value {
    json!({"$ref": format!("#/components/schemas/{name}")})
}

/// `lastSeen` of a robot, in lists and the robot view.
fn last_seen() -> Value {
    json!({"type": "string", "format": "date-time",
        "description": "When the robot was last heard from: its latest heartbeat as the gateway that answers knows it, when that gateway holds the robot's session; else status.lastHeartbeatTime (written at least every --status-refresh-seconds). Absent when neither is known."})
}

fn build() -> Value {
    let named = |mut extra: Vec<Value>| {
        let mut p = path_params(true);
        p.append(&mut extra);
        p
    };
    let listed = |ns: bool, mut extra: Vec<Value>| {
        let mut p = if ns { path_params(false) } else { Vec::new() };
        p.append(&mut extra);
        p.extend(page_params());
        p
    };
    let action = |what: &str| json!({"post": op(what, "patch robotdeployments", named(vec![]), schema("RobotDeployment"))});
    let doc = json!({
        "openapi": "3.0.3",
        "info": {"title": "LeKiwi Fleet API", "version": "v1",
                 "description": "Robots, their history and rollouts, authorized by Kubernetes RBAC (group fleet.lekiwi.io)."},
        "security": [{"bearer": []}],
        "paths": {
            paths::OPENAPI: {"get": op("This document.", "an authenticated user", vec![], json!({"type": "object"}))},
            paths::ACCESS: {"get": op("Who the caller is and which actions RBAC allows them in the namespace (each the check its route makes).",
                "an authenticated user", path_params(false), schema("Access"))},
            paths::ROBOTS: {"get": op("Robots of every namespace.", "list robots in all namespaces",
                listed(false, robot_filters()), page_of("RobotItem"))},
            paths::SUMMARY: {"get": op("The robots of a namespace counted by phase and release (the 20 most common; the rest under `(other)`, none reported under `(none)`), teleoperated and unhealthy; the same filters as the list but phase.",
                "list robots", {
                    let mut p = path_params(false);
                    p.extend(robot_filters().into_iter().filter(|f| f["name"] != "phase"));
                    p
                }, schema("Summary"))},
            paths::NAMESPACED_ROBOTS: {"get": op("Robots of a namespace.", "list robots",
                listed(true, robot_filters()), page_of("RobotItem"))},
            paths::ROBOT: {"get": op("One robot and its latest vitals.", "get robots", named(vec![]), schema("RobotView"))},
            paths::ROBOT_EVENTS: {"get": op("A robot's stored events, ascending seq (404 for a robot the gateway does not hold).", "get robots/events",
                named([history_params(false), page_params()].concat()), page_of("StoredEvent"))},
            paths::ROBOT_TELEMETRY: {"get": op("A robot's stored telemetry samples, oldest first (404 for a robot the gateway does not hold).", "get robots/telemetry",
                named([history_params(true), page_params()].concat()), page_of("StoredSample"))},
            paths::ROLLOUTS: {"get": op("RobotDeployments of every namespace.", "list robotdeployments in all namespaces",
                listed(false, vec![]), page_of("RobotDeployment"))},
            paths::NAMESPACED_ROLLOUTS: {"get": op("RobotDeployments of a namespace.", "list robotdeployments",
                listed(true, vec![]), page_of("RobotDeployment"))},
            paths::ROLLOUT: {"get": op("One RobotDeployment; status.robots is its per-robot progress.", "get robotdeployments",
                named(vec![]), schema("RobotDeployment"))},
            paths::ROLLOUT_PAUSE: action("Pause: sets spec.paused to true."),
            paths::ROLLOUT_RESUME: action("Resume: sets spec.paused to false."),
            paths::ROLLOUT_ABORT: action("Abort: sets annotation fleet.lekiwi.io/abortRequestedAt to now (the rollout stops where it stands and ends Aborted)."),
            paths::ROLLOUT_UNDO: action("Undo: sets annotation fleet.lekiwi.io/undoRequestedAt to now."),
            paths::ROLLOUT_RESTART: action("Restart: sets annotation fleet.lekiwi.io/restartedAt to now."),
            paths::RELEASES: {"get": op("The releases pushed to the namespace (kubectl lekiwi release push), newest first, with their size and who uses them; garbage collection removes those nothing uses beyond the newest --release-retention.",
                "list releases", path_params(false), json!({"type": "object", "required": ["items"], "properties": {
                    "items": {"type": "array", "items": schema("Release")}}}))},
            paths::RELEASE: {"delete": release_delete()},
            paths::GRAPHQL: graphql(),
        },
        "components": components(),
    });
    doc
}

/// `DELETE` of one release: 409 while it is in use.
fn release_delete() -> Value {
    let mut params = path_params(false);
    params.push(param(
        "release",
        "path",
        "The release's digest (`sha256:...`), or its version when only one release of the namespace has it.",
        json!({"type": "string"}),
    ));
    let mut delete = op(
        "Delete a release and the blobs no other release lists.",
        "delete releases",
        params,
        json!({"type": "object", "description": "The release deleted (namespace, version, digest, pushed) with the blobs and bytes removed.",
            "properties": {"namespace": {"type": "string"}, "version": {"type": "string"}, "digest": {"type": "string"},
                "pushed": {"type": "string", "format": "date-time"}, "blobs": {"type": "integer"}, "bytes": {"type": "integer"}}}),
    );
    delete["responses"]["409"] = json!({"description": "A Robot or RobotDeployment references the release, or a robot is downloading it now; the message says which.",
        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/Error"}}}});
    delete
}

/// The GraphQL endpoint: a query or mutation by `POST`; subscriptions over a WebSocket.
fn graphql() -> Value {
    let mut post = op(
        "A GraphQL query or mutation over the same data (schema by introspection; README, GraphQL). Each field checks the RBAC permission of the REST route it mirrors; errors come as GraphQL `errors` with `extensions.code` the REST error code.",
        "an authenticated user, and per field the permission of its REST route",
        vec![],
        json!({"type": "object", "properties": {"data": {"type": "object", "nullable": true}, "errors": {"type": "array", "items": {"type": "object"}}}}),
    );
    post["requestBody"] = json!({"required": true,
        "description": "At most --graphql-max-body-bytes (default 65536) bytes; beyond, 413.",
        "content": {"application/json": {"schema": {
        "type": "object", "required": ["query"], "properties": {
            "query": {"type": "string"}, "variables": {"type": "object", "nullable": true},
            "operationName": {"type": "string", "nullable": true}}}}}});
    // The same answer under either media type: `application/graphql-response+json` when the
    // request's Accept names it (GraphQL over HTTP), `application/json` otherwise.
    let ok = post["responses"]["200"]["content"]["application/json"].clone();
    post["responses"]["200"] = json!({
        "description": "GraphQL's answer, errors of fields and of the query included.",
        "content": {"application/json": ok.clone(), (super::graphql::GRAPHQL_RESPONSE): ok}});
    post["responses"]["413"] = json!({"description": "The body is longer than --graphql-max-body-bytes.",
        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/Error"}}}});
    let mut get = op(
        "Subscriptions (robotChanges, rolloutProgress): a WebSocket with subprotocol `graphql-transport-ws`, the token as `{\"authorization\": \"Bearer TOKEN\"}` in the `connection_init` payload (closed with 4408 when none comes in time, 1002 when refused).",
        "an authenticated user, and per subscription the permission of its REST route",
        vec![],
        json!({"type": "object"}),
    );
    let responses = get["responses"].as_object_mut().expect("op has responses");
    responses.remove("200");
    responses.insert(
        "101".into(),
        json!({"description": "Switching to the WebSocket protocol graphql-transport-ws."}),
    );
    responses["400"]["description"] =
        "No WebSocket upgrade, or a subprotocol other than graphql-transport-ws.".into();
    json!({"post": post, "get": get})
}

fn components() -> Value {
    json!({
        "securitySchemes": {"bearer": {"type": "http", "scheme": "bearer",
            "description": "Any token the Kubernetes API server accepts (kubectl create token, a kubeconfig's token, OIDC)."}},
        "schemas": {
            "Error": {"type": "object", "required": ["error", "message"], "properties": {
                "error": {"type": "string", "description": "Stable code: bad_request, unauthorized, forbidden, not_found, conflict, method_not_allowed, too_large, rate_limited, unavailable, internal."},
                "message": {"type": "string"}}},
            "Access": {"type": "object", "required": ["user", "namespace", "allowed"], "properties": {
                "user": {"type": "string", "description": "The username the API server gave the token."},
                "namespace": {"type": "string"},
                "allowed": {"type": "object", "description": "Each action and whether RBAC allows it.", "properties": {
                    "listRobots": {"type": "boolean", "description": "list robots"},
                    "getRobots": {"type": "boolean", "description": "get robots"},
                    "getEvents": {"type": "boolean", "description": "get robots/events"},
                    "getTelemetry": {"type": "boolean", "description": "get robots/telemetry"},
                    "listRollouts": {"type": "boolean", "description": "list robotdeployments"},
                    "patchRollouts": {"type": "boolean", "description": "patch robotdeployments (pause, resume, undo, restart)"}}}}},
            "Summary": {"type": "object", "required": ["total", "phases", "releases", "teleoperated", "unhealthy"], "properties": {
                "total": {"type": "integer"},
                "phases": {"type": "object", "additionalProperties": {"type": "integer"}, "description": "Every phase, 0 included; no phase yet counts as Pending."},
                "releases": {"type": "object", "additionalProperties": {"type": "integer"}, "description": "Robots per status.currentRelease.version."},
                "teleoperated": {"type": "integer"}, "unhealthy": {"type": "integer"}}},
            "Robot": {"type": "object", "description": "The Robot resource (fleet.lekiwi.io/v1alpha1) as `kubectl get -o json` shows it, without managedFields."},
            "RobotItem": {"allOf": [schema("Robot"), {"type": "object", "properties": {"lastSeen": last_seen()}}],
                "description": "A list's robot: the Robot resource plus lastSeen."},
            "RobotDeployment": {"type": "object", "description": "The RobotDeployment resource (fleet.lekiwi.io/v1alpha1) without managedFields."},
            "RobotView": {"type": "object", "required": ["robot"], "properties": {
                "robot": schema("Robot"),
                "vitals": {"type": "object", "nullable": true, "description": "status.telemetry: cpuPercent, memoryPercent, temperatureCelsius, batteryPercent, hostMemoryBytes, hostCpuPercent."},
                "vitalsTime": {"type": "string", "format": "date-time", "nullable": true, "description": "status.lastHeartbeatTime."},
                "lastSeen": last_seen()}},
            "Release": {"type": "object", "required": ["namespace", "version", "digest", "pushed", "robots", "deployments"], "properties": {
                "namespace": {"type": "string"}, "version": {"type": "string"},
                "digest": {"type": "string", "description": "The manifest's digest."},
                "size": {"type": "integer", "nullable": true, "description": "Bytes of its files (absent when the manifest cannot be read)."},
                "files": {"type": "integer", "nullable": true},
                "pushed": {"type": "string", "format": "date-time", "description": "When it was first pushed to the namespace."},
                "robots": {"type": "object", "properties": {
                    "desired": {"type": "integer", "description": "Robots whose spec.release it is."},
                    "current": {"type": "integer", "description": "Robots whose status.currentRelease it is."},
                    "previous": {"type": "integer", "description": "Robots a RobotDeployment would roll back to it (status.robots[].previousRelease)."}}},
                "deployments": {"type": "object", "properties": {
                    "release": {"type": "integer", "description": "RobotDeployments whose spec.release it is."},
                    "rollbackTarget": {"type": "integer", "description": "RobotDeployments that would roll some robot back to it."}}}}},
            "StoredEvent": {"type": "object", "required": ["seq", "ts_ms", "kind", "severity", "message", "data"], "properties": {
                "seq": {"type": "integer"}, "ts_ms": {"type": "integer", "description": "Unix milliseconds."},
                "kind": {"type": "string"}, "severity": {"type": "string"}, "message": {"type": "string"}, "data": {}}},
            "StoredSample": {"type": "object", "required": ["seq", "metric", "ts_ms", "value"], "properties": {
                "seq": {"type": "integer"}, "metric": {"type": "string"},
                "ts_ms": {"type": "integer", "description": "Unix milliseconds."}, "value": {"type": "number"}}},
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_route_is_documented_and_nothing_else() {
        let documented = DOCUMENT["paths"].as_object().unwrap();
        for (method, path) in ROUTES {
            assert!(
                documented[path].get(method).is_some(),
                "{method} {path} undocumented"
            );
        }
        let count: usize = documented
            .values()
            .map(|p| p.as_object().unwrap().len())
            .sum();
        assert_eq!(
            count,
            ROUTES.len(),
            "documented operations that are not routes"
        );
    }
}
