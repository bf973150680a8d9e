//! `mwb bench sampler`: what the full sampling path costs compared with rapier stepping alone.
//!
//! * raw: instantiate + build + step the same scene on one thread, no perturbation, no
//!   recording, no bus — the baseline.
//! * pipeline: a store and a one-worker sampler in two zenoh sessions joined by TCP loopback;
//!   a job of N worlds goes through perturbation, encoding, the bus and the store's assembly.
//!
//! Ratio = pipeline steps/s ÷ raw steps/s (both one simulation thread). Core-seconds per world
//! is the whole process's CPU time (simulation, zenoh, store) per world of the pipeline run.

use super::free_port;
use crate::bus::{BusArgs, Mode};
use crate::client;
use crate::output::{Summary, fields_table};
use anyhow::Result;
use mwb_core::keys::Keys;
use mwb_core::rng::world_seed;
use mwb_core::scene::SceneTemplate;
use mwb_sampler::{RunOptions, SamplerConfig, run_sampler, run_world};
use mwb_store::{StoreConfig, run_store};
use std::ops::ControlFlow;
use std::time::{Duration, Instant};

/// Arguments of `mwb bench sampler`.
#[derive(Debug, Clone, clap::Args)]
pub struct SamplerArgs {
    #[arg(long, default_value = "tumble")]
    pub scene: String,
    #[arg(long, default_value_t = 50)]
    pub worlds: u32,
    /// Print the result as one JSON line.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub motion: client::MotionArgs,
}

/// Runs `mwb bench sampler`.
pub async fn run(args: SamplerArgs) -> Result<()> {
    let b = bench_sampler(&args.scene, args.worlds, args.motion).await?;
    crate::output::print(&b, args.json)
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct SamplerBench {
    pub scene: String,
    /// Segment payload: "spline" (the §4.3 codec) or "frames" (quantised frames).
    pub encoding: String,
    pub worlds: u32,
    pub bodies: usize,
    pub raw_steps_per_s: f64,
    pub pipeline_steps_per_s: f64,
    pub ratio: f64,
    pub worlds_per_s: f64,
    pub core_seconds_per_world: f64,
    pub steps_per_world: f64,
    pub bytes_per_world: f64,
}

impl Summary for SamplerBench {
    fn table(&self) -> String {
        fields_table(self)
    }
}

/// CPU time of the whole process (all threads), seconds (0 where it is not read: not unix).
#[cfg(not(unix))]
pub fn process_cpu_seconds() -> f64 {
    0.0
}

/// CPU time of the whole process (all threads), seconds.
#[cfg(unix)]
pub fn process_cpu_seconds() -> f64 {
    // SAFETY: getrusage fills the struct we pass; a zeroed rusage is a valid value.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: valid pointer to an rusage.
    if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut ru) } != 0 {
        return 0.0;
    }
    let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    tv(ru.ru_utime) + tv(ru.ru_stime)
}

pub async fn bench_sampler(
    scene_arg: &str,
    worlds: u32,
    motion: client::MotionArgs,
) -> Result<SamplerBench> {
    let (file, text) = client::load_scene(scene_arg)?;
    let template = SceneTemplate::parse(&text, &file)?;

    // Baseline: rapier alone, same scene, same number of worlds, one thread.
    let raw = {
        let t = Instant::now();
        let mut steps = 0u64;
        for i in 0..worlds {
            let seed = world_seed("bench-raw", "raw", u64::from(i));
            let opts = RunOptions {
                perturb: false,
                record: false,
                ..RunOptions::default()
            };
            let s = run_world(&template, seed, opts, &mut |_| ControlFlow::Continue(()))?;
            steps += s.steps;
        }
        steps as f64 / t.elapsed().as_secs_f64().max(1e-9)
    };

    // Pipeline: store session (router) ⇄ TCP loopback ⇄ sampler session (client).
    let port = free_port()?;
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let space = format!("bench{}", std::process::id());
    let store_bus = BusArgs {
        connect: vec![],
        listen: vec![endpoint.clone()],
        config: None,
        mode: Some(Mode::Router),
        space: space.clone(),
        multicast: false,
    };
    let sampler_bus = BusArgs {
        connect: vec![endpoint],
        listen: vec![],
        mode: Some(Mode::Client),
        ..store_bus.clone()
    };
    let keys = Keys::new(&space)?;
    let store_session = store_bus.open(Mode::Router).await?;
    let sampler_session = sampler_bus.open(Mode::Client).await?;
    let store = run_store(
        store_session.clone(),
        StoreConfig {
            space: space.clone(),
            ..Default::default()
        },
    )
    .await?;
    let mut job = client::make_job(&file, &text, worlds, 0, None)?;
    motion.apply(&mut job);
    let cpu0 = process_cpu_seconds();
    let t = Instant::now();
    let sampler = run_sampler(
        sampler_session.clone(),
        SamplerConfig {
            space: space.clone(),
            workers: 1,
            ..Default::default()
        },
    )
    .await?;
    let state = client::submit_job(&store_session, &keys, &job).await?;
    let state = if state.closed {
        state
    } else {
        client::wait_job(
            &store_session,
            &keys,
            &job.id,
            Some(Duration::from_secs(3600)),
            |_| {},
        )
        .await?
    };
    let wall = t.elapsed().as_secs_f64();
    let cpu = process_cpu_seconds() - cpu0;
    // Steps of the stored worlds (a world abandoned when the job closed is not counted).
    let mut steps = 0u64;
    for i in 0..state.worlds_done {
        if let Some(w) = store.world(i) {
            steps += w.done()?.sim_steps;
        }
    }
    sampler.stop().await;
    store.stop();
    crate::bus::close(sampler_session).await;
    crate::bus::close(store_session).await;
    let n = f64::from(state.worlds_done.max(1));
    let pipeline = steps as f64 / wall.max(1e-9);
    Ok(SamplerBench {
        scene: file,
        encoding: format!("{:?}", motion.encoding).to_lowercase(),
        worlds: state.worlds_done,
        bodies: template.body_count(),
        raw_steps_per_s: raw,
        pipeline_steps_per_s: pipeline,
        ratio: pipeline / raw.max(1e-9),
        worlds_per_s: n / wall.max(1e-9),
        core_seconds_per_world: cpu / n,
        steps_per_world: steps as f64 / n,
        bytes_per_world: state.bytes_stored as f64 / n,
    })
}
