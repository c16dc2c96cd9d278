//! OpenTelemetry: with `OTEL_EXPORTER_OTLP_ENDPOINT` set, the real operator exports its
//! reconcile and gateway-session spans over OTLP/HTTP to a collector (a stand-in that accepts
//! `POST /v1/traces` and keeps the bodies); without it, nothing is sent.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use lekiwi_tests::{
    AgentProcess, ControlPlane, OperatorProcess, enrollment_token_file, gateway_url, namespace,
    wait_for,
};
use serde_json::Value;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// A minimal OTLP/HTTP receiver: every request's path and JSON body.
#[derive(Clone, Default)]
struct Collector {
    received: Arc<Mutex<Vec<(String, Value)>>>,
}

impl Collector {
    async fn start(self) -> anyhow::Result<u16> {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let port = listener.local_addr()?.port();
        tokio::spawn(async move {
            while let Ok((mut sock, _)) = listener.accept().await {
                let received = self.received.clone();
                tokio::spawn(async move {
                    // One request per connection is enough for a stand-in; answer and close.
                    let mut buf = Vec::new();
                    let mut chunk = [0u8; 8192];
                    let (head_end, len) = loop {
                        let Ok(n) = sock.read(&mut chunk).await else {
                            return;
                        };
                        if n == 0 {
                            return;
                        }
                        buf.extend_from_slice(&chunk[..n]);
                        if let Some(i) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
                            let head = String::from_utf8_lossy(&buf[..i]).to_ascii_lowercase();
                            let len = head
                                .lines()
                                .find_map(|l| l.strip_prefix("content-length:"))
                                .and_then(|v| v.trim().parse::<usize>().ok())
                                .unwrap_or(0);
                            break (i + 4, len);
                        }
                    };
                    while buf.len() < head_end + len {
                        let Ok(n) = sock.read(&mut chunk).await else {
                            return;
                        };
                        if n == 0 {
                            break;
                        }
                        buf.extend_from_slice(&chunk[..n]);
                    }
                    let head = String::from_utf8_lossy(&buf[..head_end]).to_string();
                    let path = head.split_whitespace().nth(1).unwrap_or("").to_owned();
                    let body: Value =
                        serde_json::from_slice(&buf[head_end..]).unwrap_or(Value::Null);
                    received.lock().unwrap().push((path, body));
                    let _ = sock
                        .write_all(b"HTTP/1.1 200 OK\r\ncontent-type: application/json\r\ncontent-length: 2\r\nconnection: close\r\n\r\n{}")
                        .await;
                });
            }
        });
        Ok(port)
    }

    /// Names of all spans received, with their service name.
    fn spans(&self) -> Vec<(String, String)> {
        let mut out = Vec::new();
        for (_, body) in self.received.lock().unwrap().iter() {
            for rs in body["resourceSpans"].as_array().into_iter().flatten() {
                let service = rs["resource"]["attributes"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .find(|a| a["key"] == "service.name")
                    .and_then(|a| a["value"]["stringValue"].as_str())
                    .unwrap_or("")
                    .to_owned();
                for ss in rs["scopeSpans"].as_array().into_iter().flatten() {
                    for span in ss["spans"].as_array().into_iter().flatten() {
                        out.push((
                            service.clone(),
                            span["name"].as_str().unwrap_or("").to_owned(),
                        ));
                    }
                }
            }
        }
        out
    }
}

#[tokio::test]
async fn reconcile_and_session_spans_reach_an_otlp_collector() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "otel").await?;
    let collector = Collector::default();
    let port = collector.clone().start().await?;
    let endpoint = format!("http://127.0.0.1:{port}");
    let mut op = OperatorProcess::start_with_env(
        cp,
        &ns,
        "otel",
        &[],
        &[
            ("OTEL_EXPORTER_OTLP_ENDPOINT", endpoint.as_str()),
            ("OTEL_EXPORTER_OTLP_PROTOCOL", "http/json"),
            ("OTEL_SERVICE_NAME", "lekiwi-operator-test"),
            ("OTEL_BSP_SCHEDULE_DELAY", "200"),
        ],
    )?;
    op.wait_ready().await?;
    // A robot that connects: its Robot is reconciled, its connection is a `session` span.
    let dir = tempfile::tempdir()?;
    let token_file = dir.path().join("enroll");
    enrollment_token_file(&client, &ns, &token_file).await?;
    let mut agent = AgentProcess::start(
        &gateway_url(&op),
        &format!("{ns}/kiwi-otel"),
        &token_file,
        &dir.path().join("state"),
        &[],
    )?;
    agent.wait_connected(Duration::from_secs(30)).await?;
    // The session span ends when the connection does.
    agent.kill();
    let spans = wait_for(
        "reconcile and session spans",
        Duration::from_secs(30),
        || async {
            let spans = collector.spans();
            let names: Vec<&str> = spans.iter().map(|(_, n)| n.as_str()).collect();
            (names.contains(&"reconcile") && names.contains(&"session")).then_some(spans)
        },
    )
    .await
    .map_err(|e| anyhow::anyhow!("{e}\noperator log:\n{}", op.log_text()))?;
    assert!(
        spans
            .iter()
            .all(|(service, _)| service == "lekiwi-operator-test"),
        "service name from OTEL_SERVICE_NAME: {spans:?}"
    );
    let paths: Vec<String> = collector
        .received
        .lock()
        .unwrap()
        .iter()
        .map(|(p, _)| p.clone())
        .collect();
    assert!(paths.iter().all(|p| p == "/v1/traces"), "{paths:?}");
    assert!(op.log_text().contains("exporting spans over OTLP"));
    // A graceful stop flushes the exporter and exits cleanly.
    let status = op.terminate()?;
    assert!(status.success(), "{status}\n{}", op.log_text());

    // Without the variable: no exporter, nothing sent.
    let quiet = Collector::default();
    let _port = quiet.clone().start().await?;
    let mut op = OperatorProcess::start(cp, &ns, "otel-off", &[])?;
    op.wait_ready().await?;
    tokio::time::sleep(Duration::from_secs(2)).await;
    assert!(!op.log_text().contains("exporting spans over OTLP"));
    assert!(quiet.received.lock().unwrap().is_empty());
    Ok(())
}
