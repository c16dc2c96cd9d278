//! The token Secrets the gateway watches, kept as only what authentication reads: for each
//! Secret its kind (a robot's token, naming the robot, or an enrollment token) and its hash.
//! A gateway holds every robot's token, so this is per robot of the fleet, not per connection:
//! about 200 bytes each, where a cached `Secret` object (its label and data maps, uid,
//! resourceVersion, ...) took about 2 KiB.
//!
//! Like `kube::runtime::reflector`, a (re)list replaces the whole index at once when it is
//! complete, so a Secret deleted while the watch was down disappears then.

use std::collections::{BTreeSet, HashMap};
use std::sync::RwLock;

use k8s_openapi::api::core::v1::Secret;
use kube::ResourceExt;
use kube::runtime::watcher;
use lekiwi_crds::contract::{HASH_KEY, KIND_ENROLLMENT, KIND_ROBOT, ROBOT_LABEL, TOKEN_LABEL};
use tokio::sync::watch;

/// What one token Secret says.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Token {
    /// The kind its labels give.
    pub kind: TokenKind,
    /// The hex SHA-256 hash of the token in its data, if any.
    pub hash: Option<Box<[u8]>>,
}

/// A token Secret's kind.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum TokenKind {
    /// A robot's own token, for the robot its label names.
    Robot(Box<str>),
    /// A fleet enrollment token of its namespace.
    Enrollment,
    /// Labelled as a token of neither kind (or a robot token without its robot label): grants
    /// nothing.
    Other,
}

impl Token {
    /// What `secret` says, from its labels and data.
    pub fn of(secret: &Secret) -> Self {
        let labels = secret.labels();
        let kind = match (
            labels.get(TOKEN_LABEL).map(String::as_str),
            labels.get(ROBOT_LABEL),
        ) {
            (Some(KIND_ROBOT), Some(robot)) => TokenKind::Robot(robot.as_str().into()),
            (Some(KIND_ENROLLMENT), _) => TokenKind::Enrollment,
            _ => TokenKind::Other,
        };
        let hash = secret
            .data
            .as_ref()
            .and_then(|d| d.get(HASH_KEY))
            .map(|b| b.0.clone().into_boxed_slice());
        Self { kind, hash }
    }
}

/// A Secret's place: namespace, then name.
type Key = (Box<str>, Box<str>);

/// Every token Secret, and which of them are enrollment tokens (a handful among a fleet's
/// robot tokens: an unknown token is checked against those alone).
#[derive(Default)]
struct Index {
    all: HashMap<Key, Token>,
    enrollments: BTreeSet<Key>,
}

impl Index {
    fn insert(&mut self, key: Key, token: Token) {
        if token.kind == TokenKind::Enrollment {
            self.enrollments.insert(key.clone());
        } else {
            self.enrollments.remove(&key);
        }
        self.all.insert(key, token);
    }

    fn remove(&mut self, key: &Key) {
        self.enrollments.remove(key);
        self.all.remove(key);
    }
}

/// The index of token Secrets, filled by [`TokenIndex::apply`] from a watch.
pub struct TokenIndex {
    secrets: RwLock<Index>,
    /// The Secrets of a relist in progress, swapped in when it completes.
    relist: RwLock<Option<Index>>,
    /// True once the first list is complete.
    ready: watch::Sender<bool>,
}

impl Default for TokenIndex {
    fn default() -> Self {
        Self {
            secrets: RwLock::default(),
            relist: RwLock::default(),
            ready: watch::Sender::new(false),
        }
    }
}

fn key(secret: &Secret) -> Key {
    (
        secret.namespace().unwrap_or_default().into(),
        secret.name_any().into(),
    )
}

impl TokenIndex {
    /// An index that counts as listed already, holding `secrets` (tests, and a gateway that
    /// authenticates from a fixed set).
    pub fn listed(secrets: impl IntoIterator<Item = Secret>) -> Self {
        let index = Self::default();
        for s in secrets {
            index.write().insert(key(&s), Token::of(&s));
        }
        index.ready.send_replace(true);
        index
    }

    /// Takes one watch event into account.
    pub fn apply(&self, event: &watcher::Event<Secret>) {
        match event {
            watcher::Event::Apply(s) => {
                self.write().insert(key(s), Token::of(s));
            }
            watcher::Event::Delete(s) => {
                self.write().remove(&key(s));
            }
            watcher::Event::Init => *self.relisting() = Some(Index::default()),
            watcher::Event::InitApply(s) => {
                if let Some(fresh) = self.relisting().as_mut() {
                    fresh.insert(key(s), Token::of(s));
                }
            }
            watcher::Event::InitDone => {
                if let Some(fresh) = self.relisting().take() {
                    *self.write() = fresh;
                }
                self.ready.send_replace(true);
            }
        }
    }

    /// Waits until the first list is complete.
    pub async fn wait_until_ready(&self) {
        let mut ready = self.ready.subscribe();
        // The sender lives in `self`, so the wait cannot fail.
        let _ = ready.wait_for(|r| *r).await;
    }

    /// The token Secret `namespace/name`, if the watch has delivered it.
    pub fn get(&self, namespace: &str, name: &str) -> Option<Token> {
        self.read()
            .all
            .get(&(namespace.into(), name.into()))
            .cloned()
    }

    /// The hashes of the enrollment tokens of `namespace` (of every namespace if `None`), each
    /// with its namespace.
    pub fn enrollments(&self, namespace: Option<&str>) -> Vec<(String, Box<[u8]>)> {
        let index = self.read();
        index
            .enrollments
            .iter()
            .filter(|(ns, _)| namespace.is_none_or(|want| want == &**ns))
            .filter_map(|k| Some((k.0.to_string(), index.all.get(k)?.hash.clone()?)))
            .collect()
    }

    /// Whether `namespace` (any namespace if `None`) has an enrollment token Secret, with or
    /// without a hash.
    pub fn has_enrollment(&self, namespace: Option<&str>) -> bool {
        self.read()
            .enrollments
            .iter()
            .any(|(ns, _)| namespace.is_none_or(|want| want == &**ns))
    }

    /// Token Secrets held.
    pub fn len(&self) -> usize {
        self.read().all.len()
    }

    /// Whether none is held.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn read(&self) -> std::sync::RwLockReadGuard<'_, Index> {
        self.secrets.read().unwrap_or_else(|p| p.into_inner())
    }

    fn write(&self) -> std::sync::RwLockWriteGuard<'_, Index> {
        self.secrets.write().unwrap_or_else(|p| p.into_inner())
    }

    fn relisting(&self) -> std::sync::RwLockWriteGuard<'_, Option<Index>> {
        self.relist.write().unwrap_or_else(|p| p.into_inner())
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use k8s_openapi::ByteString;

    use super::*;

    fn secret(ns: &str, name: &str, labels: &[(&str, &str)], hash: Option<&str>) -> Secret {
        let mut s = Secret::default();
        s.metadata.namespace = Some(ns.into());
        s.metadata.name = Some(name.into());
        s.metadata.labels = Some(
            labels
                .iter()
                .map(|(k, v)| ((*k).to_owned(), (*v).to_owned()))
                .collect(),
        );
        s.data = hash.map(|h| BTreeMap::from([(HASH_KEY.to_owned(), ByteString(h.into()))]));
        s
    }

    #[test]
    fn keeps_the_kind_and_hash_of_each_token_secret() {
        let robot = secret(
            "lab",
            "kiwi-token",
            &[(TOKEN_LABEL, KIND_ROBOT), (ROBOT_LABEL, "kiwi")],
            Some("aa"),
        );
        let enrollment = secret(
            "lab",
            "fleet",
            &[(TOKEN_LABEL, KIND_ENROLLMENT)],
            Some("bb"),
        );
        let unlabelled = secret("lab", "odd", &[(TOKEN_LABEL, KIND_ROBOT)], Some("cc"));
        let index = TokenIndex::listed([robot, enrollment, unlabelled]);
        assert_eq!(
            index.get("lab", "kiwi-token"),
            Some(Token {
                kind: TokenKind::Robot("kiwi".into()),
                hash: Some(b"aa".to_vec().into_boxed_slice()),
            })
        );
        assert_eq!(index.get("lab", "odd").unwrap().kind, TokenKind::Other);
        assert_eq!(
            index.enrollments(Some("lab")),
            vec![("lab".to_owned(), b"bb".to_vec().into_boxed_slice())]
        );
        assert!(index.enrollments(Some("other")).is_empty());
        assert!(index.has_enrollment(Some("lab")) && index.has_enrollment(None));
        assert!(!index.has_enrollment(Some("other")));
    }

    #[tokio::test]
    async fn a_relist_replaces_everything_when_complete() {
        let index = TokenIndex::default();
        let old = secret("lab", "gone", &[(TOKEN_LABEL, KIND_ENROLLMENT)], Some("aa"));
        let new = secret("lab", "kept", &[(TOKEN_LABEL, KIND_ENROLLMENT)], Some("bb"));
        index.apply(&watcher::Event::Init);
        index.apply(&watcher::Event::InitApply(old.clone()));
        assert!(index.is_empty(), "nothing until the list is complete");
        index.apply(&watcher::Event::InitDone);
        tokio::time::timeout(std::time::Duration::from_secs(1), index.wait_until_ready())
            .await
            .expect("ready after the first list");
        assert_eq!(index.len(), 1);
        // Deleted while the watch was down: gone once the relist completes.
        index.apply(&watcher::Event::Init);
        index.apply(&watcher::Event::InitApply(new.clone()));
        assert!(index.get("lab", "gone").is_some(), "old state until then");
        index.apply(&watcher::Event::InitDone);
        assert!(index.get("lab", "gone").is_none());
        assert!(index.get("lab", "kept").is_some());
        index.apply(&watcher::Event::Delete(new));
        assert!(index.is_empty());
        index.apply(&watcher::Event::Apply(old));
        assert_eq!(index.len(), 1);
    }
}
