//! `mwb bench ingest`: one store process on the bus, filled as fast as it takes worlds in
//! (issue 23: a million 10-object tumble worlds in one store, and how fast it ingests them).
//!
//! The store runs as its own process (`mwb store`, TCP loopback, multicast off, no query node,
//! a memory cap above what the worlds need). This process samples 24 real worlds of the scene
//! once, then publishes `--worlds` worlds made of them as a sampler does: each sampled world's
//! segments and summary (with the index its sampler built, unless `--no-sent-index`) under a
//! world counter and seed of its own, its payloads and checksums as sampled, with blocking
//! congestion control, so that the bus holds the feeder back when the
//! store falls behind. The job's state says when the store has every world stored, indexed and
//! counted (a store publishes a batch's counts after indexing its worlds).
//!
//! * `ingest_worlds_per_s`: worlds ÷ seconds from the first put to the job closed;
//! * `publish_worlds_per_s`: worlds ÷ seconds the puts took (the feeder's side; equal to the
//!   ingest rate when the store sets the pace);
//! * `rss_bytes`: the store process's resident set at the end; `rss_max_bytes` the largest seen
//!   (read every 100 ms); `rss_growth_bytes_per_world` = (end − before the first world) ÷ worlds;
//! * `memory_bytes_per_world`, `index_bytes_per_world`: the store's own accounting
//!   (`NodeStats`): what its memory cap counts, and the browsing index's part of it;
//! * `indexes_sent`, `indexes_checked`, `index_mismatches`, `indexes_refused`: what the store
//!   did with the indexes sent (`--store-arg=--verify-index-every=N` sets how many it checks).

use super::chaos::{LoopbackStore, Proc, rss_bytes, store_stats, until};
use super::query::{WorldMessages, sample_pool};
use crate::client;
use crate::output::{Summary, fields_table};
use anyhow::{Context, Result, anyhow, bail};
use mwb_core::keys::Keys;
use mwb_proto::v1::{Message, MotionSegment, NodeStats, WorldDone};
use mwb_store::index::DEFAULT_PATH_TOLERANCE_M;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};
use zenoh::qos::CongestionControl;

/// Arguments of `mwb bench ingest`.
#[derive(Debug, Clone, clap::Args)]
pub struct IngestArgs {
    /// Worlds to publish into the store.
    #[arg(long, default_value_t = 100_000)]
    pub worlds: u32,
    /// A scene file or shipped scene's name [default: the built-in 10-body tumble10].
    #[arg(long, default_value = "tumble10")]
    pub scene: String,
    /// The store's memory cap, MiB (above what the worlds need: nothing is refused).
    #[arg(long, default_value_t = 16_384)]
    pub memory_cap_mib: u64,
    /// The `mwb` binary the store runs [default: this one] (to compare two builds' stores
    /// under the same feeder).
    #[arg(long, value_name = "PATH")]
    pub store_bin: Option<std::path::PathBuf>,
    /// One more argument of the store's `mwb store` command line (repeatable), e.g.
    /// `--store-arg=--verify-index-every=1`.
    #[arg(long, value_name = "ARG", allow_hyphen_values = true)]
    pub store_arg: Vec<String>,
    /// Send each world's summary without the index its sampler built, so that the store
    /// indexes every world from its motion (as stores did before samplers sent the index).
    #[arg(long)]
    pub no_sent_index: bool,
    /// Give up after this many seconds.
    #[arg(long, default_value_t = 7_200)]
    pub timeout_s: u64,
    /// Print the result as one JSON line.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct IngestBench {
    pub scene: String,
    pub worlds: u32,
    pub bodies: usize,
    /// The store process's cores.
    pub threads: usize,
    pub ingest_worlds_per_s: f64,
    pub publish_worlds_per_s: f64,
    pub ingest_s: f64,
    /// Worlds the store holds at the end (`NodeStats.worlds`).
    pub stored_worlds: u64,
    pub rss_baseline_bytes: u64,
    pub rss_bytes: u64,
    pub rss_max_bytes: u64,
    pub rss_growth_bytes_per_world: f64,
    pub memory_bytes_per_world: f64,
    pub index_bytes_per_world: f64,
    pub index_failures: u64,
    pub refused_memory: u64,
    /// Worlds inserted with the index their sampler sent (`NodeStats.indexes_sent`), of those
    /// checked by the store's own indexing, found different, and sent indexes refused.
    pub indexes_sent: u64,
    pub indexes_checked: u64,
    pub index_mismatches: u64,
    pub indexes_refused: u64,
}

impl Summary for IngestBench {
    fn table(&self) -> String {
        fields_table(self)
    }
}

/// Runs `mwb bench ingest`.
pub async fn run(args: IngestArgs) -> Result<()> {
    if args.worlds == 0 {
        bail!("--worlds must be positive");
    }
    let mwb = match args.store_bin {
        Some(p) => p,
        None => std::env::current_exe().context("finding the mwb binary")?,
    };
    let (file, text) = if args.scene == "tumble10" {
        (
            super::viewer::TUMBLE10_NAME.to_owned(),
            super::viewer::TUMBLE10.to_owned(),
        )
    } else {
        client::load_scene(&args.scene)?
    };
    let pool_file = file.clone();
    let pool_text = text.clone();
    let (_, mut messages, _, _) = tokio::task::spawn_blocking(move || {
        sample_pool(&pool_file, &pool_text, 24, DEFAULT_PATH_TOLERANCE_M)
    })
    .await??;
    if args.no_sent_index {
        for (done, _) in &mut messages {
            done.index = None;
        }
    }
    let bodies = messages
        .first()
        .and_then(|(_, segments)| segments.first())
        .map_or(0, |s| s.body_count as usize);
    let mut store =
        LoopbackStore::start(&mwb, "ingest-store", args.memory_cap_mib, &args.store_arg).await?;
    let feed = Feed {
        file: &file,
        text: &text,
        messages: &messages,
        worlds: args.worlds,
        timeout: Duration::from_secs(args.timeout_s),
    };
    let r = feed
        .run(&store.session, &store.keys, &mut store.proc, store.pid)
        .await;
    store.close().await;
    let mut b = r?;
    b.scene = file;
    b.bodies = bodies;
    crate::output::print(&b, args.json)
}

/// What the feeder publishes.
struct Feed<'a> {
    file: &'a str,
    text: &'a str,
    messages: &'a [WorldMessages],
    worlds: u32,
    timeout: Duration,
}

impl Feed<'_> {
    async fn run(
        &self,
        session: &zenoh::Session,
        keys: &Keys,
        store: &mut Proc,
        pid: u32,
    ) -> Result<IngestBench> {
        until(
            "the store's statistics",
            Duration::from_secs(30),
            || async { !store_stats(session, keys).await.is_empty() },
        )
        .await?;
        tokio::time::sleep(Duration::from_secs(1)).await;
        let baseline = rss_bytes(pid).ok_or_else(|| anyhow!("no VmRSS for the store ({pid})"))?;
        let job_id = format!("ingest{}", std::process::id());
        let job = client::make_job(self.file, self.text, self.worlds, 0, Some(job_id.clone()))?;
        tokio::time::timeout(
            Duration::from_secs(60),
            client::submit_job(session, keys, &job),
        )
        .await
        .map_err(|_| anyhow!("submitting the job timed out"))??;
        // The store's RSS every 100 ms, on its own task.
        let (max, stop) = (
            Arc::new(AtomicU64::new(baseline)),
            Arc::new(AtomicBool::new(false)),
        );
        let watcher = {
            let (max, stop) = (max.clone(), stop.clone());
            tokio::spawn(async move {
                while !stop.load(Ordering::Relaxed) {
                    if let Some(rss) = rss_bytes(pid) {
                        max.fetch_max(rss, Ordering::Relaxed);
                    }
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            })
        };
        let r = self.publish_and_wait(session, keys, store, &job_id).await;
        stop.store(true, Ordering::Relaxed);
        let _ = watcher.await;
        let (publish_s, ingest_s) = r?;
        let end = rss_bytes(pid).unwrap_or(0);
        let st: NodeStats = store_stats(session, keys)
            .await
            .into_iter()
            .next()
            .ok_or_else(|| anyhow!("the store did not answer for its statistics"))?;
        let n = f64::from(self.worlds);
        Ok(IngestBench {
            scene: String::new(),
            worlds: self.worlds,
            bodies: 0,
            threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            ingest_worlds_per_s: n / ingest_s.max(1e-9),
            publish_worlds_per_s: n / publish_s.max(1e-9),
            ingest_s,
            stored_worlds: st.worlds,
            rss_baseline_bytes: baseline,
            rss_bytes: end,
            rss_max_bytes: max.load(Ordering::Relaxed).max(end),
            rss_growth_bytes_per_world: end.saturating_sub(baseline) as f64 / n,
            memory_bytes_per_world: st.memory_bytes as f64 / n,
            index_bytes_per_world: st.index_bytes as f64 / n,
            index_failures: st.index_failures,
            indexes_sent: st.indexes_sent,
            indexes_checked: st.indexes_checked,
            index_mismatches: st.index_mismatches,
            indexes_refused: st.indexes_refused,
            refused_memory: st.refused_memory,
        })
    }

    /// Publishes every world, then waits for the job to close: (seconds the puts took,
    /// seconds to the job closed), both from the first put.
    async fn publish_and_wait(
        &self,
        session: &zenoh::Session,
        keys: &Keys,
        store: &mut Proc,
        job: &str,
    ) -> Result<(f64, f64)> {
        let node = "ingest-feeder";
        let put = |key: String, bytes: Vec<u8>| async move {
            session
                .put(&key, bytes)
                .congestion_control(CongestionControl::Block)
                .await
                .map_err(|e| anyhow!("put {key}: {e}"))
        };
        let t0 = Instant::now();
        for i in 0..self.worlds {
            if i % 1024 == 0 && !store.running() {
                bail!("the store exited:\n{}", store.log_tail());
            }
            let (done, segments) = &self.messages[i as usize % self.messages.len()];
            let counter = u64::from(i);
            for s in segments {
                let seg = MotionSegment {
                    job_id: job.to_owned(),
                    node_id: node.to_owned(),
                    world_counter: counter,
                    seed: counter,
                    ..s.clone()
                };
                put(keys.segment(job, node, counter, s.seq), seg.encode_to_vec()).await?;
            }
            let done = WorldDone {
                job_id: job.to_owned(),
                node_id: node.to_owned(),
                world_counter: counter,
                seed: counter,
                ..done.clone()
            };
            put(keys.done(job, node, counter), done.encode_to_vec()).await?;
        }
        let publish_s = t0.elapsed().as_secs_f64();
        let mut last = None;
        loop {
            if !store.running() {
                bail!("the store exited:\n{}", store.log_tail());
            }
            let st = tokio::time::timeout(
                Duration::from_secs(10),
                client::job_state(session, keys, job),
            )
            .await
            .ok()
            .and_then(Result::ok)
            .flatten();
            // Closed: every world stored and counted; then browsable (a store's job state can
            // be a batch ahead of its index; a build older than `browsable_worlds` says 0).
            if let Some(st) = &st
                && st.closed
                && store_stats(session, keys).await.first().is_some_and(|s| {
                    s.browsable_worlds == 0
                        || s.browsable_worlds + s.index_failures >= u64::from(self.worlds)
                })
            {
                return Ok((publish_s, t0.elapsed().as_secs_f64()));
            }
            last = st.or(last);
            if t0.elapsed() > self.timeout {
                bail!(
                    "the store had {} of {} worlds after {:?}",
                    last.map_or(0, |s| s.worlds_done),
                    self.worlds,
                    self.timeout
                );
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }
}
