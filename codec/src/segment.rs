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

/// Angular accelerations are quantised like quadratic position terms, `Δθ·4⁻ᵏ`
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

/// `round(q)` if it is representable, else `None`.
fn round_checked(q: f64) -> Option<i64> {
    if q.abs() < QLIM {
        return Some(round_small(q));
    }
    let q = q.round();
    (q.is_finite() && q.abs() <= QLIM).then_some(q as i64)
}

/// `round(x / step)`, total (unlike [`round_checked`]): a prediction only needs to be deterministic, not accurate.
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
    /// The start-step divisors ([`crate::params::START_STEP_DIVISORS`]).
    pub start_divisor: f64,
    pub rot_start_divisor: f64,
    /// The lattice of steps and coefficients.
    pub lattice: Lattice,
}

impl PositionCoding {
    pub(crate) fn new(step: f64, gravity: Option<Vec3>, frame_dt: f64) -> Self {
        let h2 = frame_dt * frame_dt;
        let [start_divisor, rot_start_divisor] = crate::params::START_STEP_DIVISORS;
        Self {
            step,
            gravity_term: gravity.map(|g| [g[0] * h2 * 0.5, g[1] * h2 * 0.5, g[2] * h2 * 0.5]),
            start_divisor,
            rot_start_divisor,
            lattice: Lattice,
        }
    }

    pub(crate) fn start_step(&self) -> f64 {
        self.step / self.start_divisor
    }
}

/// Position segment types, in code order (see `format`).
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

/// Rotation segment types, in code order; the first is the initial "previous type".
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum RotationType {
    Linear,
    Quadratic,
    Step,
    Rest,
    Key,
    /// Worlds with rotation dynamics only: torque-free flight ([`FreeDynamics`]).
    Free,
}

/// The rotation types in code order. Free flight is last: a world without rotation dynamics codes
/// the five before it, and (the type code not depending on how many there are) a world with
/// dynamics whose objects use none is coded as one without.
const ROTATION_TYPES: [RotationType; 6] = [
    RotationType::Linear,
    RotationType::Quadratic,
    RotationType::Step,
    RotationType::Rest,
    RotationType::Key,
    RotationType::Free,
];

/// The rotation types a world codes: with rotation dynamics the free-flight type too.
pub(crate) fn rotation_types(dynamics: bool) -> &'static [RotationType] {
    if dynamics {
        &ROTATION_TYPES
    } else {
        &ROTATION_TYPES[..5]
    }
}

/// How a body turns in free flight, for [`RotationCurve::Free`] segments.
///
/// Between contacts a body's angular momentum is constant, but unless its inertia is isotropic its
/// angular velocity is not: a box thrown with a spin about a non-principal axis wobbles
/// (precession), so neither a linear nor a quadratic log-map curve follows it for long — on the
/// shipped tumble scene 9-frame quadratics were the best, a third of the rotation bits. Knowing
/// the body's principal moments (body axes = principal axes), the whole flight follows from the
/// angular velocity at its start. The integrator mirrors the simulator's (rapier 0.36): per frame,
/// `substeps` times an explicit gyroscopic update that keeps |L| and then a linearised quaternion
/// step `q ← normalise((h·ω/2, 1) ⊗ q)` (computed in the body frame, see [`Self::frame`]), then
/// angular damping `ω ← ω·damping`. It uses only `+`, `−`, `×`, `/` and `√`, which IEEE 754
/// rounds exactly, so every platform decodes the same bits. The model only has to be close: the
/// encoder checks every frame against the bound and ends the segment where it drifts (on tumble a
/// throw takes one to three such segments).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct FreeDynamics {
    /// Principal moments of inertia along the body axes, the largest 1 (as decoded).
    pub inertia: Vec3,
    /// Their reciprocals.
    pub inv_inertia: Vec3,
    /// The moments as stored: `round(I/I_max · 4095)`, each in `1..=4095`.
    pub inertia_code: [u16; 3],
    /// Gyroscopic and integration substeps per frame (≥ 1).
    pub substeps: u32,
    /// Angular velocity factor per frame, `1 / (1 + dt·c)` for angular damping `c`.
    pub damping: f64,
}

/// Longest free-flight segment (frames; 34 s at 120 Hz). Decoding simulates every frame of a
/// flight, so the format bounds one flight's work; a longer flight is several segments.
pub(crate) const MAX_FREE_LEN: u32 = 4096;

/// Bits per stored principal moment (relative precision 2.4·10⁻⁴; measured on the shipped
/// scenes, 8 and 16 bits gave streams within ±0.5 %).
pub(crate) const INERTIA_BITS: u32 = 12;

/// An object's principal moments as stored (relative to the largest, [`INERTIA_BITS`] each; only
/// their ratios matter to a torque-free body), or `None` if one is zero, negative or not finite,
/// or so small against the largest that it would round to zero.
pub(crate) fn quantise_inertia(i: Vec3) -> Option<[u16; 3]> {
    let max = i[0].max(i[1]).max(i[2]);
    if !(i.iter().all(|v| v.is_finite() && *v > 0.0) && max.is_finite()) {
        return None;
    }
    let scale = f64::from((1u32 << INERTIA_BITS) - 1);
    let code = i.map(|v| (v / max * scale).round());
    code.iter()
        .all(|&c| (1.0..=scale).contains(&c))
        .then(|| code.map(|c| c as u16))
}

impl FreeDynamics {
    /// From stored moments (each ≥ 1), substeps (≥ 1) and the damping coefficient.
    pub(crate) fn new(
        inertia_code: [u16; 3],
        substeps: u32,
        angular_damping: f64,
        frame_dt: f64,
    ) -> Self {
        let scale = f64::from((1u32 << INERTIA_BITS) - 1);
        let inertia = inertia_code.map(|c| f64::from(c) / scale);
        Self {
            inertia,
            inv_inertia: inertia.map(|i| 1.0 / i),
            inertia_code,
            substeps: substeps.max(1),
            damping: 1.0 / (1.0 + frame_dt * angular_damping),
        }
    }

    /// The body-frame angular velocity of world-frame `w` at orientation `q` (the simulation's
    /// state: in the body frame the gyroscopic step needs no rotation).
    pub(crate) fn body(q: Quat, w: Vec3) -> Vec3 {
        rotation::rotate(rotation::conj(q), w)
    }

    /// The world-frame angular velocity of body-frame `wb` at orientation `q`.
    pub(crate) fn world(q: Quat, wb: Vec3) -> Vec3 {
        rotation::rotate(q, wb)
    }

    /// One frame: `q` and `wb` (body-frame angular velocity, rad per frame) at the start of a
    /// frame → at the start of the next. A world-frame step `(h·ω/2, 1) ⊗ q` is the body-frame
    /// step `q ⊗ (h·ω_b/2, 1)`, so nothing is rotated: the encoder's fit runs this ~10⁵ times
    /// per segment.
    pub(crate) fn frame(&self, q: &mut Quat, wb: &mut Vec3) {
        let h = 1.0 / f64::from(self.substeps);
        for _ in 0..self.substeps {
            self.substep(q, wb, h);
        }
        *wb = rotation::scale3(*wb, self.damping);
    }

    /// [`Self::frame`] for `N` independent bodies at once, each computed exactly as `frame`
    /// computes it. One substep's operations form a long chain of dependent square roots and
    /// divisions; running the bodies' chains side by side lets the processor overlap them (the
    /// free-flight fit simulates four start velocities over the same frames: 3 % of the
    /// encoder's time on tumble, the same instructions).
    pub(crate) fn frames<const N: usize>(&self, q: &mut [Quat; N], wb: &mut [Vec3; N]) {
        let h = 1.0 / f64::from(self.substeps);
        for _ in 0..self.substeps {
            for (q, wb) in q.iter_mut().zip(wb.iter_mut()) {
                self.substep(q, wb, h);
            }
        }
        for wb in wb.iter_mut() {
            *wb = rotation::scale3(*wb, self.damping);
        }
    }

    /// One of a frame's substeps of length `h`: the gyroscopic update, then the rotation.
    #[inline(always)]
    fn substep(&self, q: &mut Quat, wb: &mut Vec3, h: f64) {
        *wb = self.gyroscopic(*wb, h);
        let hw = rotation::scale3(*wb, 0.5 * h);
        // `q ⊗ (hw, 1)`, the products with the 1 left out: `x·1.0 = x` exactly, so these are
        // the bits of `rotation::mul(*q, [hw[0], hw[1], hw[2], 1.0])` with four fewer products.
        let [ax, ay, az, aw] = *q;
        let [bx, by, bz] = hw;
        let n = [
            aw * bx + ax + ay * bz - az * by,
            aw * by - ax * bz + ay + az * bx,
            aw * bz + ax * by - ay * bx + az,
            aw - ax * bx - ay * by - az * bz,
        ];
        let n2 = n[0] * n[0] + n[1] * n[1] + n[2] * n[2] + n[3] * n[3];
        // |n|² ≥ 1 for a unit q (the step only adds an orthogonal part), unless w is huge.
        if n2.is_finite() && n2 > 0.0 {
            let r = 1.0 / n2.sqrt();
            *q = [n[0] * r, n[1] * r, n[2] * r, n[3] * r];
        }
    }

    /// The explicit gyroscopic term over `h` frames in the body (principal) frame, rescaled to
    /// keep |L| (as rapier does).
    fn gyroscopic(&self, wb: Vec3, h: f64) -> Vec3 {
        let (i, inv) = (self.inertia, self.inv_inertia);
        // A body with equal moments (a sphere's are stored as three 1s) has L = ω exactly, so
        // ω × L is exactly zero (each component is a product minus the same product), L is kept
        // and the rescale is x/x = 1: the computation below returns `wb` bit for bit, in every
        // branch. Skipping it saves about half of each simulated substep of a ball (by operation
        // count), to encode and to decode.
        if i == [1.0; 3] && inv == [1.0; 3] {
            return wb;
        }
        self.gyroscopic_general(wb, h)
    }

    /// [`FreeDynamics::gyroscopic`] without the shortcut for equal moments.
    fn gyroscopic_general(&self, wb: Vec3, h: f64) -> Vec3 {
        let (i, inv) = (self.inertia, self.inv_inertia);
        let l = [i[0] * wb[0], i[1] * wb[1], i[2] * wb[2]];
        let g = rotation::cross3(wb, l);
        let lt = [l[0] - g[0] * h, l[1] - g[1] * h, l[2] - g[2] * h];
        let lt2 = rotation::dot3(lt, lt);
        if !(lt2 > 0.0 && lt2.is_finite()) {
            return wb;
        }
        let s = (rotation::dot3(l, l) / lt2).sqrt();
        let out = [lt[0] * s * inv[0], lt[1] * s * inv[1], lt[2] * s * inv[2]];
        if out.iter().all(|v| v.is_finite()) {
            out
        } else {
            wb
        }
    }

    /// Orientation and world-frame angular velocity after `frames` frames from `(q0, w)`.
    pub(crate) fn advance(&self, q0: Quat, w: Vec3, frames: u32) -> (Quat, Vec3) {
        let (mut q, mut wb) = (q0, Self::body(q0, w));
        for _ in 0..frames {
            self.frame(&mut q, &mut wb);
        }
        (q, Self::world(q, wb))
    }
}

/// Step segments (one frame each, no length): where a body is in contact the motion
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

/// How 3-vectors (steps and curve coefficients) are quantised: the body-centred cubic (BCC)
/// lattice with the covering radius √3/2·s of the cubic lattice of spacing `s` — every point of
/// space within that distance of a lattice point, which is what the error bound needs — and a
/// cell volume 1.86× larger: the BCC lattice is the thinnest covering of 3-space, the cubic one is
/// 1.86× thicker. At the same worst-case error a coefficient costs log₂ 1.86 ≈ 0.9 bit less.
///
/// A BCC point is two interleaved cubic lattices of spacing a = s·2√3/√5: `a·k` and
/// `a·(k + ½·(1, 1, 1))`. Lattice coordinates are doubled, `K = 2k + c·(1, 1, 1)` (the point
/// is `K·a/2`, all three of one parity); the stream holds the coset bit c (equiprobable: coded
/// relative to the coset nearest the prediction, with a context, it measured 0.5 % larger), then
/// k against the prediction `round(p/a − c/2)`, as three residuals on the vector's stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Lattice;

/// a / s for the BCC lattice: 2√3/√5.
const BCC_SCALE: f64 = 1.549_193_338_482_966_8;

impl Lattice {
    /// Lattice coordinates of the point nearest `x`, for the lattice with the covering radius of
    /// the cubic lattice of spacing `step`; `None` if not representable.
    pub(crate) fn quantise(self, x: Vec3, step: f64) -> Option<[i64; 3]> {
        // In units of a: the nearest point of each coset, then the nearer of the two.
        let inv = 1.0 / (step * BCC_SCALE);
        let u: Vec3 = x.map(|v| v * inv);
        let (mut even, mut odd) = ([0i64; 3], [0i64; 3]);
        let (mut d_even, mut d_odd) = (0.0, 0.0);
        for i in 0..3 {
            // The nearest odd point is o + ½ with o = e or e − 1, whichever side of e u lies on.
            let e = round_checked(u[i])?;
            let de = u[i] - e as f64;
            let o = if de >= 0.0 { e } else { e - 1 };
            let d_o = u[i] - 0.5 - o as f64;
            d_even += de * de;
            d_odd += d_o * d_o;
            (even[i], odd[i]) = (2 * e, 2 * o + 1);
        }
        Some(if d_odd < d_even { odd } else { even })
    }

    /// Up to `n` lattice points near `x` other than `q` (its nearest), nearest first: the
    /// candidates an encoder may try when the nearest point's curve breaks the bound (the
    /// coefficients nearest the least-squares fit are not always those that stay within the
    /// bound longest). BCC: among the 14 neighbours of `q` (8 in the other coset at a·√3/2, 6 in
    /// its own at a), from the 10 that can be among the 4 nearest (for n ≤ 4 these are the n
    /// nearest of all 14).
    pub(crate) fn alternatives(self, q: [i64; 3], x: Vec3, step: f64, n: usize) -> Near {
        let mut out = Near::EMPTY;
        // In half-spacing units x is q + u; a neighbour q + d is at |u − d|², which ranks as
        // |d|² − 2 u·d. The best diagonal neighbour is d = sign(u) and each flipped component adds
        // 4|uᵢ|; the best axial ones go along u's components. The diagonal with all three flipped
        // is beaten by seven others and the axial ones against u by their opposites, so these
        // ten contain the four nearest of all fourteen.
        let inv_h = 2.0 / (step * BCC_SCALE);
        let u: Vec3 = std::array::from_fn(|i| x[i] * inv_h - q[i] as f64);
        let sgn: [i64; 3] = u.map(|v| if v < 0.0 { -1 } else { 1 });
        let abs = u.map(f64::abs);
        let base = 3.0 - 2.0 * (abs[0] + abs[1] + abs[2]);
        // Ranks and offsets of the ten, and their order (sorting the small indices, not the
        // offsets, is what makes this cheap).
        let mut rank = [0.0f64; 10];
        let mut offset = [[0i64; 3]; 10];
        (rank[0], offset[0]) = (base, sgn);
        for i in 0..3 {
            let mut flip = sgn;
            flip[i] = -flip[i];
            (rank[1 + i], offset[1 + i]) = (base + 4.0 * abs[i], flip);
            let mut keep = sgn.map(|v| -v);
            keep[i] = sgn[i];
            (rank[4 + i], offset[4 + i]) = (base + 4.0 * (abs[0] + abs[1] + abs[2] - abs[i]), keep);
            let mut axial = [0; 3];
            axial[i] = 2 * sgn[i];
            (rank[7 + i], offset[7 + i]) = (4.0 - 4.0 * abs[i], axial);
        }
        let mut order: [u8; 10] = std::array::from_fn(|i| i as u8);
        // The n nearest, by selection (n is small; the first of equal ranks; all are finite,
        // since `x` quantised, and none is −0).
        let n = n.min(rank.len());
        for i in 0..n {
            let mut m = i;
            for j in i + 1..rank.len() {
                if rank[j] < rank[m] {
                    m = j;
                }
            }
            rank.swap(i, m);
            order.swap(i, m);
            let d = offset[usize::from(order[i])];
            out.points[i] = std::array::from_fn(|j| q[j].saturating_add(d[j]));
        }
        out.len = n;
        out
    }

    /// The point with lattice coordinates `q`.
    pub(crate) fn point(self, q: [i64; 3], step: f64) -> Vec3 {
        dequantise3(q, step * BCC_SCALE * 0.5)
    }

    /// `q` as written: its coset bit and the integers `k` (`K = 2k + c`).
    pub(crate) fn coset_and_integers(self, q: [i64; 3]) -> (u64, [i64; 3]) {
        let c = q[0].rem_euclid(2);
        (c as u64, q.map(|v| (v - c) / 2))
    }

    /// How `q` is written against the prediction `pred` (a point of space): the coset bit, then
    /// the integers and their integer prediction (the stream codes the difference).
    pub(crate) fn split(self, q: [i64; 3], pred: Vec3, step: f64) -> Coded {
        let (coset, k) = self.coset_and_integers(q);
        Coded {
            coset,
            k,
            pred: self.prediction(coset, pred, step),
        }
    }

    /// The integer prediction of a vector's integers given its coset bit — what the reader needs
    /// before reading them.
    pub(crate) fn prediction(self, coset: u64, pred: Vec3, step: f64) -> [i64; 3] {
        let a = step * BCC_SCALE;
        let off = if coset == 1 { 0.5 * a } else { 0.0 };
        pred.map(|p| predict(p - off, a))
    }

    /// Lattice coordinates from what was read; `None` if they overflow.
    pub(crate) fn join(self, coset: u64, k: [i64; 3]) -> Option<[i64; 3]> {
        let mut out = [0i64; 3];
        for (o, v) in out.iter_mut().zip(k) {
            *o = v.checked_mul(2)?.checked_add(coset as i64)?;
        }
        Some(out)
    }
}

/// Lattice points near a point, nearest first ([`Lattice::alternatives`]; no allocation).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Near {
    points: [[i64; 3]; 10],
    len: usize,
}

impl Near {
    pub(crate) const EMPTY: Near = Near {
        points: [[0; 3]; 10],
        len: 0,
    };

    pub(crate) fn as_slice(&self) -> &[[i64; 3]] {
        &self.points[..self.len]
    }
}

/// A lattice vector as written: coset bit, integers, their prediction.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Coded {
    pub coset: u64,
    pub k: [i64; 3],
    pub pred: [i64; 3],
}

/// What a step decodes to: the prediction plus the quantised residual (a position, or for
/// rotations the rotation vector of the frame), lattice point `q`.
pub(crate) fn step_end(pred: Vec3, q: [i64; 3], step: f64, lattice: Lattice) -> Vec3 {
    let d = lattice.point(q, step);
    std::array::from_fn(|i| pred[i] + d[i])
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
    /// The start point, held (a body at rest costs a type code and a length).
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
    /// The model's `h²g/2` (a segment type of its own in gravity worlds).
    Gravity,
    /// None: the segment is linear.
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
        let b = coding.lattice.point(self.bq, step_linear(coding.step, k));
        let a = match self.term {
            QuadraticTerm::Fitted(aq) => coding.lattice.point(aq, step_quadratic(coding.step, k)),
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

    /// The predicted quadratic term (the previous segment's).
    pub(crate) fn quadratic(&self) -> Vec3 {
        self.quadratic
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
    /// Constant angular acceleration in the log map, `q(u) = exp(u·ω + u²·α) ⊗ q₀` —
    /// a box tipping over an edge, a ball spun up by friction (§4.3 found linear "sufficient"
    /// at its bounds; at 1 mrad contact phases need the second term).
    Quadratic { w: Vec3, a: Vec3 },
    /// A one-frame jump to an exactly stored orientation (fallback, as for positions).
    Key { end: Quat },
    /// The start orientation, held.
    Rest,
    /// Torque-free flight from angular velocity `w` (world frame, rad per frame).
    Free { w: Vec3, dynamics: FreeDynamics },
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
            RotationCurve::Key { .. } | RotationCurve::Rest | RotationCurve::Free { .. } => None,
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
            RotationCurve::Free { w, dynamics } => {
                // Frames are simulated; between frames, the two neighbours are interpolated.
                // Callers bound `u` by the segment length.
                let whole = u.floor().clamp(0.0, f64::from(u32::MAX)) as u32;
                let (q, w) = dynamics.advance(q0, w, whole);
                let frac = u - f64::from(whole);
                if frac > 0.0 {
                    let (next, _) = dynamics.advance(q, w, 1);
                    rotation::nlerp(q, next, frac)
                } else {
                    q
                }
            }
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
    /// The angular velocity (per frame) at the end of the previous segment.
    pub(crate) fn angular_velocity(&self) -> Vec3 {
        self.w
    }

    /// Quadratic segments: the predicted angular acceleration.
    pub(crate) fn angular_acceleration(&self) -> Vec3 {
        self.a
    }

    /// `q0`: the segment's start orientation (a free flight's end depends on it).
    pub(crate) fn advance(&mut self, curve: &RotationCurve, len: u32, q0: Quat) {
        match *curve {
            RotationCurve::Linear { w } => self.w = w,
            RotationCurve::Quadratic { w, a } => {
                let l = f64::from(len);
                self.w = std::array::from_fn(|i| w[i] + 2.0 * a[i] * l);
                self.a = a;
            }
            RotationCurve::Rest => self.w = [0.0; 3],
            RotationCurve::Key { .. } => {}
            // The angular velocity at the end of the flight (the next curve's prediction).
            RotationCurve::Free { w, dynamics } => self.w = dynamics.advance(q0, w, len).1,
        }
    }

    /// [`Self::advance`] over a segment of `len ≥ 1` frames from `q0`, also returning the
    /// orientations of its last two frames (`len − 1` and `len`) — for a free flight from one
    /// simulation instead of three.
    pub(crate) fn follow(&mut self, curve: &RotationCurve, len: u32, q0: Quat) -> (Quat, Quat) {
        self.follow_into(curve, len, q0, None)
    }

    /// [`Self::follow`]; a free flight's frames `1..=len` are also pushed onto `frames` (the
    /// simulation that finds the segment's end computes them anyway: a reader decoding every
    /// frame then simulates each flight once). Other curves push nothing.
    pub(crate) fn follow_into(
        &mut self,
        curve: &RotationCurve,
        len: u32,
        q0: Quat,
        mut frames: Option<&mut Vec<Quat>>,
    ) -> (Quat, Quat) {
        if let RotationCurve::Free { w, dynamics } = *curve {
            let (mut q, mut wb) = (q0, FreeDynamics::body(q0, w));
            let mut before = q0;
            for _ in 0..len {
                before = q;
                dynamics.frame(&mut q, &mut wb);
                if let Some(out) = frames.as_deref_mut() {
                    out.push(q);
                }
            }
            self.w = FreeDynamics::world(q, wb);
            return (before, q);
        }
        self.advance(curve, len, q0);
        (
            curve.eval(q0, f64::from(len - 1)),
            curve.eval(q0, f64::from(len)),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn equal_moments_skip_a_gyroscopic_step_that_changes_nothing() {
        let sphere = FreeDynamics::new([4095; 3], 4, 0.5, 1.0 / 120.0);
        assert_eq!(sphere.inertia, [1.0; 3]);
        let mut seed = 7u64;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let mut cases: Vec<Vec3> = (0..20_000)
            .map(|i| {
                let scale = [1e-12, 1e-3, 1.0, 40.0, 1e150][i % 5];
                [rnd() * scale, rnd() * scale, rnd() * scale]
            })
            .collect();
        cases.extend([
            [0.0; 3],
            [-0.0, 0.0, -0.0],
            [f64::NAN, 1.0, 0.0],
            [f64::INFINITY, 0.0, 0.0],
            [1e300, -1e300, 1e300],
            [f64::MIN_POSITIVE, 0.0, 0.0],
        ]);
        for wb in cases {
            for h in [1.0, 0.25, 1.0 / 16.0] {
                let general = sphere.gyroscopic_general(wb, h);
                let skipped = sphere.gyroscopic(wb, h);
                // Bit for bit (NaN included).
                assert_eq!(
                    skipped.map(f64::to_bits),
                    general.map(f64::to_bits),
                    "{wb:?}"
                );
            }
        }
    }

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
        assert_eq!(round_checked(1.26 / 0.5), Some(3));
        assert_eq!(round_checked(f64::NAN), None);
        assert_eq!(round_checked(1e300 / 1e-300), None);
        assert_eq!(Lattice.quantise([1e300, 0.0, 0.0], 1e-300), None);
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

    /// The BCC lattice keeps the cubic lattice's covering radius (what the error bound needs),
    /// `quantise` finds the nearest point, coordinates of a point share their parity, and what a
    /// writer splits a reader joins back.
    #[test]
    fn the_bcc_lattice_covers_like_the_cubic_one_with_fewer_points() {
        let lattice = Lattice;
        let step = 0.37;
        let radius = 3f64.sqrt() / 2.0 * step;
        let mut seed = 11u64;
        let mut next = || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64 * 20.0 - 10.0
        };
        let mut worst = 0.0f64;
        for _ in 0..20_000 {
            let x = [next(), next(), next()];
            let q = lattice.quantise(x, step).unwrap();
            assert!(
                q.iter().all(|v| v.rem_euclid(2) == q[0].rem_euclid(2)),
                "{q:?}"
            );
            let p = lattice.point(q, step);
            let d = rotation::norm3(std::array::from_fn(|i| p[i] - x[i]));
            worst = worst.max(d / radius);
            // Nearest: no neighbour is closer; the alternatives are the nearest of the 14.
            let mut all: Vec<f64> = neighbours(q)
                .map(|k| {
                    let a = lattice.point(k, step);
                    rotation::norm3(std::array::from_fn(|i| a[i] - x[i]))
                })
                .collect();
            all.sort_by(f64::total_cmp);
            assert!(all[0] >= d - 1e-12);
            let alts = lattice.alternatives(q, x, step, 4);
            for (&k, want) in alts.as_slice().iter().zip(&all) {
                let a = lattice.point(k, step);
                let got = rotation::norm3(std::array::from_fn(|i| a[i] - x[i]));
                assert!((got - want).abs() < 1e-9, "{got} {want}");
            }
            let pred = [next(), next(), next()];
            let c = lattice.split(q, pred, step);
            assert_eq!(c.pred, lattice.prediction(c.coset, pred, step));
            assert_eq!(lattice.join(c.coset, c.k), Some(q));
        }
        // The covering radius is reached (deep holes exist) but never exceeded.
        assert!(worst <= 1.0 + 1e-12 && worst > 0.95, "{worst}");
        // Cell volume: a³/2 with a = step·2√3/√5, against step³ — 1.86 times larger.
        let a = step * BCC_SCALE;
        assert!((a.powi(3) / 2.0 / step.powi(3) - 1.859).abs() < 1e-3);
    }

    /// The 14 neighbours of a BCC point: 8 diagonal (other coset), 6 axial (same coset).
    fn neighbours(q: [i64; 3]) -> impl Iterator<Item = [i64; 3]> {
        (0..8)
            .map(|m| [m & 1, (m >> 1) & 1, (m >> 2) & 1].map(|b| 2 * b - 1))
            .chain((0..6).map(|m| {
                let mut d = [0; 3];
                d[m / 2] = if m % 2 == 0 { -2 } else { 2 };
                d
            }))
            .map(move |d| std::array::from_fn(|i| q[i] + d[i]))
    }

    /// The alternatives an encoder tries are lattice points, nearest first, never the nearest
    /// itself.
    #[test]
    fn lattice_alternatives_are_the_next_nearest_points() {
        let step = 1.0;
        let x = [0.3, -0.2, 0.45];
        let q = Lattice.quantise(x, step).unwrap();
        let near = Lattice.alternatives(q, x, step, 4);
        let alts = near.as_slice();
        assert_eq!(alts.len(), 4);
        let dist = |k: [i64; 3]| {
            let p = Lattice.point(k, step);
            rotation::norm3(std::array::from_fn(|i| p[i] - x[i]))
        };
        for w in alts.windows(2) {
            assert!(dist(w[0]) <= dist(w[1]));
        }
        for a in alts {
            assert_ne!(*a, q);
            assert!(a.iter().all(|v| v.rem_euclid(2) == a[0].rem_euclid(2)));
            assert!(dist(*a) >= dist(q));
        }
    }
}
