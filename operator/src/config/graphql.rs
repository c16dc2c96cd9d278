//! The Fleet API's GraphQL limits, a section of the operator's flags.

/// The GraphQL endpoint's limits (`lekiwi-operator --help`).
#[derive(Clone, Debug, clap::Args)]
pub struct GraphQlConfig {
    /// Deepest GraphQL selection allowed (fields nested in fields; introspection's `ofType` does
    /// not count); deeper queries are refused before they run.
    #[arg(long, env = "LEKIWI_GRAPHQL_MAX_DEPTH", default_value_t = 10)]
    pub graphql_max_depth: usize,

    /// Largest GraphQL request, in bytes: a `POST` body (beyond, 413 with a JSON error) or a
    /// WebSocket message (beyond, the socket is closed). Parsing a query takes time in
    /// proportion to its length; this bounds what one request can cost.
    #[arg(long, env = "LEKIWI_GRAPHQL_MAX_BODY_BYTES", default_value_t = 65_536)]
    pub graphql_max_body_bytes: usize,

    /// Highest GraphQL query complexity allowed: a field counts 1 plus what is selected in it;
    /// a paged field (robots, rollouts, events, telemetry) 1 plus its `limit` times what is
    /// selected in it (its items' fields and `continue`).
    #[arg(long, env = "LEKIWI_GRAPHQL_MAX_COMPLEXITY", default_value_t = 20_000)]
    pub graphql_max_complexity: usize,

    /// GraphQL WebSocket connections open at once; beyond, 503.
    #[arg(long, env = "LEKIWI_GRAPHQL_MAX_CONNECTIONS", default_value_t = 2_000)]
    pub graphql_max_connections: usize,

    /// GraphQL subscriptions one user may hold at once, over all their connections.
    #[arg(
        long,
        env = "LEKIWI_GRAPHQL_MAX_SUBSCRIPTIONS_PER_USER",
        default_value_t = 100
    )]
    pub graphql_max_subscriptions_per_user: usize,

    /// GraphQL WebSockets one user may hold open at once; beyond, `connection_init` is refused
    /// (close code 1002, reason `forbidden: ...`), so no one user takes every connection.
    #[arg(
        long,
        env = "LEKIWI_GRAPHQL_MAX_CONNECTIONS_PER_USER",
        default_value_t = 20
    )]
    pub graphql_max_connections_per_user: usize,

    /// Seconds a GraphQL WebSocket may stay open without its `connection_init`; then it is
    /// closed with code 4408, as `graphql-transport-ws` prescribes.
    #[arg(
        long,
        env = "LEKIWI_GRAPHQL_INIT_TIMEOUT_SECONDS",
        default_value_t = 10
    )]
    pub graphql_init_timeout_seconds: u64,
}
