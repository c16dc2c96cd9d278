//! The gateway's release API as the CLI uses it: the user's Kubernetes token, requests that
//! retry transient failures, and the answers about blobs, uploads and releases.

use std::time::Duration;

use anyhow::{Context as _, bail};
use lekiwi_protocol::release::{ReleaseManifest, blob_path};
use reqwest::{Method, StatusCode};
use serde::{Deserialize, Serialize};

use super::ServerArgs;

/// The gateway's HTTP API with the user's Kubernetes token.
pub(crate) struct Gateway {
    http: reqwest::Client,
    /// Base URL, without a trailing `/`.
    pub(crate) base: String,
    token: String,
    /// The namespace requests act in (`?namespace=`), when the routes want it.
    namespace: Option<String>,
    /// The port-forward to the chart's gateway, open while this lives (without `--server`).
    _forward: Option<crate::forward::Forward>,
}

/// The chart's gateway in `--gateway-namespace` through a port-forward: its base URL (by the
/// Service's DNS name, which its certificate carries), the forward, and the chart's CA.
async fn through_api_server(
    kube: &crate::KubeContext,
    api: bool,
) -> anyhow::Result<(String, crate::forward::Forward, Option<String>)> {
    let gw = if api {
        crate::locate::locate_api(&kube.client, &kube.gateway_namespace).await
    } else {
        crate::locate::locate(&kube.client, &kube.gateway_namespace).await
    }
    .context("no --server given, and the chart's gateway cannot be found")?;
    let forward = crate::forward::open(&kube.client, &gw).await?;
    let scheme = if forward.tls { "https" } else { "http" };
    let base = format!(
        "{scheme}://{}.{}.svc:{}",
        gw.service,
        gw.namespace,
        forward.local.port()
    );
    Ok((base, forward, gw.ca_pem))
}

/// An error answer of the gateway.
#[derive(Debug, Deserialize)]
struct ApiError {
    message: String,
}

/// The gateway's answer to an upload request.
#[derive(Debug, Deserialize)]
pub(super) struct UploadAnswer {
    /// Bytes the gateway holds of the blob.
    pub(super) offset: u64,
    /// Whether the blob is stored and verified.
    #[serde(default)]
    pub(super) complete: bool,
}

/// A stored release as `GET /v1/releases/{digest}` answers it.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ReleaseInfo {
    /// Digest of the manifest.
    pub digest: String,
    /// The manifest, its fields inline (`mediaType`, `version`, `files`).
    #[serde(flatten)]
    pub manifest: ReleaseManifest,
    /// Referenced blobs the gateway lacks.
    pub missing: Vec<String>,
}

/// Attempts of a request that fails transiently (network, 5xx, 429) before giving up.
pub(super) const ATTEMPTS: u32 = 6;

/// Pause before attempt `attempt`: doubling from 250 ms, at most 5 s.
pub(super) fn backoff(attempt: u32) -> Duration {
    Duration::from_millis(250u64 << attempt.min(5)).min(Duration::from_secs(5))
}

/// Whether an answer is worth repeating the request for.
pub(super) fn transient(status: StatusCode) -> bool {
    status.is_server_error()
        || status == StatusCode::TOO_MANY_REQUESTS
        || status == StatusCode::REQUEST_TIMEOUT
}

/// The gateway's message in an error answer, or the body as it is.
pub(crate) async fn message(resp: reqwest::Response) -> String {
    let status = resp.status();
    let text = resp.text().await.unwrap_or_default();
    match serde_json::from_str::<ApiError>(&text) {
        Ok(e) => e.message,
        Err(_) if text.trim().is_empty() => status.to_string(),
        Err(_) => text.trim().to_owned(),
    }
}

impl Gateway {
    /// Builds the HTTP client (trusting `--certificate-authority`) with `--token` or the
    /// kubeconfig user's token, its requests naming `namespace`; refuses plain `http://` to
    /// another host first (see [`ServerArgs::check_transport`]). Without `--server`, the chart's
    /// gateway through a port-forward the plugin opens (see [`crate::forward`]).
    pub(crate) async fn connect(
        kube: &crate::KubeContext,
        server: &ServerArgs,
        namespace: Option<&str>,
    ) -> anyhow::Result<Self> {
        Self::connect_to(kube, server, namespace, false).await
    }

    /// As [`Self::connect`], for the Fleet API's routes (`/api/v1/...`): without `--server`,
    /// the chart's API Service when it serves the API on a port of its own.
    pub(crate) async fn connect_api(
        kube: &crate::KubeContext,
        server: &ServerArgs,
    ) -> anyhow::Result<Self> {
        Self::connect_to(kube, server, None, true).await
    }

    async fn connect_to(
        kube: &crate::KubeContext,
        server: &ServerArgs,
        namespace: Option<&str>,
        api: bool,
    ) -> anyhow::Result<Self> {
        // Before anything is sent: the token must not cross the network in clear.
        server.check_transport()?;
        let token = match (&server.token, &kube.bearer) {
            (Some(token), _) => token.trim().to_owned(),
            (None, Ok(token)) => token.clone(),
            (None, Err(why)) => bail!("{why}"),
        };
        let mut http = reqwest::Client::builder()
            .connect_timeout(Duration::from_secs(10))
            .read_timeout(Duration::from_secs(120));
        let mut ca_pem = match &server.certificate_authority {
            Some(ca) => {
                Some(std::fs::read(ca).with_context(|| format!("cannot read {}", ca.display()))?)
            }
            None => None,
        };
        let (base, forward) = match &server.server {
            Some(url) => (url.trim_end_matches('/').to_owned(), None),
            None => {
                let (base, forward, chart_ca) = through_api_server(kube, api).await?;
                // The name the gateway's certificate carries, at the forwarded port.
                let host = base.split("://").nth(1).and_then(|h| h.split(':').next());
                http = http.resolve(host.unwrap_or_default(), forward.local);
                ca_pem = ca_pem.or(chart_ca.map(String::into_bytes));
                (base, Some(forward))
            }
        };
        if let Some(pem) = ca_pem {
            http = http.add_root_certificate(
                reqwest::Certificate::from_pem(&pem)
                    .context("--certificate-authority is not a PEM certificate")?,
            );
        }
        Ok(Self {
            http: http.build()?,
            base,
            token,
            namespace: namespace.map(str::to_owned),
            _forward: forward,
        })
    }

    /// A request to `path` on the gateway, with the token (and the namespace, if any).
    pub(crate) fn request(&self, method: Method, path: &str) -> reqwest::RequestBuilder {
        let request = self
            .http
            .request(method, format!("{}{path}", self.base))
            .bearer_auth(&self.token);
        match &self.namespace {
            Some(ns) => request.query(&[("namespace", ns)]),
            None => request,
        }
    }

    /// Sends a request that is safe to repeat, retrying transient failures.
    async fn send(
        &self,
        method: Method,
        path: &str,
        what: &str,
    ) -> anyhow::Result<reqwest::Response> {
        let mut attempt = 0;
        loop {
            let failure = match self.request(method.clone(), path).send().await {
                Ok(resp) if !transient(resp.status()) => return Ok(resp),
                Ok(resp) => format!("{}: {}", resp.status(), message(resp).await),
                Err(e) if crate::tls_refused(&e) => bail!(
                    "{what}: TLS with the gateway at {} failed ({}); check --certificate-authority",
                    self.base,
                    crate::http_error(&e)
                ),
                Err(e) => crate::http_error(&e),
            };
            attempt += 1;
            if attempt >= ATTEMPTS {
                bail!(
                    "{what}: the gateway at {} did not answer ({failure}); check --server or LEKIWI_SERVER",
                    self.base
                );
            }
            tokio::time::sleep(backoff(attempt)).await;
        }
    }

    /// Whether the gateway stores the blob (`HEAD`); a refused token is a clear error.
    pub(super) async fn has_blob(&self, digest: &str) -> anyhow::Result<bool> {
        let resp = self
            .send(Method::HEAD, &blob_path(digest), "checking blobs")
            .await?;
        match resp.status() {
            StatusCode::OK => Ok(true),
            StatusCode::NOT_FOUND => Ok(false),
            StatusCode::UNAUTHORIZED | StatusCode::FORBIDDEN => {
                // A HEAD answer has no body: name the permission here.
                let ns = self.namespace.as_deref().unwrap_or_default();
                let need = format!(
                    "pushing needs create and get on releases.fleet.lekiwi.io in namespace {ns}"
                );
                bail!("{}", refused(resp, &need).await)
            }
            s => bail!("checking blob {digest}: the gateway answered {s}"),
        }
    }

    /// How far an upload of `digest` got (`GET /v1/uploads/{digest}`).
    pub(super) async fn upload_offset(&self, digest: &str) -> anyhow::Result<UploadAnswer> {
        let resp = self
            .send(
                Method::GET,
                &format!("/v1/uploads/{digest}"),
                "resuming an upload",
            )
            .await?;
        if !resp.status().is_success() {
            bail!("resuming the upload of {digest}: {}", message(resp).await);
        }
        Ok(resp.json().await?)
    }

    /// Sends a small blob whole (`PUT` without a range): for a manifest the gateway stores
    /// already, this records it as a release of the namespace too. Returns whether this
    /// request stored it.
    pub(super) async fn put_whole(&self, digest: &str, bytes: Vec<u8>) -> anyhow::Result<bool> {
        let mut attempt = 0;
        loop {
            let sent = self
                .request(Method::PUT, &blob_path(digest))
                .body(bytes.clone())
                .send()
                .await;
            let failure = match sent {
                Ok(resp) if resp.status() == StatusCode::CREATED => return Ok(true),
                Ok(resp) if resp.status() == StatusCode::OK => return Ok(false),
                Ok(resp) if transient(resp.status()) => message(resp).await,
                Ok(resp) => bail!("uploading the manifest: {}", message(resp).await),
                Err(e) => crate::http_error(&e),
            };
            attempt += 1;
            if attempt >= ATTEMPTS {
                bail!("uploading the manifest: {failure}");
            }
            tokio::time::sleep(backoff(attempt)).await;
        }
    }

    /// The releases of the namespace (`GET /api/v1/namespaces/NS/releases`), as JSON items.
    pub(super) async fn releases(&self, namespace: &str) -> anyhow::Result<Vec<serde_json::Value>> {
        let path = format!("/api/v1/namespaces/{namespace}/releases");
        let resp = self.send(Method::GET, &path, "listing releases").await?;
        if !resp.status().is_success() {
            bail!("listing releases: {}", message(resp).await);
        }
        let page: serde_json::Value = resp.json().await.context("reading the release list")?;
        Ok(page["items"].as_array().cloned().unwrap_or_default())
    }

    /// Deletes a release of the namespace by version or digest; the gateway's answer.
    pub(super) async fn delete_release(
        &self,
        namespace: &str,
        reference: &str,
    ) -> anyhow::Result<serde_json::Value> {
        let path = format!("/api/v1/namespaces/{namespace}/releases/{reference}");
        let resp = self
            .send(Method::DELETE, &path, "deleting the release")
            .await?;
        if !resp.status().is_success() {
            bail!("{}", message(resp).await);
        }
        resp.json().await.context("reading the answer")
    }

    /// A stored release and the blobs it lacks.
    pub(super) async fn release(&self, digest: &str) -> anyhow::Result<ReleaseInfo> {
        let resp = self
            .send(
                Method::GET,
                &format!("/v1/releases/{digest}"),
                "reading the release",
            )
            .await?;
        if !resp.status().is_success() {
            bail!("{}", message(resp).await);
        }
        resp.json()
            .await
            .with_context(|| format!("reading release {digest}"))
    }
}

/// What to tell the user when the gateway refused the token (401) or the permission (403);
/// `need` says what the request needs when the answer has no message (a `HEAD`).
pub(crate) async fn refused(resp: reqwest::Response, need: &str) -> String {
    let status = resp.status();
    let mut text = message(resp).await;
    if text == status.to_string() {
        text = need.to_owned();
    }
    if status == StatusCode::UNAUTHORIZED {
        format!(
            "the gateway refused the token (401: {text}): the API server does not accept it; \
             pass --token with a valid token (e.g. `kubectl create token SERVICE_ACCOUNT`)"
        )
    } else {
        format!(
            "the gateway refused the request (403 Forbidden: {text}): ask for an RBAC binding \
             (e.g. to the ClusterRole lekiwi-release-pusher or lekiwi-viewer)"
        )
    }
}
