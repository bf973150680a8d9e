//! The worker skeleton over a real zenoh session (one local peer, no network) with a kind whose
//! worlds are trivial: jobs are taken from announcements, worlds are published as segments then
//! summaries with the skeleton's fields filled in, a closed job stops, failing and refused
//! jobs are given up, malformed announcements are counted, statistics are published.

use mwb_core::keys::{Keys, role};
use mwb_node::{SegmentBody, WorkerConfig, WorkerKind, WorldTask, run_workers, segment_message};
use mwb_proto::v1::{
    Encoding, Job, JobKind, JobState, Message, MotionSegment, NodeStats, Scene, WorldDone,
};
use std::ops::ControlFlow;
use std::time::{Duration, Instant};
use zenoh::qos::CongestionControl;

/// Worlds of two segments; a scene named "fail" fails every world, "refuse" is refused.
struct Trivial;

#[derive(Debug, thiserror::Error)]
enum Refused {
    #[error("{0}")]
    Scene(String),
    #[error("no world today")]
    World,
    #[error("stopped by the caller")]
    Stopped,
}

impl WorkerKind for Trivial {
    const ROLE: &'static str = role::SAMPLER;
    const GIVE_UP_AFTER: u32 = 2;
    type Scene = String;
    type SceneError = Refused;
    type WorldError = Refused;

    fn takes(kind: JobKind) -> bool {
        kind == JobKind::Sample
    }

    fn prepare(&self, _job: &Job, scene: &Scene) -> Result<String, Refused> {
        if scene.name == "refuse" {
            Err(Refused::Scene("refused".into()))
        } else {
            Ok(scene.name.clone())
        }
    }

    fn run(
        &self,
        w: &WorldTask<'_>,
        scene: &String,
        emit: &mut dyn FnMut(MotionSegment) -> ControlFlow<()>,
    ) -> Result<WorldDone, Refused> {
        if scene == "fail" {
            return Err(Refused::World);
        }
        for seq in 0..2 {
            let body = SegmentBody {
                bodies: Vec::new(),
                seq,
                first_frame: seq * 10,
                frame_count: 10,
                body_count: 1,
                encoding: Encoding::SplineV1,
                payload: vec![7; 5],
            };
            if emit(segment_message(&w.job.id, w.node, w.counter, w.seed, body)).is_break() {
                return Err(Refused::Stopped);
            }
        }
        // Slow enough that the test's subscribers (which it drains only now and then) never
        // fill up, fast enough for a test.
        std::thread::sleep(Duration::from_millis(50));
        Ok(WorldDone {
            job_id: w.job.id.clone(),
            node_id: w.node.to_owned(),
            world_counter: w.counter,
            seed: w.seed,
            frame_count: 20,
            segment_count: 2,
            sim_steps: 20,
            ..Default::default()
        })
    }

    fn stopped(e: &Refused) -> bool {
        matches!(e, Refused::Stopped)
    }

    fn provenance(&self) -> String {
        "trivial-1".into()
    }
}

async fn session() -> zenoh::Session {
    let c = mwb_node::bus::isolated_config();
    tokio::time::timeout(Duration::from_secs(20), zenoh::open(c))
        .await
        .unwrap_or_else(|_| panic!("open timed out"))
        .unwrap_or_else(|e| panic!("{e}"))
}

async fn put(s: &zenoh::Session, key: String, bytes: Vec<u8>) {
    tokio::time::timeout(
        Duration::from_secs(10),
        s.put(key, bytes)
            .congestion_control(CongestionControl::Block),
    )
    .await
    .unwrap_or_else(|_| panic!("put timed out"))
    .unwrap_or_else(|e| panic!("{e}"));
}

fn job(id: &str, scene: &str, target: u32) -> Job {
    Job {
        id: id.into(),
        revision: 1,
        kind: JobKind::Sample as i32,
        scene: Some(Scene {
            name: scene.into(),
            content_hash: 0xabcd,
            ..Default::default()
        }),
        target_worlds: target,
        ..Default::default()
    }
}

async fn until(what: &str, mut f: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(20);
    while !f() {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn worlds_are_published_closed_jobs_stop_bad_jobs_are_given_up() {
    let s = session().await;
    let keys = Keys::new("nodetest").unwrap_or_else(|e| panic!("{e}"));
    let dones = s
        .declare_subscriber(keys.dones())
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let segs = s
        .declare_subscriber(keys.segments())
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let stats = s
        .declare_subscriber(keys.stats_all())
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let node = run_workers(
        s.clone(),
        WorkerConfig {
            space: "nodetest".into(),
            workers: 2,
            node_id: Some("w1".into()),
            refresh: Duration::from_millis(200),
            queue: 8,
        },
        Trivial,
    )
    .await
    .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(node.node_id(), "w1");

    put(&s, keys.job("ok"), job("ok", "fine", 3).encode_to_vec()).await;
    // No store here, so nobody says the job is done: the node keeps producing.
    let mut seen = Vec::new();
    while seen.len() < 3 {
        let sample = tokio::time::timeout(Duration::from_secs(20), dones.recv_async())
            .await
            .unwrap_or_else(|_| panic!("no WorldDone"))
            .unwrap_or_else(|e| panic!("{e}"));
        let d = WorldDone::decode(sample.payload().to_bytes().as_ref())
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            sample.key_expr().as_str(),
            keys.done("ok", "w1", d.world_counter)
        );
        assert_eq!(d.provenance, "trivial-1");
        assert_eq!(d.scene_hash, 0xabcd);
        assert_eq!(
            d.seed,
            mwb_core::rng::world_seed("ok", "w1", d.world_counter)
        );
        seen.push(d.world_counter);
    }
    // Segments come before their summary, on their own keys.
    let sample = segs
        .try_recv()
        .unwrap_or_else(|e| panic!("{e}"))
        .unwrap_or_else(|| panic!("segments were not published"));
    let seg = MotionSegment::decode(sample.payload().to_bytes().as_ref())
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(
        sample.key_expr().as_str(),
        keys.segment("ok", "w1", seg.world_counter, seg.seq)
    );
    assert_eq!(seg.crc32, crc32fast::hash(&[7; 5]));

    // The stores close the job: the node stops taking its worlds.
    let closed = JobState {
        job_id: "ok".into(),
        worlds_done: 3,
        target_worlds: 3,
        closed: true,
        ..Default::default()
    };
    put(&s, keys.job_state("ok"), closed.encode_to_vec()).await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let after_close = node.worlds();
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(node.worlds(), after_close, "worlds of a closed job");
    assert!(node.steps() >= 20 * after_close);

    // Failing worlds: given up after GIVE_UP_AFTER in a row. A refused scene: never run.
    put(&s, keys.job("bad"), job("bad", "fail", 100).encode_to_vec()).await;
    put(&s, keys.job("no"), job("no", "refuse", 100).encode_to_vec()).await;
    until("two failed worlds", || node.failed() >= 2).await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(node.failed(), 2, "a given-up job was run again");
    assert_eq!(node.worlds(), after_close);

    // Garbage on the job key is dropped and counted.
    put(&s, keys.job("junk"), vec![0x0a, 0xff]).await;
    until("a malformed job counted", || node.malformed() == 1).await;

    // Statistics every second, with the kind's role and the node's counters.
    let deadline = Instant::now() + Duration::from_secs(10);
    let st = loop {
        assert!(Instant::now() < deadline, "no stats");
        let sample = tokio::time::timeout(Duration::from_secs(5), stats.recv_async())
            .await
            .unwrap_or_else(|_| panic!("no stats"))
            .unwrap_or_else(|e| panic!("{e}"));
        let st = NodeStats::decode(sample.payload().to_bytes().as_ref())
            .unwrap_or_else(|e| panic!("{e}"));
        if st.malformed == 1 {
            break st;
        }
    };
    assert_eq!((st.role.as_str(), st.node_id.as_str()), ("sampler", "w1"));
    assert_eq!(st.workers, 2);
    assert_eq!(st.worlds, after_close);
    assert_eq!(st.bytes, 10 * after_close);
    assert_eq!(st.pid, std::process::id());

    tokio::time::timeout(Duration::from_secs(10), node.stop())
        .await
        .unwrap_or_else(|_| panic!("stop timed out"));
    let _ = tokio::time::timeout(Duration::from_secs(5), s.close()).await;
}
