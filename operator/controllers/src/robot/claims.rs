//! Claims of live gateways on robots whose status still names a dead one: a gateway lists the
//! robots that moved to it and are not written yet in its Lease
//! ([`lekiwi_crds::contract::CLAIMS_ANNOTATION`]); the Robot controller does not mark those
//! `Unknown` (the claimant's status write, queued first, follows within seconds). A dropped
//! claim (the claimant's own Robot watch showed the write) still counts for [`RELEASED_GRACE`]:
//! this controller's Robot watch can be behind the claimant's.
//!
//! A write the dead gateway sent before it died can land after its Lease expired (an API server
//! answering seconds late). The gateway that holds the robot now claims it once its own watch
//! shows that write; until then, for at most [`LATE_WRITE_GRACE`], [`late_write_wait`] holds
//! the `Unknown` back.

use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Mutex};

use jiff::Timestamp;
use k8s_openapi::api::coordination::v1::Lease;
use kube::ResourceExt;
use kube::runtime::reflector::{ObjectRef, Store};
use lekiwi_crds::Robot;
use lekiwi_crds::contract::{CLAIMS_ANNOTATION, GATEWAY_LEASE_LABEL, managers, parse_claims};

use super::gateways::{lease_alive, valid_until};

/// How long after a gateway's status write that landed once its Lease had expired the robot
/// may still be claimed before it turns `Unknown`: the new gateway's watch, its Lease renewal
/// and the controller's Lease watch, on an API server that answers late.
pub const LATE_WRITE_GRACE: std::time::Duration = std::time::Duration::from_secs(30);

/// How long to wait before calling connected robot `robot` `Unknown` because its gateway's
/// Lease (in `leases`, namespace `namespace`) expired: `Some` while its status was last
/// written by a gateway after that Lease had expired (a request that outlived its sender),
/// for at most [`LATE_WRITE_GRACE`] after that write; the gateway now holding the robot claims
/// it meanwhile. The time of the write is the API server's, from the gateways' entry in the
/// managed fields.
pub fn late_write_wait(
    leases: &Store<Lease>,
    namespace: &str,
    robot: &Robot,
    now: Timestamp,
) -> Option<std::time::Duration> {
    let (_, expired) = connected_through_expired(leases, namespace, robot)?;
    let written = robot
        .metadata
        .managed_fields
        .iter()
        .flatten()
        .filter(|f| f.manager.as_deref() == Some(managers::GATEWAY))
        // API servers before 1.22 name no subresource.
        .filter(|f| f.subresource.as_deref().is_none_or(|s| s == "status"))
        .filter_map(|f| f.time.as_ref().map(|t| t.0))
        .max()?;
    if written <= expired {
        return None;
    }
    let until = written.checked_add(LATE_WRITE_GRACE).ok()?;
    let left = now.duration_until(until);
    (left.is_positive()).then(|| left.unsigned_abs())
}

/// How soon a robot of a dead gateway is looked at again while [`renewal_wait`] holds it.
const RENEWAL_RECHECK: std::time::Duration = std::time::Duration::from_secs(1);

/// How long to wait before calling connected robot `robot`, whose gateway's Lease (in
/// `leases`, namespace `namespace`) expired, `Unknown`: `Some` while another live gateway's Lease
/// was last renewed before that expiry. A gateway lists every robot that moved to it and is not
/// written yet in each renewal, so one renewed after the expiry claims every robot that
/// reconnected before it; without this wait a robot that reconnected in the last seconds before
/// the expiry turned `Unknown` when the renewal claiming it was still on its way (64 of 5,000 in
/// a kill benchmark). Bounded: a live gateway renews every third of its Lease, and one that
/// stops renewing is not live any more once its own Lease expires.
pub fn renewal_wait(
    leases: &Store<Lease>,
    namespace: &str,
    robot: &Robot,
    now: Timestamp,
) -> Option<std::time::Duration> {
    let (dead, expired) = connected_through_expired(leases, namespace, robot)?;
    live_others(leases, dead, now)
        .any(|l| {
            let renewed = l.spec.as_ref().and_then(|s| s.renew_time.as_ref());
            renewed.is_none_or(|t| t.0 < expired)
        })
        .then_some(RENEWAL_RECHECK)
}

/// The gateway a connected `robot`'s status names and when its Lease (in `leases`, namespace
/// `namespace`) stops or stopped being valid; `None` for a disconnected robot or a gateway
/// without a Lease.
fn connected_through_expired<'r>(
    leases: &Store<Lease>,
    namespace: &str,
    robot: &'r Robot,
) -> Option<(&'r str, Timestamp)> {
    let status = robot
        .status
        .as_ref()
        .filter(|s| s.connected == Some(true))?;
    let gateway = status.gateway.as_deref()?;
    let lease = leases.get(&ObjectRef::new(gateway).within(namespace))?;
    Some((gateway, valid_until(&lease)?))
}

/// The live gateway Leases of `leases` other than `holder`'s.
fn live_others<'a>(
    leases: &Store<Lease>,
    holder: &'a str,
    now: Timestamp,
) -> impl Iterator<Item = Arc<Lease>> + 'a {
    leases
        .state()
        .into_iter()
        .filter(|l| l.labels().contains_key(GATEWAY_LEASE_LABEL))
        .filter(move |l| l.name_any() != holder && lease_alive(l, now))
}

/// The claimed `namespace/name` entries of one Lease version (its resourceVersion).
type Parsed = (Option<String>, Arc<HashSet<String>>);

/// How long after a live gateway dropped its claim on a robot the robot still counts as claimed
/// by it. A gateway drops a claim once its own Robot watch shows its status write of the robot;
/// this controller's Robot watch can be behind that one (and a robot that leaves before its
/// write drops its claim at once): planning `Unknown` from the older status meanwhile would be
/// refused (409) at best, once per moved robot.
pub const RELEASED_GRACE: std::time::Duration = std::time::Duration::from_secs(30);

/// The claims of each gateway Lease, parsed once per Lease version, and the claims dropped
/// within [`RELEASED_GRACE`].
#[derive(Default)]
pub struct ClaimIndex {
    /// Lease name → (resourceVersion, claimed `namespace/name` entries).
    parsed: Mutex<HashMap<String, Parsed>>,
    /// `namespace/name` → (gateway, when this index saw its Lease drop the claim).
    released: Mutex<HashMap<String, (String, Timestamp)>>,
}

impl ClaimIndex {
    /// Notes the claims of a gateway Lease version the Lease watch brought. Without it only the
    /// versions read when a robot was looked at would be compared, and a claim made and
    /// dropped between two such looks (a robot that came back and left again before its
    /// write) would never count as dropped.
    pub fn observe(&self, lease: &Lease, now: Timestamp) {
        if lease.labels().contains_key(GATEWAY_LEASE_LABEL) {
            self.claims_of(lease, now);
        }
    }

    /// The live gateway other than `holder` whose Lease claims robot `namespace/name`, or
    /// dropped its claim less than [`RELEASED_GRACE`] ago, if any.
    pub fn claimant(
        &self,
        leases: &Store<Lease>,
        holder: &str,
        namespace: &str,
        name: &str,
        now: Timestamp,
    ) -> Option<String> {
        let robot = format!("{namespace}/{name}");
        let live: Vec<Arc<Lease>> = live_others(leases, holder, now).collect();
        // Every live Lease is read (and its dropped claims noted) before `released` is.
        if let Some(l) = live
            .iter()
            .find(|l| self.claims_of(l, now).contains(&robot))
        {
            return Some(l.name_any());
        }
        let released = self.released.lock().unwrap_or_else(|p| p.into_inner());
        let (gateway, at) = released.get(&robot)?;
        (within_grace(*at, now) && live.iter().any(|l| l.name_any() == *gateway))
            .then(|| gateway.clone())
    }

    /// The entries `lease` claims, parsed again only when its version changed; entries the
    /// new version no longer has are noted as dropped at `now`.
    fn claims_of(&self, lease: &Lease, now: Timestamp) -> Arc<HashSet<String>> {
        let name = lease.name_any();
        let version = lease.resource_version();
        let mut parsed = self.parsed.lock().unwrap_or_else(|p| p.into_inner());
        if let Some((seen, claims)) = parsed.get(&name)
            && *seen == version
        {
            return claims.clone();
        }
        let claims: Arc<HashSet<String>> = Arc::new(
            lease
                .annotations()
                .get(CLAIMS_ANNOTATION)
                .map(|v| parse_claims(v).collect())
                .unwrap_or_default(),
        );
        let before = parsed.insert(name.clone(), (version, claims.clone()));
        let mut released = self.released.lock().unwrap_or_else(|p| p.into_inner());
        released.retain(|robot, (_, at)| !claims.contains(robot) && within_grace(*at, now));
        for robot in before.iter().flat_map(|(_, old)| old.difference(&claims)) {
            released.insert(robot.clone(), (name.clone(), now));
        }
        claims
    }
}

/// Whether a claim dropped at `at` still counts at `now` (see [`RELEASED_GRACE`]).
fn within_grace(at: Timestamp, now: Timestamp) -> bool {
    now.duration_since(at).unsigned_abs() < RELEASED_GRACE
}

#[cfg(test)]
mod tests {
    use kube::runtime::{reflector, watcher};

    use super::*;

    fn lease(name: &str, version: &str, renewed_ago_s: i64, claims: Option<&str>) -> Lease {
        let mut lease = super::super::gateways::test_lease(name, renewed_ago_s);
        lease.metadata.resource_version = Some(version.into());
        lease.metadata.annotations =
            claims.map(|c| [(CLAIMS_ANNOTATION.to_owned(), c.to_owned())].into());
        lease
    }

    /// Only a live Lease of another gateway claims, and a new version of it is read again.
    #[test]
    fn a_live_gateways_claim_counts_until_it_drops_it() {
        let (store, mut writer) = reflector::store::<Lease>();
        for l in [
            lease("gw-a", "1", 60, Some("fleet/kiwi-3")),
            lease("gw-b", "1", 1, Some("fleet/kiwi-1,fleet/kiwi-2")),
            lease("gw-c", "1", 60, Some("fleet/kiwi-4")),
        ] {
            writer.apply_watcher_event(&watcher::Event::Apply(l));
        }
        let index = ClaimIndex::default();
        let now = Timestamp::now();
        let who = |robot: &str| index.claimant(&store, "gw-a", "fleet", robot, now);
        assert_eq!(who("kiwi-2").as_deref(), Some("gw-b"));
        assert_eq!(who("kiwi-3"), None, "the dead holder's own claim");
        assert_eq!(who("kiwi-4"), None, "a dead gateway's claim");
        assert_eq!(index.claimant(&store, "gw-a", "lab", "kiwi-2", now), None);
        // gw-b wrote kiwi-2 and renewed its Lease without it.
        writer.apply_watcher_event(&watcher::Event::Apply(lease(
            "gw-b",
            "2",
            0,
            Some("fleet/kiwi-1"),
        )));
        assert_eq!(who("kiwi-1").as_deref(), Some("gw-b"));
        // Its write may reach the Robot watch later than the Lease: held for the grace.
        assert_eq!(who("kiwi-2").as_deref(), Some("gw-b"), "dropped just now");
        // A later renewal (valid then) with the same claims; past the grace, kiwi-2 is free.
        writer.apply_watcher_event(&watcher::Event::Apply(lease(
            "gw-b",
            "3",
            -40,
            Some("fleet/kiwi-1"),
        )));
        let later = now + jiff::SignedDuration::from_secs(31);
        let at_later = |robot: &str| index.claimant(&store, "gw-a", "fleet", robot, later);
        assert_eq!(at_later("kiwi-2"), None, "dropped 31 s ago");
        assert_eq!(at_later("kiwi-1").as_deref(), Some("gw-b"));
    }

    /// A claim made and dropped while no robot was looked at still counts for the grace, if
    /// the Lease watch brought the version that had it.
    #[test]
    fn a_claim_the_watch_saw_counts_though_dropped_before_a_look() {
        let (store, mut writer) = reflector::store::<Lease>();
        let index = ClaimIndex::default();
        let now = Timestamp::now();
        for (version, claims) in [("1", None), ("2", Some("fleet/kiwi-1")), ("3", None)] {
            let l = lease("gw-b", version, 0, claims);
            index.observe(&l, now);
            writer.apply_watcher_event(&watcher::Event::Apply(l));
        }
        let who = |at: Timestamp| index.claimant(&store, "gw-a", "fleet", "kiwi-1", at);
        assert_eq!(who(now).as_deref(), Some("gw-b"));
        assert_eq!(who(now + jiff::SignedDuration::from_secs(31)), None);
        let unwatched = ClaimIndex::default();
        assert_eq!(
            unwatched.claimant(&store, "gw-a", "fleet", "kiwi-1", now),
            None,
            "a look alone sees only the latest version"
        );
    }

    /// `Unknown` waits until every other live gateway renewed after the dead one expired.
    #[test]
    fn unknown_waits_for_the_live_gateways_next_renewal() {
        let (store, mut writer) = reflector::store::<Lease>();
        // gw-a: renewed 20 s ago for 15 s, expired 5 s ago.
        writer.apply_watcher_event(&watcher::Event::Apply(lease("gw-a", "1", 20, None)));
        // gw-b renewed 6 s ago (before the expiry), gw-c 1 s ago, gw-d is dead too.
        for (name, ago) in [("gw-b", 6), ("gw-c", 1), ("gw-d", 60)] {
            writer.apply_watcher_event(&watcher::Event::Apply(lease(name, "1", ago, None)));
        }
        let now = Timestamp::now();
        let wait = |gateway: &str, connected: bool| {
            let mut r = Robot::new("kiwi-1", lekiwi_crds::RobotSpec::default());
            r.status = Some(lekiwi_crds::RobotStatus {
                connected: Some(connected),
                gateway: Some(gateway.into()),
                ..lekiwi_crds::RobotStatus::default()
            });
            renewal_wait(&store, "ops", &r, now)
        };
        assert_eq!(
            wait("gw-a", true),
            Some(RENEWAL_RECHECK),
            "gw-b not renewed since"
        );
        assert_eq!(wait("gw-a", false), None, "a disconnected robot");
        writer.apply_watcher_event(&watcher::Event::Apply(lease("gw-b", "2", 0, None)));
        assert_eq!(wait("gw-a", true), None, "every live gateway renewed since");
        assert_eq!(wait("gw-x", true), None, "no Lease: no expiry to wait past");
    }

    /// A connected robot's status written by its gateway after that gateway's Lease expired
    /// holds `Unknown` back for at most the grace after the write; a write from before the
    /// expiry, another manager's, or a disconnected robot's does not.
    #[test]
    fn a_write_landing_after_the_lease_expired_waits_for_a_claim() {
        use k8s_openapi::apimachinery::pkg::apis::meta::v1::{ManagedFieldsEntry, Time};
        use lekiwi_crds::{RobotSpec, RobotStatus};

        let (store, mut writer) = reflector::store::<Lease>();
        // Renewed 60 s ago for 15 s: expired 45 s ago.
        writer.apply_watcher_event(&watcher::Event::Apply(lease("gw-a", "1", 60, None)));
        let now = Timestamp::now();
        let robot = |manager: &str, written_ago_s: i64, connected: bool| {
            let mut r = Robot::new("kiwi-1", RobotSpec::default());
            r.metadata.namespace = Some("fleet".into());
            r.metadata.managed_fields = Some(vec![ManagedFieldsEntry {
                manager: Some(manager.into()),
                operation: Some("Apply".into()),
                subresource: Some("status".into()),
                time: Some(Time(now - jiff::SignedDuration::from_secs(written_ago_s))),
                ..ManagedFieldsEntry::default()
            }]);
            r.status = Some(RobotStatus {
                connected: Some(connected),
                gateway: Some("gw-a".into()),
                ..RobotStatus::default()
            });
            r
        };
        let wait = |r: &Robot| late_write_wait(&store, "ops", r, now);
        let waited = wait(&robot(managers::GATEWAY, 10, true)).expect("a late write waits");
        assert!(
            waited.as_secs() >= 19 && waited.as_secs() <= 20,
            "{waited:?}"
        );
        assert_eq!(
            wait(&robot(managers::GATEWAY, 50, true)),
            None,
            "written before"
        );
        assert_eq!(
            wait(&robot(managers::GATEWAY, 40, true)),
            None,
            "grace over"
        );
        assert_eq!(
            wait(&robot(managers::GATEWAY, 10, false)),
            None,
            "disconnected"
        );
        assert_eq!(
            wait(&robot("someone-else", 10, true)),
            None,
            "not a gateway"
        );
    }
}
