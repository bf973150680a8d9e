//! One world: a scene instance in rapier3d, stepped with §4.1.2 perturbations, recorded.
//!
//! This module is pure computation (no bus, no async): [`run_world`] turns `(scene, seed)` into
//! motion segments and a summary, deterministically. The node around it only ships the bytes.
//!
//! Recording: every ~1 s of frames becomes one [`Segment`] whose payload is a self-contained
//! `mwb-codec` world stream (§4.3; one track per body, decodable without its neighbours) and
//! whose low-resolution path travels beside it.

use mwb_codec::{
    EncodeParams, MotionModel, Quality, RotationDynamics, Track, encode_world_with_dynamics,
};
use mwb_core::frames::Pose as FramePose;
use mwb_core::perturb::{self, V3};
use mwb_core::rng::{Stream, WorldRng};
use mwb_core::scene::{BodyRef, JointKind, Scene, SceneTemplate, Shape};
use rapier3d::na::Unit;
use rapier3d::prelude::*;
use std::ops::ControlFlow;

use crate::plan::SimPlan;

/// What the physics build is, recorded in every world's provenance: worlds are regenerated
/// bit for bit only by the same binary and build (STACK-NOTES: the enhanced-determinism build
/// gives different trajectories from the default one).
pub const PHYSICS_BUILD: &str = "rapier3d 0.36.1 f32 enhanced-determinism";

/// The provenance string of this binary.
pub fn provenance() -> String {
    format!("mwb {} / {PHYSICS_BUILD}", env!("CARGO_PKG_VERSION"))
}

/// Scenes rapier cannot build.
#[derive(Debug, thiserror::Error)]
pub enum BuildError {
    #[error("body {name:?}: convex hull of its points is degenerate")]
    DegenerateHull { name: String },
    #[error("static {name:?}: triangle mesh rejected: {reason}")]
    BadTriMesh { name: String, reason: String },
    #[error("body {name:?}: shape {shape} cannot be dynamic")]
    NotDynamic { name: String, shape: &'static str },
    #[error("{item} {name:?}: part {part}: shape {shape} cannot be a part of a compound")]
    BadPart {
        item: &'static str,
        name: String,
        part: usize,
        shape: &'static str,
    },
}

/// How to run a world.
#[derive(Debug, Clone, Copy)]
pub struct RunOptions {
    /// Apply §4.1.2 perturbations (off for the raw-stepping baseline of the benchmark).
    pub perturb: bool,
    /// Record and encode frames (off for the raw-stepping baseline: then nothing is encoded).
    pub record: bool,
    /// Error bounds of the motion codec (the job's; standard by default).
    pub quality: Quality,
    /// What a segment's payload is (the job's; the spline codec by default).
    pub encoding: PayloadEncoding,
}

/// A segment payload's encoding: the speed-versus-size knob of the sampler.
///
/// The spline codec (§4.3) is 4–20× smaller but costs about as much CPU per object-frame as a
/// rapier step (docs/performance.md); the quantised frames cost almost nothing to produce and
/// are the choice when samplers, not store memory or bandwidth, are the bottleneck.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PayloadEncoding {
    /// `ENCODING_SPLINE_V1`: error-bounded piecewise splines (`mwb-codec`).
    #[default]
    Spline,
    /// `ENCODING_QUANTISED_FRAMES_V1`: every frame, 0.1 mm / 1/32767, delta varints.
    QuantisedFrames,
}

impl Default for RunOptions {
    fn default() -> Self {
        Self {
            perturb: true,
            record: true,
            quality: Quality::default(),
            encoding: PayloadEncoding::default(),
        }
    }
}

/// One encoded segment of a world's motion.
#[derive(Debug, Clone, PartialEq)]
pub struct Segment {
    pub seq: u32,
    pub first_frame: u32,
    pub frame_count: u32,
    pub body_count: u32,
    /// The scene indices of the bodies whose tracks the payload holds, in order; empty when it
    /// holds every body (a refined world's segments carry only the bodies it re-simulated).
    pub bodies: Vec<u32>,
    /// An `mwb-codec` world stream of this segment's frames, one object per body in scene order
    /// (`ENCODING_SPLINE_V1` on the wire).
    pub payload: Vec<u8>,
    /// How `payload` is encoded.
    pub encoding: PayloadEncoding,
}

/// What happened in a world.
#[derive(Debug, Clone, PartialEq)]
pub struct WorldSummary {
    pub seed: u64,
    /// Frames recorded: the initial state plus one per step.
    pub frame_count: u32,
    pub segment_count: u32,
    pub frame_dt: f64,
    pub rested: bool,
    /// Impacts per body (onsets of ‖Δv‖ > C_v or ‖Δω‖ > C_ω).
    pub impacts: Vec<u32>,
    /// Per body, the time of the first frame from which it stayed below the rest thresholds
    /// (from the simulator's exact velocities; 0 if it never moved). For a body still moving
    /// at the end, the end time, and `body_rested` is false.
    pub rest_time_s: Vec<f64>,
    pub body_rested: Vec<bool>,
    pub perturbations: u32,
    pub steps: u64,
    pub payload_bytes: u64,
    /// The simulation plan the world ran with ([`SimPlan::describe`]): `WorldDone.sim`.
    pub sim: String,
}

/// Why a world stopped early.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    #[error(transparent)]
    Build(#[from] BuildError),
    #[error("stopped by the caller")]
    Stopped,
    #[error("motion encoding: {0}")]
    Codec(#[from] mwb_codec::CodecError),
    #[error("frame encoding: {0}")]
    Frames(#[from] mwb_core::frames::FrameError),
}

/// The codec's position model, chosen from the scene and never by the user (§4.3: "model only
/// what the scene requires").
///
/// Without linear damping and joints, a body between contacts feels gravity alone, and rapier's
/// symplectic Euler (`v += g·dt; x += v·dt`) gives `x_n = x_0 + n·dt·v_0 + g·dt²·n(n+1)/2`: the
/// `n²` term of every flight segment is exactly gravity's, so it costs one flag bit instead of
/// three quantised coefficients. Linear damping scales the velocity every step (an exponential,
/// not a parabola) and joints add constraint forces, so there the flag would almost never hold and
/// only cost a bit per segment: such scenes use the general per-axis quadratic. Angular damping
/// does not touch the centre-of-mass path and does not matter here. Either way the bound holds:
/// the gravity model only adds a cheaper candidate, segments that are not in free flight (contact,
/// rolling, rest) still get a full quadratic.
pub fn motion_model(scene: &Scene) -> MotionModel {
    if scene.settings.linear_damping == 0.0 && scene.joints.is_empty() {
        MotionModel::FreeFlightGravity {
            g: scene.settings.gravity,
        }
    } else {
        MotionModel::General
    }
}

/// How the simulator turns the world's bodies in free flight, for the codec's free-flight
/// rotation segments: its substeps per frame, the scene's angular damping, and each
/// body's principal moments where its inertia tensor is diagonal in its body axes with the centre
/// of mass at its origin (boxes, spheres, capsules, cylinders — every shape built around its
/// centre). `None` for scenes with joints (their constraint torques break the torque-free model,
/// which would then only cost encoder time) or with more than 16 solver iterations (the format's
/// most substeps).
pub fn rotation_dynamics(scene: &Scene, sim: &SimWorld) -> Option<RotationDynamics> {
    // More substeps than the codec's model allows: no free-flight segments.
    let substeps = scene.settings.solver_iterations;
    if !scene.joints.is_empty() || !(1..=16).contains(&substeps) {
        return None;
    }
    let inertia = sim
        .bodies
        .iter()
        .map(|&h| {
            let m = &sim.world.bodies.get(h)?.mass_properties().local_mprops;
            if m.local_com.length() > 1e-6 {
                return None;
            }
            // The tensor in body axes, R·diag(I)·Rᵀ: the principal frame may be any rotation
            // that permutes the body axes.
            let f = m.principal_inertia_local_frame;
            let [x, y, z, w] = [f.x, f.y, f.z, f.w].map(f64::from);
            let r = [
                [
                    1.0 - 2.0 * (y * y + z * z),
                    2.0 * (x * y - z * w),
                    2.0 * (x * z + y * w),
                ],
                [
                    2.0 * (x * y + z * w),
                    1.0 - 2.0 * (x * x + z * z),
                    2.0 * (y * z - x * w),
                ],
                [
                    2.0 * (x * z - y * w),
                    2.0 * (y * z + x * w),
                    1.0 - 2.0 * (x * x + y * y),
                ],
            ];
            let pi = m.principal_inertia();
            let pi = [pi.x, pi.y, pi.z].map(f64::from);
            let t = |i: usize, j: usize| (0..3).map(|k| r[i][k] * pi[k] * r[j][k]).sum::<f64>();
            let diag = [t(0, 0), t(1, 1), t(2, 2)];
            let max = diag.iter().fold(0.0f64, |a, &b| a.max(b));
            let off = [t(0, 1), t(0, 2), t(1, 2)];
            (max > 0.0 && off.iter().all(|v| v.abs() <= 1e-6 * max)).then_some(diag)
        })
        .collect();
    Some(RotationDynamics {
        substeps,
        angular_damping: scene.settings.angular_damping,
        inertia,
    })
}

fn v3(a: [f64; 3]) -> Vector {
    Vector::new(a[0] as f32, a[1] as f32, a[2] as f32)
}

fn quat(q: [f64; 4]) -> Rotation {
    Rotation::from_xyzw(q[0] as f32, q[1] as f32, q[2] as f32, q[3] as f32).normalize()
}

fn to_v3(v: Vector) -> V3 {
    [f64::from(v.x), f64::from(v.y), f64::from(v.z)]
}

fn shape_builder(name: &str, shape: &Shape) -> Result<ColliderBuilder, BuildError> {
    Ok(match shape {
        Shape::Box { half_extents: h } => {
            ColliderBuilder::cuboid(h[0] as f32, h[1] as f32, h[2] as f32)
        }
        Shape::Sphere { radius } => ColliderBuilder::ball(*radius as f32),
        Shape::Capsule {
            half_height,
            radius,
        } => ColliderBuilder::capsule_y(*half_height as f32, *radius as f32),
        Shape::Cylinder {
            half_height,
            radius,
        } => ColliderBuilder::cylinder(*half_height as f32, *radius as f32),
        Shape::ConvexHull { points } => {
            let pts: Vec<Vector> = points.iter().map(|p| v3(*p)).collect();
            ColliderBuilder::convex_hull(&pts).ok_or_else(|| BuildError::DegenerateHull {
                name: name.to_owned(),
            })?
        }
        Shape::Plane { normal } => {
            let n = v3(*normal).normalize();
            ColliderBuilder::halfspace(Unit::new_unchecked(n))
        }
        Shape::TriMesh { vertices, indices } => {
            let verts: Vec<Vector> = vertices.iter().map(|p| v3(*p)).collect();
            ColliderBuilder::trimesh(verts, indices.clone()).map_err(|e| {
                BuildError::BadTriMesh {
                    name: name.to_owned(),
                    reason: e.to_string(),
                }
            })?
        }
        // The parser never nests compounds; a compound is built part by part (`colliders`).
        Shape::Compound { .. } => {
            return Err(BuildError::BadPart {
                item: "body",
                name: name.to_owned(),
                part: 0,
                shape: "compound",
            });
        }
    })
}

/// The colliders of one body or static: one per part of a compound, each at its pose in the
/// body's frame with its own material, else the one shape with the body's material.
///
/// Mass properties: every collider carries its material's density, and rapier sums the parts'
/// masses, centres of mass and inertia tensors (about the common centre, parallel-axis) into the
/// body's, so a compound's mass is the union's (overlapping parts count twice where they
/// overlap — the scene format documents it). A single shape is built exactly as before
/// compounds existed, so existing scenes give the same bytes.
fn colliders(
    scene: &Scene,
    item: &'static str,
    name: &str,
    shape: &Shape,
    material: usize,
) -> Result<Vec<ColliderBuilder>, BuildError> {
    let with = |co: ColliderBuilder, material: usize| {
        let m = &scene.materials[material];
        co.friction(m.friction as f32)
            .restitution(m.restitution as f32)
            .density(m.density as f32)
    };
    match shape {
        Shape::Compound { parts } => parts
            .iter()
            .enumerate()
            .map(|(i, p)| {
                if matches!(p.shape, Shape::Compound { .. } | Shape::Plane { .. }) {
                    return Err(BuildError::BadPart {
                        item,
                        name: name.to_owned(),
                        part: i,
                        shape: p.shape.kind(),
                    });
                }
                let co = shape_builder(name, &p.shape)?
                    .position(Pose::from_parts(v3(p.position), quat(p.rotation)));
                Ok(with(co, p.material))
            })
            .collect(),
        single => Ok(vec![with(shape_builder(name, single)?, material)]),
    }
}

/// Inserts a body with its colliders (in part order: the insertion order is the scene's, so the
/// same scene gives the same world).
fn insert_body(
    world: &mut PhysicsWorld,
    rb: RigidBodyBuilder,
    colliders: Vec<ColliderBuilder>,
) -> RigidBodyHandle {
    let h = world.insert_body(rb);
    for co in colliders {
        world.insert_collider(co, Some(h));
    }
    h
}

/// A bound on any body's speed in the scene (m/s), from its energy: no body can move faster
/// than the fastest body's initial speed (its spin included, at its rim) plus what it gains
/// falling to the lowest static surface, with the margin the perturbations may add (α of a
/// velocity change). Without a floor, what gravity adds over the whole end time.
pub fn speed_bound(scene: &Scene) -> f64 {
    let s = &scene.settings;
    let g = perturb::norm(s.gravity);
    let up = if g > 0.0 {
        s.gravity.map(|x| -x / g)
    } else {
        [0.0, 1.0, 0.0]
    };
    let height = |p: [f64; 3]| p[0] * up[0] + p[1] * up[1] + p[2] * up[2];
    let floor = scene
        .statics
        .iter()
        .map(|st| match st.shape {
            Shape::Plane { .. } => height(st.position),
            _ => height(st.position) - st.shape.bounding_radius(),
        })
        .fold(f64::INFINITY, f64::min);
    let v_max = scene
        .bodies
        .iter()
        .map(|b| {
            let drop = if floor.is_finite() {
                (height(b.position) - floor).max(0.0)
            } else {
                0.5 * g * s.end_time * s.end_time
            };
            perturb::norm(b.linvel)
                + perturb::norm(b.angvel) * b.shape.bounding_radius()
                + (2.0 * g * drop).sqrt()
        })
        .fold(0.0, f64::max);
    v_max * (1.0 + s.alpha)
}

/// Which bodies can tunnel and need CCD (DESIGN: "CCD only for bodies that can tunnel"): the
/// `auto` CCD policy.
///
/// From [`speed_bound`]: an elastic hit can at most double that speed for the body it hits. A
/// body needs CCD when that speed carries it further than its own half-thickness (or the
/// thinnest static slab's) in one step.
pub fn ccd_bodies(scene: &Scene) -> Vec<bool> {
    let s = &scene.settings;
    // Planes and meshes are left out (as they always were), also as parts of a compound.
    let thinnest_static = scene
        .statics
        .iter()
        .flat_map(|st| st.shape.placed_parts(st.material))
        .filter(|part| !matches!(part.shape, Shape::Plane { .. } | Shape::TriMesh { .. }))
        .map(|part| part.shape.min_half_thickness())
        .fold(f64::INFINITY, f64::min);
    let step = 2.0 * speed_bound(scene) * s.dt;
    scene
        .bodies
        .iter()
        .map(|b| step > b.shape.min_half_thickness().min(thinnest_static))
        .collect()
}

/// A scene instance built in rapier.
pub struct SimWorld {
    pub world: PhysicsWorld,
    pub bodies: Vec<RigidBodyHandle>,
    pub gravity: V3,
    pub dt: f64,
    /// What the world was built with ([`SimPlan::of`] its scene).
    pub plan: SimPlan,
}

impl SimWorld {
    /// Builds only what the scene needs: statics, bodies (CCD where they can tunnel), joints if
    /// any. Insertion order is the scene order, so the same scene gives the same world.
    pub fn build(scene: &Scene) -> Result<Self, BuildError> {
        let s = &scene.settings;
        let mut world = PhysicsWorld::new();
        world.gravity = v3(s.gravity);
        world.integration_parameters.dt = s.dt as f32;
        let plan = SimPlan::of(scene);
        let ip = &mut world.integration_parameters;
        ip.num_solver_iterations = plan.substeps as usize;
        ip.num_internal_pgs_iterations = plan.iterations as usize;
        ip.num_internal_stabilization_iterations = plan.stabilization as usize;
        ip.length_unit = plan.length_unit as f32;
        // rapier scales these by the length unit; the plan's are in metres.
        ip.normalized_prediction_distance = (plan.prediction_distance / plan.length_unit) as f32;
        ip.normalized_max_linear_velocity = (plan.max_speed / plan.length_unit) as f32;
        for st in &scene.statics {
            let rb = RigidBodyBuilder::fixed()
                .pose(Pose::from_parts(v3(st.position), quat(st.rotation)));
            let co = colliders(scene, "static", &st.name, &st.shape, st.material)?;
            insert_body(&mut world, rb, co);
        }
        let mut bodies = Vec::with_capacity(scene.bodies.len());
        for ((b, &needs_ccd), &gyroscopic) in
            scene.bodies.iter().zip(&plan.ccd).zip(&plan.gyroscopic)
        {
            if !b.shape.can_be_dynamic() {
                return Err(BuildError::NotDynamic {
                    name: b.name.clone(),
                    shape: b.shape.kind(),
                });
            }
            let rb = RigidBodyBuilder::dynamic()
                .pose(Pose::from_parts(v3(b.position), quat(b.rotation)))
                .linvel(v3(b.linvel))
                .angvel(v3(b.angvel))
                .linear_damping(s.linear_damping as f32)
                .angular_damping(s.angular_damping as f32)
                .ccd_enabled(needs_ccd)
                .gyroscopic_forces_enabled(gyroscopic)
                .can_sleep(plan.sleep);
            let co = colliders(scene, "body", &b.name, &b.shape, b.material)?;
            let h = insert_body(&mut world, rb, co);
            if plan.length_unit > 1.0
                && let Some(body) = world.bodies.get_mut(h)
            {
                // rapier scales the threshold by the length unit; the plan's is in m/s.
                body.activation_mut().normalized_linear_threshold =
                    (plan.sleep_speed / plan.length_unit) as f32;
            }
            bodies.push(h);
        }
        if !scene.joints.is_empty() {
            // Joints to the world need a fixed anchor body (at the origin, so world-space
            // anchors are its local anchors).
            let anchor = world.bodies.insert(RigidBodyBuilder::fixed());
            let handle = |r: BodyRef| match r {
                BodyRef::World => anchor,
                BodyRef::Body(i) => bodies[i],
            };
            for j in &scene.joints {
                // Two bodies joined by a joint do not collide with each other (their shapes
                // usually overlap at the hinge): the same rule as our own stepper
                // (`mwb_reverse::joint`), so forward and backward worlds of a scene agree.
                let mut data: GenericJoint = match j.kind {
                    JointKind::Revolute { axis } => RevoluteJointBuilder::new(v3(axis).normalize())
                        .local_anchor1(v3(j.anchor1))
                        .local_anchor2(v3(j.anchor2))
                        .build()
                        .into(),
                    JointKind::Spherical => SphericalJointBuilder::new()
                        .local_anchor1(v3(j.anchor1))
                        .local_anchor2(v3(j.anchor2))
                        .build()
                        .into(),
                    JointKind::Fixed => FixedJointBuilder::new()
                        .local_anchor1(v3(j.anchor1))
                        .local_anchor2(v3(j.anchor2))
                        .build()
                        .into(),
                };
                data.set_contacts_enabled(false);
                world
                    .impulse_joints
                    .insert(handle(j.body1), handle(j.body2), data, true);
            }
        }
        Ok(Self {
            world,
            bodies,
            gravity: s.gravity,
            dt: s.dt,
            plan,
        })
    }

    /// A copy of this world that steps exactly as this one would from here: every set rapier
    /// keeps between steps (bodies, colliders, joints, islands, broad and narrow phase with
    /// their warm-start impulses) is cloned; the pipelines hold only scratch memory and start
    /// empty. Refinement forks its parent at the branch frame with it.
    pub fn fork(&self) -> Self {
        let w = &self.world;
        Self {
            world: PhysicsWorld {
                gravity: w.gravity,
                integration_parameters: w.integration_parameters,
                physics_pipeline: PhysicsPipeline::new(),
                collision_pipeline: CollisionPipeline::new(),
                islands: w.islands.clone(),
                broad_phase: w.broad_phase.clone(),
                narrow_phase: w.narrow_phase.clone(),
                bodies: w.bodies.clone(),
                colliders: w.colliders.clone(),
                impulse_joints: w.impulse_joints.clone(),
                multibody_joints: w.multibody_joints.clone(),
                soft_bodies: w.soft_bodies.clone(),
                ccd_solver: w.ccd_solver.clone(),
            },
            bodies: self.bodies.clone(),
            gravity: self.gravity,
            dt: self.dt,
            plan: self.plan.clone(),
        }
    }

    /// Body `i`'s pose as recorded (the simulator's `f32` values, widened exactly).
    pub fn pose(&self, i: usize) -> FramePose {
        frame_pose(self.world.bodies[self.bodies[i]].position())
    }

    /// Body `i`'s exact state.
    pub(crate) fn state(&self, i: usize) -> BodyState {
        let rb = &self.world.bodies[self.bodies[i]];
        BodyState {
            pose: *rb.position(),
            linvel: rb.linvel(),
            angvel: rb.angvel(),
            sleeping: rb.is_sleeping(),
            in_impact: false,
        }
    }
}

/// A rapier pose as a recorded frame pose (`f32` → `f64` is exact).
pub(crate) fn frame_pose(p: &Pose) -> FramePose {
    let q = p.rotation;
    FramePose {
        position: to_v3(p.translation),
        rotation: [
            f64::from(q.x),
            f64::from(q.y),
            f64::from(q.z),
            f64::from(q.w),
        ],
    }
}

/// One body's state at one frame exactly as the simulator holds it (`f32`): what refinement
/// needs of a parent world to fork it and to move its inactive bodies.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BodyState {
    pub pose: Pose,
    pub linvel: Vector,
    pub angvel: Vector,
    pub sleeping: bool,
    /// Whether the stepper counted the body as in an impact at this frame (§4.1.2: the contact
    /// part of its velocity change above `C_v` / `C_ω`, measured before the perturbation). A body
    /// that replays this motion counts its impacts from it, as the world it replays did.
    pub in_impact: bool,
}

/// Per-body state the stepper carries between steps.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Tracker {
    pub(crate) in_impact: bool,
    pub(crate) impacts: u32,
    /// The last step after which the body was above the rest thresholds.
    last_moving_step: Option<u64>,
    resting: bool,
}

/// A world being stepped: the simulator and everything the stepper carries from one step to the
/// next, so that a world can be continued from any frame ([`Progress::fork`]).
pub(crate) struct Progress {
    pub sim: SimWorld,
    pub trackers: Vec<Tracker>,
    /// Steps taken, which is the index of the frame the simulator holds.
    pub steps: u64,
    pub perturbations: u32,
    /// How long every body has been resting.
    pub rest_time: f64,
    pub rested: bool,
}

impl Progress {
    pub fn new(sim: SimWorld) -> Self {
        let n = sim.bodies.len();
        Self {
            sim,
            trackers: vec![Tracker::default(); n],
            steps: 0,
            perturbations: 0,
            rest_time: 0.0,
            rested: false,
        }
    }

    pub fn fork(&self) -> Self {
        Self {
            sim: self.sim.fork(),
            trackers: self.trackers.clone(),
            steps: self.steps,
            perturbations: self.perturbations,
            rest_time: self.rest_time,
            rested: self.rested,
        }
    }

    /// Per body, the time of the first frame from which it stayed resting (see
    /// [`WorldSummary::rest_time_s`]).
    pub(crate) fn rest_times(&self, dt: f64) -> Vec<f64> {
        // Frame k is recorded after step k: a body last moving after step k rests from frame
        // k + 1.
        self.trackers
            .iter()
            .map(|t| match t.last_moving_step {
                None => 0.0,
                Some(k) if t.resting => (k + 1) as f64 * dt,
                Some(_) => self.steps as f64 * dt,
            })
            .collect()
    }
}

/// A body the simulator does not move itself at a step: it follows a parent world's motion
/// (refinement's inactive set). Its velocities, sleep state and impacts are the parent's.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Followed {
    pub after: BodyState,
}

/// What distinguishes one kind of run from another inside the one stepping loop, so that a
/// refined world and its parent step through the same code.
pub(crate) trait StepHooks {
    /// Just before the step from frame `p.steps`.
    fn before_step(&mut self, _p: &mut Progress) {}
    /// `Some` when body `i` follows a parent's motion into frame `frame` instead of being
    /// simulated (then it is neither perturbed nor counted from the simulator's velocities).
    fn followed(&self, _i: usize, _frame: u64) -> Option<Followed> {
        None
    }
    /// Frame `p.steps` is complete (recorded by the hook, if it records).
    fn frame(&mut self, p: &Progress) -> Result<(), RunError>;
}

/// The stepping loop (§4.1.2): step, count impacts from the contact part of each body's velocity
/// change, perturb the simulated bodies, track rest; until every body has rested for
/// `rest_hold` or the scene's end time.
pub(crate) fn advance(
    scene: &Scene,
    p: &mut Progress,
    rng: &mut WorldRng,
    perturb_on: bool,
    hooks: &mut dyn StepHooks,
) -> Result<(), RunError> {
    let s = &scene.settings;
    let n = p.sim.bodies.len();
    let dt = s.dt;
    let max_steps = (s.end_time / dt).ceil() as u64;
    let mut before: Vec<(V3, V3)> = vec![([0.0; 3], [0.0; 3]); n];
    let zero = [0.0; 3];
    while p.steps < max_steps && !p.rested {
        hooks.before_step(p);
        for (i, h) in p.sim.bodies.iter().enumerate() {
            let rb = &p.sim.world.bodies[*h];
            before[i] = (to_v3(rb.linvel()), to_v3(rb.angvel()));
        }
        p.sim.world.step();
        p.steps += 1;

        let mut all_rest = true;
        for (i, before) in before.iter_mut().enumerate() {
            let tracker = &mut p.trackers[i];
            let (v, w, sleeping) = match hooks.followed(i, p.steps) {
                Some(f) => {
                    // The parent's own impacts: it measured them before its perturbation, which
                    // its recorded velocities already hold.
                    let hit = f.after.in_impact && !f.after.sleeping;
                    if hit && !tracker.in_impact {
                        tracker.impacts += 1;
                    }
                    tracker.in_impact = hit;
                    (
                        to_v3(f.after.linvel),
                        to_v3(f.after.angvel),
                        f.after.sleeping,
                    )
                }
                None => {
                    let rb = &mut p.sim.world.bodies[p.sim.bodies[i]];
                    let v = to_v3(rb.linvel());
                    let w = to_v3(rb.angvel());
                    if !rb.is_sleeping() {
                        // §4.1.2: the contact part of the velocity change, compared with C_v / C_ω.
                        let rate_v = perturb::impact_rate(before.0, v, p.sim.gravity, dt);
                        let rate_w = perturb::impact_rate(before.1, w, zero, dt);
                        let hit =
                            perturb::norm(rate_v) > s.c_v || perturb::norm(rate_w) > s.c_omega;
                        if hit && !tracker.in_impact {
                            tracker.impacts += 1;
                        }
                        tracker.in_impact = hit;
                        if perturb_on {
                            let dv = perturb::perturbation(
                                rate_v,
                                s.c_v,
                                dt,
                                s.alpha,
                                s.cos_exponent,
                                rng,
                            );
                            let dw = perturb::perturbation(
                                rate_w,
                                s.c_omega,
                                dt,
                                s.alpha,
                                s.cos_exponent,
                                rng,
                            );
                            if let Some(d) = dv {
                                rb.set_linvel(v3([v[0] + d[0], v[1] + d[1], v[2] + d[2]]), true);
                                p.perturbations += 1;
                            }
                            if let Some(d) = dw {
                                rb.set_angvel(v3([w[0] + d[0], w[1] + d[1], w[2] + d[2]]), true);
                                p.perturbations += 1;
                            }
                        }
                    } else {
                        tracker.in_impact = false;
                    }
                    (v, w, rb.is_sleeping())
                }
            };
            let resting =
                sleeping || (perturb::norm(v) < s.rest_linear && perturb::norm(w) < s.rest_angular);
            if !resting {
                tracker.last_moving_step = Some(p.steps);
            }
            tracker.resting = resting;
            all_rest &= resting;
        }

        hooks.frame(p)?;
        p.rest_time = if all_rest { p.rest_time + dt } else { 0.0 };
        if p.rest_time >= s.rest_hold - 1e-9 {
            p.rested = true;
        }
    }
    Ok(())
}

/// Turns recorded frames into [`Segment`]s: every `segment_seconds` of frames of the chosen
/// bodies become one self-contained codec world (or quantised frames), emitted at once.
pub(crate) struct Recorder<'a> {
    opts: RunOptions,
    frames_per_segment: usize,
    params: EncodeParams,
    dynamics: Option<RotationDynamics>,
    /// The frames of the segment being recorded, one track per body.
    pub pending: Vec<Track>,
    /// Frames recorded so far (the next frame's index).
    pub frame_count: u32,
    pub segment_count: u32,
    pub payload_bytes: u64,
    /// The bodies a segment carries (all, unless a refinement chooses).
    pub keep: Vec<bool>,
    emit: &'a mut dyn FnMut(Segment) -> ControlFlow<()>,
    observe: &'a mut dyn FnMut(&[Track]),
}

impl<'a> Recorder<'a> {
    pub fn new(
        scene: &Scene,
        sim: &SimWorld,
        opts: RunOptions,
        emit: &'a mut dyn FnMut(Segment) -> ControlFlow<()>,
        observe: &'a mut dyn FnMut(&[Track]),
    ) -> Self {
        let s = &scene.settings;
        let frames_per_segment = frames_per_segment(scene);
        Self {
            opts,
            frames_per_segment,
            params: EncodeParams::from_quality(opts.quality, s.dt, motion_model(scene)),
            dynamics: rotation_dynamics(scene, sim),
            pending: (0..sim.bodies.len())
                .map(|_| Track {
                    positions: Vec::with_capacity(frames_per_segment),
                    rotations: Vec::with_capacity(frames_per_segment),
                })
                .collect(),
            frame_count: 0,
            segment_count: 0,
            payload_bytes: 0,
            keep: vec![true; sim.bodies.len()],
            emit,
            observe,
        }
    }

    /// Appends one frame (one pose per body); a full segment is emitted at once.
    pub fn push(&mut self, poses: impl Iterator<Item = FramePose>) -> Result<(), RunError> {
        for (t, p) in self.pending.iter_mut().zip(poses) {
            t.positions.push(p.position);
            t.rotations.push(p.rotation);
        }
        self.frame_count += 1;
        if self.pending.first().map_or(0, Track::len) >= self.frames_per_segment {
            self.flush()?;
        }
        Ok(())
    }

    /// Emits the frames recorded since the last segment (nothing if there are none), with the
    /// bodies [`Recorder::keep`] selects; the segment lists them in [`Segment::bodies`] unless it
    /// has them all.
    pub fn flush(&mut self) -> Result<(), RunError> {
        let frame_count = self.pending.first().map_or(0, Track::len) as u32;
        if frame_count == 0 {
            return Ok(());
        }
        let chosen: Vec<usize> = (0..self.pending.len()).filter(|&b| self.keep[b]).collect();
        let all = chosen.len() == self.pending.len();
        let tracks: Vec<Track>;
        let (selected, dynamics): (&[Track], Option<RotationDynamics>) = if all {
            (&self.pending, self.dynamics.clone())
        } else {
            tracks = chosen.iter().map(|&b| self.pending[b].clone()).collect();
            let dynamics = self.dynamics.as_ref().map(|d| RotationDynamics {
                inertia: chosen
                    .iter()
                    .map(|&b| d.inertia.get(b).copied().flatten())
                    .collect(),
                ..d.clone()
            });
            (&tracks, dynamics)
        };
        let n = selected.len();
        let payload = match self.opts.encoding {
            // Each segment is its own codec world, so it decodes without its neighbours.
            PayloadEncoding::Spline => {
                encode_world_with_dynamics(selected, &self.params, dynamics.as_ref())?.bytes
            }
            PayloadEncoding::QuantisedFrames => {
                let frames = frame_count as usize;
                let poses: Vec<FramePose> = (0..frames)
                    .flat_map(|f| {
                        selected.iter().map(move |t| FramePose {
                            position: t.positions[f],
                            rotation: t.rotations[f],
                        })
                    })
                    .collect();
                mwb_core::frames::encode(&poses, n)?
            }
        };
        (self.observe)(selected);
        self.payload_bytes += payload.len() as u64;
        let seg = Segment {
            seq: self.segment_count,
            first_frame: self.frame_count - frame_count,
            frame_count,
            body_count: n as u32,
            bodies: if all {
                Vec::new()
            } else {
                chosen.iter().map(|&b| b as u32).collect()
            },
            payload,
            encoding: self.opts.encoding,
        };
        for t in self.pending.iter_mut() {
            t.positions.clear();
            t.rotations.clear();
        }
        self.segment_count += 1;
        match (self.emit)(seg) {
            ControlFlow::Continue(()) => Ok(()),
            ControlFlow::Break(()) => Err(RunError::Stopped),
        }
    }
}

/// Frames per recorded segment: `segment_seconds` of them, at least one.
pub fn frames_per_segment(scene: &Scene) -> usize {
    ((scene.settings.segment_seconds / scene.settings.dt).round() as usize).max(1)
}

/// Runs one world of `template` from `seed`: instantiate, build, step with perturbations until
/// everything rests (held for `rest_hold`) or `end_time`, emitting a [`Segment`] about every
/// `segment_seconds`. `emit` may stop the world by returning `ControlFlow::Break` (the job
/// closed); the world is then abandoned and nothing else is emitted.
///
/// Deterministic: the same binary, template and seed give the same segments byte for byte.
pub fn run_world(
    template: &SceneTemplate,
    seed: u64,
    opts: RunOptions,
    emit: &mut dyn FnMut(Segment) -> ControlFlow<()>,
) -> Result<WorldSummary, RunError> {
    run_world_observed(template, seed, opts, emit, &mut |_| {})
}

/// Records every frame of a root world.
struct RootHooks<'r, 'a> {
    rec: Option<&'r mut Recorder<'a>>,
}

impl StepHooks for RootHooks<'_, '_> {
    fn frame(&mut self, p: &Progress) -> Result<(), RunError> {
        match self.rec.as_deref_mut() {
            Some(rec) => rec.push((0..p.sim.bodies.len()).map(|i| p.sim.pose(i))),
            None => Ok(()),
        }
    }
}

/// [`run_world`], also handing `observe` the simulated poses of every segment (one [`Track`] per
/// body, full rate, before encoding), just before the segment is emitted. For tests and the codec
/// benchmark, which compare them with what the payload decodes to; the segments are the same.
pub fn run_world_observed(
    template: &SceneTemplate,
    seed: u64,
    opts: RunOptions,
    emit: &mut dyn FnMut(Segment) -> ControlFlow<()>,
    observe: &mut dyn FnMut(&[Track]),
) -> Result<WorldSummary, RunError> {
    let scene = template.instantiate(seed);
    let sim = SimWorld::build(&scene)?;
    let mut p = Progress::new(sim);
    let mut rng = WorldRng::new(seed, Stream::Perturbation);
    let mut rec = Recorder::new(&scene, &p.sim, opts, emit, observe);
    let n = p.sim.bodies.len();
    // Frame 0: the initial state.
    if opts.record {
        rec.push((0..n).map(|i| p.sim.pose(i)))?;
    }
    let mut hooks = RootHooks {
        rec: opts.record.then_some(&mut rec),
    };
    advance(&scene, &mut p, &mut rng, opts.perturb, &mut hooks)?;
    if opts.record {
        rec.flush()?;
    }
    Ok(summary_of(&p, &rec, seed, scene.settings.dt))
}

/// The summary of a finished world.
pub(crate) fn summary_of(p: &Progress, rec: &Recorder<'_>, seed: u64, dt: f64) -> WorldSummary {
    WorldSummary {
        seed,
        frame_count: rec.frame_count,
        segment_count: rec.segment_count,
        frame_dt: dt,
        rested: p.rested,
        impacts: p.trackers.iter().map(|t| t.impacts).collect(),
        rest_time_s: p.rest_times(dt),
        body_rested: p.trackers.iter().map(|t| t.resting).collect(),
        perturbations: p.perturbations,
        steps: p.steps,
        payload_bytes: rec.payload_bytes,
        sim: p.sim.plan.describe(),
    }
}
