//! One world: a scene instance in rapier3d, stepped with §4.1.2 perturbations, recorded.
//!
//! This module is pure computation (no bus, no async): [`run_world`] turns `(scene, seed)` into
//! motion segments and a summary, deterministically. The node around it only ships the bytes.
//!
//! Recording: every ~1 s of frames becomes one [`Segment`] whose payload is a self-contained
//! `mwb-codec` world stream (§4.3; one track per body, decodable without its neighbours) and
//! whose low-resolution path travels beside it.

use mwb_codec::{
    EncodeParams, LowResPath, MotionModel, Quality, RotationDynamics, Track,
    encode_world_with_dynamics,
};
use mwb_core::frames::Pose as FramePose;
use mwb_core::perturb::{self, V3};
use mwb_core::rng::{Stream, WorldRng};
use mwb_core::scene::{BodyRef, JointKind, Scene, SceneTemplate, Shape};
use rapier3d::na::Unit;
use rapier3d::prelude::*;
use std::ops::ControlFlow;

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
    /// An `mwb-codec` world stream of this segment's frames, one object per body in scene order
    /// (`ENCODING_SPLINE_V1` on the wire).
    pub payload: Vec<u8>,
    /// The few-Hz path of each body over this segment (frames relative to `first_frame`).
    pub lowres: Vec<LowResPath>,
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
    })
}

/// Which bodies can tunnel and need CCD (DESIGN: "CCD only for bodies that can tunnel").
///
/// A conservative energy bound: no body in the scene can move faster than the fastest body's
/// initial speed plus what it gains falling to the lowest static surface; an elastic hit can at
/// most double that for the body it hits. A body needs CCD when that speed carries it further
/// than its own half-thickness (or the thinnest static slab's) in one step.
pub fn ccd_bodies(scene: &Scene) -> Vec<bool> {
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
    let thinnest_static = scene
        .statics
        .iter()
        .filter(|st| !matches!(st.shape, Shape::Plane { .. } | Shape::TriMesh { .. }))
        .map(|st| st.shape.min_half_thickness())
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
    // Perturbations add at most α of a velocity change: include that margin too.
    let step = 2.0 * v_max * (1.0 + s.alpha) * s.dt;
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
}

impl SimWorld {
    /// Builds only what the scene needs: statics, bodies (CCD where they can tunnel), joints if
    /// any. Insertion order is the scene order, so the same scene gives the same world.
    pub fn build(scene: &Scene) -> Result<Self, BuildError> {
        let s = &scene.settings;
        let mut world = PhysicsWorld::new();
        world.gravity = v3(s.gravity);
        world.integration_parameters.dt = s.dt as f32;
        world.integration_parameters.num_solver_iterations = (s.solver_iterations as usize).max(1);
        let material = |i: usize| &scene.materials[i];
        for st in &scene.statics {
            let m = material(st.material);
            let rb = RigidBodyBuilder::fixed()
                .pose(Pose::from_parts(v3(st.position), quat(st.rotation)));
            let co = shape_builder(&st.name, &st.shape)?
                .friction(m.friction as f32)
                .restitution(m.restitution as f32)
                .density(m.density as f32);
            world.insert(rb, co);
        }
        let ccd = ccd_bodies(scene);
        let mut bodies = Vec::with_capacity(scene.bodies.len());
        for (b, needs_ccd) in scene.bodies.iter().zip(ccd) {
            if !b.shape.can_be_dynamic() {
                return Err(BuildError::NotDynamic {
                    name: b.name.clone(),
                    shape: match b.shape {
                        Shape::Plane { .. } => "plane",
                        _ => "trimesh",
                    },
                });
            }
            let m = material(b.material);
            let rb = RigidBodyBuilder::dynamic()
                .pose(Pose::from_parts(v3(b.position), quat(b.rotation)))
                .linvel(v3(b.linvel))
                .angvel(v3(b.angvel))
                .linear_damping(s.linear_damping as f32)
                .angular_damping(s.angular_damping as f32)
                .ccd_enabled(needs_ccd);
            let co = shape_builder(&b.name, &b.shape)?
                .friction(m.friction as f32)
                .restitution(m.restitution as f32)
                .density(m.density as f32);
            let (h, _) = world.insert(rb, co);
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
        })
    }

    /// Appends every body's current pose to its track.
    fn record(&self, tracks: &mut [Track]) {
        for (i, t) in tracks.iter_mut().enumerate() {
            let p = self.pose(i);
            t.positions.push(p.position);
            t.rotations.push(p.rotation);
        }
    }

    fn pose(&self, i: usize) -> FramePose {
        let rb = &self.world.bodies[self.bodies[i]];
        let p = rb.position();
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
}

/// Per-body state the stepper carries between steps.
struct Tracker {
    in_impact: bool,
    impacts: u32,
    /// The last step after which the body was above the rest thresholds.
    last_moving_step: Option<u64>,
    resting: bool,
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
    let mut sim = SimWorld::build(&scene)?;
    let s = &scene.settings;
    let n = sim.bodies.len();
    let dt = s.dt;
    let mut rng = WorldRng::new(seed, Stream::Perturbation);
    let frames_per_segment = ((s.segment_seconds / dt).round() as usize).max(1);
    let max_steps = (s.end_time / dt).ceil() as u64;

    let mut trackers: Vec<Tracker> = (0..n)
        .map(|_| Tracker {
            in_impact: false,
            impacts: 0,
            last_moving_step: None,
            resting: false,
        })
        .collect();
    let params = EncodeParams::from_quality(opts.quality, dt, motion_model(&scene));
    let dynamics = rotation_dynamics(&scene, &sim);
    // The frames of the segment being recorded, one track per body.
    let mut pending: Vec<Track> = (0..n)
        .map(|_| Track {
            positions: Vec::with_capacity(frames_per_segment),
            rotations: Vec::with_capacity(frames_per_segment),
        })
        .collect();
    let mut summary = WorldSummary {
        seed,
        frame_count: 0,
        segment_count: 0,
        frame_dt: dt,
        rested: false,
        impacts: Vec::new(),
        rest_time_s: Vec::new(),
        body_rested: Vec::new(),
        perturbations: 0,
        steps: 0,
        payload_bytes: 0,
    };
    let mut flush = |pending: &mut [Track], summary: &mut WorldSummary| {
        let frame_count = pending.first().map_or(0, Track::len) as u32;
        if frame_count == 0 {
            return Ok(());
        }
        let (payload, lowres) = match opts.encoding {
            // Each segment is its own codec world, so it decodes without its neighbours.
            PayloadEncoding::Spline => {
                let encoded = encode_world_with_dynamics(pending, &params, dynamics.as_ref())?;
                (encoded.bytes, encoded.lowres)
            }
            PayloadEncoding::QuantisedFrames => {
                let frames = frame_count as usize;
                let poses: Vec<FramePose> = (0..frames)
                    .flat_map(|f| {
                        pending.iter().map(move |t| FramePose {
                            position: t.positions[f],
                            rotation: t.rotations[f],
                        })
                    })
                    .collect();
                let lowres = pending
                    .iter()
                    .map(|t| {
                        LowResPath::from_positions(&t.positions, dt, mwb_codec::DEFAULT_LOWRES_HZ)
                    })
                    .collect();
                (mwb_core::frames::encode(&poses, n)?, lowres)
            }
        };
        observe(pending);
        summary.payload_bytes += payload.len() as u64;
        let seg = Segment {
            seq: summary.segment_count,
            first_frame: summary.frame_count - frame_count,
            frame_count,
            body_count: n as u32,
            payload,
            lowres,
            encoding: opts.encoding,
        };
        for t in pending.iter_mut() {
            t.positions.clear();
            t.rotations.clear();
        }
        summary.segment_count += 1;
        match emit(seg) {
            ControlFlow::Continue(()) => Ok(()),
            ControlFlow::Break(()) => Err(RunError::Stopped),
        }
    };

    // Frame 0: the initial state.
    if opts.record {
        sim.record(&mut pending);
        summary.frame_count += 1;
    }
    let mut before: Vec<(V3, V3)> = vec![([0.0; 3], [0.0; 3]); n];
    let mut rest_time = 0.0;
    let zero = [0.0; 3];
    while summary.steps < max_steps {
        for (i, h) in sim.bodies.iter().enumerate() {
            let rb = &sim.world.bodies[*h];
            before[i] = (to_v3(rb.linvel()), to_v3(rb.angvel()));
        }
        sim.world.step();
        summary.steps += 1;

        let mut all_rest = true;
        for (i, h) in sim.bodies.iter().enumerate() {
            let rb = &mut sim.world.bodies[*h];
            let v = to_v3(rb.linvel());
            let w = to_v3(rb.angvel());
            if !rb.is_sleeping() {
                // §4.1.2: the contact part of the velocity change, compared with C_v / C_ω.
                let rate_v = perturb::impact_rate(before[i].0, v, sim.gravity, dt);
                let rate_w = perturb::impact_rate(before[i].1, w, zero, dt);
                let hit = perturb::norm(rate_v) > s.c_v || perturb::norm(rate_w) > s.c_omega;
                if hit && !trackers[i].in_impact {
                    trackers[i].impacts += 1;
                }
                trackers[i].in_impact = hit;
                if opts.perturb {
                    let dv =
                        perturb::perturbation(rate_v, s.c_v, dt, s.alpha, s.cos_exponent, &mut rng);
                    let dw = perturb::perturbation(
                        rate_w,
                        s.c_omega,
                        dt,
                        s.alpha,
                        s.cos_exponent,
                        &mut rng,
                    );
                    if let Some(d) = dv {
                        rb.set_linvel(v3([v[0] + d[0], v[1] + d[1], v[2] + d[2]]), true);
                        summary.perturbations += 1;
                    }
                    if let Some(d) = dw {
                        rb.set_angvel(v3([w[0] + d[0], w[1] + d[1], w[2] + d[2]]), true);
                        summary.perturbations += 1;
                    }
                }
            } else {
                trackers[i].in_impact = false;
            }
            let resting = rb.is_sleeping()
                || (perturb::norm(v) < s.rest_linear && perturb::norm(w) < s.rest_angular);
            if !resting {
                trackers[i].last_moving_step = Some(summary.steps);
            }
            trackers[i].resting = resting;
            all_rest &= resting;
        }

        if opts.record {
            sim.record(&mut pending);
            summary.frame_count += 1;
            if pending.first().map_or(0, Track::len) >= frames_per_segment {
                flush(&mut pending, &mut summary)?;
            }
        }
        rest_time = if all_rest { rest_time + dt } else { 0.0 };
        if rest_time >= s.rest_hold - 1e-9 {
            summary.rested = true;
            break;
        }
    }
    if opts.record {
        flush(&mut pending, &mut summary)?;
    }
    summary.impacts = trackers.iter().map(|t| t.impacts).collect();
    // Frame k is recorded after step k: a body last moving after step k rests from frame k + 1.
    summary.rest_time_s = trackers
        .iter()
        .map(|t| match t.last_moving_step {
            None => 0.0,
            Some(k) if t.resting => (k + 1) as f64 * dt,
            Some(_) => summary.steps as f64 * dt,
        })
        .collect();
    summary.body_rested = trackers.iter().map(|t| t.resting).collect();
    Ok(summary)
}
