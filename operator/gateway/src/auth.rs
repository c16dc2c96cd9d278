//! Agent authentication: per-robot tokens and fleet enrollment tokens, both kept in Secrets
//! only as SHA-256 hashes; registration of unknown robots that present an enrollment token.
//! (People and tools authenticate to the HTTP API with Kubernetes tokens: see `kube_auth`.)

use std::sync::Arc;

use k8s_openapi::api::core::v1::Secret;
use kube::Api;
use lekiwi_crds::contract::{
    HASH_KEY, KIND_ENROLLMENT, KIND_ROBOT, MAX_ROBOT_NAME_LEN, ROBOT_LABEL, TOKEN_LABEL,
    hash_token, robot_secret_name,
};

use crate::enroll;
use crate::lookup::{Lookups, Skip, Subject};
use crate::tokens::{TokenIndex, TokenKind};
use lekiwi_core::RobotKey;
pub use lekiwi_core::http::Refusal;
use lekiwi_core::http::valid_name;

/// Who the caller is, once the token checks out.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Grant {
    /// A known robot with its own token.
    Robot(RobotKey),
    /// A robot enrolling with a fleet enrollment token; it gets its own token after `hello`.
    Enroll(RobotKey),
}

impl Grant {
    /// The robot either way.
    pub fn robot(&self) -> &RobotKey {
        match self {
            Grant::Robot(k) | Grant::Enroll(k) => k,
        }
    }
}

/// Compares two hashes without an early exit, so timing says nothing about the token.
fn same_hash(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

fn secret_hash(secret: &Secret) -> Option<Vec<u8>> {
    secret.data.as_ref()?.get(HASH_KEY).map(|b| b.0.clone())
}

/// Parses the robot header: `namespace/name`, or `name` alone for enrollment.
pub fn parse_robot(header: &str) -> Option<(Option<String>, String)> {
    let (ns, name) = match header.split_once('/') {
        Some((ns, name)) => (Some(ns.to_owned()), name.to_owned()),
        None => (None, header.to_owned()),
    };
    (valid_name(&name) && ns.as_deref().is_none_or(valid_name)).then_some((ns, name))
}

/// The robot a request names, if it is a name a robot with a token can have.
fn robot_of(header: Option<&str>) -> Result<(Option<String>, String), Refusal> {
    let (namespace, name) = header.and_then(parse_robot).ok_or(Refusal::BadRobotName)?;
    if name.len() > MAX_ROBOT_NAME_LEN {
        return Err(Refusal::RobotNameTooLong);
    }
    Ok((namespace, name))
}

/// Checks tokens against the Secrets the gateway watches, falling back to a direct read for a
/// robot token minted a moment ago that the watch has not delivered yet; those reads go
/// through [`Lookups`] (misses remembered, a budget of their own).
#[derive(Clone)]
pub struct Authenticator {
    client: kube::Client,
    tokens: Arc<TokenIndex>,
    /// Enrollment costs three API requests; a fleet enrolling at once waits here instead of
    /// flooding the API server.
    enrollments: std::sync::Arc<tokio::sync::Semaphore>,
    /// Direct lookups of enrollment tokens the cache has not seen yet, at most a few at once.
    lookups: std::sync::Arc<tokio::sync::Semaphore>,
    /// The budget and memory of live reads for requests the cache cannot authenticate.
    reads: std::sync::Arc<Lookups>,
}

/// Enrollments in flight at once; more wait for a permit.
const MAX_CONCURRENT_ENROLLMENTS: usize = 16;

/// The robot whose token `secret` holds, when it carries our labels of a robot token Secret
/// (see [`lekiwi_crds::contract::robot_token_secret`]); `None` for any other Secret.
pub fn robot_of_secret(secret: &Secret) -> Option<RobotKey> {
    let labels = secret.metadata.labels.as_ref()?;
    if labels.get(TOKEN_LABEL).map(String::as_str) != Some(KIND_ROBOT) {
        return None;
    }
    Some(RobotKey {
        namespace: secret.metadata.namespace.clone()?,
        name: labels.get(ROBOT_LABEL)?.clone(),
    })
}

/// The token hash in a robot token Secret made by us for robot `name`; a Secret of that name
/// without our labels grants nothing.
fn robot_hash(secret: &Secret, name: &str) -> Option<Vec<u8>> {
    let ours = robot_of_secret(secret).is_some_and(|robot| robot.name == name);
    ours.then(|| secret_hash(secret)).flatten()
}

impl Authenticator {
    /// Whether the token hash `hash` (hex, [`hash_token`]) counts for `robot` by the watched
    /// Secrets alone: false when its Secret is gone (or not seen yet), not ours, or holds
    /// another hash (the token was rotated or revoked).
    pub fn still_counts(&self, robot: &RobotKey, hash: &str) -> bool {
        self.tokens
            .get(&robot.namespace, &robot_secret_name(&robot.name))
            .is_some_and(|t| {
                matches!(&t.kind, TokenKind::Robot(r) if **r == *robot.name)
                    && t.hash.is_some_and(|h| same_hash(&h, hash.as_bytes()))
            })
    }

    /// An authenticator over the watched token Secrets, with the default [`Lookups`].
    pub fn new(client: kube::Client, tokens: Arc<TokenIndex>) -> Self {
        Self {
            client,
            tokens,
            enrollments: std::sync::Arc::new(tokio::sync::Semaphore::new(
                MAX_CONCURRENT_ENROLLMENTS,
            )),
            lookups: std::sync::Arc::new(tokio::sync::Semaphore::new(4)),
            reads: std::sync::Arc::default(),
        }
    }

    /// The same, with `reads` guarding its live reads.
    pub fn with_lookups(self, reads: Lookups) -> Self {
        Self {
            reads: std::sync::Arc::new(reads),
            ..self
        }
    }

    /// Decides who presents `token` for `robot_header`. The watched Secrets answer first; only
    /// then, within the [`Lookups`] budget, the API server ([`Refusal::Throttled`] when the
    /// budget is spent and nothing matched).
    pub async fn authenticate(
        &self,
        token: Option<&str>,
        robot_header: Option<&str>,
    ) -> Result<Grant, Refusal> {
        let token = token
            .filter(|t| !t.is_empty())
            .ok_or(Refusal::MissingToken)?;
        let (namespace, name) = robot_of(robot_header)?;
        let hex = hash_token(token);
        let hash = hex.as_bytes();
        let robot = |ns: &str| RobotKey {
            namespace: ns.to_owned(),
            name: name.clone(),
        };
        if let Some(ns) = &namespace
            && self.still_counts(&robot(ns), &hex)
        {
            return Ok(Grant::Robot(robot(ns)));
        }
        let (enrollment_ns, namespace_has_enrollment) = self.cached_enrollment(&namespace, hash);
        if let Some(ns) = enrollment_ns {
            return Ok(Grant::Enroll(robot(&ns)));
        }
        let Some(ns) = &namespace else {
            return Err(Refusal::WrongToken);
        };
        // Not (yet) in the cache, or rotated a moment ago: ask the API server.
        let mut throttled = false;
        match self.read_robot_secret(ns, &name, hash).await {
            Ok(true) => return Ok(Grant::Robot(robot(ns))),
            Ok(false) | Err(Skip::Remembered) => {}
            Err(Skip::Throttled) => throttled = true,
        }
        // An enrollment token created a moment ago may not have reached the watch yet. Ask the
        // API server, but only for a namespace the cache knows no enrollment token of (so wrong
        // tokens against a configured namespace never cost a request).
        if !namespace_has_enrollment {
            match self.list_enrollment(ns, hash).await {
                Ok(true) => return Ok(Grant::Enroll(robot(ns))),
                Ok(false) | Err(Skip::Remembered) => {}
                Err(Skip::Throttled) => throttled = true,
            }
        }
        Err(if throttled {
            Refusal::Throttled
        } else {
            Refusal::WrongToken
        })
    }

    /// The namespace of the cached enrollment token `hash` matches (in `namespace` when given),
    /// and whether the cache holds any enrollment token of `namespace`.
    fn cached_enrollment(&self, namespace: &Option<String>, hash: &[u8]) -> (Option<String>, bool) {
        let namespace = namespace.as_deref();
        let matched = self
            .tokens
            .enrollments(namespace)
            .into_iter()
            .find(|(_, h)| same_hash(h, hash))
            .map(|(ns, _)| ns);
        let has = matched.is_some() || self.tokens.has_enrollment(namespace);
        (matched, has)
    }

    /// Reads robot `ns/name`'s token Secret from the API server, within the budget, and says
    /// whether it is ours and holds `hash`; a read that finds no match is remembered.
    async fn read_robot_secret(&self, ns: &str, name: &str, hash: &[u8]) -> Result<bool, Skip> {
        let subject = Subject::Robot(ns, name);
        self.reads.admit(subject)?;
        let api: Api<Secret> = Api::namespaced(self.client.clone(), ns);
        let matches = match api.get_opt(&robot_secret_name(name)).await {
            Ok(Some(s)) => robot_hash(&s, name).is_some_and(|h| same_hash(&h, hash)),
            Ok(None) => false,
            // Not remembered, and no verdict: an API server that failed to answer says nothing
            // about the token, so the caller is told to retry (503), not that it is wrong.
            Err(_) => return Err(Skip::Throttled),
        };
        if !matches {
            self.reads.missed(subject);
        }
        Ok(matches)
    }

    /// Lists namespace `ns`'s enrollment token Secrets, within the budget and a few at once,
    /// and says whether one holds `hash`; a list that finds no match is remembered.
    async fn list_enrollment(&self, ns: &str, hash: &[u8]) -> Result<bool, Skip> {
        let subject = Subject::Enrollment(ns);
        let _slot = self.lookups.try_acquire().map_err(|_| Skip::Throttled)?;
        self.reads.admit(subject)?;
        let api: Api<Secret> = Api::namespaced(self.client.clone(), ns);
        let params =
            kube::api::ListParams::default().labels(&format!("{TOKEN_LABEL}={KIND_ENROLLMENT}"));
        let matches = match api.list(&params).await {
            Ok(list) => list
                .items
                .iter()
                .any(|s| secret_hash(s).is_some_and(|h| same_hash(&h, hash))),
            // As in `read_robot_secret`: no answer, no verdict.
            Err(_) => return Err(Skip::Throttled),
        };
        if !matches {
            self.reads.missed(subject);
        }
        Ok(matches)
    }

    /// Whether the enrolling `robot` may enroll (see [`enroll::check`]), before the upgrade.
    /// Its live reads wait for an enrollment slot, so they are bounded too.
    pub async fn may_enroll(&self, robot: &RobotKey) -> Result<(), enroll::Error> {
        let _slot = self.enrollments.acquire().await;
        enroll::check(&self.client, &self.tokens, robot).await
    }

    /// Registers an enrolling robot and mints its token (see [`enroll::register`]), a few at a
    /// time.
    pub async fn register(&self, robot: &RobotKey) -> Result<String, enroll::Error> {
        let _slot = self.enrollments.acquire().await;
        let token = enroll::register(&self.client, robot).await?;
        // Its next connection must not be refused by a miss remembered a moment ago.
        self.reads
            .forget(Subject::Robot(&robot.namespace, &robot.name));
        Ok(token)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lekiwi_crds::contract::new_token;

    #[test]
    fn robot_header_forms() {
        assert_eq!(
            parse_robot("lab/kiwi-1"),
            Some((Some("lab".into()), "kiwi-1".into()))
        );
        assert_eq!(parse_robot("kiwi-1"), Some((None, "kiwi-1".into())));
        assert_eq!(parse_robot("Lab/Kiwi"), None);
        assert_eq!(parse_robot("lab/"), None);
        assert_eq!(parse_robot("../etc"), None);
    }

    #[test]
    fn tokens_are_random_and_hashes_compare() {
        let a = new_token("lkr_");
        assert!(a.starts_with("lkr_") && a.len() == 68);
        assert_ne!(a, new_token("lkr_"));
        assert!(same_hash(
            hash_token(&a).as_bytes(),
            hash_token(&a).as_bytes()
        ));
        assert!(!same_hash(
            hash_token(&a).as_bytes(),
            hash_token("x").as_bytes()
        ));
    }
}
