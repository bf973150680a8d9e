//! `mwb viewer`: the workstation viewer (mwb-viewer). Live by default — it connects to a running
//! cluster (`--connect`, `$MWB_CONNECT`, else tcp/127.0.0.1:7447), draws worlds as the stores
//! index them and browses in a node-query session — or offline with `--scene`, sampling worlds
//! in this process. `--screenshot` renders the real UI to a PNG without a display. The window
//! keeps its saved views with the session (`--views-file`).

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, Result, anyhow, bail};
use mwb_core::browse::{Polarity, ScreenRect};
use mwb_viewer::live::{LiveConfig, LiveLink};
use mwb_viewer::screenshot::{parse_size, png_bytes, screenshot};
use mwb_viewer::ui::RepaintSlot;
use mwb_viewer::views::{VIEWS_FILE_ENV, ViewsFile};
use mwb_viewer::{Msg, OrbitCamera, ViewerApp, ViewerState};

use crate::bus::BusArgs;
use crate::client;

/// Arguments of `mwb viewer`.
#[derive(Debug, Clone, clap::Args)]
pub struct ViewerArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// Offline: sample this scene (file or shipped name) in this process instead of connecting.
    #[arg(long)]
    pub scene: Option<String>,
    /// Offline: how many worlds to sample (world i has seed i).
    #[arg(long, default_value_t = 200, requires = "scene")]
    pub worlds: u32,
    /// Offline: sampling threads (default: every core).
    #[arg(long, requires = "scene")]
    pub threads: Option<usize>,
    /// Live: the browsing session the viewer's constraints live in (`mwb query --session`
    /// shows the same one).
    #[arg(long, default_value = "viewer")]
    pub session: String,
    /// Live: the most worlds whose paths the viewer holds and draws (0: every world). When the
    /// stores hold more, it holds a sample: half of it uniform over every world, half over the
    /// survivors, so that a narrow result is drawn whole. 10 000 worlds of one object draw in
    /// about 10 ms a frame.
    #[arg(long, default_value_t = mwb_viewer::live::DEFAULT_MAX_WORLDS)]
    pub max_worlds: usize,
    /// Render the UI once to this PNG file instead of opening a window.
    #[arg(long)]
    pub screenshot: Option<PathBuf>,
    /// Screenshot (or window) size in pixels, WIDTHxHEIGHT.
    #[arg(long, default_value = "1280x720")]
    pub size: String,
    /// Live --screenshot: wait for this many worlds [default: what the stores hold when the
    /// viewer connects]; at most --wait-s seconds.
    #[arg(long, requires = "screenshot")]
    pub wait_worlds: Option<u64>,
    /// Live --screenshot: the longest wait for worlds and answers, seconds.
    #[arg(long, default_value_t = 60.0, requires = "screenshot")]
    pub wait_s: f64,
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
    /// Rank the survivors at start (the sorter's choices: spin, rest, impacts, turn,
    /// constraints); a --screenshot without --select shows the top-ranked world.
    #[arg(long, value_enum)]
    pub rank: Option<RankArg>,
    /// Select this world at start.
    #[arg(long)]
    pub select: Option<u32>,
    /// Playback time at start, seconds.
    #[arg(long)]
    pub time: Option<f64>,
    /// Where the window keeps its saved views [default: manyworlds/views/<session>.json in
    /// $XDG_CONFIG_HOME, else ~/.config, on Windows %APPDATA%; offline, the session is
    /// "offline-<scene>"]. Read at start, rewritten whenever a view is saved or deleted.
    #[arg(long, env = VIEWS_FILE_ENV)]
    pub views_file: Option<PathBuf>,
}

/// The sorter's choices on the command line.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum RankArg {
    Spin,
    Rest,
    Impacts,
    Turn,
    Constraints,
}

impl From<RankArg> for mwb_viewer::ui::SortBy {
    fn from(r: RankArg) -> Self {
        use mwb_viewer::ui::SortBy;
        match r {
            RankArg::Spin => SortBy::Spin,
            RankArg::Rest => SortBy::TimeToRest,
            RankArg::Impacts => SortBy::Impacts,
            RankArg::Turn => SortBy::OrientationError,
            RankArg::Constraints => SortBy::ConstraintsSatisfied,
        }
    }
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

/// Opens the window, or writes the screenshot.
pub async fn run(args: ViewerArgs) -> Result<()> {
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
    if args.screenshot.is_none() && !rects.is_empty() {
        bail!("--rect and --not-rect are for --screenshot; in the window, drag a box");
    }
    let (app, title, session) = match &args.scene {
        Some(scene) => {
            let (app, title) = tokio::task::block_in_place(|| offline(&args, scene))?;
            (app, title, None)
        }
        None => {
            let (app, title, session) = live(&args).await?;
            (app, title, Some(session))
        }
    };
    let (mut app, repaint) = app;
    let placed = start_camera(&mut app, args.camera.as_deref())?;
    app = app.with_camera_placed(placed);
    let result = match &args.screenshot {
        Some(out) => shoot(app, &args, rects, size, out).await,
        None => {
            start_choices(&mut app, &args)?;
            match views_file(&args, &app) {
                Some(file) => app = app.with_views_file(file),
                None => eprintln!(
                    "mwb viewer: no configuration directory ($XDG_CONFIG_HOME, $HOME): saved \
                     views last only while the viewer runs (--views-file keeps them)"
                ),
            }
            tokio::task::block_in_place(|| {
                mwb_viewer::ui::run_window(app, &title, size, repaint)
                    .map_err(|e| anyhow!("opening the viewer window: {e}"))
            })
        }
    };
    if let Some(s) = session {
        crate::bus::close(s).await;
    }
    result
}

type Started = (ViewerApp, RepaintSlot);

/// The file the window keeps its saved views in: `--views-file`, else the session's file in
/// the user's configuration directory. Offline there is no browsing session; the views are
/// kept per scene (session "offline-<scene>").
fn views_file(args: &ViewerArgs, app: &ViewerApp) -> Option<ViewsFile> {
    let session = match &args.scene {
        Some(_) => format!("offline-{}", app.state.scene_name()),
        None => args.session.clone(),
    };
    let path = args
        .views_file
        .clone()
        .or_else(|| mwb_viewer::views::default_path(&session))?;
    Some(ViewsFile::new(path, session))
}

/// Offline: samples `--worlds` of the scene here.
fn offline(args: &ViewerArgs, scene: &str) -> Result<(Started, String)> {
    let (file, text) = client::load_scene(scene)?;
    let template = mwb_core::scene::SceneTemplate::parse(&text, &file)?;
    let threads = args
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let started = std::time::Instant::now();
    let results = mwb_viewer::offline::sample_worlds(&template, args.worlds, threads);
    let first = template.instantiate(0);
    let names = first.bodies.iter().map(|b| b.name.clone()).collect();
    let mut state = ViewerState::new(template.name(), names, first.statics.clone())
        .with_initial(first.bodies.clone());
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
    let title = format!("manyworlds viewer — {} (offline)", template.name());
    Ok(((ViewerApp::new(state), RepaintSlot::default()), title))
}

/// Live: connects and starts the bus task.
async fn live(args: &ViewerArgs) -> Result<(Started, String, zenoh::Session)> {
    let mode = args.bus.client_default();
    let (endpoints, _) = args.bus.endpoints(mode);
    let session = args.bus.open(mode).await?;
    let endpoint = if endpoints.is_empty() {
        "the bus".to_owned()
    } else {
        endpoints.join(", ")
    };
    let repaint = RepaintSlot::default();
    let link = LiveLink::start(
        session.clone(),
        LiveConfig {
            space: args.bus.space.clone(),
            session: args.session.clone(),
            endpoint: endpoint.clone(),
            max_worlds: args.max_worlds,
            ..LiveConfig::default()
        },
        &tokio::runtime::Handle::current(),
        repaint.waker(),
    )?;
    let app = ViewerApp::live(ViewerState::live(endpoint.clone()), link);
    let title = format!("manyworlds viewer — {endpoint}");
    Ok(((app, repaint), title, session))
}

/// Places the camera from `--camera`; whether it was placed.
fn start_camera(app: &mut ViewerApp, path: Option<&std::path::Path>) -> Result<bool> {
    let Some(path) = path else {
        return Ok(false);
    };
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading camera file {}", path.display()))?;
    let camera: mwb_core::browse::Camera =
        serde_json::from_str(&text).with_context(|| format!("camera file {}", path.display()))?;
    let focus = app.state.bounds().map_or([0.0; 3], |(c, _)| c);
    let orbit = OrbitCamera::from_browse(&camera, focus)
        .with_context(|| format!("camera file {}", path.display()))?;
    app.state
        .update(Msg::SetCamera(orbit))
        .map_err(|e| anyhow!("{e}"))?;
    Ok(true)
}

/// `--rank`, `--select` and `--time`.
fn start_choices(app: &mut ViewerApp, args: &ViewerArgs) -> Result<()> {
    if let Some(r) = args.rank {
        app.set_sort(r.into());
    }
    if let Some(w) = args.select {
        // Live, a world not held yet (still arriving, or outside the sample of a large store)
        // is fetched and picked when it arrives.
        if !app.state.is_live() && app.state.world(w).is_none() {
            bail!(
                "--select {w}: no such world (there are {})",
                app.state.worlds().len()
            );
        }
        app.state
            .update(Msg::SelectWorld(Some(w)))
            .map_err(|e| anyhow!("{e}"))?;
    }
    if let Some(t) = args.time {
        app.state.update(Msg::Seek(t)).map_err(|e| anyhow!("{e}"))?;
    }
    Ok(())
}

/// Renders the screenshot: waits (live) for the worlds, adds the boxes in the laid-out view,
/// waits for their answers and the shown world's motion, then paints.
async fn shoot(
    mut app: ViewerApp,
    args: &ViewerArgs,
    rects: Vec<(ScreenRect, Polarity)>,
    size: [u32; 2],
    out: &std::path::Path,
) -> Result<()> {
    let wait = Duration::from_secs_f64(args.wait_s.max(0.0));
    let live = app.state.is_live();
    if live {
        let want = args.wait_worlds;
        let ok = app
            .pump_until(wait, |a| {
                let Some(link) = a.state.link() else {
                    return false;
                };
                a.state.holds_worlds(want.unwrap_or(link.store_worlds))
            })
            .await;
        if !ok {
            let link = app.state.link().cloned().unwrap_or_default();
            bail!(
                "the viewer had {} worlds after {:.0} s (the stores hold {}; {}): \
                 is a store with worlds running there?",
                app.state.worlds().len(),
                wait.as_secs_f64(),
                link.store_worlds,
                link.error.as_deref().unwrap_or("connected")
            );
        }
    }
    // Lay the UI out (and frame the camera), then add the boxes in that view, then paint.
    let _ = screenshot(&mut app, size, 1.0, 2);
    for (r, p) in rects {
        app.add_box_px(r, p, 1.0);
        if let Some(e) = app.last_error() {
            bail!("--rect: {e}");
        }
    }
    start_choices(&mut app, args)?;
    if live {
        let settled = app
            .pump_until(wait, |a| {
                a.state.pending() == 0
                    && a.unsent() == 0
                    && !a.state.shown_loading()
                    && (a.state.rank_spec().is_none() || a.state.ranking().is_some())
                    && args.select.is_none_or(|w| a.state.selected() == Some(w))
            })
            .await;
        if let Some(w) = args.select.filter(|&w| app.state.selected() != Some(w)) {
            bail!(
                "--select {w}: no store sent world {w} within {:.0} s (the stores hold {})",
                wait.as_secs_f64(),
                app.state.world_total()
            );
        }
        if !settled {
            bail!(
                "no answer from the cluster within {:.0} s: {}",
                wait.as_secs_f64(),
                app.state
                    .browse_error()
                    .unwrap_or("node-query did not answer")
            );
        }
    }
    // Ranked without --select: show the top-ranked world.
    let top = app
        .state
        .ranking()
        .and_then(|r| r.rows.first())
        .map(|r| r.world);
    if let (None, Some(w)) = (args.select, top) {
        app.state
            .update(Msg::SelectWorld(Some(w)))
            .map_err(|e| anyhow!("{e}"))?;
        if let Some(t) = args.time {
            app.state.update(Msg::Seek(t)).map_err(|e| anyhow!("{e}"))?;
        }
        if live && !app.pump_until(wait, |a| !a.state.shown_loading()).await {
            bail!(
                "world {w}'s motion did not arrive within {:.0} s",
                wait.as_secs_f64()
            );
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
        app.state.world_total(),
        app.state.survivor_count()
    );
    Ok(())
}
