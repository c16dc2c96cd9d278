//! Claims of live gateways on robots whose status still names a dead one: a gateway lists the
//! robots that moved to it and are not written yet in its Lease
//! ([`lekiwi_crds::contract::CLAIMS_ANNOTATION`]); the Robot controller does not mark those
//! `Unknown` (the claimant's status write, queued first, follows within seconds).

use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Mutex};

use jiff::Timestamp;
use k8s_openapi::api::coordination::v1::Lease;
use kube::ResourceExt;
use kube::runtime::reflector::Store;
use lekiwi_crds::contract::{CLAIMS_ANNOTATION, GATEWAY_LEASE_LABEL, parse_claims};

use super::gateways::lease_alive;

/// The claimed `namespace/name` entries of one Lease version (its resourceVersion).
type Parsed = (Option<String>, Arc<HashSet<String>>);

/// The claims of each gateway Lease, parsed once per Lease version.
#[derive(Default)]
pub struct ClaimIndex {
    /// Lease name → (resourceVersion, claimed `namespace/name` entries).
    parsed: Mutex<HashMap<String, Parsed>>,
}

impl ClaimIndex {
    /// The live gateway other than `holder` whose Lease claims robot `namespace/name`, if any.
    pub fn claimant(
        &self,
        leases: &Store<Lease>,
        holder: &str,
        namespace: &str,
        name: &str,
        now: Timestamp,
    ) -> Option<String> {
        let robot = format!("{namespace}/{name}");
        leases
            .state()
            .iter()
            .filter(|l| l.labels().contains_key(GATEWAY_LEASE_LABEL))
            .filter(|l| l.name_any() != holder && lease_alive(l, now))
            .find(|l| self.claims_of(l).contains(&robot))
            .map(|l| l.name_any())
    }

    /// The entries `lease` claims, parsed again only when its version changed.
    fn claims_of(&self, lease: &Lease) -> Arc<HashSet<String>> {
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
        parsed.insert(name, (version, claims.clone()));
        claims
    }
}

#[cfg(test)]
mod tests {
    use k8s_openapi::api::coordination::v1::LeaseSpec;
    use k8s_openapi::apimachinery::pkg::apis::meta::v1::MicroTime;
    use kube::api::ObjectMeta;
    use kube::runtime::{reflector, watcher};

    use super::*;

    fn lease(name: &str, version: &str, renewed_ago_s: i64, claims: Option<&str>) -> Lease {
        Lease {
            metadata: ObjectMeta {
                name: Some(name.into()),
                namespace: Some("ops".into()),
                resource_version: Some(version.into()),
                labels: Some([(GATEWAY_LEASE_LABEL.to_owned(), "true".to_owned())].into()),
                annotations: claims.map(|c| [(CLAIMS_ANNOTATION.to_owned(), c.to_owned())].into()),
                ..ObjectMeta::default()
            },
            spec: Some(LeaseSpec {
                holder_identity: Some(name.into()),
                lease_duration_seconds: Some(15),
                renew_time: Some(MicroTime(
                    Timestamp::now() - jiff::SignedDuration::from_secs(renewed_ago_s),
                )),
                ..LeaseSpec::default()
            }),
        }
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
        assert_eq!(who("kiwi-2"), None);
        assert_eq!(who("kiwi-1").as_deref(), Some("gw-b"));
    }
}
