//! The flags of the simulated robots' command handling: the hooks they pretend to run, the
//! shares of robots that fail, and for which releases (chosen by name, the same ones every
//! run), and the bound on the fleet's downloads.

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
    /// Release versions whose health check those robots fail, comma-separated (default: every
    /// release), so that a first release rolls out cleanly and a later one fails.
    #[arg(long, value_delimiter = ',')]
    pub fail_health_versions: Vec<String>,
    /// Share (0 to 1) of the robots whose download stalls and never ends (a link that stopped
    /// moving): the rollout's robot timeout sees them, and a `cancel` stops them.
    #[arg(long, default_value_t = 0.0)]
    pub timeout_share: f64,
    /// Release versions whose download stalls on those robots (default: every release).
    #[arg(long, value_delimiter = ',')]
    pub timeout_versions: Vec<String>,
    /// Share (0 to 1) of the robots that go offline halfway through a download: the session
    /// drops, the deploy fails, and after `--offline-seconds` the robot connects again and the
    /// gateway's new `deploy` resumes the partial download (`Range`).
    #[arg(long, default_value_t = 0.0)]
    pub offline_mid_download_share: f64,
    /// Release versions whose download those robots break off (default: every release).
    #[arg(long, value_delimiter = ',')]
    pub offline_mid_download_versions: Vec<String>,
    /// Seconds a robot of `--offline-mid-download-share` stays offline.
    #[arg(long, default_value_t = 30.0)]
    pub offline_seconds: f64,
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
    /// Refuses shares outside 0..1 and a zero download bound.
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
        if self.max_downloads == 0 {
            return Err("--max-downloads must be at least 1".into());
        }
        Ok(())
    }

    /// How robot `name` fails a deploy of release `version`. Each fault picks its share of the
    /// robots by its own hash of the name (so a rerun picks the same robots, and the faults
    /// pick independently of each other), for the versions it names; a robot picked by several
    /// for the same version gets the first of health, timeout, offline.
    pub fn fault_of(&self, name: &str, version: &str) -> Fault {
        let picks = |fault: &str, share: f64, versions: &[String]| {
            (versions.is_empty() || versions.iter().any(|v| v == version))
                && point_of(fault, name) < share
        };
        if picks("health", self.fail_health_share, &self.fail_health_versions) {
            Fault::FailHealth
        } else if picks("timeout", self.timeout_share, &self.timeout_versions) {
            Fault::Timeout
        } else if picks(
            "offline",
            self.offline_mid_download_share,
            &self.offline_mid_download_versions,
        ) {
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

/// A stable point in [0, 1) for robot `name` and `fault`, independent of the one
/// `--late-share` uses.
fn point_of(fault: &str, name: &str) -> f64 {
    let mut hasher = std::hash::DefaultHasher::new();
    ("commands", fault, name).hash(&mut hasher);
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

    /// Each share picks about its part of the robots, independently of the others, the same
    /// robots every time, and only for the versions it names.
    #[test]
    fn faults_are_stable_shares_for_their_versions() {
        let a = parse(&[
            "--fail-health-share",
            "0.1",
            "--fail-health-versions",
            "2.0.0,3.0.0",
            "--timeout-share",
            "0.05",
            "--timeout-versions",
            "3.0.0",
            "--offline-mid-download-share",
            "0.2",
        ]);
        assert_eq!(a.validate(), Ok(()));
        let names: Vec<String> = (1..=10_000).map(|i| format!("sim-{i:05}")).collect();
        let count = |v: &str, f: Fault| names.iter().filter(|n| a.fault_of(n, v) == f).count();
        let health = count("2.0.0", Fault::FailHealth);
        assert!((900..=1100).contains(&health), "{health}");
        assert_eq!(count("2.0.0", Fault::Timeout), 0, "not a timeout version");
        let timeout = count("3.0.0", Fault::Timeout);
        // Those also picked for the health check fail that first.
        assert!((400..=550).contains(&timeout), "{timeout}");
        let offline = count("1.0.0", Fault::Offline);
        assert!((1800..=2200).contains(&offline), "{offline}");
        for n in &names {
            assert_eq!(
                a.fault_of(n, "3.0.0") == Fault::FailHealth,
                a.fault_of(n, "2.0.0") == Fault::FailHealth,
                "{n}"
            );
            assert_ne!(
                a.fault_of(n, "1.0.0"),
                Fault::FailHealth,
                "{n}: not a health version"
            );
        }
        let all = parse(&["--fail-health-share", "1", "--timeout-share", "1"]);
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
    fn shares_are_fractions() {
        assert!(parse(&["--timeout-share", "1.5"]).validate().is_err());
        assert!(parse(&["--fail-health-share=-0.1"]).validate().is_err());
        assert!(parse(&["--max-downloads", "0"]).validate().is_err());
    }
}
