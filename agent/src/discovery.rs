//! Discovery: the mDNS advertisement of `_lekiwi._tcp.local` and the local JSON status endpoint.
//!
//! Interface the agent loop uses (keep these signatures):
//! - `StatusSnapshot` (Serialize + Deserialize, camelCase): robot, agentVersion, release,
//!   gateway, connected, teleoperation, outboxPending, lastRttMs, bytesSent, startedAtMs
//! - `serve_status(listener: tokio::net::TcpListener, status: tokio::sync::watch::Receiver<StatusSnapshot>)`
//! - `Advertiser::start(&StatusSnapshot, port: u16) -> Result<Advertiser, Error>`,
//!   `Advertiser::update(&mut self, &StatusSnapshot)`; dropping it withdraws the advertisement
