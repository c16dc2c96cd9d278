//! A real browser for the dashboard's tests: Debian's headless Chromium driven over the Chrome
//! DevTools Protocol (a WebSocket): open a page, evaluate JavaScript in it, wait for a
//! condition, take a screenshot. No WebDriver or Node: the protocol's few calls are written here.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context as _, Result, bail, ensure};
use base64::Engine as _;
use futures::{SinkExt as _, StreamExt as _};
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;

use crate::log_dir;

type Socket =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

/// How long one protocol call may take.
const CALL_TIMEOUT: Duration = Duration::from_secs(30);

/// A headless Chromium with one page; killed when dropped.
pub struct Browser {
    child: Child,
    socket: Socket,
    session: String,
    next_id: u64,
    _profile: tempfile::TempDir,
}

impl Browser {
    /// Starts Chromium (`/usr/bin/chromium`, installed by `scripts/setup.sh`) with a fresh
    /// profile and a `width`×`height` page. Its output goes to `chromium-<name>.log`.
    pub async fn start(name: &str, width: u32, height: u32) -> Result<Self> {
        let binary =
            which("chromium").context("chromium is not installed: run scripts/setup.sh")?;
        let profile = tempfile::tempdir()?;
        let log = std::fs::File::create(log_dir().join(format!("chromium-{name}.log")))?;
        let child = Command::new(binary)
            .args([
                "--headless=new",
                // Root may not use Chromium's sandbox; the pages are our own, on loopback.
                "--no-sandbox",
                "--disable-gpu",
                "--disable-dev-shm-usage",
                "--no-first-run",
                "--no-default-browser-check",
                "--disable-extensions",
                "--disable-background-networking",
                "--disable-sync",
                "--remote-debugging-address=127.0.0.1",
                "--remote-debugging-port=0",
                &format!("--window-size={width},{height}"),
                &format!("--user-data-dir={}", profile.path().display()),
                "about:blank",
            ])
            .stdin(Stdio::null())
            .stdout(log.try_clone()?)
            .stderr(log)
            .spawn()
            .context("starting chromium")?;
        let endpoint = devtools_endpoint(profile.path()).await?;
        let (socket, _) = tokio_tungstenite::connect_async(&endpoint)
            .await
            .with_context(|| format!("connecting to {endpoint}"))?;
        let mut browser = Self {
            child,
            socket,
            session: String::new(),
            next_id: 0,
            _profile: profile,
        };
        let target = browser
            .call(None, "Target.createTarget", json!({"url": "about:blank"}))
            .await?;
        let target_id = target["targetId"]
            .as_str()
            .context("no targetId")?
            .to_owned();
        let attached = browser
            .call(
                None,
                "Target.attachToTarget",
                json!({"targetId": target_id, "flatten": true}),
            )
            .await?;
        browser.session = attached["sessionId"]
            .as_str()
            .context("no sessionId")?
            .to_owned();
        browser
            .page(
                "Emulation.setDeviceMetricsOverride",
                json!({"width": width, "height": height, "deviceScaleFactor": 1, "mobile": false}),
            )
            .await?;
        Ok(browser)
    }

    /// Loads `url` and waits until the document has loaded.
    pub async fn goto(&mut self, url: &str) -> Result<()> {
        let nav = self.page("Page.navigate", json!({"url": url})).await?;
        if let Some(error) = nav["errorText"].as_str() {
            bail!("loading {url}: {error}");
        }
        self.wait_for(
            "the page to load",
            "document.readyState === 'complete'",
            Duration::from_secs(20),
        )
        .await?;
        Ok(())
    }

    /// The value of the JavaScript expression `expr` in the page (promises awaited).
    pub async fn eval(&mut self, expr: &str) -> Result<Value> {
        let out = self
            .page(
                "Runtime.evaluate",
                json!({"expression": expr, "returnByValue": true, "awaitPromise": true}),
            )
            .await?;
        if let Some(ex) = out.get("exceptionDetails") {
            bail!(
                "{expr}: {}",
                ex["exception"]["description"]
                    .as_str()
                    .unwrap_or(&ex.to_string())
            );
        }
        Ok(out["result"]["value"].clone())
    }

    /// Polls `expr` until it is truthy (not null, false, 0 or ""); returns its value.
    pub async fn wait_for(&mut self, what: &str, expr: &str, within: Duration) -> Result<Value> {
        let deadline = Instant::now() + within;
        loop {
            let value = self.eval(expr).await?;
            let truthy = match &value {
                Value::Null | Value::Bool(false) => false,
                Value::Number(n) => n.as_f64() != Some(0.0),
                Value::String(s) => !s.is_empty(),
                _ => true,
            };
            if truthy {
                return Ok(value);
            }
            if Instant::now() > deadline {
                let status = self
                    .eval("document.getElementById('status')?.textContent")
                    .await;
                bail!(
                    "waited {within:?} for {what} ({expr}): last {value}; page status {status:?}"
                );
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }

    /// A PNG of the whole page, written to `path`; returns its size in bytes.
    pub async fn screenshot(&mut self, path: &Path) -> Result<usize> {
        let shot = self
            .page(
                "Page.captureScreenshot",
                json!({"format": "png", "captureBeyondViewport": true}),
            )
            .await?;
        let png = base64::engine::general_purpose::STANDARD
            .decode(shot["data"].as_str().context("no screenshot data")?)?;
        ensure!(png.starts_with(b"\x89PNG"), "not a PNG");
        std::fs::write(path, &png)?;
        Ok(png.len())
    }

    async fn page(&mut self, method: &str, params: Value) -> Result<Value> {
        let session = self.session.clone();
        self.call(Some(&session), method, params).await
    }

    /// One protocol call; events that arrive meanwhile are skipped.
    async fn call(&mut self, session: Option<&str>, method: &str, params: Value) -> Result<Value> {
        self.next_id += 1;
        let id = self.next_id;
        let mut request = json!({"id": id, "method": method, "params": params});
        if let Some(s) = session {
            request["sessionId"] = json!(s);
        }
        self.socket.send(Message::text(request.to_string())).await?;
        let answer = tokio::time::timeout(CALL_TIMEOUT, async {
            while let Some(message) = self.socket.next().await {
                let Message::Text(text) = message? else {
                    continue;
                };
                let value: Value = serde_json::from_str(&text)?;
                if value["id"] == json!(id) {
                    return Ok(value);
                }
            }
            bail!("chromium closed the DevTools connection")
        })
        .await
        .with_context(|| format!("{method} took over {CALL_TIMEOUT:?}"))??;
        if let Some(error) = answer.get("error") {
            bail!("{method}: {error}");
        }
        Ok(answer["result"].clone())
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The browser's DevTools WebSocket URL, from the `DevToolsActivePort` file Chromium writes
/// into its profile (port, then path) once it listens.
async fn devtools_endpoint(profile: &Path) -> Result<String> {
    let file = profile.join("DevToolsActivePort");
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        if let Ok(text) = std::fs::read_to_string(&file) {
            let mut lines = text.lines();
            if let (Some(port), Some(path)) = (lines.next(), lines.next()) {
                return Ok(format!("ws://127.0.0.1:{port}{path}"));
            }
        }
        ensure!(
            Instant::now() < deadline,
            "chromium did not open its DevTools port within 30 s (see its log)"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

fn which(name: &str) -> Option<PathBuf> {
    std::env::var_os("PATH")?
        .to_str()?
        .split(':')
        .map(|d| Path::new(d).join(name))
        .find(|p| p.is_file())
}
