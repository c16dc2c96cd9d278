//! The state directory: the robot's own token (mode 0600), written atomically.

use std::io::Write;
use std::os::unix::fs::{OpenOptionsExt, PermissionsExt};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

/// State directory errors.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file or directory could not be read or written.
    #[error("state directory: {path}: {source}")]
    Io {
        /// The file or directory (in the state directory) that failed.
        path: PathBuf,
        /// Why: permissions, a full disk, a missing mount.
        source: std::io::Error,
    },
    /// The credentials file is not what this agent writes.
    #[error("state directory: {path} is corrupt ({source}); delete it to enroll again")]
    Corrupt {
        /// The credentials file.
        path: PathBuf,
        /// Where its JSON is not what this agent writes.
        source: serde_json::Error,
    },
    /// `lekiwi-agent adopt` was given something it must not write.
    #[error("adopt: {0}")]
    Refused(String),
}

/// The robot's own credentials, issued by the gateway at enrollment.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Credentials {
    /// `namespace/name`, as the gateway named the robot in `welcome`.
    pub robot: String,
    /// The per-robot token, sent instead of the enrollment token from now on.
    pub token: String,
}

const CREDENTIALS: &str = "credentials.json";

fn io(path: &Path) -> impl Fn(std::io::Error) -> Error + '_ {
    move |source| Error::Io {
        path: path.to_owned(),
        source,
    }
}

/// Creates the state directory (mode 0700) if needed.
pub fn ensure_dir(dir: &Path) -> Result<(), Error> {
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let mode = std::fs::metadata(dir)
        .map_err(io(dir))?
        .permissions()
        .mode();
    if mode & 0o077 != 0 {
        std::fs::set_permissions(dir, std::fs::Permissions::from_mode(0o700)).map_err(io(dir))?;
    }
    Ok(())
}

/// The saved credentials, if the robot has enrolled.
pub fn load_credentials(dir: &Path) -> Result<Option<Credentials>, Error> {
    let path = dir.join(CREDENTIALS);
    match std::fs::read(&path) {
        Ok(bytes) => serde_json::from_slice(&bytes)
            .map(Some)
            .map_err(|source| Error::Corrupt { path, source }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(io(&path)(e)),
    }
}

/// Saves credentials durably: a 0600 temporary file, fsync, rename over the old one, fsync of
/// the directory. A crash leaves either the old or the new file, never a torn one.
pub fn save_credentials(dir: &Path, creds: &Credentials) -> Result<(), Error> {
    let path = dir.join(CREDENTIALS);
    let tmp = dir.join(format!("{CREDENTIALS}.tmp"));
    let mut file = std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .mode(0o600)
        .open(&tmp)
        .map_err(io(&tmp))?;
    // An existing temporary file keeps its mode through `open`; make sure.
    file.set_permissions(std::fs::Permissions::from_mode(0o600))
        .map_err(io(&tmp))?;
    let json = serde_json::to_vec(creds).unwrap_or_default();
    file.write_all(&json).map_err(io(&tmp))?;
    file.sync_all().map_err(io(&tmp))?;
    drop(file);
    std::fs::rename(&tmp, &path).map_err(io(&path))?;
    std::fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(io(dir))?;
    Ok(())
}

/// What [`adopt`] did.
#[derive(Debug, PartialEq, Eq)]
pub enum Adopted {
    /// The credentials were written.
    Written,
    /// The state directory already held exactly these credentials.
    Unchanged,
}

/// Longest token [`adopt`] accepts; the gateway issues 68 characters.
const MAX_TOKEN: usize = 512;

/// Takes over a robot's existing token (`lekiwi-agent adopt`): checks `robot` (`namespace/name`)
/// and `token` (a robot token, never an enrollment token) and saves them as the state
/// directory's credentials, unless it holds another robot's (a second robot's identity must
/// not be replaced by accident; delete `credentials.json` to do it on purpose).
pub fn adopt(dir: &Path, robot: &str, token: &str) -> Result<Adopted, Error> {
    let refuse = |why: String| Err(Error::Refused(why));
    let Some((ns, name)) = robot.split_once('/') else {
        return refuse(format!("--robot {robot:?} must be namespace/name"));
    };
    if !dns_label(ns) || !dns_subdomain(name) {
        return refuse(format!(
            "--robot {robot:?} is not a Kubernetes namespace/name (lower-case letters, digits, '-')"
        ));
    }
    if token.starts_with("lke_") {
        return refuse(
            "that is a fleet enrollment token; a new robot enrolls with it \
             (enrollmentTokenFile), adopt takes the robot's own token (lkr_...)"
                .into(),
        );
    }
    if !token.starts_with("lkr_")
        || token.len() > MAX_TOKEN
        || !token.bytes().all(|b| b.is_ascii_graphic())
    {
        return refuse(format!(
            "the token is not a robot token (lkr_ followed by at most {MAX_TOKEN} visible characters)"
        ));
    }
    ensure_dir(dir)?;
    let creds = Credentials {
        robot: robot.to_owned(),
        token: token.to_owned(),
    };
    match load_credentials(dir)? {
        Some(have) if have == creds => return Ok(Adopted::Unchanged),
        Some(have) if have.robot != creds.robot => {
            return refuse(format!(
                "{} holds the credentials of robot {}; delete it first to make this {robot}",
                dir.join(CREDENTIALS).display(),
                have.robot
            ));
        }
        _ => {}
    }
    save_credentials(dir, &creds)?;
    Ok(Adopted::Written)
}

/// An RFC 1123 label: a namespace.
fn dns_label(s: &str) -> bool {
    s.len() <= 63
        && !s.is_empty()
        && s.bytes()
            .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-')
        && !s.starts_with('-')
        && !s.ends_with('-')
}

/// An RFC 1123 subdomain: an object name.
fn dns_subdomain(s: &str) -> bool {
    s.len() <= 253 && s.split('.').all(dns_label)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn credentials_round_trip_with_private_permissions() {
        let dir = tempfile::tempdir().unwrap();
        let state = dir.path().join("state");
        ensure_dir(&state).unwrap();
        assert_eq!(
            std::fs::metadata(&state).unwrap().permissions().mode() & 0o777,
            0o700
        );
        assert_eq!(load_credentials(&state).unwrap(), None);
        let creds = Credentials {
            robot: "lab/kiwi-1".into(),
            token: "lkr_secret".into(),
        };
        save_credentials(&state, &creds).unwrap();
        save_credentials(&state, &creds).unwrap();
        assert_eq!(load_credentials(&state).unwrap(), Some(creds));
        let mode = std::fs::metadata(state.join(CREDENTIALS))
            .unwrap()
            .permissions()
            .mode();
        assert_eq!(mode & 0o777, 0o600);

        std::fs::write(state.join(CREDENTIALS), "{").unwrap();
        let err = load_credentials(&state).unwrap_err().to_string();
        assert!(err.contains("delete it to enroll again"), "{err}");
    }

    #[test]
    fn adopt_takes_a_robot_token_once_and_refuses_the_rest() {
        let dir = tempfile::tempdir().unwrap();
        let state = dir.path().join("state");
        let token = format!("lkr_{}", "a".repeat(64));
        let refused =
            |robot: &str, token: &str| adopt(&state, robot, token).unwrap_err().to_string();
        assert!(refused("kiwi-1", &token).contains("namespace/name"));
        assert!(refused("Lab/kiwi-1", &token).contains("not a Kubernetes"));
        assert!(refused("lab/kiwi_1", &token).contains("not a Kubernetes"));
        assert!(refused("lab/kiwi-1", "lke_abc").contains("enrollment token"));
        assert!(refused("lab/kiwi-1", "hunter2").contains("not a robot token"));
        assert!(refused("lab/kiwi-1", "lkr_a b").contains("not a robot token"));
        assert!(!state.exists(), "nothing written for a refusal");

        assert_eq!(
            adopt(&state, "lab/kiwi-1", &token).unwrap(),
            Adopted::Written
        );
        assert_eq!(
            adopt(&state, "lab/kiwi-1", &token).unwrap(),
            Adopted::Unchanged
        );
        let saved = load_credentials(&state).unwrap().unwrap();
        assert_eq!(
            (saved.robot.as_str(), saved.token.as_str()),
            ("lab/kiwi-1", token.as_str())
        );
        let mode = std::fs::metadata(state.join(CREDENTIALS))
            .unwrap()
            .permissions()
            .mode();
        assert_eq!(mode & 0o777, 0o600);

        // A rotated token of the same robot replaces the old one; another robot's never does.
        let rotated = format!("lkr_{}", "b".repeat(64));
        assert_eq!(
            adopt(&state, "lab/kiwi-1", &rotated).unwrap(),
            Adopted::Written
        );
        let err = refused("lab/kiwi-2", &token);
        assert!(err.contains("credentials of robot lab/kiwi-1"), "{err}");
        assert_eq!(load_credentials(&state).unwrap().unwrap().token, rotated);
    }
}
