//! `mwb export` end to end, as a user runs it: from a recording of `mwb demo --record`, from a
//! running store (store and sampler as OS processes), and from a seed alone — the three agree
//! on every pose — and bad input (unknown world, damaged recording, wrong scene, unknown
//! format) fails naming the thing.

mod common;

use common::{Procs, wait_port};
use mwb::bench::free_port;
use serde_json::Value;
use std::path::Path;
use std::process::{Command, Output};

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_mwb"))
        .args(args)
        .env("RUST_LOG", "warn")
        .output()
        .unwrap_or_else(|e| panic!("running mwb {args:?}: {e}"))
}

/// Runs `mwb <args>`, which must succeed; its stdout.
fn ok(args: &[&str]) -> String {
    let out = run(args);
    assert!(
        out.status.success(),
        "mwb {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Runs `mwb <args>`, which must fail; its stderr.
fn fails(args: &[&str]) -> String {
    let out = run(args);
    assert!(!out.status.success(), "mwb {args:?} succeeded");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// The JSON lines of `mwb export … --json`, one per file.
fn summaries(stdout: &str) -> Vec<Value> {
    stdout
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{e}: {l}")))
        .collect()
}

fn path(p: &Path) -> &str {
    p.to_str().unwrap_or_else(|| panic!("non-UTF-8 path"))
}

/// CSV rows without their first field (the world index, which a simulated world lacks).
fn rows_without_world(csv: &Path, world: Option<&str>) -> Vec<String> {
    let text = std::fs::read_to_string(csv).unwrap_or_else(|e| panic!("{e}"));
    text.lines()
        .skip(1)
        .filter_map(|l| {
            let (w, rest) = l.split_once(',')?;
            world.is_none_or(|want| w == want).then(|| rest.to_owned())
        })
        .collect()
}

fn glb_nodes(file: &Path) -> usize {
    let bytes = std::fs::read(file).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
    let doc = gltf::Gltf::from_slice(&bytes).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(doc.animations().count(), 1);
    doc.nodes().count()
}

#[test]
fn export_from_a_recording_and_from_the_seed_agree() {
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let rec = dir.path().join("session.mcap");
    let space = format!("export{}", std::process::id());
    ok(&[
        "demo",
        "--worlds",
        "3",
        "--samplers",
        "1",
        "--space",
        &space,
        "--record",
        path(&rec),
    ]);

    // Two worlds to one CSV; both named in the summary with their seeds.
    let csv = dir.path().join("rec.csv");
    let out = ok(&[
        "export",
        "--from",
        path(&rec),
        "--worlds",
        "0,2",
        "--format",
        "csv",
        "--out",
        path(&csv),
        "--json",
    ]);
    let s = summaries(&out);
    assert_eq!(s.len(), 1);
    assert_eq!(s[0]["worlds"], serde_json::json!([0, 2]));
    let seed = s[0]["seeds"][0]
        .as_u64()
        .unwrap_or_else(|| panic!("no seed in {}", s[0]));

    // The same world regenerated from its seed alone: the same rows, pose for pose.
    let sim = dir.path().join("sim.csv");
    ok(&[
        "export",
        "--scene",
        "tumble",
        "--seed",
        &seed.to_string(),
        "--format",
        "csv",
        "--out",
        path(&sim),
    ]);
    let from_recording = rows_without_world(&csv, Some("0"));
    assert!(from_recording.len() > 100 * 5);
    assert_eq!(from_recording, rows_without_world(&sim, None));

    // glb: one file per world, a node per static and body under one root.
    let glb = dir.path().join("w.glb");
    ok(&[
        "export",
        "--from",
        path(&rec),
        "--worlds",
        "0,1",
        "--out",
        path(&glb),
    ]);
    for w in ["w-0.glb", "w-1.glb"] {
        assert_eq!(glb_nodes(&dir.path().join(w)), 1 + 1 + 5, "{w}");
    }
    // Foxglove and JSON write too.
    let fox = dir.path().join("w.mcap");
    ok(&[
        "export",
        "--from",
        path(&rec),
        "--world",
        "1",
        "--format",
        "foxglove",
        "--out",
        path(&fox),
    ]);
    let bytes = std::fs::read(&fox).unwrap_or_else(|e| panic!("{e}"));
    assert!(bytes.starts_with(b"\x89MCAP0\r\n"));
    let json = dir.path().join("w.json");
    ok(&[
        "export",
        "--from",
        path(&rec),
        "--world",
        "1",
        "--format",
        "json",
        "--out",
        path(&json),
    ]);
    let doc: Value =
        serde_json::from_slice(&std::fs::read(&json).unwrap_or_else(|e| panic!("{e}")))
            .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(doc["worlds"][0]["world"], 1);

    // Bad input.
    let out = path(&glb);
    let e = fails(&[
        "export",
        "--from",
        path(&rec),
        "--world",
        "99",
        "--out",
        out,
    ]);
    assert!(
        e.contains("world 99") && e.contains("3 complete worlds"),
        "{e}"
    );
    let e = fails(&[
        "export",
        "--from",
        path(&rec),
        "--world",
        "0",
        "--scene",
        "chute",
        "--out",
        out,
    ]);
    assert!(e.contains("not this world's scene"), "{e}");
    let e = fails(&[
        "export",
        "--from",
        path(&rec),
        "--world",
        "0",
        "--format",
        "obj",
        "--out",
        out,
    ]);
    assert!(e.contains("obj"), "{e}");
    let e = fails(&["export", "--out", out]);
    assert!(e.contains("which worlds"), "{e}");
    let whole = std::fs::read(&rec).unwrap_or_else(|e| panic!("{e}"));
    let cut = dir.path().join("cut.mcap");
    std::fs::write(&cut, &whole[..whole.len() / 2]).unwrap_or_else(|e| panic!("{e}"));
    let e = fails(&["export", "--from", path(&cut), "--world", "0", "--out", out]);
    assert!(e.contains("cut.mcap") && e.contains("byte"), "{e}");
    let junk = dir.path().join("junk.mcap");
    std::fs::write(&junk, b"not a recording at all").unwrap_or_else(|e| panic!("{e}"));
    let e = fails(&[
        "export",
        "--from",
        path(&junk),
        "--world",
        "0",
        "--out",
        out,
    ]);
    assert!(e.contains("junk.mcap"), "{e}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn export_from_a_running_store() {
    let port = free_port().unwrap_or_else(|e| panic!("{e}"));
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let space = format!("expcli{}", std::process::id());
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
    let bus = ["--connect", endpoint.as_str(), "--space", space.as_str()];
    let with_bus = |args: &[&str]| -> Vec<String> {
        args.iter().chain(&bus).map(|s| (*s).to_owned()).collect()
    };
    fn strs(v: &[String]) -> Vec<&str> {
        v.iter().map(String::as_str).collect()
    }
    ok(&strs(&with_bus(&[
        "job",
        "submit",
        "tumble",
        "--worlds",
        "2",
        "--wait",
        "--timeout",
        "120",
    ])));

    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let csv = dir.path().join("store.csv");
    let csv_s = path(&csv).to_owned();
    // The job is closed; the store holding its worlds still serves its scene (`q/job/<job>`),
    // so no --scene is needed, and the export equals the one with the scene given.
    let bare_csv = dir.path().join("bare.csv");
    ok(&strs(&with_bus(&[
        "export",
        "--world",
        "1",
        "--format",
        "csv",
        "--out",
        path(&bare_csv),
    ])));
    let out = ok(&strs(&with_bus(&[
        "export", "--world", "1", "--scene", "tumble", "--format", "csv", "--out", &csv_s, "--json",
    ])));
    assert_eq!(
        std::fs::read(&bare_csv).unwrap_or_else(|e| panic!("{e}")),
        std::fs::read(&csv).unwrap_or_else(|e| panic!("{e}")),
        "the store's scene and --scene give the same export"
    );
    let s = summaries(&out);
    let seed = s[0]["seeds"][0]
        .as_u64()
        .unwrap_or_else(|| panic!("no seed in {}", s[0]));
    let sim = dir.path().join("sim.csv");
    ok(&[
        "export",
        "--scene",
        "tumble",
        "--seed",
        &seed.to_string(),
        "--format",
        "csv",
        "--out",
        path(&sim),
    ]);
    assert_eq!(
        rows_without_world(&csv, Some("1")),
        rows_without_world(&sim, None)
    );
    let glb = dir.path().join("store.glb");
    let glb_s = path(&glb).to_owned();
    ok(&strs(&with_bus(&[
        "export", "--world", "0", "--scene", "tumble", "--out", &glb_s,
    ])));
    assert_eq!(glb_nodes(&glb), 1 + 1 + 5);

    let e = fails(&strs(&with_bus(&[
        "export", "--world", "7", "--scene", "tumble", "--out", &glb_s,
    ])));
    assert!(
        e.contains("world 7") && e.contains("no store holds it"),
        "{e}"
    );
    let e = fails(&strs(&with_bus(&[
        "export", "--world", "0", "--scene", "pachinko", "--out", &glb_s,
    ])));
    assert!(e.contains("not this world's scene"), "{e}");
}
