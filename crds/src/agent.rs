//! The agent build a robot should run (`Robot.spec.agent`) and how its latest agent update went
//! (`Robot.status.agentUpdate`).

use k8s_openapi::apimachinery::pkg::apis::meta::v1::MicroTime;
use lekiwi_protocol::rules;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// An agent version and its builds, one per CPU architecture, as pushed by
/// `kubectl lekiwi agent push`.
#[derive(Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq, Eq, Hash)]
#[serde(rename_all = "camelCase")]
pub struct AgentRef {
    /// Version of the agent, exactly as the new `lekiwi-agent` reports it in `hello` (the
    /// robot counts as updated when it does), for example `0.2.0`. Letters, digits, `.`, `_`,
    /// `+` and `-`; 1 to 128 characters.
    #[schemars(
        length(min = 1, max = rules::MAX_VERSION_CHARS),
        regex(pattern = rules::VERSION_PATTERN)
    )]
    pub version: String,

    /// The binaries of this version, at most one per architecture. A robot whose architecture
    /// (from its `hello`) has none keeps its agent; its `status.agentUpdate` says so.
    #[schemars(length(min = 1, max = 8))]
    pub builds: Vec<AgentBuild>,
}

/// One `lekiwi-agent` binary in the gateway's blob store.
#[derive(Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq, Eq, Hash)]
#[serde(rename_all = "camelCase")]
pub struct AgentBuild {
    /// CPU architecture the binary is built for: `amd64` (x86_64) or `arm64` (aarch64, the
    /// Raspberry Pi 5).
    pub arch: AgentArch,
    /// Digest of the binary, as printed by `kubectl lekiwi agent push`: `sha256:` followed by
    /// 64 lowercase hex digits.
    #[schemars(regex(pattern = rules::DIGEST_PATTERN))]
    pub digest: String,
}

/// A CPU architecture agent builds exist for.
#[derive(Clone, Copy, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq, Eq, Hash)]
#[serde(rename_all = "lowercase")]
pub enum AgentArch {
    /// x86_64.
    #[default]
    Amd64,
    /// aarch64 (Raspberry Pi 4 and 5 with a 64-bit OS).
    Arm64,
}

impl AgentArch {
    /// The name written in the spec.
    pub fn as_str(self) -> &'static str {
        match self {
            AgentArch::Amd64 => "amd64",
            AgentArch::Arm64 => "arm64",
        }
    }

    /// The architecture of a `uname -m` (or Rust) machine name, as agents report it in
    /// `hello`; `None` for one without builds.
    pub fn of_machine(machine: &str) -> Option<Self> {
        match machine {
            "x86_64" | "amd64" => Some(AgentArch::Amd64),
            "aarch64" | "arm64" => Some(AgentArch::Arm64),
            _ => None,
        }
    }
}

impl AgentRef {
    /// The digest of the build for `arch`, if there is one.
    pub fn build_for(&self, arch: AgentArch) -> Option<&str> {
        self.builds
            .iter()
            .find(|b| b.arch == arch)
            .map(|b| b.digest.as_str())
    }
}

/// How the robot's latest agent update went, as the gateway saw it. Written by the gateway.
#[derive(Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct AgentUpdateReport {
    /// The agent version of `spec.agent` it is about.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub version: Option<String>,
    /// `Sent` (the gateway sent `update_agent`), `Started` (the agent switched and restarts),
    /// `Succeeded` (the new agent connected and committed), `Failed` (nothing switched),
    /// `FallenBack` (the new agent did not come back; the robot switched back by itself),
    /// `Unavailable` (no build for the robot's architecture) or `Unsupported` (the running
    /// agent cannot update itself: install the new package by hand).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub phase: Option<String>,
    /// Why, in words.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
    /// When the gateway saw it, to the microsecond (a rollout tells the outcome of the update
    /// it started from that of one before it in the same second).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time: Option<MicroTime>,
}
