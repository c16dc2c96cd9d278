//! `kubectl lekiwi robots`: a fleet-at-a-glance table.

use jiff::Timestamp;
use kube::api::ListParams;
use kube::{Api, ResourceExt};
use lekiwi_crds::Robot;
use lekiwi_crds::robot::CONDITION_TELEOPERATING;

use crate::Output;

/// Lists robots of one namespace (or all) in the given format.
pub async fn list(
    client: kube::Client,
    namespace: Option<&str>,
    output: Output,
) -> anyhow::Result<String> {
    let api: Api<Robot> = match namespace {
        Some(ns) => Api::namespaced(client, ns),
        None => Api::all(client),
    };
    let mut robots = api.list(&ListParams::default()).await?.items;
    robots.sort_by_key(|r| (r.namespace(), r.name_any()));
    Ok(match output.structured(&robots)? {
        Some(text) => text,
        None => table(
            &robots,
            namespace.is_none(),
            output == Output::Wide,
            Timestamp::now(),
        ),
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
                .map(|x| x.version.clone())
                .unwrap_or_else(dash),
            r.spec
                .release
                .as_ref()
                .map(|x| x.version.clone())
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
            row.push(status.agent_version.unwrap_or_else(dash));
            row.push(status.gateway.unwrap_or_else(dash));
            row.push(status.address.unwrap_or_else(dash));
        }
        if with_namespace {
            row.insert(0, r.namespace().unwrap_or_default());
        }
        rows.push(row);
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
    let widths: Vec<usize> = (0..rows[0].len())
        .map(|i| rows.iter().map(|r| r[i].len()).max().unwrap_or(0))
        .collect();
    let mut out = String::new();
    for row in rows {
        let line: Vec<String> = row
            .iter()
            .zip(&widths)
            .map(|(c, w)| format!("{c:<w$}"))
            .collect();
        out.push_str(line.join("   ").trim_end());
        out.push('\n');
    }
    out
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
}
