//! Client-side bus operations shared by the CLI, the demo and the benchmarks: submitting and
//! following jobs, fetching worlds, reading node status. Every wait is bounded.

use crate::stall::Watch;
use anyhow::{Context, Result, anyhow, bail};
use mwb_core::keys::{Keys, role};
use mwb_core::scene::SimPreset;
use mwb_proto::v1::{Encoding, Job, JobKind, JobState, Message, NodeStats, Quality, Scene, World};
use std::collections::BTreeMap;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use zenoh::Session;
use zenoh::qos::CongestionControl;

pub fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// Reads a scene argument: a path to a TOML file, or the name of a shipped scene
/// ([`mwb_node::load_scene`]).
pub fn load_scene(arg: &str) -> Result<(String, String)> {
    Ok(mwb_node::load_scene(arg)?)
}

/// Builds a job for `target` worlds of the scene text, validating the scene first
/// ([`mwb_node::sample_job`]).
pub fn make_job(
    file: &str,
    text: &str,
    target: u32,
    priority: i32,
    id: Option<String>,
) -> Result<Job> {
    Ok(mwb_node::sample_job(
        file,
        text,
        target,
        priority,
        id,
        unix_ms(),
    )?)
}

/// Waits until at least one store is alive.
pub async fn wait_for_store(session: &Session, keys: &Keys, timeout: Duration) -> Result<()> {
    let deadline = Instant::now() + timeout;
    loop {
        let replies = session
            .liveliness()
            .get(keys.alive_role(role::STORE))
            .timeout(Duration::from_millis(500))
            .await
            .map_err(|e| anyhow!("liveliness query: {e}"))?;
        if let Ok(reply) = replies.recv_async().await
            && reply.result().is_ok()
        {
            return Ok(());
        }
        if Instant::now() > deadline {
            bail!("no store answered within {timeout:?} (is `mwb store` running and reachable?)");
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Current state of a job from the stores, if any store knows it.
pub async fn job_state(session: &Session, keys: &Keys, job: &str) -> Result<Option<JobState>> {
    let replies = session
        .get(keys.job_state(job))
        .timeout(Duration::from_secs(2))
        .await
        .map_err(|e| anyhow!("job state query: {e}"))?;
    let mut best: Option<JobState> = None;
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(s) = reply.result()
            && let Ok(st) = JobState::decode(s.payload().to_bytes().as_ref())
            && best.as_ref().is_none_or(|b| st.revision > b.revision)
        {
            best = Some(st);
        }
    }
    Ok(best)
}

/// Announces a job and waits until a store acknowledges it.
pub async fn submit_job(session: &Session, keys: &Keys, job: &Job) -> Result<JobState> {
    wait_for_store(session, keys, Duration::from_secs(15)).await?;
    let deadline = Instant::now() + Duration::from_secs(15);
    loop {
        session
            .put(keys.job(&job.id), job.encode_to_vec())
            .congestion_control(CongestionControl::Block)
            .await
            .map_err(|e| anyhow!("announcing job: {e}"))?;
        for _ in 0..10 {
            if let Some(st) = job_state(session, keys, &job.id).await? {
                return Ok(st);
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        if Instant::now() > deadline {
            bail!("no store acknowledged job {}", job.id);
        }
    }
}

/// Follows a job until it closes (or `timeout`), calling `progress` on every new state. A job
/// that cannot complete — its store refuses worlds for memory, no node of its kind is alive,
/// every such node gave it up — ends the wait with an error saying why
/// ([`crate::stall::Stall`]), once the stall has lasted [`crate::stall::STALL_GRACE`].
pub async fn wait_job(
    session: &Session,
    keys: &Keys,
    job: &str,
    timeout: Option<Duration>,
    mut progress: impl FnMut(&JobState),
) -> Result<JobState> {
    let sub = session
        .declare_subscriber(keys.job_state(job))
        .await
        .map_err(|e| anyhow!("subscribing to job state: {e}"))?;
    let mut nodes = NodeWatch::start(session, keys).await?;
    let role = job_role(session, keys, job).await?;
    let mut watch = Watch::new(unix_ms());
    let start = Instant::now();
    let mut last: Option<JobState> = job_state(session, keys, job).await?;
    if let Some(st) = &last {
        progress(st);
    }
    loop {
        if let Some(st) = &last
            && st.closed
        {
            return Ok(st.clone());
        }
        if let Some(t) = timeout
            && start.elapsed() > t
        {
            bail!("job {job} did not finish within {t:?}");
        }
        // Subscription for promptness, a periodic query in case an update was missed.
        let next = match tokio::time::timeout(Duration::from_secs(1), sub.recv_async()).await {
            Ok(Ok(s)) => JobState::decode(s.payload().to_bytes().as_ref()).ok(),
            _ => job_state(session, keys, job).await?,
        };
        if let Some(st) = next
            && last.as_ref().is_none_or(|l| st.revision > l.revision)
        {
            progress(&st);
            last = Some(st);
        }
        if let Some(st) = &last
            && !st.closed
            && nodes.due()
        {
            let (workers, stores) = nodes.look(session, keys, role).await?;
            let space = keys.prefix().trim_start_matches("mwb/");
            if let Some(stall) = watch.observe(unix_ms(), space, st, role, &workers, &stores) {
                return Err(anyhow::Error::new(stall).context(format!(
                    "job {job} cannot complete ({}/{} worlds)",
                    st.worlds_done, st.target_worlds
                )));
            }
        }
    }
}

/// The role of the nodes that take `job` (from its announcement; a sampler's if no store
/// serves it any more).
async fn job_role(session: &Session, keys: &Keys, job: &str) -> Result<&'static str> {
    let replies = session
        .get(keys.job(job))
        .timeout(Duration::from_secs(2))
        .await
        .map_err(|e| anyhow!("job query: {e}"))?;
    let mut kind = JobKind::Sample;
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(s) = reply.result()
            && let Ok(j) = Job::decode(s.payload().to_bytes().as_ref())
        {
            kind = j.kind();
        }
    }
    Ok(crate::stall::worker_role(kind))
}

/// The live nodes and their latest statistics, for telling a stuck job from a slow one.
struct NodeWatch {
    /// A ring: a waiter that looks once a second must never hold up the bus (a full FIFO
    /// would); only each node's latest statistics matter.
    stats: zenoh::pubsub::Subscriber<zenoh::handlers::RingChannelHandler<zenoh::sample::Sample>>,
    latest: BTreeMap<(String, String), NodeStats>,
    next: Instant,
}

impl NodeWatch {
    /// How often [`NodeWatch::look`] is worth asking (nodes publish statistics every second).
    const EVERY: Duration = Duration::from_secs(1);

    async fn start(session: &Session, keys: &Keys) -> Result<Self> {
        let stats = session
            .declare_subscriber(keys.stats_all())
            .with(zenoh::handlers::RingChannel::new(1024))
            .await
            .map_err(|e| anyhow!("subscribing to stats: {e}"))?;
        Ok(Self {
            stats,
            latest: BTreeMap::new(),
            next: Instant::now(),
        })
    }

    fn due(&self) -> bool {
        Instant::now() >= self.next
    }

    /// The live nodes of `role` and the live stores, each with its latest statistics (a node
    /// that has not published yet: defaults with its id).
    async fn look(
        &mut self,
        session: &Session,
        keys: &Keys,
        role: &str,
    ) -> Result<(Vec<NodeStats>, Vec<NodeStats>)> {
        self.next = Instant::now() + Self::EVERY;
        while let Ok(Some(s)) = self.stats.try_recv() {
            if let Ok(st) = NodeStats::decode(s.payload().to_bytes().as_ref()) {
                self.latest
                    .insert((st.role.clone(), st.node_id.clone()), st);
            }
        }
        let alive = alive_nodes(session, keys).await?;
        let of = |wanted: &str| -> Vec<NodeStats> {
            alive
                .iter()
                .filter(|(r, _)| r == wanted)
                .map(|(r, n)| {
                    self.latest
                        .get(&(r.clone(), n.clone()))
                        .cloned()
                        .unwrap_or_else(|| NodeStats {
                            node_id: n.clone(),
                            role: r.clone(),
                            ..Default::default()
                        })
                })
                .collect()
        };
        Ok((of(role), of(role::STORE)))
    }
}

/// Every live node's `(role, node)`, by liveliness token.
pub async fn alive_nodes(session: &Session, keys: &Keys) -> Result<Vec<(String, String)>> {
    let replies = session
        .liveliness()
        .get(keys.alive_all())
        .timeout(Duration::from_millis(500))
        .await
        .map_err(|e| anyhow!("liveliness query: {e}"))?;
    let mut alive = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(s) = reply.result()
            && let Some(parts) = keys.split(s.key_expr().as_str())
            && let [_, role, node] = parts.as_slice()
        {
            alive.push(((*role).to_owned(), (*node).to_owned()));
        }
    }
    Ok(alive)
}

/// Fetches a complete world by store index.
pub async fn fetch_world(session: &Session, keys: &Keys, index: u32) -> Result<Option<World>> {
    let replies = session
        .get(keys.world(index))
        .timeout(Duration::from_secs(10))
        .await
        .map_err(|e| anyhow!("world query: {e}"))?;
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(s) = reply.result() {
            let w = World::decode(s.payload().to_bytes().as_ref())
                .with_context(|| format!("world {index}: malformed reply"))?;
            return Ok(Some(w));
        }
    }
    Ok(None)
}

/// How a submitted job is run and followed (`mwb job submit`, `mwb refine`, `mwb scene edit`).
#[derive(Debug, Clone, clap::Args)]
pub struct FollowArgs {
    #[arg(long, default_value_t = 0)]
    pub priority: i32,
    /// Follow the job until it closes.
    #[arg(long)]
    pub wait: bool,
    /// Give up waiting after this many seconds.
    #[arg(long)]
    pub timeout: Option<u64>,
    /// Print the result as one JSON line.
    #[arg(long)]
    pub json: bool,
}

/// A scene revision from the stores (`q/scene/<rev>` or `q/scene/latest`), `None` when no
/// store has it.
pub async fn fetch_scene(
    session: &Session,
    keys: &Keys,
    what: mwb_core::keys::SceneRev,
) -> Result<Option<Scene>> {
    let replies = session
        .get(keys.scene_query(what))
        .timeout(Duration::from_secs(2))
        .await
        .map_err(|e| anyhow!("scene query: {e}"))?;
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(s) = reply.result() {
            let scene = Scene::decode(s.payload().to_bytes().as_ref())
                .with_context(|| format!("scene revision {what}: malformed reply"))?;
            return Ok(Some(scene));
        }
    }
    Ok(None)
}

/// All jobs the stores know, with their states.
pub async fn list_jobs(session: &Session, keys: &Keys) -> Result<Vec<JobState>> {
    let replies = session
        .get(keys.job_states())
        .timeout(Duration::from_secs(2))
        .await
        .map_err(|e| anyhow!("job list query: {e}"))?;
    let mut by_id: BTreeMap<String, JobState> = BTreeMap::new();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(s) = reply.result()
            && let Ok(st) = JobState::decode(s.payload().to_bytes().as_ref())
        {
            let keep = by_id
                .get(&st.job_id)
                .is_none_or(|b| st.revision > b.revision);
            if keep {
                by_id.insert(st.job_id.clone(), st);
            }
        }
    }
    Ok(by_id.into_values().collect())
}

/// Cancels a job: re-announces it with a higher revision and `cancelled` set.
pub async fn cancel_job(session: &Session, keys: &Keys, job: &str) -> Result<JobState> {
    let replies = session
        .get(keys.job(job))
        .timeout(Duration::from_secs(2))
        .await
        .map_err(|e| anyhow!("job query: {e}"))?;
    let mut found: Option<Job> = None;
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(s) = reply.result()
            && let Ok(j) = Job::decode(s.payload().to_bytes().as_ref())
        {
            found = Some(j);
        }
    }
    let Some(mut j) = found else {
        bail!("job {job} is not open on any store");
    };
    j.revision += 1;
    j.cancelled = true;
    session
        .put(keys.job(job), j.encode_to_vec())
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(|e| anyhow!("announcing cancel: {e}"))?;
    wait_job(session, keys, job, Some(Duration::from_secs(10)), |_| {}).await
}

/// Live nodes (by liveliness token) and their latest statistics.
#[derive(Debug, Default, serde::Serialize)]
pub struct Status {
    pub nodes: Vec<NodeStatus>,
    pub jobs: Vec<JobStatus>,
}

#[derive(Debug, Default, serde::Serialize)]
pub struct NodeStatus {
    pub role: String,
    pub node: String,
    pub worlds: u64,
    pub worlds_per_s: f64,
    pub memory_bytes: u64,
    pub memory_cap_bytes: u64,
    pub uptime_s: f64,
    pub crc_failures: u64,
    pub malformed: u64,
    pub refused_memory: u64,
    pub discarded_partial: u64,
    /// Stores: worlds stored but not browsable (their motion could not be indexed), and
    /// indexes sent by samplers that differed from the store's own indexing of the same world.
    pub index_failures: u64,
    pub index_mismatches: u64,
    /// The node's zenoh session id (empty until its statistics arrive).
    pub zid: String,
    /// Its links to other zenoh sessions: who is connected, under which certificate.
    pub connections: Vec<ConnectionStatus>,
}

/// One link of a node's session ([`mwb_proto::v1::Connection`]), the other end named.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ConnectionStatus {
    /// The node at the other end, `role/node`, when it publishes statistics; empty for a
    /// client (the CLI, a viewer) or a node not heard from yet.
    pub peer: String,
    /// The other end's zenoh id.
    pub zid: String,
    /// `client`, `peer` or `router`.
    pub whatami: String,
    /// The other end's address.
    pub address: String,
    /// The common name of the certificate it proved (the role access control gave it); `None`
    /// on plain TCP, where nobody proved anything.
    pub certificate: Option<String>,
}

/// Each node's connections, the other end named by the zenoh ids the nodes publish.
pub fn connection_status(nodes: &[NodeStats]) -> Vec<Vec<ConnectionStatus>> {
    // Nodes in one process share its session (a store and its browsing coordinator): a link
    // to that session names them all.
    let mut names: BTreeMap<&str, String> = BTreeMap::new();
    for n in nodes.iter().filter(|n| !n.zid.is_empty()) {
        let name = format!("{}/{}", n.role, n.node_id);
        names
            .entry(n.zid.as_str())
            .and_modify(|all| *all = format!("{all} + {name}"))
            .or_insert(name);
    }
    nodes
        .iter()
        .map(|n| {
            n.connections
                .iter()
                .map(|c| ConnectionStatus {
                    peer: names.get(c.zid.as_str()).cloned().unwrap_or_default(),
                    zid: c.zid.clone(),
                    whatami: c.whatami.clone(),
                    address: c.address.clone(),
                    certificate: Some(c.certificate.clone()).filter(|s| !s.is_empty()),
                })
                .collect()
        })
        .collect()
}

#[derive(Debug, serde::Serialize)]
pub struct JobStatus {
    pub job: String,
    pub done: u32,
    pub target: u32,
    pub closed: bool,
    pub cancelled: bool,
    pub rejected: u32,
    pub worlds_per_s: f64,
    /// Why an open job cannot complete, if the bus shows it (`crate::stall`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stalled: Option<String>,
}

/// Gathers status: liveliness, then stats publications for `listen` (nodes publish every 1 s).
pub async fn status(session: &Session, keys: &Keys, listen: Duration) -> Result<Status> {
    let stats_sub = session
        .declare_subscriber(keys.stats_all())
        .await
        .map_err(|e| anyhow!("subscribing to stats: {e}"))?;
    let replies = session
        .liveliness()
        .get(keys.alive_all())
        .timeout(Duration::from_secs(2))
        .await
        .map_err(|e| anyhow!("liveliness query: {e}"))?;
    let mut alive: BTreeMap<(String, String), Option<NodeStats>> = BTreeMap::new();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(s) = reply.result()
            && let Some(parts) = keys.split(s.key_expr().as_str())
            && let [_, role, node] = parts.as_slice()
        {
            alive.insert(((*role).to_owned(), (*node).to_owned()), None);
        }
    }
    let deadline = Instant::now() + listen;
    while let Some(left) = deadline.checked_duration_since(Instant::now()) {
        match tokio::time::timeout(left, stats_sub.recv_async()).await {
            Ok(Ok(s)) => {
                if let Ok(st) = NodeStats::decode(s.payload().to_bytes().as_ref())
                    && let Some(slot) = alive.get_mut(&(st.role.clone(), st.node_id.clone()))
                {
                    *slot = Some(st);
                }
            }
            _ => break,
        }
    }
    let live: Vec<NodeStats> = alive
        .iter()
        .map(|((role, node), st)| {
            st.clone().unwrap_or_else(|| NodeStats {
                role: role.clone(),
                node_id: node.clone(),
                ..Default::default()
            })
        })
        .collect();
    let kinds = open_job_kinds(session, keys).await?;
    let links = connection_status(&live);
    let nodes = alive
        .into_iter()
        .zip(links)
        .map(|(((role, node), st), connections)| {
            let st = st.unwrap_or_default();
            NodeStatus {
                zid: st.zid.clone(),
                connections,
                role,
                node,
                worlds: st.worlds,
                worlds_per_s: st.worlds_per_s,
                memory_bytes: st.memory_bytes,
                memory_cap_bytes: st.memory_cap_bytes,
                uptime_s: st.uptime_s,
                crc_failures: st.crc_failures,
                malformed: st.malformed,
                refused_memory: st.refused_memory,
                discarded_partial: st.discarded_partial,
                index_failures: st.index_failures,
                index_mismatches: st.index_mismatches,
            }
        })
        .collect();
    let jobs = list_jobs(session, keys)
        .await?
        .into_iter()
        .map(|st| JobStatus {
            stalled: snapshot_stall(keys, &st, &kinds, &live).map(|s| s.to_string()),
            worlds_per_s: job_rate(&st),
            job: st.job_id,
            done: st.worlds_done,
            target: st.target_worlds,
            closed: st.closed,
            cancelled: st.cancelled,
            rejected: st.worlds_rejected,
        })
        .collect();
    Ok(Status { nodes, jobs })
}

/// The kind of every open job (the stores serve open jobs only).
async fn open_job_kinds(session: &Session, keys: &Keys) -> Result<BTreeMap<String, JobKind>> {
    let replies = session
        .get(keys.jobs())
        .timeout(Duration::from_secs(2))
        .await
        .map_err(|e| anyhow!("open jobs query: {e}"))?;
    let mut kinds = BTreeMap::new();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(s) = reply.result()
            && let Ok(j) = Job::decode(s.payload().to_bytes().as_ref())
        {
            kinds.insert(j.id.clone(), j.kind());
        }
    }
    Ok(kinds)
}

/// What one look at the bus says about an open job (`mwb status`; a waiting command watches
/// over time instead).
fn snapshot_stall(
    keys: &Keys,
    st: &JobState,
    kinds: &BTreeMap<String, JobKind>,
    live: &[NodeStats],
) -> Option<crate::stall::Stall> {
    let kind = kinds.get(&st.job_id).copied().unwrap_or(JobKind::Sample);
    let role = crate::stall::worker_role(kind);
    let workers: Vec<NodeStats> = live.iter().filter(|n| n.role == role).cloned().collect();
    let stores: Vec<NodeStats> = live
        .iter()
        .filter(|n| n.role == role::STORE)
        .cloned()
        .collect();
    crate::stall::diagnose(&crate::stall::Evidence {
        space: keys.prefix().trim_start_matches("mwb/"),
        state: st,
        role,
        workers: &workers,
        refused_since_progress: stores.iter().any(|s| crate::stall::store_looks_full(s, st)),
        stores: &stores,
    })
}

/// A job's state in one word, as tables print it.
pub fn state_name(closed: bool, cancelled: bool) -> &'static str {
    if cancelled {
        "cancelled"
    } else if closed {
        "closed"
    } else {
        "open"
    }
}

/// The progress bar of a command that follows a job of `worlds` worlds.
pub fn progress_bar(worlds: u32) -> indicatif::ProgressBar {
    let b = indicatif::ProgressBar::new(u64::from(worlds));
    if let Ok(style) = indicatif::ProgressStyle::with_template(
        "{spinner} {bar:40} {pos}/{len} worlds  {per_sec}  eta {eta}",
    ) {
        b.set_style(style);
    }
    b
}

/// Worlds per second over the job's life so far.
pub fn job_rate(st: &JobState) -> f64 {
    let span = st.last_world_unix_ms.saturating_sub(st.first_world_unix_ms) as f64 / 1000.0;
    if st.worlds_done > 1 && span > 0.0 {
        f64::from(st.worlds_done - 1) / span
    } else {
        0.0
    }
}

/// How a job's worlds are simulated and encoded: the sampler's speed-versus-accuracy and
/// speed-versus-size knobs.
#[derive(Debug, Clone, Copy, Default, clap::Args)]
pub struct MotionArgs {
    /// Segment payload: the spline codec (small) or quantised frames (cheap to produce).
    #[arg(long, value_enum, default_value_t = EncodingArg::Spline)]
    pub encoding: EncodingArg,
    /// Codec error bounds: draft 5 mm / 5 mrad, standard 1 mm / 1 mrad, final 0.1 mm / 0.1 mrad
    /// [default: the simulation preset's: draft → draft, final → final, else standard].
    #[arg(long, value_enum)]
    pub quality: Option<QualityArg>,
    /// Simulation preset (substeps, iterations, CCD, sleeping; docs/scene-format.md), written
    /// into the job's scene; `auto` runs a short calibration and picks the cheapest preset
    /// within the scene's tolerance [default: the scene's `sim`, else standard].
    #[arg(long, value_enum)]
    pub sim: Option<SimArg>,
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum EncodingArg {
    #[default]
    Spline,
    Frames,
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum QualityArg {
    Draft,
    #[default]
    Standard,
    Final,
}

/// `--sim`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SimArg {
    Draft,
    Standard,
    Final,
    Auto,
}

impl From<SimArg> for SimPreset {
    fn from(s: SimArg) -> Self {
        match s {
            SimArg::Draft => SimPreset::Draft,
            SimArg::Standard => SimPreset::Standard,
            SimArg::Final => SimPreset::Final,
            SimArg::Auto => SimPreset::Auto,
        }
    }
}

impl MotionArgs {
    /// The scene text the job carries: `--sim` written into it, a preset of `auto` (from the
    /// flag or the scene) resolved by calibration, and the scene checked for what the simulator
    /// cannot do faithfully ([`crate::sim::resolve_checked`]: warnings printed, refusals an
    /// error).
    pub fn resolve_scene(&self, file: &str, text: &str) -> Result<String> {
        crate::sim::resolve_checked(file, text, self.sim.map(SimPreset::from))
    }

    /// Sets the job's encoding and quality; without `--quality`, the codec preset follows the
    /// simulation preset of the job's scene.
    pub fn apply(&self, job: &mut Job) {
        job.encoding = match self.encoding {
            EncodingArg::Spline => Encoding::SplineV1,
            EncodingArg::Frames => Encoding::QuantisedFramesV1,
        } as i32;
        let quality = self.quality.unwrap_or_else(|| {
            let preset = job.scene.as_ref().and_then(|s| {
                mwb_core::scene::SceneTemplate::parse(&s.toml, "job scene")
                    .ok()
                    .map(|t| t.settings().sim)
            });
            match preset {
                Some(SimPreset::Draft) => QualityArg::Draft,
                Some(SimPreset::Final | SimPreset::Reference) => QualityArg::Final,
                _ => QualityArg::Standard,
            }
        });
        job.quality = Quality::from(quality) as i32;
    }
}

impl From<QualityArg> for Quality {
    fn from(q: QualityArg) -> Self {
        match q {
            QualityArg::Draft => Quality::Draft,
            QualityArg::Standard => Quality::Standard,
            QualityArg::Final => Quality::Final,
        }
    }
}

/// The job's announcement from the stores that hold its worlds (open or closed jobs).
pub async fn held_job(session: &zenoh::Session, keys: &Keys, job: &str) -> Result<Option<Job>> {
    let replies = session
        .get(keys.held_job(job))
        .timeout(Duration::from_secs(2))
        .await
        .map_err(|e| anyhow::anyhow!("job query: {e}"))?;
    let mut best: Option<Job> = None;
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(s) = reply.result()
            && let Ok(j) = Job::decode(s.payload().to_bytes().as_ref())
            && j.id == job
            && best.as_ref().is_none_or(|b| j.revision > b.revision)
        {
            best = Some(j);
        }
    }
    Ok(best)
}

#[cfg(test)]
mod tests {
    use super::*;
    use mwb_proto::v1::Connection;

    fn node(role: &str, id: &str, zid: &str, links: &[(&str, &str)]) -> NodeStats {
        NodeStats {
            role: role.into(),
            node_id: id.into(),
            zid: zid.into(),
            connections: links
                .iter()
                .map(|(zid, cert)| Connection {
                    zid: (*zid).into(),
                    whatami: "peer".into(),
                    address: "tls/127.0.0.1:1".into(),
                    certificate: (*cert).into(),
                })
                .collect(),
            ..Default::default()
        }
    }

    /// A link's other end is named when that node publishes its zid; a client is not; an
    /// empty common name (plain TCP) is no certificate.
    #[test]
    fn connections_name_the_nodes_at_the_other_end() {
        let nodes = [
            node(
                "store",
                "s",
                "aa",
                &[("bb", "mwb-worker"), ("cc", "mwb-client")],
            ),
            node("sampler", "w", "bb", &[("aa", "")]),
        ];
        let got = connection_status(&nodes);
        assert_eq!(got.len(), 2);
        assert_eq!(got[0][0].peer, "sampler/w");
        assert_eq!(got[0][0].certificate.as_deref(), Some("mwb-worker"));
        assert_eq!(got[0][1].peer, "");
        assert_eq!(got[0][1].certificate.as_deref(), Some("mwb-client"));
        assert_eq!(got[1][0].peer, "store/s");
        assert_eq!(got[1][0].certificate, None);
        // A coordinator in the store's process shares its session: both are named.
        let mut with_query = nodes.to_vec();
        with_query.push(node("query", "s-query", "aa", &[("bb", "mwb-worker")]));
        assert_eq!(
            connection_status(&with_query)[1][0].peer,
            "store/s + query/s-query"
        );
    }
}
