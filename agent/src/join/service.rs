//! The agent service after a join: enabled and started by systemd (restarted when join changed
//! its files), then watched through the agent's local status endpoint until it is connected.

use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};

use super::Error;
use crate::config::Config;

/// The systemd unit the `.deb` installs.
const UNIT: &str = "lekiwi-agent";

/// `systemctl enable --now`, or enable and restart when the files changed under a running agent.
pub fn start(changed: bool) -> Result<(), Error> {
    let steps: &[&[&str]] = if changed {
        &[&["enable", UNIT], &["restart", UNIT]]
    } else {
        &[&["enable", "--now", UNIT]]
    };
    for args in steps {
        let out = std::process::Command::new("systemctl")
            .args(*args)
            .output()
            .map_err(|e| {
                Error::Service(format!(
                    "cannot run systemctl ({e}); without systemd pass --no-start and start \
                     lekiwi-agent yourself"
                ))
            })?;
        if !out.status.success() {
            return Err(Error::Service(format!(
                "systemctl {} failed: {}",
                args.join(" "),
                String::from_utf8_lossy(&out.stderr).trim()
            )));
        }
    }
    println!(
        "{} {UNIT}",
        if changed {
            "enabled and restarted"
        } else {
            "enabled and started"
        }
    );
    Ok(())
}

/// Waits until the agent's status endpoint says it is connected to `gateway`, then prints the
/// robot's name and phase; `within` zero does not wait.
pub async fn wait_connected(config: &Config, gateway: &str, within: Duration) -> Result<(), Error> {
    if within.is_zero() {
        return Ok(());
    }
    let Some(addr) = config.status_addr() else {
        println!(
            "statusListen is off: cannot see when the agent connects; see `journalctl -u {UNIT}`"
        );
        return Ok(());
    };
    println!("waiting for the agent to reach the gateway (status at {addr})");
    let deadline = Instant::now() + within;
    let mut last = String::from("no answer from the agent's status endpoint");
    while Instant::now() < deadline {
        match status(addr).await {
            Ok(s) if s["connected"] == true && s["gateway"] == gateway => {
                let robot = s["robot"].as_str().unwrap_or_default();
                println!("robot {robot} joined: Online at {gateway}");
                return Ok(());
            }
            Ok(s) => last = format!("the agent is not connected yet (gateway {})", s["gateway"]),
            Err(e) => last = e,
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
    Err(Error::Service(format!(
        "the agent did not reach the gateway within {within:?} ({last}); see `journalctl -u {UNIT}`"
    )))
}

/// `GET /status` of the agent's endpoint (one request per connection, the body is JSON).
async fn status(addr: std::net::SocketAddr) -> Result<serde_json::Value, String> {
    let ask = async {
        let mut tcp = tokio::net::TcpStream::connect(addr).await?;
        tcp.write_all(b"GET /status HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n")
            .await?;
        let mut answer = Vec::new();
        tcp.take(1 << 20).read_to_end(&mut answer).await?;
        std::io::Result::Ok(answer)
    };
    let answer = tokio::time::timeout(Duration::from_secs(2), ask)
        .await
        .map_err(|_| "the status endpoint did not answer".to_owned())?
        .map_err(|e| format!("status endpoint: {e}"))?;
    let text = String::from_utf8_lossy(&answer);
    let body = text
        .split_once("\r\n\r\n")
        .map(|(_, b)| b)
        .ok_or("the status endpoint's answer has no body")?;
    serde_json::from_str(body).map_err(|e| format!("status endpoint: {e}"))
}
