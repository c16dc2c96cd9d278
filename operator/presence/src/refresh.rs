//! When a robot's routine status refresh is due: once per refresh period, at the robot's own
//! point in it.

use jiff::Timestamp;

use super::Entry;
use lekiwi_core::RobotKey;

/// Whether the routine refresh of `e`, last written at `written`, is due at `now`.
///
/// Normally once per `refresh` period, at the robot's own point in it (its [`refresh_hash`]): a
/// refresh is due once such a point passed since the last write. A fleet that connected within
/// a minute (after a gateway restart, say) then refreshes spread evenly over the whole period,
/// at most N/period writes per second at any time, instead of in the same one-minute wave every
/// period; a transition's write does not move the robot's point. So `lastHeartbeatTime` is
/// never more than a period old (the Robot controller's `--heartbeat-grace-seconds` counts on
/// that), and a robot's first refresh after a transition may come sooner than a period. An
/// analysis window does not make it sooner (see [`analysis`]).
pub(super) fn refresh_due(
    e: &Entry,
    written: Timestamp,
    now: Timestamp,
    refresh: jiff::SignedDuration,
) -> bool {
    let period = refresh.as_micros().clamp(1, i64::MAX.into()) as i64;
    // `period` is positive, so the remainder fits in i64.
    let phase = (e.refresh_hash % period.unsigned_abs()) as i64;
    let slot = |t: Timestamp| t.as_microsecond().saturating_sub(phase).div_euclid(period);
    slot(now) > slot(written)
}

/// A hash of the robot's name that places it in each refresh period: spread evenly over the
/// fleet, and the same on every gateway and after every restart.
pub(super) fn refresh_hash(key: &RobotKey) -> u64 {
    use sha2::Digest;
    let digest = sha2::Sha256::new()
        .chain_update(key.namespace.as_bytes())
        .chain_update(b"/")
        .chain_update(key.name.as_bytes())
        .finalize();
    let mut first = [0u8; 8];
    first.copy_from_slice(&digest[..8]);
    u64::from_be_bytes(first)
}
