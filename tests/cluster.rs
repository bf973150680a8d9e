//! A real cluster on one machine: a store and samplers as separate OS processes over TCP
//! loopback (issue: "opportunistic samplers"). One sampler is SIGKILLed in the middle of a
//! world, a fourth joins late, and the 100-world job must still complete with only complete,
//! CRC-valid, distinct worlds.

mod common;

use common::{Procs, sigkill, wait_port};
use mwb::bench::free_port;
use mwb::bus::{BusArgs, Mode};
use mwb::check::verify_world;
use mwb::client;
use mwb_core::keys::Keys;
use mwb_proto::v1::{Message, MotionSegment, NodeStats, WorldDone};
use std::collections::{HashMap, HashSet};
use std::time::{Duration, Instant};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sampler_killed_mid_world_job_still_completes() {
    let port = free_port().unwrap_or_else(|e| panic!("{e}"));
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let space = format!("cluster{}", std::process::id());
    let mut procs = Procs(Vec::new());
    procs.spawn(
        "store",
        &["store", "--listen", &endpoint, "--space", &space],
    );
    wait_port(port).await;
    for i in 0..3 {
        procs.spawn(
            &format!("sampler{i}"),
            &[
                "sampler",
                "--connect",
                &endpoint,
                "--space",
                &space,
                "--workers",
                "1",
            ],
        );
    }

    let bus = BusArgs {
        connect: vec![endpoint.clone()],
        listen: vec![],
        config: None,
        mode: Some(Mode::Client),
        space: space.clone(),
        multicast: false,
    };
    let keys = Keys::new(&space).unwrap_or_else(|e| panic!("{e}"));
    let session = tokio::time::timeout(Duration::from_secs(30), bus.open(Mode::Client))
        .await
        .unwrap_or_else(|_| panic!("open timed out"))
        .unwrap_or_else(|e| panic!("{e}"));
    // Watch the traffic ourselves: which worlds each sampler has started and finished.
    let segs = session
        .declare_subscriber(keys.segments())
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let dones = session
        .declare_subscriber(keys.dones())
        .await
        .unwrap_or_else(|e| panic!("{e}"));

    // The tower: each world takes long enough that a kill lands mid-world.
    let (file, text) = client::load_scene("tower").unwrap_or_else(|e| panic!("{e}"));
    let job = client::make_job(&file, &text, 100, 0, Some("killtest".into()))
        .unwrap_or_else(|e| panic!("{e}"));
    tokio::time::timeout(
        Duration::from_secs(60),
        client::submit_job(&session, &keys, &job),
    )
    .await
    .unwrap_or_else(|_| panic!("submit timed out"))
    .unwrap_or_else(|e| panic!("{e}"));

    // Which node id is which process (every node's stats carry its pid).
    let names = process_names(&session, &keys, &procs).await;

    // Kill a sampler in the middle of a world: right after the second segment of a world
    // whose WorldDone has not been seen (tower worlds last several seconds of simulated time,
    // so at least two more segments are still to come).
    let mut started: HashMap<(String, u64), u32> = HashMap::new();
    let mut finished: HashSet<(String, u64)> = HashSet::new();
    let deadline = Instant::now() + Duration::from_secs(180);
    let (victim_node, victim_world) = loop {
        assert!(Instant::now() < deadline, "never saw a world in flight");
        tokio::select! {
            s = segs.recv_async() => {
                let s = s.unwrap_or_else(|e| panic!("{e}"));
                let m = MotionSegment::decode(s.payload().to_bytes().as_ref())
                    .unwrap_or_else(|e| panic!("{e}"));
                *started.entry((m.node_id.clone(), m.world_counter)).or_default() += 1;
                // Wait until some worlds are done so the job is well under way, then pick the
                // sampler of a world that is streaming but unfinished.
                let key = (m.node_id.clone(), m.world_counter);
                if finished.len() >= 6 && m.seq == 1 && !finished.contains(&key) {
                    let victim = names.get(&m.node_id)
                        .unwrap_or_else(|| panic!("unknown node {}", m.node_id));
                    sigkill(procs.pid(victim));
                    break key;
                }
            }
            d = dones.recv_async() => {
                let d = d.unwrap_or_else(|e| panic!("{e}"));
                let m = WorldDone::decode(d.payload().to_bytes().as_ref())
                    .unwrap_or_else(|e| panic!("{e}"));
                finished.insert((m.node_id, m.world_counter));
            }
            _ = tokio::time::sleep(Duration::from_secs(5)) => {}
        }
    };
    // Stop listening to the motion stream: an undrained subscriber would push back on the
    // router (segments are sent with blocking congestion control) and stall the whole cluster.
    drop(segs);
    drop(dones);
    procs.spawn(
        "sampler3",
        &[
            "sampler",
            "--connect",
            &endpoint,
            "--space",
            &space,
            "--workers",
            "1",
        ],
    );

    let state = client::wait_job(
        &session,
        &keys,
        &job.id,
        Some(Duration::from_secs(600)),
        |_| {},
    )
    .await
    .unwrap_or_else(|e| panic!("{e}"));
    assert!(state.closed && !state.cancelled);
    assert_eq!(state.worlds_done, 100);

    // Every stored world is complete and CRC-valid, and no seed repeats.
    let mut seeds = HashSet::new();
    for i in 0..100 {
        let w = client::fetch_world(&session, &keys, i)
            .await
            .unwrap_or_else(|e| panic!("{e}"))
            .unwrap_or_else(|| panic!("world {i} missing"));
        assert_eq!(w.job_id, job.id);
        let check = verify_world(&w).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(check.bodies, 193);
        let done = w.done.unwrap_or_default();
        assert!(seeds.insert(done.seed), "duplicate seed {}", done.seed);
        assert!(
            !(done.node_id == victim_node && done.world_counter == victim_world),
            "the killed sampler's partial world must not be stored"
        );
    }
    assert!(
        client::fetch_world(&session, &keys, 100)
            .await
            .unwrap_or_else(|e| panic!("{e}"))
            .is_none(),
        "exactly 100 worlds"
    );
    // The store noticed the departure and discarded the partial world.
    let stats = store_stats(&session, &keys).await;
    assert!(
        stats.discarded_partial >= 1,
        "store should have discarded the victim's partial world: {stats:?}"
    );
    assert_eq!(stats.crc_failures, 0);
    mwb::bus::close(session).await;
}

async fn store_stats(session: &zenoh::Session, keys: &Keys) -> NodeStats {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let replies = session
            .get(keys.store_stats())
            .timeout(Duration::from_secs(2))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        if let Ok(r) = replies.recv_async().await
            && let Ok(s) = r.result()
        {
            return NodeStats::decode(s.payload().to_bytes().as_ref())
                .unwrap_or_else(|e| panic!("{e}"));
        }
        assert!(Instant::now() < deadline, "store stats never answered");
    }
}

/// Maps each sampler's node id to the name of our child process, from the pids in their stats.
async fn process_names(
    session: &zenoh::Session,
    keys: &Keys,
    procs: &Procs,
) -> HashMap<String, String> {
    let sub = session
        .declare_subscriber(keys.stats_all())
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let mut names = HashMap::new();
    let deadline = Instant::now() + Duration::from_secs(60);
    while names.len() < 3 {
        assert!(
            Instant::now() < deadline,
            "stats of all samplers never seen: {names:?}"
        );
        let Ok(Ok(s)) = tokio::time::timeout(Duration::from_secs(3), sub.recv_async()).await else {
            continue;
        };
        let st =
            NodeStats::decode(s.payload().to_bytes().as_ref()).unwrap_or_else(|e| panic!("{e}"));
        for i in 0..3 {
            let name = format!("sampler{i}");
            if procs.pid(&name) == st.pid {
                names.insert(st.node_id.clone(), name);
            }
        }
    }
    names
}
