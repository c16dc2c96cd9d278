//! What every part of the operator shares: a robot's identity ([`RobotKey`]), the token bucket
//! that paces frames and writes ([`rate`]), and the typed server-side apply patches every
//! writer of a Robot or RobotDeployment sends ([`apply`]).

pub mod apply;
pub mod rate;
mod robot;

pub use robot::RobotKey;
