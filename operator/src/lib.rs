//! The LeKiwi fleet operator: wires the Kubernetes client, leader election, controllers and the
//! HTTP endpoints together and runs them until a signal.

pub mod config;
pub mod crd_install;
pub mod error;
pub mod http;
pub mod leader;
pub mod telemetry;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use kube::config::{KubeConfigOptions, Kubeconfig};
use kube::runtime::events::{Recorder, Reporter};
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tracing::{error, info};

use crate::config::Config;
pub use crate::error::{Error, Result};
use axum::http::{HeaderValue, header::USER_AGENT};
use clap::ValueEnum;
use lekiwi_controllers::Context;
use lekiwi_metrics::Metrics;

/// Builds a client from `--kubeconfig`/`--context`, `$KUBECONFIG`, `~/.kube/config` or the
/// in-cluster service account, in that order; its requests name this process by
/// [`user_agent`].
pub async fn client(config: &Config, identity: &str) -> Result<kube::Client> {
    let options = KubeConfigOptions {
        context: config.context.clone(),
        ..KubeConfigOptions::default()
    };
    let mut kube_config = match (&config.kubeconfig, &config.context) {
        (Some(path), _) => {
            let kc = Kubeconfig::read_from(path)
                .map_err(|e| Error::KubeConfig(format!("{}: {e}", path.display())))?;
            kube::Config::from_custom_kubeconfig(kc, &options)
                .await
                .map_err(|e| Error::KubeConfig(e.to_string()))?
        }
        (None, Some(_)) => kube::Config::from_kubeconfig(&options)
            .await
            .map_err(|e| Error::KubeConfig(e.to_string()))?,
        (None, None) => kube::Config::infer()
            .await
            .map_err(|e| Error::KubeConfig(e.to_string()))?,
    };
    kube_config
        .headers
        .push((USER_AGENT, user_agent(config, identity)));
    kube::Client::try_from(kube_config).map_err(|e| Error::KubeConfig(e.to_string()))
}

/// `lekiwi-operator/<version> (<role>; <identity>)`: the API server's audit log and request
/// logs tell the replicas (and the controller from a gateway) apart by it.
fn user_agent(config: &Config, identity: &str) -> HeaderValue {
    let role = config.role.to_possible_value();
    let role = role.as_ref().map_or("?", |v| v.get_name());
    let product = format!("lekiwi-operator/{}", env!("CARGO_PKG_VERSION"));
    HeaderValue::from_str(&format!("{product} ({role}; {identity})"))
        .or_else(|_| HeaderValue::from_str(&format!("{product} ({role})")))
        .unwrap_or_else(|_| HeaderValue::from_static("lekiwi-operator"))
}

/// Every long-lived task reports its name and outcome; the first to end stops the rest.
type Tasks = tokio::task::JoinSet<(&'static str, Result<()>)>;

/// What the long-lived tasks of one process share.
struct Process {
    config: Arc<Config>,
    identity: String,
    client: kube::Client,
    metrics: Metrics,
    cancel: CancellationToken,
}

/// Runs the operator until SIGTERM/SIGINT; returns an error if a long-lived task dies.
pub async fn run(config: Config) -> Result<()> {
    let config = Arc::new(config);
    let identity = config.identity();
    let client = client(&config, &identity).await?;
    crd_install::ensure(client.clone(), config.install_crds).await?;
    let shared = Process {
        identity,
        metrics: Metrics::new(config.per_robot_metrics),
        cancel: CancellationToken::new(),
        config,
        client,
    };
    let (leader_tx, leader_rx) = watch::channel(false);
    let ready = Arc::new(AtomicBool::new(false));
    let gateway_ready = shared
        .config
        .runs_gateway()
        .then(|| Arc::new(AtomicBool::new(false)));
    let mut tasks = Tasks::new();
    let app = http::router(http::HttpState {
        metrics: shared.metrics.clone(),
        ready: ready.clone(),
        leader: leader_rx.clone(),
        gateway_ready: gateway_ready.clone(),
    });
    serve_http(&shared, app, &mut tasks).await?;
    if shared.config.runs_controllers() {
        start_controllers(&shared, leader_tx, leader_rx.clone(), &mut tasks);
    }
    if shared.config.runs_gateway() {
        // Without leader election (`--role gateway`) the gateway collects blobs on its own.
        let leader = if shared.config.runs_controllers() {
            leader_rx.clone()
        } else {
            watch::channel(true).1
        };
        start_gateway(
            &shared,
            gateway_ready.unwrap_or_default(),
            leader,
            &mut tasks,
        )
        .await?;
    }
    tokio::spawn(shutdown_on_signal(shared.cancel.clone()));
    ready.store(true, Ordering::Release);
    let config = &shared.config;
    info!(identity = %shared.identity, namespace = %config.namespace, role = ?config.role, "lekiwi-operator started");
    let outcome = wait_first_end(&shared.cancel, &mut tasks).await;
    shared.cancel.cancel();
    ready.store(false, Ordering::Release);
    drain(tasks).await;
    info!("lekiwi-operator stopped");
    outcome
}

/// Binds the HTTP address and serves /metrics, /healthz and /readyz until cancelled.
async fn serve_http(shared: &Process, app: axum::Router, tasks: &mut Tasks) -> Result<()> {
    let addr = shared.config.http_addr;
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .map_err(|source| Error::Serve { addr, source })?;
    info!(addr = %listener.local_addr().map(|a| a.to_string()).unwrap_or_default(), "serving /metrics, /healthz and /readyz");
    let cancel = shared.cancel.clone();
    tasks.spawn(async move {
        let served = axum::serve(listener, app)
            .with_graceful_shutdown(async move { cancel.cancelled().await })
            .await
            .map_err(|source| Error::Serve { addr, source });
        ("http server", served)
    });
    Ok(())
}

/// Campaigns for the leader Lease and runs the controllers while this replica leads.
fn start_controllers(
    shared: &Process,
    leader_tx: watch::Sender<bool>,
    leader_rx: watch::Receiver<bool>,
    tasks: &mut Tasks,
) {
    let config = &shared.config;
    let elector = leader::LeaderElector::new(
        shared.client.clone(),
        &config.namespace,
        &config.leader_lease,
        shared.identity.clone(),
        config.lease_duration(),
        config.lease_retry(),
    );
    let (metrics, cancel) = (shared.metrics.clone(), shared.cancel.clone());
    tasks.spawn(async move {
        elector.run(leader_tx, metrics, cancel).await;
        ("leader election", Ok(()))
    });
    let recorder = Recorder::new(
        shared.client.clone(),
        Reporter {
            controller: "lekiwi-operator".into(),
            instance: Some(shared.identity.clone()),
        },
    );
    let ctx = Arc::new(Context::new(
        shared.client.clone(),
        recorder,
        shared.metrics.clone(),
        Arc::new(config.controller_settings()),
    ));
    let cancel = shared.cancel.clone();
    tasks.spawn(async move {
        (
            "controllers",
            run_while_leader(ctx, leader_rx, cancel).await,
        )
    });
}

/// Connects the event store and runs the gateway; `listening` turns true once it accepts.
async fn start_gateway(
    shared: &Process,
    listening: Arc<AtomicBool>,
    leader: watch::Receiver<bool>,
    tasks: &mut Tasks,
) -> Result<()> {
    let store = lekiwi_event_store::Store::connect(&shared.config.store_url)
        .await?
        .with_quota(shared.config.robot_quota());
    info!(backend = store.backend(), "event store ready");
    let (config, client, metrics, cancel) = (
        Arc::new(shared.config.gateway_settings()),
        shared.client.clone(),
        shared.metrics.clone(),
        shared.cancel.clone(),
    );
    tasks.spawn(async move {
        (
            "gateway",
            lekiwi_gateway::run(config, client, metrics, store, (listening, leader), cancel)
                .await
                .map_err(Error::from),
        )
    });
    Ok(())
}

/// Waits for a signal or for the first task to end; a task ending on its own is an error.
async fn wait_first_end(cancel: &CancellationToken, tasks: &mut Tasks) -> Result<()> {
    tokio::select! {
        biased;
        () = cancel.cancelled() => Ok(()),
        Some(joined) = tasks.join_next() => match joined {
            // A task that ends cleanly because we are stopping is fine; on its own it is not.
            Ok((_, Ok(()))) if cancel.is_cancelled() => Ok(()),
            Ok((name, Ok(()))) => Err(Error::TaskStopped(name)),
            Ok((_, Err(e))) => Err(e),
            Err(_) => Err(Error::TaskStopped("a task panicked")),
        },
    }
}

/// Lets the controllers drain, the Lease be released, the gateway flush and HTTP close, for
/// at most 10 s.
async fn drain(mut tasks: Tasks) {
    let drained = tokio::time::timeout(std::time::Duration::from_secs(10), async {
        while tasks.join_next().await.is_some() {}
    })
    .await;
    if drained.is_err() {
        tracing::warn!("shutdown did not finish within 10s; exiting anyway");
    }
}

/// Starts the controllers whenever this replica leads and stops them when it no longer does.
async fn run_while_leader(
    ctx: Arc<Context>,
    mut leader: watch::Receiver<bool>,
    cancel: CancellationToken,
) -> Result<()> {
    loop {
        tokio::select! {
            () = cancel.cancelled() => return Ok(()),
            r = wait_leader(&mut leader, true) => if r.is_err() { return Ok(()) },
        }
        let term = cancel.child_token();
        let Some((ctx, leases)) =
            lekiwi_controllers::robot::watch_gateway_leases(&ctx, &term).await?
        else {
            return Ok(());
        };
        let _leases = tokio_util::task::AbortOnDropHandle::new(leases);
        let mut robot = tokio::spawn(lekiwi_controllers::robot::run(ctx.clone(), term.clone()));
        let mut rollout = tokio::spawn(lekiwi_controllers::deployment::run(
            ctx.clone(),
            term.clone(),
        ));
        let stopped = |r: Result<lekiwi_controllers::Result<()>, tokio::task::JoinError>,
                       what: &'static str| match r {
            Ok(Ok(())) if cancel.is_cancelled() => Ok(()),
            Ok(Err(e)) => Err(e.into()),
            _ => Err(Error::TaskStopped(what)),
        };
        tokio::select! {
            r = &mut robot => {
                term.cancel();
                let _ = rollout.await;
                return stopped(r, "robot controller");
            }
            r = &mut rollout => {
                term.cancel();
                let _ = robot.await;
                return stopped(r, "robot deployment controller");
            }
            _ = wait_leader(&mut leader, false) => {
                info!("no longer leader; stopping controllers");
                term.cancel();
                let _ = robot.await;
                let _ = rollout.await;
            }
            () = cancel.cancelled() => {
                let _ = robot.await;
                let _ = rollout.await;
                return Ok(());
            }
        }
    }
}

/// Waits until leadership equals `want`, without holding the watch guard across an await.
async fn wait_leader(
    leader: &mut watch::Receiver<bool>,
    want: bool,
) -> Result<(), watch::error::RecvError> {
    leader.wait_for(|l| *l == want).await.map(|_| ())
}

async fn shutdown_on_signal(cancel: CancellationToken) {
    let mut term = match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
        Ok(s) => s,
        Err(e) => {
            error!(error = %e, "cannot listen for SIGTERM");
            return;
        }
    };
    tokio::select! {
        _ = term.recv() => info!("SIGTERM received; shutting down"),
        _ = tokio::signal::ctrl_c() => info!("SIGINT received; shutting down"),
    }
    cancel.cancel();
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;

    /// The API server sees which process of the operator asks: role and identity, and still
    /// the product when the identity cannot go in a header.
    #[test]
    fn requests_name_the_role_and_identity() {
        let config = Config::try_parse_from(["lekiwi-operator", "--role", "gateway"]).unwrap();
        let version = env!("CARGO_PKG_VERSION");
        assert_eq!(
            user_agent(&config, "gw-b").to_str().unwrap(),
            format!("lekiwi-operator/{version} (gateway; gw-b)")
        );
        assert_eq!(
            user_agent(&config, "bad\nname").to_str().unwrap(),
            format!("lekiwi-operator/{version} (gateway)")
        );
    }
}
