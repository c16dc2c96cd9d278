//! A fleet of real agents in one process: each runs the agent's own run loop with its own state
//! directory (token, outbox, content store, releases), for end-to-end tests and benchmarks of
//! rollouts. One machine cannot tell robots' vitals apart, so each robot's telemetry reads a
//! synthetic world of its own ([`Telemetry::synthetic`]) through the agent's own collector, and
//! teleoperation detection is off; everything else — enrollment, outbox, telemetry batches,
//! deploys, hooks — is the real thing.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Duration;

use clap::Parser;
use tracing::info;

use crate::config::Config;
use crate::discovery::StatusSnapshot;
use crate::run::Agent;
use crate::telemetry::Telemetry;

/// Runs N real agents in one process.
#[derive(Clone, Debug, Parser)]
#[command(name = "lekiwi-fleet", version, about)]
pub struct Args {
    /// Gateway WebSocket URL.
    #[arg(long, env = "LEKIWI_GATEWAY_URL")]
    pub gateway: String,
    /// File holding the fleet enrollment token.
    #[arg(long)]
    pub enrollment_token_file: PathBuf,
    /// Namespace of the robots.
    #[arg(long)]
    pub namespace: String,
    /// Number of robots.
    #[arg(long, default_value_t = 50)]
    pub robots: usize,
    /// Robot names are PREFIX-000, PREFIX-001, ...
    #[arg(long, default_value = "kiwi")]
    pub prefix: String,
    /// Parent of the robots' state directories (one subdirectory per robot).
    #[arg(long)]
    pub state_root: PathBuf,
    /// CA file for wss://.
    #[arg(long)]
    pub ca_file: Option<PathBuf>,
    /// Restart command after a switch (run with `sh -c`).
    #[arg(long, default_value = "")]
    pub restart_command: String,
    /// Health command after a switch (run with `sh -c`); the environment has
    /// `LEKIWI_RELEASE_DIR`, so `test ! -e "$LEKIWI_RELEASE_DIR/../../fail-health"` fails
    /// for robots whose state directory holds a `fail-health` file.
    #[arg(long, default_value = "")]
    pub health_command: String,
    /// Pre-switch command.
    #[arg(long, default_value = "")]
    pub pre_switch_command: String,
    /// Seconds the health command may take to pass.
    #[arg(long, default_value_t = 30)]
    pub health_timeout_s: u64,
    /// Seconds between summary lines on stderr (0: none).
    #[arg(long, default_value_t = 5.0)]
    pub report_every: f64,
    /// Reconnect backoff cap, milliseconds.
    #[arg(long, default_value_t = 5000)]
    pub backoff_max_ms: u64,
    /// Seconds between a robot's CPU and network samples (synthetic readings; memory every
    /// 2×, temperature 6×, disk 12×, as the agent's defaults; sent on a change, as the agent
    /// does); 0: no telemetry.
    #[arg(long, default_value_t = 5)]
    pub telemetry_interval_s: u64,
    /// Seconds between a robot's telemetry batches (durable `telemetry` messages).
    #[arg(long, default_value_t = 60)]
    pub telemetry_batch_interval_s: u64,
}

/// The robot names of a fleet.
pub fn names(args: &Args) -> Vec<String> {
    (0..args.robots)
        .map(|i| format!("{}-{i:03}", args.prefix))
        .collect()
}

/// The configuration of one robot of the fleet.
pub fn robot_config(args: &Args, name: &str) -> Config {
    let config = Config {
        gateway: args.gateway.clone(),
        ca_file: args.ca_file.clone(),
        state_dir: args.state_root.join(name),
        robot_name: format!("{}/{name}", args.namespace),
        enrollment_token_file: Some(args.enrollment_token_file.clone()),
        backoff_initial_ms: 200,
        backoff_max_ms: args.backoff_max_ms,
        status_listen: "off".into(),
        mdns: false,
        release_restart_command: args.restart_command.clone(),
        release_health_command: args.health_command.clone(),
        release_pre_switch_command: args.pre_switch_command.clone(),
        release_health_timeout_s: args.health_timeout_s,
        ..Config::default()
    }
    // One machine, many robots: no per-robot vitals worth sampling here (see `run`).
    .without_sensors();
    if args.telemetry_interval_s == 0 {
        return config;
    }
    config.with_telemetry_every(args.telemetry_interval_s, args.telemetry_batch_interval_s)
}

/// Runs the fleet until `shutdown` completes.
pub async fn run(
    args: Args,
    shutdown: impl std::future::Future<Output = ()> + 'static,
) -> anyhow::Result<()> {
    let local = tokio::task::LocalSet::new();
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let mut statuses = Vec::new();
    let mut handles = Vec::new();
    for name in names(&args) {
        let config = robot_config(&args, &name);
        let mut agent = Agent::new(config.clone()).await?;
        if args.telemetry_interval_s > 0 {
            agent = agent.with_telemetry(Telemetry::synthetic(&config, &name));
        }
        statuses.push((name.clone(), agent.status()));
        let mut stop = stop_rx.clone();
        handles.push(local.spawn_local(async move {
            let stopped = async move {
                let _ = stop.wait_for(|s| *s).await;
            };
            if let Err(e) = agent.run(stopped).await {
                tracing::error!(robot = %name, error = %e, "agent stopped");
            }
        }));
    }
    info!(robots = statuses.len(), "fleet started");
    let every = args.report_every;
    local
        .run_until(async move {
            let report = async {
                if every <= 0.0 {
                    return std::future::pending().await;
                }
                let mut tick = tokio::time::interval(Duration::from_secs_f64(every));
                loop {
                    tick.tick().await;
                    eprintln!("{}", summary(&statuses));
                }
            };
            tokio::select! {
                () = shutdown => {}
                () = report => {}
            }
            let _ = stop_tx.send(true);
            for h in handles {
                let _ = h.await;
            }
        })
        .await;
    Ok(())
}

fn summary(statuses: &[(String, tokio::sync::watch::Receiver<StatusSnapshot>)]) -> String {
    let mut connected = 0;
    let mut releases: BTreeMap<String, usize> = BTreeMap::new();
    let mut pending = 0;
    for (_, rx) in statuses {
        let s = rx.borrow();
        connected += usize::from(s.connected);
        pending += s.outbox_pending;
        *releases
            .entry(
                s.release
                    .as_ref()
                    .map_or("-".to_owned(), |r| r.version.clone()),
            )
            .or_default() += 1;
    }
    format!(
        "fleet: {connected}/{} connected, outbox {pending}, releases {releases:?}",
        statuses.len()
    )
}
