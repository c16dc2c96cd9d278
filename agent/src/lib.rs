//! The LeKiwi robot agent: configuration and the gateway connection (shared with the fleet
//! simulator). Telemetry, the durable outbox and release execution follow.

pub mod config;
pub mod connection;
pub mod sim;
