//! `kubectl lekiwi robots`: a fleet-at-a-glance table, or robots counted by agent version,
//! release or phase (`--group-by`), which is how a mixed fleet is watched during an agent update.

use std::collections::BTreeMap;

use jiff::Timestamp;
use kube::{Api, ResourceExt};
use lekiwi_crds::Robot;
use lekiwi_crds::robot::CONDITION_TELEOPERATING;

use crate::Output;

/// `kubectl lekiwi robots` options.
#[derive(Debug, clap::Args)]
pub struct RobotsArgs {
    /// Instead of one line per robot, one line per value of this: `agent` (the agent version a
    /// robot runs, from its `hello`), `desired-agent` (`spec.agent.version`), `release` (the
    /// release it runs), `phase` or `protocol` (`websocket` for the agent, `poll` for a robot
    /// still on the legacy polling endpoint); with how many robots have it, how many of those are
    /// Online, and the first few names. A robot without the value counts under `-`.
    #[arg(long, value_enum)]
    pub group_by: Option<GroupBy>,
    /// Selector and watch.
    #[command(flatten)]
    pub list: crate::list::ListArgs,
}

/// What `--group-by` counts robots by.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum GroupBy {
    /// The agent version the robot runs (`status.agentVersion`).
    Agent,
    /// The agent version its spec asks for (`spec.agent.version`).
    DesiredAgent,
    /// The release it runs (`status.currentRelease.version`).
    Release,
    /// Its phase.
    Phase,
    /// How it last connected (`status.protocol`): `websocket` (the agent) or `poll` (legacy).
    Protocol,
}

/// Robots sharing one value of the `--group-by` field.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
#[serde(rename_all = "camelCase")]
pub struct Group {
    /// The value (`-` for robots without one).
    pub value: String,
    /// Robots with it.
    pub robots: usize,
    /// Of those, how many are Online.
    pub online: usize,
    /// Their names (`namespace/name` across namespaces), in order.
    pub names: Vec<String>,
}

/// How many names a table row shows before `...`.
const NAMES_SHOWN: usize = 3;

/// Lists robots of one namespace (or all) in the given format, or their groups; with
/// `--watch`, then prints each robot again when it changes.
pub async fn run(
    client: kube::Client,
    namespace: Option<&str>,
    output: &Output,
    no_headers: bool,
    args: RobotsArgs,
) -> anyhow::Result<()> {
    let api: Api<Robot> = match namespace {
        Some(ns) => Api::namespaced(client, ns),
        None => Api::all(client),
    };
    let selector = args.list.selector.as_deref();
    let mut robots = api.list(&crate::list::params(selector)).await?.items;
    robots.sort_by_key(|r| (r.namespace(), r.name_any()));
    let text = match args.group_by {
        Some(by) => {
            let groups = groups(&robots, by, namespace.is_none());
            match output.rows(&groups, |g| g.value.clone())? {
                Some(text) => text,
                None => group_table(&groups, by),
            }
        }
        None => render(&robots, namespace.is_none(), output)?,
    };
    print!(
        "{}",
        crate::list::headers(text, no_headers && output.table())
    );
    if args.list.watch && args.group_by.is_none() {
        let seen = crate::list::seen(&robots);
        let all = namespace.is_none();
        let row = |r: &Robot| {
            table(
                std::slice::from_ref(r),
                all,
                output.wide(),
                Timestamp::now(),
            )
        };
        crate::list::watch(api, selector, seen, output, row).await?;
    }
    Ok(())
}

/// The robots in the given format (`now` for the table's ages).
pub fn render(robots: &[Robot], with_namespace: bool, output: &Output) -> anyhow::Result<String> {
    Ok(match output.resources(robots)? {
        Some(text) => text,
        None => table(robots, with_namespace, output.wide(), Timestamp::now()),
    })
}

/// Renders the table; `now` is passed in so ages are testable.
pub fn table(robots: &[Robot], with_namespace: bool, wide: bool, now: Timestamp) -> String {
    let mut header = vec!["NAME", "PHASE", "RELEASE", "DESIRED", "TELEOP", "HEARTBEAT"];
    if wide {
        header.extend(["AGENT", "GATEWAY", "ADDRESS"]);
    }
    if with_namespace {
        header.insert(0, "NAMESPACE");
    }
    let mut rows: Vec<Vec<String>> = vec![header.iter().map(|s| s.to_string()).collect()];
    for r in robots {
        let status = r.status.clone().unwrap_or_default();
        let dash = || "-".to_owned();
        let mut row = vec![
            r.name_any(),
            status
                .phase
                .map(|p| p.to_string())
                .unwrap_or_else(|| "Pending".into()),
            status
                .current_release
                .as_ref()
                .map(|x| x.version.to_string())
                .unwrap_or_else(dash),
            r.spec
                .release
                .as_ref()
                .map(|x| x.version.to_string())
                .unwrap_or_else(dash),
            r.condition(CONDITION_TELEOPERATING)
                .map(|c| match c.status {
                    lekiwi_crds::ConditionStatus::True => "yes".to_owned(),
                    lekiwi_crds::ConditionStatus::False => "no".to_owned(),
                    lekiwi_crds::ConditionStatus::Unknown => "?".to_owned(),
                })
                .unwrap_or_else(dash),
            status
                .last_heartbeat_time
                .as_ref()
                .map(|t| age(now, t.0))
                .unwrap_or_else(dash),
        ];
        if wide {
            row.push(status.agent_version.map(String::from).unwrap_or_else(dash));
            row.push(status.gateway.map(String::from).unwrap_or_else(dash));
            row.push(status.address.unwrap_or_else(dash));
        }
        if with_namespace {
            row.insert(0, r.namespace().unwrap_or_default());
        }
        rows.push(row);
    }
    format_table(rows)
}

/// The robots grouped by `by`, in value order (`-` last); names as `namespace/name` when
/// `with_namespace`.
pub fn groups(robots: &[Robot], by: GroupBy, with_namespace: bool) -> Vec<Group> {
    let mut by_value: BTreeMap<(bool, String), Group> = BTreeMap::new();
    for r in robots {
        let status = r.status.as_ref();
        let value = match by {
            GroupBy::Agent => status.and_then(|s| s.agent_version.clone().map(String::from)),
            GroupBy::DesiredAgent => r.spec.agent.as_ref().map(|a| a.version.clone()),
            GroupBy::Release => status
                .and_then(|s| s.current_release.as_ref())
                .map(|x| x.version.to_string()),
            GroupBy::Phase => Some(
                status
                    .and_then(|s| s.phase)
                    .map(|p| p.to_string())
                    .unwrap_or_else(|| "Pending".into()),
            ),
            GroupBy::Protocol => status.and_then(|s| s.protocol.clone().map(String::from)),
        };
        let key = (value.is_none(), value.unwrap_or_else(|| "-".to_owned()));
        let group = by_value.entry(key.clone()).or_insert_with(|| Group {
            value: key.1,
            robots: 0,
            online: 0,
            names: Vec::new(),
        });
        group.robots += 1;
        if status.and_then(|s| s.phase) == Some(lekiwi_crds::RobotPhase::Online) {
            group.online += 1;
        }
        group.names.push(if with_namespace {
            format!("{}/{}", r.namespace().unwrap_or_default(), r.name_any())
        } else {
            r.name_any()
        });
    }
    by_value.into_values().collect()
}

/// The groups as a table: value, robots, online, the first names.
pub fn group_table(groups: &[Group], by: GroupBy) -> String {
    let column = match by {
        GroupBy::Agent => "AGENT",
        GroupBy::DesiredAgent => "DESIRED AGENT",
        GroupBy::Release => "RELEASE",
        GroupBy::Phase => "PHASE",
        GroupBy::Protocol => "PROTOCOL",
    };
    let mut rows = vec![
        [column, "ROBOTS", "ONLINE", "NAMES"]
            .map(str::to_owned)
            .to_vec(),
    ];
    for g in groups {
        let mut names = g.names[..g.names.len().min(NAMES_SHOWN)].join(",");
        if g.names.len() > NAMES_SHOWN {
            names.push_str(",...");
        }
        rows.push(vec![
            g.value.clone(),
            g.robots.to_string(),
            g.online.to_string(),
            names,
        ]);
    }
    format_table(rows)
}

/// Left-aligned columns separated by three spaces; the first row is the header. Every cell is
/// [`crate::sanitize::cell`]ed: tables show robot-supplied text.
pub(crate) fn format_table(rows: Vec<Vec<String>>) -> String {
    let rows: Vec<Vec<String>> = rows
        .into_iter()
        .map(|r| {
            r.iter()
                .map(|c| crate::sanitize::cell(c).into_owned())
                .collect()
        })
        .collect();
    crate::output::aligned(&rows)
}

/// kubectl-style age: `45s`, `3m`, `5h`, `2d`.
pub(crate) fn age(now: Timestamp, then: Timestamp) -> String {
    let secs = now.duration_since(then).as_secs().max(0);
    match secs {
        s if s < 120 => format!("{s}s ago"),
        s if s < 7200 => format!("{}m ago", s / 60),
        s if s < 172_800 => format!("{}h ago", s / 3600),
        s => format!("{}d ago", s / 86400),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_shows_phase_release_teleop_and_heartbeat_age() {
        let robot: Robot = serde_yaml::from_str(
            r#"
apiVersion: fleet.lekiwi.io/v1alpha1
kind: Robot
metadata: { name: kiwi-01, namespace: lab }
spec:
  release: { version: "1.1.0", digest: "sha256:1111111111111111111111111111111111111111111111111111111111111111" }
status:
  phase: Online
  lastHeartbeatTime: "2026-11-22T10:00:00Z"
  currentRelease: { version: "1.0.0", digest: "sha256:0000000000000000000000000000000000000000000000000000000000000000" }
  conditions:
  - { type: Teleoperating, status: "True", reason: TeleoperationDetected, lastTransitionTime: "2026-11-22T09:00:00Z" }
"#,
        )
        .unwrap();
        let pending: Robot = serde_yaml::from_str("apiVersion: fleet.lekiwi.io/v1alpha1\nkind: Robot\nmetadata: {name: kiwi-02}\nspec: {}\n").unwrap();
        let out = table(
            &[robot, pending],
            false,
            false,
            "2026-11-22T10:00:42Z".parse().unwrap(),
        );
        let lines: Vec<&str> = out.lines().collect();
        assert_eq!(lines.len(), 3);
        assert!(lines[0].starts_with("NAME"));
        let cols: Vec<&str> = lines[1].split_whitespace().collect();
        assert_eq!(
            cols,
            ["kiwi-01", "Online", "1.0.0", "1.1.0", "yes", "42s", "ago"]
        );
        let cols: Vec<&str> = lines[2].split_whitespace().collect();
        assert_eq!(cols, ["kiwi-02", "Pending", "-", "-", "-", "-"]);
    }

    fn robot(name: &str, phase: &str, agent: Option<&str>) -> Robot {
        let agent = agent.map_or(String::new(), |a| format!(", agentVersion: \"{a}\""));
        serde_yaml::from_str(&format!(
            "apiVersion: fleet.lekiwi.io/v1alpha1\nkind: Robot\nmetadata: {{name: {name}, namespace: lab}}\nspec: {{}}\nstatus: {{phase: {phase}{agent}}}\n"
        ))
        .unwrap()
    }

    #[test]
    fn groups_count_robots_and_online_ones_per_agent_version_unknown_last() {
        let robots = [
            robot("kiwi-1", "Online", Some("0.2.0")),
            robot("kiwi-2", "Offline", Some("0.1.0")),
            robot("kiwi-3", "Online", None),
            robot("kiwi-4", "Online", Some("0.2.0")),
            robot("kiwi-5", "Online", Some("0.2.0")),
            robot("kiwi-6", "Unknown", Some("0.2.0")),
        ];
        let groups = groups(&robots, GroupBy::Agent, false);
        let summary: Vec<_> = groups
            .iter()
            .map(|g| (g.value.as_str(), g.robots, g.online))
            .collect();
        assert_eq!(summary, [("0.1.0", 1, 0), ("0.2.0", 4, 3), ("-", 1, 1)]);
        assert_eq!(groups[1].names, ["kiwi-1", "kiwi-4", "kiwi-5", "kiwi-6"]);
        let table = group_table(&groups, GroupBy::Agent);
        let lines: Vec<Vec<&str>> = table
            .lines()
            .map(|l| l.split_whitespace().collect())
            .collect();
        assert_eq!(lines[0], ["AGENT", "ROBOTS", "ONLINE", "NAMES"]);
        assert_eq!(lines[2], ["0.2.0", "4", "3", "kiwi-1,kiwi-4,kiwi-5,..."]);
        assert_eq!(lines[3], ["-", "1", "1", "kiwi-3"]);
        let across = groups_of_phase(&robots);
        let want = [("Offline", 1), ("Online", 4), ("Unknown", 1)].map(|(p, n)| (p.to_owned(), n));
        assert_eq!(across, want);

        let mut polling = robot("kiwi-7", "Online", Some("legacy-0.9"));
        polling.status.as_mut().unwrap().protocol = Some("poll".into());
        let mut ws = robot("kiwi-8", "Online", Some("0.2.0"));
        ws.status.as_mut().unwrap().protocol = Some("websocket".into());
        let mixed = [polling, ws, robots[2].clone()];
        let by_protocol: Vec<_> = super::groups(&mixed, GroupBy::Protocol, false)
            .into_iter()
            .map(|g| (g.value, g.names))
            .collect();
        let want = [("poll", "kiwi-7"), ("websocket", "kiwi-8"), ("-", "kiwi-3")]
            .map(|(v, n)| (v.to_owned(), vec![n.to_owned()]));
        assert_eq!(by_protocol, want);
    }

    fn groups_of_phase(robots: &[Robot]) -> Vec<(String, usize)> {
        groups(robots, GroupBy::Phase, true)
            .into_iter()
            .map(|g| {
                assert!(g.names.iter().all(|n| n.starts_with("lab/")));
                (g.value, g.robots)
            })
            .collect()
    }
}
