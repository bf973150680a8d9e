//! `mwb`: the manyworlds command line. See README.md and ARCHITECTURE.md.
//!
//! This file only parses the command line and hands each command to its module.

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use mwb::query::QueryCommand;
use std::process::ExitCode;

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
    /// The workstation viewer: worlds' paths as a live cluster indexes them (or, with --scene,
    /// sampled here), screen boxes, rankings, playback; --screenshot renders it to a PNG.
    Viewer(mwb::viewer_cmd::ViewerArgs),
    /// Regenerate one world from its scene and seed alone: its summary and digest (--check N:
    /// compare with stored world N).
    World(mwb::world_cmd::WorldArgs),
    /// Refine a stored world (§4.5): re-simulate the picked bodies from the first frame one of
    /// them enters a box, keeping the rest of the world; submits a REFINE job.
    Refine(mwb::refine_cmd::RefineArgs),
    /// Export worlds (from a store, a recording, or a seed) as glTF 2.0 .glb, Foxglove MCAP, CSV
    /// or JSON.
    Export(mwb::export_cmd::ExportArgs),
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

/// Every error exits non-zero; a reader that closed the pipe (`mwb … | head`) ends the command
/// quietly and successfully, as Unix tools do.
fn main() -> ExitCode {
    quiet_on_closed_stdout();
    match start() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) if mwb::output::is_broken_pipe(&e) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("Error: {e:?}");
            ExitCode::FAILURE
        }
    }
}

/// Our output goes through `mwb::output::out`, which returns a closed pipe as an error; a
/// `println!` left anywhere would panic instead ("failed printing to stdout: Broken pipe").
/// This hook turns exactly that panic into the same quiet, successful exit; every other panic
/// is reported as before.
fn quiet_on_closed_stdout() {
    let report = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let message = info
            .payload()
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| info.payload().downcast_ref::<&str>().copied())
            .unwrap_or("");
        if message.starts_with("failed printing to stdout") && message.contains("Broken pipe") {
            std::process::exit(0);
        }
        report(info);
    }));
}

fn start() -> Result<()> {
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
        Command::Viewer(args) => mwb::viewer_cmd::run(args).await,
        Command::World(args) => mwb::world_cmd::run(args).await,
        Command::Refine(args) => mwb::refine_cmd::run(args).await,
        Command::Export(args) => mwb::export_cmd::run(args).await,
        Command::Record(args) => mwb::record_cmd::record(args).await,
        Command::Replay(args) => mwb::record_cmd::replay(args).await,
        Command::Bench { command } => mwb::bench::run(command).await,
    }
}
