//! A `graphql-transport-ws` client for the Fleet API's GraphQL WebSocket: connect (optionally
//! with a small receive buffer, to stand for a client that stops reading), `connection_init`
//! with a token, and the next message or close frame as JSON.

use std::time::Duration;

use anyhow::{Context as _, Result, ensure};
use futures::{SinkExt, StreamExt};
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;

use crate::OperatorProcess;

/// A GraphQL WebSocket.
pub type Ws =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

/// A `graphql-transport-ws` WebSocket after `connection_init` with `token`.
pub async fn open(op: &OperatorProcess, token: &str) -> Result<Ws> {
    let mut ws = connect(op).await?;
    init(&mut ws, token).await?;
    Ok(ws)
}

/// Sends `connection_init` with `token` as the bearer.
pub async fn init(ws: &mut Ws, token: &str) -> Result<()> {
    let init =
        json!({"type": "connection_init", "payload": {"authorization": format!("Bearer {token}")}});
    ws.send(Message::text(init.to_string())).await?;
    Ok(())
}

/// A `graphql-transport-ws` WebSocket that has sent nothing yet.
pub async fn connect(op: &OperatorProcess) -> Result<Ws> {
    connect_with_buffer(op, None).await
}

/// Like [`connect`], with the socket's kernel receive buffer set to `receive_buffer` bytes
/// before it connects (the kernel doubles and floors it), so a client that stops reading is
/// felt by the server after little data.
pub async fn connect_with_buffer(op: &OperatorProcess, receive_buffer: Option<u32>) -> Result<Ws> {
    let address = std::net::SocketAddr::from(([127, 0, 0, 1], op.gateway_port));
    let socket = tokio::net::TcpSocket::new_v4()?;
    if let Some(bytes) = receive_buffer {
        socket.set_recv_buffer_size(bytes)?;
    }
    let stream = socket.connect(address).await?;
    let mut request =
        format!("ws://127.0.0.1:{}/api/v1/graphql", op.gateway_port).into_client_request()?;
    request
        .headers_mut()
        .insert("sec-websocket-protocol", "graphql-transport-ws".parse()?);
    let stream = tokio_tungstenite::MaybeTlsStream::Plain(stream);
    let (ws, response) = tokio_tungstenite::client_async(request, stream).await?;
    ensure!(
        response
            .headers()
            .get("sec-websocket-protocol")
            .is_some_and(|p| p == "graphql-transport-ws")
    );
    Ok(ws)
}

/// Sends a `subscribe` message: operation `id`, `query`.
pub async fn subscribe(ws: &mut Ws, id: &str, query: &str) -> Result<()> {
    let subscribe = json!({"id": id, "type": "subscribe", "payload": {"query": query}});
    ws.send(Message::text(subscribe.to_string())).await?;
    Ok(())
}

/// The next JSON message within `within`, or the close frame's code and reason as
/// `{"close": code, "reason": ...}`.
pub async fn next(ws: &mut Ws, within: Duration) -> Result<Value> {
    loop {
        let msg = tokio::time::timeout(within, ws.next())
            .await
            .with_context(|| format!("nothing within {within:?}"))?
            .context("closed")??;
        match msg {
            Message::Text(t) => return Ok(serde_json::from_str(&t)?),
            Message::Close(frame) => {
                let (code, reason) = frame
                    .map(|f| (u16::from(f.code), f.reason.to_string()))
                    .unwrap_or_default();
                return Ok(json!({"close": code, "reason": reason}));
            }
            _ => {}
        }
    }
}
