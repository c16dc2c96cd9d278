//! Warning Events on a Robot whose agent sends past its event store quota: at most one per
//! robot per interval, each saying how many messages were refused since the last.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use kube::api::Api;
use kube::runtime::events::{Event, EventType, Recorder, Reporter};
use kube::{Resource as _, ResourceExt as _};
use lekiwi_crds::Robot;
use tracing::warn;

use lekiwi_core::RobotKey;
use lekiwi_event_store::Quota;

/// Reason of the Warning Event.
pub const REASON: &str = "EventQuotaExceeded";

#[derive(Default)]
struct Pending {
    /// When the last Event for this robot went out.
    last: Option<Instant>,
    /// Refusals not yet reported.
    refused: u64,
    /// The newest refused seq.
    last_seq: u64,
}

/// Publishes quota Warning Events, rate-limited per robot; cheap to clone.
#[derive(Clone)]
pub struct QuotaWarnings {
    client: kube::Client,
    recorder: Recorder,
    every: Duration,
    robots: Arc<Mutex<HashMap<RobotKey, Pending>>>,
}

impl QuotaWarnings {
    /// Events reported as gateway `gateway`, at most one per robot per `every`.
    pub fn new(client: kube::Client, gateway: &str, every: Duration) -> Self {
        let recorder = Recorder::new(
            client.clone(),
            Reporter {
                controller: "lekiwi-gateway".into(),
                instance: Some(gateway.to_owned()),
            },
        );
        Self {
            client,
            recorder,
            every,
            robots: Arc::default(),
        }
    }

    /// Notes that message `seq` of `robot` was refused; publishes a Warning Event (in the
    /// background) when none went out for this robot within the interval. Refusals in between
    /// are counted into the next Event, so none goes unreported for long.
    pub fn refused(&self, robot: &RobotKey, seq: u64, quota: Quota, limit: &'static str) {
        let refused = {
            let mut robots = self.robots.lock().unwrap_or_else(|e| e.into_inner());
            let pending = robots.entry(robot.clone()).or_default();
            pending.refused += 1;
            pending.last_seq = seq;
            if pending.last.is_some_and(|at| at.elapsed() < self.every) {
                return;
            }
            pending.last = Some(Instant::now());
            (std::mem::take(&mut pending.refused), pending.last_seq)
        };
        let note = format!(
            "the agent sent past its event store quota ({limit} limit; {} rows, {} bytes per robot): {} message(s) refused and not stored since the last warning, the latest seq {}",
            quota.rows, quota.bytes, refused.0, refused.1
        );
        warn!(%robot, refused = refused.0, last_seq = refused.1, "robot over its event store quota");
        let this = self.clone();
        let robot = robot.clone();
        tokio::spawn(async move { this.publish(&robot, note).await });
    }

    async fn publish(&self, robot: &RobotKey, note: String) {
        let api: Api<Robot> = Api::namespaced(self.client.clone(), &robot.namespace);
        let obj = match api.get(&robot.name).await {
            Ok(obj) => obj,
            Err(e) => {
                warn!(%robot, error = %e, "cannot read the Robot for a quota warning");
                return;
            }
        };
        let event = Event {
            type_: EventType::Warning,
            reason: REASON.into(),
            note: Some(note),
            action: "StoreEvent".into(),
            secondary: None,
        };
        if let Err(e) = self.recorder.publish(&event, &obj.object_ref(&())).await {
            warn!(robot = %obj.name_any(), error = %e, "cannot publish a quota warning");
        }
    }
}
