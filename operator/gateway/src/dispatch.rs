//! Deploy dispatch and takeover: from the changes of the gateway's Robot cache (the Fleet API's,
//! [`lekiwi_core::cache`]: one watch of Robots per gateway), the gateway tells a connected
//! robot's session when its `spec.release` changes (the session then sends the agent a `deploy`
//! command, PROTOCOL.md §12) or when another gateway's later session took the robot over (the
//! session closes, see [`lekiwi_presence::holder`]); and presence when another gateway's earlier session
//! shows up only now in a robot whose session is here (the robot moved here: see
//! [`lekiwi_presence::claims`]), or shows such a robot, or one whose live session here it
//! names, `Unknown` or `Offline` (its write then goes first). A release a rollout told the robot
//! to switch to after a user aborted or undid that rollout is passed on held (not deployed:
//! [`Holds`]).

use std::sync::Arc;

use kube::ResourceExt;
use lekiwi_crds::Robot;
use lekiwi_protocol::Release;
use tokio::sync::broadcast::error::RecvError;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use super::halt::Holds;
use super::registry::Registry;
use crate::error::{Error, Result};
use lekiwi_core::RobotKey;
use lekiwi_core::cache::{Cache, Change};
use lekiwi_presence::holder::{self, Holder};
use lekiwi_presence::watched::WatchedRobots;
use lekiwi_presence::{Presence, claims};

/// Follows the changes of `robots` (the gateway's Robot cache, filled by its own watch); returns,
/// once the cache holds the first full list, what sessions read their desired release (and the
/// robot's holder) from, and the task that forwards changes to sessions of this gateway
/// (`gateway`).
pub async fn start(
    robots: Arc<Cache<Robot>>,
    holds: Holds,
    registry: Arc<Registry>,
    presence: Presence,
    gateway: &str,
    cancel: &CancellationToken,
) -> Result<(WatchedRobots, tokio::task::JoinHandle<()>)> {
    let (gateway, cancel) = (gateway.to_owned(), cancel.clone());
    // Subscribed before the first list is awaited, so no change falls between the two.
    let mut changes = robots.subscribe();
    wait_listed(&robots, &cancel).await?;
    let cache = robots.clone();
    let task = tokio::spawn(async move {
        let dispatch = Dispatch {
            registry,
            holds,
            presence,
            gateway,
        };
        // What the first list held, and everything since then through the changes.
        dispatch.all(&cache);
        loop {
            let change = tokio::select! {
                () = cancel.cancelled() => return,
                c = changes.recv() => c,
            };
            match change {
                Ok(Change::Applied(old, robot)) => dispatch.applied(old.as_deref(), &robot),
                Ok(Change::Deleted(_)) => {}
                // Fell behind (a relist of a large fleet): the cache holds the truth, and
                // every robot's session is told its desired release and agent again (a
                // session ignores what it already knows).
                Err(RecvError::Lagged(missed)) => {
                    debug!(missed, "Robot changes lagged; reading the whole cache");
                    dispatch.all(&cache);
                }
                Err(RecvError::Closed) => return,
            }
        }
    });
    Ok((WatchedRobots(robots), task))
}

/// The dispatch task: which sessions to tell, the rollouts that may hold a release, the robots'
/// presence, and this gateway's name. It keeps nothing per robot: each change carries the Robot
/// as it was, so a change of `spec.release` or `spec.agent` shows by comparing the two.
struct Dispatch {
    registry: Arc<Registry>,
    holds: Holds,
    presence: Presence,
    gateway: String,
}

impl Dispatch {
    /// Every Robot of the cache, as if each had just appeared.
    fn all(&self, cache: &Cache<Robot>) {
        for robot in cache.page(None, None, usize::MAX, |_| true).0 {
            self.applied(None, &robot);
        }
    }

    /// `robot` changed from `old` (`None`: new to this gateway, or the cache was read again).
    fn applied(&self, old: Option<&Robot>, robot: &Robot) {
        let key = RobotKey::new(robot.namespace().unwrap_or_default(), robot.name_any());
        let holder = Holder::of(robot);
        if let (Some(epoch), Some(other)) = (holder.epoch, holder.gateway.as_deref()) {
            if other == self.gateway {
                self.presence.write_seen(&key, epoch);
                if claims::is_shown_gone(robot) && self.presence.shown_gone_here(&key, epoch) {
                    debug!(robot = %key, "the robot is shown gone under its live session here; writing it first");
                }
            } else if self.registry.moved(&key, |ours| {
                holder::later(epoch, other, ours, &self.gateway)
            }) {
                info!(robot = %key, gateway = other, "a later session on another gateway took the robot over; closing ours");
            } else {
                if self.presence.moved_later(&key, epoch, other) {
                    debug!(robot = %key, gateway = other, "the robot's status names an earlier session on another gateway; claiming it");
                }
                if claims::is_shown_gone(robot) && self.presence.shown_gone(&key, epoch, other) {
                    debug!(robot = %key, gateway = other, "the robot is shown gone while its session here is live; writing it first");
                }
            }
        }
        let agent = &robot.spec.agent;
        if old.is_none_or(|o| o.spec.agent != *agent) {
            let told = self.registry.notify_desired_agent(&key, agent.clone());
            debug!(robot = %key, agent = ?agent.as_ref().map(|a| &a.version), told, "desired agent changed");
        }
        if old.is_none_or(|o| o.spec.release != robot.spec.release) {
            let desired = robot.spec.release.as_ref().map(Release::from);
            let version = desired.as_ref().map(|r| r.version.clone());
            let held = desired.is_some() && self.holds.held(robot);
            let told = self.registry.notify_desired_release(&key, desired, held);
            if held {
                info!(robot = %key, release = ?version, told, "a rollout a user stopped told the robot to switch after the request; not deploying it");
            } else {
                debug!(robot = %key, release = ?version, told, "desired release changed");
            }
        }
    }
}

/// Longest wait for the first list of Robots. Under heavy write load a list of 10,000 Robots
/// took over two minutes here (the API server answers pages slowly then); giving up sooner only
/// restarts the same list. The gateway is not ready (`/readyz`) meanwhile.
const FIRST_LIST_DEADLINE: std::time::Duration = std::time::Duration::from_secs(600);

/// Waits until `robots` holds the first full list, telling the log every 30 s how long it has
/// waited; fails after [`FIRST_LIST_DEADLINE`].
async fn wait_listed(robots: &Cache<Robot>, cancel: &CancellationToken) -> Result<()> {
    let started = tokio::time::Instant::now();
    let every = std::time::Duration::from_secs(30);
    let mut progress = tokio::time::interval_at(started + every, every);
    let mut look = tokio::time::interval(std::time::Duration::from_millis(100));
    loop {
        tokio::select! {
            _ = look.tick() => if robots.is_ready() {
                return Ok(());
            },
            () = cancel.cancelled() => return Ok(()),
            () = tokio::time::sleep_until(started + FIRST_LIST_DEADLINE) => {
                return Err(Error::TaskStopped("robot watch of the gateway"));
            }
            _ = progress.tick() => warn!(
                waited_s = started.elapsed().as_secs(),
                "still listing Robots before accepting connections (the API server is slow)"
            ),
        }
    }
}
