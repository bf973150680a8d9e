//! Recording and replay over a real zenoh bus (peer sessions on 127.0.0.1 TCP, no scouting):
//! puts recorded with their keys and bytes and replayed in order at the recorded pace (or
//! faster) into another space; a disk that cannot keep up either loses messages loudly and
//! counts them or makes the bus wait; and a sampled session replayed into a fresh store gives
//! it the same worlds, byte for byte.

use mwb_proto::v1::{
    Encoding, Job, JobKind, JobState, Message, MotionSegment, NodeStats, Quality, Scene, WorldDone,
};
use mwb_record::{
    Family, Overflow, RecorderConfig, ReplayConfig, Speed, WriterOptions, read_recording, replay,
    run_recorder,
};
use std::future::pending;
use std::path::Path;
use std::time::{Duration, Instant};
use zenoh::qos::CongestionControl;

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .unwrap()
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
        serde_json::to_string(&listen).unwrap(),
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
        .expect("open timed out")
        .unwrap()
}

async fn close(s: zenoh::Session) {
    let _ = tokio::time::timeout(Duration::from_secs(5), s.close()).await;
}

async fn put(s: &zenoh::Session, key: &str, bytes: Vec<u8>) {
    tokio::time::timeout(
        Duration::from_secs(20),
        s.put(key, bytes)
            .congestion_control(CongestionControl::Block),
    )
    .await
    .expect("put timed out")
    .unwrap();
}

/// Waits until `f` holds (60 s at most).
async fn until(what: &str, mut f: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(60);
    while !f() {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Waits until `s` knows a subscriber for `key` (a put before that is not routed to it).
async fn until_subscribed(s: &zenoh::Session, key: &str) {
    let p = s.declare_publisher(key.to_owned()).await.unwrap();
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let m = tokio::time::timeout(Duration::from_secs(5), p.matching_status())
            .await
            .expect("matching status timed out")
            .unwrap();
        if m.matching() {
            return;
        }
        assert!(Instant::now() < deadline, "no subscriber for {key}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

fn recorder_config(space: &str, out: &Path) -> RecorderConfig {
    RecorderConfig {
        space: space.into(),
        out: out.to_owned(),
        node_id: Some(format!("rec-{space}")),
        ..Default::default()
    }
}

/// The messages of a small session in space `space`: (key, payload).
fn small_session(space: &str) -> Vec<(String, Vec<u8>)> {
    let k = |rest: &str| format!("mwb/{space}/{rest}");
    let job = Job {
        id: "j1".into(),
        revision: 1,
        target_worlds: 1,
        created_unix_ms: 1_600_000_000_000,
        ..Default::default()
    };
    let mut v = vec![(k("job/j1"), job.encode_to_vec())];
    for seq in 0..2u32 {
        let seg = MotionSegment {
            job_id: "j1".into(),
            node_id: "n1".into(),
            seq,
            payload: vec![seq as u8; 300],
            ..Default::default()
        };
        v.push((k(&format!("seg/j1/n1/0/{seq}")), seg.encode_to_vec()));
    }
    let done = WorldDone {
        job_id: "j1".into(),
        node_id: "n1".into(),
        segment_count: 2,
        ..Default::default()
    };
    v.push((k("done/j1/n1/0"), done.encode_to_vec()));
    let st = JobState {
        job_id: "j1".into(),
        worlds_done: 1,
        closed: true,
        ..Default::default()
    };
    v.push((k("job/j1/state"), st.encode_to_vec()));
    let stats = NodeStats {
        node_id: "n1".into(),
        role: "sampler".into(),
        ..Default::default()
    };
    v.push((k("stats/sampler/n1"), stats.encode_to_vec()));
    v.push((k("browse/s1"), br#"{"list": {"k": 2}}"#.to_vec()));
    // Not a JobState: recorded as raw, replayed as it was.
    v.push((k("job/j2/state"), vec![0x18, 0xff]));
    v
}

/// Collects every put under `mwb/<space>/**` on `s`.
async fn collector(
    s: &zenoh::Session,
    space: &str,
) -> zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>> {
    s.declare_subscriber(format!("mwb/{space}/**"))
        .await
        .unwrap()
}

async fn drain(
    sub: &zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    n: usize,
) -> Vec<(String, Vec<u8>)> {
    let mut got = Vec::new();
    while got.len() < n {
        let s = tokio::time::timeout(Duration::from_secs(20), sub.recv_async())
            .await
            .unwrap_or_else(|_| panic!("only {} of {n} replayed messages arrived", got.len()))
            .unwrap();
        got.push((
            s.key_expr().as_str().to_owned(),
            s.payload().to_bytes().into_owned(),
        ));
    }
    got
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn puts_are_recorded_and_replayed_in_order_at_the_recorded_pace_into_another_space() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("s.mcap");
    let port = free_port();
    let a = session(Some(port), None).await;
    let b = session(None, Some(port)).await;

    let rec = run_recorder(&a, recorder_config("r1", &out)).await.unwrap();
    until_subscribed(&b, "mwb/r1/seg/x/y/0/0").await;
    let msgs = small_session("r1");
    let gap = Duration::from_millis(100);
    for (key, payload) in &msgs {
        put(&b, key, payload.clone()).await;
        tokio::time::sleep(gap).await;
    }
    until("the recorder to write everything", || {
        rec.written() == msgs.len() as u64
    })
    .await;
    let sum = tokio::time::timeout(Duration::from_secs(20), rec.finish())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(sum.received, msgs.len() as u64);
    assert_eq!(sum.dropped, 0);
    assert!(sum.write_error.is_none());
    assert_eq!(sum.written.messages, msgs.len() as u64);
    assert_eq!(sum.written.by_family[&Family::Raw], 1);
    assert_eq!(sum.written.by_family[&Family::Browse], 1);
    assert_eq!(sum.file_bytes, std::fs::metadata(&out).unwrap().len());

    let back = read_recording(&out).unwrap();
    assert!(back.error.is_none() && back.stats.complete);
    let got: Vec<(String, Vec<u8>)> = back
        .messages
        .iter()
        .map(|m| (m.key.clone(), m.payload.clone()))
        .collect();
    assert_eq!(got, msgs);
    assert_eq!(back.info.as_ref().unwrap().space, "r1");
    assert_eq!(back.end.as_ref().unwrap()["not_written"], "0");
    let span = Duration::from_nanos(
        back.messages.last().unwrap().log_time_ns - back.messages[0].log_time_ns,
    );
    assert!(span >= gap * (msgs.len() as u32 - 1), "span {span:?}");

    // Back onto the bus, into another space, at three speeds.
    let sub = collector(&a, "r2").await;
    let mut took = Vec::new();
    for speed in [Speed::Factor(1.0), Speed::Factor(4.0), Speed::Max] {
        let cfg = ReplayConfig {
            path: out.clone(),
            speed,
            space: "r2".into(),
            wait_for_subscribers: Duration::from_secs(10),
        };
        let start = Instant::now();
        let s = tokio::time::timeout(Duration::from_secs(30), replay(&b, &cfg, pending()))
            .await
            .unwrap()
            .unwrap();
        let t = start.elapsed();
        assert!(s.subscribers_seen);
        assert!(s.damage.is_none());
        assert_eq!(s.published, msgs.len() as u64);
        assert_eq!(s.recorded_space.as_deref(), Some("r1"));
        let replayed = drain(&sub, msgs.len()).await;
        let expected: Vec<(String, Vec<u8>)> = msgs
            .iter()
            .map(|(k, p)| (k.replacen("mwb/r1/", "mwb/r2/", 1), p.clone()))
            .collect();
        assert_eq!(replayed, expected, "speed {speed}");
        took.push(t);
    }
    assert!(
        took[0] >= span,
        "speed 1 took {:?}, recorded {span:?}",
        took[0]
    );
    assert!(took[1] >= span / 4, "speed 4 took {:?}", took[1]);
    assert!(took[1] < took[0] && took[2] < took[0], "{took:?}");
    drop(sub);
    close(b).await;
    close(a).await;
}

/// Incompressible bytes (xorshift), so that zstd at its slowest level is the bottleneck.
fn noise(n: usize, mut x: u64) -> Vec<u8> {
    (0..n)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x as u8
        })
        .collect()
}

/// A burst of 1 MiB segments against a queue of one message and the slowest zstd level.
async fn burst(
    overflow: Overflow,
    space: &str,
) -> (mwb_record::RecordSummary, mwb_record::Recovered) {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("burst.mcap");
    let port = free_port();
    let a = session(Some(port), None).await;
    let b = session(None, Some(port)).await;
    let cfg = RecorderConfig {
        queue_messages: 1,
        overflow,
        writer: WriterOptions {
            compression_level: 19,
            ..Default::default()
        },
        ..recorder_config(space, &out)
    };
    let rec = run_recorder(&a, cfg).await.unwrap();
    until_subscribed(&b, &format!("mwb/{space}/seg/x/y/0/0")).await;
    let n = 8u32;
    for seq in 0..n {
        let seg = MotionSegment {
            job_id: "j".into(),
            node_id: "n".into(),
            seq,
            payload: noise(1 << 20, u64::from(seq) + 1),
            ..Default::default()
        };
        put(
            &b,
            &format!("mwb/{space}/seg/j/n/0/{seq}"),
            seg.encode_to_vec(),
        )
        .await;
    }
    until("every put to reach the recorder", || {
        rec.received() == u64::from(n)
    })
    .await;
    let sum = tokio::time::timeout(Duration::from_secs(60), rec.finish())
        .await
        .unwrap()
        .unwrap();
    let back = read_recording(&out).unwrap();
    close(b).await;
    close(a).await;
    (sum, back)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_slow_disk_loses_messages_only_counted_and_reported() {
    let (sum, back) = burst(Overflow::Drop, "d1").await;
    assert_eq!(sum.received, 8);
    assert!(sum.dropped > 0, "the writer kept up: {sum:?}");
    assert_eq!(sum.written.messages + sum.dropped, 8);
    assert_eq!(sum.dropped_by_family[&Family::Segment], sum.dropped);
    assert!(sum.dropped_bytes > sum.dropped * (1 << 20));
    // The file is whole and says what it lacks.
    assert!(back.error.is_none() && back.stats.complete);
    assert_eq!(back.messages.len() as u64, sum.written.messages);
    let end = back.end.unwrap();
    assert_eq!(end["not_written"], sum.dropped.to_string());
    assert_eq!(end["not_written.seg"], sum.dropped.to_string());
    assert_eq!(end["received"], "8");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_slow_disk_in_lossless_mode_makes_the_bus_wait_and_loses_nothing() {
    let (sum, back) = burst(Overflow::Block, "d2").await;
    assert_eq!(sum.received, 8);
    assert_eq!(sum.dropped, 0);
    assert_eq!(sum.written.messages, 8);
    assert!(sum.bus_waited > Duration::ZERO);
    assert!(back.error.is_none());
    let seqs: Vec<u32> = back
        .messages
        .iter()
        .map(|m| MotionSegment::decode(m.payload.as_slice()).unwrap().seq)
        .collect();
    assert_eq!(seqs, (0..8).collect::<Vec<_>>());
    assert_eq!(back.end.unwrap()["not_written"], "0");
}

fn tumble_job(id: &str, worlds: u32) -> Job {
    let text = include_str!("../../scenes/tumble.toml");
    Job {
        id: id.into(),
        revision: 1,
        kind: JobKind::Sample as i32,
        scene: Some(Scene {
            revision: 1,
            name: "tumble".into(),
            toml: text.into(),
            content_hash: mwb_core::content_hash(text),
        }),
        target_worlds: worlds,
        created_unix_ms: 1_700_000_000_000,
        encoding: Encoding::SplineV1 as i32,
        quality: Quality::Standard as i32,
        ..Default::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_replayed_session_gives_a_fresh_store_the_same_worlds_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("demo.mcap");
    // MWB_RECORD_E2E_WORLDS / MWB_RECORD_E2E_OUT: a larger session, kept for other tools
    // (the Python `mcap` cross-check in the report was made from such a copy).
    let worlds: u32 = std::env::var("MWB_RECORD_E2E_WORLDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(3);

    // The recorded session: a store, a sampler and the recorder on one peer session.
    let a = session(Some(free_port()), None).await;
    let store = mwb_store::run_store(
        a.clone(),
        mwb_store::StoreConfig {
            space: "e1".into(),
            node_id: Some("store-e1".into()),
            ..Default::default()
        },
    )
    .await
    .unwrap();
    let rec = run_recorder(&a, recorder_config("e1", &out)).await.unwrap();
    let sampler = mwb_sampler::run_sampler(
        a.clone(),
        mwb_sampler::SamplerConfig {
            space: "e1".into(),
            workers: 1,
            node_id: Some("sampler-e1".into()),
            ..Default::default()
        },
    )
    .await
    .unwrap();
    let job = tumble_job("tumble-rec", worlds);
    put(&a, "mwb/e1/job/tumble-rec", job.encode_to_vec()).await;
    until("the recorded store to close the job", || {
        store.job_state("tumble-rec").is_some_and(|s| s.closed)
    })
    .await;
    tokio::time::timeout(Duration::from_secs(60), sampler.stop())
        .await
        .unwrap();
    // The last job state and a round of stats.
    tokio::time::sleep(Duration::from_millis(1200)).await;
    let sum = tokio::time::timeout(Duration::from_secs(20), rec.finish())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(sum.dropped, 0);
    assert!(sum.write_error.is_none());
    let stored = store.world_count();
    assert_eq!(stored, worlds as usize);
    let provenance = mwb_sampler::world::provenance();
    let back = read_recording(&out).unwrap();
    assert!(back.error.is_none());
    assert_eq!(back.end.as_ref().unwrap()["provenance"], provenance);
    assert_eq!(
        back.end.as_ref().unwrap()["scene_hashes"],
        format!(
            "{:016x}",
            mwb_core::content_hash(include_str!("../../scenes/tumble.toml"))
        )
    );

    // A fresh store in another space, on another pair of sessions, fed by the replay.
    let port = free_port();
    let c = session(Some(port), None).await;
    let d = session(None, Some(port)).await;
    let fresh = mwb_store::run_store(
        c.clone(),
        mwb_store::StoreConfig {
            space: "e2".into(),
            node_id: Some("store-e2".into()),
            ..Default::default()
        },
    )
    .await
    .unwrap();
    let cfg = ReplayConfig {
        path: out.clone(),
        speed: Speed::Max,
        space: "e2".into(),
        ..Default::default()
    };
    let r = tokio::time::timeout(Duration::from_secs(60), replay(&d, &cfg, pending()))
        .await
        .unwrap()
        .unwrap();
    assert!(r.subscribers_seen);
    // Everything is replayed but the recorded store's counts of its own worlds (a store that
    // takes in the replay counts what it stores).
    assert!(
        r.skipped_keys >= 1,
        "the store's counts were recorded: {r:?}"
    );
    assert_eq!(r.published + r.skipped_keys, sum.written.messages);
    until("the fresh store to hold every world", || {
        fresh.world_count() == stored
    })
    .await;
    let st = fresh.job_state("tumble-rec").unwrap();
    assert!(st.closed);
    assert_eq!(st.worlds_done, worlds);
    let mut store_bytes = 0;
    // Matched by (node, counter), not by store index: a store numbers worlds as they complete,
    // and two worlds finishing together may complete in either order in each store.
    let key = |w: &mwb_store::StoredWorld| {
        let done = w.done().unwrap_or_else(|e| panic!("{e}"));
        (done.node_id, done.world_counter)
    };
    let fresh_worlds: std::collections::HashMap<_, _> = (0..stored as u32)
        .map(|i| {
            let w = fresh.world(i).unwrap();
            (key(&w), w)
        })
        .collect();
    for i in 0..stored as u32 {
        let w1 = store.world(i).unwrap();
        let w2 = fresh_worlds
            .get(&key(&w1))
            .unwrap_or_else(|| panic!("world {i} ({:?}) not replayed", key(&w1)));
        assert_eq!(w1.job_id, w2.job_id);
        let (d1, segs1) = w1.decode().unwrap_or_else(|e| panic!("{e}"));
        let (d2, segs2) = w2.decode().unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(d1.encode_to_vec(), d2.encode_to_vec(), "world {i}");
        assert_eq!(segs1.len(), segs2.len(), "world {i}");
        for (s1, s2) in segs1.iter().zip(&segs2) {
            assert_eq!(
                s1.encode_to_vec(),
                s2.encode_to_vec(),
                "world {i} seg {}",
                s1.seq
            );
        }
        store_bytes += w1.bytes;
    }
    let seg_msgs = back.stats.by_family[&Family::Segment];
    eprintln!(
        "recording: {} bytes, {} messages ({} segments), {} worlds: {:.0} bytes/world on disk, \
         {:.0} bytes/world in the store; replay at max {:.2} s",
        sum.file_bytes,
        sum.written.messages,
        seg_msgs,
        stored,
        sum.file_bytes as f64 / stored as f64,
        store_bytes as f64 / stored as f64,
        r.seconds
    );
    if let Ok(keep) = std::env::var("MWB_RECORD_E2E_OUT") {
        std::fs::copy(&out, keep).unwrap();
    }
    fresh.stop();
    store.stop();
    close(d).await;
    close(c).await;
    close(a).await;
}
