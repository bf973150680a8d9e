//! The viewer's window: panels around a 3D view. Everything the user does becomes a [`Msg`]
//! applied to the [`ViewerState`]; this module holds only what a gesture needs while it lasts
//! (the rectangle being dragged) and the last frame's view rectangle.
//!
//! Mouse in the 3D view: left-drag draws a positive box, Shift+left-drag a negative one;
//! right-drag or Alt+left-drag orbits; middle-drag or Alt+middle-drag pans; wheel or
//! Alt+right-drag zooms; a click picks the nearest path's world. Keys: F frames the selected
//! world (everything when none is selected), A frames everything,
//! Ctrl+Z / Ctrl+Shift+Z (or Ctrl+Y) undo and redo, Space plays / pauses, ←/→ step a frame.

use std::collections::VecDeque;
use std::sync::{Arc, OnceLock};

use egui::{
    Align, Color32, Key, KeyboardShortcut, Layout, Modifiers, PointerButton, Pos2, Rect, RichText,
    Sense,
};
use mwb_core::browse::{Aggregate, Metric, Order, Polarity, Quat, RankKey, ScreenRect, TimeWindow};

use crate::draw::{self, Overlay, View};
use crate::live::LiveLink;
use crate::session::Command;
use crate::state::{MAX_SPEED, MIN_SPEED, Msg, RankSpec, ViewerState};
use crate::views::ViewsFile;

/// Radians of orbit per point of mouse travel.
const ORBIT_PER_PT: f64 = 0.008;
/// Smallest rectangle side that makes a constraint, points (smaller drags are clicks).
const MIN_BOX_PT: f32 = 3.0;

/// A rectangle being dragged in the 3D view.
#[derive(Debug, Clone, Copy)]
struct Drag {
    start: Pos2,
    current: Pos2,
    negative: bool,
}

/// What the metric sorter offers (§4.4.3), in the order of its menu.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SortBy {
    Spin,
    TimeToRest,
    Impacts,
    OrientationError,
    /// Orientation error to the goal picked in the view ([`crate::state::Goal`]).
    OrientationToGoal,
    ConstraintsSatisfied,
}

impl SortBy {
    pub const ALL: [SortBy; 6] = [
        SortBy::Spin,
        SortBy::TimeToRest,
        SortBy::Impacts,
        SortBy::OrientationError,
        SortBy::OrientationToGoal,
        SortBy::ConstraintsSatisfied,
    ];

    pub fn label(self) -> &'static str {
        match self {
            SortBy::Spin => "most spin",
            SortBy::TimeToRest => "rests soonest",
            SortBy::Impacts => "most impacts",
            SortBy::OrientationError => "turned most from start",
            SortBy::OrientationToGoal => "closest to the goal orientation",
            SortBy::ConstraintsSatisfied => "constraints satisfied (all worlds)",
        }
    }

    /// The ranking over `objects` (the chosen ones), with the aggregate and order an animator
    /// means by the label; `None` for [`SortBy::OrientationToGoal`] without a `goal`.
    pub fn spec(
        self,
        objects: Vec<u32>,
        aggregate: Option<Aggregate>,
        k: usize,
        goal: Option<Quat>,
    ) -> Option<RankSpec> {
        let metric = |metric: Metric, order| RankSpec {
            key: RankKey::Metric {
                metric,
                objects: objects.clone(),
                aggregate: aggregate.unwrap_or(metric.default_aggregate()),
            },
            order,
            k,
            all_worlds: false,
        };
        Some(match self {
            SortBy::Spin => metric(Metric::AngularTravel, Order::Descending),
            SortBy::TimeToRest => metric(Metric::TimeToRest, Order::Ascending),
            SortBy::Impacts => metric(Metric::Impacts, Order::Descending),
            SortBy::OrientationError => metric(Metric::OrientationError, Order::Descending),
            // Summed like the error to the start (§4.4.3: total error), least first.
            SortBy::OrientationToGoal => RankSpec {
                key: RankKey::OrientationTo {
                    goal: goal?,
                    aggregate: aggregate.unwrap_or(Metric::OrientationError.default_aggregate()),
                    objects,
                },
                order: Order::Ascending,
                k,
                all_worlds: false,
            },
            SortBy::ConstraintsSatisfied => RankSpec {
                key: RankKey::ConstraintsSatisfied,
                order: Order::Descending,
                k,
                all_worlds: true,
            },
        })
    }

    /// The unit of its values.
    pub fn unit(self) -> &'static str {
        match self {
            SortBy::Spin | SortBy::OrientationError | SortBy::OrientationToGoal => "rad",
            SortBy::TimeToRest => "s",
            SortBy::Impacts | SortBy::ConstraintsSatisfied => "",
        }
    }
}

/// Rows the sorter lists.
pub const SORTER_ROWS: usize = 20;
/// Objects listed before the list scrolls (and gets "all" / "none" buttons).
const OBJECT_ROWS: usize = 8;

/// The jobs panel's form: what the next job samples.
#[derive(Debug, Clone)]
struct JobForm {
    /// A scene file or a shipped scene's name.
    scene: String,
    worlds: u32,
    quality: mwb_proto::v1::Quality,
    /// Simulation preset written into the job's scene; `None`: the scene's own.
    sim: Option<mwb_core::scene::SimPreset>,
    /// The next box drawn refines the shown world instead of constraining (§4.5).
    refine_next: bool,
    refine_worlds: u32,
}

impl Default for JobForm {
    fn default() -> Self {
        Self {
            scene: String::new(),
            worlds: 200,
            quality: mwb_proto::v1::Quality::Standard,
            sim: None,
            refine_next: false,
            refine_worlds: 50,
        }
    }
}

/// The viewer: state plus the gesture in progress, and for a live viewer its bus task.
pub struct ViewerApp {
    pub state: ViewerState,
    drag: Option<Drag>,
    view_rect: Rect,
    hovered: Option<u32>,
    /// The world under the cursor in the sorter list.
    sorter_hover: Option<u32>,
    sort_by: SortBy,
    /// The last error an action caused (shown in the top bar until the next action).
    last_error: Option<String>,
    /// The camera was framed on the worlds (or placed by the user's camera file).
    framed: bool,
    /// The camera was framed on the scene as it starts (no worlds yet); worlds reframe it.
    framed_scene: bool,
    /// Panels, bars and timeline drawn around the 3D view (off: the view alone, a preview).
    chrome: bool,
    /// The 3D view's path meshes, kept between frames.
    path_meshes: draw::PathMeshes,
    link: Option<LiveLink>,
    /// Commands the bus task could not take yet (its queue was full), oldest first.
    unsent: VecDeque<Command>,
    job_form: JobForm,
    /// Where the saved views are kept with the session (`None`: only while the viewer runs).
    views_file: Option<ViewsFile>,
    /// The state's [`ViewerState::views_edits`] the file last had.
    views_written: u64,
    /// What became of reading or writing the views file (shown in the status bar).
    views_notice: Option<Notice>,
}

/// A line for the status bar: news, or a problem that needs the user's attention.
#[derive(Debug, Clone, PartialEq)]
pub enum Notice {
    Info(String),
    Problem(String),
}

impl ViewerApp {
    pub fn new(state: ViewerState) -> Self {
        Self {
            state,
            drag: None,
            view_rect: Rect::NOTHING,
            hovered: None,
            sorter_hover: None,
            sort_by: SortBy::Spin,
            last_error: None,
            framed: false,
            framed_scene: false,
            chrome: true,
            path_meshes: draw::PathMeshes::default(),
            link: None,
            unsent: VecDeque::new(),
            job_form: JobForm::default(),
            views_file: None,
            views_written: 0,
            views_notice: None,
        }
    }

    /// Keeps the saved views in `file`: reads them now (a file that cannot be read is shown in
    /// the status bar and replaced, kept aside, when a view is next saved) and writes them
    /// whenever the user saves or deletes one.
    pub fn with_views_file(mut self, mut file: ViewsFile) -> Self {
        self.views_notice = match file.load() {
            Ok(views) => {
                let n = views.len();
                self.send(Msg::LoadViews(views));
                Some(Notice::Info(format!(
                    "{n} saved view{} from {}",
                    if n == 1 { "" } else { "s" },
                    file.path().display()
                )))
            }
            Err(e) => Some(Notice::Problem(format!(
                "{e} (saving a view replaces it; the old file is kept as .bad)"
            ))),
        };
        self.views_written = self.state.views_edits();
        self.views_file = Some(file);
        self
    }

    /// What became of reading or writing the views file.
    pub fn views_notice(&self) -> Option<&Notice> {
        self.views_notice.as_ref()
    }

    /// Writes the saved views when the user changed them since the last write. A failed write
    /// is shown and tried again at the next change.
    fn keep_views(&mut self) {
        let edits = self.state.views_edits();
        let Some(file) = &mut self.views_file else {
            return;
        };
        if edits == self.views_written {
            return;
        }
        self.views_written = edits;
        self.views_notice = Some(match file.save(self.state.views()) {
            Ok(()) => Notice::Info(format!("views kept in {}", file.path().display())),
            Err(e) => Notice::Problem(e.to_string()),
        });
    }

    /// A live viewer: `state` should be [`ViewerState::live`]; `link` its bus task.
    pub fn live(state: ViewerState, link: LiveLink) -> Self {
        let mut app = Self::new(state);
        app.link = Some(link);
        app
    }

    /// Applies what the bus task reported and hands it the state's requests, without waiting
    /// (done at the start of every frame; tests and screenshots call it directly).
    pub fn pump(&mut self) {
        if let Some(link) = &mut self.link {
            for msg in link.drain() {
                if let Err(e) = self.state.update(msg) {
                    self.last_error = Some(e.to_string());
                }
            }
        }
        self.unsent.extend(self.state.take_commands());
        if let Some(link) = &self.link {
            while let Some(cmd) = self.unsent.pop_front() {
                if let Err(cmd) = link.send(cmd) {
                    self.unsent.push_front(cmd);
                    break;
                }
            }
        }
    }

    /// Pumps (see [`pump`](Self::pump)) every 2 ms until `done` holds or `timeout` passes;
    /// returns whether it held. For headless use (screenshots, tests): a window pumps every
    /// frame instead.
    pub async fn pump_until(
        &mut self,
        timeout: std::time::Duration,
        done: impl Fn(&ViewerApp) -> bool,
    ) -> bool {
        let deadline = tokio::time::Instant::now() + timeout;
        loop {
            self.pump();
            if done(self) {
                return true;
            }
            if tokio::time::Instant::now() >= deadline {
                return false;
            }
            tokio::time::sleep(std::time::Duration::from_millis(2)).await;
        }
    }

    /// Ranks by `by` over the chosen objects (what choosing it in the sorter does; by the
    /// goal orientation, nothing is ranked until a goal is picked).
    pub fn set_sort(&mut self, by: SortBy) {
        self.sort_by = by;
        self.send(Msg::Rank(self.sort_spec(by)));
    }

    /// The ranking `by` means now: over the chosen objects, to the current goal.
    fn sort_spec(&self, by: SortBy) -> Option<RankSpec> {
        let goal = self.state.goal().map(|g| g.rotation);
        by.spec(self.state.chosen_objects(), None, SORTER_ROWS, goal)
    }

    /// The sorter's choice.
    pub fn sort_by(&self) -> SortBy {
        self.sort_by
    }

    /// Commands waiting for room in the bus task's queue.
    pub fn unsent(&self) -> usize {
        self.unsent.len()
    }

    /// Sets whether the camera was already placed (then the first frame does not frame all).
    pub fn with_camera_placed(mut self, placed: bool) -> Self {
        self.framed = placed;
        self
    }

    /// Draws the 3D view alone, without panels, bars or timeline (`mwb scene preview`).
    pub fn view_only(mut self) -> Self {
        self.chrome = false;
        self
    }

    /// The 3D view's rectangle in the last frame, egui points.
    pub fn view_rect(&self) -> Rect {
        self.view_rect
    }

    pub fn last_error(&self) -> Option<&str> {
        self.last_error.as_deref()
    }

    /// Adds a constraint from a rectangle in pixels of the 3D view as it was last drawn (what
    /// a drag there does; for scripts, screenshots and tests).
    pub fn add_box_px(&mut self, rect: ScreenRect, polarity: Polarity, ppp: f32) {
        let Some(view) = View::new(&self.state.camera, self.view_rect, ppp) else {
            self.last_error = Some("the 3D view has not been laid out yet".into());
            return;
        };
        self.send(Msg::AddConstraint {
            viewport: view.viewport,
            rect,
            polarity,
        });
    }

    fn send(&mut self, msg: Msg) {
        match self.state.update(msg) {
            Ok(()) => self.last_error = None,
            Err(e) => self.last_error = Some(e.to_string()),
        }
    }

    /// Draws the whole UI into `ui` (the window's root) and applies what the user did.
    pub fn ui(&mut self, ui: &mut egui::Ui) {
        self.pump();
        self.keys(ui);
        if self.chrome {
            self.top_bar(ui);
            self.status_bar(ui);
            self.timeline(ui);
            self.side_panel(ui);
        }
        egui::CentralPanel::no_frame().show(ui, |ui| self.view(ui));
        // What the frame's gestures asked for leaves now, not a frame later.
        self.pump();
        self.keep_views();
    }

    fn keys(&mut self, ui: &egui::Ui) {
        if ui.ctx().text_edit_focused() {
            return;
        }
        let (redo, undo, frame, frame_all, play, back, fwd) = ui.input_mut(|i| {
            let redo = i.consume_shortcut(&KeyboardShortcut::new(
                Modifiers::COMMAND | Modifiers::SHIFT,
                Key::Z,
            )) || i.consume_shortcut(&KeyboardShortcut::new(Modifiers::COMMAND, Key::Y));
            let undo = i.consume_shortcut(&KeyboardShortcut::new(Modifiers::COMMAND, Key::Z));
            let frame = i.consume_key(Modifiers::NONE, Key::F);
            let frame_all = i.consume_key(Modifiers::NONE, Key::A);
            let play = i.consume_key(Modifiers::NONE, Key::Space);
            let back = i.consume_key(Modifiers::NONE, Key::ArrowLeft);
            let fwd = i.consume_key(Modifiers::NONE, Key::ArrowRight);
            (redo, undo, frame, frame_all, play, back, fwd)
        });
        if redo {
            self.send(Msg::Redo);
        } else if undo {
            self.send(Msg::Undo);
        }
        if frame {
            self.send(Msg::FrameSelected {
                aspect: self.aspect(),
            });
        }
        if frame_all {
            self.frame_all();
        }
        if play {
            self.send(Msg::TogglePlay);
        }
        if back {
            self.send(Msg::Step(-1));
        }
        if fwd {
            self.send(Msg::Step(1));
        }
    }

    /// The 3D view's aspect ratio (16:9 before it is laid out).
    fn aspect(&self) -> f64 {
        let r = self.view_rect;
        if r.is_positive() {
            f64::from(r.width() / r.height())
        } else {
            16.0 / 9.0
        }
    }

    fn frame_all(&mut self) {
        self.send(Msg::FrameAll {
            aspect: self.aspect(),
        });
    }

    fn top_bar(&mut self, ui: &mut egui::Ui) {
        egui::Panel::top("mwb-top").show(ui, |ui| {
            ui.horizontal(|ui| {
                ui.label(RichText::new("manyworlds").strong());
                ui.separator();
                ui.label(format!("scene {}", self.state.scene_name()));
                ui.separator();
                let n = self.state.world_total();
                let s = self.state.survivor_count();
                ui.label(format!("{n} worlds"));
                let pending = self.state.pending() as usize + self.unsent.len();
                let survive = if pending > 0 {
                    format!("{s} survive …")
                } else {
                    format!("{s} survive")
                };
                ui.label(
                    RichText::new(survive)
                        .color(Color32::from_rgb(120, 195, 255))
                        .strong(),
                )
                .on_hover_text(if pending > 0 {
                    "waiting for the store's answer to the last edit"
                } else {
                    "worlds that satisfy every constraint"
                });
                // Offline every world is here: no count to make each frame.
                let drawn = if self.state.is_live() {
                    self.state.held_survivors() as u64
                } else {
                    s
                };
                if drawn < s {
                    ui.label(RichText::new(format!("({drawn} drawn)")).weak())
                        .on_hover_text(
                            "the stores hold more worlds than this viewer draws: it holds a \
                             uniform sample of the survivors (viewer --max-worlds)",
                        );
                }
                if !self.state.problems().is_empty() {
                    ui.separator();
                    let problems = self.state.problems();
                    let shown: Vec<&str> =
                        problems.iter().rev().take(20).map(String::as_str).collect();
                    ui.colored_label(
                        Color32::from_rgb(240, 170, 60),
                        format!("{} problems", problems.len()),
                    )
                    .on_hover_text(shown.join("\n"));
                }
                let error = self
                    .last_error
                    .clone()
                    .or_else(|| self.state.browse_error().map(str::to_owned));
                if let Some(e) = error {
                    ui.separator();
                    ui.colored_label(Color32::from_rgb(240, 90, 90), e);
                }
                ui.with_layout(Layout::right_to_left(Align::Center), |ui| {
                    if ui.button("Frame all (A)").clicked() {
                        self.frame_all();
                    }
                    let (can_undo, can_redo) = (self.state.can_undo(), self.state.can_redo());
                    if ui
                        .add_enabled(can_redo, egui::Button::new("Redo"))
                        .on_hover_text("Ctrl+Shift+Z")
                        .clicked()
                    {
                        self.send(Msg::Redo);
                    }
                    if ui
                        .add_enabled(can_undo, egui::Button::new("Undo"))
                        .on_hover_text("Ctrl+Z")
                        .clicked()
                    {
                        self.send(Msg::Undo);
                    }
                });
            });
        });
    }

    /// The connection and the cluster (live viewers), or where the worlds came from.
    fn status_bar(&mut self, ui: &mut egui::Ui) {
        egui::Panel::bottom("mwb-status").show(ui, |ui| {
            ui.horizontal(|ui| {
                self.link_status(ui);
                match &self.views_notice {
                    Some(Notice::Info(n)) => {
                        ui.separator();
                        ui.label(RichText::new(n).weak());
                    }
                    Some(Notice::Problem(p)) => {
                        ui.separator();
                        ui.colored_label(Color32::from_rgb(240, 170, 60), p);
                    }
                    None => {}
                }
            });
        });
    }

    /// The status bar's account of the bus (or of the offline worlds).
    fn link_status(&self, ui: &mut egui::Ui) {
        let Some(link) = self.state.link() else {
            ui.label(
                RichText::new(format!(
                    "offline: {} worlds sampled in this process",
                    self.state.worlds().len()
                ))
                .weak(),
            );
            return;
        };
        let (colour, what) = if link.connected {
            (Color32::from_rgb(90, 200, 110), "connected")
        } else {
            (Color32::from_rgb(230, 90, 80), "not connected")
        };
        let (r, _) = ui.allocate_exact_size(egui::vec2(10.0, 10.0), Sense::hover());
        ui.painter().circle_filled(r.center(), 4.5, colour);
        ui.label(format!("{what} to {}", link.endpoint))
            .on_hover_text(link.error.as_deref().unwrap_or("every request answered"));
        if let Some(e) = &link.error {
            ui.colored_label(Color32::from_rgb(240, 170, 60), e);
        }
        ui.separator();
        ui.label(format!(
            "{} store{} · {} sampler{}",
            link.stores,
            if link.stores == 1 { "" } else { "s" },
            link.samplers,
            if link.samplers == 1 { "" } else { "s" }
        ));
        ui.separator();
        let held = self.state.worlds().len();
        let sampled = link.max_worlds > 0 && link.held < link.indexed;
        ui.label(format!(
            "{} stored · {held} {} · {:.1} worlds/s",
            link.store_worlds,
            if sampled {
                "drawn (a sample)"
            } else {
                "loaded here"
            },
            link.worlds_per_s
        ))
        .on_hover_text(if sampled {
            format!(
                "this viewer holds the paths of at most {} worlds (--max-worlds): half a \
                 uniform sample of every world, half the survivors",
                link.max_worlds
            )
        } else {
            "every stored world's paths are here".to_owned()
        });
        if link.memory_cap_bytes > 0 {
            ui.separator();
            ui.label(format!(
                "store memory {:.0} / {:.0} MiB",
                link.memory_bytes as f64 / 1048576.0,
                link.memory_cap_bytes as f64 / 1048576.0
            ));
        }
        for (job, done, target) in &link.jobs {
            ui.separator();
            let frac = if *target > 0 {
                *done as f32 / *target as f32
            } else {
                0.0
            };
            ui.label(format!("job {job}"));
            ui.add(
                egui::ProgressBar::new(frac)
                    .desired_width(90.0)
                    .text(format!("{done}/{target}")),
            );
        }
        if !self.unsent.is_empty() {
            ui.separator();
            ui.colored_label(
                Color32::from_rgb(240, 170, 60),
                format!("{} edits waiting for the bus", self.unsent.len()),
            );
        }
    }

    fn side_panel(&mut self, ui: &mut egui::Ui) {
        egui::Panel::left("mwb-side")
            .default_size(270.0)
            .show(ui, |ui| {
                egui::ScrollArea::vertical()
                    .auto_shrink([false, false])
                    .show(ui, |ui| {
                        if self.state.is_live() {
                            self.jobs_section(ui);
                            ui.separator();
                        }
                        self.objects_section(ui);
                        ui.separator();
                        self.constraints_section(ui);
                        ui.separator();
                        self.sorter_section(ui);
                        ui.separator();
                        self.views_section(ui);
                        ui.separator();
                        self.survivors_section(ui);
                    });
            });
    }

    /// Live: submit a job of a scene (a file or a shipped name), follow and cancel open jobs.
    fn jobs_section(&mut self, ui: &mut egui::Ui) {
        use mwb_proto::v1::Quality;
        egui::CollapsingHeader::new("Jobs")
            .default_open(true)
            .show(ui, |ui| {
                if self.job_form.scene.is_empty() && !self.state.body_names().is_empty() {
                    self.job_form.scene = self.state.scene_name().to_owned();
                }
                ui.horizontal(|ui| {
                    let label = ui.label("scene");
                    ui.add(
                        egui::TextEdit::singleline(&mut self.job_form.scene)
                            .hint_text("tumble, or a .toml file")
                            .desired_width(150.0),
                    )
                    .labelled_by(label.id);
                });
                ui.horizontal(|ui| {
                    ui.add(
                        egui::DragValue::new(&mut self.job_form.worlds)
                            .range(1..=1_000_000)
                            .speed(10)
                            .suffix(" worlds"),
                    );
                    let q = &mut self.job_form.quality;
                    egui::ComboBox::new("mwb-job-quality", "quality")
                        .selected_text(match q {
                            Quality::Draft => "draft",
                            Quality::Final => "final",
                            _ => "standard",
                        })
                        .show_ui(ui, |ui| {
                            ui.selectable_value(q, Quality::Draft, "draft (5 mm)");
                            ui.selectable_value(q, Quality::Standard, "standard (1 mm)");
                            ui.selectable_value(q, Quality::Final, "final (0.1 mm)");
                        });
                });
                ui.horizontal(|ui| {
                    use mwb_core::scene::SimPreset;
                    let p = &mut self.job_form.sim;
                    egui::ComboBox::new("mwb-job-sim", "simulation")
                        .selected_text(p.map_or("the scene's", SimPreset::name))
                        .show_ui(ui, |ui| {
                            ui.selectable_value(p, None, "the scene's");
                            ui.selectable_value(p, Some(SimPreset::Draft), "draft (fastest)");
                            ui.selectable_value(p, Some(SimPreset::Standard), "standard");
                            ui.selectable_value(p, Some(SimPreset::Final), "final (accurate)");
                            ui.selectable_value(p, Some(SimPreset::Auto), "auto (calibrate)");
                        })
                        .response
                        .on_hover_text(
                            "substeps, iterations, CCD and sleeping (docs/fidelity.md); auto \
                             samples a few worlds at each preset and picks the cheapest within \
                             the scene's tolerance",
                        );
                });
                let ready = !self.job_form.scene.trim().is_empty();
                if ui
                    .add_enabled(ready, egui::Button::new("Submit job"))
                    .on_hover_text("samplers on the bus take it at once")
                    .clicked()
                {
                    let f = self.job_form.clone();
                    self.send(Msg::SubmitJob {
                        scene: f.scene.trim().to_owned(),
                        worlds: f.worlds,
                        quality: f.quality,
                        sim: f.sim,
                    });
                }
                // §4.5: the next box drawn says where the shown world must change.
                ui.horizontal(|ui| {
                    let shown = self.state.selected().is_some();
                    ui.add_enabled(
                        shown,
                        egui::Checkbox::new(&mut self.job_form.refine_next, "next box refines"),
                    )
                    .on_hover_text(
                        "re-simulate the chosen objects of the shown world from the first frame \
                         one of them is inside the next box you draw",
                    );
                    ui.add(
                        egui::DragValue::new(&mut self.job_form.refine_worlds)
                            .range(1..=100_000)
                            .speed(5)
                            .suffix(" worlds"),
                    );
                });
                match self.state.job_notice() {
                    Some(Ok(n)) => {
                        ui.label(RichText::new(n).weak());
                    }
                    Some(Err(e)) => {
                        ui.colored_label(Color32::from_rgb(240, 90, 90), e);
                    }
                    None => {}
                }
                let jobs = self
                    .state
                    .link()
                    .map(|l| l.jobs.clone())
                    .unwrap_or_default();
                let mut cancel = None;
                for (job, done, target) in jobs {
                    ui.horizontal(|ui| {
                        let frac = if target > 0 {
                            done as f32 / target as f32
                        } else {
                            0.0
                        };
                        ui.add(
                            egui::ProgressBar::new(frac)
                                .desired_width(120.0)
                                .text(format!("{done}/{target}")),
                        )
                        .on_hover_text(format!("job {job}"));
                        if ui
                            .small_button("cancel")
                            .on_hover_text(format!("cancel job {job}"))
                            .clicked()
                        {
                            cancel = Some(job.clone());
                        }
                    });
                }
                if let Some(job) = cancel {
                    self.send(Msg::CancelJob(job));
                }
            });
    }

    fn objects_section(&mut self, ui: &mut egui::Ui) {
        ui.add_space(4.0);
        let names: Vec<String> = self.state.body_names().to_vec();
        let many = names.len() > OBJECT_ROWS;
        ui.horizontal(|ui| {
            ui.heading("Objects");
            if many {
                // Scenes of many bodies (tower: 193) are browsed an object or two at a time.
                let n = names.len() as u32;
                if ui
                    .small_button("all")
                    .on_hover_text("choose every object")
                    .clicked()
                {
                    self.send(Msg::ChooseObjects((0..n).collect()));
                }
                if ui
                    .small_button("none")
                    .on_hover_text("choose no object (then tick the ones to browse)")
                    .clicked()
                {
                    self.send(Msg::ChooseObjects(Vec::new()));
                }
                let chosen = self.state.chosen_objects().len();
                ui.label(RichText::new(format!("{chosen} of {n}")).weak());
            }
        });
        if names.is_empty() {
            ui.label(RichText::new("waiting for the first world …").weak());
        }
        if many {
            egui::ScrollArea::vertical()
                .id_salt("mwb-objects")
                .max_height(OBJECT_ROWS as f32 * 23.0)
                .auto_shrink([false, true])
                .show(ui, |ui| self.object_rows(ui, &names));
        } else {
            self.object_rows(ui, &names);
        }
    }

    /// One checkbox per object, with its colour.
    fn object_rows(&mut self, ui: &mut egui::Ui, names: &[String]) {
        for (i, name) in names.iter().enumerate() {
            let mut on = self.state.is_chosen(i as u32);
            ui.horizontal(|ui| {
                let c = draw::palette::BODIES[i % draw::palette::BODIES.len()]
                    .map(|v| (v * 255.0) as u8);
                let (r, _) = ui.allocate_exact_size(egui::vec2(10.0, 10.0), Sense::hover());
                ui.painter()
                    .rect_filled(r, 2.0, Color32::from_rgb(c[0], c[1], c[2]));
                if ui.checkbox(&mut on, name.as_str()).changed() {
                    self.send(Msg::ToggleObject(i as u32));
                }
            });
        }
    }

    fn constraints_section(&mut self, ui: &mut egui::Ui) {
        ui.heading("Constraints");
        let names = self.state.body_names();
        let total = self.state.world_total();
        let rows = self.state.constraint_rows();
        if rows.is_empty() {
            ui.label(
                RichText::new(
                    "Drag a box in the view: keep worlds whose paths pass through it. \
                     Shift+drag: worlds that never do.",
                )
                .weak(),
            );
        }
        let mut remove = None;
        for row in rows {
            ui.horizontal(|ui| {
                let (sign, col) = match row.polarity {
                    Polarity::Positive => ("+", draw::palette::POSITIVE),
                    Polarity::Negative => ("-", draw::palette::NEGATIVE),
                };
                ui.label(
                    RichText::new(sign)
                        .strong()
                        .color(Color32::from_rgb(col[0], col[1], col[2])),
                );
                let over = if row.objects.len() == names.len() {
                    "all".to_owned()
                } else {
                    row.objects
                        .iter()
                        .map(|&o| {
                            names
                                .get(o as usize)
                                .cloned()
                                .unwrap_or_else(|| format!("#{o}"))
                        })
                        .collect::<Vec<_>>()
                        .join(", ")
                };
                let window = row
                    .window
                    .map(|w| format!(" [{:.2}–{:.2} s]", w.start(), w.end()))
                    .unwrap_or_default();
                ui.label(format!(
                    "#{} {over}{window}: {}/{total}",
                    row.id, row.satisfied
                ));
                ui.with_layout(Layout::right_to_left(Align::Center), |ui| {
                    if ui
                        .small_button(format!("x #{}", row.id))
                        .on_hover_text("remove this constraint")
                        .clicked()
                    {
                        remove = Some(row.id);
                    }
                });
            });
        }
        if let Some(id) = remove {
            self.send(Msg::RemoveConstraint(id));
        }
    }

    fn sorter_section(&mut self, ui: &mut egui::Ui) {
        ui.heading("Sort");
        let mut by = self.sort_by;
        let mut on = self.state.rank_spec().is_some();
        let before = (by, on);
        ui.horizontal(|ui| {
            ui.checkbox(&mut on, "rank");
            egui::ComboBox::new("mwb-sort-by", "first")
                .selected_text(by.label())
                .show_ui(ui, |ui| {
                    for b in SortBy::ALL {
                        ui.selectable_value(&mut by, b, b.label());
                    }
                });
        });
        // A new choice of objects re-ranks over them.
        let objects = self.state.chosen_objects();
        let stale = self.state.rank_spec().is_some_and(|s| match &s.key {
            RankKey::Metric { objects: o, .. } | RankKey::OrientationTo { objects: o, .. } => {
                *o != objects
            }
            _ => false,
        });
        if (by, on) != before || (on && stale) {
            self.sort_by = by;
            if by != before.0 {
                on = true;
            }
            let spec = if on { self.sort_spec(by) } else { None };
            self.send(Msg::Rank(spec));
        }
        self.goal_rows(ui);
        let Some(ranking) = self.state.ranking() else {
            if self.state.rank_spec().is_some() {
                ui.label(RichText::new("ranking …").weak());
            }
            return;
        };
        let unit = self.sort_by.unit();
        let mut summary = format!("top {} of {}", ranking.rows.len(), ranking.candidates);
        if ranking.unscored > 0 {
            summary += &format!(" · {} without a value, last", ranking.unscored);
        }
        ui.label(RichText::new(summary).weak());
        let rows = ranking.rows.clone();
        let selected = self.state.selected();
        let mut pick = None;
        self.sorter_hover = None;
        for (rank, r) in rows.iter().enumerate() {
            let value = r
                .score
                .map_or_else(|| "—".to_owned(), |v| format!("{v:.3} {unit}"));
            let resp = ui.selectable_label(
                selected == Some(r.world),
                format!("{:>2}. world {}   {}", rank + 1, r.world, value),
            );
            if resp.hovered() {
                self.sorter_hover = Some(r.world);
            }
            if resp.clicked() {
                pick = Some(r.world);
            }
        }
        if let Some(w) = pick {
            self.send(Msg::SelectWorld(Some(w)));
        }
    }

    /// The goal orientation for "closest to the goal orientation": taken from the playback
    /// (the first chosen object, in the world shown, at the frame shown), and what it is.
    fn goal_rows(&mut self, ui: &mut egui::Ui) {
        let names = self.state.body_names().to_vec();
        let name = |o: u32| {
            names
                .get(o as usize)
                .cloned()
                .unwrap_or_else(|| format!("#{o}"))
        };
        let object = self.state.chosen_objects().first().copied();
        let shown = self
            .state
            .shown_world()
            .filter(|w| w.motion.is_some())
            .map(|w| w.index);
        let why_not = match (object, shown) {
            (None, _) => "choose an object first".to_owned(),
            (Some(_), None) => "play a world first (pick one; its motion must be loaded)".into(),
            (Some(o), Some(w)) => format!(
                "{}'s orientation in world {w} at the frame shown (the first chosen object)",
                name(o)
            ),
        };
        let pick = ui
            .add_enabled(
                object.is_some() && shown.is_some(),
                egui::Button::new("Use this frame's orientation as goal").small(),
            )
            .on_hover_text(&why_not)
            .on_disabled_hover_text(&why_not)
            .clicked();
        let goal = self.state.goal().copied();
        if let Some(g) = goal {
            ui.horizontal(|ui| {
                ui.label(
                    RichText::new(format!(
                        "goal: {} in world {} at {:.2} s",
                        name(g.object),
                        g.world,
                        g.time
                    ))
                    .weak(),
                );
                if ui.small_button("clear goal").clicked() {
                    self.send(Msg::ClearGoal);
                }
            });
        } else if self.sort_by == SortBy::OrientationToGoal {
            ui.label(RichText::new("no goal yet: play a world, stop at a frame, use it").weak());
        }
        if pick {
            self.send(Msg::GoalFromPlayback);
            if self.last_error.is_none() {
                self.set_sort(SortBy::OrientationToGoal);
            }
        }
    }

    /// Saved cameras: save the current one, go back to one, forget one.
    fn views_section(&mut self, ui: &mut egui::Ui) {
        ui.horizontal(|ui| {
            ui.heading("Views");
            if ui
                .small_button("save view")
                .on_hover_text("keep this camera to come back to")
                .clicked()
            {
                let name = self.state.next_view_name();
                self.send(Msg::SaveView(name));
            }
        });
        let names: Vec<String> = self.state.views().iter().map(|v| v.name.clone()).collect();
        let (mut recall, mut delete) = (None, None);
        for (i, name) in names.iter().enumerate() {
            ui.horizontal(|ui| {
                if ui.selectable_label(false, name).clicked() {
                    recall = Some(i);
                }
                if ui
                    .small_button(format!("x {name}"))
                    .on_hover_text("forget this view")
                    .clicked()
                {
                    delete = Some(i);
                }
            });
        }
        if let Some(i) = recall {
            self.send(Msg::RecallView(i));
        }
        if let Some(i) = delete {
            self.send(Msg::DeleteView(i));
        }
    }

    fn survivors_section(&mut self, ui: &mut egui::Ui) {
        ui.heading(format!("Survivors ({})", self.state.survivor_count()));
        // Every survivor, in a list of its own that lays out only the rows in sight (a frame
        // with 10 000 survivors costs what one with 20 does).
        let survivors: Vec<u32> = self.state.survivors().collect();
        let selected = self.state.selected();
        let mut pick = None;
        let row = ui.text_style_height(&egui::TextStyle::Button) + ui.spacing().item_spacing.y;
        egui::ScrollArea::vertical()
            .id_salt("mwb-survivors")
            .max_height(320.0)
            .auto_shrink([false, true])
            .show_rows(ui, row, survivors.len(), |ui, range| {
                for &w in &survivors[range] {
                    let label = match self.state.world(w) {
                        Some(d) => format!("world {w}  (seed {:#x})", d.seed),
                        // Not arrived yet, or outside the sample a viewer of a large store
                        // holds: picking it fetches it.
                        None => format!("world {w}  (not drawn; pick to fetch)"),
                    };
                    if ui.selectable_label(selected == Some(w), label).clicked() {
                        pick = Some(if selected == Some(w) { None } else { Some(w) });
                    }
                }
            });
        if let Some(p) = pick {
            self.send(Msg::SelectWorld(p));
        }
    }

    fn timeline(&mut self, ui: &mut egui::Ui) {
        egui::Panel::bottom("mwb-timeline").show(ui, |ui| {
            ui.add_space(3.0);
            ui.horizontal(|ui| {
                let pb = self.state.playback();
                let label = if pb.playing { "Pause" } else { "Play" };
                if ui.button(label).on_hover_text("Space").clicked() {
                    self.send(Msg::TogglePlay);
                }
                if ui
                    .button("<")
                    .on_hover_text("one frame back (Left)")
                    .clicked()
                {
                    self.send(Msg::Step(-1));
                }
                if ui
                    .button(">")
                    .on_hover_text("one frame on (Right)")
                    .clicked()
                {
                    self.send(Msg::Step(1));
                }
                let end = self.state.duration();
                let mut t = pb.time;
                ui.style_mut().spacing.slider_width = (ui.available_width() - 640.0).max(120.0);
                let r = ui.add(
                    egui::Slider::new(&mut t, 0.0..=end.max(1e-3))
                        .show_value(false)
                        .text("time"),
                );
                if r.changed() {
                    self.send(Msg::Seek(t));
                }
                ui.monospace(format!("{:5.2} / {:.2} s", pb.time, end));
                ui.separator();
                let mut speed = pb.speed;
                ui.style_mut().spacing.slider_width = 80.0;
                if ui
                    .add(
                        egui::Slider::new(&mut speed, MIN_SPEED..=MAX_SPEED)
                            .logarithmic(true)
                            .show_value(false)
                            .text(format!("{:.1}× speed", pb.speed)),
                    )
                    .changed()
                {
                    self.send(Msg::SetSpeed(speed));
                }
                let mut looping = pb.looping;
                if ui.checkbox(&mut looping, "loop").changed() {
                    self.send(Msg::SetLoop(looping));
                }
                ui.separator();
                let loading = if self.state.shown_loading() {
                    " — loading motion …"
                } else {
                    ""
                };
                match self.state.shown_world() {
                    Some(w) if self.state.selected() == Some(w.index) => {
                        ui.label(format!("world {} (seed {:#x}){loading}", w.index, w.seed));
                    }
                    Some(w) => {
                        ui.label(
                            RichText::new(format!("world {} (first survivor)", w.index)).weak(),
                        );
                    }
                    None => {
                        ui.label(RichText::new("no world").weak());
                    }
                }
            });
            self.window_row(ui);
            ui.add_space(2.0);
        });
    }

    /// The time window new boxes count in: off (the whole motion), or [start, end] seconds, set
    /// by value or from the playhead.
    fn window_row(&mut self, ui: &mut egui::Ui) {
        ui.horizontal(|ui| {
            let current = self.state.window();
            let mut on = current.is_some();
            let now = self.state.playback().time;
            let end_max = self.state.duration().max(1e-3);
            let (mut a, mut b) = current.map_or((0.0, end_max), |w| (w.start(), w.end()));
            let before = (on, a, b);
            ui.checkbox(&mut on, "new boxes count only from")
                .on_hover_text(
                    "a box then keeps worlds whose objects pass through it in this window",
                );
            // One end of the window: typed, or set from the playhead.
            let end = |ui: &mut egui::Ui, t: &mut f64, which: &str| {
                ui.add_enabled(
                    on,
                    egui::DragValue::new(t)
                        .speed(0.01)
                        .max_decimals(2)
                        .range(0.0..=end_max)
                        .suffix(" s"),
                );
                if ui
                    .add_enabled(on, egui::Button::new("now").small())
                    .on_hover_text(format!("{which} at the playhead"))
                    .clicked()
                {
                    *t = now;
                }
            };
            end(ui, &mut a, "start");
            ui.label("to");
            end(ui, &mut b, "end");
            if (on, a, b) != before {
                let window = if on {
                    match TimeWindow::new(a.min(b), a.max(b)) {
                        Ok(w) => Some(w),
                        Err(e) => {
                            self.last_error = Some(e.to_string());
                            return;
                        }
                    }
                } else {
                    None
                };
                self.send(Msg::SetWindow(window));
            }
        });
    }

    fn view(&mut self, ui: &mut egui::Ui) {
        let rect = ui.max_rect();
        self.view_rect = rect;
        if !self.framed && rect.is_positive() {
            if !self.state.worlds().is_empty() {
                self.framed = true;
                self.frame_all();
            } else if !self.framed_scene && !self.state.initial().is_empty() {
                self.framed_scene = true;
                self.frame_all();
            }
        }
        let resp = ui.allocate_rect(rect, Sense::click_and_drag());
        let ppp = ui.ctx().pixels_per_point();
        let (mods, scroll) = ui.input(|i| (i.modifiers, i.smooth_scroll_delta));

        // Camera gestures.
        let d = resp.drag_delta();
        let alt = mods.alt;
        if resp.dragged_by(PointerButton::Secondary) && alt {
            self.send(Msg::Zoom {
                factor: (f64::from(d.y - d.x) * -0.01).exp(),
            });
        } else if resp.dragged_by(PointerButton::Secondary)
            || (alt && resp.dragged_by(PointerButton::Primary))
        {
            self.send(Msg::Orbit {
                d_yaw: -f64::from(d.x) * ORBIT_PER_PT,
                d_pitch: f64::from(d.y) * ORBIT_PER_PT,
            });
        } else if resp.dragged_by(PointerButton::Middle) {
            self.send(Msg::Pan {
                dx: f64::from(d.x * ppp),
                dy: f64::from(d.y * ppp),
                height: f64::from(rect.height() * ppp),
            });
        }
        if resp.hovered() && scroll.y != 0.0 {
            self.send(Msg::Zoom {
                factor: (-f64::from(scroll.y) * 0.0015).exp(),
            });
        }

        // Box drawing with the primary button.
        if resp.drag_started_by(PointerButton::Primary) && !alt {
            let start = ui
                .input(|i| i.pointer.press_origin())
                .or(resp.interact_pointer_pos())
                .unwrap_or(rect.center());
            self.drag = Some(Drag {
                start,
                current: start,
                negative: mods.shift,
            });
        }
        if let Some(drag) = &mut self.drag {
            if let Some(p) = resp.interact_pointer_pos() {
                drag.current = p;
            }
            drag.negative = mods.shift;
        }
        if resp.drag_stopped_by(PointerButton::Primary)
            && let Some(drag) = self.drag.take()
        {
            self.finish_box(drag, rect, ppp);
        }
        if !resp.dragged() && !resp.drag_stopped() {
            self.drag = None;
        }

        let view = View::new(&self.state.camera, rect, ppp);
        self.hovered = match (&view, resp.hover_pos()) {
            (Some(v), Some(p)) if self.drag.is_none() => draw::pick_world(&self.state, v, p, 6.0),
            _ => None,
        };
        if resp.clicked_by(PointerButton::Primary) {
            self.send(Msg::SelectWorld(self.hovered));
        }
        if let Some(view) = view {
            let overlay = Overlay {
                drag: self.drag.map(|d| (d.start, d.current, d.negative)),
                hovered: self.hovered.or(self.sorter_hover),
            };
            let painter = ui.painter_at(rect);
            painter.extend(draw::scene_shapes(
                &self.state,
                &view,
                overlay,
                &mut self.path_meshes,
            ));
            if self.chrome {
                let hint = "drag: keep paths through a box · shift+drag: never through · \
                            right-drag: orbit · middle-drag: pan · wheel: zoom · F: frame selected · A: frame all";
                painter.text(
                    rect.left_bottom() + egui::vec2(8.0, -8.0),
                    egui::Align2::LEFT_BOTTOM,
                    hint,
                    egui::FontId::proportional(11.0),
                    Color32::from_gray(130),
                );
            }
            if let Some(w) = self.hovered {
                painter.text(
                    resp.hover_pos().unwrap_or(rect.center()) + egui::vec2(12.0, -4.0),
                    egui::Align2::LEFT_BOTTOM,
                    format!("world {w}"),
                    egui::FontId::proportional(12.0),
                    Color32::from_gray(230),
                );
            }
        }
    }

    fn finish_box(&mut self, drag: Drag, rect: Rect, ppp: f32) {
        let r = Rect::from_two_pos(drag.start, drag.current).intersect(rect);
        if r.width() < MIN_BOX_PT || r.height() < MIN_BOX_PT {
            return;
        }
        let Some(view) = View::new(&self.state.camera, rect, ppp) else {
            return;
        };
        let (a, b) = (view.pixel(r.min), view.pixel(r.max));
        let rect = ScreenRect {
            x0: a[0],
            y0: a[1],
            x1: b[0],
            y1: b[1],
        };
        if std::mem::take(&mut self.job_form.refine_next) {
            self.send(Msg::Refine {
                viewport: view.viewport,
                rect,
                worlds: self.job_form.refine_worlds,
            });
            return;
        }
        self.send(Msg::AddConstraint {
            viewport: view.viewport,
            rect,
            polarity: if drag.negative {
                Polarity::Negative
            } else {
                Polarity::Positive
            },
        });
    }
}

impl eframe::App for ViewerApp {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        let dt = ui.input(|i| i.stable_dt);
        // Ticks cannot fail; going through `send` would clear the last error every frame.
        let _ = self.state.update(Msg::Tick(f64::from(dt)));
        self.ui(ui);
        if self.state.playback().playing {
            ui.ctx().request_repaint();
        } else if self.link.is_some() {
            // The status bar stays current even when the bus task has nothing to say.
            ui.ctx()
                .request_repaint_after(std::time::Duration::from_millis(500));
        }
    }
}

/// Where a bus task finds the window to wake when it has news (filled when the window opens).
#[derive(Clone, Default)]
pub struct RepaintSlot(Arc<OnceLock<egui::Context>>);

impl RepaintSlot {
    /// What the bus task calls after queueing messages.
    pub fn waker(&self) -> Arc<dyn Fn() + Send + Sync> {
        let slot = self.0.clone();
        Arc::new(move || {
            if let Some(ctx) = slot.get() {
                ctx.request_repaint();
            }
        })
    }

    pub fn set(&self, ctx: &egui::Context) {
        // A second window would keep waking the first; there is only ever one.
        let _ = self.0.set(ctx.clone());
    }
}

/// Opens the viewer in a native window (eframe, glow) and runs until it is closed.
pub fn run_window(
    app: ViewerApp,
    title: &str,
    size: [u32; 2],
    repaint: RepaintSlot,
) -> Result<(), eframe::Error> {
    let options = eframe::NativeOptions {
        viewport: egui::ViewportBuilder::default()
            .with_title(title)
            .with_inner_size([size[0] as f32, size[1] as f32]),
        ..Default::default()
    };
    eframe::run_native(
        "manyworlds viewer",
        options,
        Box::new(move |cc| {
            repaint.set(&cc.egui_ctx);
            Ok(Box::new(app))
        }),
    )
}
