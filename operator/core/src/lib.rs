//! What every part of the operator shares: a robot's identity ([`RobotKey`]), the in-memory copy
//! of the fleet's Robots and RobotDeployments that the gateway and the Fleet API read
//! ([`cache`]), the token bucket that paces frames and writes ([`rate`]), the typed server-side
//! apply patches every writer of a Robot or RobotDeployment sends ([`apply`]), and how long a
//! request to the API server may wait ([`api_client`]), the watch that starts before its list so a
//! long list cannot expire it ([`watch`]), and the JSON errors every HTTP route answers
//! ([`http`]).

pub mod api_client;
pub mod apply;
pub mod cache;
pub mod http;
pub mod list;
pub mod rate;
mod robot;
pub mod watch;

pub use robot::RobotKey;
