//! Status conditions with metav1 `Condition` semantics, shared by both resources.

use jiff::Timestamp;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::Time;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::text::Text;

/// Whether a condition holds.
#[derive(Clone, Copy, Debug, Deserialize, Serialize, JsonSchema, PartialEq, Eq)]
pub enum ConditionStatus {
    /// The condition holds.
    True,
    /// The condition does not hold.
    False,
    /// Nobody can tell right now, for example because the robot is not connected.
    Unknown,
}

/// One aspect of an object's current state, following the Kubernetes `metav1.Condition` rules:
/// `lastTransitionTime` changes only when `status` changes.
#[derive(Clone, Debug, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct Condition {
    /// Kind of condition in CamelCase, for example `Connected` or `Progressing`.
    #[schemars(length(min = 1, max = 316))]
    pub r#type: Text,
    /// `True`, `False` or `Unknown`.
    pub status: ConditionStatus,
    /// When `status` last changed.
    pub last_transition_time: Time,
    /// Machine-readable CamelCase reason for the current status.
    #[schemars(length(min = 1, max = 1024))]
    pub reason: Text,
    /// Human-readable explanation of the current status; may be empty.
    #[serde(default)]
    pub message: Text,
    /// The `metadata.generation` the condition was computed from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub observed_generation: Option<i64>,
}

impl Condition {
    /// A condition as computed now; `lastTransitionTime` is fixed up by [`merge_conditions`].
    pub fn new(
        r#type: &str,
        status: ConditionStatus,
        reason: &str,
        message: impl Into<String>,
        generation: Option<i64>,
    ) -> Self {
        Self {
            r#type: r#type.into(),
            status,
            last_transition_time: Time(Timestamp::now()),
            reason: reason.into(),
            message: Text::from(message.into()),
            observed_generation: generation,
        }
    }
}

/// Finds a condition by type.
pub fn find<'a>(conditions: &'a [Condition], r#type: &str) -> Option<&'a Condition> {
    conditions.iter().find(|c| c.r#type == r#type)
}

/// Keeps `lastTransitionTime` of every desired condition whose status did not change from the
/// existing one, so re-computing conditions never looks like a transition.
pub fn merge_conditions(existing: &[Condition], desired: Vec<Condition>) -> Vec<Condition> {
    desired
        .into_iter()
        .map(|mut c| {
            if let Some(old) = find(existing, &c.r#type)
                && old.status == c.status
            {
                c.last_transition_time = old.last_transition_time.clone();
            }
            c
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transition_time_kept_while_status_unchanged() {
        let old_time = Time("2026-01-01T00:00:00Z".parse().unwrap());
        let mut old = Condition::new("Connected", ConditionStatus::True, "Heartbeat", "", Some(1));
        old.last_transition_time = old_time.clone();
        let same = Condition::new(
            "Connected",
            ConditionStatus::True,
            "Heartbeat",
            "fresh",
            Some(2),
        );
        let merged = merge_conditions(std::slice::from_ref(&old), vec![same]);
        assert_eq!(merged[0].last_transition_time, old_time);
        assert_eq!(merged[0].message, "fresh");

        let flipped = Condition::new(
            "Connected",
            ConditionStatus::False,
            "Disconnected",
            "",
            Some(2),
        );
        let merged = merge_conditions(&[old], vec![flipped]);
        assert_ne!(merged[0].last_transition_time, old_time);
    }
}
