//! `mwb bench query`: browsing speed over a store shard (§4.4.2), one JSON line.
//!
//! Worlds are synthetic but their paths are real: a few worlds of a shipped scene are sampled
//! and indexed exactly as the store does (decode, error-bounded polyline stored grid-rounded,
//! metrics);
//! each synthetic world takes `objects` of those object paths, each shifted sideways by up to a
//! metre so that no two worlds are alike. Constraints are screen rectangles (2–20 % of the image
//! side) drawn through a camera looking at the scene from a random direction, aimed at a random
//! point of a random path, over that object and up to two others, a fifth of them negative, with
//! a time window in a third of them.
//!
//! * add: a new constraint over every world (`Shard::handle`, every core), including the AND;
//! * remove: removing one of four live constraints (AND of the other bitsets, no geometry);
//! * index: the store's path index — per object index a hierarchy of path pieces (8 segments
//!   each, referring to the world's one stored copy of the path) is walked down to the pieces
//!   near the frustum, whose segments are clipped, on every core; per_world: every world's
//!   stored paths, world by world, segment by segment (every core);
//! * brute: the same constraint tested segment by segment on every polyline without any tree,
//!   on every core, from a plain copy of the polylines (each world's side by side, allocated
//!   world after world: the cheapest layout for it, sharing nothing with the index);
//!   obb_speedup = brute ÷ index, per_world_speedup = brute ÷ per_world (medians).
//!   All three must agree on every world;
//! * rank: top 10 by angular travel summed over all objects, over every world;
//! * ingest: `Shard::insert` of each world as the shard is filled (no live constraint), mean
//!   and slowest — the slowest builds a block of the hierarchies;
//! * `--with-motion`: every world's sampled messages (its summary with the index its sampler
//!   built) go through the store's assembly and the world is indexed as a store indexes it
//!   ([`index_stored`], 256 worlds at a time: the sent index taken, the first and one in 256 also indexed from
//!   the stored motion and compared): `store_ingest_worlds_per_s` is the store's own work;
//! * `--shards N`: world i is shard (i mod N)'s, as stores number them; each shard uses every
//!   core, as its own process would, and every request goes to all of them at once (answers
//!   merged) — N store processes on one machine, without the bus;
//! * `--no-brute`: no brute force and no copy of the worlds for it, so `rss_bytes` is the
//!   stores' own (the index is still checked against the world-by-world test).

use crate::output::{Summary, fields_table};
use anyhow::{Result, bail};
use mwb_core::browse::api::{Reply, Request, ShardReply, ShardRequest};
use mwb_core::browse::{
    Aggregate, Camera, Constraint, ConstraintId, Frustum, Intrinsics, Metric, Order, Polarity,
    Polyline, RankKey, RestThresholds, ScreenRect, TimeWindow, Viewport, WorldSet,
};
use mwb_core::rng::{Stream, WorldRng};
use mwb_core::scene::SceneTemplate;
use mwb_proto::v1::{Job, Message, MotionSegment, WorldDone, WorldIndex};
use mwb_sampler::{RunOptions, run_world, segment_message, world_done};
use mwb_store::index::{
    DEFAULT_PATH_TOLERANCE_M, IndexedObject, SentChecks, SentIndex, index_stored,
};
use mwb_store::{
    Assembler, IndexedWorld, Outcome, Shard, ShardBytes, ShardSpec, StoredWorld, index_world,
};
use std::ops::ControlFlow;
use std::time::Instant;

/// Arguments of `mwb bench query`.
#[derive(Debug, Clone, clap::Args)]
pub struct QueryArgs {
    /// Scene whose sampled paths the synthetic worlds are made of.
    #[arg(long, default_value = "tumble")]
    pub scene: String,
    #[arg(long, default_value_t = 10_000)]
    pub worlds: u32,
    /// Objects per world.
    #[arg(long, default_value_t = 10)]
    pub objects: u32,
    /// Random constraints to time.
    #[arg(long, default_value_t = 60)]
    pub constraints: usize,
    /// The store's path tolerance (polyline vs decoded path), mm.
    #[arg(long, default_value_t = 10.0)]
    pub path_tolerance_mm: f64,
    /// Shift each synthetic object path sideways by up to this many metres.
    #[arg(long, default_value_t = 1.0)]
    pub spread_m: f64,
    /// Split the worlds over this many store shards in this process (world i to shard
    /// i mod N, as the stores number them), each using every core as its own process would,
    /// asked at once: how one machine does with 1, 2 or 4 store processes.
    #[arg(long, default_value_t = 1)]
    pub shards: u32,
    /// Skip brute force, and with it the bench's own copy of every world: `rss_bytes` is then
    /// the stores' (and the process's runtime). The index is still checked against the store's
    /// world-by-world test.
    #[arg(long)]
    pub no_brute: bool,
    /// Also store every world's motion as a store does (its sampled segments and summary,
    /// given to the store's assembly under a seed of its own), each world's objects then all
    /// taken from that one sampled world: `rss_bytes` is then what a store holding these worlds
    /// takes. Needs as many bodies in the scene as `--objects` (`--scene tumble10`: the viewer
    /// bench's built-in 10-body tumble) and one shard.
    #[arg(long)]
    pub with_motion: bool,
    /// Print the result as one JSON line.
    #[arg(long)]
    pub json: bool,
}

/// Runs `mwb bench query`.
pub async fn run(args: QueryArgs) -> Result<()> {
    let opts = QueryBenchOptions {
        scene: args.scene,
        worlds: args.worlds,
        objects: args.objects,
        constraints: args.constraints,
        path_tolerance_m: args.path_tolerance_mm * 1e-3,
        spread_m: args.spread_m,
        shards: args.shards,
        brute: !args.no_brute,
        with_motion: args.with_motion,
    };
    let b = tokio::task::spawn_blocking(move || bench_query(&opts)).await??;
    crate::output::print(&b, args.json)
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct QueryBench {
    pub scene: String,
    pub path_tolerance_mm: f64,
    pub spread_m: f64,
    pub worlds: u32,
    pub objects: u32,
    /// Store shards the worlds are split over (one process; each shard uses every core).
    pub shards: u32,
    pub threads: usize,
    pub constraints: usize,
    /// Fraction of worlds a constraint kept, median (how selective the boxes were).
    pub kept_fraction_p50: f64,
    pub add_p50_ms: f64,
    pub add_p95_ms: f64,
    pub remove_p50_ms: f64,
    /// The store's path index: per object index, a hierarchy of path pieces walked down to the
    /// pieces near the frustum, whose segments are then clipped (`tree_p50_ms` in earlier
    /// lines).
    pub index_p50_ms: f64,
    /// Every world's stored paths, world by world, without the hierarchy (the store's
    /// `evaluate_each`; `per_world_trees_p50_ms` when worlds held §4.4.2 OBB trees).
    pub per_world_p50_ms: f64,
    /// Absent with `--no-brute`.
    pub brute_p50_ms: Option<f64>,
    /// brute ÷ index (the name for it).
    pub obb_speedup: Option<f64>,
    /// brute ÷ per-world.
    pub per_world_speedup: Option<f64>,
    pub rank_p50_ms: f64,
    /// `Shard::insert` of one indexed world (its pieces into the hierarchies, now and then a
    /// block built, no live constraint): mean over the worlds, and the slowest.
    pub ingest_mean_us: f64,
    pub ingest_max_ms: f64,
    /// Worlds inserted per second of insert time (one thread, nothing else in the shard).
    pub ingest_worlds_per_s: f64,
    /// Inserts that took longer than 10 ms (the longest allowed pause).
    pub ingest_pauses_over_10ms: usize,
    /// The shard's heap bytes per world (`Shard::heap_bytes`, by capacity): paths, hierarchies,
    /// metrics, world records, bitsets — everything the store holds for browsing.
    pub memory_bytes_per_world: f64,
    /// `memory_bytes_per_world` by structure: stored paths (the only copy of the vertices),
    /// hierarchies of path pieces, metrics, the rest of the world records, bitsets.
    pub paths_bytes_per_world: f64,
    pub hierarchy_bytes_per_world: f64,
    pub metrics_bytes_per_world: f64,
    pub records_bytes_per_world: f64,
    pub bitsets_bytes_per_world: f64,
    /// The codec payloads of a world of `objects` objects (the compressed motion; charged at the
    /// sampled worlds' mean per object).
    pub payload_bytes_per_world: f64,
    /// A world's segments as encoded (payload and header fields: `StoredWorld::bytes`),
    /// charged the same way.
    pub motion_bytes_per_world: f64,
    /// `motion_bytes_per_world + memory_bytes_per_world`: the store's total per world, its
    /// motion counted as encoded.
    pub total_bytes_per_world: f64,
    /// What a stored world costs in memory beyond its codec payloads: its encoded summary and
    /// segment headers, its struct, its job id and the allocator's share of each block
    /// (`StoredWorld::held_bytes` − payload, the mean over the sampled worlds: per world, not
    /// per object).
    pub held_overhead_bytes_per_world: f64,
    /// `payload_bytes_per_world + held_overhead_bytes_per_world + memory_bytes_per_world`:
    /// the store's total with its motion as held in memory, what its memory cap counts.
    pub held_total_bytes_per_world: f64,
    /// `--with-motion`: worlds the store's assembly holds, and what it counts for them
    /// (`Assembler::memory_bytes` ÷ worlds: their motion as held); `null` without.
    pub stored_worlds: Option<usize>,
    pub stored_held_bytes_per_world: Option<f64>,
    /// `--with-motion`: worlds per second of the store's own work on them — assembly,
    /// indexing from the stored motion (decode, polylines, metrics) on every core, `threads`
    /// of them, in batches of 256 as they reach a busy store, and insert — what one store
    /// process can take in; `null` without. `ingest_worlds_per_s` is the insert alone.
    pub store_ingest_worlds_per_s: Option<f64>,
    /// Resident set of the whole bench process at the end (the shards, and unless `--no-brute`
    /// the bench's own copy of the worlds for brute force), from /proc/self/status; 0 where
    /// unavailable.
    pub rss_bytes: u64,
    /// Polyline vertices per object, mean (the index's size driver).
    pub vertices_per_object: f64,
    pub path_radius_mm_p50: f64,
}

impl Summary for QueryBench {
    fn table(&self) -> String {
        fields_table(self)
    }
}

/// The bench's random draws: a SplitMix64 stream of a fixed seed.
struct Rng(WorldRng);

impl Rng {
    fn unit(&mut self) -> f64 {
        self.0.next_f64()
    }
    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        self.0.uniform(lo, hi)
    }
    fn index(&mut self, n: usize) -> usize {
        ((self.unit() * n as f64) as usize).min(n.saturating_sub(1))
    }
}

fn percentile(v: &mut [f64], p: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

/// What the sampled worlds' motion costs the store, per object (the synthetic worlds hold no
/// motion of their own: each of their objects is charged the pool's mean).
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct MotionBytes {
    /// Segment messages as the store's assembly counts them against its memory cap
    /// (`StoredWorld::bytes`: payload, low-res path, header fields).
    encoded_per_object: f64,
    /// The codec payloads alone (the compressed motion).
    payload_per_object: f64,
    /// Per world: held in memory − payload ([`StoredWorld::held_bytes`]).
    held_overhead_per_world: f64,
}

/// A sampled world's summary and segments, as a sampler sends them.
pub(super) type WorldMessages = (WorldDone, Vec<MotionSegment>);

/// Real indexed worlds of `scene`, as the store builds them, their messages, and their motion's
/// bytes.
pub(super) fn sample_pool(
    file: &str,
    text: &str,
    worlds: u32,
    tolerance: f64,
) -> Result<(
    Vec<IndexedWorld>,
    Vec<WorldMessages>,
    MotionBytes,
    RestThresholds,
)> {
    let template = SceneTemplate::parse(text, file)?;
    let rest = RestThresholds::from(template.settings());
    let (mut out, mut messages) = (Vec::new(), Vec::new());
    let (mut encoded, mut payload, mut objects, mut overhead) = (0u64, 0u64, 0u64, 0u64);
    // For the held bytes: ids as long as a real job's and sampler's, so that their copies in
    // every segment and summary weigh what they do in a store (the encoded bytes keep the
    // one-letter ids, which scale with objects as the motion does).
    let (job, node) = ("bench-query-0123456789", "sampler-0123abcd");
    for i in 0..worlds {
        let seed = mwb_core::rng::world_seed("bench-query", "local", u64::from(i));
        let mut segments = Vec::new();
        let summary = run_world(&template, seed, RunOptions::default(), &mut |seg| {
            segments.push(segment_message("q", "n", u64::from(i), seed, seg));
            ControlFlow::Continue(())
        })?;
        let done = world_done("q", "n", u64::from(i), &summary);
        let bytes = segments.iter().map(|s| s.encoded_len() as u64).sum();
        encoded += bytes;
        let world_payload: u64 = segments.iter().map(|s| s.payload.len() as u64).sum();
        payload += world_payload;
        objects += segments.first().map_or(0, |s| u64::from(s.body_count));
        let mut named = segments.clone();
        for s in &mut named {
            (s.job_id, s.node_id) = (job.into(), node.into());
        }
        let named_done = WorldDone {
            job_id: job.into(),
            node_id: node.into(),
            ..done.clone()
        };
        let held = StoredWorld::new(i, job.into(), &named_done, &named, 0, None).held_bytes();
        overhead += held.saturating_sub(world_payload);
        let stored = StoredWorld::new(i, "q".into(), &done, &segments, bytes, None);
        out.push(index_world(&stored, i, rest, tolerance)?);
        // As a sampler sends it: with the index it built (the store's, by construction).
        let mut done = done;
        mwb_sampler::attach_index(&mut done, &segments, &template);
        messages.push((done, segments));
    }
    let per = |b: u64| b as f64 / objects.max(1) as f64;
    Ok((
        out,
        messages,
        MotionBytes {
            encoded_per_object: per(encoded),
            payload_per_object: per(payload),
            held_overhead_per_world: overhead as f64 / f64::from(worlds.max(1)),
        },
        rest,
    ))
}

/// Worlds a `--with-motion` bench gives the store's assembly and indexes at a time.
const INGEST_BATCH: u32 = 256;

/// A sampled world's messages through the store's assembly as world `i` (its own counter and
/// seed; the payloads and their checksums as they were): the world as the store holds it, and
/// the index its sampler sent.
fn store_world(
    assembler: &mut Assembler,
    (done, segments): &WorldMessages,
    i: u32,
) -> Result<(std::sync::Arc<StoredWorld>, Option<Box<WorldIndex>>)> {
    let mut last = Outcome::Pending;
    for s in segments {
        let seg = MotionSegment {
            world_counter: u64::from(i),
            seed: u64::from(i),
            ..s.clone()
        };
        last = assembler.on_segment(seg, 0);
    }
    if last == Outcome::Pending {
        let done = WorldDone {
            world_counter: u64::from(i),
            seed: u64::from(i),
            ..done.clone()
        };
        last = assembler.on_done(done, 0);
    }
    match last {
        Outcome::Stored {
            index, sent_index, ..
        } => Ok((
            assembler
                .world(index)
                .ok_or_else(|| anyhow::anyhow!("world {i}: stored as {index} but not found"))?,
            sent_index,
        )),
        other => bail!("world {i}: the store's assembly did not store it: {other:?}"),
    }
}

/// `obj` moved by `d` (rounded to the path's grid, so the move adds no rounding and the radius
/// stays exact); where that is not possible, stored again from the moved polyline, the new
/// rounding added to the radius.
fn shifted(obj: &IndexedObject, frame_dt: f64, d: [f64; 3]) -> Result<IndexedObject> {
    if let Some(moved) = obj.translated(d) {
        return Ok(moved);
    }
    let p = obj.polyline();
    let points = p
        .points()
        .iter()
        .map(|x| [x[0] + d[0], x[1] + d[1], x[2] + d[2]])
        .collect();
    let moved = Polyline::new(p.times().to_vec(), points)?;
    Ok(IndexedObject::new(&moved, frame_dt, obj.radius)?)
}

/// World `g` of the bench's shards (world i is shard i mod N's).
fn world_of(shards: &[Shard], g: u32) -> Option<&IndexedWorld> {
    shards.get(g as usize % shards.len().max(1))?.world(g)
}

fn random_constraint(rng: &mut Rng, id: u64, worlds: u32, shards: &[Shard]) -> Result<Constraint> {
    let Some(w) = world_of(shards, rng.index(worlds as usize) as u32) else {
        bail!("a synthetic world is missing from its shard");
    };
    let o = rng.index(w.objects.len());
    let path = &w.objects[o];
    let (target, _) = path.vertex(rng.index(path.len()));
    let (yaw, pitch) = (rng.range(0.0, std::f64::consts::TAU), rng.range(0.2, 1.2));
    let dist = rng.range(4.0, 12.0);
    let dir = [
        pitch.cos() * yaw.sin(),
        pitch.sin(),
        pitch.cos() * yaw.cos(),
    ];
    let eye = [
        target[0] + dist * dir[0],
        target[1] + dist * dir[1],
        target[2] + dist * dir[2],
    ];
    // Camera −z looks along −dir: yaw about y, then pitch down about x.
    let (sy, cy) = (0.5 * yaw).sin_cos();
    let (sp, cp) = (-0.5 * pitch).sin_cos();
    let qy = [0.0, sy, 0.0, cy];
    let qx = [sp, 0.0, 0.0, cp];
    let rotation = [
        qy[3] * qx[0] + qy[0] * qx[3] + qy[1] * qx[2] - qy[2] * qx[1],
        qy[3] * qx[1] - qy[0] * qx[2] + qy[1] * qx[3] + qy[2] * qx[0],
        qy[3] * qx[2] + qy[0] * qx[1] - qy[1] * qx[0] + qy[2] * qx[3],
        qy[3] * qx[3] - qy[0] * qx[0] - qy[1] * qx[1] - qy[2] * qx[2],
    ];
    let camera = Camera {
        position: eye,
        rotation,
        intrinsics: Intrinsics::VerticalFov { fov_y_rad: 0.9 },
        viewport: Viewport {
            width: 1280,
            height: 720,
        },
        near: 0.1,
        far: 50.0,
    };
    let proj = camera.projection()?;
    let (centre, _) = proj.project(target).unwrap_or(([640.0, 360.0], 1.0));
    let side = rng.range(0.02, 0.2) * 720.0;
    let rect = ScreenRect {
        x0: centre[0] - 0.5 * side,
        y0: centre[1] - 0.5 * side,
        x1: centre[0] + 0.5 * side,
        y1: centre[1] + 0.5 * side,
    };
    let window = if rng.unit() < 1.0 / 3.0 {
        let a = rng.range(0.0, 2.0);
        Some(TimeWindow::new(a, a + rng.range(0.3, 1.5))?)
    } else {
        None
    };
    // "This rock", sometimes "any of these two or three".
    let n = w.objects.len();
    let mut objects = vec![o as u32];
    for _ in 0..rng.index(3) {
        objects.push(rng.index(n) as u32);
    }
    objects.sort_unstable();
    objects.dedup();
    Ok(Constraint {
        id: ConstraintId(id),
        polarity: if rng.unit() < 0.8 {
            Polarity::Positive
        } else {
            Polarity::Negative
        },
        frustum: proj.frustum(&rect)?,
        objects,
        quantifier: Default::default(),
        window,
        scope: Default::default(),
    })
}

/// Per world, per object: the polyline and its never-miss radius, stored plainly (each world's
/// objects side by side, their polylines allocated world after world): all brute force needs.
type PlainWorld = Vec<(Polyline, f64)>;

/// The constraint evaluated without the tree: every segment of every chosen polyline. World
/// `i` is `worlds[i]`; returns the worlds that satisfy it.
fn brute(worlds: &[PlainWorld], c: &Constraint, threads: usize) -> WorldSet {
    let eval = |w: &PlainWorld| {
        let touched = c.objects.iter().any(|&o| {
            w.get(o as usize).is_some_and(|(path, radius)| {
                let f: Frustum = c.frustum.inflated(*radius);
                path.first_entry(&f, c.window).is_some()
            })
        });
        c.satisfied_given(touched)
    };
    let chunk = worlds.len().div_ceil(threads.max(1)).max(1);
    std::thread::scope(|s| {
        let handles: Vec<_> = worlds
            .chunks(chunk)
            .enumerate()
            .map(|(k, part)| {
                s.spawn(move || {
                    let base = (k * chunk) as u32;
                    (base..)
                        .zip(part)
                        .filter(|(_, w)| eval(w))
                        .map(|(i, _)| i)
                        .collect::<Vec<u32>>()
                })
            })
            .collect();
        handles
            .into_iter()
            .flat_map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e)))
            .collect()
    })
}

/// What to measure.
#[derive(Debug, Clone)]
pub struct QueryBenchOptions {
    pub scene: String,
    pub worlds: u32,
    pub objects: u32,
    pub constraints: usize,
    /// The store's path tolerance, metres (longer polylines when smaller).
    pub path_tolerance_m: f64,
    /// Each synthetic object path is shifted sideways by up to this much, metres: 1 m keeps a
    /// scene as compact as it was sampled (every box meets most paths); larger values spread
    /// the worlds' objects over a wider set, as in a scene with many separate areas.
    pub spread_m: f64,
    /// Store shards the worlds are split over.
    pub shards: u32,
    /// Also run brute force (keeping its own copy of every world).
    pub brute: bool,
    /// Also hold every world's motion in the store's assembly (see [`QueryArgs::with_motion`]).
    pub with_motion: bool,
}

impl Default for QueryBenchOptions {
    fn default() -> Self {
        Self {
            scene: "tumble".into(),
            worlds: 10_000,
            objects: 10,
            constraints: 60,
            path_tolerance_m: DEFAULT_PATH_TOLERANCE_M,
            spread_m: 1.0,
            shards: 1,
            brute: true,
            with_motion: false,
        }
    }
}

pub fn bench_query(opts: &QueryBenchOptions) -> Result<QueryBench> {
    let (worlds, objects, constraints) = (opts.worlds, opts.objects, opts.constraints);
    if !(opts.spread_m.is_finite() && opts.spread_m >= 0.0) {
        bail!("--spread-m must be a non-negative number");
    }
    if !(opts.path_tolerance_m.is_finite() && opts.path_tolerance_m >= 0.0) {
        bail!("--path-tolerance-mm must be a non-negative number");
    }
    if worlds == 0 || objects == 0 || constraints == 0 || opts.shards == 0 {
        bail!("--worlds, --objects, --constraints and --shards must be positive");
    }
    let (file, text) = if opts.scene == "tumble10" {
        (
            crate::bench::viewer::TUMBLE10_NAME.to_owned(),
            crate::bench::viewer::TUMBLE10.to_owned(),
        )
    } else {
        crate::client::load_scene(&opts.scene)?
    };
    let (pool, messages, motion, rest) = sample_pool(&file, &text, 24, opts.path_tolerance_m)?;
    if opts.with_motion {
        if opts.shards != 1 {
            bail!("--with-motion: one shard only (--shards 1)");
        }
        if let Some(w) = pool.iter().find(|w| w.objects.len() != objects as usize) {
            bail!(
                "--with-motion: {file} has {} bodies, --objects is {objects}: each world's \
                 objects are its sampled world's bodies (--scene tumble10 has 10)",
                w.objects.len()
            );
        }
    }
    // With the motion: the store's own assembly, one job of all the worlds.
    let mut assembler = Assembler::new(u64::MAX / 4);
    assembler.submit_job(Job {
        id: "q".into(),
        revision: 1,
        target_worlds: worlds,
        ..Default::default()
    });
    let pool_objects: Vec<(&IndexedObject, mwb_core::browse::PackedMetrics)> = pool
        .iter()
        .flat_map(|w| w.objects.iter().zip(w.metrics.iter().copied()))
        .collect();
    if pool_objects.is_empty() {
        bail!("{file}: no dynamic bodies to take paths from");
    }
    let mut rng = Rng(WorldRng::new(0x5EED, Stream::Scene));
    let mut shards = (0..opts.shards)
        .map(|i| {
            Ok(Shard::new(
                ShardSpec::new(i, opts.shards)?,
                format!("bench-{i}"),
            ))
        })
        .collect::<Result<Vec<Shard>>>()?;
    let count = opts.shards;
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut vertices = 0usize;
    let mut radii = Vec::new();
    let mut ingest = Vec::with_capacity(worlds as usize);
    let job_id: std::sync::Arc<str> = std::sync::Arc::from("synthetic");
    // With the motion, the store's own work on each world, timed apart from the bench's:
    // assembly, indexing from the stored motion (every core, as a store indexes the worlds that
    // reach it together), insert.
    let mut store_s = 0.0;
    let scene = mwb_store::index::JobScene::from(rest);
    let mut checks = SentChecks::every(mwb_store::DEFAULT_VERIFY_INDEX_EVERY);
    let mut batch_start = 0u32;
    while batch_start < worlds {
        let batch_end = worlds.min(batch_start.saturating_add(INGEST_BATCH));
        let from_store = if opts.with_motion {
            let t = Instant::now();
            let mut stored = (batch_start..batch_end)
                .map(|i| store_world(&mut assembler, &messages[i as usize % pool.len()], i))
                .collect::<Result<Vec<_>>>()?;
            let indexed = index_stored(
                stored
                    .iter_mut()
                    .map(|(w, sent)| (&**w, sent.take(), scene.clone()))
                    .collect(),
                opts.path_tolerance_m,
                threads,
                &mut checks,
            )
            .into_iter()
            .zip(batch_start..)
            .map(|((r, sent), i)| {
                if let SentIndex::Refused(why) = &sent {
                    bail!("world {i}: its sent index was refused: {why}");
                }
                if sent == (SentIndex::Checked { same: false }) {
                    bail!("world {i}: its sent index differs from the store's own");
                }
                r.map_err(|e| anyhow::anyhow!("world {i}: {e}"))
            })
            .collect::<Result<Vec<IndexedWorld>>>()?;
            store_s += t.elapsed().as_secs_f64();
            indexed
        } else {
            Vec::new()
        };
        for i in batch_start..batch_end {
            let mut objs = Vec::with_capacity(objects as usize);
            let mut metrics = Vec::with_capacity(objects as usize);
            let own = from_store.get((i - batch_start) as usize);
            for k in 0..objects as usize {
                let (obj, m) = match own {
                    Some(w) => (&w.objects[k], w.metrics[k]),
                    None => pool_objects[rng.index(pool_objects.len())],
                };
                let d = [
                    rng.range(-opts.spread_m, opts.spread_m),
                    0.0,
                    rng.range(-opts.spread_m, opts.spread_m),
                ];
                let o = shifted(obj, pool[0].frame_dt, d)?;
                vertices += o.len();
                radii.push(o.radius * 1000.0);
                objs.push(o);
                metrics.push(m);
            }
            let w = IndexedWorld {
                world: i,
                job_id: job_id.clone(),
                seed: u64::from(i),
                frames: 0,
                frame_dt: pool[0].frame_dt,
                rested: true,
                bodies: std::sync::Arc::from(Vec::new()),
                objects: objs.into_boxed_slice(),
                metrics: metrics.into_boxed_slice(),
                measured: None,
                refined: None,
            };
            // World i is shard (i mod N)'s, as stores number their worlds.
            let shard = &mut shards[(i % count) as usize];
            let t = Instant::now();
            shard.insert(w);
            ingest.push(t.elapsed().as_secs_f64() * 1e3);
        }
        batch_start = batch_end;
    }
    let ingest_s = ingest.iter().sum::<f64>() / 1e3;
    let ingest_mean_us = ingest_s * 1e6 / ingest.len().max(1) as f64;
    let ingest_max_ms = ingest.iter().copied().fold(0.0, f64::max);
    let ingest_worlds_per_s = if ingest_s > 0.0 {
        ingest.len() as f64 / ingest_s
    } else {
        f64::NAN
    };
    let ingest_pauses_over_10ms = ingest.iter().filter(|ms| **ms > 10.0).count();
    // Brute force's own copy, allocated in one pass after the stores' (so neither gets a
    // tidier memory layout than the other).
    let plain: Vec<PlainWorld> = if opts.brute {
        (0..worlds)
            .map(|g| {
                world_of(&shards, g).map_or_else(Vec::new, |w| {
                    w.objects.iter().map(|o| (o.polyline(), o.radius)).collect()
                })
            })
            .collect()
    } else {
        Vec::new()
    };
    let mut seq = 0u64;
    let (mut add, mut remove, mut index, mut brute_ms, mut rank, mut kept) =
        (vec![], vec![], vec![], vec![], vec![], vec![]);
    let mut per_world = vec![];
    let key = RankKey::Metric {
        metric: Metric::AngularTravel,
        objects: (0..objects).collect(),
        aggregate: Aggregate::Sum,
    };
    for round in 0..constraints {
        let c = random_constraint(&mut rng, round as u64 + 1, worlds, &shards)?;
        // Index, world by world and brute force on the same threads, same constraint; every
        // shard at once, their answers merged as node-query merges them.
        let t = Instant::now();
        let by_index = on_every_shard(&shards, |s| s.evaluate_all(&c));
        index.push(t.elapsed().as_secs_f64() * 1e3);
        let t = Instant::now();
        let each = on_every_shard(&shards, |s| s.evaluate_each(&c));
        per_world.push(t.elapsed().as_secs_f64() * 1e3);
        if opts.brute {
            let t = Instant::now();
            let by_brute = brute(&plain, &c, threads);
            brute_ms.push(t.elapsed().as_secs_f64() * 1e3);
            if by_index != by_brute {
                bail!(
                    "constraint {round}: the index kept {} worlds, brute force {} (not the \
                     same worlds)",
                    by_index.len(),
                    by_brute.len()
                );
            }
        }
        if by_index != each {
            bail!(
                "constraint {round}: the index kept {} worlds, world by world {} (not the same \
                 worlds)",
                by_index.len(),
                each.len()
            );
        }
        kept.push(by_index.len() as f64 / f64::from(worlds));
        // Add it to the session (evaluation + AND), keeping at most four live.
        seq += 1;
        let t = Instant::now();
        send(
            &mut shards,
            seq,
            Request::Add {
                constraint: Box::new(c),
            },
        )?;
        add.push(t.elapsed().as_secs_f64() * 1e3);
        if round >= 3 {
            // Remove one of the older ones (not the newest): AND of the rest only.
            let id = ConstraintId((round - 3) as u64 + 1);
            seq += 1;
            let t = Instant::now();
            send(&mut shards, seq, Request::Remove { id })?;
            remove.push(t.elapsed().as_secs_f64() * 1e3);
        }
        let t = Instant::now();
        send(
            &mut shards,
            seq,
            Request::Rank {
                key: key.clone(),
                order: Order::Descending,
                k: 10,
                all_worlds: true,
                plausible_only: false,
            },
        )?;
        rank.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let index_p50 = percentile(&mut index, 0.5);
    let per_world_p50 = percentile(&mut per_world, 0.5);
    let brute_p50 = opts.brute.then(|| percentile(&mut brute_ms, 0.5));
    let per_world = |bytes: usize| bytes as f64 / f64::from(worlds);
    let memory = per_world(shards.iter().map(Shard::heap_bytes).sum());
    let parts = shards
        .iter()
        .map(Shard::heap_bytes_by_part)
        .fold(ShardBytes::default(), |a, b| ShardBytes {
            paths: a.paths + b.paths,
            hierarchies: a.hierarchies + b.hierarchies,
            metrics: a.metrics + b.metrics,
            records: a.records + b.records,
            bitsets: a.bitsets + b.bitsets,
        });
    Ok(QueryBench {
        scene: file,
        path_tolerance_mm: opts.path_tolerance_m * 1e3,
        spread_m: opts.spread_m,
        worlds,
        objects,
        shards: count,
        threads,
        constraints,
        kept_fraction_p50: percentile(&mut kept, 0.5),
        add_p50_ms: percentile(&mut add, 0.5),
        add_p95_ms: percentile(&mut add, 0.95),
        remove_p50_ms: percentile(&mut remove, 0.5),
        index_p50_ms: index_p50,
        per_world_p50_ms: per_world_p50,
        brute_p50_ms: brute_p50,
        obb_speedup: brute_p50.map(|b| b / index_p50.max(1e-9)),
        per_world_speedup: brute_p50.map(|b| b / per_world_p50.max(1e-9)),
        rank_p50_ms: percentile(&mut rank, 0.5),
        ingest_mean_us,
        ingest_max_ms,
        ingest_worlds_per_s,
        ingest_pauses_over_10ms,
        memory_bytes_per_world: memory,
        paths_bytes_per_world: per_world(parts.paths),
        hierarchy_bytes_per_world: per_world(parts.hierarchies),
        metrics_bytes_per_world: per_world(parts.metrics),
        records_bytes_per_world: per_world(parts.records),
        bitsets_bytes_per_world: per_world(parts.bitsets),
        payload_bytes_per_world: motion.payload_per_object * f64::from(objects),
        motion_bytes_per_world: motion.encoded_per_object * f64::from(objects),
        total_bytes_per_world: motion.encoded_per_object * f64::from(objects) + memory,
        held_overhead_bytes_per_world: motion.held_overhead_per_world,
        held_total_bytes_per_world: motion.payload_per_object * f64::from(objects)
            + motion.held_overhead_per_world
            + memory,
        stored_worlds: opts.with_motion.then(|| assembler.world_count()),
        store_ingest_worlds_per_s: opts
            .with_motion
            .then(|| f64::from(worlds) / (store_s + ingest_s).max(1e-9)),
        stored_held_bytes_per_world: opts
            .with_motion
            .then(|| assembler.memory_bytes() as f64 / f64::from(worlds)),
        rss_bytes: rss_bytes(),
        vertices_per_object: vertices as f64 / (f64::from(worlds) * f64::from(objects)),
        path_radius_mm_p50: percentile(&mut radii, 0.5),
    })
}

/// `f` run on every shard at once (one thread each; each shard uses its own threads inside),
/// their world sets merged (global indices never collide).
fn on_every_shard(shards: &[Shard], f: impl Fn(&Shard) -> WorldSet + Sync) -> WorldSet {
    if let [one] = shards {
        return f(one);
    }
    std::thread::scope(|s| {
        let handles: Vec<_> = shards.iter().map(|sh| s.spawn(|| f(sh))).collect();
        let mut out = WorldSet::new();
        for h in handles {
            out.or_assign(&h.join().unwrap_or_else(|e| std::panic::resume_unwind(e)));
        }
        out
    })
}

/// One request of the bench's session (edit number `seq`) to every shard at once, as
/// node-query sends it; an error if any shard refused it (the bench reads no reply).
fn send(shards: &mut [Shard], seq: u64, request: Request) -> Result<()> {
    let edit = request.is_edit();
    let ask = |shard: &mut Shard| match shard.handle(&ShardRequest {
        session: "bench".into(),
        seq: edit.then_some(seq),
        request: request.clone(),
    }) {
        ShardReply::Ok {
            reply: Reply::Error { message },
            ..
        } => bail!("{message}"),
        ShardReply::Ok { .. } => Ok(()),
        ShardReply::OutOfSync { edits } => bail!("bench session out of sync at {edits}"),
    };
    let replies: Vec<Result<()>> = if let [one] = shards {
        vec![ask(one)]
    } else {
        std::thread::scope(|s| {
            let handles: Vec<_> = shards.iter_mut().map(|sh| s.spawn(|| ask(sh))).collect();
            handles
                .into_iter()
                .map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e)))
                .collect()
        })
    };
    replies.into_iter().collect()
}

/// The process's resident set (`VmRSS`), bytes; 0 where /proc is not there to ask.
fn rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmRSS:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small run end to end: it fails if the index, the world-by-world test and brute force keep
    /// different worlds for any constraint, and reports sane figures.
    #[test]
    fn a_small_bench_agrees_with_brute_force() {
        let b = bench_query(&QueryBenchOptions {
            worlds: 300,
            objects: 4,
            constraints: 12,
            ..QueryBenchOptions::default()
        })
        .unwrap_or_else(|e| panic!("{e:#}"));
        assert_eq!((b.worlds, b.objects, b.constraints), (300, 4, 12));
        assert!((0.0..=1.0).contains(&b.kept_fraction_p50), "{b:?}");
        assert!(b.memory_bytes_per_world > 100.0, "{b:?}");
        assert!(b.payload_bytes_per_world > 0.0, "{b:?}");
        assert_eq!(
            b.total_bytes_per_world,
            b.motion_bytes_per_world + b.memory_bytes_per_world
        );
        assert!(
            b.vertices_per_object >= 2.0 && b.ingest_max_ms >= 0.0 && b.ingest_worlds_per_s > 0.0,
            "{b:?}"
        );
        assert!(
            (b.ingest_worlds_per_s * b.ingest_mean_us / 1e6 - 1.0).abs() < 1e-9,
            "{b:?}"
        );
        assert!(
            b.obb_speedup.is_some_and(|x| x > 0.0 && x.is_finite()),
            "{b:?}"
        );
        // The held total adds to the payloads what the worlds' structs and blocks take.
        assert!(b.held_overhead_bytes_per_world > 0.0, "{b:?}");
        assert_eq!(
            b.held_total_bytes_per_world,
            b.payload_bytes_per_world + b.held_overhead_bytes_per_world + b.memory_bytes_per_world
        );
        assert_eq!(
            (b.stored_worlds, b.stored_held_bytes_per_world),
            (None, None)
        );
    }

    /// With the motion, every world is stored by the store's own assembly, each counted as
    /// held: more than its payloads, as the sampled worlds' held bytes say; a scene with fewer
    /// bodies than `objects` is refused, naming both.
    #[test]
    fn with_motion_the_assembly_stores_every_world() {
        let b = bench_query(&QueryBenchOptions {
            scene: "tumble".into(),
            worlds: 100,
            objects: 5,
            constraints: 4,
            brute: false,
            with_motion: true,
            ..QueryBenchOptions::default()
        })
        .unwrap_or_else(|e| panic!("{e:#}"));
        assert_eq!(b.stored_worlds, Some(100));
        let held = b.stored_held_bytes_per_world.unwrap_or(0.0);
        assert!(held > b.payload_bytes_per_world, "{b:?}");
        // Each world is one of the 24 sampled ones: its mean is theirs, within the rounding of
        // 100 worlds over 24 and a few bytes of seed and counter.
        let sampled = b.payload_bytes_per_world + b.held_overhead_bytes_per_world;
        assert!(
            (held - sampled).abs() < 0.2 * sampled,
            "{held} against {sampled}"
        );
        let refused = bench_query(&QueryBenchOptions {
            worlds: 10,
            objects: 10,
            constraints: 1,
            with_motion: true,
            ..QueryBenchOptions::default()
        });
        let message = format!("{:#}", refused.err().unwrap_or_else(|| anyhow::anyhow!("")));
        assert!(
            message.contains("has 5 bodies, --objects is 10"),
            "{message}"
        );
    }

    /// Split over three shards, without brute force: the merged answers still equal the
    /// world-by-world test's (the run fails otherwise), every world is held once, and brute
    /// force's fields are absent.
    #[test]
    fn shards_and_no_brute_agree_and_count_every_world_once() {
        let one = bench_query(&QueryBenchOptions {
            worlds: 300,
            objects: 4,
            constraints: 6,
            brute: false,
            ..QueryBenchOptions::default()
        })
        .unwrap_or_else(|e| panic!("{e:#}"));
        let three = bench_query(&QueryBenchOptions {
            worlds: 300,
            objects: 4,
            constraints: 6,
            shards: 3,
            brute: false,
            ..QueryBenchOptions::default()
        })
        .unwrap_or_else(|e| panic!("{e:#}"));
        assert_eq!(three.shards, 3);
        assert_eq!(three.brute_p50_ms, None);
        assert_eq!(three.obb_speedup, None);
        // The same worlds, the same paths: the same bytes of paths and metrics.
        assert_eq!(one.paths_bytes_per_world, three.paths_bytes_per_world);
        assert_eq!(one.metrics_bytes_per_world, three.metrics_bytes_per_world);
        assert_eq!(one.kept_fraction_p50, three.kept_fraction_p50);
    }
}
