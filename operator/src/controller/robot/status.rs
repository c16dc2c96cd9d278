//! Client steps of the Robot controller: write the planned status by server-side apply.

use kube::Api;
use lekiwi_crds::Robot;
use lekiwi_crds::contract::managers;
use serde_json::json;

use super::plan::Plan;
use crate::controller::apply_status;
use crate::error::Result;

/// Applies `phase`, `conditions` and `observedGeneration`, and nothing else.
pub async fn apply(api: &Api<Robot>, name: &str, plan: &Plan) -> Result<()> {
    let mut status = json!({ "phase": plan.phase, "conditions": plan.conditions });
    // The schema has no `nullable`: omit unset fields rather than sending null.
    if let Some(generation) = plan.observed_generation {
        status["observedGeneration"] = json!(generation);
    }
    apply_status(api, name, name, status, managers::ROBOT_CONTROLLER)
        .await
        .map(drop)
}
