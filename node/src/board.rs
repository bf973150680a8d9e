//! The job board of a worker node: the open jobs this node's kind takes, what the stores say
//! about them, and which one a free worker should take next. Pure: the bus tasks feed it job
//! announcements and states, the workers take and return worlds.

use mwb_proto::v1::{Job, JobKind, JobState};
use std::collections::HashMap;
use std::sync::{Arc, OnceLock};

/// A job's scene made ready to run (parsed, a chain learned), by whichever worker needs it
/// first; `None` if the kind refused it.
pub(crate) type SceneSlot<S> = Arc<OnceLock<Option<Arc<S>>>>;

/// How a taken world ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Ended {
    /// Published.
    Stored,
    /// Abandoned because the job closed or the node stops: says nothing about the job.
    Stopped,
    /// The world failed (non-finite state, codec refusal, …).
    Failed,
}

/// A job as this node sees it.
struct Entry<S> {
    job: Arc<Job>,
    scene: SceneSlot<S>,
    /// Closed by the stores (target reached) or cancelled.
    closed: bool,
    /// Given up locally: its scene was refused, or its worlds kept failing. A new revision with
    /// another scene tries again.
    given_up: bool,
    done: u32,
    in_flight: u32,
    /// Worlds that failed since the last one that did not.
    failures: u32,
}

impl<S> Entry<S> {
    fn open(&self) -> bool {
        !self.closed && !self.given_up
    }
}

/// What a worker takes: one world of `job`.
pub(crate) struct Picked<S> {
    pub job: Arc<Job>,
    pub scene: SceneSlot<S>,
}

/// The open jobs of one worker kind.
pub(crate) struct Board<S> {
    jobs: HashMap<String, Entry<S>>,
    takes: fn(JobKind) -> bool,
    give_up_after: u32,
}

impl<S> Board<S> {
    /// A board for jobs of the kinds `takes` accepts; a job whose worlds fail `give_up_after`
    /// times in a row is given up.
    pub fn new(takes: fn(JobKind) -> bool, give_up_after: u32) -> Self {
        Self {
            jobs: HashMap::new(),
            takes,
            give_up_after: give_up_after.max(1),
        }
    }

    /// The job a free worker should take: highest priority, then refinements, then the job
    /// with the fewest worlds still missing ("refinement and small jobs first"), then oldest.
    pub fn pick(&mut self) -> Option<Picked<S>> {
        let best = self
            .jobs
            .iter()
            .filter(|(_, e)| {
                e.open() && e.job.scene.is_some() && e.done + e.in_flight < e.job.target_worlds
            })
            .min_by_key(|(id, e)| {
                (
                    -i64::from(e.job.priority),
                    e.job.kind() != JobKind::Refine,
                    e.job.target_worlds.saturating_sub(e.done),
                    e.job.created_unix_ms,
                    (*id).clone(),
                )
            })
            .map(|(id, _)| id.clone())?;
        let e = self.jobs.get_mut(&best)?;
        e.in_flight += 1;
        Some(Picked {
            job: e.job.clone(),
            scene: e.scene.clone(),
        })
    }

    /// The jobs this node has given up (scene refused, or worlds failing in a row) and that
    /// the stores have not closed: what its statistics report, so that a client can tell a job
    /// nobody will finish from a slow one.
    pub fn given_up(&self) -> Vec<String> {
        let mut ids: Vec<String> = self
            .jobs
            .iter()
            .filter(|(_, e)| e.given_up && !e.closed)
            .map(|(id, _)| id.clone())
            .collect();
        ids.sort();
        ids
    }

    /// Whether worlds of `job` are still wanted from this node.
    pub fn is_open(&self, job: &str) -> bool {
        self.jobs.get(job).is_some_and(Entry::open)
    }

    /// Takes a job announcement (a newer revision replaces an older one). Jobs of kinds this
    /// board does not take are someone else's and are not even remembered.
    pub fn upsert(&mut self, job: Job) {
        if !(self.takes)(job.kind()) {
            return;
        }
        if let Some(e) = self.jobs.get_mut(&job.id) {
            if e.job.revision >= job.revision {
                return;
            }
            if e.job.scene != job.scene {
                e.scene = SceneSlot::default();
                e.failures = 0;
                e.given_up = false;
            }
            e.closed |= job.cancelled;
            e.job = Arc::new(job);
            return;
        }
        self.jobs.insert(
            job.id.clone(),
            Entry {
                closed: job.cancelled,
                job: Arc::new(job),
                scene: SceneSlot::default(),
                given_up: false,
                done: 0,
                in_flight: 0,
                failures: 0,
            },
        );
    }

    /// Takes a job state from the stores.
    pub fn apply_state(&mut self, st: &JobState) {
        if let Some(e) = self.jobs.get_mut(&st.job_id) {
            e.done = e.done.max(st.worlds_done);
            e.closed |= st.closed;
        }
    }

    /// A world of `job` ended: it is no longer in flight. Returns the failures in a row if this
    /// one made the node give the job up.
    pub fn finished(&mut self, job: &str, ended: Ended) -> Option<u32> {
        let e = self.jobs.get_mut(job)?;
        e.in_flight = e.in_flight.saturating_sub(1);
        match ended {
            Ended::Stored => e.failures = 0,
            Ended::Stopped => {}
            Ended::Failed => e.failures += 1,
        }
        let give_up = e.failures >= self.give_up_after && !e.given_up;
        e.given_up |= give_up;
        give_up.then_some(e.failures)
    }

    /// A worker took a world of `job` but its scene was refused: the job is given up (until a
    /// revision brings another scene).
    pub fn refused(&mut self, job: &str) {
        if let Some(e) = self.jobs.get_mut(job) {
            e.in_flight = e.in_flight.saturating_sub(1);
            e.given_up = true;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mwb_proto::v1::Scene;

    fn job(id: &str, target: u32, priority: i32, kind: JobKind, created: u64) -> Job {
        Job {
            id: id.into(),
            revision: 1,
            kind: kind as i32,
            scene: Some(Scene {
                toml: format!("# scene of {id}"),
                ..Default::default()
            }),
            target_worlds: target,
            priority,
            created_unix_ms: created,
            ..Default::default()
        }
    }

    fn forward(kind: JobKind) -> bool {
        kind != JobKind::Reverse
    }

    fn reverse(kind: JobKind) -> bool {
        kind == JobKind::Reverse
    }

    fn picks(board: &mut Board<()>, n: usize) -> Vec<String> {
        (0..n)
            .filter_map(|_| board.pick())
            .map(|p| p.job.id.clone())
            .collect()
    }

    #[test]
    fn priority_then_refinement_then_small_jobs_first() {
        let mut b: Board<()> = Board::new(forward, 1);
        b.upsert(job("big", 1000, 0, JobKind::Sample, 1));
        b.upsert(job("small", 3, 0, JobKind::Sample, 2));
        b.upsert(job("refine", 1, 0, JobKind::Refine, 3));
        b.upsert(job("urgent", 2, 5, JobKind::Sample, 4));
        // Higher priority first, until its worlds are all in flight; then refinements, then
        // the smallest remaining job, then the big one.
        assert_eq!(
            picks(&mut b, 7),
            [
                "urgent", "urgent", "refine", "small", "small", "small", "big"
            ]
        );
    }

    #[test]
    fn among_equals_the_oldest_then_the_id_goes_first() {
        let mut b: Board<()> = Board::new(forward, 1);
        b.upsert(job("b", 1, 0, JobKind::Sample, 5));
        b.upsert(job("c", 1, 0, JobKind::Sample, 5));
        b.upsert(job("a", 1, 0, JobKind::Sample, 7));
        assert_eq!(picks(&mut b, 4), ["b", "c", "a"]);
    }

    #[test]
    fn closed_cancelled_and_sceneless_jobs_are_never_picked() {
        let mut b: Board<()> = Board::new(forward, 1);
        b.upsert(job("a", 10, 0, JobKind::Sample, 1));
        b.upsert(Job {
            scene: None,
            ..job("noscene", 10, 9, JobKind::Sample, 1)
        });
        b.apply_state(&JobState {
            job_id: "a".into(),
            worlds_done: 10,
            closed: true,
            ..Default::default()
        });
        assert!(b.pick().is_none());
        let mut c = job("c", 10, 0, JobKind::Sample, 1);
        b.upsert(c.clone());
        c.revision = 2;
        c.cancelled = true;
        b.upsert(c);
        assert!(b.pick().is_none());
        assert!(!b.is_open("c"));
    }

    #[test]
    fn a_kind_takes_only_its_jobs() {
        let mut f: Board<()> = Board::new(forward, 1);
        let mut r: Board<()> = Board::new(reverse, 1);
        for board in [&mut f, &mut r] {
            board.upsert(job("sample", 1, 0, JobKind::Sample, 1));
            board.upsert(job("refine", 1, 0, JobKind::Refine, 1));
            board.upsert(job("old", 1, 0, JobKind::Unspecified, 1));
            board.upsert(job("rev", 2, 9, JobKind::Reverse, 1));
        }
        assert_eq!(picks(&mut f, 9), ["refine", "old", "sample"]);
        assert_eq!(picks(&mut r, 9), ["rev", "rev"]);
        // A reverse job is not even remembered by a forward board: its state is ignored.
        assert!(!f.is_open("rev"));
    }

    #[test]
    fn in_flight_and_done_worlds_count_towards_the_target() {
        let mut b: Board<()> = Board::new(forward, 1);
        b.upsert(job("a", 3, 0, JobKind::Sample, 1));
        b.apply_state(&JobState {
            job_id: "a".into(),
            worlds_done: 1,
            ..Default::default()
        });
        assert_eq!(picks(&mut b, 5).len(), 2);
        b.finished("a", Ended::Stopped);
        assert_eq!(picks(&mut b, 5).len(), 1);
    }

    #[test]
    fn failures_in_a_row_give_the_job_up_and_a_stored_world_resets_them() {
        let mut b: Board<()> = Board::new(reverse, 3);
        b.upsert(job("a", 100, 0, JobKind::Reverse, 1));
        for _ in 0..2 {
            assert!(b.pick().is_some());
            assert_eq!(b.finished("a", Ended::Failed), None);
        }
        assert!(b.pick().is_some());
        assert_eq!(b.finished("a", Ended::Stored), None);
        for _ in 0..2 {
            assert!(b.pick().is_some());
            assert_eq!(b.finished("a", Ended::Failed), None);
        }
        // A stopped world says nothing about the job: the count goes on.
        assert!(b.pick().is_some());
        assert_eq!(b.finished("a", Ended::Stopped), None);
        assert!(b.pick().is_some());
        assert_eq!(b.finished("a", Ended::Failed), Some(3));
        assert!(b.pick().is_none());
        assert!(!b.is_open("a"));
        assert_eq!(b.given_up(), ["a"]);
        // Once the stores close it, it is nobody's concern any more.
        b.apply_state(&JobState {
            job_id: "a".into(),
            closed: true,
            ..Default::default()
        });
        assert!(b.given_up().is_empty());
    }

    #[test]
    fn a_refused_scene_is_retried_only_when_a_revision_changes_it() {
        let mut b: Board<()> = Board::new(forward, 1);
        let mut a = job("a", 10, 0, JobKind::Sample, 1);
        b.upsert(a.clone());
        assert!(b.pick().is_some());
        b.refused("a");
        assert!(b.pick().is_none());
        // Same scene, new revision: still refused.
        a.revision = 2;
        a.priority = 1;
        b.upsert(a.clone());
        assert!(b.pick().is_none());
        // Another scene: a fresh slot, taken again.
        a.revision = 3;
        if let Some(s) = a.scene.as_mut() {
            s.toml = "# fixed".into();
        }
        b.upsert(a);
        let p = b
            .pick()
            .unwrap_or_else(|| panic!("the fixed job is not picked"));
        assert!(p.scene.get().is_none(), "the old scene slot was kept");
    }
}
