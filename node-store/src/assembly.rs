//! World assembly: motion segments and `WorldDone`s in, complete CRC-verified worlds out.
//!
//! Pure state machine (no bus, no clock of its own: callers pass `now_ms`), so every rule is
//! unit-tested: CRC checks, completeness, duplicate seeds, the memory cap, job closure, and
//! discarding the partial worlds of samplers that left.

use crate::browse::ShardSpec;
use mwb_proto::v1::{Job, JobKind, JobState, Message, MotionSegment, WorldDone};
use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::Arc;

/// A complete world held in memory.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredWorld {
    /// Global index: dense per shard, `local × shard count + shard index` (bitsets in the
    /// browsing layer are over these).
    pub index: u32,
    pub job_id: String,
    pub done: WorldDone,
    /// In order, `seq` 0..n.
    pub segments: Vec<MotionSegment>,
    /// Encoded size of the segments and the summary.
    pub bytes: u64,
    /// A refined world stored as a difference from its parent (§4.5; see
    /// [`StoredWorld::is_layered`]): the parent, held here for as long as this world is, so a
    /// parent of a live refined world is never dropped.
    pub parent: Option<Arc<StoredWorld>>,
}

impl StoredWorld {
    /// Whether this world's segments are a difference from its parent: they start past segment
    /// 0 (`WorldDone.first_segment`) or carry only some bodies (`MotionSegment.bodies`).
    pub fn is_layered(&self) -> bool {
        is_layered(&self.done, self.segments.iter())
    }

    /// The wire form (`q/world/<index>`), with the parent chain of a layered world.
    pub fn message(&self) -> mwb_proto::v1::World {
        mwb_proto::v1::World {
            index: self.index,
            job_id: self.job_id.clone(),
            done: Some(self.done.clone()),
            segments: self.segments.clone(),
            parent: self.parent.as_ref().map(|p| Box::new(p.message())),
        }
    }
}

fn is_layered<'s>(done: &WorldDone, mut segments: impl Iterator<Item = &'s MotionSegment>) -> bool {
    done.first_segment > 0 || segments.any(|s| !s.bodies.is_empty())
}

/// Why a world was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rejection {
    CrcMismatch,
    /// Segments missing or inconsistent with the `WorldDone`.
    Incomplete,
    /// A refined world sent as a difference from a parent this store does not hold (counted
    /// with the incomplete ones).
    NoParent,
    DuplicateSeed,
    MemoryCap,
    UnknownJob,
    /// The job already had its target (or was cancelled).
    Late,
}

/// The result of feeding one message.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// Waiting for more of this world.
    Pending,
    /// A world was stored; the job's new state.
    Stored { index: u32, state: JobState },
    /// A complete, verified world that belongs to another shard: counted towards its job, not
    /// kept here.
    Counted { state: JobState },
    /// A world was refused; the job's new state if it counts rejections.
    Rejected {
        reason: Rejection,
        state: Option<JobState>,
    },
}

/// Counters for `NodeStats`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Counters {
    pub crc_failures: u64,
    pub incomplete: u64,
    pub duplicates: u64,
    pub refused_memory: u64,
    pub unknown_job: u64,
    pub late: u64,
    pub discarded_partial: u64,
    pub malformed: u64,
}

type WorldKey = (String, String, u64);

#[derive(Debug, Default)]
struct Partial {
    segments: BTreeMap<u32, MotionSegment>,
    done: Option<WorldDone>,
    crc_bad: bool,
    bytes: u64,
    last_ms: u64,
    /// Set when the sampler's liveliness token went away.
    orphaned_ms: Option<u64>,
    /// Complete, but its job is not known yet: since when (see [`Assembler::on_done`]).
    held_ms: Option<u64>,
}

#[derive(Debug)]
struct JobRecord {
    job: Job,
    state: JobState,
    seeds: HashSet<u64>,
}

/// The store's world table.
#[derive(Debug)]
pub struct Assembler {
    jobs: BTreeMap<String, JobRecord>,
    partial: HashMap<WorldKey, Partial>,
    worlds: Vec<Arc<StoredWorld>>,
    stored_bytes: u64,
    /// The browsing index's bytes, as last reported by the node.
    index_bytes: u64,
    /// What the index may grow by on the next world ([`Assembler::set_index_growth`]).
    index_growth: u64,
    partial_bytes: u64,
    cap_bytes: u64,
    shard: ShardSpec,
    /// Bytes of complete worlds held for a job not known yet.
    held_bytes: u64,
    unknown_job_hold_ms: u64,
    pub counters: Counters,
}

/// The global index of the world a REFINE job refines (its worlds are stored on that world's
/// shard).
fn refine_parent(job: &Job) -> Option<u32> {
    if job.kind() != JobKind::Refine {
        return None;
    }
    job.refine.as_ref().map(|r| r.parent_world)
}

/// How long a complete world of a job the store has not seen is held for that job, ms.
pub const UNKNOWN_JOB_HOLD_MS: u64 = 10_000;

impl Assembler {
    /// `cap_bytes`: complete worlds past this total are refused.
    pub fn new(cap_bytes: u64) -> Self {
        Self::sharded(cap_bytes, ShardSpec::default())
    }

    /// A table that keeps only the worlds of `shard` but counts every complete world towards
    /// its job, so that every shard closes a job at the same count.
    pub fn sharded(cap_bytes: u64, shard: ShardSpec) -> Self {
        Self {
            jobs: BTreeMap::new(),
            partial: HashMap::new(),
            worlds: Vec::new(),
            stored_bytes: 0,
            index_bytes: 0,
            index_growth: 0,
            partial_bytes: 0,
            cap_bytes,
            shard,
            held_bytes: 0,
            unknown_job_hold_ms: UNKNOWN_JOB_HOLD_MS,
            counters: Counters::default(),
        }
    }

    pub fn shard(&self) -> ShardSpec {
        self.shard
    }

    /// How long a complete world whose job is unknown is held (default
    /// [`UNKNOWN_JOB_HOLD_MS`]).
    pub fn set_unknown_job_hold_ms(&mut self, ms: u64) {
        self.unknown_job_hold_ms = ms;
    }

    /// Complete worlds held for a job not known yet.
    pub fn held_count(&self) -> usize {
        self.partial
            .values()
            .filter(|p| p.held_ms.is_some())
            .count()
    }

    pub fn world_count(&self) -> usize {
        self.worlds.len()
    }
    /// A stored world by global index.
    pub fn world(&self, index: u32) -> Option<Arc<StoredWorld>> {
        let local = self.shard.local(index)?;
        self.worlds.get(local as usize).cloned()
    }

    /// Every stored world, in index order.
    pub fn stored(&self) -> impl Iterator<Item = &Arc<StoredWorld>> {
        self.worlds.iter()
    }
    /// Bytes held: stored worlds, partial worlds in flight, and the browsing index (as last
    /// reported with [`set_index_bytes`](Self::set_index_bytes)) — what the cap limits.
    pub fn memory_bytes(&self) -> u64 {
        self.stored_bytes + self.partial_bytes + self.index_bytes
    }

    /// Tells the assembler how many bytes the browsing index of its worlds takes (the index
    /// lives beside it, in the browse shard). Counted against the memory cap: a world is
    /// refused when its bytes, the stored ones, the index and the index the world itself will
    /// need (estimated as the mean so far) would exceed the cap. On a 10-object scene the
    /// index is several times the compressed world, so leaving it out would let a store grow
    /// far past its cap.
    pub fn set_index_bytes(&mut self, bytes: u64) {
        self.index_bytes = bytes;
    }

    /// Tells the assembler how much the index may grow beyond a world's own bytes when the
    /// next world is indexed ([`crate::Shard::growth_bytes`]: a vector doubling its capacity),
    /// kept free under the cap so that a growing index never carries the store past it.
    pub fn set_index_growth(&mut self, bytes: u64) {
        self.index_growth = bytes;
    }

    /// The index bytes a new world is expected to add: the mean over the stored worlds.
    fn index_estimate(&self) -> u64 {
        match self.worlds.len() as u64 {
            0 => 0,
            n => self.index_bytes / n,
        }
    }
    pub fn cap_bytes(&self) -> u64 {
        self.cap_bytes
    }
    pub fn partial_count(&self) -> usize {
        self.partial.len()
    }
    pub fn jobs(&self) -> impl Iterator<Item = (&Job, &JobState)> {
        self.jobs.values().map(|r| (&r.job, &r.state))
    }
    pub fn job_state(&self, job: &str) -> Option<&JobState> {
        self.jobs.get(job).map(|r| &r.state)
    }

    /// A job announcement (new, or a higher revision: e.g. cancelled). Returns the state to
    /// publish when something changed.
    pub fn submit_job(&mut self, job: Job) -> Option<JobState> {
        match self.jobs.get_mut(&job.id) {
            Some(rec) if rec.job.revision >= job.revision => None,
            Some(rec) => {
                let cancel = job.cancelled && !rec.state.closed;
                rec.job = job;
                if cancel {
                    rec.state.closed = true;
                    rec.state.cancelled = true;
                }
                rec.state.target_worlds = rec.job.target_worlds;
                if rec.state.worlds_done >= rec.state.target_worlds {
                    rec.state.closed = true;
                }
                rec.state.revision += 1;
                Some(rec.state.clone())
            }
            None => {
                let state = JobState {
                    job_id: job.id.clone(),
                    revision: 1,
                    target_worlds: job.target_worlds,
                    closed: job.cancelled || job.target_worlds == 0,
                    cancelled: job.cancelled,
                    ..Default::default()
                };
                self.jobs.insert(
                    job.id.clone(),
                    JobRecord {
                        job,
                        state: state.clone(),
                        seeds: HashSet::new(),
                    },
                );
                Some(state)
            }
        }
    }

    /// The authority's view of a job (another shard): its count is adopted when higher (this
    /// shard joined late and missed worlds), and its closure is followed, so that worlds the
    /// authority counts as late are not kept here.
    pub fn adopt_state(&mut self, theirs: &JobState) {
        let Some(rec) = self.jobs.get_mut(&theirs.job_id) else {
            return;
        };
        let st = &mut rec.state;
        let before = (st.worlds_done, st.closed);
        st.worlds_done = st.worlds_done.max(theirs.worlds_done);
        st.closed |= theirs.closed;
        st.cancelled |= theirs.cancelled;
        if (st.worlds_done, st.closed) != before {
            st.revision += 1;
        }
    }

    /// A job state read back from the store's own journal ([`crate::journal`]): counts,
    /// closure and revision are taken where they are ahead of the table's (worlds of other
    /// shards are counted there, not journaled; and the revision must not go back, or those
    /// who follow the job would ignore the next states).
    pub fn restore_state(&mut self, saved: &JobState) {
        let Some(rec) = self.jobs.get_mut(&saved.job_id) else {
            return;
        };
        let st = &mut rec.state;
        st.worlds_done = st.worlds_done.max(saved.worlds_done);
        st.worlds_rejected = st.worlds_rejected.max(saved.worlds_rejected);
        st.worlds_late = st.worlds_late.max(saved.worlds_late);
        st.bytes_stored = st.bytes_stored.max(saved.bytes_stored);
        st.closed |= saved.closed;
        st.cancelled |= saved.cancelled;
        st.revision = st.revision.max(saved.revision);
        if st.first_world_unix_ms == 0 {
            st.first_world_unix_ms = saved.first_world_unix_ms;
        }
        st.last_world_unix_ms = st.last_world_unix_ms.max(saved.last_world_unix_ms);
    }

    pub fn on_segment(&mut self, seg: MotionSegment, now_ms: u64) -> Outcome {
        let key = (seg.job_id.clone(), seg.node_id.clone(), seg.world_counter);
        let crc_ok = crc32fast::hash(&seg.payload) == seg.crc32;
        let size = seg.encoded_len() as u64;
        let p = self.partial.entry(key.clone()).or_default();
        p.last_ms = now_ms;
        if !crc_ok {
            // §4.2: the checksum catches a corrupted segment; the whole world is refused.
            self.counters.crc_failures += 1;
            p.crc_bad = true;
        }
        if !p.segments.contains_key(&seg.seq) {
            p.bytes += size;
            self.partial_bytes += size;
            // A segment for a world already held whole (its summary promised fewer segments):
            // the world is refused as inconsistent below, and what it holds is released — the
            // held total must have counted this segment too.
            if p.held_ms.is_some() {
                self.held_bytes += size;
            }
            p.segments.insert(seg.seq, seg);
        }
        // A single partial world larger than the whole cap can never be stored.
        if p.bytes > self.cap_bytes {
            self.drop_partial(&key);
            self.counters.refused_memory += 1;
            let state = self.count_rejection(&key.0);
            return Outcome::Rejected {
                reason: Rejection::MemoryCap,
                state,
            };
        }
        self.try_complete(key, now_ms)
    }

    pub fn on_done(&mut self, done: WorldDone, now_ms: u64) -> Outcome {
        let key = (
            done.job_id.clone(),
            done.node_id.clone(),
            done.world_counter,
        );
        let p = self.partial.entry(key.clone()).or_default();
        p.last_ms = now_ms;
        p.done = Some(done);
        self.try_complete(key, now_ms)
    }

    fn drop_partial(&mut self, key: &WorldKey) -> Option<Partial> {
        let p = self.partial.remove(key)?;
        self.partial_bytes -= p.bytes;
        if p.held_ms.is_some() {
            self.held_bytes -= p.bytes;
        }
        Some(p)
    }

    /// The worlds held for `job` (complete, but they arrived before the job did), tried again:
    /// call after [`submit_job`](Self::submit_job) announced a new job.
    pub fn release_held(&mut self, job: &str, now_ms: u64) -> Vec<Outcome> {
        let keys: Vec<WorldKey> = self
            .partial
            .iter()
            .filter(|((j, _, _), p)| j == job && p.held_ms.is_some())
            .map(|(k, _)| k.clone())
            .collect();
        keys.into_iter()
            .map(|k| self.try_complete(k, now_ms))
            .collect()
    }

    fn count_rejection(&mut self, job: &str) -> Option<JobState> {
        let rec = self.jobs.get_mut(job)?;
        rec.state.worlds_rejected += 1;
        rec.state.revision += 1;
        Some(rec.state.clone())
    }

    fn reject(&mut self, key: &WorldKey, reason: Rejection) -> Outcome {
        self.drop_partial(key);
        let c = &mut self.counters;
        match reason {
            Rejection::CrcMismatch => {} // counted per segment on arrival
            Rejection::Incomplete | Rejection::NoParent => c.incomplete += 1,
            Rejection::DuplicateSeed => c.duplicates += 1,
            Rejection::MemoryCap => c.refused_memory += 1,
            Rejection::UnknownJob => c.unknown_job += 1,
            Rejection::Late => c.late += 1,
        }
        let state = if reason == Rejection::Late {
            self.jobs.get_mut(&key.0).map(|rec| {
                rec.state.worlds_late += 1;
                rec.state.revision += 1;
                rec.state.clone()
            })
        } else {
            self.count_rejection(&key.0)
        };
        Outcome::Rejected { reason, state }
    }

    fn try_complete(&mut self, key: WorldKey, now_ms: u64) -> Outcome {
        let Some(p) = self.partial.get(&key) else {
            return Outcome::Pending;
        };
        let Some(done) = &p.done else {
            return Outcome::Pending;
        };
        // A refined world may send only its segments from `first_segment` on (§4.5).
        let Some(own) = done.segment_count.checked_sub(done.first_segment) else {
            return self.reject(&key, Rejection::Incomplete);
        };
        if (p.segments.len() as u64) < u64::from(own) {
            return Outcome::Pending;
        }
        if p.crc_bad {
            return self.reject(&key, Rejection::CrcMismatch);
        }
        let layered = is_layered(done, p.segments.values());
        if !Self::consistent(done, &p.segments, own, layered) {
            return self.reject(&key, Rejection::Incomplete);
        }
        let job_id = key.0.clone();
        let Some(rec) = self.jobs.get(&job_id) else {
            // The job and its worlds come on separate subscriptions (and a replay puts them
            // microseconds apart), so a world can be complete before its job is applied: held,
            // within a time and byte bound, and completed when the job arrives.
            return self.hold(key, now_ms);
        };
        if rec.state.closed {
            return self.reject(&key, Rejection::Late);
        }
        if rec.seeds.contains(&done.seed) {
            return self.reject(&key, Rejection::DuplicateSeed);
        }
        let world_bytes = p.bytes + done.encoded_len() as u64;
        // A refined world lives on its parent's shard, whose motion it is composed with.
        let parent_index = refine_parent(&rec.job);
        let owned = match parent_index {
            Some(parent) => self.shard.local(parent).is_some(),
            None => self.shard.owns(&job_id, done.seed),
        };
        // A difference needs the parent it is composed with: held here, with as many bodies
        // (a difference outside a REFINE job has none).
        let parent = match (owned && layered, parent_index) {
            (false, _) => None,
            (true, Some(i)) => match self.world(i) {
                Some(w) if w.done.impacts.len() == done.impacts.len() => Some(w),
                _ => return self.reject(&key, Rejection::NoParent),
            },
            (true, None) => return self.reject(&key, Rejection::NoParent),
        };
        if owned
            && self.stored_bytes
                + self.index_bytes
                + world_bytes
                + self.index_estimate()
                + self.index_growth
                > self.cap_bytes
        {
            return self.reject(&key, Rejection::MemoryCap);
        }
        let Some(index) = self.shard.global(self.worlds.len() as u32) else {
            return self.reject(&key, Rejection::MemoryCap);
        };
        let Some(p) = self.drop_partial(&key) else {
            return Outcome::Pending;
        };
        let Some(done) = p.done else {
            return Outcome::Pending;
        };
        let Some(rec) = self.jobs.get_mut(&job_id) else {
            return Outcome::Pending;
        };
        rec.seeds.insert(done.seed);
        let st = &mut rec.state;
        st.worlds_done += 1;
        // The job's bytes over all shards (each counts every world the same way).
        st.bytes_stored += world_bytes;
        if st.first_world_unix_ms == 0 {
            st.first_world_unix_ms = now_ms;
        }
        st.last_world_unix_ms = now_ms;
        if st.worlds_done >= st.target_worlds {
            st.closed = true;
        }
        st.revision += 1;
        let state = st.clone();
        if !owned {
            return Outcome::Counted { state };
        }
        self.stored_bytes += world_bytes;
        self.worlds.push(Arc::new(StoredWorld {
            index,
            job_id,
            done,
            segments: p.segments.into_values().collect(),
            bytes: world_bytes,
            parent,
        }));
        Outcome::Stored { index, state }
    }

    /// Whether `segments` are exactly the world `done` announces: `own` of them, `seq`
    /// consecutive from `done.first_segment`, frames contiguous and adding up to the frame count
    /// (from 0 for a whole world, from where the first one starts for a layered one), the seed
    /// the summary's; each carries every body of the world, or (layered) the distinct bodies it
    /// lists, all in range, exactly those active (`WorldDone.active_from`) before it ends.
    fn consistent(
        done: &WorldDone,
        segments: &BTreeMap<u32, MotionSegment>,
        own: u32,
        layered: bool,
    ) -> bool {
        let bodies = done.impacts.len();
        let Some(first) = segments.values().next() else {
            return false;
        };
        if segments.len() != own as usize || (!layered && first.first_frame != 0) {
            return false;
        }
        // A layered world's own segments start at or before the first new frame.
        if layered
            && done
                .active_from
                .iter()
                .any(|&a| a >= 0 && a < i64::from(first.first_frame))
        {
            return false;
        }
        let mut next_frame = u64::from(first.first_frame);
        for (i, (seq, s)) in segments.iter().enumerate() {
            let carried = if s.bodies.is_empty() {
                bodies
            } else {
                let mut listed = s.bodies.clone();
                listed.sort_unstable();
                listed.dedup();
                if listed.len() != s.bodies.len()
                    || listed.last().is_some_and(|&b| b as usize >= bodies)
                {
                    return false;
                }
                s.bodies.len()
            };
            if u64::from(*seq) != u64::from(done.first_segment) + i as u64
                || u64::from(s.first_frame) != next_frame
                || s.body_count as usize != carried
                || s.seed != done.seed
            {
                return false;
            }
            // A layered world carries each body exactly in the segments that end after the
            // frame it became active (`active_from`, -1: never): no new motion left out, none
            // claimed for a body that kept its parent's.
            if layered {
                if done.active_from.len() != bodies {
                    return false;
                }
                let end = i64::from(s.first_frame) + i64::from(s.frame_count);
                let carries = |b: usize| s.bodies.is_empty() || s.bodies.contains(&(b as u32));
                if (0..bodies).any(|b| {
                    let from = done.active_from[b];
                    carries(b) != (from >= 0 && from < end)
                }) {
                    return false;
                }
            }
            next_frame += u64::from(s.frame_count);
        }
        next_frame == u64::from(done.frame_count)
    }

    fn hold(&mut self, key: WorldKey, now_ms: u64) -> Outcome {
        let Some(p) = self.partial.get_mut(&key) else {
            return Outcome::Pending;
        };
        if p.held_ms.is_some() {
            return Outcome::Pending;
        }
        if self.held_bytes + p.bytes > self.cap_bytes / 8 {
            return self.reject(&key, Rejection::UnknownJob);
        }
        p.held_ms = Some(now_ms);
        self.held_bytes += p.bytes;
        Outcome::Pending
    }

    /// A sampler's liveliness token went away: its partial worlds will not complete. They are
    /// discarded after `grace` (the last messages it sent may still be in our queues).
    pub fn node_left(&mut self, node: &str, now_ms: u64) {
        for ((_, n, _), p) in self.partial.iter_mut() {
            if n == node {
                p.orphaned_ms.get_or_insert(now_ms);
            }
        }
    }

    /// Discards partial worlds orphaned for longer than `grace_ms` or idle for `idle_ms`, and
    /// refuses ([`Rejection::UnknownJob`]) complete worlds held longer than the hold for a
    /// job that never came. Returns how many partial worlds were discarded.
    pub fn expire(&mut self, now_ms: u64, grace_ms: u64, idle_ms: u64) -> usize {
        let hold = self.unknown_job_hold_ms;
        let unclaimed: Vec<WorldKey> = self
            .partial
            .iter()
            .filter(|(_, p)| p.held_ms.is_some_and(|t| now_ms.saturating_sub(t) >= hold))
            .map(|(k, _)| k.clone())
            .collect();
        for k in &unclaimed {
            self.reject(k, Rejection::UnknownJob);
        }
        let stale: Vec<WorldKey> = self
            .partial
            .iter()
            .filter(|(_, p)| {
                p.orphaned_ms
                    .is_some_and(|t| now_ms.saturating_sub(t) >= grace_ms)
                    || now_ms.saturating_sub(p.last_ms) >= idle_ms
            })
            .map(|(k, _)| k.clone())
            .collect();
        for k in &stale {
            self.drop_partial(k);
        }
        self.counters.discarded_partial += stale.len() as u64;
        stale.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job(id: &str, target: u32) -> Job {
        Job {
            id: id.into(),
            revision: 1,
            target_worlds: target,
            ..Default::default()
        }
    }

    fn world(
        job: &str,
        node: &str,
        counter: u64,
        seed: u64,
        segs: u32,
    ) -> (Vec<MotionSegment>, WorldDone) {
        let segments: Vec<MotionSegment> = (0..segs)
            .map(|i| {
                let payload = vec![i as u8; 10 + i as usize];
                MotionSegment {
                    job_id: job.into(),
                    node_id: node.into(),
                    world_counter: counter,
                    seed,
                    seq: i,
                    first_frame: i * 5,
                    frame_count: 5,
                    body_count: 2,
                    crc32: crc32fast::hash(&payload),
                    payload,
                    ..Default::default()
                }
            })
            .collect();
        let done = WorldDone {
            job_id: job.into(),
            node_id: node.into(),
            world_counter: counter,
            seed,
            frame_count: segs * 5,
            segment_count: segs,
            impacts: vec![0, 1],
            ..Default::default()
        };
        (segments, done)
    }

    fn feed(a: &mut Assembler, segs: Vec<MotionSegment>, done: WorldDone) -> Outcome {
        let mut last = Outcome::Pending;
        for s in segs {
            last = a.on_segment(s, 1);
        }
        assert_eq!(last, Outcome::Pending);
        a.on_done(done, 2)
    }

    #[test]
    fn complete_worlds_get_dense_indices_and_close_the_job() {
        let mut a = Assembler::new(1 << 20);
        a.submit_job(job("j", 2));
        let (s, d) = world("j", "n", 0, 11, 3);
        assert!(matches!(
            feed(&mut a, s, d),
            Outcome::Stored { index: 0, .. }
        ));
        // done before segments also works
        let (s, d) = world("j", "m", 0, 12, 2);
        assert_eq!(a.on_done(d, 3), Outcome::Pending);
        let mut out = Outcome::Pending;
        for seg in s.into_iter().rev() {
            out = a.on_segment(seg, 4);
        }
        let Outcome::Stored { index: 1, state } = out else {
            panic!("{out:?}")
        };
        assert!(state.closed && state.worlds_done == 2);
        assert_eq!(a.world_count(), 2);
        assert_eq!(a.partial_count(), 0);
        // a third is late
        let (s, d) = world("j", "k", 0, 13, 1);
        assert!(matches!(
            feed(&mut a, s, d),
            Outcome::Rejected {
                reason: Rejection::Late,
                ..
            }
        ));
    }

    #[test]
    fn a_shard_keeps_its_worlds_and_counts_all() {
        let spec = ShardSpec { index: 1, count: 2 };
        let mut a = Assembler::sharded(1 << 20, spec);
        a.submit_job(job("j", 6));
        let mut kept = Vec::new();
        let mut counted = 0;
        for seed in 0..6u64 {
            let (s, d) = world("j", "n", seed, 100 + seed, 2);
            match feed(&mut a, s, d) {
                Outcome::Stored { index, state } => {
                    assert!(spec.owns("j", 100 + seed));
                    assert_eq!(index % 2, 1, "shard 1 numbers odd");
                    kept.push(index);
                    assert_eq!(state.worlds_done as usize, kept.len() + counted);
                }
                Outcome::Counted { state } => {
                    assert!(!spec.owns("j", 100 + seed));
                    counted += 1;
                    assert_eq!(state.worlds_done as usize, kept.len() + counted);
                }
                other => panic!("{other:?}"),
            }
        }
        assert!(
            !kept.is_empty() && counted > 0,
            "seeds 100..106 all on one shard"
        );
        assert_eq!(
            kept,
            (0..kept.len() as u32)
                .map(|i| 2 * i + 1)
                .collect::<Vec<_>>()
        );
        assert_eq!(a.world_count(), kept.len());
        assert!(
            a.job_state("j")
                .is_some_and(|st| st.closed && st.worlds_done == 6)
        );
        for &i in &kept {
            assert_eq!(a.world(i).map(|w| w.index), Some(i));
        }
        assert!(a.world(0).is_none());
        // Only kept worlds take memory.
        let stored: u64 = a.stored().map(|w| w.bytes).sum();
        assert_eq!(a.memory_bytes(), stored);
    }

    #[test]
    fn a_late_shard_adopts_the_authority_count_and_closure() {
        let mut a = Assembler::sharded(1 << 20, ShardSpec { index: 1, count: 2 });
        a.submit_job(job("j", 10));
        let theirs = JobState {
            job_id: "j".into(),
            worlds_done: 7,
            target_worlds: 10,
            ..Default::default()
        };
        a.adopt_state(&theirs);
        assert_eq!(a.job_state("j").map(|s| s.worlds_done), Some(7));
        // A lower count never lowers ours.
        a.adopt_state(&JobState {
            worlds_done: 2,
            ..theirs.clone()
        });
        assert_eq!(a.job_state("j").map(|s| s.worlds_done), Some(7));
        a.adopt_state(&JobState {
            closed: true,
            ..theirs
        });
        let (s, d) = world("j", "n", 0, 5, 1);
        assert!(matches!(
            feed(&mut a, s, d),
            Outcome::Rejected {
                reason: Rejection::Late,
                ..
            }
        ));
        // Unknown jobs are ignored.
        a.adopt_state(&JobState {
            job_id: "other".into(),
            ..Default::default()
        });
        assert!(a.job_state("other").is_none());
    }

    #[test]
    fn crc_mismatch_rejects_the_world() {
        let mut a = Assembler::new(1 << 20);
        a.submit_job(job("j", 5));
        let (mut s, d) = world("j", "n", 0, 11, 3);
        s[1].payload[0] ^= 0x40;
        assert!(matches!(
            feed(&mut a, s, d),
            Outcome::Rejected {
                reason: Rejection::CrcMismatch,
                ..
            }
        ));
        assert_eq!(a.counters.crc_failures, 1);
        assert_eq!(a.world_count(), 0);
        assert_eq!(a.memory_bytes(), 0);
    }

    #[test]
    fn duplicate_seed_and_inconsistent_worlds_are_refused() {
        let mut a = Assembler::new(1 << 20);
        a.submit_job(job("j", 5));
        let (s, d) = world("j", "n", 0, 11, 2);
        assert!(matches!(feed(&mut a, s, d), Outcome::Stored { .. }));
        let (s, d) = world("j", "m", 3, 11, 2);
        assert!(matches!(
            feed(&mut a, s, d),
            Outcome::Rejected {
                reason: Rejection::DuplicateSeed,
                ..
            }
        ));
        let (s, mut d) = world("j", "m", 4, 12, 2);
        d.frame_count += 1;
        assert!(matches!(
            feed(&mut a, s, d),
            Outcome::Rejected {
                reason: Rejection::Incomplete,
                ..
            }
        ));
    }

    #[test]
    fn memory_cap_refuses_new_worlds() {
        let (s, d) = world("j", "n", 0, 1, 2);
        let one: u64 =
            s.iter().map(|x| x.encoded_len() as u64).sum::<u64>() + d.encoded_len() as u64;
        let mut a = Assembler::new(one * 2 + one / 2);
        a.submit_job(job("j", 10));
        for c in 0..3u64 {
            let (s, d) = world("j", "n", c, 100 + c, 2);
            let out = feed(&mut a, s, d);
            if c < 2 {
                assert!(matches!(out, Outcome::Stored { .. }), "{c}: {out:?}");
            } else {
                assert!(matches!(
                    out,
                    Outcome::Rejected {
                        reason: Rejection::MemoryCap,
                        ..
                    }
                ));
            }
        }
        assert_eq!(a.counters.refused_memory, 1);
        assert!(a.memory_bytes() <= a.cap_bytes());
    }

    /// The browsing index counts against the cap: with room for three worlds' bytes, a store
    /// whose index takes one world's worth per world holds fewer.
    #[test]
    fn index_bytes_count_against_the_cap() {
        let (s, d) = world("j", "n", 0, 1, 2);
        let one: u64 =
            s.iter().map(|x| x.encoded_len() as u64).sum::<u64>() + d.encoded_len() as u64;
        let mut a = Assembler::new(one * 3 + one / 2);
        a.submit_job(job("j", 10));
        let mut stored = 0u64;
        for c in 0..4u64 {
            let (s, d) = world("j", "n", c, 100 + c, 2);
            if matches!(feed(&mut a, s, d), Outcome::Stored { .. }) {
                stored += 1;
                // The node reports the index after indexing each stored world.
                a.set_index_bytes(stored * one);
            }
        }
        // World 0 (0 + 1 + est 0 ≤ 3.5), world 1 (1 + 1 + 1 + est 1 = 4 > 3.5): refused, …
        assert_eq!(stored, 1);
        assert_eq!(a.counters.refused_memory, 3);
        assert_eq!(a.memory_bytes(), 2 * one);
        assert!(a.memory_bytes() <= a.cap_bytes());
    }

    #[test]
    fn departed_samplers_lose_only_their_partial_worlds() {
        let mut a = Assembler::new(1 << 20);
        a.submit_job(job("j", 5));
        let (s, _) = world("j", "dead", 0, 1, 3);
        for seg in s.into_iter().take(2) {
            a.on_segment(seg, 10);
        }
        let (s, _) = world("j", "alive", 0, 2, 3);
        a.on_segment(s[0].clone(), 10);
        a.node_left("dead", 20);
        assert_eq!(a.expire(500, 1000, 60_000), 0, "grace not over");
        assert_eq!(a.expire(1100, 1000, 60_000), 1);
        assert_eq!(a.partial_count(), 1);
        assert_eq!(a.counters.discarded_partial, 1);
        assert_eq!(a.expire(100_000, 1000, 60_000), 1, "idle partial expires");
        assert_eq!(a.memory_bytes(), 0);
    }

    /// A world that completes before its job arrives is stored when the job comes.
    #[test]
    fn a_world_ahead_of_its_job_is_held_and_stored_when_the_job_comes() {
        let mut a = Assembler::new(1 << 20);
        let (s, d) = world("j", "n", 0, 1, 2);
        assert_eq!(feed(&mut a, s, d), Outcome::Pending);
        let (s, d) = world("other", "n", 1, 2, 2);
        assert_eq!(feed(&mut a, s, d), Outcome::Pending);
        assert_eq!(a.held_count(), 2);
        assert_eq!(
            a.release_held("j", 3),
            [Outcome::Pending],
            "job j not known yet: still held"
        );
        a.submit_job(job("j", 5));
        let out = a.release_held("j", 3);
        assert!(
            matches!(out.as_slice(), [Outcome::Stored { index: 0, state }] if state.worlds_done == 1),
            "{out:?}"
        );
        assert_eq!(a.held_count(), 1, "the other job's world is still held");
        assert_eq!(a.world_count(), 1);
        // The byte bound: held worlds may take an eighth of the cap at most.
        let mut small = Assembler::new(200);
        let (s, d) = world("x", "n", 0, 1, 2);
        assert!(matches!(
            feed(&mut small, s, d),
            Outcome::Rejected {
                reason: Rejection::UnknownJob,
                ..
            }
        ));
    }

    /// A world complete by its summary, for a job not known yet, is held; a segment more of
    /// that world arriving after it must not upset the held total (it once underflowed and
    /// stopped the store's applier). A summary promising no segments at all is refused.
    #[test]
    fn a_segment_after_a_held_world_releases_what_it_added() {
        let mut a = Assembler::new(1 << 20);
        let (mut segs, mut d) = world("late", "n", 0, 1, 2);
        let extra = segs.pop().unwrap_or_else(|| panic!("two segments"));
        d.segment_count = 1;
        d.frame_count = 5;
        assert_eq!(feed(&mut a, segs, d.clone()), Outcome::Pending);
        assert_eq!(a.held_count(), 1);
        assert!(matches!(
            a.on_segment(extra, 2),
            Outcome::Rejected {
                reason: Rejection::Incomplete,
                ..
            }
        ));
        assert_eq!(a.held_count(), 0);
        assert_eq!(a.held_bytes, 0);
        assert_eq!(a.memory_bytes(), 0);
        let empty = WorldDone {
            world_counter: 1,
            segment_count: 0,
            frame_count: 0,
            impacts: Vec::new(),
            ..d
        };
        assert!(matches!(
            a.on_done(empty, 3),
            Outcome::Rejected {
                reason: Rejection::Incomplete,
                ..
            }
        ));
        assert_eq!(a.memory_bytes(), 0);
    }

    #[test]
    fn unknown_job_and_cancel() {
        let mut a = Assembler::new(1 << 20);
        let (s, d) = world("nope", "n", 0, 1, 1);
        // Complete before its job: held, then refused once the hold is over.
        assert_eq!(feed(&mut a, s, d), Outcome::Pending);
        assert_eq!(a.held_count(), 1);
        assert_eq!(a.expire(UNKNOWN_JOB_HOLD_MS, 1000, u64::MAX), 0);
        assert_eq!(a.held_count(), 1, "hold not over yet");
        a.expire(UNKNOWN_JOB_HOLD_MS + 2, 1000, u64::MAX);
        assert_eq!(a.held_count(), 0);
        assert_eq!(a.counters.unknown_job, 1);
        assert_eq!(a.memory_bytes(), 0);
        a.submit_job(job("j", 5));
        let mut cancel = job("j", 5);
        cancel.revision = 2;
        cancel.cancelled = true;
        let st = a.submit_job(cancel).unwrap_or_default();
        assert!(st.closed && st.cancelled);
        // stale revisions are ignored
        assert!(a.submit_job(job("j", 5)).is_none());
    }
}
