//! The simulated world and the pieces shared by the forward and the backward step: parameters,
//! reports, per-island LCP assembly and the semi-implicit position update (3.17)–(3.18).

use nalgebra::{DMatrix, Matrix3, UnitQuaternion, Vector3};

use crate::body::{Body, StaticBody};
use crate::contact::{ContactSet, JacobianRow, NarrowPhase};
use crate::joint::{Joint, JointError, JointRow, JointType};
use crate::lcp::{LcpOptions, LcpStatus};

/// Default restitution cutoff `ε` (§3.5): an approach slower than this is treated as inelastic.
pub const DEFAULT_RESTITUTION_CUTOFF: f64 = 0.1;
/// Default `δ ≪ ε` of (5.1): contact velocities below it count as zero when stepping backward.
pub const DEFAULT_REST_THRESHOLD: f64 = 1e-5;
/// Default contact prediction distance (m): points closer than this enter the LCP. Kept tiny,
/// because the velocity-level conditions treat a predicted point as touching.
pub const DEFAULT_PREDICTION: f64 = 1e-5;
/// Default Baumgarte factor `β` of the joint rows (§5.3.4): the fraction of a joint's position
/// error a step removes.
pub const DEFAULT_JOINT_ERP: f64 = 0.2;

/// Stepper settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepParams {
    /// `ε`: restitution applies only when the incoming normal speed exceeds it (§3.5).
    pub restitution_cutoff: f64,
    /// `δ` of (5.1): below it a contact velocity is "zero" (resting, not sliding).
    pub rest_threshold: f64,
    /// Contact prediction distance.
    pub prediction: f64,
    /// Baumgarte factor `β ∈ [0, 1)` of the joint rows: a forward step asks `J v⁺ = −β e / Δt`
    /// of a joint with position error `e`, a backward step `J v⁻ = +β e / Δt` (§5.3.4).
    pub joint_erp: f64,
    /// LCP solver settings.
    pub lcp: LcpOptions,
}

impl Default for StepParams {
    fn default() -> Self {
        Self {
            restitution_cutoff: DEFAULT_RESTITUTION_CUTOFF,
            rest_threshold: DEFAULT_REST_THRESHOLD,
            prediction: DEFAULT_PREDICTION,
            joint_erp: DEFAULT_JOINT_ERP,
            // Stacks of boxes give redundant contact rows (four coplanar corners per face);
            // the pivoting path then gets stuck more often and another row order helps.
            lcp: LcpOptions {
                restarts: 10,
                ..LcpOptions::default()
            },
        }
    }
}

/// Impulses of one contact in the forward sense (what the forward step applies), N·s.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ContactImpulse {
    /// Along the normal (≥ 0).
    pub normal: f64,
    /// Along `tangent_u`.
    pub tangent_u: f64,
    /// Along `tangent_w`.
    pub tangent_w: f64,
    /// Rolling-friction torque impulses (N·m·s) about [`crate::Contact::rolling_axes`]
    /// (zero for contacts without rolling rows).
    pub rolling: [f64; 3],
}

/// How one island's LCP went.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IslandSolve {
    /// Solver status.
    pub status: LcpStatus,
    /// Complementarity residual of the returned impulses.
    pub residual: f64,
    /// Number of LCP rows.
    pub rows: usize,
    /// Pivots taken.
    pub pivots: usize,
}

/// What a forward step did.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct StepReport {
    /// The contact set and Jacobian directions used.
    pub contacts: ContactSet,
    /// One entry per contact of `contacts`.
    pub impulses: Vec<ContactImpulse>,
    /// Joint impulses (Lagrange multipliers), one per row of `contacts.joints`.
    pub joint_impulses: Vec<f64>,
    /// One entry per island.
    pub islands: Vec<IslandSolve>,
    /// Shape pairs parry could not handle (skipped).
    pub unsupported_pairs: usize,
    /// Bodies disabled in this step because their state became non-finite.
    pub disabled: Vec<usize>,
}

impl StepReport {
    /// True when every island's LCP was solved and nothing was disabled or skipped.
    pub fn all_solved(&self) -> bool {
        self.islands.iter().all(|s| s.status.is_solution())
            && self.disabled.is_empty()
            && self.unsupported_pairs == 0
    }
}

/// A world of dynamic bodies and static geometry.
#[derive(Debug, Clone)]
pub struct World {
    /// Dynamic bodies.
    pub bodies: Vec<Body>,
    /// Static geometry.
    pub statics: Vec<StaticBody>,
    /// Joints (§5.3.4); add them with [`World::add_joint`], which checks them.
    pub joints: Vec<Joint>,
    /// Gravitational acceleration.
    pub gravity: Vector3<f64>,
    /// Stepper settings.
    pub params: StepParams,
    pub(crate) narrow_phase: NarrowPhase,
}

impl Default for World {
    fn default() -> Self {
        Self::new()
    }
}

impl World {
    /// An empty world with gravity `(0, 0, −9.81)` and default parameters.
    pub fn new() -> Self {
        Self {
            bodies: Vec::new(),
            statics: Vec::new(),
            joints: Vec::new(),
            gravity: Vector3::new(0.0, 0.0, -9.81),
            params: StepParams::default(),
            narrow_phase: NarrowPhase::default(),
        }
    }

    /// Adds a body; returns its index.
    pub fn add_body(&mut self, body: Body) -> usize {
        self.bodies.push(body);
        self.bodies.len() - 1
    }

    /// Adds static geometry; returns its index.
    pub fn add_static(&mut self, body: StaticBody) -> usize {
        self.statics.push(body);
        self.statics.len() - 1
    }

    /// Adds a joint after checking it against the bodies; returns its index.
    pub fn add_joint(&mut self, joint: Joint) -> Result<usize, JointError> {
        joint.validate(self.bodies.len())?;
        self.joints.push(joint);
        Ok(self.joints.len() - 1)
    }

    /// A joint between `body1` and `body2` (`None`: the world) at the world point `point`,
    /// given in the world frame at the bodies' current poses: local anchors (and axes) are
    /// computed from them, and a fixed joint keeps the current relative orientation.
    pub fn joint_at(
        &self,
        kind: JointType,
        body1: usize,
        body2: Option<usize>,
        point: Vector3<f64>,
    ) -> Result<Joint, JointError> {
        let len = self.bodies.len();
        let out = |which, index| JointError::BodyOutOfRange { which, index, len };
        let b1 = self.bodies.get(body1).ok_or(out("body1", body1))?;
        let b2 = match body2 {
            Some(i) => Some(self.bodies.get(i).ok_or(out("body2", i))?),
            None => None,
        };
        if !point.iter().all(|x| x.is_finite()) {
            return Err(JointError::NonFinite("point"));
        }
        let local = |b: Option<&Body>, p: Vector3<f64>| match b {
            Some(b) => b.orientation.inverse() * (p - b.position),
            None => p,
        };
        let anchors = (local(Some(b1), point), local(b2, point));
        let q2 = b2.map_or(UnitQuaternion::identity(), |b| b.orientation);
        let joint = match kind {
            JointType::Spherical => Joint::spherical(body1, body2, anchors.0, anchors.1),
            JointType::Revolute { axis } => Joint::revolute(
                body1,
                body2,
                anchors,
                (b1.orientation.inverse() * axis, q2.inverse() * axis),
            )?,
            JointType::Fixed => Joint::fixed(body1, body2, anchors, b1.orientation.inverse() * q2),
        };
        joint.validate(len)?;
        Ok(joint)
    }

    /// The rows of every joint at the current poses (no recorded goals).
    pub fn joint_rows(&self) -> Vec<JointRow> {
        self.joints
            .iter()
            .enumerate()
            .flat_map(|(i, j)| j.rows(i, &self.bodies))
            .collect()
    }

    /// Contacts at the current poses (default tangents) and joint rows, with islands. Updates
    /// the persistent manifolds. The second value counts shape pairs parry could not handle.
    pub fn detect_contacts(&mut self) -> (ContactSet, usize) {
        let (mut contacts, unsupported) =
            self.narrow_phase
                .detect(&self.bodies, &self.statics, self.params.prediction);
        // Two bodies joined by a joint do not collide (as in ODE): their contacts would only
        // repeat what the joint rows hold, and make the LCP degenerate.
        if !self.joints.is_empty() {
            let joined: std::collections::BTreeSet<(usize, usize)> = self
                .joints
                .iter()
                .filter_map(|j| j.body2.map(|b| (j.body1.min(b), j.body1.max(b))))
                .collect();
            contacts.retain(|c| match c.partner {
                crate::Partner::Body(p) => !joined.contains(&(c.body.min(p), c.body.max(p))),
                crate::Partner::Static(_) => true,
            });
        }
        let joints = self.joint_rows();
        (
            ContactSet::with_joints(contacts, joints, self.bodies.len()),
            unsupported,
        )
    }

    /// Pushes penetrating bodies apart, positions only: every contact of `contacts` deeper
    /// than `slop` plus `dt` × its point's speed ([`crate::Contact::point_speed`], one step's
    /// travel without continuous collision detection) is moved out to that depth along its
    /// normal, shared between its two bodies in proportion to their inverse masses (statics and
    /// disabled bodies do not move), by `iterations` Gauss–Seidel sweeps (a body in several
    /// contacts is settled against all of them). Velocities are untouched, so no kinetic energy
    /// is added; the bodies rise by at most the depth removed. Each contact's `dist` is updated
    /// to the bodies' new positions (exact for a translation, which is all this does; contact
    /// points are left). Returns the largest displacement (m).
    ///
    /// The stepper has no position correction of its own (every condition is on velocities),
    /// so a backward step whose contact appeared only at the earlier poses keeps the overlap;
    /// forward engines correct it the same way (split impulses, post-stabilisation).
    pub fn depenetrate(
        &mut self,
        contacts: &mut ContactSet,
        slop: f64,
        dt: f64,
        iterations: usize,
    ) -> f64 {
        if !(slop.is_finite() && slop >= 0.0) {
            return 0.0;
        }
        let dt = if dt.is_finite() { dt.max(0.0) } else { 0.0 };
        let allowed: Vec<f64> = contacts
            .contacts
            .iter()
            .map(|c| slop + dt * c.point_speed(&self.bodies))
            .collect();
        let weight = |b: &Body| {
            if b.enabled && b.inv_mass.is_finite() {
                b.inv_mass.max(0.0)
            } else {
                0.0
            }
        };
        let mut moved = vec![Vector3::zeros(); self.bodies.len()];
        let shift = |moved: &[Vector3<f64>], c: &crate::Contact| {
            let own = moved.get(c.body).copied().unwrap_or_default();
            let other = match c.partner {
                crate::Partner::Body(p) => moved.get(p).copied().unwrap_or_default(),
                crate::Partner::Static(_) => Vector3::zeros(),
            };
            c.normal.dot(&(own - other))
        };
        for _ in 0..iterations {
            let mut any = false;
            for (c, allowed) in contacts.contacts.iter().zip(&allowed) {
                let depth = -(c.dist + shift(&moved, c)) - allowed;
                if !(depth > 0.0 && depth.is_finite()) {
                    continue;
                }
                let w1 = self.bodies.get(c.body).map_or(0.0, weight);
                let w2 = match c.partner {
                    crate::Partner::Body(p) => self.bodies.get(p).map_or(0.0, weight),
                    crate::Partner::Static(_) => 0.0,
                };
                let total = w1 + w2;
                if total <= 0.0 {
                    continue;
                }
                if let Some(m) = moved.get_mut(c.body) {
                    *m += c.normal * (depth * w1 / total);
                }
                if let crate::Partner::Body(p) = c.partner
                    && let Some(m) = moved.get_mut(p)
                {
                    *m -= c.normal * (depth * w2 / total);
                }
                any = true;
            }
            if !any {
                break;
            }
        }
        for c in &mut contacts.contacts {
            c.dist += shift(&moved, c);
        }
        let mut largest = 0.0f64;
        for (b, m) in self.bodies.iter_mut().zip(&moved) {
            if m.iter().all(|x| x.is_finite()) {
                b.position += m;
                largest = largest.max(m.norm());
            }
        }
        largest
    }

    /// The largest anchor separation (m) of the world's joints at the current poses.
    pub fn joint_separation(&self) -> f64 {
        crate::joint::max_separation(&self.joints, &self.bodies)
    }

    /// The largest angular error (rad) of the world's revolute and fixed joints.
    pub fn joint_angular_error(&self) -> f64 {
        crate::joint::max_angular_error(&self.joints, &self.bodies)
    }

    /// Total kinetic energy.
    pub fn kinetic_energy(&self) -> f64 {
        self.bodies.iter().map(Body::kinetic_energy).sum()
    }

    /// Total kinetic plus gravitational potential energy.
    pub fn energy(&self) -> f64 {
        self.bodies
            .iter()
            .map(|b| b.kinetic_energy() - b.position.dot(&self.gravity) / b.inv_mass)
            .sum()
    }
}

/// Per-body inverse mass data at the pose where the Jacobian is taken.
#[derive(Debug, Clone, Copy)]
pub(crate) struct InvMass {
    pub(crate) inv_mass: f64,
    pub(crate) inv_inertia: Matrix3<f64>,
}

impl InvMass {
    pub(crate) fn of(body: &Body) -> Self {
        Self {
            inv_mass: if body.enabled { body.inv_mass } else { 0.0 },
            inv_inertia: if body.enabled {
                body.world_inv_inertia()
            } else {
                Matrix3::zeros()
            },
        }
    }

    /// `M⁻¹ j` for one body's 6-vector.
    pub(crate) fn apply(&self, j: &[f64; 6]) -> [f64; 6] {
        let ang = self.inv_inertia * Vector3::new(j[3], j[4], j[5]);
        [
            self.inv_mass * j[0],
            self.inv_mass * j[1],
            self.inv_mass * j[2],
            ang.x,
            ang.y,
            ang.z,
        ]
    }
}

/// A body's generalized velocity `(v, ω)`.
pub(crate) fn velocity6(body: &Body) -> [f64; 6] {
    [
        body.linvel.x,
        body.linvel.y,
        body.linvel.z,
        body.angvel.x,
        body.angvel.y,
        body.angvel.z,
    ]
}

fn dot6(a: &[f64; 6], b: &[f64; 6]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// An impulse direction (column of `Jᵀ`, possibly with sliding friction folded in) premultiplied
/// by `M⁻¹`: the velocity change per unit impulse, per body.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Response {
    pub(crate) a: (usize, [f64; 6]),
    pub(crate) b: Option<(usize, [f64; 6])>,
}

impl Response {
    pub(crate) fn new(dir: &JacobianRow, inv: &[InvMass]) -> Self {
        Self {
            a: (dir.a.0, inv[dir.a.0].apply(&dir.a.1)),
            b: dir.b.map(|(i, j)| (i, inv[i].apply(&j))),
        }
    }

    /// Adds `scale ×` this response to the velocities.
    pub(crate) fn add_to(&self, scale: f64, vel: &mut [[f64; 6]]) {
        for (i, r) in std::iter::once(&self.a).chain(self.b.as_ref()) {
            for (v, d) in vel[*i].iter_mut().zip(r) {
                *v += scale * d;
            }
        }
    }
}

/// `J_row · v` over generalized body velocities.
pub(crate) fn row_velocity(row: &JacobianRow, vel: &[[f64; 6]]) -> f64 {
    dot6(&row.a.1, &vel[row.a.0]) + row.b.map_or(0.0, |(i, j)| dot6(&j, &vel[i]))
}

/// `A_ij = J_i M⁻¹ G_jᵀ` (3.13)–(3.14), with `G_j` the impulse direction of unknown `j`.
pub(crate) fn delassus(rows: &[JacobianRow], responses: &[Response]) -> DMatrix<f64> {
    let n = rows.len();
    DMatrix::from_fn(n, n, |i, j| {
        let row = &rows[i];
        let resp = &responses[j];
        let mut sum = 0.0;
        for (bi, ji) in std::iter::once(&row.a).chain(row.b.as_ref()) {
            for (bj, rj) in std::iter::once(&resp.a).chain(resp.b.as_ref()) {
                if bi == bj {
                    sum += dot6(ji, rj);
                }
            }
        }
        sum
    })
}

/// Writes generalized velocities back into the bodies.
pub(crate) fn store_velocities(bodies: &mut [Body], vel: &[[f64; 6]]) {
    for (b, v) in bodies.iter_mut().zip(vel) {
        if b.enabled {
            b.linvel = Vector3::new(v[0], v[1], v[2]);
            b.angvel = Vector3::new(v[3], v[4], v[5]);
        }
    }
}

/// Orientation after rotating by `ω Δt` in the world frame (3.18), renormalised.
pub(crate) fn rotate(
    q: &UnitQuaternion<f64>,
    angvel: &Vector3<f64>,
    dt: f64,
) -> UnitQuaternion<f64> {
    UnitQuaternion::new_normalize((UnitQuaternion::from_scaled_axis(angvel * dt) * q).into_inner())
}
