//! `lekiwi-operator` entry point: parse flags, start telemetry, run until a signal or a failure.

use clap::Parser;

/// The process's allocator. A gateway runs for weeks while rollouts come and go: with glibc's
/// allocator its resident memory grew 49 MiB in the soak's last 40 minutes at a constant number
/// of sessions; with mimalloc, which returns freed pages to the system, it stayed within the
/// noise (`bench/soak.sh`, docs/src/benchmarks/soak.md).
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[tokio::main]
async fn main() -> std::process::ExitCode {
    let config = lekiwi_operator::config::Config::parse();
    // One file descriptor per agent connection: use all the kernel allows us.
    let _ = rlimit::increase_nofile_limit(u64::MAX);
    let telemetry = match lekiwi_operator::telemetry::init(&config.log_format, &config.log_level) {
        Ok(t) => t,
        Err(e) => {
            eprintln!("lekiwi-operator: cannot start logging and tracing: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    let code = match lekiwi_operator::run(config).await {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            tracing::error!(error = %e, "lekiwi-operator stopped");
            eprintln!("lekiwi-operator: {e}");
            std::process::ExitCode::FAILURE
        }
    };
    // The batch exporter flushes with blocking HTTP: off the async workers.
    let _ = tokio::task::spawn_blocking(move || telemetry.shutdown()).await;
    code
}
