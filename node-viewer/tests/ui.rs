//! The real viewer UI driven through egui_kittest: boxes dragged in the 3D view become the
//! constraints `mwb_core::browse` computes for that camera and rectangle; remove, undo and redo
//! through the UI; playback of a picked world; one image snapshot (software-painted, so it needs
//! no GPU) of a fixed scene, camera and worlds.

use std::sync::OnceLock;

use egui::{Event, Modifiers, PointerButton, Pos2, TexturesDelta, pos2, vec2};
use egui_kittest::kittest::Queryable;
use egui_kittest::{Harness, TestRenderer};
use mwb_core::browse::{Constraint, ConstraintId, Polarity, ScreenRect};
use mwb_core::scene::SceneTemplate;
use mwb_viewer::draw::viewport_of;
use mwb_viewer::softpaint::SoftPainter;
use mwb_viewer::ui::{Notice, SortBy};
use mwb_viewer::views::{ViewsFile, decode};
use mwb_viewer::{Msg, OrbitCamera, ViewerApp, ViewerState, WorldData};

const WORLDS: u32 = 12;

/// Tumble's first worlds, sampled and decoded once for every test.
fn worlds() -> &'static (ViewerState, SceneTemplate) {
    static W: OnceLock<(ViewerState, SceneTemplate)> = OnceLock::new();
    W.get_or_init(|| {
        let text = mwb_core::scene::builtin::get("tumble").expect("tumble ships");
        let template = SceneTemplate::parse(text, "scenes/tumble.toml").expect("parses");
        let first = template.instantiate(0);
        let names = first.bodies.iter().map(|b| b.name.clone()).collect();
        let mut state = ViewerState::new(template.name(), names, first.statics.clone());
        for w in mwb_viewer::offline::sample_worlds(&template, WORLDS, 2) {
            state.add_world(w.expect("samples")).expect("adds");
        }
        (state, template)
    })
}

/// A fixed camera looking at the tumble pile from the front and above.
fn camera() -> OrbitCamera {
    OrbitCamera {
        target: [0.0, 0.4, 0.0],
        yaw: 0.5,
        pitch: 0.55,
        distance: 7.0,
        ..OrbitCamera::default()
    }
}

/// egui_kittest's renderer hook, painted by the viewer's software rasteriser.
#[derive(Default)]
struct Soft(SoftPainter);

impl TestRenderer for Soft {
    fn handle_delta(&mut self, delta: &mut TexturesDelta) {
        self.0.handle_delta(delta);
        delta.clear();
    }

    fn render(
        &mut self,
        ctx: &egui::Context,
        output: &egui::FullOutput,
    ) -> Result<image::RgbaImage, String> {
        let ppp = output.pixels_per_point;
        let r = ctx.viewport_rect();
        let size = [
            (r.width() * ppp).round() as u32,
            (r.height() * ppp).round() as u32,
        ];
        let clear = ctx.global_style().visuals.panel_fill;
        Ok(self
            .0
            .paint_shapes(ctx, output.shapes.clone(), ppp, size, clear))
    }
}

fn harness() -> Harness<'static, ViewerApp> {
    harness_of(|app| app)
}

/// [`harness`] with the app changed by `setup` before the first frame.
fn harness_of(setup: impl FnOnce(ViewerApp) -> ViewerApp) -> Harness<'static, ViewerApp> {
    let mut state = worlds().0.clone();
    state.update(Msg::SetCamera(camera())).expect("camera");
    let app = setup(ViewerApp::new(state).with_camera_placed(true));
    let mut h = Harness::builder()
        .with_size(vec2(1100.0, 700.0))
        .renderer(Soft::default())
        .build_ui_state(|ui, app: &mut ViewerApp| app.ui(ui), app);
    h.run();
    h
}

/// Presses at `a`, moves to `b` in a few steps, releases there.
fn drag(h: &mut Harness<'_, ViewerApp>, a: Pos2, b: Pos2, modifiers: Modifiers) {
    h.event(Event::ModifiersChanged(modifiers));
    h.event(Event::PointerMoved(a));
    h.step();
    h.event(Event::PointerButton {
        pos: a,
        button: PointerButton::Primary,
        pressed: true,
        modifiers,
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
        modifiers,
    });
    h.step();
    h.event(Event::ModifiersChanged(Modifiers::NONE));
    h.event(Event::PointerGone);
    h.run();
}

/// The screen point (egui points) where world `w`'s body `b` is at time `t`.
fn screen_of(h: &Harness<'_, ViewerApp>, w: usize, b: usize, t: f64) -> Pos2 {
    let app = h.state();
    let vr = app.view_rect();
    let cam = app.state.camera.browse_camera(viewport_of(vr, 1.0));
    let (p, _) = app.state.worlds()[w].pose_at(b, t).expect("pose");
    let (px, _) = cam
        .projection()
        .expect("camera")
        .project(p)
        .expect("in front");
    pos2(vr.min.x + px[0] as f32, vr.min.y + px[1] as f32)
}

/// Worlds satisfying `c`, evaluated here with `mwb_core::browse` over the worlds' paths.
fn expected_survivors(worlds: &[WorldData], c: &Constraint) -> Vec<u32> {
    worlds
        .iter()
        .filter(|w| c.evaluate(|o| w.paths.get(o as usize).map(|p| (&p.tree, p.radius))))
        .map(|w| w.index)
        .collect()
}

#[test]
fn a_dragged_box_is_the_frustum_mwb_core_computes_and_remove_undo_redo_work() {
    let mut h = harness();
    // Constraints over the crate only: untick the other bodies in the objects list.
    for name in ["plank", "brick", "die", "slab"] {
        if h.query_by_label(name).is_some() {
            h.get_by_label(name).click();
            h.run();
        }
    }
    assert_eq!(h.state().state.chosen_objects(), vec![0]);

    // A box around where world 0's crate is at 1 s.
    let c = screen_of(&h, 0, 0, 1.0);
    let (a, b) = (c - vec2(30.0, 22.0), c + vec2(30.0, 22.0));
    drag(&mut h, a, b, Modifiers::NONE);

    let app = h.state();
    assert_eq!(app.last_error(), None);
    let constraints: Vec<Constraint> = app.state.constraint_list();
    assert_eq!(constraints.len(), 1, "one box, one constraint");
    let got = &constraints[0];
    let vr = app.view_rect();
    let camera = app.state.camera.browse_camera(viewport_of(vr, 1.0));
    let rect = ScreenRect {
        x0: f64::from(a.x - vr.min.x),
        y0: f64::from(a.y - vr.min.y),
        x1: f64::from(b.x - vr.min.x),
        y1: f64::from(b.y - vr.min.y),
    };
    assert_eq!(got.frustum, camera.frustum(&rect).expect("frustum"));
    assert_eq!(got.polarity, Polarity::Positive);
    assert_eq!(got.objects, vec![0]);
    let survivors: Vec<u32> = app.state.survivors().collect();
    assert_eq!(survivors, expected_survivors(app.state.worlds(), got));
    assert!(
        survivors.contains(&0),
        "world 0's crate passes through the box"
    );
    // Never-miss: every world whose decoded crate position is inside the box survives.
    for w in app.state.worlds() {
        if w.motion
            .as_ref()
            .expect("offline worlds have motion")
            .tracks[0]
            .positions
            .iter()
            .any(|&p| got.frustum.contains(p))
        {
            assert!(
                survivors.contains(&w.index),
                "world {} enters the box",
                w.index
            );
        }
    }
    let positive_count = survivors.len();

    // Shift+drag elsewhere: a negative constraint; the result is the AND of both.
    let c2 = screen_of(&h, 1, 0, 0.6);
    drag(
        &mut h,
        c2 - vec2(15.0, 15.0),
        c2 + vec2(15.0, 15.0),
        Modifiers::SHIFT,
    );
    let app = h.state();
    let all: Vec<Constraint> = app.state.constraint_list();
    assert_eq!(all.len(), 2);
    assert_eq!(all[1].polarity, Polarity::Negative);
    let neg = expected_survivors(app.state.worlds(), &all[1]);
    let both: Vec<u32> = expected_survivors(app.state.worlds(), &all[0])
        .into_iter()
        .filter(|w| neg.contains(w))
        .collect();
    assert_eq!(app.state.survivors().collect::<Vec<_>>(), both);
    assert!(
        !neg.contains(&1),
        "world 1's crate is inside its own negative box at 0.6 s"
    );

    // Remove the first through its button in the constraint list.
    h.get_by_label("x #1").click();
    h.run();
    let ids: Vec<ConstraintId> = h
        .state()
        .state
        .constraint_rows()
        .iter()
        .map(|c| c.id)
        .collect();
    assert_eq!(ids, vec![ConstraintId(2)]);
    assert_eq!(h.state().state.survivor_count(), neg.len() as u64);

    // Ctrl+Z brings it back (with its bits), Ctrl+Shift+Z removes it again.
    h.key_press_modifiers(Modifiers::COMMAND, egui::Key::Z);
    h.run();
    assert_eq!(h.state().state.constraint_rows().len(), 2);
    assert_eq!(h.state().state.survivor_count(), both.len() as u64);
    h.key_press_modifiers(Modifiers::COMMAND | Modifiers::SHIFT, egui::Key::Z);
    h.run();
    assert_eq!(h.state().state.constraint_rows().len(), 1);
    // Undo twice more: the removal, then the negative box: only the positive one is left.
    h.key_press_modifiers(Modifiers::COMMAND, egui::Key::Z);
    h.run();
    h.key_press_modifiers(Modifiers::COMMAND, egui::Key::Z);
    h.run();
    let ids: Vec<ConstraintId> = h
        .state()
        .state
        .constraint_rows()
        .iter()
        .map(|c| c.id)
        .collect();
    assert_eq!(ids, vec![ConstraintId(1)]);
    assert_eq!(h.state().state.survivor_count(), positive_count as u64);

    // A click without a drag makes no constraint.
    let p = screen_of(&h, 0, 0, 0.0) + vec2(200.0, 0.0);
    drag(&mut h, p, p, Modifiers::NONE);
    assert_eq!(h.state().state.constraint_rows().len(), 1);
}

#[test]
fn picking_a_survivor_plays_it_back() {
    let mut h = harness();
    h.get_by_label("world 3  (seed 0x3)").click();
    h.run();
    assert_eq!(h.state().state.selected(), Some(3));
    h.get_by_label("Play").click();
    h.run();
    assert!(h.state().state.playback().playing);
    h.state_mut().state.update(Msg::Tick(0.5)).expect("tick");
    h.run();
    let t = h.state().state.playback().time;
    assert!((t - 0.5).abs() < 1e-9, "time {t}");
    h.get_by_label("Pause").click();
    h.run();
    assert!(!h.state().state.playback().playing);
    // The frame-step keys move by one frame of the world.
    h.key_press(egui::Key::ArrowRight);
    h.run();
    let dt = h.state().state.worlds()[3].frame_dt;
    let t2 = h.state().state.playback().time;
    assert!((t2 - (0.5 + dt)).abs() < 1e-9, "time {t2}");
}

#[test]
fn the_sorter_ranks_the_survivors_and_a_picked_row_plays_back() {
    let mut h = harness();
    h.get_by_label("rank").click();
    h.run();
    let ranking = h
        .state()
        .state
        .ranking()
        .cloned()
        .expect("ranked at once offline");
    assert_eq!(ranking.candidates, u64::from(WORLDS));
    assert_eq!(
        ranking.rows.len(),
        mwb_viewer::ui::SORTER_ROWS.min(WORLDS as usize)
    );
    // Most spin first, over the chosen (all) objects, summed: the store's own scoring.
    let spin = |w: u32| -> f64 {
        h.state()
            .state
            .world(w)
            .expect("world")
            .metrics
            .iter()
            .map(|m| m.angular_travel_rad)
            .sum()
    };
    for pair in ranking.rows.windows(2) {
        assert!(spin(pair[0].world) >= spin(pair[1].world));
        assert_eq!(pair[0].score, Some(spin(pair[0].world)));
    }
    let top = ranking.rows[0].world;
    h.get_by_label_contains(&format!(" 1. world {top} "))
        .click();
    h.run();
    assert_eq!(h.state().state.selected(), Some(top));
    // The picked world's bodies are drawn at their decoded poses.
    let p = screen_of(&h, top as usize, 0, 0.0);
    let img = h.render().expect("renders");
    let px = img.get_pixel(p.x as u32, p.y as u32).0;
    let sky_bottom = mwb_viewer::draw::palette::SKY_BOTTOM.to_array();
    let sky_top = mwb_viewer::draw::palette::SKY_TOP.to_array();
    let far = |sky: [u8; 4]| (0..3).map(|i| px[i].abs_diff(sky[i]) as u32).sum::<u32>() > 90;
    assert!(far(sky_top) && far(sky_bottom), "crate pixel {px:?}");
}

#[test]
fn snapshot_of_tumble_with_a_box_and_a_selected_world() {
    let mut h = harness();
    let c = screen_of(&h, 0, 0, 1.0);
    let app = h.state_mut();
    let vr = app.view_rect();
    let rect = ScreenRect {
        x0: f64::from(c.x - vr.min.x - 40.0),
        y0: f64::from(c.y - vr.min.y - 30.0),
        x1: f64::from(c.x - vr.min.x + 40.0),
        y1: f64::from(c.y - vr.min.y + 30.0),
    };
    app.add_box_px(rect, Polarity::Positive, 1.0);
    app.state.update(Msg::SelectWorld(Some(0))).expect("select");
    app.state.update(Msg::Seek(1.0)).expect("seek");
    h.run();
    // The selected world's crate is drawn where its decoded pose projects: the pixel there is
    // not the view's background.
    let img = h.render().expect("renders");
    let p = screen_of(&h, 0, 0, 1.0);
    let px = img.get_pixel(p.x as u32, p.y as u32).0;
    let sky_bottom = mwb_viewer::draw::palette::SKY_BOTTOM.to_array();
    let sky_top = mwb_viewer::draw::palette::SKY_TOP.to_array();
    // (Another body may stand in front of the crate from this camera, so the test asks only
    // that something is drawn there, well away from both ends of the sky's gradient.)
    let far = |sky: [u8; 4]| (0..3).map(|i| px[i].abs_diff(sky[i]) as u32).sum::<u32>() > 90;
    assert!(
        far(sky_top) && far(sky_bottom),
        "crate pixel {px:?} (sky {sky_top:?}..{sky_bottom:?})"
    );
    h.snapshot("viewer_tumble");
}

/// A fresh scratch directory under the system's temporary directory: tests never read or write
/// the user's configuration directory.
fn scratch(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("mwb-viewer-ui-{}-{name}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    dir
}

#[test]
fn saved_views_are_kept_with_the_session_and_a_bad_file_is_shown_not_fatal() {
    let dir = scratch("views");
    let path = dir.join("views").join("viewer.json");
    let on_disk = || {
        let text = std::fs::read_to_string(&path).expect("the views file is written");
        decode(&text, "viewer.json").expect("and reads back")
    };
    let mut h = harness_of(|app| app.with_views_file(ViewsFile::new(&path, "viewer")));
    assert!(h.state().state.views().is_empty());
    assert!(!path.exists(), "nothing is written until a view is saved");
    h.get_by_label("save view").click();
    h.run();
    assert_eq!(on_disk(), h.state().state.views());
    h.state_mut()
        .state
        .update(Msg::Orbit {
            d_yaw: 0.7,
            d_pitch: -0.2,
        })
        .expect("orbit");
    h.get_by_label("save view").click();
    h.run();
    let saved = h.state().state.views().to_vec();
    assert_eq!(saved.len(), 2);
    assert_eq!(on_disk(), saved);
    assert!(
        h.query_by_label_contains("views kept in").is_some(),
        "the status bar says where"
    );
    drop(h);

    // The viewer opened again on the session: the views are back and recall their cameras.
    let mut h = harness_of(|app| app.with_views_file(ViewsFile::new(&path, "viewer")));
    assert_eq!(h.state().state.views(), &saved[..]);
    assert!(h.query_by_label_contains("2 saved views from").is_some());
    assert_ne!(h.state().state.camera, saved[1].camera);
    h.get_by_label("view 2").click();
    h.run();
    assert_eq!(h.state().state.camera, saved[1].camera);
    h.get_by_label("x view 1").click();
    h.run();
    assert_eq!(on_disk(), saved[1..].to_vec());
    drop(h);

    // A corrupt file: the viewer starts without views and says why in the status bar.
    std::fs::write(&path, "{\"version\": 1, \"views\": [tru").expect("write");
    let mut h = harness_of(|app| app.with_views_file(ViewsFile::new(&path, "viewer")));
    assert!(h.state().state.views().is_empty());
    let shown = format!("views file {}:1:", path.display());
    assert!(
        matches!(h.state().views_notice(), Some(Notice::Problem(p)) if p.starts_with(&shown)),
        "{:?}",
        h.state().views_notice()
    );
    assert!(h.query_by_label_contains(&shown).is_some(), "shown");
    // Saving a view replaces it; the unreadable one is kept aside.
    h.get_by_label("save view").click();
    h.run();
    assert_eq!(on_disk(), h.state().state.views());
    assert!(dir.join("views").join("viewer.json.bad").exists());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_goal_taken_from_the_playback_frame_ranks_the_worlds_by_their_error_to_it() {
    let mut h = harness();
    // The goal is the first chosen object's orientation: choose the crate only.
    for name in ["plank", "brick", "die", "slab"] {
        h.get_by_label(name).click();
        h.run();
    }
    h.get_by_label("world 5  (seed 0x5)").click();
    h.run();
    let end = h.state().state.duration();
    h.state_mut().state.update(Msg::Seek(end)).expect("seek");
    h.run();
    h.get_by_label("Use this frame's orientation as goal")
        .click();
    h.run();
    let app = h.state();
    assert_eq!(app.last_error(), None);
    let goal = *app.state.goal().expect("a goal");
    let motion = app
        .state
        .world(5)
        .and_then(|w| w.motion.clone())
        .expect("motion");
    let last = motion.tracks[0].rotations.len() - 1;
    assert_eq!((goal.world, goal.object, goal.frame), (5, 0, last));
    // The frame's rotation, normalised (within rounding of the decoded quaternion).
    let frame_rotation = motion.tracks[0].rotations[last];
    assert!(
        goal.rotation
            .iter()
            .zip(frame_rotation)
            .all(|(a, b)| (a - b).abs() < 1e-12),
        "{:?} vs {frame_rotation:?}",
        goal.rotation
    );
    assert!(
        h.query_by_label_contains("goal: crate in world 5 at")
            .is_some(),
        "the goal is shown"
    );
    // The sorter switched to the goal: least error first, world 5 itself (its final pose)
    // first, each score the angle to its crate's final orientation (the store's metric).
    let app = h.state();
    assert_eq!(app.sort_by(), SortBy::OrientationToGoal);
    let ranking = app
        .state
        .ranking()
        .cloned()
        .expect("ranked at once offline");
    assert_eq!(ranking.rows[0].world, 5);
    assert!(
        ranking.rows[0].score.is_some_and(|s| s < 1e-6),
        "{ranking:?}"
    );
    for r in &ranking.rows {
        let final_rotation = app.state.world(r.world).expect("world").metrics[0].final_rotation;
        let want = mwb_core::browse::quat_angle_between(goal.rotation, final_rotation);
        assert!(r.score.is_some_and(|s| (s - want).abs() < 1e-12), "{r:?}");
    }
    assert!(ranking.rows.windows(2).all(|w| w[0].score <= w[1].score));
    h.get_by_label("clear goal").click();
    h.run();
    assert!(h.state().state.goal().is_none() && h.state().state.ranking().is_none());
}

#[test]
fn a_scene_of_many_bodies_lists_them_in_a_short_scrolled_list_with_all_and_none() {
    let names: Vec<String> = (0..40).map(|i| format!("block{i}")).collect();
    let app = ViewerApp::new(ViewerState::new("many", names, Vec::new()));
    let mut h = Harness::builder()
        .with_size(vec2(1100.0, 700.0))
        .build_ui_state(|ui, app: &mut ViewerApp| app.ui(ui), app);
    h.run();
    assert!(h.query_by_label("40 of 40").is_some());
    // The list scrolls: the sorter stays in reach below it, not under 40 rows.
    let sort = h.get_by_label("Sort").rect();
    assert!(sort.min.y < 400.0, "the Sort heading is at {sort:?}");
    h.get_by_label("none").click();
    h.run();
    assert!(h.state().state.chosen_objects().is_empty());
    h.get_by_label("block2").click();
    h.run();
    assert_eq!(h.state().state.chosen_objects(), vec![2]);
    assert!(h.query_by_label("1 of 40").is_some());
    h.get_by_label("all").click();
    h.run();
    assert_eq!(h.state().state.chosen_objects().len(), 40);
}
