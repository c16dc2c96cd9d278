//! `lekiwi-sim`: simulate a fleet of agents against a gateway.

use clap::Parser;

fn main() -> anyhow::Result<()> {
    let args = lekiwi_agent::sim::Args::parse();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let summary = runtime.block_on(lekiwi_agent::sim::run(args))?;
    println!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(())
}
