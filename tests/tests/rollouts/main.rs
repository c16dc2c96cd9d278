//! Releases and rollouts end to end: pushing, rolling out, cancelling, analysis, ownership,
//! garbage collection, and the simulator answering commands.
//!
//! One test binary per group, a module per file: the harness is linked once per group.

mod analysis;
mod cancel;
mod ownership;
mod release_gc;
mod releases;
mod rollout;
mod sim_commands;
mod slow_writes;
mod stale_store;
