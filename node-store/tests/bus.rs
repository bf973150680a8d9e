//! The store over a real zenoh bus (two peer sessions on 127.0.0.1 TCP, no scouting): garbage
//! and corrupted messages are dropped and counted, a good world is stored and served, a job's
//! state closes at its target.

use mwb_core::keys::Keys;
use mwb_proto::v1::{Job, JobState, Message, MotionSegment, NodeStats, World, WorldDone};
use mwb_store::{StoreConfig, run_store};
use std::time::{Duration, Instant};
use zenoh::qos::CongestionControl;

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .unwrap_or_else(|e| panic!("{e}"))
}

async fn session(listen: Option<u16>, connect: Option<u16>) -> zenoh::Session {
    let mut c = zenoh::Config::default();
    let set = |c: &mut zenoh::Config, k: &str, v: String| {
        c.insert_json5(k, &v).unwrap_or_else(|e| panic!("{k}: {e}"))
    };
    set(&mut c, "mode", "\"peer\"".into());
    set(&mut c, "scouting/multicast/enabled", "false".into());
    set(&mut c, "scouting/gossip/enabled", "false".into());
    let listen: Vec<String> = listen
        .map(|p| format!("tcp/127.0.0.1:{p}"))
        .into_iter()
        .collect();
    set(
        &mut c,
        "listen/endpoints",
        serde_json::to_string(&listen).unwrap_or_default(),
    );
    if let Some(p) = connect {
        set(
            &mut c,
            "connect/endpoints",
            format!("[\"tcp/127.0.0.1:{p}\"]"),
        );
        set(&mut c, "connect/exit_on_failure", "true".into());
    }
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

async fn get_one<T: Message + Default>(s: &zenoh::Session, key: String) -> Option<T> {
    let replies = tokio::time::timeout(
        Duration::from_secs(10),
        s.get(key).timeout(Duration::from_secs(3)),
    )
    .await
    .unwrap_or_else(|_| panic!("get timed out"))
    .unwrap_or_else(|e| panic!("{e}"));
    while let Ok(Ok(r)) = tokio::time::timeout(Duration::from_secs(5), replies.recv_async()).await {
        if let Ok(sample) = r.result() {
            return T::decode(sample.payload().to_bytes().as_ref()).ok();
        }
    }
    None
}

fn world(job: &str, counter: u64, seed: u64) -> (Vec<MotionSegment>, WorldDone) {
    let segs: Vec<MotionSegment> = (0..2u32)
        .map(|i| {
            let payload = vec![7u8 + i as u8; 64];
            MotionSegment {
                job_id: job.into(),
                node_id: "sampler-a".into(),
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
        node_id: "sampler-a".into(),
        world_counter: counter,
        seed,
        frame_count: 20,
        segment_count: 2,
        impacts: vec![1],
        ..Default::default()
    };
    (segs, done)
}

async fn until<F: AsyncFnMut() -> bool>(what: &str, mut f: F) {
    let deadline = Instant::now() + Duration::from_secs(20);
    while !f().await {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_and_corrupt_messages_are_counted_good_worlds_stored() {
    let port = free_port();
    let store_session = session(Some(port), None).await;
    let client = session(None, Some(port)).await;
    let space = "storetest";
    let keys = Keys::new(space).unwrap_or_else(|e| panic!("{e}"));
    let store = run_store(
        store_session.clone(),
        StoreConfig {
            space: space.into(),
            ..Default::default()
        },
    )
    .await
    .unwrap_or_else(|e| panic!("{e}"));

    let job = Job {
        id: "j1".into(),
        revision: 1,
        target_worlds: 1,
        ..Default::default()
    };
    // Re-announce until the store answers: a put made before the store's subscriptions have
    // reached this session is routed nowhere (zenoh routes to known subscribers only).
    until("job state", async || {
        put(&client, keys.job("j1"), job.encode_to_vec()).await;
        get_one::<JobState>(&client, keys.job_state("j1"))
            .await
            .is_some()
    })
    .await;

    // Garbage on every ingest key.
    put(&client, keys.segment("j1", "x", 0, 0), vec![0xff; 9]).await;
    put(&client, keys.done("j1", "x", 0), vec![0xff, 0x01]).await;
    put(&client, keys.job("bad"), vec![0x0a, 0xff]).await;
    // A world with one corrupted segment.
    let (mut segs, done) = world("j1", 1, 100);
    segs[1].payload[3] ^= 1;
    for s in &segs {
        put(
            &client,
            keys.segment("j1", "sampler-a", 1, s.seq),
            s.encode_to_vec(),
        )
        .await;
    }
    put(
        &client,
        keys.done("j1", "sampler-a", 1),
        done.encode_to_vec(),
    )
    .await;
    // A good world.
    let (segs, done) = world("j1", 2, 200);
    for s in &segs {
        put(
            &client,
            keys.segment("j1", "sampler-a", 2, s.seq),
            s.encode_to_vec(),
        )
        .await;
    }
    put(
        &client,
        keys.done("j1", "sampler-a", 2),
        done.encode_to_vec(),
    )
    .await;

    until("job closed", async || {
        get_one::<JobState>(&client, keys.job_state("j1"))
            .await
            .is_some_and(|s| s.closed && s.worlds_done == 1)
    })
    .await;
    let stats: NodeStats = get_one(&client, keys.store_stats())
        .await
        .unwrap_or_else(|| panic!("no stats"));
    assert_eq!(stats.malformed, 3, "{stats:?}");
    assert_eq!(stats.crc_failures, 1, "{stats:?}");
    assert_eq!(stats.worlds, 1);
    let state: JobState = get_one(&client, keys.job_state("j1"))
        .await
        .unwrap_or_else(|| panic!("no state"));
    assert_eq!(state.worlds_rejected, 1);

    let w: World = get_one(&client, keys.world(0))
        .await
        .unwrap_or_else(|| panic!("world 0 not served"));
    assert_eq!(w.done.map(|d| d.seed), Some(200));
    assert_eq!(w.segments, segs);
    assert!(get_one::<World>(&client, keys.world(1)).await.is_none());

    store.stop();
    let _ = tokio::time::timeout(Duration::from_secs(3), client.close()).await;
    let _ = tokio::time::timeout(Duration::from_secs(3), store_session.close()).await;
}
