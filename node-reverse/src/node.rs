//! The reverse node: takes `JOB_KIND_REVERSE` jobs from the bus (and only those), samples
//! backward worlds on worker threads ([`crate::sample`]) and publishes them exactly as a forward
//! sampler does — `MotionSegment`s on `seg/<job>/<node>/<n>/<seq>` (SPLINE_V1 payload, CRC32 over
//! the payload, low-res path beside it), then a `WorldDone` on `done/<job>/<node>/<n>` — so the
//! store assembles, indexes and serves them like any world. Liveliness token
//! `alive/reverse/<node>`, statistics on `stats/reverse/<node>` every second.
//!
//! Joining and leaving follow the sampler (§4.2): open jobs are learned from announcements and
//! from the stores (for jobs announced before the node joined); a node that dies loses only the
//! worlds it was computing. A job's scene is prepared (parsed, chain learned) once, by the first
//! worker that needs it; its `[reverse]` table ([`crate::settings_toml`]) makes the job's worlds
//! mixed (§5.4.4) and/or hinted. `WorldDone` carries each world's §5.3.1 plausibility numbers
//! (`energy_growth`, `angular_speed_growth`).

use crate::sample::{ReverseScene, SampleError, Segment, provenance, sample_world};
use mwb_core::keys::{Keys, role};
use mwb_core::rng::world_seed;
use mwb_proto::v1::{
    Encoding, Job, JobKind, JobState, LowResPath, Message, MotionSegment, NodeStats, Quality,
    WorldDone,
};
use std::collections::HashMap;
use std::ops::ControlFlow;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, OnceLock};
use std::time::{Duration, Instant};
use tokio::sync::mpsc;
use tracing::{debug, info, warn};
use zenoh::Session;
use zenoh::qos::CongestionControl;
use zenoh::sample::SampleKind;

/// A job whose worlds fail this many times in a row (non-finite state, codec refusal) is
/// given up locally: the scene, not the seed, is the problem.
pub const MAX_CONSECUTIVE_FAILURES: u32 = 8;

/// Reverse node settings.
#[derive(Debug, Clone)]
pub struct ReverseConfig {
    /// Browsing space (`mwb/<space>/…`).
    pub space: String,
    /// Worker threads (one world each at a time).
    pub workers: usize,
    /// Node id; defaults to the session's zenoh id. Nodes sharing a session need distinct ids.
    pub node_id: Option<String>,
    /// How often to re-ask the stores for open jobs and their states.
    pub refresh: Duration,
    /// Capacity of the outgoing message queue (back-pressure on the workers).
    pub queue: usize,
}

impl Default for ReverseConfig {
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

/// Why the node could not start.
#[derive(Debug, thiserror::Error)]
pub enum ReverseNodeError {
    /// The space or node id is not a valid key segment.
    #[error(transparent)]
    Key(#[from] mwb_core::keys::BadIdentifier),
    /// zenoh refused a declaration.
    #[error("zenoh: {0}")]
    Zenoh(String),
}

fn zerr(e: impl std::fmt::Display) -> ReverseNodeError {
    ReverseNodeError::Zenoh(e.to_string())
}

/// The job's codec preset; unspecified (or unknown to this version) is standard.
fn codec_quality(q: Quality) -> mwb_codec::Quality {
    match q {
        Quality::Draft => mwb_codec::Quality::Draft,
        Quality::Final => mwb_codec::Quality::Final,
        Quality::Standard | Quality::Unspecified => mwb_codec::Quality::Standard,
    }
}

/// The wire form of a segment of world `(job, node, counter)` (the sampler's
/// `segment_message`, for backward worlds; always `SPLINE_V1`).
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
        encoding: Encoding::SplineV1 as i32,
        crc32: crc32fast::hash(&seg.payload),
        lowres: Some(lowres_message(&seg.lowres, mwb_codec::DEFAULT_LOWRES_HZ)),
        payload: seg.payload,
    }
}

/// A segment's low-resolution paths on the wire, as the sampler sends them: the vertex frames
/// once, then every body's vertices; deviations rounded up so they stay bounds in f32.
fn lowres_message(paths: &[mwb_codec::LowResPath], hz: f64) -> LowResPath {
    LowResPath {
        hz,
        frames: paths.first().map(|p| p.frames.clone()).unwrap_or_default(),
        xyz: paths
            .iter()
            .flat_map(|p| p.positions.iter().flatten().copied())
            .collect(),
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

/// A job's scene, prepared at most once by whichever worker needs it first.
type Prepared = Arc<OnceLock<Result<Arc<ReverseScene>, String>>>;

/// A reverse job as this node sees it.
struct JobEntry {
    job: Job,
    prepared: Prepared,
    closed: bool,
    done: u32,
    in_flight: u32,
    failures: u32,
}

/// What a worker needs to run one world of a job.
struct Picked {
    job_id: String,
    text: Arc<str>,
    prepared: Prepared,
    scene_hash: u64,
    quality: mwb_codec::Quality,
}

/// The open reverse jobs.
#[derive(Default)]
struct Board {
    jobs: HashMap<String, JobEntry>,
}

impl Board {
    /// The job a free worker should take: highest priority, then the fewest worlds missing,
    /// then oldest (the sampler's order, without refinements).
    fn pick(&mut self) -> Option<Picked> {
        let best = self
            .jobs
            .iter()
            .filter(|(_, e)| !e.closed && e.done + e.in_flight < e.job.target_worlds)
            .min_by_key(|(id, e)| {
                (
                    -i64::from(e.job.priority),
                    e.job.target_worlds.saturating_sub(e.done),
                    e.job.created_unix_ms,
                    (*id).clone(),
                )
            })
            .map(|(id, _)| id.clone())?;
        let e = self.jobs.get_mut(&best)?;
        e.in_flight += 1;
        let scene = e.job.scene.as_ref();
        Some(Picked {
            text: Arc::from(scene.map_or("", |s| s.toml.as_str())),
            scene_hash: scene.map_or(0, |s| s.content_hash),
            prepared: e.prepared.clone(),
            quality: codec_quality(e.job.quality()),
            job_id: best,
        })
    }

    fn is_open(&self, job: &str) -> bool {
        self.jobs.get(job).is_some_and(|e| !e.closed)
    }

    /// Takes a job announcement. Anything but a reverse job is someone else's (samplers take
    /// sample and refine jobs) and is not even remembered.
    fn upsert_job(&mut self, job: Job) {
        if job.kind() != JobKind::Reverse {
            return;
        }
        if let Some(e) = self.jobs.get(&job.id)
            && e.job.revision >= job.revision
        {
            return;
        }
        let cancelled = job.cancelled;
        let same_scene = |e: &JobEntry| {
            e.job.scene.as_ref().map(|s| &s.toml) == job.scene.as_ref().map(|s| &s.toml)
        };
        match self.jobs.get_mut(&job.id) {
            Some(e) => {
                if !same_scene(e) {
                    e.prepared = Prepared::default();
                    e.failures = 0;
                }
                e.job = job;
                e.closed |= cancelled;
            }
            None => {
                self.jobs.insert(
                    job.id.clone(),
                    JobEntry {
                        job,
                        prepared: Prepared::default(),
                        closed: cancelled,
                        done: 0,
                        in_flight: 0,
                        failures: 0,
                    },
                );
            }
        }
    }

    fn apply_state(&mut self, st: &JobState) {
        if let Some(e) = self.jobs.get_mut(&st.job_id) {
            e.done = e.done.max(st.worlds_done);
            e.closed |= st.closed;
        }
    }

    /// A world of `job` ended (stored, stopped or failed): it is no longer in flight.
    fn finished(&mut self, job: &str, failed: bool) -> Option<&mut JobEntry> {
        let e = self.jobs.get_mut(job)?;
        e.in_flight = e.in_flight.saturating_sub(1);
        e.failures = if failed { e.failures + 1 } else { 0 };
        Some(e)
    }
}

struct Shared {
    board: Mutex<Board>,
    wake: Condvar,
    stop: AtomicBool,
    counter: AtomicU64,
    worlds: AtomicU64,
    failed: AtomicU64,
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

struct Put {
    key: String,
    bytes: Vec<u8>,
}

/// A running reverse node. Dropping it does not stop it; call [`ReverseHandle::stop`].
pub struct ReverseHandle {
    shared: Arc<Shared>,
    node_id: String,
    tasks: Vec<tokio::task::JoinHandle<()>>,
    workers: Vec<std::thread::JoinHandle<()>>,
}

impl ReverseHandle {
    /// This node's id (the `<node>` of its keys).
    pub fn node_id(&self) -> &str {
        &self.node_id
    }
    /// Worlds this node has finished and published.
    pub fn worlds(&self) -> u64 {
        self.shared.worlds.load(Ordering::Relaxed)
    }
    /// Worlds that failed (non-finite state, codec refusal) and were not published.
    pub fn failed(&self) -> u64 {
        self.shared.failed.load(Ordering::Relaxed)
    }
    /// Stepper steps of the published worlds (backward, and forward for mixed worlds).
    pub fn steps(&self) -> u64 {
        self.shared.steps.load(Ordering::Relaxed)
    }
    /// Bus messages that did not decode, dropped.
    pub fn malformed(&self) -> u64 {
        self.shared.malformed.load(Ordering::Relaxed)
    }
    /// Stops the workers (after their current world) and the bus tasks.
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

/// Starts a reverse node on `session` (in the current tokio runtime).
pub async fn run_reverse(
    session: Session,
    cfg: ReverseConfig,
) -> Result<ReverseHandle, ReverseNodeError> {
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
        failed: AtomicU64::new(0),
        steps: AtomicU64::new(0),
        bytes: AtomicU64::new(0),
        malformed: AtomicU64::new(0),
    });
    let token = session
        .liveliness()
        .declare_token(keys.alive(role::REVERSE, &node_id))
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
    let (tx, mut rx) = mpsc::channel::<Put>(cfg.queue.max(1));
    let mut tasks = Vec::new();

    // Publisher: blocking congestion control for everything (STACK-NOTES: Drop loses puts).
    {
        let session = session.clone();
        tasks.push(tokio::spawn(async move {
            while let Some(Put { key, bytes }) = rx.recv().await {
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
        let key = keys.stats(role::REVERSE, &node_id);
        let node = node_id.clone();
        let workers = cfg.workers.max(1);
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
                    role: role::REVERSE.into(),
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
                let put = Put {
                    key: key.clone(),
                    bytes: stats.encode_to_vec(),
                };
                if tx.send(put).await.is_err() {
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
                .name(format!("mwb-reverse-{w}"))
                .spawn(move || worker(&shared, &tx, &keys, &node))
                .map_err(zerr)?,
        );
    }
    info!(node = %node_id, workers = cfg.workers, space = %cfg.space, "reverse node started");
    Ok(ReverseHandle {
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

fn worker(shared: &Shared, tx: &mpsc::Sender<Put>, keys: &Keys, node: &str) {
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
            text,
            prepared,
            scene_hash,
            quality,
        }) = picked
        else {
            continue;
        };
        let scene = prepared.get_or_init(|| {
            ReverseScene::prepare(&text, &format!("job {job_id} scene"))
                .map(Arc::new)
                .map_err(|e| e.to_string())
        });
        let scene = match scene {
            Ok(s) => s.clone(),
            Err(e) => {
                let mut board = shared.lock();
                if let Some(entry) = board.finished(&job_id, false)
                    && !entry.closed
                {
                    warn!(job = %job_id, error = %e, "reverse scene refused; ignoring the job");
                    entry.closed = true;
                }
                continue;
            }
        };
        let counter = shared.counter.fetch_add(1, Ordering::Relaxed);
        let seed = world_seed(&job_id, node, counter);
        let started = cpu_time();
        let mut emit = |seg: Segment| -> ControlFlow<()> {
            if shared.stop.load(Ordering::SeqCst) || !shared.lock().is_open(&job_id) {
                return ControlFlow::Break(());
            }
            let put = Put {
                key: keys.segment(&job_id, node, counter, seg.seq),
                bytes: segment_message(&job_id, node, counter, seed, seg).encode_to_vec(),
            };
            match tx.blocking_send(put) {
                Ok(()) => ControlFlow::Continue(()),
                Err(_) => ControlFlow::Break(()),
            }
        };
        let result = sample_world(&scene, seed, quality, &mut emit);
        let failed = matches!(
            result,
            Err(SampleError::NonFinite { .. } | SampleError::Codec(_) | SampleError::Scene(_))
        );
        {
            let mut board = shared.lock();
            if let Some(e) = board.finished(&job_id, failed)
                && e.failures >= MAX_CONSECUTIVE_FAILURES
                && !e.closed
            {
                warn!(job = %job_id, failures = e.failures, "every recent world failed; giving up the job locally");
                e.closed = true;
            }
        }
        match result {
            Ok(summary) => {
                debug!(
                    job = %job_id,
                    counter,
                    energy_growth = summary.report.energy_growth,
                    angular_speed_growth = summary.report.angular_speed_growth,
                    "backward world done"
                );
                let done = WorldDone {
                    cpu_seconds: cpu_time() - started,
                    provenance: provenance.clone(),
                    scene_hash,
                    ..summary.world_done(&job_id, node, counter)
                };
                let put = Put {
                    key: keys.done(&job_id, node, counter),
                    bytes: done.encode_to_vec(),
                };
                if tx.blocking_send(put).is_err() {
                    return;
                }
                shared.worlds.fetch_add(1, Ordering::Relaxed);
                shared.steps.fetch_add(summary.steps, Ordering::Relaxed);
                shared
                    .bytes
                    .fetch_add(summary.payload_bytes, Ordering::Relaxed);
            }
            Err(SampleError::Stopped) => {
                debug!(job = %job_id, counter, "world abandoned: job closed");
            }
            Err(e) => {
                shared.failed.fetch_add(1, Ordering::Relaxed);
                warn!(job = %job_id, counter, error = %e, "backward world failed");
            }
        }
    }
}

/// CPU time of the calling thread, seconds (0 where the clock is unavailable).
fn cpu_time() -> f64 {
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

    fn job(id: &str, target: u32, priority: i32, kind: JobKind) -> Job {
        Job {
            id: id.into(),
            revision: 1,
            kind: kind as i32,
            scene: Some(Scene {
                toml: crate::scene::builtin::WORD.to_owned(),
                ..Default::default()
            }),
            target_worlds: target,
            priority,
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
    fn only_reverse_jobs_are_taken() {
        let mut b = Board::default();
        b.upsert_job(job("sample", 5, 9, JobKind::Sample));
        b.upsert_job(job("refine", 5, 9, JobKind::Refine));
        b.upsert_job(job("old", 5, 9, JobKind::Unspecified));
        b.upsert_job(job("rev", 2, 0, JobKind::Reverse));
        assert_eq!(picks(&mut b, 5), ["rev", "rev"]);
    }

    #[test]
    fn priority_then_small_jobs_and_closure() {
        let mut b = Board::default();
        b.upsert_job(job("big", 100, 0, JobKind::Reverse));
        b.upsert_job(job("small", 1, 0, JobKind::Reverse));
        b.upsert_job(job("urgent", 1, 3, JobKind::Reverse));
        assert_eq!(picks(&mut b, 3), ["urgent", "small", "big"]);
        b.apply_state(&JobState {
            job_id: "big".into(),
            closed: true,
            ..Default::default()
        });
        assert!(b.pick().is_none());
        let mut c = job("c", 10, 0, JobKind::Reverse);
        b.upsert_job(c.clone());
        c.revision = 2;
        c.cancelled = true;
        b.upsert_job(c);
        assert!(b.pick().is_none());
    }

    #[test]
    fn failures_in_a_row_are_counted_and_reset_by_a_success() {
        let mut b = Board::default();
        b.upsert_job(job("a", 100, 0, JobKind::Reverse));
        for _ in 0..3 {
            assert!(b.pick().is_some());
            b.finished("a", true);
        }
        assert_eq!(b.jobs["a"].failures, 3);
        assert!(b.pick().is_some());
        b.finished("a", false);
        assert_eq!(b.jobs["a"].failures, 0);
        assert_eq!(b.jobs["a"].in_flight, 0);
    }
}
