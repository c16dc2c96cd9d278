//! Whether a gateway can be trusted with the robots it holds, read from the gateways' Leases:
//! a Lease renewed within its duration is a live gateway ([`lease_alive`], [`gateway_state`]);
//! the status lag a live one declares extends its robots' heartbeat grace ([`status_lag`]); and
//! a robot whose gateway's Lease expired is held back from `Unknown` while another gateway may
//! still claim it ([`renewal_wait`], [`late_write_wait`]). Pure reads of a Lease store; the
//! Robot controller applies them.

use std::sync::Arc;
use std::time::Duration;

use jiff::Timestamp;
use k8s_openapi::api::coordination::v1::Lease;
use kube::ResourceExt;
use kube::runtime::reflector::{ObjectRef, Store};
use lekiwi_crds::Robot;
use lekiwi_crds::contract::{GATEWAY_LEASE_LABEL, STATUS_LAG_ANNOTATION, managers};

use crate::GatewayState;

/// The end of a Lease's validity: its last renewal plus its duration (`None` without either).
pub fn valid_until(lease: &Lease) -> Option<Timestamp> {
    let spec = lease.spec.as_ref()?;
    let renew = spec.renew_time.as_ref()?.0;
    renew
        .checked_add(jiff::SignedDuration::from_secs(i64::from(
            spec.lease_duration_seconds?,
        )))
        .ok()
}

/// Whether a Lease has a holder and was renewed within its duration.
pub fn lease_alive(lease: &Lease, now: Timestamp) -> bool {
    lease
        .spec
        .as_ref()
        .and_then(|s| s.holder_identity.as_deref())
        .is_some_and(|h| !h.is_empty())
        && valid_until(lease).is_some_and(|end| now <= end)
}

pub fn gateway_state(
    store: &Store<Lease>,
    namespace: &str,
    gateway: &str,
    now: Timestamp,
) -> GatewayState {
    match store.get(&ObjectRef::new(gateway).within(namespace)) {
        Some(lease) if lease_alive(&lease, now) => GatewayState::Alive,
        _ => GatewayState::Gone,
    }
}

/// The status lag (see [`lekiwi_crds::contract::STATUS_LAG_ANNOTATION`]) that the live Lease of
/// `gateway` declares, at most `max`; zero for a dead or missing Lease, or a value that is not a
/// whole number of seconds.
pub fn status_lag(
    store: &Store<Lease>,
    namespace: &str,
    gateway: &str,
    now: Timestamp,
    max: Duration,
) -> Duration {
    store
        .get(&ObjectRef::new(gateway).within(namespace))
        .filter(|lease| lease_alive(lease, now))
        .and_then(|lease| {
            let value = lease.annotations().get(STATUS_LAG_ANNOTATION)?;
            value.parse::<u64>().ok().map(Duration::from_secs)
        })
        .unwrap_or_default()
        .min(max)
}

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
pub fn live_others<'a>(
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

/// A gateway's Lease in namespace `ops` for tests: held by `name`, 15 s long, renewed
/// `renewed_ago_s` seconds ago, resourceVersion `1`.
#[cfg(any(test, feature = "test-util"))]
pub fn test_lease(name: &str, renewed_ago_s: i64) -> Lease {
    use k8s_openapi::api::coordination::v1::LeaseSpec;
    use k8s_openapi::apimachinery::pkg::apis::meta::v1::MicroTime;
    Lease {
        metadata: kube::api::ObjectMeta {
            name: Some(name.into()),
            namespace: Some("ops".into()),
            resource_version: Some("1".into()),
            labels: Some(
                [(
                    lekiwi_crds::contract::GATEWAY_LEASE_LABEL.to_owned(),
                    "true".to_owned(),
                )]
                .into(),
            ),
            ..kube::api::ObjectMeta::default()
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

#[cfg(test)]
mod tests {
    use kube::runtime::{reflector, watcher};

    use super::*;

    fn lease(name: &str, version: &str, renewed_ago_s: i64) -> Lease {
        let mut lease = test_lease(name, renewed_ago_s);
        lease.metadata.resource_version = Some(version.into());
        lease
    }

    /// A live Lease's status lag counts, capped; a dead Lease's, a missing one's or a value
    /// that is not whole seconds does not.
    #[test]
    fn a_live_gateways_status_lag_extends_within_the_cap() {
        let (store, mut writer) = reflector::store::<Lease>();
        let annotated = |name: &str, renewed_ago_s: i64, lag: &str| {
            let mut l = lease(name, "1", renewed_ago_s);
            l.metadata.namespace = Some("ops".into());
            l.metadata.annotations =
                Some([(STATUS_LAG_ANNOTATION.to_owned(), lag.to_owned())].into());
            l
        };
        for l in [
            annotated("gw-late", 2, "120"),
            annotated("gw-very-late", 2, "5000"),
            annotated("gw-dead", 60, "120"),
            annotated("gw-garbled", 2, "2m"),
            annotated("gw-negative", 2, "-30"),
        ] {
            writer.apply_watcher_event(&watcher::Event::Apply(l));
        }
        let max = Duration::from_secs(900);
        let lag = |gw: &str| status_lag(&store, "ops", gw, Timestamp::now(), max).as_secs();
        assert_eq!(lag("gw-late"), 120);
        assert_eq!(lag("gw-very-late"), 900, "capped");
        assert_eq!(lag("gw-dead"), 0, "a dead gateway vouches for nothing");
        assert_eq!(lag("gw-garbled"), 0);
        assert_eq!(lag("gw-negative"), 0);
        assert_eq!(lag("gw-missing"), 0);
        assert_eq!(
            status_lag(&store, "lab", "gw-late", Timestamp::now(), max).as_secs(),
            0
        );
    }

    /// `Unknown` waits until every other live gateway renewed after the dead one expired.
    #[test]
    fn unknown_waits_for_the_live_gateways_next_renewal() {
        let (store, mut writer) = reflector::store::<Lease>();
        // gw-a: renewed 20 s ago for 15 s, expired 5 s ago.
        writer.apply_watcher_event(&watcher::Event::Apply(lease("gw-a", "1", 20)));
        // gw-b renewed 6 s ago (before the expiry), gw-c 1 s ago, gw-d is dead too.
        for (name, ago) in [("gw-b", 6), ("gw-c", 1), ("gw-d", 60)] {
            writer.apply_watcher_event(&watcher::Event::Apply(lease(name, "1", ago)));
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
        writer.apply_watcher_event(&watcher::Event::Apply(lease("gw-b", "2", 0)));
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
        writer.apply_watcher_event(&watcher::Event::Apply(lease("gw-a", "1", 60)));
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
