//! `mwb bench …`: the benchmarks, one module each. Each prints a table, or with `--json` one
//! JSON line per result; docs/performance.md quotes the JSON fields.

use anyhow::Result;
use clap::Subcommand;

pub mod chaos;
pub mod codec;
pub mod fidelity;
pub mod ingest;
pub mod query;
pub mod record;
pub mod refine;
pub mod reverse;
pub mod sampler;
pub mod scene;
pub mod stepper;
pub mod viewer;

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Our LCP stepper (forward) and rapier on the same simple scenes vs analytic answers:
    /// rest height, bounce apex, slide distance, rolling speed.
    Stepper(stepper::StepperArgs),
    /// Our LCP stepper forward vs backward (ch. 5): step cost, round trip, energy growth.
    Reverse(reverse::ReverseArgs),
    /// Raw rapier stepping vs the full sampling pipeline into a store over the bus.
    Sampler(sampler::SamplerArgs),
    /// Browsing over one store shard: add/remove a constraint, OBB tree vs brute force, rank.
    Query(query::QueryArgs),
    /// One store process on the bus filled with worlds as fast as it takes them in: worlds/s
    /// from first put to every world stored, indexed and counted; the store's RSS.
    Ingest(ingest::IngestArgs),
    /// The motion codec on sampled worlds: one line per (scene, preset).
    Codec(codec::CodecArgs),
    /// Recording, replay and the store's journal: writer MB/s, recorder overhead, replay
    /// worlds/s, journal restart time and bytes per world on disk.
    Record(record::RecordArgs),
    /// The live viewer over a store of many worlds: UI frame CPU time, box → survivor count
    /// round trip, world pick → playback.
    Viewer(viewer::ViewerArgs),
    /// Refinement (§4.5) against fresh worlds: CPU per world, active fraction, stored bytes,
    /// parent regeneration.
    Refine(refine::RefineArgs),
    /// The simulation presets against a reference run, per scene: CPU per world and how far
    /// each moves where bodies rest, when, and how often they hit (issue 19).
    Fidelity(fidelity::FidelityArgs),
    /// Validating big scene files: parse and instantiate time by body count.
    Scene(scene::SceneArgs),
    /// Faults across hosts (issue 21): two store shards and four samplers in network
    /// namespaces, samplers killed, links cut, a shard restarted; lost, duplicate and damaged
    /// worlds against a clean run; a store's real RSS under a flood against its cap. Root only.
    Chaos(chaos::ChaosArgs),
}

/// Runs `mwb bench …`.
pub async fn run(command: BenchCommand) -> Result<()> {
    match command {
        BenchCommand::Stepper(args) => stepper::run(args).await,
        BenchCommand::Reverse(args) => reverse::run(args).await,
        BenchCommand::Sampler(args) => sampler::run(args).await,
        BenchCommand::Query(args) => query::run(args).await,
        BenchCommand::Ingest(args) => ingest::run(args).await,
        BenchCommand::Codec(args) => codec::run(args),
        BenchCommand::Record(args) => record::run(args).await,
        BenchCommand::Refine(args) => refine::run(args).await,
        BenchCommand::Viewer(args) => viewer::run(args).await,
        BenchCommand::Scene(args) => scene::run(args),
        BenchCommand::Fidelity(args) => fidelity::run(args),
        BenchCommand::Chaos(args) => chaos::run(args).await,
    }
}

/// Free TCP port on 127.0.0.1 (bind :0, read, drop).
pub fn free_port() -> Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}
