//! The LeKiwi fleet operator: wires the Kubernetes client, leader election, controllers and the
//! HTTP endpoints together and runs them until a signal.

pub mod config;
pub mod controller;
pub mod crds;
pub mod error;
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
    crds::ensure(client.clone(), config.install_crds).await?;

    let metrics = Metrics::default();
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
    let app = http::router(http::HttpState {
        metrics: metrics.clone(),
        ready: ready.clone(),
        leader: leader_rx.clone(),
    });
    let http_cancel = cancel.clone();
    let mut http_task = tokio::spawn(async move {
        axum::serve(listener, app)
            .with_graceful_shutdown(async move { http_cancel.cancelled().await })
            .await
    });

    let elector = leader::LeaderElector::new(
        client.clone(),
        &config.namespace,
        &config.leader_lease,
        identity.clone(),
        config.lease_duration(),
        config.lease_retry(),
    );
    let mut elector_task = tokio::spawn(elector.run(leader_tx, metrics.clone(), cancel.clone()));

    let recorder = Recorder::new(
        client.clone(),
        Reporter {
            controller: "lekiwi-operator".into(),
            instance: Some(identity.clone()),
        },
    );
    let ctx = Arc::new(Context::new(client, recorder, metrics, config.clone()));
    let mut controllers_task = tokio::spawn(run_while_leader(ctx, leader_rx, cancel.clone()));

    tokio::spawn(shutdown_on_signal(cancel.clone()));
    ready.store(true, Ordering::Release);
    info!(%identity, namespace = %config.namespace, "lekiwi-operator started");

    // Which task ended first; a finished JoinHandle must not be awaited again below.
    let (mut http_done, mut elector_done, mut controllers_done) = (false, false, false);
    let outcome = tokio::select! {
        biased;
        () = cancel.cancelled() => Ok(()),
        r = &mut http_task => {
            http_done = true;
            match r {
                // The server closes as soon as the token fires; that is a clean stop.
                Ok(Ok(())) if cancel.is_cancelled() => Ok(()),
                Ok(Err(source)) => Err(Error::Serve { addr: config.http_addr, source }),
                _ => Err(Error::TaskStopped("http server")),
            }
        }
        _ = &mut elector_task => {
            elector_done = true;
            if cancel.is_cancelled() { Ok(()) } else { Err(Error::TaskStopped("leader election")) }
        }
        r = &mut controllers_task => {
            controllers_done = true;
            match r {
                Ok(Ok(())) if cancel.is_cancelled() => Ok(()),
                Ok(Err(e)) => Err(e),
                _ => Err(Error::TaskStopped("controllers")),
            }
        }
    };
    cancel.cancel();
    ready.store(false, Ordering::Release);
    // Let the controllers drain, the Lease be released and the HTTP server close.
    let drained = tokio::time::timeout(std::time::Duration::from_secs(10), async {
        if !controllers_done {
            let _ = controllers_task.await;
        }
        if !elector_done {
            let _ = elector_task.await;
        }
        if !http_done {
            let _ = http_task.await;
        }
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
        tokio::select! {
            r = &mut robot => {
                return match r {
                    Ok(Ok(())) if cancel.is_cancelled() => Ok(()),
                    Ok(Err(e)) => Err(e),
                    _ => Err(Error::TaskStopped("robot controller")),
                };
            }
            _ = wait_leader(&mut leader, false) => {
                info!("no longer leader; stopping controllers");
                term.cancel();
                let _ = robot.await;
            }
            () = cancel.cancelled() => {
                let _ = robot.await;
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
