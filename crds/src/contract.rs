//! Contracts that several binaries share about objects other than our own resources: the token
//! Secrets (written by `kubectl lekiwi` and the gateway, read by the gateway), the gateway Lease
//! label and the server-side-apply field managers of every writer.

use std::collections::BTreeMap;

use k8s_openapi::ByteString;
use k8s_openapi::api::core::v1::Secret;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::OwnerReference;
use kube::api::ObjectMeta;
use sha2::{Digest, Sha256};

/// Label on every token Secret; its value says which kind ([`KIND_ENROLLMENT`], [`KIND_ROBOT`]).
pub const TOKEN_LABEL: &str = "fleet.lekiwi.io/token";
/// [`TOKEN_LABEL`] value of a fleet enrollment token.
pub const KIND_ENROLLMENT: &str = "enrollment";
/// [`TOKEN_LABEL`] value of a per-robot token.
pub const KIND_ROBOT: &str = "robot";
/// Label naming the robot a per-robot token belongs to.
pub const ROBOT_LABEL: &str = "fleet.lekiwi.io/robot";
/// Key in a token Secret's data holding the hex SHA-256 of the token.
pub const HASH_KEY: &str = "sha256";
/// Annotation on a `Robot` that lets an enrollment token re-enroll it once (RFC 3339 time until
/// which the permission holds): set by `kubectl lekiwi robot reenroll`, removed by the gateway
/// when it issues the new token. Without it, enrollment never touches a robot that has a token.
pub const REENROLL_ANNOTATION: &str = "fleet.lekiwi.io/reenroll-until";
/// Longest robot name that can have a token: the name is the value of [`ROBOT_LABEL`] on its
/// token Secret, and label values are at most 63 characters.
pub const MAX_ROBOT_NAME_LEN: usize = 63;
/// Label (value `true`) on a `Robot` the gateway created for an enrolling robot. Its session
/// opens in the same connection and the gateway writes its first status then; until that write
/// (at most a couple of minutes), the Robot controller leaves its status empty.
pub const ENROLLED_LABEL: &str = "fleet.lekiwi.io/enrolled";
/// Name of the fleet enrollment token Secret `kubectl lekiwi enroll-token` makes.
pub const ENROLLMENT_SECRET: &str = "fleet-enrollment";
/// Label on the Lease each gateway renews (value `true`; the Lease's name is the gateway's):
/// the Robot controller's stale-Lease sweep considers only Leases that carry it.
pub const GATEWAY_LEASE_LABEL: &str = "fleet.lekiwi.io/gateway";
/// Annotation on a gateway's Lease listing the robots it holds a session of while their status
/// still names another gateway (its status write has not landed yet): entries separated by
/// commas, each `namespace/name`, or a bare `name` in the namespace of the entry before it (so a
/// namespace is written once per run of its robots); at most [`MAX_CLAIMS_BYTES`] long. The Robot controller does not mark
/// such a robot `Unknown` when the gateway its status names dies, as long as this Lease is alive.
pub const CLAIMS_ANNOTATION: &str = "fleet.lekiwi.io/claimed-robots";
/// Annotation on a gateway's Lease: how many seconds (a whole number) the robot next in line for
/// a status write has waited there, when that is a second or more. While a gateway's status
/// writes run late, the `lastHeartbeatTime` of its connected robots ages past the refresh period;
/// the Robot controller extends their heartbeat grace by this much (at most its
/// `--max-status-lag-seconds`) instead of showing them `Offline`.
pub const STATUS_LAG_ANNOTATION: &str = "fleet.lekiwi.io/status-lag-seconds";
/// Annotation on a dead gateway's Lease, written by the Robot controller
/// ([`managers::ROBOT_CONTROLLER`]): the robots it marked `Unknown` because that gateway died and
/// no live gateway claimed them, whose status still names that gateway, in the order marked; the
/// format of [`CLAIMS_ANNOTATION`], at most [`MAX_MARKED_BYTES`] long (later marks are left
/// out). A gateway holding a session of one of them writes it before every other waiting robot:
/// it is shown `Unknown` although connected, and the gateway's Robot watch may show that write
/// a minute late on a saturated API server, its Lease watch seconds late. Removed once the
/// gateway's Lease is alive again.
pub const MARKED_ANNOTATION: &str = "fleet.lekiwi.io/marked-unknown";

/// Longest [`CLAIMS_ANNOTATION`] value in bytes: an API server takes at most 256 KiB of
/// annotations per object; robots beyond this are left out (and may show `Unknown` briefly).
pub const MAX_CLAIMS_BYTES: usize = 128 * 1024;
/// Longest [`MARKED_ANNOTATION`] value in bytes: with [`MAX_CLAIMS_BYTES`] and the rest of a
/// Lease's annotations, within the API server's 256 KiB.
pub const MAX_MARKED_BYTES: usize = 96 * 1024;

/// The [`CLAIMS_ANNOTATION`] value of `robots` (`(namespace, name)`), in their order, cut at
/// whole entries to at most [`MAX_CLAIMS_BYTES`]; also how many robots it lists.
pub fn encode_claims<'a>(robots: impl IntoIterator<Item = (&'a str, &'a str)>) -> (String, usize) {
    encode_robot_list(robots, MAX_CLAIMS_BYTES)
}

/// A list of robots (`(namespace, name)`) in the format of [`CLAIMS_ANNOTATION`], in their
/// order, cut at whole entries to at most `max_bytes`; also how many robots it lists. A robot of
/// the same namespace as the one before it is written as its bare name.
pub fn encode_robot_list<'a>(
    robots: impl IntoIterator<Item = (&'a str, &'a str)>,
    max_bytes: usize,
) -> (String, usize) {
    let mut out = String::new();
    let mut listed = 0;
    let mut previous: Option<&str> = None;
    for (namespace, name) in robots {
        let same = previous == Some(namespace);
        let prefix = if same { 0 } else { namespace.len() + 1 };
        let extra = usize::from(!out.is_empty()) + prefix + name.len();
        if out.len() + extra > max_bytes {
            break;
        }
        if !out.is_empty() {
            out.push(',');
        }
        if !same {
            out.push_str(namespace);
            out.push('/');
        }
        out.push_str(name);
        previous = Some(namespace);
        listed += 1;
    }
    (out, listed)
}

/// The `namespace/name` of every entry of a [`CLAIMS_ANNOTATION`] (or [`MARKED_ANNOTATION`])
/// value (bare names take the namespace of the entry before them; a bare name with none before
/// it is skipped).
pub fn parse_claims(value: &str) -> impl Iterator<Item = String> + '_ {
    let mut namespace: Option<&str> = None;
    value
        .split(',')
        .map(str::trim)
        .filter(|e| !e.is_empty())
        .filter_map(move |entry| match entry.split_once('/') {
            Some((ns, _)) => {
                namespace = Some(ns);
                Some(entry.to_owned())
            }
            None => namespace.map(|ns| format!("{ns}/{entry}")),
        })
}

/// Server-side-apply field managers, one per writer, so `managedFields` say who wrote what.
pub mod managers {
    /// The gateway: robot token Secrets, its Lease, presence in `Robot.status`.
    pub const GATEWAY: &str = "lekiwi-gateway";
    /// The operator's CRD installer (`--install-crds`).
    pub const CRD_INSTALLER: &str = "lekiwi-operator";
    /// The Robot controller: phase and conditions in `Robot.status`.
    pub const ROBOT_CONTROLLER: &str = "lekiwi-robot-controller";
    /// The RobotDeployment controller's rollouts: `Robot.spec.release` and the rollout mark.
    pub const ROLLOUT: &str = "lekiwi-rollout";
    /// The RobotDeployment controller's agent rollouts: `Robot.spec.agent` and the agent
    /// rollout mark.
    pub const AGENT_ROLLOUT: &str = "lekiwi-agent-rollout";
    /// The RobotDeployment controller: `RobotDeployment.status`.
    pub const DEPLOYMENT_STATUS: &str = "lekiwi-deployment-controller";
    /// `kubectl lekiwi`: tokens and rollout actions.
    pub const CLI: &str = "kubectl-lekiwi";
}

/// Hex SHA-256 of a token: the only form in which the cluster keeps it.
pub fn hash_token(token: &str) -> String {
    hex::encode(Sha256::digest(token.as_bytes()))
}

/// A fresh random token (256 bits) with a kind prefix (`lkr_` robot, `lke_` enrollment).
pub fn new_token(prefix: &str) -> String {
    use rand::RngCore;
    let mut bytes = [0u8; 32];
    rand::rng().fill_bytes(&mut bytes);
    format!("{prefix}{}", hex::encode(bytes))
}

/// Name of the Secret holding a robot's token hash.
pub fn robot_secret_name(robot: &str) -> String {
    format!("{robot}-agent-token")
}

/// The Secret that holds the hash of a robot's own token, owned by its `Robot` so it goes with it.
pub fn robot_token_secret(robot: &str, token: &str, owner: Option<OwnerReference>) -> Secret {
    token_secret(
        robot_secret_name(robot),
        BTreeMap::from([
            (TOKEN_LABEL.to_owned(), KIND_ROBOT.to_owned()),
            (ROBOT_LABEL.to_owned(), robot.to_owned()),
        ]),
        token,
        owner,
    )
}

/// The Secret that holds the hash of a namespace's fleet enrollment token.
pub fn enrollment_token_secret(token: &str) -> Secret {
    token_secret(
        ENROLLMENT_SECRET.to_owned(),
        BTreeMap::from([(TOKEN_LABEL.to_owned(), KIND_ENROLLMENT.to_owned())]),
        token,
        None,
    )
}

fn token_secret(
    name: String,
    labels: BTreeMap<String, String>,
    token: &str,
    owner: Option<OwnerReference>,
) -> Secret {
    Secret {
        metadata: ObjectMeta {
            name: Some(name),
            labels: Some(labels),
            owner_references: owner.map(|r| vec![r]),
            ..ObjectMeta::default()
        },
        data: Some(BTreeMap::from([(
            HASH_KEY.to_owned(),
            ByteString(hash_token(token).into_bytes()),
        )])),
        type_: Some("Opaque".to_owned()),
        ..Secret::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn robot_secret_carries_the_hash_and_the_labels_the_gateway_reads() {
        let s = robot_token_secret("kiwi-1", "lkr_x", None);
        assert_eq!(s.metadata.name.as_deref(), Some("kiwi-1-agent-token"));
        let labels = s.metadata.labels.unwrap();
        assert_eq!(labels[TOKEN_LABEL], KIND_ROBOT);
        assert_eq!(labels[ROBOT_LABEL], "kiwi-1");
        let hash = &s.data.unwrap()[HASH_KEY];
        assert_eq!(hash.0, hash_token("lkr_x").into_bytes());
        assert_ne!(hash_token("lkr_x"), hash_token("lkr_y"));
    }
    #[test]
    fn claims_round_trip_and_stay_bounded() {
        let robots = [
            ("fleet", "kiwi-1"),
            ("fleet", "kiwi-3"),
            ("lab", "kiwi-2"),
            ("fleet", "kiwi-4"),
        ];
        let (value, n) = encode_claims(robots);
        assert_eq!(value, "fleet/kiwi-1,kiwi-3,lab/kiwi-2,fleet/kiwi-4");
        assert_eq!(n, 4);
        assert_eq!(
            parse_claims(&value).collect::<Vec<_>>(),
            ["fleet/kiwi-1", "fleet/kiwi-3", "lab/kiwi-2", "fleet/kiwi-4"]
        );
        assert_eq!(parse_claims("").count(), 0);
        // The first format (every entry `namespace/name`) still parses; a bare name with no
        // namespace before it is skipped.
        assert_eq!(
            parse_claims("orphan,a/x, a/y ,,b/z").collect::<Vec<_>>(),
            ["a/x", "a/y", "b/z"]
        );
        // 10,000 robots of one namespace, even a long one, fit whole; 20,000 are cut at an
        // entry.
        let ns = "recovery-bench-namespace-0123456789";
        let names: Vec<String> = (0..20_000).map(|i| format!("robot-{i:05}")).collect();
        let (value, n) = encode_claims(names[..10_000].iter().map(|n| (ns, n.as_str())));
        assert_eq!(n, 10_000);
        let parsed: Vec<String> = parse_claims(&value).collect();
        assert_eq!(parsed.len(), 10_000);
        assert_eq!(parsed[9_999], format!("{ns}/robot-09999"));
        let (value, n) = encode_claims(names.iter().map(|n| (ns, n.as_str())));
        assert!(value.len() <= MAX_CLAIMS_BYTES);
        assert!(n < 20_000 && n > 10_000, "{n}");
        assert_eq!(parse_claims(&value).count(), n);
        // The marks' shorter bound cuts the same list sooner, still at an entry.
        let (value, n) = encode_robot_list(names.iter().map(|n| (ns, n.as_str())), 1_000);
        assert!(
            value.len() <= 1_000 && value.len() > 1_000 - 12,
            "{}",
            value.len()
        );
        assert_eq!(parse_claims(&value).count(), n);
        assert_eq!(
            parse_claims(&value).last(),
            Some(format!("{ns}/robot-{:05}", n - 1))
        );
    }
}
