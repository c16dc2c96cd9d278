//! Server-side apply patches built from the `crds` types: the `apiVersion` and `kind` come from
//! the resource type, the body from its typed status or a typed part of its spec, so a renamed
//! or retyped field fails to compile where it is written instead of silently sending a key the
//! CRD schema does not know. Every writer of a Robot or RobotDeployment uses them: the gateway's
//! status writer and both controllers.
//!
//! A patch holds exactly the fields its field manager owns: server-side apply drops a field
//! its manager stops sending, so an unset field is left out (the `crds` types skip `None` and
//! empty lists), never sent as `null`.

use std::collections::BTreeMap;

use kube::Resource;
use lekiwi_crds::deployment::RolloutKind;
use lekiwi_crds::{AgentRef, ReleaseRef, RobotSpec};
use serde::Serialize;

/// `apiVersion` and `kind` of `K`, as every apply patch of it starts.
#[derive(Clone, Debug, Serialize)]
#[serde(rename_all = "camelCase")]
struct TypeMeta {
    api_version: String,
    kind: String,
}

impl TypeMeta {
    fn of<K: Resource<DynamicType = ()>>() -> Self {
        Self {
            api_version: K::api_version(&()).into_owned(),
            kind: K::kind(&()).into_owned(),
        }
    }
}

/// The metadata an apply patch may carry: a `resourceVersion` precondition (the API server
/// refuses the write with 409 if the object changed since it was read) and annotations.
#[derive(Clone, Debug, Default, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct Metadata {
    /// The `metadata.resourceVersion` the object had when it was read.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub resource_version: Option<String>,
    /// Annotations this field manager owns.
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub annotations: BTreeMap<String, String>,
}

impl Metadata {
    /// Only a `resourceVersion` precondition.
    pub fn fence(resource_version: Option<String>) -> Self {
        Self {
            resource_version,
            ..Self::default()
        }
    }
}

/// An apply patch of `K`'s status subresource: `apiVersion`, `kind`, optional metadata (a
/// precondition) and the status `S` (e.g. `RobotStatus` with only the fields its writer owns).
#[derive(Clone, Debug, Serialize)]
pub struct StatusApply<S> {
    #[serde(flatten)]
    type_meta: TypeMeta,
    #[serde(skip_serializing_if = "Option::is_none")]
    metadata: Option<Metadata>,
    status: S,
}

impl<S: Serialize> StatusApply<S> {
    /// The patch of `K`'s status to `status`.
    pub fn new<K: Resource<DynamicType = ()>>(status: S) -> Self {
        Self {
            type_meta: TypeMeta::of::<K>(),
            metadata: None,
            status,
        }
    }

    /// The same patch, applied only against the object as it was at `resource_version`.
    pub fn fenced(self, resource_version: Option<String>) -> Self {
        self.with_metadata(Some(Metadata::fence(resource_version)))
    }

    /// The same patch with `metadata` (e.g. a precondition), or none.
    pub fn with_metadata(mut self, metadata: Option<Metadata>) -> Self {
        self.metadata = metadata;
        self
    }
}

/// The part of a Robot's `spec` a rollout owns: `release` (a release rollout) or `agent` (an
/// agent rollout), never the rest, which the lab owns.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct RobotSpecPart {
    /// The release the robot should run.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub release: Option<ReleaseRef>,
    /// The agent build the robot should run.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub agent: Option<AgentRef>,
}

impl RobotSpecPart {
    /// The part of `spec` a rollout of `kind` owns, when `spec` has it set.
    pub fn owned(kind: RolloutKind, spec: &RobotSpec) -> Option<Self> {
        match kind {
            RolloutKind::Release => spec.release.clone().map(|release| Self {
                release: Some(release),
                agent: None,
            }),
            RolloutKind::Agent => spec.agent.clone().map(|agent| Self {
                release: None,
                agent: Some(agent),
            }),
        }
    }

    /// Whether it carries the part a rollout of `kind` owns.
    pub fn owns(&self, kind: RolloutKind) -> bool {
        match kind {
            RolloutKind::Release => self.release.is_some(),
            RolloutKind::Agent => self.agent.is_some(),
        }
    }

    /// Sets on `spec` the parts it carries, as the write that sends it leaves the Robot.
    pub fn set_on(&self, spec: &mut RobotSpec) {
        if let Some(release) = &self.release {
            spec.release = Some(release.clone());
        }
        if let Some(agent) = &self.agent {
            spec.agent = Some(agent.clone());
        }
    }
}

/// An apply patch of a Robot's metadata (annotations) and, optionally, the part of its spec
/// its field manager owns.
#[derive(Clone, Debug, Serialize)]
pub struct RobotApply {
    #[serde(flatten)]
    type_meta: TypeMeta,
    metadata: Metadata,
    #[serde(skip_serializing_if = "Option::is_none")]
    spec: Option<RobotSpecPart>,
}

impl RobotApply {
    /// The patch that sets `annotations` and, if given, `spec`.
    pub fn new(annotations: BTreeMap<String, String>, spec: Option<RobotSpecPart>) -> Self {
        Self {
            type_meta: TypeMeta::of::<lekiwi_crds::Robot>(),
            metadata: Metadata {
                resource_version: None,
                annotations,
            },
            spec,
        }
    }
}

#[cfg(test)]
mod tests {
    use lekiwi_crds::{Robot, RobotDeployment, RobotPhase, RobotStatus};
    use serde_json::json;

    use super::*;

    /// A rollout of each kind owns its own part of the spec, and a part sets only what it holds.
    #[test]
    fn a_spec_part_is_the_part_its_rollout_kind_owns() {
        let release: ReleaseRef = serde_json::from_value(json!({
            "version": "1.0.0", "digest": format!("sha256:{}", "a".repeat(64)),
        }))
        .unwrap();
        let spec = lekiwi_crds::RobotSpec {
            release: Some(release.clone()),
            ..Default::default()
        };
        let part = RobotSpecPart::owned(RolloutKind::Release, &spec).expect("set");
        assert!(part.owns(RolloutKind::Release) && !part.owns(RolloutKind::Agent));
        assert_eq!(RobotSpecPart::owned(RolloutKind::Agent, &spec), None);
        let mut other = lekiwi_crds::RobotSpec {
            display_name: Some("kiwi".into()),
            ..Default::default()
        };
        part.set_on(&mut other);
        assert_eq!(other.release, Some(release));
        assert_eq!(
            other.display_name.as_deref(),
            Some("kiwi"),
            "the rest is the lab's"
        );
    }

    #[test]
    fn a_status_patch_names_its_type_and_only_the_fields_set() {
        let status = RobotStatus {
            phase: Some(RobotPhase::Online),
            observed_generation: Some(3),
            ..RobotStatus::default()
        };
        let patch = serde_json::to_value(StatusApply::new::<Robot>(status)).unwrap();
        assert_eq!(
            patch,
            json!({
                "apiVersion": "fleet.lekiwi.io/v1alpha1",
                "kind": "Robot",
                "status": { "phase": "Online", "observedGeneration": 3 },
            })
        );
        let fenced = StatusApply::new::<RobotDeployment>(json!({})).fenced(Some("42".into()));
        assert_eq!(
            serde_json::to_value(fenced).unwrap(),
            json!({
                "apiVersion": "fleet.lekiwi.io/v1alpha1",
                "kind": "RobotDeployment",
                "metadata": { "resourceVersion": "42" },
                "status": {},
            })
        );
    }

    #[test]
    fn a_robot_patch_carries_annotations_and_only_the_owned_spec_part() {
        let release: ReleaseRef = serde_json::from_value(json!({
            "version": "1.0.0",
            "digest": format!("sha256:{}", "a".repeat(64)),
        }))
        .unwrap();
        let annotations = BTreeMap::from([("fleet.lekiwi.io/mark".to_owned(), "{}".to_owned())]);
        let spec = RobotSpecPart {
            release: Some(release),
            agent: None,
        };
        let patch = serde_json::to_value(RobotApply::new(annotations.clone(), Some(spec))).unwrap();
        assert_eq!(
            patch,
            json!({
                "apiVersion": "fleet.lekiwi.io/v1alpha1",
                "kind": "Robot",
                "metadata": { "annotations": { "fleet.lekiwi.io/mark": "{}" } },
                "spec": { "release": { "version": "1.0.0", "digest": format!("sha256:{}", "a".repeat(64)) } },
            })
        );
        let bare = serde_json::to_value(RobotApply::new(annotations, None)).unwrap();
        assert!(bare.get("spec").is_none(), "{bare}");
    }
}
