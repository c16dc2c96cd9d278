//! `lekiwi-agent join`: a robot joins its fleet with one command, as `kubeadm join
//! --discovery-token-ca-cert-hash` does it. The gateway's CA is fetched from the TLS handshake
//! and trusted only if its pin matches; the settings go into a drop-in beside the lab's own
//! configuration, the CA and the token into their files with their modes; the service is
//! enabled and started, and join waits until the agent is connected.

mod fetch;
mod files;
mod service;

use std::path::PathBuf;
use std::time::Duration;

use lekiwi_protocol::join::{
    CA_FILE, CONFIG_FILE, ENROLLMENT_TOKEN_FILE, JOIN_DROP_IN, PinError, STATE_DIR, ca_cert_hash,
    parse_pin,
};
use rustls_pki_types::CertificateDer;

use crate::backoff::Backoff;
pub use crate::config::JoinArgs;
pub use fetch::Endpoint;
use files::{DropIn, Existing, Root};

/// Why a join failed.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The gateway's certificate is not usable, or it answers no TLS.
    #[error("{0}")]
    Gateway(String),
    /// No connection to the gateway (refused, unreachable, timed out), or no answer to the TLS
    /// handshake in time: tried again until `--wait-s` ends.
    #[error("{0}")]
    Unreachable(String),
    /// No CA the gateway presents has the pin.
    #[error(
        "refusing to join {gateway}: --ca-cert-hash is {want}, but the CA it presents is \
         {presented}. Either the pin is wrong (`kubectl lekiwi enroll-token` prints the right \
         one) or something between this robot and the gateway answers in its place"
    )]
    PinMismatch {
        /// `host:port`.
        gateway: String,
        /// The pin asked for.
        want: String,
        /// The pin of the CA the gateway presented.
        presented: String,
    },
    /// The gateway presents only its own certificate, no CA to check the pin against.
    #[error(
        "refusing to join {gateway}: it presents no CA to check --ca-cert-hash {want} against, \
         only its own certificate ({own}); the gateway must send its CA after its certificate \
         (operator flag --tls-ca, set by the chart when it makes the CA)"
    )]
    NoCa {
        /// `host:port`.
        gateway: String,
        /// The pin asked for.
        want: String,
        /// The pin of the gateway's own certificate.
        own: String,
    },
    /// A malformed pin.
    #[error(transparent)]
    Pin(#[from] PinError),
    /// The robot joined another gateway before.
    #[error(
        "this robot joined {old_gateway} (CA {old_pin}) before; joining {new_gateway} (CA \
         {new_pin}) would replace {replaced}. Pass --force to do it"
    )]
    OtherGateway {
        /// The gateway of the existing drop-in.
        old_gateway: String,
        /// The pin of the existing CA file.
        old_pin: String,
        /// The gateway asked for.
        new_gateway: String,
        /// Its CA's pin.
        new_pin: String,
        /// The files (and token) that would change.
        replaced: String,
    },
    /// The token or name cannot be used.
    #[error("{0}")]
    Token(String),
    /// A file cannot be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The merged configuration is invalid.
    #[error(transparent)]
    Config(#[from] crate::config::Error),
    /// The state directory cannot take the robot's token.
    #[error(transparent)]
    State(#[from] crate::state::Error),
    /// systemctl failed, or the agent did not connect in time.
    #[error("{0}")]
    Service(String),
}

/// Time for the TLS handshake that fetches the CA.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(15);

/// Which kind of token join was given.
enum Token<'a> {
    /// A fleet enrollment token: written to its file, read by the agent once.
    Enrollment(&'a str),
    /// The robot's own token: saved as the state directory's credentials.
    Robot { robot: &'a str, token: &'a str },
}

fn token_kind<'a>(args: &'a JoinArgs) -> Result<Token<'a>, Error> {
    let token = args.token.trim();
    if token.starts_with("lke_") {
        return Ok(Token::Enrollment(token));
    }
    if token.starts_with("lkr_") {
        let robot = args.name.as_deref().filter(|n| n.contains('/'));
        return match robot {
            Some(robot) => Ok(Token::Robot { robot, token }),
            None => Err(Error::Token(
                "a robot's own token (lkr_...) needs --name namespace/name".into(),
            )),
        };
    }
    Err(Error::Token(
        "--token is neither a fleet enrollment token (lke_...) nor a robot token (lkr_...)".into(),
    ))
}

/// The certificate chain the gateway at `at` presents; a gateway that cannot be connected to
/// yet (its Service's endpoint not up, the robot's network coming up) is tried again, backing
/// off, until `within` has passed.
async fn reach(at: &Endpoint, within: Duration) -> Result<Vec<CertificateDer<'static>>, Error> {
    let deadline = std::time::Instant::now() + within;
    let mut backoff = Backoff::new(Duration::from_millis(250), Duration::from_secs(5));
    loop {
        match fetch::presented_chain(at, HANDSHAKE_TIMEOUT).await {
            Err(Error::Unreachable(e)) if std::time::Instant::now() < deadline => {
                println!("{e}; trying again");
                tokio::time::sleep(backoff.next_delay()).await;
            }
            other => return other,
        }
    }
}

/// Runs `join`, printing what it does to standard output.
pub async fn run(args: &JoinArgs) -> Result<(), Error> {
    let pin = parse_pin(&args.ca_cert_hash)?;
    let token = token_kind(args)?;
    let at = Endpoint::of_url(&args.gateway)?;
    let chain = reach(&at, Duration::from_secs(args.wait_s)).await?;
    let ca = fetch::pinned_ca(&at, &chain, &pin)?;
    println!(
        "the gateway at {}:{} presents the CA {pin}",
        at.host, at.port
    );
    let root = Root(args.root.clone());
    let lab = lab_config(&root)?;
    let state_dir = rooted(&root, &lab.state_dir);
    let drop_in = DropIn {
        gateway: args.gateway.clone(),
        ca_file: Some(root.shown(CA_FILE)),
        robot_name: args.name.clone(),
        enrollment_token_file: matches!(token, Token::Enrollment(_))
            .then(|| root.shown(ENROLLMENT_TOKEN_FILE)),
        state_dir: (!root.is_slash()).then(|| state_dir.to_string_lossy().into_owned()),
    };
    let ca_pem = pem(&ca);
    let existing = Existing::read(&root)?;
    let other_fleet = check_existing(&existing, &drop_in, &pin, &state_dir, args.force)?;
    if other_fleet {
        forget_credentials(&state_dir)?;
    }
    let enrollment = match token {
        Token::Enrollment(t) => Some(t),
        Token::Robot { .. } => None,
    };
    let mut changed = false;
    for (path, content, mode) in files::files(&root, &drop_in, &ca_pem, enrollment) {
        let wrote = files::write_if_changed(&path, &content, mode)?;
        println!(
            "{} {}",
            if wrote { "wrote" } else { "unchanged" },
            path.display()
        );
        changed |= wrote;
    }
    if let Token::Robot { robot, token } = token {
        crate::state::ensure_dir(&state_dir)?;
        let adopted = crate::state::adopt(&state_dir, robot, token)?;
        let wrote = adopted == crate::state::Adopted::Written;
        println!(
            "{} {}",
            if wrote { "wrote" } else { "unchanged" },
            state_dir.join("credentials.json").display()
        );
        changed |= wrote;
    }
    if !args.no_start {
        service::start(changed)?;
    }
    let merged = lab_config(&root)?;
    service::wait_connected(&merged, &args.gateway, Duration::from_secs(args.wait_s)).await
}

/// The lab's configuration under `root` (its file and drop-ins, no flags or environment).
fn lab_config(root: &Root) -> Result<crate::config::Config, Error> {
    let flags = crate::config::Flags {
        config: root.at(CONFIG_FILE),
        ..Default::default()
    };
    Ok(crate::config::Config::merge(&flags)?)
}

/// `path` (as the configuration names it) under the root, unless it is already there.
fn rooted(root: &Root, path: &std::path::Path) -> PathBuf {
    if root.is_slash() || path.starts_with(&root.0) {
        return path.to_owned();
    }
    root.at(&path.to_string_lossy())
}

/// Refuses to replace another gateway's files without `force`; returns whether the robot moves
/// to another fleet (another CA), whose token is no good there.
fn check_existing(
    existing: &Existing,
    drop_in: &DropIn,
    pin: &str,
    state_dir: &std::path::Path,
    force: bool,
) -> Result<bool, Error> {
    let Some(old) = &existing.drop_in else {
        return Ok(false);
    };
    let old_pin = existing
        .ca_pem
        .as_deref()
        .and_then(pem_pin)
        .unwrap_or_else(|| "none".into());
    let other_ca = old_pin != pin;
    if old.gateway == drop_in.gateway && !other_ca {
        return Ok(false);
    }
    if !force {
        let mut replaced = vec![JOIN_DROP_IN.to_owned()];
        if other_ca {
            replaced.push(CA_FILE.to_owned());
            if state_dir.join("credentials.json").exists() {
                replaced.push(format!(
                    "and forget the robot's own token ({})",
                    STATE_DIR.to_owned() + "/credentials.json"
                ));
            }
        }
        return Err(Error::OtherGateway {
            old_gateway: old.gateway.clone(),
            old_pin,
            new_gateway: drop_in.gateway.clone(),
            new_pin: pin.to_owned(),
            replaced: replaced.join(", "),
        });
    }
    Ok(other_ca)
}

/// Removes the robot's own token, issued by another fleet's gateway.
fn forget_credentials(state_dir: &std::path::Path) -> Result<(), Error> {
    let path = state_dir.join("credentials.json");
    match std::fs::remove_file(&path) {
        Ok(()) => {
            println!("removed {} (the other fleet's token)", path.display());
            Ok(())
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(source) => Err(Error::Io { path, source }),
    }
}

/// The pin of the first certificate of a PEM text.
fn pem_pin(pem: &str) -> Option<String> {
    use rustls_pki_types::pem::PemObject;
    let cert = CertificateDer::pem_slice_iter(pem.as_bytes())
        .next()?
        .ok()?;
    ca_cert_hash(&cert).ok()
}

/// A certificate as PEM.
fn pem(cert: &CertificateDer<'_>) -> String {
    use base64::Engine as _;
    let b64 = base64::engine::general_purpose::STANDARD.encode(cert.as_ref());
    let mut out = String::from("-----BEGIN CERTIFICATE-----\n");
    for line in b64.as_bytes().chunks(64) {
        out.push_str(&String::from_utf8_lossy(line));
        out.push('\n');
    }
    out.push_str("-----END CERTIFICATE-----\n");
    out
}
