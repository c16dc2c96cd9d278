//! `lekiwi-agent` entry point: flags, logging, a single-threaded runtime, signals.

use anyhow::Context;
use clap::Parser;
use lekiwi_agent::config::{Command, Config, Flags};
use lekiwi_agent::outbox::{Lane, Outbox};
use lekiwi_agent::run::{Agent, Stopped};
use lekiwi_agent::selfupdate::{self, guard};
use lekiwi_protocol::{AgentMessage, MAX_FRAME_BYTES, MAX_SEQ, Severity};

fn main() -> anyhow::Result<()> {
    let flags = Flags::parse();
    match &flags.command {
        Some(Command::Guard { check }) => return run_guard(&flags, *check),
        Some(Command::Adopt { robot, token_file }) => return run_adopt(&flags, robot, token_file),
        Some(Command::Join(args)) => return run_join(args),
        Some(command) => return queue_event(&flags, command),
        None => {}
    }
    let hostname = std::fs::read_to_string("/etc/hostname").unwrap_or_default();
    let config = Config::load(&flags, hostname.trim())?;
    if flags.print_config {
        print!("{}", serde_yaml::to_string(&config)?);
        return Ok(());
    }
    init_logging(&config.log_format);
    if let Some(warning) = config.plaintext_warning() {
        tracing::warn!("{warning}");
    }
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let stopped = runtime.block_on(async {
        let agent = Agent::new(config).await?;
        anyhow::Ok(agent.run(shutdown_signal()).await?)
    })?;
    if stopped == Stopped::Updated {
        tracing::info!(
            status = selfupdate::EXIT_UPDATED,
            "exiting so that the service manager starts the new agent build"
        );
        std::process::exit(selfupdate::EXIT_UPDATED);
    }
    Ok(())
}

/// `lekiwi-agent guard [--check]`: undoes an agent update that did not come back (see
/// [`guard`]); prints what it did.
fn run_guard(flags: &Flags, check: bool) -> anyhow::Result<()> {
    let config = Config::merge(flags)?;
    let slots = selfupdate::Slots::new(&config.state_dir);
    let mode = if check {
        guard::Mode::Check
    } else {
        guard::Mode::Start
    };
    let undone = match guard::run(&slots, mode, lekiwi_protocol::now_ms()) {
        Ok(u) => u,
        Err(e) => {
            // Never keep the agent from starting: the next run tries again.
            eprintln!("lekiwi-agent guard: {e}");
            return Ok(());
        }
    };
    if let Some(fb) = undone {
        println!(
            "switched back from agent {} ({}): {}",
            fb.version, fb.digest, fb.reason
        );
        if check {
            std::process::exit(guard::EXIT_FELL_BACK);
        }
    }
    Ok(())
}

/// `lekiwi-agent join`: see [`lekiwi_agent::join`].
fn run_join(args: &lekiwi_agent::join::JoinArgs) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    runtime.block_on(lekiwi_agent::join::run(args))?;
    Ok(())
}

/// `lekiwi-agent adopt`: saves a robot's existing token as the state directory's credentials.
fn run_adopt(flags: &Flags, robot: &str, token_file: &std::path::Path) -> anyhow::Result<()> {
    use std::io::Read as _;
    let config = Config::merge(flags)?;
    let mut token = String::new();
    if token_file.as_os_str() == "-" {
        std::io::stdin()
            .take(4096)
            .read_to_string(&mut token)
            .context("reading the token from standard input")?;
    } else {
        std::fs::File::open(token_file)
            .and_then(|f| f.take(4096).read_to_string(&mut token))
            .with_context(|| format!("reading the token from {}", token_file.display()))?;
    }
    let dir = &config.state_dir;
    match lekiwi_agent::state::adopt(dir, robot, token.trim())? {
        lekiwi_agent::state::Adopted::Written => println!(
            "saved the token of {robot} in {}; the agent connects as that robot",
            dir.display()
        ),
        lekiwi_agent::state::Adopted::Unchanged => {
            println!("{} already holds this token of {robot}", dir.display())
        }
    }
    Ok(())
}

/// `lekiwi-agent event`: stores the event in the outbox (the running agent sends it) and
/// prints its sequence number.
fn queue_event(flags: &Flags, command: &Command) -> anyhow::Result<()> {
    let Command::Event {
        kind,
        message,
        severity,
        data,
        critical,
    } = command
    else {
        anyhow::bail!("not an event command");
    };
    let config = Config::merge(flags)?;
    let data: serde_json::Value = match data {
        Some(d) => serde_json::from_str(d).context("--data is not valid JSON")?,
        None => serde_json::Value::Null,
    };
    let severity = match severity.as_str() {
        "warning" => Severity::Warning,
        "error" => Severity::Error,
        _ => Severity::Info,
    };
    let ts_ms = lekiwi_protocol::now_ms();
    let event = |seq| AgentMessage::Event {
        seq,
        ts_ms,
        kind: kind.clone(),
        severity,
        message: message.clone(),
        data: data.clone(),
    };
    // A frame the gateway refuses as too large would never be stored: refuse it here.
    let size = lekiwi_protocol::encode(&event(MAX_SEQ)).len();
    if size > MAX_FRAME_BYTES {
        anyhow::bail!(
            "the event is {size} bytes as a frame; the gateway accepts at most {MAX_FRAME_BYTES}: shorten --message or --data"
        );
    }
    lekiwi_agent::state::ensure_dir(&config.state_dir)?;
    let mut outbox = Outbox::open(&config.state_dir, config.outbox_max_bytes)?;
    let lane = if *critical {
        Lane::Critical
    } else {
        Lane::Event
    };
    let seq = outbox.push(lane, ts_ms, event)?;
    println!("{seq}");
    Ok(())
}

fn init_logging(format: &str) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    // No colour codes under journald or in a file: only a terminal gets them.
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stdout()));
    if format == "json" {
        builder.json().init();
    } else {
        builder.init();
    }
}

async fn shutdown_signal() {
    use tokio::signal::unix::{SignalKind, signal};
    let mut term = signal(SignalKind::terminate()).expect("SIGTERM handler");
    let mut int = signal(SignalKind::interrupt()).expect("SIGINT handler");
    tokio::select! {
        _ = term.recv() => {}
        _ = int.recv() => {}
    }
}
