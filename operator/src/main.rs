//! `lekiwi-operator` entry point: parse flags, start telemetry, run until a signal or a failure.

use clap::Parser;

#[tokio::main]
async fn main() -> std::process::ExitCode {
    let config = lekiwi_operator::config::Config::parse();
    // One file descriptor per agent connection: use all the kernel allows us.
    let _ = rlimit::increase_nofile_limit(u64::MAX);
    if let Err(e) = lekiwi_operator::telemetry::init(&config.log_format, &config.log_level) {
        eprintln!("lekiwi-operator: cannot start logging: {e}");
        return std::process::ExitCode::FAILURE;
    }
    match lekiwi_operator::run(config).await {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            tracing::error!(error = %e, "lekiwi-operator stopped");
            eprintln!("lekiwi-operator: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}
