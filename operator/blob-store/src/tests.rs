//! The blob store against temporary directories: whole and chunked uploads, resuming,
//! verification, limits, concurrency and release manifests.

use futures::Stream;
use lekiwi_protocol::release::ManifestFile;
use sha2::{Digest, Sha256};

use super::*;

fn digest(bytes: &[u8]) -> String {
    format!("sha256:{}", hex::encode(Sha256::digest(bytes)))
}

fn body(parts: &[&[u8]]) -> impl Stream<Item = Result<Vec<u8>, std::io::Error>> + use<> {
    let parts: Vec<_> = parts.iter().map(|p| Ok(p.to_vec())).collect();
    futures::stream::iter(parts)
}

fn store(max: u64) -> (tempfile::TempDir, BlobStore) {
    let dir = tempfile::tempdir().unwrap();
    let store = BlobStore::new(dir.path().join("blobs"), max);
    (dir, store)
}

#[tokio::test]
async fn whole_uploads_are_verified_stored_and_idempotent() {
    let (_dir, store) = store(1024);
    let content = b"hello, kiwi";
    let d = digest(content);
    assert_eq!(store.stat(&d).await.unwrap(), None);
    let state = store
        .write_at(&d, 0, None, body(&[b"hello, ", b"kiwi"]))
        .await;
    assert_eq!(state.unwrap(), UploadState::Complete { size: 11 });
    assert_eq!(store.stat(&d).await.unwrap(), Some(11));
    let on_disk = store.root().join("sha256").join(&d[7..]);
    assert_eq!(std::fs::read(&on_disk).unwrap(), content);
    let mtime = std::fs::metadata(&on_disk).unwrap().modified().unwrap();

    // Again: nothing is read or written.
    let again = store.write_at(&d, 0, None, body(&[b"garbage"])).await;
    assert_eq!(again.unwrap(), UploadState::Exists { size: 11 });
    assert_eq!(
        std::fs::metadata(&on_disk).unwrap().modified().unwrap(),
        mtime
    );
    let (_, size) = store.open(&d).await.unwrap().unwrap();
    assert_eq!(size, 11);

    // The empty blob is a blob too.
    let empty = digest(b"");
    let state = store.write_at(&empty, 0, None, body(&[])).await.unwrap();
    assert_eq!(state, UploadState::Complete { size: 0 });
}

/// Interrupted uploads older than the limit go; fresh ones, stored blobs and other files stay.
#[tokio::test]
async fn stale_partial_uploads_are_removed() {
    let (_dir, store) = store(1024);
    let content: Vec<u8> = (0..100u8).collect();
    let (old, fresh) = (digest(&content), digest(&content[..50]));
    for d in [&old, &fresh] {
        let state = store
            .write_at(d, 0, Some(100), body(&[&content[..10]]))
            .await;
        assert_eq!(state.unwrap(), UploadState::Partial { offset: 10 });
    }
    let stored = digest(b"kept");
    store
        .write_at(&stored, 0, None, body(&[b"kept"]))
        .await
        .unwrap();
    let uploads = store.root().join("uploads");
    std::fs::write(uploads.join("notes.txt"), "not a partial").unwrap();
    let two_days_ago = std::time::SystemTime::now() - std::time::Duration::from_secs(2 * 86_400);
    std::fs::File::options()
        .write(true)
        .open(uploads.join(format!("{}.partial", &old[7..])))
        .unwrap()
        .set_modified(two_days_ago)
        .unwrap();

    let day = std::time::Duration::from_secs(86_400);
    assert_eq!(store.remove_stale_uploads(day).await.unwrap(), (1, 10));
    assert_eq!(store.partial_offset(&old).await.unwrap(), 0);
    assert_eq!(store.partial_offset(&fresh).await.unwrap(), 10);
    assert_eq!(store.stat(&stored).await.unwrap(), Some(4));
    assert!(uploads.join("notes.txt").exists());
    assert_eq!(store.remove_stale_uploads(day).await.unwrap(), (0, 0));
}

#[tokio::test]
async fn chunks_resume_at_the_right_offset_only() {
    let (_dir, store) = store(1024);
    let content: Vec<u8> = (0..100u8).collect();
    let d = digest(&content);
    let state = store
        .write_at(&d, 0, Some(100), body(&[&content[..40]]))
        .await
        .unwrap();
    assert_eq!(state, UploadState::Partial { offset: 40 });
    assert_eq!(store.partial_offset(&d).await.unwrap(), 40);
    assert_eq!(store.stat(&d).await.unwrap(), None);

    match store
        .write_at(&d, 30, Some(100), body(&[&content[30..]]))
        .await
    {
        Err(Error::OffsetMismatch {
            current: 40,
            given: 30,
            ..
        }) => {}
        other => panic!("expected an offset mismatch, got {other:?}"),
    }
    // A body running past the total is refused and leaves the partial as it was.
    let too_long = [&content[40..], b"extra".as_slice()].concat();
    assert!(matches!(
        store.write_at(&d, 40, Some(100), body(&[&too_long])).await,
        Err(Error::BadChunk(_))
    ));
    assert_eq!(store.partial_offset(&d).await.unwrap(), 40);

    let state = store
        .write_at(&d, 40, Some(100), body(&[&content[40..70], &content[70..]]))
        .await
        .unwrap();
    assert_eq!(state, UploadState::Complete { size: 100 });
    assert_eq!(store.partial_offset(&d).await.unwrap(), 0);
    let mut read = Vec::new();
    let (mut file, _) = store.open(&d).await.unwrap().unwrap();
    tokio::io::AsyncReadExt::read_to_end(&mut file, &mut read)
        .await
        .unwrap();
    assert_eq!(read, content);
}

#[tokio::test]
async fn a_complete_partial_is_finished_by_an_empty_chunk() {
    let (_dir, store) = store(1024);
    let content = vec![3u8; 50];
    let d = digest(&content);
    store.ensure_dirs().await.unwrap();
    // All bytes arrived, but the gateway stopped before verifying them.
    let partial = store
        .root()
        .join("uploads")
        .join(format!("{}.partial", &d[7..]));
    std::fs::write(&partial, &content).unwrap();
    assert_eq!(store.partial_offset(&d).await.unwrap(), 50);
    let state = store.write_at(&d, 50, Some(50), body(&[])).await.unwrap();
    assert_eq!(state, UploadState::Complete { size: 50 });

    // A partial longer than the declared total is discarded: start again from 0.
    let other = digest(b"short");
    let partial = store
        .root()
        .join("uploads")
        .join(format!("{}.partial", &other[7..]));
    std::fs::write(&partial, b"much too long").unwrap();
    assert!(matches!(
        store.write_at(&other, 13, Some(5), body(&[])).await,
        Err(Error::BadChunk(_))
    ));
    match store.write_at(&other, 5, Some(5), body(&[])).await {
        Err(Error::OffsetMismatch { current: 0, .. }) => {}
        other => panic!("{other:?}"),
    }
    let state = store.write_at(&other, 0, Some(5), body(&[b"short"])).await;
    assert_eq!(state.unwrap(), UploadState::Complete { size: 5 });
}

#[tokio::test]
async fn a_broken_body_keeps_what_arrived() {
    let (_dir, store) = store(1024);
    let content = vec![7u8; 64];
    let d = digest(&content);
    let broken = futures::stream::iter(vec![
        Ok(content[..20].to_vec()),
        Err(std::io::Error::other("connection reset")),
    ]);
    match store.write_at(&d, 0, Some(64), broken).await {
        Err(Error::Body { received: 20, .. }) => {}
        other => panic!("{other:?}"),
    }
    assert_eq!(store.partial_offset(&d).await.unwrap(), 20);
    let state = store
        .write_at(&d, 20, Some(64), body(&[&content[20..]]))
        .await
        .unwrap();
    assert_eq!(state, UploadState::Complete { size: 64 });
}

#[tokio::test]
async fn wrong_content_is_refused_and_not_stored() {
    let (_dir, store) = store(1024);
    let d = digest(b"the real thing");
    match store.write_at(&d, 0, None, body(&[b"a forgery"])).await {
        Err(Error::DigestMismatch { expected, actual }) => {
            assert_eq!(expected, d);
            assert_eq!(actual, digest(b"a forgery"));
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(store.stat(&d).await.unwrap(), None);
    assert_eq!(store.partial_offset(&d).await.unwrap(), 0);
    // Chunked too: the mismatch shows at the last chunk and discards the partial.
    assert!(matches!(
        store.write_at(&d, 0, Some(9), body(&[b"a forgery"])).await,
        Err(Error::DigestMismatch { .. })
    ));
    assert_eq!(store.partial_offset(&d).await.unwrap(), 0);
    assert!(matches!(
        store.stat("sha256:XYZ").await,
        Err(Error::Digest(_))
    ));
}

#[tokio::test]
async fn size_limits_hold() {
    let (_dir, store) = store(8);
    let content = b"0123456789";
    let d = digest(content);
    assert!(matches!(
        store.write_at(&d, 0, Some(10), body(&[content])).await,
        Err(Error::TooLarge { limit: 8 })
    ));
    assert!(matches!(
        store.write_at(&d, 0, None, body(&[content])).await,
        Err(Error::TooLarge { limit: 8 })
    ));
    assert_eq!(store.partial_offset(&d).await.unwrap(), 0);
}

#[tokio::test]
async fn concurrent_uploads_of_one_blob_do_not_corrupt_it() {
    let (_dir, store) = store(1 << 20);
    let content: Vec<u8> = (0..200_000u32).map(|i| (i % 251) as u8).collect();
    let d = digest(&content);
    let chunks: Vec<Vec<u8>> = content.chunks(4096).map(<[u8]>::to_vec).collect();
    let mut tasks = Vec::new();
    for _ in 0..8 {
        let (store, d, chunks) = (store.clone(), d.clone(), chunks.clone());
        tasks.push(tokio::spawn(async move {
            let parts = futures::stream::iter(chunks.into_iter().map(Ok::<_, std::io::Error>));
            store.write_at(&d, 0, None, parts).await
        }));
    }
    let mut complete = 0;
    for t in tasks {
        match t.await.unwrap().unwrap() {
            UploadState::Complete { .. } => complete += 1,
            UploadState::Exists { size } => assert_eq!(size, content.len() as u64),
            other => panic!("{other:?}"),
        }
    }
    assert_eq!(complete, 1, "exactly one upload writes the blob");
    let stored = std::fs::read(store.root().join("sha256").join(&d[7..])).unwrap();
    assert_eq!(stored, content);
}

#[tokio::test]
async fn releases_list_missing_blobs_and_refuse_non_manifests() {
    let (_dir, store) = store(1 << 20);
    let present = b"print('hi')\n";
    let pd = digest(present);
    store
        .write_at(&pd, 0, None, body(&[present]))
        .await
        .unwrap();
    let absent = digest(b"policy weights");
    let manifest = ReleaseManifest::new(
        "1.0.0",
        vec![
            ManifestFile {
                path: "main.py".into(),
                digest: pd.clone(),
                size: present.len() as u64,
                mode: 0o755,
            },
            ManifestFile {
                path: "policy/model.bin".into(),
                digest: absent.clone(),
                size: 14,
                mode: 0o644,
            },
        ],
    );
    let bytes = manifest.to_bytes();
    let md = digest(&bytes);
    store.write_at(&md, 0, None, body(&[&bytes])).await.unwrap();
    let info = store.release(&md).await.unwrap();
    assert_eq!(info.manifest, manifest);
    assert_eq!(info.missing, vec![absent]);
    let json = serde_json::to_value(&info).unwrap();
    assert_eq!(json["version"], "1.0.0");
    assert_eq!(json["files"][0]["mode"], 0o755);

    assert!(matches!(
        store.release(&digest(b"nothing")).await,
        Err(Error::NotFound(_))
    ));
    match store.release(&pd).await {
        Err(e @ Error::Manifest { .. }) => {
            assert!(
                e.to_string().contains("not a valid release manifest"),
                "{e}"
            )
        }
        other => panic!("{other:?}"),
    }
}
