//! The backward step (§5.2, Figure 5.5): from the state at `t`, a state at `t − Δt` and
//! impulses such that the forward step of [`crate::step`] would take the one to the other.
//!
//! # Order of work
//!
//! The forward position update `x_t = x_{t−Δt} + Δt v_t`, `Θ_t = exp(Δt ω_t) Θ_{t−Δt}` uses only
//! the *post*-step velocities, which we are given, so positions go back first and exactly (to
//! round-off). The contacts and the Jacobian are then taken at the earlier poses — where the
//! forward step would take them — and only the velocities are left to solve for (5.9)–(5.13):
//!
//! `−v_{t−Δt} = −v_t + Δt M⁻¹ f_ext + M⁻¹ Jᵀ f`,  so per row `w = −J v_{t−Δt} − c = A f + b`
//!
//! with the positive semi-definite `A = J M⁻¹ Jᵀ` of the forward step and a per-row goal `c`.
//!
//! # Per-contact choices (Figure 5.5)
//!
//! Let `v_N`, `v_T` be the normal and tangential relative velocity at `t`.
//!
//! * `v_N ≥ δ` and `v_N > α ε`: an elastic collision happened (§5.2.2). LCP (5.3): the incoming
//!   speed is at least `v_N / α`, with equality when the contact pushes.
//! * `v_N ≥ δ` but `v_N ≤ α ε` (or `α = 0`): no elastic response can explain it, because a
//!   forward step only bounces above the cutoff. This is the thesis' case 2 (Figure 5.1): the
//!   contact did not push, and its rows are left out (zero impulse).
//! * `v_N < δ`: resting or inelastic (§5.2.3). LCP (5.5): incoming speed at least the chosen
//!   lift-off goal (`0` by default, below `ε` so the forward step treats it as inelastic).
//! * `|v_T| > δ`: sliding, friction was maximal and opposed the slip (5.6), the "goal ±∞" of
//!   (5.7). The first tangent is aligned with the slip and its impulse is fixed at `−μ f_N`,
//!   which folds it into the normal's column (the non-symmetric matrix of §3.6.1).
//! * `|v_T| ≤ δ`: friction is free inside its bounds and drives the earlier tangential velocity
//!   towards a chosen goal (5.7)–(5.8), along a chosen direction; zero by default.
//!
//! These choices make any solution of the backward LCP a solution of the forward one (the
//! round-trip of §5.2), except where an impulse-free contact ends up approaching faster than `ε`
//! because of its neighbours; [`BackwardReport::forward_residual`] measures that every step.
//! None of the plausibility heuristics of §5.3 (reverse damping, restitution pushed to 1,
//! sticky stacks) are applied here.

use std::collections::BTreeMap;

use nalgebra::{DVector, Vector3};

use crate::contact::{ContactSet, JacobianRow, Partner};
use crate::lcp::{self, LcpProblem, LcpStatus, RowKind};
use crate::step::{contact_rows, disable_non_finite};
use crate::world::{
    ContactImpulse, InvMass, IslandSolve, Response, World, delassus, rotate, row_velocity,
    store_velocities, velocity6,
};

/// A user's (or sampler's) wish for one body when its contacts are at rest (§5.3.6, Figure
/// 5.10): both are goals, honoured only as far as the other constraints allow (§5.2.3).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct BodyHint {
    /// Incoming normal speed goal at the body's resting contacts (5.5); clamped to
    /// `[0, 0.99 ε]` so that the forward step would see an inelastic impact.
    pub lift_off_speed: f64,
    /// Goal for the body's relative velocity at its resting contacts at `t − Δt` (5.7): the
    /// first friction direction is aligned with its tangential part.
    pub slide_velocity: Vector3<f64>,
}

/// Which of a body's resting contacts leave the ground in this step: the contact-count
/// transition of §5.3.6 (Figure 5.12) made concrete. The `count` resting contacts of the body
/// whose points lie furthest along `direction` get the lift-off goal `speed` (5.5); the others
/// keep goal 0, so a box resting on a face tips onto an edge instead of jumping flat.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LiftPlan {
    /// How many resting contacts to lift.
    pub count: usize,
    /// Ranks the contacts (world frame); ties keep contact order.
    pub direction: Vector3<f64>,
    /// Incoming normal speed goal of a lifted contact; clamped to `[0, 0.99 ε]`.
    pub speed: f64,
}

/// Choices for one backward step.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BackwardChoices {
    /// Hints by body index.
    pub hints: BTreeMap<usize, BodyHint>,
    /// Contact-count transitions by body index; they override the hint's `lift_off_speed` for
    /// that body's resting contacts.
    pub lifts: BTreeMap<usize, LiftPlan>,
    /// Restitution used *by the backward decision* for a pair `(body, partner)` (as
    /// [`crate::Contact`] names them) instead of the material's: the rattling heuristic of
    /// §5.3.1 pushes it to 1 after an elastic contact. The contact set keeps the material's
    /// value, so [`BackwardReport::forward_residual`] measures the departure.
    pub restitution: BTreeMap<(usize, Partner), f64>,
    /// The stacking heuristic of §5.3.3: a resting contact between two bodies that are not
    /// free to bounce (or between such a body and static geometry) is held, allowing the
    /// normal impulse to pull, so a stack does not fly apart when stepped backward. `None`:
    /// off. The value caps the pulling impulse (and the friction impulse) of a held contact in
    /// units of the body's weight times `Δt`.
    pub stacking_glue: Option<f64>,
}

/// The free-to-bounce test of §5.3.3 for every body: true when every pair of its contact
/// normals (each pointing into the body) has a non-negative dot product, false when two of
/// them oppose (something above and something below: the body is part of a stack).
pub fn free_to_bounce(set: &ContactSet, n_bodies: usize) -> Vec<bool> {
    let mut normals: Vec<Vec<Vector3<f64>>> = vec![Vec::new(); n_bodies];
    for c in &set.contacts {
        if let Some(list) = normals.get_mut(c.body) {
            list.push(c.normal);
        }
        if let Partner::Body(p) = c.partner
            && let Some(list) = normals.get_mut(p)
        {
            list.push(-c.normal);
        }
    }
    normals
        .iter()
        .map(|ns| {
            ns.iter()
                .enumerate()
                .all(|(i, a)| ns[i + 1..].iter().all(|b| a.dot(b) >= -1e-9))
        })
        .collect()
}

/// What happened at a contact's normal, as decided by the backward step.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum NormalCase {
    /// Elastic collision, LCP (5.3).
    Elastic,
    /// Resting or inelastic impact, LCP (5.5).
    Resting,
    /// Separating without an impulse of its own (Figure 5.1, case 2).
    Separating,
    /// Resting contact of a stacked body, held bilateral with a bounded pull (the stacking
    /// heuristic of §5.3.3; not forward-valid when it pulls).
    Held,
}

/// What happened in a contact's tangent plane.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum FrictionCase {
    /// Maximal friction against the slip (5.6).
    Sliding,
    /// Friction inside its bounds, towards a goal (5.7).
    Sticking,
}

/// The decision taken for one contact.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContactChoice {
    /// Normal case.
    pub normal: NormalCase,
    /// Friction case.
    pub friction: FrictionCase,
    /// Goal incoming normal speed (`v_N / α`, the lift-off speed, or 0).
    pub normal_goal: f64,
    /// Goal earlier tangential velocity along `tangent_u` (sticking contacts).
    pub tangent_goal: f64,
}

/// What a backward step did; enough to replay it forward.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BackwardReport {
    /// Contacts and Jacobian directions, at the poses of `t − Δt`.
    pub contacts: ContactSet,
    /// Impulses in the forward sense, one per contact.
    pub impulses: Vec<ContactImpulse>,
    /// One decision per contact.
    pub choices: Vec<ContactChoice>,
    /// One entry per island.
    pub islands: Vec<IslandSolve>,
    /// Forward-LCP residual of `impulses` at the new state ([`World::forward_residual`]):
    /// about zero when the step is forward-valid.
    pub forward_residual: f64,
    /// Contacts whose normal velocity at `t` approaches faster than `δ`. No forward step ends
    /// like that (it stops every approach in its contact set), so such a state has no exact
    /// forward-valid predecessor and `forward_residual` will be about that speed. It happens
    /// when a body rotates while its contact point slides along it (a box tipping over an
    /// edge): the previous backward step zeroed the normal velocity at the old material point.
    pub approaching_contacts: usize,
    /// Shape pairs parry could not handle.
    pub unsupported_pairs: usize,
    /// Bodies disabled because their state became non-finite.
    pub disabled: Vec<usize>,
}

impl BackwardReport {
    /// True when every island was solved and nothing was disabled or skipped.
    pub fn all_solved(&self) -> bool {
        self.islands.iter().all(|s| s.status.is_solution())
            && self.disabled.is_empty()
            && self.unsupported_pairs == 0
    }
}

/// Rounds of re-solving with raised lift-off goals (see `step_backward`).
const LIFT_ROUNDS: usize = 4;
/// A landing must clear this multiple of the remaining prediction band in one step.
const LIFT_CLEARANCE: f64 = 2.0;
/// Approach speeds below this (m/s) are round-off, not landings.
const LIFT_NOISE: f64 = 1e-9;

fn fold(normal: &JacobianRow, tangent: &JacobianRow, mu: f64) -> JacobianRow {
    let mix = |n: &[f64; 6], t: &[f64; 6]| std::array::from_fn(|k| n[k] - mu * t[k]);
    JacobianRow {
        a: (normal.a.0, mix(&normal.a.1, &tangent.a.1)),
        b: match (normal.b, tangent.b) {
            (Some((i, n)), Some((_, t))) => Some((i, mix(&n, &t))),
            _ => None,
        },
    }
}

/// Which contact slot of an island a variable belongs to and what it is.
#[derive(Debug, Clone, Copy)]
enum Var {
    Normal(usize),
    U(usize),
    W(usize),
}

impl World {
    /// Per contact index, the lift-off goal the [`LiftPlan`]s ask for (absent: no plan).
    fn lifted_contacts(&self, set: &ContactSet, choices: &BackwardChoices) -> BTreeMap<usize, f64> {
        let mut out = BTreeMap::new();
        for (&body, plan) in &choices.lifts {
            let mut mine: Vec<(f64, usize)> = set
                .contacts
                .iter()
                .enumerate()
                .filter(|(_, c)| c.body == body || c.partner == Partner::Body(body))
                .map(|(k, c)| {
                    let along = c.point.dot(&plan.direction);
                    (if along.is_finite() { along } else { 0.0 }, k)
                })
                .collect();
            // Furthest along the direction first; stable for ties.
            mine.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
            for &(_, k) in mine.iter().take(plan.count) {
                out.insert(k, plan.speed);
            }
            for &(_, k) in mine.iter().skip(plan.count) {
                out.entry(k).or_insert(0.0);
            }
        }
        out
    }

    /// One backward step of length `dt` (see the [module docs](self)). The world's state
    /// becomes the state at `t − Δt`.
    pub fn step_backward(&mut self, dt: f64, choices: &BackwardChoices) -> BackwardReport {
        let before = self.bodies.clone();
        let v_plus: Vec<[f64; 6]> = self.bodies.iter().map(velocity6).collect();
        // Positions first, exactly inverting (3.17)–(3.18).
        for b in self.bodies.iter_mut().filter(|b| b.enabled) {
            b.position -= b.linvel * dt;
            b.orientation = rotate(&b.orientation, &b.angvel, -dt);
        }
        let (mut set, unsupported) = self.detect_contacts();
        let eps = self.params.restitution_cutoff;
        let delta = self.params.rest_threshold;
        let free = if choices.stacking_glue.is_some() {
            free_to_bounce(&set, self.bodies.len())
        } else {
            Vec::new()
        };
        let lifted = self.lifted_contacts(&set, choices);

        // Figure 5.5, per contact.
        let mut decisions = Vec::with_capacity(set.contacts.len());
        let mut approaching = 0;
        for k in 0..set.contacts.len() {
            let rel = self.relative_velocity(&set.contacts[k]);
            let c = &mut set.contacts[k];
            let v_n = c.normal.dot(&rel);
            let slip = rel - c.normal * v_n;
            let hint = choices
                .hints
                .get(&c.body)
                .copied()
                .or_else(|| match c.partner {
                    Partner::Body(p) => choices.hints.get(&p).map(|h| BodyHint {
                        lift_off_speed: h.lift_off_speed,
                        slide_velocity: -h.slide_velocity,
                    }),
                    Partner::Static(_) => None,
                });
            let hint = hint.unwrap_or_default();
            let (friction, tangent_goal) = if slip.norm() > delta {
                c.align_tangents(&slip, delta);
                (FrictionCase::Sliding, 0.0)
            } else if c.align_tangents(&hint.slide_velocity, delta) {
                let speed = c.tangent_u.dot(&hint.slide_velocity);
                (FrictionCase::Sticking, speed)
            } else {
                (FrictionCase::Sticking, 0.0)
            };
            let alpha = choices
                .restitution
                .get(&(c.body, c.partner))
                .copied()
                .filter(|a| a.is_finite())
                .map_or(c.restitution, |a| a.clamp(0.0, 1.0));
            let elastic_floor = alpha * eps * (1.0 + 1e-9) + f64::EPSILON;
            if v_n < -delta {
                approaching += 1;
            }
            let (normal, normal_goal) = if v_n >= delta {
                if alpha > 0.0 && v_n > elastic_floor {
                    (NormalCase::Elastic, v_n / alpha)
                } else {
                    (NormalCase::Separating, 0.0)
                }
            } else {
                let held = !free.is_empty()
                    && choices
                        .stacking_glue
                        .is_some_and(|g| g > 0.0 && g.is_finite())
                    && friction == FrictionCase::Sticking
                    && !free[c.body]
                    && match c.partner {
                        Partner::Body(p) => !free[p],
                        Partner::Static(_) => true,
                    };
                let wish = lifted.get(&k).copied().unwrap_or(hint.lift_off_speed);
                let lift = if wish.is_finite() {
                    wish.clamp(0.0, 0.99 * eps)
                } else {
                    0.0
                };
                if held && lift == 0.0 {
                    (NormalCase::Held, 0.0)
                } else {
                    (NormalCase::Resting, lift)
                }
            };
            decisions.push(ContactChoice {
                normal,
                friction,
                normal_goal,
                tangent_goal,
            });
        }

        let inv: Vec<InvMass> = self.bodies.iter().map(InvMass::of).collect();
        let gdt = self.gravity * dt;
        // v_t − Δt M⁻¹ f_ext: the earlier velocity before contact impulses are undone.
        let mut vel: Vec<[f64; 6]> = v_plus.clone();
        for (b, v) in self.bodies.iter().zip(vel.iter_mut()) {
            if b.enabled {
                v[0] -= gdt.x;
                v[1] -= gdt.y;
                v[2] -= gdt.z;
            }
        }
        let free_vel = vel.clone();
        let mut impulses = vec![ContactImpulse::default(); set.contacts.len()];
        let mut islands = Vec::with_capacity(set.islands.len());
        for island in &set.islands {
            let mut rows = Vec::new();
            let mut dirs = Vec::new();
            let mut kinds = Vec::new();
            let mut b = Vec::new();
            let mut vars = Vec::new();
            for &k in &island.contacts {
                let d = decisions[k];
                if d.normal == NormalCase::Separating {
                    continue;
                }
                let c = &set.contacts[k];
                let [rn, ru, rw] = contact_rows(c, &self.bodies);
                let normal = kinds.len();
                let mu = c.friction;
                if d.normal == NormalCase::Held {
                    // §5.3.3: hold the contact, w = 0 while the impulses stay inside ±cap.
                    let weight = self.gravity.norm() * dt / self.bodies[c.body].inv_mass;
                    let cap = choices.stacking_glue.unwrap_or(0.0).max(0.0) * weight;
                    for (row, var, hi) in [
                        (rn, Var::Normal(k), f64::INFINITY),
                        (ru, Var::U(k), cap),
                        (rw, Var::W(k), cap),
                    ] {
                        rows.push(row);
                        dirs.push(row);
                        kinds.push(RowKind::Bounded { lo: -cap, hi });
                        b.push(-row_velocity(&row, &free_vel));
                        vars.push(var);
                    }
                    continue;
                }
                // Normal: w = −v⁻_N − goal (5.3)/(5.5).
                rows.push(rn);
                dirs.push(match d.friction {
                    FrictionCase::Sliding => fold(&rn, &ru, mu),
                    FrictionCase::Sticking => rn,
                });
                kinds.push(RowKind::Normal);
                b.push(-row_velocity(&rn, &free_vel) - d.normal_goal);
                vars.push(Var::Normal(k));
                // Friction: w = −(v⁻_T − goal_T) (5.7); interior impulse ⇒ the goal is met.
                if d.friction == FrictionCase::Sticking {
                    rows.push(ru);
                    dirs.push(ru);
                    kinds.push(RowKind::Friction { normal, mu });
                    b.push(-row_velocity(&ru, &free_vel) + d.tangent_goal);
                    vars.push(Var::U(k));
                }
                rows.push(rw);
                dirs.push(rw);
                kinds.push(RowKind::Friction { normal, mu });
                b.push(-row_velocity(&rw, &free_vel));
                vars.push(Var::W(k));
            }
            if rows.is_empty() {
                islands.push(IslandSolve {
                    status: LcpStatus::Solved,
                    residual: 0.0,
                    rows: 0,
                    pivots: 0,
                });
                continue;
            }
            let responses: Vec<Response> = dirs.iter().map(|r| Response::new(r, &inv)).collect();
            let a = delassus(&rows, &responses);
            let n = rows.len();
            let problem = LcpProblem::new(a, DVector::from_vec(b), kinds);
            let Ok(mut problem) = problem else {
                islands.push(IslandSolve {
                    status: LcpStatus::Degenerate,
                    residual: f64::NAN,
                    rows: n,
                    pivots: 0,
                });
                continue;
            };
            let mut solved = lcp::solve(&problem, &self.params.lcp);
            // A contact left approaching (forward in time) too slowly to leave the prediction
            // band within one step would still be in the next backward step's contact set with
            // an approaching post-step velocity, which no forward step produces: the forward
            // step stops every approach it sees. Such a landing is re-explained as an inelastic
            // impact at a speed that clears the band, a lift-off goal below ε (5.5).
            for _ in 0..LIFT_ROUNDS {
                let Ok(sol) = &solved else { break };
                if !sol.x.iter().all(|v| v.is_finite()) {
                    break;
                }
                // J v⁻ after undoing the impulses is J v − A x (A = J M⁻¹ Gᵀ): no need to
                // touch the velocities of bodies outside the island.
                let undone = &problem.a * &sol.x;
                let mut changed = false;
                for (j, var) in vars.iter().enumerate() {
                    let Var::Normal(k) = *var else { continue };
                    if decisions[k].normal != NormalCase::Resting {
                        continue;
                    }
                    let incoming = -(row_velocity(&rows[j], &vel) - undone[j]);
                    let clearance = (self.params.prediction - set.contacts[k].dist).max(0.0);
                    let needed = LIFT_CLEARANCE * clearance / dt + delta;
                    if incoming > LIFT_NOISE
                        && incoming < needed
                        && needed < 0.99 * eps
                        && decisions[k].normal_goal < needed
                    {
                        problem.b[j] -= needed - decisions[k].normal_goal;
                        decisions[k].normal_goal = needed;
                        changed = true;
                    }
                }
                if !changed {
                    break;
                }
                solved = lcp::solve(&problem, &self.params.lcp);
            }
            let Ok(sol) = solved else {
                islands.push(IslandSolve {
                    status: LcpStatus::Degenerate,
                    residual: f64::NAN,
                    rows: n,
                    pivots: 0,
                });
                continue;
            };
            let finite = sol.x.iter().all(|v| v.is_finite());
            if finite {
                for (j, resp) in responses.iter().enumerate() {
                    // v⁻ = (v_t − Δt M⁻¹ f_ext) − M⁻¹ Gᵀ f  (5.9)–(5.11).
                    resp.add_to(-sol.x[j], &mut vel);
                }
                for (j, var) in vars.iter().enumerate() {
                    match *var {
                        Var::Normal(k) => {
                            impulses[k].normal = sol.x[j];
                            if decisions[k].friction == FrictionCase::Sliding {
                                impulses[k].tangent_u = -set.contacts[k].friction * sol.x[j];
                            }
                        }
                        Var::U(k) => impulses[k].tangent_u = sol.x[j],
                        Var::W(k) => impulses[k].tangent_w = sol.x[j],
                    }
                }
            }
            islands.push(IslandSolve {
                status: if finite {
                    sol.status
                } else {
                    LcpStatus::Degenerate
                },
                residual: sol.residual,
                rows: n,
                pivots: sol.pivots,
            });
        }
        store_velocities(&mut self.bodies, &vel);
        let disabled = disable_non_finite(&mut self.bodies, &before);
        let forward_residual = self.forward_residual(&set, &impulses, dt);
        BackwardReport {
            contacts: set,
            impulses,
            choices: decisions,
            islands,
            forward_residual,
            approaching_contacts: approaching,
            unsupported_pairs: unsupported,
            disabled,
        }
    }
}
