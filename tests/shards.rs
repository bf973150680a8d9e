//! Browsing over a real bus (issue 4): two store shards behind node-query return the same
//! answers as one store, including a shard that joins after the browsing session began.
//!
//! Two spaces share one zenoh router on 127.0.0.1 (free port, no scouting). Space `one` has a
//! single store; space `two` has shard 0/2 (with node-query) from the start and shard 1/2,
//! in its own client session, only after the first constraint was added. One sampler per space
//! with the same node id and one worker samples the same job id, so both spaces hold exactly
//! the same worlds (the sampler is deterministic; world = counter hash of job, node, counter).
//! Answers are compared through world seeds, since global indices depend on the sharding.

use mwb::bench::free_port;
use mwb::bus::{BusArgs, Mode};
use mwb::client;
use mwb_core::browse::api::{Reply, Request, SessionStatus};
use mwb_core::browse::{
    Aggregate, Constraint, ConstraintId, Frustum, Metric, Order, Polarity, RankKey, TimeWindow,
};
use mwb_core::keys::Keys;
use mwb_query::{QueryConfig, QueryHandle, run_query};
use mwb_sampler::{SamplerConfig, run_sampler};
use mwb_store::{ShardSpec, StoreConfig, StoreHandle, run_store};
use std::collections::{BTreeMap, BTreeSet};
use std::time::{Duration, Instant};

const WORLDS: u32 = 40;
const T: Duration = Duration::from_secs(60);

fn bus(space: &str, mode: Mode, port: u16) -> BusArgs {
    let endpoint = format!("tcp/127.0.0.1:{port}");
    BusArgs {
        connect: if mode == Mode::Router {
            vec![]
        } else {
            vec![endpoint.clone()]
        },
        listen: if mode == Mode::Router {
            vec![endpoint]
        } else {
            vec![]
        },
        config: None,
        mode: Some(mode),
        space: space.to_owned(),
        multicast: false,
    }
}

async fn open(space: &str, mode: Mode, port: u16) -> zenoh::Session {
    tokio::time::timeout(T, bus(space, mode, port).open(mode))
        .await
        .unwrap_or_else(|_| panic!("open timed out"))
        .unwrap_or_else(|e| panic!("{e:#}"))
}

async fn store(session: &zenoh::Session, space: &str, shard: ShardSpec, id: &str) -> StoreHandle {
    tokio::time::timeout(
        T,
        run_store(
            session.clone(),
            StoreConfig {
                space: space.to_owned(),
                node_id: Some(id.to_owned()),
                shard,
                // Every index the samplers send is checked against the store's own.
                verify_index_every: 1,
                ..Default::default()
            },
        ),
    )
    .await
    .unwrap_or_else(|_| panic!("store start timed out"))
    .unwrap_or_else(|e| panic!("{e}"))
}

async fn query(session: &zenoh::Session, space: &str) -> QueryHandle {
    tokio::time::timeout(
        T,
        run_query(
            session.clone(),
            QueryConfig {
                space: space.to_owned(),
                node_id: Some(format!("{space}-query")),
                ..Default::default()
            },
        ),
    )
    .await
    .unwrap_or_else(|_| panic!("query start timed out"))
    .unwrap_or_else(|e| panic!("{e}"))
}

async fn ask(q: &QueryHandle, req: Request) -> Reply {
    let reply = tokio::time::timeout(T, q.request("s1", req.clone()))
        .await
        .unwrap_or_else(|_| panic!("{req:?} timed out"))
        .unwrap_or_else(|e| panic!("{req:?}: {e}"));
    if let Reply::Error { message } = &reply {
        panic!("{req:?}: {message}");
    }
    reply
}

fn status(r: Reply) -> SessionStatus {
    match r {
        Reply::Status(s) => s,
        other => panic!("status expected, got {other:?}"),
    }
}

fn aabb(id: u64, polarity: Polarity, min: [f64; 3], max: [f64; 3], window: bool) -> Constraint {
    Constraint {
        id: ConstraintId(id),
        polarity,
        frustum: Frustum::aabb(min, max).unwrap_or_else(|e| panic!("{e}")),
        objects: vec![0],
        quantifier: Default::default(),
        window: window.then(|| TimeWindow::new(1.0, 3.0).unwrap_or_else(|e| panic!("{e}"))),
        scope: Default::default(),
    }
}

/// Every world, ranked by the number of constraints it satisfies.
async fn by_constraints(q: &QueryHandle) -> Vec<mwb_core::browse::Ranked> {
    match ask(
        q,
        Request::Rank {
            key: RankKey::ConstraintsSatisfied,
            order: Order::Descending,
            k: 10_000,
            all_worlds: true,
            plausible_only: false,
        },
    )
    .await
    {
        Reply::Ranking { rows, .. } => rows,
        other => panic!("ranking expected, got {other:?}"),
    }
}

/// World index → seed, from the summaries (every world of the space).
async fn seeds(q: &QueryHandle) -> BTreeMap<u32, u64> {
    let rows = by_constraints(q).await;
    let mut out = BTreeMap::new();
    for r in rows {
        match ask(q, Request::Summary { world: r.world }).await {
            Reply::Summary(s) => {
                out.insert(r.world, s.seed);
            }
            other => panic!("summary of {}: {other:?}", r.world),
        }
    }
    out
}

/// What a space answers to the probing requests, with worlds named by seed.
#[derive(Debug, PartialEq)]
struct Answers {
    status: (u64, u64, Vec<(u64, u64)>),
    result: BTreeSet<u64>,
    ranking: Vec<(u64, Option<f64>)>,
    by_constraints: Vec<(u64, Option<f64>)>,
}

async fn answers(q: &QueryHandle, seed_of: &BTreeMap<u32, u64>) -> Answers {
    let st = status(ask(q, Request::Status).await);
    let Reply::Worlds { result, worlds } = ask(q, Request::Result { limit: None }).await else {
        panic!("worlds expected")
    };
    assert_eq!(result as usize, worlds.len());
    let named = |w: u32| *seed_of.get(&w).unwrap_or_else(|| panic!("world {w}"));
    let rank = |key, order| Request::Rank {
        key,
        order,
        k: 7,
        all_worlds: false,
        plausible_only: false,
    };
    let Reply::Ranking { rows, .. } = ask(
        q,
        rank(
            RankKey::Metric {
                metric: Metric::AngularTravel,
                objects: vec![0, 1, 2, 3, 4],
                aggregate: Aggregate::Sum,
            },
            Order::Descending,
        ),
    )
    .await
    else {
        panic!("ranking expected")
    };
    let rows2 = by_constraints(q).await;
    // Ties in satisfied counts are broken by world index, which differs between the layouts:
    // compare those as (score, seed) sets.
    let mut by_constraints: Vec<(u64, Option<f64>)> =
        rows2.iter().map(|r| (named(r.world), r.score)).collect();
    by_constraints.sort_by_key(|a| a.0);
    Answers {
        status: (
            st.worlds,
            st.result,
            st.constraints
                .iter()
                .map(|c| (c.id.0, c.satisfied))
                .collect(),
        ),
        result: worlds.into_iter().map(named).collect(),
        ranking: rows.iter().map(|r| (named(r.world), r.score)).collect(),
        by_constraints,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_shards_answer_like_one_and_a_late_shard_catches_up() {
    let port = free_port().unwrap_or_else(|e| panic!("{e}"));
    let pid = std::process::id();
    let (one, two) = (format!("one{pid}"), format!("two{pid}"));
    let router = open(&one, Mode::Router, port).await;
    let store_one = store(&router, &one, ShardSpec::default(), "one-store").await;
    let q_one = query(&router, &one).await;
    let shard0 = store(
        &router,
        &two,
        ShardSpec::new(0, 2).unwrap_or_default(),
        "shard0",
    )
    .await;
    let q_two = query(&router, &two).await;

    // The session begins with only shard 0 alive.
    let c1 = aabb(
        1,
        Polarity::Positive,
        [-0.5, 0.0, -0.5],
        [0.5, 0.3, 0.5],
        true,
    );
    for q in [&q_one, &q_two] {
        let st = status(
            ask(
                q,
                Request::Add {
                    constraint: Box::new(c1.clone()),
                },
            )
            .await,
        );
        assert_eq!((st.worlds, st.result, st.edits), (0, 0, 1));
    }
    assert_eq!(q_two.shards(), vec!["shard0".to_owned()]);

    // Shard 1 joins late, in its own session.
    let late = open(&two, Mode::Client, port).await;
    let shard1 = store(
        &late,
        &two,
        ShardSpec::new(1, 2).unwrap_or_default(),
        "shard1",
    )
    .await;
    let deadline = Instant::now() + T;
    while q_two.shards().len() < 2 {
        assert!(Instant::now() < deadline, "node-query never saw shard 1");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }

    // Same job, same sampler id, one worker each: the same worlds in both spaces.
    let work = open(&one, Mode::Client, port).await;
    let scene = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/tumble.toml"))
        .unwrap_or_else(|e| panic!("{e}"));
    let job = client::make_job("tumble.toml", &scene, WORLDS, 0, Some("shardjob".into()))
        .unwrap_or_else(|e| panic!("{e:#}"));
    let mut samplers = Vec::new();
    for space in [&one, &two] {
        let keys = Keys::new(space).unwrap_or_else(|e| panic!("{e}"));
        samplers.push(
            run_sampler(
                work.clone(),
                SamplerConfig {
                    space: space.clone(),
                    workers: 1,
                    node_id: Some("s0".into()),
                    ..Default::default()
                },
            )
            .await
            .unwrap_or_else(|e| panic!("{e}")),
        );
        tokio::time::timeout(T, client::submit_job(&work, &keys, &job))
            .await
            .unwrap_or_else(|_| panic!("submit timed out"))
            .unwrap_or_else(|e| panic!("{e:#}"));
    }
    for space in [&one, &two] {
        let keys = Keys::new(space).unwrap_or_else(|e| panic!("{e}"));
        let st = client::wait_job(
            &work,
            &keys,
            &job.id,
            Some(Duration::from_secs(120)),
            |_| {},
        )
        .await
        .unwrap_or_else(|e| panic!("{space}: {e:#}"));
        assert_eq!(st.worlds_done, WORLDS, "{space}");
    }
    for s in samplers {
        s.stop().await;
    }
    // The stores index a world before they announce the job state that counts it; shard 1
    // learns of the closing world through the bus, so wait for the total.
    let deadline = Instant::now() + T;
    while shard0.indexed_count() + shard1.indexed_count() < u64::from(WORLDS) {
        assert!(
            Instant::now() < deadline,
            "shards never indexed every world"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(store_one.indexed_count(), u64::from(WORLDS));
    let (n0, n1) = (shard0.indexed_count(), shard1.indexed_count());
    assert!(
        n0 > 0 && n1 > 0,
        "hash split left a shard empty: {n0} / {n1}"
    );
    let st = store_one.stats();
    assert_eq!(st.index_failures, 0);
    // Every world came with its sampler's index, each checked and found the same.
    assert_eq!(
        (
            st.indexes_sent,
            st.indexes_checked,
            st.index_mismatches,
            st.indexes_refused
        ),
        (u64::from(WORLDS), u64::from(WORLDS), 0, 0),
        "{st:?}"
    );
    assert_eq!(st.browsable_worlds, u64::from(WORLDS));

    let seeds_one = seeds(&q_one).await;
    let seeds_two = seeds(&q_two).await;
    let set = |m: &BTreeMap<u32, u64>| m.values().copied().collect::<BTreeSet<u64>>();
    assert_eq!(seeds_one.len(), WORLDS as usize);
    assert_eq!(
        set(&seeds_one),
        set(&seeds_two),
        "different worlds in the two spaces"
    );
    // Shard 1's worlds are odd-numbered, shard 0's even.
    for (w, seed) in &seeds_two {
        let owner = ShardSpec::shard_of(&job.id, *seed, 2);
        assert_eq!(w % 2, owner, "world {w} numbered by the wrong shard");
    }

    // The late shard was given constraint 1 when it joined (first request after joining).
    let mut history = Vec::new();
    let c2 = aabb(
        2,
        Polarity::Negative,
        [0.0, 0.0, 0.0],
        [2.0, 1.0, 2.0],
        false,
    );
    let c3 = aabb(
        3,
        Polarity::Positive,
        [-2.0, 0.0, -2.0],
        [2.0, 2.0, 2.0],
        false,
    );
    let edits = [
        Request::Status,
        Request::Add {
            constraint: Box::new(c2),
        },
        Request::Add {
            constraint: Box::new(c3),
        },
        Request::Remove {
            id: ConstraintId(1),
        },
        Request::Undo,
        Request::Undo,
        Request::Redo,
        Request::Remove {
            id: ConstraintId(2),
        },
    ];
    for req in edits {
        let mut pair = Vec::new();
        for (q, seeds) in [(&q_one, &seeds_one), (&q_two, &seeds_two)] {
            if req.is_edit() {
                ask(q, req.clone()).await;
            }
            pair.push(answers(q, seeds).await);
        }
        assert_eq!(pair[0], pair[1], "after {req:?}");
        history.push(pair.remove(0));
    }
    // The probes mean something: constraint 1 splits the worlds somewhere along the way.
    let first = &history[0];
    assert_eq!(first.status.2.len(), 1);
    let sat1 = first.status.2[0].1;
    assert!(
        sat1 > 0 && sat1 < u64::from(WORLDS),
        "constraint 1 keeps {sat1} of {WORLDS}"
    );
    assert!(history.iter().any(|a| a.result.len() < WORLDS as usize));

    // A removed constraint's shard bits come back on undo without re-evaluation, and the
    // session keeps working for worlds' summaries on the late shard.
    let odd = seeds_two.keys().find(|w| *w % 2 == 1).copied();
    if let Some(w) = odd {
        match ask(&q_two, Request::Summary { world: w }).await {
            Reply::Summary(s) => assert_eq!(s.shard, "shard1"),
            other => panic!("summary expected, got {other:?}"),
        }
    }
    // Unknown constraint ids are refused by every shard, naming the id.
    let refused = tokio::time::timeout(
        T,
        q_two.request(
            "s1",
            Request::Remove {
                id: ConstraintId(99),
            },
        ),
    )
    .await
    .unwrap_or_else(|_| panic!("timed out"))
    .unwrap_or_else(|e| panic!("{e}"));
    match refused {
        Reply::Error { message } => assert!(message.contains("99"), "{message}"),
        other => panic!("error expected, got {other:?}"),
    }
    // The shards stay in step after the refused edit.
    let st1 = status(ask(&q_two, Request::Status).await);
    assert_eq!(st1.edits, 9, "1 + 7 edits + the refused one");

    q_one.stop();
    q_two.stop();
    store_one.stop();
    shard0.stop();
    shard1.stop();
    for s in [late, work, router] {
        mwb::bus::close(s).await;
    }
}
