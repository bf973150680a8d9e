//! Plausibility of a world, defined so that it can be checked (docs/reverse.md).
//!
//! Twigg and James, SIGGRAPH 2008, judge backward worlds by eye (§5.3.1, §5.4): a world whose
//! bodies gain energy or spin from nowhere looks "highly unrealistic" and is rejected. We turn
//! that judgement into a number per body.
//!
//! **Definition.** A body's *energy height* in a frame is its centre-of-mass height plus its
//! kinetic energy, translation *and* rotation, as a height: `h + (½ m v² + ½ ωᵀIω) / (m g)` (with
//! the stepper's `½ Δt g·v` term, which makes it exactly constant in the stepper's free flight).
//! Its *source height* `H` is the highest point its centre of mass reaches in the world,
//! including the apex of the free flight that brought it into the first frame if it is falling
//! there (the world starts mid-fall; before it, the body fell from somewhere) and the apex it
//! flies on to if it is rising in the last frame. An apex is the one the stepper's flight
//! reaches ([`apex_height`]). A body is plausible when
//!
//! 1. its energy height never exceeds `H` by more than the allowance `a`
//!    ([`PLAUSIBILITY_ALLOWANCE_M`]): it never moves or spins faster than a fall from its highest
//!    point, to where it is, could make it, plus what a sampled lift-off or slide gives a body at
//!    rest; and
//! 2. its energy height never exceeds its energy height in the last frame by more than
//!    `G` ([`MAX_ENERGY_GROWTH_M`]): however it started, it fell no further than that.
//!
//! 3. it never sinks into another body or a static by more than `P` ([`MAX_PENETRATION_M`])
//!    plus the distance the contact point moves in one step, `Δt |v + ω × r|` of the faster of
//!    the two bodies there ([`crate::Contact::point_speed`]: the stepper has no continuous
//!    collision detection, so a fast body — or a spinning box's corner — enters a contact by up
//!    to one step's travel; it has no position correction either, and a body pushed slowly
//!    into the floor would otherwise look "plausible" by its low height).
//!
//! A world is plausible when every body is. A body's *excess* is the largest of `max e − H − a`,
//! `max e − e_last − G` and `max depth − P` (metres; ≤ 0: plausible); the world's is its worst
//! body's.
//!
//! The test is per body, so it is strict where physics is not: a resting body knocked away by
//! another exceeds its own fall legitimately, and the test calls the world implausible unless
//! the transfer fits in the allowance. In the shipped scenes bodies arrive one by one and settle,
//! so we prefer the strict test, which names one body, to a per-world energy sum in which one
//! wild ball hides among three thousand quiet ones.
//!
//! Every quantity is a running maximum or a first/last value, so [`PlausibilityMeter`] keeps a
//! few numbers per body and costs `O(bodies)` per frame, in either time direction.

use nalgebra::Vector3;

use crate::{Body, World};

/// `a`, m: how far a body's energy height may exceed its source height. A backward run gives a
/// body at rest a sampled slide or lift-off of at most ~0.6 m/s played forward (1.8 cm of
/// height); the rest is round-off and rolling resistance reversed over a few centimetres.
pub const PLAUSIBILITY_ALLOWANCE_M: f64 = 0.03;

/// `G`, m: the largest fall a body may come from, measured as the drop of its energy height
/// from its highest to the last frame. The shipped scenes are table-sized.
pub const MAX_ENERGY_GROWTH_M: f64 = 2.0;

/// `P`, m: the deepest a body may sink into another body or a static in any frame.
pub const MAX_PENETRATION_M: f64 = 0.005;

/// The thresholds of the definition.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlausibilityLimits {
    /// `a` (m).
    pub allowance_m: f64,
    /// `G` (m).
    pub max_growth_m: f64,
    /// `P` (m).
    pub max_penetration_m: f64,
}

impl Default for PlausibilityLimits {
    fn default() -> Self {
        Self {
            allowance_m: PLAUSIBILITY_ALLOWANCE_M,
            max_growth_m: MAX_ENERGY_GROWTH_M,
            max_penetration_m: MAX_PENETRATION_M,
        }
    }
}

/// Which clause of the definition a body breaks most.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Clause {
    /// Faster than a fall from its source height (clause 1).
    #[default]
    FasterThanFall,
    /// Fell from higher than `G` (clause 2).
    TooHigh,
    /// Sank deeper than `P` into something (clause 3).
    Penetration,
}

/// The plausibility of one world (see the [module docs](self)).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plausibility {
    /// `excess_m ≤ 0`.
    pub plausible: bool,
    /// The worst body's excess (m). ≤ 0: plausible. +∞ when a body went non-finite.
    pub excess_m: f64,
    /// Index of that body (`None` for a world without bodies).
    pub worst_body: Option<usize>,
    /// The clause the worst body breaks most (or comes closest to breaking).
    pub worst_clause: Clause,
    /// Bodies whose own excess is > 0.
    pub implausible_bodies: usize,
    /// The thresholds used.
    pub limits: PlausibilityLimits,
}

impl Default for Plausibility {
    fn default() -> Self {
        Self {
            plausible: true,
            excess_m: -PLAUSIBILITY_ALLOWANCE_M,
            worst_body: None,
            worst_clause: Clause::FasterThanFall,
            implausible_bodies: 0,
            limits: PlausibilityLimits::default(),
        }
    }
}

/// One body's numbers over a world (m).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BodyPeaks {
    /// Its highest energy height.
    pub peak_energy_height: f64,
    /// Its source height `H`.
    pub source_height: f64,
    /// Its energy height in the last frame.
    pub last_energy_height: f64,
    /// Its deepest penetration into another body or a static beyond one step's travel (m, ≥ 0).
    pub max_penetration: f64,
}

impl BodyPeaks {
    /// Its excess over clause 1 and clause 2, NaN read as +∞.
    pub fn excess(&self, limits: &PlausibilityLimits) -> (f64, Clause) {
        let nan_inf = |x: f64| if x.is_nan() { f64::INFINITY } else { x };
        let fall = nan_inf(self.peak_energy_height - self.source_height - limits.allowance_m);
        let high = nan_inf(self.peak_energy_height - self.last_energy_height - limits.max_growth_m);
        let deep = nan_inf(self.max_penetration - limits.max_penetration_m);
        let mut worst = (fall, Clause::FasterThanFall);
        if high > worst.0 {
            worst = (high, Clause::TooHigh);
        }
        if deep > worst.0 {
            worst = (deep, Clause::Penetration);
        }
        worst
    }
}

impl Plausibility {
    /// The verdict over bodies' numbers.
    pub fn from_bodies(bodies: &[BodyPeaks], limits: PlausibilityLimits) -> Self {
        let mut p = Self {
            limits,
            excess_m: -limits.allowance_m,
            ..Self::default()
        };
        for (b, peaks) in bodies.iter().enumerate() {
            let (x, clause) = peaks.excess(&limits);
            if x > 0.0 {
                p.implausible_bodies += 1;
            }
            if p.worst_body.is_none() || x > p.excess_m {
                p.excess_m = x;
                p.worst_body = Some(b);
                p.worst_clause = clause;
            }
        }
        p.plausible = p.excess_m <= 0.0;
        p
    }
}

/// A body's energy height (m), with `up` the unit vector against gravity, `g` its magnitude and
/// `dt` the run's step (the `½ Δt g·v` shadow term of [`crate::run::shadow_energy`]). `None`
/// for a body without mass or a world without gravity.
pub fn energy_height(body: &Body, up: &Vector3<f64>, g: f64, dt: f64) -> Option<f64> {
    if !(body.inv_mass > 0.0 && g > 0.0) {
        return None;
    }
    let m = 1.0 / body.inv_mass;
    let kinetic = body.kinetic_energy() / m - 0.5 * dt * g * up.dot(&body.linvel);
    Some(up.dot(&body.position) + kinetic / g)
}

/// The apex (m) of a free flight at height `h` moving up at `vz` (m/s, negative: falling), as
/// the stepper flies it: the vertical part of the energy height, `h + v_z²/2g − ½ Δt v_z`, which
/// its semi-implicit flight conserves exactly (a body dropped from rest at `H` has it equal to
/// `H` all the way down). The continuous apex `h + v_z²/2g` is lower by `½ Δt |v_z|` for a falling
/// body: 1.8 cm of the 3 cm allowance after a 1 m fall at 120 Hz.
pub fn apex_height(h: f64, vz: f64, g: f64, dt: f64) -> f64 {
    h + vz * vz / (2.0 * g) - 0.5 * dt * vz
}

fn up_and_g(world: &World) -> (Vector3<f64>, f64) {
    let up = (-world.gravity)
        .try_normalize(1e-12)
        .unwrap_or(Vector3::z());
    (up, world.gravity.norm())
}

/// Every body's numbers over the frames of a run, observed in any order, with the first and the
/// last frame named.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PlausibilityMeter {
    /// Per body.
    pub bodies: Vec<BodyPeaks>,
    dt: f64,
}

impl PlausibilityMeter {
    /// A meter over `world`'s bodies, which starts with the current frame's energy heights as
    /// the last frame's (call [`Self::set_last`] for the frame that ends the world — this one,
    /// or a later one — and [`Self::set_first`] for the first).
    pub fn new(world: &World, dt: f64) -> Self {
        let blank = BodyPeaks {
            peak_energy_height: f64::NEG_INFINITY,
            source_height: f64::NEG_INFINITY,
            last_energy_height: f64::NEG_INFINITY,
            max_penetration: 0.0,
        };
        let mut m = Self {
            bodies: vec![blank; world.bodies.len()],
            dt,
        };
        m.observe(world);
        m.record_last_energy(world);
        m
    }

    /// Takes one more frame into account.
    pub fn observe(&mut self, world: &World) {
        let (up, g) = up_and_g(world);
        for (p, body) in self.bodies.iter_mut().zip(&world.bodies) {
            let Some(e) = energy_height(body, &up, g, self.dt) else {
                continue;
            };
            // NaN (a body gone non-finite) is kept as +∞: never plausible.
            p.peak_energy_height = if e.is_nan() {
                f64::INFINITY
            } else {
                p.peak_energy_height.max(e)
            };
            p.source_height = p.source_height.max(up.dot(&body.position));
        }
    }

    /// Takes the contacts of one frame of `world` into account: their penetration depths,
    /// less one step's travel of the contact point ([`crate::Contact::point_speed`] × Δt).
    pub fn observe_contacts(&mut self, contacts: &crate::ContactSet, world: &World) {
        for c in &contacts.contacts {
            let partner = match c.partner {
                crate::Partner::Body(p) => Some(p),
                crate::Partner::Static(_) => None,
            };
            let travel = self.dt * c.point_speed(&world.bodies);
            let depth = -c.dist - travel;
            let depth = if depth.is_nan() { f64::INFINITY } else { depth };
            for b in [Some(c.body), partner].into_iter().flatten() {
                if let Some(p) = self.bodies.get_mut(b) {
                    p.max_penetration = p.max_penetration.max(depth);
                }
            }
        }
    }

    /// `world` is the first frame (played forward): a body falling in it came from the apex of
    /// its free flight. Call after [`Self::observe`] of that frame.
    pub fn set_first(&mut self, world: &World) {
        let (up, g) = up_and_g(world);
        if g.is_nan() || g <= 0.0 {
            return;
        }
        for (p, body) in self.bodies.iter_mut().zip(&world.bodies) {
            let vz = up.dot(&body.linvel);
            if vz < 0.0 {
                let apex = apex_height(up.dot(&body.position), vz, g, self.dt);
                p.source_height = p.source_height.max(apex);
            }
        }
    }

    /// `world` is the last frame (played forward). A body rising in it reaches the apex of its
    /// free flight after the world ends, and that apex is a point it reaches (as a body falling
    /// in the first frame came from its apex, [`Self::set_first`]): without it a body thrown up
    /// through the last frame would be "faster than its fall" by its unfinished climb.
    pub fn set_last(&mut self, world: &World) {
        self.record_last_energy(world);
        let (up, g) = up_and_g(world);
        for (p, body) in self.bodies.iter_mut().zip(&world.bodies) {
            let vz = up.dot(&body.linvel);
            if vz > 0.0 && g > 0.0 {
                let apex = apex_height(up.dot(&body.position), vz, g, self.dt);
                p.source_height = p.source_height.max(apex);
            }
        }
    }

    /// Every body's energy height in `world` becomes its last frame's.
    fn record_last_energy(&mut self, world: &World) {
        let (up, g) = up_and_g(world);
        for (p, body) in self.bodies.iter_mut().zip(&world.bodies) {
            if let Some(e) = energy_height(body, &up, g, self.dt) {
                p.last_energy_height = if e.is_nan() { f64::INFINITY } else { e };
            }
        }
    }

    /// The world's plausibility with the default limits.
    pub fn plausibility(&self) -> Plausibility {
        self.plausibility_with(PlausibilityLimits::default())
    }

    /// The world's plausibility with `limits`.
    pub fn plausibility_with(&self, limits: PlausibilityLimits) -> Plausibility {
        Plausibility::from_bodies(&self.bodies, limits)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Material, StaticBody};
    use nalgebra::UnitQuaternion;
    use proptest::prelude::*;

    const STRICT: PlausibilityLimits = PlausibilityLimits {
        allowance_m: 0.0,
        max_growth_m: MAX_ENERGY_GROWTH_M,
        max_penetration_m: MAX_PENETRATION_M,
    };

    fn ball_at(h: f64) -> Body {
        match Body::ball(0.1, 1000.0) {
            Ok(b) => b.at(Vector3::new(0.0, 0.0, h), UnitQuaternion::identity()),
            Err(e) => panic!("{e}"),
        }
    }

    fn ground() -> StaticBody {
        match StaticBody::plane(Vector3::z(), 0.0) {
            Ok(s) => s.with_material(Material {
                friction: 0.5,
                restitution: 0.5,
            }),
            Err(e) => panic!("{e}"),
        }
    }

    /// Steps `w` forward `steps` times from its current state as the first frame.
    fn forward(mut w: World, steps: usize) -> (World, PlausibilityMeter) {
        let dt = 1.0 / 120.0;
        let mut meter = PlausibilityMeter::new(&w, dt);
        meter.set_first(&w);
        for _ in 0..steps {
            // A forward step detects its contacts at the poses it starts from.
            let before = w.clone();
            let report = w.step_forward(dt);
            meter.observe(&w);
            meter.observe_contacts(&report.contacts, &before);
        }
        meter.set_last(&w);
        (w, meter)
    }

    #[test]
    fn a_ball_dropped_and_bouncing_forward_is_plausible() {
        let mut w = World::new();
        w.add_static(ground());
        w.add_body(ball_at(1.0).with_material(Material {
            friction: 0.5,
            restitution: 0.5,
        }));
        let (w, meter) = forward(w, 360);
        // It lost energy in its bounces: well below its drop height.
        assert!(w.bodies[0].position.z < 0.5);
        let p = meter.plausibility_with(STRICT);
        assert!(p.plausible, "{p:?}");
        assert!(p.excess_m < 1e-9, "{p:?}");
        assert_eq!(p.worst_body, Some(0));
    }

    #[test]
    fn a_ball_already_falling_in_the_first_frame_fell_from_its_apex() {
        let mut w = World::new();
        w.add_static(ground());
        // Falling at 3 m/s from 0.5 m: it came from 0.5 + 9 / 19.62 m.
        w.add_body(ball_at(0.5).moving(Vector3::new(0.0, 0.0, -3.0), Vector3::zeros()));
        let (_, meter) = forward(w, 240);
        // The apex of the stepper's flight: the continuous one plus the shadow term ½ Δt |v_z|.
        let apex = 0.5 + 9.0 / (2.0 * 9.81) + 0.5 / 120.0 * 3.0;
        assert!((meter.bodies[0].source_height - apex).abs() < 1e-12);
        let p = meter.plausibility_with(STRICT);
        // Its energy height is that apex until the first bounce, and only falls after it.
        assert!(p.excess_m < 1e-9, "{p:?}");
        assert!(meter.plausibility().plausible);
    }

    #[test]
    fn a_ball_still_rising_in_the_last_frame_reaches_its_apex() {
        let mut w = World::new();
        w.add_static(ground());
        // Thrown up at 3 m/s from 0.5 m; the world ends 0.1 s later, 0.2 s before its apex.
        w.add_body(ball_at(0.5).moving(Vector3::new(0.0, 0.0, 3.0), Vector3::zeros()));
        let (w, meter) = forward(w, 12);
        let (h, vz) = (w.bodies[0].position.z, w.bodies[0].linvel.z);
        assert!(vz > 1.0);
        let apex = apex_height(h, vz, 9.81, 1.0 / 120.0);
        assert!((meter.bodies[0].source_height - apex).abs() < 1e-12);
        // Its energy height is the apex of its flight: exactly plausible, with no allowance.
        let p = meter.plausibility_with(STRICT);
        assert!(p.excess_m.abs() < 1e-9, "{p:?}");
    }

    #[test]
    fn a_body_gaining_speed_from_nowhere_is_not() {
        let mut w = World::new();
        w.add_static(ground());
        w.add_body(ball_at(0.1));
        w.add_body(ball_at(0.1).at(Vector3::new(1.0, 0.0, 0.1), UnitQuaternion::identity()));
        let dt = 1.0 / 120.0;
        let mut meter = PlausibilityMeter::new(&w, dt);
        // Body 1 is pushed sideways along the ground to 2 m/s: 0.204 m of energy height.
        w.bodies[1].linvel = Vector3::new(2.0, 0.0, 0.0);
        meter.observe(&w);
        let p = meter.plausibility();
        assert!(!p.plausible);
        assert_eq!(p.worst_body, Some(1));
        assert_eq!(p.worst_clause, Clause::FasterThanFall);
        assert_eq!(p.implausible_bodies, 1);
        let want = 2.0f64.powi(2) / (2.0 * 9.81) - PLAUSIBILITY_ALLOWANCE_M;
        assert!((p.excess_m - want).abs() < 1e-9, "{} vs {want}", p.excess_m);
    }

    #[test]
    fn a_fall_from_too_high_is_not() {
        let mut w = World::new();
        w.add_static(ground());
        // Falls from 2.6 m and ends near the ground: more than G = 2 m.
        w.add_body(ball_at(2.6));
        let (_, meter) = forward(w, 240);
        let p = meter.plausibility();
        assert!(!p.plausible, "{p:?}");
        assert_eq!(p.worst_clause, Clause::TooHigh);
        assert!(p.excess_m > 0.4 && p.excess_m < 0.6, "{p:?}");
    }

    #[test]
    fn a_body_sunk_into_the_ground_is_not() {
        let mut w = World::new();
        w.add_static(ground());
        // A ball of radius 0.1 m with its centre 2 cm above the plane: 8 cm deep.
        w.add_body(ball_at(0.02));
        let mut meter = PlausibilityMeter::new(&w, 1.0 / 120.0);
        let (contacts, _) = w.detect_contacts();
        meter.observe_contacts(&contacts, &w);
        let p = meter.plausibility();
        assert!(!p.plausible);
        assert_eq!(p.worst_clause, Clause::Penetration);
        assert!(
            (p.excess_m - (0.08 - MAX_PENETRATION_M)).abs() < 1e-6,
            "{p:?}"
        );
    }

    #[test]
    fn spin_counts_as_energy() {
        let mut w = World::new();
        w.add_body(ball_at(0.0));
        let mut meter = PlausibilityMeter::new(&w, 0.0);
        w.bodies[0].angvel = Vector3::new(0.0, 0.0, 100.0);
        meter.observe(&w);
        // ½ I ω² / (m g) with I = 2/5 m r²: 0.2 · 0.01 · 10⁴ / 9.81.
        let want = 0.2 * 0.01 * 1.0e4 / 9.81;
        let p = meter.plausibility_with(STRICT);
        assert!((p.excess_m - want).abs() < 1e-9, "{p:?}");
    }

    #[test]
    fn a_non_finite_body_is_infinitely_implausible() {
        let fine = BodyPeaks {
            peak_energy_height: 0.0,
            source_height: 0.0,
            last_energy_height: 0.0,
            max_penetration: 0.0,
        };
        let broken = BodyPeaks {
            peak_energy_height: f64::NAN,
            ..fine
        };
        let p = Plausibility::from_bodies(&[fine, broken], PlausibilityLimits::default());
        assert!(!p.plausible);
        assert_eq!(p.worst_body, Some(1));
        assert_eq!(p.excess_m, f64::INFINITY);
    }

    #[test]
    fn no_bodies_is_plausible() {
        let p = Plausibility::from_bodies(&[], PlausibilityLimits::default());
        assert!(p.plausible);
        assert_eq!(p.worst_body, None);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// Free flight from any state, forward: the energy height is conserved and the source
        /// height is at least the launch height, so the excess is at most the launch's kinetic
        /// height; a launch straight down (its apex extrapolated) is plausible.
        #[test]
        fn free_flight_is_bounded_by_its_launch(
            h in 0.0f64..1.5, vx in -3.0f64..3.0, vz in -3.0f64..3.0, steps in 1usize..200
        ) {
            let dt = 1.0 / 120.0;
            let mut w = World::new();
            w.add_body(ball_at(h).moving(Vector3::new(vx, 0.0, vz), Vector3::zeros()));
            let (_, meter) = forward(w.clone(), steps);
            let p = meter.plausibility_with(STRICT);
            // The launch's kinetic height, with the stepper's shadow term `½ Δt |v_z|`.
            let kinetic_h = (vx * vx + vz * vz) / (2.0 * 9.81) + 0.5 * dt * vz.abs();
            prop_assert!(p.excess_m <= kinetic_h + 1e-9, "{p:?} > {kinetic_h}");
            w.bodies[0].linvel.x = 0.0;
            w.bodies[0].linvel.z = -vz.abs();
            let (_, meter) = forward(w, steps);
            prop_assert!(meter.plausibility().plausible, "{:?}", meter.plausibility());
        }

        /// Giving a resting body more speed makes the world less plausible, never more.
        #[test]
        fn excess_grows_with_injected_speed(a in 0.0f64..5.0, b in 0.0f64..5.0) {
            let excess = |s: f64| {
                let mut w = World::new();
                w.add_body(ball_at(0.0));
                let mut meter = PlausibilityMeter::new(&w, 0.0);
                w.bodies[0].linvel = Vector3::new(s, 0.0, 0.0);
                meter.observe(&w);
                meter.plausibility().excess_m
            };
            let (lo, hi) = if a <= b { (a, b) } else { (b, a) };
            prop_assert!(excess(lo) <= excess(hi));
        }
    }
}
