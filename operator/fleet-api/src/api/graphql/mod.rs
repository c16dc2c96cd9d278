//! GraphQL at `/api/v1/graphql` over the same caches, event store and checks as the REST routes:
//! `POST` answers queries and mutations (the bearer token in `Authorization`); `GET` upgrades to
//! a WebSocket speaking `graphql-transport-ws` for subscriptions, authenticated by the
//! `connection_init` payload `{"authorization": "Bearer <token>"}` (browsers cannot set headers
//! on WebSockets). Every request, and every WebSocket, costs its user one request of the
//! per-user budget; each field checks the caller's RBAC (a cached `SubjectAccessReview`) for its
//! namespace and verb. A request is at most `--graphql-max-body-bytes` long; it is parsed and
//! validated off the async runtime, and queries deeper or more complex than configured are
//! refused before they run ([`guard`]); introspection is open to authenticated callers only
//! (there is no unauthenticated request). Subscriptions ([`subscribe`]) share the caches'
//! broadcasts.

mod guard;
mod http;
mod query;
mod scalar;
mod subscribe;

pub use self::http::{GRAPHQL_RESPONSE, post};

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use async_graphql::{Data, ErrorExtensions, Schema};
use async_graphql_axum::{GraphQLProtocol, GraphQLWebSocket};
use axum::extract::State;
use axum::extract::ws::rejection::WebSocketUpgradeRejection;
use axum::extract::ws::{CloseFrame, Message, WebSocketUpgrade};
use axum::http::{HeaderMap, StatusCode};
use axum::response::Response;
use futures::{SinkExt, StreamExt};
use tokio::sync::Semaphore;

use self::query::{MutationRoot, QueryRoot};
use self::subscribe::SubscriptionRoot;
use super::authorize;
use crate::config::GraphQlConfig;
use crate::kube_auth::Access;
use crate::{ApiError, FleetState};

/// The schema and what bounds its requests and WebSockets.
pub struct GraphQl {
    schema: Schema<QueryRoot, MutationRoot, SubscriptionRoot>,
    guard: Arc<guard::Guard>,
    connections: Arc<Semaphore>,
    subscriptions: Arc<subscribe::PerUser>,
    sockets: Arc<subscribe::PerUser>,
    init_timeout: Duration,
    max_body_bytes: usize,
}

impl GraphQl {
    /// The schema with `config`'s limits.
    pub fn new(config: &GraphQlConfig) -> Self {
        // The depth limit is the guard's (introspection's `ofType` does not count).
        let guard = Arc::new(guard::Guard::new(
            config.graphql_max_depth,
            config.graphql_max_complexity,
        ));
        let schema = Schema::build(QueryRoot, MutationRoot, SubscriptionRoot)
            .limit_complexity(config.graphql_max_complexity)
            .extension(guard::Guarded(guard.clone()))
            .finish();
        Self {
            schema,
            guard,
            connections: Arc::new(Semaphore::new(config.graphql_max_connections)),
            subscriptions: Arc::new(subscribe::PerUser {
                what: "subscriptions",
                max: config.graphql_max_subscriptions_per_user,
                held: Mutex::new(HashMap::new()),
            }),
            sockets: Arc::new(subscribe::PerUser {
                what: "GraphQL WebSockets",
                max: config.graphql_max_connections_per_user,
                held: Mutex::new(HashMap::new()),
            }),
            init_timeout: Duration::from_secs(config.graphql_init_timeout_seconds.max(1)),
            max_body_bytes: config.graphql_max_body_bytes.max(1),
        }
    }

    /// The schema in GraphQL SDL, for people and code generators.
    pub fn sdl(&self) -> String {
        self.schema.sdl()
    }
}

/// Who is asking: the token (for the per-field access checks) and its username.
#[derive(Clone)]
pub(crate) struct Caller {
    token: String,
    user: String,
}

/// `GET /api/v1/graphql`: the `graphql-transport-ws` WebSocket (400 for a request that is no
/// WebSocket upgrade or offers another subprotocol, 503 at the connection limit). The token
/// comes in `connection_init`; a refused one closes the socket with code 1002 and the reason
/// (`unauthorized: ...`, `forbidden: ...`, `rate_limited: ...`). A message longer than
/// `--graphql-max-body-bytes` ends the connection.
pub async fn websocket(
    State(state): State<FleetState>,
    headers: HeaderMap,
    protocol: Result<GraphQLProtocol, StatusCode>,
    upgrade: Result<WebSocketUpgrade, WebSocketUpgradeRejection>,
) -> Result<Response, ApiError> {
    let Ok(upgrade) = upgrade else {
        return Err(ApiError::BadRequest(
            "GET /api/v1/graphql is the subscriptions' WebSocket (subprotocol \
             graphql-transport-ws); POST queries and mutations"
                .into(),
        ));
    };
    let protocol = match protocol {
        Ok(p) if transport_ws(&headers) => p,
        _ => {
            return Err(ApiError::BadRequest(
                "the only WebSocket subprotocol is graphql-transport-ws".into(),
            ));
        }
    };
    let gql = state.fleet.graphql.clone();
    let permit = gql.connections.clone().try_acquire_owned().map_err(|_| {
        ApiError::Unavailable("the gateway is at its GraphQL connection limit; retry later")
    })?;
    let schema = gql.schema.clone();
    let init_timeout = gql.init_timeout;
    let max_message = gql.max_body_bytes;
    // The user's WebSocket slot, taken at `connection_init`, given back when the socket ends.
    let slot = Arc::new(Mutex::new(None));
    let held = slot.clone();
    let mut data = Data::default();
    data.insert(state.clone());
    Ok(upgrade
        .protocols(["graphql-transport-ws"])
        .max_message_size(max_message)
        .max_frame_size(max_message)
        .on_upgrade(move |socket| async move {
            let (mut sink, stream) = socket.split();
            let initialised = Arc::new(AtomicBool::new(false));
            let seen = initialised.clone();
            let served = GraphQLWebSocket::new_with_pair(&mut sink, stream, schema, protocol)
                .with_data(data)
                .on_connection_init(move |payload| {
                    seen.store(true, Ordering::Relaxed);
                    connection_init(state, payload, held)
                })
                .serve();
            let timed_out = tokio::select! {
                () = served => false,
                () = init_deadline(init_timeout, &initialised) => true,
            };
            if timed_out {
                let close = CloseFrame {
                    code: 4408,
                    reason: "Connection initialisation timeout".into(),
                };
                let _ = tokio::time::timeout(init_timeout, sink.send(Message::Close(Some(close))))
                    .await;
            }
            drop(slot.lock().unwrap_or_else(|p| p.into_inner()).take());
            drop(permit);
        }))
}

/// Resolves `timeout` after it starts unless `initialised` is set by then; otherwise never.
async fn init_deadline(timeout: Duration, initialised: &AtomicBool) {
    tokio::time::sleep(timeout).await;
    if initialised.load(Ordering::Relaxed) {
        std::future::pending::<()>().await;
    }
}

/// Whether the first GraphQL subprotocol the client offers is `graphql-transport-ws` (the one
/// the extractor then picks), not the older `graphql-ws`.
fn transport_ws(headers: &HeaderMap) -> bool {
    headers
        .get(axum::http::header::SEC_WEBSOCKET_PROTOCOL)
        .and_then(|v| v.to_str().ok())
        .and_then(|offered| {
            offered
                .split(',')
                .map(str::trim)
                .find(|p| async_graphql::http::ALL_WEBSOCKET_PROTOCOLS.contains(p))
        })
        == Some("graphql-transport-ws")
}

/// Accepts a WebSocket whose `connection_init` payload carries an accepted token of a user
/// below their WebSocket cap; the user's slot goes into `held`.
async fn connection_init(
    state: FleetState,
    payload: serde_json::Value,
    held: Arc<Mutex<Option<subscribe::Slot>>>,
) -> async_graphql::Result<Data> {
    let token = payload["authorization"]
        .as_str()
        .and_then(|a| a.strip_prefix("Bearer "))
        .map(str::trim)
        .unwrap_or_default()
        .to_owned();
    let mut headers = HeaderMap::new();
    if let Ok(value) = format!("Bearer {token}").parse() {
        headers.insert(axum::http::header::AUTHORIZATION, value);
    }
    let user = authorize(&state, &headers, None).await.map_err(refusal)?;
    let slot = state.fleet.graphql.sockets.hold(&user)?;
    *held.lock().unwrap_or_else(|p| p.into_inner()) = Some(slot);
    let mut data = Data::default();
    data.insert(Caller { token, user });
    Ok(data)
}

/// A refusal as a GraphQL error: the message says why, `extensions.code` is the REST error code
/// (`unauthorized`, `forbidden`, `bad_request`, `not_found`, `rate_limited`, `unavailable`,
/// `internal`).
pub(crate) fn refusal(e: ApiError) -> async_graphql::Error {
    let (code, message) = match e {
        ApiError::Unauthorized(m) => ("unauthorized", m.to_owned()),
        ApiError::Forbidden(m) => ("forbidden", m),
        ApiError::BadRequest(m) => ("bad_request", m),
        ApiError::NotFound(m) => ("not_found", m),
        ApiError::TooLarge(m) => ("too_large", m),
        ApiError::Unavailable(m) | ApiError::Throttled(m) => ("unavailable", m.to_owned()),
        ApiError::RateLimited(s)
        | ApiError::TooManySessions(s)
        | ApiError::EnrollmentsThrottled(s) => (
            "rate_limited",
            format!("too many requests from this user; retry in {s} s"),
        ),
        ApiError::Internal(detail) => {
            tracing::warn!(%detail, "internal error answering a GraphQL request");
            ("internal", "internal error".to_owned())
        }
    };
    async_graphql::Error::new(format!("{code}: {message}")).extend_with(|_, e| e.set("code", code))
}

/// The caller and the gateway's state, once RBAC allows the caller `access`.
pub(crate) async fn allowed<'a>(
    ctx: &async_graphql::Context<'a>,
    access: Access,
) -> async_graphql::Result<(&'a FleetState, &'a Caller)> {
    let state = ctx.data::<FleetState>()?;
    let caller = ctx.data::<Caller>()?;
    state
        .kube_auth
        .check(&caller.token, &access)
        .await
        .map_err(|d| refusal(state.denied(d)))?;
    Ok((state, caller))
}

#[cfg(test)]
mod tests {
    use std::time::Instant;

    use super::*;

    /// The query GraphiQL, Apollo and code generators send first.
    const INTROSPECTION: &str = include_str!(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../tests/fixtures/introspection.graphql"
    ));

    fn defaults() -> GraphQlConfig {
        #[derive(clap::Parser)]
        struct Flags {
            #[command(flatten)]
            graphql: GraphQlConfig,
        }
        <Flags as clap::Parser>::parse_from(["lekiwi-operator"]).graphql
    }

    /// The messages of the errors `query` is answered with (no caller: fields that run fail).
    async fn errors(config: &GraphQlConfig, query: &str) -> Vec<String> {
        let response = GraphQl::new(config).schema.execute(query).await;
        response.errors.into_iter().map(|e| e.message).collect()
    }

    #[tokio::test]
    async fn the_standard_introspection_query_passes_the_default_limits() {
        let response = GraphQl::new(&defaults())
            .schema
            .execute(INTROSPECTION)
            .await;
        assert!(response.errors.is_empty(), "{:?}", response.errors);
        let data = response.data.into_json().unwrap();
        let types = data["__schema"]["types"].as_array().unwrap();
        assert!(types.iter().any(|t| t["name"] == "Robot"), "{data}");
    }

    #[test]
    fn sixty_four_bit_fields_are_big_ints() {
        let sdl = GraphQl::new(&defaults()).sdl();
        for field in ["seq: BigInt!", "tsMs: BigInt!", "scalar BigInt"] {
            assert!(sdl.contains(field), "{field} missing from {sdl}");
        }
        assert!(
            !sdl.contains("tsMs: Int") && !sdl.contains("seq: Int"),
            "{sdl}"
        );
    }

    #[tokio::test]
    async fn deeper_queries_are_still_refused() {
        let too_deep = ["Query is nested too deep.".to_owned()];
        // Introspection that fans out (types, their fields' types' fields, ...): 11 deep.
        let fanned = "{ __schema { types { fields { type { fields { type { fields { type { \
                      fields { type { name } } } } } } } } } } }";
        assert_eq!(errors(&defaults(), fanned).await, too_deep);
        let config = GraphQlConfig {
            graphql_max_depth: 4,
            ..defaults()
        };
        let deep = "{ robots(limit: 1) { items { events(limit: 1) { items { seq } } } } }";
        assert_eq!(errors(&config, deep).await, too_deep);
    }

    #[tokio::test]
    async fn a_paged_field_costs_one_plus_its_limit_times_its_selection() {
        // The README's example: 1 + 50 × (items 1 + name 1 + phase 1, continue 1) = 201.
        let query = "{ robots(limit: 50) { items { name phase } continue } }";
        for (max, refused) in [(201, false), (200, true)] {
            let config = GraphQlConfig {
                graphql_max_complexity: max,
                ..defaults()
            };
            let errors = errors(&config, query).await;
            let too_complex = errors.iter().any(|e| e == "Query is too complex.");
            assert_eq!(too_complex, refused, "at most {max}: {errors:?}");
        }
    }

    #[tokio::test]
    async fn a_fragment_bomb_is_refused_before_it_is_walked() {
        // 1.3 KB whose fragments expand to 2^26 fields.
        let mut bomb = String::from("{ ...F26 } fragment F0 on QueryRoot { __typename }");
        for i in 1..=26 {
            let p = i - 1;
            bomb.push_str(&format!(
                " fragment F{i} on QueryRoot {{ ...F{p} ...F{p} }}"
            ));
        }
        let started = Instant::now();
        assert_eq!(
            errors(&defaults(), &bomb).await,
            ["Query is too complex.".to_owned()]
        );
        assert!(
            started.elapsed() < Duration::from_secs(5),
            "{:?}",
            started.elapsed()
        );
    }
}
