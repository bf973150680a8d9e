//! The viewer's window: panels around a 3D view. Everything the user does becomes a [`Msg`]
//! applied to the [`ViewerState`]; this module holds only what a gesture needs while it lasts
//! (the rectangle being dragged) and the last frame's view rectangle.
//!
//! Mouse in the 3D view: left-drag draws a positive box, Shift+left-drag a negative one;
//! right-drag or Alt+left-drag orbits; middle-drag or Alt+middle-drag pans; wheel or
//! Alt+right-drag zooms; a click picks the nearest path's world. Keys: F frames everything,
//! Ctrl+Z / Ctrl+Shift+Z (or Ctrl+Y) undo and redo, Space plays / pauses, ←/→ step a frame.

use egui::{
    Align, Color32, Key, KeyboardShortcut, Layout, Modifiers, PointerButton, Pos2, Rect, RichText,
    Sense,
};
use mwb_core::browse::{Polarity, ScreenRect};

use crate::draw::{self, Overlay, View};
use crate::state::{MAX_SPEED, MIN_SPEED, Msg, ViewerState};

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

/// The viewer: state plus the gesture in progress.
pub struct ViewerApp {
    pub state: ViewerState,
    drag: Option<Drag>,
    view_rect: Rect,
    hovered: Option<u32>,
    /// The last error an action caused (shown in the top bar until the next action).
    last_error: Option<String>,
    framed: bool,
}

impl ViewerApp {
    pub fn new(state: ViewerState) -> Self {
        Self {
            state,
            drag: None,
            view_rect: Rect::NOTHING,
            hovered: None,
            last_error: None,
            framed: false,
        }
    }

    /// Sets whether the camera was already placed (then the first frame does not frame all).
    pub fn with_camera_placed(mut self, placed: bool) -> Self {
        self.framed = placed;
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
        self.keys(ui);
        self.top_bar(ui);
        self.side_panel(ui);
        self.timeline(ui);
        egui::CentralPanel::no_frame().show(ui, |ui| self.view(ui));
    }

    fn keys(&mut self, ui: &egui::Ui) {
        if ui.ctx().text_edit_focused() {
            return;
        }
        let (redo, undo, frame, play, back, fwd) = ui.input_mut(|i| {
            let redo = i.consume_shortcut(&KeyboardShortcut::new(
                Modifiers::COMMAND | Modifiers::SHIFT,
                Key::Z,
            )) || i.consume_shortcut(&KeyboardShortcut::new(Modifiers::COMMAND, Key::Y));
            let undo = i.consume_shortcut(&KeyboardShortcut::new(Modifiers::COMMAND, Key::Z));
            let frame = i.consume_key(Modifiers::NONE, Key::F);
            let play = i.consume_key(Modifiers::NONE, Key::Space);
            let back = i.consume_key(Modifiers::NONE, Key::ArrowLeft);
            let fwd = i.consume_key(Modifiers::NONE, Key::ArrowRight);
            (redo, undo, frame, play, back, fwd)
        });
        if redo {
            self.send(Msg::Redo);
        } else if undo {
            self.send(Msg::Undo);
        }
        if frame {
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

    fn frame_all(&mut self) {
        let r = self.view_rect;
        let aspect = if r.is_positive() {
            f64::from(r.width() / r.height())
        } else {
            16.0 / 9.0
        };
        self.send(Msg::FrameAll { aspect });
    }

    fn top_bar(&mut self, ui: &mut egui::Ui) {
        egui::Panel::top("mwb-top").show(ui, |ui| {
            ui.horizontal(|ui| {
                ui.label(RichText::new("manyworlds").strong());
                ui.separator();
                ui.label(format!("scene {}", self.state.scene_name()));
                ui.separator();
                let n = self.state.worlds().len();
                let s = self.state.survivor_count();
                ui.label(format!("{n} worlds"));
                ui.label(
                    RichText::new(format!("{s} survive"))
                        .color(Color32::from_rgb(120, 195, 255))
                        .strong(),
                );
                if !self.state.problems().is_empty() {
                    ui.separator();
                    ui.colored_label(
                        Color32::from_rgb(240, 170, 60),
                        format!("{} worlds failed", self.state.problems().len()),
                    )
                    .on_hover_text(self.state.problems().join("\n"));
                }
                if let Some(e) = &self.last_error {
                    ui.separator();
                    ui.colored_label(Color32::from_rgb(240, 90, 90), e.clone());
                }
                ui.with_layout(Layout::right_to_left(Align::Center), |ui| {
                    if ui.button("Frame all (F)").clicked() {
                        self.frame_all();
                    }
                    let c = self.state.constraints();
                    let (can_undo, can_redo) = (c.can_undo(), c.can_redo());
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

    fn side_panel(&mut self, ui: &mut egui::Ui) {
        egui::Panel::left("mwb-side")
            .default_size(250.0)
            .show(ui, |ui| {
                ui.add_space(4.0);
                ui.heading("Objects");
                let names: Vec<String> = self.state.body_names().to_vec();
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
                ui.separator();
                ui.heading("Constraints");
                let total = self.state.worlds().len();
                let rows: Vec<_> = self
                    .state
                    .constraints()
                    .constraints()
                    .map(|c| {
                        let sat = self
                            .state
                            .constraints()
                            .satisfied(c.id)
                            .map_or(0, |s| s.len());
                        (c.id, c.polarity, c.objects.clone(), sat)
                    })
                    .collect();
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
                for (id, polarity, objects, sat) in rows {
                    ui.horizontal(|ui| {
                        let (sign, col) = match polarity {
                            Polarity::Positive => ("+", draw::palette::POSITIVE),
                            Polarity::Negative => ("-", draw::palette::NEGATIVE),
                        };
                        ui.label(
                            RichText::new(sign)
                                .strong()
                                .color(Color32::from_rgb(col[0], col[1], col[2])),
                        );
                        let over = if objects.len() == names.len() {
                            "all".to_owned()
                        } else {
                            objects
                                .iter()
                                .filter_map(|&o| names.get(o as usize).cloned())
                                .collect::<Vec<_>>()
                                .join(", ")
                        };
                        ui.label(format!("#{id} {over}: {sat}/{total}"));
                        ui.with_layout(Layout::right_to_left(Align::Center), |ui| {
                            if ui
                                .small_button(format!("x #{id}"))
                                .on_hover_text("remove this constraint")
                                .clicked()
                            {
                                remove = Some(id);
                            }
                        });
                    });
                }
                if let Some(id) = remove {
                    self.send(Msg::RemoveConstraint(id));
                }
                ui.separator();
                ui.heading(format!("Survivors ({})", self.state.survivor_count()));
                let survivors: Vec<u32> =
                    self.state.constraints().result().iter().take(500).collect();
                let selected = self.state.selected();
                let mut pick = None;
                egui::ScrollArea::vertical()
                    .auto_shrink([false, false])
                    .show(ui, |ui| {
                        for w in survivors {
                            let seed = self.state.worlds().get(w as usize).map_or(0, |d| d.seed);
                            if ui
                                .selectable_label(
                                    selected == Some(w),
                                    format!("world {w}  (seed {seed})"),
                                )
                                .clicked()
                            {
                                pick = Some(if selected == Some(w) { None } else { Some(w) });
                            }
                        }
                    });
                if let Some(p) = pick {
                    self.send(Msg::SelectWorld(p));
                }
            });
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
                ui.style_mut().spacing.slider_width = (ui.available_width() - 420.0).max(120.0);
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
                match self.state.shown_world() {
                    Some(w) if self.state.selected() == Some(w.index) => {
                        ui.label(format!("world {} (seed {})", w.index, w.seed));
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
            ui.add_space(2.0);
        });
    }

    fn view(&mut self, ui: &mut egui::Ui) {
        let rect = ui.max_rect();
        self.view_rect = rect;
        if !self.framed && rect.is_positive() {
            self.framed = true;
            self.frame_all();
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
                hovered: self.hovered,
            };
            let painter = ui.painter_at(rect);
            painter.extend(draw::scene_shapes(&self.state, &view, overlay));
            let hint = "drag: keep paths through a box · shift+drag: never through · \
                        right-drag: orbit · middle-drag: pan · wheel: zoom · F: frame all";
            painter.text(
                rect.left_bottom() + egui::vec2(8.0, -8.0),
                egui::Align2::LEFT_BOTTOM,
                hint,
                egui::FontId::proportional(11.0),
                Color32::from_gray(130),
            );
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
        self.send(Msg::AddConstraint {
            viewport: view.viewport,
            rect: ScreenRect {
                x0: a[0],
                y0: a[1],
                x1: b[0],
                y1: b[1],
            },
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
        }
    }
}

/// Opens the viewer in a native window (eframe, glow) and runs until it is closed.
pub fn run_window(app: ViewerApp, title: &str, size: [u32; 2]) -> Result<(), eframe::Error> {
    let options = eframe::NativeOptions {
        viewport: egui::ViewportBuilder::default()
            .with_title(title)
            .with_inner_size([size[0] as f32, size[1] as f32]),
        ..Default::default()
    };
    eframe::run_native(
        "manyworlds viewer",
        options,
        Box::new(move |_cc| Ok(Box::new(app))),
    )
}
