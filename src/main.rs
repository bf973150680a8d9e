//! `mwb`: the manyworlds command line. See README.md and ARCHITECTURE.md.
//!
//! This file only parses the command line and hands each command to its module.

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use mwb::query::QueryCommand;

#[derive(Parser)]
#[command(
    name = "mwb",
    version,
    about = "manyworlds: sample, store and browse thousands of plausible rigid-body worlds"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Everything in one process: an embedded bus, a store, samplers; sample a shipped scene.
    Demo(mwb::demo::DemoArgs),
    /// Run a store node (default: a zenoh router other nodes --connect to).
    Store(mwb::store::StoreArgs),
    /// Browse: constraints, results, rankings (talks to node-query); `serve` runs node-query.
    Query {
        #[command(subcommand)]
        command: QueryCommand,
    },
    /// Run a sampler node; it joins open jobs at any time.
    Sampler(mwb::sampler::SamplerArgs),
    /// Backward worlds from a final state (ch. 5): a reverse node, or node + job with --scene.
    Reverse(mwb::reverse_cmd::ReverseArgs),
    /// Submit, list and cancel jobs.
    Job {
        #[command(subcommand)]
        command: mwb::job::JobCommand,
    },
    /// Live nodes, job progress and throughput.
    Status(mwb::status::StatusArgs),
    /// Check a scene file: parse, validate, instantiate one world.
    Scene(mwb::scene::SceneArgs),
    /// Record every put on the bus (mwb/<space>/**) into an MCAP file until Ctrl-C or --duration.
    Record(mwb::record_cmd::RecordArgs),
    /// Put a recording back on the bus in order (--speed 1|4|max) into --space.
    Replay(mwb::record_cmd::ReplayArgs),
    /// Benchmarks: a table each, or with --json one JSON line per result.
    Bench {
        #[command(subcommand)]
        command: mwb::bench::BenchCommand,
    },
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    // Long-running nodes log what they do; one-shot commands (demo, bench, job, …) print their
    // result and only warnings. RUST_LOG overrides both.
    let default_filter = match cli.command {
        Command::Store(_)
        | Command::Sampler(_)
        | Command::Record(_)
        | Command::Query {
            command: QueryCommand::Serve { .. },
        } => "warn,mwb=info",
        _ => "warn",
    };
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_filter)),
        )
        .with_writer(std::io::stderr)
        .init();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    rt.block_on(run(cli.command))
}

async fn run(command: Command) -> Result<()> {
    match command {
        Command::Demo(args) => mwb::demo::run(args).await,
        Command::Store(args) => mwb::store::run(args).await,
        Command::Query { command } => mwb::query::run(command).await,
        Command::Sampler(args) => mwb::sampler::run(args).await,
        Command::Reverse(args) => mwb::reverse_cmd::run(args).await,
        Command::Job { command } => mwb::job::run(command).await,
        Command::Status(args) => mwb::status::run(args).await,
        Command::Scene(args) => mwb::scene::run(args),
        Command::Record(args) => mwb::record_cmd::record(args).await,
        Command::Replay(args) => mwb::record_cmd::replay(args).await,
        Command::Bench { command } => mwb::bench::run(command).await,
    }
}
