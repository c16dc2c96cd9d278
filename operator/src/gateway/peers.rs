//! The gateways' Leases as this gateway sees them. A robot that moves here from a gateway whose
//! Lease has expired is shown `Unknown` by the Robot controller (unless a claim of this gateway
//! reached it first), and this gateway's Robot watch can show that write a minute late on a
//! saturated API server: knowing the expiry itself, the gateway writes such a robot before the
//! moves that still show `Online` (see [`crate::gateway::presence::claims`]).

use futures::StreamExt;
use jiff::Timestamp;
use k8s_openapi::api::coordination::v1::Lease;
use kube::Api;
use kube::runtime::reflector::{ObjectRef, Store, store};
use kube::runtime::{WatchStreamExt, reflector, watcher};
use lekiwi_crds::contract::GATEWAY_LEASE_LABEL;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use crate::controller::robot::gateways::lease_alive;
use crate::gateway::presence::Presence;

/// The gateways' Leases of one namespace, listed and kept by a watch; cheap to clone.
#[derive(Clone)]
pub struct Peers {
    leases: Store<Lease>,
    namespace: String,
}

impl Peers {
    /// Peers over `leases`, the gateway Leases of `namespace`.
    pub fn new(leases: Store<Lease>, namespace: impl Into<String>) -> Self {
        Self {
            leases,
            namespace: namespace.into(),
        }
    }

    /// Whether gateway `name` is dead at `now` as the Robot controller reads it: its Lease is
    /// missing, has no holder, or was not renewed within its duration.
    pub fn dead(&self, name: &str, now: Timestamp) -> bool {
        self.leases
            .get(&ObjectRef::new(name).within(&self.namespace))
            .is_none_or(|lease| !lease_alive(&lease, now))
    }
}

/// Watches the gateway Leases (by their label) in `namespace` until `cancel` fires; once they
/// are listed, `presence` reads them (see [`Presence::watch_peers`]).
pub fn watch(
    client: kube::Client,
    namespace: String,
    presence: Presence,
    cancel: CancellationToken,
) -> JoinHandle<()> {
    tokio::spawn(async move {
        let api: Api<Lease> = Api::namespaced(client, &namespace);
        let (leases, writer) = store();
        let config = watcher::Config::default().labels(GATEWAY_LEASE_LABEL);
        let stream = reflector(writer, watcher(api, config))
            .default_backoff()
            .touched_objects()
            .for_each(|event| {
                if let Err(e) = event {
                    // Retried with backoff; meanwhile such robots wait for the Robot watch.
                    tracing::warn!(error = %e, "cannot watch the gateway Leases");
                }
                std::future::ready(())
            });
        // One task: aborting it ends the watch too.
        let listed = async {
            if leases.wait_until_ready().await.is_ok() {
                presence.watch_peers(Peers::new(leases.clone(), namespace));
            }
            std::future::pending::<()>().await;
        };
        tokio::select! {
            () = cancel.cancelled() => {}
            () = stream => {}
            () = listed => {}
        }
    })
}
