//! Properties of the decoders every peer feeds (issue 12, "Proof beyond examples"): arbitrary
//! frames and manifests are refused, never a panic; the status rules' checks agree with the
//! patterns the CRD carries. Case counts come from `PROPTEST_CASES` (`bench/fuzz.sh` runs many).

use lekiwi_protocol::release::{MANIFEST_MEDIA_TYPE, ReleaseManifest};
use lekiwi_protocol::rules::{
    self, DIGEST_PATTERN, MAX_VERSION_CHARS, VERSION_PATTERN, is_valid_digest, is_valid_version,
};
use lekiwi_protocol::{AgentMessage, MAX_FRAME_BYTES, ServerMessage, decode, hello_version};
use proptest::prelude::*;

/// Text that looks like a frame often enough to get past the first byte: fragments of the
/// protocol's own vocabulary, glued together with JSON punctuation and arbitrary characters.
fn frame_like() -> impl Strategy<Value = String> {
    let token = prop_oneof![
        Just("{".to_owned()),
        Just("}".to_owned()),
        Just("[".to_owned()),
        Just("]".to_owned()),
        Just(",".to_owned()),
        Just(":".to_owned()),
        Just(r#""type""#.to_owned()),
        Just(r#""hello""#.to_owned()),
        Just(r#""heartbeat""#.to_owned()),
        Just(r#""event""#.to_owned()),
        Just(r#""progress""#.to_owned()),
        Just(r#""command""#.to_owned()),
        Just(r#""error""#.to_owned()),
        Just(r#""seq""#.to_owned()),
        Just(r#""protocol_version""#.to_owned()),
        Just(r#""current_release""#.to_owned()),
        Just("null".to_owned()),
        any::<i64>().prop_map(|n| n.to_string()),
        any::<u64>().prop_map(|n| n.to_string()),
        any::<f64>().prop_map(|n| n.to_string()),
        "\\PC{0,8}",
        "\"[^\"]{0,8}\"",
    ];
    prop::collection::vec(token, 0..24).prop_map(|parts| parts.concat())
}

proptest! {
    #[test]
    fn arbitrary_text_never_panics_the_frame_decoder(text in "\\PC{0,256}") {
        let _ = decode::<AgentMessage>(&text, MAX_FRAME_BYTES).map_err(|e| e.code());
        let _ = decode::<ServerMessage>(&text, MAX_FRAME_BYTES).map_err(|e| e.code());
        let _ = hello_version(&text);
    }

    #[test]
    fn frame_like_text_never_panics_the_frame_decoder(text in frame_like()) {
        if let Ok(mut msg) = decode::<AgentMessage>(&text, MAX_FRAME_BYTES) {
            let _ = msg.seq();
            let _ = rules::sanitize(&mut msg);
        }
        let _ = decode::<ServerMessage>(&text, MAX_FRAME_BYTES).map_err(|e| e.to_string());
        let _ = hello_version(&text);
    }

    #[test]
    fn arbitrary_bytes_never_panic_the_manifest_parser(bytes in prop::collection::vec(any::<u8>(), 0..512)) {
        let _ = ReleaseManifest::parse(&bytes).map_err(|e| e.to_string());
    }

    #[test]
    fn manifest_like_text_never_panics_the_manifest_parser(
        version in "\\PC{0,12}",
        path in "[a-z./\\\\]{0,12}",
        digest in "(sha256:)?[0-9a-fA-F]{0,66}",
        size in 0u64..1 << 40,
        mode in 0u32..0o10000,
        extra in frame_like(),
    ) {
        let quote = |s: &str| serde_json::to_string(s).unwrap();
        let text = format!(
            r#"{{"mediaType":{},"version":{},"files":[{{"path":{},"digest":{},"size":{size},"mode":{mode}}}{extra}]}}"#,
            quote(MANIFEST_MEDIA_TYPE),
            quote(&version),
            quote(&path),
            quote(&digest),
        );
        let _ = ReleaseManifest::parse(text.as_bytes()).map_err(|e| e.to_string());
    }

    #[test]
    fn the_rule_checks_agree_with_the_crd_patterns(text in "(sha256:)?[0-9a-fA-F._+ -]{0,130}") {
        let digest = regex::Regex::new(DIGEST_PATTERN).unwrap();
        let version = regex::Regex::new(VERSION_PATTERN).unwrap();
        prop_assert_eq!(is_valid_digest(&text), digest.is_match(&text));
        let fits = (1..=MAX_VERSION_CHARS as usize).contains(&text.chars().count());
        prop_assert_eq!(is_valid_version(&text), fits && version.is_match(&text));
        if let Ok(normal) = rules::normalize_digest(&text) {
            prop_assert!(digest.is_match(&normal));
        }
    }

    /// The agent-side check of a health reason is the CRD's pattern and length.
    #[test]
    fn the_health_reason_check_agrees_with_the_crd_pattern(text in "[A-Za-z0-9 _]{0,70}") {
        let pattern = regex::Regex::new(rules::HEALTH_REASON_PATTERN).unwrap();
        let fits = (1..=rules::MAX_HEALTH_REASON_CHARS as usize).contains(&text.len());
        prop_assert_eq!(rules::is_valid_health_reason(&text), fits && pattern.is_match(&text));
    }
}
