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
}
