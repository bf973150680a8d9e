//! One backward world as a stored world (DESIGN.md "Backward simulation", Output): a
//! [`run_backward`] from the scene's final state, **time-reversed for playback** (frame 0 is the
//! earliest state, the last frame is the state the user gave), cut into ~1 s segments that are
//! each a self-contained `mwb-codec` stream (`ENCODING_SPLINE_V1`), exactly like the forward
//! sampler's, plus the per-body summary the store indexes (impacts, rest) described *as played
//! forward*, and the run's §5.3.1 plausibility numbers.
//!
//! A scene's optional `[reverse]` table ([`crate::settings_toml`]) asks for user hints and for a
//! mixed world instead (§5.4.4, [`run_mixed`]): the scene's state is then an intermediate frame,
//! `end_time` seconds of backward run lead into it and `forward_time` seconds of forward steps
//! out of it — one world, played forward across both parts.
//!
//! Pure computation, no bus: [`ReverseScene::prepare`] once per job (parse, convert, learn the
//! contact-count chain of §5.3.6), then [`sample_world`] per seed. Deterministic: the same binary,
//! scene text and seed give the same segments byte for byte.
//!
//! ```
//! use mwb_reverse::sample::{ReverseScene, sample_world};
//! use mwb_reverse::scene::builtin;
//!
//! // A short run of the word scene: 0.5 s back from the boxes spelling "MWB".
//! let text = builtin::WORD.replace("end_time = 3.0", "end_time = 0.5");
//! let scene = ReverseScene::prepare(&text, "word.toml")?;
//! let mut segments = Vec::new();
//! let world = sample_world(&scene, 7, mwb_codec::Quality::Standard, &mut |s| {
//!     segments.push(s);
//!     std::ops::ControlFlow::Continue(())
//! })?;
//! assert_eq!(world.frame_count, 61); // the final state plus one frame per backward step
//! assert_eq!(segments.iter().map(|s| s.frame_count).sum::<u32>(), world.frame_count);
//! assert!(world.body_rested.iter().all(|&r| r)); // played forward, the boxes end at rest
//! # Ok::<(), mwb_reverse::sample::SampleError>(())
//! ```

use std::ops::ControlFlow;

use mwb_codec::{EncodeParams, MotionModel, Quality, Track, encode_world};
use mwb_core::perturb;
use mwb_core::scene::{Scene, SceneTemplate};
use mwb_proto::v1::WorldDone;
use nalgebra::{UnitQuaternion, Vector3};

use crate::chain::{ChainLearning, ContactChain};
use crate::run::{BackwardRunReport, Frame, ReverseSettings, run_backward, run_mixed};
use crate::scene::{SceneConvertError, world_from_scene};
use crate::settings_toml::{ReverseTable, RunMode, parse_reverse_scene};

/// What the reverse stepper is, recorded in every world's provenance: a world is regenerated
/// bit for bit only by the same binary.
pub const STEPPER_BUILD: &str = "mwb-reverse LCP stepper f64 backward";

/// The provenance string of this binary's backward worlds.
pub fn provenance() -> String {
    format!("mwb {} / {STEPPER_BUILD}", env!("CARGO_PKG_VERSION"))
}

/// Seed of the contact-count chain's learning runs: fixed, so that the chain (and hence every
/// world) depends only on the scene, and all worlds of a scene share one chain (§5.3.6: learned
/// per scene).
pub const CHAIN_SEED: u64 = 1;

/// Why a scene cannot be sampled backward, or a world failed.
#[derive(Debug, thiserror::Error)]
pub enum SampleError {
    /// The scene did not parse or convert (joints, bad shapes, …).
    #[error(transparent)]
    Scene(#[from] SceneConvertError),
    /// A time setting the backward run cannot use.
    #[error("[settings] {name} = {value}: must be finite and > 0 for a backward run")]
    Setting {
        /// Which setting.
        name: &'static str,
        /// Its value.
        value: f64,
    },
    /// A body's pose went non-finite (the stepper disables such bodies; their frames cannot
    /// be stored).
    #[error("body {body}: non-finite pose in frame {frame}")]
    NonFinite {
        /// Body index.
        body: usize,
        /// Frame index (played forward).
        frame: usize,
    },
    /// The motion codec refused the frames.
    #[error("motion encoding: {0}")]
    Codec(#[from] mwb_codec::CodecError),
    /// The caller stopped the world (the job closed).
    #[error("stopped by the caller")]
    Stopped,
}

/// A final-state (or, mixed, intermediate-state) scene ready for sampling: parsed once per job.
#[derive(Debug, Clone)]
pub struct ReverseScene {
    template: SceneTemplate,
    settings: ReverseSettings,
    mode: RunMode,
}

impl ReverseScene {
    /// Parses the scene (`file` names it in errors), checks that the reverse stepper can build
    /// it, and learns its contact-count chain (a few dozen short forward runs; tens of
    /// milliseconds for the shipped word scene).
    ///
    /// The run goes back `[settings] end_time` seconds with the scene's `dt`, the default §5.3
    /// heuristics, and without the per-step departure measurement (it costs a forward step per
    /// step; `mwb bench reverse` measures it). The scene's `[reverse]` table, if any, sets the
    /// user hints, the mode and the energy budget ([`crate::settings_toml`]).
    pub fn prepare(text: &str, file: &str) -> Result<Self, SampleError> {
        let (
            template,
            ReverseTable {
                mode,
                hints,
                energy_budget,
            },
        ) = parse_reverse_scene(text, file).map_err(SceneConvertError::from)?;
        let s = template.settings();
        for (name, value) in [("dt", s.dt), ("end_time", s.end_time)] {
            if !(value.is_finite() && value > 0.0) {
                return Err(SampleError::Setting { name, value });
            }
        }
        let world = world_from_scene(&template.instantiate(0))?;
        let learning = ChainLearning {
            dt: s.dt,
            ..ChainLearning::default()
        };
        let chain = ContactChain::learn(&world, &learning, CHAIN_SEED);
        let mut settings = ReverseSettings {
            dt: s.dt,
            duration: s.end_time,
            chain: Some(chain),
            hints,
            measure_departure: false,
            ..ReverseSettings::default()
        };
        if let Some(b) = energy_budget {
            settings.heuristics.energy_budget = Some(b);
        }
        Ok(Self {
            template,
            settings,
            mode,
        })
    }

    /// Backward from the scene's state, or mixed through it.
    pub fn mode(&self) -> RunMode {
        self.mode
    }

    /// The run settings.
    pub fn settings(&self) -> &ReverseSettings {
        &self.settings
    }

    /// The parsed scene.
    pub fn template(&self) -> &SceneTemplate {
        &self.template
    }
}

/// One encoded segment of a backward world, in playback order.
#[derive(Debug, Clone, PartialEq)]
pub struct Segment {
    /// 0-based segment number.
    pub seq: u32,
    /// First frame (playback order).
    pub first_frame: u32,
    /// Frames in this segment.
    pub frame_count: u32,
    /// Bodies (scene order).
    pub body_count: u32,
    /// An `mwb-codec` world stream of this segment's frames, one object per body
    /// (`ENCODING_SPLINE_V1`).
    pub payload: Vec<u8>,
}

/// What a backward world looks like played forward, and how plausible it is.
#[derive(Debug, Clone, PartialEq)]
pub struct ReverseWorldSummary {
    /// The world's seed.
    pub seed: u64,
    /// Frames: the given state plus one per backward step (and, mixed, one per forward step).
    pub frame_count: u32,
    /// Index of the given state among the frames (`frame_count − 1` for a backward world).
    pub join: u32,
    /// Segments emitted.
    pub segment_count: u32,
    /// Seconds between frames.
    pub frame_dt: f64,
    /// Every body at rest in the last frame (for a backward world, the given state).
    pub rested: bool,
    /// Per body, impacts played forward: onsets of a contact acceleration above the scene's
    /// `c_v` / `c_omega` (the forward sampler's §4.1.2 rule, gravity removed).
    pub impacts: Vec<u32>,
    /// Per body, the time of the first frame from which it stayed below the scene's rest
    /// thresholds (0 if it never moved); the end time if it moves in the last frame.
    pub rest_time_s: Vec<f64>,
    /// Per body, at rest in the last frame.
    pub body_rested: Vec<bool>,
    /// Contact lift-offs the run sampled: the random choices that make backward worlds differ,
    /// as perturbations make forward worlds differ.
    pub lifts: u32,
    /// Steps: backward, plus forward for a mixed world (`frame_count − 1`).
    pub steps: u64,
    /// Encoded bytes over all segments.
    pub payload_bytes: u64,
    /// The run's plausibility measurements (§5.3.1: energy and angular-speed growth, …); of the
    /// backward part only for a mixed world.
    pub report: BackwardRunReport,
}

impl ReverseWorldSummary {
    /// The wire summary of world `(job, node, counter)`, with the §5.3.1 plausibility numbers
    /// (`energy_growth`, m; `angular_speed_growth`, rad/s) that only backward and mixed worlds
    /// carry, and the world's [`crate::plausible`] verdict (`plausible`, `plausibility_excess`,
    /// m); a non-finite measurement is sent as +∞ (ranks as least plausible). CPU time,
    /// provenance and scene hash are the caller's to add.
    pub fn world_done(&self, job_id: &str, node: &str, counter: u64) -> WorldDone {
        let measured = |x: f64| Some(if x.is_nan() { f64::INFINITY } else { x });
        WorldDone {
            job_id: job_id.to_owned(),
            node_id: node.to_owned(),
            world_counter: counter,
            seed: self.seed,
            frame_count: self.frame_count,
            segment_count: self.segment_count,
            frame_dt: self.frame_dt,
            rested: self.rested,
            impacts: self.impacts.clone(),
            perturbations: self.lifts,
            sim_steps: self.steps,
            rest_time_s: self.rest_time_s.clone(),
            body_rested: self.body_rested.clone(),
            energy_growth: measured(self.report.energy_growth),
            angular_speed_growth: measured(self.report.angular_speed_growth),
            plausible: Some(self.report.plausibility.plausible),
            plausibility_excess: measured(self.report.plausibility.excess_m),
            ..Default::default()
        }
    }
}

/// The codec's position model: the stepper has no damping and no joints, and its free flight
/// is the same semi-implicit Euler as rapier's (run backward, then replayed forward, it is
/// exact), so the gravity-only candidate applies.
fn motion_model(scene: &Scene) -> MotionModel {
    MotionModel::FreeFlightGravity {
        g: scene.settings.gravity,
    }
}

/// Per-body velocities in playback order, from consecutive frames. The stepper moves positions
/// with the *new* velocity (3.17)–(3.18), `x_k = x_{k−1} + v_k Δt` and
/// `q_k = exp(ω_k Δt) q_{k−1}`, so the differences give back its velocities to round-off;
/// frame 0 takes the run's earliest state.
fn velocities(
    frames: &[Frame],
    first: &[(Vector3<f64>, Vector3<f64>)],
    dt: f64,
) -> Vec<Vec<(Vector3<f64>, Vector3<f64>)>> {
    let mut out = Vec::with_capacity(frames.len());
    out.push(first.to_vec());
    for pair in frames.windows(2) {
        out.push(
            pair[0]
                .poses
                .iter()
                .zip(&pair[1].poses)
                .map(|(a, b)| {
                    let v = (b.position - a.position) / dt;
                    let w = (b.orientation * a.orientation.inverse()).scaled_axis() / dt;
                    (v, w)
                })
                .collect(),
        );
    }
    out
}

fn arr(v: &Vector3<f64>) -> [f64; 3] {
    [v.x, v.y, v.z]
}

/// One world's run before encoding: what [`sample_world`] stores, and what `mwb bench reverse`
/// measures.
#[derive(Debug, Clone)]
pub struct SceneRun {
    /// The scene instantiated with the world's seed.
    pub concrete: Scene,
    /// Per body, its centre of mass in its own frame relative to the scene's body origin.
    pub com_offset: Vec<Vector3<f64>>,
    /// Frames in time order (played forward).
    pub frames: Vec<Frame>,
    /// Index of the given state in `frames`.
    pub join: usize,
    /// Per body, `(linear, angular)` velocity of `frames[0]`.
    pub first: Vec<(Vector3<f64>, Vector3<f64>)>,
    /// The run's measurements, plausibility included.
    pub report: BackwardRunReport,
}

/// Runs the backward (or mixed) world of `scene` for `seed`, without encoding it.
pub fn run_world(scene: &ReverseScene, seed: u64) -> Result<SceneRun, SampleError> {
    let concrete = scene.template.instantiate(seed);
    let mut world = world_from_scene(&concrete)?;
    // The stepper's body position is the centre of mass; a stored pose is the scene's body
    // origin (what the sampler records and the viewer draws from). They differ for hulls only.
    let com_offset: Vec<Vector3<f64>> = world
        .bodies
        .iter()
        .zip(&concrete.bodies)
        .map(|(b, s)| {
            let origin = Vector3::new(s.position[0], s.position[1], s.position[2]);
            b.orientation.inverse() * (b.position - origin)
        })
        .collect();
    let settings = &scene.settings;
    let (frames, join, first, report) = match scene.mode {
        RunMode::Backward => {
            let run = run_backward(&mut world, seed, settings);
            let first: Vec<_> = world.bodies.iter().map(|b| (b.linvel, b.angvel)).collect();
            let join = run.frames.len().saturating_sub(1);
            (run.frames, join, first, run.report)
        }
        RunMode::Mixed { forward_time } => {
            let run = run_mixed(&mut world, seed, settings, forward_time);
            (run.frames, run.join, run.first_velocities, run.report)
        }
    };
    Ok(SceneRun {
        concrete,
        com_offset,
        frames,
        join,
        first,
        report,
    })
}

/// Samples the backward (or, per the scene's `[reverse] mode`, mixed) world of `scene` for
/// `seed` and hands its segments, in playback order, to `emit` (which may stop the world with
/// `ControlFlow::Break`: then [`SampleError::Stopped`]).
///
/// The scene is instantiated with `seed` (a final state with distributions varies per world)
/// and the backward run draws its free choices from the same seed. Segments hold
/// `[settings] segment_seconds` of frames each, the last one the rest.
pub fn sample_world(
    scene: &ReverseScene,
    seed: u64,
    quality: Quality,
    emit: &mut dyn FnMut(Segment) -> ControlFlow<()>,
) -> Result<ReverseWorldSummary, SampleError> {
    let SceneRun {
        concrete,
        com_offset,
        frames,
        join,
        first,
        report,
    } = run_world(scene, seed)?;
    let settings = &scene.settings;
    let dt = settings.dt;
    let s = &concrete.settings;
    let n = com_offset.len();

    // Poses in playback order, checked finite before anything is encoded.
    let mut tracks: Vec<Track> = (0..n)
        .map(|_| Track {
            positions: Vec::with_capacity(frames.len()),
            rotations: Vec::with_capacity(frames.len()),
        })
        .collect();
    for (f, frame) in frames.iter().enumerate() {
        for (b, (pose, t)) in frame.poses.iter().zip(tracks.iter_mut()).enumerate() {
            let q: UnitQuaternion<f64> = pose.orientation;
            let origin = pose.position - q * com_offset[b];
            let c = q.coords;
            let rotation = [c.x, c.y, c.z, c.w];
            if !(origin.iter().all(|x| x.is_finite()) && rotation.iter().all(|x| x.is_finite())) {
                return Err(SampleError::NonFinite { body: b, frame: f });
            }
            t.positions.push(arr(&origin));
            t.rotations.push(rotation);
        }
    }

    // Impacts and rest as a viewer of the played-forward world sees them.
    let vel = velocities(&frames, &first, dt);
    let rest =
        |v: &Vector3<f64>, w: &Vector3<f64>| v.norm() < s.rest_linear && w.norm() < s.rest_angular;
    let mut impacts = vec![0u32; n];
    let mut in_impact = vec![false; n];
    let mut last_moving: Vec<Option<usize>> = vec![None; n];
    for (k, frame_vel) in vel.iter().enumerate() {
        for (b, (v, w)) in frame_vel.iter().enumerate() {
            if k > 0 {
                let (v0, w0) = vel[k - 1][b];
                let rate_v = perturb::impact_rate(arr(&v0), arr(v), s.gravity, dt);
                let rate_w = perturb::impact_rate(arr(&w0), arr(w), [0.0; 3], dt);
                let hit = perturb::norm(rate_v) > s.c_v || perturb::norm(rate_w) > s.c_omega;
                if hit && !in_impact[b] {
                    impacts[b] += 1;
                }
                in_impact[b] = hit;
            }
            if !rest(v, w) {
                last_moving[b] = Some(k);
            }
        }
    }
    let last = vel.len().saturating_sub(1);
    let body_rested: Vec<bool> = last_moving.iter().map(|m| *m != Some(last)).collect();
    let rest_time_s = last_moving
        .iter()
        .map(|m| match m {
            None => 0.0,
            Some(k) if *k == last => last as f64 * dt,
            Some(k) => (k + 1) as f64 * dt,
        })
        .collect();

    // Segments of ~segment_seconds, each its own codec stream.
    let frame_count = frames.len();
    let per_segment = ((s.segment_seconds / dt).round() as usize).max(1);
    let params = EncodeParams::from_quality(quality, dt, motion_model(&concrete));
    let mut payload_bytes = 0u64;
    let mut segment_count = 0u32;
    let mut start = 0usize;
    while start < frame_count {
        let end = (start + per_segment).min(frame_count);
        let chunk: Vec<Track> = tracks
            .iter()
            .map(|t| Track {
                positions: t.positions[start..end].to_vec(),
                rotations: t.rotations[start..end].to_vec(),
            })
            .collect();
        let encoded = encode_world(&chunk, &params)?;
        payload_bytes += encoded.bytes.len() as u64;
        let seg = Segment {
            seq: segment_count,
            first_frame: start as u32,
            frame_count: (end - start) as u32,
            body_count: n as u32,
            payload: encoded.bytes,
        };
        segment_count += 1;
        if emit(seg).is_break() {
            return Err(SampleError::Stopped);
        }
        start = end;
    }

    Ok(ReverseWorldSummary {
        seed,
        frame_count: frame_count as u32,
        join: join as u32,
        segment_count,
        frame_dt: dt,
        rested: body_rested.iter().all(|&r| r),
        impacts,
        rest_time_s,
        body_rested,
        lifts: u32::try_from(report.lifts).unwrap_or(u32::MAX),
        steps: frame_count.saturating_sub(1) as u64,
        payload_bytes,
        report,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Our stepper solves each step's LCP exactly, with no substeps, iteration count, CCD or
    /// sleeping to set: of a simulation preset it takes the step, which only `reference`
    /// changes (÷ 8).
    #[test]
    fn the_reference_preset_shortens_the_step() {
        let text = crate::scene::builtin::WORD;
        let plain = ReverseScene::prepare(text, "word.toml").unwrap_or_else(|e| panic!("{e}"));
        let with = |preset: &str| {
            let t = text.replacen(
                "[settings]\n",
                &format!("[settings]\nsim = \"{preset}\"\n"),
                1,
            );
            ReverseScene::prepare(&t, "word.toml").unwrap_or_else(|e| panic!("{e}"))
        };
        assert_eq!(with("final").settings.dt, plain.settings.dt);
        assert_eq!(with("draft").settings.dt, plain.settings.dt);
        assert_eq!(with("reference").settings.dt, plain.settings.dt / 8.0);
    }
}
