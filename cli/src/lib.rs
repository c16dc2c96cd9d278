//! `kubectl lekiwi`: the fleet's kubectl plugin. Lists and registers robots, makes enrollment
//! tokens, discovers agents on the network, pushes and inspects releases, steers rollouts and
//! shows a robot's stored events.

pub mod discover;
pub mod duration;
pub mod events;
pub mod forward;
pub mod list;
pub mod locate;
pub mod output;
pub mod release;
pub mod robots;
pub mod rollout;
pub mod sanitize;
pub mod tokens;

use std::path::PathBuf;

use clap::{Parser, Subcommand};
use kube::config::{KubeConfigOptions, Kubeconfig};

pub use output::Output;

/// Manage a LeKiwi robot fleet.
#[derive(Debug, Parser)]
#[command(name = "kubectl-lekiwi", bin_name = "kubectl lekiwi", version, about)]
pub struct Cli {
    /// Path to the kubeconfig file.
    #[arg(long, global = true, env = "KUBECONFIG")]
    pub kubeconfig: Option<PathBuf>,
    /// Kubeconfig context to use.
    #[arg(long, global = true)]
    pub context: Option<String>,
    /// Namespace (default: the context's namespace).
    #[arg(short = 'n', long, global = true)]
    pub namespace: Option<String>,
    /// List across all namespaces.
    #[arg(short = 'A', long, global = true)]
    pub all_namespaces: bool,
    /// Output format: table, wide, json, yaml (a `List` for lists, as kubectl prints), name
    /// (`kind.group/name`), or jsonpath=TEMPLATE (kubectl's `{.items[*].metadata.name}`
    /// syntax; `{range}` loops are not supported).
    #[arg(short = 'o', long, global = true, default_value = "table")]
    pub output: Output,
    /// Print tables without their header line.
    #[arg(long, global = true)]
    pub no_headers: bool,
    /// Namespace the chart installed the gateway in (its Service and CA ConfigMap are found
    /// there by label).
    #[arg(
        long,
        global = true,
        env = "LEKIWI_GATEWAY_NAMESPACE",
        default_value = locate::DEFAULT_GATEWAY_NAMESPACE
    )]
    pub gateway_namespace: String,
    #[command(subcommand)]
    pub command: Command,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// List robots with phase, release, teleoperation and last heartbeat, or count them by
    /// agent version, release or phase (`--group-by`).
    Robots(robots::RobotsArgs),
    /// Register robots by hand.
    Robot {
        /// What to do.
        #[command(subcommand)]
        command: tokens::RobotCommand,
    },
    /// Create (or rotate) the namespace's fleet enrollment token and print it once.
    EnrollToken(tokens::EnrollArgs),
    /// Find agents on the network (mDNS and --probe) and show which are registered.
    ///
    /// Lists every agent found, whatever namespace it names; `-n` narrows the list to one
    /// namespace (a robot advertising a bare name counts as in the current namespace).
    Discover(discover::DiscoverArgs),
    /// Show a robot's stored events (from the gateway's event store).
    Events(events::EventsArgs),
    /// Watch and steer a RobotDeployment's rollout.
    Rollout {
        /// What to do.
        #[command(subcommand)]
        command: rollout::RolloutCommand,
    },
    /// Push a directory as a release to the gateway's blob store, or inspect a stored release.
    Release {
        /// Where the gateway is and which Kubernetes token to present to it.
        #[command(flatten)]
        server: release::ServerArgs,
        /// What to do.
        #[command(subcommand)]
        command: release::ReleaseCommand,
    },
    /// Push a build of `lekiwi-agent` to the gateway's blob store, for `Robot.spec.agent`.
    Agent {
        /// Where the gateway is and which Kubernetes token to present to it.
        #[command(flatten)]
        server: release::ServerArgs,
        /// What to do.
        #[command(subcommand)]
        command: release::agent::AgentCommand,
    },
    /// Print a shell completion script for `kubectl-lekiwi` (bash, zsh, fish, elvish or
    /// powershell), e.g. `source <(kubectl lekiwi completion bash)`.
    Completion {
        /// The shell.
        shell: clap_complete::Shell,
    },
}

/// Runs one command.
pub async fn run(cli: Cli) -> anyhow::Result<()> {
    if let Command::Completion { shell } = cli.command {
        let mut command = <Cli as clap::CommandFactory>::command();
        let mut script = Vec::new();
        clap_complete::generate(shell, &mut command, "kubectl-lekiwi", &mut script);
        // Written at once, so that a closed pipe is an error rather than a panic.
        std::io::Write::write_all(&mut std::io::stdout(), &script)?;
        return Ok(());
    }
    if let Command::Discover(_) = &cli.command {
        // Discovery works without a cluster: it only cannot say what is registered then.
        let (client, default_ns) = match context(&cli).await {
            Ok(k) => (Ok(k.client), k.namespace),
            Err(e) => (Err(e), "default".to_owned()),
        };
        let namespace = cli.namespace.clone().unwrap_or(default_ns);
        let only = (!cli.all_namespaces && cli.namespace.is_some()).then_some(namespace.as_str());
        let Command::Discover(args) = cli.command else {
            unreachable!("matched above")
        };
        return discover::run(client, &namespace, only, &cli.output, cli.no_headers, args).await;
    }
    let kube = context(&cli).await?;
    let (client, namespace) = (kube.client.clone(), kube.namespace.clone());
    match cli.command {
        Command::Robots(args) => {
            let ns = if cli.all_namespaces {
                None
            } else {
                Some(namespace.as_str())
            };
            robots::run(client, ns, &cli.output, cli.no_headers, args).await?;
        }
        Command::Rollout { command } => {
            let ns = (!cli.all_namespaces).then_some(namespace.as_str());
            let format = (&cli.output, cli.no_headers);
            rollout::run(&kube, ns, format, command).await?;
        }
        Command::Release { server, command } => {
            release::run(&kube, &server, cli.output.clone(), command).await?;
        }
        Command::Agent { server, command } => {
            release::agent::run(&kube, &server, command).await?;
        }
        Command::Robot {
            command: tokens::RobotCommand::Add(args),
        } => {
            tokens::robot_add(
                client,
                &namespace,
                &cli.gateway_namespace,
                cli.output.clone(),
                args,
            )
            .await?;
        }
        Command::Robot {
            command: tokens::RobotCommand::Reenroll(args),
        } => {
            tokens::robot_reenroll(client, &namespace, args).await?;
        }
        Command::EnrollToken(args) => {
            tokens::enroll_token(
                client,
                &namespace,
                &cli.gateway_namespace,
                cli.output.clone(),
                args,
            )
            .await?;
        }
        Command::Discover(_) | Command::Completion { .. } => {
            unreachable!("handled before the client is required")
        }
        Command::Events(args) => {
            events::run(&kube, &cli.output, cli.no_headers, args).await?;
        }
    }
    Ok(())
}

/// What commands take from the kubeconfig.
pub struct KubeContext {
    /// A client with the user's credentials.
    pub client: kube::Client,
    /// `-n`, else the context's namespace.
    pub namespace: String,
    /// The user's bearer token for the gateway, or why the kubeconfig has none.
    pub bearer: Result<String, String>,
    /// `--gateway-namespace`: where the chart's gateway is found.
    pub gateway_namespace: String,
}

async fn context(cli: &Cli) -> anyhow::Result<KubeContext> {
    let options = KubeConfigOptions {
        context: cli.context.clone(),
        ..KubeConfigOptions::default()
    };
    let config = match &cli.kubeconfig {
        // KUBECONFIG may list several files separated by ':'; kube merges them.
        Some(path) if !path.as_os_str().to_string_lossy().contains(':') => {
            let kc = Kubeconfig::read_from(path)?;
            kube::Config::from_custom_kubeconfig(kc, &options).await?
        }
        _ if cli.context.is_some() => kube::Config::from_kubeconfig(&options).await?,
        _ => kube::Config::infer().await?,
    };
    let namespace = cli
        .namespace
        .clone()
        .unwrap_or_else(|| config.default_namespace.clone());
    let bearer = bearer_token(&config).await;
    Ok(KubeContext {
        client: kube::Client::try_from(config)?,
        namespace,
        bearer,
        gateway_namespace: cli.gateway_namespace.clone(),
    })
}

/// The bearer token kube would send to the API server for this kubeconfig user: a `token` or
/// `tokenFile`, or what its exec plugin or OIDC provider returns (refreshed as kube refreshes
/// it); or why there is none. The gateway takes only bearer tokens: a user with a client
/// certificate (or basic auth) needs `--token`.
async fn bearer_token(config: &kube::Config) -> Result<String, String> {
    use http::{Request, Response, header::AUTHORIZATION};
    use kube::client::{Body, ConfigExt as _};
    use tower::{Layer as _, ServiceExt as _};
    let hint = "pass --token (or LEKIWI_TOKEN) with a bearer token the API server accepts, e.g. \
                `kubectl create token SERVICE_ACCOUNT -n NAMESPACE`";
    let how = if config.auth_info.client_certificate.is_some()
        || config.auth_info.client_certificate_data.is_some()
    {
        "a client certificate"
    } else if config.auth_info.username.is_some() {
        "a user name and password"
    } else {
        "no credentials"
    };
    let cannot = |how: &str| {
        Err(format!(
            "the kubeconfig user authenticates with {how}, which the gateway cannot check (it \
             takes bearer tokens): {hint}"
        ))
    };
    let layer = match config.auth_layer() {
        Ok(Some(layer)) => layer,
        Ok(None) => return cannot(how),
        Err(e) => return Err(format!("the kubeconfig user's credentials: {e}; or {hint}")),
    };
    let seen = std::sync::Arc::new(std::sync::Mutex::new(None));
    let capture = {
        let seen = seen.clone();
        tower::service_fn(move |req: Request<Body>| {
            let header = req.headers().get(AUTHORIZATION).cloned();
            *seen.lock().unwrap_or_else(|e| e.into_inner()) = header;
            async { Ok::<_, tower::BoxError>(Response::new(Body::empty())) }
        })
    };
    if let Err(e) = layer
        .layer(capture)
        .oneshot(Request::new(Body::empty()))
        .await
    {
        return Err(format!(
            "the kubeconfig user's credential plugin failed: {e}; or {hint}"
        ));
    }
    let header = seen.lock().unwrap_or_else(|e| e.into_inner()).take();
    match header.as_ref().and_then(|h| h.to_str().ok()) {
        Some(value) => match value.strip_prefix("Bearer ") {
            Some(token) => Ok(token.trim().to_owned()),
            None => cannot("a user name and password"),
        },
        None => cannot(how),
    }
}

/// A reqwest error with its cause chain (where a certificate or a connection failed) and without
/// the URL (the caller names the address).
pub(crate) fn http_error(e: &reqwest::Error) -> String {
    let mut text = if e.is_timeout() {
        "timed out".to_owned()
    } else if e.is_connect() {
        "cannot connect".to_owned()
    } else {
        "request failed".to_owned()
    };
    let mut source = std::error::Error::source(e);
    while let Some(s) = source {
        text.push_str(&format!(": {s}"));
        source = s.source();
    }
    text
}

/// Whether a request failed in the TLS handshake (an untrusted or wrong certificate): trying
/// again cannot help.
pub(crate) fn tls_refused(e: &reqwest::Error) -> bool {
    /// `e` or what it wraps or was caused by is a rustls error (I/O errors carry it inside).
    fn rustls_inside(e: &(dyn std::error::Error + 'static)) -> bool {
        if e.is::<rustls::Error>() {
            return true;
        }
        if let Some(inner) = e
            .downcast_ref::<std::io::Error>()
            .and_then(|io| io.get_ref())
            && rustls_inside(inner)
        {
            return true;
        }
        e.source().is_some_and(rustls_inside)
    }
    std::error::Error::source(e).is_some_and(rustls_inside)
}

#[cfg(test)]
mod tests {
    use super::bearer_token;
    use kube::config::{KubeConfigOptions, Kubeconfig};

    async fn token_of(user: &str) -> Result<String, String> {
        let user = user.replace('\n', "\n    ");
        let yaml = format!(
            "apiVersion: v1\nkind: Config\ncurrent-context: c\n\
             clusters: [{{name: k, cluster: {{server: 'https://127.0.0.1:1'}}}}]\n\
             contexts: [{{name: c, context: {{cluster: k, user: u}}}}]\n\
             users:\n- name: u\n  user:\n    {user}\n"
        );
        let kc: Kubeconfig = serde_yaml::from_str(&yaml).unwrap();
        let config = kube::Config::from_custom_kubeconfig(kc, &KubeConfigOptions::default())
            .await
            .unwrap();
        bearer_token(&config).await
    }

    #[tokio::test]
    async fn the_gateway_gets_the_token_kube_would_send_exec_plugins_included() {
        assert_eq!(token_of("token: abc").await.unwrap(), "abc");
        let file = tempfile::NamedTempFile::new().unwrap();
        std::fs::write(file.path(), "from-file").unwrap();
        let with_file = format!("tokenFile: {}", file.path().display());
        assert_eq!(token_of(&with_file).await.unwrap(), "from-file");
        // An exec plugin (EKS, GKE, AKS, kubelogin, Teleport work this way): its token.
        let plugin = tempfile::NamedTempFile::new().unwrap();
        std::fs::write(
            plugin.path(),
            r#"{"apiVersion":"client.authentication.k8s.io/v1","kind":"ExecCredential","status":{"token":"from-exec"}}"#,
        )
        .unwrap();
        let exec = format!(
            "exec: {{apiVersion: client.authentication.k8s.io/v1, command: cat, args: ['{}'], interactiveMode: Never}}",
            plugin.path().display()
        );
        assert_eq!(token_of(&exec).await.unwrap(), "from-exec");
        for (user, how) in [
            (
                "client-certificate-data: Zm9v\nclient-key-data: Zm9v",
                "a client certificate",
            ),
            (
                "exec: {apiVersion: client.authentication.k8s.io/v1, command: /nonexistent/plugin, interactiveMode: Never}",
                "credential",
            ),
        ] {
            let err = token_of(user).await.unwrap_err();
            assert!(err.contains(how) && err.contains("--token"), "{err}");
            assert!(err.contains("kubectl create token"), "{err}");
        }
    }
}
