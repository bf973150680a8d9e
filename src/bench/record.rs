//! `mwb bench record`: what recording, replay and the store's journal cost.
//!
//! * pipeline: a store (router), a one-worker sampler and — in every other round — a recorder,
//!   each on its own zenoh session over TCP loopback, as `mwb bench sampler` runs it. Rounds
//!   alternate without / with the recorder (the same run, so machine noise falls on both);
//!   `overhead_ratio` = simulation steps/s of the stored worlds with ÷ without.
//! * `produced_mb_per_s`: bus payload the pipeline produced per second without a recorder
//!   (what a recorder must keep up with at full sampling speed); `record_mb_per_s`: the
//!   recording's own messages written again and again through the MCAP writer (zstd, one
//!   thread) to a file in `--dir`, payload MB per second including the final flush and footer;
//!   `record_headroom` = their ratio (the issue's target: ≥ 10).
//! * `replay_worlds_per_s`: the recording replayed at `max` into a fresh store, until the
//!   store holds every world.
//! * journal: the recording is replayed into a store with `--journal`, which stops once its
//!   journal has committed every world; a store restarted on that journal is timed from
//!   reading the journal to holding every world (`journal_restart_s_per_10k_worlds`, scaled
//!   linearly from the run's worlds; it includes making each world browsable — taking the
//!   index journaled with it, one in 256 rebuilt and compared — not opening the zenoh
//!   session). `bytes_per_world_on_disk` is the journal directory's size
//!   per world, `store_bytes_per_world` the store's in-memory bytes (worlds + browsing index)
//!   per world.

use super::free_port;
use super::sampler::process_cpu_seconds;
use crate::bus::{BusArgs, Mode};
use crate::client;
use crate::output::{Summary, fields_table};
use anyhow::{Context, Result, bail};
use mwb_core::keys::Keys;
use mwb_record::{
    BusMessage, RecorderConfig, RecordingInfo, RecordingWriter, ReplayConfig, Speed, WriterOptions,
    read_recording, replay, run_recorder,
};
use mwb_sampler::{SamplerConfig, run_sampler};
use mwb_store::{StoreConfig, StoreHandle, run_store};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Arguments of `mwb bench record`.
#[derive(Debug, Clone, clap::Args)]
pub struct RecordArgs {
    #[arg(long, default_value = "tumble")]
    pub scene: String,
    /// Worlds per pipeline round.
    #[arg(long, default_value_t = 100)]
    pub worlds: u32,
    /// Pipeline rounds without and with a recorder each (alternating).
    #[arg(long, default_value_t = 2)]
    pub rounds: u32,
    /// Payload MB written in the writer measurement.
    #[arg(long, default_value_t = 64)]
    pub write_mb: u64,
    /// Where the recordings and journals go (a directory on the disk to measure); default a
    /// new directory under the system's temporary directory, removed afterwards.
    #[arg(long)]
    pub dir: Option<PathBuf>,
    /// Print the result as one JSON line.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub motion: client::MotionArgs,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct RecordBench {
    pub scene: String,
    pub worlds: u32,
    pub rounds: u32,
    pub record_mb_per_s: f64,
    pub produced_mb_per_s: f64,
    pub record_headroom: f64,
    pub steps_per_s_without: f64,
    pub steps_per_s_with: f64,
    pub overhead_ratio: f64,
    /// Messages the recorder could not write (queue full): 0 means the recording is whole.
    pub recorder_dropped: u64,
    pub recording_bytes_per_world: f64,
    pub replay_worlds_per_s: f64,
    pub journal_restart_s_per_10k_worlds: f64,
    pub bytes_per_world_on_disk: f64,
    pub store_bytes_per_world: f64,
    pub core_seconds: f64,
}

impl Summary for RecordBench {
    fn table(&self) -> String {
        fields_table(self)
    }
}

/// Runs `mwb bench record`.
pub async fn run(args: RecordArgs) -> Result<()> {
    let (dir, remove) = match &args.dir {
        Some(d) => (d.clone(), false),
        None => (
            std::env::temp_dir().join(format!("mwb-bench-record-{}", std::process::id())),
            true,
        ),
    };
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let r = bench_record(&args, &dir).await;
    if remove && let Err(e) = std::fs::remove_dir_all(&dir) {
        tracing::warn!(dir = %dir.display(), error = %e, "removing the bench directory");
    }
    crate::output::print(&r?, args.json)
}

/// One pipeline round's result.
struct Round {
    steps_per_s: f64,
    payload_bytes_per_s: f64,
    dropped: u64,
}

fn bus_pair(space: &str) -> Result<(BusArgs, BusArgs)> {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port()?);
    let router = BusArgs {
        connect: vec![],
        listen: vec![endpoint.clone()],
        config: None,
        mode: Some(Mode::Router),
        space: space.to_owned(),
        multicast: false,
    };
    let client = BusArgs {
        connect: vec![endpoint],
        listen: vec![],
        mode: Some(Mode::Client),
        ..router.clone()
    };
    Ok((router, client))
}

/// A store, a sampler and optionally a recorder (into `record`), `worlds` worlds.
async fn pipeline(
    args: &RecordArgs,
    space: &str,
    record: Option<&Path>,
) -> Result<(Round, Option<mwb_record::RecordSummary>)> {
    let (file, text) = client::load_scene(&args.scene)?;
    let (store_bus, client_bus) = bus_pair(space)?;
    let keys = Keys::new(space)?;
    let store_session = store_bus.open(Mode::Router).await?;
    let sampler_session = client_bus.open(Mode::Client).await?;
    let store = run_store(
        store_session.clone(),
        StoreConfig {
            space: space.to_owned(),
            ..Default::default()
        },
    )
    .await?;
    let recorder = match record {
        Some(out) => {
            let s = client_bus.open(Mode::Client).await?;
            let rec = run_recorder(
                &s,
                RecorderConfig {
                    space: space.to_owned(),
                    out: out.to_owned(),
                    ..Default::default()
                },
            )
            .await?;
            Some((s, rec))
        }
        None => None,
    };
    let mut job = client::make_job(&file, &text, args.worlds, 0, None)?;
    args.motion.apply(&mut job);
    let t = Instant::now();
    let sampler = run_sampler(
        sampler_session.clone(),
        SamplerConfig {
            space: space.to_owned(),
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
    let wall = t.elapsed().as_secs_f64().max(1e-9);
    let mut steps = 0u64;
    let mut payload = 0u64;
    for i in 0..state.worlds_done {
        if let Some(w) = store.world(i) {
            steps += w.done()?.sim_steps;
            // Encoded segments and summary: the bus bytes of the world.
            payload += w.bytes;
        }
    }
    sampler.stop().await;
    let summary = match recorder {
        Some((s, rec)) => {
            // The last job state reaches the recorder before it stops.
            tokio::time::sleep(Duration::from_millis(300)).await;
            let sum = rec.finish().await?;
            crate::bus::close(s).await;
            Some(sum)
        }
        None => None,
    };
    store.stop();
    crate::bus::close(sampler_session).await;
    crate::bus::close(store_session).await;
    let round = Round {
        steps_per_s: steps as f64 / wall,
        payload_bytes_per_s: payload as f64 / wall,
        dropped: summary.as_ref().map_or(0, |s| s.dropped),
    };
    Ok((round, summary))
}

/// Payload MB/s of the MCAP writer, writing `messages` again and again to `path`.
fn write_speed(messages: &[BusMessage], path: &Path, mb: u64) -> Result<f64> {
    if messages.is_empty() {
        bail!("the recording is empty");
    }
    let target = mb.max(1) * 1_000_000;
    let t = Instant::now();
    let mut w = RecordingWriter::create(
        path,
        &RecordingInfo::now("bench"),
        &WriterOptions::default(),
    )?;
    let mut bytes = 0u64;
    'outer: loop {
        for m in messages {
            w.write(m)?;
            bytes += m.payload.len() as u64;
            if bytes >= target {
                break 'outer;
            }
        }
    }
    w.finish(Default::default())?;
    Ok(bytes as f64 / 1e6 / t.elapsed().as_secs_f64().max(1e-9))
}

async fn store_on(space: &str, cfg: StoreConfig) -> Result<(zenoh::Session, StoreHandle)> {
    let (router, _) = bus_pair(space)?;
    let s = router.open(Mode::Router).await?;
    let store = run_store(
        s.clone(),
        StoreConfig {
            space: space.to_owned(),
            ..cfg
        },
    )
    .await?;
    Ok((s, store))
}

/// Replays `recording` at `max` into a fresh store (journaling into `journal`, if given) and
/// returns the seconds until the store holds `worlds` worlds; with a journal, the store is
/// stopped only once its journal has committed everything (its counters stay still).
async fn replay_into(
    recording: &Path,
    space: &str,
    journal: Option<&Path>,
    worlds: usize,
) -> Result<f64> {
    let (store_bus, client_bus) = bus_pair(space)?;
    let s = store_bus.open(Mode::Router).await?;
    let c = client_bus.open(Mode::Client).await?;
    let store = run_store(
        s.clone(),
        StoreConfig {
            space: space.to_owned(),
            journal: journal.map(Path::to_owned),
            ..Default::default()
        },
    )
    .await?;
    let cfg = ReplayConfig {
        path: recording.to_owned(),
        speed: Speed::Max,
        space: space.to_owned(),
        wait_for_subscribers: Duration::from_secs(10),
    };
    let t = Instant::now();
    let summary = replay(&c, &cfg, std::future::pending()).await?;
    if let Some(e) = summary.damage {
        bail!("replay stopped: {e}");
    }
    let deadline = Instant::now() + Duration::from_secs(600);
    while store.world_count() < worlds {
        if Instant::now() > deadline {
            bail!(
                "the replayed store holds {} of {worlds} worlds",
                store.world_count()
            );
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let seconds = t.elapsed().as_secs_f64();
    if journal.is_some() {
        let mut last = store.journal_counters();
        loop {
            tokio::time::sleep(Duration::from_millis(300)).await;
            let now = store.journal_counters();
            if now == last {
                break;
            }
            last = now;
        }
    }
    store.stop();
    crate::bus::close(c).await;
    crate::bus::close(s).await;
    // The stopped store's journal writer finishes its file as it is dropped.
    tokio::time::sleep(Duration::from_millis(200)).await;
    Ok(seconds)
}

fn dir_bytes(dir: &Path) -> Result<u64> {
    let mut n = 0;
    for e in std::fs::read_dir(dir)? {
        n += e?.metadata()?.len();
    }
    Ok(n)
}

pub async fn bench_record(args: &RecordArgs, dir: &Path) -> Result<RecordBench> {
    let pid = std::process::id();
    let cpu0 = process_cpu_seconds();
    let recording = dir.join("session.mcap");
    let (mut without, mut with) = (Vec::new(), Vec::new());
    for round in 0..args.rounds.max(1) {
        let (r, _) = pipeline(args, &format!("benchrec{pid}a{round}"), None).await?;
        without.push(r);
        let (r, sum) = pipeline(args, &format!("benchrec{pid}b{round}"), Some(&recording)).await?;
        if let Some(e) = sum.and_then(|s| s.write_error) {
            bail!("the recorder failed: {e}");
        }
        with.push(r);
    }
    let mean = |v: &[Round], f: fn(&Round) -> f64| v.iter().map(f).sum::<f64>() / v.len() as f64;
    let steps_without = mean(&without, |r| r.steps_per_s);
    let steps_with = mean(&with, |r| r.steps_per_s);
    let produced = mean(&without, |r| r.payload_bytes_per_s) / 1e6;
    let dropped: u64 = with.iter().map(|r| r.dropped).sum();

    // The last round's recording: what it holds, how fast the writer writes it again.
    let back = read_recording(&recording)?;
    if let Some(e) = &back.error {
        bail!("the bench's own recording is damaged: {e}");
    }
    let messages: Vec<BusMessage> = back
        .messages
        .iter()
        .map(|m| BusMessage {
            key: m.key.clone(),
            payload: m.payload.clone(),
            log_time_ns: m.log_time_ns,
            publish_time_ns: Some(m.publish_time_ns),
        })
        .collect();
    let recording_bytes = std::fs::metadata(&recording)?.len();
    let record_mb_per_s = write_speed(&messages, &dir.join("write.mcap"), args.write_mb)?;
    std::fs::remove_file(dir.join("write.mcap"))?;

    // Replay at max speed into a fresh store.
    let replay_seconds = replay_into(
        &recording,
        &format!("benchrec{pid}r"),
        None,
        args.worlds as usize,
    )
    .await?;
    let replay_worlds_per_s = f64::from(args.worlds) / replay_seconds.max(1e-9);

    // The journal: written by a store the recording is replayed into (live ingest, group
    // commits), read back by a restart. (Not by `--load`ing the recording into a journaling
    // store: such a journal begins with a checkpoint whose job states already count the
    // loaded worlds, so a restart refuses every one of them as late.)
    let journal = dir.join("journal");
    replay_into(
        &recording,
        &format!("benchrec{pid}j"),
        Some(&journal),
        args.worlds as usize,
    )
    .await?;
    // What a restart must find: every world journaled by the store that was stopped.
    let mut journaled = 0;
    let mut files: Vec<PathBuf> = std::fs::read_dir(&journal)?
        .map(|e| e.map(|e| e.path()))
        .collect::<std::io::Result<_>>()?;
    files.sort();
    for f in &files {
        mwb_store::journal::read_store_input(f, true, |m| {
            journaled += usize::from(matches!(m, mwb_store::journal::StoreInput::Done(_)));
        });
    }
    let (s, store) = store_on(
        &format!("benchrec{pid}k"),
        StoreConfig {
            journal: Some(journal.clone()),
            ..Default::default()
        },
    )
    .await?;
    // Reading the journal and indexing its worlds (the session was opened before).
    let restart = store.start_report().seconds;
    let restored = store.world_count();
    let memory = store.stats().memory_bytes;
    store.stop();
    crate::bus::close(s).await;
    if restored != journaled || restored == 0 {
        bail!("the restart found {restored} of {journaled} journaled worlds");
    }
    let disk = dir_bytes(&journal)?;
    std::fs::remove_dir_all(&journal)?;
    let n = restored as f64;
    Ok(RecordBench {
        scene: args.scene.clone(),
        worlds: args.worlds,
        rounds: args.rounds.max(1),
        record_mb_per_s,
        produced_mb_per_s: produced,
        record_headroom: record_mb_per_s / produced.max(1e-12),
        steps_per_s_without: steps_without,
        steps_per_s_with: steps_with,
        overhead_ratio: steps_with / steps_without.max(1e-9),
        recorder_dropped: dropped,
        recording_bytes_per_world: recording_bytes as f64 / n,
        replay_worlds_per_s,
        journal_restart_s_per_10k_worlds: restart / n * 10_000.0,
        bytes_per_world_on_disk: disk as f64 / n,
        store_bytes_per_world: memory as f64 / n,
        core_seconds: process_cpu_seconds() - cpu0,
    })
}
