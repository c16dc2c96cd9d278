//! The gateway's own Lease: renewed while the gateway lives, so the Robot controller can tell
//! that robots held by a dead gateway are Unknown; it also carries the gateway's claims (robots
//! that moved here and are not written yet, see [`crate::gateway::presence::claims`]).

use std::time::Duration;

use jiff::Timestamp;
use k8s_openapi::api::coordination::v1::{Lease, LeaseSpec};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::MicroTime;
use kube::Api;
use kube::api::{ObjectMeta, Patch, PatchParams};
use std::collections::BTreeMap;
use tokio_util::sync::CancellationToken;
use tracing::warn;

use lekiwi_crds::contract::{CLAIMS_ANNOTATION, GATEWAY_LEASE_LABEL, managers};

use crate::gateway::presence::Presence;

/// Shortest time between two renewals: a robot moving here renews the Lease early (its claim
/// must be seen before the dead gateway's Lease expires), at most this often.
const MIN_RENEW_GAP: Duration = Duration::from_secs(1);

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
    loop {
        let now = MicroTime(Timestamp::now());
        let lease = Lease {
            metadata: ObjectMeta {
                name: Some(name.clone()),
                labels: Some(BTreeMap::from([(
                    GATEWAY_LEASE_LABEL.to_owned(),
                    "true".to_owned(),
                )])),
                // Left out when empty: server-side apply then removes the annotation.
                annotations: presence
                    .as_ref()
                    .and_then(Presence::claims_annotation)
                    .map(|claims| BTreeMap::from([(CLAIMS_ANNOTATION.to_owned(), claims)])),
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
            Ok(_) => acquired = acquired.or(Some(now)),
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
