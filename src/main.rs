//! `mwb`: the manyworlds command line. See README.md and ARCHITECTURE.md.

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use mwb::bus::{BusArgs, Mode};
use mwb::client;
use mwb_core::keys::Keys;
use std::time::Duration;

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
    Demo {
        #[command(flatten)]
        bus: BusArgs,
        /// Scene file, or a shipped scene name (tumble, pachinko, tower, chute).
        #[arg(long, default_value = "tumble")]
        scene: String,
        #[arg(long, default_value_t = 200)]
        worlds: u32,
        #[arg(long, default_value_t = 2)]
        samplers: usize,
        /// Store memory cap, MiB (stored motion and the browsing index).
        #[arg(long, default_value_t = 2048)]
        memory_cap_mib: u64,
        /// Print the summary as one JSON line.
        #[arg(long)]
        json: bool,
        /// Keep serving after the summary (store + node-query) so `mwb query` can browse.
        #[arg(long)]
        stay: bool,
        #[command(flatten)]
        motion: client::MotionArgs,
    },
    /// Run a store node (default: a zenoh router other nodes --connect to).
    Store {
        #[command(flatten)]
        bus: BusArgs,
        /// Refuse new worlds past this many MiB in memory.
        #[arg(long, default_value_t = 4096)]
        memory_cap_mib: u64,
        /// This store's shard when several split the worlds: INDEX/COUNT, e.g. 1/3. Start every
        /// shard before submitting jobs; shard 0 answers job states.
        #[arg(long, default_value = "0/1")]
        shard: String,
        /// Do not run the browsing coordinator (node-query) in this process. By default shard 0
        /// runs it; with `mwb query serve` elsewhere, pass this.
        #[arg(long)]
        no_query: bool,
    },
    /// Browse: constraints, results, rankings (talks to node-query); `serve` runs node-query.
    Query {
        #[command(subcommand)]
        command: mwb::query::QueryCommand,
    },
    /// Run a sampler node; it joins open jobs at any time.
    Sampler {
        #[command(flatten)]
        bus: BusArgs,
        /// Worker threads [default: all cores].
        #[arg(long)]
        workers: Option<usize>,
    },
    /// Backward worlds from a final state (ch. 5): a reverse node, or node + job with --scene.
    Reverse(mwb::reverse_cmd::ReverseArgs),
    /// Submit, list and cancel jobs.
    Job {
        #[command(subcommand)]
        command: JobCommand,
    },
    /// Live nodes, job progress and throughput.
    Status {
        #[command(flatten)]
        bus: BusArgs,
        #[arg(long)]
        json: bool,
    },
    /// Check a scene file: parse, validate, instantiate one world.
    Scene {
        /// Scene file or shipped scene name.
        scene: String,
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Benchmarks (one JSON line each).
    Bench {
        #[command(subcommand)]
        command: BenchCommand,
    },
}

#[derive(Subcommand)]
enum JobCommand {
    /// Submit a sampling job.
    Submit {
        #[command(flatten)]
        bus: BusArgs,
        /// Scene file or shipped scene name.
        scene: String,
        #[arg(long, default_value_t = 100)]
        worlds: u32,
        #[arg(long, default_value_t = 0)]
        priority: i32,
        /// Job id [default: <scene name>-<time>].
        #[arg(long)]
        id: Option<String>,
        /// Follow the job until it closes.
        #[arg(long)]
        wait: bool,
        /// Give up waiting after this many seconds.
        #[arg(long)]
        timeout: Option<u64>,
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        motion: client::MotionArgs,
    },
    /// List jobs known to the stores.
    List {
        #[command(flatten)]
        bus: BusArgs,
        #[arg(long)]
        json: bool,
    },
    /// Cancel a job.
    Cancel {
        #[command(flatten)]
        bus: BusArgs,
        id: String,
    },
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Our LCP stepper (forward) and rapier on the same simple scenes vs analytic answers:
    /// rest height, bounce apex, slide distance, rolling speed.
    Stepper {
        /// Accepted for symmetry with the other benches (the output is always one JSON line).
        #[arg(long)]
        json: bool,
    },
    /// Raw rapier stepping vs the full sampling pipeline into a store over the bus.
    /// Our LCP stepper forward vs backward (ch. 5): step cost, round trip, energy growth.
    Reverse {
        /// Worlds sampled backward for the round-trip and energy numbers.
        #[arg(long, default_value_t = 16)]
        worlds: usize,
        /// Skip the big ball-array run.
        #[arg(long)]
        no_balls: bool,
        /// (Output is always one JSON line.)
        #[arg(long)]
        json: bool,
    },
    Sampler {
        #[arg(long, default_value = "tumble")]
        scene: String,
        #[arg(long, default_value_t = 50)]
        worlds: u32,
        /// (Output is always one JSON line; the flag is accepted for scripts.)
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        motion: client::MotionArgs,
    },
    /// Browsing over one store shard: add/remove a constraint, OBB tree vs brute force, rank.
    Query {
        /// Scene whose sampled paths the synthetic worlds are made of.
        #[arg(long, default_value = "tumble")]
        scene: String,
        #[arg(long, default_value_t = 10_000)]
        worlds: u32,
        /// Objects per world.
        #[arg(long, default_value_t = 10)]
        objects: u32,
        /// Random constraints to time.
        #[arg(long, default_value_t = 60)]
        constraints: usize,
        /// The store's path tolerance (polyline vs decoded path), mm.
        #[arg(long, default_value_t = 10.0)]
        path_tolerance_mm: f64,
        /// Shift each synthetic object path sideways by up to this many metres.
        #[arg(long, default_value_t = 1.0)]
        spread_m: f64,
        /// (Output is always one JSON line.)
        #[arg(long)]
        json: bool,
    },
    /// The motion codec on sampled worlds: one JSON line per (scene, preset).
    Codec {
        /// Scene files or shipped scene names [default: every shipped scene].
        #[arg(long = "scene")]
        scenes: Vec<String>,
        /// Worlds sampled per scene.
        #[arg(long, default_value_t = 8)]
        worlds: u32,
        /// Also sweep the bounds and write a rate–distortion plot (PNG) here.
        #[arg(long)]
        plot: Option<std::path::PathBuf>,
        /// Also write each scene's sampled motion to `<dir>/<scene>.tracks`, the input of the
        /// codec's own scenes test (`MWB_SCENE_TRACKS=<dir>`, codec/tests/scenes.rs).
        #[arg(long, value_name = "DIR")]
        tracks_out: Option<std::path::PathBuf>,
        /// (Output is always JSON lines; the flag is accepted for scripts.)
        #[arg(long)]
        json: bool,
    },
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    // Long-running nodes log what they do; one-shot commands (demo, bench, job, …) print their
    // result and only warnings. RUST_LOG overrides both.
    let default_filter = match cli.command {
        Command::Store { .. }
        | Command::Sampler { .. }
        | Command::Query {
            command: mwb::query::QueryCommand::Serve { .. },
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
    rt.block_on(run(cli))
}

fn bench_codec(
    scenes: Vec<String>,
    worlds: u32,
    plot: Option<&std::path::Path>,
    tracks_out: Option<&std::path::Path>,
) -> Result<()> {
    use mwb::bench::codec::{PRESETS, SceneMotion, measure, plot_rate_distortion, rate_distortion};
    let scenes = if scenes.is_empty() {
        mwb_core::scene::builtin::NAMES
            .iter()
            .map(|s| (*s).to_owned())
            .collect()
    } else {
        scenes
    };
    let mut curves = Vec::new();
    for scene in &scenes {
        let motion = SceneMotion::sample(scene, worlds)?;
        if let Some(dir) = tracks_out {
            motion.write_tracks(dir)?;
        }
        for quality in PRESETS {
            print_json(&measure(&motion, quality)?)?;
        }
        if plot.is_some() {
            curves.push((motion.scene.clone(), rate_distortion(&motion)?));
        }
    }
    if let Some(path) = plot {
        let labelled = plot_rate_distortion(path, &curves)?;
        eprintln!(
            "wrote {}{}",
            path.display(),
            if labelled {
                ""
            } else {
                " (no font found: drawn without labels)"
            }
        );
    }
    Ok(())
}

fn print_json<T: serde::Serialize>(v: &T) -> Result<()> {
    println!("{}", serde_json::to_string(v)?);
    Ok(())
}

async fn until_ctrl_c() {
    let _ = tokio::signal::ctrl_c().await;
}

async fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Demo {
            bus,
            scene,
            worlds,
            samplers,
            memory_cap_mib,
            motion,
            json,
            stay,
        } => {
            let opts = mwb::demo::DemoOptions {
                stay,
                scene,
                worlds,
                samplers,
                memory_cap_bytes: memory_cap_mib << 20,
                motion,
                show_progress: !json && std::io::IsTerminal::is_terminal(&std::io::stderr()),
            };
            if !json {
                eprintln!(
                    "mwb demo: {} worlds of {} with {} samplers on an embedded bus …",
                    opts.worlds, opts.scene, opts.samplers
                );
            }
            mwb::demo::run_demo_with(&bus, &opts, |s| {
            if json {
                print_json(s)?;
            } else {
                println!("scene            {}", s.scene);
                println!(
                    "worlds           {} ({} CRC-verified, {} bodies each)",
                    s.worlds, s.crc_valid_worlds, s.bodies
                );
                println!(
                    "time             {:.2} s with {} samplers",
                    s.seconds, s.samplers
                );
                println!("worlds/s         {:.1}", s.worlds_per_s);
                println!("impacts/world    {:.1}", s.impacts_per_world);
                println!("perturbs/world   {:.1}", s.perturbations_per_world);
                println!("frames/world     {:.0}", s.frames_per_world);
                println!(
                    "bytes/world      {:.0} (motion codec; 7 × f32 would be {:.0}, {:.0}× more)",
                    s.bytes_per_world,
                    s.raw_f32_bytes_per_world,
                    s.raw_f32_bytes_per_world / s.bytes_per_world.max(1.0)
                );
                println!("came to rest     {:.0} %", s.rested_fraction * 100.0);
                println!("browsable        {} worlds indexed", s.browsable_worlds);
                if let (Some(w), Some(t)) = (s.soonest_rest_world, s.soonest_rest_s) {
                    println!("rests soonest    world {w} ({t:.2} s; `mwb query show {w}`)");
                }
            }
            Ok(())
            })
            .await?;
        }
        Command::Store {
            bus,
            memory_cap_mib,
            shard,
            no_query,
        } => {
            let shard = mwb_store::ShardSpec::parse(&shard).map_err(|e| anyhow::anyhow!(e))?;
            let session = bus.open(Mode::Router).await?;
            let store = mwb_store::run_store(
                session.clone(),
                mwb_store::StoreConfig {
                    space: bus.space.clone(),
                    memory_cap_bytes: memory_cap_mib << 20,
                    shard,
                    ..Default::default()
                },
            )
            .await?;
            let query = if shard.is_authority() && !no_query {
                Some(
                    mwb_query::run_query(
                        session.clone(),
                        mwb_query::QueryConfig {
                            space: bus.space.clone(),
                            node_id: Some(format!("{}-query", store.node_id())),
                            ..Default::default()
                        },
                    )
                    .await?,
                )
            } else {
                None
            };
            tracing::info!(
                node = store.node_id(),
                shard = %format!("{}/{}", shard.index, shard.count),
                query = query.is_some(),
                "store running; Ctrl-C stops it"
            );
            until_ctrl_c().await;
            if let Some(q) = query {
                q.stop();
            }
            store.stop();
            mwb::bus::close(session).await;
        }
        Command::Query { command } => mwb::query::run(command).await?,
        Command::Sampler { bus, workers } => {
            let session = bus.open(bus.client_default()).await?;
            let mut cfg = mwb_sampler::SamplerConfig {
                space: bus.space.clone(),
                ..Default::default()
            };
            if let Some(w) = workers {
                cfg.workers = w.max(1);
            }
            let sampler = mwb_sampler::run_sampler(session.clone(), cfg).await?;
            until_ctrl_c().await;
            sampler.stop().await;
            mwb::bus::close(session).await;
        }
        Command::Reverse(args) => mwb::reverse_cmd::run(args).await?,
        Command::Job { command } => job(command).await?,
        Command::Status { bus, json } => {
            let keys = Keys::new(&bus.space)?;
            let session = bus.open(bus.client_default()).await?;
            let st = client::status(&session, &keys, Duration::from_millis(1500)).await?;
            mwb::bus::close(session).await;
            if json {
                print_json(&st)?;
            } else {
                println!(
                    "{:<8} {:<40} {:>8} {:>9} {:>12}",
                    "ROLE", "NODE", "WORLDS", "WORLDS/S", "MEMORY MiB"
                );
                for n in &st.nodes {
                    println!(
                        "{:<8} {:<40} {:>8} {:>9.1} {:>12.1}",
                        n.role,
                        n.node,
                        n.worlds,
                        n.worlds_per_s,
                        n.memory_bytes as f64 / f64::from(1u32 << 20)
                    );
                }
                println!();
                println!(
                    "{:<40} {:>12} {:>8} {:>9}",
                    "JOB", "DONE", "STATE", "WORLDS/S"
                );
                for j in &st.jobs {
                    let state = if j.cancelled {
                        "cancelled"
                    } else if j.closed {
                        "closed"
                    } else {
                        "open"
                    };
                    println!(
                        "{:<40} {:>5}/{:<6} {:>8} {:>9.1}",
                        j.job, j.done, j.target, state, j.worlds_per_s
                    );
                }
            }
        }
        Command::Scene { scene, seed } => {
            let (file, text) = client::load_scene(&scene)?;
            let t = mwb_core::scene::SceneTemplate::parse(&text, &file)?;
            let s = t.instantiate(seed);
            println!(
                "{file}: ok — scene {:?}, {} dynamic bodies, {} statics, {} joints, {} materials, distributions: {}",
                t.name(),
                s.bodies.len(),
                s.statics.len(),
                s.joints.len(),
                s.materials.len(),
                if t.has_distributions() { "yes" } else { "no" }
            );
        }
        Command::Bench { command } => match command {
            BenchCommand::Stepper { json: _ } => {
                let b = tokio::task::spawn_blocking(mwb::bench::stepper::run).await??;
                print_json(&b)?;
            }
            BenchCommand::Reverse {
                worlds,
                no_balls,
                json: _,
            } => {
                let mut o = mwb_reverse::BenchOptions {
                    worlds,
                    ..Default::default()
                };
                if no_balls {
                    o.balls_scene = None;
                }
                let b = tokio::task::spawn_blocking(move || mwb_reverse::bench(&o)).await??;
                print_json(&serde_json::json!({
                    "bodies": b.bodies,
                    "forward_step_us": b.forward_step_us,
                    "backward_step_us": b.backward_step_us,
                    "ratio": b.ratio,
                    "roundtrip_max_rel_err": b.roundtrip_max_rel_err,
                    "roundtrip_p50_rel_err": b.roundtrip_p50_rel_err,
                    "roundtrip_departed_fraction": b.roundtrip_departed_fraction,
                    "energy_growth_p50": b.energy_growth_p50,
                    "angular_speed_peak_p50": b.angular_speed_peak_p50,
                    "balls": b.balls,
                    "balls_steps": b.balls_steps,
                    "balls_seconds": b.balls_seconds,
                    "balls_learn_seconds": b.balls_learn_seconds,
                    "balls_energy_growth": b.balls_energy_growth,
                }))?;
            }
            BenchCommand::Query {
                scene,
                worlds,
                objects,
                constraints,
                path_tolerance_mm,
                spread_m,
                json: _,
            } => {
                let opts = mwb::bench::query::QueryBenchOptions {
                    scene,
                    worlds,
                    objects,
                    constraints,
                    path_tolerance_m: path_tolerance_mm * 1e-3,
                    spread_m,
                };
                let b = tokio::task::spawn_blocking(move || mwb::bench::query::bench_query(&opts))
                    .await??;
                print_json(&b)?;
            }
            BenchCommand::Sampler {
                scene,
                worlds,
                json: _,
                motion,
            } => {
                let b = mwb::bench::sampler::bench_sampler(&scene, worlds, motion).await?;
                print_json(&b)?;
            }
            BenchCommand::Codec {
                scenes,
                worlds,
                plot,
                tracks_out,
                json: _,
            } => bench_codec(scenes, worlds, plot.as_deref(), tracks_out.as_deref())?,
        },
    }
    Ok(())
}

async fn job(command: JobCommand) -> Result<()> {
    match command {
        JobCommand::Submit {
            bus,
            scene,
            worlds,
            priority,
            id,
            wait,
            timeout,
            json,
            motion,
        } => {
            let keys = Keys::new(&bus.space)?;
            let (file, text) = client::load_scene(&scene)?;
            let mut job = client::make_job(&file, &text, worlds, priority, id)?;
            motion.apply(&mut job);
            let session = bus.open(bus.client_default()).await?;
            let mut state = client::submit_job(&session, &keys, &job).await?;
            if !json {
                eprintln!("submitted job {} ({} worlds of {})", job.id, worlds, file);
            }
            if wait {
                let bar =
                    (!json && std::io::IsTerminal::is_terminal(&std::io::stderr())).then(|| {
                        let b = indicatif::ProgressBar::new(u64::from(worlds));
                        if let Ok(style) = indicatif::ProgressStyle::with_template(
                            "{spinner} {bar:40} {pos}/{len} worlds  {per_sec}  eta {eta}",
                        ) {
                            b.set_style(style);
                        }
                        b
                    });
                state = client::wait_job(
                    &session,
                    &keys,
                    &job.id,
                    timeout.map(Duration::from_secs),
                    |st| {
                        if let Some(b) = &bar {
                            b.set_position(u64::from(st.worlds_done));
                        }
                    },
                )
                .await?;
                if let Some(b) = bar {
                    b.finish_and_clear();
                }
            }
            mwb::bus::close(session).await;
            if json {
                print_json(&serde_json::json!({
                    "job": job.id,
                    "done": state.worlds_done,
                    "target": state.target_worlds,
                    "closed": state.closed,
                    "rejected": state.worlds_rejected,
                    "worlds_per_s": client::job_rate(&state),
                }))?;
            } else if wait {
                println!(
                    "job {}: {}/{} worlds, {:.1} worlds/s, {} rejected",
                    job.id,
                    state.worlds_done,
                    state.target_worlds,
                    client::job_rate(&state),
                    state.worlds_rejected
                );
            } else {
                println!("{}", job.id);
            }
        }
        JobCommand::List { bus, json } => {
            let keys = Keys::new(&bus.space)?;
            let session = bus.open(bus.client_default()).await?;
            let jobs = client::list_jobs(&session, &keys).await?;
            mwb::bus::close(session).await;
            if json {
                let v: Vec<_> = jobs
                    .iter()
                    .map(|s| serde_json::json!({"job": s.job_id, "done": s.worlds_done, "target": s.target_worlds, "closed": s.closed, "cancelled": s.cancelled}))
                    .collect();
                print_json(&v)?;
            } else {
                for s in jobs {
                    println!(
                        "{:<40} {:>6}/{:<6} {}",
                        s.job_id,
                        s.worlds_done,
                        s.target_worlds,
                        if s.cancelled {
                            "cancelled"
                        } else if s.closed {
                            "closed"
                        } else {
                            "open"
                        }
                    );
                }
            }
        }
        JobCommand::Cancel { bus, id } => {
            let keys = Keys::new(&bus.space)?;
            let session = bus.open(bus.client_default()).await?;
            let st = client::cancel_job(&session, &keys, &id).await;
            mwb::bus::close(session).await;
            let st = st?;
            if !st.cancelled {
                bail!("job {id} closed before the cancel arrived");
            }
            println!(
                "cancelled {id} at {}/{} worlds",
                st.worlds_done, st.target_worlds
            );
        }
    }
    Ok(())
}
