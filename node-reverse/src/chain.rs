//! The contact-count Markov chain of §5.3.6, learned per scene.
//!
//! A body's state `η` is the number of its contacts that carry a normal impulse (the LCP's
//! active set, not parry's raw point count). Forward runs of the scene's own geometry give
//! transitions `η_{t−Δt} → η_t`; read backwards they are samples of `η_t → η_{t−Δt}` (5.19),
//! counted into the matrix (5.20). A backward step can only *remove* contacts (it explains a
//! resting contact as an inelastic landing, (5.5)), so the entries towards more contacts are set
//! to zero before each row is normalised (Figure 5.12).

use mwb_core::rng::{Stream, WorldRng};
use nalgebra::{UnitQuaternion, Vector3};

use crate::World;
use crate::contact::Partner;

/// States `0 ..= MAX_STATE`; a body with more active contacts counts as `MAX_STATE`.
pub const MAX_STATE: usize = 4;
/// Speed (m/s) and angular speed (rad/s) below which a learning run counts as resting …
pub const REST_SPEED: (f64, f64) = (0.02, 0.05);
/// … and how long (s) it must rest before the run stops: a short hold, so that a forward run's
/// final rest does not swamp the transitions out of rest.
pub const REST_HOLD: f64 = 0.25;
/// Normal impulses (N·s) at or below this do not make a contact active.
pub const ACTIVE_IMPULSE: f64 = 1e-12;

/// Transition probabilities between contact counts when stepping backward.
#[derive(Debug, Clone, PartialEq)]
pub struct ContactChain {
    /// `counts[j][i]`: how often a forward run went from `i` active contacts to `j` (one step
    /// later), i.e. backward transitions `j → i`. Entries with `i > j` are kept here as seen.
    pub counts: Vec<Vec<u64>>,
    /// `probabilities[j][i] = P(η_{t−Δt} = i | η_t = j)` (5.20); zero for `i > j`; every row
    /// sums to 1 (a row without data stays where it is).
    pub probabilities: Vec<Vec<f64>>,
}

/// How to learn a chain.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChainLearning {
    /// Forward runs ("a few dozen", §5.3.6).
    pub runs: usize,
    /// Time step (s).
    pub dt: f64,
    /// Longest run (s).
    pub max_duration: f64,
    /// Drop height above the body's resting pose, uniform in this range (m).
    pub height: (f64, f64),
    /// Each component of the initial linear velocity, uniform in ±this (m/s).
    pub speed: f64,
    /// Each component of the initial angular velocity, uniform in ±this (rad/s).
    pub spin: f64,
}

impl Default for ChainLearning {
    fn default() -> Self {
        Self {
            runs: 24,
            dt: 1.0 / 120.0,
            max_duration: 3.0,
            height: (0.2, 0.8),
            speed: 1.0,
            spin: 4.0,
        }
    }
}

impl ContactChain {
    /// A chain from raw counts (`counts[j][i]`: backward transitions `j → i`), see
    /// [`ContactChain::probabilities`].
    pub fn from_counts(counts: Vec<Vec<u64>>) -> Self {
        let n = MAX_STATE + 1;
        let mut c = vec![vec![0u64; n]; n];
        for (j, row) in counts.iter().enumerate().take(n) {
            for (i, &v) in row.iter().enumerate().take(n) {
                c[j][i] = v;
            }
        }
        let probabilities = c
            .iter()
            .enumerate()
            .map(|(j, row)| {
                // Figure 5.12: only transitions to fewer (or as many) contacts.
                let total: u64 = row[..=j].iter().sum();
                (0..n)
                    .map(|i| {
                        if i > j {
                            0.0
                        } else if total == 0 {
                            if i == j { 1.0 } else { 0.0 }
                        } else {
                            row[i] as f64 / total as f64
                        }
                    })
                    .collect()
            })
            .collect();
        Self {
            counts: c,
            probabilities,
        }
    }

    /// A chain in which nothing ever lifts off (every row stays).
    pub fn stay() -> Self {
        Self::from_counts(Vec::new())
    }

    /// Learns the chain of a scene: run `k` drops body `k mod n` alone onto the scene's static
    /// geometry from above its resting pose (the "few dozen simple forward simulations with the
    /// provided geometry" of §5.3.6), with random height, orientation, velocity and spin drawn
    /// from `seed`, and counts each body-step's transition. Uses the crate's own forward step.
    pub fn learn(world: &World, learning: &ChainLearning, seed: u64) -> Self {
        let n = MAX_STATE + 1;
        let mut counts = vec![vec![0u64; n]; n];
        let up = (-world.gravity)
            .try_normalize(1e-12)
            .unwrap_or(Vector3::z());
        let mut rng = WorldRng::new(seed ^ CHAIN_SALT, Stream::Perturbation);
        let dt = if learning.dt.is_finite() && learning.dt > 0.0 {
            learning.dt
        } else {
            1.0 / 120.0
        };
        let max_steps = (learning.max_duration.max(0.0) / dt).ceil() as usize;
        let hold_steps = (REST_HOLD / dt).ceil() as usize;
        for run in 0..learning.runs {
            let Some(template) = world.bodies.get(run % world.bodies.len().max(1)) else {
                break;
            };
            let mut body = template.clone();
            let h = rng.uniform(learning.height.0, learning.height.1);
            let axis = Vector3::new(
                rng.normal(0.0, 1.0),
                rng.normal(0.0, 1.0),
                rng.normal(0.0, 1.0),
            );
            let angle = rng.uniform(-std::f64::consts::PI, std::f64::consts::PI);
            let turn = UnitQuaternion::new(axis.try_normalize(1e-9).unwrap_or(up) * angle);
            let mut r = || rng.uniform(-1.0, 1.0);
            let v = Vector3::new(r(), r(), r()) * learning.speed;
            let w = Vector3::new(r(), r(), r()) * learning.spin;
            body.position += up * h;
            body.orientation = turn * body.orientation;
            // No upward throw: it would only add free flight.
            body.linvel = v - up * v.dot(&up).max(0.0);
            body.angvel = w;
            let mut solo = World {
                bodies: vec![body],
                statics: world.statics.clone(),
                // One body dropped alone: the contact-count chain learns its contacts only.
                joints: Vec::new(),
                gravity: world.gravity,
                params: world.params,
                narrow_phase: Default::default(),
            };
            let mut previous = 0usize;
            let mut resting = 0usize;
            for _ in 0..max_steps {
                let report = solo.step_forward(dt);
                let eta = report
                    .contacts
                    .contacts
                    .iter()
                    .zip(&report.impulses)
                    .filter(|(c, i)| {
                        (c.body == 0 || c.partner == Partner::Body(0)) && i.normal > ACTIVE_IMPULSE
                    })
                    .count()
                    .min(MAX_STATE);
                // Forward previous → eta is backward eta → previous.
                counts[eta][previous] += 1;
                previous = eta;
                let b = &solo.bodies[0];
                if !b.enabled {
                    break;
                }
                if b.linvel.norm() < REST_SPEED.0 && b.angvel.norm() < REST_SPEED.1 {
                    resting += 1;
                    if resting >= hold_steps {
                        break;
                    }
                } else {
                    resting = 0;
                }
            }
        }
        Self::from_counts(counts)
    }

    /// The next (earlier) state from `from`, given a uniform draw `u ∈ [0, 1)`.
    pub fn sample(&self, from: usize, u: f64) -> usize {
        let from = from.min(MAX_STATE);
        let row = &self.probabilities[from];
        let mut acc = 0.0;
        for (i, p) in row.iter().enumerate() {
            acc += p;
            if u < acc {
                return i;
            }
        }
        from
    }
}

/// Mixed into the seed so that learning draws differ from a run's draws for the same seed.
const CHAIN_SALT: u64 = 0x6368_6169_6e5f_6d77;
