//! `rollout list` (a table of RobotDeployments) and `rollout get NAME` (one rollout as a tree
//! of batches and robots), each once or live with `-w`.

use std::collections::BTreeMap;
use std::io::{IsTerminal as _, Write as _};

use futures::TryStreamExt as _;
use jiff::Timestamp;
use kube::runtime::watcher::watch_object;
use kube::{Api, ResourceExt as _};
use lekiwi_crds::RobotDeployment;
use lekiwi_crds::deployment::RobotResult;

use crate::Output;
use crate::list::ListArgs;
use crate::robots::{age, format_table};
use crate::sanitize::cell;

/// Lists rollouts (in every namespace when `all`), then watches them with `-w`.
pub(super) async fn list(
    api: Api<RobotDeployment>,
    all: bool,
    (output, no_headers): (&Output, bool),
    args: ListArgs,
) -> anyhow::Result<()> {
    let selector = args.selector.as_deref();
    let mut items = api.list(&crate::list::params(selector)).await?.items;
    items.sort_by_key(|d| (d.namespace(), d.name_any()));
    let text = match output.resources(&items)? {
        Some(text) => text,
        None if items.is_empty() && !args.watch => String::new(),
        None => list_table(&items, all, output.wide(), Timestamp::now()),
    };
    if items.is_empty() && output.table() {
        eprintln!("No rollouts found.");
    }
    print!(
        "{}",
        crate::list::headers(text, no_headers && output.table())
    );
    if args.watch {
        let seen = crate::list::seen(&items);
        let row = |d: &RobotDeployment| {
            list_table(
                std::slice::from_ref(d),
                all,
                output.wide(),
                Timestamp::now(),
            )
        };
        crate::list::watch(api, selector, seen, output, row).await?;
    }
    Ok(())
}

/// What a deployment rolls out: `VERSION` of a release, `agent VERSION` of an agent.
fn target(d: &RobotDeployment) -> (String, String) {
    match (&d.spec.release, &d.spec.agent) {
        (Some(r), _) => (r.version.to_string(), r.digest.to_string()),
        (None, Some(a)) => (format!("agent {}", a.version), "-".to_owned()),
        (None, None) => ("-".to_owned(), "-".to_owned()),
    }
}

/// The rollouts as a table (with a NAMESPACE column when `all`); `now` for the ages.
pub fn list_table(items: &[RobotDeployment], all: bool, wide: bool, now: Timestamp) -> String {
    let mut header = vec![
        "NAME", "PHASE", "RELEASE", "UPDATED", "FAILED", "BATCH", "AGE",
    ];
    if wide {
        header.extend(["DIGEST", "MESSAGE"]);
    }
    if all {
        header.insert(0, "NAMESPACE");
    }
    let mut rows = vec![header.iter().map(|s| s.to_string()).collect::<Vec<_>>()];
    for d in items {
        let st = d.status.clone().unwrap_or_default();
        let (release, digest) = target(d);
        let mut row = vec![
            d.name_any(),
            st.phase.map_or("Pending".to_owned(), |p| format!("{p:?}")),
            release,
            format!("{}/{}", st.updated, st.targeted),
            st.failed.to_string(),
            st.batch_progress.clone().unwrap_or_else(|| "-".into()),
            d.metadata
                .creation_timestamp
                .as_ref()
                .map_or("-".into(), |t| age(now, t.0).replace(" ago", "")),
        ];
        if wide {
            row.extend([digest, st.message.clone().unwrap_or_default()]);
        }
        if all {
            row.insert(0, d.namespace().unwrap_or_default());
        }
        rows.push(row);
    }
    format_table(rows)
}

/// Shows one rollout as a tree; with `watch`, redraws it at every change until interrupted.
pub(super) async fn get(
    api: &Api<RobotDeployment>,
    name: &str,
    watch: bool,
    output: &Output,
) -> anyhow::Result<()> {
    let d = api.get(name).await.map_err(|e| super::not_found(e, name))?;
    let draw = |d: &RobotDeployment| -> anyhow::Result<String> {
        Ok(match output.structured(d)? {
            Some(text) => text,
            None => tree(d),
        })
    };
    print!("{}", draw(&d)?);
    if !watch {
        return Ok(());
    }
    let tty = std::io::stdout().is_terminal() && output.table();
    let mut last = d.resource_version();
    let mut changes = std::pin::pin!(watch_object(api.clone(), name));
    while let Some(d) = changes.try_next().await? {
        let Some(d) = d else {
            anyhow::bail!("robotdeployment {name:?} was deleted");
        };
        if d.resource_version() == last {
            continue;
        }
        last = d.resource_version();
        // A terminal redraws in place; a pipe gets each state after a blank line.
        print!("{}{}", if tty { "\x1b[H\x1b[2J" } else { "\n" }, draw(&d)?);
        std::io::stdout().flush()?;
    }
    Ok(())
}

/// The rollout as Argo Rollouts' `get rollout` draws one: a header, then its batches and the
/// robots in each with their state and message (from `status.robots`; robots not yet in a
/// batch are counted).
pub fn tree(d: &RobotDeployment) -> String {
    let st = d.status.clone().unwrap_or_default();
    let (release, digest) = target(d);
    let phase = st.phase.map_or("Pending".to_owned(), |p| format!("{p:?}"));
    let mut out = String::new();
    for (key, value) in [
        ("Name", d.name_any()),
        ("Namespace", d.namespace().unwrap_or_default()),
        ("Release", format!("{release} ({digest})")),
        ("Phase", phase.clone()),
        (
            "Message",
            cell(st.message.as_deref().unwrap_or("-")).into_owned(),
        ),
        (
            "Batch",
            format!(
                "{} (paused: {})",
                st.batch_progress.as_deref().unwrap_or("-"),
                d.spec.paused
            ),
        ),
        (
            "Robots",
            format!(
                "{} targeted, {} updated, {} failed, {} skipped, {} pending",
                st.targeted, st.updated, st.failed, st.skipped, st.pending
            ),
        ),
    ] {
        out.push_str(&format!("{:<11}{value}\n", format!("{key}:")));
    }
    let mut batches: BTreeMap<i32, Vec<&RobotResult>> = BTreeMap::new();
    for r in &st.robots {
        batches.entry(r.batch).or_default().push(r);
    }
    let mut rows = vec![vec![
        "NAME".to_owned(),
        "STATE".to_owned(),
        "MESSAGE".to_owned(),
    ]];
    rows.push(vec![d.name_any(), phase, String::new()]);
    let count = batches.len() + usize::from(st.pending > 0);
    for (i, (batch, robots)) in batches.iter_mut().enumerate() {
        let last = i + 1 == count;
        let label = match *batch {
            b if b < 0 => "not in a batch".to_owned(),
            0 if d.spec.strategy.canary > 0 => "batch 0 (canary)".to_owned(),
            b => format!("batch {b}"),
        };
        rows.push(vec![
            format!("{}# {label}", branch(last)),
            String::new(),
            String::new(),
        ]);
        robots.sort_by(|a, b| a.robot.cmp(&b.robot));
        for (j, r) in robots.iter().enumerate() {
            let stem = if last { "   " } else { "│  " };
            rows.push(vec![
                format!("{stem}{}{}", branch(j + 1 == robots.len()), r.robot),
                format!("{:?}", r.state),
                r.message.clone().unwrap_or_default(),
            ]);
        }
    }
    if st.pending > 0 {
        rows.push(vec![
            format!("└──{} robot(s) not started yet", st.pending),
            "Pending".to_owned(),
            String::new(),
        ]);
    }
    out.push('\n');
    out.push_str(&format_table(rows));
    out
}

fn branch(last: bool) -> &'static str {
    if last { "└──" } else { "├──" }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rollout() -> RobotDeployment {
        serde_yaml::from_str(
            r#"
apiVersion: fleet.lekiwi.io/v1alpha1
kind: RobotDeployment
metadata: {name: cli, namespace: lab, creationTimestamp: "2026-12-05T08:00:00Z"}
spec:
  selector: {}
  release: {version: 2.0.0, digest: "sha256:abc"}
  strategy: {canary: 1}
status:
  phase: Aborted
  targeted: 5
  updated: 2
  pending: 2
  skipped: 1
  batchProgress: 2/3
  message: aborted by a user
  robots:
  - {robot: kiwi-00, batch: 0, state: Updated}
  - {robot: kiwi-02, batch: 1, state: Skipped, message: "aborted before it switched"}
  - {robot: kiwi-01, batch: 1, state: Updated}
"#,
        )
        .unwrap()
    }

    #[test]
    fn a_rollout_is_a_tree_of_batches_and_robots() {
        let text = tree(&rollout());
        assert!(text.contains("Phase:     Aborted"), "{text}");
        let lines: Vec<&str> = text
            .lines()
            .skip_while(|l| !l.starts_with("NAME"))
            .collect();
        let names: Vec<&str> = lines
            .iter()
            .map(|l| l.split("   ").next().unwrap_or_default().trim_end())
            .collect();
        assert_eq!(
            names,
            [
                "NAME",
                "cli",
                "├──# batch 0 (canary)",
                "│  └──kiwi-00",
                "├──# batch 1",
                "│  ├──kiwi-01",
                "│  └──kiwi-02",
                "└──2 robot(s) not started yet"
            ],
            "{text}"
        );
        assert!(lines[6].contains("Skipped") && lines[6].contains("aborted before"));
    }

    #[test]
    fn the_list_has_phase_release_progress_and_batch() {
        let now: Timestamp = "2026-12-05T08:05:00Z".parse().unwrap();
        let text = list_table(&[rollout()], true, false, now);
        let mut lines = text.lines();
        let header: Vec<&str> = lines.next().unwrap().split_whitespace().collect();
        assert_eq!(
            header,
            [
                "NAMESPACE",
                "NAME",
                "PHASE",
                "RELEASE",
                "UPDATED",
                "FAILED",
                "BATCH",
                "AGE"
            ]
        );
        let row: Vec<&str> = lines.next().unwrap().split_whitespace().collect();
        assert_eq!(
            row,
            ["lab", "cli", "Aborted", "2.0.0", "2/5", "0", "2/3", "5m"]
        );
    }
}
