//! `mwb demo`: one process, one embedded zenoh session (peer, loopback, no multicast, no
//! router), a store and N samplers as separate nodes that talk only over the bus; samples a
//! shipped scene and prints what came back.

use crate::bus::{BusArgs, Mode};
use crate::check::verify_world;
use crate::client;
use crate::output::Summary;
use anyhow::{Context, Result, bail};
use mwb_core::browse::api::{Reply, Request};
use mwb_core::browse::{Metric, Order, RankKey};
use mwb_core::keys::Keys;
use mwb_sampler::{SamplerConfig, run_sampler};
use mwb_store::{StoreConfig, run_store};
use std::time::{Duration, Instant};

/// Where `mwb demo --stay` listens unless --listen says otherwise: where client commands
/// connect by default.
pub const STAY_ENDPOINT: &str = crate::bus::DEFAULT_ENDPOINT;

/// Keeps the demo's nodes (store, node-query and samplers) serving; prints where to connect.
async fn stay_until_ctrl_c(endpoints: &[String]) {
    let first = endpoints.first().map_or(STAY_ENDPOINT, String::as_str);
    let connect = if first == STAY_ENDPOINT {
        String::new()
    } else {
        format!(" --connect {first}")
    };
    eprintln!(
        "mwb demo: serving on {} — browse with `mwb query list{connect}`, sample more with \
         `mwb job submit <scene> --wait{connect}` (Ctrl-C stops)",
        endpoints.join(", "),
    );
    crate::bus::until_ctrl_c().await;
}

/// Arguments of `mwb demo`.
#[derive(Debug, Clone, clap::Args)]
pub struct DemoArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// Scene file, or a shipped scene name (tumble, pachinko, tower, chute).
    #[arg(long, default_value = "tumble")]
    pub scene: String,
    #[arg(long, default_value_t = 200)]
    pub worlds: u32,
    #[arg(long, default_value_t = 2)]
    pub samplers: usize,
    /// Store memory cap, MiB (stored motion and the browsing index).
    #[arg(long, default_value_t = 2048)]
    pub memory_cap_mib: u64,
    /// Print the summary as one JSON line.
    #[arg(long)]
    pub json: bool,
    /// Keep serving after the summary (store + node-query) so `mwb query` can browse.
    #[arg(long)]
    pub stay: bool,
    /// After the summary, open the viewer on the demo's bus (a window: needs a display); the
    /// demo's nodes serve until the window is closed.
    #[arg(long)]
    pub viewer: bool,
    /// Record the demo's bus into this MCAP file (as `mwb record` would, losing nothing: the
    /// demo waits for the disk). The recording ends with the summary.
    #[arg(long, value_name = "FILE")]
    pub record: Option<std::path::PathBuf>,
    #[command(flatten)]
    pub motion: client::MotionArgs,
}

/// Runs `mwb demo`: the summary as a table or one JSON line, then (`--stay`) serves.
pub async fn run(args: DemoArgs) -> Result<()> {
    let opts = DemoOptions {
        stay: args.stay,
        viewer: args.viewer,
        scene: args.scene,
        worlds: args.worlds,
        samplers: args.samplers,
        memory_cap_bytes: args.memory_cap_mib << 20,
        record: args.record,
        motion: args.motion,
        show_progress: !args.json && std::io::IsTerminal::is_terminal(&std::io::stderr()),
    };
    if !args.json {
        eprintln!(
            "mwb demo: {} worlds of {} with {} samplers on an embedded bus …",
            opts.worlds, opts.scene, opts.samplers
        );
    }
    run_demo_with(&args.bus, &opts, |s| crate::output::print(s, args.json)).await?;
    Ok(())
}

#[derive(Debug, Clone)]
pub struct DemoOptions {
    pub scene: String,
    pub worlds: u32,
    pub samplers: usize,
    pub memory_cap_bytes: u64,
    pub show_progress: bool,
    pub motion: client::MotionArgs,
    /// After the summary, keep the bus, store and node-query running until Ctrl-C so that
    /// `mwb query --connect <endpoint>` can browse the worlds.
    pub stay: bool,
    /// After the summary, open the viewer window on the demo's own session until it is closed
    /// (with `stay`, the demo serves on after that).
    pub viewer: bool,
    /// Record every put on the demo's bus into this MCAP file, from before the job is
    /// submitted until every world has been read back.
    pub record: Option<std::path::PathBuf>,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct DemoSummary {
    pub scene: String,
    pub job: String,
    pub samplers: usize,
    pub worlds: u32,
    pub seconds: f64,
    pub worlds_per_s: f64,
    pub impacts_per_world: f64,
    pub perturbations_per_world: f64,
    pub frames_per_world: f64,
    /// Motion payload per world, as stored and served (motion codec, the job's quality).
    pub bytes_per_world: f64,
    /// The same motion as 7 × f32 per body-frame.
    pub raw_f32_bytes_per_world: f64,
    pub rested_fraction: f64,
    pub crc_valid_worlds: u32,
    pub bodies: u32,
    /// Worlds indexed for browsing (path trees + metrics) by the store.
    pub browsable_worlds: u64,
    /// The world that comes to rest soonest (node-query ranking over the bus) and its time.
    pub soonest_rest_world: Option<u32>,
    pub soonest_rest_s: Option<f64>,
    /// With `--record`: the recording and how many messages it holds.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub recording: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub recorded_messages: Option<u64>,
}

impl Summary for DemoSummary {
    fn table(&self) -> String {
        let mut t = format!(
            "scene            {}\n\
             worlds           {} ({} CRC-verified, {} bodies each)\n\
             time             {:.2} s with {} samplers\n\
             worlds/s         {:.1}\n\
             impacts/world    {:.1}\n\
             perturbs/world   {:.1}\n\
             frames/world     {:.0}\n\
             bytes/world      {:.0} (motion codec; 7 × f32 would be {:.0}, {:.0}× more)\n\
             came to rest     {:.0} %\n\
             browsable        {} worlds indexed\n",
            self.scene,
            self.worlds,
            self.crc_valid_worlds,
            self.bodies,
            self.seconds,
            self.samplers,
            self.worlds_per_s,
            self.impacts_per_world,
            self.perturbations_per_world,
            self.frames_per_world,
            self.bytes_per_world,
            self.raw_f32_bytes_per_world,
            self.raw_f32_bytes_per_world / self.bytes_per_world.max(1.0),
            self.rested_fraction * 100.0,
            self.browsable_worlds,
        );
        if let (Some(w), Some(s)) = (self.soonest_rest_world, self.soonest_rest_s) {
            t += &format!(
                "rests soonest    world {w} (all bodies at rest after {s:.2} s; `mwb query show {w}`, \
                 `mwb query rank --by time-to-rest`)\n"
            );
        }
        if let (Some(f), Some(n)) = (&self.recording, self.recorded_messages) {
            t += &format!("recorded         {n} messages in {f} (`mwb replay {f}`)\n");
        }
        t
    }
}

pub async fn run_demo(bus: &BusArgs, opts: &DemoOptions) -> Result<DemoSummary> {
    run_demo_with(bus, opts, |_| Ok(())).await
}

/// [`run_demo`], calling `report` with the summary before staying to be browsed.
pub async fn run_demo_with(
    bus: &BusArgs,
    opts: &DemoOptions,
    report: impl FnOnce(&DemoSummary) -> Result<()>,
) -> Result<DemoSummary> {
    let keys = Keys::new(&bus.space)?;
    let (file, text) = client::load_scene(&opts.scene)?;
    let text = opts.motion.resolve_scene(&file, &text)?;
    let mut job = client::make_job(&file, &text, opts.worlds, 0, None)?;
    opts.motion.apply(&mut job);
    // Staying to be browsed needs a known port.
    let mut bus = bus.clone();
    if opts.stay && bus.listen.is_empty() {
        bus.listen = vec![STAY_ENDPOINT.to_owned()];
    }
    let bus = &bus;
    let session = bus.open(Mode::Peer).await?;
    let zid = session.zid().to_string();
    let store = run_store(
        session.clone(),
        StoreConfig {
            space: bus.space.clone(),
            memory_cap_bytes: opts.memory_cap_bytes,
            node_id: Some(format!("{zid}-store")),
            ..Default::default()
        },
    )
    .await?;
    let query = mwb_query::run_query(
        session.clone(),
        mwb_query::QueryConfig {
            space: bus.space.clone(),
            node_id: Some(format!("{zid}-query")),
            ..Default::default()
        },
    )
    .await?;
    let mut samplers = Vec::new();
    for i in 0..opts.samplers.max(1) {
        samplers.push(
            run_sampler(
                session.clone(),
                SamplerConfig {
                    space: bus.space.clone(),
                    workers: 1,
                    node_id: Some(format!("{zid}-s{i}")),
                    ..Default::default()
                },
            )
            .await?,
        );
    }
    let recorder = match &opts.record {
        Some(out) => Some(
            mwb_record::run_recorder(
                &session,
                mwb_record::RecorderConfig {
                    space: bus.space.clone(),
                    out: out.clone(),
                    overflow: mwb_record::Overflow::Block,
                    mwb_version: env!("CARGO_PKG_VERSION").into(),
                    extra_metadata: [(
                        "recorder_build".to_owned(),
                        mwb_sampler::world::provenance(),
                    )]
                    .into(),
                    node_id: Some(format!("{zid}-record")),
                    ..Default::default()
                },
            )
            .await
            .with_context(|| format!("starting to record into {}", out.display()))?,
        ),
        None => None,
    };
    let start = Instant::now();
    client::submit_job(&session, &keys, &job).await?;
    let bar = opts
        .show_progress
        .then(|| client::progress_bar(opts.worlds));
    let state = client::wait_job(&session, &keys, &job.id, None, |st| {
        if let Some(b) = &bar {
            b.set_position(u64::from(st.worlds_done));
        }
    })
    .await;
    let seconds = start.elapsed().as_secs_f64();
    if let Some(b) = &bar {
        b.finish_and_clear();
    }
    let state = match state {
        Ok(state) => state,
        Err(e) => {
            if let Some(recorder) = recorder
                && let Err(re) = recorder.finish().await
            {
                tracing::warn!(error = %re, "finishing the demo's recording");
            }
            stop_all(samplers, query, store, session).await;
            return Err(e);
        }
    };
    // Staying (or viewing), the samplers serve on: `mwb job submit --wait` against the demo,
    // or the viewer's jobs panel, gets worlds.
    let samplers = if opts.stay || opts.viewer {
        samplers
    } else {
        for s in samplers {
            s.stop().await;
        }
        Vec::new()
    };

    // Read every world back over the bus and verify it.
    let mut summary = DemoSummary {
        scene: file,
        job: job.id.clone(),
        samplers: opts.samplers.max(1),
        worlds: state.worlds_done,
        seconds,
        worlds_per_s: f64::from(state.worlds_done) / seconds.max(1e-9),
        impacts_per_world: 0.0,
        perturbations_per_world: 0.0,
        frames_per_world: 0.0,
        bytes_per_world: 0.0,
        raw_f32_bytes_per_world: 0.0,
        rested_fraction: 0.0,
        crc_valid_worlds: 0,
        bodies: 0,
        browsable_worlds: store.indexed_count(),
        soonest_rest_world: None,
        soonest_rest_s: None,
        recording: None,
        recorded_messages: None,
    };
    for i in 0..state.worlds_done {
        let Some(w) = client::fetch_world(&session, &keys, i).await? else {
            bail!("world {i} is missing from the store");
        };
        let check = verify_world(&w)?;
        let done = w.done.unwrap_or_default();
        summary.crc_valid_worlds += 1;
        summary.bodies = check.bodies;
        summary.impacts_per_world += check.impacts as f64;
        summary.perturbations_per_world += f64::from(done.perturbations);
        summary.frames_per_world += f64::from(check.frames);
        summary.bytes_per_world += check.bytes as f64;
        summary.raw_f32_bytes_per_world += check.raw_f32_bytes as f64;
        summary.rested_fraction += f64::from(u8::from(done.rested));
    }
    let n = f64::from(state.worlds_done.max(1));
    summary.impacts_per_world /= n;
    summary.perturbations_per_world /= n;
    summary.frames_per_world /= n;
    summary.bytes_per_world /= n;
    summary.raw_f32_bytes_per_world /= n;
    summary.rested_fraction /= n;

    // Browse once over the bus, as `mwb query rank --by time-to-rest --objects all` would.
    let objects: Vec<u32> = (0..summary.bodies).collect();
    let ranked = mwb_query::send(
        &session,
        &keys,
        "demo",
        &Request::Rank {
            key: RankKey::Metric {
                metric: Metric::TimeToRest,
                objects,
                // The definition `mwb query rank --by time-to-rest` uses: the last body's rest
                // time; worlds with a body still moving at the end have none and rank last.
                aggregate: Metric::TimeToRest.default_aggregate(),
            },
            order: Order::Ascending,
            k: 1,
            all_worlds: false,
            plausible_only: false,
        },
        Duration::from_secs(10),
    )
    .await?;
    match ranked {
        Reply::Ranking { rows, .. } => {
            if let Some(best) = rows.first() {
                summary.soonest_rest_world = Some(best.world);
                summary.soonest_rest_s = best.score;
            }
        }
        Reply::Error { message } => bail!("browsing the demo worlds: {message}"),
        other => bail!("browsing the demo worlds: unexpected reply {other:?}"),
    }
    if let Some(recorder) = recorder {
        let rec = recorder
            .finish()
            .await
            .context("finishing the demo's recording")?;
        if let Some(e) = rec.write_error {
            return Err(anyhow::Error::new(e).context(format!(
                "recording into {} stopped early; the file ends at its last whole chunk",
                rec.path.display()
            )));
        }
        summary.recording = Some(rec.path.display().to_string());
        summary.recorded_messages = Some(rec.received.saturating_sub(rec.dropped));
    }
    report(&summary)?;
    if opts.viewer {
        let shown = open_viewer(&session, &bus.space, &summary.scene).await;
        if let Err(e) = shown {
            stop_all(samplers, query, store, session).await;
            return Err(e);
        }
    }
    if opts.stay {
        stay_until_ctrl_c(&bus.listen).await;
    }
    stop_all(samplers, query, store, session).await;
    Ok(summary)
}

/// The viewer window on the demo's own session (live: it browses what the demo's store holds),
/// until the user closes it.
async fn open_viewer(session: &zenoh::Session, space: &str, scene: &str) -> Result<()> {
    let repaint = mwb_viewer::ui::RepaintSlot::default();
    let endpoint = "the demo's embedded bus".to_owned();
    let link = mwb_viewer::live::LiveLink::start(
        session.clone(),
        mwb_viewer::live::LiveConfig {
            space: space.to_owned(),
            session: "viewer".into(),
            endpoint: endpoint.clone(),
            ..Default::default()
        },
        &tokio::runtime::Handle::current(),
        repaint.waker(),
    )?;
    let mut app = mwb_viewer::ViewerApp::live(mwb_viewer::ViewerState::live(endpoint), link);
    // Saved views kept with the session, as `mwb viewer` keeps them.
    match mwb_viewer::views::default_path("viewer") {
        Some(path) => app = app.with_views_file(mwb_viewer::views::ViewsFile::new(path, "viewer")),
        None => eprintln!(
            "mwb demo: no configuration directory ($XDG_CONFIG_HOME, $HOME): saved views last \
             only while the viewer runs"
        ),
    }
    eprintln!("mwb demo: opening the viewer (close its window to stop)");
    tokio::task::block_in_place(|| {
        mwb_viewer::ui::run_window(
            app,
            &format!("manyworlds viewer — demo ({scene})"),
            [1280, 800],
            repaint,
        )
    })
    .map_err(|e| {
        anyhow::anyhow!(
            "opening the viewer window: {e} (it needs a display; without one, browse with `mwb \
             demo --stay` and `mwb query`, or `mwb viewer --connect … --screenshot out.png`)"
        )
    })
}

/// Stops the demo's nodes and closes its session.
async fn stop_all(
    samplers: Vec<mwb_sampler::SamplerHandle>,
    query: mwb_query::QueryHandle,
    store: mwb_store::StoreHandle,
    session: zenoh::Session,
) {
    for s in samplers {
        s.stop().await;
    }
    query.stop();
    store.stop();
    crate::bus::close(session).await;
}
