//! The gateway's own Lease: renewed while the gateway lives, so the Robot controller can tell
//! that robots held by a dead gateway are Unknown.

use std::time::Duration;

use jiff::Timestamp;
use k8s_openapi::api::coordination::v1::{Lease, LeaseSpec};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::MicroTime;
use kube::Api;
use kube::api::{ObjectMeta, Patch, PatchParams};
use std::collections::BTreeMap;
use tokio_util::sync::CancellationToken;
use tracing::warn;

use lekiwi_crds::contract::{GATEWAY_LEASE_LABEL, managers};

/// Renews `namespace/name` every third of `duration` until cancelled.
pub async fn renew(
    client: kube::Client,
    namespace: String,
    name: String,
    duration: Duration,
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
        tokio::select! {
            () = cancel.cancelled() => return,
            () = tokio::time::sleep(period) => {}
        }
    }
}
