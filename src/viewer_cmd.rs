//! `mwb viewer`: the workstation viewer (mwb-viewer). This increment is offline only: worlds are
//! sampled in this process with the sampler and codec libraries (`--scene`, `--worlds`) and
//! decoded for their true motion; `--screenshot` renders the real UI to a PNG without a display.

use std::path::PathBuf;

use anyhow::{Context, Result, anyhow, bail};
use mwb_core::browse::{Polarity, ScreenRect};
use mwb_viewer::screenshot::{parse_size, png_bytes, screenshot};
use mwb_viewer::{Msg, OrbitCamera, ViewerApp, ViewerState};

use crate::client;

/// Arguments of `mwb viewer`.
#[derive(Debug, Clone, clap::Args)]
pub struct ViewerArgs {
    /// Scene file or shipped scene name; its worlds are sampled in this process.
    #[arg(long)]
    pub scene: String,
    /// How many worlds to sample (world i has seed i).
    #[arg(long, default_value_t = 200)]
    pub worlds: u32,
    /// Sampling threads (default: every core).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Render the UI once to this PNG file instead of opening a window.
    #[arg(long)]
    pub screenshot: Option<PathBuf>,
    /// Screenshot size in pixels, WIDTHxHEIGHT.
    #[arg(long, default_value = "1280x720")]
    pub size: String,
    /// Start from this camera: JSON in the format `mwb query add --camera` reads (position,
    /// rotation, intrinsics, viewport). Without it the view frames every path.
    #[arg(long)]
    pub camera: Option<PathBuf>,
    /// Add a positive constraint before showing: a rectangle X0,Y0,X1,Y1 in pixels of the 3D
    /// view (repeatable).
    #[arg(long = "rect", value_name = "X0,Y0,X1,Y1")]
    pub rects: Vec<String>,
    /// Like --rect, for a negative constraint (worlds that never pass through).
    #[arg(long = "not-rect", value_name = "X0,Y0,X1,Y1")]
    pub not_rects: Vec<String>,
    /// Select this world at start.
    #[arg(long)]
    pub select: Option<u32>,
    /// Playback time at start, seconds.
    #[arg(long)]
    pub time: Option<f64>,
}

fn parse_rect(text: &str) -> Result<ScreenRect> {
    let v: Vec<f64> = text
        .split(',')
        .map(|s| s.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| anyhow!("--rect {text:?}: expected four numbers X0,Y0,X1,Y1"))?;
    let [x0, y0, x1, y1] = v[..] else {
        bail!("--rect {text:?}: expected four numbers X0,Y0,X1,Y1");
    };
    Ok(ScreenRect { x0, y0, x1, y1 })
}

/// Samples the worlds, then opens the window or writes the screenshot.
pub fn run(args: ViewerArgs) -> Result<()> {
    let size = parse_size(&args.size).map_err(|e| anyhow!("--size: {e}"))?;
    let rects: Vec<(ScreenRect, Polarity)> = args
        .rects
        .iter()
        .map(|r| parse_rect(r).map(|r| (r, Polarity::Positive)))
        .chain(
            args.not_rects
                .iter()
                .map(|r| parse_rect(r).map(|r| (r, Polarity::Negative))),
        )
        .collect::<Result<_>>()?;
    let (file, text) = client::load_scene(&args.scene)?;
    let template = mwb_core::scene::SceneTemplate::parse(&text, &file)?;
    let threads = args
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let started = std::time::Instant::now();
    let results = mwb_viewer::offline::sample_worlds(&template, args.worlds, threads);
    let first = template.instantiate(0);
    let names = first.bodies.iter().map(|b| b.name.clone()).collect();
    let mut state = ViewerState::new(template.name(), names, first.statics.clone());
    for r in results {
        match r.map_err(|e| e.to_string()).and_then(|w| {
            let i = w.index;
            state.add_world(w).map_err(|e| format!("world {i}: {e}"))
        }) {
            Ok(()) => {}
            Err(e) => {
                eprintln!("mwb viewer: {e}");
                state.add_problem(e);
            }
        }
    }
    eprintln!(
        "mwb viewer: {} of {} worlds of {} sampled and decoded in {:.1} s on {threads} threads",
        state.worlds().len(),
        args.worlds,
        template.name(),
        started.elapsed().as_secs_f64()
    );
    let placed = if let Some(path) = &args.camera {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading camera file {}", path.display()))?;
        let camera: mwb_core::browse::Camera = serde_json::from_str(&text)
            .with_context(|| format!("camera file {}", path.display()))?;
        let focus = state.bounds().map_or([0.0; 3], |(c, _)| c);
        let orbit = OrbitCamera::from_browse(&camera, focus)
            .with_context(|| format!("camera file {}", path.display()))?;
        state
            .update(Msg::SetCamera(orbit))
            .map_err(|e| anyhow!("{e}"))?;
        true
    } else {
        false
    };
    if let Some(w) = args.select {
        if (w as usize) >= state.worlds().len() {
            bail!("--select {w}: there are {} worlds", state.worlds().len());
        }
        state
            .update(Msg::SelectWorld(Some(w)))
            .map_err(|e| anyhow!("{e}"))?;
    }
    if let Some(t) = args.time {
        state.update(Msg::Seek(t)).map_err(|e| anyhow!("{e}"))?;
    }
    let mut app = ViewerApp::new(state).with_camera_placed(placed);
    if let Some(out) = &args.screenshot {
        // Lay the UI out (and frame the camera), then add the boxes in that view, then paint.
        let _ = screenshot(&mut app, size, 1.0, 2);
        for (r, p) in rects {
            app.add_box_px(r, p, 1.0);
            if let Some(e) = app.last_error() {
                bail!("--rect: {e}");
            }
        }
        let img = screenshot(&mut app, size, 1.0, 3);
        let bytes = png_bytes(&img).context("encoding the screenshot")?;
        std::fs::write(out, bytes).with_context(|| format!("writing {}", out.display()))?;
        println!(
            "{}: {}x{} screenshot, {} worlds, {} survive",
            out.display(),
            size[0],
            size[1],
            app.state.worlds().len(),
            app.state.survivor_count()
        );
        return Ok(());
    }
    if !rects.is_empty() {
        bail!("--rect and --not-rect are for --screenshot; in the window, drag a box");
    }
    mwb_viewer::ui::run_window(
        app,
        &format!("manyworlds viewer — {}", template.name()),
        size,
    )
    .map_err(|e| anyhow!("opening the viewer window: {e}"))
}
