//! The files `lekiwi-agent join` owns on the robot, under a root directory: its drop-in, the
//! gateway's CA and the enrollment token. Each is written only when its content changes,
//! atomically and with its mode; the lab's own `agent.yaml` is never written.

use std::io::Write as _;
use std::os::unix::fs::{OpenOptionsExt, PermissionsExt};
use std::path::{Path, PathBuf};

use lekiwi_protocol::join::{CA_FILE, ENROLLMENT_TOKEN_FILE, JOIN_DROP_IN};
use serde::{Deserialize, Serialize};

use super::Error;

/// The robot's file system as `join` sees it: `/` on a robot, a directory in tests.
#[derive(Clone, Debug)]
pub struct Root(pub PathBuf);

impl Root {
    /// `path` (absolute, as on the robot) under the root.
    pub fn at(&self, path: &str) -> PathBuf {
        self.0.join(path.trim_start_matches('/'))
    }

    /// `path` under the root, as a string for a configuration file.
    pub fn shown(&self, path: &str) -> String {
        self.at(path).to_string_lossy().into_owned()
    }

    /// Whether this is the real root.
    pub fn is_slash(&self) -> bool {
        self.0 == Path::new("/")
    }
}

/// The keys of the join drop-in.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct DropIn {
    /// The gateway's agent URL.
    pub gateway: String,
    /// The CA file (under the root).
    #[serde(default)]
    pub ca_file: Option<String>,
    /// `namespace/name`, unless the robot is named after its host.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub robot_name: Option<String>,
    /// The enrollment token's file, when joining with a fleet enrollment token.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub enrollment_token_file: Option<String>,
    /// The state directory, only when the root is not `/`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub state_dir: Option<String>,
}

/// What the drop-in says before the keys.
const HEADER: &str = "# Written by `lekiwi-agent join`: run it again to change this file (--force to \
                      join another gateway).\n# The lab's own settings belong in \
                      /etc/lekiwi/agent.yaml, which join never writes; a later drop-in overrides \
                      this one.\n";

impl DropIn {
    /// The file's text.
    pub fn render(&self) -> String {
        format!(
            "{HEADER}{}",
            serde_yaml::to_string(self).unwrap_or_default()
        )
    }
}

/// What is on disk already from an earlier join.
#[derive(Debug, Default)]
pub struct Existing {
    /// The drop-in's keys, if it exists.
    pub drop_in: Option<DropIn>,
    /// The CA file's text, if it exists.
    pub ca_pem: Option<String>,
}

impl Existing {
    /// Reads the drop-in and the CA under `root`; a drop-in that is not ours counts as absent.
    pub fn read(root: &Root) -> Result<Self, Error> {
        let drop_in = read_optional(&root.at(JOIN_DROP_IN))?
            .and_then(|text| serde_yaml::from_str::<DropIn>(&text).ok());
        let ca_pem = read_optional(&root.at(CA_FILE))?;
        Ok(Self { drop_in, ca_pem })
    }
}

fn read_optional(path: &Path) -> Result<Option<String>, Error> {
    match std::fs::read_to_string(path) {
        Ok(text) => Ok(Some(text)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(source) => Err(Error::Io {
            path: path.to_owned(),
            source,
        }),
    }
}

/// Writes `content` to `path` with `mode` unless the file holds exactly that with that mode;
/// returns whether it wrote. A temporary file renamed over the old one: never a torn file, and
/// a token file is never readable by others, not even for a moment.
pub fn write_if_changed(path: &Path, content: &str, mode: u32) -> Result<bool, Error> {
    let io = |source| Error::Io {
        path: path.to_owned(),
        source,
    };
    if let Ok(meta) = std::fs::metadata(path)
        && meta.permissions().mode() & 0o777 == mode
        && std::fs::read_to_string(path).is_ok_and(|old| old == content)
    {
        return Ok(false);
    }
    let dir = path.parent().unwrap_or(Path::new("/"));
    std::fs::create_dir_all(dir).map_err(io)?;
    let name = path.file_name().unwrap_or_default().to_string_lossy();
    let tmp = dir.join(format!(".{name}.join-tmp"));
    let mut file = std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .mode(0o600)
        .open(&tmp)
        .map_err(io)?;
    file.set_permissions(std::fs::Permissions::from_mode(mode))
        .map_err(io)?;
    file.write_all(content.as_bytes()).map_err(io)?;
    file.sync_all().map_err(io)?;
    drop(file);
    std::fs::rename(&tmp, path).map_err(io)?;
    Ok(true)
}

/// The files join writes, in order: the CA (0644), the enrollment token (0600) if any, the
/// drop-in (0644) last, so the agent never reads a drop-in naming files not yet there.
pub fn files(
    root: &Root,
    drop_in: &DropIn,
    ca_pem: &str,
    enrollment_token: Option<&str>,
) -> Vec<(PathBuf, String, u32)> {
    let mut files = vec![(root.at(CA_FILE), ca_pem.to_owned(), 0o644)];
    if let Some(token) = enrollment_token {
        files.push((root.at(ENROLLMENT_TOKEN_FILE), format!("{token}\n"), 0o600));
    }
    files.push((root.at(JOIN_DROP_IN), drop_in.render(), 0o644));
    files
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_is_written_once_with_its_mode_and_rewritten_when_it_differs() {
        let dir = tempfile::tempdir().unwrap();
        let root = Root(dir.path().to_owned());
        let token = root.at(ENROLLMENT_TOKEN_FILE);
        assert!(write_if_changed(&token, "lke_a\n", 0o600).unwrap());
        let mode = std::fs::metadata(&token).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode, 0o600);
        assert!(!write_if_changed(&token, "lke_a\n", 0o600).unwrap());
        std::fs::set_permissions(&token, std::fs::Permissions::from_mode(0o644)).unwrap();
        assert!(
            write_if_changed(&token, "lke_a\n", 0o600).unwrap(),
            "mode fixed"
        );
        assert!(write_if_changed(&token, "lke_b\n", 0o600).unwrap());
        assert_eq!(std::fs::read_to_string(&token).unwrap(), "lke_b\n");
    }

    #[test]
    fn the_drop_in_reads_back_as_written() {
        let drop_in = DropIn {
            gateway: "wss://gw:30443/v1/agent".into(),
            ca_file: Some("/etc/lekiwi/ca.crt".into()),
            robot_name: Some("lab/kiwi-1".into()),
            enrollment_token_file: Some("/etc/lekiwi/enrollment-token".into()),
            state_dir: None,
        };
        let text = drop_in.render();
        assert!(
            text.starts_with("# Written by `lekiwi-agent join`"),
            "{text}"
        );
        assert!(!text.contains("stateDir"), "{text}");
        assert_eq!(serde_yaml::from_str::<DropIn>(&text).unwrap(), drop_in);
    }
}
