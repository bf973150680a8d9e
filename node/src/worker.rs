//! The worker node (§4.2 "opportunistic computing"): joins at any time, learns open jobs from
//! the bus (announcements, and a periodic query to the stores for jobs announced before it
//! joined), runs worlds on worker threads and streams them out through one bounded publisher.
//! A node that dies loses only the worlds it was computing; the stores discard those partial
//! worlds when its liveliness token goes away.
//!
//! What a world *is* belongs to a [`WorkerKind`]: the forward sampler (rapier3d), the reverse
//! stepper, and next refinement each implement only "prepare a job's scene" and "turn a job
//! and a seed into segments and a summary"; everything else — the job board, the publisher,
//! the worker threads, stopping a world when its job closes, giving up a job whose worlds keep
//! failing, the statistics — is here, once.

use crate::board::{Board, Ended, Picked};
use crate::bus::{self, Node, NodeError, Subscription};
use crate::room::StoreRoom;
use mwb_core::rng::world_seed;
use mwb_proto::v1::{Job, JobKind, JobState, Message, MotionSegment, NodeStats, Scene, WorldDone};
use std::ops::ControlFlow;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tracing::{debug, info, warn};
use zenoh::Session;

/// How long an idle worker sleeps before looking at the board again (it is woken earlier when
/// a job arrives).
const IDLE_WAIT: Duration = Duration::from_millis(200);

/// One kind of worker: what it makes of a job and a seed.
pub trait WorkerKind: Send + Sync + 'static {
    /// The role in the node's keys (`alive/<role>/<node>`, `stats/<role>/<node>`), one of
    /// `mwb_core::keys::role`.
    const ROLE: &'static str;
    /// Worlds of one job failing this many times in a row make the node give the job up: the
    /// scene, not the seed, is then the problem.
    const GIVE_UP_AFTER: u32;

    /// A job's scene made ready to run, shared by every worker of the node.
    type Scene: Send + Sync + 'static;
    /// Why a scene cannot be run by this kind.
    type SceneError: std::error::Error;
    /// Why one world did not finish: stopped (see [`WorkerKind::stopped`]) or failed.
    type WorldError: std::error::Error;

    /// Whether this kind runs jobs of `kind`; the others are left to other nodes.
    fn takes(kind: JobKind) -> bool;

    /// Prepares `job`'s `scene`, once per job and scene, on the first worker that needs it (it
    /// may be slow: a chain is learned, a template validated).
    fn prepare(&self, job: &Job, scene: &Scene) -> Result<Self::Scene, Self::SceneError>;

    /// Runs world `world` of `scene`, handing each segment to `emit` as soon as it is recorded
    /// and stopping when `emit` breaks. Returns the world's summary; the skeleton adds CPU
    /// time, provenance and scene hash.
    fn run(
        &self,
        world: &WorldTask<'_>,
        scene: &Self::Scene,
        emit: &mut dyn FnMut(MotionSegment) -> ControlFlow<()>,
    ) -> Result<WorldDone, Self::WorldError>;

    /// Whether `e` says only that `emit` broke (the job closed, the node is stopping): not a
    /// failure of the job.
    fn stopped(e: &Self::WorldError) -> bool;

    /// What computed the worlds (binary version and physics build), recorded in each.
    fn provenance(&self) -> String;
}

/// One world to compute: world `counter` of `node` for `job`, from `seed`.
#[derive(Debug, Clone, Copy)]
pub struct WorldTask<'a> {
    pub job: &'a Job,
    pub node: &'a str,
    pub counter: u64,
    pub seed: u64,
}

/// Worker node settings.
#[derive(Debug, Clone)]
pub struct WorkerConfig {
    /// Browsing space (`mwb/<space>/…`); default [`mwb_core::keys::DEFAULT_SPACE`].
    pub space: String,
    /// Worker threads, one world each at a time (at least one); default: one per core.
    pub workers: usize,
    /// Node id; default: the session's zenoh id. Nodes sharing a session (as in `mwb demo`)
    /// need distinct ids.
    pub node_id: Option<String>,
    /// How often to re-ask the stores for open jobs and their states; default 2 s.
    pub refresh: Duration,
    /// Capacity of the outgoing message queue (back-pressure on the workers); default 256.
    pub queue: usize,
}

impl Default for WorkerConfig {
    fn default() -> Self {
        Self {
            space: mwb_core::keys::DEFAULT_SPACE.into(),
            workers: std::thread::available_parallelism().map_or(1, |n| n.get()),
            node_id: None,
            refresh: Duration::from_secs(2),
            queue: 256,
        }
    }
}

/// What the handle and the workers share, whatever the kind.
#[derive(Debug, Default)]
struct Control {
    stop: AtomicBool,
    /// Paired with the board's mutex: idle workers wait on it.
    wake: Condvar,
    counter: AtomicU64,
    worlds: AtomicU64,
    failed: AtomicU64,
    /// The last world failure's (or scene refusal's) message, for the statistics.
    last_failure: Mutex<String>,
    steps: AtomicU64,
    bytes: AtomicU64,
}

impl Control {
    fn stopping(&self) -> bool {
        self.stop.load(Ordering::SeqCst)
    }

    fn note_failure(&self, message: String) {
        *self.last_failure.lock().unwrap_or_else(|p| p.into_inner()) = message;
    }
}

struct Shared<K: WorkerKind> {
    kind: K,
    node: Arc<Node>,
    board: Mutex<Board<K::Scene>>,
    control: Arc<Control>,
    /// The stores' room (back-pressure: no new world while a store is full).
    room: Mutex<StoreRoom>,
    /// Whether the workers are paused for a full store (logged when it changes).
    paused: AtomicBool,
}

impl<K: WorkerKind> Shared<K> {
    fn lock(&self) -> MutexGuard<'_, Board<K::Scene>> {
        // A worker that panicked mid-world poisons nothing we rely on: keep going.
        self.board.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn take_job(&self, job: Job) {
        debug!(job = %job.id, "job announced");
        self.lock().upsert(job);
        self.control.wake.notify_all();
    }

    /// Why no new world may start: a store is full ([`crate::room`]).
    fn store_full(&self) -> Option<String> {
        let room = self.room.lock().unwrap_or_else(|p| p.into_inner());
        let why = room.full(Instant::now()).map(str::to_owned);
        let was = self.paused.swap(why.is_some(), Ordering::Relaxed);
        match (&why, was) {
            (Some(w), false) => info!(why = %w, "pausing: a store is full"),
            (None, true) => info!("resuming: the stores have room"),
            _ => {}
        }
        why
    }

    /// The next world to compute, or `None` after waiting a while for one (or while a store is
    /// full: back-pressure instead of worlds that would be refused).
    fn next_world(&self) -> Option<Picked<K::Scene>> {
        if self.store_full().is_some() {
            let board = self.lock();
            let _ = self.control.wake.wait_timeout(board, IDLE_WAIT);
            return None;
        }
        let mut board = self.lock();
        let picked = board.pick();
        if picked.is_none() {
            // Woken early by a new job or by stop; a poisoned wait is as good as a timeout.
            let _ = self.control.wake.wait_timeout(board, IDLE_WAIT);
        }
        picked
    }

    fn stats(&self, workers: usize) -> NodeStats {
        let c = &self.control;
        let last_failure = c
            .last_failure
            .lock()
            .map_or_else(|p| p.into_inner().clone(), |m| m.clone());
        NodeStats {
            worlds: c.worlds.load(Ordering::Relaxed),
            worlds_failed: c.failed.load(Ordering::Relaxed),
            jobs_given_up: self.lock().given_up(),
            last_failure,
            sim_steps: c.steps.load(Ordering::Relaxed),
            bytes: c.bytes.load(Ordering::Relaxed),
            workers: u32::try_from(workers).unwrap_or(u32::MAX),
            ..self.node.stats()
        }
    }
}

/// One message for the publisher.
struct Put {
    key: String,
    bytes: Vec<u8>,
}

/// A running worker node. Dropping it does not stop it; call [`WorkerHandle::stop`].
pub struct WorkerHandle {
    node: Arc<Node>,
    control: Arc<Control>,
    tasks: Vec<JoinHandle<()>>,
    workers: Vec<std::thread::JoinHandle<()>>,
}

impl WorkerHandle {
    /// This node's id (the `<node>` of its keys).
    pub fn node_id(&self) -> &str {
        self.node.id()
    }
    /// Worlds this node has finished and published.
    pub fn worlds(&self) -> u64 {
        self.control.worlds.load(Ordering::Relaxed)
    }
    /// Worlds that failed and were not published.
    pub fn failed(&self) -> u64 {
        self.control.failed.load(Ordering::Relaxed)
    }
    /// Simulation steps of the published worlds.
    pub fn steps(&self) -> u64 {
        self.control.steps.load(Ordering::Relaxed)
    }
    /// Bus messages that did not decode, dropped.
    pub fn malformed(&self) -> u64 {
        self.node.malformed()
    }
    /// Stops the workers (after their current step or segment) and the bus tasks.
    pub async fn stop(self) {
        self.control.stop.store(true, Ordering::SeqCst);
        self.control.wake.notify_all();
        for w in self.workers {
            let name = w.thread().name().unwrap_or("worker").to_owned();
            if !matches!(
                tokio::task::spawn_blocking(move || w.join()).await,
                Ok(Ok(()))
            ) {
                warn!(thread = %name, "a worker thread panicked");
            }
        }
        for t in self.tasks {
            t.abort();
        }
    }
}

/// Starts a worker node of `kind` on `session` (in the current tokio runtime).
pub async fn run_workers<K: WorkerKind>(
    session: Session,
    cfg: WorkerConfig,
    kind: K,
) -> Result<WorkerHandle, NodeError> {
    let node = Node::new(&session, &cfg.space, cfg.node_id.as_deref(), K::ROLE)?;
    let jobs = node.subscribe(node.keys().jobs()).await?;
    let states = node.subscribe(node.keys().job_states()).await?;
    let token = node.declare_alive().await?;
    let control = Arc::new(Control::default());
    let shared = Arc::new(Shared {
        kind,
        node: node.clone(),
        board: Mutex::new(Board::new(K::takes, K::GIVE_UP_AFTER)),
        control: control.clone(),
        room: Mutex::new(StoreRoom::default()),
        paused: AtomicBool::new(false),
    });
    let stores = node
        .subscribe(node.keys().stats(mwb_core::keys::role::STORE, "*"))
        .await?;
    let (out, rx) = mpsc::channel::<Put>(cfg.queue.max(1));
    let workers = cfg.workers.max(1);
    let stats = {
        let shared = shared.clone();
        move || shared.stats(workers)
    };
    let mut handle = WorkerHandle {
        node: node.clone(),
        control,
        tasks: vec![
            tokio::spawn(bus::hold(token)),
            tokio::spawn(publish(node.clone(), rx)),
            tokio::spawn(follow_jobs(shared.clone(), jobs)),
            tokio::spawn(follow_states(shared.clone(), states)),
            tokio::spawn(follow_stores(shared.clone(), stores)),
            tokio::spawn(refresh(shared.clone(), cfg.refresh)),
            tokio::spawn(bus::publish_stats(node.clone(), stats)),
        ],
        workers: Vec::new(),
    };
    for w in 0..workers {
        match spawn_worker(&shared, &out, w) {
            Ok(t) => handle.workers.push(t),
            Err(e) => {
                handle.stop().await;
                return Err(e);
            }
        }
    }
    info!(node = %node.id(), role = K::ROLE, workers, space = %cfg.space, "worker node started");
    Ok(handle)
}

/// The publisher: the only sender of the workers' segments and summaries, in queue order.
async fn publish(node: Arc<Node>, mut rx: mpsc::Receiver<Put>) {
    while let Some(Put { key, bytes }) = rx.recv().await {
        node.put(&key, bytes).await;
    }
}

/// Job announcements.
async fn follow_jobs<K: WorkerKind>(shared: Arc<Shared<K>>, sub: Subscription) {
    bus::apply(shared.node.clone(), sub, |job: Job| shared.take_job(job)).await;
}

/// Job states: a job closes when the stores hold its target.
async fn follow_states<K: WorkerKind>(shared: Arc<Shared<K>>, sub: Subscription) {
    bus::apply(shared.node.clone(), sub, |st: JobState| {
        shared.lock().apply_state(&st);
    })
    .await;
}

/// The stores' statistics: their room under the memory cap.
async fn follow_stores<K: WorkerKind>(shared: Arc<Shared<K>>, sub: Subscription) {
    bus::apply(shared.node.clone(), sub, |st: NodeStats| {
        shared
            .room
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .observe(&st, Instant::now());
    })
    .await;
}

/// Late joining: asks the stores for the open jobs and their states, now and every `every`.
async fn refresh<K: WorkerKind>(shared: Arc<Shared<K>>, every: Duration) {
    let node = &shared.node;
    loop {
        let jobs = node.get::<Job>(node.keys().jobs()).await;
        let states = node.get::<JobState>(node.keys().job_states()).await;
        {
            let mut board = shared.lock();
            jobs.into_iter().for_each(|j| board.upsert(j));
            states.iter().for_each(|st| board.apply_state(st));
        }
        shared.control.wake.notify_all();
        tokio::time::sleep(every).await;
    }
}

fn spawn_worker<K: WorkerKind>(
    shared: &Arc<Shared<K>>,
    out: &mpsc::Sender<Put>,
    index: usize,
) -> Result<std::thread::JoinHandle<()>, NodeError> {
    let name = format!("mwb-{}-{index}", K::ROLE);
    let shared = shared.clone();
    let out = out.clone();
    std::thread::Builder::new()
        .name(name.clone())
        .spawn(move || work(&shared, &out))
        .map_err(|source| NodeError::Thread { name, source })
}

/// A worker thread: takes worlds from the board until the node stops.
fn work<K: WorkerKind>(shared: &Shared<K>, out: &mpsc::Sender<Put>) {
    let provenance = shared.kind.provenance();
    while !shared.control.stopping() {
        let Some(picked) = shared.next_world() else {
            continue;
        };
        if run_world(shared, out, &provenance, picked).is_break() {
            return;
        }
    }
}

/// Computes and publishes one world of `picked`. Breaks when the publisher is gone.
fn run_world<K: WorkerKind>(
    shared: &Shared<K>,
    out: &mpsc::Sender<Put>,
    provenance: &str,
    Picked { job, scene: slot }: Picked<K::Scene>,
) -> ControlFlow<()> {
    let Some(job_scene) = job.scene.as_ref() else {
        // The board hands out only jobs with a scene.
        shared.lock().refused(&job.id);
        return ControlFlow::Continue(());
    };
    let prepared = slot.get_or_init(|| match shared.kind.prepare(&job, job_scene) {
        Ok(s) => Some(Arc::new(s)),
        Err(e) => {
            warn!(job = %job.id, error = %e, "job scene refused; ignoring the job");
            shared
                .control
                .note_failure(format!("job {}: scene refused: {e}", job.id));
            None
        }
    });
    let Some(scene) = prepared.clone() else {
        shared.lock().refused(&job.id);
        return ControlFlow::Continue(());
    };
    let node = shared.node.as_ref();
    let control = shared.control.as_ref();
    let counter = control.counter.fetch_add(1, Ordering::Relaxed);
    let world = WorldTask {
        job: &job,
        node: node.id(),
        counter,
        seed: world_seed(&job.id, node.id(), counter),
    };
    let started = bus::cpu_time();
    let mut payload_bytes = 0u64;
    let mut emit = |seg: MotionSegment| -> ControlFlow<()> {
        if control.stopping() || !shared.lock().is_open(&job.id) {
            return ControlFlow::Break(());
        }
        payload_bytes += seg.payload.len() as u64;
        let put = Put {
            key: node.keys().segment(&job.id, node.id(), counter, seg.seq),
            bytes: seg.encode_to_vec(),
        };
        match out.blocking_send(put) {
            Ok(()) => ControlFlow::Continue(()),
            Err(_) => ControlFlow::Break(()),
        }
    };
    let result = shared.kind.run(&world, &scene, &mut emit);
    let ended = match &result {
        Ok(_) => Ended::Stored,
        Err(e) if K::stopped(e) => Ended::Stopped,
        Err(_) => Ended::Failed,
    };
    if let Some(failures) = shared.lock().finished(&job.id, ended) {
        warn!(job = %job.id, failures, "worlds keep failing; giving the job up locally");
    }
    match result {
        Ok(summary) => {
            let steps = summary.sim_steps;
            let done = WorldDone {
                cpu_seconds: bus::cpu_time() - started,
                provenance: provenance.to_owned(),
                scene_hash: job_scene.content_hash,
                ..summary
            };
            let put = Put {
                key: node.keys().done(&job.id, node.id(), counter),
                bytes: done.encode_to_vec(),
            };
            if out.blocking_send(put).is_err() {
                return ControlFlow::Break(());
            }
            control.worlds.fetch_add(1, Ordering::Relaxed);
            control.steps.fetch_add(steps, Ordering::Relaxed);
            control.bytes.fetch_add(payload_bytes, Ordering::Relaxed);
        }
        Err(e) if K::stopped(&e) => debug!(job = %job.id, counter, "world abandoned: job closed"),
        Err(e) => {
            control.failed.fetch_add(1, Ordering::Relaxed);
            warn!(job = %job.id, counter, error = %e, "world failed");
            control.note_failure(format!("job {}: world failed: {e}", job.id));
        }
    }
    ControlFlow::Continue(())
}
