//! The LeKiwi robot agent: configuration, joining a fleet, the gateway connection (shared with the fleet
//! simulator), the durable outbox, telemetry, teleoperation detection, health checks, discovery
//! and the run loop.

pub mod backoff;
pub mod config;
pub mod connection;
pub mod discovery;
pub mod fleet;
pub mod health;
pub mod join;
pub mod outbox;
pub mod release;
pub mod run;
pub mod selfupdate;
pub mod sim;
pub mod state;
pub mod telemetry;
pub mod teleop;
