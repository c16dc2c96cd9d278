//! Reloads the gateway's certificate and key when their files change: a Kubernetes Secret
//! volume updates by swapping its `..data` symlink, cert-manager renews, an administrator
//! copies new files. The files are read every few seconds and compared with what was loaded;
//! new handshakes get the new certificate, open connections keep theirs. A pair that does not
//! load (half-written, a key of another certificate) keeps the old one, counted and logged.
//! The expiry (notAfter) of the certificate served is a gauge, set at each load.

use std::path::PathBuf;
use std::time::Duration;

use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use rustls::pki_types::CertificateDer;
use rustls::pki_types::pem::PemObject;
use sha2::{Digest, Sha256};
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};
use x509_cert::der::Decode as _;

use super::Acceptor;
use crate::config::Config;
use crate::error::{Error, Result};
use lekiwi_metrics::KindLabels;

/// The certificate chain and key files the gateway serves.
#[derive(Clone, Debug)]
pub struct CertFiles {
    /// PEM certificate chain, the gateway's own certificate first.
    pub cert: PathBuf,
    /// PEM private key of that certificate.
    pub key: PathBuf,
    /// PEM certificate of the CA that signs it (`--tls-ca`), sent after the chain so that
    /// `lekiwi-agent join` can pin it; reloaded with the others.
    pub ca: Option<PathBuf>,
}

/// What the reloads report.
#[derive(Clone, Debug, Default)]
pub struct TlsMetrics {
    /// `lekiwi_gateway_tls_reloads_total{kind}`: `reloaded` and `failed`.
    pub reloads: Family<KindLabels, Counter>,
    /// `lekiwi_gateway_tls_certificate_expiry_timestamp_seconds`: the notAfter of the
    /// certificate new connections get, in Unix seconds (0 until one is loaded).
    pub expiry: Gauge,
}

impl TlsMetrics {
    /// Sets the expiry gauge to the notAfter of the first certificate in `pem`; one that cannot
    /// be read is logged and leaves the gauge as it was.
    fn served(&self, pem: &[u8]) {
        match not_after(pem) {
            Some(at) => {
                self.expiry.set(at);
            }
            None => warn!("cannot read the served TLS certificate's expiry"),
        }
    }
}

/// The notAfter of the first certificate in `pem`, in Unix seconds.
pub fn not_after(pem: &[u8]) -> Option<i64> {
    let der = CertificateDer::pem_slice_iter(pem).next()?.ok()?;
    let cert = x509_cert::Certificate::from_der(der.as_ref()).ok()?;
    let at = cert.tbs_certificate.validity.not_after.to_unix_duration();
    i64::try_from(at.as_secs()).ok()
}

/// The bytes of both files, as last read.
#[derive(PartialEq, Eq)]
pub struct Loaded {
    cert: Vec<u8>,
    key: Vec<u8>,
}

impl CertFiles {
    async fn read(&self) -> std::io::Result<Loaded> {
        let mut cert = tokio::fs::read(&self.cert).await?;
        if let Some(ca) = &self.ca {
            super::append_pem(&mut cert, &tokio::fs::read(ca).await?);
        }
        Ok(Loaded {
            cert,
            key: tokio::fs::read(&self.key).await?,
        })
    }

    /// An acceptor for the files as they are now, and what it loaded.
    pub async fn load(&self) -> std::io::Result<(Acceptor, Loaded)> {
        let loaded = self.read().await?;
        let acceptor = Acceptor::from_pem(&loaded.cert, &loaded.key)?;
        info!(
            cert = %self.cert.display(),
            sha256 = %fingerprint(&loaded.cert),
            "gateway TLS certificate loaded"
        );
        Ok((acceptor, loaded))
    }
}

/// The SHA-256 of the first certificate in `pem` (its DER), in hex: what the log shows of a
/// certificate, and what `openssl x509 -fingerprint -sha256` prints.
fn fingerprint(pem: &[u8]) -> String {
    match CertificateDer::pem_slice_iter(pem).next() {
        Some(Ok(der)) => hex::encode(Sha256::digest(der.as_ref())),
        _ => "none".to_owned(),
    }
}

/// Reads `files` every `every` until `cancel` and hands `acceptor` what changed since `loaded`;
/// `metrics` count `reloaded` and `failed` and follow the served certificate's expiry.
pub async fn watch(
    acceptor: Acceptor,
    files: CertFiles,
    mut loaded: Loaded,
    every: Duration,
    metrics: TlsMetrics,
    cancel: CancellationToken,
) {
    metrics.served(&loaded.cert);
    let reloads = &metrics.reloads;
    let mut tick = tokio::time::interval(every);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    // An unreadable file is logged once until it reads again, not every few seconds.
    let mut unreadable = false;
    loop {
        tokio::select! {
            () = cancel.cancelled() => return,
            _ = tick.tick() => {}
        }
        let now = match files.read().await {
            Ok(now) => now,
            Err(e) => {
                if !unreadable {
                    warn!(error = %e, cert = %files.cert.display(), key = %files.key.display(), "cannot read the gateway's TLS files; serving the certificate loaded before");
                    reloads.get_or_create(&KindLabels { kind: "failed" }).inc();
                }
                unreadable = true;
                continue;
            }
        };
        unreadable = false;
        if now == loaded {
            continue;
        }
        match acceptor.replace(&now.cert, &now.key) {
            Ok(()) => {
                info!(sha256 = %fingerprint(&now.cert), "gateway TLS certificate reloaded; new connections get it");
                metrics.served(&now.cert);
                reloads
                    .get_or_create(&KindLabels { kind: "reloaded" })
                    .inc();
            }
            Err(e) => {
                warn!(error = %e, sha256 = %fingerprint(&now.cert), "the gateway's new TLS files do not load; serving the certificate loaded before");
                reloads.get_or_create(&KindLabels { kind: "failed" }).inc();
            }
        }
        // Compared with what was read, not what loaded: a pair that failed is not tried again
        // until it changes.
        loaded = now;
    }
}

/// The TLS acceptor for `--tls-cert` and `--tls-key`, if given, with the task that reloads them
/// when they change (every `--tls-reload-seconds`, until `cancel`); `metrics` follow them.
pub async fn acceptor(
    config: &Config,
    metrics: TlsMetrics,
    cancel: &CancellationToken,
) -> Result<Option<Acceptor>> {
    let (Some(cert), Some(key)) = (&config.flags.tls_cert, &config.flags.tls_key) else {
        return Ok(None);
    };
    let files = CertFiles {
        cert: cert.clone(),
        key: key.clone(),
        ca: config.flags.tls_ca.clone(),
    };
    let addr = config.flags.gateway_addr;
    let (acceptor, loaded) = files
        .load()
        .await
        .map_err(|source| Error::Serve { addr, source })?;
    if config.flags.tls_reload_seconds > 0 {
        let every = Duration::from_secs(config.flags.tls_reload_seconds);
        let watch = watch(
            acceptor.clone(),
            files,
            loaded,
            every,
            metrics,
            cancel.clone(),
        );
        tokio::spawn(watch);
    } else {
        metrics.served(&loaded.cert);
    }
    Ok(Some(acceptor))
}
