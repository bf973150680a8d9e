//! `mwb refine` against a running cluster (store and sampler as OS processes): a sampled world is
//! refined from the first frame a picked body enters a box; the refined worlds are stored,
//! browsable (`mwb query list` counts them) and exportable, start as their parent did, and can be
//! refined again; kept worlds get children of an edited scene (`mwb scene edit`, a published
//! revision applied again); every bad request is refused before anything is submitted, naming
//! what is wrong.

mod common;

use common::{Procs, wait_port};
use mwb::bench::free_port;
use serde_json::Value;
use std::process::{Command, Output};

struct Bus {
    endpoint: String,
    space: String,
}

impl Bus {
    fn run(&self, args: &[&str]) -> Output {
        Command::new(env!("CARGO_BIN_EXE_mwb"))
            .args(args)
            .args(["--connect", &self.endpoint, "--space", &self.space])
            .env("RUST_LOG", "warn")
            .output()
            .unwrap_or_else(|e| panic!("running mwb {args:?}: {e}"))
    }

    fn ok(&self, args: &[&str]) -> String {
        let out = self.run(args);
        assert!(
            out.status.success(),
            "mwb {args:?} failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    fn json(&self, args: &[&str]) -> Value {
        let text = self.ok(args);
        serde_json::from_str(text.trim()).unwrap_or_else(|e| panic!("{args:?}: {e}: {text}"))
    }

    fn fails(&self, args: &[&str]) -> String {
        let out = self.run(args);
        assert!(
            !out.status.success(),
            "mwb {args:?} should have failed: {}",
            String::from_utf8_lossy(&out.stdout)
        );
        String::from_utf8_lossy(&out.stderr).into_owned()
    }
}

fn u(v: &Value, key: &str) -> u64 {
    v[key]
        .as_u64()
        .unwrap_or_else(|| panic!("no number {key} in {v}"))
}

/// The CSV rows of frame 0 (world and seed columns dropped).
fn first_frame(csv: &std::path::Path) -> Vec<String> {
    let text = std::fs::read_to_string(csv).unwrap_or_else(|e| panic!("{e}"));
    text.lines()
        .skip(1)
        .filter_map(|l| {
            let fields: Vec<&str> = l.splitn(4, ',').collect();
            (fields.len() == 4 && fields[2] == "0").then(|| fields[3].to_owned())
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refine_a_stored_world_then_its_child() {
    let port = free_port().unwrap_or_else(|e| panic!("{e}"));
    let bus = Bus {
        endpoint: format!("tcp/127.0.0.1:{port}"),
        space: format!("refine{}", std::process::id()),
    };
    let mut procs = Procs(Vec::new());
    procs.spawn(
        "store",
        &["store", "--listen", &bus.endpoint, "--space", &bus.space],
    );
    wait_port(port).await;
    procs.spawn(
        "sampler",
        &[
            "sampler",
            "--connect",
            &bus.endpoint,
            "--space",
            &bus.space,
            "--workers",
            "1",
        ],
    );
    bus.ok(&[
        "job",
        "submit",
        "tumble",
        "--worlds",
        "2",
        "--wait",
        "--timeout",
        "120",
    ]);

    // The crate is thrown along +x from x = −1.5: the slab x ≥ −1.3 is entered a few frames on.
    let slab = "--aabb=-1.3,-1,-5,10,10,5";
    let r = bus.json(&[
        "refine",
        "--world",
        "0",
        "--objects",
        "crate",
        slab,
        "--worlds",
        "3",
        "--id",
        "refined",
        "--wait",
        "--timeout",
        "120",
        "--json",
    ]);
    assert_eq!(r["job"], "refined");
    assert_eq!(r["objects"], serde_json::json!([0]));
    assert_eq!(
        (r["done"].as_u64(), r["closed"].as_bool()),
        (Some(3), Some(true))
    );
    let branch = r["branch_frame"].as_u64().unwrap_or(0);
    assert!(branch > 0, "the crate starts outside the slab: {r}");

    // Stored and browsable: the session sees parent, siblings and children.
    let list = bus.json(&["query", "list", "--session", "refine-test", "--json"]);
    assert_eq!(list["worlds"].as_u64(), Some(5), "{list}");

    // Exportable, and as its parent at the start.
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let parent_csv = dir.path().join("parent.csv");
    let child_csv = dir.path().join("child.csv");
    let p = |x: &std::path::Path| x.to_str().unwrap_or_else(|| panic!("path")).to_owned();
    bus.ok(&[
        "export",
        "--world",
        "0",
        "--format",
        "csv",
        "--out",
        &p(&parent_csv),
    ]);
    bus.ok(&[
        "export",
        "--world",
        "2",
        "--format",
        "csv",
        "--out",
        &p(&child_csv),
    ]);
    let (a, b) = (first_frame(&parent_csv), first_frame(&child_csv));
    assert_eq!(a.len(), 5);
    assert_eq!(a, b, "a refined world starts where its parent did");

    // A refined world refines again (its lineage grows by one step).
    let again = bus.json(&[
        "refine",
        "--world",
        "2",
        "--objects",
        "0",
        "--aabb=-1.2,-1,-5,10,10,5",
        "--worlds",
        "1",
        "--wait",
        "--timeout",
        "120",
        "--json",
    ]);
    assert_eq!(again["done"].as_u64(), Some(1), "{again}");
    assert!(again["branch_frame"].as_u64().unwrap_or(0) >= branch);

    // Deterministic in (lineage, seed): each refined world, regenerated in another process
    // from the lineage it was stored with, has the stored world's digest.
    for world in ["2", "5"] {
        let show = bus.json(&["query", "show", world, "--json"]);
        let steps = show["refined"]["steps"].as_array().map(Vec::len);
        assert_eq!(steps, Some(if world == "2" { 1 } else { 2 }), "{show}");
        assert_eq!(show["refined"]["steps"][0]["frame"].as_u64(), Some(branch));
        // New motion from its own branch (the last step) on.
        let own = show["refined"]["steps"][steps.unwrap_or(1) - 1]["frame"].as_u64();
        assert_eq!(show["refined"]["active_from"][0].as_u64(), own, "{show}");
        let text = bus.ok(&["query", "show", world]);
        assert!(text.contains("refined (§4.5) from world seed"), "{text}");
        let seed = format!("{:#x}", u(&show, "seed"));
        let check = bus.json(&["world", "--seed", &seed, "--check", world, "--json"]);
        assert_eq!(
            check["matches"].as_bool(),
            Some(true),
            "world {world}: {check}"
        );
    }

    // Scene edits (§4.5 from frame 0): world 0 without its brick, published as revision 1.
    let e = bus.json(&[
        "scene",
        "edit",
        "--world",
        "0",
        "--remove",
        "brick",
        "--worlds",
        "2",
        "--id",
        "edited",
        "--wait",
        "--timeout",
        "120",
        "--json",
    ]);
    assert_eq!(
        (u(&e, "revision"), e["published"].as_bool()),
        (1, Some(true)),
        "{e}"
    );
    assert_eq!(e["removed"], serde_json::json!(["brick"]), "{e}");
    assert_eq!(e["jobs"][0]["job"], "edited", "{e}");
    assert_eq!(e["jobs"][0]["done"].as_u64(), Some(2), "{e}");
    let list = bus.json(&["query", "list", "--session", "edit-test", "--json"]);
    assert_eq!(list["worlds"].as_u64(), Some(8), "{list}");
    // Exportable as worlds of the edited scene: four bodies, each starting where its parent
    // started (unchanged bodies keep the parent's random draws).
    let edited_csv = dir.path().join("edited.csv");
    bus.ok(&[
        "export",
        "--world",
        "6",
        "--format",
        "csv",
        "--out",
        &p(&edited_csv),
    ]);
    let by_name = |rows: Vec<String>| -> std::collections::BTreeMap<String, String> {
        rows.iter()
            .filter_map(|r| {
                // time,body,name,pose…: keyed by name, the body index dropped.
                let f: Vec<&str> = r.splitn(4, ',').collect();
                (f.len() == 4).then(|| (f[2].to_owned(), f[3].to_owned()))
            })
            .collect()
    };
    let (mut parent_rows, edited_rows) = (by_name(a.clone()), by_name(first_frame(&edited_csv)));
    assert!(parent_rows.remove("brick").is_some());
    assert_eq!(
        edited_rows, parent_rows,
        "an edited world starts where its parent did"
    );
    // The same revision applied to another kept world.
    let again = bus.json(&[
        "scene",
        "edit",
        "--world",
        "1",
        "--revision",
        "1",
        "--worlds",
        "1",
        "--wait",
        "--timeout",
        "120",
        "--json",
    ]);
    assert_eq!(
        (u(&again, "revision"), again["published"].as_bool()),
        (1, Some(false))
    );
    assert_eq!(again["jobs"][0]["done"].as_u64(), Some(1), "{again}");
    // Refused, naming what is wrong: a revision nobody has, a body the scene lacks, an edit of
    // the settings, a world made by an edit (to edit or to refine).
    let e = bus.fails(&["scene", "edit", "--world", "0", "--revision", "9"]);
    assert!(e.contains("--revision 9: no store has it"), "{e}");
    let e = bus.fails(&["scene", "edit", "--world", "0", "--remove", "anvil"]);
    assert!(e.contains("anvil"), "{e}");
    let longer = dir.path().join("longer.toml");
    let text = mwb_core::scene::builtin::TUMBLE.replace("end_time = 6.0", "end_time = 7.0");
    std::fs::write(&longer, text).unwrap_or_else(|e| panic!("{e}"));
    let e = bus.fails(&["scene", "edit", "--world", "0", "--file", &p(&longer)]);
    assert!(e.contains("settings: `end_time` changed"), "{e}");
    let e = bus.fails(&["scene", "edit", "--world", "6", "--remove", "die"]);
    assert!(
        e.contains("--world 6") && e.contains("scene edit (revision 1)"),
        "{e}"
    );
    let e = bus.fails(&["refine", "--world", "6", "--objects", "0", slab]);
    assert!(
        e.contains("--world 6") && e.contains("scene edit (revision 1)"),
        "{e}"
    );

    // Refusals, before anything is submitted.
    let e = bus.fails(&["refine", "--world", "99", "--objects", "0", slab]);
    assert!(e.contains("--world 99: no store holds it"), "{e}");
    let e = bus.fails(&["refine", "--world", "0", "--objects", "anvil", slab]);
    assert!(e.contains("--objects"), "{e}");
    let e = bus.fails(&["refine", "--world", "0", "--objects", "7", slab]);
    assert!(e.contains("--objects"), "{e}");
    let e = bus.fails(&[
        "refine",
        "--world",
        "0",
        "--objects",
        "0",
        "--aabb=50,50,50,51,51,51",
    ]);
    assert!(e.contains("the box"), "{e}");
    let e = bus.fails(&[
        "refine",
        "--world",
        "0",
        "--objects",
        "0",
        "--rect",
        "0,0,9,9",
    ]);
    assert!(e.contains("--camera"), "{e}");
    let jobs = bus.ok(&["job", "list", "--json"]);
    let jobs: Value = serde_json::from_str(jobs.trim()).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(jobs.as_array().map(Vec::len), Some(5), "{jobs}");
}
