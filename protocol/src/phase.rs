//! `progress.phase`: the steps of a deploy command, their wire names and which ones end it.

use serde::{Deserialize, Serialize};

/// Phase of a command in `progress.phase` (§12). The agent sends these; the gateway and the
/// rollout planner match on them instead of on strings.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProgressPhase {
    /// Fetching the manifest and missing blobs.
    Downloading,
    /// Checking the blobs already held.
    Verifying,
    /// Building `releases/<version>/`.
    Assembling,
    /// Running the pre-switch command.
    PreSwitch,
    /// Pointing `current` at a release.
    Switching,
    /// Running the restart command.
    Restarting,
    /// Waiting for the health command to pass.
    HealthCheck,
    /// Finished: the release runs.
    Done,
    /// Finished: nothing was switched (or the switch was interrupted before it happened).
    Failed,
    /// Finished: the release was switched to, failed, and the previous one runs again.
    RolledBack,
    /// Finished: a `cancel` stopped it before the switch; the release that ran before still
    /// runs, untouched, and the blobs downloaded so far are kept for a later resume.
    Cancelled,
}

impl ProgressPhase {
    /// The wire name.
    pub fn as_str(self) -> &'static str {
        match self {
            ProgressPhase::Downloading => "downloading",
            ProgressPhase::Verifying => "verifying",
            ProgressPhase::Assembling => "assembling",
            ProgressPhase::PreSwitch => "pre_switch",
            ProgressPhase::Switching => "switching",
            ProgressPhase::Restarting => "restarting",
            ProgressPhase::HealthCheck => "health_check",
            ProgressPhase::Done => "done",
            ProgressPhase::Failed => "failed",
            ProgressPhase::RolledBack => "rolled_back",
            ProgressPhase::Cancelled => "cancelled",
        }
    }
}

impl std::fmt::Display for ProgressPhase {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl ProgressPhase {
    /// Every phase, in the order a deploy goes through them.
    pub const ALL: [ProgressPhase; 11] = [
        ProgressPhase::Downloading,
        ProgressPhase::Verifying,
        ProgressPhase::Assembling,
        ProgressPhase::PreSwitch,
        ProgressPhase::Switching,
        ProgressPhase::Restarting,
        ProgressPhase::HealthCheck,
        ProgressPhase::Done,
        ProgressPhase::Failed,
        ProgressPhase::RolledBack,
        ProgressPhase::Cancelled,
    ];

    /// The phase a wire name stands for; `None` for a name this version does not know.
    pub fn parse(name: &str) -> Option<ProgressPhase> {
        Self::ALL.into_iter().find(|p| p.as_str() == name)
    }

    /// Whether the command is over (`done`, `failed`, `rolled_back` or `cancelled`).
    pub fn is_final(self) -> bool {
        matches!(
            self,
            ProgressPhase::Done
                | ProgressPhase::Failed
                | ProgressPhase::RolledBack
                | ProgressPhase::Cancelled
        )
    }

    /// Whether the command ended without its release running (`failed` or `rolled_back`).
    pub fn is_failure(self) -> bool {
        matches!(self, ProgressPhase::Failed | ProgressPhase::RolledBack)
    }
}

#[cfg(test)]
mod tests {
    use super::ProgressPhase;

    #[test]
    fn wire_names_round_trip_and_the_spec_lists_them_all() {
        let spec = include_str!("../PROTOCOL.md");
        let row = spec
            .lines()
            .find(|l| l.starts_with("| `phase`"))
            .expect("the progress table's phase row");
        for phase in ProgressPhase::ALL {
            let json = serde_json::to_string(&phase).unwrap();
            assert_eq!(json, format!("\"{phase}\""));
            assert_eq!(ProgressPhase::parse(phase.as_str()), Some(phase));
            assert!(
                row.contains(&format!("`{phase}`")),
                "{phase} missing in {row}"
            );
        }
    }
}
