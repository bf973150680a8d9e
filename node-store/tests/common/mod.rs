//! A sampled world and a refined child of it (§4.5) as samplers send them, for the tests of
//! refined worlds stored as differences (`refined.rs`, `journal.rs`); and the bus helpers of
//! the tests that run a store on a session of their own (`journal.rs`, `scenes.rs`): every
//! await under a timeout.
#![allow(dead_code)]

use mwb_core::scene::{SceneTemplate, builtin};
use mwb_proto::v1::{Job, JobKind, MotionSegment, Refinement, Scene, WorldDone};
use mwb_sampler::node::{lineage_to_wire, refined_done};
use mwb_sampler::refine::{BranchAt, Lineage, regenerate};
use mwb_sampler::{RunOptions, run_world, segment_message, world_done};
use std::ops::ControlFlow;
use std::time::{Duration, Instant};
use zenoh::qos::CongestionControl;

pub const ROOT_SEED: u64 = 0x5eed;
pub const BRANCH: u32 = 150;

pub fn template() -> SceneTemplate {
    SceneTemplate::parse(builtin::TUMBLE, "tumble.toml").unwrap_or_else(|e| panic!("{e}"))
}

pub fn job(id: &str, kind: JobKind, refine: Option<Refinement>) -> Job {
    Job {
        id: id.into(),
        revision: 1,
        kind: kind as i32,
        target_worlds: 10,
        scene: Some(Scene {
            toml: builtin::TUMBLE.into(),
            ..Default::default()
        }),
        refine,
        ..Default::default()
    }
}

/// The root world (job `s`, seed [`ROOT_SEED`]) as a sampler sends it.
pub fn root() -> (Vec<MotionSegment>, WorldDone) {
    let mut segs = Vec::new();
    let summary = run_world(&template(), ROOT_SEED, RunOptions::default(), &mut |s| {
        segs.push(segment_message("s", "n", 0, ROOT_SEED, s));
        ControlFlow::Continue(())
    })
    .unwrap_or_else(|e| panic!("{e}"));
    (segs, world_done("s", "n", 0, &summary))
}

/// Child `seed` of the root world refining the crate (body 0) from [`BRANCH`]: as a sampler
/// sends it (a difference), and the same world recorded whole.
pub fn child(seed: u64) -> ((Vec<MotionSegment>, WorldDone), Vec<MotionSegment>) {
    let parent = regenerate(
        &template(),
        &Lineage::root(ROOT_SEED),
        &BranchAt::Frame(BRANCH),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let mut own = Vec::new();
    let refined = parent
        .refine(&[0], seed, RunOptions::default(), &mut |s| {
            own.push(segment_message("r", "n", seed, seed, s));
            ControlFlow::Continue(())
        })
        .unwrap_or_else(|e| panic!("{e}"));
    let mut whole = Vec::new();
    parent
        .refine_whole(&[0], seed, RunOptions::default(), &mut |s| {
            whole.push(segment_message("w", "n", seed, seed, s));
            ControlFlow::Continue(())
        })
        .unwrap_or_else(|e| panic!("{e}"));
    ((own, refined_done("r", "n", seed, "s", &refined)), whole)
}

pub fn refine_job(parent_world: u32) -> Job {
    job(
        "r",
        JobKind::Refine,
        Some(Refinement {
            parent_job: "s".into(),
            parent_world,
            parent: Some(lineage_to_wire("s", &Lineage::root(ROOT_SEED))),
            objects: vec![0],
            branch_frame: BRANCH,
            parent_scene: None,
        }),
    )
}

/// A session of its own (peer, no listen, no connect, no scouting): puts and queries reach a
/// store running on it.
pub async fn session() -> zenoh::Session {
    let c = mwb_node::bus::isolated_config();
    tokio::time::timeout(Duration::from_secs(20), zenoh::open(c))
        .await
        .unwrap_or_else(|_| panic!("open timed out"))
        .unwrap_or_else(|e| panic!("{e}"))
}

pub async fn close(s: zenoh::Session) {
    tokio::time::timeout(Duration::from_secs(10), s.close())
        .await
        .unwrap_or_else(|_| panic!("close timed out"))
        .unwrap_or_else(|e| panic!("{e}"));
}

pub async fn put(s: &zenoh::Session, key: String, bytes: Vec<u8>) {
    tokio::time::timeout(
        Duration::from_secs(10),
        s.put(key, bytes)
            .congestion_control(CongestionControl::Block),
    )
    .await
    .unwrap_or_else(|_| panic!("put timed out"))
    .unwrap_or_else(|e| panic!("{e}"));
}

pub async fn until(what: &str, mut f: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(30);
    while !f() {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Every answer to a get on `key` within `wait`: a reply's payload, or an error reply's
/// message.
pub async fn ask(s: &zenoh::Session, key: String, wait: Duration) -> Vec<Result<Vec<u8>, String>> {
    let replies = tokio::time::timeout(Duration::from_secs(10), s.get(key).timeout(wait))
        .await
        .unwrap_or_else(|_| panic!("get timed out"))
        .unwrap_or_else(|e| panic!("{e}"));
    let mut answers = Vec::new();
    // The channel closes once every queryable answered, or when `wait` has passed.
    while let Ok(Ok(r)) =
        tokio::time::timeout(wait + Duration::from_secs(5), replies.recv_async()).await
    {
        answers.push(match r.result() {
            Ok(sample) => Ok(sample.payload().to_bytes().into_owned()),
            Err(e) => Err(String::from_utf8_lossy(&e.payload().to_bytes()).into_owned()),
        });
    }
    answers
}

/// Starts a store on `s` under a name of its own (stores follow each other on one session):
/// `cfg` with a fresh `node_id`.
pub async fn start_store(
    s: &zenoh::Session,
    cfg: mwb_store::StoreConfig,
) -> mwb_store::StoreHandle {
    use std::sync::atomic::{AtomicU32, Ordering};
    static N: AtomicU32 = AtomicU32::new(0);
    let node_id = format!("store{}", N.fetch_add(1, Ordering::Relaxed));
    tokio::time::timeout(
        Duration::from_secs(60),
        mwb_store::run_store(
            s.clone(),
            mwb_store::StoreConfig {
                node_id: Some(node_id),
                ..cfg
            },
        ),
    )
    .await
    .unwrap_or_else(|_| panic!("store start timed out"))
    .unwrap_or_else(|e| panic!("{e}"))
}
