//! Refinement (Twigg and James, SIGGRAPH 2007, §4.5): re-simulate only the part of an
//! almost-right world that goes wrong.
//!
//! The animator picks objects and a screen box over the part of their path that must change.
//! The branch frame `t_min` is the first frame at which any picked object's centre of mass is
//! inside the box's frustum, on the parent's own motion. From there a *child* world is stepped
//! with three sets of objects (the paper's Figure 4.12):
//!
//! * **active** bodies are simulated and perturbed (§4.1.2) — at first only the picked ones;
//! * **inactive** bodies are kinematic and replay the parent's motion exactly;
//! * every active body has a **ghost** that replays its parent motion.
//!
//! An inactive body that an active body is about to touch becomes active (Figure 4.11a: it must
//! respond to the new motion), and so does one that an active body's ghost is about to touch
//! (Figure 4.11b: the parent's version of the active body hit it, the new one may not). Bodies
//! joined by a joint change sets together. We activate *before* the step in which the contact
//! could happen, by a conservative distance test (parry's exact distance between the shapes
//! against the distance both can cover in one step plus the contact prediction distance). The
//! paper reads interactions from the simulator's callbacks instead; rapier reports contacts after
//! the step has solved them, so an inactive body would act as an immovable wall for one step.
//! Interactions between two inactive bodies change nothing (both replay one physically valid
//! motion), so unlike a literal reading of Figure 4.12 they do not activate anything.
//!
//! Neither does an active body that still follows its parent motion: until it is further than
//! 1 mm from it ([`FOLLOW_TOLERANCE_M`], the standard codec bound; position, rotation at its
//! bounding radius, and what its velocity difference makes of one step), it does to its
//! neighbours what its parent
//! version did, which their replayed motion already contains. Without this gate every refinement
//! of a body in a stack would activate the whole stack through resting contacts (the paper's
//! rule), and refining the projectile of `scenes/tower.toml` would cost a full world; with it
//! the refined world is physically consistent to within the precision its parent is stored at.
//!
//! **Exact parents.** A world is regenerated from its [`Lineage`] (root seed, then each
//! refinement's branch frame, objects and seed): the sampler is deterministic, so the
//! regenerated parent is the stored world bit for bit, the child starts from the parent's exact
//! simulator state at the branch frame (bodies, contacts and their warm-start impulses — a fork of
//! rapier's sets), and inactive bodies replay the parent's exact `f32` poses rather than the
//! stored, lossy ones (the paper replayed stored motion). One regenerated [`Parent`] serves any
//! number of children.
//!
//! **What a child records.** Only the bodies that became active, as segments on the parent's
//! segment grid from the one holding the branch frame on ([`Segment::bodies`] names them); the
//! rest of the world is the parent's. [`RefinedWorld::active_from`] says from which frame each
//! body's motion is new. This is what samplers send: the store composes the whole world from the
//! parent it holds (`mwb_codec::Layered`). [`Parent::refine_whole`] records the whole world
//! instead (tests compare the composition with it).
//! Whatever is recorded, the simulation is the same: a refined world regenerates from its
//! lineage alone.
//!
//! **Scene edits** ([`crate::edit`]) step through the same child loop (`ChildStart`): from
//! frame 0 of a world built from the edited scene, its bodies mapped to the parent's by name,
//! bodies the edit dropped kept only as ghosts.

use crate::world::{
    BodyState, Followed, Progress, Recorder, RunError, RunOptions, Segment, SimWorld, StepHooks,
    WorldSummary, advance, frame_pose, frames_per_segment, summary_of,
};
use mwb_core::browse::Frustum;
use mwb_core::rng::{Stream, WorldRng};
use mwb_core::scene::{BodyRef, Scene, SceneTemplate};
use rapier3d::parry::bounding_volume::{Aabb, BoundingVolume};
use rapier3d::prelude::*;
use std::ops::ControlFlow;

/// How far (metres) an active body may be from its parent motion and still count as following
/// it (see the module docs): the standard codec bound. A constant, not the job's codec quality,
/// so that a world regenerates to the same motion whatever quality it was recorded at.
pub const FOLLOW_TOLERANCE_M: f32 = 1e-3;

/// How a world came to be: a root world of the job's scene from `root_seed`, then each
/// refinement in order. Regenerating a world means replaying its lineage.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Lineage {
    pub root_seed: u64,
    pub steps: Vec<Branch>,
}

/// One refinement: from frame `frame` of its parent, the bodies `objects` were re-simulated with
/// perturbation seed `seed`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Branch {
    pub frame: u32,
    pub objects: Vec<u32>,
    pub seed: u64,
    /// Picked bodies that start with other velocities than the parent's there.
    pub kicks: Vec<Kick>,
}

/// A picked body's velocities replaced at the branch frame: a scene edit that changes an
/// object's motion, and the way tests force a child to diverge.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Kick {
    pub body: u32,
    pub linvel: [f64; 3],
    pub angvel: [f64; 3],
}

impl Eq for Kick {}

impl Lineage {
    /// A root world.
    pub fn root(seed: u64) -> Self {
        Self {
            root_seed: seed,
            steps: Vec::new(),
        }
    }

    /// This world's child by `branch`.
    pub fn child(&self, branch: Branch) -> Self {
        let mut out = self.clone();
        out.steps.push(branch);
        out
    }
}

/// Where to fork the regenerated parent.
#[derive(Debug, Clone)]
pub enum BranchAt {
    /// At this frame.
    Frame(u32),
    /// §4.5's `t_min`: the first frame at which the centre of any of these bodies is inside
    /// the frustum.
    FirstInside {
        objects: Vec<u32>,
        frustum: Box<Frustum>,
    },
}

/// Refinements that cannot be done, each naming what is wrong.
#[derive(Debug, thiserror::Error)]
pub enum RefineError {
    #[error(transparent)]
    Run(#[from] RunError),
    #[error("objects: none picked")]
    NoObjects,
    #[error("objects: body {object} out of range (the scene has {bodies} bodies)")]
    ObjectOutOfRange { object: u32, bodies: usize },
    #[error(
        "frustum: the centre of {objects:?} is never inside it in the parent's {frames} frames"
    )]
    NeverInside { objects: Vec<u32>, frames: u32 },
    #[error("frame: {frame} is past the parent's last frame {last}")]
    FramePastEnd { frame: u32, last: u32 },
    #[error("kicks: body {body} is not one of the picked objects")]
    KickNotPicked { body: u32 },
    #[error("lineage step {step}: {source}")]
    Lineage {
        step: usize,
        #[source]
        source: Box<RefineError>,
    },
}

/// A world's exact motion: every body's simulator state at every frame.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ExactMotion {
    bodies: usize,
    /// Frame-major: `frames × bodies`.
    states: Vec<BodyState>,
}

impl ExactMotion {
    /// Frames held.
    pub fn frame_count(&self) -> u32 {
        (self.states.len() / self.bodies.max(1)) as u32
    }

    /// Bodies per frame.
    pub fn body_count(&self) -> usize {
        self.bodies
    }

    /// Body `body`'s state at `frame`; after the last frame, its last pose at rest. `None` for
    /// a body out of range or a world without frames.
    pub fn state(&self, frame: u32, body: usize) -> Option<BodyState> {
        if body >= self.bodies {
            return None;
        }
        let frames = self.frame_count();
        if frame < frames {
            self.states
                .get(frame as usize * self.bodies + body)
                .copied()
        } else {
            let last = *self
                .states
                .get((frames as usize).checked_sub(1)? * self.bodies + body)?;
            Some(BodyState {
                linvel: Vector::ZERO,
                angvel: Vector::ZERO,
                sleeping: true,
                in_impact: false,
                ..last
            })
        }
    }

    /// Body `body`'s linear and angular velocity at `frame` (after that frame's step and its
    /// perturbation), widened exactly.
    pub fn velocities(&self, frame: u32, body: usize) -> Option<([f64; 3], [f64; 3])> {
        let v = |x: Vector| [x.x, x.y, x.z].map(f64::from);
        self.state(frame, body).map(|s| (v(s.linvel), v(s.angvel)))
    }

    /// Body `body`'s pose at `frame` as a recorded frame pose.
    pub fn pose(&self, frame: u32, body: usize) -> Option<mwb_core::frames::Pose> {
        self.state(frame, body).map(|s| frame_pose(&s.pose))
    }
}

/// A parent world regenerated exactly, forked at its branch frame.
pub struct Parent {
    scene: Scene,
    lineage: Lineage,
    motion: ExactMotion,
    bodies: usize,
    fork: Progress,
    branch_frame: u32,
}

/// A refined world.
#[derive(Debug, Clone, PartialEq)]
pub struct RefinedWorld {
    pub lineage: Lineage,
    /// Over the whole world (the parent's frames before the branch included); `payload_bytes`
    /// counts only the segments this child emitted.
    pub summary: WorldSummary,
    pub branch_frame: u32,
    /// The first segment the child emitted (the one holding the branch frame).
    pub first_segment: u32,
    /// Per body, the frame from which its motion is new (`None`: the parent's throughout).
    pub active_from: Vec<Option<u32>>,
}

impl RefinedWorld {
    /// Bodies re-simulated ÷ bodies.
    pub fn active_fraction(&self) -> f64 {
        let n = self.active_from.len().max(1);
        self.active_from.iter().filter(|a| a.is_some()).count() as f64 / n as f64
    }
}

/// The bodies joined to each body by joints, transitively (itself included): they change sets
/// together, since a joint to a kinematic body would drag an active one along the parent's path.
pub(crate) fn joint_groups(scene: &Scene) -> Vec<Vec<usize>> {
    let n = scene.bodies.len();
    let mut root: Vec<usize> = (0..n).collect();
    fn find(root: &mut [usize], mut i: usize) -> usize {
        while root[i] != i {
            root[i] = root[root[i]];
            i = root[i];
        }
        i
    }
    for j in &scene.joints {
        if let (BodyRef::Body(a), BodyRef::Body(b)) = (j.body1, j.body2) {
            let (ra, rb) = (find(&mut root, a), find(&mut root, b));
            root[ra] = rb;
        }
    }
    let mut groups = vec![Vec::new(); n];
    for i in 0..n {
        let r = find(&mut root, i);
        groups[r].push(i);
    }
    (0..n)
        .map(|i| {
            let r = find(&mut root, i);
            groups[r].clone()
        })
        .collect()
}

fn check_objects(objects: &[u32], bodies: usize) -> Result<(), RefineError> {
    if objects.is_empty() {
        return Err(RefineError::NoObjects);
    }
    match objects.iter().find(|&&o| o as usize >= bodies) {
        Some(&object) => Err(RefineError::ObjectOutOfRange { object, bodies }),
        None => Ok(()),
    }
}

/// What one generation (the root world or a child) leaves for the next: its exact motion from
/// its first frame on, and forks at the frames later generations start from.
pub(crate) struct Capture<'a> {
    /// Fork at these frames.
    frames: Vec<u32>,
    /// Also fork at the first frame at which the centre of any of these bodies is inside the
    /// frustum.
    inside: Option<(&'a [u32], &'a Frustum)>,
    first_inside: Option<u32>,
    motion: Vec<BodyState>,
    forks: Vec<(u32, Progress)>,
}

impl<'a> Capture<'a> {
    pub(crate) fn new(frames: Vec<u32>, inside: Option<(&'a [u32], &'a Frustum)>) -> Self {
        Self {
            frames,
            inside,
            first_inside: None,
            motion: Vec::new(),
            forks: Vec::new(),
        }
    }

    fn frame(&mut self, p: &Progress, states: impl Iterator<Item = BodyState>) {
        let start = self.motion.len();
        self.motion
            .extend(states.zip(&p.trackers).map(|(s, t)| BodyState {
                in_impact: t.in_impact,
                ..s
            }));
        let frame = p.steps as u32;
        let mut fork = self.frames.contains(&frame);
        if let Some((objects, frustum)) = self.inside
            && self.first_inside.is_none()
            && inside(objects, frustum, &self.motion[start..])
        {
            self.first_inside = Some(frame);
            fork = true;
        }
        if fork {
            self.forks.push((frame, p.fork()));
        }
    }

    fn take_fork(&mut self, frame: u32) -> Option<Progress> {
        let i = self.forks.iter().position(|(f, _)| *f == frame)?;
        Some(self.forks.swap_remove(i).1)
    }

    /// The motion captured, as a world of `bodies` bodies from its first frame.
    pub(crate) fn into_motion(self, bodies: usize) -> ExactMotion {
        ExactMotion {
            bodies,
            states: self.motion,
        }
    }
}

/// Whether the centre of any of `objects` is inside `frustum` in one frame's states.
fn inside(objects: &[u32], frustum: &Frustum, states: &[BodyState]) -> bool {
    objects.iter().any(|&o| {
        states
            .get(o as usize)
            .is_some_and(|s| frustum.contains(frame_pose(&s.pose).position))
    })
}

struct RootHooks<'c, 'a> {
    capture: &'c mut Capture<'a>,
}

impl StepHooks for RootHooks<'_, '_> {
    fn frame(&mut self, p: &Progress) -> Result<(), RunError> {
        let n = p.sim.bodies.len();
        self.capture.frame(p, (0..n).map(|i| p.sim.state(i)));
        Ok(())
    }
}

/// Regenerates the world `lineage` names (exactly, encoding nothing) and forks it at `at`. The
/// regenerated world is the stored one bit for bit (same binary, scene and lineage).
pub fn regenerate(
    template: &SceneTemplate,
    lineage: &Lineage,
    at: &BranchAt,
) -> Result<Parent, RefineError> {
    let (frame, rule) = match at {
        BranchAt::Frame(f) => (*f, None),
        BranchAt::FirstInside { objects, frustum } => {
            (u32::MAX, Some((objects.as_slice(), &**frustum)))
        }
    };
    match regenerate_at(template, lineage, frame, rule)? {
        Regen::Parent(p) => Ok(*p),
        // t_min falls before the last refinement's branch: fork the ancestor that holds it.
        Regen::Earlier(t_min) => match regenerate_at(template, lineage, t_min, None)? {
            Regen::Parent(p) => Ok(*p),
            Regen::Earlier(frame) => Err(RefineError::FramePastEnd { frame, last: frame }),
        },
    }
}

enum Regen {
    Parent(Box<Parent>),
    /// t_min lies before the last refinement's branch, where no fork was kept.
    Earlier(u32),
}

/// [`regenerate`] forking at `frame`, or at the first frame inside.
fn regenerate_at(
    template: &SceneTemplate,
    lineage: &Lineage,
    frame: u32,
    inside_rule: Option<(&[u32], &Frustum)>,
) -> Result<Regen, RefineError> {
    let scene = template.instantiate(lineage.root_seed);
    let n = scene.bodies.len();
    if let Some((objects, _)) = inside_rule {
        check_objects(objects, n)?;
    }
    // Generation 0 is the root, generation g ≥ 1 the child of step g − 1, starting at frame
    // start[g]. Generation m + 1 forks from the generation whose frames hold its branch frame
    // in generation m's history: the latest one that started at or before it.
    let generations = lineage.steps.len() + 1;
    let start: Vec<u32> = std::iter::once(0)
        .chain(lineage.steps.iter().map(|b| b.frame))
        .collect();
    let owner = |history: usize, f: u32| (0..=history).rev().find(|&j| start[j] <= f).unwrap_or(0);
    // The frames each generation forks at.
    let mut wanted: Vec<Vec<u32>> = vec![Vec::new(); generations];
    for (m, b) in lineage.steps.iter().enumerate() {
        wanted[owner(m, b.frame)].push(b.frame);
    }
    if inside_rule.is_none() {
        wanted[owner(generations - 1, frame)].push(frame);
    }
    let mut captures: Vec<Capture<'_>> = Vec::with_capacity(generations);
    let mut history: Vec<BodyState> = Vec::new();
    for g in 0..generations {
        let last = g + 1 == generations;
        let mut capture = Capture::new(
            std::mem::take(&mut wanted[g]),
            if last { inside_rule } else { None },
        );
        if g == 0 {
            let sim = SimWorld::build(&scene).map_err(RunError::from)?;
            let mut p = Progress::new(sim);
            let mut rng = WorldRng::new(lineage.root_seed, Stream::Perturbation);
            capture.frame(&p, (0..n).map(|i| p.sim.state(i)));
            advance(
                &scene,
                &mut p,
                &mut rng,
                true,
                &mut RootHooks {
                    capture: &mut capture,
                },
            )?;
            history = std::mem::take(&mut capture.motion);
        } else {
            let branch = &lineage.steps[g - 1];
            let frames = (history.len() / n.max(1)) as u32;
            let Some(fork) = captures[owner(g - 1, branch.frame)].take_fork(branch.frame) else {
                return Err(RefineError::Lineage {
                    step: g - 1,
                    source: Box::new(RefineError::FramePastEnd {
                        frame: branch.frame,
                        last: frames.saturating_sub(1),
                    }),
                });
            };
            let parent = Parent {
                scene: scene.clone(),
                lineage: Lineage {
                    root_seed: lineage.root_seed,
                    steps: lineage.steps[..g - 1].to_vec(),
                },
                motion: ExactMotion {
                    bodies: n,
                    states: std::mem::take(&mut history),
                },
                bodies: n,
                fork,
                branch_frame: branch.frame,
            };
            parent
                .child(
                    branch,
                    RunOptions {
                        record: false,
                        ..RunOptions::default()
                    },
                    Some(&mut capture),
                    &mut |_| ControlFlow::Continue(()),
                )
                .map_err(|e| RefineError::Lineage {
                    step: g - 1,
                    source: Box::new(e),
                })?;
            // The child's history: its parent's before the branch, its own from there.
            let mut motion = parent.motion.states;
            motion.truncate(branch.frame as usize * n);
            motion.append(&mut capture.motion);
            history = motion;
        }
        captures.push(capture);
    }
    let frames = (history.len() / n.max(1)) as u32;
    let branch_frame = match inside_rule {
        None => frame,
        Some((objects, frustum)) => {
            let Some(t_min) = (0..frames).find(|&f| {
                let at = f as usize * n;
                inside(objects, frustum, &history[at..at + n])
            }) else {
                return Err(RefineError::NeverInside {
                    objects: objects.to_vec(),
                    frames,
                });
            };
            if t_min < start[generations - 1] {
                return Ok(Regen::Earlier(t_min));
            }
            t_min
        }
    };
    let Some(fork) = captures[owner(generations - 1, branch_frame)].take_fork(branch_frame) else {
        return Err(RefineError::FramePastEnd {
            frame: branch_frame,
            last: frames.saturating_sub(1),
        });
    };
    Ok(Regen::Parent(Box::new(Parent {
        scene,
        lineage: lineage.clone(),
        motion: ExactMotion {
            bodies: n,
            states: history,
        },
        bodies: n,
        fork,
        branch_frame,
    })))
}

impl Parent {
    /// The frame the children start from.
    pub fn branch_frame(&self) -> u32 {
        self.branch_frame
    }

    /// The parent's exact motion (its whole history).
    pub fn motion(&self) -> &ExactMotion {
        &self.motion
    }

    /// Body `body`'s exact state at `frame` (`body` in range: the parent has at least its
    /// first frame).
    fn state(&self, frame: u32, body: usize) -> BodyState {
        self.motion.state(frame, body).unwrap_or(BodyState {
            pose: Pose::IDENTITY,
            linvel: Vector::ZERO,
            angvel: Vector::ZERO,
            in_impact: false,
            sleeping: true,
        })
    }

    /// The parent's lineage.
    pub fn lineage(&self) -> &Lineage {
        &self.lineage
    }

    /// The scene instance (the root seed's).
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// [`Parent::refine`], recording the whole world as a sampled world is recorded: every
    /// segment from the first, every body (the parent's exact frames before the branch and for
    /// inactive bodies, encoded again): the reference a composed world is checked against; it
    /// costs the encoding of a whole world.
    pub fn refine_whole(
        &self,
        objects: &[u32],
        seed: u64,
        opts: RunOptions,
        emit: &mut dyn FnMut(Segment) -> ControlFlow<()>,
    ) -> Result<RefinedWorld, RefineError> {
        let branch = Branch {
            frame: self.branch_frame,
            objects: objects.to_vec(),
            seed,
            kicks: Vec::new(),
        };
        self.child_recorded(&branch, opts, true, None, emit)
    }

    /// Refines: a child world that re-simulates `objects` from the branch frame with
    /// perturbation seed `seed`, emitting its segments. Deterministic in (lineage, objects,
    /// seed).
    pub fn refine(
        &self,
        objects: &[u32],
        seed: u64,
        opts: RunOptions,
        emit: &mut dyn FnMut(Segment) -> ControlFlow<()>,
    ) -> Result<RefinedWorld, RefineError> {
        self.refine_with(objects, seed, opts, &[], emit)
    }

    /// [`Parent::refine`], some picked objects starting with other velocities than the
    /// parent's ([`Kick`]).
    pub fn refine_with(
        &self,
        objects: &[u32],
        seed: u64,
        opts: RunOptions,
        kicks: &[Kick],
        emit: &mut dyn FnMut(Segment) -> ControlFlow<()>,
    ) -> Result<RefinedWorld, RefineError> {
        let branch = Branch {
            frame: self.branch_frame,
            objects: objects.to_vec(),
            seed,
            kicks: kicks.to_vec(),
        };
        self.child(&branch, opts, None, emit)
    }

    /// [`Parent::refine_with`], also returning the child's exact motion over the whole world
    /// (the parent's before the branch frame): for tests and benchmarks.
    pub fn refine_traced(
        &self,
        objects: &[u32],
        seed: u64,
        opts: RunOptions,
        kicks: &[Kick],
        emit: &mut dyn FnMut(Segment) -> ControlFlow<()>,
    ) -> Result<(RefinedWorld, ExactMotion), RefineError> {
        let branch = Branch {
            frame: self.branch_frame,
            objects: objects.to_vec(),
            seed,
            kicks: kicks.to_vec(),
        };
        let mut capture = Capture::new(Vec::new(), None);
        let world = self.child(&branch, opts, Some(&mut capture), emit)?;
        let mut states = self.motion.states[..self.branch_frame as usize * self.bodies].to_vec();
        states.append(&mut capture.motion);
        Ok((
            world,
            ExactMotion {
                bodies: self.bodies,
                states,
            },
        ))
    }

    /// Steps one child (see the module docs); `capture` keeps its exact motion from the branch
    /// frame on and forks it, for regenerating it as a parent.
    fn child(
        &self,
        branch: &Branch,
        opts: RunOptions,
        capture: Option<&mut Capture<'_>>,
        emit: &mut dyn FnMut(Segment) -> ControlFlow<()>,
    ) -> Result<RefinedWorld, RefineError> {
        self.child_recorded(branch, opts, false, capture, emit)
    }

    /// [`Parent::child`]; `whole` records every segment and body (see
    /// [`Parent::refine_whole`]).
    fn child_recorded(
        &self,
        branch: &Branch,
        opts: RunOptions,
        whole: bool,
        capture: Option<&mut Capture<'_>>,
        emit: &mut dyn FnMut(Segment) -> ControlFlow<()>,
    ) -> Result<RefinedWorld, RefineError> {
        check_objects(&branch.objects, self.bodies)?;
        let scene = &self.scene;
        let n = self.bodies;
        let k = self.branch_frame;
        let mut p = self.fork.fork();
        let groups = joint_groups(scene);
        let mut active = vec![false; n];
        for &o in &branch.objects {
            for &b in &groups[o as usize] {
                active[b] = true;
            }
        }
        // Sets at the branch frame: active bodies dynamic with the parent's exact state there
        // (a body a previous refinement kept kinematic has the parent's velocity, not its own),
        // the others kinematic on the parent's poses.
        for (i, &h) in p.sim.bodies.iter().enumerate() {
            let s = self.state(k, i);
            let rb = &mut p.sim.world.bodies[h];
            if active[i] {
                rb.set_body_type(RigidBodyType::Dynamic, true);
                rb.set_linvel(s.linvel, true);
                rb.set_angvel(s.angvel, true);
            } else {
                rb.set_body_type(RigidBodyType::KinematicPositionBased, false);
            }
        }
        for kick in &branch.kicks {
            let b = kick.body as usize;
            if b >= n || !branch.objects.contains(&kick.body) {
                return Err(RefineError::KickNotPicked { body: kick.body });
            }
            let rb = &mut p.sim.world.bodies[p.sim.bodies[b]];
            let f = |a: [f64; 3]| Vector::new(a[0] as f32, a[1] as f32, a[2] as f32);
            rb.set_linvel(f(kick.linvel), true);
            rb.set_angvel(f(kick.angvel), true);
        }
        let fps = frames_per_segment(scene) as u32;
        let first_segment = if whole { 0 } else { k / fps };
        let mut observe = |_: &[mwb_codec::Track]| {};
        let mut rec = Recorder::new(scene, &p.sim, opts, emit, &mut observe);
        rec.frame_count = first_segment * fps;
        rec.segment_count = first_segment;
        rec.keep = if whole { vec![true; n] } else { active.clone() };
        // The segment holding the branch frame starts with the parent's frames (all of them
        // before the branch, recording the whole world).
        if opts.record {
            for f in first_segment * fps..=k {
                rec.push((0..n).map(|i| frame_pose(&self.state(f, i).pose)))?;
            }
        }
        let start = ChildStart {
            scene,
            parent_of: (0..n).map(Some).collect(),
            active,
            diverged: vec![false; n],
            ghosts: Vec::new(),
            groups,
            seed: branch.seed,
        };
        let active_from = self.step_child(start, &mut p, opts, &mut rec, capture)?;
        let summary = summary_of(&p, &rec, branch.seed, scene.settings.dt);
        Ok(RefinedWorld {
            lineage: self.lineage.child(branch.clone()),
            summary,
            branch_frame: k,
            first_segment,
            active_from,
        })
    }

    /// Steps a child from the frame `p` holds to its end (see the module docs), recording its
    /// frames with `rec` (which already holds the frames before) and flushing it; `capture`
    /// keeps its exact motion from that frame on. Returns, per child body, the frame from which
    /// it was simulated. The one stepping loop of refinement and of scene edits
    /// ([`crate::edit`]).
    pub(crate) fn step_child(
        &self,
        start: ChildStart<'_>,
        p: &mut Progress,
        opts: RunOptions,
        rec: &mut Recorder<'_>,
        capture: Option<&mut Capture<'_>>,
    ) -> Result<Vec<Option<u32>>, RunError> {
        let ChildStart {
            scene,
            parent_of,
            active,
            diverged,
            ghosts,
            groups,
            seed,
        } = start;
        let k = p.steps as u32;
        let mut active_from: Vec<Option<u32>> = active.iter().map(|&a| a.then_some(k)).collect();
        let margin = 2.0 * p.sim.world.integration_parameters.prediction_distance();
        let gravity = p.sim.world.gravity.length();
        let mut capture = capture;
        if let Some(c) = capture.as_deref_mut() {
            let sim = &p.sim;
            c.frame(
                p,
                (0..active.len()).map(|i| match parent_of[i] {
                    Some(j) if !active[i] => self.state(k, j),
                    _ => sim.state(i),
                }),
            );
        }
        let mut rng = WorldRng::new(seed, Stream::Perturbation);
        let mut hooks = ChildHooks {
            parent: self,
            radius: radii(scene, &p.sim),
            parent_radius: radii(&self.scene, &self.fork.sim),
            parent_of,
            ghosts,
            diverged,
            tolerance: FOLLOW_TOLERANCE_M,
            active,
            active_from: &mut active_from,
            groups,
            margin,
            gravity,
            rec,
            record: opts.record,
            capture,
        };
        advance(scene, p, &mut rng, opts.perturb, &mut hooks)?;
        if opts.record {
            hooks.rec.flush()?;
        }
        Ok(active_from)
    }
}

/// How a child starts (Figure 4.12): who its bodies are in the parent, which are simulated, and
/// which ghosts it keeps. A refinement's child has its parent's bodies; a scene edit's
/// ([`crate::edit`]) has the new scene's, some of them new, and ghosts of bodies it dropped.
pub(crate) struct ChildStart<'s> {
    /// The child's scene (its bodies are the child's bodies).
    pub scene: &'s Scene,
    /// Per child body, the parent body whose motion it replays while inactive (`None`: the
    /// parent has no such body; it must be active from the start).
    pub parent_of: Vec<Option<usize>>,
    /// Per child body, whether it is simulated from the start.
    pub active: Vec<bool>,
    /// Per child body, whether it counts as diverged from its parent motion from the start: a
    /// new or changed body is not its parent version, so what that version did to its
    /// neighbours says nothing about what it will do.
    pub diverged: Vec<bool>,
    /// Parent bodies the child does not have: their ghosts replay the parent motion and
    /// activate what they are about to touch from the start (Figure 4.11b).
    pub ghosts: Vec<usize>,
    /// [`joint_groups`] of the child's scene.
    pub groups: Vec<Vec<usize>>,
    /// The child's perturbation seed (§4.1.2).
    pub seed: u64,
}

/// Each body's bounding radius about its centre of mass, where rapier's velocities are: the
/// shape's radius about its origin plus how far the centre is from it (non-zero for a compound
/// or an off-centre hull; exactly zero for the primitives).
fn radii(scene: &Scene, sim: &SimWorld) -> Vec<f32> {
    scene
        .bodies
        .iter()
        .zip(&sim.bodies)
        .map(|(b, &h)| {
            let com = sim.world.bodies[h]
                .mass_properties()
                .local_mprops
                .local_com
                .length();
            b.shape.bounding_radius() as f32 + com
        })
        .collect()
}

struct ChildHooks<'a, 'r, 'c, 'k> {
    parent: &'a Parent,
    /// Per child body, its body in the parent ([`ChildStart::parent_of`]).
    parent_of: Vec<Option<usize>>,
    /// Parent bodies whose ghosts alone stand for them ([`ChildStart::ghosts`]).
    ghosts: Vec<usize>,
    active: Vec<bool>,
    /// Active bodies that have left their parent motion by more than `tolerance` (once, for
    /// good), or were never their parent version. Only they can change what happens to an
    /// inactive body.
    diverged: Vec<bool>,
    /// [`FOLLOW_TOLERANCE_M`].
    tolerance: f32,
    active_from: &'a mut Vec<Option<u32>>,
    groups: Vec<Vec<usize>>,
    /// Each child body's bounding radius about its centre of mass (at most).
    radius: Vec<f32>,
    /// The same for the parent's bodies (their ghosts).
    parent_radius: Vec<f32>,
    /// Distance at which two bodies count as about to touch (twice rapier's contact prediction).
    margin: f32,
    gravity: f32,
    rec: &'r mut Recorder<'c>,
    record: bool,
    capture: Option<&'r mut Capture<'k>>,
}

/// The shapes of body `body` of simulator `sim`: a child's own body, or a parent's for a ghost.
#[derive(Clone, Copy)]
struct BodyShapes<'s> {
    sim: &'s SimWorld,
    body: usize,
}

/// The body's shapes at a pose.
fn placed<'s>(
    of: BodyShapes<'s>,
    pose: &Pose,
) -> impl Iterator<Item = (Pose, &'s dyn rapier3d::parry::shape::Shape)> + 's {
    let sim = of.sim;
    let rb = &sim.world.bodies[sim.bodies[of.body]];
    let pose = *pose;
    rb.colliders().iter().filter_map(move |&c| {
        let co = sim.world.colliders.get(c)?;
        let local = co.position_wrt_parent().copied().unwrap_or(Pose::IDENTITY);
        Some((pose * local, co.shape()))
    })
}

/// The AABB of a body's shapes at `pose` (`None` for a body without colliders).
fn aabb(of: BodyShapes<'_>, pose: &Pose) -> Option<Aabb> {
    placed(of, pose)
        .map(|(x, shape)| shape.compute_aabb(&x))
        .reduce(|a, b| a.merged(&b))
}

/// Whether bodies `a` (at `pa`) and `b` (at `pb`) are within `reach` of each other. Conservative:
/// a distance query parry does not support counts as touching.
fn within(a: BodyShapes<'_>, pa: &Pose, b: BodyShapes<'_>, pb: &Pose, reach: f32) -> bool {
    for (xa, sa) in placed(a, pa) {
        let box_a = sa.compute_aabb(&xa).loosened(reach);
        for (xb, sb) in placed(b, pb) {
            if !box_a.intersects(&sb.compute_aabb(&xb)) {
                continue;
            }
            match rapier3d::parry::query::distance(&xa, sa, &xb, sb) {
                Ok(d) if d.distance > reach => {}
                _ => return true,
            }
        }
    }
    false
}

impl<'a> ChildHooks<'a, '_, '_, '_> {
    /// How far a body of bounding radius `radius` can move in one step at most, from its state
    /// `s`.
    fn reach(&self, radius: f32, s: &BodyState, dt: f32) -> f32 {
        (s.linvel.length() + s.angvel.length() * radius + self.gravity * dt) * dt
    }

    /// Child body `i`'s parent motion at `frame` (`None`: the parent has no such body).
    fn replayed(&self, frame: u32, i: usize) -> Option<BodyState> {
        self.parent_of[i].map(|j| self.parent.state(frame, j))
    }

    /// How far active body `a` is from its parent motion at this frame: position, rotation at
    /// its bounding radius, and the difference the velocities make over one step.
    fn divergence(&self, p: &Progress, a: usize, frame: u32) -> f32 {
        let Some(g) = self.replayed(frame, a) else {
            return f32::INFINITY;
        };
        let s = p.sim.state(a);
        let r = self.radius[a];
        let dt = p.sim.dt as f32;
        let angle = (s.pose.rotation * g.pose.rotation.inverse())
            .to_axis_angle()
            .1;
        let angle = angle.min(std::f32::consts::TAU - angle).abs();
        (s.pose.translation - g.pose.translation).length()
            + r * angle
            + dt * ((s.linvel - g.linvel).length() + r * (s.angvel - g.angvel).length())
    }

    /// Parent body `g`'s ghost as a source this step (Figure 4.11b): where the parent had it,
    /// with what it could cover in the step.
    fn ghost(&self, g: usize, frame: u32, dt: f32) -> (BodyShapes<'a>, Pose, f32) {
        let parent: &'a Parent = self.parent;
        let at = parent.state(frame, g);
        let next = parent.state(frame + 1, g);
        let shapes = BodyShapes {
            sim: &parent.fork.sim,
            body: g,
        };
        let radius = self.parent_radius.get(g).copied().unwrap_or(0.0);
        (shapes, at.pose, self.margin + self.reach(radius, &next, dt))
    }

    fn activate(&mut self, p: &mut Progress, body: usize) {
        let frame = p.steps as u32;
        for &b in &self.groups[body] {
            if self.active[b] {
                continue;
            }
            self.active[b] = true;
            self.active_from[b] = Some(frame);
            self.rec.keep[b] = true;
            let s = self.replayed(frame, b);
            let rb = &mut p.sim.world.bodies[p.sim.bodies[b]];
            rb.set_body_type(RigidBodyType::Dynamic, true);
            if let Some(s) = s {
                rb.set_linvel(s.linvel, true);
                rb.set_angvel(s.angvel, true);
            }
        }
    }
}

impl StepHooks for ChildHooks<'_, '_, '_, '_> {
    fn before_step(&mut self, p: &mut Progress) {
        let frame = p.steps as u32;
        let n = self.active.len();
        let dt = p.sim.dt as f32;
        for a in 0..n {
            if self.active[a] && !self.diverged[a] {
                self.diverged[a] = self.divergence(p, a, frame) > self.tolerance;
            }
        }
        // Who can reach whom this step. A body activated now has its parent's exact state, so it
        // has not diverged and cannot reach further: one round is enough.
        let mut sources = Vec::new();
        for a in (0..n).filter(|&a| self.diverged[a]) {
            // Figure 4.11a: the active body where it is now (its speed counted twice: a contact
            // this step may speed it up).
            let sa = p.sim.state(a);
            let shapes = BodyShapes {
                sim: &p.sim,
                body: a,
            };
            let reach = self.margin + 2.0 * self.reach(self.radius[a], &sa, dt);
            sources.push((shapes, sa.pose, reach));
            // Figure 4.11b: its ghost, where the parent had it.
            if let Some(g) = self.parent_of[a] {
                sources.push(self.ghost(g, frame, dt));
            }
        }
        // Ghosts of bodies the child does not have.
        for &g in &self.ghosts {
            sources.push(self.ghost(g, frame, dt));
        }
        let boxes: Vec<Option<Aabb>> = sources
            .iter()
            .map(|(of, pose, reach)| aabb(*of, pose).map(|b| b.loosened(*reach)))
            .collect();
        let mut newly = Vec::new();
        for o in (0..n).filter(|&o| !self.active[o] && !sources.is_empty()) {
            let (Some(so), Some(next)) = (self.replayed(frame, o), self.replayed(frame + 1, o))
            else {
                continue;
            };
            let reach_o = self.reach(self.radius[o], &next, dt);
            let target = BodyShapes {
                sim: &p.sim,
                body: o,
            };
            let Some(box_o) = aabb(target, &so.pose).map(|b| b.loosened(reach_o)) else {
                continue;
            };
            let hit = sources.iter().zip(&boxes).any(|((of, pose, reach), b)| {
                b.is_some_and(|b| b.intersects(&box_o))
                    && within(*of, pose, target, &so.pose, reach + reach_o)
            });
            if hit {
                newly.push(o);
            }
        }
        for o in newly {
            self.activate(p, o);
        }
        for i in (0..n).filter(|&i| !self.active[i]) {
            if let Some(next) = self.replayed(frame + 1, i) {
                p.sim.world.bodies[p.sim.bodies[i]].set_next_kinematic_position(next.pose);
            }
        }
    }

    fn followed(&self, i: usize, frame: u64) -> Option<Followed> {
        if self.active[i] {
            return None;
        }
        Some(Followed {
            after: self.replayed(frame as u32, i)?,
        })
    }

    fn frame(&mut self, p: &Progress) -> Result<(), RunError> {
        let n = self.active.len();
        let frame = p.steps as u32;
        if let Some(c) = self.capture.as_deref_mut() {
            let (parent, parent_of, active) = (self.parent, &self.parent_of, &self.active);
            c.frame(
                p,
                (0..n).map(|i| match parent_of[i] {
                    // Where the simulator put it (the parent's pose, exactly), moving as the
                    // parent moved it.
                    Some(j) if !active[i] => BodyState {
                        pose: p.sim.state(i).pose,
                        ..parent.state(frame, j)
                    },
                    _ => p.sim.state(i),
                }),
            );
        }
        if self.record {
            self.rec.push((0..n).map(|i| p.sim.pose(i)))?;
        }
        Ok(())
    }
}
