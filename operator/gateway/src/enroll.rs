//! Enrollment: an enrollment token registers a robot that has no credentials yet; a robot that
//! has its own token is re-enrolled only with a person's one-time, expiring permission (the
//! [`REENROLL_ANNOTATION`] on its `Robot`), which the gateway removes when it issues the token.

use std::collections::BTreeMap;

use k8s_openapi::api::core::v1::Secret;
use kube::api::{ObjectMeta, Patch, PatchParams, PostParams};
use kube::{Api, Resource};
use lekiwi_crds::Robot;
use lekiwi_crds::contract::{
    ENROLLED_LABEL, REENROLL_ANNOTATION, managers, new_token, robot_secret_name, robot_token_secret,
};

use crate::tokens::TokenIndex;
use lekiwi_core::RobotKey;

/// Why an enrollment token may not (re-)enroll a robot.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Refused {
    /// The robot has its own token and no permission to enroll again.
    AlreadyEnrolled,
    /// The permission to enroll again has expired (or is not a time).
    PermissionExpired,
    /// Another enrollment used the permission (or made the token) first.
    Raced,
}

impl Refused {
    /// Bounded metric label and log text.
    pub fn as_str(&self) -> &'static str {
        match self {
            Refused::AlreadyEnrolled => "already_enrolled",
            Refused::PermissionExpired => "reenroll_expired",
            Refused::Raced => "reenroll_raced",
        }
    }

    /// What the agent (and the person reading its log) is told.
    pub fn message(&self, robot: &RobotKey) -> String {
        let (ns, name) = (&robot.namespace, &robot.name);
        let how = format!("`kubectl lekiwi -n {ns} robot reenroll {name}` allows it once");
        match self {
            Refused::AlreadyEnrolled => {
                format!("robot {ns}/{name} is already enrolled; {how}")
            }
            Refused::PermissionExpired => {
                format!("the permission to re-enroll robot {ns}/{name} has expired; {how}")
            }
            Refused::Raced => {
                format!("robot {ns}/{name} was enrolled by another connection; {how}")
            }
        }
    }
}

/// Why enrollment did not issue a token.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Not allowed (see [`Refused`]).
    #[error("enrollment refused: {}", .0.as_str())]
    Refused(Refused),
    /// The API server failed.
    #[error(transparent)]
    Kube(#[from] kube::Error),
}

/// Whether the permission on `robot` lets it enroll again now.
fn permission(robot: &Robot) -> Result<(), Refused> {
    let until = robot
        .metadata
        .annotations
        .as_ref()
        .and_then(|a| a.get(REENROLL_ANNOTATION))
        .ok_or(Refused::AlreadyEnrolled)?;
    match until.parse::<jiff::Timestamp>() {
        Ok(t) if jiff::Timestamp::now() < t => Ok(()),
        _ => Err(Refused::PermissionExpired),
    }
}

/// Whether `robot` may enroll, checked before the WebSocket upgrade so that a refused agent gets
/// a plain 403: yes when it has no token Secret, or when its Robot carries a valid permission.
/// [`register`] decides again, atomically.
pub async fn check(
    client: &kube::Client,
    tokens: &TokenIndex,
    robot: &RobotKey,
) -> Result<(), Error> {
    let secret_name = robot_secret_name(&robot.name);
    let has_token = tokens.get(&robot.namespace, &secret_name).is_some()
        || Api::<Secret>::namespaced(client.clone(), &robot.namespace)
            .get_metadata_opt(&secret_name)
            .await?
            .is_some();
    if !has_token {
        return Ok(());
    }
    let robots: Api<Robot> = Api::namespaced(client.clone(), &robot.namespace);
    match robots.get_opt(&robot.name).await? {
        Some(r) => permission(&r).map_err(Error::Refused),
        // A token Secret outliving its Robot goes with it shortly (owner reference).
        None => Err(Error::Refused(Refused::AlreadyEnrolled)),
    }
}

/// Registers an enrolling robot and mints its token, stored only as a hash: creates the `Robot`
/// (or reads it, if it exists: never two), then creates its token Secret, which fails for a
/// robot that has one. Such a robot is re-enrolled only while its Robot carries a valid
/// permission, which is removed first under a resourceVersion precondition, so two racing
/// enrollments cannot both use it.
pub async fn register(client: &kube::Client, robot: &RobotKey) -> Result<String, Error> {
    let robots: Api<Robot> = Api::namespaced(client.clone(), &robot.namespace);
    // Created first, read only if it exists: a fleet's first boot is mostly new robots, and a
    // read before every create was one more request each while the API server is busiest.
    let existing = create_robot(&robots, &robot.name).await?;
    let token = new_token("lkr_");
    let secret = robot_token_secret(&robot.name, &token, existing.controller_owner_ref(&()));
    let secrets: Api<Secret> = Api::namespaced(client.clone(), &robot.namespace);
    match secrets.create(&PostParams::default(), &secret).await {
        Ok(_) => return Ok(token),
        Err(kube::Error::Api(s)) if s.code == 409 => {}
        Err(e) => return Err(e.into()),
    }
    // The robot has a token: only a person's permission lets it enroll again, once.
    consume_permission(&robots, existing).await?;
    secrets
        .patch(
            &robot_secret_name(&robot.name),
            &PatchParams::apply(managers::GATEWAY).force(),
            &Patch::Apply(&secret),
        )
        .await?;
    Ok(token)
}

/// Removes the permission from `robot` if it holds, with the Robot's resourceVersion as a
/// precondition: of two enrollments racing for it, one sees it gone ([`Refused::Raced`]). Other
/// writers (status, labels) change the resourceVersion too; then the Robot is read again.
async fn consume_permission(robots: &Api<Robot>, mut robot: Robot) -> Result<(), Error> {
    let name = robot.metadata.name.clone().unwrap_or_default();
    let mut attempt = 0;
    loop {
        match permission(&robot) {
            Ok(()) => {}
            Err(Refused::AlreadyEnrolled) if attempt > 0 => {
                return Err(Error::Refused(Refused::Raced));
            }
            Err(r) => return Err(Error::Refused(r)),
        }
        let consume = serde_json::json!({
            "metadata": {
                "resourceVersion": robot.metadata.resource_version,
                "annotations": { REENROLL_ANNOTATION: null },
            }
        });
        match robots
            .patch(&name, &PatchParams::default(), &Patch::Merge(&consume))
            .await
        {
            Ok(_) => return Ok(()),
            Err(kube::Error::Api(s)) if s.code == 409 && attempt < 5 => {
                robot = robots.get(&name).await?;
                attempt += 1;
            }
            Err(kube::Error::Api(s)) if s.code == 409 => {
                return Err(Error::Refused(Refused::Raced));
            }
            Err(e) => return Err(e.into()),
        }
    }
}

/// Creates the Robot of an enrolling robot, or reads it if it exists (provisioned by a person,
/// enrolled before, or created by another connection first).
async fn create_robot(robots: &Api<Robot>, name: &str) -> Result<Robot, kube::Error> {
    let new = Robot {
        metadata: ObjectMeta {
            name: Some(name.to_owned()),
            labels: Some(BTreeMap::from([(
                ENROLLED_LABEL.to_owned(),
                "true".to_owned(),
            )])),
            ..ObjectMeta::default()
        },
        ..Robot::default()
    };
    match robots.create(&PostParams::default(), &new).await {
        Ok(r) => Ok(r),
        Err(kube::Error::Api(s)) if s.code == 409 => robots.get(name).await,
        // A full quota refuses the create even of a Robot that exists (admission comes
        // before the name is looked up): such a robot may still enroll again.
        Err(kube::Error::Api(s)) if s.code == 403 => match robots.get_opt(name).await? {
            Some(existing) => Ok(existing),
            None => Err(kube::Error::Api(s)),
        },
        Err(e) => Err(e),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn robot_with(until: Option<String>) -> Robot {
        Robot {
            metadata: ObjectMeta {
                annotations: until.map(|u| BTreeMap::from([(REENROLL_ANNOTATION.to_owned(), u)])),
                ..ObjectMeta::default()
            },
            ..Robot::default()
        }
    }

    #[test]
    fn permission_must_be_present_and_in_the_future() {
        let later = jiff::Timestamp::now() + jiff::SignedDuration::from_secs(60);
        let earlier = jiff::Timestamp::now() - jiff::SignedDuration::from_secs(60);
        assert_eq!(permission(&robot_with(None)), Err(Refused::AlreadyEnrolled));
        assert_eq!(permission(&robot_with(Some(later.to_string()))), Ok(()));
        assert_eq!(
            permission(&robot_with(Some(earlier.to_string()))),
            Err(Refused::PermissionExpired)
        );
        assert_eq!(
            permission(&robot_with(Some("soon".into()))),
            Err(Refused::PermissionExpired)
        );
    }
}
