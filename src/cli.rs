//! The command line's shape: every subcommand and its arguments, as clap sees them. `main.rs`
//! parses it and dispatches; tests read it ([`command`]) to check that what `deploy/` runs
//! exists.

use clap::{CommandFactory as _, Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "mwb",
    version,
    about = "manyworlds: sample, store and browse thousands of plausible rigid-body worlds"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand)]
pub enum Command {
    /// Everything in one process: an embedded bus, a store, samplers; sample a shipped scene.
    Demo(crate::demo::DemoArgs),
    /// Run a store node (default: a zenoh router other nodes --connect to).
    Store(crate::store::StoreArgs),
    /// Browse: constraints, results, rankings (talks to node-query); `serve` runs node-query.
    Query {
        #[command(subcommand)]
        command: crate::query::QueryCommand,
    },
    /// Run a sampler node; it joins open jobs at any time.
    Sampler(crate::sampler::SamplerArgs),
    /// Backward worlds from a final state (ch. 5): a reverse node, or node + job with --scene.
    Reverse(crate::reverse_cmd::ReverseArgs),
    /// Submit, list and cancel jobs.
    Job {
        #[command(subcommand)]
        command: crate::job::JobCommand,
    },
    /// Live nodes, job progress and throughput.
    Status(crate::status::StatusArgs),
    /// Check a scene file: parse, validate, instantiate one world.
    Scene(crate::scene::SceneArgs),
    /// The workstation viewer: worlds' paths as a live cluster indexes them (or, with --scene,
    /// sampled here), screen boxes, rankings, playback; --screenshot renders it to a PNG.
    Viewer(crate::viewer_cmd::ViewerArgs),
    /// Regenerate one world from its scene and seed alone: its summary and digest (--check N:
    /// compare with stored world N).
    World(crate::world_cmd::WorldArgs),
    /// Refine a stored world (§4.5): re-simulate the picked bodies from the first frame one of
    /// them enters a box, keeping the rest of the world; submits a REFINE job.
    Refine(crate::refine_cmd::RefineArgs),
    /// Export worlds (from a store, a recording, or a seed) as glTF 2.0 .glb, Foxglove MCAP, CSV
    /// or JSON.
    Export(crate::export_cmd::ExportArgs),
    /// Record every put on the bus (mwb/<space>/**) into an MCAP file until Ctrl-C or --duration.
    Record(crate::record_cmd::RecordArgs),
    /// Put a recording back on the bus in order (--speed 1|4|max) into --space.
    Replay(crate::record_cmd::ReplayArgs),
    /// Make a certificate authority and a TLS bundle per machine (store, workers, clients)
    /// for the TLS + access-control configs in deploy/.
    Certs(crate::certs_cmd::CertsArgs),
    /// Benchmarks: a table each, or with --json one JSON line per result.
    Bench {
        #[command(subcommand)]
        command: crate::bench::BenchCommand,
    },
}

/// The `mwb` command as clap builds it: subcommands, flags, help.
pub fn command() -> clap::Command {
    Cli::command()
}
