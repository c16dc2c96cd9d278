//! Bare HTTP clients for the endpoints tests read (`/readyz`, `/metrics`, `/status`, the API),
//! a Prometheus sample reader, and a throw-away CA for the HTTPS tests.

use std::path::Path;
use std::process::Command;

use anyhow::{Result, bail};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// Finds one sample in Prometheus text by its exact series name.
pub fn sample(text: &str, series: &str) -> Option<f64> {
    text.lines().find_map(|l| {
        l.strip_prefix(series)
            .and_then(|rest| rest.strip_prefix(' '))
            .and_then(|v| v.trim().parse().ok())
    })
}

/// Sends `request` to 127.0.0.1:`port` and reads until the server closes: the response's head
/// (status line and headers) and body.
async fn exchange(port: u16, request: &[u8]) -> Result<(String, Vec<u8>)> {
    let mut stream = tokio::net::TcpStream::connect(("127.0.0.1", port)).await?;
    stream.write_all(request).await?;
    let mut buf = Vec::new();
    stream.read_to_end(&mut buf).await?;
    let Some(split) = buf.windows(4).position(|w| w == b"\r\n\r\n") else {
        return Ok((String::from_utf8_lossy(&buf).into_owned(), Vec::new()));
    };
    let head = String::from_utf8_lossy(&buf[..split]).into_owned();
    Ok((head, buf[split + 4..].to_vec()))
}

/// The status code of a status line (0 when there is none).
fn status_code(status_line: &str) -> u16 {
    status_line
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0)
}

/// A minimal HTTP/1.0 GET against 127.0.0.1: status code and body.
pub async fn http_get(port: u16, path: &str) -> Result<(u16, String)> {
    let request = format!("GET {path} HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n");
    let (head, body) = exchange(port, request.as_bytes()).await?;
    Ok((
        status_code(&head),
        String::from_utf8_lossy(&body).into_owned(),
    ))
}

/// A plain HTTP/1.1 GET with headers: status, response headers (lowercase names) and body.
pub async fn http_get_with(
    port: u16,
    path: &str,
    headers: &[(&str, &str)],
) -> Result<(u16, Vec<(String, String)>, String)> {
    let (code, hdrs, body) = http_request(port, "GET", path, headers, None).await?;
    Ok((code, hdrs, String::from_utf8_lossy(&body).into_owned()))
}

/// One HTTP/1.1 request on a fresh connection (`Connection: close`, and `Content-Length` when
/// there is a body): status, response headers (lowercase names) and the body's bytes.
pub async fn http_request(
    port: u16,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: Option<&[u8]>,
) -> Result<(u16, Vec<(String, String)>, Vec<u8>)> {
    let mut request =
        format!("{method} {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n");
    if let Some(body) = body {
        request.push_str(&format!("Content-Length: {}\r\n", body.len()));
    }
    for (k, v) in headers {
        request.push_str(&format!("{k}: {v}\r\n"));
    }
    request.push_str("\r\n");
    let mut bytes = request.into_bytes();
    bytes.extend_from_slice(body.unwrap_or_default());
    let (head, body) = exchange(port, &bytes).await?;
    let mut lines = head.lines();
    let code = lines.next().map(status_code).unwrap_or(0);
    let hdrs = lines
        .filter_map(|l| {
            l.split_once(':')
                .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_owned()))
        })
        .collect();
    Ok((code, hdrs, body))
}

/// Makes, with openssl, a self-signed CA (`ca.crt`) and a server certificate it signed for
/// 127.0.0.1 and localhost (`tls.crt`, `tls.key`) in `dir`.
pub fn test_ca(dir: &Path) -> Result<()> {
    let d = dir.display();
    let sh = |cmd: String| -> Result<()> {
        let out = Command::new("bash").arg("-c").arg(&cmd).output()?;
        if !out.status.success() {
            bail!("{cmd}: {}", String::from_utf8_lossy(&out.stderr));
        }
        Ok(())
    };
    sh(format!(
        "openssl req -x509 -newkey rsa:2048 -nodes -days 1 -subj /CN=lekiwi-test-ca -keyout {d}/ca.key -out {d}/ca.crt"
    ))?;
    sh(format!(
        "openssl req -newkey rsa:2048 -nodes -subj /CN=127.0.0.1 -keyout {d}/tls.key -out {d}/tls.csr"
    ))?;
    std::fs::write(
        dir.join("ext"),
        "subjectAltName=IP:127.0.0.1,DNS:localhost\nbasicConstraints=CA:FALSE\n",
    )?;
    sh(format!(
        "openssl x509 -req -in {d}/tls.csr -CA {d}/ca.crt -CAkey {d}/ca.key -CAcreateserial -days 1 -extfile {d}/ext -out {d}/tls.crt"
    ))
}
