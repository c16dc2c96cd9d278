//! The LeKiwi fleet operator: wires the Kubernetes client, leader election, controllers and the
//! HTTP endpoints together and runs them until a signal.

pub mod config;
pub mod controller;
pub mod crd_install;
pub mod error;
pub mod gateway;
pub mod http;
pub mod leader;
pub mod metrics;
pub mod telemetry;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use kube::config::{KubeConfigOptions, Kubeconfig};
use kube::runtime::events::{Recorder, Reporter};
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tracing::{error, info};

use crate::config::Config;
use crate::controller::Context;
pub use crate::error::{Error, Result};
use crate::metrics::Metrics;

/// Builds a client from `--kubeconfig`/`--context`, `$KUBECONFIG`, `~/.kube/config` or the
/// in-cluster service account, in that order.
pub async fn client(config: &Config) -> Result<kube::Client> {
    let options = KubeConfigOptions {
        context: config.context.clone(),
        ..KubeConfigOptions::default()
    };
    let kube_config = match (&config.kubeconfig, &config.context) {
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
    kube::Client::try_from(kube_config).map_err(|e| Error::KubeConfig(e.to_string()))
}

/// Runs the operator until SIGTERM/SIGINT; returns an error if a long-lived task dies.
pub async fn run(config: Config) -> Result<()> {
    let config = Arc::new(config);
    let identity = config.identity();
    let client = client(&config).await?;
    crd_install::ensure(client.clone(), config.install_crds).await?;

    let metrics = Metrics::new(config.per_robot_metrics);
    let cancel = CancellationToken::new();
    let (leader_tx, leader_rx) = watch::channel(false);
    let ready = Arc::new(AtomicBool::new(false));

    let listener = tokio::net::TcpListener::bind(config.http_addr)
        .await
        .map_err(|source| Error::Serve {
            addr: config.http_addr,
            source,
        })?;
    info!(addr = %listener.local_addr().map(|a| a.to_string()).unwrap_or_default(), "serving /metrics, /healthz and /readyz");
    let gateway_ready = config
        .runs_gateway()
        .then(|| Arc::new(AtomicBool::new(false)));
    let app = http::router(http::HttpState {
        metrics: metrics.clone(),
        ready: ready.clone(),
        leader: leader_rx.clone(),
        gateway_ready: gateway_ready.clone(),
    });
    // Every long-lived task reports its name and outcome; the first to end stops the rest.
    let mut tasks: tokio::task::JoinSet<(&'static str, Result<()>)> = tokio::task::JoinSet::new();
    let http_cancel = cancel.clone();
    let http_addr = config.http_addr;
    tasks.spawn(async move {
        let served = axum::serve(listener, app)
            .with_graceful_shutdown(async move { http_cancel.cancelled().await })
            .await
            .map_err(|source| Error::Serve {
                addr: http_addr,
                source,
            });
        ("http server", served)
    });

    if config.runs_controllers() {
        let elector = leader::LeaderElector::new(
            client.clone(),
            &config.namespace,
            &config.leader_lease,
            identity.clone(),
            config.lease_duration(),
            config.lease_retry(),
        );
        let (m, c) = (metrics.clone(), cancel.clone());
        tasks.spawn(async move {
            elector.run(leader_tx, m, c).await;
            ("leader election", Ok(()))
        });
        let recorder = Recorder::new(
            client.clone(),
            Reporter {
                controller: "lekiwi-operator".into(),
                instance: Some(identity.clone()),
            },
        );
        let ctx = Arc::new(Context::new(
            client.clone(),
            recorder,
            metrics.clone(),
            config.clone(),
        ));
        let c = cancel.clone();
        tasks.spawn(async move { ("controllers", run_while_leader(ctx, leader_rx, c).await) });
    }
    if config.runs_gateway() {
        let store = gateway::event_store::Store::connect(&config.store_url).await?;
        info!(backend = store.backend(), "event store ready");
        let (cfg, cl, m, c) = (
            config.clone(),
            client.clone(),
            metrics.clone(),
            cancel.clone(),
        );
        let listening = gateway_ready.clone().unwrap_or_default();
        tasks.spawn(async move {
            (
                "gateway",
                gateway::run(cfg, cl, m, store, listening, c).await,
            )
        });
    }

    tokio::spawn(shutdown_on_signal(cancel.clone()));
    ready.store(true, Ordering::Release);
    info!(%identity, namespace = %config.namespace, role = ?config.role, "lekiwi-operator started");

    let outcome = tokio::select! {
        biased;
        () = cancel.cancelled() => Ok(()),
        Some(joined) = tasks.join_next() => match joined {
            // A task that ends cleanly because we are stopping is fine; on its own it is not.
            Ok((_, Ok(()))) if cancel.is_cancelled() => Ok(()),
            Ok((name, Ok(()))) => Err(Error::TaskStopped(name)),
            Ok((_, Err(e))) => Err(e),
            Err(_) => Err(Error::TaskStopped("a task panicked")),
        },
    };
    cancel.cancel();
    ready.store(false, Ordering::Release);
    // Let the controllers drain, the Lease be released, the gateway flush and HTTP close.
    let drained = tokio::time::timeout(std::time::Duration::from_secs(10), async {
        while tasks.join_next().await.is_some() {}
    })
    .await;
    if drained.is_err() {
        tracing::warn!("shutdown did not finish within 10s; exiting anyway");
    }
    info!("lekiwi-operator stopped");
    outcome
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
        let mut robot = tokio::spawn(controller::robot::run(ctx.clone(), term.clone()));
        let mut rollout = tokio::spawn(controller::deployment::run(ctx.clone(), term.clone()));
        let stopped = |r: Result<Result<()>, tokio::task::JoinError>, what: &'static str| match r {
            Ok(Ok(())) if cancel.is_cancelled() => Ok(()),
            Ok(Err(e)) => Err(e),
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
