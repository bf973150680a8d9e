//! The CLI tells the truth (issue 24, items 5–9), checked on real OS processes over a real bus:
//! a closed pipe ends a command quietly, errors exit non-zero and name what was tried, a job
//! that cannot complete says why within seconds, a stayed demo takes more jobs, a stored
//! world regenerates from its seed to the same digest, and `mwb scene` refuses a scene the
//! simulator cannot do faithfully (issue 19).

mod common;

use common::Procs;
use mwb::bench::free_port;
use serde_json::Value;
use std::io::Read;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

fn mwb() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_mwb"));
    c.env("RUST_LOG", "warn").env_remove("MWB_CONNECT");
    c
}

/// Waits for `child` at most `limit` (a hang guard, not a speed test); kills it past that.
fn wait(child: &mut Child, limit: Duration, what: &str) -> ExitStatus {
    let deadline = Instant::now() + limit;
    loop {
        match child.try_wait() {
            Ok(Some(status)) => return status,
            Ok(None) if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(50)),
            Ok(None) => {
                let _ = child.kill();
                panic!("{what} still running after {limit:?}");
            }
            Err(e) => panic!("{what}: {e}"),
        }
    }
}

/// Runs `cmd` to its end (at most `limit`): status, stdout, stderr.
fn run(cmd: &mut Command, limit: Duration, what: &str) -> (ExitStatus, String, String) {
    let mut child = cmd
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("spawning {what}: {e}"));
    // Drain both pipes on threads, so a chatty child never blocks on a full pipe.
    let drain = |mut r: Box<dyn Read + Send>| {
        std::thread::spawn(move || {
            let mut s = String::new();
            let _ = r.read_to_string(&mut s);
            s
        })
    };
    let out = child.stdout.take().map(|r| drain(Box::new(r)));
    let err = child.stderr.take().map(|r| drain(Box::new(r)));
    let status = wait(&mut child, limit, what);
    let text = |h: Option<std::thread::JoinHandle<String>>| {
        h.and_then(|h| h.join().ok()).unwrap_or_default()
    };
    (status, text(out), text(err))
}

const LIMIT: Duration = Duration::from_secs(120);

/// Waits until something listens on `port` (at most [`LIMIT`]).
fn wait_port(port: u16) {
    let deadline = Instant::now() + LIMIT;
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(Instant::now() < deadline, "nothing listened on {port}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn a_closed_pipe_ends_quietly_and_errors_exit_non_zero_naming_what_was_tried() {
    // Output through `output::out` (mwb world) and through a plain println! (mwb scene): the
    // reader is gone before the command writes.
    for args in [
        &[
            "world",
            "--scene",
            "tumble",
            "--seed",
            "7",
            "--quality",
            "draft",
        ][..],
        &["scene", "tumble"][..],
    ] {
        let mut child = mwb()
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("spawning mwb {args:?}: {e}"));
        drop(child.stdout.take());
        let mut stderr = String::new();
        if let Some(mut e) = child.stderr.take() {
            let _ = e.read_to_string(&mut stderr);
        }
        let status = wait(&mut child, LIMIT, "mwb with a closed stdout");
        assert!(status.success(), "mwb {args:?}: {status}, stderr {stderr}");
        assert!(!stderr.contains("panicked"), "mwb {args:?}: {stderr}");
    }

    // Nothing listens: the error names the endpoint, where it came from and what to pass.
    let port = free_port().unwrap_or_else(|e| panic!("{e:#}"));
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let (status, _, stderr) = run(
        mwb().args(["status", "--connect", &endpoint]),
        LIMIT,
        "mwb status",
    );
    assert!(!status.success());
    assert!(
        stderr.contains(&endpoint) && stderr.contains("given with --connect"),
        "{stderr}"
    );
    let (status, _, stderr) = run(
        mwb().args(["job", "list"]).env("MWB_CONNECT", &endpoint),
        LIMIT,
        "mwb job list",
    );
    assert!(!status.success());
    assert!(
        stderr.contains(&endpoint) && stderr.contains("from $MWB_CONNECT"),
        "{stderr}"
    );
    assert!(stderr.contains("--connect ENDPOINT"), "{stderr}");

    // A bad argument is an error, not a quiet nothing.
    let (status, _, stderr) = run(
        mwb().args(["world", "--scene", "no-such-scene", "--seed", "1"]),
        LIMIT,
        "mwb world",
    );
    assert!(!status.success());
    assert!(stderr.contains("no-such-scene"), "{stderr}");
}

#[test]
fn a_job_that_cannot_complete_says_why_and_fails() {
    // A full store: every world is refused for memory; the demo used to wait for ever.
    let (status, _, stderr) = run(
        mwb().args([
            "demo",
            "--memory-cap-mib",
            "0",
            "--worlds",
            "20",
            "--samplers",
            "1",
            "--quality",
            "draft",
            "--space",
            &format!("full{}", std::process::id()),
        ]),
        LIMIT,
        "mwb demo with a full store",
    );
    assert!(!status.success(), "{stderr}");
    assert!(
        stderr.contains("store full: 0 of 20 worlds kept")
            && stderr.contains("raise --memory-cap-mib or add a shard"),
        "{stderr}"
    );

    // No sampler anywhere: said at once on submit, and --wait gives up saying why.
    let port = free_port().unwrap_or_else(|e| panic!("{e:#}"));
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let space = format!("nosampler{}", std::process::id());
    let mut procs = Procs(Vec::new());
    procs.spawn(
        "store",
        &["store", "--listen", &endpoint, "--space", &space],
    );
    // The store must be listening before a client connects (a busy machine starts it slowly).
    wait_port(port);
    let (status, _, stderr) = run(
        mwb()
            .args(["job", "submit", "tumble", "--worlds", "3", "--wait"])
            .args(["--timeout", "100", "--space", &space])
            .env("MWB_CONNECT", &endpoint),
        LIMIT,
        "mwb job submit --wait",
    );
    assert!(!status.success(), "{stderr}");
    assert!(
        stderr.contains("warning: no sampler node is alive")
            && stderr.contains("cannot complete (0/3 worlds)")
            && !stderr.contains("did not finish within"),
        "{stderr}"
    );
}

/// Fetches stored world `index` over the bus.
fn stored_world(endpoint: &str, space: &str, index: u32) -> mwb_proto::v1::World {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap_or_else(|e| panic!("{e}"));
    rt.block_on(async {
        let bus = mwb::bus::BusArgs {
            connect: vec![endpoint.to_owned()],
            listen: vec![],
            config: None,
            mode: None,
            space: space.to_owned(),
            multicast: false,
        };
        let session = tokio::time::timeout(Duration::from_secs(30), bus.open(bus.client_default()))
            .await
            .unwrap_or_else(|_| panic!("opening a session timed out"))
            .unwrap_or_else(|e| panic!("{e:#}"));
        let keys = mwb_core::keys::Keys::new(space).unwrap_or_else(|e| panic!("{e}"));
        let w = tokio::time::timeout(
            Duration::from_secs(30),
            mwb::client::fetch_world(&session, &keys, index),
        )
        .await
        .unwrap_or_else(|_| panic!("fetching world {index} timed out"))
        .unwrap_or_else(|e| panic!("{e:#}"))
        .unwrap_or_else(|| panic!("no store holds world {index}"));
        mwb::bus::close(session).await;
        w
    })
}

fn json_line(stdout: &str) -> Value {
    let line = stdout.lines().last().unwrap_or_default();
    serde_json::from_str(line).unwrap_or_else(|e| panic!("{e}: {stdout:?}"))
}

#[test]
fn a_stayed_demo_takes_more_jobs_and_its_worlds_regenerate_from_their_seeds() {
    let port = free_port().unwrap_or_else(|e| panic!("{e:#}"));
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let space = format!("stay{}", std::process::id());
    let mut procs = Procs(Vec::new());
    procs.spawn(
        "demo",
        &[
            "demo",
            "--stay",
            "--listen",
            &endpoint,
            "--space",
            &space,
            "--worlds",
            "3",
            "--samplers",
            "1",
            "--quality",
            "draft",
        ],
    );
    wait_port(port);

    // The demo's samplers serve on while it stays: another job completes.
    let (status, stdout, stderr) = run(
        mwb()
            .args([
                "job", "submit", "tumble", "--worlds", "2", "--wait", "--json",
            ])
            .args(["--timeout", "100", "--space", &space])
            .env("MWB_CONNECT", &endpoint),
        LIMIT,
        "mwb job submit --wait against mwb demo --stay",
    );
    assert!(status.success(), "{stderr}");
    let submitted = json_line(&stdout);
    assert_eq!(submitted["done"], 2, "{stdout}");
    assert_eq!(submitted["closed"], true, "{stdout}");

    // A stored world, and its regeneration from (scene, seed) alone: the same digest.
    let world = stored_world(&endpoint, &space, 0);
    let done = world.done.clone().unwrap_or_default();
    let stored = mwb_node::world_digest(&world.segments, &done);
    let seed = format!("{:#x}", done.seed);
    let (status, stdout, stderr) = run(
        mwb().args([
            "world",
            "--scene",
            "tumble",
            "--seed",
            &seed,
            "--quality",
            "draft",
            "--json",
        ]),
        LIMIT,
        "mwb world",
    );
    assert!(status.success(), "{stderr}");
    let regenerated = json_line(&stdout);
    assert_eq!(regenerated["digest"], format!("{stored:#010x}"), "{stdout}");
    assert_eq!(regenerated["frames"], done.frame_count, "{stdout}");

    // --check finds the scene and quality from the stored world and compares; another seed
    // is caught.
    let check = |seed: &str| {
        run(
            mwb()
                .args(["world", "--seed", seed, "--check", "0", "--json"])
                .args(["--space", &space, "--connect", &endpoint]),
            LIMIT,
            "mwb world --check",
        )
    };
    let (status, stdout, stderr) = check(&seed);
    assert!(status.success(), "{stderr}");
    assert_eq!(json_line(&stdout)["matches"], true, "{stdout}");
    let (status, stdout, stderr) = check(&format!("{:#x}", done.seed ^ 1));
    assert!(!status.success(), "{stdout}");
    assert!(stderr.contains("the seeds differ"), "{stderr}");
}

/// Issue 19: `mwb scene` prints the simulation plan of the preset asked for, and a scene the
/// simulator cannot do faithfully exits non-zero naming the body, the field and the limit,
/// before any world is sampled.
#[test]
fn mwb_scene_prints_the_plan_and_refuses_what_the_simulator_cannot_do() {
    let limit = Duration::from_secs(60);
    let (status, stdout, stderr) = run(
        mwb().args(["scene", "tumble", "--sim", "draft"]),
        limit,
        "mwb scene --sim draft",
    );
    assert!(status.success(), "{stderr}");
    assert!(
        stdout.contains("simulation: draft: 1 substep x 1 iteration, CCD on 4 of 5 bodies"),
        "{stdout}"
    );
    // A 0.1 m ball at 1000 m/s against a 0.1 m wall tunnels (extremes matrix): refused.
    let dir = std::env::temp_dir().join(format!("mwb-limits-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let file = dir.join("bullet.toml");
    std::fs::write(
        &file,
        "name = \"bullet\"\n[settings]\nend_time = 0.2\ngravity = [0, 0, 0]\n\
         [[material]]\nname = \"m\"\n\
         [[static]]\nname = \"wall\"\nshape = \"box\"\nsize = [0.1, 2, 2]\nmaterial = \"m\"\nposition = [5, 1, 0]\n\
         [[body]]\nname = \"bullet\"\nshape = \"sphere\"\nradius = 0.05\nmaterial = \"m\"\n\
         position = [0, 1, 0]\nlinvel = [1000, 0, 0]\n",
    )
    .expect("scene file");
    let (status, stdout, stderr) = run(
        mwb().arg("scene").arg(&file),
        limit,
        "mwb scene bullet.toml",
    );
    assert!(!status.success(), "{stdout}");
    assert!(
        stdout.contains("refused: body \"bullet\": field `linvel`"),
        "{stdout}"
    );
    assert!(
        stderr.contains("cannot do this scene faithfully"),
        "{stderr}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
