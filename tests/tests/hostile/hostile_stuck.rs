//! A peer that stops reading (issue 12, point 7): a robot that keeps the gateway sending while
//! never reading its socket has its session ended after the send timeout, counted, and its
//! connection slot freed, while the gateway's health endpoints keep answering.

use std::time::Duration;

use futures::SinkExt;
use lekiwi_protocol::ROBOT_HEADER;
use lekiwi_tests::{
    ControlPlane, OperatorProcess, connect_agent, enrollment_token, gateway_url, http_get,
    namespace, wait_for,
};
use tokio::net::{TcpSocket, TcpStream};
use tokio_tungstenite::WebSocketStream;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::tungstenite::http::HeaderValue;

const ENDED: &str = r#"lekiwi_gateway_sessions_ended_total{kind="send_timeout"}"#;

/// Both health endpoints (operator and gateway port) answer 200.
async fn healthy(op: &OperatorProcess) -> bool {
    for port in [op.http_port, op.gateway_port] {
        match tokio::time::timeout(Duration::from_secs(2), http_get(port, "/healthz")).await {
            Ok(Ok((200, _))) => {}
            _ => return false,
        }
    }
    true
}

/// Upgrades a TCP connection with a 4 KiB receive buffer to a WebSocket as `robot`.
async fn raw_upgrade(
    port: u16,
    url: &str,
    token: &str,
    robot: &str,
) -> anyhow::Result<WebSocketStream<TcpStream>> {
    let socket = TcpSocket::new_v4()?;
    socket.set_recv_buffer_size(4096)?;
    let tcp = socket.connect(format!("127.0.0.1:{port}").parse()?).await?;
    let mut request = url.into_client_request()?;
    let headers = request.headers_mut();
    headers.insert(
        "authorization",
        HeaderValue::from_str(&format!("Bearer {token}"))?,
    );
    headers.insert(ROBOT_HEADER, HeaderValue::from_str(robot)?);
    Ok(tokio_tungstenite::client_async(request, tcp).await?.0)
}

#[tokio::test]
async fn a_session_that_stops_reading_is_closed_and_its_slot_freed() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hstuck").await?;
    let args = [
        "--send-timeout-seconds",
        "2",
        "--max-connections",
        "1",
        "--agent-rate",
        "1000000",
        "--agent-burst",
        "1000000",
    ];
    let mut op = OperatorProcess::start(cp, &ns, "hs-stuck", &args)?;
    op.wait_ready().await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let (ws, enrolled) = connect_agent(&op, &enroll, &format!("{ns}/kiwi-1")).await?;
    let own = enrolled
        .robot_token
        .ok_or_else(|| anyhow::anyhow!("enrollment gave no robot token"))?;
    drop(ws);

    // A raw TCP client with a small receive buffer upgrades as the robot and says hello (retried:
    // the enrollment session's slot is freed a moment after it ends)...
    let url = gateway_url(&op);
    let robot = format!("{ns}/kiwi-1");
    let mut stuck = wait_for(
        "a free connection slot",
        Duration::from_secs(10),
        || async { raw_upgrade(op.gateway_port, &url, &own, &robot).await.ok() },
    )
    .await?;
    let hello = lekiwi_protocol::encode(&lekiwi_tests::hello());
    stuck.send(Message::text(hello)).await?;
    // ...then makes the gateway answer many frames (each binary frame gets an error frame)
    // without ever reading, until its own writes stall or the gateway drops it.
    let mut sent = 0u32;
    while sent < 400_000 {
        let batch = async {
            for _ in 0..1000 {
                stuck.feed(Message::binary(vec![0u8])).await?;
            }
            stuck.flush().await
        };
        match tokio::time::timeout(Duration::from_secs(1), batch).await {
            Ok(Ok(())) => sent += 1000,
            Ok(Err(_)) | Err(_) => break,
        }
    }
    println!("sent {sent} frames before stopping");
    assert!(
        healthy(&op).await,
        "/healthz answers while the session is stuck"
    );

    // Within a few seconds the gateway gives up on the session and counts why.
    wait_for(
        "the stuck session to end",
        Duration::from_secs(20),
        || async {
            assert!(healthy(&op).await, "/healthz answers throughout");
            (op.metric(ENDED).await == Some(1.0)).then_some(())
        },
    )
    .await?;
    assert!(
        op.log_text().contains("agent stopped reading"),
        "the gateway logs why it closed the session"
    );
    // The slot is free although the stuck client still holds its socket: with
    // --max-connections 1, the real robot connects again.
    let (_ws, welcome) = wait_for("the freed slot", Duration::from_secs(5), || async {
        connect_agent(&op, &own, &robot).await.ok()
    })
    .await?;
    assert!(welcome.robot_token.is_none());
    drop(stuck);
    op.terminate()?;
    Ok(())
}
