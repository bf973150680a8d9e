//! The reverse benchmark behind `mwb bench reverse` (issue 5, "Measure"): cost of a backward
//! step against a forward step of the same stepper on the same scene, the round-trip error, the
//! energy growth of sampled worlds (§5.3.1) and the wall time of the big ball scene (§5.4.1).
//! Plain data, no serde: the CLI decides how to print it.

use std::time::Instant;

use crate::chain::{ChainLearning, ContactChain};
use crate::run::{Heuristics, ReverseSettings, run_backward};
use crate::scene::{SceneConvertError, builtin, world_from_toml};
use crate::{BackwardChoices, World};

/// Alternating forward/backward timing rounds; the fastest round of each is reported.
const TIMING_ROUNDS: usize = 5;

/// What to run.
#[derive(Debug, Clone, PartialEq)]
pub struct BenchOptions {
    /// Steps timed for the forward/backward step cost.
    pub timing_steps: usize,
    /// Sampled worlds for `energy_growth_p50` and the round trip.
    pub worlds: usize,
    /// Seconds each sampled world goes back.
    pub world_duration: f64,
    /// Scene of the step-cost, round-trip and energy measurements (TOML).
    pub scene: String,
    /// The big ball scene (TOML); `None` skips it.
    pub balls_scene: Option<String>,
    /// Seconds the ball run goes back.
    pub balls_duration: f64,
    /// Measure each ball step's departure (one extra forward step per step).
    pub balls_measure_departure: bool,
    /// First seed.
    pub seed: u64,
}

impl Default for BenchOptions {
    fn default() -> Self {
        Self {
            timing_steps: 240,
            worlds: 16,
            world_duration: 2.0,
            scene: builtin::WORD.to_owned(),
            balls_scene: Some(builtin::BALLS.to_owned()),
            balls_duration: 3.0,
            balls_measure_departure: false,
            seed: 1,
        }
    }
}

/// The numbers.
#[derive(Debug, Clone, PartialEq)]
pub struct ReverseBench {
    /// Bodies in the step-cost scene.
    pub bodies: usize,
    /// Mean forward step (µs) over `timing_steps` steps from the scene's resting state; the
    /// fastest of a few rounds alternating with the backward ones.
    pub forward_step_us: f64,
    /// Mean backward step (µs) from the same state, forward-residual check included; the
    /// fastest of the same rounds.
    pub backward_step_us: f64,
    /// `backward_step_us / forward_step_us` (target ≤ 1.2).
    pub ratio: f64,
    /// Largest relative velocity error of a backward step replayed forward with its own
    /// contacts, over the sampled worlds with every heuristic off (§5.2's test). One world
    /// whose energy runs away (§5.3.1) decides it, so it jumps with the seeds.
    pub roundtrip_max_rel_err: f64,
    /// Median over the same worlds of each world's largest error: the typical world.
    pub roundtrip_p50_rel_err: f64,
    /// Fraction of all their steps whose error exceeds
    /// [`crate::run::FORWARD_VALID_REL`].
    pub roundtrip_departed_fraction: f64,
    /// Median of [`crate::BackwardRunReport::energy_growth`] (m) over the sampled worlds, with
    /// the default heuristics.
    pub energy_growth_p50: f64,
    /// Median of the peak angular speed (rad/s) over the same worlds.
    pub angular_speed_peak_p50: f64,
    /// Balls in the ball scene (0 when skipped).
    pub balls: usize,
    /// Backward steps of the ball run.
    pub balls_steps: usize,
    /// Wall time of the ball run on one core (s), chain learning excluded.
    pub balls_seconds: f64,
    /// Wall time of learning the ball scene's contact chain (s).
    pub balls_learn_seconds: f64,
    /// Energy growth (m) of the ball world.
    pub balls_energy_growth: f64,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.retain(|x| !x.is_nan());
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let m = v.len() / 2;
    if v.len() % 2 == 1 {
        v[m]
    } else {
        0.5 * (v[m - 1] + v[m])
    }
}

/// Runs the benchmark (single-threaded; takes minutes in release with the default options).
pub fn bench(opts: &BenchOptions) -> Result<ReverseBench, SceneConvertError> {
    let world = world_from_toml(&opts.scene, "bench scene")?;
    let dt = 1.0 / 120.0;
    let steps = opts.timing_steps.max(1);

    // Forward and backward runs alternate and each keeps its fastest round, so that a busy
    // machine slowing one of them down does not show up as a ratio.
    let choices = BackwardChoices::default();
    let (mut forward_step_us, mut backward_step_us) = (f64::INFINITY, f64::INFINITY);
    for _ in 0..TIMING_ROUNDS {
        let mut fwd = world.clone();
        let t = Instant::now();
        for _ in 0..steps {
            fwd.step_forward(dt);
        }
        forward_step_us = forward_step_us.min(t.elapsed().as_secs_f64() * 1e6 / steps as f64);
        let mut back = world.clone();
        let t = Instant::now();
        for _ in 0..steps {
            back.step_backward(dt, &choices);
        }
        backward_step_us = backward_step_us.min(t.elapsed().as_secs_f64() * 1e6 / steps as f64);
    }

    let chain = ContactChain::learn(&world, &ChainLearning::default(), opts.seed);
    let mut roundtrip_max_rel_err = 0.0f64;
    let mut world_errs = Vec::new();
    let (mut departed, mut stepped) = (0usize, 0usize);
    let mut growth = Vec::new();
    let mut spin = Vec::new();
    for k in 0..opts.worlds as u64 {
        let seed = opts.seed.wrapping_add(k);
        let exact = ReverseSettings {
            duration: opts.world_duration,
            heuristics: Heuristics::off(),
            chain: Some(chain.clone()),
            ..Default::default()
        };
        let run = run_backward(&mut world.clone(), seed, &exact);
        roundtrip_max_rel_err = roundtrip_max_rel_err.max(run.report.max_departure);
        world_errs.push(run.report.max_departure);
        departed += run.report.departed_steps;
        stepped += run.report.steps;
        let plausible = ReverseSettings {
            heuristics: Heuristics::default(),
            measure_departure: false,
            ..exact
        };
        let run = run_backward(&mut world.clone(), seed, &plausible);
        growth.push(run.report.energy_growth);
        spin.push(run.report.angular_speed_peak);
    }

    let (mut balls, mut balls_steps, mut balls_seconds) = (0, 0, 0.0);
    let (mut balls_learn_seconds, mut balls_energy_growth) = (0.0, f64::NAN);
    if let Some(src) = &opts.balls_scene {
        let world: World = world_from_toml(src, "balls scene")?;
        balls = world.bodies.len();
        let t = Instant::now();
        let chain = ContactChain::learn(&world, &ChainLearning::default(), opts.seed);
        balls_learn_seconds = t.elapsed().as_secs_f64();
        let settings = ReverseSettings {
            duration: opts.balls_duration,
            chain: Some(chain),
            measure_departure: opts.balls_measure_departure,
            ..Default::default()
        };
        let t = Instant::now();
        let run = run_backward(&mut world.clone(), opts.seed, &settings);
        balls_seconds = t.elapsed().as_secs_f64();
        balls_steps = run.report.steps;
        balls_energy_growth = run.report.energy_growth;
    }
    Ok(ReverseBench {
        bodies: world.bodies.len(),
        forward_step_us,
        backward_step_us,
        ratio: backward_step_us / forward_step_us,
        roundtrip_max_rel_err,
        roundtrip_p50_rel_err: median(world_errs),
        roundtrip_departed_fraction: if stepped > 0 {
            departed as f64 / stepped as f64
        } else {
            0.0
        },
        energy_growth_p50: median(growth),
        angular_speed_peak_p50: median(spin),
        balls,
        balls_steps,
        balls_seconds,
        balls_learn_seconds,
        balls_energy_growth,
    })
}
