//! The gateway's CA for `lekiwi-agent join`: the certificate chain the gateway presents in a TLS
//! handshake (trusted by nobody yet), the CA in it whose pin is `--ca-cert-hash`, and a check
//! that the gateway's own certificate is valid for its name under that CA.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use lekiwi_protocol::join::ca_cert_hash;
use rustls::DigitallySignedStruct;
use rustls::client::danger::{HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier};
use rustls::crypto::{CryptoProvider, verify_tls12_signature, verify_tls13_signature};
use rustls_pki_types::{CertificateDer, ServerName, UnixTime};

use super::Error;

/// Where the gateway of a `wss://` URL listens: host and port.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Endpoint {
    /// The host as the URL names it (a DNS name or an IP address, without brackets).
    pub host: String,
    /// The port (443 when the URL names none).
    pub port: u16,
}

impl Endpoint {
    /// The host and port of a `wss://` (or `https://`) URL; any other scheme is refused: a
    /// join sends a token and trusts a CA, which plain text cannot protect.
    pub fn of_url(url: &str) -> Result<Self, Error> {
        let uri: tokio_tungstenite::tungstenite::http::Uri = url
            .parse()
            .map_err(|e| Error::Gateway(format!("{url:?} is not a URL: {e}")))?;
        if !matches!(uri.scheme_str(), Some("wss" | "https")) {
            return Err(Error::Gateway(format!(
                "{url:?} is not a wss:// URL: joining needs TLS to check the gateway's CA"
            )));
        }
        let host = uri
            .host()
            .ok_or_else(|| Error::Gateway(format!("{url:?} names no host")))?;
        let host = host
            .trim_start_matches('[')
            .trim_end_matches(']')
            .to_owned();
        Ok(Self {
            host,
            port: uri.port_u16().unwrap_or(443),
        })
    }

    fn server_name(&self) -> Result<ServerName<'static>, Error> {
        ServerName::try_from(self.host.clone())
            .map_err(|e| Error::Gateway(format!("{:?} is not a host name: {e}", self.host)))
    }
}

/// Accepts any certificate and records the chain: the first handshake with a gateway whose CA
/// is not known yet (the pin decides afterwards). Handshake signatures are still checked, so
/// the peer holds the key of the certificate it presented.
#[derive(Debug)]
struct Recorder {
    chain: Mutex<Vec<CertificateDer<'static>>>,
    provider: Arc<CryptoProvider>,
}

impl ServerCertVerifier for Recorder {
    fn verify_server_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        intermediates: &[CertificateDer<'_>],
        _server_name: &ServerName<'_>,
        _ocsp: &[u8],
        _now: UnixTime,
    ) -> Result<ServerCertVerified, rustls::Error> {
        let mut chain = self.chain.lock().unwrap_or_else(|e| e.into_inner());
        *chain = std::iter::once(end_entity)
            .chain(intermediates)
            .map(|c| c.clone().into_owned())
            .collect();
        Ok(ServerCertVerified::assertion())
    }

    fn verify_tls12_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        let algs = &self.provider.signature_verification_algorithms;
        verify_tls12_signature(message, cert, dss, algs)
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        let algs = &self.provider.signature_verification_algorithms;
        verify_tls13_signature(message, cert, dss, algs)
    }

    fn supported_verify_schemes(&self) -> Vec<rustls::SignatureScheme> {
        self.provider
            .signature_verification_algorithms
            .supported_schemes()
    }
}

/// The certificate chain the gateway at `at` presents, its own certificate first.
pub async fn presented_chain(
    at: &Endpoint,
    timeout: Duration,
) -> Result<Vec<CertificateDer<'static>>, Error> {
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let recorder = Arc::new(Recorder {
        chain: Mutex::new(Vec::new()),
        provider: provider.clone(),
    });
    let config = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| Error::Gateway(e.to_string()))?
        .dangerous()
        .with_custom_certificate_verifier(recorder.clone())
        .with_no_client_auth();
    let name = at.server_name()?;
    let address = format!("{}:{}", at.host, at.port);
    let connect = tokio::net::TcpStream::connect(&address);
    let tcp = match tokio::time::timeout(timeout, connect).await {
        Err(_) => {
            return Err(Error::Unreachable(format!(
                "no connection to the gateway at {address} within {timeout:?}"
            )));
        }
        Ok(Err(e)) => {
            return Err(Error::Unreachable(format!(
                "cannot reach the gateway at {address}: {e}"
            )));
        }
        Ok(Ok(tcp)) => tcp,
    };
    let handshake = tokio_rustls::TlsConnector::from(Arc::new(config)).connect(name, tcp);
    match tokio::time::timeout(timeout, handshake).await {
        // A gateway that takes the connection but does not answer its TLS (a process just
        // starting, a Service whose endpoint is changing) is not there yet: tried again.
        Err(_) => Err(Error::Unreachable(format!(
            "no TLS handshake with {address} within {timeout:?}"
        ))),
        Ok(Err(e)) => Err(Error::Gateway(format!(
            "no TLS handshake with the gateway at {address}: {e}"
        ))),
        Ok(Ok(_tls)) => Ok(std::mem::take(
            &mut *recorder.chain.lock().unwrap_or_else(|e| e.into_inner()),
        )),
    }
}

/// The CA of `chain` whose pin is `pin`, once the gateway's certificate (the chain's first) is
/// checked to be valid for `at`'s host under it. Refuses, naming both pins, when no CA in the
/// chain has the pin: a wrong pin, or someone else answering in the gateway's place.
pub fn pinned_ca(
    at: &Endpoint,
    chain: &[CertificateDer<'static>],
    pin: &str,
) -> Result<CertificateDer<'static>, Error> {
    let Some((leaf, rest)) = chain.split_first() else {
        return Err(Error::Gateway(
            "the gateway presented no certificate".into(),
        ));
    };
    let pins: Vec<String> = rest
        .iter()
        .map(|c| ca_cert_hash(c).map_err(|e| Error::Gateway(e.to_string())))
        .collect::<Result<_, _>>()?;
    let Some(at_index) = pins.iter().position(|p| p == pin) else {
        let gateway = format!("{}:{}", at.host, at.port);
        return Err(match pins.last() {
            Some(ca) => Error::PinMismatch {
                gateway,
                want: pin.to_owned(),
                presented: ca.clone(),
            },
            None => Error::NoCa {
                gateway,
                want: pin.to_owned(),
                own: ca_cert_hash(leaf).map_err(|e| Error::Gateway(e.to_string()))?,
            },
        });
    };
    let ca = rest[at_index].clone();
    verify_under(at, leaf, &rest[..at_index], &ca)?;
    Ok(ca)
}

/// Checks that `leaf` (with `intermediates`) is valid for `at`'s host under `ca`, as the
/// agent's every later connection will check it.
fn verify_under(
    at: &Endpoint,
    leaf: &CertificateDer<'static>,
    intermediates: &[CertificateDer<'static>],
    ca: &CertificateDer<'static>,
) -> Result<(), Error> {
    let mut roots = rustls::RootCertStore::empty();
    roots
        .add(ca.clone())
        .map_err(|e| Error::Gateway(format!("the pinned CA is not usable: {e}")))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let verifier =
        rustls::client::WebPkiServerVerifier::builder_with_provider(Arc::new(roots), provider)
            .build()
            .map_err(|e| Error::Gateway(e.to_string()))?;
    verifier
        .verify_server_cert(
            leaf,
            intermediates,
            &at.server_name()?,
            &[],
            UnixTime::now(),
        )
        .map_err(|e| {
            Error::Gateway(format!(
                "the gateway's certificate is not valid for {} under the pinned CA: {e}",
                at.host
            ))
        })?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_wss_urls_name_a_gateway_to_join() {
        assert_eq!(
            Endpoint::of_url("wss://10.0.0.5:30443/v1/agent").unwrap(),
            Endpoint {
                host: "10.0.0.5".into(),
                port: 30443
            }
        );
        assert_eq!(
            Endpoint::of_url("wss://[::1]/v1/agent").unwrap(),
            Endpoint {
                host: "::1".into(),
                port: 443
            }
        );
        let err = Endpoint::of_url("ws://10.0.0.5/v1/agent").unwrap_err();
        assert!(err.to_string().contains("wss://"), "{err}");
    }

    /// A gateway that takes the connection and never answers the TLS handshake (a process
    /// still starting) is not there yet, which join tries again; one that answers something
    /// other than TLS is the wrong gateway, which join does not.
    #[tokio::test]
    async fn a_silent_handshake_is_tried_again_a_wrong_answer_is_not() {
        let silent = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let at = Endpoint {
            host: "127.0.0.1".into(),
            port: silent.local_addr().unwrap().port(),
        };
        let held = tokio::spawn(async move {
            let (conn, _) = silent.accept().await.unwrap();
            tokio::time::sleep(Duration::from_secs(5)).await;
            drop(conn);
        });
        let err = presented_chain(&at, Duration::from_millis(300))
            .await
            .unwrap_err();
        assert!(matches!(err, Error::Unreachable(_)), "{err:?}");
        held.abort();

        let plain = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let at = Endpoint {
            host: "127.0.0.1".into(),
            port: plain.local_addr().unwrap().port(),
        };
        tokio::spawn(async move {
            use tokio::io::AsyncWriteExt;
            let (mut conn, _) = plain.accept().await.unwrap();
            let _ = conn.write_all(b"HTTP/1.1 400 Bad Request\r\n\r\n").await;
        });
        let err = presented_chain(&at, Duration::from_secs(5))
            .await
            .unwrap_err();
        assert!(matches!(err, Error::Gateway(_)), "{err:?}");
    }
}
