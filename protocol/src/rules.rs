//! The rules a `hello` or `heartbeat` field must meet to reach a `Robot`'s status: the single
//! source of truth that the gateway applies at the protocol boundary and that `lekiwi-crds`
//! writes into the CRD schema (its schema attributes name these constants).
//!
//! Each field is either *normalised* (an uppercase-hex digest is lowercased, free text is cut,
//! a teleoperation score is clamped) or *refused*: the field is dropped from the report and the
//! gateway answers with a non-fatal `invalid_field` error naming it (PROTOCOL.md §5.4).

use crate::messages::AgentMessage;
use crate::types::{Health, Release, SystemFacts, Teleoperation};

/// Pattern of a release version: letters, digits, `.`, `_`, `+` and `-`, starting with a letter
/// or digit.
pub const VERSION_PATTERN: &str = r"^[A-Za-z0-9][A-Za-z0-9._+-]*$";
/// Longest release version, in characters.
pub const MAX_VERSION_CHARS: u32 = 128;
/// Pattern of a release digest as stored: `sha256:` and 64 lowercase hex digits.
pub const DIGEST_PATTERN: &str = r"^sha256:[a-f0-9]{64}$";
/// Longest agent version, host name, OS, kernel or architecture, in characters; longer text is
/// cut to it.
pub const MAX_TEXT_CHARS: u32 = 256;
/// Longest health message, in characters; a longer one is cut to it.
pub const MAX_MESSAGE_CHARS: u32 = 1024;
/// Pattern of a health reason: a CamelCase word, as a Kubernetes condition reason.
pub const HEALTH_REASON_PATTERN: &str = r"^[A-Z][A-Za-z0-9]*$";
/// Longest health reason, in characters.
pub const MAX_HEALTH_REASON_CHARS: u32 = 64;
/// Largest `memory_bytes`: Kubernetes stores integers as int64.
pub const MAX_MEMORY_BYTES: u64 = i64::MAX as u64;

/// A field the rules refuse.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("field `{field}` refused: {reason}")]
pub struct FieldError {
    /// Path of the field in the message, e.g. `current_release.digest`.
    pub field: &'static str,
    /// Which rule it breaks.
    pub reason: String,
}

/// Whether `v` is a valid release version ([`VERSION_PATTERN`], 1 to [`MAX_VERSION_CHARS`]).
pub fn is_valid_version(v: &str) -> bool {
    let mut bytes = v.bytes();
    let first_ok = bytes.next().is_some_and(|b| b.is_ascii_alphanumeric());
    first_ok
        && v.len() <= MAX_VERSION_CHARS as usize
        && bytes.all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'+' | b'-'))
}

/// Whether `d` matches [`DIGEST_PATTERN`] exactly (lowercase).
pub fn is_valid_digest(d: &str) -> bool {
    d.strip_prefix("sha256:").is_some_and(|hex| {
        hex.len() == 64 && hex.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f'))
    })
}

/// Whether `r` is a valid health reason ([`HEALTH_REASON_PATTERN`], 1 to
/// [`MAX_HEALTH_REASON_CHARS`]).
pub fn is_valid_health_reason(r: &str) -> bool {
    let mut bytes = r.bytes();
    bytes.next().is_some_and(|b| b.is_ascii_uppercase())
        && r.len() <= MAX_HEALTH_REASON_CHARS as usize
        && bytes.all(|b| b.is_ascii_alphanumeric())
}

/// The digest in its stored form (hex lowercased), or why it is refused.
pub fn normalize_digest(d: &str) -> Result<String, String> {
    let lower = match d.strip_prefix("sha256:") {
        Some(hex) => format!("sha256:{}", hex.to_ascii_lowercase()),
        None => d.to_owned(),
    };
    if is_valid_digest(&lower) {
        Ok(lower)
    } else {
        Err("must be `sha256:` followed by 64 hex digits".into())
    }
}

/// `text` cut to at most `max` characters.
pub fn cut_text(text: &str, max: u32) -> String {
    text.chars().take(max as usize).collect()
}

/// A reported release in its stored form, or the refused field (`current_release.version` or
/// `current_release.digest`).
pub fn check_release(r: &Release) -> Result<Release, FieldError> {
    if !is_valid_version(&r.version) {
        return Err(FieldError {
            field: "current_release.version",
            reason: format!(
                "must match {VERSION_PATTERN} with 1 to {MAX_VERSION_CHARS} characters"
            ),
        });
    }
    let digest = normalize_digest(&r.digest).map_err(|reason| FieldError {
        field: "current_release.digest",
        reason,
    })?;
    Ok(Release {
        version: r.version.clone(),
        digest,
    })
}

/// Applies the rules to a `hello` or `heartbeat` in place: normalised fields are rewritten,
/// refused ones removed (a refused release removes the whole `current_release`), and the refused
/// fields returned. Other messages are left alone.
pub fn sanitize(msg: &mut AgentMessage) -> Vec<FieldError> {
    let mut refused = Vec::new();
    match msg {
        AgentMessage::Hello {
            agent_version,
            agent_digest,
            system,
            current_release,
            health,
            teleoperation,
            ..
        } => {
            *agent_version = cut_text(agent_version, MAX_TEXT_CHARS);
            if let Some(d) = agent_digest.take() {
                match normalize_digest(&d) {
                    Ok(d) => *agent_digest = Some(d),
                    Err(reason) => refused.push(FieldError {
                        field: "agent_digest",
                        reason,
                    }),
                }
            }
            sanitize_system(system, &mut refused);
            sanitize_reports(current_release, health, teleoperation, &mut refused);
        }
        AgentMessage::Heartbeat {
            current_release,
            health,
            teleoperation,
            ..
        } => sanitize_reports(current_release, health, teleoperation, &mut refused),
        _ => {}
    }
    refused
}

fn sanitize_system(system: &mut SystemFacts, refused: &mut Vec<FieldError>) {
    for text in [
        &mut system.hostname,
        &mut system.os,
        &mut system.kernel,
        &mut system.arch,
    ]
    .into_iter()
    .flatten()
    {
        *text = cut_text(text, MAX_TEXT_CHARS);
    }
    if let Some(bytes) = system.memory_bytes.filter(|b| *b > MAX_MEMORY_BYTES) {
        system.memory_bytes = None;
        refused.push(FieldError {
            field: "system.memory_bytes",
            reason: format!("{bytes} exceeds {MAX_MEMORY_BYTES}"),
        });
    }
}

fn sanitize_reports(
    release: &mut Option<Release>,
    health: &mut Option<Health>,
    teleoperation: &mut Option<Teleoperation>,
    refused: &mut Vec<FieldError>,
) {
    if let Some(r) = release.take() {
        match check_release(&r) {
            Ok(r) => *release = Some(r),
            Err(e) => refused.push(e),
        }
    }
    if let Some(h) = health.as_mut() {
        if let Some(message) = h.message.as_mut() {
            *message = cut_text(message, MAX_MESSAGE_CHARS);
        }
        if h.reason
            .as_deref()
            .is_some_and(|r| !is_valid_health_reason(r))
        {
            h.reason = None;
            refused.push(FieldError {
                field: "health.reason",
                reason: format!(
                    "must match {HEALTH_REASON_PATTERN} and be at most {MAX_HEALTH_REASON_CHARS} characters"
                ),
            });
        }
    }
    if let Some(t) = teleoperation.as_mut() {
        // NaN cannot arrive in JSON; anything else lands in 0..=1.
        t.score = t.score.filter(|s| s.is_finite()).map(|s| s.clamp(0.0, 1.0));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn heartbeat(release: Release) -> AgentMessage {
        AgentMessage::Heartbeat {
            sent_at_ms: 1,
            rtt_ms: None,
            vitals: Default::default(),
            current_release: Some(release),
            health: None,
            teleoperation: None,
        }
    }

    #[test]
    fn the_documents_own_examples_keep_the_rules() {
        let doc = include_str!("../PROTOCOL.md");
        let frames: Vec<&str> = doc
            .lines()
            .filter(|l| {
                l.starts_with(r#"{"type":"hello""#) || l.starts_with(r#"{"type":"heartbeat""#)
            })
            .collect();
        assert_eq!(frames.len(), 2, "{frames:?}");
        for frame in frames {
            let mut msg: AgentMessage = crate::decode(frame, usize::MAX).unwrap();
            assert_eq!(sanitize(&mut msg), Vec::new(), "{frame}");
        }
    }

    #[test]
    fn the_issues_examples_are_refused_or_normalised() {
        let hex = "AB".repeat(32);
        let mut upper = heartbeat(Release {
            version: "1.0".into(),
            digest: format!("sha256:{hex}"),
        });
        assert!(sanitize(&mut upper).is_empty());
        let AgentMessage::Heartbeat {
            current_release: Some(r),
            ..
        } = upper
        else {
            panic!()
        };
        assert_eq!(r.digest, format!("sha256:{}", "ab".repeat(32)));
        for (version, digest, field) in [
            ("1.0", "sha256:11", "current_release.digest"),
            ("", "sha256:00", "current_release.version"),
            ("1.0 beta", "sha256:00", "current_release.version"),
        ] {
            let mut msg = heartbeat(Release {
                version: version.into(),
                digest: digest.into(),
            });
            let refused = sanitize(&mut msg);
            assert_eq!(refused.len(), 1, "{version} {digest}");
            assert_eq!(refused[0].field, field);
            assert!(matches!(
                msg,
                AgentMessage::Heartbeat {
                    current_release: None,
                    ..
                }
            ));
        }
        let mut system = SystemFacts {
            memory_bytes: Some(u64::MAX),
            hostname: Some("h".repeat(1000)),
            ..Default::default()
        };
        let mut refused = Vec::new();
        sanitize_system(&mut system, &mut refused);
        assert_eq!(refused[0].field, "system.memory_bytes");
        assert_eq!(system.memory_bytes, None);
        assert_eq!(system.hostname.unwrap().len(), MAX_TEXT_CHARS as usize);
    }

    /// A hello's agent digest is lowercased, or dropped and named when it is no digest; the
    /// rest of the hello stands.
    #[test]
    fn a_hellos_agent_digest_is_normalised_or_refused() {
        let hello = |digest: &str| AgentMessage::Hello {
            protocol_version: crate::PROTOCOL_VERSION,
            agent_version: "0.2.0".into(),
            agent_digest: Some(digest.into()),
            system: SystemFacts::default(),
            current_release: None,
            last_acked_seq: None,
            health: None,
            teleoperation: None,
            features: Vec::new(),
        };
        let digest_of = |msg: &AgentMessage| match msg {
            AgentMessage::Hello { agent_digest, .. } => agent_digest.clone(),
            _ => panic!(),
        };
        let mut upper = hello(&format!("sha256:{}", "CD".repeat(32)));
        assert!(sanitize(&mut upper).is_empty());
        assert_eq!(
            digest_of(&upper),
            Some(format!("sha256:{}", "cd".repeat(32)))
        );
        for bad in [
            "",
            "sha256:12",
            "md5:00",
            &format!("sha256:{}", "g".repeat(64)),
        ] {
            let mut msg = hello(bad);
            let refused = sanitize(&mut msg);
            assert_eq!(refused.len(), 1, "{bad:?}");
            assert_eq!(refused[0].field, "agent_digest");
            assert_eq!(digest_of(&msg), None, "{bad:?}");
        }
    }

    /// A health reason that is no CamelCase word is refused; the verdict itself stands.
    #[test]
    fn a_health_reason_must_be_one_camel_case_word() {
        for (reason, kept) in [
            ("HostProcessNotRunning", true),
            ("DiskFull2", true),
            ("disk full", false),
            ("diskFull", false),
            ("", false),
            (&"A".repeat(65), false),
        ] {
            let mut health = Some(Health {
                healthy: false,
                message: None,
                reason: Some(reason.to_owned()),
            });
            let mut refused = Vec::new();
            sanitize_reports(&mut None, &mut health, &mut None, &mut refused);
            let health = health.unwrap();
            assert!(!health.healthy);
            assert_eq!(health.reason.is_some(), kept, "{reason}");
            assert_eq!(refused.len(), usize::from(!kept), "{reason}");
        }
    }
}
