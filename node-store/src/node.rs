//! The store node: subscribes to segments, world summaries, jobs and (the authority) scene
//! revisions; serves open jobs, held jobs, job states, scene revisions, worlds by index, the
//! browsing index's paths, browsing requests and statistics as queryables; publishes job
//! states and stats. [`run_store`] declares what the node listens to and starts one task per
//! duty; each task is a function below.
//!
//! **Acknowledgement across shards.** After each group commit every shard publishes, for each
//! job whose count it changed, how many worlds of it it has stored (`ShardCount` on
//! `job/<id>/shard/<index>`): durable worlds only. The authority (shard 0) sums those counts
//! and its own into the job states it publishes (see [`crate::assembly`]), so an acknowledged
//! world is always on the disk of the shard that keeps it. A count the authority's states do
//! not show yet is sent again every [`COUNT_RESEND`], and every count when a store appears
//! (an authority restarted from its journal learns what it missed while it was down).

use crate::assembly::{Assembler, Outcome};
use crate::browse::{Shard, ShardSpec};
use crate::index::{JobScene, SentChecks, SentIndex, index_stored};
use crate::journal::{
    Journal, JournalCounters, JournalError, MAX_BATCH, StartReport, StoreInput, checkpoint,
    read_store_input,
};
use crate::scenes::{Offered, SceneRefusal, SceneRevisions, scene_from_put};
use mwb_core::browse::api::{Reply, ShardReply, ShardRequest};
use mwb_core::keys::{Keys, SceneRev, check_identifier, last_chunk, role};
use mwb_node::bus::{self, Queries, Subscription};
use mwb_node::{Node, NodeError};
use mwb_proto::v1::{
    Job, JobState, Message, MotionSegment, NodeStats, PathsRequest, Scene, ShardCount, WorldDone,
    WorldIndex,
};
use std::collections::{BTreeSet, HashMap};
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tracing::{debug, error, info, warn};
use zenoh::Session;
use zenoh::key_expr::KeyExpr;
use zenoh::sample::SampleKind;

/// The store's default memory cap, MiB (the CLI's `--memory-cap-mib` default too).
pub const DEFAULT_MEMORY_CAP_MIB: u64 = 4096;
/// Capacity of the ingest queue between the subscribers and the applier.
const INGEST_QUEUE: usize = 4096;
/// Worlds per shard in one `q/paths` answer when the request does not say (about 3 kB each for
/// a 5-body world: answers stay well under a megabyte).
pub const DEFAULT_PATH_BATCH: usize = 256;
/// How often the applier looks for partial worlds to discard.
const TICK: Duration = Duration::from_millis(250);
/// How often a shard sends again the counts the authority's job states do not show yet (a
/// `ShardCount` lost while the authority was down or a link was cut).
pub const COUNT_RESEND: Duration = Duration::from_secs(1);

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
    /// Directory of the store's journal ([`crate::journal`]): read back at start, then every
    /// world is durable before it is acknowledged. `None` (the default): memory only.
    pub journal: Option<PathBuf>,
    /// Recordings whose worlds are loaded at start, in order, after the journal (and written
    /// to it).
    pub load: Vec<PathBuf>,
    /// Of the worlds that come with the index their sampler built (`WorldDone.index`), this
    /// store indexes one in this many itself too and compares (a mismatch is counted and
    /// warned, and the store's own index kept); 1 checks every one, 0 none. Default
    /// [`DEFAULT_VERIFY_INDEX_EVERY`].
    pub verify_index_every: u32,
}

/// A store checks the first sent index and then one in this many by indexing the world itself:
/// samplers of another build are caught at once, at ~3 % of the store's work a world (a check
/// costs what indexing a world without a sent index does; measured with `mwb bench ingest`: one
/// in 32 took a tumble10 store from ~10 800 to ~8 600 worlds/s).
pub const DEFAULT_VERIFY_INDEX_EVERY: u32 = 256;

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
            journal: None,
            load: Vec::new(),
            verify_index_every: DEFAULT_VERIFY_INDEX_EVERY,
        }
    }
}

/// Why the store could not start.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error(transparent)]
    Node(#[from] NodeError),
    /// The journal directory cannot be created or its first file written (damage in the
    /// files already there never stops the store: they are read up to it).
    #[error(transparent)]
    Journal(#[from] JournalError),
}

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
    /// Sent indexes taken, refused, checked and found different (`NodeStats`).
    indexes_sent: AtomicU64,
    indexes_refused: AtomicU64,
    indexes_checked: AtomicU64,
    index_mismatches: AtomicU64,
    /// The journal's counts after its last commit (`None`: no journal).
    journal: Mutex<Option<JournalCounters>>,
    /// Every scene revision (the authority's; empty on the other shards).
    scenes: Mutex<SceneRevisions>,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, Assembler> {
        self.table.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn browse(&self) -> MutexGuard<'_, Shard> {
        self.browse.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn scenes(&self) -> MutexGuard<'_, SceneRevisions> {
        self.scenes.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A scene revision put on the bus: kept if new; dropped and counted if refused (a
    /// conflict is logged as a warning, naming both hashes).
    fn offer_put_scene(&self, scene: Scene) -> Option<Offered> {
        let revision = scene.revision;
        let offered = self.scenes().offer(scene);
        match &offered {
            Ok(Offered::New) => info!(revision, "scene revision"),
            Ok(Offered::Same) => {}
            Err(e) => {
                self.node.count_malformed();
                if matches!(e, SceneRefusal::Conflict { .. }) {
                    warn!(error = %e, "scene put refused");
                } else {
                    debug!(error = %e, "scene put refused");
                }
            }
        }
        offered.ok()
    }

    /// The scene a job carries. Not counted when refused: the job itself is applied (and
    /// today every job `mwb job submit` makes claims revision 1 of the scene it samples).
    fn learn_scene(&self, job: &str, scene: Scene) {
        let revision = scene.revision;
        match self.scenes().offer(scene) {
            Ok(Offered::New) => info!(revision, %job, "scene revision from a job"),
            Ok(Offered::Same) => {}
            Err(e) => debug!(%job, error = %e, "a job's scene is not kept as a revision"),
        }
    }

    /// A statistics snapshot (`worlds_per_s` is the publisher's to measure).
    fn stats(&self) -> NodeStats {
        let (index_bytes, spec, browsable) = {
            let b = self.browse();
            (b.heap_bytes() as u64, b.spec(), b.world_count())
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
            indexes_sent: self.indexes_sent.load(Ordering::Relaxed),
            indexes_refused: self.indexes_refused.load(Ordering::Relaxed),
            indexes_checked: self.indexes_checked.load(Ordering::Relaxed),
            index_mismatches: self.index_mismatches.load(Ordering::Relaxed),
            browsable_worlds: browsable,
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
    started: Arc<StartReport>,
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
    /// Complete worlds held for a job the store has not seen yet.
    pub fn held_worlds(&self) -> usize {
        self.shared.lock().held_count()
    }
    /// A scene revision the store holds, or its latest (the authority shard; the others hold
    /// none).
    pub fn scene(&self, rev: SceneRev) -> Option<Scene> {
        self.shared.scenes().at(rev).cloned()
    }
    /// Scene revisions held.
    pub fn scene_count(&self) -> usize {
        self.shared.scenes().len()
    }
    /// What the store read at start (journal files, recordings) and what it skipped.
    pub fn start_report(&self) -> &StartReport {
        &self.started
    }
    /// The journal's counts after its last commit (`None`: no journal).
    pub fn journal_counters(&self) -> Option<JournalCounters> {
        *self
            .shared
            .journal
            .lock()
            .unwrap_or_else(|p| p.into_inner())
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
    /// A scene revision put on `scene/<rev>`, its key checked (the authority only).
    Scene(Scene),
    /// A job state read back from the journal.
    Restored(JobState),
    /// Another shard's count of its durable worlds of a job (the authority only).
    Count(ShardCount),
    /// A producer of worlds (or a store) left.
    Left(String),
    /// A store appeared (perhaps the authority, restarted): every count is sent again.
    StoreAppeared,
    Tick,
}

/// A job announcement whose id can be a key chunk; `None` (counted as malformed) otherwise.
fn valid_job(job: Job) -> Option<Incoming> {
    check_identifier("job id", &job.id)
        .is_ok()
        .then_some(Incoming::Job(job))
}

/// A shard count whose job id can be a key chunk; `None` (counted as malformed) otherwise.
fn valid_count(c: ShardCount) -> Option<Incoming> {
    check_identifier("job id", &c.job_id)
        .is_ok()
        .then_some(Incoming::Count(c))
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
        indexes_sent: AtomicU64::new(0),
        indexes_refused: AtomicU64::new(0),
        indexes_checked: AtomicU64::new(0),
        index_mismatches: AtomicU64::new(0),
        journal: Mutex::new(None),
        scenes: Mutex::new(SceneRevisions::default()),
    });
    // The journal and the recordings are read before the node subscribes or answers.
    let mut applier = Applier::new(shared.clone(), &cfg, keys.clone());
    let started = Arc::new(applier.start(&cfg)?);
    let segments = node.subscribe(keys.segments()).await?;
    let dones = node.subscribe(keys.dones()).await?;
    let jobs = node.subscribe(keys.jobs()).await?;
    // Every producer of worlds (samplers, reverse nodes) holds a token; a node that holds no
    // partial worlds leaving costs nothing.
    let departures = node.watch_alive(keys.alive_all()).await?;
    // Job-level answers come from one shard only (shard 0, the authority), so that a client
    // never mixes job states of different shards; the other shards follow its job states.
    let authority = cfg.shard.is_authority();
    // Scene revisions too: one shard keeps them all, so "latest" has one answer.
    // The authority also sums the other shards' counts into the job states it publishes.
    let (job_queries, state_queries, authority_states, scene_puts, scene_queries, shard_counts) =
        if authority {
            (
                Some(node.queryable(keys.jobs()).await?),
                Some(node.queryable(keys.job_states()).await?),
                None,
                Some(node.subscribe(keys.scenes()).await?),
                Some(node.queryable(keys.scene_queries()).await?),
                Some(node.subscribe(keys.job_shards()).await?),
            )
        } else {
            let states = node.subscribe(keys.job_states()).await?;
            (None, None, Some(states), None, None, None)
        };
    let browse_queries = node.queryable(keys.shard_browse_all(node.id())).await?;
    let world_queries = node.queryable(keys.worlds()).await?;
    let stats_queries = node.queryable(keys.store_stats()).await?;
    let path_queries = node.queryable(keys.paths()).await?;
    let held_job_queries = node.queryable(keys.held_jobs()).await?;
    let token = node.declare_alive().await?;

    // All ingest goes through one bounded queue, so segments and summaries are applied in the
    // order they arrived and a slow store pushes back on the subscribers.
    let (tx, rx) = mpsc::channel::<Incoming>(INGEST_QUEUE);
    let stats = {
        let shared = shared.clone();
        move || shared.stats()
    };
    let scene_tx = tx.clone();
    let count_tx = tx.clone();
    let mut tasks = vec![
        tokio::spawn(bus::hold(token)),
        tokio::spawn(bus::forward(node.clone(), segments, tx.clone(), |m| {
            Some(Incoming::Segment(m))
        })),
        tokio::spawn(bus::forward(node.clone(), dones, tx.clone(), |m| {
            Some(Incoming::Done(m))
        })),
        tokio::spawn(bus::forward(node.clone(), jobs, tx.clone(), valid_job)),
        tokio::spawn(watch_departures(departures, keys.clone(), tx.clone())),
        tokio::spawn(tick(tx.clone())),
        tokio::spawn(catch_up(node.clone(), tx, authority_states)),
        tokio::spawn(apply(applier, rx)),
        tokio::spawn(serve_browse(shared.clone(), browse_queries)),
        tokio::spawn(serve_worlds(shared.clone(), world_queries)),
        tokio::spawn(serve_stats(shared.clone(), stats_queries)),
        tokio::spawn(serve_paths(shared.clone(), path_queries)),
        tokio::spawn(serve_held_jobs(shared.clone(), held_job_queries)),
        tokio::spawn(bus::publish_stats(node.clone(), stats)),
    ];
    if let Some(q) = job_queries {
        tasks.push(tokio::spawn(serve_open_jobs(shared.clone(), q)));
    }
    if let Some(q) = state_queries {
        tasks.push(tokio::spawn(serve_job_states(shared.clone(), q)));
    }
    if let Some(sub) = shard_counts {
        tasks.push(tokio::spawn(bus::forward(
            node.clone(),
            sub,
            count_tx,
            valid_count,
        )));
    }
    if let (Some(sub), Some(q)) = (scene_puts, scene_queries) {
        tasks.push(tokio::spawn(forward_scenes(node.clone(), sub, scene_tx)));
        tasks.push(tokio::spawn(serve_scenes(shared.clone(), q)));
    }
    info!(node = %node.id(), space = %cfg.space, cap = cfg.memory_cap_bytes, "store started");
    Ok(StoreHandle {
        shared,
        tasks,
        started,
    })
}

/// Liveliness: a producer of worlds left (its partial worlds will be discarded), or a store
/// appeared (this shard's counts are sent again, for an authority that restarted).
async fn watch_departures(sub: Subscription, keys: Keys, tx: mpsc::Sender<Incoming>) {
    while let Ok(s) = sub.recv_async().await {
        let key = s.key_expr().as_str();
        let msg = match s.kind() {
            SampleKind::Delete => Incoming::Left(last_chunk(key).to_owned()),
            SampleKind::Put
                if keys
                    .split(key)
                    .is_some_and(|c| c.len() == 3 && c[0] == "alive" && c[1] == role::STORE) =>
            {
                Incoming::StoreAppeared
            }
            SampleKind::Put => continue,
        };
        if tx.send(msg).await.is_err() {
            break;
        }
    }
}

/// Scene revisions put on `scene/<rev>` (the authority only): a payload that is not a `Scene`
/// or whose revision is not its key's is dropped and counted here; the applier offers the rest
/// to the table.
async fn forward_scenes(node: Arc<Node>, sub: Subscription, tx: mpsc::Sender<Incoming>) {
    while let Ok(s) = sub.recv_async().await {
        if s.kind() != SampleKind::Put {
            continue;
        }
        match scene_from_put(s.key_expr().as_str(), &s.payload().to_bytes()) {
            Ok(scene) => {
                if tx.send(Incoming::Scene(scene)).await.is_err() {
                    break;
                }
            }
            Err(e) => {
                node.count_malformed();
                debug!(error = %e, "scene put dropped");
            }
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
    /// Each job's rest thresholds (for the time-to-rest metric) and body names.
    rest: HashMap<String, JobScene>,
    keys: Keys,
    journal: Option<Journal>,
    /// What [`Applier::take`] has for the journal, in order, held until the worlds among it
    /// are indexed ([`Applier::index`]), so that each world is journaled with the index this
    /// store keeps for it (read back, it is taken like a sent one instead of built again).
    journal_queue: Vec<Journaled>,
    /// Jobs whose count this shard publishes after the next commit.
    counts_due: BTreeSet<String>,
    /// When the counts the authority lacks were last sent again.
    last_resend: Instant,
    /// Threads a batch of worlds is indexed on (every core).
    index_threads: usize,
    /// Worlds read from the journal or a recording at start, not indexed yet (indexed
    /// [`LOAD_INDEX_BATCH`] at a time, on every core).
    unindexed: Vec<StoredSent>,
    /// Stored worlds the index has taken in (indexed, or failed to index).
    index_taken: u64,
    /// Which sent indexes are checked ([`StoreConfig::verify_index_every`]).
    checks: SentChecks,
}

/// A stored world and the index its sampler sent with it, if any.
type StoredSent = (Arc<crate::StoredWorld>, Option<Box<WorldIndex>>);

/// A record waiting for the journal ([`Applier::journal_queue`]).
#[derive(Debug)]
enum Journaled {
    /// A job, scene or job state: key and encoded message.
    Record(String, Vec<u8>),
    /// A stored world, journaled with its index once it has one.
    World(Arc<crate::StoredWorld>),
}

/// Worlds loaded at start are indexed this many at a time.
const LOAD_INDEX_BATCH: usize = 256;

impl Applier {
    fn new(shared: Arc<Shared>, cfg: &StoreConfig, keys: Keys) -> Self {
        Self {
            shared,
            authority: cfg.shard.is_authority(),
            grace_ms: cfg.orphan_grace.as_millis() as u64,
            idle_ms: cfg.partial_idle.as_millis() as u64,
            path_tolerance_m: cfg.path_tolerance_m,
            rest: HashMap::new(),
            keys,
            journal: None,
            journal_queue: Vec::new(),
            counts_due: BTreeSet::new(),
            last_resend: Instant::now(),
            index_threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            unindexed: Vec::new(),
            index_taken: 0,
            checks: SentChecks::every(cfg.verify_index_every),
        }
    }

    /// Indexes the worlds loaded so far.
    fn index_loaded(&mut self) {
        let worlds = std::mem::take(&mut self.unindexed);
        self.index(worlds);
    }

    /// Reads the journal (if any), opens it for writing, then loads the recordings (their
    /// worlds are journaled like any other).
    fn start(&mut self, cfg: &StoreConfig) -> Result<StartReport, JournalError> {
        let t0 = Instant::now();
        let mut report = StartReport::default();
        let worlds = |a: &Self| a.shared.lock().world_count() as u64;
        let refused = |a: &Self| {
            let c = a.shared.lock().counters;
            c.crc_failures + c.incomplete + c.duplicates + c.refused_memory + c.late
        };
        let refused0 = refused(self);
        if let Some(dir) = &cfg.journal {
            let (journal, files) = Journal::open(dir, &cfg.space)?;
            for f in &files {
                let fr = read_store_input(f, true, |m| self.load(m));
                log_file("journal", &fr);
                report.journal.push(fr);
            }
            self.index_loaded();
            report.worlds_from_journal = worlds(self);
            self.journal = Some(journal);
            // This run's file starts now, with a checkpoint of the jobs as the journal left
            // them. Started later, its checkpoint would already count (and perhaps close the
            // jobs of) the worlds loaded below, which it precedes in the file: read back, those
            // worlds would be counted twice or refused as late.
            self.commit_now()?;
        }
        for f in &cfg.load {
            let fr = read_store_input(f, false, |m| self.load(m));
            log_file("recording", &fr);
            report.recordings.push(fr);
        }
        self.index_loaded();
        report.worlds_from_recordings = worlds(self) - report.worlds_from_journal;
        report.worlds_refused = refused(self) - refused0;
        // What is still partial now can only be a world cut by damage, or held for a job no
        // file announced: nothing will complete it.
        report.partial_discarded = self.shared.lock().expire(u64::MAX, 0, 0) as u64;
        // The worlds loaded from recordings reach the disk before the store answers anyone.
        self.commit_now()?;
        report.seconds = t0.elapsed().as_secs_f64();
        if cfg.journal.is_some() || !cfg.load.is_empty() {
            info!(
                from_journal = report.worlds_from_journal,
                from_recordings = report.worlds_from_recordings,
                refused = report.worlds_refused,
                partial_discarded = report.partial_discarded,
                damaged_files = report.damaged_files(),
                skipped_bytes = report.skipped_bytes(),
                seconds = report.seconds,
                "store loaded"
            );
        }
        Ok(report)
    }

    /// One message read from a journal or a recording, applied like a live one.
    fn load(&mut self, input: StoreInput) {
        let msg = match input {
            StoreInput::Job(j) => Incoming::Job(j),
            StoreInput::State(st) => Incoming::Restored(st),
            StoreInput::Segment(s) => Incoming::Segment(s),
            StoreInput::Done(d) => Incoming::Done(d),
            StoreInput::Scene(scene) => Incoming::Scene(scene),
        };
        let (_, worlds) = self.take(msg);
        self.unindexed.extend(worlds);
        if self.unindexed.len() >= LOAD_INDEX_BATCH {
            self.index_loaded();
        }
        if self
            .journal
            .as_ref()
            .is_some_and(|j| j.pending() >= MAX_BATCH)
        {
            let r = self.commit_now();
            self.commit_failed(r);
        }
    }

    /// Commits the journal on this thread (at start). The first commit of a run creates its
    /// file, so a directory that cannot be written fails the start.
    fn commit_now(&mut self) -> Result<(), JournalError> {
        let Some(j) = self.journal.as_mut() else {
            return Ok(());
        };
        let (shared, keys) = (&self.shared, &self.keys);
        let r = j.commit(|| checkpoint(&shared.lock(), keys));
        *self
            .shared
            .journal
            .lock()
            .unwrap_or_else(|p| p.into_inner()) = Some(j.counters);
        r
    }

    fn commit_failed(&mut self, r: Result<(), JournalError>) {
        if let Err(e) = r {
            error!(error = %e, "journal commit failed: worlds of this batch are not durable");
            if let Some(j) = self.journal.as_mut() {
                j.counters.failures += 1;
                // The next commit starts a new file rather than writing after a failed write.
                j.abandon_file();
            }
        }
    }

    /// Group commit: everything the batch appended reaches the disk (on a blocking thread)
    /// before the caller publishes the batch's job states.
    async fn commit(&mut self) {
        let Some(mut j) = self.journal.take() else {
            return;
        };
        if j.pending() == 0 {
            self.journal = Some(j);
            return;
        }
        let (shared, keys) = (self.shared.clone(), self.keys.clone());
        match tokio::task::spawn_blocking(move || {
            let r = j.commit(|| checkpoint(&shared.lock(), &keys));
            (j, r)
        })
        .await
        {
            Ok((j, r)) => {
                *self
                    .shared
                    .journal
                    .lock()
                    .unwrap_or_else(|p| p.into_inner()) = Some(j.counters);
                self.journal = Some(j);
                self.commit_failed(r);
            }
            Err(e) => error!(error = %e, "journal writer failed; the store goes on without it"),
        }
    }

    /// Applies one message to the table: the job states to publish (in order) and the worlds
    /// it stored; both are queued for the journal, if there is one, after the job (and
    /// appended by [`Applier::index`], once the worlds are indexed).
    fn take(&mut self, msg: Incoming) -> (Vec<JobState>, Vec<StoredSent>) {
        let now = now_ms();
        let mut t = self.shared.lock();
        let mut outcomes = Vec::new();
        let mut states = Vec::new();
        match msg {
            Incoming::Segment(m) => outcomes.push(t.on_segment(m, now)),
            Incoming::Done(m) => outcomes.push(t.on_done(m, now)),
            Incoming::Scene(scene) => {
                let record = self
                    .journal
                    .is_some()
                    .then(|| (self.keys.scene(scene.revision), scene.encode_to_vec()));
                // Read back at start like jobs (and revisions also come back with the jobs
                // that carry them).
                if self.shared.offer_put_scene(scene) == Some(Offered::New)
                    && let Some((key, bytes)) = record
                {
                    self.journal_queue.push(Journaled::Record(key, bytes));
                }
            }
            Incoming::Job(j) => {
                info!(job = %j.id, target = j.target_worlds, cancelled = j.cancelled, "job");
                // A job carries its scene: how revisions come back from the journal (and from
                // the authority after a restart, or a recording).
                if self.authority
                    && let Some(scene) = j.scene.as_ref().filter(|s| s.revision > 0)
                {
                    self.shared.learn_scene(&j.id, scene.clone());
                }
                self.rest
                    .entry(j.id.clone())
                    .or_insert_with(|| rest_thresholds(&j));
                let (id, bytes) = (
                    j.id.clone(),
                    self.journal.is_some().then(|| j.encode_to_vec()),
                );
                if let Some(st) = t.submit_job(j) {
                    if let Some(bytes) = bytes {
                        self.journal_queue
                            .push(Journaled::Record(self.keys.job(&id), bytes));
                    }
                    states.push(st);
                    // Worlds that completed before their job arrived.
                    outcomes.extend(t.release_held(&id, now));
                }
            }
            Incoming::State(st) => t.adopt_state(&st),
            Incoming::Restored(st) => t.restore_state(&st),
            Incoming::Count(c) => {
                let spec = t.shard();
                if c.shard_count != spec.count || c.shard_index >= spec.count {
                    // Stores started with different shard counts: their worlds cannot be
                    // summed (nor found by index). Said loudly, not counted.
                    warn!(
                        job = %c.job_id, node = %c.node_id, shard = c.shard_index,
                        shards = c.shard_count, ours = spec.count,
                        "shard count from a store with another sharding, ignored"
                    );
                } else {
                    let from = ShardSpec {
                        index: c.shard_index,
                        count: c.shard_count,
                    };
                    states.extend(t.on_shard_count(
                        &c.job_id,
                        from,
                        c.worlds_stored,
                        c.bytes_stored,
                        now,
                    ));
                }
            }
            Incoming::Left(node) => {
                debug!(%node, "producer of worlds left");
                t.node_left(&node, now);
            }
            Incoming::StoreAppeared => self.counts_due.extend(t.jobs_with_worlds()),
            Incoming::Tick => {
                let n = t.expire(now, self.grace_ms, self.idle_ms);
                if n > 0 {
                    info!(
                        discarded = n,
                        "discarded partial worlds of departed samplers"
                    );
                }
                if self.last_resend.elapsed() >= COUNT_RESEND {
                    self.last_resend = Instant::now();
                    self.counts_due.extend(t.unacknowledged_counts());
                }
            }
        }
        let mut stored = Vec::new();
        for o in outcomes {
            let mut index = None;
            states.extend(outcome_state(o, &mut index));
            stored.extend(index.and_then(|(i, sent)| Some((t.world(i)?, sent))));
        }
        self.counts_due
            .extend(stored.iter().map(|(w, _): &StoredSent| w.job_id.clone()));
        if self.journal.is_some() {
            self.journal_queue
                .extend(stored.iter().map(|(w, _)| Journaled::World(w.clone())));
            self.journal_queue.extend(
                states.iter().map(|st| {
                    Journaled::Record(self.keys.job_state(&st.job_id), st.encode_to_vec())
                }),
            );
        }
        (states, stored)
    }

    /// Publishes this shard's count of every job in `counts_due` (after the commit that made
    /// those worlds durable: the authority acknowledges what the counts say).
    async fn publish_counts(&mut self) {
        if self.counts_due.is_empty() {
            return;
        }
        let node = self.shared.node.clone();
        let counts: Vec<ShardCount> = {
            let t = self.shared.lock();
            let spec = t.shard();
            std::mem::take(&mut self.counts_due)
                .into_iter()
                .filter_map(|job| {
                    let (worlds, bytes) = t.own_count(&job)?;
                    Some(ShardCount {
                        job_id: job,
                        shard_index: spec.index,
                        shard_count: spec.count,
                        worlds_stored: worlds,
                        bytes_stored: bytes,
                        node_id: node.id().to_owned(),
                    })
                })
                .collect()
        };
        for c in counts {
            let key = self.keys.job_shard(&c.job_id, c.shard_index);
            node.put(&key, c.encode_to_vec()).await;
        }
    }

    /// Indexes stored worlds for browsing and inserts them in the order given; a world that
    /// cannot be indexed stays stored (and fetchable) and is counted.
    ///
    /// A world whose sampler sent its index is inserted with it once it checks out; one in
    /// [`StoreConfig::verify_index_every`] of those is also indexed here and compared (a
    /// difference is counted and warned, and this store's own index kept). Every other world —
    /// refined differences, reverse nodes' worlds, a refused sent index — is indexed here, all
    /// of them together on every core ([`index_stored`]). Then what [`Applier::take`] queued
    /// for the journal is appended, each world with the index it was inserted with.
    fn index(&mut self, mut worlds: Vec<StoredSent>) {
        let mut wires = HashMap::new();
        self.index_worlds(&mut worlds, &mut wires);
        self.flush_journal(wires);
    }

    /// Appends what [`Applier::take`] queued for the journal, in order, each world with its
    /// index from `wires` (by world number) if it has one.
    fn flush_journal(&mut self, mut wires: HashMap<u32, WorldIndex>) {
        let queue = std::mem::take(&mut self.journal_queue);
        let Some(journal) = self.journal.as_mut() else {
            return;
        };
        for q in queue {
            match q {
                Journaled::Record(key, bytes) => journal.append(key, bytes),
                Journaled::World(w) => {
                    if let Err(e) = journal.append_world(&self.keys, &w, wires.remove(&w.index)) {
                        error!(error = %e, "not journalled");
                    }
                }
            }
        }
    }

    /// Indexes `worlds` (taking their sent indexes where they pass) and inserts them; with a
    /// journal, puts the index each world is browsed by into `wires` (not for a refined
    /// difference, which is composed and indexed at load).
    fn index_worlds(&mut self, worlds: &mut [StoredSent], wires: &mut HashMap<u32, WorldIndex>) {
        if worlds.is_empty() {
            return;
        }
        let rest = &self.rest;
        let jobs: Vec<_> = worlds
            .iter_mut()
            .map(|(w, sent)| {
                let scene = rest.get(&w.job_id).cloned().unwrap_or_default();
                (&**w, sent.take(), scene)
            })
            .collect();
        let results = index_stored(
            jobs,
            self.path_tolerance_m,
            self.index_threads,
            &mut self.checks,
        );
        for ((w, _), (r, sent)) in worlds.iter().zip(results) {
            self.index_taken += 1;
            let counter = |c: &AtomicU64| {
                c.fetch_add(1, Ordering::Relaxed);
            };
            match &sent {
                SentIndex::None => {}
                SentIndex::Taken => counter(&self.shared.indexes_sent),
                SentIndex::Refused(why) => {
                    counter(&self.shared.indexes_refused);
                    debug!(world = w.index, why, "sent index refused: indexed here");
                }
                SentIndex::Checked { same } => {
                    counter(&self.shared.indexes_sent);
                    counter(&self.shared.indexes_checked);
                    if !same {
                        counter(&self.shared.index_mismatches);
                        warn!(
                            world = w.index, job = %w.job_id,
                            "the index a sampler sent differs from this store's: keeping this store's"
                        );
                    }
                }
            }
            let (index_bytes, growth) = {
                let mut b = self.shared.browse();
                match r {
                    Ok(indexed) => {
                        if self.journal.is_some() && !w.is_layered() {
                            wires.insert(w.index, indexed.to_wire(self.path_tolerance_m));
                        }
                        b.insert(indexed)
                    }
                    Err(e) => {
                        self.shared.index_failures.fetch_add(1, Ordering::Relaxed);
                        warn!(world = w.index, error = %e, "world stored but not browsable");
                    }
                }
                (b.heap_bytes() as u64, b.growth_bytes() as u64)
            };
            let mut t = self.shared.lock();
            t.set_index_bytes(index_bytes, self.index_taken);
            t.set_index_growth(growth);
        }
    }
}

/// Applies what is queued in batches of up to [`MAX_BATCH`] (group commit): the batch's
/// worlds and states reach the journal's disk before its job states are published.
async fn apply(mut a: Applier, mut rx: mpsc::Receiver<Incoming>) {
    while let Some(first) = rx.recv().await {
        let mut states = Vec::new();
        let mut next = Some(first);
        let mut n = 0;
        let mut stored = Vec::new();
        while let Some(msg) = next {
            let (st, worlds) = a.take(msg);
            stored.extend(worlds);
            states.extend(st);
            n += 1;
            next = if n < MAX_BATCH {
                rx.try_recv().ok()
            } else {
                None
            };
        }
        // The batch's worlds are browsable before its job states and counts go out.
        a.index(stored);
        a.commit().await;
        if a.authority {
            let node = &a.shared.node;
            for st in states {
                node.put(&node.keys().job_state(&st.job_id), st.encode_to_vec())
                    .await;
            }
        }
        a.publish_counts().await;
    }
}

fn log_file(what: &str, f: &crate::journal::FileReport) {
    if f.damage.is_some() && !f.cut_short {
        warn!("{what} damaged: {}", f.describe());
    } else {
        info!("{what}: {}", f.describe());
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

/// A scene revision, or the latest (authority only); an unknown revision gets no answer (like
/// `q/job` for an unknown job), a key that names no revision an error naming it.
async fn serve_scenes(shared: Arc<Shared>, queries: Queries) {
    let node = &shared.node;
    while let Ok(q) = queries.recv_async().await {
        let rev = match SceneRev::parse(last_chunk(q.key_expr().as_str())) {
            Ok(rev) => rev,
            Err(e) => {
                node.reply_err(&q, &e.to_string()).await;
                continue;
            }
        };
        let scene = shared.scenes().at(rev).map(Message::encode_to_vec);
        if let Some(bytes) = scene {
            node.reply(&q, &node.keys().scene_query(rev), bytes).await;
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
            // A refined world stored as a difference comes with its parent chain.
            match w.message() {
                Ok(m) => {
                    node.reply(&q, &node.keys().world(idx), m.encode_to_vec())
                        .await
                }
                Err(e) => {
                    error!(error = %e, "world not served");
                    node.reply_err(&q, &e.to_string()).await;
                }
            }
        }
    }
}

/// The browsing index's paths from the asker's cursor for this shard (`PathsRequest` →
/// `PathBatch`), for viewers drawing worlds as they arrive (all of them, or the sample the
/// request names), or of the worlds the request names. A malformed request is answered with an
/// error and counted.
async fn serve_paths(shared: Arc<Shared>, queries: Queries) {
    let node = &shared.node;
    while let Ok(q) = queries.recv_async().await {
        let req = match q
            .payload()
            .map(|p| PathsRequest::decode(p.to_bytes().as_ref()))
        {
            None => PathsRequest::default(),
            Some(Ok(r)) => r,
            Some(Err(e)) => {
                node.count_malformed();
                node.reply_err(&q, &format!("malformed PathsRequest: {e}"))
                    .await;
                continue;
            }
        };
        let batch = {
            let b = shared.browse();
            let seen = req.seen.get(b.spec().index as usize).copied().unwrap_or(0);
            let max = match req.max_worlds {
                0 => DEFAULT_PATH_BATCH,
                n => (n as usize).min(4 * DEFAULT_PATH_BATCH),
            };
            if req.worlds.is_empty() {
                b.path_batch(seen, max, req.sample_below)
            } else {
                b.paths_of(&req.worlds, max)
            }
        };
        node.reply(&q, &node.keys().paths(), batch.encode_to_vec())
            .await;
    }
}

/// A job this store holds (open or closed), so that a client can read the scene of any world
/// it was given. A shard that does not know the job stays silent.
async fn serve_held_jobs(shared: Arc<Shared>, queries: Queries) {
    let node = &shared.node;
    while let Ok(q) = queries.recv_async().await {
        let id = last_chunk(q.key_expr().as_str()).to_owned();
        let job = shared
            .lock()
            .jobs()
            .find(|(j, _)| j.id == id)
            .map(|(j, _)| j.clone());
        if let Some(j) = job {
            node.reply(&q, &node.keys().held_job(&j.id), j.encode_to_vec())
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
fn outcome_state(
    o: Outcome,
    stored: &mut Option<(u32, Option<Box<WorldIndex>>)>,
) -> Option<JobState> {
    match o {
        Outcome::Pending => None,
        Outcome::Stored {
            state,
            index,
            sent_index,
        } => {
            *stored = Some((index, sent_index));
            Some(state)
        }
        Outcome::Elsewhere => None,
        Outcome::Rejected { reason, state } => {
            debug!(?reason, "world rejected");
            state
        }
    }
}

/// The rest thresholds of a job's scene (the ones its sampler ends a world with), for the
/// time-to-rest metric, and its body names; the scene defaults if the scene does not parse here.
fn rest_thresholds(job: &Job) -> JobScene {
    JobScene::of(job)
}

fn intersects(query: &KeyExpr<'_>, key: &str) -> bool {
    KeyExpr::try_from(key).is_ok_and(|k| query.intersects(&k))
}
