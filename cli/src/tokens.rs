//! `kubectl lekiwi robot add NAME` and `kubectl lekiwi enroll-token`: register a robot with its
//! own token, or make the namespace's fleet enrollment token. Tokens are printed once and kept
//! in the cluster only as SHA-256 hashes, in Secrets shaped exactly as the gateway reads them.

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
use serde::Serialize;

use crate::Output;

/// The agent's default state directory (agent `stateDir`).
pub const AGENT_STATE_DIR: &str = "/var/lib/lekiwi";
/// The agent's default config file.
pub const AGENT_CONFIG: &str = "/etc/lekiwi/agent.yaml";

/// `robot` subcommands.
#[derive(Debug, Subcommand)]
pub enum RobotCommand {
    /// Register a robot: create the Robot and its own token, print the agent's configuration.
    ///
    /// The agent then connects with that token and needs no enrollment token. The token is
    /// printed once; the cluster keeps only its SHA-256.
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
    /// WebSocket URL of the gateway for the agent config (default: from LEKIWI_SERVER).
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
    /// Contents of `/etc/lekiwi/agent.yaml`.
    pub agent_config: AgentConfig,
    /// Contents of `<stateDir>/credentials.json` (mode 0600).
    pub credentials: Credentials,
}

/// The agent config keys `robot add` sets.
#[derive(Clone, Debug, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct AgentConfig {
    /// Gateway WebSocket URL.
    pub gateway: String,
    /// `namespace/name`.
    pub robot_name: String,
    /// Where the agent keeps its credentials.
    pub state_dir: String,
}

/// The agent's `credentials.json`.
#[derive(Clone, Debug, Serialize)]
pub struct Credentials {
    /// `namespace/name`.
    pub robot: String,
    /// The per-robot token.
    pub token: String,
}

impl AgentSetup {
    /// Shell commands that install the configuration on the robot.
    pub fn install_script(&self) -> anyhow::Result<String> {
        let yaml = serde_yaml::to_string(&self.agent_config)?;
        let creds = serde_json::to_string(&self.credentials)?;
        let dir = &self.agent_config.state_dir;
        Ok(format!(
            "# On the robot, as root:\n\
             install -d -m 0755 /etc/lekiwi\n\
             install -d -m 0700 {dir}\n\
             cat > {AGENT_CONFIG} <<'EOF'\n{yaml}EOF\n\
             (umask 077 && cat > {dir}/credentials.json <<'EOF'\n{creds}\nEOF\n)\n\
             chmod 0600 {dir}/credentials.json\n\
             systemctl restart lekiwi-agent  # or start lekiwi-agent by hand\n"
        ))
    }
}

/// Runs `robot add`.
pub async fn robot_add(
    client: kube::Client,
    namespace: &str,
    output: Output,
    args: AddArgs,
) -> anyhow::Result<()> {
    let setup = add(client, namespace, &args).await?;
    match output.structured(&setup)? {
        Some(text) => print!("{text}"),
        None => {
            eprintln!(
                "robot {} registered; its token is shown once (the cluster keeps only its hash)",
                setup.robot
            );
            print!("{}", setup.install_script()?);
        }
    }
    Ok(())
}

/// The gateway URL for the agent's config: `--gateway`, else derived from `LEKIWI_SERVER`, else a
/// placeholder (with a warning) for the person to edit.
fn agent_gateway(args: &AddArgs) -> String {
    match &args.gateway {
        Some(g) => g.clone(),
        None => match std::env::var("LEKIWI_SERVER") {
            Ok(server) if !server.is_empty() => gateway_from_server(&server),
            _ => {
                eprintln!(
                    "warning: no --gateway (or LEKIWI_GATEWAY_URL / LEKIWI_SERVER): edit `gateway` in the printed config"
                );
                "wss://GATEWAY-HOST/v1/agent".to_owned()
            }
        },
    }
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
    args: &AddArgs,
) -> anyhow::Result<AgentSetup> {
    check_name(&args.name)?;
    let gateway = agent_gateway(args);
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
        agent_config: AgentConfig {
            gateway,
            robot_name: full.clone(),
            state_dir: AGENT_STATE_DIR.to_owned(),
        },
        credentials: Credentials { robot: full, token },
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
}

/// Runs `enroll-token`.
pub async fn enroll_token(
    client: kube::Client,
    namespace: &str,
    output: Output,
    args: EnrollArgs,
) -> anyhow::Result<()> {
    let made = make_enrollment_token(client, namespace, args.rotate).await?;
    match output.structured(&made)? {
        Some(text) => print!("{text}"),
        None => {
            eprintln!(
                "fleet enrollment token for namespace {namespace} (Secret {}; shown once, the cluster keeps only its hash).\n\
                 On each robot: write it to a file readable only by root, e.g. /etc/lekiwi/enrollment-token,\n\
                 and set in {AGENT_CONFIG}:\n  enrollmentTokenFile: /etc/lekiwi/enrollment-token\n  robotName: {namespace}/<name>",
                made.secret
            );
            println!("{}", made.token);
        }
    }
    Ok(())
}

/// Creates the namespace's enrollment token Secret, or replaces its hash with `rotate`.
pub async fn make_enrollment_token(
    client: kube::Client,
    namespace: &str,
    rotate: bool,
) -> anyhow::Result<EnrollmentToken> {
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
    Ok(EnrollmentToken {
        namespace: namespace.to_owned(),
        secret: ENROLLMENT_SECRET.to_owned(),
        token,
    })
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
    fn install_script_writes_private_credentials() {
        let setup = AgentSetup {
            robot: "lab/kiwi".into(),
            agent_config: AgentConfig {
                gateway: "ws://gw/v1/agent".into(),
                robot_name: "lab/kiwi".into(),
                state_dir: AGENT_STATE_DIR.into(),
            },
            credentials: Credentials {
                robot: "lab/kiwi".into(),
                token: "lkr_x".into(),
            },
        };
        let script = setup.install_script().unwrap();
        assert!(script.contains("robotName: lab/kiwi"));
        assert!(script.contains(r#"{"robot":"lab/kiwi","token":"lkr_x"}"#));
        assert!(script.contains("chmod 0600 /var/lib/lekiwi/credentials.json"));
    }
}
