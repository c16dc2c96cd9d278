//! The gateway and the controllers around it: sessions, replicas, the event store on both
//! backends, recovery after a replica or the API server dies, leader election, storms, certificate
//! rotation, OpenTelemetry and the Robot controller.
//!
//! One test binary per group, a module per file: the harness is linked once per group.

mod api_server_restart;
mod event_store;
mod gateway;
mod gateway_replicas;
mod leader_election;
mod otel;
mod recovery;
mod replica_lag;
mod robot_controller;
mod slow_list;
mod storm;
mod tls_rotation;
