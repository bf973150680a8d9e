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
//!   forward step only bounces above the cutoff. This is the authors' case 2 (Figure 5.1): the
//!   contact did not push, and its rows are left out (zero impulse).
//! * `v_N < δ`: resting or inelastic (§5.2.3). LCP (5.5): incoming speed at least the chosen
//!   lift-off goal (`0` by default, below `ε` so the forward step treats it as inelastic).
//! * `|v_T| > δ`: sliding, friction was maximal and opposed the slip (5.6), the "goal ±∞" of
//!   (5.7). The first tangent is aligned with the slip and its impulse is fixed at `−μ f_N`,
//!   which folds it into the normal's column (the non-symmetric matrix of §3.6.1).
//! * `|v_T| ≤ δ`: friction is free inside its bounds and drives the earlier tangential velocity
//!   towards a chosen goal (5.7)–(5.8), along a chosen direction; zero by default.
//!
//! * Round bodies (§5.3.5): three rolling-friction rows (5.15)–(5.17) per contact, bounded by
//!   the rolling arm times the normal impulse. While the pair rotates relative to each other the
//!   first axis is aligned with the rotation and its torque impulse is maximal against it (5.18),
//!   folded into the normal's column exactly like sliding friction; otherwise the rows are free
//!   and keep the earlier relative rotation at zero.
//!
//! # Repairs that keep the step forward-valid
//!
//! Figure 5.5 alone leaves two ways for the result to be a state no forward step produces, and
//! the step repairs both before it returns (at most a few re-solves of the affected islands):
//!
//! * **Look-ahead.** The next backward step takes its Jacobian at `x − Δt v⁻`, not at `x`. When a
//!   body rotates (a box pivoting on an edge, tipping, rocking), its contact points and normals
//!   move between the two poses, so "no approach at `x`" becomes an approach (or a creep below
//!   `δ`) at `x − Δt v⁻`, which no forward step ends with. The step predicts the next poses,
//!   asks the narrow phase for those contacts (on copies of its manifolds), and shifts the
//!   goals of its pushing resting contacts and sticking friction by the difference, so that the
//!   next step sees exactly zero normal and tangential velocity there. The shift is a tiny
//!   incoming speed (positive or negative, far below `ε`), which is what a forward step of a
//!   pivoting body has too. Islands where no body turns by more than round-off, or only balls
//!   turn (a ball's contacts do not move when it spins), skip all of this, so a resting scene
//!   costs what a forward step costs.
//! * **Cutoffs.** A resting contact must arrive slower than `ε` and an elastic one exactly at
//!   `v_N / α`, or the forward step would bounce it; an impulse-free neighbour can break either
//!   (see `repair_cutoffs`).
//!
//! # Joints (§5.3.4)
//!
//! Joint rows enter the island's LCP unchanged, as equality rows, except that the Baumgarte
//! term changes sign: the backward step asks `J v_{t−Δt} = +β e / Δt` of a row with position
//! error `e` at the poses of `t − Δt`, so that the error shrinks as the run goes further back
//! (the next poses are `x − Δt v_{t−Δt}`). The forward step that would replay this one asks
//! `J v_t` of the same rows, which the state at `t` fixes; the report's contact set records
//! that value as each row's goal ([`crate::JointRow::goal`]), so that
//! [`World::step_forward_with`] returns exactly `v_t`. How far it is from the forward
//! Baumgarte goal `−β e / Δt` is part of [`BackwardReport::forward_residual`]: zero for a state
//! a forward step produced, about `2 β |e| / Δt` (tiny: `e` is the drift) along a backward run.
//!
//! What is left unexplained is measured every step: [`BackwardReport::forward_residual`].
//! None of the plausibility heuristics of §5.3 (reverse damping, restitution pushed to 1,
//! sticky stacks) are applied here.

use std::collections::BTreeMap;

use nalgebra::{DVector, Vector3};

use crate::body::Body;
use crate::contact::{Contact, ContactSet, Island, JacobianRow, Partner};
use crate::lcp::{self, LcpProblem, LcpStatus, RowKind};
use crate::step::{contact_rows, disable_non_finite, rolling_rows};
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
    /// Scale in `[0, 1]` of the friction coefficient used *by the backward decision* for a
    /// pair, as [`Self::restitution`] (absent: 1). The rattling heuristic lowers it after an
    /// elastic contact: reversed sliding friction at a bounce adds `μ f_N |v_T|` of energy
    /// (§5.3.1 advises small friction coefficients for reversibility). The contact set keeps
    /// the material's value, so [`BackwardReport::forward_residual`] measures the departure.
    pub friction_scale: BTreeMap<(usize, Partner), f64>,
    /// Per body, a restitution floor used by the backward decision at every contact of the
    /// body (the larger of it and the pair's): the energy-budget heuristic
    /// ([`crate::run::Heuristics::energy_budget`]) raises it to 1 for a body that has gained as
    /// much as it may, so that it gains no more. Departures are measured as for
    /// [`Self::restitution`].
    pub body_restitution: BTreeMap<usize, f64>,
    /// As [`Self::body_restitution`], but only at the body's contacts whose normal is more than
    /// 45° from the vertical (walls, sides of other bodies): a bounce off the ground may still
    /// gain height going back, which a fall explains, but not speed along it.
    pub body_side_restitution: BTreeMap<usize, f64>,
    /// Per body, a scale in `[0, 1]` of the friction coefficient of every contact of the body
    /// (the smaller of the two bodies' applies, times the pair's [`Self::friction_scale`]): the
    /// energy-budget heuristic sets 0 for a body whose speed a fall can no longer explain, since
    /// reversed friction is what speeds it up.
    pub body_friction_scale: BTreeMap<usize, f64>,
    /// Per body, the last rung of a backward bounce ladder ([`ApexFinish`]): a bounce off static
    /// ground may send the body up at the speed that brings it to its apex exactly at the run's
    /// first frame.
    pub apex_finish: BTreeMap<usize, ApexFinish>,
    /// Skip [`BackwardReport::forward_residual`] (it is then NaN): a diagnostic that builds
    /// every island's forward LCP again, 6 % of a step on the word scene. A run that measures
    /// no departures ([`crate::run::ReverseSettings::measure_departure`] off, as `mwb reverse`
    /// samples) skips it.
    pub skip_forward_residual: bool,
    /// The stacking heuristic of §5.3.3: a resting contact between two bodies that are not
    /// free to bounce (or between such a body and static geometry) is held, allowing the
    /// normal impulse to pull, so a stack does not fly apart when stepped backward. `None`:
    /// off. The value caps the pulling impulse (and the friction impulse) of a held contact in
    /// units of the body's weight times `Δt`.
    pub stacking_glue: Option<f64>,
}

/// The last rung of a round body's backward bounce ladder (ours). Going back, each bounce off
/// the floor divides the body's vertical speed by the restitution, so its flights grow, but
/// rung by rung: the run's first frame can find it low, between two bounces (lorem: 8 % of its
/// balls still in their bins). A bounce off static geometry whose normal is within 45° of the
/// vertical, elastic in the backward decision, that would bring the body back down before the
/// first frame (it leaves at `v_n / α < g · seconds`) leaves instead at `g · seconds`, so that
/// it reaches its apex at the first frame — provided the bounce, played forward (`v_n` over
/// that speed), keeps at least `min_ratio` of the material's restitution. Played forward, the
/// body starts at rest in mid-air, falls, and its first bounce is deader than its material's
/// (lorem: the 5 % deadest keep 0.43 of their speed against the material's 0.55); the rest
/// are its material's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ApexFinish {
    /// Time (s) from the end of this backward step to the run's first frame.
    pub seconds: f64,
    /// Smallest fraction of the material's restitution the bounce may keep, in `(0, 1]`.
    pub min_ratio: f64,
}

impl ApexFinish {
    /// The elastic goal (incoming normal speed, m/s) of a bounce at separating speed `v_n`
    /// with the decision's restitution `alpha` and the material's `material` under gravity `g`
    /// (m/s²): `v_n / alpha`, or the apex-finishing speed `g · seconds` where that is faster
    /// and `v_n` is at least `min_ratio · material` of it.
    pub fn goal(&self, v_n: f64, alpha: f64, material: f64, g: f64) -> f64 {
        let natural = v_n / alpha;
        let finish = g * self.seconds;
        if finish.is_finite() && finish > natural && v_n >= self.min_ratio * material * finish {
            finish
        } else {
            natural
        }
    }
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
    /// Friction coefficient the decision used: the contact's, times
    /// [`BackwardChoices::friction_scale`] and [`BackwardChoices::body_friction_scale`].
    pub mu: f64,
    /// Rolling-resistance arm (m) the decision used: the contact's, times
    /// [`BackwardChoices::body_friction_scale`].
    pub rolling: f64,
}

/// What a backward step did; enough to replay it forward.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BackwardReport {
    /// Contacts and Jacobian directions, at the poses of `t − Δt`.
    pub contacts: ContactSet,
    /// Impulses in the forward sense, one per contact.
    pub impulses: Vec<ContactImpulse>,
    /// Joint impulses in the forward sense, one per row of `contacts.joints`.
    pub joint_impulses: Vec<f64>,
    /// One decision per contact.
    pub choices: Vec<ContactChoice>,
    /// One entry per island.
    pub islands: Vec<IslandSolve>,
    /// Forward-LCP residual of `impulses` and `joint_impulses` at the new state
    /// ([`World::forward_residual_with_joints`]): about zero when the step is forward-valid.
    /// NaN when [`BackwardChoices::skip_forward_residual`] asked not to measure it.
    pub forward_residual: f64,
    /// Contacts whose normal velocity at `t` approaches faster than `δ`. No forward step ends
    /// like that (it stops every approach in its contact set), so such a state has no exact
    /// forward-valid predecessor and `forward_residual` will be about that speed. The previous
    /// step's look-ahead removes the approach at contacts it knew; what remains are contacts
    /// that appear only at the earlier poses (a new feature pair of a penetrating, rotating
    /// box).
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
/// Rounds of look-ahead and cutoff repairs per backward step (each re-solves the islands it
/// changed).
const CORRECTION_ROUNDS: usize = 6;
/// Look-ahead corrections below this (m/s) are round-off.
const LOOKAHEAD_TOL: f64 = 1e-13;
/// Islands whose bodies all turn less than this per step (rad) need no look-ahead.
const LOOKAHEAD_ANGLE: f64 = 1e-12;
/// Resting contacts must arrive slower than this fraction of `ε`.
const CUTOFF_MARGIN: f64 = 0.99;
/// Extra shrink of lift-off goals when a neighbour broke the cutoff.
const LIFT_SCALE: f64 = 0.95;

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
    Roll(usize, usize),
    /// A joint row (index into `ContactSet::joints`).
    Joint(usize),
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
        let v_t = v_plus.clone();
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
        let up = (-self.gravity).try_normalize(1e-12);
        let g_abs = self.gravity.norm();

        // Figure 5.5, per contact.
        let mut decisions = Vec::with_capacity(set.contacts.len());
        let mut rolling_slip = Vec::with_capacity(set.contacts.len());
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
            // §5.3.5: rolling friction is maximal against a relative rotation, like sliding
            // friction against a slip (the "goal ±∞" of (5.7) on (5.15)–(5.18)).
            let spin = self.relative_angular_velocity(&set.contacts[k]);
            let c = &mut set.contacts[k];
            rolling_slip.push(c.rolling > 0.0 && c.align_rolling(&spin, delta));
            let partner_body = match c.partner {
                Partner::Body(p) => Some(p),
                Partner::Static(_) => None,
            };
            let this_body = c.body;
            let bodies_here = [Some(this_body), partner_body];
            // The pair's bodies' entries, clamped to [0, 1], folded into `init` (no allocation:
            // most maps are empty).
            let per_body = |map: &BTreeMap<usize, f64>, init: f64, f: fn(f64, f64) -> f64| {
                bodies_here
                    .into_iter()
                    .flatten()
                    .filter_map(|b| map.get(&b).copied())
                    .filter(|x| x.is_finite())
                    .map(|x| x.clamp(0.0, 1.0))
                    .fold(init, f)
            };
            let alpha = choices
                .restitution
                .get(&(c.body, c.partner))
                .copied()
                .filter(|a| a.is_finite())
                .map_or(c.restitution, |a| a.clamp(0.0, 1.0));
            let alpha = per_body(&choices.body_restitution, alpha, f64::max);
            let side = up.is_some_and(|u| c.normal.dot(&u).abs() < std::f64::consts::FRAC_1_SQRT_2);
            let alpha = if side {
                per_body(&choices.body_side_restitution, alpha, f64::max)
            } else {
                alpha
            };
            let body_mu = per_body(&choices.body_friction_scale, 1.0, f64::min);
            let elastic_floor = alpha * eps * (1.0 + 1e-9) + f64::EPSILON;
            if v_n < -delta {
                approaching += 1;
            }
            let finish = match (c.partner, side, choices.apex_finish.get(&c.body)) {
                (Partner::Static(_), false, Some(f)) => Some(f),
                _ => None,
            };
            let (normal, normal_goal) = if v_n >= delta {
                if alpha > 0.0 && v_n > elastic_floor {
                    let goal =
                        finish.map_or(v_n / alpha, |f| f.goal(v_n, alpha, c.restitution, g_abs));
                    (NormalCase::Elastic, goal)
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
            let mu = c.friction
                * body_mu
                * choices
                    .friction_scale
                    .get(&(c.body, c.partner))
                    .copied()
                    .filter(|s| s.is_finite())
                    .map_or(1.0, |s| s.clamp(0.0, 1.0));
            decisions.push(ContactChoice {
                normal,
                friction,
                normal_goal,
                tangent_goal,
                mu,
                rolling: c.rolling * body_mu,
            });
        }

        let n_contacts = set.contacts.len();
        // Goals that ask a contact to leave (lift-offs, landings), as opposed to rest goals.
        let mut lifting: Vec<bool> = decisions
            .iter()
            .map(|d| d.normal == NormalCase::Resting && d.normal_goal > 0.0)
            .collect();
        // A user's slide goal is kept as given; zero tangent goals get the look-ahead.
        let slide_goal: Vec<bool> = decisions.iter().map(|d| d.tangent_goal != 0.0).collect();
        let mut w_goals = vec![0.0; n_contacts];
        // Elastic contacts held to (5.2) with equality (see `repair_cutoffs`).
        let mut exact = vec![false; n_contacts];

        let inv: Vec<InvMass> = self.bodies.iter().map(InvMass::of).collect();
        let gdt = self.gravity * dt;
        // v_t − Δt M⁻¹ f_ext: the earlier velocity before contact impulses are undone.
        let mut free_vel: Vec<[f64; 6]> = v_plus;
        for (b, v) in self.bodies.iter().zip(free_vel.iter_mut()) {
            if b.enabled {
                v[0] -= gdt.x;
                v[1] -= gdt.y;
                v[2] -= gdt.z;
            }
        }
        let mut vel = free_vel.clone();
        let mut solutions: Vec<IslandOutcome> = Vec::with_capacity(set.islands.len());
        let mut dirty = vec![true; set.islands.len()];
        let mut impulses = vec![ContactImpulse::default(); n_contacts];
        let mut joint_impulses = vec![0.0; set.joints.len()];
        for round in 0..=CORRECTION_ROUNDS {
            for (i, island) in set.islands.iter().enumerate() {
                if !dirty[i] {
                    continue;
                }
                for &b in &island.bodies {
                    vel[b] = free_vel[b];
                }
                let outcome = self.solve_backward_island(
                    &set,
                    island,
                    &mut decisions,
                    &mut lifting,
                    (&w_goals, &exact, &rolling_slip),
                    choices,
                    &inv,
                    &vel,
                    dt,
                );
                if let Some(x) = &outcome.x {
                    for (j, resp) in outcome.responses.iter().enumerate() {
                        // v⁻ = (v_t − Δt M⁻¹ f_ext) − M⁻¹ Gᵀ f  (5.9)–(5.11).
                        resp.add_to(-x[j], &mut vel);
                    }
                }
                for &k in &island.contacts {
                    impulses[k] = ContactImpulse::default();
                }
                for &k in &island.joints {
                    joint_impulses[k] = 0.0;
                }
                outcome.write_impulses(
                    (&decisions, &rolling_slip),
                    (&mut impulses, &mut joint_impulses),
                );
                if i < solutions.len() {
                    solutions[i] = outcome;
                } else {
                    solutions.push(outcome);
                }
            }
            if round == CORRECTION_ROUNDS {
                break;
            }
            dirty.fill(false);
            for (i, island) in set.islands.iter().enumerate() {
                if solutions[i].x.is_some()
                    && self.repair_cutoffs(
                        &set,
                        island,
                        (&mut decisions, &mut exact),
                        &lifting,
                        &impulses,
                        &vel,
                    )
                {
                    dirty[i] = true;
                }
            }
            self.look_ahead(
                &set,
                &solutions,
                &mut dirty,
                (&mut decisions, &mut w_goals),
                (&lifting, &slide_goal),
                &impulses,
                &vel,
                dt,
            );
            if !dirty.iter().any(|d| *d) {
                break;
            }
        }
        let islands = solutions.iter().map(|o| o.solve).collect();
        store_velocities(&mut self.bodies, &vel);
        let disabled = disable_non_finite(&mut self.bodies, &before);
        let forward_residual = if choices.skip_forward_residual {
            f64::NAN
        } else {
            self.forward_residual_with_joints(&set, &impulses, &joint_impulses, dt)
        };
        // The replay's joint goals: what the forward step from here must end with, J v_t at
        // these poses (see the module docs).
        for jr in &mut set.joints {
            jr.goal = Some(row_velocity(&jr.row, &v_t));
        }
        BackwardReport {
            contacts: set,
            impulses,
            joint_impulses,
            choices: decisions,
            islands,
            forward_residual,
            approaching_contacts: approaching,
            unsupported_pairs: unsupported,
            disabled,
        }
    }

    /// Builds and solves the backward LCP of one island with the current decisions and goals.
    /// `vel` holds the free velocities of the island's bodies. Landings too slow to leave the
    /// prediction band get raised goals here (and become `lifting`).
    #[allow(clippy::too_many_arguments)]
    fn solve_backward_island(
        &self,
        set: &ContactSet,
        island: &Island,
        decisions: &mut [ContactChoice],
        lifting: &mut [bool],
        (w_goals, exact, rolling_slip): (&[f64], &[bool], &[bool]),
        choices: &BackwardChoices,
        inv: &[InvMass],
        vel: &[[f64; 6]],
        dt: f64,
    ) -> IslandOutcome {
        let eps = self.params.restitution_cutoff;
        let delta = self.params.rest_threshold;
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
            let mu = d.mu;
            if d.normal == NormalCase::Held {
                // §5.3.3: hold the contact, w = 0 while the impulses stay inside ±cap.
                let weight = self.gravity.norm() * dt / self.bodies[c.body].inv_mass;
                let cap = choices.stacking_glue.unwrap_or(0.0).max(0.0) * weight;
                for (row, var, hi, goal) in [
                    (rn, Var::Normal(k), f64::INFINITY, -d.normal_goal),
                    (ru, Var::U(k), cap, d.tangent_goal),
                    (rw, Var::W(k), cap, w_goals[k]),
                ] {
                    rows.push(row);
                    dirs.push(row);
                    kinds.push(RowKind::Bounded { lo: -cap, hi });
                    b.push(-row_velocity(&row, vel) + goal);
                    vars.push(var);
                }
                continue;
            }
            let rolling = rolling_rows(c);
            let normal_dir = {
                let slid = match d.friction {
                    FrictionCase::Sliding => fold(&rn, &ru, mu),
                    FrictionCase::Sticking => rn,
                };
                match &rolling {
                    Some([r0, _, _]) if rolling_slip[k] => fold(&slid, r0, d.rolling),
                    _ => slid,
                }
            };
            if exact[k] && d.normal == NormalCase::Elastic {
                // (5.2) with equality; friction only through the folds of a sliding or
                // rolling contact (the free rows would need a normal row that cannot pull).
                rows.push(rn);
                dirs.push(normal_dir);
                kinds.push(RowKind::Equality);
                b.push(-row_velocity(&rn, vel) - d.normal_goal);
                vars.push(Var::Normal(k));
                continue;
            }
            // Normal: w = −v⁻_N − goal (5.3)/(5.5).
            rows.push(rn);
            dirs.push(normal_dir);
            kinds.push(RowKind::Normal);
            b.push(-row_velocity(&rn, vel) - d.normal_goal);
            vars.push(Var::Normal(k));
            // Friction: w = −(v⁻_T − goal_T) (5.7); interior impulse ⇒ the goal is met.
            if d.friction == FrictionCase::Sticking {
                rows.push(ru);
                dirs.push(ru);
                kinds.push(RowKind::Friction { normal, mu });
                b.push(-row_velocity(&ru, vel) + d.tangent_goal);
                vars.push(Var::U(k));
            }
            rows.push(rw);
            dirs.push(rw);
            kinds.push(RowKind::Friction { normal, mu });
            b.push(-row_velocity(&rw, vel) + w_goals[k]);
            vars.push(Var::W(k));
            // Rolling rows (5.15)–(5.17): the first axis is folded into the normal while the
            // contact rolls; free rows keep the earlier relative rotation at zero otherwise.
            let skip = usize::from(rolling_slip[k]);
            for (axis, row) in rolling.into_iter().flatten().enumerate().skip(skip) {
                rows.push(row);
                dirs.push(row);
                kinds.push(RowKind::Friction {
                    normal,
                    mu: d.rolling,
                });
                b.push(-row_velocity(&row, vel));
                vars.push(Var::Roll(k, axis));
            }
        }
        // §5.3.4: joint rows as in the forward step, with the Baumgarte sign reversed:
        // w = −J v⁻ + β e / Δt = 0.
        let erp = self.params.joint_erp;
        for &k in &island.joints {
            let jr = &set.joints[k];
            rows.push(jr.row);
            dirs.push(jr.row);
            kinds.push(RowKind::Equality);
            b.push(-row_velocity(&jr.row, vel) + jr.backward_goal(erp, dt));
            vars.push(Var::Joint(k));
        }
        let n = rows.len();
        let failed = |responses: Vec<Response>, vars: Vec<Var>| IslandOutcome {
            solve: IslandSolve {
                status: LcpStatus::Degenerate,
                residual: f64::NAN,
                rows: n,
                pivots: 0,
            },
            x: None,
            responses,
            vars,
        };
        if rows.is_empty() {
            return IslandOutcome {
                solve: IslandSolve {
                    status: LcpStatus::Solved,
                    residual: 0.0,
                    rows: 0,
                    pivots: 0,
                },
                x: None,
                responses: Vec::new(),
                vars,
            };
        }
        let responses: Vec<Response> = dirs.iter().map(|r| Response::new(r, inv)).collect();
        let a = delassus(&rows, &responses);
        let Ok(mut problem) = LcpProblem::new(a, DVector::from_vec(b), kinds) else {
            return failed(responses, vars);
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
                let incoming = -(row_velocity(&rows[j], vel) - undone[j]);
                // A resting contact meeting a small look-ahead goal is not landing.
                if !lifting[k] && incoming - decisions[k].normal_goal <= LIFT_NOISE {
                    continue;
                }
                let clearance = (self.params.prediction - set.contacts[k].dist).max(0.0);
                let needed = LIFT_CLEARANCE * clearance / dt + delta;
                if incoming > LIFT_NOISE
                    && incoming < needed
                    && needed < 0.99 * eps
                    && decisions[k].normal_goal < needed
                {
                    problem.b[j] -= needed - decisions[k].normal_goal;
                    decisions[k].normal_goal = needed;
                    lifting[k] = true;
                    changed = true;
                }
            }
            if !changed {
                break;
            }
            solved = lcp::solve(&problem, &self.params.lcp);
        }
        let Ok(sol) = solved else {
            return failed(responses, vars);
        };
        let finite = sol.x.iter().all(|v| v.is_finite());
        IslandOutcome {
            solve: IslandSolve {
                status: if finite {
                    sol.status
                } else {
                    LcpStatus::Degenerate
                },
                residual: sol.residual,
                rows: n,
                pivots: sol.pivots,
            },
            x: finite.then_some(sol.x),
            responses,
            vars,
        }
    }

    /// The restitution cutoff seen from the forward step (§3.5): a contact whose earlier
    /// incoming speed exceeds `ε` bounces, so the backward solution must not leave one there
    /// unless it explains the bounce. Two repairs, each followed by a re-solve:
    ///
    /// * a resting contact that arrives faster than `ε` without pushing, because lift-offs of
    ///   its neighbours rotated the body (lifting three corners of a box at one speed drives
    ///   the fourth at twice that speed): the island's lift-off goals are scaled down;
    /// * an elastic contact (5.3) that ended up not pushing while arriving faster than its
    ///   goal (the relaxation of (5.2)): a forward step would bounce it harder than `v_N`, so
    ///   (5.2) is imposed with equality, which makes its neighbours push less; if even then
    ///   it would have to pull, it is re-explained as case 2 of Figure 5.1 (no impulse).
    ///
    /// Returns whether anything changed.
    fn repair_cutoffs(
        &self,
        set: &ContactSet,
        island: &Island,
        (decisions, exact): (&mut [ContactChoice], &mut [bool]),
        lifting: &[bool],
        impulses: &[ContactImpulse],
        vel: &[[f64; 6]],
    ) -> bool {
        let eps = self.params.restitution_cutoff;
        let mut worst = 0.0f64;
        let mut changed = false;
        for &k in &island.contacts {
            let c = &set.contacts[k];
            if c.restitution <= 0.0 {
                continue;
            }
            let incoming = -row_velocity(&JacobianRow::new(c, &c.normal, &self.bodies), vel);
            let d = decisions[k];
            match d.normal {
                NormalCase::Resting if incoming > CUTOFF_MARGIN * eps => {
                    worst = worst.max(incoming);
                }
                NormalCase::Elastic if exact[k] && impulses[k].normal < 0.0 => {
                    // Even with equality the contact would have to pull: no bounce explains
                    // it, so it did not push (case 2 of Figure 5.1), and stays invalid unless
                    // it arrives below ε.
                    exact[k] = false;
                    decisions[k].normal = NormalCase::Separating;
                    decisions[k].normal_goal = 0.0;
                    changed = true;
                }
                NormalCase::Elastic
                    if !exact[k]
                        && impulses[k].normal <= 0.0
                        && incoming > eps
                        && incoming - d.normal_goal > 1e-9 * d.normal_goal.max(1.0) =>
                {
                    exact[k] = true;
                    changed = true;
                }
                _ => {}
            }
        }
        if worst > 0.0 {
            let scale = LIFT_SCALE * CUTOFF_MARGIN * eps / worst;
            for &k in &island.contacts {
                if lifting[k] && decisions[k].normal_goal > 0.0 {
                    decisions[k].normal_goal *= scale;
                    changed = true;
                }
            }
        }
        changed
    }

    /// Looks one step further back (see the [module docs](self)): at the poses the next
    /// backward step will start from, `x − Δt v⁻`, the contacts that rest now must still rest
    /// (`J' v⁻ = 0` along the normal, no slip when friction sticks), or the next step starts
    /// from a state no forward step produces (approaching, or creeping below `δ`). Where the
    /// next Jacobian `J'` differs from this step's `J` (a body rotates, so its contact points
    /// and normals move), the goals are shifted by the difference and the island is marked
    /// for a re-solve. Only islands with a rotating body can differ.
    #[allow(clippy::too_many_arguments)]
    fn look_ahead(
        &self,
        set: &ContactSet,
        solutions: &[IslandOutcome],
        dirty: &mut [bool],
        (decisions, w_goals): (&mut [ContactChoice], &mut [f64]),
        (lifting, slide_goal): (&[bool], &[bool]),
        impulses: &[ContactImpulse],
        vel: &[[f64; 6]],
        dt: f64,
    ) {
        let eps = self.params.restitution_cutoff;
        // Round-off leaves resting bodies with |ω| ~ 1e-16 rad/s; a turn of LOOKAHEAD_ANGLE
        // per step moves no contact point or normal enough to change the next step's
        // velocities by LOOKAHEAD_TOL, so such islands are not looked at. A ball turning
        // about its centre moves neither its contact points nor its normals.
        let rotating = |b: usize| {
            let [.., wx, wy, wz] = vel[b];
            let body = &self.bodies[b];
            body.enabled
                && body.shape.as_ball().is_none()
                && Vector3::new(wx, wy, wz).norm() * dt > LOOKAHEAD_ANGLE
        };
        let look: Vec<usize> = set
            .islands
            .iter()
            .enumerate()
            .filter(|(i, island)| {
                solutions[*i].x.is_some() && island.bodies.iter().any(|&b| rotating(b))
            })
            .map(|(i, _)| i)
            .collect();
        if look.is_empty() {
            return;
        }
        // Only the bodies of the looked-at islands move to their next poses (partners of
        // their contacts are in the same island or static).
        let mut ahead: BTreeMap<usize, Body> = BTreeMap::new();
        for &i in &look {
            for &b in &set.islands[i].bodies {
                let mut body = self.bodies[b].clone();
                let [vx, vy, vz, wx, wy, wz] = vel[b];
                body.linvel = Vector3::new(vx, vy, vz);
                body.angvel = Vector3::new(wx, wy, wz);
                if body.enabled {
                    body.position -= body.linvel * dt;
                    body.orientation = rotate(&body.orientation, &body.angvel, -dt);
                }
                ahead.insert(b, body);
            }
        }
        let mut keys: Vec<(usize, Partner)> = look
            .iter()
            .flat_map(|&i| set.islands[i].contacts.iter())
            .map(|&k| (set.contacts[k].body, set.contacts[k].partner))
            .collect();
        keys.sort_unstable();
        keys.dedup();
        let predicted = self.narrow_phase.predict(
            &keys,
            |b| ahead.get(&b),
            &self.statics,
            self.params.prediction,
        );
        let by_feature: BTreeMap<(usize, Partner, (u32, u32)), &Contact> = predicted
            .iter()
            .rev() // the first of duplicates wins, as a linear search would pick it
            .map(|p| ((p.body, p.partner, p.features), p))
            .collect();
        let point_velocity = |b: usize, c: &Contact| {
            ahead
                .get(&b)
                .map_or(Vector3::zeros(), |body| body.point_velocity(&c.point))
        };
        let relative = |c: &Contact| {
            let va = point_velocity(c.body, c);
            match c.partner {
                Partner::Body(p) => va - point_velocity(p, c),
                Partner::Static(_) => va,
            }
        };
        for &i in &look {
            let mut changed = false;
            for &k in &set.islands[i].contacts {
                let c = &set.contacts[k];
                let d = decisions[k];
                if !matches!(d.normal, NormalCase::Resting | NormalCase::Held) {
                    continue;
                }
                let Some(&next) = by_feature.get(&(c.body, c.partner, c.features)) else {
                    continue;
                };
                let rel = relative(next);
                let v_n = next.normal.dot(&rel);
                let f = impulses[k];
                let pushing = d.normal == NormalCase::Held || f.normal > 0.0;
                if pushing {
                    // Pushing contacts meet their goal with equality, so the next step's
                    // normal velocity moves one for one with the goal.
                    let shift = if lifting[k] { v_n.min(0.0) } else { v_n };
                    if shift.abs() > LOOKAHEAD_TOL {
                        decisions[k].normal_goal = (d.normal_goal + shift).min(CUTOFF_MARGIN * eps);
                        changed = true;
                    }
                }
                let interior = match d.normal {
                    NormalCase::Held => true,
                    _ => {
                        let bound = d.mu * f.normal * (1.0 - 1e-9);
                        f.normal > 0.0 && f.tangent_u.abs() < bound && f.tangent_w.abs() < bound
                    }
                };
                if d.friction == FrictionCase::Sticking && !slide_goal[k] && interior {
                    let slip = rel - next.normal * v_n;
                    let (du, dw) = (slip.dot(&c.tangent_u), slip.dot(&c.tangent_w));
                    if du.abs() > LOOKAHEAD_TOL || dw.abs() > LOOKAHEAD_TOL {
                        decisions[k].tangent_goal -= du;
                        w_goals[k] -= dw;
                        changed = true;
                    }
                }
            }
            if changed {
                dirty[i] = true;
            }
        }
    }
}

/// One island's backward solve.
struct IslandOutcome {
    solve: IslandSolve,
    /// The impulses (`None`: no finite solution; velocities keep their free values).
    x: Option<DVector<f64>>,
    responses: Vec<Response>,
    vars: Vec<Var>,
}

impl IslandOutcome {
    /// Writes the island's impulses, in the forward sense, into `impulses`.
    fn write_impulses(
        &self,
        (decisions, rolling_slip): (&[ContactChoice], &[bool]),
        (impulses, joint_impulses): (&mut [ContactImpulse], &mut [f64]),
    ) {
        let Some(x) = &self.x else { return };
        for (j, var) in self.vars.iter().enumerate() {
            match *var {
                Var::Normal(k) => {
                    impulses[k].normal = x[j];
                    if decisions[k].friction == FrictionCase::Sliding
                        && decisions[k].normal != NormalCase::Held
                    {
                        impulses[k].tangent_u = -decisions[k].mu * x[j];
                    }
                    if rolling_slip[k] && decisions[k].normal != NormalCase::Held {
                        impulses[k].rolling[0] = -decisions[k].rolling * x[j];
                    }
                }
                Var::Roll(k, axis) => impulses[k].rolling[axis] = x[j],
                Var::U(k) => impulses[k].tangent_u = x[j],
                Var::W(k) => impulses[k].tangent_w = x[j],
                Var::Joint(k) => joint_impulses[k] = x[j],
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{ApexFinish, BackwardChoices};
    use crate::scene::{builtin, world_from_toml};

    #[test]
    fn skipping_the_forward_residual_changes_nothing_else() {
        let Ok(world) = world_from_toml(builtin::WORD, "word") else {
            panic!("word scene");
        };
        let (mut measured, mut skipped) = (world.clone(), world);
        let skip = BackwardChoices {
            skip_forward_residual: true,
            ..Default::default()
        };
        for _ in 0..30 {
            let a = measured.step_backward(1.0 / 120.0, &BackwardChoices::default());
            let b = skipped.step_backward(1.0 / 120.0, &skip);
            assert!(a.forward_residual.is_finite());
            assert!(b.forward_residual.is_nan());
            assert_eq!(a.impulses, b.impulses);
        }
        for (a, b) in measured.bodies.iter().zip(&skipped.bodies) {
            assert_eq!(a.position, b.position);
            assert_eq!(a.linvel, b.linvel);
            assert_eq!(a.angvel, b.angvel);
        }
    }

    #[test]
    fn the_last_rung_reaches_its_apex_when_the_bounce_may_keep_that_little() {
        // g = 10, 0.5 s left: the apex-finishing speed is 5 m/s.
        let f = ApexFinish {
            seconds: 0.5,
            min_ratio: 0.5,
        };
        // Leaving at 3 m/s with α = 0.5: naturally 6 m/s, faster than finishing: unchanged (it
        // flies past the first frame).
        assert_eq!(f.goal(3.0, 0.5, 0.5, 10.0), 6.0);
        // 1 m/s: naturally 2 m/s (back down after 0.4 s); finishing keeps 1/5 = 0.2 of its
        // speed, under half the material's 0.5: unchanged.
        assert_eq!(f.goal(1.0, 0.5, 0.5, 10.0), 2.0);
        // 1.4 m/s with the material at 0.5 but the rattling blend's α = 0.8: naturally 1.75 m/s;
        // finishing keeps 1.4/5 = 0.28 ≥ 0.25: it leaves at 5 m/s.
        assert_eq!(f.goal(1.4, 0.8, 0.5, 10.0), 5.0);
        // Exactly at the bound, and just under it.
        assert_eq!(f.goal(1.25, 0.5, 0.5, 10.0), 5.0);
        assert_eq!(f.goal(1.24, 0.5, 0.5, 10.0), 1.24 / 0.5);
        // No time left, or none that is finite: natural.
        let none = ApexFinish {
            seconds: 0.0,
            min_ratio: 0.5,
        };
        assert_eq!(none.goal(1.0, 0.5, 0.5, 10.0), 2.0);
        let inf = ApexFinish {
            seconds: f64::INFINITY,
            min_ratio: 0.5,
        };
        assert_eq!(inf.goal(1.0, 0.5, 0.5, 10.0), 2.0);
    }
}
