//! Client steps of the Robot controller: write the planned status by server-side apply.

use kube::Api;
use kube::api::{Patch, PatchParams};
use lekiwi_crds::Robot;
use serde_json::json;

use super::plan::Plan;
use crate::error::{Error, Result};

/// Applies `phase`, `conditions` and `observedGeneration`, and nothing else.
pub async fn apply(api: &Api<Robot>, name: &str, plan: &Plan) -> Result<()> {
    let mut status = json!({ "phase": plan.phase, "conditions": plan.conditions });
    // The schema has no `nullable`: omit unset fields rather than sending null.
    if let Some(generation) = plan.observed_generation {
        status["observedGeneration"] = json!(generation);
    }
    let patch =
        json!({ "apiVersion": "fleet.lekiwi.io/v1alpha1", "kind": "Robot", "status": status });
    api.patch_status(
        name,
        &PatchParams::apply(lekiwi_crds::contract::managers::ROBOT_CONTROLLER).force(),
        &Patch::Apply(&patch),
    )
    .await
    .map_err(|source| Error::PatchStatus {
        object: name.to_owned(),
        source,
    })?;
    Ok(())
}
