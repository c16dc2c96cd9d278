//! The robots this controller marked `Unknown` because their gateway died, listed on that
//! gateway's Lease ([`lekiwi_crds::contract::MARKED_ANNOTATION`]). A robot marked so may
//! reconnect through another gateway a moment later; that gateway writes it before its other
//! waiting robots once it knows the robot is shown `Unknown`, and its Lease watch (a few events)
//! tells it seconds after the mark, where its Robot watch (every status write of the fleet) can
//! run a minute late on a saturated API server.
//!
//! The list lives in memory (a restarted controller starts a new one) and is published once a
//! second when it changed; a robot leaves it once this controller's Robot watch shows its status
//! naming another gateway, and the whole list goes once the gateway's Lease is alive again.

use std::collections::{HashMap, HashSet};
use std::sync::Mutex;

use jiff::Timestamp;
use k8s_openapi::api::coordination::v1::Lease;
use kube::api::{Patch, PatchParams};
use kube::runtime::reflector::Store;
use kube::{Api, ResourceExt};
use lekiwi_crds::contract::{MARKED_ANNOTATION, MAX_MARKED_BYTES, encode_robot_list, managers};
use tracing::{debug, warn};

use super::gateways::ByGateway;
use crate::Context;
use lekiwi_liveness::gateways::lease_alive;

/// A robot: `(namespace, name)`.
type RobotId = (String, String);

/// The robots marked per dead gateway, and what was last published for it.
#[derive(Default)]
pub struct Marks(Mutex<Inner>);

#[derive(Default)]
struct Inner {
    /// Gateway → the robots marked through it.
    marked: HashMap<String, Marked>,
    /// Gateway → the resourceVersion of its live Lease when its list was last removed: not
    /// removed again until a later version (the Lease watch may be seconds behind).
    cleared: HashMap<String, Option<String>>,
}

/// The robots marked through one gateway, in the order marked.
#[derive(Default)]
struct Marked {
    robots: Vec<RobotId>,
    /// The annotation value last published (`None`: not published yet).
    published: Option<String>,
}

/// A change to make to a gateway's Lease: its new [`MARKED_ANNOTATION`] value, or `None` to
/// remove the annotation.
#[derive(Debug, PartialEq)]
struct Publish {
    gateway: String,
    value: Option<String>,
}

impl Marks {
    /// This controller wrote robot `namespace/name`, whose status names `gateway`, `Unknown`
    /// because that gateway's Lease expired.
    pub fn record(&self, gateway: &str, namespace: &str, name: &str) {
        let mut inner = self.0.lock().unwrap_or_else(|p| p.into_inner());
        let marked = inner.marked.entry(gateway.to_owned()).or_default();
        let id = (namespace.to_owned(), name.to_owned());
        if !marked.robots.contains(&id) {
            marked.robots.push(id);
        }
    }

    /// The Lease changes due at `now`: for each gateway with marks, the robots whose status
    /// (as this controller's Robot watch shows it) still names it (`holds`), when that list
    /// changed; the removal of the list from each live gateway's Lease in `leases` that carries
    /// one (marks of a gateway that came back are forgotten). A missing Lease changes nothing:
    /// it cannot carry the list, and must not be created for it.
    fn due(
        &self,
        leases: &[std::sync::Arc<Lease>],
        holds: impl Fn(&str, &RobotId) -> bool,
        now: Timestamp,
    ) -> Vec<Publish> {
        let mut inner = self.0.lock().unwrap_or_else(|p| p.into_inner());
        let Inner {
            marked: all,
            cleared,
        } = &mut *inner;
        let mut out = Vec::new();
        for lease in leases {
            let gateway = lease.name_any();
            if !lease_alive(lease, now) {
                continue;
            }
            all.remove(&gateway);
            let version = lease.resource_version();
            if lease.annotations().contains_key(MARKED_ANNOTATION)
                && cleared.get(&gateway) != Some(&version)
            {
                cleared.insert(gateway.clone(), version);
                out.push(Publish {
                    gateway,
                    value: None,
                });
            }
        }
        let present: HashSet<String> = leases.iter().map(|l| l.name_any()).collect();
        all.retain(|gateway, _| present.contains(gateway));
        cleared.retain(|gateway, _| present.contains(gateway));
        for (gateway, marked) in all.iter_mut() {
            marked.robots.retain(|id| holds(gateway, id));
            let (value, _) = encode_robot_list(
                marked
                    .robots
                    .iter()
                    .map(|(ns, n)| (ns.as_str(), n.as_str())),
                MAX_MARKED_BYTES,
            );
            if marked.published.as_deref() != Some(value.as_str()) {
                let value = (!value.is_empty()).then_some(value);
                out.push(Publish {
                    gateway: gateway.clone(),
                    value: value.clone(),
                });
                marked.published = Some(value.unwrap_or_default());
            }
        }
        all.retain(|_, marked| !marked.robots.is_empty());
        out
    }

    /// Publishes the changes due at `now` (see [`Marks::due`]) to the Leases of `leases`;
    /// `by_gateway` holds the robots whose status names each gateway. A change that fails is
    /// made again at the next call.
    pub(super) async fn publish(
        &self,
        ctx: &Context,
        leases: &Store<Lease>,
        by_gateway: &ByGateway,
        now: Timestamp,
    ) {
        let marked: Vec<String> = {
            let inner = self.0.lock().unwrap_or_else(|p| p.into_inner());
            inner.marked.keys().cloned().collect()
        };
        // The robots naming each gateway marked so far (none: no robot names it any more).
        let held: HashMap<&str, HashSet<(&str, &str)>> = marked
            .iter()
            .map(|gw| {
                let refs = by_gateway.get(gw).into_iter().flatten();
                let ids =
                    refs.map(|r| (r.namespace.as_deref().unwrap_or_default(), r.name.as_str()));
                (gw.as_str(), ids.collect())
            })
            .collect();
        // A gateway marked since `marked` was read keeps its robots until the next call.
        let holds = |gateway: &str, (ns, name): &RobotId| {
            held.get(gateway)
                .is_none_or(|ids| ids.contains(&(ns.as_str(), name.as_str())))
        };
        let due = self.due(&leases.state(), holds, now);
        let api: Api<Lease> = Api::namespaced(ctx.client.clone(), &ctx.config.namespace);
        for change in due {
            // A merge patch, not an apply: an apply would create a Lease deleted meanwhile.
            let patch = serde_json::json!({
                "metadata": { "annotations": { MARKED_ANNOTATION: change.value } }
            });
            let params = PatchParams {
                field_manager: Some(managers::ROBOT_CONTROLLER.to_owned()),
                ..PatchParams::default()
            };
            match api
                .patch(&change.gateway, &params, &Patch::Merge(&patch))
                .await
            {
                Ok(_) => {
                    debug!(gateway = %change.gateway, listed = change.value.is_some(), "published the robots marked Unknown")
                }
                Err(kube::Error::Api(e)) if e.code == 404 => {}
                Err(e) => {
                    warn!(gateway = %change.gateway, error = %e, "cannot publish the robots marked Unknown");
                    self.unpublished(&change.gateway);
                }
            }
        }
    }

    /// The last change for `gateway` did not land: make it again.
    fn unpublished(&self, gateway: &str) {
        let mut inner = self.0.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(marked) = inner.marked.get_mut(gateway) {
            marked.published = None;
        }
        inner.cleared.remove(gateway);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lekiwi_liveness::gateways::test_lease;
    use std::sync::Arc;

    /// Marks of a dead gateway are published once per change, in the order marked, without the
    /// robots its status no longer names; a live gateway's are dropped and removed from its
    /// Lease; a missing Lease gets nothing.
    #[test]
    fn marks_are_published_per_change_and_dropped_when_the_gateway_lives() {
        let marks = Marks::default();
        marks.record("dead", "lab", "r2");
        marks.record("dead", "lab", "r1");
        marks.record("dead", "lab", "r2");
        marks.record("missing", "lab", "r3");
        let dead = Arc::new(test_lease("dead", 60));
        let mut back = test_lease("back", 1);
        back.metadata.annotations =
            Some([(MARKED_ANNOTATION.to_owned(), "lab/x".to_owned())].into());
        let leases = [dead.clone(), Arc::new(back)];
        let now = Timestamp::now();
        let all = |_: &str, _: &RobotId| true;
        let due = marks.due(&leases, all, now);
        let publish = |gateway: &str, value: Option<&str>| Publish {
            gateway: gateway.to_owned(),
            value: value.map(str::to_owned),
        };
        assert_eq!(
            due,
            [publish("back", None), publish("dead", Some("lab/r2,r1"))]
        );
        assert!(
            marks.due(&leases, all, now).is_empty(),
            "unchanged: nothing again"
        );
        let mut renewed = (*leases[1]).clone();
        renewed.metadata.resource_version = Some("2".into());
        let renewed = [dead.clone(), Arc::new(renewed)];
        assert_eq!(
            marks.due(&renewed, all, now),
            [publish("back", None)],
            "a later version still carries it: removed again"
        );
        let leases = renewed;
        // r2 moved to another gateway: the list shrinks; then both did.
        let moved = |_: &str, id: &RobotId| id.1 != "r2";
        assert_eq!(
            marks.due(&leases, moved, now),
            [publish("dead", Some("lab/r1"))]
        );
        marks.unpublished("dead");
        assert_eq!(
            marks.due(&leases, moved, now),
            [publish("dead", Some("lab/r1"))]
        );
        assert_eq!(
            marks.due(&leases, |_, _| false, now),
            [publish("dead", None)]
        );
        assert!(marks.due(&leases, all, now).is_empty());
        // A new mark, then the gateway comes back: its list goes.
        marks.record("dead", "lab", "r4");
        assert_eq!(
            marks.due(&leases, all, now),
            [publish("dead", Some("lab/r4"))]
        );
        let alive = test_lease("dead", 1);
        assert!(
            marks.due(&[Arc::new(alive)], all, now).is_empty(),
            "no annotation seen on it"
        );
        assert!(marks.0.lock().unwrap().marked.is_empty());
    }
}
