//! The Fleet API's flags, a section of the operator's: each user's request budget and the
//! GraphQL endpoint's limits.

/// The Fleet API's budgets and limits (`lekiwi-operator --help`).
#[derive(Clone, Debug, clap::Args)]
pub struct FleetApiConfig {
    /// Fleet API requests per second one user (the username a TokenReview names) may make,
    /// sustained; faster gets 429 with `Retry-After`.
    #[arg(long, env = "LEKIWI_API_RATE", default_value_t = 20.0)]
    pub api_rate: f64,

    /// Fleet API requests one user may make at once before that rate applies.
    #[arg(long, env = "LEKIWI_API_BURST", default_value_t = 100)]
    pub api_burst: u32,

    /// The GraphQL endpoint's limits.
    #[command(flatten)]
    pub graphql: GraphQlConfig,
}

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
