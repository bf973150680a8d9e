//! Scene edits (Twigg and James, SIGGRAPH 2007, §4.5, Figures 4.11–4.12): the worlds kept so far
//! get children with an edit of the scene applied, re-simulating only the bodies the edit
//! reaches.
//!
//! An edit is a refinement ([`crate::refine`]) that branches at frame 0 with a changed set of
//! bodies. [`diff`] matches the new scene's bodies to the old one's by name:
//!
//! * a **same** body (every field equal: shape, material values, initial pose and velocities)
//!   starts *inactive*: kinematic on the parent's exact poses, its impacts and rest read from
//!   the parent, exactly as refinement's inactive bodies;
//! * an **added** body starts *active* at frame 0 with the new scene's initial state;
//! * a **removed** body leaves only its *ghost*, replaying the parent motion;
//! * a **modified** body is both: active with its new initial state, and ghosted on its old
//!   motion (with its old shape).
//!
//! Active bodies are perturbed (§4.1.2) from the child's seed, inactive ones never.
//! Before every step an inactive body that a diverged active body or a ghost is about to touch
//! becomes dynamic with the parent's exact state at that frame (Figure 4.11a: it must respond
//! to the new motion; 4.11b: the parent's version of a body touched it, and that body is now
//! gone or different), by refinement's conservative distance test; joint groups change sets
//! together. Added and modified bodies count as diverged from the start: they are not their
//! parent version, so what that version did to its neighbours says nothing of what they will
//! do (a reshaped body touches what its old ghost never reaches while it still moves exactly as
//! the old one did). A same body that became active is a source once it leaves its parent
//! motion, as in refinement.
//!
//! **Why a fresh world.** The child is [`SimWorld::build`] of the *new* scene, not a fork of
//! the parent's simulator: a fork has the old bodies. At frame 0 nothing is lost by it: a world
//! just built holds no contacts, no warm-start impulses and no islands yet, so a fresh build of
//! the old scene *is* the parent at frame 0, and the new scene's build is that state with the
//! edit applied. Ghosts are looked up in the parent's simulator (the old shapes).
//!
//! **What is refused.** Only edits of bodies are local. A changed static touches every body
//! that rests on it, a changed setting (time step, gravity, thresholds, perturbation law) every
//! body's motion, and a changed joint the bodies it holds in ways the distance test does not
//! see: each is an [`EditError`] naming the static, setting or joint (a new job is the honest
//! way to get them). Joints must therefore be identical, matched by name with their ends by
//! body name; a joint to an added or removed body is a changed joint.
//!
//! **What is recorded.** The whole world in the new scene's body order, every body and segment
//! from frame 0, as a sampled world of the new scene is recorded: the simulation re-simulates
//! only what it must, the storage is a plain world of the new scene. Deterministic: the same
//! parent lineage, new scene and seed give the same segments byte for byte.

use crate::refine::{Capture, ChildStart, ExactMotion, Lineage, Parent, joint_groups};
use crate::world::{
    Progress, Recorder, RunError, RunOptions, Segment, SimWorld, WorldSummary, summary_of,
};
use mwb_core::scene::{Body, BodyRef, Joint, Material, Scene, Settings, Shape, StaticBody};
use rapier3d::prelude::RigidBodyType;
use std::collections::HashMap;
use std::fmt;
use std::ops::ControlFlow;

/// What became of one body of the new scene.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BodyEdit {
    /// Unchanged: the old scene's body at this index.
    Same(usize),
    /// The old scene's body at this index, with some field changed ([`body_changes`]).
    Modified(usize),
    /// Not in the old scene.
    Added,
}

/// How a new scene differs from an old one in its bodies (the only local edits).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SceneDiff {
    /// Per body of the new scene, in its order.
    pub bodies: Vec<BodyEdit>,
    /// Bodies of the old scene the new one does not have (old indices, ascending).
    pub removed: Vec<usize>,
}

impl SceneDiff {
    /// Per body of the new scene, its body in the old scene (`None`: added).
    pub fn old_index(&self) -> Vec<Option<usize>> {
        self.bodies
            .iter()
            .map(|e| match *e {
                BodyEdit::Same(j) | BodyEdit::Modified(j) => Some(j),
                BodyEdit::Added => None,
            })
            .collect()
    }

    /// Whether nothing changed.
    pub fn is_empty(&self) -> bool {
        self.removed.is_empty() && self.bodies.iter().all(|e| matches!(e, BodyEdit::Same(_)))
    }
}

/// How a static or joint changed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Change {
    Added,
    Removed,
    /// These fields differ.
    Changed(Vec<&'static str>),
}

impl fmt::Display for Change {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Change::Added => f.write_str("added"),
            Change::Removed => f.write_str("removed"),
            Change::Changed(fields) => write!(f, "changed ({})", fields.join(", ")),
        }
    }
}

/// Which of the two scenes of an edit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    Old,
    New,
}

impl fmt::Display for Side {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Side::Old => "old",
            Side::New => "new",
        })
    }
}

/// Edits that cannot be applied to kept worlds, each naming what is wrong.
#[derive(Debug, thiserror::Error)]
pub enum EditError {
    #[error("scene: nothing changed (every body, static, joint and setting is as it was)")]
    NothingChanged,
    #[error("settings: `{field}` changed: an edit of the settings needs a new job")]
    Settings { field: &'static str },
    #[error("statics: `{name}` {change}: an edit of static geometry needs a new job")]
    Static { name: String, change: Change },
    #[error("joints: `{name}` {change}: an edit of a joint needs a new job")]
    Joint { name: String, change: Change },
    #[error("bodies: `{name}` names two bodies of the {side} scene")]
    DuplicateBody { name: String, side: Side },
    #[error("diff: not the diff of the parent's scene and the new scene")]
    StaleDiff,
    #[error(transparent)]
    Run(#[from] RunError),
}

/// Matches `new`'s bodies to `old`'s by name (see the module docs). Refuses, naming the field,
/// an edit of settings, statics or joints, duplicate body names, and an edit that changes
/// nothing.
pub fn diff(old: &Scene, new: &Scene) -> Result<SceneDiff, EditError> {
    if let Some(field) = settings_changes(&old.settings, &new.settings).first() {
        return Err(EditError::Settings { field });
    }
    let statics = first_change(
        &old.statics,
        &new.statics,
        |s| s.name.as_str(),
        |a, b| static_changes(old, a, new, b),
    );
    if let Some((name, change)) = statics {
        return Err(EditError::Static { name, change });
    }
    // Joints must be the same in both scenes, their ends matched by body name.
    let joints = first_change(
        &old.joints,
        &new.joints,
        |j| j.name.as_str(),
        |a, b| joint_changes(old, a, new, b),
    );
    if let Some((name, change)) = joints {
        return Err(EditError::Joint { name, change });
    }
    let old_bodies = unique_bodies(old, Side::Old)?;
    let new_bodies = unique_bodies(new, Side::New)?;
    let bodies = new
        .bodies
        .iter()
        .map(|b| match old_bodies.get(b.name.as_str()) {
            None => BodyEdit::Added,
            Some(&j) if body_changes(old, &old.bodies[j], new, b).is_empty() => BodyEdit::Same(j),
            Some(&j) => BodyEdit::Modified(j),
        })
        .collect();
    let removed = (0..old.bodies.len())
        .filter(|&j| !new_bodies.contains_key(old.bodies[j].name.as_str()))
        .collect();
    let d = SceneDiff { bodies, removed };
    if d.is_empty() {
        return Err(EditError::NothingChanged);
    }
    Ok(d)
}

/// The first of `new`'s items (statics or joints) that differs from `old`'s item of its name,
/// else the first of `old`'s that `new` lacks; with how it changed.
fn first_change<T>(
    old: &[T],
    new: &[T],
    name: impl Fn(&T) -> &str,
    changes: impl Fn(&T, &T) -> Vec<&'static str>,
) -> Option<(String, Change)> {
    let old_index = by_name(old.iter().map(&name));
    for item in new {
        let change = match old_index.get(name(item)) {
            None => Change::Added,
            Some(&i) => {
                let fields = changes(&old[i], item);
                if fields.is_empty() {
                    continue;
                }
                Change::Changed(fields)
            }
        };
        return Some((name(item).to_owned(), change));
    }
    let new_index = by_name(new.iter().map(&name));
    old.iter()
        .find(|item| !new_index.contains_key(name(item)))
        .map(|item| (name(item).to_owned(), Change::Removed))
}

/// Index of each name (the first, for a repeated one).
fn by_name<'s>(names: impl Iterator<Item = &'s str>) -> HashMap<&'s str, usize> {
    let mut out = HashMap::new();
    for (i, name) in names.enumerate() {
        out.entry(name).or_insert(i);
    }
    out
}

fn unique_bodies(scene: &Scene, side: Side) -> Result<HashMap<&str, usize>, EditError> {
    let index = by_name(scene.bodies.iter().map(|b| b.name.as_str()));
    if index.len() == scene.bodies.len() {
        return Ok(index);
    }
    let repeated = scene
        .bodies
        .iter()
        .enumerate()
        .find(|(i, b)| index.get(b.name.as_str()) != Some(i))
        .map(|(_, b)| b.name.clone())
        .unwrap_or_default();
    Err(EditError::DuplicateBody {
        name: repeated,
        side,
    })
}

/// The names of the fields that are not the same, from `(name, same)` pairs.
fn differing<const N: usize>(fields: [(&'static str, bool); N]) -> Vec<&'static str> {
    fields
        .into_iter()
        .filter_map(|(field, same)| (!same).then_some(field))
        .collect()
}

/// The settings fields that differ, by their names in the scene format.
fn settings_changes(a: &Settings, b: &Settings) -> Vec<&'static str> {
    differing([
        ("dt", a.dt == b.dt),
        ("end_time", a.end_time == b.end_time),
        ("gravity", a.gravity == b.gravity),
        ("rest_linear", a.rest_linear == b.rest_linear),
        ("rest_angular", a.rest_angular == b.rest_angular),
        ("rest_hold", a.rest_hold == b.rest_hold),
        (
            "solver_iterations",
            a.solver_iterations == b.solver_iterations,
        ),
        ("alpha", a.alpha == b.alpha),
        ("cos_exponent", a.cos_exponent == b.cos_exponent),
        ("c_v", a.c_v == b.c_v),
        ("c_omega", a.c_omega == b.c_omega),
        ("segment_seconds", a.segment_seconds == b.segment_seconds),
        ("linear_damping", a.linear_damping == b.linear_damping),
        ("angular_damping", a.angular_damping == b.angular_damping),
        ("sim", a.sim == b.sim),
        ("pgs_iterations", a.pgs_iterations == b.pgs_iterations),
        (
            "stabilization_iterations",
            a.stabilization_iterations == b.stabilization_iterations,
        ),
        ("ccd", a.ccd == b.ccd),
        (
            "prediction_distance",
            a.prediction_distance == b.prediction_distance,
        ),
        ("sleep", a.sleep == b.sleep),
        ("length_unit", a.length_unit == b.length_unit),
        ("max_speed", a.max_speed == b.max_speed),
        ("tolerance", a.tolerance == b.tolerance),
    ])
}

/// Whether two materials act the same (their names do not matter). A missing one never does.
fn same_material(a: Option<&Material>, b: Option<&Material>) -> bool {
    match (a, b) {
        (Some(a), Some(b)) => {
            a.friction == b.friction && a.restitution == b.restitution && a.density == b.density
        }
        _ => false,
    }
}

/// Which of a shape's geometry (`"shape"`) and material values (`"material"`) differ, walking
/// the simple shapes it is made of with their materials (a compound part by part).
fn shape_changes(
    old: &Scene,
    (old_shape, old_material): (&Shape, usize),
    new: &Scene,
    (new_shape, new_material): (&Shape, usize),
) -> Vec<&'static str> {
    let (a, b) = (
        old_shape.placed_parts(old_material),
        new_shape.placed_parts(new_material),
    );
    let geometry = a.len() == b.len()
        && a.iter().zip(&b).all(|(x, y)| {
            x.shape == y.shape && x.position == y.position && x.rotation == y.rotation
        });
    if !geometry {
        return vec!["shape"];
    }
    let materials = a
        .iter()
        .zip(&b)
        .all(|(x, y)| same_material(old.materials.get(x.material), new.materials.get(y.material)));
    if materials {
        Vec::new()
    } else {
        vec!["material"]
    }
}

/// The fields of a body that differ between the old scene's `a` and the new scene's `b`:
/// `shape`, `material` (its values), `position`, `rotation`, `linvel`, `angvel`. Empty for the
/// same body.
pub fn body_changes(old: &Scene, a: &Body, new: &Scene, b: &Body) -> Vec<&'static str> {
    let mut out = shape_changes(old, (&a.shape, a.material), new, (&b.shape, b.material));
    out.extend(differing([
        ("position", a.position == b.position),
        ("rotation", a.rotation == b.rotation),
        ("linvel", a.linvel == b.linvel),
        ("angvel", a.angvel == b.angvel),
    ]));
    out
}

/// The fields of a static that differ: `shape`, `material` (its values), `position`,
/// `rotation`.
fn static_changes(old: &Scene, a: &StaticBody, new: &Scene, b: &StaticBody) -> Vec<&'static str> {
    let mut out = shape_changes(old, (&a.shape, a.material), new, (&b.shape, b.material));
    out.extend(differing([
        ("position", a.position == b.position),
        ("rotation", a.rotation == b.rotation),
    ]));
    out
}

/// A joint's end by body name (`None`: the world).
fn end(scene: &Scene, r: BodyRef) -> Option<Option<&str>> {
    match r {
        BodyRef::World => Some(None),
        BodyRef::Body(i) => scene.bodies.get(i).map(|b| Some(b.name.as_str())),
    }
}

/// The fields of a joint that differ: `kind`, `body1`, `body2` (by body name), `anchor1`,
/// `anchor2`.
fn joint_changes(old: &Scene, a: &Joint, new: &Scene, b: &Joint) -> Vec<&'static str> {
    differing([
        ("kind", a.kind == b.kind),
        ("body1", end(old, a.body1) == end(new, b.body1)),
        ("body2", end(old, a.body2) == end(new, b.body2)),
        ("anchor1", a.anchor1 == b.anchor1),
        ("anchor2", a.anchor2 == b.anchor2),
    ])
}

/// A child world of an edited scene.
#[derive(Debug, Clone, PartialEq)]
pub struct EditedWorld {
    /// The world the edit was applied to.
    pub parent: Lineage,
    /// Over the whole world (every body, every frame), in the new scene's body order.
    pub summary: WorldSummary,
    /// Per body of the new scene, the frame from which its motion is new (`None`: the parent's
    /// throughout). Added and modified bodies: frame 0.
    pub active_from: Vec<Option<u32>>,
    /// Same bodies that became active (the edit reached them), ascending.
    pub reached: Vec<usize>,
}

impl EditedWorld {
    /// Bodies re-simulated ÷ bodies.
    pub fn active_fraction(&self) -> f64 {
        let n = self.active_from.len().max(1);
        self.active_from.iter().filter(|a| a.is_some()).count() as f64 / n as f64
    }
}

/// The child of `parent` (regenerated exactly, forked anywhere: its whole motion is used) with
/// `new_scene` in place of its scene, `diff` being [`diff`] of the two; perturbation seed
/// `seed`. Emits the whole world's segments (see the module docs). Deterministic in (parent
/// lineage, new scene, seed).
pub fn edit_child(
    parent: &Parent,
    new_scene: &Scene,
    diff: &SceneDiff,
    seed: u64,
    opts: RunOptions,
    emit: &mut dyn FnMut(Segment) -> ControlFlow<()>,
) -> Result<EditedWorld, EditError> {
    step_edit(parent, new_scene, diff, seed, opts, None, emit)
}

/// [`edit_child`], also returning the child's exact motion (every body of the new scene, every
/// frame): for tests and benchmarks.
pub fn edit_child_traced(
    parent: &Parent,
    new_scene: &Scene,
    diff: &SceneDiff,
    seed: u64,
    opts: RunOptions,
    emit: &mut dyn FnMut(Segment) -> ControlFlow<()>,
) -> Result<(EditedWorld, ExactMotion), EditError> {
    let mut capture = Capture::new(Vec::new(), None);
    let world = step_edit(
        parent,
        new_scene,
        diff,
        seed,
        opts,
        Some(&mut capture),
        emit,
    )?;
    Ok((world, capture.into_motion(new_scene.bodies.len())))
}

fn step_edit(
    parent: &Parent,
    new_scene: &Scene,
    edit: &SceneDiff,
    seed: u64,
    opts: RunOptions,
    capture: Option<&mut Capture<'_>>,
    emit: &mut dyn FnMut(Segment) -> ControlFlow<()>,
) -> Result<EditedWorld, EditError> {
    // The diff decides who replays which parent body: one made for other scenes would replay
    // the wrong motion (or none), so it is checked, not trusted.
    if &diff(parent.scene(), new_scene)? != edit {
        return Err(EditError::StaleDiff);
    }
    let n = new_scene.bodies.len();
    let mut p = Progress::new(SimWorld::build(new_scene).map_err(RunError::from)?);
    let groups = joint_groups(new_scene);
    // Added and modified bodies are not their parent version: active and diverged from frame 0,
    // with the bodies jointed to them.
    let fresh: Vec<bool> = edit
        .bodies
        .iter()
        .map(|e| !matches!(e, BodyEdit::Same(_)))
        .collect();
    let mut active = vec![false; n];
    for i in (0..n).filter(|&i| fresh[i]) {
        for &b in &groups[i] {
            active[b] = true;
        }
    }
    // The others kinematic on the parent's poses (frame 0 is the scene's initial state, the
    // same in both scenes for a same body).
    for (i, &h) in p.sim.bodies.iter().enumerate() {
        if !active[i] {
            p.sim.world.bodies[h].set_body_type(RigidBodyType::KinematicPositionBased, false);
        }
    }
    let mut observe = |_: &[mwb_codec::Track]| {};
    let mut rec = Recorder::new(new_scene, &p.sim, opts, emit, &mut observe);
    if opts.record {
        rec.push((0..n).map(|i| p.sim.pose(i)))?;
    }
    let start = ChildStart {
        scene: new_scene,
        parent_of: edit.old_index(),
        active,
        diverged: fresh.clone(),
        ghosts: edit.removed.clone(),
        groups,
        seed,
    };
    let active_from = parent.step_child(start, &mut p, opts, &mut rec, capture)?;
    let summary = summary_of(&p, &rec, seed, new_scene.settings.dt);
    let reached = (0..n)
        .filter(|&i| !fresh[i] && active_from[i].is_some())
        .collect();
    Ok(EditedWorld {
        parent: parent.lineage().clone(),
        summary,
        active_from,
        reached,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use mwb_core::scene::{SceneTemplate, builtin};

    fn tumble() -> Scene {
        SceneTemplate::parse(builtin::TUMBLE, "tumble.toml")
            .unwrap_or_else(|e| panic!("{e}"))
            .instantiate(1)
    }

    fn err(r: Result<SceneDiff, EditError>) -> String {
        match r {
            Ok(d) => panic!("accepted: {d:?}"),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn bodies_are_matched_by_name() {
        let old = tumble();
        let mut new = old.clone();
        // Drop `plank` (1), move `brick` (2 → 1), add a ball at the end.
        new.bodies.remove(1);
        new.bodies[1].position[0] += 0.5;
        let mut ball = new.bodies[0].clone();
        ball.name = "ball".into();
        ball.shape = Shape::Sphere { radius: 0.1 };
        new.bodies.push(ball);
        let d = diff(&old, &new).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            d.bodies,
            vec![
                BodyEdit::Same(0),
                BodyEdit::Modified(2),
                BodyEdit::Same(3),
                BodyEdit::Same(4),
                BodyEdit::Added,
            ]
        );
        assert_eq!(d.removed, vec![1]);
        assert_eq!(
            d.old_index(),
            vec![Some(0), Some(2), Some(3), Some(4), None]
        );
        assert_eq!(
            body_changes(&old, &old.bodies[2], &new, &new.bodies[1]),
            vec!["position"]
        );
    }

    #[test]
    fn materials_compare_by_value_not_index_or_name() {
        let old = tumble();
        let mut new = old.clone();
        // The same values under another name and index: nothing changed for `crate`…
        let mut copy = new.materials[1].clone();
        copy.name = "oak".into();
        new.materials.push(copy);
        new.bodies[0].material = 2;
        // …but `die` gets a denser wood.
        let mut dense = new.materials[1].clone();
        dense.density *= 2.0;
        new.materials.push(dense);
        new.bodies[3].material = 3;
        let d = diff(&old, &new).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(d.bodies[0], BodyEdit::Same(0));
        assert_eq!(d.bodies[3], BodyEdit::Modified(3));
        assert_eq!(
            body_changes(&old, &old.bodies[3], &new, &new.bodies[3]),
            vec!["material"]
        );
        let mut grown = old.clone();
        grown.bodies[4].shape = Shape::Box {
            half_extents: [0.4, 0.1, 0.3],
        };
        grown.bodies[4].angvel = [0.0; 3];
        assert_eq!(
            body_changes(&old, &old.bodies[4], &grown, &grown.bodies[4]),
            vec!["shape", "angvel"]
        );
    }

    #[test]
    fn edits_that_are_not_local_are_refused_naming_the_field() {
        let old = tumble();
        let msg = err(diff(&old, &old));
        assert!(msg.starts_with("scene: nothing changed"), "{msg}");

        let mut new = old.clone();
        new.settings.dt = 1.0 / 240.0;
        let msg = err(diff(&old, &new));
        assert!(msg.starts_with("settings: `dt` changed"), "{msg}");

        let mut new = old.clone();
        new.statics[0].position[1] = 0.1;
        let msg = err(diff(&old, &new));
        assert_eq!(
            msg,
            "statics: `ground` changed (position): an edit of static geometry needs a new job"
        );
        let mut new = old.clone();
        new.materials[0].friction = 0.1;
        let msg = err(diff(&old, &new));
        assert!(
            msg.starts_with("statics: `ground` changed (material)"),
            "{msg}"
        );
        let mut new = old.clone();
        new.statics[0].name = "floor".into();
        let msg = err(diff(&old, &new));
        assert!(msg.starts_with("statics: `floor` added"), "{msg}");

        let mut new = old.clone();
        new.bodies[1].name = new.bodies[0].name.clone();
        let msg = err(diff(&old, &new));
        assert_eq!(msg, "bodies: `crate` names two bodies of the new scene");
    }

    #[test]
    fn joints_must_stay_as_they_were() {
        use mwb_core::scene::{BodyRef, JointKind};
        let mut old = tumble();
        old.joints.push(Joint {
            name: "hinge".into(),
            kind: JointKind::Spherical,
            body1: BodyRef::Body(0),
            body2: BodyRef::Body(1),
            anchor1: [0.0; 3],
            anchor2: [0.3, 0.0, 0.0],
        });
        // Moving a jointed body is a body edit; the joint, by body names, is unchanged even
        // though the indices moved.
        let mut new = old.clone();
        new.bodies.swap(0, 1);
        new.joints[0].body1 = BodyRef::Body(1);
        new.joints[0].body2 = BodyRef::Body(0);
        new.bodies[1].linvel[1] += 1.0;
        let d = diff(&old, &new).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(d.bodies[1], BodyEdit::Modified(0));
        // Removing a jointed body changes its joint.
        let mut new = old.clone();
        new.bodies.remove(1);
        new.joints[0].body2 = BodyRef::Body(3);
        let msg = err(diff(&old, &new));
        assert_eq!(
            msg,
            "joints: `hinge` changed (body2): an edit of a joint needs a new job"
        );
        let mut new = old.clone();
        new.joints.clear();
        let msg = err(diff(&old, &new));
        assert!(msg.starts_with("joints: `hinge` removed"), "{msg}");
    }
}
