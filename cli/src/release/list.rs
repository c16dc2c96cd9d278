//! `release list` and `release delete`: the releases pushed to a namespace with their size and
//! users (`GET /api/v1/namespaces/NS/releases`), and deleting one nothing uses.

use jiff::Timestamp;
use serde::{Deserialize, Serialize};

use super::human;
use crate::Output;
use crate::robots::age;

/// Who references a release: robots.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize)]
pub struct RobotUses {
    /// Robots whose `spec.release` it is.
    #[serde(default)]
    pub desired: u32,
    /// Robots running it.
    #[serde(default)]
    pub current: u32,
    /// Robots a RobotDeployment would roll back to it.
    #[serde(default)]
    pub previous: u32,
}

/// Who references a release: RobotDeployments.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct DeploymentUses {
    /// Deployments rolling it out.
    #[serde(default)]
    pub release: u32,
    /// Deployments that would roll some robot back to it.
    #[serde(default)]
    pub rollback_target: u32,
}

/// One release as the gateway lists it.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ReleaseItem {
    /// Its version.
    pub version: String,
    /// The manifest's digest.
    pub digest: String,
    /// Bytes of its files.
    #[serde(default)]
    pub size: Option<u64>,
    /// Its files.
    #[serde(default)]
    pub files: Option<usize>,
    /// When it was first pushed to the namespace.
    pub pushed: Timestamp,
    /// Robots that use it.
    #[serde(default)]
    pub robots: RobotUses,
    /// RobotDeployments that use it.
    #[serde(default)]
    pub deployments: DeploymentUses,
}

/// The list as `-o json|yaml` prints it: a Kubernetes-style `List`.
#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
struct List<'a> {
    api_version: &'static str,
    kind: &'static str,
    items: &'a [ReleaseItem],
}

/// Renders the releases in the chosen format; `now` is passed in so ages are testable.
pub fn render(items: &[ReleaseItem], output: Output, now: Timestamp) -> anyhow::Result<String> {
    let list = List {
        api_version: "v1",
        kind: "List",
        items,
    };
    Ok(match output.structured(&list)? {
        Some(text) => text,
        None => table(items, output == Output::Wide, now),
    })
}

fn table(items: &[ReleaseItem], wide: bool, now: Timestamp) -> String {
    let mut header = vec![
        "VERSION",
        "DIGEST",
        "SIZE",
        "PUSHED",
        "DESIRED",
        "CURRENT",
        "PREVIOUS",
        "DEPLOYMENTS",
    ];
    if wide {
        header.extend(["ROLLBACK-TARGET", "FILES"]);
    }
    let mut rows: Vec<Vec<String>> = vec![header.iter().map(|s| s.to_string()).collect()];
    for r in items {
        let mut row = vec![
            crate::sanitize::cell(&r.version).into_owned(),
            if wide {
                r.digest.clone()
            } else {
                r.digest.chars().take(7 + 12).collect()
            },
            r.size.map(human).unwrap_or_else(|| "-".into()),
            age(now, r.pushed),
            r.robots.desired.to_string(),
            r.robots.current.to_string(),
            r.robots.previous.to_string(),
            r.deployments.release.to_string(),
        ];
        if wide {
            row.push(r.deployments.rollback_target.to_string());
            row.push(r.files.map(|f| f.to_string()).unwrap_or_else(|| "-".into()));
        }
        rows.push(row);
    }
    crate::output::aligned(&rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_table_shows_size_age_and_users() {
        let now: Timestamp = "2026-01-01T12:00:00Z".parse().unwrap();
        let item: ReleaseItem = serde_json::from_value(serde_json::json!({
            "namespace": "lab", "version": "1.2.0", "digest": format!("sha256:{}", "a".repeat(64)),
            "size": 3 * 1024 * 1024, "files": 4, "pushed": "2026-01-01T09:00:00Z",
            "robots": {"desired": 2, "current": 1, "previous": 0},
            "deployments": {"release": 1, "rollbackTarget": 0}
        }))
        .unwrap();
        let text = render(std::slice::from_ref(&item), Output::Table, now).unwrap();
        let line = text.lines().nth(1).unwrap();
        let cells: Vec<&str> = line.split_whitespace().collect();
        assert_eq!(
            cells,
            [
                "1.2.0",
                "sha256:aaaaaaaaaaaa",
                "3.0",
                "MiB",
                "3h",
                "ago",
                "2",
                "1",
                "0",
                "1"
            ]
        );
        let json = render(&[item], Output::Json, now).unwrap();
        let v: serde_json::Value = serde_json::from_str(&json).unwrap();
        assert_eq!(v["kind"], "List");
        assert_eq!(v["items"][0]["robots"]["desired"], 2);
    }
}
