//! The Fleet API: what people and their tools read and do over HTTP, beside the robots'
//! gateway. REST and GraphQL over the fleet's Robots and RobotDeployments ([`api`], answered
//! from the shared cache of `lekiwi_core`), each robot's stored events ([`events`]), the
//! releases pushed to the blob store and their care ([`releases`]), the web dashboard
//! ([`dashboard`]), and the Kubernetes authentication and authorization every request passes
//! ([`kube_auth`], [`users`]). The operator's gateway merges these routes into its own and hands
//! them a [`FleetState`].

pub mod api;
pub mod config;
pub mod dashboard;
pub mod events;
pub mod kube_auth;
pub mod releases;
pub mod users;

pub use lekiwi_core::http::{ApiError, bearer};

use std::sync::Arc;

use jiff::Timestamp;
use lekiwi_core::RobotKey;
use lekiwi_event_store::Store;
use lekiwi_metrics::GatewayMetrics;

use self::api::FleetApi;
use self::kube_auth::KubeAuth;
use self::releases::Releases;

/// When the robots this gateway holds last sent a heartbeat: the live `lastSeen` the API
/// answers beside a Robot's stored status (the gateway's presence implements it).
pub trait Heartbeats: Send + Sync {
    /// When each of `keys` last sent a heartbeat in a session held here, in the same order;
    /// `None` for a robot not held here.
    fn last_heartbeats(&self, keys: &[RobotKey]) -> Vec<Option<Timestamp>>;
}

/// What the Fleet API's handlers share (axum's router state; the gateway's own state hands it
/// out by `FromRef`). Cheap to clone.
#[derive(Clone)]
pub struct FleetState {
    /// The caches of Robots and RobotDeployments, the per-user budgets, GraphQL.
    pub fleet: Arc<FleetApi>,
    /// Checks people's and tools' bearer tokens and permissions with the API server.
    pub kube_auth: Arc<KubeAuth>,
    /// The releases of the blob store, who uses them, and their garbage collection.
    pub releases: Arc<Releases>,
    /// The event store: robots' events and telemetry.
    pub store: Store,
    /// The live heartbeats of the robots this gateway holds.
    pub presence: Arc<dyn Heartbeats>,
    /// Counts refused requests.
    pub metrics: GatewayMetrics,
}
