//! Why an open job cannot complete, from what the bus shows: the store refuses its worlds for
//! memory, no node that takes its kind is alive, or every such node has given it up (its worlds
//! keep failing). Pure: [`diagnose`] judges one snapshot (what `mwb status` shows), a
//! [`Watch`] follows a job over time (what `mwb job submit --wait` and `mwb demo` stop on) and
//! waits [`STALL_GRACE`] before it calls a job stuck, so a world in flight or a node about to
//! join is not mistaken for a dead end.

use mwb_core::keys::role;
use mwb_proto::v1::{JobKind, JobState, NodeStats};
use std::time::Duration;

/// How long a job may show a stall before it is reported (a world still being stored, a
/// sampler still connecting).
pub const STALL_GRACE: Duration = Duration::from_secs(5);

/// Why a job cannot complete.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Stall {
    #[error(
        "store full: {kept} of {target} worlds kept ({store}: {memory_mib:.1} of {cap_mib:.1} \
         MiB used, {refused} refusals for memory); raise --memory-cap-mib or add a shard"
    )]
    StoreFull {
        kept: u32,
        target: u32,
        store: String,
        refused: u64,
        memory_mib: f64,
        cap_mib: f64,
    },
    #[error(
        "no {role} node is alive in space {space:?} ({kept} of {target} worlds kept); start \
         `mwb {role} --connect <store endpoint>`: the job stays open and a node that joins \
         takes it"
    )]
    NoWorker {
        role: &'static str,
        space: String,
        kept: u32,
        target: u32,
    },
    #[error(
        "every {role} node gave the job up: its worlds keep failing ({kept} of {target} worlds \
         kept; last failure: {last_failure})"
    )]
    WorldsFailing {
        role: &'static str,
        kept: u32,
        target: u32,
        last_failure: String,
    },
}

/// The role of the nodes that compute a job's worlds.
pub fn worker_role(kind: JobKind) -> &'static str {
    match kind {
        JobKind::Reverse => role::REVERSE,
        JobKind::Sample | JobKind::Refine | JobKind::Unspecified => role::SAMPLER,
    }
}

/// What the bus shows about one open job at one moment.
#[derive(Debug, Clone)]
pub struct Evidence<'a> {
    pub space: &'a str,
    pub state: &'a JobState,
    /// The role of the nodes that take the job ([`worker_role`]).
    pub role: &'static str,
    /// Statistics of the live nodes of that role (one per node; a node that has not published
    /// yet is `NodeStats::default()`).
    pub workers: &'a [NodeStats],
    /// Statistics of the live stores.
    pub stores: &'a [NodeStats],
    /// Whether a store refused a world for memory since the job last stored one.
    pub refused_since_progress: bool,
}

/// The stall the evidence shows, if any (no grace: see [`Watch`]).
pub fn diagnose(e: &Evidence<'_>) -> Option<Stall> {
    let st = e.state;
    if st.closed {
        return None;
    }
    let (kept, target) = (st.worlds_done, st.target_worlds);
    if e.refused_since_progress
        && let Some(store) = e
            .stores
            .iter()
            .filter(|s| s.refused_memory > 0)
            .max_by_key(|s| s.refused_memory)
    {
        let mib = |b: u64| b as f64 / f64::from(1u32 << 20);
        return Some(Stall::StoreFull {
            kept,
            target,
            store: format!("store {}", store.node_id),
            refused: store.refused_memory,
            memory_mib: mib(store.memory_bytes),
            cap_mib: mib(store.memory_cap_bytes),
        });
    }
    if e.workers.is_empty() {
        return Some(Stall::NoWorker {
            role: e.role,
            space: e.space.to_owned(),
            kept,
            target,
        });
    }
    if e.workers
        .iter()
        .all(|w| w.jobs_given_up.contains(&st.job_id))
    {
        let last_failure = e
            .workers
            .iter()
            .map(|w| w.last_failure.as_str())
            .find(|m| !m.is_empty())
            .unwrap_or("not reported")
            .to_owned();
        return Some(Stall::WorldsFailing {
            role: e.role,
            kept,
            target,
            last_failure,
        });
    }
    None
}

/// A snapshot's guess whether a store that refused worlds for memory is full for this job: its
/// memory and the job's mean world would pass its cap. For `mwb status`, which sees one moment.
pub fn store_looks_full(store: &NodeStats, st: &JobState) -> bool {
    let mean = st.bytes_stored.checked_div(u64::from(st.worlds_done));
    store.refused_memory > 0
        && store.memory_bytes + mean.unwrap_or(0) >= store.memory_cap_bytes.saturating_sub(1)
}

/// Follows one job over time: a stall is reported once it has lasted [`STALL_GRACE`].
#[derive(Debug, Clone, Default)]
pub struct Watch {
    /// Worlds kept at the last progress, and when (ms on the caller's clock).
    done: u32,
    progress_ms: u64,
    /// The stores' memory refusals at the last progress (`None` until first seen).
    refused_at_progress: Option<u64>,
    /// Since when the current stall has been seen.
    stalled_since_ms: Option<u64>,
}

impl Watch {
    /// Starts watching at `now_ms`.
    pub fn new(now_ms: u64) -> Self {
        Self {
            progress_ms: now_ms,
            ..Self::default()
        }
    }

    /// Takes one observation at `now_ms` (`refused_total`: the stores' refused_memory summed);
    /// returns the stall once it has lasted the grace.
    pub fn observe(
        &mut self,
        now_ms: u64,
        space: &str,
        state: &JobState,
        role: &'static str,
        workers: &[NodeStats],
        stores: &[NodeStats],
    ) -> Option<Stall> {
        let refused_total: u64 = stores.iter().map(|s| s.refused_memory).sum();
        if state.worlds_done > self.done || self.refused_at_progress.is_none() {
            self.done = self.done.max(state.worlds_done);
            self.progress_ms = now_ms;
            self.refused_at_progress = Some(refused_total);
        }
        let evidence = Evidence {
            space,
            state,
            role,
            workers,
            stores,
            refused_since_progress: self.refused_at_progress.is_some_and(|r| refused_total > r),
        };
        let Some(stall) = diagnose(&evidence) else {
            self.stalled_since_ms = None;
            return None;
        };
        // A store refusing worlds while the job stores none: stuck since the last progress.
        let since = match stall {
            Stall::StoreFull { .. } => self.progress_ms,
            _ => *self.stalled_since_ms.get_or_insert(now_ms),
        };
        (now_ms.saturating_sub(since) >= STALL_GRACE.as_millis() as u64).then_some(stall)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state(done: u32) -> JobState {
        JobState {
            job_id: "j".into(),
            worlds_done: done,
            target_worlds: 200,
            ..Default::default()
        }
    }

    fn store(refused: u64) -> NodeStats {
        NodeStats {
            node_id: "s".into(),
            role: role::STORE.into(),
            refused_memory: refused,
            memory_bytes: 1 << 20,
            memory_cap_bytes: 1 << 20,
            ..Default::default()
        }
    }

    fn sampler(given_up: &[&str]) -> NodeStats {
        NodeStats {
            node_id: "w".into(),
            role: role::SAMPLER.into(),
            jobs_given_up: given_up.iter().map(|s| (*s).to_owned()).collect(),
            last_failure: "job j: world failed: non-finite".into(),
            ..Default::default()
        }
    }

    const G: u64 = STALL_GRACE.as_millis() as u64;

    #[test]
    fn refusals_without_progress_are_a_full_store_after_the_grace() {
        let mut w = Watch::new(0);
        let workers = [sampler(&[])];
        assert_eq!(
            w.observe(0, "sp", &state(0), role::SAMPLER, &workers, &[store(0)]),
            None
        );
        // Progress at 1 s, then only refusals.
        assert_eq!(
            w.observe(1000, "sp", &state(37), role::SAMPLER, &workers, &[store(0)]),
            None
        );
        assert_eq!(
            w.observe(2000, "sp", &state(37), role::SAMPLER, &workers, &[store(2)]),
            None
        );
        let stall = w.observe(
            1000 + G,
            "sp",
            &state(37),
            role::SAMPLER,
            &workers,
            &[store(5)],
        );
        let Some(s @ Stall::StoreFull { kept: 37, .. }) = stall else {
            panic!("{stall:?}");
        };
        let text = s.to_string();
        assert!(
            text.starts_with("store full: 37 of 200 worlds kept")
                && text.ends_with("raise --memory-cap-mib or add a shard"),
            "{text}"
        );
    }

    #[test]
    fn progress_clears_a_refusal_and_closed_jobs_never_stall() {
        let mut w = Watch::new(0);
        let workers = [sampler(&[])];
        w.observe(0, "sp", &state(0), role::SAMPLER, &workers, &[store(3)]);
        // Refusals before watching began are not this job's stall.
        assert_eq!(
            w.observe(
                10 * G,
                "sp",
                &state(0),
                role::SAMPLER,
                &workers,
                &[store(3)]
            ),
            None
        );
        w.observe(
            11 * G,
            "sp",
            &state(0),
            role::SAMPLER,
            &workers,
            &[store(4)],
        );
        // A smaller world still fits: progress, and the refusal is history.
        assert_eq!(
            w.observe(
                12 * G,
                "sp",
                &state(1),
                role::SAMPLER,
                &workers,
                &[store(4)]
            ),
            None
        );
        assert_eq!(
            w.observe(
                20 * G,
                "sp",
                &state(1),
                role::SAMPLER,
                &workers,
                &[store(4)]
            ),
            None
        );
        let closed = JobState {
            closed: true,
            ..state(1)
        };
        assert_eq!(
            w.observe(30 * G, "sp", &closed, role::SAMPLER, &[], &[store(9)]),
            None
        );
    }

    #[test]
    fn no_worker_is_reported_only_after_the_grace_and_a_joiner_clears_it() {
        let mut w = Watch::new(0);
        assert_eq!(
            w.observe(0, "sp", &state(0), role::SAMPLER, &[], &[store(0)]),
            None
        );
        assert_eq!(
            w.observe(G - 1, "sp", &state(0), role::SAMPLER, &[], &[store(0)]),
            None
        );
        let workers = [sampler(&[])];
        assert_eq!(
            w.observe(G, "sp", &state(0), role::SAMPLER, &workers, &[store(0)]),
            None
        );
        w.observe(2 * G, "sp", &state(0), role::SAMPLER, &[], &[store(0)]);
        let stall = w.observe(3 * G, "sp", &state(0), role::SAMPLER, &[], &[store(0)]);
        assert!(
            matches!(
                stall,
                Some(Stall::NoWorker {
                    role: "sampler",
                    ..
                })
            ),
            "{stall:?}"
        );
    }

    #[test]
    fn every_live_worker_giving_up_is_failing_worlds_with_the_last_message() {
        let mut w = Watch::new(0);
        let one_left = [sampler(&["j"]), sampler(&[])];
        w.observe(0, "sp", &state(0), role::SAMPLER, &one_left, &[]);
        assert_eq!(
            w.observe(2 * G, "sp", &state(0), role::SAMPLER, &one_left, &[]),
            None
        );
        let all = [sampler(&["j"]), sampler(&["j", "k"])];
        w.observe(3 * G, "sp", &state(0), role::SAMPLER, &all, &[]);
        let stall = w.observe(4 * G, "sp", &state(0), role::SAMPLER, &all, &[]);
        let Some(s @ Stall::WorldsFailing { .. }) = stall else {
            panic!("{stall:?}");
        };
        assert!(s.to_string().contains("non-finite"), "{s}");
    }

    #[test]
    fn a_snapshot_calls_a_store_full_when_the_mean_world_would_pass_its_cap() {
        let st = JobState {
            bytes_stored: 37 * 20_000,
            ..state(37)
        };
        let mut s = store(4);
        assert!(store_looks_full(&s, &st));
        s.memory_bytes = 1_000_000;
        assert!(!store_looks_full(&s, &st));
        assert!(!store_looks_full(&store(0), &st));
        assert_eq!(worker_role(JobKind::Reverse), role::REVERSE);
        assert_eq!(worker_role(JobKind::Sample), role::SAMPLER);
    }
}
