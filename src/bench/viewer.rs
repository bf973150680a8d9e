//! `mwb bench viewer`: what the live viewer costs with many worlds.
//!
//! A store (router, running node-query) and samplers in one process fill a store with
//! `--worlds` worlds of `--scene` over TCP loopback; the viewer connects as its own zenoh
//! client, exactly as `mwb viewer --connect` does, and loads every world's indexed paths. Then:
//!
//! * `frame_ms_p50/p95`: CPU time of one whole UI frame (egui pass over the real `ViewerApp::ui`
//!   plus tessellation) with every world's path of one object drawn;
//! * `constraint_roundtrip_ms_p95`: a box added in the view until its survivor count is shown
//!   (request to node-query, evaluation in the store, status and survivors back, applied);
//! * `world_open_ms_p95`: a world picked until its motion is fetched, decoded and drawable.

use super::free_port;
use crate::bus::{BusArgs, Mode};
use crate::client;
use crate::output::{Summary, fields_table};
use anyhow::{Result, bail};
use mwb_core::browse::{Polarity, ScreenRect};
use mwb_core::keys::Keys;
use mwb_sampler::{SamplerConfig, run_sampler};
use mwb_store::{StoreConfig, run_store};
use mwb_viewer::live::{LiveConfig, LiveLink};
use mwb_viewer::{Msg, ViewerApp, ViewerState};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Arguments of `mwb bench viewer`.
#[derive(Debug, Clone, clap::Args)]
pub struct ViewerArgs {
    #[arg(long, default_value = "tumble")]
    pub scene: String,
    #[arg(long, default_value_t = 10_000)]
    pub worlds: u32,
    /// Sampler nodes (one worker each) filling the store.
    #[arg(long, default_value_t = 2)]
    pub samplers: usize,
    /// Frames timed.
    #[arg(long, default_value_t = 40)]
    pub frames: usize,
    /// Boxes added and worlds opened (each).
    #[arg(long, default_value_t = 20)]
    pub repeats: usize,
    /// Frame size, WIDTHxHEIGHT.
    #[arg(long, default_value = "1280x720")]
    pub size: String,
    /// Print the result as one JSON line.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct ViewerBench {
    pub scene: String,
    pub worlds: usize,
    pub bodies: usize,
    /// Vertices of the drawn paths (one object, every world).
    pub path_vertices: usize,
    pub frame_ms_p50: f64,
    pub frame_ms_p95: f64,
    pub constraint_roundtrip_ms_p50: f64,
    pub constraint_roundtrip_ms_p95: f64,
    pub world_open_ms_p50: f64,
    pub world_open_ms_p95: f64,
    /// Seconds from the viewer's start until every world's paths were loaded.
    pub load_s: f64,
    pub fill_s: f64,
}

impl Summary for ViewerBench {
    fn table(&self) -> String {
        fields_table(self)
    }
}

fn percentile(v: &mut [f64], p: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

/// Runs `mwb bench viewer`.
pub async fn run(args: ViewerArgs) -> Result<()> {
    let b = bench_viewer(&args).await?;
    crate::output::print(&b, args.json)
}

pub async fn bench_viewer(args: &ViewerArgs) -> Result<ViewerBench> {
    let size = mwb_viewer::screenshot::parse_size(&args.size)
        .map_err(|e| anyhow::anyhow!("--size: {e}"))?;
    let (file, text) = client::load_scene(&args.scene)?;
    let port = free_port()?;
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let space = format!("vbench{}", std::process::id());
    let store_bus = BusArgs {
        connect: vec![],
        listen: vec![endpoint.clone()],
        config: None,
        mode: Some(Mode::Router),
        space: space.clone(),
        multicast: false,
    };
    let client_bus = BusArgs {
        connect: vec![endpoint.clone()],
        listen: vec![],
        mode: Some(Mode::Client),
        ..store_bus.clone()
    };
    let keys = Keys::new(&space)?;
    let store_session = store_bus.open(Mode::Router).await?;
    let store = run_store(
        store_session.clone(),
        StoreConfig {
            space: space.clone(),
            memory_cap_bytes: 16 << 30,
            ..Default::default()
        },
    )
    .await?;
    let query = mwb_query::run_query(
        store_session.clone(),
        mwb_query::QueryConfig {
            space: space.clone(),
            ..Default::default()
        },
    )
    .await?;
    let sampler_session = client_bus.open(Mode::Client).await?;
    let mut samplers = Vec::new();
    for _ in 0..args.samplers.max(1) {
        samplers.push(
            run_sampler(
                sampler_session.clone(),
                SamplerConfig {
                    space: space.clone(),
                    workers: 1,
                    ..Default::default()
                },
            )
            .await?,
        );
    }
    let job = client::make_job(&file, &text, args.worlds, 0, None)?;
    let t = Instant::now();
    client::submit_job(&store_session, &keys, &job).await?;
    let state = client::wait_job(
        &store_session,
        &keys,
        &job.id,
        Some(Duration::from_secs(7200)),
        |_| {},
    )
    .await?;
    let fill_s = t.elapsed().as_secs_f64();
    for s in samplers {
        s.stop().await;
    }
    crate::bus::close(sampler_session).await;

    // The viewer, as `mwb viewer --connect` runs it.
    let viewer_session = client_bus.open(Mode::Client).await?;
    let link = LiveLink::start(
        viewer_session.clone(),
        LiveConfig {
            space: space.clone(),
            session: "bench".into(),
            endpoint,
            ..LiveConfig::default()
        },
        &tokio::runtime::Handle::current(),
        Arc::new(|| {}),
    )?;
    let mut app = ViewerApp::live(ViewerState::live("bench"), link);
    let want = state.worlds_done as usize;
    let t = Instant::now();
    let loaded = app
        .pump_until(Duration::from_secs(600), |a| a.state.worlds().len() >= want)
        .await;
    let load_s = t.elapsed().as_secs_f64();
    if !loaded {
        bail!(
            "the viewer loaded {} of {want} worlds in {load_s:.0} s",
            app.state.worlds().len()
        );
    }
    // One object drawn (the first), as an animator browsing one object would.
    for o in 1..app.state.body_names().len() as u32 {
        app.state
            .update(Msg::ToggleObject(o))
            .map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    let path_vertices = app
        .state
        .worlds()
        .iter()
        .filter_map(|w| w.paths.first())
        .map(|p| p.tree.path().len())
        .sum();
    let mut frames = tokio::task::block_in_place(|| {
        mwb_viewer::screenshot::frame_times_ms(&mut app, size, args.frames)
    });

    // Boxes around the middle of the view, a different size each time; each undone after.
    let vr = app.view_rect();
    let (w, h) = (f64::from(vr.width()), f64::from(vr.height()));
    let mut roundtrips = Vec::new();
    for i in 0..args.repeats {
        let half = 0.05 + 0.02 * (i % 10) as f64;
        let rect = ScreenRect {
            x0: w * (0.5 - half),
            y0: h * (0.55 - half),
            x1: w * (0.5 + half),
            y1: h * (0.55 + half),
        };
        let t = Instant::now();
        app.add_box_px(rect, Polarity::Positive, 1.0);
        let answered = app
            .pump_until(Duration::from_secs(30), |a| {
                a.state.pending() == 0 && a.unsent() == 0
            })
            .await;
        roundtrips.push(t.elapsed().as_secs_f64() * 1e3);
        if !answered {
            bail!("no answer to a box within 30 s");
        }
        app.state
            .update(Msg::Undo)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        app.pump_until(Duration::from_secs(30), |a| {
            a.state.pending() == 0 && a.unsent() == 0
        })
        .await;
    }

    // Worlds picked one after another (spread over the store), each until it is drawable.
    let indices: Vec<u32> = app.state.worlds().iter().map(|w| w.index).collect();
    let mut opens = Vec::new();
    for i in 0..args.repeats {
        let w = indices[(i * 7919) % indices.len()];
        let t = Instant::now();
        app.state
            .update(Msg::SelectWorld(Some(w)))
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let open = app
            .pump_until(Duration::from_secs(30), |a| {
                a.state.world(w).is_some_and(|d| d.motion.is_some())
            })
            .await;
        opens.push(t.elapsed().as_secs_f64() * 1e3);
        if !open {
            bail!("world {w} did not open within 30 s");
        }
    }
    let bodies = app.state.body_names().len();
    drop(app);
    crate::bus::close(viewer_session).await;
    query.stop();
    store.stop();
    crate::bus::close(store_session).await;
    Ok(ViewerBench {
        scene: file,
        worlds: want,
        bodies,
        path_vertices,
        frame_ms_p50: percentile(&mut frames, 0.5),
        frame_ms_p95: percentile(&mut frames, 0.95),
        constraint_roundtrip_ms_p50: percentile(&mut roundtrips, 0.5),
        constraint_roundtrip_ms_p95: percentile(&mut roundtrips, 0.95),
        world_open_ms_p50: percentile(&mut opens, 0.5),
        world_open_ms_p95: percentile(&mut opens, 0.95),
        load_s,
        fill_s,
    })
}
