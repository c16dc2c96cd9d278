//! `kubectl lekiwi robot add NAME` and `kubectl lekiwi enroll-token`: register a robot with its
//! own token, or make the namespace's fleet enrollment token, and print the `lekiwi-agent join`
//! command that joins a robot with it (the gateway's address and the pin of its CA, found in
//! the cluster). Tokens are printed once and kept in the cluster only as SHA-256 hashes, in
//! Secrets shaped exactly as the gateway reads them.

use anyhow::{Context as _, bail};
use clap::{Args, Subcommand};
use k8s_openapi::api::core::v1::Secret;
use kube::api::{ObjectMeta, Patch, PatchParams, PostParams};
use kube::{Api, Resource};
use lekiwi_crds::Robot;
use lekiwi_crds::contract::{
    ENROLLMENT_SECRET, MAX_ROBOT_NAME_LEN, REENROLL_ANNOTATION, enrollment_token_secret, managers,
    new_token, robot_token_secret,
};
use lekiwi_protocol::join::Join;
use serde::Serialize;

use crate::Output;

/// `robot` subcommands.
#[derive(Debug, Subcommand)]
pub enum RobotCommand {
    /// Register a robot: create the Robot and its own token, print the command that joins it.
    ///
    /// `lekiwi-agent join` on the robot (printed with the gateway's address, the pin of its CA
    /// and the token) configures the agent; it connects with that token and needs no enrollment
    /// token. The token is printed once; the cluster keeps only its SHA-256.
    Add(AddArgs),
    /// Allow an enrolled robot to enroll again, once, with the enrollment token.
    ///
    /// The gateway never lets an enrollment token take over a robot that has its own token; this
    /// gives that permission once, until it expires. The robot's next enrollment gets a new token
    /// (its current token stops working) and uses up the permission.
    Reenroll(ReenrollArgs),
}

/// Arguments of `robot reenroll`.
#[derive(Debug, Args)]
pub struct ReenrollArgs {
    /// Name of the Robot resource.
    pub name: String,
    /// How long the permission holds (e.g. 15m, 1h).
    #[arg(long = "for", default_value = "15m", value_parser = crate::duration::parse)]
    pub valid_for: std::time::Duration,
}

/// Arguments of `robot add`.
#[derive(Debug, Args)]
pub struct AddArgs {
    /// Name of the Robot resource.
    pub name: String,
    /// Name people use for the robot.
    #[arg(long)]
    pub display_name: Option<String>,
    /// Label of the Robot, `key=value` (repeatable).
    #[arg(long = "label", short = 'l', value_parser = parse_label)]
    pub labels: Vec<(String, String)>,
    /// The gateway's agent URL as robots reach it (default: from the gateway Service's load
    /// balancer or NodePort, else from LEKIWI_SERVER).
    #[arg(long, env = "LEKIWI_GATEWAY_URL")]
    pub gateway: Option<String>,
    /// If the Robot exists, issue it a new token (the old one stops working) instead of failing.
    #[arg(long)]
    pub rotate_token: bool,
}

/// Arguments of `enroll-token`.
#[derive(Debug, Args)]
pub struct EnrollArgs {
    /// Replace an existing enrollment token (robots already enrolled keep their own tokens).
    #[arg(long)]
    pub rotate: bool,
    /// Print the `lekiwi-agent join` command on standard output instead of the bare token.
    #[arg(long)]
    pub print_join_command: bool,
    /// The gateway's agent URL as robots reach it (default: from the gateway Service's load
    /// balancer or NodePort, else from LEKIWI_SERVER).
    #[arg(long, env = "LEKIWI_GATEWAY_URL")]
    pub gateway: Option<String>,
}

fn parse_label(s: &str) -> Result<(String, String), String> {
    let (k, v) = s
        .split_once('=')
        .ok_or_else(|| format!("label {s:?} is not key=value"))?;
    if k.is_empty() {
        return Err(format!("label {s:?} has an empty key"));
    }
    Ok((k.to_owned(), v.to_owned()))
}

/// The agent's WebSocket URL derived from the gateway's HTTP base URL.
pub fn gateway_from_server(server: &str) -> String {
    let server = server.trim_end_matches('/');
    let ws = if let Some(rest) = server.strip_prefix("https://") {
        format!("wss://{rest}")
    } else if let Some(rest) = server.strip_prefix("http://") {
        format!("ws://{rest}")
    } else {
        server.to_owned()
    };
    format!("{ws}{}", lekiwi_protocol::AGENT_PATH)
}

/// What `robot add` hands to the robot.
#[derive(Clone, Debug, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct AgentSetup {
    /// `namespace/name`.
    pub robot: String,
    /// The gateway's agent URL.
    pub gateway: String,
    /// The pin of the gateway's CA, if the cluster publishes the CA.
    pub ca_cert_hash: Option<String>,
    /// The robot's own token.
    pub token: String,
    /// The command that joins the robot, to run on it as root.
    pub join_command: String,
}

/// Where robots join: the gateway's agent URL and the pin of its CA.
#[derive(Clone, Debug)]
pub struct JoinTarget {
    /// `wss://HOST:PORT/v1/agent`.
    pub gateway: String,
    /// `sha256:...` of the gateway's CA; `None` when the cluster does not publish it.
    pub ca_cert_hash: Option<String>,
}

/// Placeholder of a pin the cluster does not publish.
const PIN_PLACEHOLDER: &str = "sha256:PIN-OF-THE-GATEWAY-CA";

impl JoinTarget {
    /// The join command for `token` (and the robot's name, with a robot token).
    pub fn join(&self, token: &str, name: Option<String>) -> Join {
        Join {
            gateway: self.gateway.clone(),
            ca_cert_hash: Some(
                self.ca_cert_hash
                    .clone()
                    .unwrap_or_else(|| PIN_PLACEHOLDER.to_owned()),
            ),
            token: token.to_owned(),
            name,
        }
    }
}

/// The gateway robots join, from `--gateway` or the chart's Service, and its CA's pin from the
/// chart's CA ConfigMap in `gateway_namespace`; what cannot be found is said on standard error
/// and left as a placeholder for the person to fill in.
pub async fn join_target(
    client: &kube::Client,
    gateway_namespace: &str,
    gateway: Option<&str>,
) -> anyhow::Result<JoinTarget> {
    let located = match crate::locate::locate(client, gateway_namespace).await {
        Ok(l) => Some(l),
        Err(e) => {
            eprintln!("warning: {e:#}");
            None
        }
    };
    let ca_cert_hash = match &located {
        Some(l) => l.ca_cert_hash()?,
        None => None,
    };
    let found_url = match (&located, gateway) {
        (Some(l), None) => l.robot_url(client).await.unwrap_or_else(|e| {
            eprintln!("warning: {e:#}");
            None
        }),
        _ => None,
    };
    let gateway = match (gateway, found_url) {
        (Some(g), _) => g.to_owned(),
        (None, Some(u)) => u,
        (None, None) => match std::env::var("LEKIWI_SERVER") {
            Ok(server) if !server.is_empty() => gateway_from_server(&server),
            _ => {
                eprintln!(
                    "warning: robots cannot reach the gateway Service (ClusterIP, or none found): \
                     pass --gateway wss://ADDRESS:PORT/v1/agent, an address robots reach it at \
                     and its certificate names"
                );
                "wss://GATEWAY-ADDRESS:PORT/v1/agent".to_owned()
            }
        },
    };
    if ca_cert_hash.is_none() {
        eprintln!(
            "warning: no CA ConfigMap ({}) in namespace {gateway_namespace}: replace \
             {PIN_PLACEHOLDER} with the pin of the CA of the gateway's certificate \
             (`openssl x509 -pubkey -noout -in ca.crt | openssl pkey -pubin -outform der | \
             sha256sum`)",
            crate::locate::COMPONENT_SELECTOR
        );
    }
    Ok(JoinTarget {
        gateway,
        ca_cert_hash,
    })
}

/// Runs `robot add`.
pub async fn robot_add(
    client: kube::Client,
    namespace: &str,
    gateway_namespace: &str,
    output: Output,
    args: AddArgs,
) -> anyhow::Result<()> {
    let target = join_target(&client, gateway_namespace, args.gateway.as_deref()).await?;
    let setup = add(client, namespace, &target, &args).await?;
    match output.structured(&setup)? {
        Some(text) => print!("{text}"),
        None => {
            eprintln!(
                "robot {} registered; its token is shown once (the cluster keeps only its hash).\n\
                 On the robot, with the lekiwi-agent package installed:",
                setup.robot
            );
            println!("{}", setup.join_command);
        }
    }
    Ok(())
}

/// Refuses a name no robot with a token can have, before anything is created.
fn check_name(name: &str) -> anyhow::Result<()> {
    if name.len() > MAX_ROBOT_NAME_LEN {
        bail!(
            "robot name {name:?} is {} characters long; robot names are at most \
             {MAX_ROBOT_NAME_LEN} (the robot's token Secret carries the name in a label)",
            name.len()
        );
    }
    Ok(())
}

/// Creates the Robot (or, with `--rotate-token`, keeps an existing one) and its token Secret.
pub async fn add(
    client: kube::Client,
    namespace: &str,
    target: &JoinTarget,
    args: &AddArgs,
) -> anyhow::Result<AgentSetup> {
    check_name(&args.name)?;
    let robots: Api<Robot> = Api::namespaced(client.clone(), namespace);
    let robot = Robot {
        metadata: ObjectMeta {
            name: Some(args.name.clone()),
            labels: (!args.labels.is_empty()).then(|| args.labels.iter().cloned().collect()),
            ..ObjectMeta::default()
        },
        spec: lekiwi_crds::RobotSpec {
            display_name: args.display_name.clone(),
            ..lekiwi_crds::RobotSpec::default()
        },
        ..Robot::default()
    };
    let robot = match robots.create(&PostParams::default(), &robot).await {
        Ok(r) => r,
        Err(kube::Error::Api(s)) if s.code == 409 => {
            if !args.rotate_token {
                bail!(
                    "robot {namespace}/{} already exists; pass --rotate-token to issue it a new token (its current token stops working)",
                    args.name
                );
            }
            robots.get(&args.name).await?
        }
        Err(kube::Error::Api(s)) if s.code == 422 || s.code == 400 => {
            bail!(
                "cannot create robot {namespace}/{}: {}",
                args.name,
                s.message
            )
        }
        Err(e) => {
            return Err(e)
                .with_context(|| format!("cannot create robot {namespace}/{}", args.name));
        }
    };
    let token = new_token("lkr_");
    let secret = robot_token_secret(&args.name, &token, robot.controller_owner_ref(&()));
    let secrets: Api<Secret> = Api::namespaced(client, namespace);
    secrets
        .patch(
            &lekiwi_crds::contract::robot_secret_name(&args.name),
            &PatchParams::apply(managers::CLI).force(),
            &Patch::Apply(&secret),
        )
        .await
        .with_context(|| {
            format!(
                "cannot write Secret {namespace}/{} with the robot's token hash",
                lekiwi_crds::contract::robot_secret_name(&args.name)
            )
        })?;
    let full = format!("{namespace}/{}", args.name);
    Ok(AgentSetup {
        robot: full.clone(),
        gateway: target.gateway.clone(),
        ca_cert_hash: target.ca_cert_hash.clone(),
        join_command: target.join(&token, Some(full)).command(),
        token,
    })
}

/// Runs `robot reenroll`: sets the one-time permission on the Robot and says until when.
pub async fn robot_reenroll(
    client: kube::Client,
    namespace: &str,
    args: ReenrollArgs,
) -> anyhow::Result<()> {
    let span = jiff::SignedDuration::try_from(args.valid_for)?;
    let until = jiff::Timestamp::now()
        .checked_add(span)?
        .round(jiff::Unit::Second)?;
    let robots: Api<Robot> = Api::namespaced(client, namespace);
    let patch = serde_json::json!({
        "metadata": { "annotations": { REENROLL_ANNOTATION: until.to_string() } }
    });
    match robots
        .patch(&args.name, &PatchParams::default(), &Patch::Merge(&patch))
        .await
    {
        Ok(_) => {}
        Err(kube::Error::Api(s)) if s.code == 404 => {
            bail!("robot {namespace}/{} does not exist", args.name)
        }
        Err(e) => {
            return Err(e)
                .with_context(|| format!("cannot update robot {namespace}/{}", args.name));
        }
    }
    eprintln!(
        "robot {namespace}/{} may enroll again once until {until}; its current token stops working when it does",
        args.name
    );
    Ok(())
}

/// What `enroll-token` prints.
#[derive(Clone, Debug, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct EnrollmentToken {
    /// Namespace robots enrolling with it are registered in.
    pub namespace: String,
    /// The Secret holding its hash.
    pub secret: String,
    /// The token itself, shown this once.
    pub token: String,
    /// The gateway's agent URL.
    pub gateway: String,
    /// The pin of the gateway's CA, if the cluster publishes the CA.
    pub ca_cert_hash: Option<String>,
    /// The command that joins a robot (named after its host), to run on it as root.
    pub join_command: String,
}

/// Runs `enroll-token`.
pub async fn enroll_token(
    client: kube::Client,
    namespace: &str,
    gateway_namespace: &str,
    output: Output,
    args: EnrollArgs,
) -> anyhow::Result<()> {
    let target = join_target(&client, gateway_namespace, args.gateway.as_deref()).await?;
    let token = make_enrollment_token(client, namespace, args.rotate).await?;
    let join_command = target.join(&token, None).command();
    let made = EnrollmentToken {
        namespace: namespace.to_owned(),
        secret: ENROLLMENT_SECRET.to_owned(),
        token,
        gateway: target.gateway,
        ca_cert_hash: target.ca_cert_hash,
        join_command,
    };
    match output.structured(&made)? {
        Some(text) => print!("{text}"),
        None if args.print_join_command => println!("{}", made.join_command),
        None => {
            eprintln!(
                "fleet enrollment token for namespace {namespace} (Secret {}; shown once, the \
                 cluster keeps only its hash). On each robot, with the lekiwi-agent package \
                 installed (the robot is named after its host; add --name {namespace}/NAME to \
                 choose):\n  {}",
                made.secret, made.join_command
            );
            println!("{}", made.token);
        }
    }
    Ok(())
}

/// Creates the namespace's enrollment token Secret, or replaces its hash with `rotate`; returns
/// the token.
pub async fn make_enrollment_token(
    client: kube::Client,
    namespace: &str,
    rotate: bool,
) -> anyhow::Result<String> {
    let secrets: Api<Secret> = Api::namespaced(client, namespace);
    let token = new_token("lke_");
    let secret = enrollment_token_secret(&token);
    let what = || format!("cannot write Secret {namespace}/{ENROLLMENT_SECRET}");
    if rotate {
        secrets
            .patch(
                ENROLLMENT_SECRET,
                &PatchParams::apply(managers::CLI).force(),
                &Patch::Apply(&secret),
            )
            .await
            .with_context(what)?;
    } else {
        match secrets.create(&PostParams::default(), &secret).await {
            Ok(_) => {}
            Err(kube::Error::Api(s)) if s.code == 409 => bail!(
                "namespace {namespace} already has an enrollment token (Secret {ENROLLMENT_SECRET}); \
                 it cannot be shown again: pass --rotate to replace it"
            ),
            Err(e) => return Err(e).with_context(what),
        }
    }
    Ok(token)
}

#[cfg(test)]
mod tests {
    use super::*;
    use lekiwi_crds::contract::{hash_token, robot_secret_name};

    #[test]
    fn tokens_hash_like_the_gateway() {
        let t = new_token("lkr_");
        assert!(t.starts_with("lkr_") && t.len() == 68);
        assert_eq!(
            hash_token("abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
        assert_eq!(robot_secret_name("kiwi-1"), "kiwi-1-agent-token");
    }

    #[test]
    fn gateway_url_from_server() {
        assert_eq!(
            gateway_from_server("http://127.0.0.1:8081/"),
            "ws://127.0.0.1:8081/v1/agent"
        );
        assert_eq!(
            gateway_from_server("https://fleet.example.com"),
            "wss://fleet.example.com/v1/agent"
        );
    }

    #[test]
    fn labels_parse() {
        assert_eq!(parse_label("a=b=c"), Ok(("a".into(), "b=c".into())));
        assert!(parse_label("nokey").is_err());
        assert!(parse_label("=v").is_err());
    }

    #[test]
    fn a_robot_token_joins_with_its_name_and_a_missing_pin_is_a_placeholder() {
        let target = JoinTarget {
            gateway: "wss://10.0.0.5:30443/v1/agent".into(),
            ca_cert_hash: None,
        };
        let line = target.join("lkr_x", Some("lab/kiwi".into())).command();
        assert_eq!(
            line,
            "sudo lekiwi-agent join --gateway wss://10.0.0.5:30443/v1/agent --ca-cert-hash \
             sha256:PIN-OF-THE-GATEWAY-CA --token lkr_x --name lab/kiwi"
        );
    }
}
