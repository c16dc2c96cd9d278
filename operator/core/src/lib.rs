//! What every part of the operator shares: a robot's identity ([`RobotKey`]), the token bucket
//! that paces frames and writes ([`rate`]), and the typed server-side apply patches every
//! writer of a Robot or RobotDeployment sends ([`apply`]), and how long a request to the API
//! server may wait ([`api_client`]).

pub mod api_client;
pub mod apply;
pub mod rate;
mod robot;

pub use robot::RobotKey;
