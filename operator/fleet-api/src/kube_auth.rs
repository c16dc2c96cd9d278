//! Kubernetes authentication and authorization of the gateway's HTTP API for people and tools
//! (release pushes, events): any bearer token the API server accepts (a `TokenReview`), allowed
//! what RBAC allows its user (a `SubjectAccessReview`), both answers kept for a few seconds.
//!
//! Answers are cached for [`TTL`] under a SHA-256 hash of the token (never the token itself), at
//! most [`MAX_ENTRIES`] of each kind, so a push of a thousand blobs makes a handful of reviews.
//! `TokenReview`s of tokens not in the cache share a budget of their own (`--auth-lookup-qps`,
//! `--auth-lookup-burst`, like the robot-token lookups): a flood of guessed tokens costs the API
//! server a bounded number of reviews, and beyond it the gateway answers 503 with `Retry-After`.
//! A token whose expired answer said "accepted" is reviewed again outside that budget, so a
//! busy client is never refused when its answer expires under many concurrent requests.
//! Reviews made are counted in `lekiwi_gateway_kube_reviews_total{kind, result}`, answers from
//! the cache in `lekiwi_gateway_kube_review_cache_hits_total{kind}`.

use std::collections::HashMap;
use std::hash::Hash;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use k8s_openapi::api::authentication::v1::{TokenReview, TokenReviewSpec, UserInfo};
use k8s_openapi::api::authorization::v1::{
    ResourceAttributes, SubjectAccessReview, SubjectAccessReviewSpec,
};
use kube::Api;
use kube::api::PostParams;
use sha2::{Digest, Sha256};
use tracing::{debug, warn};

use lekiwi_core::rate::SharedBucket;
use lekiwi_metrics::KindLabels;
use lekiwi_metrics::{GatewayMetrics, ReviewLabels};

/// API group of the fleet's resources, the group every check names.
pub const GROUP: &str = "fleet.lekiwi.io";
/// How long a token review or an access decision is reused.
pub const TTL: Duration = Duration::from_secs(10);
/// Entries kept per cache; past this many, expired ones go, then all.
pub const MAX_ENTRIES: usize = 4096;

/// One permission a request needs, in RBAC's terms.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct Access {
    /// `create`, `get`, `list`.
    pub verb: &'static str,
    /// `releases`, `robots`.
    pub resource: &'static str,
    /// `events` for a robot's events.
    pub subresource: Option<&'static str>,
    /// The namespace; empty for all namespaces.
    pub namespace: String,
    /// One object's name, when the request names one.
    pub name: Option<String>,
}

impl Access {
    /// `verb` on `resource` of the fleet group in `namespace`.
    pub fn new(verb: &'static str, resource: &'static str, namespace: &str) -> Self {
        Self {
            verb,
            resource,
            subresource: None,
            namespace: namespace.to_owned(),
            name: None,
        }
    }

    /// The permission as a 403 names it: `create releases.fleet.lekiwi.io in namespace lab`.
    pub fn describe(&self) -> String {
        let sub = self
            .subresource
            .map(|s| format!("/{s}"))
            .unwrap_or_default();
        let name = self
            .name
            .as_ref()
            .map(|n| format!(" {n}"))
            .unwrap_or_default();
        let place = if self.namespace.is_empty() {
            "in all namespaces".to_owned()
        } else {
            format!("in namespace {}", self.namespace)
        };
        format!("{} {}{sub}.{GROUP}{name} {place}", self.verb, self.resource)
    }

    fn attributes(&self) -> ResourceAttributes {
        ResourceAttributes {
            group: Some(GROUP.to_owned()),
            verb: Some(self.verb.to_owned()),
            resource: Some(self.resource.to_owned()),
            subresource: self.subresource.map(str::to_owned),
            namespace: Some(self.namespace.clone()).filter(|n| !n.is_empty()),
            name: self.name.clone(),
            ..ResourceAttributes::default()
        }
    }
}

/// Why a request was not let through.
#[derive(Debug)]
pub enum Denied {
    /// The API server does not accept the token (401).
    Unauthenticated,
    /// The token's user lacks the permission, named (403).
    Forbidden(String),
    /// A review could not be made (500; logged).
    Unavailable(String),
    /// The budget of token reviews is spent for now (503 with `Retry-After`).
    Throttled,
}

/// Answers kept for [`TTL`], keyed by a hash, bounded.
struct Cache<K, V> {
    entries: Mutex<HashMap<K, (Instant, V)>>,
}

impl<K: Hash + Eq, V: Clone> Cache<K, V> {
    fn new() -> Self {
        Self {
            entries: Mutex::new(HashMap::new()),
        }
    }

    fn get(&self, key: &K) -> Option<V> {
        let entries = self.entries.lock().unwrap_or_else(|p| p.into_inner());
        entries
            .get(key)
            .filter(|(at, _)| at.elapsed() < TTL)
            .map(|(_, v)| v.clone())
    }

    /// The value even when expired (`false`), while it is still held.
    fn get_stale(&self, key: &K) -> Option<(bool, V)> {
        let entries = self.entries.lock().unwrap_or_else(|p| p.into_inner());
        entries
            .get(key)
            .map(|(at, v)| (at.elapsed() < TTL, v.clone()))
    }

    fn put(&self, key: K, value: V) {
        let mut entries = self.entries.lock().unwrap_or_else(|p| p.into_inner());
        if entries.len() >= MAX_ENTRIES {
            entries.retain(|_, (at, _)| at.elapsed() < TTL);
            if entries.len() >= MAX_ENTRIES {
                entries.clear();
            }
        }
        entries.insert(key, (Instant::now(), value));
    }
}

type TokenHash = [u8; 32];

/// Checks tokens and permissions with the API server, caching the answers.
pub struct KubeAuth {
    client: kube::Client,
    metrics: GatewayMetrics,
    /// The user a token belongs to; `None` for a token the API server refused.
    users: Cache<TokenHash, Option<UserInfo>>,
    /// Whether a token's user is allowed an [`Access`].
    decisions: Cache<(TokenHash, Access), bool>,
    /// Token reviews of tokens not in the cache, per second and at once.
    budget: SharedBucket,
}

impl KubeAuth {
    /// Reviews with `client` (which needs `create` on `tokenreviews` and
    /// `subjectaccessreviews`); at most `qps` token reviews per second (`burst` at once) for
    /// tokens not in the cache.
    pub fn new(client: kube::Client, metrics: GatewayMetrics, qps: f64, burst: u32) -> Self {
        Self {
            client,
            metrics,
            users: Cache::new(),
            decisions: Cache::new(),
            budget: SharedBucket::new(qps, burst),
        }
    }

    /// Lets `token` through when the API server accepts it and its user is allowed `access`.
    pub async fn check(&self, token: &str, access: &Access) -> Result<(), Denied> {
        let hash: TokenHash = Sha256::digest(token.as_bytes()).into();
        let key = (hash, access.clone());
        let allowed = match self.decisions.get(&key) {
            Some(allowed) => {
                self.hit("access_review");
                allowed
            }
            None => {
                let Some(user) = self.user(hash, token).await? else {
                    return Err(Denied::Unauthenticated);
                };
                let allowed = self.review_access(&user, access).await?;
                self.decisions.put(key, allowed);
                allowed
            }
        };
        if allowed {
            Ok(())
        } else {
            Err(Denied::Forbidden(access.describe()))
        }
    }

    /// The user the API server says `token` belongs to (from the cache or a `TokenReview`):
    /// who the Fleet API counts a request against before it checks the permission.
    pub async fn user_of(&self, token: &str) -> Result<UserInfo, Denied> {
        let hash: TokenHash = Sha256::digest(token.as_bytes()).into();
        self.user(hash, token).await?.ok_or(Denied::Unauthenticated)
    }

    /// The user of `token`, from the cache or a `TokenReview`.
    async fn user(&self, hash: TokenHash, token: &str) -> Result<Option<UserInfo>, Denied> {
        // A token the API server accepted a moment ago is reviewed again when its answer
        // expires, outside the budget: that budget is for unknown (new or guessed) tokens, and
        // a busy client's requests all miss the cache at the same instant.
        let known = match self.users.get_stale(&hash) {
            Some((true, user)) => {
                self.hit("token_review");
                return Ok(user);
            }
            Some((false, user)) => user.is_some(),
            None => false,
        };
        if !known && !self.budget.try_take() {
            self.reviewed("token_review", "throttled");
            return Err(Denied::Throttled);
        }
        let review = TokenReview {
            spec: TokenReviewSpec {
                token: Some(token.to_owned()),
                audiences: None,
            },
            ..TokenReview::default()
        };
        let answer = Api::<TokenReview>::all(self.client.clone())
            .create(&PostParams::default(), &review)
            .await;
        let status = match answer {
            Ok(r) => r.status.unwrap_or_default(),
            Err(e) => {
                self.reviewed("token_review", "error");
                return Err(Denied::Unavailable(format!("TokenReview: {e}")));
            }
        };
        let user = status
            .authenticated
            .unwrap_or(false)
            .then_some(status.user)
            .flatten();
        self.reviewed(
            "token_review",
            if user.is_some() {
                "accepted"
            } else {
                "refused"
            },
        );
        if user.is_none() {
            debug!(error = ?status.error, "the API server refused a token");
        }
        self.users.put(hash, user.clone());
        Ok(user)
    }

    /// Whether `user` is allowed `access`, by a `SubjectAccessReview`.
    async fn review_access(&self, user: &UserInfo, access: &Access) -> Result<bool, Denied> {
        let review = SubjectAccessReview {
            spec: SubjectAccessReviewSpec {
                user: user.username.clone(),
                groups: user.groups.clone(),
                uid: user.uid.clone(),
                extra: user.extra.clone(),
                resource_attributes: Some(access.attributes()),
                non_resource_attributes: None,
            },
            ..SubjectAccessReview::default()
        };
        let answer = Api::<SubjectAccessReview>::all(self.client.clone())
            .create(&PostParams::default(), &review)
            .await;
        match answer {
            Ok(r) => {
                let allowed = r.status.is_some_and(|s| s.allowed);
                self.reviewed("access_review", if allowed { "allowed" } else { "denied" });
                if !allowed {
                    warn!(user = ?user.username, access = %access.describe(), "refused a request RBAC does not allow");
                }
                Ok(allowed)
            }
            Err(e) => {
                self.reviewed("access_review", "error");
                Err(Denied::Unavailable(format!("SubjectAccessReview: {e}")))
            }
        }
    }

    fn hit(&self, kind: &'static str) {
        self.metrics
            .kube_review_cache_hits
            .get_or_create(&KindLabels { kind })
            .inc();
    }

    fn reviewed(&self, kind: &'static str, result: &'static str) {
        self.metrics
            .kube_reviews
            .get_or_create(&ReviewLabels { kind, result })
            .inc();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_permission_is_named_as_rbac_spells_it() {
        assert_eq!(
            Access::new("create", "releases", "lab").describe(),
            "create releases.fleet.lekiwi.io in namespace lab"
        );
        let events = Access {
            subresource: Some("events"),
            name: Some("kiwi-1".into()),
            ..Access::new("get", "robots", "b")
        };
        assert_eq!(
            events.describe(),
            "get robots/events.fleet.lekiwi.io kiwi-1 in namespace b"
        );
        assert_eq!(
            Access::new("list", "robots", "").describe(),
            "list robots.fleet.lekiwi.io in all namespaces"
        );
    }

    #[test]
    fn the_cache_forgets_after_its_ttl_and_stays_bounded() {
        let cache: Cache<u32, bool> = Cache::new();
        for i in 0..(MAX_ENTRIES as u32 + 10) {
            cache.put(i, true);
        }
        assert!(cache.entries.lock().unwrap().len() <= MAX_ENTRIES);
        assert_eq!(cache.get(&(MAX_ENTRIES as u32 + 9)), Some(true));
        cache
            .entries
            .lock()
            .unwrap()
            .insert(1, (Instant::now() - TTL, true));
        assert_eq!(cache.get(&1), None);
        // Still known as expired until evicted: whose token to review again outside the budget.
        assert_eq!(cache.get_stale(&1), Some((false, true)));
        assert_eq!(
            cache.get_stale(&(MAX_ENTRIES as u32 + 9)),
            Some((true, true))
        );
    }
}
