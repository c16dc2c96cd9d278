//! Client steps of the Robot controller: write the planned status by server-side apply.

use kube::api::{Patch, PatchParams};
use kube::{Api, Resource};
use lekiwi_crds::Robot;
use lekiwi_crds::contract::managers;
use serde_json::json;

use crate::controller::apply_status;
use crate::error::{Error, Result};
use crate::liveness::Plan;

/// Applies `phase`, `conditions` and `observedGeneration`, and nothing else. With `fence` (the
/// Robot's `resourceVersion` as the plan saw it), the API server refuses the write (409) if the
/// Robot changed since.
///
/// Every write of the controller is fenced: gateways write phase and conditions too (with the
/// facts they follow from), so a plan made from an older version of the Robot would undo a
/// newer one — e.g. a robot just created plans `Pending` while its gateway already wrote it
/// `Online`; unfenced, it would flap `Online → Pending → Online`. And a robot marked `Unknown`
/// because its gateway died may have reconnected through another gateway already.
pub async fn apply(api: &Api<Robot>, name: &str, plan: &Plan, fence: Option<&str>) -> Result<()> {
    let mut status = json!({ "phase": plan.phase, "conditions": plan.conditions });
    // The schema has no `nullable`: omit unset fields rather than sending null.
    if let Some(generation) = plan.observed_generation {
        status["observedGeneration"] = json!(generation);
    }
    let Some(version) = fence else {
        return apply_status(api, name, name, status, managers::ROBOT_CONTROLLER)
            .await
            .map(drop);
    };
    let patch = json!({
        "apiVersion": Robot::api_version(&()),
        "kind": Robot::kind(&()),
        "metadata": { "resourceVersion": version },
        "status": status,
    });
    api.patch_status(
        name,
        &PatchParams::apply(managers::ROBOT_CONTROLLER).force(),
        &Patch::Apply(&patch),
    )
    .await
    .map(drop)
    .map_err(|source| Error::PatchStatus {
        object: name.to_owned(),
        source,
    })
}
