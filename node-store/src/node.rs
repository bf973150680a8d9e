//! The store node: subscribes to segments, world summaries and jobs; serves open jobs, job
//! states, worlds by index, browsing requests and statistics as queryables; publishes job
//! states and stats. [`run_store`] declares what the node listens to and starts one task per
//! duty; each task is a function below.

use crate::assembly::{Assembler, Outcome};
use crate::browse::{Shard, ShardSpec};
use crate::index::index_world;
use mwb_core::browse::RestThresholds;
use mwb_core::browse::api::{Reply, ShardReply, ShardRequest};
use mwb_core::keys::{check_identifier, last_chunk, role};
use mwb_node::bus::{self, Queries, Subscription};
use mwb_node::{Node, NodeError};
use mwb_proto::v1::{Job, JobState, Message, MotionSegment, NodeStats, World, WorldDone};
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tracing::{debug, info, warn};
use zenoh::Session;
use zenoh::key_expr::KeyExpr;
use zenoh::sample::SampleKind;

/// The store's default memory cap, MiB (the CLI's `--memory-cap-mib` default too).
pub const DEFAULT_MEMORY_CAP_MIB: u64 = 4096;
/// Capacity of the ingest queue between the subscribers and the applier.
const INGEST_QUEUE: usize = 4096;
/// How often the applier looks for partial worlds to discard.
const TICK: Duration = Duration::from_millis(250);

/// Store settings.
#[derive(Debug, Clone)]
pub struct StoreConfig {
    /// Browsing space (`mwb/<space>/…`); default [`mwb_core::keys::DEFAULT_SPACE`].
    pub space: String,
    /// Complete worlds past this many bytes are refused (and counted in stats); default
    /// [`DEFAULT_MEMORY_CAP_MIB`] MiB.
    pub memory_cap_bytes: u64,
    /// Partial worlds of a departed sampler are discarded this long after it left; default 1 s.
    pub orphan_grace: Duration,
    /// Partial worlds that receive nothing for this long are discarded; default 120 s.
    pub partial_idle: Duration,
    /// Node id; default: the session's zenoh id.
    pub node_id: Option<String>,
    /// Which worlds this store keeps when several split them; default all (`0/1`).
    pub shard: ShardSpec,
    /// Largest distance between an indexed polyline and the decoded path, metres (query boxes
    /// are widened by this plus the codec's e_max); default
    /// [`crate::index::DEFAULT_PATH_TOLERANCE_M`].
    pub path_tolerance_m: f64,
}

impl Default for StoreConfig {
    fn default() -> Self {
        Self {
            space: mwb_core::keys::DEFAULT_SPACE.into(),
            memory_cap_bytes: DEFAULT_MEMORY_CAP_MIB << 20,
            orphan_grace: Duration::from_secs(1),
            partial_idle: Duration::from_secs(120),
            node_id: None,
            shard: ShardSpec::default(),
            path_tolerance_m: crate::index::DEFAULT_PATH_TOLERANCE_M,
        }
    }
}

/// Why the store could not start.
pub type StoreError = NodeError;

fn now_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

struct Shared {
    node: Arc<Node>,
    table: Mutex<Assembler>,
    /// The browsing index and sessions (a separate lock: evaluating a constraint over every
    /// world must not stall ingest of segments).
    browse: Mutex<Shard>,
    index_failures: AtomicU64,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, Assembler> {
        self.table.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn browse(&self) -> MutexGuard<'_, Shard> {
        self.browse.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A statistics snapshot (`worlds_per_s` is the publisher's to measure).
    fn stats(&self) -> NodeStats {
        let (index_bytes, spec) = {
            let b = self.browse();
            (b.heap_bytes() as u64, b.spec())
        };
        let t = self.lock();
        let c = t.counters;
        NodeStats {
            worlds: t.world_count() as u64,
            bytes: t.memory_bytes(),
            memory_bytes: t.memory_bytes(),
            memory_cap_bytes: t.cap_bytes(),
            refused_memory: c.refused_memory,
            crc_failures: c.crc_failures,
            malformed: c.malformed + self.node.malformed(),
            discarded_partial: c.discarded_partial,
            duplicates: c.duplicates,
            index_bytes,
            index_failures: self.index_failures.load(Ordering::Relaxed),
            shard_index: spec.index,
            shard_count: spec.count,
            ..self.node.stats()
        }
    }
}

/// A running store.
pub struct StoreHandle {
    shared: Arc<Shared>,
    tasks: Vec<JoinHandle<()>>,
}

impl StoreHandle {
    pub fn node_id(&self) -> &str {
        self.shared.node.id()
    }
    pub fn world_count(&self) -> usize {
        self.shared.lock().world_count()
    }
    pub fn job_state(&self, job: &str) -> Option<JobState> {
        self.shared.lock().job_state(job).cloned()
    }
    pub fn stats(&self) -> NodeStats {
        self.shared.stats()
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

/// A job announcement whose id can be a key chunk; `None` (counted as malformed) otherwise.
fn valid_job(job: Job) -> Option<Incoming> {
    check_identifier("job id", &job.id)
        .is_ok()
        .then_some(Incoming::Job(job))
}

/// Starts a store node on `session` (in the current tokio runtime).
pub async fn run_store(session: Session, cfg: StoreConfig) -> Result<StoreHandle, StoreError> {
    let node = Node::new(&session, &cfg.space, cfg.node_id.as_deref(), role::STORE)?;
    let keys = node.keys().clone();
    let shared = Arc::new(Shared {
        node: node.clone(),
        table: Mutex::new(Assembler::sharded(cfg.memory_cap_bytes, cfg.shard)),
        browse: Mutex::new(Shard::new(cfg.shard, node.id())),
        index_failures: AtomicU64::new(0),
    });
    let segments = node.subscribe(keys.segments()).await?;
    let dones = node.subscribe(keys.dones()).await?;
    let jobs = node.subscribe(keys.jobs()).await?;
    // Every producer of worlds (samplers, reverse nodes) holds a token; a node that holds no
    // partial worlds leaving costs nothing.
    let departures = node.watch_alive(keys.alive_all()).await?;
    // Job-level answers come from one shard only (shard 0, the authority), so that a client
    // never mixes job states of different shards; the other shards follow its job states.
    let authority = cfg.shard.is_authority();
    let (job_queries, state_queries, authority_states) = if authority {
        let jobs = node.queryable(keys.jobs()).await?;
        (
            Some(jobs),
            Some(node.queryable(keys.job_states()).await?),
            None,
        )
    } else {
        (None, None, Some(node.subscribe(keys.job_states()).await?))
    };
    let browse_queries = node.queryable(keys.shard_browse_all(node.id())).await?;
    let world_queries = node.queryable(keys.worlds()).await?;
    let stats_queries = node.queryable(keys.store_stats()).await?;
    let token = node.declare_alive().await?;

    // All ingest goes through one bounded queue, so segments and summaries are applied in the
    // order they arrived and a slow store pushes back on the subscribers.
    let (tx, rx) = mpsc::channel::<Incoming>(INGEST_QUEUE);
    let stats = {
        let shared = shared.clone();
        move || shared.stats()
    };
    let mut tasks = vec![
        tokio::spawn(bus::hold(token)),
        tokio::spawn(bus::forward(node.clone(), segments, tx.clone(), |m| {
            Some(Incoming::Segment(m))
        })),
        tokio::spawn(bus::forward(node.clone(), dones, tx.clone(), |m| {
            Some(Incoming::Done(m))
        })),
        tokio::spawn(bus::forward(node.clone(), jobs, tx.clone(), valid_job)),
        tokio::spawn(watch_departures(departures, tx.clone())),
        tokio::spawn(tick(tx.clone())),
        tokio::spawn(catch_up(node.clone(), tx, authority_states)),
        tokio::spawn(apply(Applier::new(shared.clone(), &cfg), rx)),
        tokio::spawn(serve_browse(shared.clone(), browse_queries)),
        tokio::spawn(serve_worlds(shared.clone(), world_queries)),
        tokio::spawn(serve_stats(shared.clone(), stats_queries)),
        tokio::spawn(bus::publish_stats(node.clone(), stats)),
    ];
    if let Some(q) = job_queries {
        tasks.push(tokio::spawn(serve_open_jobs(shared.clone(), q)));
    }
    if let Some(q) = state_queries {
        tasks.push(tokio::spawn(serve_job_states(shared.clone(), q)));
    }
    info!(node = %node.id(), space = %cfg.space, cap = cfg.memory_cap_bytes, "store started");
    Ok(StoreHandle { shared, tasks })
}

/// Liveliness deletes: a producer of worlds left (its partial worlds will be discarded).
async fn watch_departures(sub: Subscription, tx: mpsc::Sender<Incoming>) {
    while let Ok(s) = sub.recv_async().await {
        if s.kind() == SampleKind::Delete
            && tx
                .send(Incoming::Left(last_chunk(s.key_expr().as_str()).to_owned()))
                .await
                .is_err()
        {
            break;
        }
    }
}

/// The applier's clock: expiry of partial worlds.
async fn tick(tx: mpsc::Sender<Incoming>) {
    loop {
        tokio::time::sleep(TICK).await;
        if tx.send(Incoming::Tick).await.is_err() {
            break;
        }
    }
}

/// A store that starts while jobs are under way (a restart, or a shard joining late) learns
/// them from the authority; a non-authority shard also takes the authority's job states, then
/// follows them on `authority_states`.
async fn catch_up(
    node: Arc<Node>,
    tx: mpsc::Sender<Incoming>,
    authority_states: Option<Subscription>,
) {
    let keys = node.keys();
    let mut learned: Vec<Option<Incoming>> = node
        .get::<Job>(keys.jobs())
        .await
        .into_iter()
        .map(valid_job)
        .collect();
    if authority_states.is_some() {
        let states = node.get::<JobState>(keys.job_states()).await;
        learned.extend(states.into_iter().map(|st| Some(Incoming::State(st))));
    }
    for item in learned {
        match item {
            Some(m) => {
                if tx.send(m).await.is_err() {
                    return;
                }
            }
            None => node.count_malformed(),
        }
    }
    if let Some(sub) = authority_states {
        bus::forward(node, sub, tx, |st| Some(Incoming::State(st))).await;
    }
}

/// The applier: the only writer of the table. Publishes job states as they change (the
/// authority) and indexes every stored world for browsing.
struct Applier {
    shared: Arc<Shared>,
    authority: bool,
    grace_ms: u64,
    idle_ms: u64,
    path_tolerance_m: f64,
    /// Each job's rest thresholds, for the time-to-rest metric.
    rest: HashMap<String, RestThresholds>,
}

impl Applier {
    fn new(shared: Arc<Shared>, cfg: &StoreConfig) -> Self {
        Self {
            shared,
            authority: cfg.shard.is_authority(),
            grace_ms: cfg.orphan_grace.as_millis() as u64,
            idle_ms: cfg.partial_idle.as_millis() as u64,
            path_tolerance_m: cfg.path_tolerance_m,
            rest: HashMap::new(),
        }
    }

    /// Applies one message to the table: the job state to publish, if it changed, and the
    /// world it stored, if any.
    fn take(&mut self, msg: Incoming) -> (Option<JobState>, Option<Arc<crate::StoredWorld>>) {
        let now = now_ms();
        let mut t = self.shared.lock();
        let mut stored = None;
        let state = match msg {
            Incoming::Segment(m) => outcome_state(t.on_segment(m, now), &mut stored),
            Incoming::Done(m) => outcome_state(t.on_done(m, now), &mut stored),
            Incoming::Job(j) => {
                info!(job = %j.id, target = j.target_worlds, cancelled = j.cancelled, "job");
                self.rest
                    .entry(j.id.clone())
                    .or_insert_with(|| rest_thresholds(&j));
                t.submit_job(j)
            }
            Incoming::State(st) => {
                t.adopt_state(&st);
                None
            }
            Incoming::Left(node) => {
                debug!(%node, "producer of worlds left");
                t.node_left(&node, now);
                None
            }
            Incoming::Tick => {
                let n = t.expire(now, self.grace_ms, self.idle_ms);
                if n > 0 {
                    info!(
                        discarded = n,
                        "discarded partial worlds of departed samplers"
                    );
                }
                None
            }
        };
        (state, stored.and_then(|i| t.world(i)))
    }

    /// Indexes a stored world for browsing; a world that cannot be indexed stays stored (and
    /// fetchable) and is counted.
    fn index(&self, w: &crate::StoredWorld) {
        let thresholds = self
            .rest
            .get(&w.job_id)
            .copied()
            .unwrap_or_else(default_rest);
        match index_world(w, w.index, thresholds, self.path_tolerance_m) {
            Ok(indexed) => {
                let index_bytes = {
                    let mut b = self.shared.browse();
                    b.insert(indexed);
                    b.heap_bytes() as u64
                };
                self.shared.lock().set_index_bytes(index_bytes);
            }
            Err(e) => {
                self.shared.index_failures.fetch_add(1, Ordering::Relaxed);
                warn!(world = w.index, error = %e, "world stored but not browsable");
            }
        }
    }
}

async fn apply(mut a: Applier, mut rx: mpsc::Receiver<Incoming>) {
    while let Some(msg) = rx.recv().await {
        let (state, world) = a.take(msg);
        if let Some(w) = world {
            a.index(&w);
        }
        if a.authority
            && let Some(st) = state
        {
            let node = &a.shared.node;
            node.put(&node.keys().job_state(&st.job_id), st.encode_to_vec())
                .await;
        }
    }
}

/// Why a browse query carries no request this shard can answer (sent back as the reply's
/// error message).
fn browse_request(q: &zenoh::query::Query, session: &str) -> Result<ShardRequest, String> {
    let payload = q.payload().ok_or_else(|| "empty request".to_owned())?;
    let req = serde_json::from_slice::<ShardRequest>(&payload.to_bytes())
        .map_err(|e| format!("malformed request: {e}"))?;
    if req.session != session {
        return Err(format!(
            "request names session {:?} but was sent to {session:?}",
            req.session
        ));
    }
    Ok(req)
}

/// Browsing requests from node-query (JSON `ShardRequest` → `ShardReply`). Evaluating a new
/// constraint runs on every core; it is done on a blocking thread so the runtime stays free.
async fn serve_browse(shared: Arc<Shared>, queries: Queries) {
    while let Ok(q) = queries.recv_async().await {
        let session = last_chunk(q.key_expr().as_str()).to_owned();
        let reply = match browse_request(&q, &session) {
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
                shared.node.count_malformed();
                ShardReply::Ok {
                    edits: 0,
                    reply: Reply::Error { message },
                }
            }
        };
        match serde_json::to_vec(&reply) {
            Ok(bytes) => {
                let node = &shared.node;
                let key = node.keys().shard_browse(node.id(), &session);
                node.reply(&q, &key, bytes).await;
            }
            Err(e) => warn!(error = %e, "serialising a browse reply"),
        }
    }
}

/// Open jobs, for nodes that join late (authority only).
async fn serve_open_jobs(shared: Arc<Shared>, queries: Queries) {
    let node = &shared.node;
    while let Ok(q) = queries.recv_async().await {
        let open: Vec<Job> = shared
            .lock()
            .jobs()
            .filter(|(_, st)| !st.closed)
            .map(|(j, _)| j.clone())
            .collect();
        for j in open {
            let key = node.keys().job(&j.id);
            if intersects(q.key_expr(), &key) {
                node.reply(&q, &key, j.encode_to_vec()).await;
            }
        }
    }
}

/// Every job's state (authority only).
async fn serve_job_states(shared: Arc<Shared>, queries: Queries) {
    let node = &shared.node;
    while let Ok(q) = queries.recv_async().await {
        let states: Vec<JobState> = shared.lock().jobs().map(|(_, s)| s.clone()).collect();
        for st in states {
            let key = node.keys().job_state(&st.job_id);
            if intersects(q.key_expr(), &key) {
                node.reply(&q, &key, st.encode_to_vec()).await;
            }
        }
    }
}

/// A stored world by its global index (only concrete indices: a wildcard would ask for every
/// world at once). The shard that does not hold the index stays silent.
async fn serve_worlds(shared: Arc<Shared>, queries: Queries) {
    let node = &shared.node;
    while let Ok(q) = queries.recv_async().await {
        let Ok(idx) = last_chunk(q.key_expr().as_str()).parse::<u32>() else {
            node.reply_err(&q, "world index must be a number").await;
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
            node.reply(&q, &node.keys().world(idx), msg.encode_to_vec())
                .await;
        }
    }
}

/// Statistics on request (`worlds_per_s` is 0 here; the published ones carry the rate).
async fn serve_stats(shared: Arc<Shared>, queries: Queries) {
    let node = &shared.node;
    while let Ok(q) = queries.recv_async().await {
        let st = shared.stats();
        node.reply(&q, &node.keys().store_stats(), st.encode_to_vec())
            .await;
    }
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
