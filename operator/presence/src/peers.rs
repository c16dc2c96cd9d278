//! The robots the Robot controller marked `Unknown` after another gateway died, as that
//! gateway's Lease lists them ([`lekiwi_crds::contract::MARKED_ANNOTATION`]). This gateway
//! watches the gateway Leases of its namespace: a robot listed there whose session is here and
//! not written yet is shown `Unknown` although connected, and its write goes before every
//! other waiting one ([`Presence::marked`]). The Robot watch tells the same, but a saturated
//! API server runs it a minute late (it carries every status write of the fleet); the Lease
//! watch carries a few events a second.

use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Mutex};

use futures::StreamExt;
use k8s_openapi::api::coordination::v1::Lease;
use kube::runtime::{WatchStreamExt, watcher};
use kube::{Api, ResourceExt};
use lekiwi_crds::contract::{GATEWAY_LEASE_LABEL, MARKED_ANNOTATION, parse_claims};
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tracing::{debug, warn};

use super::Presence;
use lekiwi_core::RobotKey;

/// The robots each other gateway's Lease lists as marked `Unknown`; cheap to clone.
#[derive(Clone, Default)]
pub struct Peers(Arc<Mutex<HashMap<String, HashSet<RobotKey>>>>);

impl Peers {
    /// Whether the Lease of gateway `gateway` lists robot `key` as marked `Unknown`.
    pub fn is_marked(&self, gateway: &str, key: &RobotKey) -> bool {
        let all = self.0.lock().unwrap_or_else(|p| p.into_inner());
        all.get(gateway).is_some_and(|keys| keys.contains(key))
    }

    /// Takes `lease`'s list (none when it lists none); returns the robots new to it.
    pub(crate) fn update(&self, lease: &Lease) -> Vec<RobotKey> {
        let listed = marked_in(lease);
        let mut all = self.0.lock().unwrap_or_else(|p| p.into_inner());
        let old = all.remove(&lease.name_any()).unwrap_or_default();
        let new = listed.difference(&old).cloned().collect();
        if !listed.is_empty() {
            all.insert(lease.name_any(), listed);
        }
        new
    }

    /// Forgets a deleted Lease's list.
    fn remove(&self, lease: &Lease) {
        let mut all = self.0.lock().unwrap_or_else(|p| p.into_inner());
        all.remove(&lease.name_any());
    }

    /// Forgets the lists of the Leases a new list of them did not hold (`listed`).
    fn keep_only(&self, listed: &HashSet<String>) {
        let mut all = self.0.lock().unwrap_or_else(|p| p.into_inner());
        all.retain(|gateway, _| listed.contains(gateway));
    }
}

/// The robots `lease` lists as marked `Unknown`.
fn marked_in(lease: &Lease) -> HashSet<RobotKey> {
    let Some(value) = lease.annotations().get(MARKED_ANNOTATION) else {
        return HashSet::new();
    };
    parse_claims(value)
        .filter_map(|entry| {
            let (ns, name) = entry.split_once('/')?;
            Some(RobotKey::new(ns, name))
        })
        .collect()
}

/// Watches the gateway Leases (by their label) of `namespace` other than gateway `own`'s until
/// `cancel` fires, telling `presence` of each robot a Lease newly lists as marked `Unknown`.
pub fn watch(
    client: kube::Client,
    namespace: String,
    own: String,
    presence: Presence,
    cancel: CancellationToken,
) -> JoinHandle<()> {
    let peers = presence.peers().clone();
    tokio::spawn(async move {
        let api: Api<Lease> = Api::namespaced(client, &namespace);
        let config = lekiwi_core::api_client::watch_config().labels(GATEWAY_LEASE_LABEL);
        let events = watcher(api, config).default_backoff();
        let mut events = std::pin::pin!(events);
        // The Leases of a list in progress (the watch lists again after it broke off).
        let mut relisted: HashSet<String> = HashSet::new();
        loop {
            let event = tokio::select! {
                () = cancel.cancelled() => return,
                e = events.next() => e,
            };
            let lease = match event {
                None => return,
                // Retried with backoff; meanwhile the Robot watch tells what the Leases would.
                Some(Err(e)) => {
                    warn!(error = %e, "cannot watch the gateway Leases");
                    continue;
                }
                Some(Ok(watcher::Event::Apply(l))) => l,
                Some(Ok(watcher::Event::InitApply(l))) => {
                    relisted.insert(l.name_any());
                    l
                }
                Some(Ok(watcher::Event::Delete(l))) => {
                    peers.remove(&l);
                    continue;
                }
                Some(Ok(watcher::Event::Init)) => {
                    relisted.clear();
                    continue;
                }
                Some(Ok(watcher::Event::InitDone)) => {
                    peers.keep_only(&relisted);
                    continue;
                }
            };
            let gateway = lease.name_any();
            if gateway == own {
                continue;
            }
            for key in peers.update(&lease) {
                if presence.marked(&key, &gateway) {
                    debug!(robot = %key, %gateway, "the robot is marked Unknown while its session here is live; writing it first");
                }
            }
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use lekiwi_liveness::gateways::test_lease;

    /// A Lease's list is read whole each time: new robots are reported once, a Lease that lists
    /// none (or is deleted) forgets its robots.
    #[test]
    fn each_lease_version_replaces_its_list() {
        let peers = Peers::default();
        let mut lease = test_lease("gw-a", 60);
        let key = |n: &str| RobotKey::new("lab", n);
        let list = |lease: &mut Lease, value: &str| {
            lease.metadata.annotations =
                Some([(MARKED_ANNOTATION.to_owned(), value.to_owned())].into());
        };
        list(&mut lease, "lab/r1,r2,other/r3");
        let mut new = peers.update(&lease);
        new.sort_by(|a, b| a.name.cmp(&b.name));
        assert_eq!(new, [key("r1"), key("r2"), RobotKey::new("other", "r3")]);
        assert!(peers.is_marked("gw-a", &key("r2")));
        assert!(
            !peers.is_marked("gw-b", &key("r2")),
            "listed by another gateway"
        );
        list(&mut lease, "lab/r2,r4");
        assert_eq!(peers.update(&lease), [key("r4")]);
        assert!(!peers.is_marked("gw-a", &key("r1")), "left the list");
        lease.metadata.annotations = None;
        assert!(peers.update(&lease).is_empty());
        assert!(!peers.is_marked("gw-a", &key("r2")));
        list(&mut lease, "lab/r5");
        peers.update(&lease);
        peers.remove(&lease);
        assert!(!peers.is_marked("gw-a", &key("r5")));
        peers.update(&lease);
        peers.keep_only(&HashSet::from(["gw-b".to_owned()]));
        assert!(
            !peers.is_marked("gw-a", &key("r5")),
            "not in a new list of the Leases"
        );
    }
}
