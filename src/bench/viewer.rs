//! `mwb bench viewer`: what the live viewer costs with many worlds.
//!
//! A store (router, running node-query) and samplers in one process fill a store with
//! `--worlds` worlds of `--scene` (by default [`TUMBLE10`], the issue's "10-body scene") over
//! TCP loopback; the viewer connects as its own zenoh client, exactly as `mwb viewer --connect`
//! does, and loads every world's indexed paths. Then:
//!
//! * `frame_ms_p50/p95`: CPU time (the thread's clock) of one whole UI frame (egui pass over
//!   the real `ViewerApp::ui` plus tessellation) with every world's path of one object drawn,
//!   and the shown world's bodies; `frame_wall_ms_p50/p95` the same frames' wall-clock time,
//!   longer when other processes share the cores;
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

/// The default scene's name as the JSON line reports it.
pub const TUMBLE10_NAME: &str = "tumble10 (built in)";

/// The default scene: the issue measures the viewer on "a 10-body scene", and the shipped
/// scenes have 1 (chute), 5 (tumble), 8 (pachinko) or 193 (tower) bodies. This is tumble's
/// five boxes and five more thrown from a second ring, 45° round from the first.
pub const TUMBLE10: &str = r#"
name = "tumble10"
description = "Ten boxes of mixed sizes thrown onto the ground from two rings (mwb bench viewer)."

[settings]
end_time = 6.0

[[material]]
name = "ground"
friction = 0.8
restitution = 0.2

[[material]]
name = "wood"
friction = 0.6
restitution = 0.3
density = 600.0

[[static]]
name = "ground"
shape = "plane"
normal = [0, 1, 0]
material = "ground"

[[body]]
name = "crate"
shape = "box"
size = [0.5, 0.5, 0.5]
material = "wood"
position = [-1.5, 1.0, 0.0]
rotation_deg = [0, { uniform = [0, 90] }, 0]
linvel = [{ uniform = [1.5, 3.0] }, { uniform = [1.0, 3.0] }, { uniform = [-0.5, 0.5] }]
angvel = [{ uniform = [-4, 4] }, { uniform = [-4, 4] }, { uniform = [-4, 4] }]

[[body]]
name = "plank"
shape = "box"
size = [0.9, 0.1, 0.3]
material = "wood"
position = [1.5, 1.2, 0.3]
rotation_deg = [{ uniform = [-20, 20] }, { uniform = [0, 180] }, { uniform = [-20, 20] }]
linvel = [{ uniform = [-3.0, -1.5] }, { uniform = [1.0, 3.0] }, { uniform = [-0.5, 0.5] }]
angvel = [{ uniform = [-6, 6] }, { uniform = [-6, 6] }, { uniform = [-6, 6] }]

[[body]]
name = "brick"
shape = "box"
size = [0.3, 0.15, 0.15]
material = "wood"
position = [0.0, 1.0, -1.5]
linvel = [{ uniform = [-0.5, 0.5] }, { uniform = [1.0, 3.0] }, { uniform = [1.5, 3.0] }]
angvel = [{ uniform = [-8, 8] }, { uniform = [-8, 8] }, { uniform = [-8, 8] }]

[[body]]
name = "die"
shape = "box"
size = [0.2, 0.2, 0.2]
material = "wood"
position = [0.0, 1.4, 1.5]
rotation_deg = [{ uniform = [0, 90] }, { uniform = [0, 90] }, { uniform = [0, 90] }]
linvel = [{ uniform = [-0.5, 0.5] }, { uniform = [1.0, 3.0] }, { uniform = [-3.0, -1.5] }]
angvel = [{ uniform = [-10, 10] }, { uniform = [-10, 10] }, { uniform = [-10, 10] }]

[[body]]
name = "slab"
shape = "box"
size = [0.6, 0.2, 0.6]
material = "wood"
position = [0.0, 2.5, 0.0]
rotation_deg = [{ normal = [0, 10] }, { uniform = [0, 90] }, { normal = [0, 10] }]
linvel = [0, { uniform = [0.0, 1.0] }, 0]
angvel = [{ uniform = [-2, 2] }, { uniform = [-2, 2] }, { uniform = [-2, 2] }]

[[body]]
name = "crate2"
shape = "box"
size = [0.4, 0.4, 0.4]
material = "wood"
position = [-1.06, 1.1, -1.06]
rotation_deg = [0, { uniform = [0, 90] }, 0]
linvel = [{ uniform = [1.0, 2.1] }, { uniform = [1.0, 3.0] }, { uniform = [1.0, 2.1] }]
angvel = [{ uniform = [-4, 4] }, { uniform = [-4, 4] }, { uniform = [-4, 4] }]

[[body]]
name = "plank2"
shape = "box"
size = [0.8, 0.1, 0.25]
material = "wood"
position = [1.06, 1.3, -1.06]
rotation_deg = [{ uniform = [-20, 20] }, { uniform = [0, 180] }, { uniform = [-20, 20] }]
linvel = [{ uniform = [-2.1, -1.0] }, { uniform = [1.0, 3.0] }, { uniform = [1.0, 2.1] }]
angvel = [{ uniform = [-6, 6] }, { uniform = [-6, 6] }, { uniform = [-6, 6] }]

[[body]]
name = "brick2"
shape = "box"
size = [0.3, 0.15, 0.15]
material = "wood"
position = [1.06, 1.0, 1.06]
linvel = [{ uniform = [-2.1, -1.0] }, { uniform = [1.0, 3.0] }, { uniform = [-2.1, -1.0] }]
angvel = [{ uniform = [-8, 8] }, { uniform = [-8, 8] }, { uniform = [-8, 8] }]

[[body]]
name = "die2"
shape = "box"
size = [0.2, 0.2, 0.2]
material = "wood"
position = [-1.06, 1.4, 1.06]
rotation_deg = [{ uniform = [0, 90] }, { uniform = [0, 90] }, { uniform = [0, 90] }]
linvel = [{ uniform = [1.0, 2.1] }, { uniform = [1.0, 3.0] }, { uniform = [-2.1, -1.0] }]
angvel = [{ uniform = [-10, 10] }, { uniform = [-10, 10] }, { uniform = [-10, 10] }]

[[body]]
name = "slab2"
shape = "box"
size = [0.5, 0.15, 0.5]
material = "wood"
position = [0.0, 3.2, 0.0]
rotation_deg = [{ normal = [0, 10] }, { uniform = [0, 90] }, { normal = [0, 10] }]
linvel = [0, { uniform = [0.0, 1.0] }, 0]
angvel = [{ uniform = [-2, 2] }, { uniform = [-2, 2] }, { uniform = [-2, 2] }]
"#;

/// Arguments of `mwb bench viewer`.
#[derive(Debug, Clone, clap::Args)]
pub struct ViewerArgs {
    /// A scene file or shipped scene's name [default: the built-in 10-body tumble10].
    #[arg(long)]
    pub scene: Option<String>,
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
    /// The viewer's `--max-worlds`: the most worlds whose paths it holds (0: every world).
    #[arg(long, default_value_t = mwb_viewer::live::DEFAULT_MAX_WORLDS)]
    pub max_worlds: usize,
    /// Print the result as one JSON line.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct ViewerBench {
    pub scene: String,
    pub worlds: usize,
    pub bodies: usize,
    /// The viewer's `--max-worlds` (0: every world).
    pub max_worlds: usize,
    /// Worlds whose paths the viewer held when it had loaded (all of them, or its sample).
    pub held_worlds: usize,
    /// Vertices of the drawn paths (one object, every world held).
    pub path_vertices: usize,
    /// CPU time of a frame (the thread's clock).
    pub frame_ms_p50: f64,
    pub frame_ms_p95: f64,
    /// Wall-clock time of a frame.
    pub frame_wall_ms_p50: f64,
    pub frame_wall_ms_p95: f64,
    pub constraint_roundtrip_ms_p50: f64,
    pub constraint_roundtrip_ms_p95: f64,
    pub world_open_ms_p50: f64,
    pub world_open_ms_p95: f64,
    /// Seconds from the viewer's start until every world's paths (or its sample) were loaded.
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
    let (file, text) = match &args.scene {
        Some(scene) => client::load_scene(scene)?,
        None => (TUMBLE10_NAME.to_owned(), TUMBLE10.to_owned()),
    };
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
            max_worlds: args.max_worlds,
            ..LiveConfig::default()
        },
        &tokio::runtime::Handle::current(),
        Arc::new(|| {}),
    )?;
    let mut app = ViewerApp::live(ViewerState::live("bench"), link);
    let want = state.worlds_done as usize;
    let t = Instant::now();
    let loaded = app
        .pump_until(Duration::from_secs(600), |a| {
            a.state.holds_worlds(want as u64)
        })
        .await;
    let load_s = t.elapsed().as_secs_f64();
    if !loaded {
        bail!(
            "the viewer held {} worlds of {want} in {load_s:.0} s, and had not caught up",
            app.state.worlds().len()
        );
    }
    // One object drawn (the first), as an animator browsing one object would.
    app.state
        .update(Msg::ChooseObjects(vec![0]))
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let held_worlds = app.state.worlds().len();
    let path_vertices = app
        .state
        .worlds()
        .iter()
        .filter_map(|w| w.paths.first())
        .map(|p| p.tree.path().len())
        .sum();
    let frames = tokio::task::block_in_place(|| {
        mwb_viewer::screenshot::frame_times(&mut app, size, args.frames)
    });
    let mut frame_cpu: Vec<f64> = frames.iter().map(|f| f.cpu_ms).collect();
    let mut frame_wall: Vec<f64> = frames.iter().map(|f| f.wall_ms).collect();

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
        max_worlds: args.max_worlds,
        held_worlds,
        path_vertices,
        frame_ms_p50: percentile(&mut frame_cpu, 0.5),
        frame_ms_p95: percentile(&mut frame_cpu, 0.95),
        frame_wall_ms_p50: percentile(&mut frame_wall, 0.5),
        frame_wall_ms_p95: percentile(&mut frame_wall, 0.95),
        constraint_roundtrip_ms_p50: percentile(&mut roundtrips, 0.5),
        constraint_roundtrip_ms_p95: percentile(&mut roundtrips, 0.95),
        world_open_ms_p50: percentile(&mut opens, 0.5),
        world_open_ms_p95: percentile(&mut opens, 0.95),
        load_s,
        fill_s,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_scene_has_ten_bodies_and_samples() {
        let template = mwb_core::scene::SceneTemplate::parse(TUMBLE10, TUMBLE10_NAME)
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(template.body_names().count(), 10);
        let world = mwb_viewer::offline::sample_one(&template, 0).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(world.paths.len(), 10);
        // Every body is thrown in and lands: its path ends near the ground, in the middle.
        for p in &world.paths {
            let end = p.tree.path().points().last().copied().unwrap_or([9.0; 3]);
            assert!(
                end[1] < 1.0 && end[0].abs() < 4.0 && end[2].abs() < 4.0,
                "{end:?}"
            );
        }
    }
}
