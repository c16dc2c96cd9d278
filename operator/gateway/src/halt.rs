//! Downloads stopped the moment a user aborts or undoes a rollout: from the changes of the
//! gateway's RobotDeployment cache, the gateway tells the sessions of the robots the rollout
//! told to switch to cancel a download in flight, without waiting for the controller to write
//! each robot's `spec.release` back (which for a batch of a large fleet takes seconds at the
//! API server's write rate). Which requests and robots count is the planner's rule
//! ([`lekiwi_controllers::deployment::plan::halt`]); the controller's writes follow as before.
//! A robot the rollout told to switch only after the request is held ([`Holds`]).

use std::sync::Arc;

use kube::ResourceExt;
use lekiwi_crds::{Robot, RobotDeployment};
use lekiwi_protocol::Release;
use tokio::sync::broadcast::error::RecvError;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info};

use super::registry::Registry;
use lekiwi_controllers::deployment::plan::{Mark, halt};
use lekiwi_core::RobotKey;
use lekiwi_core::cache::{Cache, Change};
use lekiwi_crds::deployment::RolloutKind;

/// Which robots' desired release is held: told to switch by a rollout a user aborted or undid
/// only after the request (the controller's writes of a batch under way when it came), read from
/// the gateway's RobotDeployment cache ([`halt::held`]). Dispatch passes such a change on held,
/// and a session that opens for such a robot does not deploy its release either.
#[derive(Clone)]
pub struct Holds(pub Arc<Cache<RobotDeployment>>);

impl Holds {
    /// Whether the rollout that told `robot` to switch (its mark's deployment) was aborted or
    /// undone before that.
    pub fn held(&self, robot: &Robot) -> bool {
        let Some(mark) = Mark::of(robot, RolloutKind::Release) else {
            return false;
        };
        let namespace = robot.namespace().unwrap_or_default();
        self.0
            .get(&namespace, &mark.deployment)
            .is_some_and(|d| halt::held(robot, &d))
    }
}

/// Starts the task that follows `rollouts` and halts downloads of the robots of `robots` whose
/// rollout a user stopped; it runs until `cancel`.
pub fn start(
    rollouts: &Cache<RobotDeployment>,
    robots: Arc<Cache<Robot>>,
    registry: Arc<Registry>,
    cancel: &CancellationToken,
) -> tokio::task::JoinHandle<()> {
    let mut changes = rollouts.subscribe();
    let cancel = cancel.clone();
    tokio::spawn(async move {
        loop {
            let change = tokio::select! {
                () = cancel.cancelled() => return,
                c = changes.recv() => c,
            };
            match change {
                Ok(Change::Applied(Some(old), new)) => stop(&old, &new, &robots, &registry),
                Ok(_) => {}
                // A missed request is not lost: the controller's plan rewrites the robots'
                // `spec.release`, which cancels their downloads as it always did.
                Err(RecvError::Lagged(missed)) => {
                    debug!(missed, "RobotDeployment changes lagged");
                }
                Err(RecvError::Closed) => return,
            }
        }
    })
}

/// Halts the downloads `new` stops, if its change from `old` asks to.
fn stop(old: &RobotDeployment, new: &RobotDeployment, robots: &Cache<Robot>, registry: &Registry) {
    let Some((rollout_id, target)) = halt::stopped_by(old, new) else {
        return;
    };
    let (namespace, name) = (new.namespace().unwrap_or_default(), new.name_any());
    let release = Release::from(&target);
    let (halted, _) = robots.page(Some(&namespace), None, usize::MAX, |r| {
        halt::halts(r, &name, &rollout_id)
    });
    let told = halted
        .iter()
        .filter(|r| {
            let key = RobotKey::new(namespace.clone(), r.name_any());
            registry.notify_halt(&key, release.clone())
        })
        .count();
    info!(
        deployment = %name, %namespace, release = %target.version, robots = halted.len(), told,
        "rollout stopped by a user; cancelling downloads in flight"
    );
}
