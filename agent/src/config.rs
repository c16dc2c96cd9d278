//! Agent configuration: a YAML file, overridden by flags and `LEKIWI_*` environment variables.

use std::path::{Path, PathBuf};

use clap::Parser;
use serde::{Deserialize, Serialize};

/// Errors loading the configuration.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The config file exists but cannot be read.
    #[error("cannot read config file {path}: {source}")]
    ReadConfig {
        path: PathBuf,
        source: std::io::Error,
    },
    /// The config file is not valid YAML of the expected shape.
    #[error("invalid config file {path}: {source}")]
    ParseConfig {
        path: PathBuf,
        source: serde_yaml::Error,
    },
    /// A required setting is missing everywhere.
    #[error("no gateway configured: set `gateway` in {path}, --gateway or LEKIWI_GATEWAY_URL")]
    MissingGateway { path: PathBuf },
}

/// Command-line flags; each also reads an environment variable and overrides the file.
#[derive(Debug, Parser)]
#[command(
    name = "lekiwi-agent",
    version,
    about = "Connects a LeKiwi robot to its fleet's gateway"
)]
pub struct Flags {
    /// Config file to read.
    #[arg(long, env = "LEKIWI_CONFIG", default_value = "/etc/lekiwi/agent.yaml")]
    pub config: PathBuf,
    /// WebSocket URL of the gateway, e.g. wss://fleet.example.com/v1/agent.
    #[arg(long, env = "LEKIWI_GATEWAY_URL")]
    pub gateway: Option<String>,
    /// Directory for the token, outbox and releases.
    #[arg(long, env = "LEKIWI_STATE_DIR")]
    pub state_dir: Option<PathBuf>,
    /// Name of this robot (defaults to the host name).
    #[arg(long, env = "LEKIWI_ROBOT_NAME")]
    pub robot_name: Option<String>,
    /// Print the effective configuration as YAML and exit.
    #[arg(long)]
    pub print_config: bool,
}

/// The config file's shape; every key optional.
#[derive(Debug, Default, Deserialize)]
#[serde(rename_all = "camelCase", deny_unknown_fields)]
struct FileConfig {
    gateway: Option<String>,
    state_dir: Option<PathBuf>,
    robot_name: Option<String>,
}

/// The effective configuration.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct Config {
    /// Gateway WebSocket URL.
    pub gateway: String,
    /// State directory.
    pub state_dir: PathBuf,
    /// Robot name.
    pub robot_name: String,
}

impl Config {
    /// Merges the file (if present) with flags and environment; flags win.
    pub fn load(flags: &Flags, hostname: &str) -> Result<Self, Error> {
        let file = read_file(&flags.config)?;
        let gateway =
            flags
                .gateway
                .clone()
                .or(file.gateway)
                .ok_or_else(|| Error::MissingGateway {
                    path: flags.config.clone(),
                })?;
        Ok(Self {
            gateway,
            state_dir: flags
                .state_dir
                .clone()
                .or(file.state_dir)
                .unwrap_or_else(|| PathBuf::from("/var/lib/lekiwi")),
            robot_name: flags
                .robot_name
                .clone()
                .or(file.robot_name)
                .unwrap_or_else(|| hostname.to_owned()),
        })
    }
}

fn read_file(path: &Path) -> Result<FileConfig, Error> {
    match std::fs::read_to_string(path) {
        Ok(text) => serde_yaml::from_str(&text).map_err(|source| Error::ParseConfig {
            path: path.to_owned(),
            source,
        }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(FileConfig::default()),
        Err(source) => Err(Error::ReadConfig {
            path: path.to_owned(),
            source,
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flags_override_file_and_file_overrides_defaults() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("agent.yaml");
        std::fs::write(&path, "gateway: wss://file/agent\nrobotName: from-file\n").unwrap();
        let flags = Flags::parse_from([
            "lekiwi-agent",
            "--config",
            path.to_str().unwrap(),
            "--robot-name",
            "kiwi-9",
        ]);
        let cfg = Config::load(&flags, "host").unwrap();
        assert_eq!(cfg.gateway, "wss://file/agent");
        assert_eq!(cfg.robot_name, "kiwi-9");
        assert_eq!(cfg.state_dir, PathBuf::from("/var/lib/lekiwi"));
    }

    #[test]
    fn bad_file_and_missing_gateway_are_clear_errors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("agent.yaml");
        std::fs::write(&path, "gatewy: typo\n").unwrap();
        let flags = Flags::parse_from(["lekiwi-agent", "--config", path.to_str().unwrap()]);
        let err = Config::load(&flags, "h").unwrap_err().to_string();
        assert!(err.contains("unknown field `gatewy`"), "{err}");

        let flags = Flags::parse_from(["lekiwi-agent", "--config", "/nonexistent/agent.yaml"]);
        let err = Config::load(&flags, "h").unwrap_err().to_string();
        assert!(err.contains("LEKIWI_GATEWAY_URL"), "{err}");
    }
}
