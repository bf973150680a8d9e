//! Security on by default (issue 21): the zenoh configs shipped in `deploy/` — TLS with mutual
//! authentication and access control by certificate common name — over real zenoh on
//! 127.0.0.1, with certificates made in the test by `mwb::certs` (what `mwb certs` writes).
//!
//! * (a) an authorised client submits a job and a sampler completes it over TLS + ACL;
//! * (b) a client with no certificate, one signed by another CA, or plain TCP cannot connect;
//! * (c) a worker certificate cannot put a job or a scene: nobody (the store included) sees it;
//! * (d) a client certificate cannot put segments or world summaries;
//! * (g) a recorder certificate records and replays worlds; a client's can do neither;
//! * (e) the configs are the shipped files: each test reads `deploy/*.json5` and changes only
//!   the certificate directory (`/etc/mwb/tls/` → the test's bundle) — endpoints come from
//!   `--listen` / `--connect`, as an admin would pass them.
//!
//! The store runs as an `mwb store` process (and in (a) an `mwb sampler`): two cores, so each
//! test keeps to one store and at most one sampler.

mod common;

use common::{Procs, wait_port};
use mwb::bench::free_port;
use mwb::bus::{BusArgs, Mode};
use mwb::certs::{self, Overwrite, Plan};
use mwb_core::keys::Keys;
use mwb_proto::v1::{Message, MotionSegment, WorldDone};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use zenoh::qos::CongestionControl;

/// Every await on the bus is bounded by this (or a longer, stated, limit).
const STEP: Duration = Duration::from_secs(30);

/// The shipped config `file`, with its certificate directory replaced by `bundle`.
fn shipped(file: &str, bundle: &Path) -> String {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("deploy")
        .join(file);
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert!(
        text.contains(certs::INSTALL_DIR),
        "{}: names no certificate under {} — the test would not load the shipped paths",
        path.display(),
        certs::INSTALL_DIR
    );
    text.replace(certs::INSTALL_DIR, &format!("{}/", bundle.display()))
}

/// Writes `text` as a config file beside the bundles, checking zenoh parses it.
fn write_config(dir: &Path, name: &str, text: &str) -> PathBuf {
    zenoh::Config::from_json5(text).unwrap_or_else(|e| panic!("{name}: {e}"));
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    path
}

/// One cluster's certificates and configs, and a store process using them.
struct Cluster {
    dir: tempfile::TempDir,
    endpoint: String,
    space: String,
    procs: Procs,
}

impl Cluster {
    async fn start(tag: &str) -> Self {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let plan = Plan {
            store_hosts: vec!["mwb-store".into(), "127.0.0.1".into()],
            workers: 1,
            clients: 1,
            days: 1,
        };
        let bundle = certs::generate(&plan).unwrap_or_else(|e| panic!("{e}"));
        certs::write_bundle(&bundle, dir.path(), Overwrite::Refuse)
            .unwrap_or_else(|e| panic!("{e}"));
        let store_cfg = write_config(
            dir.path(),
            "store.json5",
            &shipped("store.json5", &dir.path().join("store")),
        );
        let port = free_port().unwrap_or_else(|e| panic!("{e}"));
        let endpoint = format!("tls/127.0.0.1:{port}");
        let space = format!("{tag}{}", std::process::id());
        let mut procs = Procs(Vec::new());
        procs.spawn(
            "store",
            &[
                "store",
                "--config",
                &store_cfg.to_string_lossy(),
                "--listen",
                &endpoint,
                "--space",
                &space,
            ],
        );
        tokio::time::timeout(STEP, wait_port(port))
            .await
            .unwrap_or_else(|_| panic!("store never listened on {port}"));
        Self {
            dir,
            endpoint,
            space,
            procs,
        }
    }

    /// A sampler process (one worker) under the shipped worker config and `worker-0`'s
    /// certificate.
    fn spawn_sampler(&mut self) {
        let cfg = self.config("worker.json5", "worker-0");
        self.procs.spawn(
            "sampler",
            &[
                "sampler",
                "--config",
                &cfg.to_string_lossy(),
                "--connect",
                &self.endpoint,
                "--space",
                &self.space,
                "--workers",
                "1",
            ],
        );
    }

    fn keys(&self) -> Keys {
        Keys::new(&self.space).unwrap_or_else(|e| panic!("{e}"))
    }

    /// The shipped `file` with `bundle`'s certificates, as a config file path.
    fn config(&self, file: &str, bundle: &str) -> PathBuf {
        let text = shipped(file, &self.dir.path().join(bundle));
        write_config(self.dir.path(), &format!("{bundle}-{file}"), &text)
    }

    fn bus(&self, config: PathBuf) -> BusArgs {
        BusArgs {
            connect: vec![self.endpoint.clone()],
            listen: vec![],
            config: Some(config),
            mode: Some(Mode::Client),
            space: self.space.clone(),
            multicast: false,
        }
    }

    /// A session under the shipped client config with `bundle`'s certificate.
    async fn open(&self, file: &str, bundle: &str) -> zenoh::Session {
        let bus = self.bus(self.config(file, bundle));
        tokio::time::timeout(STEP, bus.open(Mode::Client))
            .await
            .unwrap_or_else(|_| panic!("opening a {bundle} session timed out"))
            .unwrap_or_else(|e| panic!("{bundle}: {e:#}"))
    }

    /// A session that sees everything: the store's certificate (allowed every key both ways)
    /// under the client config. What the store's router drops at ingress, it never routes, to
    /// its own subscribers or to this one.
    async fn observer(&self) -> zenoh::Session {
        let text = shipped("client.json5", &self.dir.path().join("store"))
            .replace("client.pem", "store.pem")
            .replace("client-key.pem", "store-key.pem");
        let cfg = write_config(self.dir.path(), "observer.json5", &text);
        tokio::time::timeout(STEP, self.bus(cfg).open(Mode::Client))
            .await
            .unwrap_or_else(|_| panic!("opening the observer timed out"))
            .unwrap_or_else(|e| panic!("observer: {e:#}"))
    }
}

/// Waits until the store's node is up (its liveliness token): its port opens before it
/// subscribes.
async fn store_ready(session: &zenoh::Session, keys: &Keys) {
    tokio::time::timeout(
        STEP,
        mwb::client::wait_for_store(session, keys, Duration::from_secs(20)),
    )
    .await
    .unwrap_or_else(|_| panic!("wait for store timed out"))
    .unwrap_or_else(|e| panic!("{e:#}"));
}

/// Submits a tumble job of `worlds` worlds named `name` and waits for its final state.
async fn tumble_job(
    session: &zenoh::Session,
    keys: &Keys,
    worlds: u32,
    name: &str,
) -> mwb_proto::v1::JobState {
    let (file, text) = mwb::client::load_scene("tumble").unwrap_or_else(|e| panic!("{e}"));
    let job = mwb::client::make_job(&file, &text, worlds, 0, Some(name.into()))
        .unwrap_or_else(|e| panic!("{e}"));
    tokio::time::timeout(STEP, mwb::client::submit_job(session, keys, &job))
        .await
        .unwrap_or_else(|_| panic!("submit timed out"))
        .unwrap_or_else(|e| panic!("submit: {e:#}"));
    tokio::time::timeout(
        Duration::from_secs(240),
        mwb::client::wait_job(
            session,
            keys,
            &job.id,
            Some(Duration::from_secs(200)),
            |_| {},
        ),
    )
    .await
    .unwrap_or_else(|_| panic!("job wait timed out"))
    .unwrap_or_else(|e| panic!("wait: {e:#}"))
}

async fn put(session: &zenoh::Session, key: &str, bytes: Vec<u8>) {
    tokio::time::timeout(
        STEP,
        session
            .put(key, bytes)
            .congestion_control(CongestionControl::Block),
    )
    .await
    .unwrap_or_else(|_| panic!("put {key} timed out"))
    .unwrap_or_else(|e| panic!("put {key}: {e}"));
}

async fn close(session: zenoh::Session) {
    mwb::bus::close(session).await;
}

/// Collects the keys the observer receives until every key of `expect` has arrived, then for
/// one more second (so anything sent before the expected keys has had time to arrive too).
async fn seen_until(
    sub: &zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    expect: &[String],
) -> Vec<String> {
    let mut seen = Vec::new();
    let deadline = Instant::now() + STEP;
    let mut settle: Option<Instant> = None;
    loop {
        let now = Instant::now();
        if settle.is_some_and(|s| now > s) {
            return seen;
        }
        assert!(now < deadline, "never saw {expect:?}; saw {seen:?}");
        if let Ok(Ok(s)) = tokio::time::timeout(Duration::from_millis(200), sub.recv_async()).await
        {
            seen.push(s.key_expr().as_str().to_owned());
        }
        if settle.is_none() && expect.iter().all(|k| seen.contains(k)) {
            settle = Some(Instant::now() + Duration::from_secs(1));
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn authorised_client_job_completes_over_tls_and_acl() {
    let mut cluster = Cluster::start("seca").await;
    cluster.spawn_sampler();
    let keys = cluster.keys();
    let session = cluster.open("client.json5", "client-0").await;
    let state = tumble_job(&session, &keys, 3, "secure").await;
    assert!(state.closed && !state.cancelled, "{state:?}");
    assert_eq!(state.worlds_done, 3);

    // The client reads what a client reads: worlds (decoded and CRC-checked) and status
    // (liveliness and statistics of the store and the sampler).
    for i in 0..3 {
        let w = tokio::time::timeout(STEP, mwb::client::fetch_world(&session, &keys, i))
            .await
            .unwrap_or_else(|_| panic!("fetch timed out"))
            .unwrap_or_else(|e| panic!("{e:#}"))
            .unwrap_or_else(|| panic!("world {i} not served to the client"));
        mwb::check::verify_world(&w).unwrap_or_else(|e| panic!("world {i}: {e:#}"));
    }
    let status = tokio::time::timeout(
        STEP,
        mwb::client::status(&session, &keys, Duration::from_millis(1500)),
    )
    .await
    .unwrap_or_else(|_| panic!("status timed out"))
    .unwrap_or_else(|e| panic!("{e:#}"));
    let roles: Vec<&str> = status.nodes.iter().map(|n| n.role.as_str()).collect();
    for role in ["store", "sampler"] {
        assert!(roles.contains(&role), "status shows {roles:?}");
    }
    // Statistics flow too: each node's latest NodeStats reached the client.
    let worlds = |role: &str| {
        status
            .nodes
            .iter()
            .filter(|n| n.role == role)
            .map(|n| n.worlds)
            .sum::<u64>()
    };
    assert_eq!(worlds("store"), 3, "the store's statistics: {status:?}");
    assert!(
        worlds("sampler") >= 1,
        "the sampler's statistics: {status:?}"
    );
    // Who is connected under which role: the store sees the sampler under the worker
    // certificate, named as the sampler, and a client (this session) under the client one.
    let store = status
        .nodes
        .iter()
        .find(|n| n.role == "store")
        .unwrap_or_else(|| panic!("no store in {status:?}"));
    let sampler = status
        .nodes
        .iter()
        .find(|n| n.role == "sampler")
        .unwrap_or_else(|| panic!("no sampler in {status:?}"));
    let certs: Vec<(&str, Option<&str>)> = store
        .connections
        .iter()
        .map(|c| (c.peer.as_str(), c.certificate.as_deref()))
        .collect();
    let want = format!("sampler/{}", sampler.node);
    assert!(
        certs.contains(&(want.as_str(), Some("mwb-worker"))),
        "the store's connections: {certs:?}"
    );
    let own = session.info().zid().await.to_string();
    assert!(
        store
            .connections
            .iter()
            .any(|c| c.zid == own && c.certificate.as_deref() == Some("mwb-client")),
        "the store's connections {certs:?} lack this client ({own})"
    );
    assert!(
        sampler
            .connections
            .iter()
            .any(|c| c.certificate.as_deref() == Some("mwb-store")),
        "the sampler's connections: {:?}",
        sampler.connections
    );
    close(session).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn strangers_cannot_connect() {
    let cluster = Cluster::start("secb").await;
    let client_text = shipped("client.json5", &cluster.dir.path().join("client-0"));

    // A foreign authority's client certificate (the client trusts our store all the same).
    let rogue = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let plan = Plan {
        store_hosts: vec!["127.0.0.1".into()],
        ..Plan::default()
    };
    let bundle = certs::generate(&plan).unwrap_or_else(|e| panic!("{e}"));
    certs::write_bundle(&bundle, rogue.path(), Overwrite::Refuse).unwrap_or_else(|e| panic!("{e}"));
    let ours = format!("{}/", cluster.dir.path().join("client-0").display());
    let theirs = format!("{}/", rogue.path().join("client-0").display());
    let foreign = client_text.replace(&format!("{ours}client"), &format!("{theirs}client"));
    assert!(foreign.contains(&format!("{theirs}client-key.pem")));

    // No certificate at all: mutual TLS off on the client's side, no certificate to show.
    let none = client_text
        .replace(&format!("\"{ours}client.pem\""), "null")
        .replace(&format!("\"{ours}client-key.pem\""), "null")
        .replace("enable_mtls: true", "enable_mtls: false");
    assert!(!none.contains(&format!("{ours}client")));

    let cases = [
        (
            "no certificate",
            write_config(cluster.dir.path(), "none.json5", &none),
        ),
        (
            "another CA",
            write_config(cluster.dir.path(), "foreign.json5", &foreign),
        ),
    ];
    for (what, cfg) in cases {
        let opened = tokio::time::timeout(STEP, cluster.bus(cfg).open(Mode::Client))
            .await
            .unwrap_or_else(|_| panic!("{what}: open neither failed nor succeeded"));
        assert!(opened.is_err(), "{what}: a session opened");
    }
    // Plain TCP to the TLS port, no config at all (what `mwb` does by default).
    let plain = BusArgs {
        connect: vec![cluster.endpoint.replace("tls/", "tcp/")],
        listen: vec![],
        config: None,
        mode: Some(Mode::Client),
        space: cluster.space.clone(),
        multicast: false,
    };
    let opened = tokio::time::timeout(STEP, plain.open(Mode::Client))
        .await
        .unwrap_or_else(|_| panic!("plain tcp: open neither failed nor succeeded"));
    assert!(opened.is_err(), "plain tcp: a session opened");

    // And the authorised client does connect, so the failures above are the certificates'.
    let session = cluster.open("client.json5", "client-0").await;
    store_ready(&session, &cluster.keys()).await;
    close(session).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn worker_certificate_cannot_put_jobs_or_scenes() {
    let cluster = Cluster::start("secc").await;
    let keys = cluster.keys();
    let observer = cluster.observer().await;
    let sub = tokio::time::timeout(STEP, observer.declare_subscriber(keys.all()))
        .await
        .unwrap_or_else(|_| panic!("subscribe timed out"))
        .unwrap_or_else(|e| panic!("{e}"));
    let worker = cluster.open("worker.json5", "worker-0").await;
    let client = cluster.open("client.json5", "client-0").await;
    store_ready(&client, &keys).await;
    let (file, text) = mwb::client::load_scene("tumble").unwrap_or_else(|e| panic!("{e}"));
    let job = |id: &str| {
        mwb::client::make_job(&file, &text, 1, 0, Some(id.into()))
            .unwrap_or_else(|e| panic!("{e}"))
            .encode_to_vec()
    };

    // The worker tries; then the client does the same, which must go through.
    put(&worker, &keys.job("from-worker"), job("from-worker")).await;
    put(&worker, &keys.scene(1), text.clone().into_bytes()).await;
    put(&client, &keys.job("from-client"), job("from-client")).await;
    put(&client, &keys.scene(2), text.clone().into_bytes()).await;
    let seen = seen_until(&sub, &[keys.job("from-client"), keys.scene(2)]).await;
    for denied in [keys.job("from-worker"), keys.scene(1)] {
        assert!(!seen.contains(&denied), "{denied} was routed: {seen:?}");
    }
    // The store took the client's job (it acknowledges asynchronously: ask until it answers)
    // and never the worker's.
    let state = |id: &'static str| {
        let (client, keys) = (&client, &keys);
        async move {
            tokio::time::timeout(STEP, mwb::client::job_state(client, keys, id))
                .await
                .unwrap_or_else(|_| panic!("job state query timed out"))
                .unwrap_or_else(|e| panic!("{e:#}"))
        }
    };
    let deadline = Instant::now() + STEP;
    while state("from-client").await.is_none() {
        assert!(Instant::now() < deadline, "the client's job was not stored");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    assert!(
        state("from-worker").await.is_none(),
        "the store knows the worker's job"
    );
    drop(sub);
    close(worker).await;
    close(client).await;
    close(observer).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn client_certificate_cannot_put_segments_or_summaries() {
    let cluster = Cluster::start("secd").await;
    let keys = cluster.keys();
    let observer = cluster.observer().await;
    let sub = tokio::time::timeout(STEP, observer.declare_subscriber(keys.all()))
        .await
        .unwrap_or_else(|_| panic!("subscribe timed out"))
        .unwrap_or_else(|e| panic!("{e}"));
    let worker = cluster.open("worker.json5", "worker-0").await;
    let client = cluster.open("client.json5", "client-0").await;
    store_ready(&client, &keys).await;
    let segment = |node: &str| MotionSegment {
        job_id: "j".into(),
        node_id: node.into(),
        world_counter: 0,
        seq: 0,
        ..Default::default()
    };
    // A world of two segments of which one is sent: never complete, so the store only keeps
    // it as a partial world until it expires.
    let done = |node: &str| WorldDone {
        job_id: "j".into(),
        node_id: node.into(),
        world_counter: 0,
        segment_count: 2,
        ..Default::default()
    };

    put(
        &client,
        &keys.segment("j", "client", 0, 0),
        segment("client").encode_to_vec(),
    )
    .await;
    put(
        &client,
        &keys.done("j", "client", 0),
        done("client").encode_to_vec(),
    )
    .await;
    put(
        &worker,
        &keys.segment("j", "worker", 0, 0),
        segment("worker").encode_to_vec(),
    )
    .await;
    put(
        &worker,
        &keys.done("j", "worker", 0),
        done("worker").encode_to_vec(),
    )
    .await;
    let seen = seen_until(
        &sub,
        &[
            keys.segment("j", "worker", 0, 0),
            keys.done("j", "worker", 0),
        ],
    )
    .await;
    for denied in [
        keys.segment("j", "client", 0, 0),
        keys.done("j", "client", 0),
    ] {
        assert!(!seen.contains(&denied), "{denied} was routed: {seen:?}");
    }
    drop(sub);
    close(worker).await;
    close(client).await;
    close(observer).await;
}

/// (g) a recorder certificate records a job's worlds and replays them into another space; a
/// client certificate's recorder is routed no segments or summaries, and its replay of them is
/// never routed (the client may still put the job it carries).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn recorder_certificate_records_and_replays_a_client_cannot() {
    use mwb_record::{Family, RecorderConfig, ReplayConfig, Speed, read_recording, replay};
    let mut cluster = Cluster::start("secg").await;
    cluster.spawn_sampler();
    let space = cluster.space.clone();
    let keys = cluster.keys();
    let recorder = cluster.open("recorder.json5", "recorder").await;
    let client = cluster.open("client.json5", "client-0").await;
    store_ready(&client, &keys).await;
    let record = |out: &Path, id: &str| RecorderConfig {
        space: space.clone(),
        out: out.to_owned(),
        node_id: Some(id.to_owned()),
        ..Default::default()
    };
    let (lab, snoop) = (
        cluster.dir.path().join("lab.mcap"),
        cluster.dir.path().join("snoop.mcap"),
    );
    let rec = tokio::time::timeout(
        STEP,
        mwb_record::run_recorder(&recorder, record(&lab, "rec")),
    )
    .await
    .unwrap_or_else(|_| panic!("recorder start timed out"))
    .unwrap_or_else(|e| panic!("recorder: {e}"));
    let spy = tokio::time::timeout(
        STEP,
        mwb_record::run_recorder(&client, record(&snoop, "spy")),
    )
    .await
    .unwrap_or_else(|_| panic!("spy start timed out"))
    .unwrap_or_else(|e| panic!("spy: {e}"));

    // The recorder's subscription has reached the router once it has received something (the
    // store's statistics, published every second): a job put before that could pass it by.
    // (The client's recorder is routed none of them, so there is nothing to wait for.)
    tokio::time::timeout(STEP, async {
        while rec.received() == 0 {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await
    .unwrap_or_else(|_| panic!("the recorder received nothing"));
    let state = tumble_job(&client, &keys, 2, "recorded").await;
    assert!(state.closed && state.worlds_done == 2, "{state:?}");
    // The store closed the job after both summaries: they have reached every subscriber.
    tokio::time::sleep(Duration::from_millis(500)).await;
    for (handle, what) in [(rec, "recorder"), (spy, "spy")] {
        tokio::time::timeout(STEP, handle.finish())
            .await
            .unwrap_or_else(|_| panic!("{what} finish timed out"))
            .unwrap_or_else(|e| panic!("{what}: {e}"));
    }
    let count = |path: &Path, family: Family| {
        read_recording(path)
            .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
            .messages
            .iter()
            .filter(|m| m.family == family)
            .count()
    };
    // Both summaries, and sometimes a third: the sampler may finish one world past the target
    // before it hears that the job closed (the store keeps two; the recording has every one).
    let recorded = count(&lab, Family::Done);
    assert!(recorded >= 2, "the recorder's summaries: {recorded}");
    assert!(count(&lab, Family::Segment) >= 2, "the recorder's segments");
    assert!(count(&lab, Family::Job) >= 1, "the recorder's job");
    assert_eq!(
        count(&snoop, Family::Done),
        0,
        "a client recorded summaries"
    );
    assert_eq!(
        count(&snoop, Family::Segment),
        0,
        "a client recorded segments"
    );

    // Replays into spaces of their own, watched with the store's certificate (subscribed to
    // exactly the keys a replay waits for, which the recorder may see declared).
    let observer = cluster.observer().await;
    let (by_recorder, by_client) = (format!("{space}r"), format!("{space}c"));
    let mut subs = Vec::new();
    for target in [&by_recorder, &by_client] {
        let k = Keys::new(target).unwrap_or_else(|e| panic!("{e}"));
        for key in [k.jobs(), k.segments(), k.dones()] {
            let sub = tokio::time::timeout(STEP, observer.declare_subscriber(key.clone()))
                .await
                .unwrap_or_else(|_| panic!("subscribe timed out"))
                .unwrap_or_else(|e| panic!("{key}: {e}"));
            subs.push((target.clone(), sub));
        }
    }
    let replay_into = |session: &zenoh::Session, target: &str, wait: u64| {
        let cfg = ReplayConfig {
            path: lab.clone(),
            speed: Speed::Max,
            space: target.to_owned(),
            wait_for_subscribers: Duration::from_secs(wait),
        };
        let session = session.clone();
        async move {
            tokio::time::timeout(STEP, replay(&session, &cfg, std::future::pending()))
                .await
                .unwrap_or_else(|_| panic!("replay timed out"))
                .unwrap_or_else(|e| panic!("replay: {e}"))
        }
    };
    let by_rec = replay_into(&recorder, &by_recorder, 10).await;
    assert!(
        by_rec.subscribers_seen,
        "the recorder saw no store-side subscribers"
    );
    let by_cli = replay_into(&client, &by_client, 2).await;
    assert_eq!(by_rec.published, by_cli.published);
    tokio::time::sleep(Duration::from_secs(1)).await;
    // Drained once: every key each target's subscribers received.
    let keys_of = |target: &str| -> Vec<String> {
        subs.iter()
            .filter(|(t, _)| t == target)
            .flat_map(|(_, sub)| sub.drain())
            .map(|s| s.key_expr().as_str().to_owned())
            .collect()
    };
    let got = [
        (by_recorder.clone(), keys_of(&by_recorder)),
        (by_client.clone(), keys_of(&by_client)),
    ];
    let received = |target: &str, part: &str| {
        got.iter()
            .filter(|(t, _)| t == target)
            .flat_map(|(_, keys)| keys)
            .filter(|k| k.contains(part))
            .count()
    };
    assert!(
        received(&by_recorder, "/seg/") >= 2,
        "the recorder's replayed segments"
    );
    assert_eq!(
        received(&by_recorder, "/done/"),
        recorded,
        "the recorder's replayed summaries"
    );
    assert_eq!(
        received(&by_client, "/seg/"),
        0,
        "a client's replayed segments were routed"
    );
    assert_eq!(
        received(&by_client, "/done/"),
        0,
        "a client's replayed summaries were routed"
    );
    drop(subs);
    close(observer).await;
    close(recorder).await;
    close(client).await;
}

/// (e) without a bus: every shipped config parses as it is, the store's enables access
/// control denying by default with one subject per role of `mwb certs`, and every client
/// config requires TLS with a certificate.
#[test]
fn shipped_configs_are_secure_by_default() {
    let dir = Path::new("/nonexistent");
    let store = shipped("store.json5", dir);
    zenoh::Config::from_json5(&store).unwrap_or_else(|e| panic!("store.json5: {e}"));
    for needle in [
        "enabled: true",
        "default_permission: \"deny\"",
        "enable_mtls: true",
        "protocols: [\"tls\"]",
        "\"tls/0.0.0.0:7447\"",
    ] {
        assert!(store.contains(needle), "store.json5 lacks {needle}");
    }
    for role in [
        certs::Role::Store,
        certs::Role::Worker,
        certs::Role::Client,
        certs::Role::Query,
        certs::Role::Recorder,
    ] {
        let subject = format!("cert_common_names: [\"{}\"]", role.common_name());
        assert!(store.contains(&subject), "store.json5 lacks {subject}");
    }
    for (file, stem) in [
        ("worker.json5", "worker"),
        ("client.json5", "client"),
        ("query.json5", "query"),
        ("recorder.json5", "recorder"),
    ] {
        let text = shipped(file, dir);
        zenoh::Config::from_json5(&text).unwrap_or_else(|e| panic!("{file}: {e}"));
        for needle in [
            "enable_mtls: true".to_owned(),
            "protocols: [\"tls\"]".to_owned(),
            format!("connect_certificate: \"/nonexistent/{stem}.pem\""),
            format!("connect_private_key: \"/nonexistent/{stem}-key.pem\""),
        ] {
            assert!(text.contains(&needle), "{file} lacks {needle}");
        }
    }
}
