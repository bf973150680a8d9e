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

/// Runs `mwb <args> --connect <endpoint> --space <space>` expecting failure; returns stderr.
fn mwb_fails(endpoint: &str, space: &str, args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_mwb"))
        .args(args)
        .args(["--connect", endpoint, "--space", space, "--timeout", "30"])
        .env("RUST_LOG", "warn")
        .output()
        .unwrap_or_else(|e| panic!("running mwb {args:?}: {e}"));
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(
        !out.status.success(),
        "mwb {args:?} should have failed; stdout {}",
        String::from_utf8_lossy(&out.stdout)
    );
    stderr
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

    issue_24_names_rest_poses_rankings_and_exit_codes(e, s, &cam);
    let _ = std::fs::remove_dir_all(&dir);
    drop(procs);
}

/// Issue 24 against the same cluster (tumble: bodies crate, plank, brick, die, slab; worlds
/// end by 6 s), each part in its own browsing session.
fn issue_24_names_rest_poses_rankings_and_exit_codes(e: &str, s: &str, cam: &str) {
    let names = ["crate", "plank", "brick", "die", "slab"];
    let bodies = json(e, s, &["query", "bodies"]);
    let scenes = bodies["scenes"].as_array().cloned().unwrap_or_default();
    assert_eq!(scenes.len(), 1, "{bodies}");
    assert_eq!(scenes[0]["names"], serde_json::json!(names));
    assert_eq!(u(&scenes[0], "worlds"), WORLDS);

    // Objects by name; an out-of-range index is refused naming the body count.
    let st = json(
        e,
        s,
        &[
            "query",
            "add",
            "--session",
            "names",
            "--aabb=-9,-9,-9,9,9,9",
            "--objects",
            "die, crate",
        ],
    );
    assert_eq!(st["constraints"][0]["objects"], serde_json::json!([3, 0]));
    let err = mwb_fails(
        e,
        s,
        &[
            "query",
            "add",
            "--session",
            "names",
            "--aabb=0,0,0,1,1,1",
            "--objects",
            "9",
        ],
    );
    assert!(err.contains("the scene has 5 bodies"), "{err}");
    let err = mwb_fails(
        e,
        s,
        &[
            "query",
            "add",
            "--session",
            "names",
            "--aabb=0,0,0,1,1,1",
            "--objects",
            "S",
        ],
    );
    assert!(
        err.contains("no body of that name") && err.contains("crate, plank"),
        "{err}"
    );
    let list = mwb(e, s, &["query", "list", "--session", "names"]);
    assert!(list.contains("any of die (#3), crate (#0)"), "{list}");

    // A box around the whole scene during a window long after every world ended: every world's
    // bodies rest in it (before issue 24 no world matched). The final pose says the same; a
    // far-away box holds no final pose; `--all` over two bodies needs both.
    for (args, want) in [
        (vec!["--window", "50:60", "--objects", "all"], WORLDS),
        (vec!["--final", "--objects", "all", "--all"], WORLDS),
        (
            vec!["--window", "50:60", "--objects", "crate,slab", "--all"],
            WORLDS,
        ),
    ] {
        let mut all = vec![
            "query",
            "add",
            "--session",
            "rest",
            "--aabb=-50,-50,-50,50,50,50",
        ];
        all.extend(args.iter().copied());
        let st = json(e, s, &all);
        let last = st["constraints"].as_array().and_then(|c| c.last().cloned());
        let last = last.unwrap_or_default();
        assert_eq!(u(&last, "satisfied"), want, "{args:?}: {st}");
        json(e, s, &["query", "undo", "--session", "rest"]);
    }
    let st = json(
        e,
        s,
        &[
            "query",
            "add",
            "--session",
            "rest",
            "--aabb=40,40,40,50,50,50",
            "--final",
            "--objects",
            "all",
        ],
    );
    assert_eq!(u(&st["constraints"][0], "satisfied"), 0, "{st}");
    assert_eq!(st["constraints"][0]["scope"].as_str(), Some("final_pose"));
    let err = mwb_fails(
        e,
        s,
        &[
            "query",
            "add",
            "--session",
            "rest",
            "--aabb=0,0,0,1,1,1",
            "--final",
            "--window",
            "1:2",
            "--objects",
            "0",
        ],
    );
    assert!(err.contains("--window") || err.contains("window"), "{err}");

    // Rankings: worlds with a body still moving at the end have no time to rest and come last;
    // a ranked world's score is the last of its bodies to rest; the text names the aggregate,
    // the unit and the count without a value.
    let rank = json(
        e,
        s,
        &[
            "query",
            "rank",
            "--session",
            "rank",
            "--by",
            "time-to-rest",
            "-k",
            "100",
        ],
    );
    let rows = rank["rows"].as_array().cloned().unwrap_or_default();
    assert_eq!(rows.len() as u64, WORLDS);
    let unscored = u(&rank, "unscored");
    let first_none = rows
        .iter()
        .position(|r| r["score"].is_null())
        .unwrap_or(rows.len());
    assert_eq!((rows.len() - first_none) as u64, unscored);
    assert!(rows[first_none..].iter().all(|r| r["score"].is_null()));
    for r in rows.iter().take(3).chain(rows.get(first_none)) {
        let w = r["world"].as_u64().unwrap_or(u64::MAX).to_string();
        let show = json(e, s, &["query", "show", "--session", "rank", &w]);
        let objs = show["objects"].as_array().cloned().unwrap_or_default();
        let rested = objs
            .iter()
            .all(|o| o["came_to_rest"].as_bool() == Some(true));
        match r["score"].as_f64() {
            Some(score) => {
                assert!(rested, "world {w} ranked with a moving body: {show}");
                let max = objs
                    .iter()
                    .filter_map(|o| o["time_to_rest_s"].as_f64())
                    .fold(0.0, f64::max);
                assert_eq!(score, max, "world {w}");
            }
            None => assert!(!rested, "world {w} rested but has no value: {show}"),
        }
        assert_eq!(show["bodies"], serde_json::json!(names));
    }
    let text = mwb(e, s, &["query", "rank", "--session", "rank", "-k", "3"]);
    assert!(
        text.contains("time to rest [s], max over crate (#0), plank (#1)")
            && text.contains(&format!("{unscored} without a value")),
        "{text}"
    );
    let text = mwb(e, s, &["query", "show", "--session", "rank", "0"]);
    assert!(text.contains("crate") && text.contains("slab"), "{text}");

    // Errors exit non-zero: a world no store holds, redo/undo with nothing to do, a screen
    // rectangle wholly outside the 1280 × 720 viewport (naming the field).
    let err = mwb_fails(e, s, &["query", "show", "--session", "exit", "999"]);
    assert!(err.contains("no store holds world 999"), "{err}");
    let err = mwb_fails(e, s, &["query", "redo", "--session", "exit"]);
    assert!(err.contains("nothing to redo"), "{err}");
    let err = mwb_fails(e, s, &["query", "undo", "--session", "exit"]);
    assert!(err.contains("nothing to undo"), "{err}");
    let err = mwb_fails(
        e,
        s,
        &[
            "query",
            "add",
            "--session",
            "exit",
            "--camera",
            cam,
            "--rect",
            "1300,100,1400,200",
            "--objects",
            "0",
        ],
    );
    assert!(
        err.contains("rect.x0") && err.contains("1280 × 720"),
        "{err}"
    );
}
