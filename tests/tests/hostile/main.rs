//! Hostile peers: stolen or guessed credentials, stalled and flooding clients, odd protocol input,
//! costly GraphQL, and what each limit does about them.
//!
//! One test binary per group, a module per file: the harness is linked once per group.

mod graphql_slow_subscriber;
mod hostile_amplify;
mod hostile_authz;
mod hostile_blobs;
mod hostile_graphql;
mod hostile_identity;
mod hostile_plaintext;
mod hostile_protocol;
mod hostile_slowloris;
mod hostile_status;
mod hostile_store;
mod hostile_stuck;
