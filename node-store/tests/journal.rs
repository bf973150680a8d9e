//! The store's journal and `--load` over a real zenoh session (peer, no scouting): a store
//! restarted on its journal holds the same worlds byte for byte and the same job state; a
//! truncated or bit-flipped journal still lets it start, with every world before the damage;
//! a world that arrives before its job is stored when the job comes (no pause needed in a
//! replay).

mod common;

use common::{close, put, session, until};
use mwb_core::keys::Keys;
use mwb_proto::v1::{Job, Message, MotionSegment, WorldDone};
use mwb_store::{StoreConfig, StoreHandle};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

const SPACE: &str = "journaltest";

fn job(id: &str, target: u32) -> Job {
    Job {
        id: id.into(),
        revision: 1,
        target_worlds: target,
        ..Default::default()
    }
}

/// A world of `segs` segments with distinct payloads (not codec data: it is stored and
/// served, and counted as not browsable).
fn world(job: &str, counter: u64, seed: u64, segs: u32) -> (Vec<MotionSegment>, WorldDone) {
    let segments: Vec<MotionSegment> = (0..segs)
        .map(|i| {
            let payload: Vec<u8> = (0..300u32)
                .map(|b| (b as u64 * 31 + seed * 7 + u64::from(i)) as u8)
                .collect();
            MotionSegment {
                job_id: job.into(),
                node_id: "sampler-j".into(),
                world_counter: counter,
                seed,
                seq: i,
                first_frame: i * 10,
                frame_count: 10,
                body_count: 1,
                crc32: crc32fast::hash(&payload),
                payload,
                ..Default::default()
            }
        })
        .collect();
    let done = WorldDone {
        job_id: job.into(),
        node_id: "sampler-j".into(),
        world_counter: counter,
        seed,
        frame_count: segs * 10,
        segment_count: segs,
        impacts: vec![1],
        ..Default::default()
    };
    (segments, done)
}

async fn put_world(s: &zenoh::Session, keys: &Keys, w: &(Vec<MotionSegment>, WorldDone)) {
    for seg in &w.0 {
        put(
            s,
            keys.segment(&seg.job_id, &seg.node_id, seg.world_counter, seg.seq),
            seg.encode_to_vec(),
        )
        .await;
    }
    let d = &w.1;
    put(
        s,
        keys.done(&d.job_id, &d.node_id, d.world_counter),
        d.encode_to_vec(),
    )
    .await;
}

async fn store(s: &zenoh::Session, journal: Option<&Path>, load: Vec<PathBuf>) -> StoreHandle {
    common::start_store(
        s,
        StoreConfig {
            space: SPACE.into(),
            journal: journal.map(Path::to_owned),
            load,
            ..Default::default()
        },
    )
    .await
}

/// Every stored world as (job, seed) → its encoded summary and segments.
fn contents(st: &StoreHandle) -> BTreeMap<(String, u64), Vec<Vec<u8>>> {
    let mut m = BTreeMap::new();
    let mut i = 0;
    while let Some(w) = st.world(i) {
        let (done, segments) = w.decode().unwrap_or_else(|e| panic!("{e}"));
        let mut bytes = vec![done.encode_to_vec()];
        bytes.extend(segments.iter().map(|s| s.encode_to_vec()));
        m.insert((w.job_id.clone(), done.seed), bytes);
        i += 1;
    }
    m
}

/// A store with a journal in `dir` takes `worlds` worlds of job `id` (one commit each: the
/// next world is sent once the store holds the last).
async fn journal_worlds(dir: &Path, id: &str, target: u32, seeds: std::ops::Range<u64>) {
    let s = session().await;
    let keys = Keys::new(SPACE).unwrap_or_else(|e| panic!("{e}"));
    let st = store(&s, Some(dir), vec![]).await;
    let before = st.world_count();
    if st.job_state(id).is_none() {
        put(&s, keys.job(id), job(id, target).encode_to_vec()).await;
        until("the job", || st.job_state(id).is_some()).await;
    }
    for (n, seed) in seeds.clone().enumerate() {
        put_world(&s, &keys, &world(id, seed, seed, 3)).await;
        until("the world", || st.world_count() == before + n + 1).await;
    }
    // Every world is acknowledged once its state is published, after the commit.
    until("the journal's commits", || {
        st.journal_counters()
            .is_some_and(|c| c.messages >= 4 * seeds.clone().count() as u64)
    })
    .await;
    st.stop();
    close(s).await;
}

fn journal_files(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{e}"))
        .map(|e| e.unwrap_or_else(|e| panic!("{e}")).path())
        .collect();
    v.sort();
    v
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restarted_store_has_every_world_and_the_job_state_of_its_journal() {
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let journal = dir.path().join("journal");
    journal_worlds(&journal, "j1", 8, 0..5).await;

    let s = session().await;
    let st = store(&s, Some(&journal), vec![]).await;
    let r = st.start_report();
    assert_eq!(r.worlds_from_journal, 5, "{r:?}");
    assert_eq!(r.journal.len(), 1);
    // A stopped store's writer finishes its file as it is dropped (a killed one leaves it cut
    // short; both are read whole).
    let f = &r.journal[0];
    assert!(f.damage.is_none() || f.cut_short, "{f:?}");
    assert_eq!(r.damaged_files(), 0);
    let state = st.job_state("j1").unwrap_or_else(|| panic!("job j1 lost"));
    assert_eq!((state.worlds_done, state.closed), (5, false));
    let expected: BTreeMap<(String, u64), Vec<Vec<u8>>> = (0..5u64)
        .map(|seed| {
            let (segs, done) = world("j1", seed, seed, 3);
            let mut v = vec![done.encode_to_vec()];
            v.extend(segs.iter().map(|s| s.encode_to_vec()));
            (("j1".to_owned(), seed), v)
        })
        .collect();
    assert_eq!(contents(&st), expected);
    // Worlds keep their indices: the journal is read in the order they were stored.
    for i in 0..5u32 {
        assert_eq!(
            st.world(i).and_then(|w| w.done().ok()).map(|d| d.seed),
            Some(u64::from(i))
        );
    }

    // The job goes on after the restart, and a replayed duplicate is still refused.
    let keys = Keys::new(SPACE).unwrap_or_else(|e| panic!("{e}"));
    put_world(&s, &keys, &world("j1", 2, 2, 3)).await;
    for seed in 5..8u64 {
        put_world(&s, &keys, &world("j1", seed, seed, 3)).await;
    }
    until("the job to close", || {
        st.job_state("j1").is_some_and(|s| s.closed)
    })
    .await;
    assert_eq!(st.world_count(), 8);
    assert_eq!(st.stats().duplicates, 1);
    st.stop();
    close(s).await;

    // Two files now (one per run); the second begins with a checkpoint of the job, so it
    // reads alone.
    let files = journal_files(&journal);
    assert_eq!(files.len(), 2, "{files:?}");
    let s = session().await;
    let lone = dir.path().join("lone");
    std::fs::create_dir(&lone).unwrap_or_else(|e| panic!("{e}"));
    let second = files.get(1).unwrap_or_else(|| panic!("no second file"));
    std::fs::copy(second, lone.join("journal-000001.mcap")).unwrap_or_else(|e| panic!("{e}"));
    let st = store(&s, Some(&lone), vec![]).await;
    assert_eq!(st.world_count(), 3, "worlds 5..8 of the second run");
    let state = st.job_state("j1").unwrap_or_else(|| panic!("job lost"));
    assert!(state.closed && state.worlds_done == 8, "{state:?}");
    st.stop();

    // The whole journal, loaded as recordings (`--load`) into a memory-only store.
    let st = store(&s, None, files).await;
    assert_eq!(st.world_count(), 8);
    assert_eq!(st.start_report().worlds_from_recordings, 8);
    st.stop();
    close(s).await;
}

/// A journaling store started with `--load`: the loaded worlds are journaled after the run's
/// checkpoint (which counts none of them), so a restart on the journal alone has each of them
/// once, and the job as the recording left it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn worlds_loaded_into_a_journaling_store_survive_its_restart() {
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let first = dir.path().join("first");
    journal_worlds(&first, "j1", 4, 0..4).await;
    let recordings = journal_files(&first);

    let s = session().await;
    let journal = dir.path().join("journal");
    let st = store(&s, Some(&journal), recordings).await;
    assert_eq!(st.start_report().worlds_from_recordings, 4);
    let before = contents(&st);
    st.stop();

    let st = store(&s, Some(&journal), vec![]).await;
    let r = st.start_report();
    assert_eq!((r.worlds_from_journal, r.worlds_refused), (4, 0), "{r:?}");
    assert_eq!(contents(&st), before);
    let state = st.job_state("j1").unwrap_or_else(|| panic!("job lost"));
    assert!(state.closed && state.worlds_done == 4, "{state:?}");
    st.stop();
    close(s).await;
}

/// Cut and flipped copies of a journal: the store starts every time, with the worlds whose
/// records precede the damage — a prefix of the original worlds, byte for byte.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_truncated_or_bit_flipped_journal_loads_what_precedes_the_damage() {
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let journal = dir.path().join("journal");
    journal_worlds(&journal, "jd", 20, 0..6).await;
    let files = journal_files(&journal);
    let [file] = files.as_slice() else {
        panic!("{files:?}")
    };
    let bytes = std::fs::read(file).unwrap_or_else(|e| panic!("{e}"));
    let s = session().await;
    let full = {
        let st = store(&s, None, vec![file.clone()]).await;
        let c = contents(&st);
        st.stop();
        c
    };
    assert_eq!(full.len(), 6);
    let full_list: Vec<_> = full.iter().collect();

    let len = bytes.len();
    let mut cases: Vec<(String, Vec<u8>)> = Vec::new();
    for cut in [0, 8, 100, len / 3, len / 2, (3 * len) / 4, len - 1] {
        cases.push((format!("cut at {cut}"), bytes[..cut].to_vec()));
    }
    for at in [len / 4, len / 2, (4 * len) / 5] {
        let mut b = bytes.clone();
        b[at] ^= 0x10;
        cases.push((format!("bit flipped at {at}"), b));
    }
    cases.push(("garbage".into(), b"not a journal at all".to_vec()));
    let mut fewer = 0;
    for (name, data) in cases {
        let d = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        std::fs::write(d.path().join("journal-000001.mcap"), &data)
            .unwrap_or_else(|e| panic!("{e}"));
        let st = store(&s, Some(d.path()), vec![]).await;
        let r = st.start_report().clone();
        let got = contents(&st);
        st.stop();
        let f = &r.journal[0];
        assert!(f.damage.is_some(), "{name}: damage not reported: {f:?}");
        assert_eq!(
            f.skipped_bytes,
            data.len() as u64 - f.damage_offset.unwrap_or(0),
            "{name}"
        );
        // A prefix of the original worlds, in order and byte for byte.
        let got_list: Vec<_> = got.iter().collect();
        assert!(
            got_list.len() <= full_list.len() && got_list[..] == full_list[..got_list.len()],
            "{name}: not a prefix of the original worlds"
        );
        assert_eq!(r.worlds_from_journal, got.len() as u64, "{name}");
        if got.len() < full.len() {
            fewer += 1;
        }
        // The damaged file is left as it was; this run writes a new one beside it.
        assert_eq!(journal_files(d.path()).len(), 2, "{name}");
        let kept =
            std::fs::read(d.path().join("journal-000001.mcap")).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(kept, data, "{name}: the damaged file was changed");
    }
    assert!(fewer >= 5, "most cuts and flips should lose some worlds");
    close(s).await;
}

/// Segments and the summary of a world put before its job (what a replay at full speed can
/// do): the store holds the world and stores it when the job comes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_world_that_arrives_before_its_job_is_stored_when_the_job_comes() {
    let s = session().await;
    let keys = Keys::new(SPACE).unwrap_or_else(|e| panic!("{e}"));
    let st = store(&s, None, vec![]).await;
    put_world(&s, &keys, &world("early", 0, 42, 2)).await;
    until("the world to be held", || st.held_worlds() == 1).await;
    assert_eq!(st.world_count(), 0);
    put(&s, keys.job("early"), job("early", 1).encode_to_vec()).await;
    until("the held world to be stored", || st.world_count() == 1).await;
    let state = st.job_state("early").unwrap_or_else(|| panic!("no job"));
    assert!(state.closed && state.worlds_done == 1 && state.worlds_rejected == 0);
    assert_eq!(
        st.world(0).and_then(|w| w.done().ok()).map(|d| d.seed),
        Some(42)
    );
    st.stop();
    close(s).await;
}

/// A refined world stored as a difference (§4.5) comes back from the journal linked to its
/// parent, served and decoded the same.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refined_world_comes_back_from_the_journal_composed_over_its_parent() {
    use mwb_proto::v1::JobKind;
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let journal = dir.path().join("journal");
    let keys = Keys::new(SPACE).unwrap_or_else(|e| panic!("{e}"));
    let root = common::root();
    let (child, _) = common::child(7);
    // Two jobs and their states, then each world's segments, summary and job state.
    let messages = (root.0.len() + child.0.len() + 8) as u64;
    let s = session().await;
    let st = store(&s, Some(&journal), vec![]).await;
    for j in [
        common::job("s", JobKind::Sample, None),
        common::refine_job(0),
    ] {
        put(&s, keys.job(&j.id), j.encode_to_vec()).await;
    }
    until("the jobs", || {
        st.job_state("s").is_some() && st.job_state("r").is_some()
    })
    .await;
    put_world(&s, &keys, &root).await;
    until("the root world", || st.world_count() == 1).await;
    put_world(&s, &keys, &child).await;
    until("the refined world", || st.world_count() == 2).await;
    until("the journal's commits", || {
        st.journal_counters()
            .is_some_and(|c| c.messages >= messages)
    })
    .await;
    let before = st
        .world(1)
        .unwrap_or_else(|| panic!("world 1"))
        .message()
        .unwrap_or_else(|e| panic!("{e}"))
        .encode_to_vec();
    st.stop();
    close(s).await;

    let s = session().await;
    let st = store(&s, Some(&journal), vec![]).await;
    let w = st
        .world(1)
        .unwrap_or_else(|| panic!("world 1 after the restart"));
    assert!(w.is_layered());
    assert_eq!(w.parent.as_ref().map(|p| p.index), Some(0));
    let message = w.message().unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(message.encode_to_vec(), before);
    let motion = mwb_export::decode_world(&message).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(motion.tracks.len(), 5);
    st.stop();
    close(s).await;
}

/// Each world is journaled with the index the store browses it by — the one its sampler sent,
/// or the store's own where none came — so a restart takes every index from the journal
/// instead of building it again; and each is the one the store would build (the restarted
/// store here rebuilds and compares every one).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restart_takes_each_worlds_index_from_the_journal() {
    use mwb_proto::v1::JobKind;
    use mwb_sampler::{RunOptions, attach_index, run_world, segment_message, world_done};
    use std::ops::ControlFlow;
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let journal = dir.path().join("journal");
    let keys = Keys::new(SPACE).unwrap_or_else(|e| panic!("{e}"));
    let template = common::template();
    let worlds: Vec<(Vec<MotionSegment>, WorldDone)> = (1..=4u64)
        .map(|seed| {
            let mut segs = Vec::new();
            let summary = run_world(&template, seed, RunOptions::default(), &mut |s| {
                segs.push(segment_message("s", "n", seed, seed, s));
                ControlFlow::Continue(())
            })
            .unwrap_or_else(|e| panic!("{e}"));
            let mut done = world_done("s", "n", seed, &summary);
            // Two come with their sampler's index; the store builds the other two.
            if seed % 2 == 0 {
                attach_index(&mut done, &segs, &template);
                assert!(done.index.is_some());
            }
            (segs, done)
        })
        .collect();
    let messages = worlds.iter().map(|w| w.0.len() as u64 + 1).sum::<u64>() + 1;

    let s = session().await;
    let st = store(&s, Some(&journal), vec![]).await;
    let j = common::job("s", JobKind::Sample, None);
    put(&s, keys.job(&j.id), j.encode_to_vec()).await;
    until("the job", || st.job_state("s").is_some()).await;
    for w in &worlds {
        put_world(&s, &keys, w).await;
    }
    until("every world indexed", || st.indexed_count() == 4).await;
    until("the journal's commits", || {
        st.journal_counters()
            .is_some_and(|c| c.messages >= messages)
    })
    .await;
    assert_eq!(st.stats().indexes_sent, 2);
    let held = |st: &StoreHandle| -> Vec<Vec<u8>> {
        (0..4)
            .map(|i| {
                let w = st.world(i).unwrap_or_else(|| panic!("world {i}"));
                w.message()
                    .unwrap_or_else(|e| panic!("{e}"))
                    .encode_to_vec()
            })
            .collect()
    };
    let before = held(&st);
    st.stop();
    close(s).await;

    let s = session().await;
    let st = common::start_store(
        &s,
        StoreConfig {
            space: SPACE.into(),
            journal: Some(journal.clone()),
            verify_index_every: 1,
            ..Default::default()
        },
    )
    .await;
    assert_eq!((st.world_count(), st.indexed_count()), (4, 4));
    let stats = st.stats();
    assert_eq!(
        (
            stats.indexes_sent,
            stats.indexes_checked,
            stats.index_mismatches
        ),
        (4, 4, 0),
        "every index taken from the journal, each the one this store builds"
    );
    // The store holds each summary without its index, as before the restart.
    assert_eq!(held(&st), before);
    st.stop();
    close(s).await;
}
