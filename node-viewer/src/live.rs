//! A live viewer's bus task: everything the viewer needs from a running cluster, on a tokio
//! task and never on the UI thread. It talks to the UI through two bounded channels: the UI
//! hands it [`Command`]s without waiting ([`LiveLink::send`]), and it hands back [`Msg`]s that
//! the UI applies once per frame ([`LiveLink::drain`]), waking the UI when it does.
//!
//! Every poll (twice a second by default) it asks
//! * the stores' `q/paths` for worlds indexed since last time (one cursor per shard), and the
//!   scene of each new job (`q/job/<job>`). When the stores hold more worlds than the viewer
//!   draws well ([`LiveConfig::max_worlds`]), it holds a sample of them
//!   ([`mwb_core::browse::sample`]): half its budget a uniform sample of every world, which the
//!   stores filter for it, half the survivors with the smallest sampling hashes, which it asks
//!   for by index whenever the survivors change; worlds that leave the sample are let go
//!   ([`Msg::Evict`]);
//! * node-query for the session's status and survivors (`browse/<session>`);
//! * liveliness, store statistics and job states, for the status bar.
//!
//! Every request has a timeout. Edits the user made while node-query could not be reached are
//! kept, in order, and sent when it answers again; if node-query lost the session (it
//! restarted), the edits it lacks are sent again, so nothing the user drew is lost.

use std::collections::{BTreeMap, HashMap, HashSet, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use mwb_core::browse::api::{Reply, Request};
use mwb_core::browse::sample::{bottom_k, context_threshold, in_context};
use mwb_core::keys::{Keys, role};
use mwb_core::scene::SceneTemplate;
use mwb_proto::v1::{Job, JobState, Message, NodeStats, PathBatch, PathsRequest, Quality, World};
use tokio::sync::mpsc;
use zenoh::Session;

use crate::session::Command;
use crate::state::{LinkStatus, Msg};
use crate::world::{Motion, WorldData};

/// Commands the UI may queue before [`LiveLink::send`] reports the link busy.
pub const COMMAND_QUEUE: usize = 256;
/// Messages the bus task may queue for the UI before it waits for the UI to take them.
pub const EVENT_QUEUE: usize = 256;

/// The default of [`LiveConfig::max_worlds`].
pub const DEFAULT_MAX_WORLDS: usize = 20_000;

/// Settings of the bus task.
#[derive(Debug, Clone)]
pub struct LiveConfig {
    /// Browsing space (`mwb/<space>/…`).
    pub space: String,
    /// The browsing session the viewer's constraints live in (`mwb query --session` sees the
    /// same one).
    pub session: String,
    /// Where the viewer connects, as the user gave it (for the status bar).
    pub endpoint: String,
    /// Time between polls; default 500 ms.
    pub poll: Duration,
    /// Timeout of every request; default 5 s.
    pub timeout: Duration,
    /// Worlds per shard asked in one `q/paths` request; default 512.
    pub path_batch: u32,
    /// The most worlds whose paths the viewer holds and draws (0: every world); default
    /// 20 000. Past it the viewer holds a sample: about half of it a uniform sample of all the
    /// stores' worlds (drawn dim when rejected), the other half the survivors with the smallest
    /// sampling hashes, so that a narrow result is drawn whole and a wide one as a uniform
    /// sample. 10 000 worlds of one object's path draw in about 10 ms a frame
    /// (docs/performance.md).
    pub max_worlds: usize,
}

impl Default for LiveConfig {
    fn default() -> Self {
        Self {
            space: mwb_core::keys::DEFAULT_SPACE.into(),
            session: "viewer".into(),
            endpoint: String::new(),
            poll: Duration::from_millis(500),
            timeout: Duration::from_secs(5),
            path_batch: 512,
            max_worlds: DEFAULT_MAX_WORLDS,
        }
    }
}

/// Why the link could not start.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    #[error(transparent)]
    Key(#[from] mwb_core::keys::BadIdentifier),
}

/// The UI's end of the bus task.
pub struct LiveLink {
    commands: mpsc::Sender<Command>,
    events: mpsc::Receiver<Msg>,
    task: tokio::task::JoinHandle<()>,
}

impl LiveLink {
    /// Starts the bus task on `runtime`. `wake` is called after messages are queued (the
    /// window's repaint request).
    pub fn start(
        session: Session,
        cfg: LiveConfig,
        runtime: &tokio::runtime::Handle,
        wake: Arc<dyn Fn() + Send + Sync>,
    ) -> Result<Self, LiveError> {
        let keys = Keys::new(&cfg.space)?;
        mwb_core::keys::check_identifier("session", &cfg.session)?;
        let (ctx, crx) = mpsc::channel(COMMAND_QUEUE);
        let (etx, erx) = mpsc::channel(EVENT_QUEUE);
        let task = Bus {
            session,
            keys,
            cfg,
            events: etx,
            wake,
            seen: Vec::new(),
            indexed: Vec::new(),
            held: HashSet::new(),
            survivor_sample: Vec::new(),
            survivors_fetched: true,
            scenes: Arc::new(Mutex::new(HashMap::new())),
            scene_sent: false,
            log: Vec::new(),
            unsent: VecDeque::new(),
            handled: 0,
            last_session: None,
            last_rate: None,
            rate: 0.0,
        };
        let task = runtime.spawn(task.run(crx));
        Ok(Self {
            commands: ctx,
            events: erx,
            task,
        })
    }

    /// Hands a command to the bus task without waiting; gives it back when the queue is full
    /// or the task has stopped (the caller keeps it and tries again).
    pub fn send(&self, cmd: Command) -> Result<(), Command> {
        self.commands.try_send(cmd).map_err(|e| match e {
            mpsc::error::TrySendError::Full(c) | mpsc::error::TrySendError::Closed(c) => c,
        })
    }

    /// The messages the bus task has queued, without waiting.
    pub fn drain(&mut self) -> Vec<Msg> {
        let mut out = Vec::new();
        while let Ok(m) = self.events.try_recv() {
            out.push(m);
        }
        out
    }

    /// Whether the bus task is still running.
    pub fn is_running(&self) -> bool {
        !self.task.is_finished()
    }
}

impl Drop for LiveLink {
    fn drop(&mut self) {
        self.task.abort();
    }
}

type SceneCache = Arc<Mutex<HashMap<String, Result<Arc<JobScene>, String>>>>;

/// A job's scene as the viewer draws its worlds: the template, and the job (a scene-edit job's
/// worlds are instances of the edited scene made from its parent's, `mwb_export::world_instance`).
struct JobScene {
    template: SceneTemplate,
    job: Job,
}

struct Bus {
    session: Session,
    keys: Keys,
    cfg: LiveConfig,
    events: mpsc::Sender<Msg>,
    wake: Arc<dyn Fn() + Send + Sync>,
    /// Per shard index, local world slots seen.
    seen: Vec<u32>,
    /// Per shard index, the worlds it has indexed, as its last path batch said.
    indexed: Vec<u64>,
    /// The worlds whose paths were handed to the UI and not let go since.
    held: HashSet<u32>,
    /// The survivors held as such ([`bottom_k`] of the last survivor list), ascending.
    survivor_sample: Vec<u32>,
    /// The last fetch of the sampled survivors' paths succeeded.
    survivors_fetched: bool,
    /// Job id → its scene (or why it has none).
    scenes: SceneCache,
    scene_sent: bool,
    /// The session's edits this viewer made and node-query accepted, in order.
    log: Vec<Request>,
    /// Edits not yet delivered (node-query unreachable), in order.
    unsent: VecDeque<Request>,
    /// Edit commands handled (answered or refused).
    handled: u32,
    /// The session status (and edits handled) last reported to the UI.
    last_session: Option<(mwb_core::browse::api::SessionStatus, u32)>,
    last_rate: Option<(Instant, u64)>,
    rate: f64,
}

/// What one edit's delivery came to.
enum Delivery {
    Accepted,
    Refused(String),
    Unreachable(String),
}

impl Bus {
    async fn run(mut self, mut commands: mpsc::Receiver<Command>) {
        let mut tick = tokio::time::interval(self.cfg.poll);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                cmd = commands.recv() => match cmd {
                    Some(c) => self.command(c).await,
                    None => return,
                },
                _ = tick.tick() => self.poll().await,
            }
        }
    }

    async fn emit(&self, msg: Msg) {
        // Waiting here is the back-pressure: the UI takes messages every frame.
        if self.events.send(msg).await.is_ok() {
            (self.wake)();
        }
    }

    async fn command(&mut self, cmd: Command) {
        match cmd {
            Command::Rank(spec) => match self.browse(&spec.request()).await {
                Ok(reply) => self.emit(Msg::Ranked { spec, reply }).await,
                Err(e) => self.emit(Msg::BrowseFailed(e)).await,
            },
            Command::Browse(req) if req.is_edit() => {
                self.unsent.push_back(req);
                self.deliver().await;
                self.refresh_session().await;
            }
            Command::Browse(req) => match self.browse(&req).await {
                Ok(Reply::Error { message }) => self.emit(Msg::BrowseFailed(message)).await,
                Ok(_) => {}
                Err(e) => self.emit(Msg::BrowseFailed(e)).await,
            },
            Command::SubmitJob {
                scene,
                worlds,
                quality,
                sim,
            } => {
                let notice = self.submit(&scene, worlds, quality, sim).await;
                self.emit(Msg::JobNotice(notice)).await;
            }
            Command::CancelJob(job) => {
                let notice = self.cancel(&job).await;
                self.emit(Msg::JobNotice(notice)).await;
            }
            Command::Refine {
                world,
                objects,
                frustum,
                worlds,
            } => {
                let notice = self.refine(world, &objects, *frustum, worlds).await;
                self.emit(Msg::JobNotice(notice)).await;
            }
            Command::FetchPaths(worlds) => {
                if let Err(e) = self.fetch_paths(&worlds).await {
                    self.emit(Msg::Problem(format!("fetching paths: {e}")))
                        .await;
                }
            }
            Command::FetchMotion { world, job } => {
                let session = self.session.clone();
                let keys = self.keys.clone();
                let timeout = self.cfg.timeout;
                let scenes = self.scenes.clone();
                let events = self.events.clone();
                let wake = self.wake.clone();
                tokio::spawn(async move {
                    let motion = fetch_motion(&session, &keys, timeout, &scenes, world, &job)
                        .await
                        .map(Arc::new);
                    if events
                        .send(Msg::MotionLoaded { world, motion })
                        .await
                        .is_ok()
                    {
                        wake();
                    }
                });
            }
        }
    }

    /// Reads the scene (off the runtime: it may be a file), announces the job and waits until
    /// a store has taken it.
    async fn submit(
        &self,
        scene: &str,
        worlds: u32,
        quality: Quality,
        sim: Option<mwb_core::scene::SimPreset>,
    ) -> Result<String, String> {
        let arg = scene.to_owned();
        // Reading, calibrating (`auto`: seconds) and checking run off the async threads.
        let (mut job, said) = tokio::task::spawn_blocking(move || prepare_job(&arg, worlds, sim))
            .await
            .map_err(|e| format!("reading the scene: {e}"))??;
        job.quality = quality as i32;
        self.announce(&job).await?;
        let deadline = Instant::now() + Duration::from_secs(15);
        loop {
            let states = self.get_all(&self.keys.job_state(&job.id), None).await?;
            if !states.is_empty() {
                return Ok(format!(
                    "job {} submitted: {worlds} worlds of {scene}{said}",
                    job.id
                ));
            }
            if Instant::now() > deadline {
                return Err(format!(
                    "job {}: no store took it within 15 s (is a store running?)",
                    job.id
                ));
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }

    /// Refines stored world `world` (§4.5): fetches it and its job, checks the request
    /// (`mwb_sampler::request::plan`, which regenerates the world off the async threads), and
    /// announces the REFINE job, as `mwb refine` does.
    async fn refine(
        &self,
        world: u32,
        objects: &[u32],
        frustum: mwb_core::browse::Frustum,
        worlds: u32,
    ) -> Result<String, String> {
        let timeout = self.cfg.timeout;
        let replies = get_all(&self.session, &self.keys.world(world), None, timeout).await?;
        let bytes = replies
            .first()
            .ok_or_else(|| format!("no store holds world {world}"))?;
        let stored = World::decode(bytes.as_slice())
            .map_err(|e| format!("world {world}: malformed reply: {e}"))?;
        let replies = get_all(
            &self.session,
            &self.keys.held_job(&stored.job_id),
            None,
            timeout,
        )
        .await?;
        let parent_job = replies
            .iter()
            .filter_map(|b| Job::decode(b.as_slice()).ok())
            .filter(|j| j.id == stored.job_id)
            .max_by_key(|j| j.revision)
            .ok_or_else(|| format!("world {world}: no store serves its job {}", stored.job_id))?;
        let text = objects
            .iter()
            .map(u32::to_string)
            .collect::<Vec<_>>()
            .join(",");
        let plan = tokio::task::spawn_blocking(move || {
            mwb_sampler::request::plan(&stored, &parent_job, &text, frustum)
        })
        .await
        .map_err(|e| format!("refining: {e}"))?
        .map_err(|e| e.to_string())?;
        let id = format!("{}-w{world}-{:x}", plan.parent_job, unix_ms());
        let job = plan.job(id.clone(), worlds, 0, unix_ms());
        self.announce(&job).await?;
        Ok(format!(
            "job {id} submitted: {worlds} worlds refining world {world} from frame {} (t = {:.3} s)",
            plan.branch_frame,
            plan.branch_time_s()
        ))
    }

    /// Re-announces an open job with `cancelled` set.
    async fn cancel(&self, id: &str) -> Result<String, String> {
        let replies = self.get_all(&self.keys.job(id), None).await?;
        let mut job = replies
            .iter()
            .filter_map(|b| Job::decode(b.as_slice()).ok())
            .filter(|j| j.id == id)
            .max_by_key(|j| j.revision)
            .ok_or_else(|| format!("job {id} is not open on any store"))?;
        job.revision += 1;
        job.cancelled = true;
        self.announce(&job).await?;
        Ok(format!("job {id} cancelled"))
    }

    async fn announce(&self, job: &Job) -> Result<(), String> {
        self.session
            .put(self.keys.job(&job.id), job.encode_to_vec())
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .await
            .map_err(|e| format!("announcing job {}: {e}", job.id))
    }

    /// One browsing request to node-query; `Err` when it could not be reached.
    async fn browse(&self, req: &Request) -> Result<Reply, String> {
        mwb_query::send(
            &self.session,
            &self.keys,
            &self.cfg.session,
            req,
            self.cfg.timeout,
        )
        .await
        .map_err(|e| e.to_string())
    }

    /// Sends the queued edits in order until one cannot be delivered.
    async fn deliver(&mut self) {
        while let Some(req) = self.unsent.front().cloned() {
            let outcome = match self.browse(&req).await {
                Ok(Reply::Error { message }) => Delivery::Refused(message),
                Ok(_) => Delivery::Accepted,
                Err(e) => Delivery::Unreachable(e),
            };
            match outcome {
                Delivery::Accepted => {
                    self.unsent.pop_front();
                    self.log.push(req);
                    self.handled += 1;
                }
                Delivery::Refused(message) => {
                    self.unsent.pop_front();
                    self.handled += 1;
                    self.emit(Msg::BrowseFailed(message)).await;
                }
                Delivery::Unreachable(e) => {
                    self.emit(Msg::BrowseFailed(format!(
                        "{e} — {} edit(s) kept, sent when node-query answers",
                        self.unsent.len()
                    )))
                    .await;
                    return;
                }
            }
        }
    }

    /// The session's status and survivors; first sends node-query the edits it lacks (it
    /// restarted and lost the session) or that could not be delivered before.
    async fn refresh_session(&mut self) -> bool {
        let mut status = None;
        for _ in 0..2 {
            let s = match self.browse(&Request::Status).await {
                Ok(Reply::Status(s)) => s,
                Ok(other) => {
                    self.emit(Msg::BrowseFailed(format!(
                        "node-query answered a status request with {other:?}"
                    )))
                    .await;
                    return false;
                }
                Err(_) => return false,
            };
            if (s.edits as usize) < self.log.len() && self.unsent.is_empty() {
                let missing: Vec<Request> = self.log.split_off(s.edits as usize);
                self.handled = self.handled.saturating_sub(missing.len() as u32);
                self.unsent.extend(missing);
                self.deliver().await;
                continue;
            }
            status = Some(s);
            break;
        }
        let Some(status) = status else {
            return false;
        };
        // The survivor list is fetched only when something changed: at a million worlds it is
        // megabytes, and polls come twice a second.
        let key = (status.clone(), self.handled);
        if self.last_session.as_ref() == Some(&key) {
            return true;
        }
        let survivors = match self.browse(&Request::Result { limit: None }).await {
            Ok(Reply::Worlds { worlds, .. }) => worlds,
            _ => return false,
        };
        // The survivors to hold: all of them while they fit half the budget, else the ones
        // with the smallest sampling hashes (a uniform sample that keeps its members as
        // constraints narrow it).
        let sample =
            (self.cfg.max_worlds > 0).then(|| bottom_k(&survivors, self.cfg.max_worlds / 2));
        self.emit(Msg::Session {
            status,
            survivors,
            handled_edits: self.handled,
        })
        .await;
        match sample {
            Some(sample) => {
                let result = self.fetch_paths(&sample).await;
                self.survivor_sample = sample;
                let fetched = result.is_ok();
                if let (Err(e), true) = (result, self.survivors_fetched) {
                    self.emit(Msg::Problem(format!("fetching survivors' paths: {e}")))
                        .await;
                }
                self.survivors_fetched = fetched;
                // Asked again next poll until it works.
                if fetched {
                    self.last_session = Some(key);
                }
                self.evict().await;
            }
            None => self.last_session = Some(key),
        }
        true
    }

    async fn poll(&mut self) {
        let mut link = LinkStatus {
            endpoint: self.cfg.endpoint.clone(),
            max_worlds: self.cfg.max_worlds,
            ..LinkStatus::default()
        };
        self.poll_paths(&mut link).await;
        if !self.unsent.is_empty() {
            self.deliver().await;
        }
        let session_ok = self.refresh_session().await;
        link.synced &= session_ok && self.survivors_fetched;
        link.indexed = self.total();
        link.held = self.held.len() as u64;
        self.poll_cluster(&mut link).await;
        link.connected = session_ok;
        if !session_ok && link.error.is_none() {
            link.error = Some(if link.stores == 0 {
                "no store answers".into()
            } else {
                "node-query does not answer (is `mwb query serve` or the store's shard 0 running?)"
                    .into()
            });
        }
        self.emit(Msg::Link(link)).await;
    }

    /// Worlds the stores hold, as their last path batches said.
    fn total(&self) -> u64 {
        self.indexed.iter().sum()
    }

    /// The context's sampling threshold now ([`context_threshold`] of half the budget; 0:
    /// every world).
    fn threshold(&self) -> u32 {
        match self.cfg.max_worlds {
            0 => 0,
            max => context_threshold(max as u64 / 2, self.total()),
        }
    }

    /// Lets go of the held worlds that are neither in the context nor among the sampled
    /// survivors (the threshold fell as worlds arrived, or the survivors changed).
    async fn evict(&mut self) {
        let t = self.threshold();
        let gone: Vec<u32> = self
            .held
            .iter()
            .copied()
            .filter(|&w| !in_context(w, t) && self.survivor_sample.binary_search(&w).is_err())
            .collect();
        if gone.is_empty() {
            return;
        }
        for w in &gone {
            self.held.remove(w);
        }
        self.emit(Msg::Evict(gone)).await;
    }

    /// Hands paths to the UI (and announces their jobs' scenes), noting them held.
    async fn hand_over(&mut self, worlds: Vec<WorldData>) {
        if worlds.is_empty() {
            return;
        }
        self.held.extend(worlds.iter().map(|w| w.index));
        self.announce_scenes(&worlds).await;
        self.emit(Msg::Worlds(worlds)).await;
    }

    /// Every shard's answer to `req` on `q/paths`, decoded (a malformed one is reported and
    /// passed over).
    async fn path_batches(&self, req: &PathsRequest) -> Result<Vec<PathBatch>, String> {
        let replies = self
            .get_all(&self.keys.paths(), Some(req.encode_to_vec()))
            .await?;
        let mut out = Vec::with_capacity(replies.len());
        for bytes in replies {
            match PathBatch::decode(bytes.as_slice()) {
                Ok(b) => out.push(b),
                Err(_) => {
                    self.emit(Msg::Problem("a store sent a malformed path batch".into()))
                        .await
                }
            }
        }
        Ok(out)
    }

    /// A batch's worlds as the viewer holds them, into `into` (a world whose paths do not
    /// check is reported and passed over).
    async fn worlds_of(&self, b: &PathBatch, into: &mut Vec<WorldData>) {
        for p in &b.worlds {
            match WorldData::from_paths(p) {
                Ok(w) => into.push(w),
                Err(e) => {
                    self.emit(Msg::Problem(format!("world {}: {e}", p.world)))
                        .await
                }
            }
        }
    }

    /// The paths of `worlds` that are not held, asked of every store by index.
    async fn fetch_paths(&mut self, worlds: &[u32]) -> Result<(), String> {
        let missing: Vec<u32> = worlds
            .iter()
            .copied()
            .filter(|w| !self.held.contains(w))
            .collect();
        for chunk in missing.chunks(self.cfg.path_batch.max(1) as usize) {
            let req = PathsRequest {
                max_worlds: chunk.len() as u32,
                worlds: chunk.to_vec(),
                ..PathsRequest::default()
            };
            let batches = self.path_batches(&req).await?;
            let mut got = Vec::new();
            for b in &batches {
                self.worlds_of(b, &mut got).await;
            }
            self.hand_over(got).await;
        }
        Ok(())
    }

    /// New worlds from every shard (those in the context: every world while the stores hold
    /// no more than half the budget), batch after batch while shards have more; then lets go
    /// of the worlds the falling threshold left out.
    async fn poll_paths(&mut self, link: &mut LinkStatus) {
        link.synced = self.poll_new_paths(link).await && link.error.is_none();
        self.evict().await;
    }

    /// Whether it read every shard to the end.
    async fn poll_new_paths(&mut self, link: &mut LinkStatus) -> bool {
        for _ in 0..64 {
            let req = PathsRequest {
                seen: self.seen.clone(),
                max_worlds: self.cfg.path_batch,
                sample_below: self.threshold(),
                ..PathsRequest::default()
            };
            let batches = match self.path_batches(&req).await {
                Ok(b) => b,
                Err(e) => {
                    link.error = Some(e);
                    return false;
                }
            };
            let mut more = false;
            let mut worlds = Vec::new();
            for b in batches {
                let shard = b.shard_index as usize;
                if self.seen.len() <= shard {
                    self.seen.resize(shard + 1, 0);
                }
                if self.indexed.len() <= shard {
                    self.indexed.resize(shard + 1, 0);
                }
                self.indexed[shard] = b.indexed;
                if b.next_local < self.seen[shard] {
                    // The shard holds fewer worlds than we saw: it restarted without them.
                    self.seen[shard] = 0;
                    let count = b.shard_count;
                    self.held
                        .retain(|&w| !(count > 0 && w % count == b.shard_index));
                    self.emit(Msg::ForgetShard {
                        shard: b.shard_index,
                        count: b.shard_count,
                    })
                    .await;
                    more = true;
                    continue;
                }
                more |= b.next_local > self.seen[shard]
                    && b.worlds.len() >= self.cfg.path_batch as usize;
                self.seen[shard] = b.next_local;
                self.worlds_of(&b, &mut worlds).await;
            }
            self.hand_over(worlds).await;
            if !more {
                return true;
            }
        }
        false
    }

    /// Fetches the scenes of jobs not seen before; the first one becomes the view's scene.
    async fn announce_scenes(&mut self, worlds: &[WorldData]) {
        let mut jobs: Vec<&str> = worlds.iter().map(|w| w.job.as_str()).collect();
        jobs.dedup();
        for job in jobs {
            let known = lock(&self.scenes).contains_key(job);
            if !known {
                let t = job_scene(&self.session, &self.keys, self.cfg.timeout, job).await;
                lock(&self.scenes).insert(job.to_owned(), t);
            }
            if self.scene_sent {
                continue;
            }
            let template = lock(&self.scenes).get(job).cloned();
            match template {
                Some(Ok(js)) => {
                    let t = &js.template;
                    self.scene_sent = true;
                    let first = t.instantiate(0);
                    self.emit(Msg::Scene {
                        name: t.name().to_owned(),
                        bodies: t.body_names().map(str::to_owned).collect(),
                        statics: first.statics.clone(),
                        initial: first.bodies.clone(),
                    })
                    .await;
                }
                Some(Err(e)) => self.emit(Msg::Problem(e)).await,
                None => {}
            }
        }
    }

    /// Liveliness, store statistics and open jobs.
    async fn poll_cluster(&mut self, link: &mut LinkStatus) {
        link.stores = self.count_alive(role::STORE).await;
        link.samplers = self.count_alive(role::SAMPLER).await;
        if let Ok(stats) = self.get_all(&self.keys.store_stats(), None).await {
            for bytes in stats {
                if let Ok(s) = NodeStats::decode(bytes.as_slice()) {
                    link.store_worlds += s.worlds;
                    link.memory_bytes += s.memory_bytes;
                    link.memory_cap_bytes += s.memory_cap_bytes;
                }
            }
        }
        let now = Instant::now();
        if let Some((t, n)) = self.last_rate {
            let dt = now.duration_since(t).as_secs_f64();
            if dt > 0.0 {
                let r = link.store_worlds.saturating_sub(n) as f64 / dt;
                self.rate = 0.6 * self.rate + 0.4 * r;
            }
        }
        self.last_rate = Some((now, link.store_worlds));
        link.worlds_per_s = self.rate;
        if let Ok(states) = self.get_all(&self.keys.job_states(), None).await {
            let mut open: BTreeMap<String, (u32, u32)> = BTreeMap::new();
            for bytes in states {
                if let Ok(s) = JobState::decode(bytes.as_slice())
                    && !s.closed
                {
                    open.insert(s.job_id, (s.worlds_done, s.target_worlds));
                }
            }
            link.jobs = open.into_iter().map(|(j, (d, t))| (j, d, t)).collect();
        }
    }

    async fn count_alive(&self, r: &str) -> u32 {
        let Ok(replies) = self
            .session
            .liveliness()
            .get(self.keys.alive_role(r))
            .timeout(self.cfg.timeout)
            .await
        else {
            return 0;
        };
        let mut n = 0;
        while let Ok(reply) = replies.recv_async().await {
            n += u32::from(reply.result().is_ok());
        }
        n
    }

    /// Every reply's payload to a query on `key`.
    async fn get_all(&self, key: &str, payload: Option<Vec<u8>>) -> Result<Vec<Vec<u8>>, String> {
        get_all(&self.session, key, payload, self.cfg.timeout).await
    }
}

/// A sampling job of the scene `arg` (a file or a shipped name) as the CLI's `mwb job submit
/// --sim` makes it: the preset written into its text (`auto` calibrated on the scene), checked
/// for what the simulator cannot do faithfully (a refusal is an error naming body and field).
/// Returns the job and what to tell the user besides (the preset `auto` chose, the first
/// warning).
fn prepare_job(
    arg: &str,
    worlds: u32,
    sim: Option<mwb_core::scene::SimPreset>,
) -> Result<(mwb_proto::v1::Job, String), String> {
    use mwb_core::scene::{SceneTemplate, SimPreset, edit_text::set_sim_preset};
    let err = |e: &dyn std::error::Error| mwb_query::error_chain(e);
    let (file, text) = mwb_node::load_scene(arg).map_err(|e| err(&e))?;
    let template = SceneTemplate::parse(&text, &file).map_err(|e| err(&e))?;
    let wanted = sim.unwrap_or(template.settings().sim);
    let mut said = String::new();
    let text = match (sim, wanted) {
        (_, SimPreset::Auto) => {
            let cal = mwb_sampler::fidelity::calibrate(&template, 24).map_err(|e| err(&e))?;
            said = format!("; sim auto chose {}", cal.chosen);
            set_sim_preset(
                &text,
                &file,
                cal.chosen,
                Some("chosen by sim = \"auto\" (viewer)"),
            )
            .map_err(|e| err(&e))?
        }
        (Some(p), _) => set_sim_preset(&text, &file, p, None).map_err(|e| err(&e))?,
        (None, _) => text,
    };
    let template = SceneTemplate::parse(&text, &file).map_err(|e| err(&e))?;
    let found = mwb_sampler::limits::check_template(&template);
    if mwb_sampler::limits::refuses(&found) {
        let lines: Vec<String> = found
            .iter()
            .filter(|f| f.severity == mwb_sampler::limits::Severity::Refuse)
            .map(|f| f.line(&file))
            .collect();
        return Err(lines.join("; "));
    }
    if let Some(w) = found.first() {
        said.push_str(&format!("; {}", w.line(&file)));
    }
    let job =
        mwb_node::sample_job(&file, &text, worlds, 0, None, unix_ms()).map_err(|e| err(&e))?;
    Ok((job, said))
}

fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

async fn get_all(
    session: &Session,
    key: &str,
    payload: Option<Vec<u8>>,
    timeout: Duration,
) -> Result<Vec<Vec<u8>>, String> {
    let mut get = session.get(key).timeout(timeout);
    if let Some(p) = payload {
        get = get.payload(p);
    }
    let replies = get.await.map_err(|e| format!("query {key}: {e}"))?;
    let mut out = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        match reply.result() {
            Ok(s) => out.push(s.payload().to_bytes().to_vec()),
            Err(e) => {
                return Err(format!(
                    "query {key}: {}",
                    String::from_utf8_lossy(&e.payload().to_bytes())
                ));
            }
        }
    }
    Ok(out)
}

/// The scene of `job`, from the store that holds its worlds.
async fn job_scene(
    session: &Session,
    keys: &Keys,
    timeout: Duration,
    job: &str,
) -> Result<Arc<JobScene>, String> {
    let replies = get_all(session, &keys.held_job(job), None, timeout).await?;
    let bytes = replies
        .first()
        .ok_or_else(|| format!("job {job}: no store holds it"))?;
    let job_msg =
        Job::decode(bytes.as_slice()).map_err(|e| format!("job {job}: malformed reply: {e}"))?;
    let scene = job_msg
        .scene
        .as_ref()
        .ok_or_else(|| format!("job {job}: it carries no scene"))?;
    let template = SceneTemplate::parse(&scene.toml, &scene.name)
        .map_err(|e| format!("job {job}: its scene cannot be drawn here: {e}"))?;
    Ok(Arc::new(JobScene {
        template,
        job: job_msg,
    }))
}

/// Fetches world `world` from the store and decodes its motion for its scene instance.
async fn fetch_motion(
    session: &Session,
    keys: &Keys,
    timeout: Duration,
    scenes: &SceneCache,
    world: u32,
    job: &str,
) -> Result<Motion, String> {
    let replies = get_all(session, &keys.world(world), None, timeout).await?;
    let bytes = replies
        .first()
        .ok_or_else(|| format!("no store holds world {world}"))?;
    let w = World::decode(bytes.as_slice()).map_err(|e| format!("malformed world: {e}"))?;
    let done = w
        .done
        .as_ref()
        .ok_or_else(|| format!("world {world} has no summary"))?;
    let cached = lock(scenes).get(job).cloned();
    let js = match cached {
        Some(t) => t?,
        None => {
            let t = job_scene(session, keys, timeout, job).await;
            lock(scenes).insert(job.to_owned(), t.clone());
            t?
        }
    };
    // A refined world is an instance of its root world's scene (§4.5: its seed is its own), an
    // edited one the edit of its parent's.
    let scene = mwb_export::world_instance(&js.template, Some(&js.job), done)
        .map_err(|e| format!("job {job}: {e}"))?;
    tokio::task::spawn_blocking(move || Motion::decode(scene, &w).map_err(|e| e.to_string()))
        .await
        .map_err(|e| format!("decoding task failed: {e}"))?
}

#[cfg(test)]
mod tests {
    use super::*;
    use mwb_core::scene::SimPreset;

    /// The jobs panel's preset goes into the job's scene, and a scene the simulator cannot do
    /// faithfully is refused naming body and field (as `mwb job submit` does).
    #[test]
    fn a_job_from_the_panel_carries_its_preset_and_refusals_name_the_body() {
        let (job, said) =
            prepare_job("tumble", 5, Some(SimPreset::Draft)).unwrap_or_else(|e| panic!("{e}"));
        let text = job.scene.map(|s| s.toml).unwrap_or_default();
        assert!(text.contains("sim = \"draft\""), "{text}");
        assert!(said.is_empty(), "{said}");
        let (job, _) = prepare_job("tumble", 5, None).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            job.scene.map(|s| s.toml).as_deref(),
            Some(mwb_core::scene::builtin::TUMBLE)
        );
        let dir = std::env::temp_dir().join(format!("mwb-viewer-limits-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{e}"));
        let file = dir.join("bullet.toml");
        std::fs::write(
            &file,
            "name = \"bullet\"\n[settings]\nend_time = 0.2\ngravity = [0, 0, 0]\n\
             [[material]]\nname = \"m\"\n\
             [[static]]\nname = \"wall\"\nshape = \"box\"\nsize = [0.1, 2, 2]\nmaterial = \"m\"\nposition = [5, 1, 0]\n\
             [[body]]\nname = \"bullet\"\nshape = \"sphere\"\nradius = 0.05\nmaterial = \"m\"\n\
             position = [0, 1, 0]\nlinvel = [1000, 0, 0]\n",
        )
        .unwrap_or_else(|e| panic!("{e}"));
        let refused = prepare_job(&file.to_string_lossy(), 5, None)
            .err()
            .unwrap_or_default();
        assert!(
            refused.contains("refused: body \"bullet\": field `linvel`"),
            "{refused}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
