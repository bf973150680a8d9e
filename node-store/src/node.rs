//! The store node: subscribes to segments, world summaries and jobs; serves open jobs, job
//! states, worlds by index and statistics as queryables; publishes job states and stats.

use crate::assembly::{Assembler, Outcome};
use crate::browse::{Shard, ShardSpec};
use crate::index::index_world;
use mwb_core::browse::RestThresholds;
use mwb_core::browse::api::{Reply, ShardReply, ShardRequest};
use mwb_core::keys::{Keys, role};
use mwb_proto::v1::{Job, JobState, Message, MotionSegment, NodeStats, World, WorldDone};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use tokio::sync::mpsc;
use tracing::{debug, info, warn};
use zenoh::Session;
use zenoh::key_expr::KeyExpr;
use zenoh::qos::CongestionControl;
use zenoh::sample::SampleKind;

/// Store settings.
#[derive(Debug, Clone)]
pub struct StoreConfig {
    pub space: String,
    /// Complete worlds past this many bytes are refused (and counted in stats).
    pub memory_cap_bytes: u64,
    /// Partial worlds of a departed sampler are discarded this long after it left.
    pub orphan_grace: Duration,
    /// Partial worlds that receive nothing for this long are discarded.
    pub partial_idle: Duration,
    pub node_id: Option<String>,
    /// Which worlds this store keeps when several split them (default: all, `0/1`).
    pub shard: ShardSpec,
    /// Largest distance between an indexed polyline and the decoded path, metres (query boxes
    /// are widened by this plus the codec's e_max).
    pub path_tolerance_m: f64,
}

impl Default for StoreConfig {
    fn default() -> Self {
        Self {
            space: "default".into(),
            memory_cap_bytes: 4 << 30,
            orphan_grace: Duration::from_secs(1),
            partial_idle: Duration::from_secs(120),
            node_id: None,
            shard: ShardSpec::default(),
            path_tolerance_m: crate::index::DEFAULT_PATH_TOLERANCE_M,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error(transparent)]
    Key(#[from] mwb_core::keys::BadIdentifier),
    #[error("zenoh: {0}")]
    Zenoh(String),
}

fn zerr(e: impl std::fmt::Display) -> StoreError {
    StoreError::Zenoh(e.to_string())
}

fn now_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

struct Shared {
    table: Mutex<Assembler>,
    /// The browsing index and sessions (a separate lock: evaluating a constraint over every
    /// world must not stall ingest of segments).
    browse: Mutex<Shard>,
    index_failures: std::sync::atomic::AtomicU64,
    start: Instant,
    node_id: String,
    revision: std::sync::atomic::AtomicU64,
}

impl Shared {
    fn lock(&self) -> std::sync::MutexGuard<'_, Assembler> {
        self.table.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn browse(&self) -> std::sync::MutexGuard<'_, Shard> {
        self.browse.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn stats(&self, worlds_per_s: f64) -> NodeStats {
        let (index_bytes, spec) = {
            let b = self.browse();
            (b.heap_bytes() as u64, b.spec())
        };
        let t = self.lock();
        let c = t.counters;
        NodeStats {
            node_id: self.node_id.clone(),
            role: role::STORE.into(),
            revision: self
                .revision
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed),
            uptime_s: self.start.elapsed().as_secs_f64(),
            worlds: t.world_count() as u64,
            worlds_per_s,
            bytes: t.memory_bytes(),
            memory_bytes: t.memory_bytes(),
            memory_cap_bytes: t.cap_bytes(),
            refused_memory: c.refused_memory,
            crc_failures: c.crc_failures,
            malformed: c.malformed,
            discarded_partial: c.discarded_partial,
            duplicates: c.duplicates,
            pid: std::process::id(),
            hostname: hostname(),
            index_bytes,
            index_failures: self
                .index_failures
                .load(std::sync::atomic::Ordering::Relaxed),
            shard_index: spec.index,
            shard_count: spec.count,
            ..Default::default()
        }
    }
}

/// A running store.
pub struct StoreHandle {
    shared: Arc<Shared>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

impl StoreHandle {
    pub fn node_id(&self) -> &str {
        &self.shared.node_id
    }
    pub fn world_count(&self) -> usize {
        self.shared.lock().world_count()
    }
    pub fn job_state(&self, job: &str) -> Option<JobState> {
        self.shared.lock().job_state(job).cloned()
    }
    pub fn stats(&self) -> NodeStats {
        self.shared.stats(0.0)
    }
    pub fn world(&self, index: u32) -> Option<Arc<crate::StoredWorld>> {
        self.shared.lock().world(index)
    }
    /// Answers a browsing request in-process (what the bus queryable does).
    pub fn browse(&self, req: &ShardRequest) -> ShardReply {
        self.shared.browse().handle(req)
    }
    /// Worlds indexed for browsing.
    pub fn indexed_count(&self) -> u64 {
        self.shared.browse().world_count()
    }
    pub fn stop(self) {
        for t in self.tasks {
            t.abort();
        }
    }
}

enum Incoming {
    Segment(MotionSegment),
    /// A job state from the authority (non-authority shards only).
    State(JobState),
    Done(WorldDone),
    Job(Job),
    Left(String),
    Tick,
}

/// Starts a store node on `session` (in the current tokio runtime).
pub async fn run_store(session: Session, cfg: StoreConfig) -> Result<StoreHandle, StoreError> {
    let keys = Keys::new(&cfg.space)?;
    let node_id = cfg
        .node_id
        .clone()
        .unwrap_or_else(|| session.zid().to_string());
    mwb_core::keys::check_identifier("node id", &node_id)?;
    let shared = Arc::new(Shared {
        table: Mutex::new(Assembler::sharded(cfg.memory_cap_bytes, cfg.shard)),
        browse: Mutex::new(Shard::new(cfg.shard, node_id.clone())),
        index_failures: std::sync::atomic::AtomicU64::new(0),
        start: Instant::now(),
        node_id: node_id.clone(),
        revision: std::sync::atomic::AtomicU64::new(1),
    });
    let token = session
        .liveliness()
        .declare_token(keys.alive(role::STORE, &node_id))
        .await
        .map_err(zerr)?;
    let seg_sub = session
        .declare_subscriber(keys.segments())
        .await
        .map_err(zerr)?;
    let done_sub = session
        .declare_subscriber(keys.dones())
        .await
        .map_err(zerr)?;
    let job_sub = session
        .declare_subscriber(keys.jobs())
        .await
        .map_err(zerr)?;
    // Every producer of worlds (samplers, reverse nodes) holds a token; a node that holds no
    // partial worlds leaving costs nothing.
    let alive_sub = session
        .liveliness()
        .declare_subscriber(keys.alive_all())
        .await
        .map_err(zerr)?;
    // Job-level answers come from one shard only (shard 0, the authority), so that a client
    // never mixes job states of different shards.
    let authority = cfg.shard.is_authority();
    let jobs_q = if authority {
        Some(session.declare_queryable(keys.jobs()).await.map_err(zerr)?)
    } else {
        None
    };
    let states_q = if authority {
        Some(
            session
                .declare_queryable(keys.job_states())
                .await
                .map_err(zerr)?,
        )
    } else {
        None
    };
    let browse_q = session
        .declare_queryable(keys.shard_browse_all(&node_id))
        .await
        .map_err(zerr)?;
    let world_q = session
        .declare_queryable(keys.worlds())
        .await
        .map_err(zerr)?;
    let stats_q = session
        .declare_queryable(keys.store_stats())
        .await
        .map_err(zerr)?;

    // All ingest goes through one bounded queue, so segments and summaries are applied in the
    // order they arrived and a slow store pushes back on the subscribers.
    let (tx, mut rx) = mpsc::channel::<Incoming>(4096);
    let mut tasks = Vec::new();
    let malformed = |shared: &Shared| shared.lock().counters.malformed += 1;

    {
        let tx = tx.clone();
        let shared = shared.clone();
        tasks.push(tokio::spawn(async move {
            while let Ok(s) = seg_sub.recv_async().await {
                match MotionSegment::decode(s.payload().to_bytes().as_ref()) {
                    Ok(m) => {
                        if tx.send(Incoming::Segment(m)).await.is_err() {
                            break;
                        }
                    }
                    Err(_) => malformed(&shared),
                }
            }
        }));
    }
    {
        let tx = tx.clone();
        let shared = shared.clone();
        tasks.push(tokio::spawn(async move {
            while let Ok(s) = done_sub.recv_async().await {
                match WorldDone::decode(s.payload().to_bytes().as_ref()) {
                    Ok(m) => {
                        if tx.send(Incoming::Done(m)).await.is_err() {
                            break;
                        }
                    }
                    Err(_) => malformed(&shared),
                }
            }
        }));
    }
    {
        let tx = tx.clone();
        let shared = shared.clone();
        tasks.push(tokio::spawn(async move {
            while let Ok(s) = job_sub.recv_async().await {
                if s.kind() != SampleKind::Put {
                    continue;
                }
                match Job::decode(s.payload().to_bytes().as_ref()) {
                    Ok(m) if mwb_core::keys::check_identifier("job id", &m.id).is_ok() => {
                        if tx.send(Incoming::Job(m)).await.is_err() {
                            break;
                        }
                    }
                    _ => malformed(&shared),
                }
            }
        }));
    }
    {
        let tx = tx.clone();
        tasks.push(tokio::spawn(async move {
            while let Ok(s) = alive_sub.recv_async().await {
                if s.kind() == SampleKind::Delete
                    && let Some(node) = s.key_expr().as_str().rsplit('/').next()
                    && tx.send(Incoming::Left(node.to_owned())).await.is_err()
                {
                    break;
                }
            }
        }));
    }
    {
        let tx = tx.clone();
        tasks.push(tokio::spawn(async move {
            loop {
                tokio::time::sleep(Duration::from_millis(250)).await;
                if tx.send(Incoming::Tick).await.is_err() {
                    break;
                }
            }
        }));
    }
    // A store that starts while jobs are under way (a restart, or a shard joining late) learns
    // them from the authority; a non-authority shard also follows the authority's job states.
    {
        let tx = tx.clone();
        let session = session.clone();
        let keys = keys.clone();
        let shared = shared.clone();
        tasks.push(tokio::spawn(async move {
            let states_sub = if authority {
                None
            } else {
                session.declare_subscriber(keys.job_states()).await.ok()
            };
            for (key, is_state) in [(keys.jobs(), false), (keys.job_states(), true)] {
                if is_state && authority {
                    continue;
                }
                let Ok(replies) = session.get(key).timeout(Duration::from_secs(2)).await else {
                    continue;
                };
                while let Ok(r) = replies.recv_async().await {
                    let Ok(sample) = r.result() else { continue };
                    let bytes = sample.payload().to_bytes();
                    let msg = if is_state {
                        JobState::decode(bytes.as_ref()).ok().map(Incoming::State)
                    } else {
                        Job::decode(bytes.as_ref())
                            .ok()
                            .filter(|j| mwb_core::keys::check_identifier("job id", &j.id).is_ok())
                            .map(Incoming::Job)
                    };
                    match msg {
                        Some(m) => {
                            if tx.send(m).await.is_err() {
                                return;
                            }
                        }
                        None => malformed(&shared),
                    }
                }
            }
            if let Some(sub) = states_sub {
                while let Ok(s) = sub.recv_async().await {
                    match JobState::decode(s.payload().to_bytes().as_ref()) {
                        Ok(st) => {
                            if tx.send(Incoming::State(st)).await.is_err() {
                                break;
                            }
                        }
                        Err(_) => malformed(&shared),
                    }
                }
            }
        }));
    }
    // The applier: the only writer of the table; publishes job states as they change and
    // indexes every stored world for browsing.
    {
        let shared = shared.clone();
        let session = session.clone();
        let keys = keys.clone();
        let grace = cfg.orphan_grace.as_millis() as u64;
        let idle = cfg.partial_idle.as_millis() as u64;
        let mut rest: HashMap<String, RestThresholds> = HashMap::new();
        let path_tolerance = cfg.path_tolerance_m;
        tasks.push(tokio::spawn(async move {
            while let Some(msg) = rx.recv().await {
                let now = now_ms();
                let mut stored = None;
                let state = {
                    let mut t = shared.lock();
                    match msg {
                        Incoming::Segment(m) => outcome_state(t.on_segment(m, now), &mut stored),
                        Incoming::Done(m) => outcome_state(t.on_done(m, now), &mut stored),
                        Incoming::Job(j) => {
                            info!(job = %j.id, target = j.target_worlds, cancelled = j.cancelled, "job");
                            rest.entry(j.id.clone())
                                .or_insert_with(|| rest_thresholds(&j));
                            t.submit_job(j)
                        }
                        Incoming::State(st) => {
                            t.adopt_state(&st);
                            None
                        }
                        Incoming::Left(node) => {
                            debug!(%node, "sampler left");
                            t.node_left(&node, now);
                            None
                        }
                        Incoming::Tick => {
                            let n = t.expire(now, grace, idle);
                            if n > 0 {
                                info!(discarded = n, "discarded partial worlds of departed samplers");
                            }
                            None
                        }
                    }
                    .map(|st| (st, stored.and_then(|i| t.world(i))))
                };
                let (state, world) = match state {
                    Some((st, w)) => (Some(st), w),
                    None => (None, None),
                };
                if let Some(w) = world {
                    let thresholds = rest
                        .get(&w.job_id)
                        .copied()
                        .unwrap_or_else(default_rest);
                    match index_world(&w, w.index, thresholds, path_tolerance) {
                        Ok(indexed) => {
                            let index_bytes = {
                                let mut b = shared.browse();
                                b.insert(indexed);
                                b.heap_bytes() as u64
                            };
                            shared.lock().set_index_bytes(index_bytes);
                        }
                        Err(e) => {
                            shared
                                .index_failures
                                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                            warn!(world = w.index, error = %e, "world stored but not browsable");
                        }
                    }
                }
                if authority
                    && let Some(st) = state
                    && let Err(e) = session
                        .put(keys.job_state(&st.job_id), st.encode_to_vec())
                        .congestion_control(CongestionControl::Block)
                        .await
                {
                    warn!(error = %e, "publishing job state failed");
                }
            }
        }));
    }
    // Browsing requests from node-query (JSON `ShardRequest` → `ShardReply`). Evaluating a new
    // constraint runs on every core; it is done on a blocking thread so the runtime stays free.
    {
        let shared = shared.clone();
        let keys = keys.clone();
        let node_id = node_id.clone();
        tasks.push(tokio::spawn(async move {
            while let Ok(q) = browse_q.recv_async().await {
                let session = mwb_core::keys::last_chunk(q.key_expr().as_str()).to_owned();
                let request = q
                    .payload()
                    .ok_or_else(|| "empty request".to_owned())
                    .and_then(|p| {
                        serde_json::from_slice::<ShardRequest>(&p.to_bytes())
                            .map_err(|e| format!("malformed request: {e}"))
                    })
                    .and_then(|r| {
                        if r.session == session {
                            Ok(r)
                        } else {
                            Err(format!(
                                "request names session {:?} but was sent to {session:?}",
                                r.session
                            ))
                        }
                    });
                let reply = match request {
                    Ok(req) => {
                        let shared = shared.clone();
                        tokio::task::spawn_blocking(move || shared.browse().handle(&req))
                            .await
                            .unwrap_or_else(|e| ShardReply::Ok {
                                edits: 0,
                                reply: Reply::Error {
                                    message: format!("shard task failed: {e}"),
                                },
                            })
                    }
                    Err(message) => {
                        shared.lock().counters.malformed += 1;
                        ShardReply::Ok {
                            edits: 0,
                            reply: Reply::Error { message },
                        }
                    }
                };
                match serde_json::to_vec(&reply) {
                    Ok(bytes) => {
                        let _ = q.reply(keys.shard_browse(&node_id, &session), bytes).await;
                    }
                    Err(e) => warn!(error = %e, "serialising a browse reply"),
                }
            }
        }));
    }
    // Queryables.
    if let Some(jobs_q) = jobs_q {
        let shared = shared.clone();
        let keys = keys.clone();
        tasks.push(tokio::spawn(async move {
            while let Ok(q) = jobs_q.recv_async().await {
                let open: Vec<Job> = shared
                    .lock()
                    .jobs()
                    .filter(|(_, st)| !st.closed)
                    .map(|(j, _)| j.clone())
                    .collect();
                for j in open {
                    let key = keys.job(&j.id);
                    if intersects(q.key_expr(), &key) {
                        let _ = q.reply(key, j.encode_to_vec()).await;
                    }
                }
            }
        }));
    }
    if let Some(states_q) = states_q {
        let shared = shared.clone();
        let keys = keys.clone();
        tasks.push(tokio::spawn(async move {
            while let Ok(q) = states_q.recv_async().await {
                let states: Vec<JobState> = shared.lock().jobs().map(|(_, s)| s.clone()).collect();
                for st in states {
                    let key = keys.job_state(&st.job_id);
                    if intersects(q.key_expr(), &key) {
                        let _ = q.reply(key, st.encode_to_vec()).await;
                    }
                }
            }
        }));
    }
    {
        let shared = shared.clone();
        let keys = keys.clone();
        tasks.push(tokio::spawn(async move {
            while let Ok(q) = world_q.recv_async().await {
                // Only concrete indices: a wildcard would ask for every world at once.
                let idx = q
                    .key_expr()
                    .as_str()
                    .rsplit('/')
                    .next()
                    .and_then(|s| s.parse::<u32>().ok());
                let Some(idx) = idx else {
                    let _ = q.reply_err("world index must be a number").await;
                    continue;
                };
                let world = shared.lock().world(idx);
                if let Some(w) = world {
                    let msg = World {
                        index: w.index,
                        job_id: w.job_id.clone(),
                        done: Some(w.done.clone()),
                        segments: w.segments.clone(),
                    };
                    let _ = q.reply(keys.world(idx), msg.encode_to_vec()).await;
                }
            }
        }));
    }
    {
        let shared = shared.clone();
        let keys = keys.clone();
        tasks.push(tokio::spawn(async move {
            while let Ok(q) = stats_q.recv_async().await {
                let st = shared.stats(0.0);
                let _ = q.reply(keys.store_stats(), st.encode_to_vec()).await;
            }
        }));
    }
    // Periodic stats.
    {
        let shared = shared.clone();
        let session = session.clone();
        let key = keys.stats(role::STORE, &node_id);
        tasks.push(tokio::spawn(async move {
            let _token = token;
            let mut last = (Instant::now(), 0u64);
            loop {
                tokio::time::sleep(Duration::from_secs(1)).await;
                let worlds = shared.lock().world_count() as u64;
                let now = Instant::now();
                let rate = (worlds - last.1) as f64 / (now - last.0).as_secs_f64().max(1e-3);
                last = (now, worlds);
                let st = shared.stats(rate);
                let _ = session.put(&key, st.encode_to_vec()).await;
            }
        }));
    }
    info!(node = %node_id, space = %cfg.space, cap = cfg.memory_cap_bytes, "store started");
    Ok(StoreHandle { shared, tasks })
}

/// The job state to publish after an outcome; `stored` receives the index of a stored world.
fn outcome_state(o: Outcome, stored: &mut Option<u32>) -> Option<JobState> {
    match o {
        Outcome::Pending => None,
        Outcome::Stored { state, index } => {
            *stored = Some(index);
            Some(state)
        }
        Outcome::Counted { state } => Some(state),
        Outcome::Rejected { reason, state } => {
            debug!(?reason, "world rejected");
            state
        }
    }
}

/// The rest thresholds of a job's scene (the ones its sampler ends a world with), for the
/// time-to-rest metric; the scene defaults if the scene does not parse here.
fn rest_thresholds(job: &Job) -> RestThresholds {
    job.scene
        .as_ref()
        .and_then(|s| mwb_core::scene::SceneTemplate::parse(&s.toml, &s.name).ok())
        .map_or_else(default_rest, |t| RestThresholds::from(t.settings()))
}

fn default_rest() -> RestThresholds {
    RestThresholds::from(&mwb_core::scene::Settings::default())
}

fn intersects(query: &KeyExpr<'_>, key: &str) -> bool {
    KeyExpr::try_from(key).is_ok_and(|k| query.intersects(&k))
}

/// This machine's host name, for node statistics (empty where unknown).
fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().to_owned())
        .unwrap_or_default()
}
