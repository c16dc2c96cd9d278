//! Client steps of the Robot controller: write the planned status by server-side apply.

use kube::Api;
use lekiwi_crds::contract::managers;
use lekiwi_crds::{Robot, RobotStatus};

use crate::Result;
use crate::apply_status;
use lekiwi_core::apply::StatusApply;
use lekiwi_liveness::Plan;

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
    // Only the fields this controller owns; the gateway owns the rest of the status.
    let status = RobotStatus {
        phase: Some(plan.phase),
        conditions: plan.conditions.clone(),
        observed_generation: plan.observed_generation,
        ..RobotStatus::default()
    };
    let mut patch = StatusApply::new::<Robot>(status);
    if let Some(version) = fence {
        patch = patch.fenced(Some(version.to_owned()));
    }
    apply_status(api, name, name, &patch, managers::ROBOT_CONTROLLER)
        .await
        .map(drop)
}
