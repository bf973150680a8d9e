//! One store shard's browsing state (§4.4): the indexed worlds it holds and, per browsing
//! session, a [`ConstraintSet`] of bitsets over them. Pure: the node feeds it worlds as they are
//! stored and [`ShardRequest`]s from node-query, and sends back the [`ShardReply`].

use crate::index::{IndexedObject, IndexedWorld};
use crate::slots::Slots;
use crate::spatial::{Aabb, Part, PathBvh, Piece, region_box};
use mwb_core::browse::api::{
    ConstraintStatus, Reply, Request, SceneBodies, SessionStatus, ShardReply, ShardRequest,
    WorldSummary, merge_bodies,
};
use mwb_core::browse::sample::in_context;
use mwb_core::browse::{
    BrowseError, Constraint, ConstraintId, ConstraintSet, PackedMetrics, Quantifier, RankKey,
    RegionCache, Scope, WorldSet, top_k_counted,
};
use mwb_proto::v1::PathBatch;
use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

/// Which worlds a store keeps when several split them (DESIGN.md: world → shard by hash).
///
/// A world `(job, seed)` belongs to shard `hash(job, seed) mod count`. Shard `s` numbers its
/// worlds `s, s + count, s + 2·count, …`, so global indices never collide and a world fetch by
/// index reaches exactly one shard.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ShardSpec {
    pub index: u32,
    pub count: u32,
}

impl Default for ShardSpec {
    fn default() -> Self {
        Self { index: 0, count: 1 }
    }
}

/// Why a shard specification is not one.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ShardSpecError {
    #[error("shard {text:?}: expected INDEX/COUNT, e.g. 0/2")]
    NoSlash { text: String },
    #[error("shard {text:?}: {field} {value:?} is not a number")]
    NotANumber {
        text: String,
        /// `index` or `count`.
        field: &'static str,
        value: String,
        #[source]
        source: std::num::ParseIntError,
    },
    #[error("shard {index}/{count}: need 0 ≤ index < count and count ≥ 1")]
    OutOfRange { index: u32, count: u32 },
}

impl ShardSpec {
    /// `index/count`, e.g. `1/2`; validated.
    pub fn parse(text: &str) -> Result<Self, ShardSpecError> {
        let (i, n) = text
            .split_once('/')
            .ok_or_else(|| ShardSpecError::NoSlash {
                text: text.to_owned(),
            })?;
        let number = |field: &'static str, value: &str| {
            value
                .trim()
                .parse::<u32>()
                .map_err(|source| ShardSpecError::NotANumber {
                    text: text.to_owned(),
                    field,
                    value: value.to_owned(),
                    source,
                })
        };
        Self::new(number("index", i)?, number("count", n)?)
    }

    pub fn new(index: u32, count: u32) -> Result<Self, ShardSpecError> {
        if count == 0 || index >= count {
            return Err(ShardSpecError::OutOfRange { index, count });
        }
        Ok(Self { index, count })
    }

    /// The shard a world belongs to. FNV-1a over the job id and the seed: stable across builds
    /// and machines (unlike `std`'s randomly keyed hasher).
    pub fn shard_of(job: &str, seed: u64, count: u32) -> u32 {
        let mut h: u64 = 0xcbf2_9ce4_8422_2325;
        for b in job.bytes().chain([0xff]).chain(seed.to_le_bytes()) {
            h ^= u64::from(b);
            h = h.wrapping_mul(0x0000_0100_0000_01b3);
        }
        (h % u64::from(count.max(1))) as u32
    }

    pub fn owns(&self, job: &str, seed: u64) -> bool {
        Self::shard_of(job, seed, self.count) == self.index
    }

    /// The global index of this shard's `local`-th world.
    pub fn global(&self, local: u32) -> Option<u32> {
        local.checked_mul(self.count)?.checked_add(self.index)
    }

    /// This shard's local index of a global one, if the shard numbers it.
    pub fn local(&self, global: u32) -> Option<u32> {
        (global % self.count == self.index).then_some(global / self.count)
    }

    /// The shard that answers the job-level questions (job states, open jobs): shard 0.
    pub fn is_authority(&self) -> bool {
        self.index == 0
    }
}

#[derive(Debug, Default)]
struct Session {
    set: ConstraintSet,
    edits: u64,
}

/// Why a shard refused an edit (the message goes back to the browsing client).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
enum EditError {
    #[error("constraint {id} is already live")]
    AlreadyLive { id: ConstraintId },
    #[error(transparent)]
    Browse(#[from] BrowseError),
    #[error("nothing to undo")]
    NothingToUndo,
    #[error("nothing to redo")]
    NothingToRedo,
    #[error("not an edit")]
    NotAnEdit,
}

/// A shard's worlds and browsing sessions.
#[derive(Debug)]
pub struct Shard {
    spec: ShardSpec,
    name: String,
    /// By local index; empty for a world that could not be indexed.
    worlds: Slots<IndexedWorld>,
    /// Job ids of the worlds held, one copy each, shared by the job's worlds.
    jobs: HashSet<Arc<str>>,
    indexed: u64,
    /// Every indexed world (the complement of a negative constraint is taken in it).
    all: WorldSet,
    /// Per object index, the boxes of that object's paths in every world.
    bvh: Vec<PathBvh>,
    /// Pieces a hierarchy block is built from ([`crate::spatial::BLOCK`]; smaller in tests).
    block: usize,
    sessions: HashMap<String, Session>,
    threads: usize,
    /// Σ over indexed worlds of their heap bytes (kept as they come and go, so that
    /// [`heap_bytes`](Self::heap_bytes) is cheap enough to ask after every world).
    world_bytes: usize,
}

/// Where a shard's heap bytes go ([`Shard::heap_bytes_by_part`]); the parts sum to
/// [`Shard::heap_bytes`]. All counted by capacity.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ShardBytes {
    /// Every world's stored paths ([`IndexedObject`]s and their vertices).
    pub paths: usize,
    /// The per-object hierarchies of path pieces.
    pub hierarchies: usize,
    /// Per-object ranking metrics.
    pub metrics: usize,
    /// The rest of each world's record (its struct, job id, lineage) and the slot table.
    pub records: usize,
    /// Every session's constraint bitsets and the set of all worlds.
    pub bitsets: usize,
}

/// Pieces whose paths a query reads together (see [`Shard::touched_by`]).
const BATCH: usize = 32;

/// Sessions a shard keeps at most (each holds one bitset per constraint).
pub const MAX_SESSIONS: usize = 256;

impl Shard {
    /// `name` identifies the shard in world summaries (its node id).
    pub fn new(spec: ShardSpec, name: impl Into<String>) -> Self {
        Self {
            spec,
            name: name.into(),
            worlds: Slots::default(),
            jobs: HashSet::new(),
            indexed: 0,
            all: WorldSet::new(),
            bvh: Vec::new(),
            block: crate::spatial::BLOCK,
            sessions: HashMap::new(),
            threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            world_bytes: 0,
        }
    }

    /// Builds hierarchy blocks of `pieces` (for tests: small stores with many blocks). Takes
    /// effect for object indexes not seen yet.
    #[cfg(test)]
    fn set_block(&mut self, pieces: usize) {
        self.block = pieces;
    }

    /// Threads used to evaluate a new constraint over all worlds (default: every core).
    pub fn set_threads(&mut self, threads: usize) {
        self.threads = threads.max(1);
    }

    pub fn spec(&self) -> ShardSpec {
        self.spec
    }

    /// Worlds indexed (and so browsable).
    pub fn world_count(&self) -> u64 {
        self.indexed
    }

    pub fn world(&self, global: u32) -> Option<&IndexedWorld> {
        let local = self.spec.local(global)?;
        self.worlds.get(local as usize)
    }

    /// The indexed paths of local slots `seen..` (at most `max` worlds), for drawing: what a
    /// `q/paths` query gets from this shard. Slots whose world could not be indexed are
    /// skipped, and so are worlds outside the sample `sample_below` names
    /// ([`in_context`]; 0: every world); `next_local` is where the asker continues.
    pub fn path_batch(&self, seen: u32, max: usize, sample_below: u32) -> PathBatch {
        let first = (seen as usize).min(self.worlds.len());
        let mut worlds = Vec::new();
        let mut next = first;
        for slot in self.worlds.iter_from(first) {
            if worlds.len() >= max.max(1) {
                break;
            }
            next += 1;
            if let Some(w) = slot.filter(|w| in_context(w.world, sample_below)) {
                worlds.push(w.paths_message());
            }
        }
        PathBatch {
            shard_index: self.spec.index,
            shard_count: self.spec.count,
            first_local: first as u32,
            next_local: next as u32,
            worlds,
            indexed: self.indexed,
        }
    }

    /// The indexed paths of the worlds of `ids` (global indices) this shard holds, at most
    /// `max` of them, in the order asked: what a `q/paths` query naming worlds gets (a viewer
    /// fetching the survivors it draws). The cursor fields are 0.
    pub fn paths_of(&self, ids: &[u32], max: usize) -> PathBatch {
        PathBatch {
            shard_index: self.spec.index,
            shard_count: self.spec.count,
            first_local: 0,
            next_local: 0,
            worlds: ids
                .iter()
                .filter_map(|&w| self.world(w))
                .take(max)
                .map(IndexedWorld::paths_message)
                .collect(),
            indexed: self.indexed,
        }
    }

    /// Heap bytes of the path index and metrics, plus every session's bitsets.
    pub fn heap_bytes(&self) -> usize {
        self.world_bytes
            + self.worlds.heap_bytes()
            + self.jobs_bytes()
            + self.bvh.iter().map(PathBvh::heap_bytes).sum::<usize>()
            + self.all.heap_bytes()
            + self
                .sessions
                .values()
                .map(|s| {
                    s.set
                        .constraints()
                        .filter_map(|c| s.set.satisfied(c.id))
                        .map(WorldSet::heap_bytes)
                        .sum::<usize>()
                        + s.set.result().heap_bytes()
                        + s.set.worlds().heap_bytes()
                })
                .sum::<usize>()
    }

    /// Heap bytes of the interned job ids (each once, with its reference counts).
    fn jobs_bytes(&self) -> usize {
        self.jobs.capacity() * std::mem::size_of::<Arc<str>>()
            + self
                .jobs
                .iter()
                .map(|j| j.len() + 2 * std::mem::size_of::<usize>())
                .sum::<usize>()
    }

    /// Bytes [`heap_bytes`](Self::heap_bytes) may grow by when the next world is inserted,
    /// beyond that world's own: vectors doubling their capacity (the world table, each
    /// hierarchy's pending list) and a hierarchy block being built. Counted against the store's
    /// cap before a world is admitted ([`crate::Assembler::set_index_bytes`]).
    pub fn growth_bytes(&self) -> usize {
        self.worlds.growth_bytes(self.worlds.len())
            + self.bvh.iter().map(PathBvh::growth_bytes).sum::<usize>()
    }

    /// [`heap_bytes`](Self::heap_bytes) by structure (walks every world: for benchmarks).
    pub fn heap_bytes_by_part(&self) -> ShardBytes {
        let worlds = self.worlds.values();
        let paths: usize = worlds
            .clone()
            .map(|w| {
                std::mem::size_of_val::<[IndexedObject]>(&w.objects)
                    + w.objects
                        .iter()
                        .map(IndexedObject::heap_bytes)
                        .sum::<usize>()
            })
            .sum();
        let metrics: usize = worlds
            .clone()
            .map(|w| std::mem::size_of_val::<[PackedMetrics]>(&w.metrics))
            .sum();
        let total = self.heap_bytes();
        let hierarchies = self.bvh.iter().map(PathBvh::heap_bytes).sum::<usize>();
        let records =
            self.world_bytes - paths - metrics + self.worlds.heap_bytes() + self.jobs_bytes();
        ShardBytes {
            paths,
            hierarchies,
            metrics,
            records,
            bitsets: total - paths - hierarchies - metrics - records,
        }
    }

    /// Stores an indexed world under its global index and evaluates it against every live
    /// constraint of every session (§4.4: results update as worlds stream in).
    pub fn insert(&mut self, mut world: IndexedWorld) {
        let Some(local) = self.spec.local(world.world) else {
            return;
        };
        let slot = local as usize;
        match self.jobs.get(&world.job_id) {
            Some(job) => world.job_id = job.clone(),
            None => {
                self.jobs.insert(world.job_id.clone());
            }
        }
        let global = world.world;
        for s in self.sessions.values_mut() {
            s.set.on_new_world(global, |c, _| evaluate(c, Some(&world)));
        }
        if let Some(old) = self.worlds.get(slot) {
            for b in self.bvh.iter_mut().take(old.objects.len()) {
                b.remove(global);
            }
        }
        if self.bvh.len() < world.objects.len() {
            let block = self.block;
            self.bvh
                .resize_with(world.objects.len(), || PathBvh::with_block(block));
        }
        for (o, obj) in world.objects.iter().enumerate() {
            self.bvh[o].insert(global, obj);
        }
        self.all.insert(global);
        self.world_bytes += world_heap_bytes(&world);
        match self.worlds.set(slot, world) {
            None => self.indexed += 1,
            Some(old) => self.world_bytes -= world_heap_bytes(&old),
        }
    }

    /// Answers one request from node-query.
    pub fn handle(&mut self, req: &ShardRequest) -> ShardReply {
        if req.request == Request::Close {
            self.sessions.remove(&req.session);
            return ShardReply::Ok {
                edits: 0,
                reply: Reply::Closed,
            };
        }
        if !self.sessions.contains_key(&req.session) {
            if self.sessions.len() >= MAX_SESSIONS {
                return ShardReply::Ok {
                    edits: 0,
                    reply: Reply::Error {
                        message: format!(
                            "shard {} already holds {MAX_SESSIONS} sessions; close some",
                            self.name
                        ),
                    },
                };
            }
            let mut session = Session::default();
            for w in self.worlds.values() {
                session.set.on_new_world(w.world, |_, _| true);
            }
            self.sessions.insert(req.session.clone(), session);
        }
        let Some(mut session) = self.sessions.remove(&req.session) else {
            return ShardReply::OutOfSync { edits: 0 };
        };
        let reply = if req.request.is_edit() {
            match req.seq {
                Some(seq) if seq == session.edits + 1 => {
                    let r = self.edit(&mut session.set, &req.request);
                    // A refused edit (e.g. unknown id) still uses up its number, so that every
                    // shard keeps counting the same way.
                    session.edits = seq;
                    ShardReply::Ok {
                        edits: session.edits,
                        reply: match r {
                            Ok(()) => self.status(&session),
                            Err(e) => Reply::Error {
                                message: e.to_string(),
                            },
                        },
                    }
                }
                Some(seq) if seq <= session.edits => ShardReply::Ok {
                    edits: session.edits,
                    reply: self.status(&session),
                },
                _ => ShardReply::OutOfSync {
                    edits: session.edits,
                },
            }
        } else {
            ShardReply::Ok {
                edits: session.edits,
                reply: self.read(&session, &req.request),
            }
        };
        self.sessions.insert(req.session.clone(), session);
        reply
    }

    fn edit(&self, set: &mut ConstraintSet, request: &Request) -> Result<(), EditError> {
        let worlds = &self.worlds;
        let spec = self.spec;
        let lookup = |w: u32| spec.local(w).and_then(|l| worlds.get(l as usize));
        match request {
            Request::Add { constraint } => {
                constraint.validate()?;
                if set.get(constraint.id).is_some() {
                    Err(EditError::AlreadyLive { id: constraint.id })
                } else {
                    let satisfied = self.evaluate_all(constraint);
                    Ok(set.add_evaluated((**constraint).clone(), satisfied)?)
                }
            }
            Request::Remove { id } => Ok(set.remove(*id)?),
            // Every shard holds the same stacks (the same numbered edits), so all refuse alike.
            Request::Undo => set
                .undo(|c, w| evaluate(c, lookup(w)))
                .then_some(())
                .ok_or(EditError::NothingToUndo),
            Request::Redo => set
                .redo(|c, w| evaluate(c, lookup(w)))
                .then_some(())
                .ok_or(EditError::NothingToRedo),
            _ => Err(EditError::NotAnEdit),
        }
    }

    /// The worlds satisfying `constraint`. The chosen objects' hierarchies are cut into shares
    /// that `threads` threads take one at a time; each walks its share down to the path pieces
    /// that may meet the frustum and runs the exact test on those (the segments in the window
    /// and, for a path's last piece, the final pose held after the end; or the final pose
    /// only), skipping the worlds it has already found touched. With [`Quantifier::Any`] a
    /// world is touched when one chosen object is, with [`Quantifier::All`] when each is
    /// (one pass per object, intersected). Positive constraints keep the touched worlds,
    /// negative ones the others.
    pub fn evaluate_all(&self, constraint: &Constraint) -> WorldSet {
        let touched = match constraint.quantifier {
            Quantifier::Any => self.touched_by(constraint, &constraint.objects, None),
            Quantifier::All => {
                let mut objects = constraint.objects.iter();
                match objects.next() {
                    None => WorldSet::new(),
                    Some(&first) => {
                        // Each later pass looks only at the worlds every earlier one kept.
                        let mut acc = self.touched_by(constraint, &[first], None);
                        for &o in objects {
                            if acc.is_empty() {
                                break;
                            }
                            acc = self.touched_by(constraint, &[o], Some(&acc));
                        }
                        acc
                    }
                }
            }
        };
        match constraint.polarity {
            mwb_core::browse::Polarity::Positive => touched,
            mwb_core::browse::Polarity::Negative => self.all.and_not(&touched),
        }
    }

    /// The worlds in which some object of `objects` enters `constraint`'s frustum (its window
    /// and scope apply; its objects and quantifier do not), among `within` if given.
    ///
    /// The work is every object's hierarchy in parts, ordered by block so that the threads
    /// work on the same few thousand worlds at a time (their paths then come from the caches),
    /// the objects of one block side by side. A world found touched is marked in one set all
    /// threads share, and its other pieces — of any object — are passed over unread.
    fn touched_by(
        &self,
        constraint: &Constraint,
        objects: &[u32],
        within: Option<&WorldSet>,
    ) -> WorldSet {
        let threads = self.threads.max(1);
        let mut work: Vec<(usize, &PathBvh, Option<Aabb>, Part)> = Vec::new();
        let mut pieces = 0;
        for &o in objects {
            let Some(b) = self.bvh.get(o as usize).filter(|b| !b.is_empty()) else {
                continue;
            };
            pieces += b.len();
            // The vertex box of the frustum inflated by every radius of this hierarchy.
            let region = region_box(&constraint.frustum.inflated_bounded(b.max_radius()));
            work.extend(
                b.parts(4 * threads)
                    .into_iter()
                    .map(|p| (o as usize, b, region, p)),
            );
        }
        // Stable: a block's subtrees stay in order.
        work.sort_by_key(|&(o, _, _, p)| (p.block(), o));
        // A final-pose constraint has no window: every path's last piece reaches to +∞ anyway.
        let window = match constraint.scope {
            Scope::Motion => constraint.window,
            Scope::FinalPose => None,
        };
        // Global indices of this shard's worlds are below this.
        let end = self
            .worlds
            .len()
            .checked_sub(1)
            .and_then(|last| self.spec.global(last as u32))
            .map_or(0, |g| g as usize + 1);
        let found: Vec<AtomicU64> = (0..end.div_ceil(64)).map(|_| AtomicU64::new(0)).collect();
        let is_found = |w: u32| {
            found
                .get(w as usize / 64)
                .is_some_and(|x| x.load(Ordering::Relaxed) & (1 << (w % 64)) != 0)
        };
        let mark = |w: u32| {
            if let Some(x) = found.get(w as usize / 64) {
                x.fetch_or(1 << (w % 64), Ordering::Relaxed);
            }
        };
        let next = AtomicUsize::new(0);
        let run = || {
            // The frustum inflated by each path radius met: radii are rounded at ingest, so
            // there are only a few.
            let mut regions = RegionCache::new(&constraint.frustum);
            let mut batch = Vec::with_capacity(BATCH);
            let mut paths = Vec::with_capacity(BATCH);
            while let Some(&(o, bvh, region, part)) = work.get(next.fetch_add(1, Ordering::Relaxed))
            {
                // The exact test of a batch of pieces: the paths they are cut from are read
                // stage by stage (world records, the objects, the paths' headers, the pieces'
                // vertices), each stage a run of independent loads, so that their cache
                // misses overlap (each costs a trip to main memory, dependent on the one
                // before: one after another they were most of a query's time).
                let mut test = |batch: &mut Vec<Piece<'_>>, regions: &mut RegionCache<'_>| {
                    batch.retain(|p| !is_found(p.world()));
                    paths.clear();
                    paths.extend(
                        batch
                            .iter()
                            .map(|p| self.world(p.world()).and_then(|w| w.objects.get(o))),
                    );
                    let mut touched = 0u64;
                    for path in paths.iter().flatten() {
                        touched ^= path.radius.to_bits();
                    }
                    for path in paths.iter().flatten() {
                        touched ^= u64::from(path.header_byte());
                    }
                    for (p, path) in batch.iter().zip(&paths) {
                        if let Some(path) = path {
                            touched ^= u64::from(path.vertex_byte(p.first_segment()));
                        }
                    }
                    std::hint::black_box(touched);
                    for (p, path) in batch.iter().zip(&paths) {
                        let Some(path) = path else { continue };
                        if is_found(p.world()) {
                            continue;
                        }
                        let region = regions.region(path.radius);
                        let hit = match constraint.scope {
                            Scope::Motion => p.first_entry(path, region, window).is_some(),
                            Scope::FinalPose => p.final_pose_inside(path, region),
                        };
                        if hit {
                            mark(p.world());
                        }
                    }
                    batch.clear();
                };
                bvh.query(
                    part,
                    &constraint.frustum,
                    region.as_ref(),
                    window,
                    |w| is_found(w) || within.is_some_and(|s| !s.contains(w)),
                    |p| {
                        // Answers that need no look-up of the path (each is what the exact
                        // test would say): only a last piece holds the final pose, and a piece
                        // inside every plane is inside from its first segment on.
                        let decided = match constraint.scope {
                            Scope::FinalPose if !p.is_last() => Some(false),
                            Scope::FinalPose => p.inside_all().then_some(true),
                            Scope::Motion => (p.inside_all() && window.is_none()).then_some(true),
                        };
                        match decided {
                            Some(true) => mark(p.world()),
                            Some(false) => {}
                            None => {
                                batch.push(p);
                                if batch.len() == BATCH {
                                    test(&mut batch, &mut regions);
                                }
                            }
                        }
                    },
                );
                test(&mut batch, &mut regions);
            }
        };
        let threads = threads.min(pieces / 4096).max(1);
        std::thread::scope(|s| {
            let handles: Vec<_> = (1..threads).map(|_| s.spawn(run)).collect();
            run();
            for h in handles {
                h.join().unwrap_or_else(|e| std::panic::resume_unwind(e));
            }
        });
        WorldSet::from_words(found.into_iter().map(AtomicU64::into_inner).collect())
    }

    /// [`evaluate_all`](Self::evaluate_all) without the hierarchies: every world's paths,
    /// world by world, segment by segment (on `threads` threads), for benchmarks and as the
    /// reference in tests.
    pub fn evaluate_each(&self, constraint: &Constraint) -> WorldSet {
        let worlds: Vec<&IndexedWorld> = self.worlds.values().collect();
        let threads = self.threads.min(worlds.len() / 256).max(1);
        let chunk = worlds.len().div_ceil(threads).max(1);
        std::thread::scope(|s| {
            let handles: Vec<_> = worlds
                .chunks(chunk)
                .map(|part| {
                    s.spawn(move || {
                        let mut regions = RegionCache::new(&constraint.frustum);
                        part.iter()
                            .filter(|w| {
                                constraint.satisfied_given(touched_world(
                                    constraint,
                                    &mut regions,
                                    w,
                                ))
                            })
                            .map(|w| w.world)
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

    fn status(&self, session: &Session) -> Reply {
        Reply::Status(status_of(&session.set, session.edits))
    }

    fn read(&self, session: &Session, request: &Request) -> Reply {
        let set = &session.set;
        match request {
            Request::Status => self.status(session),
            Request::Result { limit } => Reply::Worlds {
                result: set.result().len() as u64,
                worlds: set
                    .result()
                    .iter()
                    .take(limit.unwrap_or(usize::MAX))
                    .collect(),
            },
            Request::Rank { key, .. } if let Err(e) = key.validate() => Reply::Error {
                message: format!("rank key: {e}"),
            },
            Request::Rank {
                key,
                order,
                k,
                all_worlds,
                plausible_only,
            } => {
                let candidates = if *all_worlds {
                    set.worlds()
                } else {
                    set.result()
                };
                let plausible = |w: u32| {
                    !*plausible_only
                        || self
                            .world(w)
                            .is_some_and(|x| x.world_metrics().plausible == Some(true))
                };
                let count = if *plausible_only {
                    candidates.iter().filter(|w| plausible(*w)).count()
                } else {
                    candidates.len()
                };
                let (rows, unscored) = top_k_counted(
                    candidates.iter().filter(|w| plausible(*w)),
                    *k,
                    *order,
                    |w| {
                        let world = self.world(w)?;
                        score(key, world, set.satisfied_count(w))
                    },
                );
                Reply::Ranking {
                    candidates: count as u64,
                    unscored,
                    rows,
                }
            }
            Request::Summary { world } => match self.world(*world) {
                None => Reply::NoSuchWorld { world: *world },
                Some(w) => Reply::Summary(Box::new(WorldSummary {
                    world: w.world,
                    job: w.job_id.to_string(),
                    seed: w.seed,
                    frames: w.frames,
                    frame_dt: w.frame_dt,
                    rested: w.rested,
                    bodies: w.bodies.to_vec(),
                    objects: w.metrics.iter().map(PackedMetrics::unpack).collect(),
                    path_radius: w.objects.iter().map(|o| o.radius).collect(),
                    world_metrics: *w.world_metrics(),
                    constraints_satisfied: set.satisfied_count(w.world),
                    in_result: set.result().contains(w.world),
                    shard: self.name.clone(),
                    refined: w.refined.as_deref().cloned(),
                })),
            },
            Request::Bodies => Reply::Bodies {
                scenes: self.bodies(),
            },
            _ => Reply::Error {
                message: "not a read".to_owned(),
            },
        }
    }

    /// One entry per distinct body list among the worlds held (worlds of one job share theirs).
    fn bodies(&self) -> Vec<SceneBodies> {
        let mut runs: Vec<(&IndexedWorld, u64)> = Vec::new();
        for w in self.worlds.values() {
            match runs.last_mut() {
                Some((first, n))
                    if std::sync::Arc::ptr_eq(&first.bodies, &w.bodies)
                        && first.objects.len() == w.objects.len() =>
                {
                    *n += 1;
                }
                _ => runs.push((w, 1)),
            }
        }
        merge_bodies(
            runs.into_iter()
                .map(|(w, worlds)| SceneBodies {
                    objects: w.objects.len() as u32,
                    names: w.bodies.to_vec(),
                    worlds,
                })
                .collect(),
        )
    }
}

/// What one indexed world holds on the heap beyond its slot in the world table.
fn world_heap_bytes(w: &IndexedWorld) -> usize {
    w.heap_bytes()
}

fn score(key: &RankKey, world: &IndexedWorld, satisfied: u32) -> Option<f64> {
    key.score_with(&world.metrics, world.world_metrics(), satisfied)
}

/// Whether a world satisfies a constraint; a world that could not be indexed satisfies none.
fn evaluate(c: &Constraint, world: Option<&IndexedWorld>) -> bool {
    world.is_some_and(|w| c.satisfied_given(touched_world(c, &mut RegionCache::new(&c.frustum), w)))
}

/// Whether `world`'s chosen objects come within `c`'s frustum inflated by each path's radius
/// (`regions`: a cache of that frustum), as [`Constraint::touched`] decides it for OBB trees:
/// some of them, or every one with [`Quantifier::All`]; objects the world lacks do not touch it.
fn touched_world(c: &Constraint, regions: &mut RegionCache<'_>, world: &IndexedWorld) -> bool {
    let mut enters = |o: u32| {
        world.objects.get(o as usize).is_some_and(|path| {
            let region = regions.region(path.radius);
            match c.scope {
                Scope::Motion => path.first_entry(region, c.window).is_some(),
                Scope::FinalPose => path.final_pose_inside(region),
            }
        })
    };
    match c.quantifier {
        Quantifier::Any => c.objects.iter().any(|&o| enters(o)),
        Quantifier::All => !c.objects.is_empty() && c.objects.iter().all(|&o| enters(o)),
    }
}

fn status_of(set: &ConstraintSet, edits: u64) -> SessionStatus {
    SessionStatus {
        worlds: set.worlds().len() as u64,
        result: set.result().len() as u64,
        constraints: set
            .constraints()
            .map(|c| ConstraintStatus {
                id: c.id,
                polarity: c.polarity,
                objects: c.objects.clone(),
                quantifier: c.quantifier,
                window: c.window,
                scope: c.scope,
                satisfied: set.satisfied(c.id).map_or(0, |s| s.len() as u64),
            })
            .collect(),
        can_undo: set.can_undo(),
        can_redo: set.can_redo(),
        edits,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mwb_core::browse::ObjectMetrics;
    use mwb_core::browse::api::SceneBodies;
    use mwb_core::browse::api::merge;
    use mwb_core::browse::{
        Aggregate, ConstraintId, Frustum, Metric, Order, Polarity, Polyline, TimeWindow,
        WorldMetric,
    };

    /// A one-object world whose object slides along x at height `y` from t = 0 to 1.
    fn world(global: u32, y: f64, spin: f64) -> IndexedWorld {
        let path = Polyline::new(vec![0.0, 1.0], vec![[-2.0, y, 0.0], [2.0, y, 0.0]])
            .unwrap_or_else(|e| panic!("{e}"));
        IndexedWorld {
            world: global,
            job_id: "j".into(),
            seed: u64::from(global) * 7 + 1,
            frames: 121,
            frame_dt: 1.0 / 120.0,
            rested: true,
            bodies: std::sync::Arc::from(vec!["box".to_owned()]),
            objects: Box::new([
                IndexedObject::new(&path, 0.5, 0.001).unwrap_or_else(|e| panic!("{e}"))
            ]),
            metrics: Box::new([PackedMetrics::pack(&ObjectMetrics {
                angular_travel_rad: spin,
                time_to_rest_s: 1.0,
                came_to_rest: true,
                impacts: 0,
                orientation_error_rad: 0.0,
                final_rotation: [0.0, 0.0, 0.0, 1.0],
            })]),
            measured: None,
            refined: None,
        }
    }

    /// Only plausible worlds are candidates under `plausible_only`, and the excess ranks them.
    #[test]
    fn plausible_only_ranks_the_plausible_worlds() {
        let mut shard = Shard::new(ShardSpec::default(), "a");
        for (i, (plausible, excess)) in [
            (None, None),
            (Some(true), Some(-0.2)),
            (Some(false), Some(0.5)),
            (Some(true), Some(-0.7)),
        ]
        .into_iter()
        .enumerate()
        {
            let mut w = world(i as u32, 0.0, 1.0);
            w.set_world_metrics(mwb_core::browse::WorldMetrics {
                plausible,
                plausibility_excess: excess,
                ..Default::default()
            });
            shard.insert(w);
        }
        let rank = |plausible_only| Request::Rank {
            key: RankKey::World {
                metric: WorldMetric::PlausibilityExcess,
            },
            order: Order::Ascending,
            k: 10,
            all_worlds: true,
            plausible_only,
        };
        match read(&mut shard, rank(true)) {
            Reply::Ranking {
                candidates,
                unscored,
                rows,
            } => {
                assert_eq!((candidates, unscored), (2, 0));
                assert_eq!(rows.iter().map(|r| r.world).collect::<Vec<_>>(), vec![3, 1]);
            }
            other => panic!("{other:?}"),
        }
        match read(&mut shard, rank(false)) {
            Reply::Ranking {
                candidates,
                unscored,
                rows,
            } => {
                // The forward world has no excess: unscored, last.
                assert_eq!((candidates, unscored), (4, 1));
                assert_eq!(
                    rows.iter().map(|r| r.world).collect::<Vec<_>>(),
                    vec![3, 1, 2, 0]
                );
                assert!(rows[3].score.is_none());
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn path_batches_follow_the_sample_and_the_named_worlds() {
        use mwb_core::browse::sample::{context_threshold, in_context};
        let mut shard = Shard::new(ShardSpec::default(), "a");
        for i in 0..2_000u32 {
            shard.insert(world(i, 0.0, 1.0));
        }
        let ids = |b: &PathBatch| b.worlds.iter().map(|w| w.world).collect::<Vec<u32>>();
        // No sample: every world, in slot order, the cursor past the last one sent.
        let b = shard.path_batch(0, 300, 0);
        assert_eq!(ids(&b), (0..300).collect::<Vec<_>>());
        assert_eq!((b.first_local, b.next_local), (0, 300));
        // A sample of about 200: batch after batch, exactly the worlds in it.
        let t = context_threshold(200, 2_000);
        let (mut seen, mut got) = (0, Vec::new());
        loop {
            let b = shard.path_batch(seen, 64, t);
            got.extend(ids(&b));
            if b.next_local == seen {
                break;
            }
            seen = b.next_local;
        }
        let want: Vec<u32> = (0..2_000).filter(|&w| in_context(w, t)).collect();
        assert_eq!(got, want);
        assert!((150..250).contains(&got.len()), "{}", got.len());
        // Named worlds: those held, in the order asked, at most `max`; no cursor.
        let b = shard.paths_of(&[7, 5_000, 3, 1_999], 10);
        assert_eq!(ids(&b), vec![7, 3, 1_999]);
        assert_eq!((b.first_local, b.next_local), (0, 0));
        assert_eq!(ids(&shard.paths_of(&[7, 3, 1_999], 2)), vec![7, 3]);
    }

    fn through_origin(id: u64, polarity: Polarity) -> Constraint {
        Constraint {
            id: ConstraintId(id),
            polarity,
            frustum: Frustum::aabb([-0.1, -0.1, -0.1], [0.1, 0.1, 0.1])
                .unwrap_or_else(|e| panic!("{e}")),
            objects: vec![0],
            window: None,
            quantifier: Quantifier::Any,
            scope: Scope::Motion,
        }
    }

    fn edit(shard: &mut Shard, seq: u64, request: Request) -> ShardReply {
        shard.handle(&ShardRequest {
            session: "s".into(),
            seq: Some(seq),
            request,
        })
    }

    fn read(shard: &mut Shard, request: Request) -> Reply {
        match shard.handle(&ShardRequest {
            session: "s".into(),
            seq: None,
            request,
        }) {
            ShardReply::Ok { reply, .. } => reply,
            other => panic!("{other:?}"),
        }
    }

    fn result(shard: &mut Shard) -> Vec<u32> {
        match read(shard, Request::Result { limit: None }) {
            Reply::Worlds { worlds, .. } => worlds,
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn shard_spec_parses_splits_and_numbers() {
        assert_eq!(
            ShardSpec::parse("1/3"),
            Ok(ShardSpec { index: 1, count: 3 })
        );
        for bad in ["3/3", "0/0", "x/2", "1", "1/y"] {
            assert!(ShardSpec::parse(bad).is_err(), "{bad}");
        }
        let s = ShardSpec::new(1, 3).unwrap_or_default();
        assert_eq!(s.global(0), Some(1));
        assert_eq!(s.global(2), Some(7));
        assert_eq!(s.local(7), Some(2));
        assert_eq!(s.local(6), None);
        assert_eq!(s.global(u32::MAX), None);
        // Every world has exactly one owner, and the split is roughly even.
        let mut per = [0u32; 3];
        for seed in 0..3000u64 {
            let owners: Vec<u32> = (0..3)
                .filter(|&i| ShardSpec { index: i, count: 3 }.owns("job", seed))
                .collect();
            assert_eq!(owners.len(), 1);
            per[owners[0] as usize] += 1;
        }
        assert!(per.iter().all(|&n| (900..1100).contains(&n)), "{per:?}");
        assert_ne!(
            (0..64)
                .map(|s| ShardSpec::shard_of("a", s, 2))
                .collect::<Vec<_>>(),
            (0..64)
                .map(|s| ShardSpec::shard_of("b", s, 2))
                .collect::<Vec<_>>()
        );
        assert!(matches!(
            ShardSpec::parse("1/y"),
            Err(ShardSpecError::NotANumber { field: "count", ref value, .. }) if value == "y"
        ));
        assert_eq!(
            ShardSpec::parse("3/3"),
            Err(ShardSpecError::OutOfRange { index: 3, count: 3 })
        );
    }

    /// Golden values of the shard assignment, minted with an independent FNV-1a 64 (offset
    /// 0xcbf29ce484222325, prime 0x100000001b3) over the job id's bytes, one 0xff byte and the
    /// seed's 8 little-endian bytes, then `mod count`. A change here moves stored worlds to
    /// other shards: shards started by different builds would disagree on which worlds they
    /// keep (two keep one, or none does) and global indices would change. Change the hash only
    /// on purpose, with every shard of a cluster upgraded together; then re-mint these from
    /// the new definition with a few lines outside this crate, not from `shard_of` itself.
    #[test]
    fn shard_assignment_is_pinned() {
        let golden: [(&str, u64, u32, u32); 8] = [
            ("job", 42, 1000, 851),
            ("job", 42, 2, 1),
            ("job", 0, 3, 2),
            ("tower-1", 7, 4, 2),
            ("demo", 1, 16, 10),
            ("job", u64::MAX, 1000, 249),
            // A count of 2^32 - 1 shows 32 bits of the hash.
            ("j", 123_456_789, u32::MAX, 1_769_579_913),
            ("", 0, u32::MAX, 1_448_280_722),
        ];
        for (job, seed, count, shard) in golden {
            assert_eq!(
                ShardSpec::shard_of(job, seed, count),
                shard,
                "shard_of({job:?}, {seed}, {count}) changed: worlds would move shards"
            );
        }
    }

    #[test]
    fn edits_apply_in_order_and_new_worlds_are_evaluated_live() {
        let mut shard = Shard::new(ShardSpec::default(), "a");
        shard.insert(world(0, 0.0, 1.0));
        shard.insert(world(1, 3.0, 2.0));
        // Edit 2 before edit 1: refused with the count it has.
        assert_eq!(
            edit(&mut shard, 2, Request::Undo),
            ShardReply::OutOfSync { edits: 0 }
        );
        let r = edit(
            &mut shard,
            1,
            Request::Add {
                constraint: Box::new(through_origin(1, Polarity::Positive)),
            },
        );
        assert!(matches!(r, ShardReply::Ok { edits: 1, .. }), "{r:?}");
        assert_eq!(result(&mut shard), vec![0]);
        // A repeated edit number is not applied twice.
        let again = edit(
            &mut shard,
            1,
            Request::Add {
                constraint: Box::new(through_origin(1, Polarity::Positive)),
            },
        );
        assert!(matches!(
            again,
            ShardReply::Ok {
                edits: 1,
                reply: Reply::Status(_)
            }
        ));
        // Live: a new world through the origin joins the result, one beside it does not.
        shard.insert(world(2, 0.05, 3.0));
        shard.insert(world(3, -4.0, 4.0));
        assert_eq!(result(&mut shard), vec![0, 2]);
        // A negative constraint on the same box keeps the complement; together: nothing.
        edit(
            &mut shard,
            2,
            Request::Add {
                constraint: Box::new(through_origin(2, Polarity::Negative)),
            },
        );
        assert_eq!(result(&mut shard), Vec::<u32>::new());
        // Removing the *first* constraint leaves the second's bits.
        edit(
            &mut shard,
            3,
            Request::Remove {
                id: ConstraintId(1),
            },
        );
        assert_eq!(result(&mut shard), vec![1, 3]);
        // Undo brings it back; a world arriving while it was off is evaluated on return.
        shard.insert(world(4, 0.0, 5.0));
        edit(&mut shard, 4, Request::Undo);
        assert_eq!(result(&mut shard), Vec::<u32>::new());
        edit(
            &mut shard,
            5,
            Request::Remove {
                id: ConstraintId(2),
            },
        );
        assert_eq!(result(&mut shard), vec![0, 2, 4]);
        // Unknown ids are refused but use up their number.
        let r = edit(
            &mut shard,
            6,
            Request::Remove {
                id: ConstraintId(9),
            },
        );
        assert!(
            matches!(&r, ShardReply::Ok { edits: 6, reply: Reply::Error { message } } if message.contains('9')),
            "{r:?}"
        );
        // Ranking: survivors by spin, descending; ties by index; constraints over all worlds.
        match read(
            &mut shard,
            Request::Rank {
                key: RankKey::Metric {
                    metric: Metric::AngularTravel,
                    objects: vec![0],
                    aggregate: Aggregate::Sum,
                },
                order: Order::Descending,
                k: 2,
                all_worlds: false,
                plausible_only: false,
            },
        ) {
            Reply::Ranking {
                candidates, rows, ..
            } => {
                assert_eq!(candidates, 3);
                assert_eq!(rows.iter().map(|r| r.world).collect::<Vec<_>>(), vec![4, 2]);
            }
            other => panic!("{other:?}"),
        }
        match read(&mut shard, Request::Summary { world: 4 }) {
            Reply::Summary(s) => {
                assert_eq!((s.world, s.seed, s.constraints_satisfied), (4, 29, 1));
                assert!(s.in_result && s.shard == "a");
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(
            read(&mut shard, Request::Summary { world: 40 }),
            Reply::NoSuchWorld { world: 40 }
        );
        assert!(shard.heap_bytes() > 0);
        assert_eq!(read(&mut shard, Request::Close), Reply::Closed);
        // A closed session starts afresh.
        match read(&mut shard, Request::Status) {
            Reply::Status(st) => assert_eq!((st.edits, st.constraints.len(), st.result), (0, 0, 5)),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn hierarchy_answers_like_testing_every_world() {
        let mut shard = Shard::new(ShardSpec::default(), "a");
        // Small hierarchy blocks: the re-insertion below rebuilds the one that held world 5.
        shard.set_block(256);
        for i in 0..2000u32 {
            let y = f64::from(i % 97) * 0.05 - 2.0;
            shard.insert(world(i, y, 0.0));
        }
        // Re-inserting a world replaces its boxes.
        shard.insert(world(5, 40.0, 0.0));
        for k in 0..60 {
            let y = f64::from(k) * 0.09 - 2.5;
            let h = 0.01 + f64::from(k % 7) * 0.05;
            let c = Constraint {
                id: ConstraintId(1),
                polarity: if k % 3 == 0 {
                    Polarity::Negative
                } else {
                    Polarity::Positive
                },
                frustum: Frustum::aabb([-0.2, y - h, -0.2], [0.2, y + h, 0.2])
                    .unwrap_or_else(|e| panic!("{e}")),
                objects: vec![0],
                window: None,
                quantifier: Quantifier::Any,
                scope: Scope::Motion,
            };
            let fast = shard.evaluate_all(&c);
            assert_eq!(fast, shard.evaluate_each(&c), "constraint {k}");
            assert!(!fast.contains(5) || c.polarity == Polarity::Negative);
        }
    }

    /// Camera frusta at every bearing, paths of every shape, a spread of radii (as rounded at
    /// ingest), a time window in a third of the constraints: the hierarchy of path pieces and
    /// the per-world OBB trees each keep exactly the worlds a segment-by-segment test of the
    /// inflated planes keeps — no more (pruning is exact where it matters) and no fewer (never
    /// miss).
    #[test]
    fn pruned_evaluation_equals_brute_force_for_camera_frusta() {
        use mwb_core::browse::{Camera, Intrinsics, ScreenRect, Viewport};
        use mwb_core::rng::{Stream, WorldRng};
        let mut rng = WorldRng::new(11, Stream::Scene);
        let mut shard = Shard::new(ShardSpec::default(), "a");
        // Small hierarchy blocks: many of them, and the pending list, are tested.
        shard.set_block(300);
        let mut paths = Vec::new();
        for i in 0..1500u32 {
            let mut p = [
                rng.uniform(-3.0, 3.0),
                rng.uniform(0.0, 2.0),
                rng.uniform(-3.0, 3.0),
            ];
            let (mut times, mut points) = (Vec::new(), Vec::new());
            for k in 0..(2 + i % 40) {
                times.push(f64::from(k) * 0.05);
                points.push(p);
                for v in &mut p {
                    *v += rng.uniform(-0.3, 0.3);
                }
            }
            let path = Polyline::new(times, points).unwrap_or_else(|e| panic!("{e}"));
            let radius = (rng.uniform(0.0, 0.05) / 0.0005).ceil() * 0.0005;
            let mut w = world(i, 0.0, 0.0);
            let obj = IndexedObject::new(&path, 0.05, radius).unwrap_or_else(|e| panic!("{e}"));
            // Brute force on the path as stored (grid-rounded, its radius grown to match).
            paths.push((obj.polyline(), obj.radius));
            w.objects[0] = obj;
            shard.insert(w);
        }
        let mut kept_some = 0;
        for k in 0..200u64 {
            let target = [
                rng.uniform(-3.0, 3.0),
                rng.uniform(0.0, 2.0),
                rng.uniform(-3.0, 3.0),
            ];
            let dir = [
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
            ];
            let len = (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2])
                .sqrt()
                .max(1e-6);
            let d = rng.uniform(2.0, 12.0);
            let eye = [0, 1, 2].map(|j| target[j] + dir[j] / len * d);
            // Rotation taking the camera's −z onto the viewing direction (target − eye).
            let f = [0, 1, 2].map(|j| -dir[j] / len);
            let (ax, dot) = ([f[1], -f[0], 0.0], -f[2]); // (0,0,−1) × f, (0,0,−1)·f
            let half = dot.clamp(-1.0, 1.0).acos() / 2.0;
            let an = (ax[0] * ax[0] + ax[1] * ax[1]).sqrt();
            let rotation = if an < 1e-9 {
                if dot > 0.0 {
                    [0.0, 0.0, 0.0, 1.0]
                } else {
                    [1.0, 0.0, 0.0, 0.0]
                }
            } else {
                let s = half.sin() / an;
                [ax[0] * s, ax[1] * s, 0.0, half.cos()]
            };
            let camera = Camera {
                position: eye,
                rotation,
                intrinsics: Intrinsics::VerticalFov {
                    fov_y_rad: rng.uniform(0.3, 1.4),
                },
                viewport: Viewport {
                    width: 1280,
                    height: 720,
                },
                near: 0.1,
                far: 50.0,
            };
            let (cx, cy) = (rng.uniform(200.0, 1080.0), rng.uniform(100.0, 620.0));
            let (rw, rh) = (rng.uniform(1.0, 300.0), rng.uniform(1.0, 300.0));
            let frustum = camera
                .frustum(&ScreenRect {
                    x0: cx,
                    y0: cy,
                    x1: cx + rw,
                    y1: cy + rh,
                })
                .unwrap_or_else(|e| panic!("{e}"));
            let window = (k % 3 == 0).then(|| {
                let a = rng.uniform(0.0, 2.0);
                TimeWindow::new(a, a + rng.uniform(0.0, 0.5)).unwrap_or_else(|e| panic!("{e}"))
            });
            let c = Constraint {
                id: ConstraintId(k + 1),
                polarity: Polarity::Positive,
                frustum,
                objects: vec![0],
                window,
                quantifier: Quantifier::Any,
                scope: Scope::Motion,
            };
            let brute: WorldSet = paths
                .iter()
                .enumerate()
                .filter(|(_, (p, r))| p.first_entry(&c.frustum.inflated(*r), window).is_some())
                .map(|(i, _)| i as u32)
                .collect();
            kept_some += usize::from(!brute.is_empty());
            assert_eq!(shard.evaluate_all(&c), brute, "constraint {k}");
            assert_eq!(shard.evaluate_each(&c), brute, "constraint {k}");
        }
        // The frusta are aimed at the paths: most keep some worlds (the test is not vacuous).
        assert!(kept_some > 100, "{kept_some}");
    }

    /// Issue 24 on the shard: "every one of the objects" (`All`), final-pose constraints and
    /// windows past the worlds' ends (bodies held at their final poses) keep exactly the worlds
    /// brute force on the polylines keeps, through the hierarchy and the per-world trees alike.
    #[test]
    fn all_objects_final_poses_and_late_windows_equal_brute_force() {
        use mwb_core::rng::{Stream, WorldRng};
        let mut rng = WorldRng::new(24, Stream::Scene);
        let mut shard = Shard::new(ShardSpec::default(), "a");
        // Small hierarchy blocks: many of them, and the pending list, are tested.
        shard.set_block(200);
        let mut paths: Vec<[(Polyline, f64); 2]> = Vec::new();
        let walk = |rng: &mut WorldRng, n: u32| {
            let mut p = [rng.uniform(-1.0, 1.0), rng.uniform(0.0, 1.0), 0.0];
            let (mut times, mut points) = (Vec::new(), Vec::new());
            for k in 0..n {
                times.push(f64::from(k) * 0.1);
                points.push(p);
                for v in &mut p[..2] {
                    *v += rng.uniform(-0.2, 0.2);
                }
            }
            Polyline::new(times, points).unwrap_or_else(|e| panic!("{e}"))
        };
        for i in 0..800u32 {
            // Worlds end between 0 and 4 s (1 to 41 vertices).
            let a = walk(&mut rng, 1 + i % 41);
            let b = walk(&mut rng, 1 + (i * 7) % 41);
            let r = (rng.uniform(0.0, 0.02) / 0.0005).ceil() * 0.0005;
            let mut w = world(i, 0.0, 0.0);
            let store =
                |p: &Polyline| IndexedObject::new(p, 0.1, r).unwrap_or_else(|e| panic!("{e}"));
            w.objects = Box::new([store(&a), store(&b)]);
            paths.push([
                (w.objects[0].polyline(), w.objects[0].radius),
                (w.objects[1].polyline(), w.objects[1].radius),
            ]);
            shard.insert(w);
        }
        let (mut kept, mut late) = (0, 0);
        for k in 0..240u64 {
            let c = [rng.uniform(-1.0, 1.0), rng.uniform(0.0, 1.0)];
            let h = rng.uniform(0.05, 0.6);
            let window = match k % 4 {
                0 => None,
                1 => {
                    late += 1;
                    let a = rng.uniform(2.0, 6.0);
                    TimeWindow::new(a, a + rng.uniform(0.0, 3.0)).ok()
                }
                _ => {
                    let a = rng.uniform(0.0, 4.0);
                    TimeWindow::new(a, a + rng.uniform(0.0, 1.0)).ok()
                }
            };
            let scope = if k % 5 == 0 {
                Scope::FinalPose
            } else {
                Scope::Motion
            };
            let constraint = Constraint {
                id: ConstraintId(k + 1),
                polarity: if k % 3 == 0 {
                    Polarity::Negative
                } else {
                    Polarity::Positive
                },
                frustum: Frustum::aabb([c[0] - h, c[1] - h, -0.1], [c[0] + h, c[1] + h, 0.1])
                    .unwrap_or_else(|e| panic!("{e}")),
                objects: if k % 7 == 0 { vec![1] } else { vec![0, 1] },
                quantifier: if k % 2 == 0 {
                    Quantifier::All
                } else {
                    Quantifier::Any
                },
                window: window.filter(|_| scope == Scope::Motion),
                scope,
            };
            let enters = |(p, r): &(Polyline, f64)| {
                let region = constraint.frustum.inflated(*r);
                match constraint.scope {
                    Scope::Motion => p.first_entry(&region, constraint.window).is_some(),
                    Scope::FinalPose => p.final_pose_inside(&region),
                }
            };
            let brute: WorldSet = paths
                .iter()
                .enumerate()
                .filter(|(_, objs)| {
                    let mut chosen = constraint
                        .objects
                        .iter()
                        .map(|&o| enters(&objs[o as usize]));
                    let touched = match constraint.quantifier {
                        Quantifier::Any => chosen.any(|x| x),
                        Quantifier::All => chosen.all(|x| x),
                    };
                    constraint.satisfied_given(touched)
                })
                .map(|(i, _)| i as u32)
                .collect();
            kept += usize::from(!brute.is_empty() && brute.len() < 800);
            assert_eq!(shard.evaluate_all(&constraint), brute, "constraint {k}");
            assert_eq!(shard.evaluate_each(&constraint), brute, "constraint {k}");
        }
        assert!(kept > 150 && late > 50, "kept {kept}, late {late}");
    }

    /// Undo and redo with nothing to undo or redo are refused (the client exits non-zero);
    /// a final-pose constraint with a window is refused naming the field; the bodies and a
    /// ranking's unscored count come back.
    #[test]
    fn refused_edits_bodies_and_unscored_worlds() {
        let mut shard = Shard::new(ShardSpec::default(), "a");
        shard.insert(world(0, 0.0, 1.0));
        let mut moving = world(1, 3.0, 2.0);
        let mut m = moving.metrics[0].unpack();
        m.came_to_rest = false;
        moving.metrics[0] = PackedMetrics::pack(&m);
        shard.insert(moving);
        for (seq, req, what) in [
            (1, Request::Redo, "nothing to redo"),
            (2, Request::Undo, "nothing to undo"),
        ] {
            match edit(&mut shard, seq, req) {
                ShardReply::Ok {
                    reply: Reply::Error { message },
                    ..
                } => assert_eq!(message, what),
                other => panic!("{other:?}"),
            }
        }
        let bad = Constraint {
            scope: Scope::FinalPose,
            window: TimeWindow::new(1.0, 2.0).ok(),
            ..through_origin(1, Polarity::Positive)
        };
        match edit(
            &mut shard,
            3,
            Request::Add {
                constraint: Box::new(bad),
            },
        ) {
            ShardReply::Ok {
                reply: Reply::Error { message },
                ..
            } => assert!(message.starts_with("window:"), "{message}"),
            other => panic!("{other:?}"),
        }
        assert_eq!(
            read(&mut shard, Request::Bodies),
            Reply::Bodies {
                scenes: vec![SceneBodies {
                    objects: 1,
                    names: vec!["box".into()],
                    worlds: 2
                }]
            }
        );
        let rank = read(
            &mut shard,
            Request::Rank {
                key: RankKey::Metric {
                    metric: Metric::TimeToRest,
                    objects: vec![0],
                    aggregate: Aggregate::Max,
                },
                order: Order::Ascending,
                k: 5,
                all_worlds: false,
                plausible_only: false,
            },
        );
        match rank {
            Reply::Ranking {
                candidates,
                unscored,
                rows,
            } => {
                assert_eq!((candidates, unscored), (2, 1));
                assert_eq!((rows[0].world, rows[1].score), (0, None));
            }
            other => panic!("{other:?}"),
        }
        match read(&mut shard, Request::Summary { world: 1 }) {
            Reply::Summary(s) => assert_eq!(s.bodies, vec!["box".to_owned()]),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn two_shards_merged_equal_one_and_threads_do_not_matter() {
        let worlds: Vec<(f64, f64)> = (0..700)
            .map(|i| {
                let y = f64::from(i % 13) * 0.04 - 0.2;
                (y, f64::from((i * 37) % 101))
            })
            .collect();
        let mut one = Shard::new(ShardSpec::default(), "one");
        let mut two = [
            Shard::new(ShardSpec { index: 0, count: 2 }, "a"),
            Shard::new(ShardSpec { index: 1, count: 2 }, "b"),
        ];
        two[1].set_threads(1);
        // Another block size must not change an answer either.
        two[0].set_block(64);
        // Same worlds: global index i in `one`, split by parity in `two` (index = i as well).
        for (i, &(y, spin)) in worlds.iter().enumerate() {
            one.insert(world(i as u32, y, spin));
            two[i % 2].insert(world(i as u32, y, spin));
        }
        let requests = [
            Request::Add {
                constraint: Box::new(through_origin(1, Polarity::Positive)),
            },
            Request::Result { limit: Some(50) },
            Request::Add {
                constraint: Box::new(through_origin(2, Polarity::Negative)),
            },
            Request::Undo,
            Request::Status,
            Request::Rank {
                key: RankKey::Metric {
                    metric: Metric::AngularTravel,
                    objects: vec![0],
                    aggregate: Aggregate::Max,
                },
                order: Order::Descending,
                k: 9,
                all_worlds: false,
                plausible_only: false,
            },
            Request::Rank {
                key: RankKey::ConstraintsSatisfied,
                order: Order::Descending,
                k: 20,
                all_worlds: true,
                plausible_only: false,
            },
            Request::Summary { world: 11 },
        ];
        let mut seq = 0;
        for req in requests {
            let seq_now = req.is_edit().then(|| {
                seq += 1;
                seq
            });
            let ask = |s: &mut Shard| match s.handle(&ShardRequest {
                session: "s".into(),
                seq: seq_now,
                request: req.clone(),
            }) {
                ShardReply::Ok { reply, .. } => reply,
                other => panic!("{other:?}"),
            };
            let single = ask(&mut one);
            let parts: Vec<Reply> = two.iter_mut().map(ask).collect();
            let mut merged = merge(&req, parts).unwrap_or_else(|e| panic!("{e}"));
            // The summary names its shard; everything else must match exactly.
            if let (Reply::Summary(a), Reply::Summary(b)) = (&single, &mut merged) {
                b.shard.clone_from(&a.shard);
            }
            assert_eq!(single, merged, "{req:?}");
        }
    }
}
