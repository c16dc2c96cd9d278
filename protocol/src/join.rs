//! Joining a robot to a fleet with one command: the files the agent reads on a robot, the pin of
//! the gateway's CA (`sha256:` of its DER SubjectPublicKeyInfo, as `kubeadm join
//! --discovery-token-ca-cert-hash`) and the `lekiwi-agent join` command line the plugin prints.
//! One place for both sides, so that what `kubectl lekiwi` prints is what the agent reads.

use sha2::{Digest, Sha256};

/// The lab's own configuration file; a package conffile, never written by `join`.
pub const CONFIG_FILE: &str = "/etc/lekiwi/agent.yaml";
/// Directory of drop-ins beside [`CONFIG_FILE`]: `*.yaml` read in name order after it, a later
/// file's keys overriding an earlier one's.
pub const DROP_IN_DIR: &str = "/etc/lekiwi/agent.d";
/// The drop-in `lekiwi-agent join` writes (gateway, CA, robot name, enrollment token file).
pub const JOIN_DROP_IN: &str = "/etc/lekiwi/agent.d/50-join.yaml";
/// The gateway's CA certificate (PEM, mode 0644).
pub const CA_FILE: &str = "/etc/lekiwi/ca.crt";
/// The fleet enrollment token (mode 0600), read once, until the robot has its own token.
pub const ENROLLMENT_TOKEN_FILE: &str = "/etc/lekiwi/enrollment-token";
/// The agent's state directory: the robot's own token (`credentials.json`, 0600), the outbox,
/// releases.
pub const STATE_DIR: &str = "/var/lib/lekiwi";

/// Prefix of a pin.
const SHA256: &str = "sha256:";

/// Errors computing or reading a pin.
#[derive(Debug, thiserror::Error)]
pub enum PinError {
    /// The certificate is not DER X.509.
    #[error("not an X.509 certificate: {0:?}")]
    Certificate(webpki::Error),
    /// A `--ca-cert-hash` that is not `sha256:` and 64 hex digits.
    #[error("{0:?} is not a CA pin: want sha256: followed by 64 hex digits")]
    Malformed(String),
}

/// The pin of a CA certificate (DER): `sha256:` and the hex SHA-256 of its DER
/// SubjectPublicKeyInfo, what `openssl x509 -pubkey | openssl pkey -pubin -outform der |
/// sha256sum` prints.
pub fn ca_cert_hash(cert_der: &[u8]) -> Result<String, PinError> {
    let der = rustls_pki_types::CertificateDer::from(cert_der);
    let cert = webpki::EndEntityCert::try_from(&der).map_err(PinError::Certificate)?;
    let spki = cert.subject_public_key_info();
    Ok(format!(
        "{SHA256}{}",
        hex::encode(Sha256::digest(spki.as_ref()))
    ))
}

/// A pin as written on the command line, checked and in lower case.
pub fn parse_pin(pin: &str) -> Result<String, PinError> {
    let hex = pin
        .trim()
        .strip_prefix(SHA256)
        .ok_or_else(|| PinError::Malformed(pin.to_owned()))?;
    if hex.len() != 64 || !hex.bytes().all(|b| b.is_ascii_hexdigit()) {
        return Err(PinError::Malformed(pin.to_owned()));
    }
    Ok(format!("{SHA256}{}", hex.to_ascii_lowercase()))
}

/// What a robot needs to join: the gateway's agent URL, the pin of its CA (none for a
/// gateway with a publicly trusted certificate), the token, and the robot's name (`None`: the
/// robot's host name).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Join {
    /// `wss://HOST:PORT/v1/agent`.
    pub gateway: String,
    /// `sha256:HEX` of the gateway's CA.
    pub ca_cert_hash: Option<String>,
    /// A fleet enrollment token (`lke_`) or the robot's own (`lkr_`).
    pub token: String,
    /// `namespace/name`, or `None` to name the robot after its host.
    pub name: Option<String>,
}

impl Join {
    /// The one-line command to run on the robot, as root.
    pub fn command(&self) -> String {
        let mut line = format!("sudo lekiwi-agent join --gateway {}", quote(&self.gateway));
        if let Some(pin) = &self.ca_cert_hash {
            line.push_str(&format!(" --ca-cert-hash {pin}"));
        }
        line.push_str(&format!(" --token {}", quote(&self.token)));
        if let Some(name) = &self.name {
            line.push_str(&format!(" --name {}", quote(name)));
        }
        line
    }
}

/// `s` as one shell word: as it is when it holds only characters no shell treats specially,
/// else in single quotes.
fn quote(s: &str) -> String {
    let plain = !s.is_empty()
        && s.bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"-_./:=@%+,".contains(&b));
    if plain {
        s.to_owned()
    } else {
        format!("'{}'", s.replace('\'', r"'\''"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A self-signed certificate (`openssl req -x509 -newkey ec -pkeyopt
    /// ec_paramgen_curve:P-256 -subj /CN=pin-test`), DER in hex.
    const CERT_HEX: &str = concat!(
        "3082017d30820123a00302010202144db3889fd0318f6b4b9df7442e87df62ac7d277f300a06082a",
        "8648ce3d04030230133111300f06035504030c0870696e2d746573743020170d3236313230353037",
        "353733325a180f32313236313131313037353733325a30133111300f06035504030c0870696e2d74",
        "6573743059301306072a8648ce3d020106082a8648ce3d030107034200048676bc25c701db939888",
        "6584f6d146fff10dfd42e7d2e7fb63ef72dd50fd8d2c5d091b3464769f604b7d65c91d06869c0c54",
        "b6b59f90b5b1b481b866421f60a0a3533051301d0603551d0e041604148c048ed328140c8b445f7a",
        "2f75ba4091cbbcbe11301f0603551d230418301680148c048ed328140c8b445f7a2f75ba4091cbbc",
        "be11300f0603551d130101ff040530030101ff300a06082a8648ce3d040302034800304502202bf8",
        "1eed2a75ee52cc23806f98acdb8bf8c6809490dd86abe0dfd9c16523ad06022100feb6f3dcb76b48",
        "4aac5fd3520a76b03d9ff729c246f35c6c0e58459bff28a3dd",
    );

    #[test]
    fn the_pin_is_what_openssl_prints_for_the_public_key() {
        // openssl x509 -pubkey -noout -in pin.crt | openssl pkey -pubin -outform der | sha256sum
        let want = "sha256:f47703e6bb499ac9cda040e0e319fc66a5a0f8b0b6b0a25c66633f98c6a00e97";
        assert_eq!(ca_cert_hash(&hex::decode(CERT_HEX).unwrap()).unwrap(), want);
        assert!(ca_cert_hash(b"not a certificate").is_err());
    }

    #[test]
    fn pins_parse_in_lower_case_and_refuse_anything_else() {
        let hex = "AB".repeat(32);
        assert_eq!(
            parse_pin(&format!("sha256:{hex}")).unwrap(),
            format!("sha256:{}", "ab".repeat(32))
        );
        for bad in [
            "",
            "sha256:",
            "md5:00",
            &format!("sha256:{}", "g".repeat(64)),
        ] {
            assert!(parse_pin(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn the_join_command_is_one_line_of_shell_words() {
        let join = Join {
            gateway: "wss://10.0.0.5:30443/v1/agent".into(),
            ca_cert_hash: Some(format!("sha256:{}", "0".repeat(64))),
            token: "lke_abc".into(),
            name: Some("lab/kiwi 1".into()),
        };
        assert_eq!(
            join.command(),
            format!(
                "sudo lekiwi-agent join --gateway wss://10.0.0.5:30443/v1/agent --ca-cert-hash sha256:{} --token lke_abc --name 'lab/kiwi 1'",
                "0".repeat(64)
            )
        );
    }
}
