//! `mwb query` against a running cluster of OS processes (issue 4: "the CLI works against a
//! running `mwb demo`-style cluster"): a store (a router, running node-query in-process) and a
//! sampler; a job submitted with `mwb job submit --wait`; then scripted browsing with `--json`.

mod common;

use common::{Procs, wait_port};
use mwb::bench::free_port;
use serde_json::Value;
use std::process::Command;

const WORLDS: u64 = 30;

/// Runs `mwb <args> --connect <endpoint> --space <space>`; returns stdout, panics with stderr
/// on failure.
fn mwb(endpoint: &str, space: &str, args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_mwb"))
        .args(args)
        .args(["--connect", endpoint, "--space", space, "--timeout", "30"])
        .env("RUST_LOG", "warn")
        .output()
        .unwrap_or_else(|e| panic!("running mwb {args:?}: {e}"));
    assert!(
        out.status.success(),
        "mwb {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn json(endpoint: &str, space: &str, args: &[&str]) -> Value {
    let mut all = args.to_vec();
    all.push("--json");
    let text = mwb(endpoint, space, &all);
    serde_json::from_str(text.trim()).unwrap_or_else(|e| panic!("{args:?}: {e}: {text}"))
}

fn u(v: &Value, key: &str) -> u64 {
    v[key]
        .as_u64()
        .unwrap_or_else(|| panic!("no number {key} in {v}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scripted_browsing_against_a_running_cluster() {
    let port = free_port().unwrap_or_else(|e| panic!("{e}"));
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let space = format!("qcli{}", std::process::id());
    let mut procs = Procs(Vec::new());
    procs.spawn(
        "store",
        &["store", "--listen", &endpoint, "--space", &space],
    );
    wait_port(port).await;
    procs.spawn(
        "sampler",
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
    // `job submit` takes no --timeout flag of ours: its own bounds it.
    let out = Command::new(env!("CARGO_BIN_EXE_mwb"))
        .args([
            "job",
            "submit",
            "tumble",
            "--worlds",
            "30",
            "--wait",
            "--timeout",
            "120",
            "--json",
            "--connect",
            &endpoint,
            "--space",
            &space,
        ])
        .env("RUST_LOG", "warn")
        .output()
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );

    let (e, s) = (endpoint.as_str(), space.as_str());
    let st = json(e, s, &["query", "list"]);
    assert_eq!((u(&st, "worlds"), u(&st, "result")), (WORLDS, WORLDS));

    // A world-space box around the middle of the ground, for every object.
    let st = json(
        e,
        s,
        &[
            "query",
            "add",
            "--aabb=-0.5,0,-0.5,0.5,0.3,0.5",
            "--objects",
            "all",
        ],
    );
    let constraints = st["constraints"].as_array().cloned().unwrap_or_default();
    assert_eq!(constraints.len(), 1);
    assert_eq!(constraints[0]["objects"].as_array().map(Vec::len), Some(5));
    let kept1 = u(&constraints[0], "satisfied");
    // A camera file and a screen rectangle: looking down from 6 m at the origin.
    let dir = std::env::temp_dir().join(format!("mwb-qcli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{e}"));
    let camera = dir.join("camera.json");
    std::fs::write(
        &camera,
        r#"{"position":[0,6,0],"rotation":[-0.7071067811865476,0,0,0.7071067811865476],
            "intrinsics":{"model":"vertical_fov","fov_y_rad":0.9},
            "viewport":{"width":1280,"height":720}}"#,
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let cam = camera.to_string_lossy().into_owned();
    let st = json(
        e,
        s,
        &[
            "query",
            "add",
            "--negative",
            "--camera",
            &cam,
            "--rect",
            "0,0,300,720",
            "--objects",
            "0,1",
            "--window",
            "0.5:3",
        ],
    );
    let cs = st["constraints"].as_array().cloned().unwrap_or_default();
    assert_eq!(cs.len(), 2);
    assert_eq!(cs[1]["id"].as_u64(), Some(2));
    assert_eq!(cs[1]["polarity"].as_str(), Some("negative"));
    let both = u(&st, "result");
    assert!(both <= kept1.min(u(&cs[1], "satisfied")));

    // The survivors, ranked; every ranked world is a survivor, scores ascending.
    let res = json(e, s, &["query", "result"]);
    let survivors: Vec<u64> = res["worlds"]
        .as_array()
        .map(|a| a.iter().filter_map(Value::as_u64).collect())
        .unwrap_or_default();
    assert_eq!(survivors.len() as u64, both);
    let rank = json(e, s, &["query", "rank", "--by", "time-to-rest", "-k", "5"]);
    let rows = rank["rows"].as_array().cloned().unwrap_or_default();
    assert_eq!(rows.len() as u64, both.min(5));
    let scores: Vec<f64> = rows.iter().filter_map(|r| r["score"].as_f64()).collect();
    assert!(scores.windows(2).all(|w| w[0] <= w[1]), "{scores:?}");
    for r in &rows {
        assert!(survivors.contains(&r["world"].as_u64().unwrap_or(u64::MAX)));
    }

    // One world's summary, in text and JSON.
    let any = survivors.first().copied().unwrap_or(0).to_string();
    let show = json(e, s, &["query", "show", &any]);
    assert_eq!(show["objects"].as_array().map(Vec::len), Some(5));
    if both > 0 {
        assert_eq!(show["constraints_satisfied"].as_u64(), Some(2));
        assert_eq!(show["in_result"].as_bool(), Some(true));
    }
    let text = mwb(e, s, &["query", "show", &any]);
    assert!(text.contains("turned[rad]"), "{text}");

    // Remove the *first* constraint, undo, redo: counts follow without re-evaluation.
    let st = json(e, s, &["query", "remove", "1"]);
    assert_eq!(st["constraints"].as_array().map(Vec::len), Some(1));
    let st = json(e, s, &["query", "undo"]);
    assert_eq!(u(&st, "result"), both);
    let st = json(e, s, &["query", "redo"]);
    assert_eq!(st["constraints"].as_array().map(Vec::len), Some(1));
    // Bad input names the field and fails.
    let bad = Command::new(env!("CARGO_BIN_EXE_mwb"))
        .args([
            "query",
            "add",
            "--aabb",
            "1,2,3",
            "--objects",
            "0",
            "--connect",
            e,
            "--space",
            s,
        ])
        .output()
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("--aabb"));
    let _ = std::fs::remove_dir_all(&dir);
    drop(procs);
}
