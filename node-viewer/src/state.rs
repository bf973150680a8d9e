//! The viewer's whole state, changed only by [`Msg`]s: no window, no I/O, no clock of its own.
//!
//! Constraints are evaluated here with `mwb_core::browse` (the code every store shard runs):
//! a screen rectangle through the current camera becomes a [`Frustum`] with
//! [`mwb_core::browse::Camera::frustum`], each world's indexed paths are tested with
//! [`Constraint::evaluate`], and a [`ConstraintSet`] keeps the bitsets, their AND and the
//! undo/redo history (§4.4.1–4.4.2 of Twigg and James, SIGGRAPH 2007).

use mwb_core::browse::{
    Constraint, ConstraintId, ConstraintSet, Frustum, Polarity, ScreenRect, TimeWindow, Viewport,
};
use mwb_core::scene::StaticBody;

use crate::ViewerError;
use crate::camera::{OrbitCamera, bounding_sphere};
use crate::math::V3;
use crate::world::WorldData;

/// Playback speeds the timeline allows.
pub const MIN_SPEED: f64 = 0.1;
pub const MAX_SPEED: f64 = 4.0;

/// The playback clock of the selected world.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Playback {
    /// Simulated time shown, seconds.
    pub time: f64,
    pub playing: bool,
    /// Simulated seconds per wall second, in [[`MIN_SPEED`], [`MAX_SPEED`]].
    pub speed: f64,
    pub looping: bool,
}

impl Default for Playback {
    fn default() -> Self {
        Self {
            time: 0.0,
            playing: false,
            speed: 1.0,
            looping: true,
        }
    }
}

/// Everything that changes the state.
#[derive(Debug, Clone, PartialEq)]
pub enum Msg {
    /// Turn the camera about its target, radians.
    Orbit {
        d_yaw: f64,
        d_pitch: f64,
    },
    /// Slide the camera by pixels on a view `height` pixels tall.
    Pan {
        dx: f64,
        dy: f64,
        height: f64,
    },
    /// Dolly: `factor` < 1 comes closer.
    Zoom {
        factor: f64,
    },
    /// Frame every path and body (F), for a view of this aspect ratio.
    FrameAll {
        aspect: f64,
    },
    SetCamera(OrbitCamera),
    /// A rectangle drawn on a view of `viewport` pixels through the current camera.
    AddConstraint {
        viewport: Viewport,
        rect: ScreenRect,
        polarity: Polarity,
    },
    RemoveConstraint(ConstraintId),
    Undo,
    Redo,
    /// Show / hide an object's paths and include / exclude it from new constraints.
    ToggleObject(u32),
    /// Limit new constraints to a time window (`None`: any time).
    SetWindow(Option<TimeWindow>),
    SelectWorld(Option<u32>),
    Play,
    Pause,
    TogglePlay,
    /// Jump to a simulated time (clamped to the selected world's motion).
    Seek(f64),
    /// One frame step forward (+1) or back (−1) of the selected world.
    Step(i32),
    /// Wall-clock seconds passed (the window's frame time): advances playback when playing.
    Tick(f64),
    SetSpeed(f64),
    SetLoop(bool),
}

/// The viewer state: scene, worlds, camera, constraints, selection, playback.
#[derive(Debug, Clone)]
pub struct ViewerState {
    scene_name: String,
    body_names: Vec<String>,
    statics: Vec<StaticBody>,
    worlds: Vec<WorldData>,
    /// Worlds that could not be used, with why (shown, never fatal).
    problems: Vec<String>,
    pub camera: OrbitCamera,
    constraints: ConstraintSet,
    next_constraint: u64,
    /// Per object: its paths are drawn and new constraints are over it.
    chosen: Vec<bool>,
    window: Option<TimeWindow>,
    selected: Option<u32>,
    playback: Playback,
}

fn evaluate(worlds: &[WorldData], c: &Constraint, w: u32) -> bool {
    let Some(world) = worlds.get(w as usize) else {
        // Unknown worlds touch nothing.
        return c.satisfied_given(false);
    };
    c.evaluate(|object| {
        world
            .paths
            .get(object as usize)
            .map(|p| (&p.tree, p.radius))
    })
}

impl ViewerState {
    /// A state for a scene with `body_names` (scene order) and its static geometry.
    pub fn new(
        scene_name: impl Into<String>,
        body_names: Vec<String>,
        statics: Vec<StaticBody>,
    ) -> Self {
        let chosen = vec![true; body_names.len()];
        Self {
            scene_name: scene_name.into(),
            body_names,
            statics,
            worlds: Vec::new(),
            problems: Vec::new(),
            camera: OrbitCamera::default(),
            constraints: ConstraintSet::new(),
            next_constraint: 1,
            chosen,
            window: None,
            selected: None,
            playback: Playback::default(),
        }
    }

    /// Adds a world; its index must be the next one (worlds are numbered densely from 0). It is
    /// evaluated against every live constraint (§4.4: worlds arriving later are filtered too).
    pub fn add_world(&mut self, world: WorldData) -> Result<(), ViewerError> {
        let expected = self.worlds.len() as u32;
        if world.index != expected {
            return Err(ViewerError::WorldIndex {
                expected,
                found: world.index,
            });
        }
        if world.scene.bodies.len() != self.body_names.len() {
            return Err(ViewerError::BodyCount {
                scene: self.body_names.len(),
                motion: world.scene.bodies.len(),
            });
        }
        self.worlds.push(world);
        let worlds = &self.worlds;
        self.constraints
            .on_new_world(expected, |c, w| evaluate(worlds, c, w));
        Ok(())
    }

    /// Records a world that could not be used (shown in the status bar).
    pub fn add_problem(&mut self, what: String) {
        self.problems.push(what);
    }

    pub fn scene_name(&self) -> &str {
        &self.scene_name
    }

    pub fn body_names(&self) -> &[String] {
        &self.body_names
    }

    pub fn statics(&self) -> &[StaticBody] {
        &self.statics
    }

    pub fn worlds(&self) -> &[WorldData] {
        &self.worlds
    }

    pub fn problems(&self) -> &[String] {
        &self.problems
    }

    pub fn constraints(&self) -> &ConstraintSet {
        &self.constraints
    }

    /// Whether world `w` satisfies every live constraint.
    pub fn survives(&self, w: u32) -> bool {
        self.constraints.result().contains(w)
    }

    pub fn survivor_count(&self) -> usize {
        self.constraints.result().len()
    }

    pub fn is_chosen(&self, object: u32) -> bool {
        self.chosen.get(object as usize).copied().unwrap_or(false)
    }

    /// The objects new constraints are over, ascending.
    pub fn chosen_objects(&self) -> Vec<u32> {
        (0..self.chosen.len() as u32)
            .filter(|&o| self.is_chosen(o))
            .collect()
    }

    pub fn window(&self) -> Option<TimeWindow> {
        self.window
    }

    pub fn selected(&self) -> Option<u32> {
        self.selected
    }

    pub fn playback(&self) -> Playback {
        self.playback
    }

    /// The world whose bodies are drawn: the selected one, else the first survivor, else none.
    pub fn shown_world(&self) -> Option<&WorldData> {
        self.selected
            .or_else(|| self.constraints.result().iter().next())
            .and_then(|w| self.worlds.get(w as usize))
    }

    /// Length of the timeline: the shown world's motion, or the longest world's.
    pub fn duration(&self) -> f64 {
        match self.shown_world() {
            Some(w) => w.duration(),
            None => self
                .worlds
                .iter()
                .map(WorldData::duration)
                .fold(0.0, f64::max),
        }
    }

    /// A sphere around every path of the chosen objects, the bodies' start poses and the
    /// bounded statics.
    pub fn bounds(&self) -> Option<(V3, f64)> {
        let chosen: Vec<usize> = (0..self.chosen.len()).filter(|&o| self.chosen[o]).collect();
        let paths = self.worlds.iter().flat_map(|w| {
            chosen
                .iter()
                .filter_map(move |&o| w.paths.get(o))
                .flat_map(|p| p.tree.path().points().iter().copied())
        });
        let statics = self.statics.iter().filter_map(|s| match &s.shape {
            mwb_core::scene::Shape::Plane { .. } => None,
            _ => Some(s.position),
        });
        bounding_sphere(paths.chain(statics))
    }

    /// Applies one message. Errors (a degenerate rectangle, an unknown constraint) leave the
    /// state as it was.
    pub fn update(&mut self, msg: Msg) -> Result<(), ViewerError> {
        match msg {
            Msg::Orbit { d_yaw, d_pitch } => self.camera.orbit(d_yaw, d_pitch),
            Msg::Pan { dx, dy, height } => self.camera.pan(dx, dy, height),
            Msg::Zoom { factor } => self.camera.zoom(factor),
            Msg::FrameAll { aspect } => {
                if let Some((c, r)) = self.bounds() {
                    self.camera.frame(c, r, aspect);
                }
            }
            Msg::SetCamera(c) => self.camera = c,
            Msg::AddConstraint {
                viewport,
                rect,
                polarity,
            } => {
                let frustum = self.camera.browse_camera(viewport).frustum(&rect)?;
                self.add_frustum(frustum, polarity)?;
            }
            Msg::RemoveConstraint(id) => self.constraints.remove(id)?,
            Msg::Undo => {
                let worlds = &self.worlds;
                self.constraints.undo(|c, w| evaluate(worlds, c, w));
            }
            Msg::Redo => {
                let worlds = &self.worlds;
                self.constraints.redo(|c, w| evaluate(worlds, c, w));
            }
            Msg::ToggleObject(o) => {
                if let Some(c) = self.chosen.get_mut(o as usize) {
                    *c = !*c;
                }
            }
            Msg::SetWindow(w) => self.window = w,
            Msg::SelectWorld(w) => {
                self.selected = w.filter(|&w| (w as usize) < self.worlds.len());
                self.playback.time = self.playback.time.clamp(0.0, self.duration());
            }
            Msg::Play => {
                if self.playback.time >= self.duration() {
                    self.playback.time = 0.0;
                }
                self.playback.playing = true;
            }
            Msg::Pause => self.playback.playing = false,
            Msg::TogglePlay => {
                let m = if self.playback.playing {
                    Msg::Pause
                } else {
                    Msg::Play
                };
                return self.update(m);
            }
            Msg::Seek(t) => {
                if t.is_finite() {
                    self.playback.time = t.clamp(0.0, self.duration());
                }
            }
            Msg::Step(n) => {
                let dt = self.shown_world().map_or(1.0 / 60.0, |w| w.frame_dt);
                let frame = (self.playback.time / dt).round() + f64::from(n);
                self.playback.playing = false;
                self.playback.time = (frame * dt).clamp(0.0, self.duration());
            }
            Msg::Tick(dt) => {
                if self.playback.playing && dt.is_finite() && dt > 0.0 {
                    let end = self.duration();
                    let t = self.playback.time + dt * self.playback.speed;
                    if t <= end {
                        self.playback.time = t;
                    } else if self.playback.looping && end > 0.0 {
                        self.playback.time = t.rem_euclid(end);
                    } else {
                        self.playback.time = end;
                        self.playback.playing = false;
                    }
                }
            }
            Msg::SetSpeed(s) => {
                if s.is_finite() {
                    self.playback.speed = s.clamp(MIN_SPEED, MAX_SPEED);
                }
            }
            Msg::SetLoop(l) => self.playback.looping = l,
        }
        Ok(())
    }

    /// Adds a constraint over the chosen objects (and the time window, if any) and returns its
    /// id.
    pub fn add_frustum(
        &mut self,
        frustum: Frustum,
        polarity: Polarity,
    ) -> Result<ConstraintId, ViewerError> {
        let id = ConstraintId(self.next_constraint);
        let constraint = Constraint {
            id,
            polarity,
            frustum,
            objects: self.chosen_objects(),
            quantifier: Default::default(),
            window: self.window,
            scope: Default::default(),
        };
        let worlds = &self.worlds;
        self.constraints
            .add(constraint, |c, w| evaluate(worlds, c, w))?;
        self.next_constraint += 1;
        Ok(id)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mwb_codec::Track;
    use mwb_core::scene::SceneTemplate;

    /// A one-body scene and worlds whose body flies along x at height `y[i]`.
    fn state(heights: &[f64]) -> ViewerState {
        let template = SceneTemplate::parse(
            "name = \"t\"\n[[material]]\nname = \"m\"\n[[body]]\nname = \"ball\"\nshape = \"sphere\"\nradius = 0.1\nmaterial = \"m\"\nposition = [0, 1, 0]\n",
            "t.toml",
        )
        .expect("scene parses");
        let scene = template.instantiate(0);
        let names = scene.bodies.iter().map(|b| b.name.clone()).collect();
        let mut s = ViewerState::new("t", names, scene.statics.clone());
        for (i, &y) in heights.iter().enumerate() {
            let positions: Vec<V3> = (0..61).map(|f| [-3.0 + 0.1 * f as f64, y, 0.0]).collect();
            let track = Track {
                rotations: vec![[0.0, 0.0, 0.0, 1.0]; positions.len()],
                positions,
            };
            let w = WorldData::new(
                i as u32,
                i as u64,
                scene.clone(),
                1.0 / 60.0,
                vec![track],
                0.0,
            )
            .expect("indexes");
            s.add_world(w).expect("adds");
        }
        s
    }

    /// A camera at z = 10 looking at the origin, 640 × 480.
    fn front(s: &mut ViewerState) -> Viewport {
        s.update(Msg::SetCamera(OrbitCamera {
            target: [0.0, 0.0, 0.0],
            yaw: 0.0,
            pitch: 0.0,
            distance: 10.0,
            ..OrbitCamera::default()
        }))
        .expect("camera");
        Viewport {
            width: 640,
            height: 480,
        }
    }

    #[test]
    fn a_box_keeps_the_worlds_that_pass_through_it_and_undo_redo_remove_work() {
        let mut s = state(&[0.0, 2.0, 0.05]);
        let viewport = front(&mut s);
        // A box around the screen centre: heights 0 and 0.05 pass through, 2 does not.
        let rect = ScreenRect {
            x0: 300.0,
            y0: 220.0,
            x1: 340.0,
            y1: 260.0,
        };
        s.update(Msg::AddConstraint {
            viewport,
            rect,
            polarity: Polarity::Positive,
        })
        .expect("adds");
        assert_eq!(
            s.constraints().result().iter().collect::<Vec<_>>(),
            vec![0, 2]
        );
        let c = s.constraints().constraints().next().expect("one").clone();
        assert_eq!(
            c.frustum,
            s.camera
                .browse_camera(viewport)
                .frustum(&rect)
                .expect("frustum")
        );
        assert_eq!(c.objects, vec![0]);
        // A negative box over the same place keeps none of them.
        s.update(Msg::AddConstraint {
            viewport,
            rect,
            polarity: Polarity::Negative,
        })
        .expect("adds");
        assert_eq!(s.survivor_count(), 0);
        s.update(Msg::Undo).expect("undo");
        assert_eq!(s.survivor_count(), 2);
        s.update(Msg::Redo).expect("redo");
        assert_eq!(s.survivor_count(), 0);
        s.update(Msg::RemoveConstraint(ConstraintId(1)))
            .expect("removes");
        // Only the negative one is left: world 1 (y = 2) never enters the box.
        assert_eq!(s.constraints().result().iter().collect::<Vec<_>>(), vec![1]);
        assert!(s.update(Msg::RemoveConstraint(ConstraintId(9))).is_err());
        // A degenerate rectangle is refused and changes nothing.
        let before = s.survivor_count();
        let flat = ScreenRect { y1: 220.0, ..rect };
        assert!(
            s.update(Msg::AddConstraint {
                viewport,
                rect: flat,
                polarity: Polarity::Positive
            })
            .is_err()
        );
        assert_eq!(s.survivor_count(), before);
        assert_eq!(s.constraints().constraints().len(), 1);
    }

    #[test]
    fn worlds_arriving_later_are_filtered_and_unchosen_objects_are_left_out() {
        let mut s = state(&[0.0]);
        let viewport = front(&mut s);
        s.update(Msg::ToggleObject(0)).expect("toggle");
        assert!(s.chosen_objects().is_empty());
        s.update(Msg::ToggleObject(0)).expect("toggle");
        let rect = ScreenRect {
            x0: 300.0,
            y0: 220.0,
            x1: 340.0,
            y1: 260.0,
        };
        s.update(Msg::AddConstraint {
            viewport,
            rect,
            polarity: Polarity::Positive,
        })
        .expect("adds");
        assert_eq!(s.survivor_count(), 1);
        let more = state(&[0.0, 3.0]);
        let w1 = more.worlds()[1].clone();
        s.add_world(w1.clone()).expect("adds");
        assert!(!s.survives(1));
        assert!(s.add_world(w1).is_err(), "index 1 is taken");
    }

    #[test]
    fn playback_clock() {
        let mut s = state(&[0.0, 1.0]);
        assert_eq!(s.duration(), 1.0);
        s.update(Msg::SelectWorld(Some(1))).expect("select");
        assert_eq!(s.shown_world().map(|w| w.index), Some(1));
        s.update(Msg::Tick(0.5)).expect("tick");
        assert_eq!(s.playback().time, 0.0, "paused clocks do not move");
        s.update(Msg::Play).expect("play");
        s.update(Msg::SetSpeed(2.0)).expect("speed");
        s.update(Msg::Tick(0.25)).expect("tick");
        assert_eq!(s.playback().time, 0.5);
        s.update(Msg::Tick(0.5)).expect("tick");
        assert!((s.playback().time - 0.5).abs() < 1e-12, "loops");
        s.update(Msg::SetLoop(false)).expect("loop");
        s.update(Msg::Tick(1.0)).expect("tick");
        assert_eq!(s.playback().time, 1.0);
        assert!(!s.playback().playing, "stops at the end");
        s.update(Msg::Seek(0.5)).expect("seek");
        s.update(Msg::Step(1)).expect("step");
        assert!((s.playback().time - 0.5 - 1.0 / 60.0).abs() < 1e-12);
        s.update(Msg::SetSpeed(100.0)).expect("speed");
        assert_eq!(s.playback().speed, MAX_SPEED);
        s.update(Msg::Seek(-4.0)).expect("seek");
        assert_eq!(s.playback().time, 0.0);
        let (p, _) = s
            .shown_world()
            .and_then(|w| w.pose_at(0, 0.5))
            .expect("pose");
        assert!((p[0] - 0.0).abs() < 1e-9 && (p[1] - 1.0).abs() < 1e-9);
    }
}
