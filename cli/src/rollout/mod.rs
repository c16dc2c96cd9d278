//! `kubectl lekiwi rollout ...`: list, show, watch and steer RobotDeployments, as an Argo
//! Rollouts user would (`list`, `get`, `status`, `pause`, `resume`, `abort`, `undo`,
//! `restart`, `set-release`).

mod get;
mod set_release;
mod status;

use std::time::Duration;

use clap::Subcommand;
use jiff::Timestamp;
use kube::Api;
use kube::api::{Patch, PatchParams};
use lekiwi_crds::RobotDeployment;
use lekiwi_crds::deployment::{ABORT_ANNOTATION, RESTART_ANNOTATION, UNDO_ANNOTATION};
use serde_json::json;

pub use self::get::{list_table, tree};
pub use self::status::{report, summary_line};
use crate::Output;
use crate::list::ListArgs;

/// Rollout subcommands.
#[derive(Debug, Subcommand)]
pub enum RolloutCommand {
    /// List RobotDeployments with phase, release, progress and batch (`-A` for every namespace,
    /// `-w` to watch).
    List {
        /// Selector and watch.
        #[command(flatten)]
        list: ListArgs,
    },
    /// Show one rollout as a tree: its batches and their robots, each with its state; `-w`
    /// redraws it live until interrupted.
    Get {
        /// The RobotDeployment.
        name: String,
        /// Redraw whenever the rollout changes.
        #[arg(short = 'w', long)]
        watch: bool,
    },
    /// Show a rollout's progress; by default follow it live until it completes, rolls back,
    /// fails or is aborted (exit status 0 only when it completes).
    Status {
        /// The RobotDeployment.
        name: String,
        /// Follow until the rollout ends (`--watch=false` prints once).
        #[arg(short = 'w', long, default_value_t = true, action = clap::ArgAction::Set)]
        watch: bool,
        /// Give up following after this long (`90s`, `5m`, `1h30m`; a bare number is
        /// seconds; 0: never).
        #[arg(long, default_value = "0", value_parser = crate::duration::parse)]
        timeout: Duration,
    },
    /// Pause: no robot starts; robots told to switch that have not switched yet stop their
    /// downloads and wait (`resume` continues them where they stopped).
    Pause {
        /// The RobotDeployment.
        name: String,
    },
    /// Resume a paused rollout.
    Resume {
        /// The RobotDeployment.
        name: String,
    },
    /// Stop the rollout where it stands: no robot starts, robots not yet switched stay on the
    /// release they run (their downloads are cancelled), robots that switched keep the new
    /// release. It ends `Aborted`; `restart` goes on, `undo` rolls back.
    Abort {
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
    /// Roll out another release: set `spec.release` to VERSION and its digest, looked up
    /// among the releases pushed to the gateway, or given with `--digest`.
    SetRelease(set_release::SetReleaseArgs),
}

/// Runs a rollout subcommand in `namespace`; `list_ns` is `None` for `-A`. `format` is `-o`
/// and `--no-headers`.
pub async fn run(
    kube: &crate::KubeContext,
    list_ns: Option<&str>,
    format: (&Output, bool),
    cmd: RolloutCommand,
) -> anyhow::Result<()> {
    let (client, namespace) = (kube.client.clone(), kube.namespace.as_str());
    let api: Api<RobotDeployment> = Api::namespaced(client.clone(), namespace);
    let output = format.0;
    match cmd {
        RolloutCommand::List { list } => {
            let api = match list_ns {
                Some(ns) => Api::namespaced(client, ns),
                None => Api::all(client),
            };
            get::list(api, list_ns.is_none(), format, list).await
        }
        RolloutCommand::Get { name, watch } => get::get(&api, &name, watch, output).await,
        RolloutCommand::Status {
            name,
            watch,
            timeout,
        } => status::status(&api, &name, watch, timeout, output).await,
        RolloutCommand::Pause { name } => {
            steer(&api, &name, json!({"spec": {"paused": true}}), "paused").await
        }
        RolloutCommand::Resume { name } => {
            steer(&api, &name, json!({"spec": {"paused": false}}), "resumed").await
        }
        RolloutCommand::Abort { name } => {
            steer(&api, &name, stamp(ABORT_ANNOTATION), "aborted").await
        }
        RolloutCommand::Undo { name } => {
            steer(&api, &name, stamp(UNDO_ANNOTATION), "rolling back").await
        }
        RolloutCommand::Restart { name } => {
            steer(&api, &name, stamp(RESTART_ANNOTATION), "restarted").await
        }
        RolloutCommand::SetRelease(args) => set_release::run(kube, &api, args).await,
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
        .map_err(|e| not_found(e, name))?;
    Ok(())
}

/// A 404 as a message naming the rollout; other errors as they are.
fn not_found(e: kube::Error, name: &str) -> anyhow::Error {
    match e {
        kube::Error::Api(s) if s.code == 404 => {
            anyhow::anyhow!("robotdeployment {name:?} not found in this namespace")
        }
        e => e.into(),
    }
}
