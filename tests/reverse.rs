//! Backward worlds over a real bus (issue 5, item 5): a store (router on a free 127.0.0.1 port,
//! no scouting), a reverse node and a forward sampler (clients) and a CLI-side client. A reverse
//! job of the word scene is taken by the reverse node only; the store assembles, verifies and
//! indexes its worlds; fetched worlds pass the CLI's verification (CRC, contiguity, decode) and
//! play forward into the scene's final state, and carry their plausibility numbers. A mixed job
//! (a scene with a `[reverse] mode = "mixed"` table) gives worlds of backward + forward frames
//! that pass through the scene's intermediate state.

use mwb::bench::free_port;
use mwb::bus::{BusArgs, Mode};
use mwb::check::{WorldCheck, verify_world};
use mwb::client::{self, QualityArg};
use mwb::reverse_cmd::{load_reverse_scene, make_reverse_job};
use mwb_codec::{Quality, WorldReader};
use mwb_core::browse::api::{Reply, Request};
use mwb_core::browse::{Order, RankKey, WorldMetric};
use mwb_core::keys::Keys;
use mwb_core::scene::SceneTemplate;
use mwb_proto::v1::{JobKind, Message, NodeStats, World, WorldDone};
use mwb_query::{QueryConfig, run_query};
use mwb_reverse::{ReverseConfig, run_reverse};
use mwb_sampler::{SamplerConfig, run_sampler};
use mwb_store::{StoreConfig, run_store};
use std::time::Duration;

const SPACE: &str = "reverse";
const WORLDS: u32 = 3;
const T: Duration = Duration::from_secs(60);

fn bus(mode: Mode, port: u16) -> BusArgs {
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let (connect, listen) = if mode == Mode::Router {
        (vec![], vec![endpoint])
    } else {
        (vec![endpoint], vec![])
    };
    BusArgs {
        connect,
        listen,
        config: None,
        mode: Some(mode),
        space: SPACE.to_owned(),
        multicast: false,
    }
}

async fn open(mode: Mode, port: u16) -> zenoh::Session {
    tokio::time::timeout(T, bus(mode, port).open(mode))
        .await
        .unwrap_or_else(|_| panic!("open timed out"))
        .unwrap_or_else(|e| panic!("{e:#}"))
}

async fn within<F: std::future::Future>(what: &str, limit: Duration, f: F) -> F::Output {
    tokio::time::timeout(limit, f)
        .await
        .unwrap_or_else(|_| panic!("{what} timed out"))
}

fn angle(a: [f64; 4], b: [f64; 4]) -> f64 {
    let d: f64 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
    2.0 * d.abs().min(1.0).acos()
}

/// Submits `job` and follows it until it closes (or the wait gives up): its last state.
async fn submit_and_wait(
    session: &zenoh::Session,
    keys: &Keys,
    job: &mwb_proto::v1::Job,
) -> mwb_proto::v1::JobState {
    within("submit", T, client::submit_job(session, keys, job))
        .await
        .unwrap_or_else(|e| panic!("{e:#}"));
    within(
        "job",
        Duration::from_secs(240),
        client::wait_job(
            session,
            keys,
            &job.id,
            Some(Duration::from_secs(200)),
            |_| {},
        ),
    )
    .await
    .unwrap_or_else(|e| panic!("{e:#}"))
}

/// World `index` from the store, checked end to end (CRCs, decoding, frame counts), with its
/// summary.
async fn fetch_checked(
    session: &zenoh::Session,
    keys: &Keys,
    index: u32,
) -> (World, WorldCheck, WorldDone) {
    let world = within("fetch", T, client::fetch_world(session, keys, index))
        .await
        .unwrap_or_else(|e| panic!("{e:#}"))
        .unwrap_or_else(|| panic!("world {index} not served"));
    let check = verify_world(&world).unwrap_or_else(|e| panic!("{e:#}"));
    let done = world
        .done
        .clone()
        .unwrap_or_else(|| panic!("world {index}: no summary"));
    (world, check, done)
}

/// A store (router) on `port`: its session and handle.
async fn start_store(port: u16) -> (zenoh::Session, mwb_store::StoreHandle) {
    let session = open(Mode::Router, port).await;
    let store = within(
        "store start",
        T,
        run_store(
            session.clone(),
            StoreConfig {
                space: SPACE.into(),
                node_id: Some("store".into()),
                ..Default::default()
            },
        ),
    )
    .await
    .unwrap_or_else(|e| panic!("{e}"));
    (session, store)
}

/// A reverse node with `workers` threads on `session`.
async fn start_reverse(
    session: &zenoh::Session,
    workers: usize,
    node_id: &str,
) -> mwb_reverse::ReverseHandle {
    within(
        "reverse start",
        T,
        run_reverse(
            session.clone(),
            ReverseConfig {
                space: SPACE.into(),
                workers,
                node_id: Some(node_id.into()),
                refresh: Duration::from_millis(300),
                ..Default::default()
            },
        ),
    )
    .await
    .unwrap_or_else(|e| panic!("{e}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reverse_job_is_sampled_stored_and_plays_forward_into_the_final_state() {
    let port = free_port().unwrap_or_else(|e| panic!("{e}"));
    let keys = Keys::new(SPACE).unwrap_or_else(|e| panic!("{e}"));
    let (store_session, store) = start_store(port).await;
    let node_session = open(Mode::Client, port).await;
    let reverse = start_reverse(&node_session, 2, "rev-a").await;
    // A forward sampler on the same bus must leave the reverse job alone.
    let sampler = within(
        "sampler start",
        T,
        run_sampler(
            node_session.clone(),
            SamplerConfig {
                space: SPACE.into(),
                workers: 1,
                node_id: Some("sampler-a".into()),
                refresh: Duration::from_millis(300),
                ..Default::default()
            },
        ),
    )
    .await
    .unwrap_or_else(|e| panic!("{e}"));

    // The shipped word scene, going back 1.5 s instead of 3 s.
    let (file, text) = load_reverse_scene("word").unwrap_or_else(|e| panic!("{e:#}"));
    let text = text.replace("end_time = 3.0", "end_time = 1.5");
    let job = make_reverse_job(
        &file,
        &text,
        WORLDS,
        0,
        Some("rev-word".into()),
        QualityArg::Standard,
    )
    .unwrap_or_else(|e| panic!("{e:#}"));
    assert_eq!(job.kind(), JobKind::Reverse);
    let client_session = open(Mode::Client, port).await;
    let state = submit_and_wait(&client_session, &keys, &job).await;
    assert!(state.closed, "{state:?}");
    assert_eq!(state.worlds_done, WORLDS, "{state:?}");
    assert_eq!(state.worlds_rejected, 0, "{state:?}");

    let template = SceneTemplate::parse(&text, &file).unwrap_or_else(|e| panic!("{e}"));
    let (e_max, theta_max) = Quality::Standard.bounds();
    let mut growth: Vec<(u32, f64)> = Vec::new();
    for index in 0..WORLDS {
        let (world, check, done) = fetch_checked(&client_session, &keys, index).await;
        assert_eq!(done.node_id, "rev-a", "a sampler took a reverse world");
        assert!(
            done.provenance.contains("mwb-reverse"),
            "{}",
            done.provenance
        );
        assert_eq!(check.frames, 181);
        assert_eq!(done.impacts.len(), 16);
        assert_eq!(done.body_rested, vec![true; 16]);
        assert!(done.rested);
        // §5.3.1 plausibility, on the wire for the store to rank by.
        for (what, x) in [
            ("energy_growth", done.energy_growth),
            ("angular_speed_growth", done.angular_speed_growth),
        ] {
            assert!(
                x.is_some_and(|x| x.is_finite() && x >= 0.0),
                "world {index}: {what} = {x:?}"
            );
        }
        growth.extend(done.energy_growth.map(|g| (index, g)));

        // Played forward, the last frame is the user's final state (within the codec bound).
        let Some(last) = world.segments.last() else {
            panic!("world {index}: no segments")
        };
        let tracks = WorldReader::new(&last.payload)
            .and_then(|r| r.decode_all())
            .unwrap_or_else(|e| panic!("{e}"));
        let final_state = template.instantiate(done.seed);
        for (b, body) in final_state.bodies.iter().enumerate() {
            let (Some(p), Some(q)) = (tracks[b].positions.last(), tracks[b].rotations.last())
            else {
                panic!("world {index} body {b}: empty track")
            };
            let d = p
                .iter()
                .zip(&body.position)
                .map(|(x, y)| (x - y).powi(2))
                .sum::<f64>()
                .sqrt();
            assert!(
                d <= e_max * (1.0 + 1e-9),
                "world {index} body {b}: {d} m off"
            );
            assert!(angle(*q, body.rotation) <= theta_max * (1.0 + 1e-6));
        }
    }
    assert_eq!(sampler.worlds(), 0, "the sampler sampled a reverse job");

    // The store indexed every backward world for browsing.
    let replies = within("stats", T, async {
        client_session
            .get(keys.store_stats())
            .timeout(Duration::from_secs(3))
            .await
    })
    .await
    .unwrap_or_else(|e| panic!("{e}"));
    let reply = within("stats reply", T, replies.recv_async())
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let stats = reply
        .result()
        .ok()
        .and_then(|s| NodeStats::decode(s.payload().to_bytes().as_ref()).ok())
        .unwrap_or_else(|| panic!("no store stats"));
    assert_eq!(stats.worlds, u64::from(WORLDS), "{stats:?}");
    assert_eq!(stats.index_failures, 0, "{stats:?}");
    assert_eq!(stats.crc_failures, 0, "{stats:?}");

    // … and ranks them by their plausibility over the browse API (least energy gained first).
    let query = within(
        "query start",
        T,
        run_query(
            store_session.clone(),
            QueryConfig {
                space: SPACE.to_owned(),
                node_id: Some("reverse-query".into()),
                ..Default::default()
            },
        ),
    )
    .await
    .unwrap_or_else(|e| panic!("{e}"));
    let request = Request::Rank {
        key: RankKey::World {
            metric: WorldMetric::EnergyGrowth,
        },
        order: Order::Ascending,
        k: WORLDS as usize,
        all_worlds: false,
        plausible_only: false,
    };
    let reply = within("rank", T, query.request("t", request))
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let Reply::Ranking {
        candidates, rows, ..
    } = reply
    else {
        panic!("{reply:?}")
    };
    assert_eq!(candidates, u64::from(WORLDS));
    growth.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
    let ranked: Vec<(u32, Option<f64>)> = rows.iter().map(|r| (r.world, r.score)).collect();
    let expected: Vec<(u32, Option<f64>)> = growth.iter().map(|&(w, g)| (w, Some(g))).collect();
    assert_eq!(ranked, expected);
    query.stop();

    within("sampler stop", T, sampler.stop()).await;
    within("reverse stop", T, reverse.stop()).await;
    store.stop();
    for s in [client_session, node_session, store_session] {
        let _ = tokio::time::timeout(Duration::from_secs(5), s.close()).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_mixed_job_from_the_scene_table_stores_backward_plus_forward_frames() {
    const MIXED: u32 = 2;
    let port = free_port().unwrap_or_else(|e| panic!("{e}"));
    let keys = Keys::new(SPACE).unwrap_or_else(|e| panic!("{e}"));
    let (store_session, store) = start_store(port).await;
    let node_session = open(Mode::Client, port).await;
    let reverse = start_reverse(&node_session, 1, "rev-m").await;

    // The shipped mixed scene (`mwb reverse --scene crash_mixed`), 0.5 s back into the frame and
    // 0.5 s forward out of it.
    let (file, text) = load_reverse_scene("crash_mixed").unwrap_or_else(|e| panic!("{e:#}"));
    let text = text
        .replace("end_time = 2.0", "end_time = 0.5")
        .replace("forward_time = 2.0", "forward_time = 0.5");
    let job = make_reverse_job(
        &file,
        &text,
        MIXED,
        0,
        Some("rev-crash".into()),
        QualityArg::Standard,
    )
    .unwrap_or_else(|e| panic!("{e:#}"));
    let Some(scene) = &job.scene else {
        panic!("job without a scene")
    };
    assert!(scene.toml.contains("mode = \"mixed\""), "the table travels");
    let client_session = open(Mode::Client, port).await;
    let state = submit_and_wait(&client_session, &keys, &job).await;
    assert!(state.closed, "{state:?}");
    assert_eq!(state.worlds_done, MIXED, "{state:?}");
    assert_eq!(state.worlds_rejected, 0, "{state:?}");

    let (template, _) =
        mwb_reverse::parse_reverse_scene(&text, &file).unwrap_or_else(|e| panic!("{e}"));
    let (e_max, _) = Quality::Standard.bounds();
    // 60 backward steps, the given frame, 60 forward steps.
    let (join, frames) = (60usize, 121u32);
    for index in 0..MIXED {
        let (world, check, done) = fetch_checked(&client_session, &keys, index).await;
        assert_eq!(done.node_id, "rev-m");
        assert_eq!(check.frames, frames);
        assert_eq!(done.frame_count, frames);
        assert_eq!(done.sim_steps, u64::from(frames - 1));
        assert_eq!(done.impacts.len(), 5);
        assert_eq!(done.rest_time_s.len(), 5);
        assert!(done.energy_growth.is_some_and(f64::is_finite), "{done:?}");
        assert!(
            done.angular_speed_growth.is_some_and(f64::is_finite),
            "{done:?}"
        );

        // Played forward, frame `join` is the scene's intermediate state, and the world goes on
        // after it (the boxes were rising; 0.5 s later they have fallen below it).
        let mut paths: Vec<Vec<[f64; 3]>> = vec![Vec::new(); 5];
        for seg in &world.segments {
            let tracks = WorldReader::new(&seg.payload)
                .and_then(|r| r.decode_all())
                .unwrap_or_else(|e| panic!("{e}"));
            for (p, t) in paths.iter_mut().zip(tracks) {
                p.extend(t.positions);
            }
        }
        let given = template.instantiate(done.seed);
        for (b, body) in given.bodies.iter().enumerate() {
            let d = paths[b][join]
                .iter()
                .zip(&body.position)
                .map(|(x, y)| (x - y).powi(2))
                .sum::<f64>()
                .sqrt();
            assert!(
                d <= e_max * (1.0 + 1e-9),
                "world {index} body {b}: {d} m off"
            );
            let Some(end) = paths[b].last() else {
                panic!("world {index} body {b}: empty path")
            };
            assert!(
                end[1] < body.position[1] - 0.2,
                "world {index} body {b}: {end:?}"
            );
        }
    }

    within("reverse stop", T, reverse.stop()).await;
    store.stop();
    for s in [client_session, node_session, store_session] {
        let _ = tokio::time::timeout(Duration::from_secs(5), s.close()).await;
    }
}
