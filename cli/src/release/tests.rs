//! Unit tests of `release`: walking, hashing, summaries and tables.

use std::os::unix::fs::PermissionsExt;

use lekiwi_protocol::release::ManifestFile;
use sha2::{Digest, Sha256};

use super::*;

#[test]
fn walks_regular_files_with_modes_and_refuses_links() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    std::fs::create_dir_all(root.join("a/b")).unwrap();
    std::fs::write(root.join("run.sh"), "#!/bin/sh\n").unwrap();
    std::fs::set_permissions(root.join("run.sh"), std::fs::Permissions::from_mode(0o755)).unwrap();
    std::fs::write(root.join("a/b/c.txt"), "c").unwrap();
    std::fs::set_permissions(
        root.join("a/b/c.txt"),
        std::fs::Permissions::from_mode(0o640),
    )
    .unwrap();
    let files = walk(root).unwrap();
    let got: Vec<(&str, u32)> = files.iter().map(|f| (f.path.as_str(), f.mode)).collect();
    assert_eq!(got, vec![("a/b/c.txt", 0o640), ("run.sh", 0o755)]);
    let (digest, size) = hash_file(&root.join("a/b/c.txt")).unwrap();
    assert_eq!(size, 1);
    assert_eq!(
        digest,
        format!("sha256:{}", hex::encode(Sha256::digest(b"c")))
    );

    std::os::unix::fs::symlink(root.join("run.sh"), root.join("a/link")).unwrap();
    let err = walk(root).unwrap_err().to_string();
    assert!(
        err.contains("a/link") && err.contains("symbolic link"),
        "{err}"
    );
}

#[test]
fn summaries_and_sizes_read_well() {
    assert_eq!(human(0), "0 B");
    assert_eq!(human(1023), "1023 B");
    assert_eq!(human(1536), "1.5 KiB");
    assert_eq!(human(5 * 1024 * 1024 * 1024), "5.0 GiB");
    let again = Pushed {
        digest: "sha256:00".into(),
        bytes: 0,
        present_files: 50,
        new_blobs: 0,
        manifest_uploaded: false,
    };
    assert_eq!(
        again.summary("1.0.0"),
        "release 1.0.0: 0 B uploaded, 50 files already present (0 new blobs, manifest already present)"
    );
    let changed = Pushed {
        bytes: 3000,
        present_files: 47,
        new_blobs: 3,
        manifest_uploaded: true,
        ..again
    };
    assert!(
        changed
            .summary("1.1.0")
            .ends_with("(3 new blobs + manifest)")
    );
}

#[test]
fn tables_show_modes_and_short_digests() {
    let info = ReleaseInfo {
        digest: format!("sha256:{}", "b".repeat(64)),
        manifest: ReleaseManifest::new(
            "1.0.0",
            vec![ManifestFile {
                path: "bin/run".into(),
                digest: format!("sha256:{}", "a".repeat(64)),
                size: 10,
                mode: 0o755,
            }],
        ),
        missing: vec![],
    };
    let text = render(&info, Output::Table).unwrap();
    assert!(text.contains("Version:  1.0.0"), "{text}");
    assert!(
        text.contains("0755   10     sha256:aaaaaaaaaaaa   bin/run"),
        "{text}"
    );
    let json: serde_json::Value =
        serde_json::from_str(&render(&info, Output::Json).unwrap()).unwrap();
    assert_eq!(json["files"][0]["mode"], 0o755);
    assert_eq!(json["missing"], serde_json::json!([]));
}

#[test]
fn the_token_goes_in_plain_text_only_to_loopback_or_when_allowed() {
    let args = |server: &str, insecure: bool| ServerArgs {
        server: Some(server.to_owned()),
        token: None,
        certificate_authority: None,
        insecure_allow_plaintext: insecure,
    };
    let err = args("http://192.0.2.1:9", false)
        .check_transport()
        .unwrap_err()
        .to_string();
    for needle in [
        "192.0.2.1",
        "https://",
        "--certificate-authority",
        "--insecure-allow-plaintext",
    ] {
        assert!(err.contains(needle), "{needle}: {err}");
    }
    args("http://192.0.2.1:9", true).check_transport().unwrap();
    for server in [
        "http://127.0.0.1:8081",
        "http://localhost:8081",
        "https://192.0.2.1",
    ] {
        args(server, false).check_transport().unwrap();
    }
}
