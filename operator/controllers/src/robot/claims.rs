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
use kube::runtime::reflector::Store;
use lekiwi_crds::contract::{CLAIMS_ANNOTATION, GATEWAY_LEASE_LABEL, parse_claims};
use lekiwi_liveness::gateways::live_others;

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
        let mut lease = lekiwi_liveness::gateways::test_lease(name, renewed_ago_s);
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
}
