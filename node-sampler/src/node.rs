//! The sampler node (§4.2 "opportunistic computing"): joins at any time, learns open jobs from
//! the bus (announcements, and a query to the stores for jobs announced before it joined),
//! runs worlds on worker threads and streams them out. A sampler that dies loses only the
//! world it was computing; the store discards that partial world when its liveliness token
//! goes away.

use crate::world::{PayloadEncoding, RunError, RunOptions, Segment, provenance, run_world};
use mwb_core::keys::{Keys, role};
use mwb_core::rng::world_seed;
use mwb_core::scene::SceneTemplate;
use mwb_proto::v1::{
    Encoding, Job, JobKind, JobState, LowResPath, Message, MotionSegment, NodeStats, Quality,
    WorldDone,
};
use std::collections::HashMap;
use std::ops::ControlFlow;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::mpsc;
use tracing::{debug, info, warn};
use zenoh::Session;
use zenoh::qos::CongestionControl;
use zenoh::sample::SampleKind;

/// Sampler settings.
#[derive(Debug, Clone)]
pub struct SamplerConfig {
    pub space: String,
    /// Worker threads (one world each at a time).
    pub workers: usize,
    /// Node id; defaults to the session's zenoh id. Two samplers sharing a session (as in
    /// `mwb demo`) need distinct ids.
    pub node_id: Option<String>,
    /// How often to re-ask the stores for open jobs and their states.
    pub refresh: Duration,
    /// Capacity of the outgoing message queue (back-pressure on the workers).
    pub queue: usize,
}

impl Default for SamplerConfig {
    fn default() -> Self {
        Self {
            space: "default".into(),
            workers: std::thread::available_parallelism().map_or(1, |n| n.get()),
            node_id: None,
            refresh: Duration::from_secs(2),
            queue: 256,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SamplerError {
    #[error(transparent)]
    Key(#[from] mwb_core::keys::BadIdentifier),
    #[error("zenoh: {0}")]
    Zenoh(String),
}

fn zerr(e: impl std::fmt::Display) -> SamplerError {
    SamplerError::Zenoh(e.to_string())
}

/// A job as the sampler sees it.
struct JobEntry {
    job: Job,
    template: Option<Arc<SceneTemplate>>,
    closed: bool,
    done: u32,
    in_flight: u32,
}

/// What a worker needs to run one world of a job.
struct Picked {
    job_id: String,
    template: Arc<SceneTemplate>,
    scene_hash: u64,
    quality: mwb_codec::Quality,
    encoding: PayloadEncoding,
}

/// The job's codec preset; unspecified (or unknown to this version) is standard.
fn codec_quality(q: Quality) -> mwb_codec::Quality {
    match q {
        Quality::Draft => mwb_codec::Quality::Draft,
        Quality::Final => mwb_codec::Quality::Final,
        Quality::Standard | Quality::Unspecified => mwb_codec::Quality::Standard,
    }
}

/// The wire summary of world `(job, node, counter)` (CPU time, provenance and scene hash are
/// the caller's to add).
pub fn world_done(
    job_id: &str,
    node: &str,
    counter: u64,
    summary: &crate::WorldSummary,
) -> WorldDone {
    WorldDone {
        job_id: job_id.to_owned(),
        node_id: node.to_owned(),
        world_counter: counter,
        seed: summary.seed,
        frame_count: summary.frame_count,
        segment_count: summary.segment_count,
        frame_dt: summary.frame_dt,
        rested: summary.rested,
        impacts: summary.impacts.clone(),
        rest_time_s: summary.rest_time_s.clone(),
        body_rested: summary.body_rested.clone(),
        perturbations: summary.perturbations,
        sim_steps: summary.steps,
        ..Default::default()
    }
}

/// The wire form of a recorded segment of world `(job, node, counter)`: the codec payload
/// (`SPLINE_V1`) with its CRC and, beside it, the low-resolution paths.
pub fn segment_message(
    job_id: &str,
    node: &str,
    counter: u64,
    seed: u64,
    seg: Segment,
) -> MotionSegment {
    MotionSegment {
        job_id: job_id.to_owned(),
        node_id: node.to_owned(),
        world_counter: counter,
        seed,
        seq: seg.seq,
        first_frame: seg.first_frame,
        frame_count: seg.frame_count,
        body_count: seg.body_count,
        encoding: match seg.encoding {
            PayloadEncoding::Spline => Encoding::SplineV1,
            PayloadEncoding::QuantisedFrames => Encoding::QuantisedFramesV1,
        } as i32,
        crc32: crc32fast::hash(&seg.payload),
        lowres: Some(lowres_message(&seg.lowres, mwb_codec::DEFAULT_LOWRES_HZ)),
        payload: seg.payload,
    }
}

/// A segment's low-resolution paths on the wire: the vertex frames once (they are the same for
/// every body of a segment), then every body's vertices.
fn lowres_message(paths: &[mwb_codec::LowResPath], hz: f64) -> LowResPath {
    LowResPath {
        hz,
        frames: paths.first().map(|p| p.frames.clone()).unwrap_or_default(),
        xyz: paths
            .iter()
            .flat_map(|p| p.positions.iter().flatten().copied())
            .collect(),
        // Rounded up, so the bound stays a bound in f32.
        max_deviation: paths
            .iter()
            .map(|p| {
                let d = p.max_deviation as f32;
                if f64::from(d) < p.max_deviation {
                    d.next_up()
                } else {
                    d
                }
            })
            .collect(),
    }
}

#[derive(Default)]
struct Board {
    jobs: HashMap<String, JobEntry>,
}

impl Board {
    /// The job a free worker should take: highest priority, then refinements, then the job
    /// with the fewest worlds still missing ("refinement and small jobs first"), then oldest.
    fn pick(&mut self) -> Option<Picked> {
        let best = self
            .jobs
            .iter()
            .filter(|(_, e)| {
                // Reverse jobs belong to reverse nodes (node-reverse).
                e.job.kind() != JobKind::Reverse
                    && !e.closed
                    && e.template.is_some()
                    && e.done + e.in_flight < e.job.target_worlds
            })
            .min_by_key(|(id, e)| {
                (
                    -i64::from(e.job.priority),
                    e.job.kind() != JobKind::Refine,
                    e.job.target_worlds.saturating_sub(e.done),
                    e.job.created_unix_ms,
                    (*id).clone(),
                )
            })
            .map(|(id, _)| id.clone())?;
        let e = self.jobs.get_mut(&best)?;
        e.in_flight += 1;
        Some(Picked {
            scene_hash: e.job.scene.as_ref().map_or(0, |s| s.content_hash),
            template: e.template.clone()?,
            quality: codec_quality(e.job.quality()),
            encoding: match e.job.encoding() {
                Encoding::QuantisedFramesV1 => PayloadEncoding::QuantisedFrames,
                Encoding::SplineV1 | Encoding::Unspecified => PayloadEncoding::Spline,
            },
            job_id: best,
        })
    }

    fn is_open(&self, job: &str) -> bool {
        self.jobs.get(job).is_some_and(|e| !e.closed)
    }

    fn upsert_job(&mut self, job: Job) {
        let id = job.id.clone();
        if let Some(e) = self.jobs.get(&id)
            && e.job.revision >= job.revision
        {
            return;
        }
        let template = job.scene.as_ref().and_then(|s| {
            match SceneTemplate::parse(&s.toml, &format!("job {id} scene")) {
                Ok(t) => Some(Arc::new(t)),
                Err(e) => {
                    warn!(job = %id, error = %e, "job scene does not validate; ignoring the job");
                    None
                }
            }
        });
        let cancelled = job.cancelled;
        let entry = self.jobs.entry(id).or_insert_with(|| JobEntry {
            job: job.clone(),
            template: None,
            closed: false,
            done: 0,
            in_flight: 0,
        });
        entry.job = job;
        entry.template = template;
        entry.closed |= cancelled;
    }

    fn apply_state(&mut self, st: &JobState) {
        if let Some(e) = self.jobs.get_mut(&st.job_id) {
            e.done = e.done.max(st.worlds_done);
            e.closed |= st.closed;
        }
    }
}

struct Shared {
    board: Mutex<Board>,
    wake: Condvar,
    stop: AtomicBool,
    counter: AtomicU64,
    worlds: AtomicU64,
    steps: AtomicU64,
    bytes: AtomicU64,
    malformed: AtomicU64,
}

impl Shared {
    fn lock(&self) -> std::sync::MutexGuard<'_, Board> {
        // A worker that panicked mid-world poisons nothing we rely on: keep going.
        self.board.lock().unwrap_or_else(|p| p.into_inner())
    }
}

enum Outgoing {
    Put { key: String, bytes: Vec<u8> },
}

/// A running sampler. Dropping it does not stop it; call [`SamplerHandle::stop`].
pub struct SamplerHandle {
    shared: Arc<Shared>,
    node_id: String,
    tasks: Vec<tokio::task::JoinHandle<()>>,
    workers: Vec<std::thread::JoinHandle<()>>,
}

impl SamplerHandle {
    pub fn node_id(&self) -> &str {
        &self.node_id
    }
    /// Worlds this node has finished and published.
    pub fn worlds(&self) -> u64 {
        self.shared.worlds.load(Ordering::Relaxed)
    }
    /// Simulation steps this node has computed (finished worlds only).
    pub fn steps(&self) -> u64 {
        self.shared.steps.load(Ordering::Relaxed)
    }
    /// Stops the workers after their current step and the bus tasks.
    pub async fn stop(self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        self.shared.wake.notify_all();
        for w in self.workers {
            let _ = tokio::task::spawn_blocking(move || w.join()).await;
        }
        for t in self.tasks {
            t.abort();
        }
    }
}

/// Starts a sampler node on `session` (in the current tokio runtime).
pub async fn run_sampler(
    session: Session,
    cfg: SamplerConfig,
) -> Result<SamplerHandle, SamplerError> {
    let keys = Keys::new(&cfg.space)?;
    let node_id = cfg
        .node_id
        .clone()
        .unwrap_or_else(|| session.zid().to_string());
    mwb_core::keys::check_identifier("node id", &node_id)?;
    let shared = Arc::new(Shared {
        board: Mutex::new(Board::default()),
        wake: Condvar::new(),
        stop: AtomicBool::new(false),
        counter: AtomicU64::new(0),
        worlds: AtomicU64::new(0),
        steps: AtomicU64::new(0),
        bytes: AtomicU64::new(0),
        malformed: AtomicU64::new(0),
    });
    let token = session
        .liveliness()
        .declare_token(keys.alive(role::SAMPLER, &node_id))
        .await
        .map_err(zerr)?;
    let jobs_sub = session
        .declare_subscriber(keys.jobs())
        .await
        .map_err(zerr)?;
    let states_sub = session
        .declare_subscriber(keys.job_states())
        .await
        .map_err(zerr)?;
    let (tx, mut rx) = mpsc::channel::<Outgoing>(cfg.queue.max(1));
    let mut tasks = Vec::new();

    // Publisher: everything that must arrive is sent with blocking congestion control
    // (STACK-NOTES: the default Drop loses puts under bursts).
    {
        let session = session.clone();
        tasks.push(tokio::spawn(async move {
            while let Some(Outgoing::Put { key, bytes }) = rx.recv().await {
                if let Err(e) = session
                    .put(&key, bytes)
                    .congestion_control(CongestionControl::Block)
                    .await
                {
                    warn!(%key, error = %e, "put failed");
                }
            }
        }));
    }
    // Job announcements.
    {
        let shared = shared.clone();
        tasks.push(tokio::spawn(async move {
            while let Ok(sample) = jobs_sub.recv_async().await {
                if sample.kind() != SampleKind::Put {
                    continue;
                }
                match Job::decode(sample.payload().to_bytes().as_ref()) {
                    Ok(job) => {
                        debug!(job = %job.id, "job announced");
                        shared.lock().upsert_job(job);
                        shared.wake.notify_all();
                    }
                    Err(_) => {
                        shared.malformed.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
        }));
    }
    // Job states (closure).
    {
        let shared = shared.clone();
        tasks.push(tokio::spawn(async move {
            while let Ok(sample) = states_sub.recv_async().await {
                match JobState::decode(sample.payload().to_bytes().as_ref()) {
                    Ok(st) => shared.lock().apply_state(&st),
                    Err(_) => {
                        shared.malformed.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
        }));
    }
    // Late joining: ask the stores for open jobs and states, now and periodically.
    {
        let shared = shared.clone();
        let session = session.clone();
        let keys = keys.clone();
        let every = cfg.refresh;
        tasks.push(tokio::spawn(async move {
            loop {
                refresh_jobs(&session, &keys, &shared).await;
                shared.wake.notify_all();
                tokio::time::sleep(every).await;
            }
        }));
    }
    // Stats.
    {
        let shared = shared.clone();
        let tx = tx.clone();
        let key = keys.stats(role::SAMPLER, &node_id);
        let node = node_id.clone();
        let workers = cfg.workers;
        tasks.push(tokio::spawn(async move {
            let start = Instant::now();
            let mut revision = 0u64;
            let mut last = (Instant::now(), 0u64);
            loop {
                tokio::time::sleep(Duration::from_secs(1)).await;
                revision += 1;
                let worlds = shared.worlds.load(Ordering::Relaxed);
                let now = Instant::now();
                let rate = (worlds - last.1) as f64 / (now - last.0).as_secs_f64().max(1e-3);
                last = (now, worlds);
                let stats = NodeStats {
                    node_id: node.clone(),
                    role: role::SAMPLER.into(),
                    revision,
                    uptime_s: start.elapsed().as_secs_f64(),
                    worlds,
                    worlds_per_s: rate,
                    sim_steps: shared.steps.load(Ordering::Relaxed),
                    bytes: shared.bytes.load(Ordering::Relaxed),
                    malformed: shared.malformed.load(Ordering::Relaxed),
                    workers: workers as u32,
                    pid: std::process::id(),
                    hostname: hostname(),
                    ..Default::default()
                };
                if tx
                    .send(Outgoing::Put {
                        key: key.clone(),
                        bytes: stats.encode_to_vec(),
                    })
                    .await
                    .is_err()
                {
                    break;
                }
            }
        }));
    }
    // Keep the liveliness token alive as long as the node runs.
    tasks.push(tokio::spawn(async move {
        let _token = token;
        std::future::pending::<()>().await;
    }));

    let mut workers = Vec::new();
    for w in 0..cfg.workers.max(1) {
        let shared = shared.clone();
        let tx = tx.clone();
        let keys = keys.clone();
        let node = node_id.clone();
        workers.push(
            std::thread::Builder::new()
                .name(format!("mwb-sampler-{w}"))
                .spawn(move || worker(&shared, &tx, &keys, &node))
                .map_err(zerr)?,
        );
    }
    info!(node = %node_id, workers = cfg.workers, space = %cfg.space, "sampler started");
    Ok(SamplerHandle {
        shared,
        node_id,
        tasks,
        workers,
    })
}

async fn refresh_jobs(session: &Session, keys: &Keys, shared: &Shared) {
    let timeout = Duration::from_secs(2);
    if let Ok(replies) = session.get(keys.jobs()).timeout(timeout).await {
        while let Ok(reply) = replies.recv_async().await {
            if let Ok(sample) = reply.result() {
                match Job::decode(sample.payload().to_bytes().as_ref()) {
                    Ok(job) => shared.lock().upsert_job(job),
                    Err(_) => {
                        shared.malformed.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
        }
    }
    if let Ok(replies) = session.get(keys.job_states()).timeout(timeout).await {
        while let Ok(reply) = replies.recv_async().await {
            if let Ok(sample) = reply.result() {
                match JobState::decode(sample.payload().to_bytes().as_ref()) {
                    Ok(st) => shared.lock().apply_state(&st),
                    Err(_) => {
                        shared.malformed.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
        }
    }
}

fn worker(shared: &Shared, tx: &mpsc::Sender<Outgoing>, keys: &Keys, node: &str) {
    let provenance = provenance();
    while !shared.stop.load(Ordering::SeqCst) {
        let picked = {
            let mut board = shared.lock();
            match board.pick() {
                Some(p) => Some(p),
                None => {
                    let _ = shared
                        .wake
                        .wait_timeout(board, Duration::from_millis(200))
                        .map_err(|_| ());
                    None
                }
            }
        };
        let Some(Picked {
            job_id,
            template,
            scene_hash,
            quality,
            encoding,
        }) = picked
        else {
            continue;
        };
        let counter = shared.counter.fetch_add(1, Ordering::Relaxed);
        let seed = world_seed(&job_id, node, counter);
        let started = cpu_time();
        let mut emit = |seg: Segment| -> ControlFlow<()> {
            if shared.stop.load(Ordering::SeqCst) || !shared.lock().is_open(&job_id) {
                return ControlFlow::Break(());
            }
            let key = keys.segment(&job_id, node, counter, seg.seq);
            let msg = segment_message(&job_id, node, counter, seed, seg);
            let out = Outgoing::Put {
                key,
                bytes: msg.encode_to_vec(),
            };
            match tx.blocking_send(out) {
                Ok(()) => ControlFlow::Continue(()),
                Err(_) => ControlFlow::Break(()),
            }
        };
        let opts = RunOptions {
            quality,
            encoding,
            ..RunOptions::default()
        };
        let result = run_world(&template, seed, opts, &mut emit);
        {
            let mut board = shared.lock();
            if let Some(e) = board.jobs.get_mut(&job_id) {
                e.in_flight = e.in_flight.saturating_sub(1);
            }
        }
        match result {
            Ok(summary) => {
                let done = WorldDone {
                    cpu_seconds: cpu_time() - started,
                    provenance: provenance.clone(),
                    scene_hash,
                    ..world_done(&job_id, node, counter, &summary)
                };
                let out = Outgoing::Put {
                    key: keys.done(&job_id, node, counter),
                    bytes: done.encode_to_vec(),
                };
                if tx.blocking_send(out).is_err() {
                    return;
                }
                shared.worlds.fetch_add(1, Ordering::Relaxed);
                shared.steps.fetch_add(summary.steps, Ordering::Relaxed);
                shared
                    .bytes
                    .fetch_add(summary.payload_bytes, Ordering::Relaxed);
            }
            Err(RunError::Stopped) => debug!(job = %job_id, counter, "world abandoned: job closed"),
            Err(e) => {
                warn!(job = %job_id, error = %e, "world failed; closing the job locally");
                if let Some(entry) = shared.lock().jobs.get_mut(&job_id) {
                    entry.closed = true;
                }
            }
        }
    }
}

/// CPU time of the calling thread, seconds.
pub fn cpu_time() -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes one timespec into the valid pointer we pass.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    if rc == 0 {
        ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
    } else {
        0.0
    }
}

/// This machine's host name, for node statistics (empty where unknown).
fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().to_owned())
        .unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;
    use mwb_proto::v1::Scene;

    fn job(id: &str, target: u32, priority: i32, kind: JobKind, created: u64) -> Job {
        let toml = mwb_core::scene::builtin::TUMBLE.to_owned();
        Job {
            id: id.into(),
            revision: 1,
            kind: kind as i32,
            scene: Some(Scene {
                toml,
                ..Default::default()
            }),
            target_worlds: target,
            priority,
            created_unix_ms: created,
            ..Default::default()
        }
    }

    fn picks(board: &mut Board, n: usize) -> Vec<String> {
        (0..n)
            .filter_map(|_| board.pick())
            .map(|p| p.job_id)
            .collect()
    }

    #[test]
    fn priority_then_refinement_then_small_jobs_first() {
        let mut b = Board::default();
        b.upsert_job(job("big", 1000, 0, JobKind::Sample, 1));
        b.upsert_job(job("small", 3, 0, JobKind::Sample, 2));
        b.upsert_job(job("refine", 500, 0, JobKind::Refine, 3));
        b.upsert_job(job("urgent", 1000, 5, JobKind::Sample, 4));
        // Higher priority first, until its worlds are all in flight.
        if let Some(e) = b.jobs.get_mut("urgent") {
            e.job.target_worlds = 2;
        }
        assert_eq!(picks(&mut b, 2), ["urgent", "urgent"]);
        // Then refinements, then the smallest remaining job, then the big one.
        if let Some(e) = b.jobs.get_mut("refine") {
            e.job.target_worlds = 1;
        }
        assert_eq!(
            picks(&mut b, 5),
            ["refine", "small", "small", "small", "big"]
        );
    }

    #[test]
    fn closed_cancelled_and_invalid_jobs_are_never_picked() {
        let mut b = Board::default();
        b.upsert_job(job("a", 10, 0, JobKind::Sample, 1));
        let mut bad = job("bad", 10, 9, JobKind::Sample, 1);
        if let Some(s) = bad.scene.as_mut() {
            s.toml = "not = [valid".into();
        }
        b.upsert_job(bad);
        b.apply_state(&JobState {
            job_id: "a".into(),
            worlds_done: 10,
            closed: true,
            ..Default::default()
        });
        assert!(b.pick().is_none());
        let mut c = job("c", 10, 0, JobKind::Sample, 1);
        b.upsert_job(c.clone());
        c.revision = 2;
        c.cancelled = true;
        b.upsert_job(c);
        assert!(b.pick().is_none());
    }

    #[test]
    fn reverse_jobs_are_left_to_reverse_nodes() {
        let mut b = Board::default();
        b.upsert_job(job("rev", 10, 9, JobKind::Reverse, 1));
        assert!(b.pick().is_none());
        b.upsert_job(job("a", 1, 0, JobKind::Sample, 2));
        assert_eq!(picks(&mut b, 3), ["a"]);
    }

    #[test]
    fn in_flight_worlds_count_towards_the_target() {
        let mut b = Board::default();
        b.upsert_job(job("a", 2, 0, JobKind::Sample, 1));
        assert_eq!(picks(&mut b, 5).len(), 2);
    }
}
