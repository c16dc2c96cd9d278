//! Discovery on the robot's side: the mDNS advertisement of this agent and its local `/status`
//! endpoint; the shared protocol (service type, TXT keys, the snapshot, browsing) is
//! `lekiwi-discovery`, re-exported here.

mod advertise;
mod status_endpoint;

pub use advertise::{AdvertiseError, Advertiser};
pub use lekiwi_discovery::{
    Error, Found, SERVICE_TYPE, StatusSnapshot, browse, instance_name, txt,
};
pub use status_endpoint::{MAX_CONNECTIONS, MAX_HEAD_BYTES, READ_TIMEOUT, serve_status};
