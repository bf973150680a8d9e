//! The forward velocity-level step (Stewart–Trinkle / Anitescu–Potra, §3.3–3.6).
//!
//! Per island, with `v⁻` the velocities at the start of the step and `J` taken at the start
//! poses, the unknown contact impulses `f` (normal, `u`, `w` per contact) solve one LCP
//!
//! * `w = J (v⁻ + Δt M⁻¹ f_ext) + J M⁻¹ Jᵀ f − goal` (3.13), (3.37),
//! * normal rows: `0 ≤ w ⊥ f_N ≥ 0` (3.19), with the Newton goal `α s` when the incoming speed
//!   `s = −v⁻_N` exceeds the cutoff `ε`, else `0` (3.20)–(3.22);
//! * friction rows: `|f_u|, |f_w| ≤ μ f_N`, bounds coupled to the normal impulse *inside* the
//!   LCP (§3.6.1), maximal and opposing the post-step slip when it is nonzero (3.23)–(3.24);
//!
//! * joint rows (§5.3.4, [`crate::joint`]): `w = 0` with unbounded multipliers, the goal
//!   being the Baumgarte term `−β e / Δt` of the joint's position error `e` (or the goal a
//!   replayed set recorded);
//!
//! then `v⁺ = v⁻ + Δt M⁻¹ f_ext + M⁻¹ Jᵀ f` (3.15)–(3.16) and the semi-implicit position update
//! `x⁺ = x⁻ + Δt v⁺`, `Θ⁺ = exp(Δt ω⁺) Θ⁻` (3.17)–(3.18). No gyroscopic term: angular velocity
//! only changes through impulses, which keeps the step exactly invertible given its contacts.
//! Contacts are not projected out of penetration (no Baumgarte term on contacts): as in the
//! papers, their conditions are on velocities only; only joints get one.

use nalgebra::{DVector, Vector3};

use crate::contact::{Contact, ContactSet, Island, JacobianRow, Partner};
use crate::lcp::{self, LcpProblem, RowKind};
use crate::world::{
    ContactImpulse, InvMass, IslandSolve, Response, StepReport, World, delassus, rotate,
    row_velocity, store_velocities, velocity6,
};

/// Rows (normal, u, w) of one contact.
pub(crate) fn contact_rows(c: &Contact, bodies: &[crate::body::Body]) -> [JacobianRow; 3] {
    [
        JacobianRow::new(c, &c.normal, bodies),
        JacobianRow::new(c, &c.tangent_u, bodies),
        JacobianRow::new(c, &c.tangent_w, bodies),
    ]
}

/// The rolling-friction rows (5.15)–(5.17) of a contact with a round body, or `None`.
pub(crate) fn rolling_rows(c: &Contact) -> Option<[JacobianRow; 3]> {
    (c.rolling > 0.0).then(|| c.rolling_axes().map(|axis| JacobianRow::angular(c, &axis)))
}

/// The forward LCP of one island at the world's current (pre-step) state.
pub(crate) struct ForwardIsland {
    pub(crate) problem: LcpProblem,
    pub(crate) responses: Vec<Response>,
    /// Per contact of the island (in island order), its first row and whether it has
    /// rolling rows (normal, u, w, then three rolling rows).
    pub(crate) slots: Vec<(usize, bool)>,
    /// LCP row of the island's first joint row; the others follow in island order.
    pub(crate) first_joint: usize,
}

impl ForwardIsland {
    /// The island's impulses as an LCP vector.
    pub(crate) fn pack(
        &self,
        island: &Island,
        impulses: &[ContactImpulse],
        joint_impulses: &[f64],
    ) -> DVector<f64> {
        let mut x = DVector::zeros(self.problem.len());
        for (j, &k) in island.joints.iter().enumerate() {
            x[self.first_joint + j] = joint_impulses[k];
        }
        for (&(row, rolling), &k) in self.slots.iter().zip(&island.contacts) {
            let i = impulses[k];
            x[row] = i.normal;
            x[row + 1] = i.tangent_u;
            x[row + 2] = i.tangent_w;
            if rolling {
                for (a, r) in i.rolling.iter().enumerate() {
                    x[row + 3 + a] = *r;
                }
            }
        }
        x
    }

    /// The impulses of one contact slot from an LCP vector.
    pub(crate) fn unpack(&self, slot: usize, x: &DVector<f64>) -> ContactImpulse {
        let (row, rolling) = self.slots[slot];
        ContactImpulse {
            normal: x[row],
            tangent_u: x[row + 1],
            tangent_w: x[row + 2],
            rolling: if rolling {
                [x[row + 3], x[row + 4], x[row + 5]]
            } else {
                [0.0; 3]
            },
        }
    }
}

impl World {
    /// Relative velocity of `contact`'s body with respect to its partner at the contact point.
    pub fn relative_velocity(&self, contact: &Contact) -> Vector3<f64> {
        let va = self.bodies[contact.body].point_velocity(&contact.point);
        match contact.partner {
            Partner::Body(b) => va - self.bodies[b].point_velocity(&contact.point),
            Partner::Static(_) => va,
        }
    }

    /// Relative angular velocity of `contact`'s body with respect to its partner.
    pub fn relative_angular_velocity(&self, contact: &Contact) -> Vector3<f64> {
        let wa = self.bodies[contact.body].angvel;
        match contact.partner {
            Partner::Body(b) => wa - self.bodies[b].angvel,
            Partner::Static(_) => wa,
        }
    }

    /// Generalized velocities `v⁻` and the free velocities `v⁻ + Δt M⁻¹ f_ext` of all bodies,
    /// computed once per step and shared by every island.
    pub(crate) fn free_velocities(&self, dt: f64) -> (Vec<[f64; 6]>, Vec<[f64; 6]>) {
        let vel: Vec<[f64; 6]> = self.bodies.iter().map(velocity6).collect();
        let gdt = self.gravity * dt;
        let free = self
            .bodies
            .iter()
            .zip(&vel)
            .map(|(b, v)| {
                if b.enabled {
                    [v[0] + gdt.x, v[1] + gdt.y, v[2] + gdt.z, v[3], v[4], v[5]]
                } else {
                    *v
                }
            })
            .collect();
        (vel, free)
    }

    /// `replay`: joint rows take their recorded goals (else their Baumgarte goals).
    pub(crate) fn forward_island(
        &self,
        set: &ContactSet,
        island: &Island,
        inv: &[InvMass],
        (vel, free): (&[[f64; 6]], &[[f64; 6]]),
        (dt, replay): (f64, bool),
    ) -> Result<ForwardIsland, crate::LcpError> {
        let eps = self.params.restitution_cutoff;
        let mut rows = Vec::with_capacity(3 * island.contacts.len());
        let mut kinds = Vec::with_capacity(rows.capacity());
        let mut b = Vec::with_capacity(rows.capacity());
        let mut slots = Vec::with_capacity(island.contacts.len());
        for &k in &island.contacts {
            let c = &set.contacts[k];
            let [rn, ru, rw] = contact_rows(c, &self.bodies);
            // §3.5: Newton restitution only above the cutoff; the goal uses the pre-step
            // approach speed.
            let incoming = -row_velocity(&rn, vel);
            let goal = if c.restitution > 0.0 && incoming > eps {
                c.restitution * incoming
            } else {
                0.0
            };
            let normal = kinds.len();
            b.push(row_velocity(&rn, free) - goal);
            b.push(row_velocity(&ru, free));
            b.push(row_velocity(&rw, free));
            let mu = c.friction;
            kinds.extend([
                RowKind::Normal,
                RowKind::Friction { normal, mu },
                RowKind::Friction { normal, mu },
            ]);
            rows.extend([rn, ru, rw]);
            let rolling = rolling_rows(c);
            slots.push((normal, rolling.is_some()));
            // §5.3.5: torque impulses about three axes, each bounded by the rolling arm times
            // the normal impulse and opposing the relative rotation (5.15)–(5.18); exactly
            // the friction rows' coupled bounds, on angular velocity.
            for row in rolling.into_iter().flatten() {
                b.push(row_velocity(&row, free));
                kinds.push(RowKind::Friction {
                    normal,
                    mu: c.rolling,
                });
                rows.push(row);
            }
        }
        // §5.3.4: joints are extra unknowns of the same LCP (Lagrange multipliers), rows with
        // w = J v⁺ − goal = 0 and no bounds.
        let first_joint = kinds.len();
        let erp = self.params.joint_erp;
        for &k in &island.joints {
            let jr = &set.joints[k];
            let goal = if replay {
                jr.forward_goal(erp, dt)
            } else {
                jr.baumgarte(erp, dt)
            };
            b.push(row_velocity(&jr.row, free) - goal);
            kinds.push(RowKind::Equality);
            rows.push(jr.row);
        }
        let responses: Vec<Response> = rows.iter().map(|r| Response::new(r, inv)).collect();
        let a = delassus(&rows, &responses);
        let problem = LcpProblem::new(a, DVector::from_vec(b), kinds)?;
        Ok(ForwardIsland {
            problem,
            responses,
            slots,
            first_joint,
        })
    }

    /// One forward step: detects contacts at the current poses, aligns each contact's first
    /// friction direction with its current slip (§3.6.1), and steps with
    /// [`World::step_forward_with`].
    pub fn step_forward(&mut self, dt: f64) -> StepReport {
        let (mut set, unsupported) = self.detect_contacts();
        let delta = self.params.rest_threshold;
        for k in 0..set.contacts.len() {
            let rel = self.relative_velocity(&set.contacts[k]);
            set.contacts[k].align_tangents(&rel, delta);
            let spin = self.relative_angular_velocity(&set.contacts[k]);
            set.contacts[k].align_rolling(&spin, delta);
        }
        let mut report = self.step_forward_with(&set, dt);
        report.unsupported_pairs = unsupported;
        report
    }

    /// One forward step with a given contact set, Jacobian directions and joint rows (no
    /// detection): the replay half of the round-trip check of §5.2. Joint rows with a recorded
    /// goal (from a backward step) enforce it; the others their Baumgarte goal.
    pub fn step_forward_with(&mut self, set: &ContactSet, dt: f64) -> StepReport {
        let inv: Vec<InvMass> = self.bodies.iter().map(InvMass::of).collect();
        let (pre, free) = self.free_velocities(dt);
        let mut vel = free.clone();
        let mut impulses = vec![ContactImpulse::default(); set.contacts.len()];
        let mut joint_impulses = vec![0.0; set.joints.len()];
        let mut islands = Vec::with_capacity(set.islands.len());
        for island in &set.islands {
            let solved = self
                .forward_island(set, island, &inv, (&pre, &free), (dt, true))
                .and_then(|fi| Ok((lcp::solve(&fi.problem, &self.params.lcp)?, fi)));
            match solved {
                Ok((sol, fi)) => {
                    let finite = sol.x.iter().all(|v| v.is_finite());
                    if finite {
                        for (j, resp) in fi.responses.iter().enumerate() {
                            resp.add_to(sol.x[j], &mut vel);
                        }
                        for (slot, &k) in island.contacts.iter().enumerate() {
                            impulses[k] = fi.unpack(slot, &sol.x);
                        }
                        for (j, &k) in island.joints.iter().enumerate() {
                            joint_impulses[k] = sol.x[fi.first_joint + j];
                        }
                    }
                    islands.push(IslandSolve {
                        status: if finite {
                            sol.status
                        } else {
                            lcp::LcpStatus::Degenerate
                        },
                        residual: sol.residual,
                        rows: fi.problem.len(),
                        pivots: sol.pivots,
                    });
                }
                Err(_) => islands.push(IslandSolve {
                    status: lcp::LcpStatus::Degenerate,
                    residual: f64::NAN,
                    rows: 3 * island.contacts.len() + island.joints.len(),
                    pivots: 0,
                }),
            }
        }
        let before: Vec<_> = self.bodies.clone();
        store_velocities(&mut self.bodies, &vel);
        for b in self.bodies.iter_mut().filter(|b| b.enabled) {
            b.position += b.linvel * dt;
            b.orientation = rotate(&b.orientation, &b.angvel, dt);
        }
        let disabled = disable_non_finite(&mut self.bodies, &before);
        StepReport {
            contacts: set.clone(),
            impulses,
            joint_impulses,
            islands,
            unsupported_pairs: 0,
            disabled,
        }
    }

    /// The largest forward-LCP complementarity residual of `impulses` (one per contact of
    /// `set`) over all islands, evaluated at the world's current state as the start of a
    /// forward step: zero exactly when the impulses are a valid forward solution. `NaN` if an
    /// island's problem cannot be built or the lengths disagree; a set with joint rows needs
    /// their impulses: [`World::forward_residual_with_joints`].
    pub fn forward_residual(&self, set: &ContactSet, impulses: &[ContactImpulse], dt: f64) -> f64 {
        self.forward_residual_with_joints(set, impulses, &[], dt)
    }

    /// [`World::forward_residual`] with joint impulses (one per row of `set.joints`). Joint rows
    /// are measured against their Baumgarte goals, not recorded ones: the residual says how
    /// far an ordinary forward step is from these impulses.
    pub fn forward_residual_with_joints(
        &self,
        set: &ContactSet,
        impulses: &[ContactImpulse],
        joint_impulses: &[f64],
        dt: f64,
    ) -> f64 {
        if impulses.len() != set.contacts.len() || joint_impulses.len() != set.joints.len() {
            return f64::NAN;
        }
        let inv: Vec<InvMass> = self.bodies.iter().map(InvMass::of).collect();
        let (pre, free) = self.free_velocities(dt);
        let mut worst = 0.0f64;
        for island in &set.islands {
            let Ok(fi) = self.forward_island(set, island, &inv, (&pre, &free), (dt, false)) else {
                return f64::NAN;
            };
            let x = fi.pack(island, impulses, joint_impulses);
            let r = lcp::complementarity_residual(&fi.problem, &x);
            if r.is_nan() {
                return f64::NAN;
            }
            worst = worst.max(r);
        }
        worst
    }
}

/// Restores and freezes bodies whose new state is not finite (rapier's habit: bad numbers
/// disable the body instead of taking the run down). Returns their indices.
pub(crate) fn disable_non_finite(
    bodies: &mut [crate::body::Body],
    before: &[crate::body::Body],
) -> Vec<usize> {
    let mut disabled = Vec::new();
    for (i, (b, old)) in bodies.iter_mut().zip(before).enumerate() {
        if b.enabled && !b.is_finite() {
            *b = old.clone();
            b.linvel = Vector3::zeros();
            b.angvel = Vector3::zeros();
            b.enabled = false;
            disabled.push(i);
        }
    }
    disabled
}
