//! `rollout status NAME`: a rollout's progress, once or followed live until it ends.

use std::io::{IsTerminal, Write};
use std::time::Duration;

use kube::{Api, ResourceExt};
use lekiwi_crds::RobotDeployment;
use lekiwi_crds::deployment::{RobotRolloutState, RolloutPhase};

use crate::Output;

pub(super) fn terminal(d: &RobotDeployment) -> Option<RolloutPhase> {
    let st = d.status.as_ref()?;
    // A status from before the latest spec change says nothing about it.
    if st.observed_generation != d.metadata.generation {
        return None;
    }
    st.phase.filter(|p| {
        matches!(
            p,
            RolloutPhase::Completed
                | RolloutPhase::RolledBack
                | RolloutPhase::Failed
                | RolloutPhase::Aborted
        )
    })
}

/// One line: phase, a bar, counts, batch, message (control characters escaped).
pub fn summary_line(d: &RobotDeployment) -> String {
    let st = d.status.clone().unwrap_or_default();
    let targeted = st.targeted.max(0) as usize;
    let updated = st.updated.max(0) as usize;
    let width = 30;
    let filled = (updated * width)
        .checked_div(targeted)
        .unwrap_or(0)
        .min(width);
    format!(
        "{:<11} [{}{}] {}/{} updated, {} failed, {} skipped, batch {}  {}",
        st.phase.map_or("Pending".to_owned(), |p| format!("{p:?}")),
        "#".repeat(filled),
        ".".repeat(width - filled),
        updated,
        targeted,
        st.failed,
        st.skipped,
        st.batch_progress.as_deref().unwrap_or("-"),
        crate::sanitize::cell(st.message.as_deref().unwrap_or("")),
    )
}

/// The full report: summary, robots in progress and failures, conditions (their messages may
/// quote robots: control characters escaped).
pub fn report(d: &RobotDeployment) -> String {
    let st = d.status.clone().unwrap_or_default();
    let target = match (&d.spec.release, &d.spec.agent) {
        (Some(r), _) => format!("{} → {}", r.version, r.digest),
        (None, Some(a)) => {
            let builds: Vec<String> = a
                .builds
                .iter()
                .map(|b| format!("{} {}", b.arch.as_str(), b.digest))
                .collect();
            format!("agent {} → {}", a.version, builds.join(", "))
        }
        (None, None) => "nothing (set spec.release or spec.agent)".to_owned(),
    };
    let mut out = format!(
        "robotdeployment/{}: {target}\n{}\n",
        d.name_any(),
        summary_line(d)
    );
    let busy: Vec<_> = st
        .robots
        .iter()
        .filter(|r| {
            matches!(
                r.state,
                RobotRolloutState::Updating
                    | RobotRolloutState::Waiting
                    | RobotRolloutState::Failed
            )
        })
        .take(20)
        .collect();
    if !busy.is_empty() {
        out.push_str("ROBOT                BATCH  STATE      MESSAGE\n");
        for r in busy {
            out.push_str(&format!(
                "{:<20} {:<6} {:<10} {}\n",
                r.robot,
                r.batch,
                format!("{:?}", r.state),
                crate::sanitize::cell(r.message.as_deref().unwrap_or(""))
            ));
        }
    }
    for c in &st.conditions {
        if c.status == lekiwi_crds::ConditionStatus::True {
            out.push_str(&format!(
                "condition {}: {} {}\n",
                c.r#type,
                c.reason,
                crate::sanitize::cell(&c.message)
            ));
        }
    }
    out
}

pub(super) async fn status(
    api: &Api<RobotDeployment>,
    name: &str,
    watch: bool,
    timeout: Duration,
    output: &Output,
) -> anyhow::Result<()> {
    let get = || async { api.get(name).await.map_err(|e| super::not_found(e, name)) };
    let d = get().await?;
    if !watch || !output.table() {
        match output.structured(&d.status)? {
            Some(text) => print!("{text}"),
            None => print!("{}", report(&d)),
        }
        return verdict(&d);
    }
    let tty = std::io::stderr().is_terminal();
    let started = std::time::Instant::now();
    let mut last = String::new();
    let mut d = d;
    loop {
        let line = summary_line(&d);
        if line != last {
            if tty {
                eprint!("\r\x1b[2K{line}");
            } else {
                eprintln!("{line}");
            }
            let _ = std::io::stderr().flush();
            last = line;
        }
        if terminal(&d).is_some() {
            if tty {
                eprintln!();
            }
            print!("{}", report(&d));
            return verdict(&d);
        }
        if !timeout.is_zero() && started.elapsed() > timeout {
            if tty {
                eprintln!();
            }
            anyhow::bail!("rollout of {name} still in progress after {timeout:?}");
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
        d = get().await?;
    }
}

fn verdict(d: &RobotDeployment) -> anyhow::Result<()> {
    let message = || {
        d.status
            .as_ref()
            .and_then(|s| s.message.clone())
            .unwrap_or_default()
    };
    match terminal(d) {
        Some(RolloutPhase::RolledBack) => anyhow::bail!("rollout rolled back: {}", message()),
        Some(RolloutPhase::Failed) => anyhow::bail!("rollout failed: {}", message()),
        Some(RolloutPhase::Aborted) => anyhow::bail!("rollout aborted: {}", message()),
        _ => Ok(()),
    }
}
