//! What people use: the CRDs on a real API server, the Fleet API (REST and GraphQL), the web
//! dashboard, the Grafana dashboards, `kubectl lekiwi` and the book's tour.
//!
//! One test binary per group, a module per file: the harness is linked once per group.

mod cli;
mod dashboard;
mod dashboards;
mod fleet_api;
mod fleet_graphql;
mod resources;
mod tour;
