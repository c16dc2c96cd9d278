//! Deploy dispatch and takeover: the gateway watches Robots and tells a connected robot's
//! session when its `spec.release` changes (the session then sends the agent a `deploy` command,
//! PROTOCOL.md §12) or when another gateway's later session took the robot over (the session
//! closes, see [`super::holder`]).

use std::collections::HashMap;
use std::sync::Arc;

use futures::StreamExt;
use kube::runtime::{WatchStreamExt, reflector, watcher};
use kube::{Api, ResourceExt};
use lekiwi_crds::{AgentRef, Robot};
use lekiwi_protocol::Release;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use super::desired::DesiredReleases;
use super::holder::{Holder, trim_status};
use super::registry::Registry;
use crate::error::{Error, Result};
use crate::gateway::event_store::RobotKey;

/// Starts the Robot watch; returns the cache sessions read their desired release (and the
/// robot's holder) from once it is ready, and the task that forwards changes to sessions of
/// this gateway (`gateway`).
pub async fn start(
    robots: Api<Robot>,
    registry: Arc<Registry>,
    gateway: String,
    cancel: CancellationToken,
) -> Result<(DesiredReleases, tokio::task::JoinHandle<()>)> {
    let (store, writer) = reflector::store();
    let stream = reflector(
        writer,
        watcher(robots, watcher::Config::default().any_semantic())
            .default_backoff()
            .modify(|r: &mut Robot| {
                // Sessions read spec.release and who holds the robot; status writes plan the
                // phase from the spec, the generation and the stored phase and conditions
                // (`presence::PhasePlanner`).
                r.metadata.managed_fields = None;
                r.metadata.annotations = None;
                r.status = trim_status(r.status.take());
            }),
    )
    .applied_objects();
    let watch_cancel = cancel.clone();
    let task = tokio::spawn(async move {
        let mut seen: HashMap<RobotKey, Option<Release>> = HashMap::new();
        let mut seen_agent: HashMap<RobotKey, Option<AgentRef>> = HashMap::new();
        let mut stream = std::pin::pin!(stream);
        loop {
            let robot = tokio::select! {
                () = watch_cancel.cancelled() => return,
                r = stream.next() => match r { Some(Ok(r)) => r, Some(Err(_)) => continue, None => return },
            };
            let key = RobotKey::new(robot.namespace().unwrap_or_default(), robot.name_any());
            let holder = Holder::of(&robot);
            if let (Some(epoch), Some(other)) = (holder.epoch, holder.gateway.as_deref())
                && other != gateway
                && registry.moved(&key, epoch)
            {
                info!(robot = %key, gateway = other, "a later session on another gateway took the robot over; closing ours");
            }
            let agent = robot.spec.agent.clone();
            if seen_agent.get(&key) != Some(&agent) {
                let told = registry.notify_desired_agent(&key, agent.clone());
                debug!(robot = %key, agent = ?agent.as_ref().map(|a| &a.version), told, "desired agent changed");
                seen_agent.insert(key.clone(), agent);
            }
            let desired = robot.spec.release.as_ref().map(Release::from);
            if seen.get(&key) != Some(&desired) {
                let told = registry.notify_desired_release(&key, desired.clone());
                debug!(robot = %key, release = ?desired.as_ref().map(|r| &r.version), told, "desired release changed");
                seen.insert(key, desired);
            }
        }
    });
    wait_listed(&store, &task, &cancel).await?;
    Ok((DesiredReleases(store), task))
}

/// Longest wait for the first list of Robots. Under heavy write load a list of 10,000 Robots
/// took over two minutes here (the API server answers pages slowly then); giving up sooner only
/// restarts the same list. The gateway is not ready (`/readyz`) meanwhile.
const FIRST_LIST_DEADLINE: std::time::Duration = std::time::Duration::from_secs(600);

/// Waits until `store` holds the first full list (it fails if the watch task ended), telling
/// the log every 30 s how long it has waited; fails after [`FIRST_LIST_DEADLINE`].
async fn wait_listed(
    store: &reflector::Store<Robot>,
    task: &tokio::task::JoinHandle<()>,
    cancel: &CancellationToken,
) -> Result<()> {
    let started = tokio::time::Instant::now();
    let every = std::time::Duration::from_secs(30);
    let mut progress = tokio::time::interval_at(started + every, every);
    let mut ready = std::pin::pin!(store.wait_until_ready());
    loop {
        tokio::select! {
            r = &mut ready => {
                return r.map_err(|_| Error::TaskStopped("robot reflector of the gateway"));
            }
            () = cancel.cancelled() => return Ok(()),
            () = tokio::time::sleep_until(started + FIRST_LIST_DEADLINE) => {
                task.abort();
                return Err(Error::TaskStopped("robot reflector of the gateway"));
            }
            _ = progress.tick() => warn!(
                waited_s = started.elapsed().as_secs(),
                "still listing Robots before accepting connections (the API server is slow)"
            ),
        }
    }
}
