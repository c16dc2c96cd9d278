//! `lekiwi-agent` entry point.

use clap::Parser;
use lekiwi_agent::config::{Config, Flags};

fn main() -> anyhow::Result<()> {
    let flags = Flags::parse();
    let hostname = std::fs::read_to_string("/etc/hostname").unwrap_or_default();
    let config = Config::load(&flags, hostname.trim())?;
    if flags.print_config {
        print!("{}", serde_yaml::to_string(&config)?);
        return Ok(());
    }
    anyhow::bail!(
        "the agent's gateway connection is not implemented yet (see the protocol issue); use --print-config"
    )
}
