//! `lekiwi-fleet`: N real agents in one process, for rollout tests and benchmarks.

use clap::Parser;

fn main() -> anyhow::Result<()> {
    let args = lekiwi_agent::fleet::Args::parse();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stdout()))
        .init();
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    runtime.block_on(lekiwi_agent::fleet::run(args, async {
        let _ = tokio::signal::ctrl_c().await;
    }))
}
