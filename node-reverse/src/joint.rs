//! Joints as equality rows of the step's LCP (§5.3.4).
//!
//! The LCP formulation takes joints as extra unknowns next to the contact impulses: one
//! Lagrange multiplier per constrained direction, each an unbounded (equality) row of the same
//! mixed LCP, so that a jointed body resting on the ground is one island and one solve with its
//! contacts. Per joint:
//!
//! * [`JointKind::Spherical`]: the two anchor points coincide (3 linear rows);
//! * [`JointKind::Revolute`]: plus the hinge axes of the two bodies stay parallel (2 angular
//!   rows about the directions perpendicular to the axis);
//! * [`JointKind::Fixed`]: plus the relative orientation is kept (3 angular rows).
//!
//! A row asks for a relative velocity `J v` after the step. With `e` the joint's position error
//! along the row (anchor separation, axis misalignment, orientation error) at the poses where
//! the Jacobian is taken and `β` = [`crate::StepParams::joint_erp`], the forward step asks for
//! `J v⁺ = −β e / Δt` (Baumgarte stabilisation): the semi-implicit position update then shrinks
//! the error by the factor `1 − β` per step. Stepping backward, the next poses are
//! `x − Δt v⁻`, so the same correction needs the opposite sign, `J v⁻ = +β e / Δt`: the
//! authors' one change to the formulation for backward simulation of jointed bodies — joint
//! error must decrease as time runs backward, not grow (§5.3.4).

use nalgebra::{UnitQuaternion, Vector3};

use crate::body::Body;
use crate::contact::{JacobianRow, default_tangents};

/// What a joint constrains. Vectors are in the local frames of the bodies (centre of mass at
/// the origin, as [`Body::position`]); a world end has the identity frame at the origin.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum JointKind {
    /// Ball and socket: the anchors coincide.
    Spherical,
    /// Hinge: the anchors coincide and `axis1` (body 1's frame) stays parallel to `axis2`
    /// (the second end's frame). Unit vectors.
    Revolute {
        /// Hinge axis in body 1's frame.
        axis1: Vector3<f64>,
        /// Hinge axis in the second end's frame.
        axis2: Vector3<f64>,
    },
    /// Weld: the anchors coincide and `orientation1⁻¹ · orientation2` stays `rotation`.
    Fixed {
        /// The kept relative rotation.
        rotation: UnitQuaternion<f64>,
    },
}

impl JointKind {
    /// Number of LCP rows (constrained degrees of freedom).
    pub fn rows(&self) -> usize {
        match self {
            Self::Spherical => 3,
            Self::Revolute { .. } => 5,
            Self::Fixed { .. } => 6,
        }
    }
}

/// A joint between dynamic body `body1` and dynamic body `body2`, or the world (`None`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Joint {
    /// What is constrained.
    pub kind: JointKind,
    /// First body (index into `World::bodies`).
    pub body1: usize,
    /// Second body, or `None` for the world.
    pub body2: Option<usize>,
    /// Anchor in body 1's frame, relative to its centre of mass.
    pub anchor1: Vector3<f64>,
    /// Anchor in body 2's frame relative to its centre of mass, or in world coordinates.
    pub anchor2: Vector3<f64>,
}

/// A joint's kind given in the world frame at the current poses, for [`crate::World::joint_at`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum JointType {
    /// Ball and socket.
    Spherical,
    /// Hinge about `axis` (world frame, any length > 0).
    Revolute {
        /// Hinge axis.
        axis: Vector3<f64>,
    },
    /// Weld at the current relative pose.
    Fixed,
}

/// Why a joint was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum JointError {
    /// A body index past the end of `World::bodies`.
    #[error("{which} = {index} is out of range ({len} bodies)")]
    BodyOutOfRange {
        /// `"body1"` or `"body2"`.
        which: &'static str,
        /// Index given.
        index: usize,
        /// Number of bodies.
        len: usize,
    },
    /// Both ends are the world.
    #[error("a joint needs a dynamic body at one end at least")]
    NoBody,
    /// Both ends are the same body.
    #[error("body1 and body2 are both body {0}")]
    SameBody(usize),
    /// NaN or ±∞ in an anchor, axis or rotation.
    #[error("{0} is not finite")]
    NonFinite(&'static str),
    /// A hinge axis of (numerically) zero length.
    #[error("{0} must be a nonzero direction")]
    ZeroAxis(&'static str),
}

impl Joint {
    /// A ball-and-socket joint.
    pub fn spherical(
        body1: usize,
        body2: Option<usize>,
        anchor1: Vector3<f64>,
        anchor2: Vector3<f64>,
    ) -> Self {
        Self {
            kind: JointKind::Spherical,
            body1,
            body2,
            anchor1,
            anchor2,
        }
    }

    /// A hinge; the axes are normalised.
    pub fn revolute(
        body1: usize,
        body2: Option<usize>,
        (anchor1, anchor2): (Vector3<f64>, Vector3<f64>),
        (axis1, axis2): (Vector3<f64>, Vector3<f64>),
    ) -> Result<Self, JointError> {
        let unit = |a: Vector3<f64>, what| {
            if !a.iter().all(|x| x.is_finite()) {
                return Err(JointError::NonFinite(what));
            }
            a.try_normalize(1e-12).ok_or(JointError::ZeroAxis(what))
        };
        Ok(Self {
            kind: JointKind::Revolute {
                axis1: unit(axis1, "axis1")?,
                axis2: unit(axis2, "axis2")?,
            },
            body1,
            body2,
            anchor1,
            anchor2,
        })
    }

    /// A weld keeping `orientation1⁻¹ · orientation2 = rotation`.
    pub fn fixed(
        body1: usize,
        body2: Option<usize>,
        (anchor1, anchor2): (Vector3<f64>, Vector3<f64>),
        rotation: UnitQuaternion<f64>,
    ) -> Self {
        Self {
            kind: JointKind::Fixed { rotation },
            body1,
            body2,
            anchor1,
            anchor2,
        }
    }

    /// Checks the body indices against `n_bodies` and that every number is finite.
    pub fn validate(&self, n_bodies: usize) -> Result<(), JointError> {
        if self.body1 >= n_bodies {
            return Err(JointError::BodyOutOfRange {
                which: "body1",
                index: self.body1,
                len: n_bodies,
            });
        }
        if let Some(b) = self.body2 {
            if b >= n_bodies {
                return Err(JointError::BodyOutOfRange {
                    which: "body2",
                    index: b,
                    len: n_bodies,
                });
            }
            if b == self.body1 {
                return Err(JointError::SameBody(b));
            }
        }
        let finite = |v: &Vector3<f64>| v.iter().all(|x| x.is_finite());
        if !finite(&self.anchor1) {
            return Err(JointError::NonFinite("anchor1"));
        }
        if !finite(&self.anchor2) {
            return Err(JointError::NonFinite("anchor2"));
        }
        match &self.kind {
            JointKind::Spherical => {}
            JointKind::Revolute { axis1, axis2 } => {
                for (a, what) in [(axis1, "axis1"), (axis2, "axis2")] {
                    if !finite(a) {
                        return Err(JointError::NonFinite(what));
                    }
                    if (a.norm() - 1.0).abs() > 1e-9 {
                        return Err(JointError::ZeroAxis(what));
                    }
                }
            }
            JointKind::Fixed { rotation } => {
                if !rotation.coords.iter().all(|x| x.is_finite()) {
                    return Err(JointError::NonFinite("rotation"));
                }
            }
        }
        Ok(())
    }

    /// The joint's rows at the bodies' current poses (see [`JointRow`]), goals left to the
    /// step (Baumgarte). No rows when no end is an enabled body (a frozen body's rows would be
    /// all zero); `index` is the joint's index in `World::joints`.
    pub fn rows(&self, index: usize, bodies: &[Body]) -> Vec<JointRow> {
        let Some(b1) = bodies.get(self.body1) else {
            return Vec::new();
        };
        let b2 = match self.body2 {
            Some(i) => match bodies.get(i) {
                Some(b) => Some((i, b)),
                None => return Vec::new(),
            },
            None => None,
        };
        if !b1.enabled && !b2.is_some_and(|(_, b)| b.enabled) {
            return Vec::new();
        }
        let r1 = b1.orientation * self.anchor1;
        let (r2, p2, q2) = match b2 {
            Some((_, b)) => {
                let r = b.orientation * self.anchor2;
                (r, b.position + r, b.orientation)
            }
            None => (Vector3::zeros(), self.anchor2, UnitQuaternion::identity()),
        };
        let separation = b1.position + r1 - p2;
        let mut out = Vec::with_capacity(self.kind.rows());
        let mut push = |row: JacobianRow, error: f64| {
            out.push(JointRow {
                joint: index,
                row,
                error,
                goal: None,
            });
        };
        // Anchor separation e = p1 − p2, ė = v1 + ω1 × r1 − v2 − ω2 × r2: per world axis d,
        // the row (d, r1 × d) on body 1 and (−d, −r2 × d) on body 2.
        for (k, d) in [Vector3::x(), Vector3::y(), Vector3::z()]
            .iter()
            .enumerate()
        {
            let half = |body: usize, r: &Vector3<f64>, sign: f64| {
                let ang = r.cross(d);
                (body, [d.x, d.y, d.z, ang.x, ang.y, ang.z].map(|v| sign * v))
            };
            let row = JacobianRow {
                a: half(self.body1, &r1, 1.0),
                b: b2.map(|(i, _)| half(i, &r2, -1.0)),
            };
            push(row, separation[k]);
        }
        let angular = |axis: &Vector3<f64>| JacobianRow {
            a: (self.body1, [0.0, 0.0, 0.0, axis.x, axis.y, axis.z]),
            b: b2.map(|(i, _)| (i, [0.0, 0.0, 0.0, -axis.x, -axis.y, -axis.z])),
        };
        match &self.kind {
            JointKind::Spherical => {}
            JointKind::Revolute { axis1, axis2 } => {
                // e = a2 × a1 has ė = (ω1 − ω2) projected off the axis (to first order), so
                // the two rows about the directions perpendicular to a1 measure it.
                let a1 = b1.orientation * axis1;
                let a2 = q2 * axis2;
                let misalignment = a2.cross(&a1);
                let (t1, t2) = default_tangents(&a1);
                for t in [t1, t2] {
                    push(angular(&t), t.dot(&misalignment));
                }
            }
            JointKind::Fixed { rotation } => {
                // E = q1 · rotation · q2⁻¹ is the identity when the weld holds; its rotation
                // vector moves with ω1 − ω2 (to first order).
                let err = (b1.orientation * rotation * q2.inverse()).scaled_axis();
                for (k, d) in [Vector3::x(), Vector3::y(), Vector3::z()]
                    .iter()
                    .enumerate()
                {
                    push(angular(d), err[k]);
                }
            }
        }
        out
    }
}

/// One equality row of a joint at the poses of one step: the unknown is the row's Lagrange
/// multiplier (an impulse, N·s or N·m·s), free of sign and bounds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointRow {
    /// Index of the joint in `World::joints`.
    pub joint: usize,
    /// The Jacobian row (relative velocity along the constrained direction).
    pub row: JacobianRow,
    /// Position error along the row at these poses (m or rad).
    pub error: f64,
    /// A recorded goal for `J v⁺` after a forward step through this set; `None`: the
    /// Baumgarte goal [`JointRow::baumgarte`] (what an ordinary forward step asks). A backward
    /// step records here the `J v_t` of the state it started from, so that replaying it
    /// forward ([`crate::World::step_forward_with`]) returns exactly that state.
    pub goal: Option<f64>,
}

impl JointRow {
    /// The forward Baumgarte goal `−β e / Δt`: with it, `J v⁺` shrinks the error by the factor
    /// `1 − β` in one step. [`crate::World::forward_residual`] measures against it.
    pub fn baumgarte(&self, erp: f64, dt: f64) -> f64 {
        if dt > 0.0 && erp.is_finite() {
            -erp * self.error / dt
        } else {
            0.0
        }
    }

    /// The goal a forward step through this row enforces: the recorded one, else Baumgarte.
    pub fn forward_goal(&self, erp: f64, dt: f64) -> f64 {
        self.goal.unwrap_or_else(|| self.baumgarte(erp, dt))
    }

    /// The backward goal for `J v⁻` (§5.3.4): the Baumgarte term with its sign reversed,
    /// `+β e / Δt`, since the next poses of a backward run are `x − Δt v⁻`.
    pub fn backward_goal(&self, erp: f64, dt: f64) -> f64 {
        -self.baumgarte(erp, dt)
    }
}

/// The largest anchor separation (m) over `joints` at the bodies' poses.
pub fn max_separation(joints: &[Joint], bodies: &[Body]) -> f64 {
    joints
        .iter()
        .enumerate()
        .map(|(i, j)| {
            let rows = j.rows(i, bodies);
            rows.iter()
                .take(3)
                .map(|r| r.error * r.error)
                .sum::<f64>()
                .sqrt()
        })
        .fold(0.0, f64::max)
}

/// The largest angular error (rad) over the revolute and fixed joints of `joints`.
pub fn max_angular_error(joints: &[Joint], bodies: &[Body]) -> f64 {
    joints
        .iter()
        .enumerate()
        .map(|(i, j)| {
            let rows = j.rows(i, bodies);
            rows.iter()
                .skip(3)
                .map(|r| r.error * r.error)
                .sum::<f64>()
                .sqrt()
        })
        .fold(0.0, f64::max)
}
