//! `mwb bench chaos`: faults across hosts (issue 21), one JSON line.
//!
//! Two store shards and four samplers run as `mwb` processes, each in a Linux network namespace
//! of its own; every namespace has one veth link to a bridge in a hub namespace, so the nodes
//! reach each other over real TCP on their veth addresses (`10.77.<n>.0/24`, a subnet no route
//! of the caller's namespace covers), and the caller reaches them through one more veth pair
//! from its own namespace. Shard 0 is the zenoh router everything connects to (and the job
//! authority); shard 1 connects to it as a client. Both journal to disk.
//!
//! While a job runs, a fault plan drawn from a seed ([`plan`]) is played against the cluster:
//!
//! * **kills**: a sampler is SIGKILLed and started again a moment later (a new node id, so new
//!   seeds: the store must discard the dead sampler's partial world after its liveliness token
//!   went away);
//! * **link cuts**: a sampler's veth port on the bridge goes down (`ip link set … down`) for
//!   longer than zenoh's 10 s lease and comes back up: both sides see the partition, the store
//!   discards what the sampler had in flight, the sampler reconnects and carries on;
//! * **a shard restart**: a shard's store is SIGKILLed and started again on the same
//!   `--journal` directory, so every world it acknowledged comes back under the same index.
//!
//! Faults are triggered by the job's progress (a fraction of its worlds), not by the clock, so
//! they all land inside the job however fast the machine samples. At the end every world is
//! fetched from the shards and checked ([`tally`]): lost (acknowledged by the authority's job
//! state but stored nowhere), duplicates (a seed stored twice), CRC failures and incomplete
//! worlds. The same job runs once without faults first (`clean_completion_s`).
//!
//! A last phase floods a store with a small `--memory-cap-mib` (no namespaces: one store, one
//! sampler, loopback) and samples the store process's real resident set (`VmRSS`) against its
//! cap: `rss_over_cap_bytes` = max(RSS − cap, 0) over the flood, beside the store's RSS before
//! any world (`rss_baseline_bytes`) so the number can be read.

use crate::bus::{BusArgs, Mode};
use crate::client;
use crate::output::{Summary, fields_table};
use anyhow::{Context, Result, anyhow, bail};
use mwb_core::keys::{Keys, role};
use mwb_core::rng::{Stream, WorldRng};
use mwb_proto::v1::{JobState, Message, MotionSegment, NodeStats, World, WorldDone};
use std::collections::{BTreeMap, HashMap, HashSet};
use std::net::Ipv4Addr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};
use zenoh::query::ConsolidationMode;
use zenoh::sample::SampleKind;

/// Samplers in a chaos run (the issue's four).
pub const SAMPLERS: usize = 4;
/// Store shards in a chaos run.
pub const SHARDS: u32 = 2;
/// zenoh's default link lease: a cut shorter than this is never seen as a partition (TCP
/// resends what was queued once the link is back).
pub const ZENOH_LEASE: Duration = Duration::from_secs(10);
/// The port shard 0 listens on inside its own namespace (nothing else listens there).
const ROUTER_PORT: u16 = 7447;

// ---------------------------------------------------------------------------------------------
// The fault plan (pure).
// ---------------------------------------------------------------------------------------------

/// One fault of a chaos run.
#[derive(Debug, Clone, PartialEq)]
pub enum Fault {
    /// SIGKILL a sampler; it is started again `restart_after` later. `sampler` is the plan's
    /// pick; the runner takes the next live one if that one cannot be killed just then.
    Kill {
        sampler: usize,
        restart_after: Duration,
    },
    /// Take a sampler's link down for `down_for`, then up again.
    Cut { sampler: usize, down_for: Duration },
    /// SIGKILL a shard's store and start it again on its journal `restart_after` later.
    RestartShard { shard: u32, restart_after: Duration },
}

/// A fault and when it is due: once the job's acknowledged worlds reach `at_progress` of its
/// target.
#[derive(Debug, Clone, PartialEq)]
pub struct Step {
    pub at_progress: f64,
    pub fault: Fault,
}

/// What a plan is drawn for.
#[derive(Debug, Clone, PartialEq)]
pub struct PlanSpec {
    pub seed: u64,
    pub samplers: usize,
    pub kills: u32,
    pub cuts: u32,
    pub shard_restarts: u32,
    /// The shard restarted (shard 0 is the router and the job authority).
    pub restart_shard: u32,
    pub cut_for: Duration,
    /// Faults are due between these fractions of the job.
    pub from: f64,
    pub to: f64,
}

impl PlanSpec {
    /// The issue's numbers: ≥ 10 kills, ≥ 3 cuts beyond the lease, one restart of shard 0.
    pub fn issue(seed: u64) -> Self {
        Self {
            seed,
            samplers: SAMPLERS,
            kills: 10,
            cuts: 3,
            shard_restarts: 1,
            restart_shard: 0,
            cut_for: ZENOH_LEASE + Duration::from_secs(5),
            from: 0.05,
            to: 0.8,
        }
    }
}

/// Draws the fault plan: the faults in a random order (kills, cuts and restarts shuffled
/// together), each due at a random point of its own equal slice of `[from, to)` (stratified, so
/// they spread over the job instead of bunching), kill victims uniform over the samplers, cut
/// victims a rotation from a random start (so that up to `samplers` cuts hit different
/// samplers), restart delays uniform in 0.2–1 s for samplers, 0.5 s for a shard. The same spec
/// always gives the same plan.
pub fn plan(spec: &PlanSpec) -> Vec<Step> {
    let mut rng = WorldRng::new(spec.seed, Stream::Scene);
    let n = spec.samplers.max(1);
    let mut faults: Vec<Fault> = Vec::new();
    for _ in 0..spec.kills {
        let sampler = pick(&mut rng, n);
        let restart_after = Duration::from_secs_f64(rng.uniform(0.2, 1.0));
        faults.push(Fault::Kill {
            sampler,
            restart_after,
        });
    }
    let first_cut = pick(&mut rng, n);
    for c in 0..spec.cuts as usize {
        faults.push(Fault::Cut {
            sampler: (first_cut + c) % n,
            down_for: spec.cut_for,
        });
    }
    for _ in 0..spec.shard_restarts {
        faults.push(Fault::RestartShard {
            shard: spec.restart_shard,
            restart_after: Duration::from_millis(500),
        });
    }
    // Fisher–Yates.
    for i in (1..faults.len()).rev() {
        let j = pick(&mut rng, i + 1);
        faults.swap(i, j);
    }
    let slice = (spec.to - spec.from) / faults.len().max(1) as f64;
    faults
        .into_iter()
        .enumerate()
        .map(|(i, fault)| Step {
            at_progress: spec.from + slice * (i as f64 + rng.next_f64()),
            fault,
        })
        .collect()
}

/// Uniform in `0..n` (n ≥ 1).
fn pick(rng: &mut WorldRng, n: usize) -> usize {
    ((rng.next_f64() * n as f64) as usize).min(n.saturating_sub(1))
}

// ---------------------------------------------------------------------------------------------
// Accounting of the stored worlds (pure).
// ---------------------------------------------------------------------------------------------

/// What the check of one fetched world found.
#[derive(Debug, Clone, PartialEq)]
pub struct WorldFacts {
    pub job_id: String,
    pub seed: u64,
    /// Every segment's payload matches its CRC-32.
    pub crc_ok: bool,
    /// [`crate::check::verify_world`] passed: every segment there, contiguous, decodable.
    pub complete: bool,
}

impl WorldFacts {
    /// Checks a fetched world.
    pub fn of(w: &World) -> Self {
        let crc_ok = w
            .segments
            .iter()
            .all(|s| crc32fast::hash(&s.payload) == s.crc32);
        Self {
            job_id: w.job_id.clone(),
            seed: w.done.as_ref().map_or(0, |d| d.seed),
            crc_ok,
            complete: crate::check::verify_world(w).is_ok(),
        }
    }
}

/// The stored worlds of one job against what was acknowledged.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct Tally {
    /// Worlds of the job the shards hold.
    pub stored: u32,
    /// Of those, with every CRC good, complete, and a seed not seen before.
    pub valid_unique: u32,
    /// Worlds whose seed another stored world of the job already has.
    pub duplicates: u32,
    /// Worlds with a segment whose payload does not match its CRC.
    pub crc_failures: u32,
    /// Worlds that do not verify for another reason (missing or out-of-order segments,
    /// undecodable payload).
    pub incomplete: u32,
    /// Acknowledged worlds not among the valid ones: `acknowledged − valid_unique`, or 0.
    pub lost: u32,
    /// Valid worlds beyond those acknowledged (a shard that kept a world the authority never
    /// counted). A count-based `lost` can hide as many lost worlds as this.
    pub unacknowledged: u32,
}

/// Tallies the worlds of `job` among `worlds` against the `acknowledged` count (the highest
/// `worlds_done` the authority published: the sum of the shards' durable counts, which may end a
/// few worlds past the target). Acknowledgement is a count, not a list of seeds — the job
/// state says how many worlds are durable, not which — so `lost` is counted, and
/// `unacknowledged` says whether other worlds could have made up for lost ones.
pub fn tally(job: &str, acknowledged: u32, worlds: &[WorldFacts]) -> Tally {
    let mut t = Tally::default();
    let mut seeds = HashSet::new();
    for w in worlds.iter().filter(|w| w.job_id == job) {
        t.stored += 1;
        let first = seeds.insert(w.seed);
        if !first {
            t.duplicates += 1;
        }
        if !w.crc_ok {
            t.crc_failures += 1;
        } else if !w.complete {
            t.incomplete += 1;
        } else if first {
            t.valid_unique += 1;
        }
    }
    t.lost = acknowledged.saturating_sub(t.valid_unique);
    t.unacknowledged = t.valid_unique.saturating_sub(acknowledged);
    t
}

// ---------------------------------------------------------------------------------------------
// Network namespaces.
// ---------------------------------------------------------------------------------------------

/// Why network namespaces cannot be made here (not root, no `ip`, a kernel or sandbox that
/// refuses them): the test skips, the bench stops with this message.
#[derive(Debug, thiserror::Error)]
#[error("network namespaces unavailable: {0}")]
pub struct Unavailable(pub String);

/// A failed `ip` command while building or changing the lab.
#[derive(Debug, thiserror::Error)]
#[error("`ip {args}` failed: {stderr}")]
pub struct IpError {
    pub args: String,
    pub stderr: String,
}

fn ip(args: &[&str]) -> Result<(), IpError> {
    let fail = |stderr: String| IpError {
        args: args.join(" "),
        stderr,
    };
    let out = Command::new("ip")
        .args(args)
        .stdin(Stdio::null())
        .output()
        .map_err(|e| fail(e.to_string()))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(fail(String::from_utf8_lossy(&out.stderr).trim().to_owned()))
    }
}

/// One "host" of the lab: a namespace with one veth link to the hub's bridge.
#[derive(Debug, Clone)]
pub struct Host {
    pub tag: String,
    pub netns: String,
    /// The link's end on the bridge, in the hub namespace: what a cut takes down.
    pub port: String,
    pub addr: Ipv4Addr,
}

/// Network namespaces joined by a bridge: one per host, a hub holding the bridge, and a veth
/// pair from the caller's namespace to the hub. Everything is named after the process id, and
/// removed on drop (also when a test panics); namespaces left by a process that died without
/// dropping its lab (SIGKILL) are removed by the next lab.
pub struct NetLab {
    prefix: String,
    hub: String,
    /// The caller's end of its link to the hub.
    local_dev: String,
    pub local_addr: Ipv4Addr,
    hosts: Vec<Host>,
    made: Vec<String>,
    local_link: bool,
}

/// Namespace names start with this, then the process id.
const NETNS_PREFIX: &str = "mwbchaos";

impl NetLab {
    /// Makes a namespace per tag (`a0`, `s1`, …; short: interface names are 15 bytes at most).
    pub fn new(tags: &[&str]) -> Result<Self, Unavailable> {
        // SAFETY: geteuid(2) has no preconditions.
        if unsafe { libc::geteuid() } != 0 {
            return Err(Unavailable("not running as root".into()));
        }
        remove_stale_namespaces();
        let pid = std::process::id();
        let prefix = format!("{NETNS_PREFIX}{pid}");
        let subnet = free_subnet(pid).ok_or_else(|| Unavailable("no free 10.77.x.0/24".into()))?;
        let mut lab = NetLab {
            hub: format!("{prefix}-hub"),
            prefix,
            local_dev: format!("mwbc{pid}"),
            local_addr: Ipv4Addr::new(10, 77, subnet, 254),
            hosts: Vec::new(),
            made: Vec::new(),
            local_link: false,
        };
        // The first namespace tells whether namespaces work here at all.
        ip(&["netns", "add", &lab.hub]).map_err(|e| Unavailable(e.to_string()))?;
        lab.made.push(lab.hub.clone());
        lab.build(tags, subnet)
            .map_err(|e| Unavailable(format!("building the lab: {e}")))?;
        Ok(lab)
    }

    fn build(&mut self, tags: &[&str], subnet: u8) -> Result<(), IpError> {
        let hub = self.hub.clone();
        ip(&["-n", &hub, "link", "set", "lo", "up"])?;
        ip(&["-n", &hub, "link", "add", "br0", "type", "bridge"])?;
        ip(&["-n", &hub, "link", "set", "br0", "up"])?;
        for (i, tag) in tags.iter().enumerate() {
            let netns = format!("{}-{tag}", self.prefix);
            ip(&["netns", "add", &netns])?;
            self.made.push(netns.clone());
            let port = format!("p-{tag}");
            let addr = Ipv4Addr::new(10, 77, subnet, 1 + i as u8);
            ip(&["-n", &netns, "link", "set", "lo", "up"])?;
            ip(&[
                "-n", &hub, "link", "add", &port, "type", "veth", "peer", "name", "eth0", "netns",
                &netns,
            ])?;
            ip(&["-n", &hub, "link", "set", &port, "master", "br0"])?;
            ip(&["-n", &hub, "link", "set", &port, "up"])?;
            ip(&[
                "-n",
                &netns,
                "addr",
                "add",
                &format!("{addr}/24"),
                "dev",
                "eth0",
            ])?;
            ip(&["-n", &netns, "link", "set", "eth0", "up"])?;
            self.hosts.push(Host {
                tag: (*tag).to_owned(),
                netns,
                port,
                addr,
            });
        }
        let local = self.local_dev.clone();
        ip(&[
            "link", "add", &local, "type", "veth", "peer", "name", "p-local", "netns", &hub,
        ])?;
        self.local_link = true;
        ip(&["-n", &hub, "link", "set", "p-local", "master", "br0"])?;
        ip(&["-n", &hub, "link", "set", "p-local", "up"])?;
        ip(&[
            "addr",
            "add",
            &format!("{}/24", self.local_addr),
            "dev",
            &local,
        ])?;
        ip(&["link", "set", &local, "up"])?;
        Ok(())
    }

    pub fn host(&self, tag: &str) -> Option<&Host> {
        self.hosts.iter().find(|h| h.tag == tag)
    }

    /// Takes a host's link down (its port on the bridge: the host's own interface stays
    /// configured, as a pulled cable leaves it) or brings it back up.
    pub fn set_link(&self, tag: &str, up: bool) -> Result<(), IpError> {
        let host = self.host(tag).ok_or_else(|| IpError {
            args: format!("link of {tag}"),
            stderr: "no such host".into(),
        })?;
        ip(&[
            "-n",
            &self.hub,
            "link",
            "set",
            &host.port,
            if up { "up" } else { "down" },
        ])
    }
}

impl Drop for NetLab {
    fn drop(&mut self) {
        if self.local_link {
            let _ = ip(&["link", "del", &self.local_dev]);
        }
        // Deleting a namespace deletes its veth ends, and so their peers.
        for ns in self.made.iter().rev() {
            let _ = ip(&["netns", "del", ns]);
        }
    }
}

/// Removes namespaces of earlier labs whose process is gone (killed before its drop ran).
fn remove_stale_namespaces() {
    let Ok(out) = Command::new("ip").args(["netns", "list"]).output() else {
        return;
    };
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        let name = line.split_whitespace().next().unwrap_or_default();
        let Some(rest) = name.strip_prefix(NETNS_PREFIX) else {
            continue;
        };
        let pid: String = rest.chars().take_while(char::is_ascii_digit).collect();
        if !pid.is_empty() && !Path::new("/proc").join(&pid).exists() {
            let _ = ip(&["netns", "del", name]);
        }
    }
}

/// A third octet for `10.77.x.0/24` that no route of this namespace covers, starting from one
/// derived from the process id (two labs at once take different subnets).
fn free_subnet(pid: u32) -> Option<u8> {
    let routes = Command::new("ip")
        .args(["-4", "route", "show", "table", "all"])
        .output()
        .map(|o| String::from_utf8_lossy(&o.stdout).into_owned())
        .unwrap_or_default();
    let covered = |x: u8| {
        let net = format!("10.77.{x}.");
        routes.lines().any(|l| {
            let dst = l.split_whitespace().next().unwrap_or_default();
            dst.starts_with(&net) || dst == "10.77.0.0/16" || dst == "10.0.0.0/8"
        })
    };
    (0..200u32)
        .map(|i| (10 + (pid + i) % 200) as u8)
        .find(|&x| !covered(x))
}

// ---------------------------------------------------------------------------------------------
// Processes.
// ---------------------------------------------------------------------------------------------

/// An `mwb` child process, in a namespace or not, that can be killed and started again with the
/// same arguments; killed on drop. Its stderr goes to a log file, for diagnostics.
pub(super) struct Proc {
    name: String,
    netns: Option<String>,
    args: Vec<String>,
    log: PathBuf,
    child: Option<Child>,
}

impl Proc {
    pub(super) fn new(name: &str, netns: Option<&str>, args: Vec<String>, dir: &Path) -> Self {
        Self {
            name: name.to_owned(),
            netns: netns.map(str::to_owned),
            args,
            log: dir.join(format!("{name}.log")),
            child: None,
        }
    }

    pub(super) fn start(&mut self, mwb: &Path) -> Result<()> {
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.log)
            .with_context(|| format!("log of {}", self.name))?;
        let mut cmd = match &self.netns {
            // `ip netns exec` execs the command itself: the child's pid is mwb's.
            Some(ns) => {
                let mut c = Command::new("ip");
                c.args(["netns", "exec", ns]).arg(mwb);
                c
            }
            None => Command::new(mwb),
        };
        let child = cmd
            .args(&self.args)
            .env("RUST_LOG", "warn")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .with_context(|| format!("starting {}", self.name))?;
        self.child = Some(child);
        Ok(())
    }

    pub(super) fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(Child::id)
    }

    /// Whether the process is running (false once it exited, or was never started).
    pub(super) fn running(&mut self) -> bool {
        self.child
            .as_mut()
            .is_some_and(|c| matches!(c.try_wait(), Ok(None)))
    }

    /// SIGKILL (what `Child::kill` sends) and reap.
    fn kill(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// The last lines of the log, for an error message.
    pub(super) fn log_tail(&self) -> String {
        let text = std::fs::read_to_string(&self.log).unwrap_or_default();
        let lines: Vec<&str> = text.lines().collect();
        let tail = lines[lines.len().saturating_sub(5)..].join("\n    ");
        format!("  {}:\n    {tail}", self.name)
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.kill();
    }
}

/// A directory removed on drop (journals and logs of one run).
pub(super) struct TempDir(pub(super) PathBuf);

impl TempDir {
    pub(super) fn new(name: &str) -> Result<Self> {
        let p = std::env::temp_dir().join(format!("mwb-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).with_context(|| format!("creating {}", p.display()))?;
        Ok(Self(p))
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A process's resident set (`VmRSS` in /proc/PID/status), bytes.
pub fn rss_bytes(pid: u32) -> Option<u64> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let kb = s
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))?
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse::<u64>()
        .ok()?;
    Some(kb * 1024)
}

// ---------------------------------------------------------------------------------------------
// What the client sees on the bus.
// ---------------------------------------------------------------------------------------------

/// Per sampler node: the last world it sent a segment of and the last it finished (one worker
/// each, so its worlds go in order).
#[derive(Debug, Default, Clone, Copy)]
struct Flight {
    segments: u64,
    last_started: Option<u64>,
    last_done: Option<u64>,
}

impl Flight {
    fn in_flight(&self) -> bool {
        match (self.last_started, self.last_done) {
            (Some(s), Some(d)) => s > d,
            (Some(_), None) => true,
            _ => false,
        }
    }
}

/// Everything the subscriptions' callbacks record (they never block: an undrained subscriber of
/// `seg/**` would push back on the router).
#[derive(Debug, Default)]
struct Seen {
    flights: HashMap<String, Flight>,
    /// When each sampler node's liveliness token went away.
    gone: HashMap<String, Vec<Instant>>,
    /// The latest statistics of every store incarnation (a restarted store has a new node id;
    /// its counters start again from zero).
    store_stats: BTreeMap<String, NodeStats>,
    /// The authority's job state with the highest revision.
    state: Option<JobState>,
    /// The most worlds any authority state counted.
    acknowledged: u32,
}

impl Seen {
    fn state(&mut self, st: JobState) {
        self.acknowledged = self.acknowledged.max(st.worlds_done);
        if self
            .state
            .as_ref()
            .is_none_or(|s| st.revision > s.revision || (st.closed && !s.closed))
        {
            self.state = Some(st);
        }
    }
    fn closed(&self) -> bool {
        self.state.as_ref().is_some_and(|s| s.closed)
    }
}

fn lock(seen: &Mutex<Seen>) -> MutexGuard<'_, Seen> {
    seen.lock().unwrap_or_else(|p| p.into_inner())
}

/// The subscriptions that feed [`Seen`]; undeclared on drop.
struct Watch {
    _subs: Vec<zenoh::pubsub::Subscriber<()>>,
}

async fn watch(
    session: &zenoh::Session,
    keys: &Keys,
    job: &str,
    seen: &Arc<Mutex<Seen>>,
) -> Result<Watch> {
    let mut subs = Vec::new();
    let s = seen.clone();
    subs.push(
        session
            .declare_subscriber(keys.segments())
            .callback(move |sample| {
                if let Ok(m) = MotionSegment::decode(sample.payload().to_bytes().as_ref()) {
                    let mut g = lock(&s);
                    let f = g.flights.entry(m.node_id).or_default();
                    f.segments += 1;
                    f.last_started = f.last_started.max(Some(m.world_counter));
                }
            })
            .await
            .map_err(|e| anyhow!("subscribing to segments: {e}"))?,
    );
    let s = seen.clone();
    subs.push(
        session
            .declare_subscriber(keys.dones())
            .callback(move |sample| {
                if let Ok(m) = WorldDone::decode(sample.payload().to_bytes().as_ref()) {
                    let mut g = lock(&s);
                    let f = g.flights.entry(m.node_id).or_default();
                    f.last_done = f.last_done.max(Some(m.world_counter));
                }
            })
            .await
            .map_err(|e| anyhow!("subscribing to summaries: {e}"))?,
    );
    let s = seen.clone();
    subs.push(
        session
            .declare_subscriber(keys.job_state(job))
            .callback(move |sample| {
                if let Ok(st) = JobState::decode(sample.payload().to_bytes().as_ref()) {
                    lock(&s).state(st);
                }
            })
            .await
            .map_err(|e| anyhow!("subscribing to the job state: {e}"))?,
    );
    let s = seen.clone();
    subs.push(
        session
            .declare_subscriber(keys.stats(role::STORE, "*"))
            .callback(move |sample| {
                if let Ok(st) = NodeStats::decode(sample.payload().to_bytes().as_ref()) {
                    lock(&s).store_stats.insert(st.node_id.clone(), st);
                }
            })
            .await
            .map_err(|e| anyhow!("subscribing to store statistics: {e}"))?,
    );
    let s = seen.clone();
    let k = keys.clone();
    let alive = session
        .liveliness()
        .declare_subscriber(keys.alive_role(role::SAMPLER))
        .callback(move |sample| {
            if sample.kind() == SampleKind::Delete
                && let Some(parts) = k.split(sample.key_expr().as_str())
                && let [_, _, node] = parts.as_slice()
            {
                lock(&s)
                    .gone
                    .entry((*node).to_owned())
                    .or_default()
                    .push(Instant::now());
            }
        })
        .await
        .map_err(|e| anyhow!("watching sampler liveliness: {e}"))?;
    subs.push(alive);
    Ok(Watch { _subs: subs })
}

/// Every store's statistics on request, one reply per live shard.
pub(super) async fn store_stats(session: &zenoh::Session, keys: &Keys) -> Vec<NodeStats> {
    // Every shard answers on the same key: zenoh's default consolidation would keep one.
    let Ok(replies) = session
        .get(keys.store_stats())
        .consolidation(ConsolidationMode::None)
        .timeout(Duration::from_secs(2))
        .await
    else {
        return Vec::new();
    };
    let mut out = Vec::new();
    while let Ok(r) = replies.recv_async().await {
        if let Ok(s) = r.result()
            && let Ok(st) = NodeStats::decode(s.payload().to_bytes().as_ref())
        {
            out.push(st);
        }
    }
    out
}

/// How many sampler tokens are alive.
async fn samplers_alive(session: &zenoh::Session, keys: &Keys) -> usize {
    let Ok(replies) = session
        .liveliness()
        .get(keys.alive_role(role::SAMPLER))
        .timeout(Duration::from_millis(500))
        .await
    else {
        return 0;
    };
    let mut n = 0;
    while let Ok(r) = replies.recv_async().await {
        n += usize::from(r.result().is_ok());
    }
    n
}

pub(super) async fn until<F, Fut>(what: &str, limit: Duration, mut f: F) -> Result<()>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = bool>,
{
    let deadline = Instant::now() + limit;
    loop {
        if tokio::time::timeout(Duration::from_secs(5), f())
            .await
            .unwrap_or(false)
        {
            return Ok(());
        }
        if Instant::now() > deadline {
            bail!("timed out after {limit:?} waiting for {what}");
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Whether something listens on `addr:port` (from the caller's namespace).
pub(super) async fn listening(addr: Ipv4Addr, port: u16) -> bool {
    matches!(
        tokio::time::timeout(
            Duration::from_secs(1),
            tokio::net::TcpStream::connect((addr, port))
        )
        .await,
        Ok(Ok(_))
    )
}

// ---------------------------------------------------------------------------------------------
// A run over the lab.
// ---------------------------------------------------------------------------------------------

/// The hosts a chaos run needs: `a0`, `a1` (shards), `s0`..`s3` (samplers).
pub fn lab_tags() -> Vec<String> {
    let mut tags: Vec<String> = (0..SHARDS).map(|i| format!("a{i}")).collect();
    tags.extend((0..SAMPLERS).map(|i| format!("s{i}")));
    tags
}

/// One run of a job over the lab.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// The `mwb` binary the nodes run.
    pub mwb: PathBuf,
    /// A name for the run, unique among runs on the same lab (space, job id, files).
    pub name: String,
    /// Scene file name and its text.
    pub scene: (String, String),
    pub worlds: u32,
    /// `None`: a clean run.
    pub faults: Option<PlanSpec>,
    /// The whole run, start to checked worlds.
    pub timeout: Duration,
}

/// What a run measured.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct RunReport {
    pub completed: bool,
    /// Submission to the closing job state.
    pub completion_s: f64,
    pub kills: u32,
    /// Kills that hit a sampler with a world in flight (a segment seen, its summary not).
    pub kills_mid_world: u32,
    pub link_cuts: u32,
    pub cuts_mid_world: u32,
    /// Cuts during which the router dropped the sampler's liveliness token (a partition seen).
    pub partitions_seen: u32,
    pub shard_restarts: u32,
    /// Faults of the plan left undone because the job had closed.
    pub faults_skipped: u32,
    /// Processes that exited without being killed (a sampler that could not reach the router
    /// while it was restarting exits, and is started again).
    pub unexpected_exits: u32,
    pub worlds_expected: u32,
    /// The most worlds an authority job state counted.
    pub worlds_acknowledged: u32,
    pub worlds_stored: u32,
    pub lost: u32,
    pub duplicates: u32,
    pub crc_failures: u32,
    pub incomplete: u32,
    pub unacknowledged: u32,
    /// Partial worlds the stores discarded (their samplers left: killed or partitioned), summed
    /// over every store incarnation's last statistics.
    pub partial_discarded: u64,
    /// Worlds the stores refused (incomplete, duplicate seed, CRC, late …), from the job state.
    pub worlds_rejected: u32,
    /// Refusals counted by the stores' statistics, summed the same way.
    pub duplicates_refused: u64,
    pub crc_refused: u64,
    /// World counts per shard at the end.
    pub per_shard: Vec<u64>,
}

struct Sampler {
    proc: Proc,
    generation: u32,
    node: String,
    restart_at: Option<Instant>,
    cut_until: Option<Instant>,
}

struct Shard {
    proc: Proc,
    restart_at: Option<Instant>,
    /// A restart counts as in progress until then (so that cuts wait for it to settle).
    settled_at: Option<Instant>,
}

/// Runs `opts.worlds` worlds of the scene over the lab, with the faults of `opts.faults` played
/// against it, then fetches and checks every stored world.
pub async fn run_cluster(lab: &NetLab, opts: &RunOptions) -> Result<RunReport> {
    let dir = TempDir::new(&format!("chaos-{}", opts.name))?;
    let space = format!("{}{}", opts.name, std::process::id());
    let keys = Keys::new(&space)?;
    let hosts: Vec<Host> = lab_tags()
        .iter()
        .map(|t| {
            lab.host(t)
                .cloned()
                .ok_or_else(|| anyhow!("the lab has no host {t}"))
        })
        .collect::<Result<_>>()?;
    let router = hosts[0].addr;
    let endpoint = format!("tcp/{router}:{ROUTER_PORT}");
    let mut shards: Vec<Shard> = (0..SHARDS)
        .map(|i| {
            let journal = dir.0.join(format!("journal{i}"));
            let mut args = vec!["store".to_owned()];
            if i == 0 {
                args.extend(["--listen".to_owned(), endpoint.clone()]);
            } else {
                args.extend([
                    "--mode".to_owned(),
                    "client".to_owned(),
                    "--connect".to_owned(),
                    endpoint.clone(),
                ]);
            }
            args.extend([
                "--space".to_owned(),
                space.clone(),
                "--shard".to_owned(),
                format!("{i}/{SHARDS}"),
                "--journal".to_owned(),
                journal.display().to_string(),
                "--no-query".to_owned(),
            ]);
            Shard {
                proc: Proc::new(
                    &format!("shard{i}"),
                    Some(&hosts[i as usize].netns),
                    args,
                    &dir.0,
                ),
                restart_at: None,
                settled_at: None,
            }
        })
        .collect();
    shards[0].proc.start(&opts.mwb)?;
    until("shard 0 to listen", Duration::from_secs(60), || {
        listening(router, ROUTER_PORT)
    })
    .await?;
    for s in &mut shards[1..] {
        s.proc.start(&opts.mwb)?;
    }

    let bus = BusArgs {
        connect: vec![endpoint.clone()],
        listen: vec![],
        config: None,
        mode: Some(Mode::Client),
        space: space.clone(),
        multicast: false,
    };
    let session = tokio::time::timeout(Duration::from_secs(30), bus.open(Mode::Client))
        .await
        .map_err(|_| anyhow!("opening the client session timed out"))??;
    let result = drive(
        lab,
        opts,
        &dir,
        &keys,
        &session,
        &endpoint,
        &hosts,
        &mut shards,
    )
    .await;
    crate::bus::close(session).await;
    result.map_err(|e| {
        let tails: Vec<String> = shards.iter().map(|s| s.proc.log_tail()).collect();
        e.context(format!(
            "run {}; store logs:\n{}",
            opts.name,
            tails.join("\n")
        ))
    })
}

#[allow(clippy::too_many_arguments)]
async fn drive(
    lab: &NetLab,
    opts: &RunOptions,
    dir: &TempDir,
    keys: &Keys,
    session: &zenoh::Session,
    endpoint: &str,
    hosts: &[Host],
    shards: &mut [Shard],
) -> Result<RunReport> {
    until("both shards", Duration::from_secs(60), || async {
        let st = store_stats(session, keys).await;
        (0..SHARDS).all(|i| {
            st.iter()
                .any(|s| s.shard_index == i && s.shard_count == SHARDS)
        })
    })
    .await?;
    let space = keys.prefix().trim_start_matches("mwb/").to_owned();
    let sampler_args = |node: &str| {
        vec![
            "sampler".to_owned(),
            "--connect".to_owned(),
            endpoint.to_owned(),
            "--space".to_owned(),
            space.clone(),
            "--workers".to_owned(),
            "1".to_owned(),
            "--node-id".to_owned(),
            node.to_owned(),
        ]
    };
    let mut samplers: Vec<Sampler> = (0..SAMPLERS)
        .map(|i| {
            let node = format!("s{i}g0");
            Sampler {
                proc: Proc::new(
                    &format!("sampler{i}"),
                    Some(&hosts[SHARDS as usize + i].netns),
                    sampler_args(&node),
                    &dir.0,
                ),
                generation: 0,
                node,
                restart_at: None,
                cut_until: None,
            }
        })
        .collect();
    for s in &mut samplers {
        s.proc.start(&opts.mwb)?;
    }
    until("every sampler", Duration::from_secs(60), || async {
        samplers_alive(session, keys).await >= SAMPLERS
    })
    .await?;

    let job_id = format!("{}-job", opts.name);
    let (file, text) = &opts.scene;
    let job = client::make_job(file, text, opts.worlds, 0, Some(job_id.clone()))?;
    let seen = Arc::new(Mutex::new(Seen::default()));
    let _watch = watch(session, keys, &job_id, &seen).await?;
    let steps = opts.faults.as_ref().map(plan).unwrap_or_default();
    let mut report = RunReport {
        worlds_expected: opts.worlds,
        ..Default::default()
    };

    let t0 = Instant::now();
    let deadline = t0 + opts.timeout;
    let st = tokio::time::timeout(
        Duration::from_secs(60),
        client::submit_job(session, keys, &job),
    )
    .await
    .map_err(|_| anyhow!("submitting the job timed out"))??;
    lock(&seen).state(st);
    let mut next = 0;
    let mut last_fault = Instant::now();
    let mut last_query = Instant::now();
    let mut cuts: Vec<(usize, Instant, Instant, String)> = Vec::new();
    let gap = Duration::from_millis(300);
    loop {
        let now = Instant::now();
        if now > deadline {
            let st = lock(&seen).state.clone();
            let tails: Vec<String> = samplers.iter().map(|s| s.proc.log_tail()).collect();
            bail!(
                "the job did not complete within {:?}: {st:?}; faults done {next}/{}; sampler \
                 logs:\n{}",
                opts.timeout,
                steps.len(),
                tails.join("\n")
            );
        }
        // A state query now and then, in case a published state was missed (a reconnection).
        if now.duration_since(last_query) > Duration::from_secs(1) {
            last_query = now;
            if let Ok(Ok(Some(st))) = tokio::time::timeout(
                Duration::from_secs(3),
                client::job_state(session, keys, &job_id),
            )
            .await
            {
                lock(&seen).state(st);
            }
        }
        let (closed, progress) = {
            let g = lock(&seen);
            if g.closed() && report.completion_s == 0.0 {
                report.completion_s = t0.elapsed().as_secs_f64();
            }
            (
                g.closed(),
                f64::from(g.acknowledged) / f64::from(opts.worlds.max(1)),
            )
        };

        // Supervision: links back up, killed processes started again, unexpected exits noted.
        for s in samplers.iter_mut() {
            if s.cut_until.is_some_and(|t| now >= t) {
                lab.set_link(&hosts[SHARDS as usize + s.proc_index()].tag, true)?;
                s.cut_until = None;
            }
            if s.restart_at.is_none() && s.proc.pid().is_some() && !s.proc.running() {
                report.unexpected_exits += 1;
                s.proc.kill();
                s.restart_at = Some(now + Duration::from_secs(1));
            }
            if s.restart_at.is_some_and(|t| now >= t) {
                s.generation += 1;
                s.node = format!("s{}g{}", s.proc_index(), s.generation);
                s.proc.args = sampler_args(&s.node);
                s.proc.start(&opts.mwb)?;
                s.restart_at = None;
            }
        }
        for s in shards.iter_mut() {
            if s.restart_at.is_none() && s.proc.pid().is_some() && !s.proc.running() {
                report.unexpected_exits += 1;
                s.proc.kill();
                s.restart_at = Some(now + Duration::from_secs(1));
            }
            if s.restart_at.is_some_and(|t| now >= t) {
                s.proc.start(&opts.mwb)?;
                s.restart_at = None;
                s.settled_at = Some(now + Duration::from_secs(3));
            }
            if s.settled_at.is_some_and(|t| now >= t) {
                s.settled_at = None;
            }
        }
        let shard_busy = shards
            .iter()
            .any(|s| s.restart_at.is_some() || s.settled_at.is_some());
        let cut_active = samplers.iter().any(|s| s.cut_until.is_some());

        if closed && !cut_active && !shard_busy {
            report.faults_skipped = (steps.len() - next) as u32;
            break;
        }
        if !closed
            && next < steps.len()
            && progress >= steps[next].at_progress
            && now.duration_since(last_fault) >= gap
        {
            let done = {
                let g = lock(&seen);
                let eligible = |s: &Sampler| {
                    s.restart_at.is_none()
                        && s.cut_until.is_none()
                        && s.proc.child.is_some()
                        && g.flights.get(&s.node).is_some_and(|f| f.segments > 0)
                };
                match &steps[next].fault {
                    Fault::Kill {
                        sampler,
                        restart_after,
                    } => {
                        let victim = (0..SAMPLERS)
                            .map(|k| (sampler + k) % SAMPLERS)
                            .find(|&i| eligible(&samplers[i]));
                        victim.map(|i| {
                            let mid = g
                                .flights
                                .get(&samplers[i].node)
                                .is_some_and(Flight::in_flight);
                            (Action::Kill(i, *restart_after), mid)
                        })
                    }
                    Fault::Cut { sampler, down_for } if !shard_busy => {
                        let victim = (0..SAMPLERS)
                            .map(|k| (sampler + k) % SAMPLERS)
                            .find(|&i| eligible(&samplers[i]));
                        victim.map(|i| {
                            let mid = g
                                .flights
                                .get(&samplers[i].node)
                                .is_some_and(Flight::in_flight);
                            (Action::Cut(i, *down_for), mid)
                        })
                    }
                    Fault::RestartShard {
                        shard,
                        restart_after,
                    } if !cut_active && !shard_busy && (*shard as usize) < shards.len() => {
                        Some((Action::Restart(*shard as usize, *restart_after), false))
                    }
                    _ => None,
                }
            };
            if let Some((action, mid)) = done {
                match action {
                    Action::Kill(i, after) => {
                        samplers[i].proc.kill();
                        samplers[i].restart_at = Some(now + after);
                        report.kills += 1;
                        report.kills_mid_world += u32::from(mid);
                    }
                    Action::Cut(i, down_for) => {
                        lab.set_link(&hosts[SHARDS as usize + i].tag, false)?;
                        samplers[i].cut_until = Some(now + down_for);
                        cuts.push((i, now, now + down_for, samplers[i].node.clone()));
                        report.link_cuts += 1;
                        report.cuts_mid_world += u32::from(mid);
                    }
                    Action::Restart(i, after) => {
                        shards[i].proc.kill();
                        shards[i].restart_at = Some(now + after);
                        report.shard_restarts += 1;
                    }
                }
                next += 1;
                last_fault = now;
            }
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    report.completed = true;

    // Orphaned partial worlds are discarded after a 1 s grace, statistics published every
    // second: let both happen before counting.
    tokio::time::sleep(Duration::from_secs(3)).await;
    let final_stats = store_stats(session, keys).await;
    {
        let mut g = lock(&seen);
        for st in &final_stats {
            g.store_stats.insert(st.node_id.clone(), st.clone());
        }
        for (_, start, end, node) in &cuts {
            let margin = Duration::from_secs(3);
            if g.gone
                .get(node)
                .is_some_and(|ts| ts.iter().any(|t| t >= start && *t <= *end + margin))
            {
                report.partitions_seen += 1;
            }
        }
        for st in g.store_stats.values() {
            report.partial_discarded += st.discarded_partial;
            report.duplicates_refused += st.duplicates;
            report.crc_refused += st.crc_failures;
        }
        report.worlds_acknowledged = g.acknowledged;
        report.worlds_rejected = g.state.as_ref().map_or(0, |s| s.worlds_rejected);
    }
    let mut facts = Vec::new();
    report.per_shard = vec![0; SHARDS as usize];
    for st in &final_stats {
        if st.shard_index >= SHARDS {
            continue;
        }
        report.per_shard[st.shard_index as usize] = st.worlds;
        for local in 0..st.worlds as u32 {
            let index = local * SHARDS + st.shard_index;
            let w = tokio::time::timeout(
                Duration::from_secs(30),
                client::fetch_world(session, keys, index),
            )
            .await
            .map_err(|_| anyhow!("fetching world {index} timed out"))??;
            // A world the shard counts but does not return is missing: `lost` counts it.
            if let Some(w) = w {
                facts.push(WorldFacts::of(&w));
            }
        }
    }
    if final_stats.len() != SHARDS as usize {
        bail!(
            "{} of {SHARDS} shards answered for their statistics at the end",
            final_stats.len()
        );
    }
    let t = tally(&job_id, report.worlds_acknowledged, &facts);
    report.worlds_stored = t.stored;
    report.lost = t.lost;
    report.duplicates = t.duplicates;
    report.crc_failures = t.crc_failures;
    report.incomplete = t.incomplete;
    report.unacknowledged = t.unacknowledged;
    Ok(report)
}

enum Action {
    Kill(usize, Duration),
    Cut(usize, Duration),
    Restart(usize, Duration),
}

impl Sampler {
    /// Which sampler this is (from its process name, `sampler<i>`).
    fn proc_index(&self) -> usize {
        self.proc
            .name
            .trim_start_matches("sampler")
            .parse()
            .unwrap_or(0)
    }
}

// ---------------------------------------------------------------------------------------------
// The flood.
// ---------------------------------------------------------------------------------------------

/// The store process's resident set under a flood.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct FloodReport {
    #[serde(rename = "rss_cap_bytes")]
    pub cap_bytes: u64,
    /// The store's RSS once started, before any world.
    pub rss_baseline_bytes: u64,
    pub rss_max_bytes: u64,
    /// max(RSS − cap, 0) over the flood.
    pub rss_over_cap_bytes: u64,
    /// max(RSS − baseline − cap, 0): what the worlds made the process grow beyond its cap.
    pub rss_growth_over_cap_bytes: u64,
    /// The store's own accounting at the end (`NodeStats.memory_bytes`).
    #[serde(rename = "flood_memory_bytes")]
    pub memory_bytes: u64,
    #[serde(rename = "flood_worlds")]
    pub worlds_stored: u64,
    #[serde(rename = "flood_refused_memory")]
    pub refused_memory: u64,
    pub flood_s: f64,
}

/// A `mwb store` process of its own on TCP loopback (no query node, a memory cap of `cap_mib`
/// MiB), killed on drop, and a client session to it.
pub(super) struct LoopbackStore {
    /// Its log and working directory, removed on drop.
    pub dir: TempDir,
    pub proc: Proc,
    pub pid: u32,
    pub endpoint: String,
    pub keys: Keys,
    pub session: zenoh::Session,
}

impl LoopbackStore {
    /// Starts the store (`name`: its log's and directory's name; `extra`: more arguments of
    /// `mwb store`) and connects once it listens.
    pub(super) async fn start(
        mwb: &Path,
        name: &str,
        cap_mib: u64,
        extra: &[String],
    ) -> Result<Self> {
        let dir = TempDir::new(name)?;
        let port = super::free_port()?;
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let space = format!("{name}{}", std::process::id());
        let keys = Keys::new(&space)?;
        let cap = cap_mib.to_string();
        let args = [
            "store",
            "--listen",
            &endpoint,
            "--space",
            &space,
            "--memory-cap-mib",
            &cap,
            "--no-query",
        ];
        let mut proc = Proc::new(
            name,
            None,
            args.iter()
                .map(|s| (*s).to_owned())
                .chain(extra.iter().cloned())
                .collect(),
            &dir.0,
        );
        proc.start(mwb)?;
        until(
            &format!("{name} to listen"),
            Duration::from_secs(60),
            || listening(Ipv4Addr::LOCALHOST, port),
        )
        .await?;
        let pid = proc.pid().ok_or_else(|| anyhow!("{name} has no pid"))?;
        let bus = BusArgs {
            connect: vec![endpoint.clone()],
            listen: vec![],
            config: None,
            mode: Some(Mode::Client),
            space,
            multicast: false,
        };
        let session = tokio::time::timeout(Duration::from_secs(30), bus.open(Mode::Client))
            .await
            .map_err(|_| anyhow!("opening the client session timed out"))??;
        Ok(Self {
            dir,
            proc,
            pid,
            endpoint,
            keys,
            session,
        })
    }

    /// Closes the client session (the process is killed when `self` drops).
    pub(super) async fn close(self) {
        crate::bus::close(self.session).await;
    }
}

/// Floods a store of `cap_mib` MiB (its own process, loopback) with a sampler's worlds until it
/// has been full for 3 s (or `limit`), sampling the store's RSS every 100 ms.
pub async fn flood(
    mwb: &Path,
    scene: &(String, String),
    cap_mib: u64,
    limit: Duration,
) -> Result<FloodReport> {
    let mut s = LoopbackStore::start(mwb, "flood-store", cap_mib, &[]).await?;
    let r = flood_with(
        mwb,
        scene,
        &s.dir,
        &mut s.proc,
        s.pid,
        &s.session,
        &s.keys,
        &s.endpoint,
        cap_mib << 20,
        limit,
    )
    .await;
    s.close().await;
    r
}

#[allow(clippy::too_many_arguments)]
async fn flood_with(
    mwb: &Path,
    scene: &(String, String),
    dir: &TempDir,
    store: &mut Proc,
    pid: u32,
    session: &zenoh::Session,
    keys: &Keys,
    endpoint: &str,
    cap: u64,
    limit: Duration,
) -> Result<FloodReport> {
    // Settled: the store answers, and its RSS is what it is before any world.
    until("the flood store", Duration::from_secs(30), || async {
        !store_stats(session, keys).await.is_empty()
    })
    .await?;
    tokio::time::sleep(Duration::from_secs(1)).await;
    let baseline = rss_bytes(pid).ok_or_else(|| anyhow!("no VmRSS for the store (pid {pid})"))?;
    let space = keys.prefix().trim_start_matches("mwb/").to_owned();
    let mut sampler = Proc::new(
        "flood-sampler",
        None,
        vec![
            "sampler".into(),
            "--connect".into(),
            endpoint.into(),
            "--space".into(),
            space,
        ],
        &dir.0,
    );
    sampler.start(mwb)?;
    let job = client::make_job(&scene.0, &scene.1, 100_000_000, 0, Some("flood".into()))?;
    tokio::time::timeout(
        Duration::from_secs(60),
        client::submit_job(session, keys, &job),
    )
    .await
    .map_err(|_| anyhow!("submitting the flood job timed out"))??;
    let t0 = Instant::now();
    let mut max = baseline;
    let mut full_since: Option<Instant> = None;
    let mut last_look = Instant::now();
    let mut last = NodeStats::default();
    loop {
        if !store.running() {
            bail!("the flood store exited:\n{}", store.log_tail());
        }
        if let Some(rss) = rss_bytes(pid) {
            max = max.max(rss);
        }
        let now = Instant::now();
        if now.duration_since(last_look) >= Duration::from_millis(500) {
            last_look = now;
            if let Some(st) = store_stats(session, keys).await.into_iter().next() {
                let full = st.refused_memory > 0
                    || st.memory_bytes as f64 >= mwb_node::room::FULL_FRACTION * cap as f64;
                if full && full_since.is_none() {
                    full_since = Some(now);
                }
                last = st;
            }
        }
        if full_since.is_some_and(|t| now.duration_since(t) >= Duration::from_secs(3))
            || t0.elapsed() > limit
        {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    if full_since.is_none() {
        bail!(
            "the flood store never filled its {cap} bytes within {limit:?} ({} worlds, {} bytes)",
            last.worlds,
            last.memory_bytes
        );
    }
    Ok(FloodReport {
        cap_bytes: cap,
        rss_baseline_bytes: baseline,
        rss_max_bytes: max,
        rss_over_cap_bytes: max.saturating_sub(cap),
        rss_growth_over_cap_bytes: max.saturating_sub(baseline).saturating_sub(cap),
        memory_bytes: last.memory_bytes,
        worlds_stored: last.worlds,
        refused_memory: last.refused_memory,
        flood_s: t0.elapsed().as_secs_f64(),
    })
}

// ---------------------------------------------------------------------------------------------
// The bench.
// ---------------------------------------------------------------------------------------------

/// Arguments of `mwb bench chaos`.
#[derive(Debug, Clone, clap::Args)]
pub struct ChaosArgs {
    /// Worlds in the job (run once clean, once under faults).
    #[arg(long, default_value_t = 200)]
    pub worlds: u32,
    /// Seed of the fault plan.
    #[arg(long, default_value_t = 21)]
    pub seed: u64,
    /// The job's scene. The tower (193 bodies, about a third of a core-second a world) keeps
    /// a world in flight whenever a sampler works and the job long enough for every fault;
    /// tumble's worlds take milliseconds, and a job of them ends before the cuts do.
    #[arg(long, default_value = "tower")]
    pub scene: String,
    /// The flood's scene: small worlds, to fill the cap quickly.
    #[arg(long, default_value = "tumble")]
    pub flood_scene: String,
    #[arg(long, default_value_t = 10)]
    pub kills: u32,
    #[arg(long, default_value_t = 3)]
    pub cuts: u32,
    /// How long a cut lasts, s (beyond zenoh's 10 s lease, so that it is a partition).
    #[arg(long, default_value_t = 15.0)]
    pub cut_s: f64,
    /// The shard restarted (0: the router and job authority).
    #[arg(long, default_value_t = 0)]
    pub restart_shard: u32,
    /// The flood store's memory cap, MiB.
    #[arg(long, default_value_t = 16)]
    pub flood_cap_mib: u64,
    /// Only the flood (one store and one sampler on loopback; no namespaces, so no root): what
    /// a real store process holds per world, against what it counts.
    #[arg(long)]
    pub flood_only: bool,
    /// Give up on each run after this many seconds.
    #[arg(long, default_value_t = 900)]
    pub timeout_s: u64,
    /// Print the result as one JSON line.
    #[arg(long)]
    pub json: bool,
}

/// The bench's line: the chaos run's counts, the clean run's completion, the flood's RSS.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ChaosBench {
    pub scene: String,
    pub flood_scene: String,
    pub seed: u64,
    pub samplers: usize,
    pub shards: u32,
    pub cut_s: f64,
    pub restart_shard: u32,
    /// The chaos run.
    #[serde(flatten)]
    pub chaos: RunReport,
    pub clean_completion_s: f64,
    pub clean_lost: u32,
    /// The flood (its fields prefixed `rss_` or `flood_` on the line).
    #[serde(flatten)]
    pub flood: FloodReport,
}

impl Summary for ChaosBench {
    fn table(&self) -> String {
        fields_table(self)
    }
}

/// `--flood-only`'s line: the flood, and per stored world what the store process grew by
/// against what its own accounting counts.
#[derive(Debug, Clone, serde::Serialize)]
pub struct FloodBench {
    pub flood_scene: String,
    #[serde(flatten)]
    pub flood: FloodReport,
    /// (RSS at its largest − RSS before any world) ÷ worlds stored: everything a world costs
    /// the process (motion as held, index, allocator).
    pub rss_growth_bytes_per_world: f64,
    /// The store's own accounting (`flood_memory_bytes`, what the cap limits) ÷ worlds stored.
    pub accounted_bytes_per_world: f64,
}

impl Summary for FloodBench {
    fn table(&self) -> String {
        fields_table(self)
    }
}

/// Runs `mwb bench chaos`.
pub async fn run(args: ChaosArgs) -> Result<()> {
    let mwb = std::env::current_exe().context("finding the mwb binary")?;
    if args.flood_only {
        let flood_scene = client::load_scene(&args.flood_scene)?;
        let f = flood(
            &mwb,
            &flood_scene,
            args.flood_cap_mib,
            Duration::from_secs(args.timeout_s),
        )
        .await?;
        let per = |bytes: u64| bytes as f64 / f.worlds_stored.max(1) as f64;
        let b = FloodBench {
            flood_scene: args.flood_scene,
            rss_growth_bytes_per_world: per(f.rss_max_bytes.saturating_sub(f.rss_baseline_bytes)),
            accounted_bytes_per_world: per(f.memory_bytes),
            flood: f,
        };
        return crate::output::print(&b, args.json);
    }
    let tags = lab_tags();
    let tag_refs: Vec<&str> = tags.iter().map(String::as_str).collect();
    let lab = NetLab::new(&tag_refs).map_err(|e| {
        anyhow!("mwb bench chaos puts nodes in network namespaces and needs root: {e}")
    })?;
    let scene = client::load_scene(&args.scene)?;
    let spec = PlanSpec {
        kills: args.kills,
        cuts: args.cuts,
        cut_for: Duration::from_secs_f64(args.cut_s.max(0.0)),
        restart_shard: args.restart_shard,
        ..PlanSpec::issue(args.seed)
    };
    let timeout = Duration::from_secs(args.timeout_s);
    let clean = run_cluster(
        &lab,
        &RunOptions {
            mwb: mwb.clone(),
            name: "clean".into(),
            scene: scene.clone(),
            worlds: args.worlds,
            faults: None,
            timeout,
        },
    )
    .await?;
    let chaos = run_cluster(
        &lab,
        &RunOptions {
            mwb: mwb.clone(),
            name: "chaos".into(),
            scene: scene.clone(),
            worlds: args.worlds,
            faults: Some(spec),
            timeout,
        },
    )
    .await?;
    drop(lab);
    let flood_scene = client::load_scene(&args.flood_scene)?;
    let f = flood(
        &mwb,
        &flood_scene,
        args.flood_cap_mib,
        Duration::from_secs(300),
    )
    .await?;
    let b = ChaosBench {
        scene: args.scene,
        flood_scene: args.flood_scene,
        seed: args.seed,
        samplers: SAMPLERS,
        shards: SHARDS,
        cut_s: args.cut_s,
        restart_shard: args.restart_shard,
        clean_completion_s: clean.completion_s,
        clean_lost: clean.lost,
        chaos,
        flood: f,
    };
    crate::output::print(&b, args.json)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(seed: u64) -> PlanSpec {
        PlanSpec::issue(seed)
    }

    #[test]
    fn the_plan_has_every_fault_in_order_within_the_window() {
        let s = spec(7);
        let p = plan(&s);
        assert_eq!(p.len(), 14);
        let count = |f: fn(&Fault) -> bool| p.iter().filter(|st| f(&st.fault)).count();
        assert_eq!(count(|f| matches!(f, Fault::Kill { .. })), 10);
        assert_eq!(count(|f| matches!(f, Fault::Cut { .. })), 3);
        assert_eq!(
            count(|f| matches!(f, Fault::RestartShard { shard: 0, .. })),
            1
        );
        for w in p.windows(2) {
            assert!(w[0].at_progress <= w[1].at_progress, "{p:?}");
        }
        for st in &p {
            assert!(st.at_progress >= s.from && st.at_progress < s.to, "{st:?}");
            match st.fault {
                Fault::Kill {
                    sampler,
                    restart_after,
                } => {
                    assert!(sampler < SAMPLERS);
                    assert!((0.2..=1.0).contains(&restart_after.as_secs_f64()));
                }
                Fault::Cut { down_for, .. } => assert!(down_for > ZENOH_LEASE),
                Fault::RestartShard { .. } => {}
            }
        }
    }

    #[test]
    fn the_plan_is_a_function_of_its_seed() {
        assert_eq!(plan(&spec(21)), plan(&spec(21)));
        assert_ne!(plan(&spec(21)), plan(&spec(22)));
    }

    #[test]
    fn cuts_hit_different_samplers() {
        for seed in 0..50 {
            let p = plan(&spec(seed));
            let mut victims: Vec<usize> = p
                .iter()
                .filter_map(|st| match st.fault {
                    Fault::Cut { sampler, .. } => Some(sampler),
                    _ => None,
                })
                .collect();
            victims.sort_unstable();
            victims.dedup();
            assert_eq!(victims.len(), 3, "seed {seed}: {p:?}");
        }
    }

    #[test]
    fn kills_reach_every_sampler_over_seeds() {
        let mut hit = [false; SAMPLERS];
        for seed in 0..20 {
            for st in plan(&spec(seed)) {
                if let Fault::Kill { sampler, .. } = st.fault {
                    hit[sampler] = true;
                }
            }
        }
        assert!(hit.iter().all(|h| *h), "{hit:?}");
    }

    #[test]
    fn an_empty_plan_is_empty() {
        let s = PlanSpec {
            kills: 0,
            cuts: 0,
            shard_restarts: 0,
            ..spec(1)
        };
        assert!(plan(&s).is_empty());
    }

    fn w(job: &str, seed: u64, crc_ok: bool, complete: bool) -> WorldFacts {
        WorldFacts {
            job_id: job.into(),
            seed,
            crc_ok,
            complete,
        }
    }

    #[test]
    fn tally_counts_lost_duplicates_and_crc() {
        let worlds = vec![
            w("j", 1, true, true),
            w("j", 2, true, true),
            w("j", 2, true, true),
            w("j", 3, false, false),
            w("j", 4, true, false),
            w("other", 5, true, true),
        ];
        let t = tally("j", 5, &worlds);
        assert_eq!(
            t,
            Tally {
                stored: 5,
                valid_unique: 2,
                duplicates: 1,
                crc_failures: 1,
                incomplete: 1,
                lost: 3,
                unacknowledged: 0,
            }
        );
    }

    #[test]
    fn tally_of_a_clean_job_loses_nothing() {
        let worlds: Vec<WorldFacts> = (0..10).map(|s| w("j", s, true, true)).collect();
        let t = tally("j", 10, &worlds);
        assert_eq!(
            (t.stored, t.lost, t.duplicates, t.unacknowledged),
            (10, 0, 0, 0)
        );
        let t = tally("j", 8, &worlds);
        assert_eq!((t.lost, t.unacknowledged), (0, 2));
    }

    #[test]
    fn the_line_names_the_issue_fields_once_each() {
        let b = ChaosBench {
            scene: "s".into(),
            flood_scene: "f".into(),
            seed: 1,
            samplers: SAMPLERS,
            shards: SHARDS,
            cut_s: 15.0,
            restart_shard: 0,
            chaos: RunReport::default(),
            clean_completion_s: 1.0,
            clean_lost: 0,
            flood: FloodReport::default(),
        };
        // Flattened structs put their fields beside the line's own: a name used twice would
        // be written twice, and a reader would keep one of them silently.
        let keys: Vec<String> = crate::output::fields(&b)
            .into_iter()
            .map(|(k, _)| k)
            .collect();
        let mut unique = keys.clone();
        unique.sort();
        unique.dedup();
        assert_eq!(unique.len(), keys.len(), "{keys:?}");
        for name in [
            "kills",
            "link_cuts",
            "shard_restarts",
            "worlds_expected",
            "worlds_stored",
            "lost",
            "duplicates",
            "crc_failures",
            "completion_s",
            "clean_completion_s",
            "rss_over_cap_bytes",
            "rss_cap_bytes",
            "flood_worlds",
        ] {
            assert!(
                keys.iter().any(|k| k == name),
                "{name} missing from {keys:?}"
            );
        }
    }

    #[test]
    fn interface_names_fit_the_kernel_limit() {
        // IFNAMSIZ is 16 with the terminating NUL.
        let pid = u32::MAX;
        assert!(format!("mwbc{pid}").len() <= 15);
        for tag in lab_tags() {
            assert!(format!("p-{tag}").len() <= 15);
        }
    }
}
