//! `kubectl lekiwi rollout status|pause|resume|undo|restart NAME`: watch and steer a
//! RobotDeployment.

use std::io::{IsTerminal, Write};
use std::time::Duration;

use clap::Subcommand;
use jiff::Timestamp;
use kube::api::{Patch, PatchParams};
use kube::{Api, ResourceExt};
use lekiwi_crds::RobotDeployment;
use lekiwi_crds::deployment::{
    RESTART_ANNOTATION, RobotRolloutState, RolloutPhase, UNDO_ANNOTATION,
};
use serde_json::json;

use crate::Output;

/// Rollout subcommands.
#[derive(Debug, Subcommand)]
pub enum RolloutCommand {
    /// Show a rollout's progress; by default follow it live until it completes, rolls back or
    /// fails (exit status 0 only when it completes).
    Status {
        /// The RobotDeployment.
        name: String,
        /// Follow until the rollout ends (`--watch=false` prints once).
        #[arg(short = 'w', long, default_value_t = true, action = clap::ArgAction::Set)]
        watch: bool,
        /// Give up following after this many seconds (0: never).
        #[arg(long, default_value_t = 0)]
        timeout: u64,
    },
    /// Pause: robots updating now finish, no new robot starts.
    Pause {
        /// The RobotDeployment.
        name: String,
    },
    /// Resume a paused rollout.
    Resume {
        /// The RobotDeployment.
        name: String,
    },
    /// Roll every robot the rollout updated back to the release it ran before.
    Undo {
        /// The RobotDeployment.
        name: String,
    },
    /// Start the rollout over from its first batch (failed and skipped robots are tried again).
    Restart {
        /// The RobotDeployment.
        name: String,
    },
}

/// Runs a rollout subcommand.
pub async fn run(
    client: kube::Client,
    namespace: &str,
    output: Output,
    cmd: RolloutCommand,
) -> anyhow::Result<()> {
    let api: Api<RobotDeployment> = Api::namespaced(client, namespace);
    match cmd {
        RolloutCommand::Status {
            name,
            watch,
            timeout,
        } => status(&api, &name, watch, timeout, output).await,
        RolloutCommand::Pause { name } => {
            steer(&api, &name, json!({"spec": {"paused": true}}), "paused").await
        }
        RolloutCommand::Resume { name } => {
            steer(&api, &name, json!({"spec": {"paused": false}}), "resumed").await
        }
        RolloutCommand::Undo { name } => {
            steer(&api, &name, stamp(UNDO_ANNOTATION), "rolling back").await
        }
        RolloutCommand::Restart { name } => {
            steer(&api, &name, stamp(RESTART_ANNOTATION), "restarted").await
        }
    }
}

/// A patch setting `annotation` to now: the controller acts on each new value once.
fn stamp(annotation: &str) -> serde_json::Value {
    json!({"metadata": {"annotations": {annotation: Timestamp::now().to_string()}}})
}

/// Merge-patches the RobotDeployment and says what was done, as kubectl does
/// (`robotdeployment/NAME paused`).
async fn steer(
    api: &Api<RobotDeployment>,
    name: &str,
    patch: serde_json::Value,
    done: &str,
) -> anyhow::Result<()> {
    merge(api, name, patch).await?;
    println!("robotdeployment/{name} {done}");
    Ok(())
}

async fn merge(
    api: &Api<RobotDeployment>,
    name: &str,
    patch: serde_json::Value,
) -> anyhow::Result<()> {
    api.patch(name, &PatchParams::default(), &Patch::Merge(&patch))
        .await
        .map_err(|e| match e {
            kube::Error::Api(s) if s.code == 404 => {
                anyhow::anyhow!("robotdeployment {name:?} not found in this namespace")
            }
            e => e.into(),
        })?;
    Ok(())
}

fn terminal(d: &RobotDeployment) -> Option<RolloutPhase> {
    let st = d.status.as_ref()?;
    // A status from before the latest spec change says nothing about it.
    if st.observed_generation != d.metadata.generation {
        return None;
    }
    st.phase.filter(|p| {
        matches!(
            p,
            RolloutPhase::Completed | RolloutPhase::RolledBack | RolloutPhase::Failed
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

async fn status(
    api: &Api<RobotDeployment>,
    name: &str,
    watch: bool,
    timeout: u64,
    output: Output,
) -> anyhow::Result<()> {
    let get = || async {
        api.get(name).await.map_err(|e| match e {
            kube::Error::Api(s) if s.code == 404 => {
                anyhow::anyhow!("robotdeployment {name:?} not found in this namespace")
            }
            e => e.into(),
        })
    };
    let d = get().await?;
    if !watch || matches!(output, Output::Json | Output::Yaml) {
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
        if timeout > 0 && started.elapsed() > Duration::from_secs(timeout) {
            if tty {
                eprintln!();
            }
            anyhow::bail!("rollout of {name} still in progress after {timeout}s");
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
        _ => Ok(()),
    }
}
