//! The robot side: the real `lekiwi-agent` (enrollment, join, discovery, teleoperation, health,
//! self-update, agent rollouts, packaging) and robots moving off legacy polling.
//!
//! One test binary per group, a module per file: the harness is linked once per group.

mod agent;
mod agent_discovery;
mod agent_join;
mod agent_rollout;
mod agent_teleop;
mod agent_update;
mod discover_methods;
mod discover_netns;
mod health;
mod legacy_migration;
mod packaging;
