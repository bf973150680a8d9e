//! The live viewer against a running cluster of OS processes (a store, which runs node-query,
//! and a sampler): worlds arrive over the bus, a box dragged in the real UI (egui_kittest)
//! becomes a constraint in node-query's session whose survivor count `mwb query list` reports
//! too; the paths the viewer draws are the store's index (evaluating the box on them here gives
//! the store's survivors); ranking and playback of a picked world; the store SIGKILLed under
//! the running viewer and restarted from its journal (the link shown lost, a box drawn
//! meanwhile kept and, with the session's earlier edits, sent to the new node-query); and
//! `mwb viewer --screenshot` of the same cluster.

mod common;

use common::{Procs, wait_port};
use egui::{Event, Modifiers, PointerButton, Pos2, vec2};
use egui_kittest::Harness;
use egui_kittest::kittest::Queryable;
use mwb::bench::free_port;
use mwb_core::browse::ScreenRect;
use mwb_core::browse::api::{EditRecord, Reply, Request};
use mwb_viewer::draw::viewport_of;
use mwb_viewer::live::{LiveConfig, LiveLink};
use mwb_viewer::ui::SortBy;
use mwb_viewer::{ViewerApp, ViewerState};
use serde_json::Value;
use std::process::Command;
use std::sync::Arc;
use std::time::Duration;

const WORLDS: usize = 24;
/// Worlds of the job submitted from the viewer.
const MORE: usize = 6;
/// Worlds refined from one of them through the viewer.
const REFINED: usize = 3;

fn mwb(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_mwb"))
        .args(args)
        .env("RUST_LOG", "warn")
        .output()
        .unwrap_or_else(|e| panic!("running mwb {args:?}: {e}"))
}

fn ok(args: &[&str]) -> String {
    let out = mwb(args);
    assert!(
        out.status.success(),
        "mwb {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// `mwb query list --json` of a browsing session: its status as node-query reports it.
fn query_list(endpoint: &str, space: &str, session: &str) -> Value {
    let out = ok(&[
        "query",
        "list",
        "--session",
        session,
        "--json",
        "--connect",
        endpoint,
        "--space",
        space,
    ]);
    serde_json::from_str(out.trim()).unwrap_or_else(|e| panic!("{e}: {out}"))
}

/// Presses at `a`, moves to `b` in a few steps, releases there.
fn drag(h: &mut Harness<'_, ViewerApp>, a: Pos2, b: Pos2) {
    h.event(Event::PointerMoved(a));
    h.step();
    h.event(Event::PointerButton {
        pos: a,
        button: PointerButton::Primary,
        pressed: true,
        modifiers: Modifiers::NONE,
    });
    h.step();
    for k in 1..=4 {
        h.event(Event::PointerMoved(a + (b - a) * (k as f32 / 4.0)));
        h.step();
    }
    h.event(Event::PointerButton {
        pos: b,
        button: PointerButton::Primary,
        pressed: false,
        modifiers: Modifiers::NONE,
    });
    h.step();
    h.event(Event::PointerGone);
    h.step();
}

/// Runs frames of the harness until `done` holds (the bus task answers between them).
fn settle(
    rt: &tokio::runtime::Runtime,
    h: &mut Harness<'_, ViewerApp>,
    what: &str,
    done: impl Fn(&ViewerApp) -> bool,
) {
    let ok = rt.block_on(
        h.state_mut()
            .pump_until(Duration::from_secs(60), |a| done(a)),
    );
    h.step();
    assert!(
        ok,
        "{what}: not within 60 s (worlds {}, link {:?}, error {:?})",
        h.state().state.worlds().len(),
        h.state().state.link(),
        h.state().state.browse_error()
    );
}

#[test]
fn the_live_viewer_browses_a_running_cluster() {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap_or_else(|e| panic!("{e}"));
    let port = free_port().unwrap_or_else(|e| panic!("{e}"));
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let space = format!("vlive{}", std::process::id());
    let journal = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let journal_arg = journal.path().display().to_string();
    let store_args = [
        "store",
        "--listen",
        &endpoint,
        "--space",
        &space,
        "--journal",
        &journal_arg,
    ];
    let mut procs = Procs(Vec::new());
    procs.spawn("store", &store_args);
    rt.block_on(wait_port(port));
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
    let n = WORLDS.to_string();
    ok(&[
        "job",
        "submit",
        "tumble",
        "--worlds",
        &n,
        "--wait",
        "--timeout",
        "120",
        "--connect",
        &endpoint,
        "--space",
        &space,
    ]);

    // The viewer: its own zenoh session (a client, as `mwb viewer --connect` opens), its bus
    // task on the runtime, the real UI in a kittest harness.
    let session = rt
        .block_on(async {
            let mut c = zenoh::Config::default();
            c.insert_json5("mode", "\"client\"")?;
            c.insert_json5("connect/endpoints", &format!("[\"{endpoint}\"]"))?;
            c.insert_json5("scouting/multicast/enabled", "false")?;
            zenoh::open(c).await
        })
        .unwrap_or_else(|e| panic!("{e}"));
    // A viewer's bus task in browsing session `viewer`, holding at most `max_worlds` worlds.
    let start_link = |max_worlds: usize| {
        LiveLink::start(
            session.clone(),
            LiveConfig {
                space: space.clone(),
                session: "viewer".into(),
                endpoint: endpoint.clone(),
                poll: Duration::from_millis(200),
                max_worlds,
                ..LiveConfig::default()
            },
            rt.handle(),
            Arc::new(|| {}),
        )
        .unwrap_or_else(|e| panic!("{e}"))
    };
    let link = start_link(mwb_viewer::live::DEFAULT_MAX_WORLDS);
    // node-query publishes every edit it applies (what a recorder keeps of the session).
    let keys = mwb_core::keys::Keys::new(&space).unwrap_or_else(|e| panic!("{e}"));
    let edits = rt
        .block_on(async {
            session
                .declare_subscriber(keys.browse_edits("viewer"))
                .await
        })
        .unwrap_or_else(|e| panic!("{e}"));
    let app = ViewerApp::live(ViewerState::live(endpoint.clone()), link);
    let mut h = Harness::builder()
        .with_size(vec2(1100.0, 700.0))
        .build_ui_state(|ui, app: &mut ViewerApp| app.ui(ui), app);
    settle(&rt, &mut h, "every world arrives", |a| {
        a.state.worlds().len() == WORLDS
            && a.state.link().is_some_and(|l| l.connected)
            && !a.state.body_names().is_empty()
    });
    assert_eq!(h.state().state.scene_name(), "tumble");
    assert_eq!(h.state().state.body_names().len(), 5);
    assert_eq!(h.state().state.survivor_count(), WORLDS as u64);
    // Constraints over the crate only (untick the others), everything framed (F).
    for name in ["plank", "brick", "die", "slab"] {
        h.get_by_label(name).click();
        h.step();
    }
    assert_eq!(h.state().state.chosen_objects(), vec![0]);
    h.key_press(egui::Key::F);
    h.step();
    // A box around a vertex of world 0's crate path that keeps some worlds but not all
    // (judged here on the loaded paths before drawing it; the store's answer must agree).
    let vr = h.state().view_rect();
    let (a, b) = {
        let app = h.state();
        let camera = app.state.camera.browse_camera(viewport_of(vr, 1.0));
        let projection = camera.projection().expect("camera");
        let w0 = app.state.world(0).expect("world 0");
        let points = w0.paths[0].tree.path().points().to_vec();
        points
            .iter()
            .rev()
            .find_map(|&p| {
                let (px, _) = projection.project(p)?;
                let c = vr.min + vec2(px[0] as f32, px[1] as f32);
                let (a, b) = (c - vec2(18.0, 18.0), c + vec2(18.0, 18.0));
                let rect = ScreenRect {
                    x0: f64::from(a.x - vr.min.x),
                    y0: f64::from(a.y - vr.min.y),
                    x1: f64::from(b.x - vr.min.x),
                    y1: f64::from(b.y - vr.min.y),
                };
                let frustum = camera.frustum(&rect).ok()?;
                let kept = app
                    .state
                    .worlds()
                    .iter()
                    .filter(|w| {
                        let c = mwb_core::browse::Constraint {
                            id: mwb_core::browse::ConstraintId(1),
                            polarity: mwb_core::browse::Polarity::Positive,
                            frustum,
                            objects: vec![0],
                            quantifier: Default::default(),
                            window: None,
                            scope: Default::default(),
                        };
                        c.evaluate(|o| w.paths.get(o as usize).map(|p| (&p.tree, p.radius)))
                    })
                    .count();
                (vr.contains(a) && vr.contains(b) && kept > 0 && kept < WORLDS).then_some((a, b))
            })
            .expect("some vertex of world 0's crate path has a box that keeps some worlds")
    };
    drag(&mut h, a, b);
    settle(&rt, &mut h, "the box's answer", |a| {
        a.state.pending() == 0 && a.unsent() == 0 && a.state.constraint_rows().len() == 1
    });

    // The constraint node-query holds is the frustum mwb_core computes for this camera and box.
    let app = h.state();
    assert_eq!(app.last_error(), None);
    let constraint = app.state.constraint_list().remove(0);
    let camera = app.state.camera.browse_camera(viewport_of(vr, 1.0));
    let rect = ScreenRect {
        x0: f64::from(a.x - vr.min.x),
        y0: f64::from(a.y - vr.min.y),
        x1: f64::from(b.x - vr.min.x),
        y1: f64::from(b.y - vr.min.y),
    };
    assert_eq!(constraint.frustum, camera.frustum(&rect).expect("frustum"));
    let survivors: Vec<u32> = app.state.survivors().collect();
    assert!(
        survivors.contains(&0) && survivors.len() < WORLDS,
        "the box keeps world 0 and not every world: {survivors:?}"
    );
    // The paths the viewer holds are the store's index: the box evaluated on them here keeps
    // exactly the store's survivors.
    let here: Vec<u32> = app
        .state
        .worlds()
        .iter()
        .filter(|w| constraint.evaluate(|o| w.paths.get(o as usize).map(|p| (&p.tree, p.radius))))
        .map(|w| w.index)
        .collect();
    assert_eq!(here, survivors);

    // The edit as node-query published it: number 1, the frustum drawn, the count shown.
    let sample = rt
        .block_on(async { tokio::time::timeout(Duration::from_secs(10), edits.recv_async()).await })
        .unwrap_or_else(|_| panic!("no edit published"))
        .unwrap_or_else(|e| panic!("{e}"));
    let record: EditRecord =
        serde_json::from_slice(&sample.payload().to_bytes()).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((record.session.as_str(), record.edit), ("viewer", 1));
    let Request::Add { constraint: sent } = &record.request else {
        panic!("expected the Add, got {:?}", record.request);
    };
    // (A frustum is checked and rebuilt from its JSON on the way in, which can move its planes
    // by an ulp: compare to 1e-12.)
    for (got, want) in sent
        .frustum
        .planes()
        .iter()
        .zip(constraint.frustum.planes())
    {
        let d = (0..3)
            .map(|k| (got.normal[k] - want.normal[k]).abs())
            .fold((got.offset - want.offset).abs(), f64::max);
        assert!(d < 1e-12, "{got:?} vs {want:?}");
    }
    let Reply::Status(answered) = &record.reply else {
        panic!("expected a status, got {:?}", record.reply);
    };
    assert_eq!(answered.result, survivors.len() as u64);

    // `mwb query list` on the same session reports the same count.
    let list = query_list(&endpoint, &space, "viewer");
    assert_eq!(list["result"].as_u64(), Some(survivors.len() as u64));
    assert_eq!(list["worlds"].as_u64(), Some(WORLDS as u64));
    assert_eq!(list["constraints"].as_array().map(Vec::len), Some(1));

    // A second viewer on the same session that holds at most 8 worlds' paths: exactly the
    // sample — the worlds in the context of 4 (the stores filter them), and the 4 survivors
    // with the smallest sampling hashes (fetched by index) — and says so.
    {
        use mwb_core::browse::sample::{bottom_k, context_threshold, in_context};
        let mut small = ViewerApp::live(ViewerState::live(endpoint.clone()), start_link(8));
        let ok = rt.block_on(small.pump_until(Duration::from_secs(60), |a| {
            a.state.holds_worlds(WORLDS as u64)
                && a.state.survivor_count() == survivors.len() as u64
        }));
        assert!(ok, "the sampled viewer caught up: {:?}", small.state.link());
        let t = context_threshold(4, WORLDS as u64);
        let mut want: Vec<u32> = (0..WORLDS as u32).filter(|&w| in_context(w, t)).collect();
        want.extend(bottom_k(&survivors, 4));
        want.sort_unstable();
        want.dedup();
        let held: Vec<u32> = small.state.worlds().iter().map(|w| w.index).collect();
        assert_eq!(held, want);
        assert!(held.len() < WORLDS, "a sample: {held:?}");
        let drawn = want.iter().filter(|w| survivors.contains(w)).count();
        assert!(drawn >= survivors.len().min(4));
        assert_eq!(small.state.held_survivors(), drawn);
        let link = small.state.link().cloned().unwrap_or_default();
        assert_eq!(
            (link.max_worlds, link.held, link.indexed),
            (8, want.len() as u64, WORLDS as u64)
        );
    }

    // Rank the survivors by spin: only survivors, most first.
    h.state_mut().set_sort(SortBy::Spin);
    settle(&rt, &mut h, "the ranking", |a| a.state.ranking().is_some());
    let ranking = h.state().state.ranking().cloned().expect("ranked");
    assert_eq!(ranking.candidates, survivors.len() as u64);
    assert!(ranking.rows.iter().all(|r| survivors.contains(&r.world)));
    assert!(
        ranking
            .rows
            .windows(2)
            .all(|w| w[0].score.unwrap_or(0.0) >= w[1].score.unwrap_or(0.0))
    );
    // Pick the top world in the sorter: its motion is fetched and decoded for playback.
    let top = ranking.rows[0].world;
    h.get_by_label_contains(&format!("1. world {top} ")).click();
    h.step();
    settle(&rt, &mut h, "the picked world's motion", |a| {
        a.state.selected() == Some(top) && a.state.world(top).is_some_and(|w| w.motion.is_some())
    });
    let w = h.state().state.world(top).expect("loaded");
    assert_eq!(w.motion.as_ref().map(|m| m.tracks.len()), Some(5));
    assert!(w.pose_at(0, 0.5).is_some());

    // A goal picked in the playback: the crate's orientation at the top world's last frame.
    // node-query ranks the survivors by their crates' final orientation to it (the stores'
    // metric): that world first, at no error.
    let end = h.state().state.duration();
    h.state_mut()
        .state
        .update(mwb_viewer::Msg::Seek(end))
        .unwrap_or_else(|e| panic!("{e}"));
    h.get_by_label("Use this frame's orientation as goal")
        .click();
    h.step();
    settle(&rt, &mut h, "the ranking by the goal", |a| {
        a.state
            .ranking()
            .is_some_and(|r| matches!(r.spec.key, mwb_core::browse::RankKey::OrientationTo { .. }))
    });
    let goal = *h.state().state.goal().expect("a goal");
    assert_eq!((goal.world, goal.object), (top, 0));
    let by_goal = h.state().state.ranking().cloned().expect("ranked");
    assert_eq!(by_goal.candidates, survivors.len() as u64);
    assert_eq!(by_goal.rows[0].world, top, "{by_goal:?}");
    assert!(
        by_goal.rows[0].score.is_some_and(|s| s < 1e-6),
        "{by_goal:?}"
    );
    assert!(by_goal.rows.windows(2).all(|w| w[0].score <= w[1].score));

    // Undo through the UI: every world survives again, in node-query's session too.
    h.key_press_modifiers(Modifiers::COMMAND, egui::Key::Z);
    h.step();
    settle(&rt, &mut h, "the undo", |a| {
        a.state.pending() == 0 && a.state.constraint_rows().is_empty()
    });
    assert_eq!(h.state().state.survivor_count(), WORLDS as u64);

    // A job from the jobs panel's message: acknowledged, and its worlds stream into the view.
    h.state_mut()
        .state
        .update(mwb_viewer::Msg::SubmitJob {
            scene: "tumble".into(),
            worlds: MORE as u32,
            quality: mwb_proto::v1::Quality::Draft,
            sim: Some(mwb_core::scene::SimPreset::Draft),
        })
        .unwrap_or_else(|e| panic!("{e}"));
    settle(&rt, &mut h, "the job's acknowledgement", |a| {
        a.state.job_notice().is_some()
    });
    let notice = h.state().state.job_notice().cloned();
    assert!(
        matches!(&notice, Some(Ok(n)) if n.contains("submitted")),
        "{notice:?}"
    );
    settle(&rt, &mut h, "the new job's worlds", |a| {
        a.state.worlds().len() == WORLDS + MORE
            && a.state.survivor_count() == (WORLDS + MORE) as u64
    });

    // Refine the shown world (§4.5) with a box over the whole view: the bus task checks the
    // request against the stored world and submits a REFINE job, whose worlds arrive too.
    h.state_mut()
        .state
        .update(mwb_viewer::Msg::SelectWorld(Some(top)))
        .unwrap_or_else(|e| panic!("{e}"));
    h.state_mut()
        .state
        .update(mwb_viewer::Msg::Refine {
            viewport: mwb_core::browse::Viewport {
                width: 800,
                height: 600,
            },
            rect: mwb_core::browse::ScreenRect {
                x0: 0.0,
                y0: 0.0,
                x1: 800.0,
                y1: 600.0,
            },
            worlds: REFINED as u32,
        })
        .unwrap_or_else(|e| panic!("{e}"));
    settle(&rt, &mut h, "the refinement's acknowledgement", |a| {
        a.state
            .job_notice()
            .is_some_and(|n| n.as_ref().is_ok_and(|n| n.contains("refining world")))
    });
    settle(&rt, &mut h, "the refined worlds", |a| {
        a.state.worlds().len() == WORLDS + MORE + REFINED
    });

    // The store (which runs node-query) is killed under the running viewer: the status bar
    // says so, a box drawn meanwhile is kept, and when the store is back (from its journal,
    // same worlds under the same indices, but a new node-query without the session) the viewer
    // reconnects and sends the session's edits again (the first box, its undo, the new box) —
    // node-query then holds the new box.
    let all = (WORLDS + MORE + REFINED) as u64;
    common::sigkill(procs.pid("store"));
    settle(&rt, &mut h, "the link shown lost", |a| {
        a.state.link().is_some_and(|l| !l.connected)
    });
    let c = h.state().view_rect().center();
    drag(&mut h, c - vec2(150.0, 120.0), c + vec2(150.0, 120.0));
    assert_eq!(h.state().state.pending(), 1, "the box is kept, unanswered");
    procs.spawn("store again", &store_args);
    rt.block_on(wait_port(port));
    settle(
        &rt,
        &mut h,
        "reconnected with the session's edits applied",
        |a| {
            a.state.link().is_some_and(|l| l.connected)
                && a.state.pending() == 0
                && a.unsent() == 0
                && a.state.constraint_rows().len() == 1
        },
    );
    // The new node-query's survivors are the box evaluated on the paths the viewer holds.
    let after: Vec<u32> = h.state().state.survivors().collect();
    let boxed = h.state().state.constraint_list().remove(0);
    let here: Vec<u32> = h
        .state()
        .state
        .worlds()
        .iter()
        .filter(|w| boxed.evaluate(|o| w.paths.get(o as usize).map(|p| (&p.tree, p.radius))))
        .map(|w| w.index)
        .collect();
    assert_eq!(here, after);
    let list = query_list(&endpoint, &space, "viewer");
    assert_eq!(list["constraints"].as_array().map(Vec::len), Some(1));
    assert_eq!(list["edits"].as_u64(), Some(3), "{list}");
    assert_eq!(list["worlds"].as_u64(), Some(all));
    assert_eq!(list["result"].as_u64(), Some(after.len() as u64));
    drop(h);
    rt.block_on(async {
        let _ = tokio::time::timeout(Duration::from_secs(3), session.close()).await;
    });

    // The headless screenshot of the same cluster, with a box, in its own session.
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let png = dir.path().join("live.png");
    let png_arg = png.display().to_string();
    let out = ok(&[
        "viewer",
        "--connect",
        &endpoint,
        "--space",
        &space,
        "--session",
        "shot",
        "--screenshot",
        &png_arg,
        "--size",
        "960x600",
        "--rect",
        "300,150,640,450",
        "--rank",
        "rest",
    ]);
    assert!(
        out.contains(&format!("{} worlds", WORLDS + MORE + REFINED)),
        "screenshot line: {out}"
    );
    let img = image::open(&png).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((img.width(), img.height()), (960, 600));
    let shot = query_list(&endpoint, &space, "shot");
    assert!(
        out.contains(&format!("{} survive", shot["result"])),
        "{out} vs {shot}"
    );

    // A viewer holding a sample of 4 is asked to show the world with the largest sampling hash
    // (outside any sample this small): it fetches it and shows it. A world no store holds is an
    // error that names it.
    let total = (WORLDS + MORE + REFINED) as u32;
    let far = (0..total)
        .max_by_key(|&w| mwb_core::browse::sample::sample_hash(w))
        .unwrap_or(0)
        .to_string();
    let shot_args = |select: &str, wait: &str| {
        vec![
            "viewer".to_owned(),
            "--connect".into(),
            endpoint.clone(),
            "--space".into(),
            space.clone(),
            "--session".into(),
            "sampled".into(),
            "--max-worlds".into(),
            "4".into(),
            "--select".into(),
            select.to_owned(),
            "--wait-s".into(),
            wait.to_owned(),
            "--screenshot".into(),
            png_arg.clone(),
        ]
    };
    let args = shot_args(&far, "60");
    let out = ok(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(out.contains(&format!("{total} worlds")), "{out}");
    let args = shot_args("999999", "3");
    let refused = mwb(&args.iter().map(String::as_str).collect::<Vec<_>>());
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(
        !refused.status.success() && err.contains("--select 999999: no store sent world 999999"),
        "{err}"
    );
    drop(procs);
}
