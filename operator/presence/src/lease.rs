//! The gateway's own Lease: renewed while the gateway lives, so the Robot controller can tell
//! that robots held by a dead gateway are Unknown; it also carries the gateway's claims (robots
//! that moved here and are not written yet, see [`crate::claims`]) and how
//! late its status writes run (see [`crate::Presence::status_lag`]).

use std::time::{Duration, Instant};

use jiff::Timestamp;
use k8s_openapi::api::coordination::v1::{Lease, LeaseSpec};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::MicroTime;
use kube::Api;
use kube::api::{ObjectMeta, Patch, PatchParams};
use std::collections::BTreeMap;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use lekiwi_crds::contract::{
    CLAIMS_ANNOTATION, GATEWAY_LEASE_LABEL, STATUS_LAG_ANNOTATION, managers,
};

use crate::{Presence, status_lag_annotation};

/// Shortest time between two renewals: a robot moving here renews the Lease early (its claim
/// must be seen before the dead gateway's Lease expires), at most this often.
const MIN_RENEW_GAP: Duration = Duration::from_secs(1);
/// A status lag above this is logged as a warning, at most once per [`LAG_WARN_EVERY`].
const LAG_WARN: Duration = Duration::from_secs(30);
const LAG_WARN_EVERY: Duration = Duration::from_secs(60);

/// The Lease's annotations from `presence` (`None` when it has none: server-side apply then
/// removes those it set before), and its status lag.
fn annotations(presence: Option<&Presence>) -> (Option<BTreeMap<String, String>>, Duration) {
    let Some(p) = presence else {
        return (None, Duration::ZERO);
    };
    let lag = p.status_lag();
    let mut out = BTreeMap::new();
    if let Some(claims) = p.claims_annotation() {
        out.insert(CLAIMS_ANNOTATION.to_owned(), claims);
    }
    if let Some(value) = status_lag_annotation(lag) {
        out.insert(STATUS_LAG_ANNOTATION.to_owned(), value);
    }
    ((!out.is_empty()).then_some(out), lag)
}

/// Warns (at most once per [`LAG_WARN_EVERY`]) while status writes run more than [`LAG_WARN`]
/// late, and says when they caught up again.
fn report_lag(lag: Duration, warned: &mut Option<Instant>) {
    if lag > LAG_WARN {
        if warned.is_none_or(|t| t.elapsed() >= LAG_WARN_EVERY) {
            warn!(
                lag_seconds = lag.as_secs(),
                "status writes run late: the API server takes fewer writes than this gateway's \
                 robots need; the Robot controller extends their heartbeat grace by the lag (see \
                 --max-status-lag-seconds)"
            );
            *warned = Some(Instant::now());
        }
    } else if lag.is_zero() && warned.take().is_some() {
        info!("status writes caught up");
    }
}

/// Renews `namespace/name` every third of `duration` (and, at most every [`MIN_RENEW_GAP`],
/// when a robot moved here) until cancelled, with the claims of `presence` in its annotation.
pub async fn renew(
    client: kube::Client,
    namespace: String,
    name: String,
    duration: Duration,
    presence: Option<Presence>,
    cancel: CancellationToken,
) {
    let api: Api<Lease> = Api::namespaced(client, &namespace);
    let period = (duration / 3).max(Duration::from_millis(500));
    let mut acquired: Option<MicroTime> = None;
    let mut warned = None;
    loop {
        let now = MicroTime(Timestamp::now());
        let (annotations, lag) = annotations(presence.as_ref());
        report_lag(lag, &mut warned);
        let lease = Lease {
            metadata: ObjectMeta {
                name: Some(name.clone()),
                labels: Some(BTreeMap::from([(
                    GATEWAY_LEASE_LABEL.to_owned(),
                    "true".to_owned(),
                )])),
                annotations,
                ..ObjectMeta::default()
            },
            spec: Some(LeaseSpec {
                holder_identity: Some(name.clone()),
                lease_duration_seconds: Some(duration.as_secs().max(1) as i32),
                acquire_time: Some(acquired.clone().unwrap_or_else(|| now.clone())),
                renew_time: Some(now.clone()),
                ..LeaseSpec::default()
            }),
        };
        match api
            .patch(
                &name,
                &PatchParams::apply(managers::GATEWAY).force(),
                &Patch::Apply(&lease),
            )
            .await
        {
            Ok(_) => {
                acquired = acquired.or(Some(now));
                if let Some(p) = &presence {
                    p.lease_renewed(duration);
                }
            }
            Err(e) => warn!(lease = %name, error = %e, "cannot renew the gateway Lease"),
        }
        let moved = async {
            match &presence {
                Some(p) => p.claims_changed().await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            () = cancel.cancelled() => return,
            () = tokio::time::sleep(period) => {}
            () = moved => tokio::time::sleep(MIN_RENEW_GAP).await,
        }
    }
}
