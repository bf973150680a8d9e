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

/// Choices for one backward step.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BackwardChoices {
    /// Hints by body index.
    pub hints: BTreeMap<usize, BodyHint>,
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
            let elastic_floor = c.restitution * eps * (1.0 + 1e-9) + f64::EPSILON;
            if v_n < -delta {
                approaching += 1;
            }
            let (normal, normal_goal) = if v_n >= delta {
                if c.restitution > 0.0 && v_n > elastic_floor {
                    (NormalCase::Elastic, v_n / c.restitution)
                } else {
                    (NormalCase::Separating, 0.0)
                }
            } else {
                let lift = if hint.lift_off_speed.is_finite() {
                    hint.lift_off_speed.clamp(0.0, 0.99 * eps)
                } else {
                    0.0
                };
                (NormalCase::Resting, lift)
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
        let free = vel.clone();
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
                // Normal: w = −v⁻_N − goal (5.3)/(5.5).
                rows.push(rn);
                dirs.push(match d.friction {
                    FrictionCase::Sliding => fold(&rn, &ru, mu),
                    FrictionCase::Sticking => rn,
                });
                kinds.push(RowKind::Normal);
                b.push(-row_velocity(&rn, &free) - d.normal_goal);
                vars.push(Var::Normal(k));
                // Friction: w = −(v⁻_T − goal_T) (5.7); interior impulse ⇒ the goal is met.
                if d.friction == FrictionCase::Sticking {
                    rows.push(ru);
                    dirs.push(ru);
                    kinds.push(RowKind::Friction { normal, mu });
                    b.push(-row_velocity(&ru, &free) + d.tangent_goal);
                    vars.push(Var::U(k));
                }
                rows.push(rw);
                dirs.push(rw);
                kinds.push(RowKind::Friction { normal, mu });
                b.push(-row_velocity(&rw, &free));
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
                let mut trial = vel.clone();
                for (j, resp) in responses.iter().enumerate() {
                    resp.add_to(-sol.x[j], &mut trial);
                }
                let mut changed = false;
                for (j, var) in vars.iter().enumerate() {
                    let Var::Normal(k) = *var else { continue };
                    if decisions[k].normal != NormalCase::Resting {
                        continue;
                    }
                    let incoming = -row_velocity(&rows[j], &trial);
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
