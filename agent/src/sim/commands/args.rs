//! The flags of the simulated robots' command handling: the hooks they pretend to run, the
//! share of robots that fail (chosen by name, the same ones every run), and the bound on the
//! fleet's downloads.

use std::hash::{Hash, Hasher};
use std::time::Duration;

/// How the simulated robots carry out `deploy`, `rollback`, `cancel` and `update_agent`
/// (PROTOCOL.md §12).
#[derive(Clone, Debug, clap::Args)]
pub struct CommandArgs {
    /// Blob downloads (manifests, release files, agent builds) in flight at once over the whole
    /// fleet; also the idle connections kept per gateway. The others wait their turn.
    #[arg(long, default_value_t = 64)]
    pub max_downloads: usize,
    /// Seconds the simulated pre-switch command takes, or `off`: no pre-switch command, so no
    /// `pre_switch` phase (as an agent without `releasePreSwitchCommand`).
    #[arg(long, default_value = "0")]
    pub pre_switch_seconds: Hook,
    /// Seconds the simulated restart command takes, or `off` (no `restarting` phase).
    #[arg(long, default_value = "0")]
    pub restart_seconds: Hook,
    /// Seconds a passing health check takes, or `off` (no `health_check` phase, and then no
    /// robot fails one).
    #[arg(long, default_value = "0")]
    pub health_check_seconds: Hook,
    /// Seconds a failing health check goes on before the robot switches back (the agent's
    /// `releaseHealthTimeoutS`).
    #[arg(long, default_value_t = 60.0)]
    pub health_timeout_seconds: f64,
    /// Share (0 to 1) of the robots whose health check fails after a switch: they switch back
    /// to the release before and report `rolled_back`.
    #[arg(long, default_value_t = 0.0)]
    pub fail_health_share: f64,
    /// Share (0 to 1) of the robots whose download stalls and never ends (a link that stopped
    /// moving): the rollout's robot timeout sees them, and a `cancel` stops them.
    #[arg(long, default_value_t = 0.0)]
    pub timeout_share: f64,
    /// Share (0 to 1) of the robots that go offline halfway through a download: the session
    /// drops, the deploy fails, and after `--offline-seconds` the robot connects again and the
    /// gateway's new `deploy` resumes the partial download (`Range`).
    #[arg(long, default_value_t = 0.0)]
    pub offline_mid_download_share: f64,
    /// Seconds a robot of `--offline-mid-download-share` stays offline.
    #[arg(long, default_value_t = 30.0)]
    pub offline_seconds: f64,
    /// Release versions the three shares apply to, comma-separated (default: every release), so
    /// that a first release rolls out cleanly and a later one fails.
    #[arg(long, value_delimiter = ',')]
    pub fault_versions: Vec<String>,
}

/// The duration of a simulated hook command, or none configured (`off`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hook(pub Option<Duration>);

impl std::str::FromStr for Hook {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        if s == "off" {
            return Ok(Hook(None));
        }
        match s.parse::<f64>() {
            Ok(secs) if secs.is_finite() && secs >= 0.0 => {
                Ok(Hook(Some(Duration::from_secs_f64(secs))))
            }
            _ => Err(format!("{s:?} is neither a number of seconds nor `off`")),
        }
    }
}

/// How a robot fails a deploy, if it does.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fault {
    /// It does not.
    None,
    /// Its health check fails after the switch (`--fail-health-share`).
    FailHealth,
    /// Its download stalls until cancelled (`--timeout-share`).
    Timeout,
    /// It goes offline halfway through a fresh download (`--offline-mid-download-share`).
    Offline,
}

impl CommandArgs {
    /// Refuses shares outside 0..1 or adding up to more than 1, and a zero download bound.
    pub fn validate(&self) -> Result<(), String> {
        let shares = [
            ("--fail-health-share", self.fail_health_share),
            ("--timeout-share", self.timeout_share),
            (
                "--offline-mid-download-share",
                self.offline_mid_download_share,
            ),
        ];
        for (flag, share) in shares {
            if !(0.0..=1.0).contains(&share) {
                return Err(format!("{flag} {share} is not between 0 and 1"));
            }
        }
        if shares.iter().map(|(_, s)| s).sum::<f64>() > 1.0 + 1e-9 {
            return Err("the fault shares add up to more than 1".into());
        }
        if self.max_downloads == 0 {
            return Err("--max-downloads must be at least 1".into());
        }
        Ok(())
    }

    /// How robot `name` fails a deploy of release `version`: the three shares are disjoint
    /// slices of one point per robot, drawn from a hash of its name, so a rerun picks the same
    /// robots.
    pub fn fault_of(&self, name: &str, version: &str) -> Fault {
        if !self.fault_versions.is_empty() && !self.fault_versions.iter().any(|v| v == version) {
            return Fault::None;
        }
        let point = point_of(name);
        let health = self.fail_health_share;
        let timeout = health + self.timeout_share;
        let offline = timeout + self.offline_mid_download_share;
        if point < health {
            Fault::FailHealth
        } else if point < timeout {
            Fault::Timeout
        } else if point < offline {
            Fault::Offline
        } else {
            Fault::None
        }
    }

    /// How long an offline robot stays away.
    pub(super) fn offline_for(&self) -> Duration {
        Duration::from_secs_f64(self.offline_seconds.max(0.0))
    }

    /// How long a failing health check goes on.
    pub(super) fn health_timeout(&self) -> Duration {
        Duration::from_secs_f64(self.health_timeout_seconds.max(0.0))
    }
}

/// A stable point in [0, 1) for robot `name`, independent of the one `--late-share` uses.
fn point_of(name: &str) -> f64 {
    let mut hasher = std::hash::DefaultHasher::new();
    ("commands", name).hash(&mut hasher);
    (hasher.finish() % 1_000_000) as f64 / 1_000_000.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        commands: CommandArgs,
    }

    fn parse(extra: &[&str]) -> CommandArgs {
        Cli::parse_from(std::iter::once("sim").chain(extra.iter().copied())).commands
    }

    #[test]
    fn hooks_take_seconds_or_off() {
        let a = parse(&["--restart-seconds", "1.5", "--pre-switch-seconds", "off"]);
        assert_eq!(a.restart_seconds, Hook(Some(Duration::from_millis(1500))));
        assert_eq!(a.pre_switch_seconds, Hook(None));
        assert_eq!(a.health_check_seconds, Hook(Some(Duration::ZERO)));
        assert!("-1".parse::<Hook>().is_err());
        assert!("soon".parse::<Hook>().is_err());
    }

    /// Each share picks about its part of the robots, disjoint from the others, the same robots
    /// every time, and only for the versions named.
    #[test]
    fn faults_are_stable_disjoint_shares() {
        let a = parse(&[
            "--fail-health-share",
            "0.1",
            "--timeout-share",
            "0.05",
            "--offline-mid-download-share",
            "0.2",
            "--fault-versions",
            "2.0.0,3.0.0",
        ]);
        assert_eq!(a.validate(), Ok(()));
        let names: Vec<String> = (1..=10_000).map(|i| format!("sim-{i:05}")).collect();
        let count = |f: Fault| names.iter().filter(|n| a.fault_of(n, "2.0.0") == f).count();
        let (health, timeout, offline) = (
            count(Fault::FailHealth),
            count(Fault::Timeout),
            count(Fault::Offline),
        );
        assert!((900..=1100).contains(&health), "{health}");
        assert!((400..=600).contains(&timeout), "{timeout}");
        assert!((1800..=2200).contains(&offline), "{offline}");
        for n in &names {
            assert_eq!(a.fault_of(n, "3.0.0"), a.fault_of(n, "2.0.0"), "{n}");
            assert_eq!(
                a.fault_of(n, "1.0.0"),
                Fault::None,
                "{n}: not a fault version"
            );
        }
        let all = parse(&["--fail-health-share", "1"]);
        assert!(
            names
                .iter()
                .all(|n| all.fault_of(n, "9") == Fault::FailHealth)
        );
        assert!(
            names
                .iter()
                .all(|n| parse(&[]).fault_of(n, "9") == Fault::None)
        );
    }

    #[test]
    fn shares_must_fit_in_one() {
        assert!(parse(&["--timeout-share", "1.5"]).validate().is_err());
        let two = parse(&["--timeout-share", "0.6", "--fail-health-share", "0.6"]);
        assert!(two.validate().is_err());
        assert!(parse(&["--max-downloads", "0"]).validate().is_err());
    }
}
