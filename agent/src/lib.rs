//! The LeKiwi robot agent. This first version loads and reports its configuration; the
//! connection, telemetry, outbox and release execution follow with the gateway.

pub mod config;
