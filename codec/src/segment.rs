//! Spline segments as both encoder and decoder see them: quantisation, dequantisation, evaluation
//! and the predictors that turn coefficients into small residuals.
//!
//! The encoder checks the error bound on exactly the values these functions produce, and the
//! decoder calls the same functions with the same inputs, so the bound verified at encode time is
//! the bound the reader gets (§4.3, Figure 4.6: "spline errors are computed with respect to the
//! quantized coefficients").
//!
//! # Time and quantisation
//! A segment starting at frame `s` is evaluated at local time `u = frame − s` (in frames, so a
//! free-flight quadratic term is exactly `h²g/2` per frame², as in §4.3). Its length `L` selects a
//! bucket `k = ⌈log₂ L⌉`; linear coefficients are quantised with step `Δ·2⁻ᵏ` and quadratic ones
//! with `Δ·4⁻ᵏ`. Over `0 ≤ u ≤ L ≤ 2ᵏ` the quantisation error is then at most `Δ/2` per term and
//! axis, whatever the length — which is what lets long segments exist at all ("quantizing the
//! quadratic coefficient ai produces sizable errors, because t² grows much faster than t").
//! Powers of two keep every step exactly representable.

use crate::rotation::{self, Quat, Vec3};

/// Quantised coefficients are kept within ±2⁵² so that they, their residuals and their `f64`
/// images are exact.
pub(crate) const QLIM: f64 = 4_503_599_627_370_496.0;

/// `2^e` for `e` in the normal range, exactly.
pub(crate) fn pow2(e: i32) -> f64 {
    debug_assert!((-1022..=1023).contains(&e));
    f64::from_bits(((1023 + e) as u64) << 52)
}

/// `⌈log₂ len⌉` for `len ≥ 1`.
pub(crate) fn bucket(len: u32) -> u32 {
    debug_assert!(len >= 1);
    32 - (len - 1).leading_zeros()
}

pub(crate) fn step_linear(step: f64, k: u32) -> f64 {
    step * pow2(-(k as i32))
}

pub(crate) fn step_quadratic(step: f64, k: u32) -> f64 {
    step * pow2(-2 * k as i32)
}

/// Format 2: angular accelerations are quantised like quadratic position terms, `Δθ·4⁻ᵏ`
/// (measured on the shipped scenes: coarser or finer steps by 2× change the size by < 1 %).
pub(crate) fn step_angular_acceleration(step: f64, k: u32) -> f64 {
    step_quadratic(step, k)
}

/// `x.round()` (half away from zero) as an integer, for `|x| < 2⁵²`. Without SSE4.1, `f64::round`
/// is a software routine and was 8 % of the encoder's instructions; truncating through `i64` and
/// correcting by the (exactly representable) fraction gives the same integer.
fn round_small(x: f64) -> i64 {
    debug_assert!(x.abs() < QLIM);
    let t = x as i64;
    let frac = x - t as f64;
    if frac >= 0.5 {
        t + 1
    } else if frac <= -0.5 {
        t - 1
    } else {
        t
    }
}

/// `round(x / step)` if it is representable, else `None`.
pub(crate) fn quantise(x: f64, step: f64) -> Option<i64> {
    let q = x / step;
    if q.abs() < QLIM {
        return Some(round_small(q));
    }
    let q = q.round();
    (q.is_finite() && q.abs() <= QLIM).then_some(q as i64)
}

pub(crate) fn quantise3(x: Vec3, step: f64) -> Option<[i64; 3]> {
    Some([
        quantise(x[0], step)?,
        quantise(x[1], step)?,
        quantise(x[2], step)?,
    ])
}

/// Like [`quantise`], but total: a prediction only needs to be deterministic, not accurate.
fn predict(x: f64, step: f64) -> i64 {
    let q = x / step;
    if q.abs() < QLIM {
        return round_small(q);
    }
    let q = q.round();
    if q.is_finite() {
        q.clamp(-QLIM, QLIM) as i64
    } else {
        0
    }
}

pub(crate) fn dequantise3(q: [i64; 3], step: f64) -> Vec3 {
    [q[0] as f64 * step, q[1] as f64 * step, q[2] as f64 * step]
}

/// `quantised − predicted` as the non-negative integer the Rice coder stores.
pub(crate) fn residual(q: i64, pred: i64) -> u64 {
    crate::bits::zigzag(q - pred)
}

/// Inverse of [`residual`]; `None` if the result leaves the legal range.
pub(crate) fn unresidual(code: u64, pred: i64) -> Option<i64> {
    pred.checked_add(crate::bits::unzigzag(code))
        .filter(|q| (q.unsigned_abs() as f64) <= QLIM)
}

/// The per-world constants of the position code.
#[derive(Debug, Clone, Copy)]
pub(crate) struct PositionCoding {
    /// Δ: base quantisation step (metres).
    pub step: f64,
    /// `h²g/2` per axis when the model is free flight under gravity.
    pub gravity_term: Option<Vec3>,
}

impl PositionCoding {
    pub(crate) fn new(step: f64, gravity: Option<Vec3>, frame_dt: f64) -> Self {
        let h2 = frame_dt * frame_dt;
        Self {
            step,
            gravity_term: gravity.map(|g| [g[0] * h2 * 0.5, g[1] * h2 * 0.5, g[2] * h2 * 0.5]),
        }
    }

    pub(crate) fn start_step(&self) -> f64 {
        self.step / crate::params::START_STEP_DIVISOR
    }
}

/// Format 2 position segment types, in code order (see `format`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum PositionType {
    Gravity,
    Quadratic,
    Step,
    Linear,
    Rest,
    Key,
}

/// The position types a world's model allows, in code order; the first is the initial "previous
/// type" of every object.
pub(crate) fn position_types(gravity: bool) -> &'static [PositionType] {
    use PositionType::*;
    if gravity {
        &[Gravity, Quadratic, Step, Linear, Rest, Key]
    } else {
        &[Quadratic, Step, Linear, Rest, Key]
    }
}

/// Format 2 rotation segment types, in code order; the first is the initial "previous type".
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum RotationType {
    Linear,
    Quadratic,
    Step,
    Rest,
    Key,
}

pub(crate) const ROTATION_TYPES: [RotationType; 5] = [
    RotationType::Linear,
    RotationType::Quadratic,
    RotationType::Step,
    RotationType::Rest,
    RotationType::Key,
];

/// Format 2 step segments (one frame each, no length): where a body is in contact the motion
/// changes every frame, no curve spans more than a frame or two, and the derivative of such a
/// short curve predicts the next one badly. A step instead predicts the next frame by constant
/// velocity from the last two *decoded* frames (closed-loop DPCM, so quantisation errors do not
/// accumulate) and stores the difference quantised with Δ: at most `√3/2·Δ` off per frame.
/// `before` is the decoded frame before `c` (`None` at the start of a track: then the predicted
/// velocity of the previous segment is used).
pub(crate) fn position_step_prediction(c: Vec3, before: Option<Vec3>, velocity: Vec3) -> Vec3 {
    match before {
        Some(b) => std::array::from_fn(|i| c[i] + (c[i] - b[i])),
        None => std::array::from_fn(|i| c[i] + velocity[i]),
    }
}

/// What a step decodes to: the prediction plus the quantised residual (a position, or for
/// rotations the rotation vector of the frame).
pub(crate) fn step_end(pred: Vec3, q: [i64; 3], step: f64) -> Vec3 {
    std::array::from_fn(|i| pred[i] + q[i] as f64 * step)
}

/// Rotation steps: the predicted rotation vector of the next frame, the last frame-to-frame
/// rotation `log(q₀ ⊗ q_before⁻¹)` (or the previous segment's angular velocity at the start).
/// The step decodes to `RotationCurve::Linear { w: prediction + residual·Δθ }` over one frame.
pub(crate) fn rotation_step_prediction(q0: Quat, before: Option<Quat>, w: Vec3) -> Vec3 {
    match before {
        Some(b) => rotation::log(rotation::mul(q0, rotation::conj(b))),
        None => w,
    }
}

/// One decoded position segment, relative to its start point `c` (the previous segment's end:
/// C⁰ continuity, so `c` is stored once per object, §4.3).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum PositionCurve {
    /// `c + b·u + a·u²` per axis.
    Quadratic { b: Vec3, a: Vec3 },
    /// A one-frame jump to an exactly stored point: the fallback when no quantised curve can meet
    /// the bound (teleports, coordinates so large that `f64` spacing exceeds e_max).
    Key { end: Vec3 },
    /// Format 2: the start point, held (a body at rest costs a type code and a length).
    Rest,
}

impl PositionCurve {
    /// The curve at local time `u`; `u = 0` is the start point itself, bit for bit.
    pub(crate) fn eval(&self, c: Vec3, u: f64) -> Vec3 {
        if u == 0.0 {
            return c;
        }
        match *self {
            PositionCurve::Quadratic { b, a } => {
                std::array::from_fn(|i| c[i] + (b[i] * u + a[i] * (u * u)))
            }
            PositionCurve::Key { end } => {
                if u >= 1.0 {
                    end
                } else {
                    std::array::from_fn(|i| c[i] + (end[i] - c[i]) * u)
                }
            }
            PositionCurve::Rest => c,
        }
    }
}

/// The quadratic term of a position segment.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum QuadraticTerm {
    /// The model's `h²g/2` (one flag bit in format 1, a type code in format 2).
    Gravity,
    /// None: the segment is linear (format 2).
    Zero,
    /// Quantised with the bucket's quadratic step.
    Fitted([i64; 3]),
}

/// Quantised form of a quadratic position segment.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct QuadraticQ {
    pub bq: [i64; 3],
    pub term: QuadraticTerm,
}

impl QuadraticQ {
    pub(crate) fn curve(&self, coding: &PositionCoding, k: u32) -> PositionCurve {
        let b = dequantise3(self.bq, step_linear(coding.step, k));
        let a = match self.term {
            QuadraticTerm::Fitted(aq) => dequantise3(aq, step_quadratic(coding.step, k)),
            QuadraticTerm::Gravity => coding.gravity_term.unwrap_or([0.0; 3]),
            QuadraticTerm::Zero => [0.0; 3],
        };
        PositionCurve::Quadratic { b, a }
    }
}

/// Predicts a segment's coefficients from the previous one: the velocity at the end of the last
/// segment and its quadratic term. Motion is smooth between impacts, so residuals are small
/// (§4.3: "adjacent coefficients are differenced").
#[derive(Debug, Clone, Copy)]
pub(crate) struct PositionPredictor {
    velocity: Vec3,
    quadratic: Vec3,
}

impl PositionPredictor {
    pub(crate) fn new(coding: &PositionCoding) -> Self {
        Self {
            velocity: [0.0; 3],
            quadratic: coding.gravity_term.unwrap_or([0.0; 3]),
        }
    }

    /// The velocity (per frame) at the end of the previous segment.
    pub(crate) fn velocity(&self) -> Vec3 {
        self.velocity
    }

    pub(crate) fn predict(&self, coding: &PositionCoding, k: u32) -> ([i64; 3], [i64; 3]) {
        let sb = step_linear(coding.step, k);
        let sa = step_quadratic(coding.step, k);
        (
            std::array::from_fn(|i| predict(self.velocity[i], sb)),
            std::array::from_fn(|i| predict(self.quadratic[i], sa)),
        )
    }

    pub(crate) fn advance(&mut self, start: Vec3, len: u32, curve: &PositionCurve) {
        match *curve {
            PositionCurve::Quadratic { b, a } => {
                let l = f64::from(len);
                self.velocity = std::array::from_fn(|i| b[i] + 2.0 * a[i] * l);
                self.quadratic = a;
            }
            PositionCurve::Key { end } => {
                self.velocity = std::array::from_fn(|i| end[i] - start[i]);
            }
            PositionCurve::Rest => self.velocity = [0.0; 3],
        }
    }
}

/// One decoded rotation segment, relative to its start orientation `q₀`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum RotationCurve {
    /// §4.3: constant angular velocity in the log map, `q(u) = exp(u·ω) ⊗ q₀` (ω per frame,
    /// world frame).
    Linear { w: Vec3 },
    /// Format 2: constant angular acceleration in the log map, `q(u) = exp(u·ω + u²·α) ⊗ q₀` —
    /// a box tipping over an edge, a ball spun up by friction (§4.3 found linear "sufficient"
    /// at its bounds; at 1 mrad contact phases need the second term).
    Quadratic { w: Vec3, a: Vec3 },
    /// A one-frame jump to an exactly stored orientation (fallback, as for positions).
    Key { end: Quat },
    /// Format 2: the start orientation, held.
    Rest,
}

impl RotationCurve {
    /// The rotation vector `r(u)` of a log-map curve (`q(u) = exp(r(u)) ⊗ q₀`); the one
    /// expression both the bound test and [`RotationCurve::eval`] use.
    pub(crate) fn log_at(&self, u: f64) -> Option<Vec3> {
        match *self {
            RotationCurve::Linear { w } => Some(rotation::scale3(w, u)),
            RotationCurve::Quadratic { w, a } => {
                Some(std::array::from_fn(|i| w[i] * u + a[i] * (u * u)))
            }
            RotationCurve::Key { .. } | RotationCurve::Rest => None,
        }
    }

    /// The orientation at local time `u`; `u = 0` is the start orientation itself, bit for bit.
    pub(crate) fn eval(&self, q0: Quat, u: f64) -> Quat {
        if u == 0.0 {
            return q0;
        }
        match *self {
            RotationCurve::Linear { .. } | RotationCurve::Quadratic { .. } => {
                let r = self.log_at(u).unwrap_or([0.0; 3]);
                let q = rotation::mul(rotation::exp(r), q0);
                rotation::normalise(q).unwrap_or(q0)
            }
            RotationCurve::Key { end } => {
                if u >= 1.0 {
                    end
                } else {
                    rotation::nlerp(q0, end, u)
                }
            }
            RotationCurve::Rest => q0,
        }
    }
}

/// Predicts a rotation segment's coefficients: the angular velocity at the end of the previous
/// segment (torque-free bodies keep spinning) and its angular acceleration.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct RotationPredictor {
    w: Vec3,
    a: Vec3,
}

impl RotationPredictor {
    pub(crate) fn predict(&self, step: f64, k: u32) -> [i64; 3] {
        let s = step_linear(step, k);
        std::array::from_fn(|i| predict(self.w[i], s))
    }

    /// The angular velocity (per frame) at the end of the previous segment.
    pub(crate) fn angular_velocity(&self) -> Vec3 {
        self.w
    }

    /// Format 2, quadratic segments: the predicted angular acceleration.
    pub(crate) fn predict_acceleration(&self, step: f64, k: u32) -> [i64; 3] {
        let s = step_angular_acceleration(step, k);
        std::array::from_fn(|i| predict(self.a[i], s))
    }

    pub(crate) fn advance(&mut self, curve: &RotationCurve, len: u32) {
        match *curve {
            RotationCurve::Linear { w } => self.w = w,
            RotationCurve::Quadratic { w, a } => {
                let l = f64::from(len);
                self.w = std::array::from_fn(|i| w[i] + 2.0 * a[i] * l);
                self.a = a;
            }
            RotationCurve::Rest => self.w = [0.0; 3],
            RotationCurve::Key { .. } => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn buckets_cover_the_length() {
        assert_eq!(bucket(1), 0);
        assert_eq!(bucket(2), 1);
        assert_eq!(bucket(3), 2);
        assert_eq!(bucket(4), 2);
        assert_eq!(bucket(5), 3);
        assert_eq!(bucket(u32::MAX), 32);
        for len in 1..5000u32 {
            let k = bucket(len);
            assert!(1u64 << k >= u64::from(len));
            assert!(k == 0 || (1u64 << (k - 1)) < u64::from(len));
        }
    }

    #[test]
    fn steps_are_exact_powers_of_two() {
        assert_eq!(pow2(0), 1.0);
        assert_eq!(pow2(-3), 0.125);
        assert_eq!(step_linear(3.0, 2), 0.75);
        assert_eq!(step_quadratic(3.0, 2), 3.0 / 16.0);
    }

    #[test]
    fn the_fast_rounding_is_f64_round() {
        let mut seed = 7u64;
        let mut values = vec![0.0, -0.0, 0.5, -0.5, 1.5, -1.5, 2.5, 0.49999999999999994];
        values.extend([QLIM - 0.5, -(QLIM - 0.5), QLIM - 1.0, 4503599627370495.5]);
        for _ in 0..100_000 {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let m = (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
            let e = ((seed >> 3) % 60) as i32 - 8;
            values.push(m * 2f64.powi(e));
            values.push((m * 2f64.powi(e)).round() + 0.5);
        }
        for x in values.into_iter().filter(|x| x.abs() < QLIM) {
            assert_eq!(round_small(x), x.round() as i64, "{x}");
        }
    }

    #[test]
    fn quantisation_refuses_unrepresentable_values() {
        assert_eq!(quantise(1.26, 0.5), Some(3));
        assert_eq!(quantise(f64::NAN, 1.0), None);
        assert_eq!(quantise(1e300, 1e-300), None);
        assert_eq!(unresidual(residual(-7, 12), 12), Some(-7));
        assert_eq!(unresidual(crate::bits::zigzag(1), QLIM as i64), None);
        assert_eq!(unresidual(crate::bits::zigzag(-1), i64::MIN), None);
    }

    #[test]
    fn key_curves_hit_their_end_exactly() {
        let c = [0.1, 0.2, 0.3];
        let end = [1e9 + 0.1, -3.3, 7.0];
        assert_eq!(PositionCurve::Key { end }.eval(c, 1.0), end);
        let q = rotation::exp([0.1, 0.2, 0.3]);
        assert_eq!(
            RotationCurve::Key { end: q }.eval(rotation::IDENTITY, 1.0),
            q
        );
    }
}
