//! `GET /api/v1/namespaces/{namespace}/summary`: the robots of a namespace counted by phase and
//! release, with how many are teleoperated or unhealthy, from the gateway's cache in one pass and
//! without copying a Robot: what a fleet overview needs, at a size that does not grow with the
//! fleet (the dashboard asks for it every refresh instead of listing every robot).

use std::cell::RefCell;
use std::collections::BTreeMap;

use axum::Json;
use axum::extract::rejection::QueryRejection;
use axum::extract::{Path, Query, State};
use axum::http::HeaderMap;
use lekiwi_crds::Robot;
use lekiwi_crds::robot::RobotPhase;
use serde::{Deserialize, Serialize};

use super::selector::Selector;
use super::{authorize, bad_query, check_names, ready};
use crate::kube_auth::Access;
use crate::{ApiError, FleetState};

/// Releases named one by one; the rest are summed under [`OTHER`].
pub const MAX_RELEASES: usize = 20;
/// The key of the releases beyond [`MAX_RELEASES`].
pub const OTHER: &str = "(other)";
/// The key of robots that report no release.
pub const NONE: &str = "(none)";

/// Query of the summary.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "camelCase")]
pub struct SummaryQuery {
    /// Label selector, as `kubectl get -l` takes it.
    #[serde(default, deserialize_with = "super::blank_is_none")]
    label_selector: Option<String>,
    /// Only robots reporting that they run this release version.
    #[serde(default, deserialize_with = "super::blank_is_none")]
    release: Option<String>,
}

/// The robots of a namespace, counted.
#[derive(Debug, Default, Serialize, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct Summary {
    /// Robots that match.
    pub total: u64,
    /// Robots per phase (every phase present, 0 included; no phase yet counts as `Pending`).
    pub phases: BTreeMap<&'static str, u64>,
    /// Robots per reported release version: the [`MAX_RELEASES`] most common, the rest under
    /// `(other)`, robots without one under `(none)`.
    pub releases: BTreeMap<String, u64>,
    /// Robots whose teleoperation is active.
    pub teleoperated: u64,
    /// Robots whose last health report is unhealthy.
    pub unhealthy: u64,
}

impl Summary {
    fn add(&mut self, robot: &Robot) {
        let status = robot.status.as_ref();
        let phase = status.and_then(|s| s.phase).unwrap_or(RobotPhase::Pending);
        self.total += 1;
        *self.phases.entry(phase.as_str()).or_default() += 1;
        let release = status
            .and_then(|s| s.current_release.as_ref())
            .map_or(NONE, |r| r.version.as_str());
        *self.releases.entry(release.to_owned()).or_default() += 1;
        if status.is_some_and(|s| s.teleoperation.as_ref().is_some_and(|t| t.active)) {
            self.teleoperated += 1;
        }
        if status.is_some_and(|s| s.health.as_ref().is_some_and(|h| !h.healthy)) {
            self.unhealthy += 1;
        }
    }

    /// Every phase present; releases cut to the most common ones.
    fn finish(mut self) -> Self {
        for phase in RobotPhase::ALL {
            self.phases.entry(phase.as_str()).or_default();
        }
        if self.releases.len() > MAX_RELEASES {
            let mut by_count: Vec<(String, u64)> =
                std::mem::take(&mut self.releases).into_iter().collect();
            by_count.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
            let rest: u64 = by_count
                .split_off(MAX_RELEASES)
                .iter()
                .map(|(_, n)| n)
                .sum();
            self.releases = by_count.into_iter().collect();
            *self.releases.entry(OTHER.to_owned()).or_default() += rest;
        }
        self
    }
}

/// `GET /api/v1/namespaces/{namespace}/summary` (`list robots` in that namespace).
pub async fn summary(
    State(state): State<FleetState>,
    Path(namespace): Path<String>,
    query: Result<Query<SummaryQuery>, QueryRejection>,
    headers: HeaderMap,
) -> Result<Json<Summary>, ApiError> {
    check_names(&namespace, None)?;
    let Query(query) = query.map_err(bad_query)?;
    authorize(
        &state,
        &headers,
        Some(Access::new("list", "robots", &namespace)),
    )
    .await?;
    let selector = Selector::parse(query.label_selector.as_deref().unwrap_or_default())
        .map_err(ApiError::BadRequest)?;
    ready(&state.fleet.robots)?;
    let counted = RefCell::new(Summary::default());
    // Nothing is kept: the page is empty and the closure sees every robot of the namespace once.
    state
        .fleet
        .robots
        .page(Some(&namespace), None, 0, |r: &Robot| {
            let labels = r.metadata.labels.as_ref();
            let running = r.status.as_ref().and_then(|s| s.current_release.as_ref());
            if selector.matches(labels.unwrap_or(&BTreeMap::new()))
                && query
                    .release
                    .as_deref()
                    .is_none_or(|v| running.is_some_and(|c| c.version == v))
            {
                counted.borrow_mut().add(r);
            }
            false
        });
    Ok(Json(counted.into_inner().finish()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use lekiwi_crds::ReleaseRef;
    use lekiwi_crds::robot::{RobotSpec, RobotStatus};

    fn robot(phase: Option<RobotPhase>, release: Option<&str>) -> Robot {
        let mut r = Robot::new("r", RobotSpec::default());
        r.status = Some(RobotStatus {
            phase,
            current_release: release.map(|v| ReleaseRef {
                version: v.into(),
                digest: Default::default(),
            }),
            ..RobotStatus::default()
        });
        r
    }

    #[test]
    fn counts_every_phase_and_cuts_releases_to_the_most_common() {
        let mut s = Summary::default();
        s.add(&robot(Some(RobotPhase::Online), Some("1.0.0")));
        s.add(&robot(Some(RobotPhase::Online), Some("1.0.0")));
        s.add(&robot(None, None));
        for i in 0..MAX_RELEASES + 3 {
            s.add(&robot(Some(RobotPhase::Offline), Some(&format!("9.{i}"))));
        }
        let s = s.finish();
        assert_eq!(s.total, 3 + MAX_RELEASES as u64 + 3);
        assert_eq!(s.phases["Online"], 2);
        assert_eq!(s.phases["Pending"], 1);
        assert_eq!(s.phases["Maintenance"], 0);
        assert_eq!(s.releases.len(), MAX_RELEASES + 1, "{:?}", s.releases);
        assert_eq!(s.releases["1.0.0"], 2);
        assert_eq!(s.releases.values().sum::<u64>(), s.total);
        assert!(s.releases[OTHER] >= 3);
    }
}
