//! A stand-in for the gateway's writes to the cluster, for tests of the Robot controller alone:
//! it drives presence (connect, heartbeat, disconnect, a dead gateway) directly and quickly, with
//! no operator gateway, agent or WebSocket in the loop.

use std::collections::{BTreeMap, HashMap};
use std::time::Duration;

use anyhow::{Context as _, Result};
use jiff::Timestamp;
use k8s_openapi::api::coordination::v1::{Lease, LeaseSpec};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::MicroTime;
use kube::api::{ObjectMeta, Patch, PatchParams};
use kube::{Api, Client};
use lekiwi_crds::Robot;
use lekiwi_crds::contract::{GATEWAY_LEASE_LABEL, managers};
use serde_json::{Value, json};

use crate::now;

/// Field manager the real gateway uses for its Lease and the presence fields of Robot status.
pub const GATEWAY_FIELD_MANAGER: &str = managers::GATEWAY;

/// Writes what the real gateway writes, as the gateway does: renews a labelled gateway Lease and
/// sets the presence fields of Robot status by server-side apply under the gateway's field
/// manager, always the whole set. Tests use it to set presence at will, including a gateway that
/// stops renewing, without an agent connected to a real gateway.
pub struct GatewayStandIn {
    /// The gateway's identity (and Lease name).
    pub name: String,
    robots: Api<Robot>,
    leases: Api<Lease>,
    renew: Option<tokio::task::JoinHandle<()>>,
    /// The presence fields written so far, per robot: each write applies the whole set.
    presence: HashMap<String, Value>,
}

impl GatewayStandIn {
    /// Creates the gateway's Lease in `namespace` and renews it every second.
    pub async fn start(
        client: &Client,
        namespace: &str,
        name: &str,
        lease_seconds: i32,
    ) -> Result<Self> {
        let leases: Api<Lease> = Api::namespaced(client.clone(), namespace);
        let mut me = Self {
            name: name.to_owned(),
            robots: Api::namespaced(client.clone(), namespace),
            leases,
            renew: None,
            presence: Default::default(),
        };
        renew(&me.leases, &me.name, lease_seconds).await?;
        me.resume_renewing(lease_seconds);
        Ok(me)
    }

    /// Starts renewing again after [`Self::stop_renewing`].
    pub fn resume_renewing(&mut self, lease_seconds: i32) {
        let (leases, name) = (self.leases.clone(), self.name.clone());
        self.renew = Some(tokio::spawn(async move {
            loop {
                let _ = renew(&leases, &name, lease_seconds).await;
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        }));
    }

    /// Stops renewing the Lease, as a crashed gateway would.
    pub fn stop_renewing(&mut self) {
        if let Some(t) = self.renew.take() {
            t.abort();
        }
    }

    async fn write(&mut self, robot: &str, fields: Value) -> Result<()> {
        let entry = self
            .presence
            .entry(robot.to_owned())
            .or_insert_with(|| json!({}));
        for (k, v) in fields.as_object().cloned().unwrap_or_default() {
            entry[k] = v;
        }
        let patch = json!({ "apiVersion": "fleet.lekiwi.io/v1alpha1", "kind": "Robot", "status": entry.clone() });
        self.robots
            .patch_status(
                robot,
                &PatchParams::apply(GATEWAY_FIELD_MANAGER).force(),
                &Patch::Apply(&patch),
            )
            .await
            .with_context(|| format!("gateway stand-in: patch status of {robot}"))?;
        Ok(())
    }

    /// An agent connects: presence facts as the gateway would record them.
    pub async fn connect(&mut self, robot: &str) -> Result<()> {
        let now = now();
        let gateway = self.name.clone();
        self.write(
            robot,
            json!({
                "connected": true,
                "gateway": gateway,
                "protocol": "websocket",
                "connectedSince": now,
                "lastHeartbeatTime": now,
                "agentVersion": "0.1.0",
                "address": "127.0.0.1",
                "health": { "healthy": true },
                "teleoperation": { "active": false },
                "system": { "os": "Debian GNU/Linux 12 (bookworm)", "arch": "aarch64", "cpus": 4, "memoryBytes": 8_589_934_592u64 },
                "telemetry": { "cpuPercent": 12.5, "memoryPercent": 31.0, "temperatureCelsius": 48.2 }
            }),
        )
        .await
    }

    /// A heartbeat worth recording: only `lastHeartbeatTime` moves.
    pub async fn heartbeat(&mut self, robot: &str) -> Result<()> {
        self.write(robot, json!({ "lastHeartbeatTime": now() }))
            .await
    }

    /// Any other presence fields, e.g. `{"teleoperation": {"active": true}}`.
    pub async fn report(&mut self, robot: &str, fields: Value) -> Result<()> {
        self.write(robot, fields).await
    }

    /// The agent's connection closed.
    pub async fn disconnect(&mut self, robot: &str) -> Result<()> {
        self.write(robot, json!({ "connected": false })).await
    }
}

impl Drop for GatewayStandIn {
    fn drop(&mut self) {
        self.stop_renewing();
    }
}

/// Applies the gateway Lease as the real gateway does (`lekiwi_presence::lease`): labelled
/// with [`GATEWAY_LEASE_LABEL`], held by the gateway, renewed now.
async fn renew(leases: &Api<Lease>, name: &str, lease_seconds: i32) -> Result<()> {
    let lease = Lease {
        metadata: ObjectMeta {
            name: Some(name.to_owned()),
            labels: Some(BTreeMap::from([(
                GATEWAY_LEASE_LABEL.to_owned(),
                "true".to_owned(),
            )])),
            ..ObjectMeta::default()
        },
        spec: Some(LeaseSpec {
            holder_identity: Some(name.to_owned()),
            lease_duration_seconds: Some(lease_seconds),
            renew_time: Some(MicroTime(Timestamp::now())),
            ..LeaseSpec::default()
        }),
    };
    leases
        .patch(
            name,
            &PatchParams::apply(GATEWAY_FIELD_MANAGER).force(),
            &Patch::Apply(&lease),
        )
        .await?;
    Ok(())
}
