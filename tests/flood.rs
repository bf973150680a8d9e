//! The memory cap under a flood: a store whose cap holds a few hundred worlds, a sampler, a job
//! of far more. Once the store is full the sampler pauses — back-pressure read from the stores'
//! statistics — instead of computing worlds that would be refused; the store holds no more than
//! its cap; and it keeps answering queries.

use mwb_core::keys::Keys;
use mwb_proto::v1::{Message, World};
use std::time::{Duration, Instant};
use zenoh::qos::CongestionControl;

/// A session of its own (isolated: no listen, no scouting): the store and the sampler share it.
async fn session() -> zenoh::Session {
    let c = mwb_node::bus::isolated_config();
    tokio::time::timeout(Duration::from_secs(20), zenoh::open(c))
        .await
        .unwrap_or_else(|_| panic!("open timed out"))
        .unwrap_or_else(|e| panic!("{e}"))
}

async fn until(
    what: &str,
    limit: Duration,
    mut f: impl FnMut() -> bool,
    state: impl Fn() -> String,
) {
    let deadline = Instant::now() + limit;
    while !f() {
        assert!(
            Instant::now() < deadline,
            "timed out waiting for {what}: {}",
            state()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_store_pauses_the_samplers_and_keeps_answering() {
    let s = session().await;
    let space = format!("flood{}", std::process::id());
    let keys = Keys::new(&space).unwrap_or_else(|e| panic!("{e}"));
    let cap = 1u64 << 20;
    let store = tokio::time::timeout(
        Duration::from_secs(30),
        mwb_store::run_store(
            s.clone(),
            mwb_store::StoreConfig {
                space: space.clone(),
                memory_cap_bytes: cap,
                ..Default::default()
            },
        ),
    )
    .await
    .unwrap_or_else(|_| panic!("store start timed out"))
    .unwrap_or_else(|e| panic!("{e}"));
    let sampler = tokio::time::timeout(
        Duration::from_secs(30),
        mwb_sampler::run_sampler(
            s.clone(),
            mwb_sampler::SamplerConfig {
                space: space.clone(),
                workers: 1,
                ..Default::default()
            },
        ),
    )
    .await
    .unwrap_or_else(|_| panic!("sampler start timed out"))
    .unwrap_or_else(|e| panic!("{e}"));
    let job = mwb::client::make_job(
        "tumble",
        mwb_core::scene::builtin::TUMBLE,
        1_000_000,
        0,
        Some("flood".into()),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    tokio::time::timeout(
        Duration::from_secs(10),
        s.put(keys.job("flood"), job.encode_to_vec())
            .congestion_control(CongestionControl::Block),
    )
    .await
    .unwrap_or_else(|_| panic!("put timed out"))
    .unwrap_or_else(|e| panic!("{e}"));

    // Full as the workers read it (`mwb_node::room`): a refusal for memory, or within
    // FULL_FRACTION of the cap. Waiting for a refusal alone raced: a store that reaches 98 %
    // between two reports pauses the sampler before any world is refused.
    until(
        "the store to be full",
        Duration::from_secs(120),
        || {
            let st = store.stats();
            st.refused_memory > 0
                || st.memory_bytes as f64 >= mwb_node::room::FULL_FRACTION * cap as f64
        },
        || {
            let st = store.stats();
            format!(
                "sampler {} worlds; store {} worlds, {} bytes, {} refused for memory",
                sampler.worlds(),
                store.world_count(),
                st.memory_bytes,
                st.refused_memory
            )
        },
    )
    .await;
    // The store's next statistics (every second) reach the sampler and pause it.
    tokio::time::sleep(Duration::from_secs(3)).await;
    let (worlds, refused) = (sampler.worlds(), store.stats().refused_memory);
    tokio::time::sleep(Duration::from_secs(4)).await;
    let (worlds_after, refused_after) = (sampler.worlds(), store.stats().refused_memory);
    // Unpaused, one worker computes a tumble world in a few milliseconds: hundreds in 4 s.
    assert!(
        worlds_after - worlds <= 4,
        "the sampler went on: {worlds} → {worlds_after} worlds in 4 s"
    );
    assert!(
        refused_after - refused <= 4,
        "refusals went on: {refused} → {refused_after}"
    );
    let stats = store.stats();
    assert!(
        stats.memory_bytes <= cap,
        "the store holds {} bytes, its cap is {cap}",
        stats.memory_bytes
    );
    assert!(store.world_count() > 10, "{} worlds", store.world_count());
    // Still answering.
    let replies = tokio::time::timeout(Duration::from_secs(10), s.get(keys.world(0)))
        .await
        .unwrap_or_else(|_| panic!("query timed out"))
        .unwrap_or_else(|e| panic!("{e}"));
    let reply = tokio::time::timeout(Duration::from_secs(10), replies.recv_async())
        .await
        .unwrap_or_else(|_| panic!("no answer within 10 s"))
        .unwrap_or_else(|e| panic!("{e}"));
    let bytes = reply
        .result()
        .unwrap_or_else(|e| panic!("{e:?}"))
        .payload()
        .to_bytes();
    let world = World::decode(bytes.as_ref()).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(world.index, 0);
    sampler.stop().await;
    store.stop();
    tokio::time::timeout(Duration::from_secs(10), s.close())
        .await
        .unwrap_or_else(|_| panic!("close timed out"))
        .unwrap_or_else(|e| panic!("{e}"));
}

/// `mwb bench ingest` end to end: a store process of its own filled over TCP loopback by the
/// bench's feeder; every world stored, indexed and counted (the job closes), none refused, and
/// the store's own accounting and resident set reported.
#[test]
fn the_ingest_bench_fills_a_store_process() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_mwb"))
        .args([
            "bench",
            "ingest",
            "--worlds",
            "40",
            "--scene",
            "tumble",
            "--memory-cap-mib",
            "256",
            "--timeout-s",
            "120",
            "--json",
        ])
        .env("RUST_LOG", "warn")
        .output()
        .unwrap_or_else(|e| panic!("running mwb bench ingest: {e}"));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "mwb bench ingest failed: {stderr}");
    let line: serde_json::Value = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&out.stdout)));
    let num = |k: &str| {
        line[k]
            .as_f64()
            .unwrap_or_else(|| panic!("{k} missing: {line}"))
    };
    assert_eq!(num("worlds"), 40.0);
    assert_eq!(num("stored_worlds"), 40.0);
    assert_eq!(num("bodies"), 5.0);
    assert_eq!(num("index_failures"), 0.0);
    assert_eq!(num("refused_memory"), 0.0);
    assert!(num("ingest_worlds_per_s") > 0.0);
    assert!(num("publish_worlds_per_s") >= num("ingest_worlds_per_s"));
    // Its index is counted (a tumble world's is a few kB), and the process grew.
    assert!(num("index_bytes_per_world") > 500.0, "{line}");
    assert!(num("memory_bytes_per_world") > num("index_bytes_per_world"));
    assert!(num("rss_bytes") > num("rss_baseline_bytes"));
}
