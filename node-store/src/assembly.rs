//! World assembly: motion segments and `WorldDone`s in, complete CRC-verified worlds out.
//!
//! Pure state machine (no bus, no clock of its own: callers pass `now_ms`), so every rule is
//! unit-tested: CRC checks, completeness, duplicate seeds, the memory cap, job closure, and
//! discarding the partial worlds of samplers that left.
//!
//! **Counting across shards.** Several shards split a job's worlds by seed
//! ([`ShardSpec::owns`]); each counts only the worlds it stored itself (`JobState.shard_worlds`
//! at its own index). The node publishes that count after the journal commit that made those
//! worlds durable (`ShardCount`), and the authority (shard 0) keeps the latest count of every
//! other shard ([`Assembler::on_shard_count`]): a job's `worlds_done` is the sum, so a world is
//! acknowledged only once the shard that keeps it has it on disk, and every world a shard
//! stores is eventually counted. Only the authority closes a job on that sum; the others follow
//! its closure ([`Assembler::adopt_state`]) and store every world they own until then, so a
//! job can end with a few more worlds than its target (those in flight when it closed), never
//! with a world acknowledged that no shard keeps. (Counting every world seen on every shard,
//! as before, let the authority acknowledge a world its owner had not written, and let two
//! shards each refuse their own world as late because each had counted the other's.)

use crate::browse::ShardSpec;
use mwb_proto::v1::{Job, JobKind, JobState, Message, MotionSegment, WorldDone, WorldIndex};
use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::Arc;

/// A complete world held in memory.
///
/// Its summary and segments are kept as their wire encoding, back to back in one heap block
/// (each prefixed with its length, the segments without the job and sampler ids, which are
/// the summary's), and decoded when asked for ([`done`](Self::done),
/// [`decode`](Self::decode), [`message`](Self::message)): a store holds a million worlds
/// and reads one now and then. Held as decoded structs, a tumble world's motion took 1.85 kB
/// of memory beyond its codec payloads (three 216-byte segment structs, a 368-byte summary, the
/// ids copied into each, a heap block for every string and list); held encoded, a few hundred.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredWorld {
    /// Global index: dense per shard, `local × shard count + shard index` (bitsets in the
    /// browsing layer are over these).
    pub index: u32,
    pub job_id: String,
    /// Encoded size of the segments and the summary, as received.
    pub bytes: u64,
    /// A refined world stored as a difference from its parent (§4.5; see
    /// [`StoredWorld::is_layered`]): the parent, held here for as long as this world is, so a
    /// parent of a live refined world is never dropped.
    pub parent: Option<Arc<StoredWorld>>,
    /// The summary, then the segments in order (`seq` from `first_segment` on), each
    /// length-delimited.
    encoded: Box<[u8]>,
    segment_count: u32,
    /// Bodies the summary counts impacts for (a difference's parent must have as many).
    bodies: u32,
    layered: bool,
}

/// A stored world's own encoding did not decode: only a bug (or memory corruption) can cause
/// this, since the store encoded it itself.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("stored world {world}: its encoding does not decode ({what})")]
pub struct StoredDecodeError {
    pub world: u32,
    pub what: String,
}

/// What the allocator adds to each heap block beyond the bytes asked for (glibc: an 8-byte
/// header and rounding to 16 bytes; 16 on average for the small blocks a world is made of).
pub const ALLOC_OVERHEAD: u64 = 16;

impl StoredWorld {
    /// A world of `done` and its `segments` (in order), `bytes` their encoded size as
    /// received, kept encoded.
    pub fn new<'s>(
        index: u32,
        job_id: String,
        done: &WorldDone,
        segments: impl IntoIterator<Item = &'s MotionSegment>,
        bytes: u64,
        parent: Option<Arc<StoredWorld>>,
    ) -> Self {
        let mut encoded = Vec::with_capacity(done.encoded_len() + 10);
        // Encoding into a Vec only fails when it runs out of room, which a Vec never does.
        let _ = done.encode_length_delimited(&mut encoded);
        let (mut count, mut layered) = (0u32, done.first_segment > 0);
        for s in segments {
            let bare = MotionSegment {
                job_id: String::new(),
                node_id: String::new(),
                ..s.clone()
            };
            let _ = bare.encode_length_delimited(&mut encoded);
            count += 1;
            layered |= !s.bodies.is_empty();
        }
        StoredWorld {
            index,
            job_id,
            bytes,
            parent,
            encoded: encoded.into_boxed_slice(),
            segment_count: count,
            bodies: done.impacts.len() as u32,
            layered,
        }
    }

    fn decode_error(&self, e: prost::DecodeError) -> StoredDecodeError {
        StoredDecodeError {
            world: self.index,
            what: e.to_string(),
        }
    }

    /// The world's summary.
    pub fn done(&self) -> Result<WorldDone, StoredDecodeError> {
        WorldDone::decode_length_delimited(&self.encoded[..]).map_err(|e| self.decode_error(e))
    }

    /// The summary and the segments, in order, with their ids as they came.
    pub fn decode(&self) -> Result<(WorldDone, Vec<MotionSegment>), StoredDecodeError> {
        let mut buf = &self.encoded[..];
        let done =
            WorldDone::decode_length_delimited(&mut buf).map_err(|e| self.decode_error(e))?;
        let mut segments = Vec::with_capacity(self.segment_count as usize);
        for _ in 0..self.segment_count {
            let mut s = MotionSegment::decode_length_delimited(&mut buf)
                .map_err(|e| self.decode_error(e))?;
            s.job_id.clone_from(&done.job_id);
            s.node_id.clone_from(&done.node_id);
            segments.push(s);
        }
        Ok((done, segments))
    }

    /// Segments held.
    pub fn segment_count(&self) -> usize {
        self.segment_count as usize
    }

    /// Bodies of the world (as its summary counts impacts).
    pub fn body_count(&self) -> usize {
        self.bodies as usize
    }

    /// Bytes this world holds in memory (what the store's cap counts): its struct in a shared
    /// block, its encoding, its job id, its slot in the world table and its seed in the job's
    /// duplicate check, each heap block with [`ALLOC_OVERHEAD`].
    pub fn held_bytes(&self) -> u64 {
        let block = |bytes: usize| match bytes {
            0 => 0,
            b => b as u64 + ALLOC_OVERHEAD,
        };
        std::mem::size_of::<Arc<StoredWorld>>() as u64
            + block(2 * std::mem::size_of::<usize>() + std::mem::size_of::<StoredWorld>())
            + block(self.encoded.len())
            + block(self.job_id.capacity())
            + 2 * std::mem::size_of::<u64>() as u64
    }

    /// Whether this world's segments are a difference from its parent: they start past segment
    /// 0 (`WorldDone.first_segment`) or carry only some bodies (`MotionSegment.bodies`).
    pub fn is_layered(&self) -> bool {
        self.layered
    }

    /// The wire form (`q/world/<index>`), with the parent chain of a layered world.
    pub fn message(&self) -> Result<mwb_proto::v1::World, StoredDecodeError> {
        let (done, segments) = self.decode()?;
        Ok(mwb_proto::v1::World {
            index: self.index,
            job_id: self.job_id.clone(),
            done: Some(done),
            segments,
            parent: match &self.parent {
                Some(p) => Some(Box::new(p.message()?)),
                None => None,
            },
        })
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
    /// A world was stored; the job's new state, and the index its sampler sent
    /// (`WorldDone.index`, taken off the summary before it was held: the store keeps it as its
    /// browsing index, not twice).
    Stored {
        index: u32,
        state: JobState,
        sent_index: Option<Box<WorldIndex>>,
    },
    /// A complete, verified world that belongs to another shard: neither kept nor counted
    /// here (its owner counts it once it is durable, and tells the authority).
    Elsewhere,
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
    /// The index the summary carried, taken off it.
    sent_index: Option<Box<WorldIndex>>,
    crc_bad: bool,
    /// Encoded bytes of the segments held.
    bytes: u64,
    /// Encoded bytes of the summary and the index it carried: held too until the world is
    /// stored or dropped (a summary whose segments never come holds them until it expires).
    summary_bytes: u64,
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
    /// Seeds of the worlds this shard stored (a seed always belongs to the same shard, so a
    /// duplicate is always caught by its owner).
    seeds: HashSet<u64>,
    /// This shard's count as the authority's latest job state has it (a non-authority shard
    /// sends its count again until the authority has it: [`Assembler::unacknowledged_counts`]).
    acked_own: u32,
}

/// The store's world table.
#[derive(Debug)]
pub struct Assembler {
    jobs: BTreeMap<String, JobRecord>,
    partial: HashMap<WorldKey, Partial>,
    worlds: Vec<Arc<StoredWorld>>,
    /// Σ [`StoredWorld::held_bytes`] of the stored worlds.
    stored_bytes: u64,
    /// The browsing index's bytes, as last reported by the node.
    index_bytes: u64,
    /// How many stored worlds `index_bytes` covers (indexed, or failed to index).
    index_worlds: u64,
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

/// Gives a state one count per shard (a state from an older store has none).
fn fit(st: &mut JobState, shard: ShardSpec) {
    let n = shard.count as usize;
    st.shard_worlds.resize(n, 0);
    st.shard_bytes.resize(n, 0);
}

/// `worlds_done` and `bytes_stored` from the per-shard counts.
fn recount(st: &mut JobState) {
    let worlds: u64 = st.shard_worlds.iter().map(|&n| u64::from(n)).sum();
    st.worlds_done = u32::try_from(worlds).unwrap_or(u32::MAX);
    st.bytes_stored = st.shard_bytes.iter().sum();
}

/// Closes a job whose counted worlds reach its target: on the authority only (the others
/// follow its closure, see the module doc).
fn close_if_done(st: &mut JobState, shard: ShardSpec) {
    if shard.is_authority() && st.worlds_done >= st.target_worlds {
        st.closed = true;
    }
}

/// Takes the other shards' counts from `from` where higher; this shard's own stays.
fn merge_others(st: &mut JobState, from: &JobState, shard: ShardSpec) {
    fit(st, shard);
    for i in 0..shard.count as usize {
        if i == shard.index as usize {
            continue;
        }
        if let Some(&n) = from.shard_worlds.get(i) {
            st.shard_worlds[i] = st.shard_worlds[i].max(n);
        }
        if let Some(&b) = from.shard_bytes.get(i) {
            st.shard_bytes[i] = st.shard_bytes[i].max(b);
        }
    }
    recount(st);
}

/// How long a complete world of a job the store has not seen is held for that job, ms.
pub const UNKNOWN_JOB_HOLD_MS: u64 = 10_000;

impl Assembler {
    /// `cap_bytes`: complete worlds past this total are refused.
    pub fn new(cap_bytes: u64) -> Self {
        Self::sharded(cap_bytes, ShardSpec::default())
    }

    /// A table that keeps and counts only the worlds of `shard`; the authority (shard 0) adds
    /// the other shards' counts ([`on_shard_count`](Self::on_shard_count)) and closes jobs.
    pub fn sharded(cap_bytes: u64, shard: ShardSpec) -> Self {
        Self {
            jobs: BTreeMap::new(),
            partial: HashMap::new(),
            worlds: Vec::new(),
            stored_bytes: 0,
            index_bytes: 0,
            index_worlds: 0,
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
    /// reported with [`set_index_bytes`](Self::set_index_bytes), stored worlds it has not taken
    /// in yet at the mean so far) — what the cap limits.
    pub fn memory_bytes(&self) -> u64 {
        self.stored_bytes + self.partial_bytes + self.index_bytes + self.index_pending()
    }

    /// Tells the assembler how many bytes the browsing index of its worlds takes (the index
    /// lives beside it, in the browse shard) and how many of the stored worlds it has taken in
    /// (indexed, or failed to index). Counted against the memory cap: a world is refused when
    /// its bytes, the stored ones, the index and the index the world itself will need
    /// (estimated as the mean so far) would exceed the cap. On a 10-object scene the index is
    /// about the size of the compressed world, so leaving it out would let a store grow far
    /// past its cap. A store indexes the worlds of a batch together, after storing them: until
    /// it reports them, each counts at the mean.
    pub fn set_index_bytes(&mut self, bytes: u64, worlds: u64) {
        self.index_bytes = bytes;
        self.index_worlds = worlds;
    }

    /// Tells the assembler how much the index may grow beyond a world's own bytes when the
    /// next world is indexed ([`crate::Shard::growth_bytes`]: a vector doubling its capacity),
    /// kept free under the cap so that a growing index never carries the store past it.
    pub fn set_index_growth(&mut self, bytes: u64) {
        self.index_growth = bytes;
    }

    /// The index bytes a new world is expected to add: the mean over the worlds indexed.
    fn index_estimate(&self) -> u64 {
        match self.index_worlds {
            0 => 0,
            n => self.index_bytes / n,
        }
    }

    /// The index the stored worlds not indexed yet will add, at the mean.
    fn index_pending(&self) -> u64 {
        (self.worlds.len() as u64).saturating_sub(self.index_worlds) * self.index_estimate()
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
                close_if_done(&mut rec.state, self.shard);
                rec.state.revision += 1;
                Some(rec.state.clone())
            }
            None => {
                let count = self.shard.count as usize;
                let state = JobState {
                    job_id: job.id.clone(),
                    revision: 1,
                    target_worlds: job.target_worlds,
                    closed: job.cancelled || job.target_worlds == 0,
                    cancelled: job.cancelled,
                    shard_worlds: vec![0; count],
                    shard_bytes: vec![0; count],
                    ..Default::default()
                };
                self.jobs.insert(
                    job.id.clone(),
                    JobRecord {
                        job,
                        state: state.clone(),
                        seeds: HashSet::new(),
                        acked_own: 0,
                    },
                );
                Some(state)
            }
        }
    }

    /// The worlds of `job` this shard stored, and their bytes.
    pub fn own_count(&self, job: &str) -> Option<(u32, u64)> {
        let st = &self.jobs.get(job)?.state;
        let i = self.shard.index as usize;
        Some((
            st.shard_worlds.get(i).copied().unwrap_or(0),
            st.shard_bytes.get(i).copied().unwrap_or(0),
        ))
    }

    /// Jobs this shard stored worlds of.
    pub fn jobs_with_worlds(&self) -> Vec<String> {
        self.jobs
            .keys()
            .filter(|id| self.own_count(id).is_some_and(|(n, _)| n > 0))
            .cloned()
            .collect()
    }

    /// Jobs whose count on this shard is ahead of what the authority's latest state shows (a
    /// `ShardCount` lost, or an authority restarted from a journal that predates it): to send
    /// again. Empty on the authority, whose own count is in the states it publishes.
    pub fn unacknowledged_counts(&self) -> Vec<String> {
        if self.shard.is_authority() {
            return Vec::new();
        }
        self.jobs
            .iter()
            .filter(|(id, rec)| self.own_count(id).is_some_and(|(n, _)| n > rec.acked_own))
            .map(|(id, _)| id.clone())
            .collect()
    }

    /// Another shard's count of its durable worlds of a job (`ShardCount`, authority only):
    /// kept when higher than the one held (counts only grow; a late or repeated one changes
    /// nothing), added into `worlds_done`, and the job closed once the sum reaches its target.
    /// Returns the state to publish when something changed. Counts for this shard's own index,
    /// for an index or a shard count that is not this table's, or for an unknown job are
    /// ignored (the sender repeats its count until the authority's state shows it).
    pub fn on_shard_count(
        &mut self,
        job: &str,
        shard: ShardSpec,
        worlds: u32,
        bytes: u64,
        now_ms: u64,
    ) -> Option<JobState> {
        if !self.shard.is_authority()
            || shard.count != self.shard.count
            || shard.index >= shard.count
            || shard.index == self.shard.index
        {
            return None;
        }
        let st = &mut self.jobs.get_mut(job)?.state;
        fit(st, self.shard);
        let i = shard.index as usize;
        if worlds <= st.shard_worlds[i] {
            return None;
        }
        st.shard_worlds[i] = worlds;
        st.shard_bytes[i] = st.shard_bytes[i].max(bytes);
        recount(st);
        if st.first_world_unix_ms == 0 {
            st.first_world_unix_ms = now_ms;
        }
        st.last_world_unix_ms = st.last_world_unix_ms.max(now_ms);
        close_if_done(st, self.shard);
        st.revision += 1;
        Some(st.clone())
    }

    /// The authority's view of a job (a non-authority shard follows it): its closure is
    /// followed, so that worlds it refuses as late are not kept here either; the other shards'
    /// counts are taken where higher (this shard's own count is what it stored, never theirs);
    /// and what it shows of this shard's count is remembered, so that a count it lacks is
    /// sent again.
    pub fn adopt_state(&mut self, theirs: &JobState) {
        let shard = self.shard;
        let Some(rec) = self.jobs.get_mut(&theirs.job_id) else {
            return;
        };
        if shard.is_authority() {
            return;
        }
        // The latest, not the highest: an authority restarted from its journal may have lost
        // what it last heard from this shard, and must be told again.
        rec.acked_own = theirs
            .shard_worlds
            .get(shard.index as usize)
            .copied()
            .unwrap_or(0);
        let st = &mut rec.state;
        let before = (st.worlds_done, st.closed);
        merge_others(st, theirs, shard);
        st.closed |= theirs.closed;
        st.cancelled |= theirs.cancelled;
        if (st.worlds_done, st.closed) != before {
            st.revision += 1;
        }
    }

    /// A job state read back from the store's own journal ([`crate::journal`]): every shard's
    /// count (this one's, and the others' as the authority last had them), closure and
    /// revision are taken where they are ahead of the table's — a journal file starts with a
    /// checkpoint and reads alone, the worlds of the files before it counted there; and the
    /// revision must not go back, or those who follow the job would ignore the next states.
    pub fn restore_state(&mut self, saved: &JobState) {
        let shard = self.shard;
        let Some(rec) = self.jobs.get_mut(&saved.job_id) else {
            return;
        };
        let st = &mut rec.state;
        merge_others(st, saved, shard);
        let own = shard.index as usize;
        if let (Some(&n), Some(&b)) = (saved.shard_worlds.get(own), saved.shard_bytes.get(own)) {
            st.shard_worlds[own] = st.shard_worlds[own].max(n);
            st.shard_bytes[own] = st.shard_bytes[own].max(b);
        } else if shard.count == 1 {
            // A state from a store older than the per-shard counts: one shard's count is the
            // job's.
            st.shard_worlds[own] = st.shard_worlds[own].max(saved.worlds_done);
            st.shard_bytes[own] = st.shard_bytes[own].max(saved.bytes_stored);
        }
        recount(st);
        st.worlds_rejected = st.worlds_rejected.max(saved.worlds_rejected);
        st.worlds_late = st.worlds_late.max(saved.worlds_late);
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
        if let Some(refused) = self.refuse_oversized(&key) {
            return refused;
        }
        self.try_complete(key, now_ms)
    }

    /// A single partial world larger than the whole cap can never be stored: refused and
    /// dropped. `None`: it fits.
    fn refuse_oversized(&mut self, key: &WorldKey) -> Option<Outcome> {
        let fits = self
            .partial
            .get(key)
            .is_none_or(|p| p.bytes + p.summary_bytes <= self.cap_bytes);
        if fits {
            return None;
        }
        self.drop_partial(key);
        self.counters.refused_memory += 1;
        let state = self.count_rejection(&key.0);
        Some(Outcome::Rejected {
            reason: Rejection::MemoryCap,
            state,
        })
    }

    /// Takes a world's summary. An index it carries (`WorldDone.index`) is taken off it and
    /// comes back with the world when it is stored ([`Outcome::Stored`]); the world's byte
    /// count does not include it. Until the world is stored, the summary and its index count
    /// against the cap as partial bytes.
    pub fn on_done(&mut self, mut done: WorldDone, now_ms: u64) -> Outcome {
        let sent_index = done.index.take().map(Box::new);
        let summary =
            done.encoded_len() as u64 + sent_index.as_ref().map_or(0, |i| i.encoded_len() as u64);
        let key = (
            done.job_id.clone(),
            done.node_id.clone(),
            done.world_counter,
        );
        let p = self.partial.entry(key.clone()).or_default();
        p.last_ms = now_ms;
        p.done = Some(done);
        p.sent_index = sent_index;
        // A repeated summary replaces the one held.
        self.partial_bytes = self.partial_bytes - p.summary_bytes + summary;
        if p.held_ms.is_some() {
            self.held_bytes = self.held_bytes - p.summary_bytes + summary;
        }
        p.summary_bytes = summary;
        if let Some(refused) = self.refuse_oversized(&key) {
            return refused;
        }
        self.try_complete(key, now_ms)
    }

    fn drop_partial(&mut self, key: &WorldKey) -> Option<Partial> {
        let p = self.partial.remove(key)?;
        let total = p.bytes + p.summary_bytes;
        self.partial_bytes -= total;
        if p.held_ms.is_some() {
            self.held_bytes -= total;
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
        // A refined world lives on its parent's shard, whose motion it is composed with.
        let parent_index = refine_parent(&rec.job);
        let owned = match parent_index {
            Some(parent) => self.shard.local(parent).is_some(),
            None => self.shard.owns(&job_id, done.seed),
        };
        if !owned {
            self.drop_partial(&key);
            return Outcome::Elsewhere;
        }
        if rec.state.closed {
            return self.reject(&key, Rejection::Late);
        }
        // A shard that is not the authority never closes a job, but it need not store a world
        // the authority will not count: when what it has stored and what the authority's
        // states showed of the others (durable counts, which only grow) already reach the
        // target, the authority will close the job on them.
        if !self.shard.is_authority() && rec.state.worlds_done >= rec.state.target_worlds {
            return self.reject(&key, Rejection::Late);
        }
        if rec.seeds.contains(&done.seed) {
            return self.reject(&key, Rejection::DuplicateSeed);
        }
        let world_bytes = p.bytes + done.encoded_len() as u64;
        let mut world = StoredWorld::new(
            0,
            job_id.clone(),
            done,
            p.segments.values(),
            world_bytes,
            None,
        );
        // What the cap counts: the world as held in memory, not as encoded.
        let held = world.held_bytes();
        // A difference needs the parent it is composed with: held here, with as many bodies
        // (a difference outside a REFINE job has none).
        let parent = match (layered, parent_index) {
            (false, _) => None,
            (true, Some(i)) => match self.world(i) {
                Some(w) if w.body_count() == done.impacts.len() => Some(w),
                _ => return self.reject(&key, Rejection::NoParent),
            },
            (true, None) => return self.reject(&key, Rejection::NoParent),
        };
        if self.stored_bytes
            + self.index_bytes
            + self.index_pending()
            + held
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
        let sent_index = p.sent_index;
        let Some(rec) = self.jobs.get_mut(&job_id) else {
            return Outcome::Pending;
        };
        (world.index, world.parent) = (index, parent);
        rec.seeds.insert(done.seed);
        let st = &mut rec.state;
        fit(st, self.shard);
        let own = self.shard.index as usize;
        st.shard_worlds[own] += 1;
        st.shard_bytes[own] += world_bytes;
        recount(st);
        if st.first_world_unix_ms == 0 {
            st.first_world_unix_ms = now_ms;
        }
        st.last_world_unix_ms = now_ms;
        close_if_done(st, self.shard);
        st.revision += 1;
        let state = st.clone();
        self.stored_bytes += held;
        self.worlds.push(Arc::new(world));
        Outcome::Stored {
            index,
            state,
            sent_index,
        }
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
        let total = p.bytes + p.summary_bytes;
        if self.held_bytes + total > self.cap_bytes / 8 {
            return self.reject(&key, Rejection::UnknownJob);
        }
        p.held_ms = Some(now_ms);
        self.held_bytes += total;
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
        let Outcome::Stored {
            index: 1, state, ..
        } = out
        else {
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

    /// Seeds of job `job` owned by shard `index` of `count`, from `from` on.
    fn seeds_of(job: &str, index: u32, count: u32, from: u64, n: usize) -> Vec<u64> {
        (from..)
            .filter(|&s| ShardSpec::shard_of(job, s, count) == index)
            .take(n)
            .collect()
    }

    fn shard(index: u32, count: u32) -> Assembler {
        Assembler::sharded(1 << 20, ShardSpec { index, count })
    }

    /// Feeds the world of `seed` (from sampler `node`, counter = seed).
    fn feed_seed(a: &mut Assembler, job: &str, seed: u64) -> Outcome {
        let (s, d) = world(job, "n", seed, seed, 2);
        feed(a, s, d)
    }

    fn done_of(a: &Assembler, job: &str) -> u32 {
        a.job_state(job).map_or(0, |s| s.worlds_done)
    }

    fn closed(a: &Assembler, job: &str) -> bool {
        a.job_state(job).is_some_and(|s| s.closed)
    }

    /// What shard 1 of two sends after a commit, taken by the authority.
    fn report(from: &Assembler, to: &mut Assembler, job: &str) -> Option<JobState> {
        let (worlds, bytes) = from.own_count(job).unwrap_or_default();
        to.on_shard_count(job, from.shard(), worlds, bytes, 9)
    }

    #[test]
    fn a_shard_keeps_and_counts_only_its_own_worlds() {
        let spec = ShardSpec { index: 1, count: 2 };
        let mut a = Assembler::sharded(1 << 20, spec);
        a.submit_job(job("j", 6));
        let mut kept = Vec::new();
        let mut elsewhere = 0;
        for seed in 0..6u64 {
            let (s, d) = world("j", "n", seed, 100 + seed, 2);
            match feed(&mut a, s, d) {
                Outcome::Stored { index, state, .. } => {
                    assert!(spec.owns("j", 100 + seed));
                    assert_eq!(index % 2, 1, "shard 1 numbers odd");
                    kept.push(index);
                    assert_eq!(state.worlds_done as usize, kept.len());
                    assert_eq!(state.shard_worlds, [0, kept.len() as u32]);
                }
                Outcome::Elsewhere => {
                    assert!(!spec.owns("j", 100 + seed));
                    elsewhere += 1;
                }
                other => panic!("{other:?}"),
            }
        }
        assert!(
            !kept.is_empty() && elsewhere > 0,
            "seeds 100..106 all on one shard"
        );
        assert_eq!(
            kept,
            (0..kept.len() as u32)
                .map(|i| 2 * i + 1)
                .collect::<Vec<_>>()
        );
        assert_eq!(a.world_count(), kept.len());
        assert_eq!(a.own_count("j").map(|(n, _)| n as usize), Some(kept.len()));
        assert!(!closed(&a, "j"));
        for &i in &kept {
            assert_eq!(a.world(i).map(|w| w.index), Some(i));
        }
        assert!(a.world(0).is_none());
        // Only kept worlds take memory (as held), and only they count as the job's bytes (as
        // encoded).
        let held: u64 = a.stored().map(|w| w.held_bytes()).sum();
        assert_eq!(a.memory_bytes(), held);
        let stored: u64 = a.stored().map(|w| w.bytes).sum();
        assert_eq!(a.own_count("j").map(|(_, b)| b), Some(stored));
    }

    /// The authority adds the others' counts; a count never goes back, and one for its own
    /// index or another sharding is ignored.
    #[test]
    fn the_authority_sums_the_shards_counts_and_closes_on_the_sum() {
        let mut a0 = shard(0, 2);
        a0.submit_job(job("j", 4));
        let mine = seeds_of("j", 0, 2, 0, 2);
        assert!(matches!(
            feed_seed(&mut a0, "j", mine[0]),
            Outcome::Stored { .. }
        ));
        let one = ShardSpec { index: 1, count: 2 };
        let st = a0.on_shard_count("j", one, 2, 200, 5);
        assert!(
            st.as_ref()
                .is_some_and(|s| s.worlds_done == 3 && s.shard_worlds == [1, 2] && !s.closed)
        );
        assert_eq!(
            a0.on_shard_count("j", one, 1, 100, 6),
            None,
            "counts only grow"
        );
        assert_eq!(
            a0.on_shard_count("j", one, 2, 200, 6),
            None,
            "a repeat changes nothing"
        );
        assert_eq!(
            a0.on_shard_count("j", ShardSpec { index: 0, count: 2 }, 9, 0, 6),
            None
        );
        assert_eq!(
            a0.on_shard_count("j", ShardSpec { index: 1, count: 3 }, 9, 0, 6),
            None
        );
        assert_eq!(a0.on_shard_count("nope", one, 9, 0, 6), None);
        let Outcome::Stored { state, .. } = feed_seed(&mut a0, "j", mine[1]) else {
            panic!("not stored")
        };
        assert!(state.closed && state.worlds_done == 4 && state.shard_worlds == [2, 2]);
        // A world shard 1 stored before it heard of the closure is still counted.
        let st = a0.on_shard_count("j", one, 3, 300, 7);
        assert!(st.is_some_and(|s| s.closed && s.worlds_done == 5 && s.bytes_stored > 300));
        // Only the authority takes counts.
        let mut a1 = shard(1, 2);
        a1.submit_job(job("j", 4));
        assert_eq!(
            a1.on_shard_count("j", ShardSpec { index: 0, count: 2 }, 3, 0, 1),
            None
        );
    }

    /// Issue 21, case 3: two worlds X (shard 0's) and Y (shard 1's) reach the two shards in
    /// opposite orders when one world is missing. Counting what it saw, each shard took the
    /// other's as the last one and refused its own as late: neither stored, one acknowledged.
    #[test]
    fn crossing_worlds_at_the_target_are_stored_and_acknowledged() {
        let zero = seeds_of("j", 0, 2, 0, 2);
        let one = seeds_of("j", 1, 2, 0, 2);
        for follower_hears_closure_first in [false, true] {
            let (mut a0, mut a1) = (shard(0, 2), shard(1, 2));
            a0.submit_job(job("j", 3));
            a1.submit_job(job("j", 3));
            // One world each, reported and acknowledged: 2 of 3.
            assert!(matches!(
                feed_seed(&mut a0, "j", zero[0]),
                Outcome::Stored { .. }
            ));
            assert!(matches!(
                feed_seed(&mut a1, "j", one[0]),
                Outcome::Stored { .. }
            ));
            let st = report(&a1, &mut a0, "j").unwrap_or_default();
            a1.adopt_state(&st);
            assert_eq!((done_of(&a0, "j"), done_of(&a1, "j")), (2, 2));
            let (x, y) = (zero[1], one[1]);
            // Shard 0 sees Y, then X; shard 1 sees X, then Y.
            assert_eq!(feed_seed(&mut a0, "j", y), Outcome::Elsewhere);
            let Outcome::Stored { state: closing, .. } = feed_seed(&mut a0, "j", x) else {
                panic!("X not stored")
            };
            assert!(closing.closed && closing.worlds_done == 3);
            assert_eq!(feed_seed(&mut a1, "j", x), Outcome::Elsewhere);
            if follower_hears_closure_first {
                a1.adopt_state(&closing);
                assert!(matches!(
                    feed_seed(&mut a1, "j", y),
                    Outcome::Rejected {
                        reason: Rejection::Late,
                        ..
                    }
                ));
            } else {
                assert!(matches!(feed_seed(&mut a1, "j", y), Outcome::Stored { .. }));
            }
            if let Some(st) = report(&a1, &mut a0, "j") {
                a1.adopt_state(&st);
            }
            let stored = (a0.world_count() + a1.world_count()) as u32;
            assert_eq!(done_of(&a0, "j"), stored, "acknowledged = stored");
            assert_eq!(stored, if follower_hears_closure_first { 3 } else { 4 });
            assert!(closed(&a0, "j") && closed(&a1, "j"));
        }
    }

    /// A shard that is not the authority never closes a job on its own count; it refuses a
    /// world the authority will not count (its own and the others' durable counts already
    /// reach the target), and follows the authority's closure.
    #[test]
    fn a_follower_never_closes_on_its_own_count() {
        let mut a1 = shard(1, 2);
        a1.submit_job(job("j", 2));
        let one = seeds_of("j", 1, 2, 0, 3);
        for &s in &one[..2] {
            assert!(matches!(feed_seed(&mut a1, "j", s), Outcome::Stored { .. }));
        }
        assert!(!closed(&a1, "j"), "closing is the authority's");
        assert!(matches!(
            feed_seed(&mut a1, "j", one[2]),
            Outcome::Rejected {
                reason: Rejection::Late,
                ..
            }
        ));
        assert!(!closed(&a1, "j"));
        assert_eq!(a1.world_count(), 2);
        // The authority closes on the count, and the follower follows.
        let mut a0 = shard(0, 2);
        a0.submit_job(job("j", 2));
        let st = report(&a1, &mut a0, "j").unwrap_or_default();
        assert!(st.closed && st.worlds_done == 2 && st.shard_worlds == [0, 2]);
        a1.adopt_state(&st);
        assert!(closed(&a1, "j"));
        assert!(a1.unacknowledged_counts().is_empty());
        // Unknown jobs are ignored.
        a1.adopt_state(&JobState {
            job_id: "other".into(),
            ..Default::default()
        });
        assert!(a1.job_state("other").is_none());
    }

    /// Issue 21, case 2: the authority restarts from a journal that lacks counts shard 1 sent
    /// while it was down. Shard 1 keeps storing (it never closes on its own count), sees its
    /// count missing from the authority's states, sends it again, and the job closes on the
    /// sum: every acknowledged world is stored.
    #[test]
    fn a_restarted_authority_relearns_the_counts_it_missed() {
        let zero = seeds_of("j", 0, 2, 0, 3);
        let one = seeds_of("j", 1, 2, 0, 4);
        let (mut a0, mut a1) = (shard(0, 2), shard(1, 2));
        a0.submit_job(job("j", 6));
        a1.submit_job(job("j", 6));
        for &s in &zero[..2] {
            assert!(matches!(feed_seed(&mut a0, "j", s), Outcome::Stored { .. }));
        }
        assert!(matches!(
            feed_seed(&mut a1, "j", one[0]),
            Outcome::Stored { .. }
        ));
        let journaled = report(&a1, &mut a0, "j").unwrap_or_default();
        a1.adopt_state(&journaled);
        assert_eq!(journaled.shard_worlds, [2, 1]);
        // The authority dies; shard 1 stores three more (their counts go nowhere).
        for &s in &one[1..4] {
            assert!(matches!(feed_seed(&mut a1, "j", s), Outcome::Stored { .. }));
        }
        assert!(
            !closed(&a1, "j"),
            "shard 1 reached 6 on its own view, but never closes"
        );
        // Restarted: its journal gives back its job, its two worlds, the last state it wrote.
        let mut b0 = shard(0, 2);
        b0.submit_job(job("j", 6));
        for &s in &zero[..2] {
            assert!(matches!(feed_seed(&mut b0, "j", s), Outcome::Stored { .. }));
        }
        b0.restore_state(&journaled);
        let restored = b0.job_state("j").cloned().unwrap_or_default();
        assert_eq!((restored.worlds_done, restored.closed), (3, false));
        assert!(restored.revision >= journaled.revision);
        // Its next state shows shard 1 behind: shard 1 sends its count again.
        a1.adopt_state(&restored);
        assert_eq!(a1.unacknowledged_counts(), ["j"]);
        let st = report(&a1, &mut b0, "j").unwrap_or_default();
        assert!(st.closed && st.worlds_done == 6 && st.shard_worlds == [2, 4]);
        a1.adopt_state(&st);
        assert!(a1.unacknowledged_counts().is_empty() && closed(&a1, "j"));
        assert_eq!(
            st.worlds_done as usize,
            b0.world_count() + a1.world_count(),
            "acknowledged = stored"
        );
        // Late now on both.
        assert!(matches!(
            feed_seed(&mut b0, "j", zero[2]),
            Outcome::Rejected {
                reason: Rejection::Late,
                ..
            }
        ));
    }

    /// A journal file reads alone: its checkpoint's counts (this shard's and the others') are
    /// taken where ahead, and the worlds that follow it add to them.
    #[test]
    fn a_restored_state_keeps_the_counts_of_its_checkpoint() {
        let mut a1 = shard(1, 2);
        a1.submit_job(job("j", 20));
        a1.restore_state(&JobState {
            job_id: "j".into(),
            worlds_done: 9,
            shard_worlds: vec![4, 5],
            shard_bytes: vec![40, 50],
            revision: 7,
            ..Default::default()
        });
        let st = a1.job_state("j").cloned().unwrap_or_default();
        assert_eq!(
            (st.worlds_done, st.shard_worlds.clone(), st.revision),
            (9, vec![4, 5], 7)
        );
        let mine = seeds_of("j", 1, 2, 0, 1);
        assert!(matches!(
            feed_seed(&mut a1, "j", mine[0]),
            Outcome::Stored { .. }
        ));
        assert_eq!(a1.own_count("j").map(|(n, _)| n), Some(6));
        // A lower one (an older state further on) lowers nothing.
        a1.restore_state(&JobState {
            job_id: "j".into(),
            shard_worlds: vec![1, 1],
            shard_bytes: vec![1, 1],
            ..Default::default()
        });
        assert_eq!(done_of(&a1, "j"), 10);
        // A single store's state from before per-shard counts.
        let mut a = Assembler::new(1 << 20);
        a.submit_job(job("j", 20));
        a.restore_state(&JobState {
            job_id: "j".into(),
            worlds_done: 3,
            bytes_stored: 30,
            ..Default::default()
        });
        assert_eq!(a.own_count("j"), Some((3, 30)));
    }

    /// A tiny deterministic generator for the interleavings below (no dependency).
    struct XorShift(u64);
    impl XorShift {
        fn below(&mut self, n: usize) -> usize {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 % n as u64) as usize
        }
    }

    /// Two shards, every world sent to both, shard 1's counts and the authority's states on
    /// their own channels, all delivered in random interleavings (each channel in order).
    /// Whatever the order: the authority never acknowledges more than the shards store, and at
    /// the end it acknowledges exactly what they store, at least the target, and the job is
    /// closed on both.
    #[test]
    fn any_interleaving_acknowledges_exactly_the_stored_worlds() {
        use std::collections::VecDeque;
        const TARGET: u32 = 5;
        for run in 0..500u64 {
            let mut rng = XorShift(0x9E37_79B9_7F4A_7C15 ^ (run + 1));
            let (mut a0, mut a1) = (shard(0, 2), shard(1, 2));
            a0.submit_job(job("j", TARGET));
            a1.submit_job(job("j", TARGET));
            // Channels: worlds to 0, worlds to 1, counts 1 → 0, states 0 → 1.
            let worlds: Vec<u64> = (0..TARGET as u64 + 4).map(|s| 1000 * run + s).collect();
            let mut to0: VecDeque<u64> = worlds.iter().copied().collect();
            let mut to1: VecDeque<u64> = worlds.iter().copied().collect();
            let mut counts: VecDeque<(u32, u64)> = VecDeque::new();
            let mut states: VecDeque<JobState> = VecDeque::new();
            loop {
                let ready: Vec<usize> = [
                    !to0.is_empty(),
                    !to1.is_empty(),
                    !counts.is_empty(),
                    !states.is_empty(),
                ]
                .iter()
                .enumerate()
                .filter(|(_, r)| **r)
                .map(|(i, _)| i)
                .collect();
                if ready.is_empty() {
                    break;
                }
                match ready[rng.below(ready.len())] {
                    0 => {
                        let s = to0.pop_front().unwrap_or_default();
                        if let Outcome::Stored { state, .. } = feed_seed(&mut a0, "j", s) {
                            states.push_back(state);
                        }
                    }
                    1 => {
                        let s = to1.pop_front().unwrap_or_default();
                        if let Outcome::Stored { .. } = feed_seed(&mut a1, "j", s) {
                            counts.push_back(a1.own_count("j").unwrap_or_default());
                        }
                    }
                    2 => {
                        let (n, b) = counts.pop_front().unwrap_or_default();
                        let one = ShardSpec { index: 1, count: 2 };
                        states.extend(a0.on_shard_count("j", one, n, b, 1));
                    }
                    _ => {
                        let st = states.pop_front().unwrap_or_default();
                        a1.adopt_state(&st);
                    }
                }
                let stored = (a0.world_count() + a1.world_count()) as u32;
                assert!(
                    done_of(&a0, "j") <= stored,
                    "run {run}: acknowledged > stored"
                );
                assert!(!closed(&a1, "j") || closed(&a0, "j"), "run {run}");
            }
            let stored = (a0.world_count() + a1.world_count()) as u32;
            assert_eq!(done_of(&a0, "j"), stored, "run {run}");
            assert!(stored >= TARGET, "run {run}: {stored}");
            assert!(closed(&a0, "j") && closed(&a1, "j"), "run {run}");
            assert!(a1.unacknowledged_counts().is_empty(), "run {run}");
        }
    }

    /// One shard: the sum is its own count, as before sharding counted anything.
    #[test]
    fn a_single_store_counts_as_before() {
        let mut a = Assembler::new(1 << 20);
        a.submit_job(job("j", 2));
        for s in 0..2 {
            assert!(matches!(feed_seed(&mut a, "j", s), Outcome::Stored { .. }));
        }
        let st = a.job_state("j").cloned().unwrap_or_default();
        assert!(st.closed && st.worlds_done == 2 && st.shard_worlds == [2]);
        assert_eq!(st.bytes_stored, a.stored().map(|w| w.bytes).sum::<u64>());
        assert!(a.unacknowledged_counts().is_empty());
        assert!(matches!(
            feed_seed(&mut a, "j", 2),
            Outcome::Rejected {
                reason: Rejection::Late,
                ..
            }
        ));
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
        let one = StoredWorld::new(0, "j".into(), &d, &s, 0, None).held_bytes();
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

    /// A stored world keeps its summary and segments encoded in one block and gives them
    /// back exactly, ids included; the cap counts it as held: its encoding, its struct and
    /// the blocks around them — a little more than its encoded bytes, far less than the
    /// decoded structs.
    #[test]
    fn a_world_is_held_encoded_given_back_exactly_and_counted_as_held() {
        let (s, d) = world("job-with-a-long-name", "sampler-a", 0, 1, 3);
        let stored = StoredWorld::new(7, "job-with-a-long-name".into(), &d, &s, 0, None);
        assert_eq!(stored.decode(), Ok((d.clone(), s.clone())));
        assert_eq!(stored.done(), Ok(d.clone()));
        assert_eq!(stored.segment_count(), 3);
        assert_eq!(stored.body_count(), d.impacts.len());
        assert!(!stored.is_layered());
        let message = stored.message().unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            (message.index, message.segments, message.done),
            (7, s.clone(), Some(d.clone()))
        );

        let encoded =
            s.iter().map(|x| x.encoded_len() as u64).sum::<u64>() + d.encoded_len() as u64;
        let held = stored.held_bytes();
        let structs = 3 * std::mem::size_of::<MotionSegment>() + std::mem::size_of::<WorldDone>();
        let payloads: u64 = s.iter().map(|x| x.payload.len() as u64).sum();
        assert!(held > payloads, "{held} against {payloads} of payloads");
        assert!(
            held < encoded + structs as u64,
            "{held} against {encoded} encoded"
        );

        let mut a = Assembler::new(1 << 20);
        a.submit_job(job("job-with-a-long-name", 10));
        assert!(matches!(feed(&mut a, s, d), Outcome::Stored { .. }));
        assert_eq!(a.memory_bytes(), held);
        // A second world alike (another seed) counts what it holds.
        let (s, d) = world("job-with-a-long-name", "sampler-a", 1, 2, 3);
        let again =
            StoredWorld::new(0, "job-with-a-long-name".into(), &d, &s, 0, None).held_bytes();
        assert!(matches!(feed(&mut a, s, d), Outcome::Stored { .. }));
        assert_eq!(a.memory_bytes(), held + again);
    }

    /// The browsing index counts against the cap: with room for three worlds' bytes, a store
    /// whose index takes one world's worth per world holds fewer.
    #[test]
    fn index_bytes_count_against_the_cap() {
        let (s, d) = world("j", "n", 0, 1, 2);
        let one = StoredWorld::new(0, "j".into(), &d, &s, 0, None).held_bytes();
        let mut a = Assembler::new(one * 3 + one / 2);
        a.submit_job(job("j", 10));
        let mut stored = 0u64;
        for c in 0..4u64 {
            let (s, d) = world("j", "n", c, 100 + c, 2);
            if matches!(feed(&mut a, s, d), Outcome::Stored { .. }) {
                stored += 1;
                // The node reports the index after indexing each stored world.
                a.set_index_bytes(stored * one, stored);
            }
        }
        // World 0 (0 + 1 + est 0 ≤ 3.5), world 1 (1 + 1 + 1 + est 1 = 4 > 3.5): refused, …
        assert_eq!(stored, 1);
        assert_eq!(a.counters.refused_memory, 3);
        assert_eq!(a.memory_bytes(), 2 * one);
        assert!(a.memory_bytes() <= a.cap_bytes());
    }

    /// Worlds stored but not yet indexed (a batch, indexed together after it is stored) count
    /// at the mean index of the worlds indexed so far, in `memory_bytes` and against the cap.
    #[test]
    fn worlds_not_yet_indexed_count_at_the_mean_index() {
        let x = 1_000u64; // index bytes per indexed world
        let mut a = Assembler::new(u64::MAX);
        a.submit_job(job("j", 10));
        let mut c = 0u64;
        let mut store = |a: &mut Assembler| {
            let (s, d) = world("j", "n", c, 100 + c, 2);
            c += 1;
            matches!(feed(a, s, d), Outcome::Stored { .. })
        };
        assert!(store(&mut a) && store(&mut a));
        a.set_index_bytes(2 * x, 2);
        assert_eq!(a.memory_bytes(), a.stored_bytes + 2 * x);
        // One more stored, not indexed yet: counted at the mean, x.
        assert!(store(&mut a));
        let stored3 = a.stored_bytes;
        assert_eq!(a.memory_bytes(), stored3 + 3 * x);
        // Room for the next world and its index only if the pending one is left out: refused.
        let next = stored3 / 3;
        a.cap_bytes = stored3 + next + 2 * x + x + x / 2;
        assert!(!store(&mut a));
        assert_eq!(a.counters.refused_memory, 1);
        // Once reported, the pending world counts at its real size.
        a.set_index_bytes(2 * x + x / 2, 3);
        assert_eq!(a.memory_bytes(), stored3 + 2 * x + x / 2);
        assert!(store(&mut a), "room again");
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

    /// A summary (and the index it carries) counts against the cap while its world is
    /// partial: a sampler that sent summaries whose segments never came held memory nobody
    /// counted. Stored, the world counts as held; a summary larger than the cap is refused.
    #[test]
    fn a_summary_and_its_index_count_while_the_world_is_partial() {
        use mwb_proto::v1::ObjectIndex;
        let mut a = Assembler::new(1 << 20);
        a.submit_job(job("j", 5));
        let (segs, mut d) = world("j", "n", 0, 1, 2);
        let index = WorldIndex {
            objects: vec![
                ObjectIndex {
                    path: vec![7; 3000],
                    ..Default::default()
                };
                2
            ],
            ..Default::default()
        };
        let index_len = index.encoded_len() as u64;
        d.index = Some(index);
        let summary_len = {
            let mut bare = d.clone();
            bare.index = None;
            bare.encoded_len() as u64
        };
        assert_eq!(a.on_done(d.clone(), 1), Outcome::Pending);
        assert_eq!(a.memory_bytes(), summary_len + index_len);
        // The same summary again replaces it.
        assert_eq!(a.on_done(d.clone(), 1), Outcome::Pending);
        assert_eq!(a.memory_bytes(), summary_len + index_len);
        let mut seg_len = 0;
        let mut out = Outcome::Pending;
        for s in segs {
            seg_len += s.encoded_len() as u64;
            out = a.on_segment(s, 2);
        }
        assert!(
            matches!(
                &out,
                Outcome::Stored {
                    sent_index: Some(_),
                    ..
                }
            ),
            "{out:?}"
        );
        let held: u64 = a.stored().map(|w| w.held_bytes()).sum();
        assert_eq!(
            a.memory_bytes(),
            held,
            "{seg_len} B of segments now held as the world"
        );
        // A summary whose segments never come expires with what it held.
        let (_, mut orphan) = world("j", "gone", 0, 2, 2);
        orphan.index = Some(WorldIndex::default());
        assert_eq!(a.on_done(orphan, 3), Outcome::Pending);
        assert!(a.memory_bytes() > held);
        assert_eq!(a.expire(100_000, 1000, 60_000), 1);
        assert_eq!(a.memory_bytes(), held);
        // Larger than the whole cap: refused at once.
        let mut small = Assembler::new(1000);
        small.submit_job(job("j", 5));
        let (_, mut big) = world("j", "n", 0, 1, 2);
        big.index = Some(WorldIndex {
            objects: vec![ObjectIndex {
                path: vec![1; 2000],
                ..Default::default()
            }],
            ..Default::default()
        });
        assert!(matches!(
            small.on_done(big, 1),
            Outcome::Rejected {
                reason: Rejection::MemoryCap,
                ..
            }
        ));
        assert_eq!(small.memory_bytes(), 0);
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
            matches!(out.as_slice(), [Outcome::Stored { index: 0, state, .. }] if state.worlds_done == 1),
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
