//! The reverse benchmark behind `mwb bench reverse` (issue 5, "Measure"; issue 20): cost of a
//! backward step against a forward step of the same stepper on the same scene, the round-trip
//! error, the energy growth of sampled worlds (§5.3.1), the wall time of the big ball scene
//! (§5.4.1), the fraction of plausible worlds per shipped reverse scene ([`crate::plausible`])
//! and the 3037-ball "Lorem ipsum" world. Plain data, no serde: the CLI decides how to print it.

use std::collections::BTreeMap;
use std::time::Instant;

use crate::chain::{ChainLearning, ContactChain};
use crate::run::{Frame, Heuristics, ReverseSettings, run_backward};
use crate::sample::{ReverseScene, SampleError, run_world};
use crate::scene::{SceneConvertError, builtin, world_from_toml};
use crate::{BackwardChoices, World};

/// Why the bench could not run.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// A scene did not convert.
    #[error(transparent)]
    Scene(#[from] SceneConvertError),
    /// A shipped scene could not be prepared or sampled.
    #[error("scene {scene}: {source}")]
    Sample {
        /// The scene's name.
        scene: String,
        /// Why.
        source: Box<SampleError>,
    },
}

/// Scenes with more bodies than this count as big: they get
/// [`BenchOptions::big_scene_worlds`] worlds instead of [`BenchOptions::scene_worlds`].
pub const BIG_SCENE_BODIES: usize = 500;

/// In lorem.toml (generate.py): half the inside of a bin (m), the walls' height (m) and the
/// ball radius (m). A ball is *in its cell* when its centre is within the half-width of the
/// cell's centre and below the walls' top plus a radius.
pub const LOREM_CELL_HALF: f64 = 0.065;
/// See [`LOREM_CELL_HALF`].
pub const LOREM_WALL_TOP: f64 = 0.04;
/// See [`LOREM_CELL_HALF`].
pub const LOREM_BALL_RADIUS: f64 = 0.02;

/// The shipped reverse scenes whose worlds the bench samples for `plausible_fraction`.
pub fn shipped_scenes() -> Vec<(String, String)> {
    builtin::ALL
        .iter()
        .filter(|(n, _)| *n != "lorem")
        .chain(&[("crash_mixed", builtin::CRASH_MIXED)])
        .map(|(n, t)| ((*n).to_owned(), (*t).to_owned()))
        .collect()
}

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
    /// `(name, TOML)` of the scenes whose worlds are sampled (as `mwb reverse` samples them:
    /// their own `end_time`, chain, hints and mode) for the per-scene plausible fraction.
    pub scenes: Vec<(String, String)>,
    /// Worlds per scene.
    pub scene_worlds: usize,
    /// Worlds per big scene (more than [`BIG_SCENE_BODIES`] bodies).
    pub big_scene_worlds: usize,
    /// The lorem scene (TOML); `None` skips it.
    pub lorem_scene: Option<String>,
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
            scenes: shipped_scenes(),
            scene_worlds: 20,
            big_scene_worlds: 20,
            lorem_scene: Some(builtin::LOREM.to_owned()),
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
    /// Mean backward step (µs) from the same state, as `mwb reverse` takes it (without the
    /// forward-residual diagnostic, [`BackwardChoices::skip_forward_residual`]); the fastest of
    /// the same rounds.
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
    /// 95th percentile of the same energy growths as `energy_growth_p50`.
    pub energy_growth_p95: f64,
    /// 95th percentile of the same peak angular speeds as `angular_speed_peak_p50`.
    pub angular_speed_peak_p95: f64,
    /// Per shipped scene, the numbers of its sampled worlds.
    pub scenes: BTreeMap<String, ScenePlausibility>,
    /// The lorem world (`None` when skipped).
    pub lorem: Option<LoremBench>,
}

/// The plausibility of one scene's sampled worlds.
#[derive(Debug, Clone, PartialEq)]
pub struct ScenePlausibility {
    /// Worlds sampled.
    pub worlds: usize,
    /// Fraction of them that are plausible ([`crate::plausible`]).
    pub plausible_fraction: f64,
    /// Median excess (m; ≤ 0: plausible).
    pub excess_p50: f64,
    /// The implausible worlds counted by the clause their worst body breaks
    /// ([`crate::plausible::Clause`]): faster than a fall, fell from too high, sank in. Why a
    /// scene falls short, in one look.
    pub implausible_by_clause: [usize; 3],
    /// Fraction of the bodies (over all its worlds) whose earliest position is at least
    /// [`MOVED_M`] from the given one: what the backward run did. A world in which nothing
    /// leaves rest is plausible and useless; this says how much of the fraction is that.
    pub moved_fraction: f64,
    /// Median and 95th percentile of energy growth (m).
    pub energy_growth_p50: f64,
    /// See `energy_growth_p50`.
    pub energy_growth_p95: f64,
    /// 95th percentile of the peak angular speed (rad/s).
    pub angular_speed_peak_p95: f64,
    /// Wall time of all its worlds (s).
    pub seconds: f64,
}

/// The 3037-ball world of §5.4.1.
#[derive(Debug, Clone, PartialEq)]
pub struct LoremBench {
    /// Balls (3037).
    pub balls: usize,
    /// Wall time of its run on one core (s), chain learning included.
    pub seconds: f64,
    /// Backward steps.
    pub steps: usize,
    /// The world is plausible.
    pub plausible: bool,
    /// Its excess (m) and the body that decides it.
    pub excess_m: f64,
    /// Balls that, played forward, start outside every bin and end in their cell, ÷ all.
    pub cells_correct: f64,
    /// Balls outside every bin in the first frame, ÷ all.
    pub left_bins: f64,
    /// Bodies the plausibility test finds implausible.
    pub implausible_balls: usize,
    /// Energy growth (m).
    pub energy_growth: f64,
    /// Played forward, its bounces ([`bounces`]).
    pub bounces: Bounces,
    /// 5th percentile and median of what the balls' first bounces keep of their speed
    /// ([`first_bounce_keeps`]; the material pair keeps 0.55).
    pub first_bounce_keep: (f64, f64),
}

/// Incoming speed (m/s) from which [`bounces`] counts a bounce: a fall of 5 cm, twice a lorem
/// bin's wall.
pub const BOUNCE_MIN_SPEED: f64 = 1.0;
/// A bounce that keeps at least this fraction of its incoming vertical speed counts as elastic:
/// far above every shipped material pair's restitution (0.6 at most), which the backward run
/// uses only where it must ([`crate::run::Heuristics::energy_budget`]'s cap).
pub const ELASTIC_KEEP: f64 = 0.9;

/// The bounces of a world played forward.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Bounces {
    /// Reversals of a body's vertical motion from falling at [`BOUNCE_MIN_SPEED`] or faster.
    pub bounces: usize,
    /// Those that rise again with at least [`ELASTIC_KEEP`] of the incoming speed: a ball that
    /// bounces like a superball although its material keeps half.
    pub elastic: usize,
    /// Bodies with at least one elastic bounce.
    pub elastic_bodies: usize,
}

/// Body `b`'s bounces in `frames` (played forward, in time order) along `up`, as
/// `(incoming, outgoing)` vertical speeds. A body's vertical speed over each frame interval is
/// its displacement over the interval's length; a bounce is an interval falling at
/// [`BOUNCE_MIN_SPEED`] or more followed by one rising. The stepper's flight is symplectic
/// Euler, so each interval's speed is one step's velocity: the ratio of the two is the
/// bounce's restitution, up to the `g Δt` that gravity adds within one step. A body missing
/// from a later frame ends there.
fn body_bounces<'a>(
    frames: &'a [Frame],
    b: usize,
    up: &'a nalgebra::Vector3<f64>,
) -> impl Iterator<Item = (f64, f64)> + 'a {
    let mut falling: Option<f64> = None;
    frames
        .windows(2)
        .map_while(move |w| {
            let (p0, p1) = (w[0].poses.get(b)?, w[1].poses.get(b)?);
            Some((w[1].time - w[0].time, up.dot(&(p1.position - p0.position))))
        })
        .filter(|(dt, _)| !dt.is_nan() && *dt > 0.0)
        .filter_map(move |(dt, dy)| {
            let v = dy / dt;
            let bounce = falling
                .take()
                .filter(|_| v > 0.0)
                .map(|incoming| (incoming, v));
            if v <= -BOUNCE_MIN_SPEED {
                falling = Some(-v);
            }
            bounce
        })
}

/// Counts the bounces of `frames` (played forward, in time order) along `up` (see
/// [`body_bounces`]), and those that keep at least [`ELASTIC_KEEP`] of their speed.
pub fn bounces(frames: &[Frame], up: &nalgebra::Vector3<f64>) -> Bounces {
    let bodies = frames.first().map_or(0, |f| f.poses.len());
    let mut out = Bounces::default();
    for b in 0..bodies {
        let mut elastic = false;
        for (incoming, outgoing) in body_bounces(frames, b, up) {
            out.bounces += 1;
            if outgoing >= ELASTIC_KEEP * incoming {
                out.elastic += 1;
                elastic = true;
            }
        }
        out.elastic_bodies += usize::from(elastic);
    }
    out
}

/// Per body of `frames` (played forward, in time order) with a bounce ([`body_bounces`]), the
/// fraction of its vertical speed its first bounce keeps. A backward run's last rung
/// ([`crate::ApexFinish`]) makes a ball's first bounce deader than its material's; this is what
/// it costs.
pub fn first_bounce_keeps(frames: &[Frame], up: &nalgebra::Vector3<f64>) -> Vec<f64> {
    let bodies = frames.first().map_or(0, |f| f.poses.len());
    (0..bodies)
        .filter_map(|b| body_bounces(frames, b, up).next())
        .map(|(incoming, outgoing)| outgoing / incoming)
        .collect()
}

fn percentile(mut v: Vec<f64>, q: f64) -> f64 {
    v.retain(|x| !x.is_nan());
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let k = ((v.len() - 1) as f64 * q).round() as usize;
    v[k.min(v.len() - 1)]
}

/// Per body, its cell: the horizontal position of its centre in the last frame. `in_cell`:
/// within [`LOREM_CELL_HALF`] of that and below the walls' top plus a radius.
fn in_cell(frame: &Frame, last: &Frame, b: usize, up: &nalgebra::Vector3<f64>) -> bool {
    let (Some(p), Some(c)) = (frame.poses.get(b), last.poses.get(b)) else {
        return false;
    };
    let d = p.position - c.position;
    let horizontal = d - up * up.dot(&d);
    horizontal.amax() < LOREM_CELL_HALF && up.dot(&p.position) < LOREM_WALL_TOP + LOREM_BALL_RADIUS
}

/// Whether any cell of `cells` (last-frame centres) holds `p`.
fn in_any_cell(
    p: &nalgebra::Vector3<f64>,
    cells: &[nalgebra::Vector3<f64>],
    up: &nalgebra::Vector3<f64>,
) -> bool {
    up.dot(p) < LOREM_WALL_TOP + LOREM_BALL_RADIUS
        && cells.iter().any(|c| {
            let d = p - c;
            (d - up * up.dot(&d)).amax() < LOREM_CELL_HALF
        })
}

/// How far (m) a body must end up from its given position to count in
/// [`ScenePlausibility::moved_fraction`]: more than the shipped scenes' smallest body (a ball of
/// 2 cm radius) is across, so a rattle in place does not count.
pub const MOVED_M: f64 = 0.05;

/// Samples `worlds` worlds of one prepared scene; `t` started before its preparation.
fn scene_plausibility(
    name: &str,
    scene: &ReverseScene,
    worlds: usize,
    seed: u64,
    t: Instant,
) -> Result<ScenePlausibility, BenchError> {
    let err = |source| BenchError::Sample {
        scene: name.to_owned(),
        source: Box::new(source),
    };
    let (mut plausible, mut excess, mut growth, mut spin) = (0, vec![], vec![], vec![]);
    let mut by_clause = [0; 3];
    let (mut moved, mut bodies) = (0usize, 0usize);
    for k in 0..worlds as u64 {
        let run = run_world(scene, seed.wrapping_add(k)).map_err(err)?;
        if let (Some(first), Some(last)) = (run.frames.first(), run.frames.get(run.join)) {
            bodies += last.poses.len();
            moved += first
                .poses
                .iter()
                .zip(&last.poses)
                .filter(|(a, b)| (a.position - b.position).norm() >= MOVED_M)
                .count();
        }
        let r = &run.report;
        plausible += usize::from(r.plausibility.plausible);
        if !r.plausibility.plausible {
            by_clause[clause_slot(r.plausibility.worst_clause)] += 1;
        }
        excess.push(r.plausibility.excess_m);
        growth.push(r.energy_growth);
        spin.push(r.angular_speed_peak);
    }
    Ok(ScenePlausibility {
        worlds,
        plausible_fraction: if worlds > 0 {
            plausible as f64 / worlds as f64
        } else {
            f64::NAN
        },
        excess_p50: median(excess),
        implausible_by_clause: by_clause,
        moved_fraction: if bodies > 0 {
            moved as f64 / bodies as f64
        } else {
            f64::NAN
        },
        energy_growth_p50: median(growth.clone()),
        energy_growth_p95: percentile(growth, 0.95),
        angular_speed_peak_p95: percentile(spin, 0.95),
        seconds: t.elapsed().as_secs_f64(),
    })
}

/// Where a clause counts in [`ScenePlausibility::implausible_by_clause`].
fn clause_slot(c: crate::plausible::Clause) -> usize {
    use crate::plausible::Clause;
    match c {
        Clause::FasterThanFall => 0,
        Clause::TooHigh => 1,
        Clause::Penetration => 2,
    }
}

/// The lorem world: one run, as `mwb reverse` samples it.
pub fn lorem_bench(text: &str, seed: u64) -> Result<LoremBench, BenchError> {
    let err = |source| BenchError::Sample {
        scene: "lorem".to_owned(),
        source: Box::new(source),
    };
    let t = Instant::now();
    let scene = ReverseScene::prepare(text, "lorem").map_err(err)?;
    let run = run_world(&scene, seed).map_err(err)?;
    let seconds = t.elapsed().as_secs_f64();
    let up = nalgebra::Vector3::new(0.0, 1.0, 0.0);
    let (Some(first), Some(last)) = (run.frames.first(), run.frames.last()) else {
        return Err(err(SampleError::Setting {
            name: "end_time",
            value: 0.0,
        }));
    };
    let balls = last.poses.len();
    let cells: Vec<_> = last.poses.iter().map(|p| p.position).collect();
    let left: Vec<bool> = first
        .poses
        .iter()
        .map(|p| !in_any_cell(&p.position, &cells, &up))
        .collect();
    let correct = (0..balls)
        .filter(|&b| left[b] && in_cell(last, last, b, &up))
        .count();
    let ratio = |k: usize| {
        if balls > 0 {
            k as f64 / balls as f64
        } else {
            f64::NAN
        }
    };
    let p = run.report.plausibility;
    Ok(LoremBench {
        balls,
        seconds,
        steps: run.report.steps,
        plausible: p.plausible,
        excess_m: p.excess_m,
        cells_correct: ratio(correct),
        left_bins: ratio(left.iter().filter(|l| **l).count()),
        implausible_balls: p.implausible_bodies,
        energy_growth: run.report.energy_growth,
        bounces: bounces(&run.frames, &up),
        first_bounce_keep: {
            let keeps = first_bounce_keeps(&run.frames, &up);
            (percentile(keeps.clone(), 0.05), percentile(keeps, 0.5))
        },
    })
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
pub fn bench(opts: &BenchOptions) -> Result<ReverseBench, BenchError> {
    let world = world_from_toml(&opts.scene, "bench scene")?;
    let dt = 1.0 / 120.0;
    let steps = opts.timing_steps.max(1);

    // Forward and backward runs alternate and each keeps its fastest round, so that a busy
    // machine slowing one of them down does not show up as a ratio. The backward step as
    // `mwb reverse` takes it: without the forward-residual diagnostic.
    let choices = BackwardChoices {
        skip_forward_residual: true,
        ..Default::default()
    };
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
    let mut scenes = BTreeMap::new();
    for (name, text) in &opts.scenes {
        let t = Instant::now();
        let scene = ReverseScene::prepare(text, name).map_err(|source| BenchError::Sample {
            scene: name.clone(),
            source: Box::new(source),
        })?;
        let worlds = if scene.template().body_count() > BIG_SCENE_BODIES {
            opts.big_scene_worlds
        } else {
            opts.scene_worlds
        };
        if worlds > 0 {
            scenes.insert(
                name.clone(),
                scene_plausibility(name, &scene, worlds, opts.seed, t)?,
            );
        }
    }
    let lorem = match &opts.lorem_scene {
        Some(text) => Some(lorem_bench(text, opts.seed)?),
        None => None,
    };
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
        energy_growth_p50: median(growth.clone()),
        angular_speed_peak_p50: median(spin.clone()),
        energy_growth_p95: percentile(growth, 0.95),
        angular_speed_peak_p95: percentile(spin, 0.95),
        scenes,
        lorem,
        balls,
        balls_steps,
        balls_seconds,
        balls_learn_seconds,
        balls_energy_growth,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::run::Pose;
    use nalgebra::{UnitQuaternion, Vector3};

    /// Frames of one body at heights `ys`, 0.1 s apart.
    fn frames(ys: &[f64]) -> Vec<Frame> {
        ys.iter()
            .enumerate()
            .map(|(k, &y)| Frame {
                time: k as f64 * 0.1,
                poses: vec![Pose {
                    position: Vector3::new(0.0, y, 0.0),
                    orientation: UnitQuaternion::identity(),
                }],
            })
            .collect()
    }

    #[test]
    fn bounces_count_reversals_from_speed_and_the_elastic_ones() {
        let up = Vector3::y();
        // 2 m/s down, 1.9 up: elastic. 2 down, 1 up: a bounce. 0.5 down, 0.4 up: too slow.
        let b = bounces(&frames(&[0.4, 0.2, 0.39, 0.19, 0.29, 0.24, 0.28]), &up);
        assert_eq!(
            b,
            Bounces {
                bounces: 2,
                elastic: 1,
                elastic_bodies: 1
            }
        );
        // Falling then resting is no bounce; neither is a fall slowed by a contact.
        let b = bounces(&frames(&[0.5, 0.3, 0.1, 0.1, 0.05, 0.05]), &up);
        assert_eq!(b, Bounces::default());
        // A body missing from later frames ends its count; no frames, nothing.
        let mut f = frames(&[0.4, 0.2, 0.39]);
        f[2].poses.clear();
        assert_eq!(bounces(&f, &up).bounces, 0);
        assert_eq!(bounces(&[], &up), Bounces::default());
    }

    #[test]
    fn first_bounce_keeps_only_each_bodys_first_counted_bounce() {
        let up = Vector3::y();
        // 0.5 down, 0.4 up (too slow to count), then 2 down, 1 up (kept), then 2 down, 1.9 up.
        let keeps = first_bounce_keeps(&frames(&[0.45, 0.4, 0.44, 0.24, 0.34, 0.14, 0.33]), &up);
        assert_eq!(keeps.len(), 1);
        assert!((keeps[0] - 0.5).abs() < 1e-9, "{keeps:?}");
        // No counted bounce, no entry.
        assert!(first_bounce_keeps(&frames(&[0.5, 0.3, 0.1, 0.1]), &up).is_empty());
        assert!(first_bounce_keeps(&[], &up).is_empty());
    }
}
