//! A durable store as a separate OS process: `mwb store --journal DIR` is SIGKILLed in the
//! middle of a job, restarted on the same journal and port, and has every world it had
//! acknowledged (a published job state counted it), byte for byte under the same index; the
//! job then completes.

mod common;

use common::{Procs, sigkill, wait_port};
use mwb::bench::free_port;
use mwb::bus::{BusArgs, Mode};
use mwb::check::verify_world;
use mwb::client;
use mwb_core::keys::Keys;
use mwb_proto::v1::{JobState, Message, World};
use std::collections::{BTreeMap, HashSet};
use std::time::{Duration, Instant};

const TARGET: u32 = 40;

fn bus(endpoint: &str, space: &str) -> BusArgs {
    BusArgs {
        connect: vec![endpoint.to_owned()],
        listen: vec![],
        config: None,
        mode: Some(Mode::Client),
        space: space.to_owned(),
        multicast: false,
    }
}

/// A client session, retried for up to 30 s: a store that has just started listening may still
/// be reading its journal, and on a loaded machine its first handshakes can fail.
async fn open(b: &BusArgs) -> zenoh::Session {
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    loop {
        match tokio::time::timeout(Duration::from_secs(30), b.open(Mode::Client)).await {
            Ok(Ok(s)) => return s,
            Ok(Err(e)) if std::time::Instant::now() < deadline => {
                eprintln!("retrying the client session: {e}");
                tokio::time::sleep(Duration::from_millis(250)).await;
            }
            Ok(Err(e)) => panic!("{e}"),
            Err(_) => panic!("open timed out"),
        }
    }
}

async fn fetch(session: &zenoh::Session, keys: &Keys, i: u32) -> Option<World> {
    tokio::time::timeout(
        Duration::from_secs(30),
        client::fetch_world(session, keys, i),
    )
    .await
    .unwrap_or_else(|_| panic!("fetching world {i} timed out"))
    .unwrap_or_else(|e| panic!("{e}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_store_killed_mid_job_restarts_from_its_journal_with_every_acknowledged_world() {
    let port = free_port().unwrap_or_else(|e| panic!("{e}"));
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let space = format!("journal{}", std::process::id());
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let journal = dir.path().join("journal");
    let journal_arg = journal.to_string_lossy().into_owned();
    let store_args = [
        "store",
        "--listen",
        &endpoint,
        "--space",
        &space,
        "--journal",
        &journal_arg,
    ];
    let sampler_args = [
        "sampler",
        "--connect",
        &endpoint,
        "--space",
        &space,
        "--workers",
        "1",
    ];
    let mut procs = Procs(Vec::new());
    procs.spawn("store", &store_args);
    wait_port(port).await;
    procs.spawn("sampler", &sampler_args);

    let keys = Keys::new(&space).unwrap_or_else(|e| panic!("{e}"));
    let session = open(&bus(&endpoint, &space)).await;
    let (file, text) = client::load_scene("tumble").unwrap_or_else(|e| panic!("{e}"));
    let job = client::make_job(&file, &text, TARGET, 0, Some("durable".into()))
        .unwrap_or_else(|e| panic!("{e}"));
    let states = session
        .declare_subscriber(keys.job_state(&job.id))
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    tokio::time::timeout(
        Duration::from_secs(60),
        client::submit_job(&session, &keys, &job),
    )
    .await
    .unwrap_or_else(|_| panic!("submit timed out"))
    .unwrap_or_else(|e| panic!("{e}"));

    // Follow the published states (the store's acknowledgements). Once a few worlds are
    // acknowledged, fetch them, then kill the store right after the next acknowledgement.
    let mut acked = 0u32;
    let mut before: BTreeMap<u32, Vec<u8>> = BTreeMap::new();
    let deadline = Instant::now() + Duration::from_secs(300);
    loop {
        assert!(
            Instant::now() < deadline,
            "too few worlds acknowledged: {acked}"
        );
        let Ok(Ok(s)) = tokio::time::timeout(Duration::from_secs(5), states.recv_async()).await
        else {
            continue;
        };
        let st =
            JobState::decode(s.payload().to_bytes().as_ref()).unwrap_or_else(|e| panic!("{e}"));
        assert!(!st.closed, "the job closed before the store was killed");
        acked = acked.max(st.worlds_done);
        if !before.is_empty() && acked > before.len() as u32 {
            sigkill(procs.pid("store"));
            break;
        }
        if before.is_empty() && acked >= 4 {
            for i in 0..acked {
                let w = fetch(&session, &keys, i)
                    .await
                    .unwrap_or_else(|| panic!("acknowledged world {i} not served"));
                before.insert(i, w.encode_to_vec());
            }
        }
    }
    drop(states);
    mwb::bus::close(session).await;

    // The same store, the same journal, the same port.
    procs.spawn("store2", &store_args);
    wait_port(port).await;
    // The first sampler may or may not find the restarted router again; a fresh one will.
    procs.spawn("sampler2", &sampler_args);
    let session = open(&bus(&endpoint, &space)).await;
    // Alive means answering: the token comes after the journal has been read.
    tokio::time::timeout(
        Duration::from_secs(90),
        client::wait_for_store(&session, &keys, Duration::from_secs(60)),
    )
    .await
    .unwrap_or_else(|_| panic!("the restarted store never came up"))
    .unwrap_or_else(|e| panic!("{e}"));
    for i in 0..acked {
        let w = fetch(&session, &keys, i)
            .await
            .unwrap_or_else(|| panic!("acknowledged world {i} lost in the restart"));
        if let Some(b) = before.get(&i) {
            assert_eq!(&w.encode_to_vec(), b, "world {i} changed in the restart");
        }
        verify_world(&w).unwrap_or_else(|e| panic!("world {i}: {e}"));
    }
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
    assert_eq!(state.worlds_done, TARGET);
    let mut seeds = HashSet::new();
    for i in 0..TARGET {
        let w = fetch(&session, &keys, i)
            .await
            .unwrap_or_else(|| panic!("world {i} missing"));
        verify_world(&w).unwrap_or_else(|e| panic!("world {i}: {e}"));
        let done = w.done.unwrap_or_default();
        assert!(seeds.insert(done.seed), "duplicate seed {}", done.seed);
    }
    assert!(fetch(&session, &keys, TARGET).await.is_none());
    mwb::bus::close(session).await;
    // Two journal files: the killed run's (cut short, read up to its last commit) and this
    // run's, which starts with a checkpoint of the job.
    let files = std::fs::read_dir(&journal)
        .unwrap_or_else(|e| panic!("{e}"))
        .count();
    assert_eq!(files, 2);
}
