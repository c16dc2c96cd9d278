//! The robots this gateway claims: sessions of robots whose status still names another gateway
//! because their first write here has not landed. The gateway's Lease lists them
//! ([`lekiwi_crds::contract::CLAIMS_ANNOTATION`]), so the Robot controller does not mark them
//! `Unknown` when that other gateway's Lease expires (one write per moved robot, not two).

use lekiwi_crds::contract::encode_claims;

use super::Presence;
use crate::gateway::event_store::RobotKey;

impl Presence {
    /// The robots claimed now, oldest session first (those the writer takes first).
    pub fn claims(&self) -> Vec<RobotKey> {
        let mut claimed: Vec<(u64, RobotKey)> = self.with_state(|s| {
            s.robots
                .iter()
                .filter(|(_, e)| e.moved && e.connected)
                .map(|(k, e)| (e.session, k.clone()))
                .collect()
        });
        claimed.sort_unstable_by_key(|(session, _)| *session);
        claimed.into_iter().map(|(_, k)| k).collect()
    }

    /// The [`lekiwi_crds::contract::CLAIMS_ANNOTATION`] value of [`Presence::claims`] (`None`
    /// when there is none), bounded in size; the gauge of claimed robots follows it.
    pub fn claims_annotation(&self) -> Option<String> {
        let claims = self.claims();
        let (value, listed) = encode_claims(
            claims
                .iter()
                .map(|k| (k.namespace.as_str(), k.name.as_str())),
        );
        self.metrics.gateway.claimed_robots.set(listed as i64);
        (listed > 0).then_some(value)
    }

    /// Returns once a robot moved here since the last call (or at once if one did meanwhile).
    pub async fn claims_changed(&self) {
        self.claims_changed.notified().await;
    }
}
