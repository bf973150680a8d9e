//! `mwb`: the manyworlds command line. See README.md and ARCHITECTURE.md.
//!
//! This file only parses the command line and hands each command to its module.

use anyhow::{Context, Result};
use clap::Parser as _;
use mwb::cli::{Cli, Command};
use mwb::query::QueryCommand;
use std::process::ExitCode;

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
        Command::Scene(args) => mwb::scene::run(args).await,
        Command::Viewer(args) => mwb::viewer_cmd::run(args).await,
        Command::World(args) => mwb::world_cmd::run(args).await,
        Command::Refine(args) => mwb::refine_cmd::run(args).await,
        Command::Export(args) => mwb::export_cmd::run(args).await,
        Command::Record(args) => mwb::record_cmd::record(args).await,
        Command::Replay(args) => mwb::record_cmd::replay(args).await,
        Command::Certs(args) => mwb::certs_cmd::run(args),
        Command::Bench { command } => mwb::bench::run(command).await,
    }
}
