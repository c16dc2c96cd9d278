//! Parsing of the `Range` and `Content-Range` headers.

use super::download::{ByteRange, parse_range};
use super::upload::parse_content_range;

#[test]
fn ranges() {
    let r = |h: &str| parse_range(Some(h), 100);
    assert_eq!(parse_range(None, 100), ByteRange::Full);
    assert_eq!(r("bytes=10-"), ByteRange::Part { start: 10, end: 99 });
    assert_eq!(r("bytes=10-19"), ByteRange::Part { start: 10, end: 19 });
    assert_eq!(r("bytes=90-500"), ByteRange::Part { start: 90, end: 99 });
    assert_eq!(r("bytes=-5"), ByteRange::Part { start: 95, end: 99 });
    assert_eq!(r("bytes=-500"), ByteRange::Part { start: 0, end: 99 });
    assert_eq!(r("bytes=100-"), ByteRange::Unsatisfiable);
    assert_eq!(r("bytes=-0"), ByteRange::Unsatisfiable);
    assert_eq!(r("bytes=0-1,5-6"), ByteRange::Full);
    assert_eq!(r("bytes=5-1"), ByteRange::Full);
    assert_eq!(r("items=1-2"), ByteRange::Full);
    assert_eq!(parse_range(Some("bytes=0-"), 0), ByteRange::Unsatisfiable);
}

#[test]
fn content_ranges() {
    assert_eq!(parse_content_range("bytes 0-9/20"), Some((0, Some(9), 20)));
    assert_eq!(
        parse_content_range("bytes 10-19/20"),
        Some((10, Some(19), 20))
    );
    assert_eq!(parse_content_range("bytes */20"), Some((20, None, 20)));
    assert_eq!(parse_content_range("bytes 10-20/20"), None);
    assert_eq!(parse_content_range("bytes 5-4/20"), None);
    assert_eq!(parse_content_range("bytes 0-9/*"), None);
}

/// A blob is readable through a release exactly when it is that release's manifest or a file
/// the manifest lists; an unknown or unparsable manifest grants nothing and is not remembered.
#[tokio::test]
async fn a_release_grants_its_manifest_and_its_files_only() {
    use std::collections::BTreeSet;

    use lekiwi_protocol::release::{ManifestFile, ReleaseManifest};
    use sha2::{Digest, Sha256};

    use super::access::ManifestFiles;
    use lekiwi_blob_store::BlobStore;

    let digest = |b: &[u8]| format!("sha256:{}", hex::encode(Sha256::digest(b)));
    let dir = tempfile::tempdir().unwrap();
    let store = BlobStore::new(dir.path(), 1 << 20);
    store.ensure_dirs().await.unwrap();
    let put = |bytes: &[u8]| {
        let path = dir.path().join("sha256").join(&digest(bytes)[7..]);
        std::fs::write(path, bytes).unwrap();
    };
    let file = digest(b"main.py of X");
    let manifest = ReleaseManifest::new(
        "1.0.0",
        vec![ManifestFile {
            path: "main.py".into(),
            digest: file.clone(),
            size: 12,
            mode: 0o644,
        }],
    )
    .to_bytes();
    let (m, other, late) = (digest(&manifest), digest(b"Y's file"), digest(b"late"));

    let files = ManifestFiles::default();
    let granted = BTreeSet::from([m.clone()]);
    // Not pushed yet: only the manifest digest itself is granted.
    assert!(files.referenced(&store, &granted, &m).await);
    assert!(!files.referenced(&store, &granted, &file).await);
    put(&manifest);
    assert!(files.referenced(&store, &granted, &file).await);
    assert!(!files.referenced(&store, &granted, &other).await);
    assert!(!files.referenced(&store, &BTreeSet::new(), &m).await);
    assert!(!files.referenced(&store, &BTreeSet::new(), &file).await);

    // A granted digest that is not a manifest lists no files.
    put(b"late");
    let not_a_manifest = BTreeSet::from([late.clone()]);
    assert!(files.referenced(&store, &not_a_manifest, &late).await);
    assert!(!files.referenced(&store, &not_a_manifest, &file).await);
}

/// A robot's read refused at first (another replica told it of a release this replica's watch
/// has not brought yet) passes once the cache shows the change; one that never passes is
/// refused when the wait is over, not sooner and not later.
#[tokio::test(start_paused = true)]
async fn a_read_refused_at_first_passes_once_the_cache_catches_up() {
    use std::sync::Arc;
    use std::time::Duration;

    use lekiwi_crds::{Robot, RobotSpec};

    use super::access::caught_up;
    use lekiwi_core::cache::Cache;

    let cache = Arc::new(Cache::<Robot>::listed(Vec::new()));
    let mut robot = Robot::new("kiwi-1", RobotSpec::default());
    robot.metadata.namespace = Some("lab".into());
    let later = cache.clone();
    tokio::spawn(async move {
        tokio::time::sleep(Duration::from_secs(1)).await;
        later.apply_for_tests(robot);
    });
    let t0 = tokio::time::Instant::now();
    let seen = caught_up(&cache, Duration::from_secs(3), || {
        let cache = cache.clone();
        async move { cache.get("lab", "kiwi-1").is_some() }
    })
    .await;
    assert!(seen, "passes with the change");
    assert_eq!(t0.elapsed(), Duration::from_secs(1), "as soon as it comes");

    let t0 = tokio::time::Instant::now();
    let never = caught_up(&cache, Duration::from_secs(3), || async { false }).await;
    assert!(!never);
    assert_eq!(
        t0.elapsed(),
        Duration::from_secs(3),
        "refused when the wait is over"
    );
}
