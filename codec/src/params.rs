//! Encoder parameters, quality presets and the codec's tuning constants (one source of truth).

use crate::error::CodecError;

/// §4.3: "we store motion at 120 frames per second" (enough to render impact motion blur).
pub const DEFAULT_FRAME_DT: f64 = 1.0 / 120.0;

/// Rate of the uncompressed low-resolution path that travels beside each world (§4.4 uses it for
/// instant display and for the query index).
pub const DEFAULT_LOWRES_HZ: f64 = 4.0;

/// Figure 4.6: a segment is least-squares fitted to its first `k = 10` points (start included);
/// beyond that the fit is only extended and checked point by point.
pub const FIT_WINDOW: usize = 10;

/// Longest segment the fitter emits. Keeps the per-segment quantisation bucket ≤ 24.
pub(crate) const MAX_SEGMENT_LEN: usize = 1 << 24;

/// Longest track (frames) the format accepts; the index stores frame counts as `u32`.
pub const MAX_TRACK_FRAMES: usize = u32::MAX as usize;

/// Quantisation steps Δ = ratio · e_max and Δθ = ratio · θ_max. A step ≤ 2/√3 of the bound
/// guarantees that a one-frame segment (which interpolates its end point exactly before
/// quantisation) always meets the bound — a point of the cubic lattice lies within `√3/2·Δ` of
/// any point, and the coefficient lattice has the same covering radius — so the greedy fitter
/// always makes progress. 1.1 is close to the limit 1.1547 (measured on the shipped scenes: 1–2 %
/// smaller than ratio 1; 1.15 was no better).
pub(crate) const STEP_RATIO: f64 = 1.1;

/// The first position and orientation of an object are quantised this much finer than Δ and Δθ
/// (`[position, rotation]`), so that the first segment does not start with an error already
/// close to the bound. An object restates its start in every ~1 s segment, so a coarser start
/// saves bits: measured on the shipped scenes, 8 for positions is ~1 % smaller than 16 (4 left
/// too little of the bound for long curves: a 5 s parabola became two segments), and 4 for
/// orientations 0.3–1 % smaller than 8 (the encoder searches lattice points near each fit where
/// the nearest breaks the bound, which recovers most of the slack).
pub(crate) const START_STEP_DIVISORS: [f64; 2] = [8.0, 4.0];

/// Rotation errors involve `sin`/`cos`, whose last bit may differ between math libraries. The
/// encoder therefore checks rotations against θ_max·(1 − margin), so a decoder on another platform
/// still stays within θ_max. Positions use only `+`, `×` and `√`, which IEEE 754 makes exact, so
/// they need no margin.
pub(crate) const ROT_BOUND_MARGIN: f64 = 1e-9;

/// Smallest accepted θ_max: below this the margin above and `f64` rounding of unit quaternions
/// (≈1e-16) would dominate the bound.
pub const MIN_THETA_MAX: f64 = 1e-9;

/// Named speed/accuracy presets. The only place the preset
/// bounds are written down.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Quality {
    /// Fast previews: 5 mm, 5 mrad.
    Draft,
    /// The default for browsing: 1 mm, 1 mrad.
    #[default]
    Standard,
    /// Final renders: 0.1 mm, 0.1 mrad.
    Final,
}

impl Quality {
    /// `(e_max` in metres, `θ_max` in radians`)`.
    pub const fn bounds(self) -> (f64, f64) {
        match self {
            Quality::Draft => (5e-3, 5e-3),
            Quality::Standard => (1e-3, 1e-3),
            Quality::Final => (1e-4, 1e-4),
        }
    }

    /// Position bound e_max (metres, Euclidean norm of the per-frame error).
    pub const fn e_max(self) -> f64 {
        self.bounds().0
    }

    /// Rotation bound θ_max (radians, angle of the residual rotation).
    pub const fn theta_max(self) -> f64 {
        self.bounds().1
    }
}

/// What the encoder may assume about the forces acting on the bodies. "Model only what the scene
/// requires" (§4.3): with gravity-only free flight the quadratic term of every flight segment is
/// known, so it costs one bit instead of three quantised coefficients.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum MotionModel {
    /// Any forces (damping, drag, joints, motors): a full per-axis quadratic in every segment.
    General,
    /// No damping: in free flight the quadratic term is exactly `g/2 · t²`. Each segment carries a
    /// flag bit — "quadratic term = gravity's" — otherwise a full per-axis quadratic follows
    /// (contacts, rolling, resting).
    FreeFlightGravity {
        /// Gravity in scene units (y-up scenes: `[0, -9.81, 0]`).
        g: [f64; 3],
    },
}

impl MotionModel {
    pub(crate) fn gravity(self) -> [f64; 3] {
        match self {
            MotionModel::General => [0.0; 3],
            MotionModel::FreeFlightGravity { g } => g,
        }
    }
}

/// How hard the encoder searches for each segment. Either way every frame decodes within the
/// bounds and the format is the same: only the encoder's choices, and so its speed and the
/// stream's size, differ.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Search {
    /// At every segment start, every candidate curve the format offers is fitted and the
    /// cheapest per frame is kept. The smallest streams, at the finest bounds especially
    /// (what [`Quality::Final`] uses).
    Exhaustive,
    /// Fewer fits for about the same size (what [`Quality::Draft`] and [`Quality::Standard`]
    /// use). A quadratic rotation curve (a fit that mostly fails: on pachinko at Standard,
    /// 82 % of them end shorter than the shortest quadratic segment written) that lost at one
    /// segment start is not fitted at the next one; after its n-th loss in a row, not at the
    /// next n (at most [`ADAPTIVE_MAX_SKIP`]); from its first win on it is fitted at every
    /// start again.
    /// Measured at Standard on the shipped scenes (`mwb bench codec --search`, medians of three
    /// alternated runs): the encoder 10–16 % faster; streams the same size on tumble, 0.9 %
    /// smaller on tower, 0.9 % larger on pachinko and 5.7 % on chute (one rolling body, whose
    /// quadratic wins come between losses).
    #[default]
    Adaptive,
}

/// Most segment starts at which [`Search::Adaptive`] skips a candidate that keeps losing
/// (from 8 to 32 the shipped scenes' streams are the same size to 0.1 %).
pub const ADAPTIVE_MAX_SKIP: u32 = 16;

/// The error for a bad parameter, naming it.
fn invalid(name: &'static str, value: f64, expected: &'static str) -> Result<(), CodecError> {
    Err(CodecError::InvalidParam {
        name,
        value,
        expected,
    })
}

/// How the simulator turns bodies in free flight, for the codec's free-flight rotation segments
/// ([`crate::encode_world_with_dynamics`]). With it, a thrown body's whole flight is one
/// segment of three coefficients instead of a quadratic every few frames.
#[derive(Debug, Clone, PartialEq)]
pub struct RotationDynamics {
    /// Velocity-integration substeps per frame (rapier: `num_solver_iterations`), 1..=16.
    pub substeps: u32,
    /// Angular damping coefficient (1/s; velocity × `1/(1 + dt·c)` per frame).
    pub angular_damping: f64,
    /// Per object, its principal moments of inertia when its principal axes are its body axes
    /// (as for boxes, spheres, capsules and cylinders built around their centre); `None` for an
    /// object the model does not describe. Missing entries count as `None`.
    pub inertia: Vec<Option<[f64; 3]>>,
}

impl RotationDynamics {
    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), CodecError> {
        if !(1..=crate::format::MAX_SUBSTEPS).contains(&self.substeps) {
            return invalid("substeps", f64::from(self.substeps), "in 1..=16");
        }
        if !(self.angular_damping.is_finite() && self.angular_damping >= 0.0) {
            return invalid("angular_damping", self.angular_damping, "finite and ≥ 0");
        }
        for i in self.inertia.iter().flatten() {
            for &v in i {
                if !(v.is_finite() && v > 0.0) {
                    return invalid("inertia", v, "finite and > 0");
                }
            }
        }
        Ok(())
    }
}

/// Everything [`crate::encode_world`] needs besides the tracks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EncodeParams {
    /// Bound on the Euclidean position error of every decoded frame (metres).
    pub e_max: f64,
    /// Bound on the rotation angle between decoded and input orientation of every frame (rad).
    pub theta_max: f64,
    /// Time between consecutive samples (seconds).
    pub frame_dt: f64,
    /// Which forces the position model may assume.
    pub model: MotionModel,
    /// Vertex rate of the [`crate::LowResPath`] produced beside the stream (Hz).
    pub lowres_hz: f64,
    /// How many candidate curves are fitted per segment start.
    pub search: Search,
}

impl EncodeParams {
    /// Parameters from a quality preset, with the default low-res rate.
    pub fn from_quality(quality: Quality, frame_dt: f64, model: MotionModel) -> Self {
        let (e_max, theta_max) = quality.bounds();
        Self {
            e_max,
            theta_max,
            frame_dt,
            model,
            lowres_hz: DEFAULT_LOWRES_HZ,
            search: match quality {
                Quality::Final => Search::Exhaustive,
                Quality::Draft | Quality::Standard => Search::Adaptive,
            },
        }
    }

    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), CodecError> {
        if !(self.e_max.is_finite() && self.e_max > 0.0) {
            return invalid("e_max", self.e_max, "finite and > 0");
        }
        if !(self.theta_max.is_finite()
            && self.theta_max >= MIN_THETA_MAX
            && self.theta_max < std::f64::consts::PI)
        {
            return invalid("theta_max", self.theta_max, "in [1e-9, π)");
        }
        if !(self.frame_dt.is_finite() && self.frame_dt > 0.0) {
            return invalid("frame_dt", self.frame_dt, "finite and > 0");
        }
        if !(self.lowres_hz.is_finite() && self.lowres_hz > 0.0) {
            return invalid("lowres_hz", self.lowres_hz, "finite and > 0");
        }
        if let MotionModel::FreeFlightGravity { g } = self.model {
            for (name, v) in ["g.x", "g.y", "g.z"].into_iter().zip(g) {
                if !v.is_finite() {
                    return invalid(name, v, "finite");
                }
            }
        }
        Ok(())
    }

    pub(crate) fn pos_step(&self) -> f64 {
        STEP_RATIO * self.e_max
    }

    pub(crate) fn rot_step(&self) -> f64 {
        STEP_RATIO * self.theta_max
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn standard_preset_is_one_millimetre_one_milliradian() {
        assert_eq!(Quality::Standard.bounds(), (1e-3, 1e-3));
        assert_eq!(Quality::default(), Quality::Standard);
        let p =
            EncodeParams::from_quality(Quality::Standard, DEFAULT_FRAME_DT, MotionModel::General);
        assert_eq!((p.e_max, p.theta_max), (1e-3, 1e-3));
        assert!(Quality::Draft.e_max() > Quality::Standard.e_max());
        assert!(Quality::Final.theta_max() < Quality::Standard.theta_max());
    }

    #[test]
    fn validation_names_the_field() {
        let ok = EncodeParams::from_quality(Quality::Draft, 0.01, MotionModel::General);
        assert!(ok.validate().is_ok());
        let cases = [
            (EncodeParams { e_max: 0.0, ..ok }, "e_max"),
            (
                EncodeParams {
                    theta_max: f64::NAN,
                    ..ok
                },
                "theta_max",
            ),
            (
                EncodeParams {
                    theta_max: 4.0,
                    ..ok
                },
                "theta_max",
            ),
            (
                EncodeParams {
                    frame_dt: -1.0,
                    ..ok
                },
                "frame_dt",
            ),
            (
                EncodeParams {
                    lowres_hz: f64::INFINITY,
                    ..ok
                },
                "lowres_hz",
            ),
            (
                EncodeParams {
                    model: MotionModel::FreeFlightGravity {
                        g: [0.0, f64::NAN, 0.0],
                    },
                    ..ok
                },
                "g.y",
            ),
        ];
        for (p, field) in cases {
            match p.validate() {
                Err(CodecError::InvalidParam { name, .. }) => assert_eq!(name, field),
                other => panic!("{field}: {other:?}"),
            }
        }
    }
}
