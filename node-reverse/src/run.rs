//! Backward runs (§5.3–5.4): many backward steps from a final (or intermediate) state, with the
//! free choices of Figure 5.5 sampled from a seed, the plausibility heuristics of §5.3, and the
//! measurements a user needs to rank or drop implausible worlds (§5.3.1).
//!
//! * [`run_backward`]: the world's state is the *last* frame; steps go back in time and the
//!   result is returned time-ordered (played forward), so it can be stored like any world.
//! * [`run_mixed`]: the state is an intermediate frame; a backward run leads into it and a
//!   forward run leads out of it, joined into one world (§5.4.4).
//!
//! A world is `(scene, seed, settings)`: the same three give the same frames, bit for bit.

use std::collections::{BTreeMap, BTreeSet};

use mwb_core::rng::{Stream, WorldRng};
use nalgebra::{UnitQuaternion, Vector3};

use crate::backward::{
    ApexFinish, BackwardChoices, BodyHint, LiftPlan, NormalCase, free_to_bounce,
};
use crate::chain::{ACTIVE_IMPULSE, ContactChain, MAX_STATE};
use crate::contact::{ContactSet, Partner};
use crate::plausible::{Plausibility, PlausibilityMeter};
use crate::{Body, World};

/// Time over which restitution blends back from 1 to the material's value after an elastic
/// contact between a pair (§5.3.1: 0.2 s).
pub const DEFAULT_RATTLE_BLEND: f64 = 0.2;
/// Default fraction of a pair's friction coefficient that the backward step uses right after
/// an elastic contact between the pair, blended back to 1 over the rattle time (§5.3.1).
pub const DEFAULT_RATTLE_FRICTION: f64 = 0.25;
/// Default cap of a held contact's pulling impulse, in body weights × Δt (§5.3.3).
pub const DEFAULT_STACKING_GLUE: f64 = 20.0;
/// A replayed step whose velocities differ by less than this (relative) is forward-valid.
pub const FORWARD_VALID_REL: f64 = 1e-6;

/// The plausibility heuristics of §5.3. Each bends physics on purpose; each is measured by
/// [`BackwardRunReport::max_departure`] when [`ReverseSettings::measure_departure`] is on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Heuristics {
    /// `k_d` (1/s) of the reverse angular damping (5.14): every backward step scales angular
    /// velocity by `1 / (1 + k_d Δt)`, per unit inertia. Played forward, bodies seem to spin up
    /// into their collisions; too much makes them "skittle" (§5.4.4). Off (0) by default.
    pub reverse_angular_damping: f64,
    /// Rattling (§5.3.1): after an elastic contact between a pair, the restitution the backward
    /// step uses for that pair is 1 and blends linearly back to the material's over this many
    /// seconds. `None`: off. Default 0.2 s.
    pub rattle_blend: Option<f64>,
    /// Rattling, friction (§5.3.1: reversibility wants restitution near 1 *and* small friction
    /// coefficients): while the restitution of a pair is raised, the backward step also uses
    /// only this fraction of the pair's friction coefficient, blended back to the full value
    /// over the same time. Reversed sliding friction adds `μ f_N |v_T|` of energy and spin at
    /// every bounce; on the word scene it was about 80 % of the energy gained.
    /// `None` (or 1): off; needs `rattle_blend`. Default [`DEFAULT_RATTLE_FRICTION`].
    pub rattle_friction: Option<f64>,
    /// Stacking (§5.3.3): only bodies that pass the free-to-bounce test get sampled lift-offs
    /// and slides, and resting contacts inside a stack are held with this pull cap (body
    /// weights × Δt). `None`: off. Default [`DEFAULT_STACKING_GLUE`].
    pub stacking_glue: Option<f64>,
    /// Energy budget per body (ours, for the plausibility test of [`crate::plausible`]), as a
    /// fraction of [`crate::plausible::PLAUSIBILITY_ALLOWANCE_M`]. A body's *debt* is its
    /// energy height minus the highest point it can be shown to fall from (the highest point it
    /// reached so far in the run or, rising backward, the apex it is flying to) minus the
    /// budget — or, if more, its energy height minus the last frame's minus
    /// [`ENERGY_CAP_FRACTION`] of [`crate::plausible::MAX_ENERGY_GROWTH_M`] (clause 2). A body
    /// the run sends off (a lift-off or a slide, sampled or asked for) is granted, on top of
    /// the budget, the energy height `v²/2g` of the fastest speed it was given.
    ///
    /// * Before a step, a body in debt (by more than 0.1 mm) gets no friction and no rolling
    ///   resistance (reversed, they are what speeds a body up along the ground and spins it)
    ///   and restitution 1 at its
    ///   contacts more than 45° from the vertical (a bounce off the ground may still gain
    ///   height going back, which a fall explains); a body whose energy height exceeds the
    ///   last frame's by [`ENERGY_CAP_FRACTION`] of [`crate::plausible::MAX_ENERGY_GROWTH_M`]
    ///   gets restitution 1 everywhere.
    /// * After a step, a body whose debt the step raised is given conservative contacts
    ///   (restitution 1, no friction) and the step is taken again (at most once); a body that
    ///   still gains more than 5 cm of debt in the step (an island the LCP left unsolved)
    ///   flies freely through it instead.
    /// * Exempt: a slide the user asked for ([`HintMotion::Slide`]), while it lasts. Going
    ///   back, reversed friction speeds a slide up (played forward it slows to its rest); a
    ///   sampled slide gets no friction once that would put its body in debt beyond its grant,
    ///   so it keeps its sampled speed, while a requested one speeds up as the user expects
    ///   and the world's plausibility says whether a fall explains it.
    ///
    /// `None`: off. Default [`DEFAULT_ENERGY_BUDGET`].
    pub energy_budget: Option<f64>,
    /// Depenetration (ours): after each backward step, bodies that overlap by more than this
    /// many metres plus one step's travel of the contact point are pushed apart to that,
    /// positions only ([`World::depenetrate`]). The stepper corrects no positions, and
    /// neighbours a sampled slide sends into each other otherwise keep sinking in (clause 3 of
    /// [`crate::plausible`]): 2 cm deep between the lorem scene's balls. The travel is left
    /// alone because a bounce ends one step's travel inside its contact: pushing that out too
    /// lifted every bounce by `|v| Δt` and pumped energy into small rattles (word worlds gained
    /// 8 cm instead of 1). `None`: off. Default [`DEFAULT_DEPENETRATION_SLOP`].
    pub depenetration: Option<f64>,
}

/// Default [`Heuristics::depenetration`] (m): well inside the plausibility test's
/// [`crate::plausible::MAX_PENETRATION_M`].
pub const DEFAULT_DEPENETRATION_SLOP: f64 = 0.001;
/// Gauss–Seidel sweeps of [`Heuristics::depenetration`].
const DEPENETRATION_SWEEPS: usize = 4;

/// Default [`Heuristics::energy_budget`]: none beyond the grants. A body gains no energy a fall
/// or its own lift-off does not explain. `mwb bench reverse`, 20 worlds a scene: word worlds
/// are plausible in 16 of 20 with it and 8 of 20 with 0.1 of the allowance.
pub const DEFAULT_ENERGY_BUDGET: f64 = 0.0;
/// See [`Heuristics::energy_budget`].
pub const ENERGY_CAP_FRACTION: f64 = 0.8;
/// A round body lifts off everything only when the run has at most this fraction of its
/// [`ladder_seconds`] left, and, whatever the contact-count chain draws, once the run has at
/// most this fraction of its fastest lift-off's ladder left. The ladder is a model: lorem's
/// balls reached the cap up to 20 % sooner than it says. Measured on lorem, seeds 1–3 (balls
/// with an elastic bounce played forward; balls out of their bins in the first frame), before
/// the forced lift-off and the last rung ([`ApexFinish`]): 1.0 → 527 (seed 1), 95.6 %;
/// 0.9 → 159, 94.9 %; 0.85 → 39–45, 92.9–93.5 %; 0.8 → 6–9, 91.2–92.5 %; no timing: 3 030
/// balls, 98.2 %. With both, seed 1: forced at 0.7 → 6, 99.7 %; 0.8 → 6, 99.9 %; 1.0 → 177,
/// 96.9 %. An elastic bounce is what an animator sees.
pub const LADDER_MARGIN: f64 = 0.8;
/// [`ApexFinish::min_ratio`] of a round body's last rung. Lorem, seed 1, without the forced
/// lift-off ([`LADDER_MARGIN`]): 0.5 → 96.0 % of the balls out of their bins in the first
/// frame, 0.45 → 99.0 %, 0.35 → 99.6 % (first bounces keeping under 0.3 of their speed: 160,
/// 366, 745; the material pair keeps 0.55). With it, 0.45 and 0.5 run alike (99.9 %, none
/// under 0.3): the balls climb high enough that no last rung needs more.
pub const APEX_MIN_RATIO: f64 = 0.5;
/// Debt (m) a backward step may add before the energy budget takes it again conservatively.
const BUDGET_SLACK: f64 = 1e-4;
/// Debt (m) a backward step may add, even with conservative contacts, before the energy budget
/// lets the body fly freely through the step instead.
const MAX_STEP_GAIN_M: f64 = 0.05;

impl Default for Heuristics {
    fn default() -> Self {
        Self {
            reverse_angular_damping: 0.0,
            rattle_blend: Some(DEFAULT_RATTLE_BLEND),
            rattle_friction: Some(DEFAULT_RATTLE_FRICTION),
            stacking_glue: Some(DEFAULT_STACKING_GLUE),
            energy_budget: Some(DEFAULT_ENERGY_BUDGET),
            depenetration: Some(DEFAULT_DEPENETRATION_SLOP),
        }
    }
}

impl Heuristics {
    /// Every heuristic off: each step is a plain §5.2 backward step.
    pub fn off() -> Self {
        Self {
            reverse_angular_damping: 0.0,
            rattle_blend: None,
            rattle_friction: None,
            stacking_glue: None,
            energy_budget: None,
            depenetration: None,
        }
    }
}

/// How the free choices are drawn (Figure 5.5's "user preference" when the user gave none).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sampling {
    /// Lift-off speed of a contact leaving rest, as a fraction of `ε`, uniform in this range.
    pub lift_speed: (f64, f64),
    /// Probability that a body leaving a contact also gets a slide goal (5.7). Round bodies
    /// (those with rolling resistance) never get a sampled slide; a user's `slide` hint
    /// still applies to them.
    pub slide_probability: f64,
    /// Slide speed (m/s), uniform in this range.
    pub slide_speed: (f64, f64),
}

impl Default for Sampling {
    fn default() -> Self {
        Self {
            lift_speed: (0.3, 0.95),
            slide_probability: 0.25,
            slide_speed: (0.05, 0.3),
        }
    }
}

/// What the user wants a body to do (Figure 5.10).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum HintMotion {
    /// Let the contact-count chain decide.
    Free,
    /// Slide in along this direction (world frame; played forward, the body arrives moving
    /// along it). Its length is ignored; the speed is sampled.
    Slide(Vector3<f64>),
    /// Bounce in: all resting contacts lift at once.
    Bounce,
    /// Stay where it is for the whole run.
    Stay,
}

/// A user hint for one body.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UserHint {
    /// What it should do.
    pub motion: HintMotion,
    /// Seconds before the run's last frame before which the body leaves its resting contacts
    /// (played forward: it settles this long before the end, not later). 0: any time.
    pub release_before_end: f64,
}

/// Settings of a backward (or mixed) run.
#[derive(Debug, Clone, PartialEq)]
pub struct ReverseSettings {
    /// Time step (s).
    pub dt: f64,
    /// Simulated time to go back (s).
    pub duration: f64,
    /// §5.3 heuristics.
    pub heuristics: Heuristics,
    /// How free choices are sampled.
    pub sampling: Sampling,
    /// The contact-count chain (§5.3.6); `None`: bodies leave rest only by user hints.
    pub chain: Option<ContactChain>,
    /// User hints by body index.
    pub hints: BTreeMap<usize, UserHint>,
    /// Replay every step forward with its contact set and measure how far it departs from a
    /// forward-valid step (costs one forward step per step), and each step's forward-LCP
    /// residual ([`BackwardRunReport::max_forward_residual`]; the forward LCP built again).
    pub measure_departure: bool,
}

impl Default for ReverseSettings {
    fn default() -> Self {
        Self {
            dt: 1.0 / 120.0,
            duration: 2.0,
            heuristics: Heuristics::default(),
            sampling: Sampling::default(),
            chain: None,
            hints: BTreeMap::new(),
            measure_departure: true,
        }
    }
}

/// A body's pose in one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Centre of mass.
    pub position: Vector3<f64>,
    /// Orientation.
    pub orientation: UnitQuaternion<f64>,
}

/// All bodies' poses at one time.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Time (s) on the played-forward clock; the first frame of a run is at 0.
    pub time: f64,
    /// One pose per body.
    pub poses: Vec<Pose>,
}

impl Frame {
    fn of(world: &World, time: f64) -> Self {
        Self {
            time,
            poses: world
                .bodies
                .iter()
                .map(|b| Pose {
                    position: b.position,
                    orientation: b.orientation,
                })
                .collect(),
        }
    }
}

/// Per-world plausibility measurements (§5.3.1) and what the heuristics cost.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BackwardRunReport {
    /// Backward steps taken.
    pub steps: usize,
    /// Total energy per frame, time-ordered like the frames (J). Kinetic plus potential, with
    /// the `½ Δt m g·v` term that makes it exact for the stepper's free flight (its
    /// semi-implicit Euler otherwise gains `½ m g² Δt²` per backward step).
    pub energy: Vec<f64>,
    /// Energy of the last (given) frame (J).
    pub energy_final: f64,
    /// Peak energy over all frames minus the final energy (J): what the run had to gain
    /// backward — dissipation run in reverse, plus anything implausible.
    pub energy_gain: f64,
    /// [`Self::energy_gain`] as the height (m) the whole mass would have to fall to lose it:
    /// comparable across scenes; a world whose bodies "came from" far higher than the scene
    /// is implausible.
    pub energy_growth: f64,
    /// Largest angular speed of any body in the last frame (rad/s).
    pub angular_speed_final: f64,
    /// Largest angular speed of any body in any frame (rad/s).
    pub angular_speed_peak: f64,
    /// `angular_speed_peak − angular_speed_final` (rad/s): the angular growth of §5.3.1.
    pub angular_speed_growth: f64,
    /// Per body, its largest angular speed (rad/s).
    pub body_angular_speed_peak: Vec<f64>,
    /// Largest forward-LCP residual of a step's impulses (0: every step's impulses are a valid
    /// forward solution with the materials' restitution). NaN when not measured: measured with
    /// the departures ([`ReverseSettings::measure_departure`]).
    pub max_forward_residual: f64,
    /// Mean of the per-step forward residuals (NaN when not measured).
    pub mean_forward_residual: f64,
    /// Largest relative velocity error of a step replayed forward with its own contact set
    /// (NaN when not measured): how far the heuristics bend a step away from forward-valid.
    pub max_departure: f64,
    /// Mean of the per-step departures (NaN when not measured).
    pub mean_departure: f64,
    /// Steps whose departure exceeded [`FORWARD_VALID_REL`].
    pub departed_steps: usize,
    /// Elastic contacts that pushed (collisions explained as bounces, §5.2.2).
    pub elastic_contacts: usize,
    /// Contact lift-offs sampled from the chain or asked by hints.
    pub lifts: usize,
    /// Held contact-steps (stacking heuristic).
    pub held_contacts: usize,
    /// Islands whose LCP came back without a solution.
    pub unsolved_islands: usize,
    /// Contacts still approaching at `t` (no exact forward-valid predecessor).
    pub approaching_contacts: usize,
    /// Bodies disabled for non-finite state.
    pub disabled_bodies: usize,
    /// Steps taken again because they would have put a body over its energy budget
    /// ([`Heuristics::energy_budget`]).
    pub budget_resteps: usize,
    /// Largest position correction of [`Heuristics::depenetration`] in one step (m).
    pub max_depenetration: f64,
    /// Body-steps the energy budget turned into free flight: a body that gained more than
    /// 5 cm of debt in one step even with conservative contacts (an unsolved island).
    pub budget_free_flights: usize,
    /// The world's plausibility ([`crate::plausible`]): of every frame, the forward half of a
    /// mixed world included.
    pub plausibility: Plausibility,
    /// Per body, the numbers the verdict is made of.
    pub plausibility_bodies: Vec<crate::plausible::BodyPeaks>,
}

/// A sampled backward world.
#[derive(Debug, Clone, PartialEq)]
pub struct BackwardRun {
    /// Frames in time order; the last one is the given state.
    pub frames: Vec<Frame>,
    /// Measurements.
    pub report: BackwardRunReport,
}

/// A mixed world (§5.4.4): backward into the given state, forward out of it.
#[derive(Debug, Clone, PartialEq)]
pub struct MixedRun {
    /// Frames in time order.
    pub frames: Vec<Frame>,
    /// Index of the given state in `frames`.
    pub join: usize,
    /// Per body, `(linear, angular)` velocity in `frames[0]` (the earliest state).
    pub first_velocities: Vec<(Vector3<f64>, Vector3<f64>)>,
    /// Measurements of the backward half.
    pub report: BackwardRunReport,
}

/// Mixed into the seed of the run's choice stream (the core `Stream`s name only scene and
/// perturbation draws).
const RUN_SALT: u64 = 0x7265_7665_7273_655f;

/// The energy of the run's energy series: kinetic + potential + `½ Δt m g·v` (see
/// [`BackwardRunReport::energy`]).
pub fn shadow_energy(world: &World, dt: f64) -> f64 {
    world
        .bodies
        .iter()
        .map(|b| {
            let m = 1.0 / b.inv_mass;
            b.kinetic_energy()
                + m * (-world.gravity.dot(&b.position))
                + 0.5 * dt * m * world.gravity.dot(&b.linvel)
        })
        .sum()
}

/// Per body, its active contacts (those that carry an impulse; every touching contact when
/// `impulses` is `None`): how many (`η` of the contact-count chain), and the largest restitution
/// among them (0 without one; what [`ladder_seconds`] climbs with).
fn body_contacts(
    set: &ContactSet,
    impulses: Option<&[crate::ContactImpulse]>,
    n: usize,
) -> (Vec<usize>, Vec<f64>) {
    let (mut eta, mut alpha) = (vec![0usize; n], vec![0.0f64; n]);
    for (k, c) in set.contacts.iter().enumerate() {
        let active = impulses.is_none_or(|i| i.get(k).is_some_and(|i| i.normal > ACTIVE_IMPULSE));
        if !active {
            continue;
        }
        let partner = match c.partner {
            Partner::Body(p) => Some(p),
            Partner::Static(_) => None,
        };
        for b in [Some(c.body), partner].into_iter().flatten() {
            if let (Some(e), Some(a)) = (eta.get_mut(b), alpha.get_mut(b)) {
                *e += 1;
                if c.restitution.is_finite() {
                    *a = a.max(c.restitution);
                }
            }
        }
    }
    (eta, alpha)
}

/// Seconds (backward) from a round body's lift-off at `v0` (m/s) off a floor of restitution
/// `alpha` until its bounces reach the energy cap ([`ENERGY_CAP_FRACTION`] of
/// [`crate::plausible::MAX_ENERGY_GROWTH_M`], `headroom_m` of it left).
///
/// Going back, each bounce off the floor divides the vertical speed by the restitution the
/// backward decision uses: the material's at the first landing, then, with the rattling
/// heuristic on (`blend`), one blended from 1 back to the material's over `blend` seconds since
/// the previous elastic bounce ([`Heuristics::rattle_blend`]). A flight at `v` lasts `2v/g`,
/// whole steps of `dt`, at least one; the first one, from a lift-off slower than a step's
/// gravity, lands at `v0 + g Δt`. Once the next bounce would pass the cap, the budget takes it
/// elastic instead: played forward, the ball bounces like a superball, keeping all its speed,
/// before it bounces like its material. On lorem (seed 1) the balls' climbs took 1.76–2.47 s
/// (median 2.07) and their bounces kept the ratios this ladder uses (0.55, then 0.87 after a
/// 0.06 s flight, 0.74 after 0.12 s, …); the ladder gives 1.9–2.3 s for its lift-off speeds.
/// Infinite when the bounces never grow (restitution 0 or 1).
pub fn ladder_seconds(
    v0: f64,
    alpha: f64,
    g: f64,
    dt: f64,
    blend: Option<f64>,
    headroom_m: f64,
) -> f64 {
    if !(alpha > 0.0 && alpha < 1.0 && g > 0.0 && dt > 0.0 && v0 >= 0.0 && headroom_m >= 0.0) {
        return f64::INFINITY;
    }
    let v_cap = (2.0 * g * headroom_m).sqrt();
    let blend = blend.filter(|b| *b > 0.0 && b.is_finite());
    // The lift-off step, then the first landing at the material's restitution.
    let (mut t, mut v) = (dt, (v0 + g * dt) / alpha);
    if v > v_cap {
        return t;
    }
    // Each bounce multiplies the speed by at least 1 + (1 − alpha) dt / blend, so this many
    // take any start past any cap a scene can state.
    for _ in 0..100_000 {
        let flight = (2.0 * v / (g * dt)).ceil().max(1.0) * dt;
        let a = blend.map_or(alpha, |b| 1.0 - (1.0 - alpha) * (flight / b).min(1.0));
        t += flight;
        v /= a;
        if v > v_cap {
            return t;
        }
    }
    t
}

/// Per body of `world`, how far (m) its energy height exceeds what a fall can explain plus its
/// budget, `fraction` of the allowance ([`Heuristics::energy_budget`]): energy height minus the
/// highest point reached so far (`meter`) or, rising backward, the apex it is flying to, minus
/// the budget — or, if more, how far it exceeds the last frame's energy height plus
/// [`ENERGY_CAP_FRACTION`] of `G` (clause 2 of [`crate::plausible`]: a backward bounce off the
/// floor multiplies a falling body's speed by 1/e, and a few of them lift it from a table-top
/// fall to a fall from the roof). > 0: over budget. NaN (a body gone non-finite) reads as +∞.
fn debts(
    world: &World,
    meter: &PlausibilityMeter,
    dt: f64,
    fraction: f64,
    grants: &[f64],
) -> Vec<f64> {
    let g = world.gravity.norm();
    let up = (-world.gravity)
        .try_normalize(1e-12)
        .unwrap_or(Vector3::z());
    let budget = fraction * crate::plausible::PLAUSIBILITY_ALLOWANCE_M;
    let cap = ENERGY_CAP_FRACTION * crate::plausible::MAX_ENERGY_GROWTH_M;
    world
        .bodies
        .iter()
        .zip(&meter.bodies)
        .enumerate()
        .map(|(b, (body, peaks))| {
            let Some(e) = crate::plausible::energy_height(body, &up, g, dt) else {
                return f64::NEG_INFINITY;
            };
            let budget = budget + grants.get(b).copied().unwrap_or(0.0);
            let h = up.dot(&body.position);
            // Rising backward (falling when played forward): its apex comes later in the run,
            // at the height its vertical motion's energy height names (the stepper's flight
            // conserves it, shadow term included; without the term a rising bounce showed
            // `½ Δt |v_z|` of debt and every growing bounce was taken again elastic).
            let vz = up.dot(&body.linvel);
            let apex = if vz < 0.0 {
                crate::plausible::apex_height(h, vz, g, dt)
            } else {
                h
            };
            // The frames sample a flight's top up to `g Δt²` below its apex.
            let fall = e - (peaks.source_height + g * dt * dt).max(apex) - budget;
            let growth = e - peaks.last_energy_height - cap;
            let d = fall.max(growth);
            if d.is_nan() { f64::INFINITY } else { d }
        })
        .collect()
}

/// The bodies of `world` whose energy height exceeds the last frame's by more than
/// [`ENERGY_CAP_FRACTION`] of [`crate::plausible::MAX_ENERGY_GROWTH_M`].
fn over_cap(world: &World, meter: &PlausibilityMeter, dt: f64) -> Vec<usize> {
    let g = world.gravity.norm();
    let up = (-world.gravity)
        .try_normalize(1e-12)
        .unwrap_or(Vector3::z());
    let cap = ENERGY_CAP_FRACTION * crate::plausible::MAX_ENERGY_GROWTH_M;
    world
        .bodies
        .iter()
        .zip(&meter.bodies)
        .enumerate()
        .filter(|(_, (body, peaks))| {
            crate::plausible::energy_height(body, &up, g, dt)
                .is_some_and(|e| e.is_nan() || e - peaks.last_energy_height > cap)
        })
        .map(|(b, _)| b)
        .collect()
}

/// How much energy height (m) body `b` may still gain before [`over_cap`] takes it: the cap
/// minus what it has already gained over the last frame's energy height (0 when past it).
/// `up` and `g`: the world's, as the run computed them once.
fn cap_headroom(
    world: &World,
    meter: &PlausibilityMeter,
    b: usize,
    (up, g): (&Vector3<f64>, f64),
    dt: f64,
) -> f64 {
    let cap = ENERGY_CAP_FRACTION * crate::plausible::MAX_ENERGY_GROWTH_M;
    match (world.bodies.get(b), meter.bodies.get(b)) {
        (Some(body), Some(peaks)) => crate::plausible::energy_height(body, up, g, dt)
            .map(|e| cap - (e - peaks.last_energy_height))
            .filter(|x| x.is_finite())
            .map_or(0.0, |x| x.max(0.0)),
        _ => 0.0,
    }
}

/// A random unit vector perpendicular to `up`.
fn horizontal(rng: &mut WorldRng, up: &Vector3<f64>) -> Vector3<f64> {
    let (u, w) = crate::contact::default_tangents(up);
    let a = rng.uniform(0.0, std::f64::consts::TAU);
    u * a.cos() + w * a.sin()
}

/// Samples a backward world from `world`'s state, taken as the last frame (see the
/// [module docs](self)). `world` is left at the earliest state.
pub fn run_backward(world: &mut World, seed: u64, settings: &ReverseSettings) -> BackwardRun {
    let (mut run, meter) = run_backward_metered(world, seed, settings, true);
    run.report.plausibility = meter.plausibility();
    run.report.plausibility_bodies = meter.bodies;
    run
}

/// [`run_backward`], and the plausibility meter over its frames (for a mixed run to go on with).
/// `given_is_last`: the given state ends the world (a backward run), so a body rising in it
/// reaches its apex after the world ([`PlausibilityMeter::set_last`]); a mixed run's forward
/// half shows where it goes instead.
fn run_backward_metered(
    world: &mut World,
    seed: u64,
    settings: &ReverseSettings,
    given_is_last: bool,
) -> (BackwardRun, PlausibilityMeter) {
    let dt = if settings.dt.is_finite() && settings.dt > 0.0 {
        settings.dt
    } else {
        1.0 / 120.0
    };
    let steps = if settings.duration.is_finite() && settings.duration > 0.0 {
        (settings.duration / dt).round() as usize
    } else {
        0
    };
    let n = world.bodies.len();
    let up = (-world.gravity)
        .try_normalize(1e-12)
        .unwrap_or(Vector3::z());
    let eps = world.params.restitution_cutoff;
    let g_abs = world.gravity.norm();
    let mut rng = WorldRng::new(seed ^ RUN_SALT, Stream::Perturbation);
    let h = settings.heuristics;
    let s = settings.sampling;

    let mut frames = Vec::with_capacity(steps + 1);
    let end_time = steps as f64 * dt;
    frames.push(Frame::of(world, end_time));
    let mut energy = vec![shadow_energy(world, dt)];
    let mut meter = PlausibilityMeter::new(world, dt);
    if given_is_last {
        meter.set_last(world);
    }
    let mut ang_peak: Vec<f64> = world.bodies.iter().map(|b| b.angvel.norm()).collect();
    let angular_speed_final = ang_peak.iter().copied().fold(0.0, f64::max);
    let mut report = BackwardRunReport {
        angular_speed_final,
        ..Default::default()
    };

    // Contacts at the final frame: every touching contact counts as active.
    let (initial, _) = world.detect_contacts();
    let (mut eta, mut alpha) = body_contacts(&initial, None, n);
    let mut free = free_to_bounce(&initial, n);
    // Slide speeds drawn once per body, so the stream does not depend on when it slides.
    let slide_speed: Vec<f64> = (0..n)
        .map(|_| rng.uniform(s.slide_speed.0, s.slide_speed.1))
        .collect();
    let mut last_elastic: BTreeMap<(usize, Partner), (f64, f64)> = BTreeMap::new();
    // Per body, the energy height (m) of the fastest lift-off or slide the run gave it.
    let mut grants = vec![0.0f64; n];
    let (mut residual_sum, mut departure_sum) = (0.0, 0.0);
    let (mut max_residual, mut max_departure) = (0.0f64, 0.0f64);

    for k in 0..steps {
        let elapsed = k as f64 * dt;
        let mut choices = BackwardChoices {
            stacking_glue: h.stacking_glue,
            skip_forward_residual: !settings.measure_departure,
            ..Default::default()
        };
        for b in 0..n {
            if eta[b] == 0 || !world.bodies[b].enabled {
                continue;
            }
            let hint = settings.hints.get(&b);
            if hint.is_some_and(|u| elapsed < u.release_before_end) {
                continue;
            }
            let user_motion = hint.map(|u| u.motion);
            if h.stacking_glue.is_some() && !free[b] && user_motion.is_none() {
                continue; // §5.3.3: only the top of a pile may leave first.
            }
            match user_motion.unwrap_or(HintMotion::Free) {
                HintMotion::Stay => {}
                HintMotion::Slide(dir) => {
                    let tangential = dir - up * up.dot(&dir);
                    if let Some(d) = tangential.try_normalize(1e-12) {
                        // Just before it stopped, the body was moving along the direction.
                        choices.hints.insert(
                            b,
                            BodyHint {
                                lift_off_speed: 0.0,
                                slide_velocity: d * slide_speed[b],
                            },
                        );
                    }
                }
                HintMotion::Bounce => {
                    let speed = eps * rng.uniform(s.lift_speed.0, s.lift_speed.1);
                    choices.lifts.insert(
                        b,
                        LiftPlan {
                            count: usize::MAX,
                            direction: up,
                            speed,
                        },
                    );
                    report.lifts += eta[b];
                }
                HintMotion::Free => {
                    let Some(chain) = &settings.chain else {
                        continue;
                    };
                    let from = eta[b].min(MAX_STATE);
                    let mut to = chain.sample(from, rng.next_f64());
                    let round = world.bodies[b].rolling_resistance > 0.0;
                    // A round body's bounce ladder, with the energy budget on: the time the run
                    // has left, and how much the body may still gain under the cap.
                    let ladder = (round && h.energy_budget.is_some()).then(|| {
                        (
                            (steps - k) as f64 * dt,
                            cap_headroom(world, &meter, b, (&up, g_abs), dt),
                        )
                    });
                    // A round body still resting when the run has `LADDER_MARGIN` of its
                    // fastest lift-off's ladder left lifts off everything now, whatever the
                    // chain drew: later, its ladder would be too short to carry it to its last
                    // rung ([`ApexFinish`]), and played forward it would start in its bin.
                    if to >= from
                        && let Some((remaining, headroom)) = ladder
                    {
                        let fastest = eps * s.lift_speed.1;
                        let climb =
                            ladder_seconds(fastest, alpha[b], g_abs, dt, h.rattle_blend, headroom);
                        if remaining <= LADDER_MARGIN * climb {
                            to = 0;
                        }
                    }
                    if to >= from {
                        continue;
                    }
                    let count = if to == 0 { eta[b] } else { from - to };
                    let direction = horizontal(&mut rng, &up);
                    let speed = eps * rng.uniform(s.lift_speed.0, s.lift_speed.1);
                    // A round body lifting off everything bounces back higher and higher; it
                    // leaves only as late (going back) as its ladder stays under the energy
                    // cap until the run's first frame ([`ladder_seconds`], [`LADDER_MARGIN`]).
                    // Earlier, the cap took its bounces elastic: played forward, lorem's balls
                    // bounced like superballs, 7 459 elastic bounces among 16 548.
                    if count >= eta[b]
                        && let Some((remaining, headroom)) = ladder
                    {
                        let climb =
                            ladder_seconds(speed, alpha[b], g_abs, dt, h.rattle_blend, headroom);
                        if remaining > LADDER_MARGIN * climb {
                            continue;
                        }
                    }
                    choices.lifts.insert(
                        b,
                        LiftPlan {
                            count,
                            direction,
                            speed,
                        },
                    );
                    report.lifts += count;
                    // A round body does not slide to rest: arriving with speed it rolls on
                    // (§5.3.5's rows let it start rolling instead). Sampled slides sent the
                    // balls of a tight bin into their neighbours, and the knocks spread as
                    // speed no fall explains (balls_small: 0 of 6 worlds plausible with them,
                    // 6 of 6 without; the reference also saw too many balls slide in).
                    if rng.next_f64() < s.slide_probability && !round {
                        let d = horizontal(&mut rng, &up);
                        choices.hints.insert(
                            b,
                            BodyHint {
                                lift_off_speed: 0.0,
                                slide_velocity: d * slide_speed[b],
                            },
                        );
                    }
                }
            }
        }
        if let Some(blend) = h.rattle_blend.filter(|b| *b > 0.0) {
            last_elastic.retain(|_, (t, _)| elapsed - *t < blend);
            let mu_after = h
                .rattle_friction
                .filter(|s| s.is_finite())
                .map(|s| s.clamp(0.0, 1.0));
            for (&pair, &(t, alpha)) in &last_elastic {
                let f = ((elapsed - t) / blend).clamp(0.0, 1.0);
                choices.restitution.insert(pair, 1.0 - (1.0 - alpha) * f);
                if let Some(s) = mu_after {
                    choices.friction_scale.insert(pair, s + (1.0 - s) * f);
                }
            }
        }

        // Grants: a body this step sends off (a lift-off or a slide, sampled or asked for) may
        // carry the energy of the speed it was given, on top of the budget.
        let g = world.gravity.norm().max(f64::MIN_POSITIVE);
        for (&b, lift) in &choices.lifts {
            if let Some(grant) = grants.get_mut(b) {
                *grant = grant.max(lift.speed * lift.speed / (2.0 * g));
            }
        }
        for (&b, hint) in &choices.hints {
            if let Some(grant) = grants.get_mut(b) {
                let v2 = hint.lift_off_speed.powi(2) + hint.slide_velocity.norm_squared();
                *grant = grant.max(v2 / (2.0 * g));
            }
        }
        // A slide the user asked for is exempt from the budget while it lasts: going back,
        // reversed friction speeds it up (played forward, it slows to its rest), as the user
        // expects; the world's plausibility still says whether a fall explains that speed.
        let requested: BTreeSet<usize> = choices
            .hints
            .keys()
            .copied()
            .filter(|b| {
                settings
                    .hints
                    .get(b)
                    .is_some_and(|u| matches!(u.motion, HintMotion::Slide(_)))
            })
            .collect();
        // The last rung of a round body's bounce ladder: once the run has little enough time
        // left that a flight to its first frame stays under the energy cap, a bounce may send
        // the body to its apex exactly there ([`ApexFinish`]).
        let seconds = (steps - k - 1) as f64 * dt;
        let fall = 0.5 * g * seconds * seconds;
        let cap = ENERGY_CAP_FRACTION * crate::plausible::MAX_ENERGY_GROWTH_M;
        if h.energy_budget.is_some() && fall <= cap {
            for (b, body) in world.bodies.iter().enumerate() {
                if body.rolling_resistance > 0.0
                    && body.enabled
                    && grants[b] > 0.0
                    && fall <= cap_headroom(world, &meter, b, (&up, g_abs), dt)
                {
                    choices.apex_finish.insert(
                        b,
                        ApexFinish {
                            seconds,
                            min_ratio: APEX_MIN_RATIO,
                        },
                    );
                }
            }
        }
        if let Some(fraction) = h.energy_budget.filter(|f| f.is_finite()) {
            let debt = debts(world, &meter, dt, fraction, &grants);
            for (b, d) in debt.into_iter().enumerate() {
                if d > BUDGET_SLACK && !requested.contains(&b) {
                    choices.body_friction_scale.insert(b, 0.0);
                    choices.body_side_restitution.insert(b, 1.0);
                }
            }
            for b in over_cap(world, &meter, dt) {
                choices.body_restitution.insert(b, 1.0);
            }
        }

        let at_t = if settings.measure_departure {
            Some(world.clone())
        } else {
            None
        };
        let budget = h.energy_budget.filter(|f| f.is_finite());
        let before = budget.map(|f| (world.clone(), debts(world, &meter, dt, f, &grants)));
        let mut step = world.step_backward(dt, &choices);
        // The energy budget, looking ahead: a body whose debt this step would raise above its
        // budget (or above what it already had) takes the step again with every contact
        // conservative — restitution 1, no friction (one re-step at most).
        if let (Some(fraction), Some((saved, debt_before))) = (budget, before) {
            let debt_after = debts(world, &meter, dt, fraction, &grants);
            let mut again = false;
            for (b, (&d0, &d1)) in debt_before.iter().zip(&debt_after).enumerate() {
                if d1 > d0.max(0.0) + BUDGET_SLACK
                    && !choices.body_restitution.contains_key(&b)
                    && !requested.contains(&b)
                {
                    choices.body_friction_scale.insert(b, 0.0);
                    choices.body_restitution.insert(b, 1.0);
                    again = true;
                }
            }
            if again {
                *world = saved.clone();
                step = world.step_backward(dt, &choices);
                report.budget_resteps += 1;
            }
            // A jump no contact between table-top bodies explains (an island the LCP left
            // unsolved, with whatever impulses it had): the body flies freely through this step.
            let debt_after = debts(world, &meter, dt, fraction, &grants);
            for (b, (&d0, &d1)) in debt_before.iter().zip(&debt_after).enumerate() {
                if d1 - d0.max(0.0) > MAX_STEP_GAIN_M
                    && let (Some(body), Some(was)) = (world.bodies.get_mut(b), saved.bodies.get(b))
                    && body.enabled
                {
                    body.linvel = was.linvel - world.gravity * dt;
                    body.angvel = was.angvel;
                    report.budget_free_flights += 1;
                }
            }
        }
        if h.reverse_angular_damping > 0.0 && h.reverse_angular_damping.is_finite() {
            let scale = 1.0 / (1.0 + h.reverse_angular_damping * dt);
            for b in world.bodies.iter_mut().filter(|b| b.enabled) {
                b.angvel *= scale;
            }
        }
        if let Some(slop) = h.depenetration {
            let moved = world.depenetrate(&mut step.contacts, slop, dt, DEPENETRATION_SWEEPS);
            report.max_depenetration = report.max_depenetration.max(moved);
        }
        if let Some(at_t) = at_t {
            let mut replay = world.clone();
            replay.step_forward_with(&step.contacts, dt);
            let scale = at_t
                .bodies
                .iter()
                .flat_map(|b| b.linvel.iter().chain(b.angvel.iter()))
                .fold(world.gravity.norm() * dt, |m, v| m.max(v.abs()));
            let err = at_t
                .bodies
                .iter()
                .zip(&replay.bodies)
                .map(|(want, got)| {
                    (want.linvel - got.linvel)
                        .amax()
                        .max((want.angvel - got.angvel).amax())
                })
                .fold(0.0, f64::max)
                / scale;
            let err = if err.is_finite() { err } else { f64::INFINITY };
            max_departure = max_departure.max(err);
            departure_sum += err;
            if err > FORWARD_VALID_REL {
                report.departed_steps += 1;
            }
        }
        let r = if step.forward_residual.is_finite() {
            step.forward_residual
        } else {
            f64::INFINITY
        };
        max_residual = max_residual.max(r);
        residual_sum += r;
        for (c, (choice, imp)) in step
            .contacts
            .contacts
            .iter()
            .zip(step.choices.iter().zip(&step.impulses))
        {
            match choice.normal {
                NormalCase::Elastic if imp.normal > ACTIVE_IMPULSE => {
                    report.elastic_contacts += 1;
                    last_elastic.insert((c.body, c.partner), (elapsed, c.restitution));
                }
                NormalCase::Held => report.held_contacts += 1,
                _ => {}
            }
        }
        report.unsolved_islands += step
            .islands
            .iter()
            .filter(|i| !i.status.is_solution())
            .count();
        report.approaching_contacts += step.approaching_contacts;
        report.disabled_bodies += step.disabled.len();
        (eta, alpha) = body_contacts(&step.contacts, Some(&step.impulses), n);
        free = free_to_bounce(&step.contacts, n);

        frames.push(Frame::of(world, end_time - (k + 1) as f64 * dt));
        energy.push(shadow_energy(world, dt));
        meter.observe(world);
        meter.observe_contacts(&step.contacts, world);
        for (p, b) in ang_peak.iter_mut().zip(&world.bodies) {
            *p = p.max(b.angvel.norm());
        }
    }
    meter.set_first(world);
    frames.reverse();
    energy.reverse();
    let energy_final = energy.last().copied().unwrap_or(0.0);
    let peak = energy.iter().copied().fold(energy_final, f64::max);
    let mass: f64 = world.bodies.iter().map(|b: &Body| 1.0 / b.inv_mass).sum();
    let g = world.gravity.norm();
    report.steps = steps;
    report.energy_final = energy_final;
    report.energy_gain = peak - energy_final;
    report.energy_growth = if mass > 0.0 && g > 0.0 {
        report.energy_gain / (mass * g)
    } else {
        report.energy_gain
    };
    report.angular_speed_peak = ang_peak.iter().copied().fold(0.0, f64::max);
    report.angular_speed_growth = report.angular_speed_peak - report.angular_speed_final;
    report.body_angular_speed_peak = ang_peak;
    report.energy = energy;
    if settings.measure_departure {
        report.max_forward_residual = max_residual;
        report.mean_forward_residual = if steps > 0 {
            residual_sum / steps as f64
        } else {
            0.0
        };
        report.max_departure = max_departure;
        report.mean_departure = if steps > 0 {
            departure_sum / steps as f64
        } else {
            0.0
        };
    } else {
        report.max_forward_residual = f64::NAN;
        report.mean_forward_residual = f64::NAN;
        report.max_departure = f64::NAN;
        report.mean_departure = f64::NAN;
    }
    (BackwardRun { frames, report }, meter)
}

/// A mixed world from an intermediate state (§5.4.4): [`run_backward`] for
/// `settings.duration` into the state, then `forward_duration` seconds of forward steps out of
/// it, one time-ordered list of frames with the given state once, at `join`. `world` is left
/// at the end of the forward half.
pub fn run_mixed(
    world: &mut World,
    seed: u64,
    settings: &ReverseSettings,
    forward_duration: f64,
) -> MixedRun {
    let start = world.clone();
    let (back, mut meter) = run_backward_metered(world, seed, settings, false);
    let first_velocities = world.bodies.iter().map(|b| (b.linvel, b.angvel)).collect();
    *world = start;
    let dt = if settings.dt.is_finite() && settings.dt > 0.0 {
        settings.dt
    } else {
        1.0 / 120.0
    };
    let forward_steps = if forward_duration.is_finite() && forward_duration > 0.0 {
        (forward_duration / dt).round() as usize
    } else {
        0
    };
    let mut frames = back.frames;
    let join = frames.len().saturating_sub(1);
    let t0 = frames.last().map_or(0.0, |f| f.time);
    for k in 0..forward_steps {
        // A forward step detects its contacts at the poses it starts from.
        let before = world.clone();
        let forward = world.step_forward(dt);
        meter.observe(world);
        meter.observe_contacts(&forward.contacts, &before);
        frames.push(Frame::of(world, t0 + (k + 1) as f64 * dt));
    }
    meter.set_last(world);
    let mut report = back.report;
    report.plausibility = meter.plausibility();
    report.plausibility_bodies = meter.bodies;
    MixedRun {
        frames,
        join,
        first_velocities,
        report,
    }
}
