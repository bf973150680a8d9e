//! A stored world's browsing index (§4.4.2–4.4.3), built by [`mwb_index`] (pure: paths,
//! radii, metrics) from the world as this store holds it: a refined world stored as a
//! difference is composed with its parent first. Many worlds are indexed at once on every core
//! ([`index_worlds`]).

use crate::assembly::StoredWorld;
pub use mwb_index::*;
use mwb_proto::v1::{MotionSegment, WorldDone};
use std::sync::Arc;

/// Every body's full-rate decoded motion, and the largest error bound of the payloads it came
/// from. A refined world stored as a difference (§4.5) is its parent's motion (composed the
/// same way, recursively) with its own segments laid over it.
fn full_tracks(
    stored: &StoredWorld,
    done: &WorldDone,
    segments: &[MotionSegment],
) -> Result<(Vec<mwb_codec::Track>, f64), IndexError> {
    if !stored.is_layered() {
        return decode_tracks(segments);
    }
    let first = segments.first().ok_or(IndexError::Empty)?;
    let parent = stored.parent.as_deref().ok_or(IndexError::NoParent)?;
    let (parent_done, parent_segments) = parent.decode().map_err(stored_error)?;
    let (tracks, mut e_max) =
        full_tracks(parent, &parent_done, &parent_segments).map_err(|e| IndexError::Parent {
            world: parent.index,
            what: e.to_string(),
        })?;
    let frames = done.frame_count as usize;
    let mut layered =
        mwb_codec::Layered::start(tracks, frames).map_err(|e| IndexError::Segment {
            seq: first.seq,
            what: e.to_string(),
        })?;
    for s in segments {
        let (decoded, bound) = decode_segment_tracks(s)?;
        e_max = e_max.max(bound);
        layered
            .overlay(s.first_frame, &s.bodies, decoded)
            .map_err(|e| IndexError::Segment {
                seq: s.seq,
                what: e.to_string(),
            })?;
    }
    Ok((layered.finish(), e_max))
}

fn stored_error(e: crate::assembly::StoredDecodeError) -> IndexError {
    IndexError::Stored(e.to_string())
}

/// [`index_world`] for many worlds on up to `threads` threads, the results in the order given
/// (each `(stored world, its global index, its job's scene facts)`).
///
/// Indexing is most of what a store spends on a world it indexes itself (a decode of all its
/// motion and an error-bounded polyline per object: 1.1–1.8 ms for a 10-body tumble world on
/// this project's 2-core test machine, against ~10 µs to insert the result), and worlds are
/// independent, so a store indexes the worlds that reach it together on every core. Threads
/// take worlds one at a time; a single world, or a single thread, is indexed on the caller's.
pub fn index_worlds(
    worlds: &[(&StoredWorld, u32, JobScene)],
    tolerance: f64,
    threads: usize,
) -> Vec<Result<IndexedWorld, IndexError>> {
    let threads = threads.clamp(1, worlds.len().max(1));
    if threads == 1 {
        return worlds
            .iter()
            .map(|(w, index, scene)| index_world(w, *index, scene.clone(), tolerance))
            .collect();
    }
    let next = std::sync::atomic::AtomicUsize::new(0);
    let run = || {
        let mut done = Vec::new();
        loop {
            let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let Some((w, index, scene)) = worlds.get(i) else {
                return done;
            };
            done.push((i, index_world(w, *index, scene.clone(), tolerance)));
        }
    };
    let mut out: Vec<(usize, Result<IndexedWorld, IndexError>)> = std::thread::scope(|s| {
        let handles: Vec<_> = (1..threads).map(|_| s.spawn(run)).collect();
        let mine = run();
        handles
            .into_iter()
            .flat_map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e)))
            .chain(mine)
            .collect()
    });
    // Each index below `worlds.len()` was taken by exactly one thread.
    out.sort_unstable_by_key(|&(i, _)| i);
    out.into_iter().map(|(_, r)| r).collect()
}

/// Indexes a complete (assembled, CRC-verified) world under global index `world`, with its
/// job's scene facts (`scene`: rest thresholds, body names; a bare
/// [`RestThresholds`](mwb_core::browse::RestThresholds) converts): every segment decoded once
/// (full rate, composed with the parent's for a refined difference), then [`index_tracks`].
pub fn index_world(
    stored: &StoredWorld,
    world: u32,
    scene: impl Into<JobScene>,
    tolerance: f64,
) -> Result<IndexedWorld, IndexError> {
    let (done, segments) = stored.decode().map_err(stored_error)?;
    let dt = done.frame_dt;
    if !(dt.is_finite() && dt > 0.0) {
        return Err(IndexError::FrameDt(dt));
    }
    let (full, e_max) = full_tracks(stored, &done, &segments)?;
    index_tracks(
        &done,
        &full,
        e_max,
        world,
        Arc::from(stored.job_id.as_str()),
        scene,
        tolerance,
    )
}

/// What became of the index a world's sampler sent ([`index_stored`]).
#[derive(Debug, Clone, PartialEq)]
pub enum SentIndex {
    /// None was sent: indexed here.
    None,
    /// Taken as sent.
    Taken,
    /// Refused (why): indexed here.
    Refused(String),
    /// Taken after indexing the world here too: whether both agreed (when not, this store's
    /// own index is the one returned).
    Checked { same: bool },
}

/// Which sent indexes a store checks by indexing their worlds itself: the first it takes and
/// then one in `every` (1: all, 0: none), so that samplers of another build are caught at once.
#[derive(Debug, Clone, Copy)]
pub struct SentChecks {
    pub every: u32,
    taken: u64,
}

impl SentChecks {
    pub fn every(every: u32) -> Self {
        Self { every, taken: 0 }
    }

    fn next(&mut self) -> bool {
        self.taken += 1;
        self.every > 0 && (self.taken - 1).is_multiple_of(u64::from(self.every))
    }
}

/// Indexes stored worlds, each `(world, the index its sampler sent, its job's scene facts)`,
/// the results in the order given with what became of each sent index.
///
/// A sent index is taken once it checks out ([`IndexedWorld::from_wire`]: this store's layout
/// and `tolerance`, well-formed paths and metrics), except for a refined difference (composed
/// with its parent here); `checks` picks the ones also indexed here and compared, and where
/// they differ this store's own is returned. Every world without a usable sent index, and
/// every checked one, is indexed here, all of them together on up to `threads` threads
/// ([`index_worlds`]).
pub fn index_stored(
    worlds: Vec<(
        &StoredWorld,
        Option<Box<mwb_proto::v1::WorldIndex>>,
        JobScene,
    )>,
    tolerance: f64,
    threads: usize,
    checks: &mut SentChecks,
) -> Vec<(Result<IndexedWorld, IndexError>, SentIndex)> {
    // Per world: the sent index taken and whether it is checked, or why it was not taken.
    let mut taken: Vec<Result<(IndexedWorld, bool), SentIndex>> = Vec::with_capacity(worlds.len());
    let mut here = Vec::new();
    for (w, sent, scene) in worlds {
        let from_wire = match sent {
            None => Err(SentIndex::None),
            Some(_) if w.is_layered() => Err(SentIndex::Refused(
                "a refined difference is composed and indexed here".into(),
            )),
            Some(sent) => w
                .done()
                .map_err(|e| e.to_string())
                .and_then(|done| {
                    IndexedWorld::from_wire(
                        &done,
                        *sent,
                        w.index,
                        Arc::from(w.job_id.as_str()),
                        scene.clone(),
                        tolerance,
                    )
                    .map_err(|e| e.to_string())
                })
                .map(|indexed| (indexed, checks.next()))
                .map_err(SentIndex::Refused),
        };
        if !matches!(from_wire, Ok((_, false))) {
            here.push((w, w.index, scene));
        }
        taken.push(from_wire);
    }
    let mut own = index_worlds(&here, tolerance, threads).into_iter();
    taken
        .into_iter()
        .map(|t| match t {
            Ok((sent, false)) => (Ok(sent), SentIndex::Taken),
            Ok((sent, true)) => {
                let own = own.next().unwrap_or(Err(IndexError::Empty));
                let same = own.as_ref().is_ok_and(|o| o.same_objects(&sent));
                (own, SentIndex::Checked { same })
            }
            Err(why) => (own.next().unwrap_or(Err(IndexError::Empty)), why),
        })
        .collect()
}
