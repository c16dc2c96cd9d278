//! Which releases and blobs can go, and removing them. The plan is pure: given the release
//! records, which of them must stay, the file lists of the manifests and the blobs in use
//! otherwise, it says which records to forget and which blobs to delete. A blob shared by a
//! release that stays, or read by a download now, is never among them.

use std::collections::{BTreeMap, BTreeSet};

use super::index::ReleaseRecord;
use super::{BlobStore, Result};

/// What one collection removes.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Plan {
    /// Release records to forget.
    pub records: Vec<ReleaseRecord>,
    /// Blobs (manifests and files) no release that stays references.
    pub blobs: BTreeSet<String>,
    /// Records that could go but one of whose blobs a download is reading now.
    pub deferred: Vec<ReleaseRecord>,
}

/// What a plan is made from.
pub struct Inputs<'a> {
    /// Every release record of every namespace.
    pub records: &'a [ReleaseRecord],
    /// Blobs that stay whatever happens: manifests referenced anywhere, their files and agent
    /// builds in use.
    pub pinned: &'a BTreeSet<String>,
    /// The file digests each known manifest lists (a manifest that cannot be read is absent).
    pub files: &'a BTreeMap<String, BTreeSet<String>>,
}

impl<'a> Inputs<'a> {
    /// A manifest and the files it lists.
    fn blobs_of<'b>(&'b self, manifest: &'b str) -> impl Iterator<Item = &'b str> + 'b {
        std::iter::once(manifest).chain(
            self.files
                .get(manifest)
                .into_iter()
                .flatten()
                .map(String::as_str),
        )
    }
}

/// The records `stays` does not keep and the blobs only they reference; a record whose blobs
/// include one that `busy` says a download reads is deferred instead.
pub fn plan(
    inputs: &Inputs<'_>,
    stays: impl Fn(&ReleaseRecord) -> bool,
    busy: impl Fn(&str) -> bool,
) -> Plan {
    let (kept, candidates): (Vec<&ReleaseRecord>, Vec<&ReleaseRecord>) =
        inputs.records.iter().partition(|r| stays(r));
    let mut keep: BTreeSet<&str> = inputs.pinned.iter().map(String::as_str).collect();
    for r in &kept {
        keep.extend(inputs.blobs_of(&r.digest));
    }
    let mut plan = Plan::default();
    let mut going = Vec::new();
    for r in candidates {
        if inputs
            .blobs_of(&r.digest)
            .any(|b| !keep.contains(b) && busy(b))
        {
            plan.deferred.push(r.clone());
        } else {
            going.push(r);
        }
    }
    for r in &plan.deferred {
        keep.extend(inputs.blobs_of(&r.digest));
    }
    for r in going {
        plan.blobs.extend(
            inputs
                .blobs_of(&r.digest)
                .filter(|b| !keep.contains(b))
                .map(str::to_owned),
        );
        plan.records.push(r.clone());
    }
    plan
}

/// The records of each namespace among the newest `n` pushed there, as `(namespace, digest)`.
pub fn newest(records: &[ReleaseRecord], n: usize) -> BTreeSet<(String, String)> {
    let mut by_ns: BTreeMap<&str, Vec<&ReleaseRecord>> = BTreeMap::new();
    for r in records {
        by_ns.entry(&r.namespace).or_default().push(r);
    }
    let mut newest = BTreeSet::new();
    for (_, mut rs) in by_ns {
        rs.sort_by(|a, b| (b.pushed, &b.digest).cmp(&(a.pushed, &a.digest)));
        newest.extend(
            rs.into_iter()
                .take(n)
                .map(|r| (r.namespace.clone(), r.digest.clone())),
        );
    }
    newest
}

/// What removing a plan freed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Removed {
    /// Release records forgotten.
    pub releases: usize,
    /// Blobs deleted.
    pub blobs: usize,
    /// Their bytes.
    pub bytes: u64,
}

impl BlobStore {
    /// Removes what `plan` says: the blobs (files before manifests, so that an interrupted
    /// removal leaves a record whose next collection finishes it), then the records. A blob a
    /// download started reading since the plan was made stays.
    pub async fn remove(&self, plan: &Plan) -> Result<Removed> {
        let mut removed = Removed::default();
        let manifests: BTreeSet<&str> = plan.records.iter().map(|r| r.digest.as_str()).collect();
        let (last, first): (Vec<&String>, Vec<&String>) = plan
            .blobs
            .iter()
            .partition(|b| manifests.contains(b.as_str()));
        for digest in first.into_iter().chain(last) {
            if let Some(bytes) = self.remove_blob(digest)? {
                removed.blobs += 1;
                removed.bytes += bytes;
            }
        }
        for r in &plan.records {
            self.index().remove(&r.namespace, &r.digest).await?;
            removed.releases += 1;
        }
        Ok(removed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(ns: &str, digest: &str, second: i64) -> ReleaseRecord {
        ReleaseRecord {
            namespace: ns.into(),
            version: format!("v{second}"),
            digest: digest.into(),
            pushed: jiff::Timestamp::from_second(second).unwrap(),
        }
    }

    fn set(items: &[&str]) -> BTreeSet<String> {
        items.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn a_shared_file_stays_while_a_release_that_lists_it_stays() {
        let records = [record("a", "m1", 1), record("a", "m2", 2)];
        let files = BTreeMap::from([
            ("m1".to_string(), set(&["f1", "shared"])),
            ("m2".to_string(), set(&["f2", "shared"])),
        ]);
        let pinned = set(&["agent"]);
        let inputs = Inputs {
            records: &records,
            pinned: &pinned,
            files: &files,
        };
        let plan = plan(&inputs, |r| r.digest == "m2", |_| false);
        assert_eq!(plan.records, vec![records[0].clone()]);
        assert_eq!(plan.blobs, set(&["f1", "m1"]));
        // Read by a download: the release waits for the next collection.
        let later = super::plan(&inputs, |r| r.digest == "m2", |b| b == "f1");
        assert!(later.records.is_empty() && later.blobs.is_empty());
        assert_eq!(later.deferred, vec![records[0].clone()]);
        // A busy blob another release keeps does not hold this one back.
        let shared_busy = super::plan(&inputs, |r| r.digest == "m2", |b| b == "shared");
        assert_eq!(shared_busy.blobs, set(&["f1", "m1"]));
    }

    #[test]
    fn the_newest_n_are_counted_per_namespace() {
        let records = [
            record("a", "m1", 1),
            record("a", "m2", 2),
            record("a", "m3", 3),
            record("b", "m1", 4),
        ];
        let newest = newest(&records, 2);
        let want: BTreeSet<(String, String)> = [("a", "m2"), ("a", "m3"), ("b", "m1")]
            .iter()
            .map(|(n, d)| (n.to_string(), d.to_string()))
            .collect();
        assert_eq!(newest, want);
    }

    #[test]
    fn a_manifest_recorded_in_two_namespaces_stays_while_one_keeps_it() {
        let records = [record("a", "m1", 1), record("b", "m1", 2)];
        let files = BTreeMap::from([("m1".to_string(), set(&["f1"]))]);
        let pinned = BTreeSet::new();
        let inputs = Inputs {
            records: &records,
            pinned: &pinned,
            files: &files,
        };
        let plan = plan(&inputs, |r| r.namespace == "b", |_| false);
        assert_eq!(plan.records, vec![records[0].clone()]);
        assert!(plan.blobs.is_empty());
    }
}
