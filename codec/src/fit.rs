//! The greedy segment fitter of §4.3, Figure 4.6, for positions and rotations.
//!
//! For the first `k = 10` points of a segment (start included) the curve is re-fitted by least
//! squares each time a point is added and *every* point is checked; after that the fit is frozen
//! and only extended, checking each new point — the authors' O(n) compromise between refitting
//! everything (O(n²), Fig. 4.5 centre) and a poor fit (Fig. 4.5 left, i–j). All checks are made on
//! the *quantised* curve. Because the quantisation step depends on the length bucket (see
//! `segment`), the coefficients are re-quantised and all points re-checked whenever the length
//! crosses a power of two; that costs O(L) per doubling, so the fitter stays linear.
//!
//! Where the lattice point nearest the least-squares coefficients breaks the bound, the next
//! nearest points (`RESCUE_CANDIDATES`, on the BCC lattice) are tried before the segment
//! ends: the nearest coefficients are not always those that stay within the bound longest, and
//! a point of a coarser lattice is further from the fit on average. Each try re-checks the
//! segment's frames, once per break, so the fitter stays linear (with a larger constant).

use crate::params::{FIT_WINDOW, MAX_SEGMENT_LEN};
use crate::rotation::{self, Quat, Vec3};
use crate::segment::{
    FreeDynamics, Lattice, MAX_FREE_LEN, PositionCoding, PositionCurve, QuadraticQ, QuadraticTerm,
    RotationCurve, bucket, step_angular_acceleration, step_linear, step_quadratic,
};

/// The position models a segment may use (chosen per segment; §4.3: "model only what the scene
/// requires").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum PositionKind {
    /// Free flight: linear term fitted, quadratic term `h²g/2`.
    Gravity,
    /// Full per-axis quadratic (contacts, rolling, damping).
    Quadratic,
    /// Linear (sliding or rolling without acceleration).
    Linear,
}

/// The rotation models a segment may use.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum RotationKind {
    /// Constant angular velocity in the log map (§4.3).
    Linear,
    /// Constant angular acceleration in the log map.
    Quadratic,
}

/// A fitted, quantised, verified position segment.
#[derive(Debug, Clone, Copy)]
pub(crate) struct PositionFit {
    pub len: u32,
    pub coeffs: QuadraticQ,
    pub curve: PositionCurve,
}

/// A fitted, quantised, verified rotation segment.
#[derive(Debug, Clone, Copy)]
pub(crate) struct RotationFit {
    pub len: u32,
    pub wq: [i64; 3],
    /// Quantised angular acceleration (quadratic segments).
    pub aq: Option<[i64; 3]>,
    pub curve: RotationCurve,
}

fn dist(a: Vec3, b: Vec3) -> f64 {
    rotation::norm3([a[0] - b[0], a[1] - b[1], a[2] - b[2]])
}

/// How a segment treats the error its start point inherits from the previous segment's end.
///
/// C⁰ continuity (§4.3) fixes each segment's start to the previous *decoded* end, which can be
/// off by up to the bound. Fitting through that point (Figure 4.6 as written) bends the first
/// frames towards the data and makes the curve diverge soon after the fit window; fitting the
/// data's own trend and correcting the inherited offset over a horizon of `H` frames keeps the
/// error flat instead. The encoder tries both and keeps the longer segment (greedy, like the
/// authors').
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum StartCorrection {
    /// Least squares with the start point fixed (Figure 4.6).
    Anchored,
    /// Trend fitted with a free start; the inherited offset δ is removed at a rate δ/H
    /// (`f64::INFINITY`: kept).
    Horizon(f64),
}

/// Both strategies (`Horizon(∞)`, keeping the offset for good, was tried too: with steps and
/// per-frame costs it never produced the chosen segment on the shipped scenes).
const CORRECTIONS: [StartCorrection; 2] = [
    StartCorrection::Anchored,
    StartCorrection::Horizon(4.0 * FIT_WINDOW as f64),
];

impl StartCorrection {
    /// Whether a fit with this correction is worth trying after the anchored fit of the same
    /// kind covered `anchored_len` frames (0: none). The horizon variant works off the start's
    /// inherited error over `H` frames, which pays where the anchored fit would diverge after
    /// the fit window; where the anchored fit already ends inside the window (contact, where
    /// the motion changes every few frames) the horizon one ends there too. Measured on the
    /// shipped scenes at Standard: 10–19 % of the encoder's instructions saved, streams 0–0.3 %
    /// larger; requiring 15 frames saved 5–6 % more but made chute 4 % larger.
    pub(crate) fn worth_fitting(self, anchored_len: u32) -> bool {
        match self {
            StartCorrection::Anchored => true,
            StartCorrection::Horizon(_) => anchored_len as usize >= FIT_WINDOW,
        }
    }
}

impl PositionKind {
    /// The start corrections the encoder tries for this kind. A full quadratic bends to absorb
    /// the start offset by itself: the horizon variant changed the size by < 0.3 % on the
    /// shipped scenes, so it is not fitted (one fit in six saved).
    pub(crate) fn corrections(self) -> &'static [StartCorrection] {
        match self {
            PositionKind::Quadratic => &CORRECTIONS[..1],
            PositionKind::Gravity | PositionKind::Linear => &CORRECTIONS,
        }
    }
}

impl RotationKind {
    /// As for positions; for rotations it is the linear kind that gains least from the horizon
    /// variant (< 0.5 %, one fit in four saved).
    pub(crate) fn corrections(self) -> &'static [StartCorrection] {
        match self {
            RotationKind::Linear => &CORRECTIONS[..1],
            RotationKind::Quadratic => &CORRECTIONS,
        }
    }
}

/// Most rows a least-squares fit takes: the fit window, start point included.
const LS_ROWS: usize = FIT_WINDOW;

/// The Householder QR of a basis `u^{p_j}` over sample times `u`, kept so that fits over the same
/// times and powers (every refit inside the fit window uses one of a few dozen) only transform
/// their right-hand sides.
///
/// Householder QR applies each reflection `H_j = I − 2vvᵀ/vᵀv` to every remaining column, and a
/// column's update reads only that column and `v`. So factoring the basis columns first and
/// applying the stored reflections to the right-hand sides later performs, on the right-hand
/// sides, exactly the floating-point operations of the interleaved algorithm: the results are
/// bit for bit the same.
#[derive(Debug, Clone, Copy)]
struct BasisQr {
    rows: usize,
    cols: usize,
    /// Reflection `j` (`None`: skipped, the column was already zero); `v[j][..rows − j]`.
    v: [Option<([f64; LS_ROWS], f64)>; 3],
    /// Upper triangle `R` (row `j`, column `l ≥ j`).
    r: [[f64; 3]; 3],
}

impl BasisQr {
    /// Factors the basis over `us` (at most [`LS_ROWS`] times; more are ignored).
    fn new(us: &[f64], powers: &[i32]) -> Self {
        let us = &us[..us.len().min(LS_ROWS)];
        let rows = us.len();
        let cols = powers.len().min(rows).min(3);
        let mut m = [[0.0; 3]; LS_ROWS];
        for (r, &u) in m.iter_mut().zip(us) {
            for (j, &p) in powers.iter().take(cols).enumerate() {
                r[j] = u.powi(p);
            }
        }
        let m = &mut m[..rows];
        let mut out = BasisQr {
            rows,
            cols,
            v: [None; 3],
            r: [[0.0; 3]; 3],
        };
        for j in 0..cols {
            let norm = m[j..].iter().map(|r| r[j] * r[j]).sum::<f64>().sqrt();
            if norm == 0.0 {
                continue;
            }
            let alpha = if m[j][j] > 0.0 { -norm } else { norm };
            let mut v = [0.0; LS_ROWS];
            for (vi, r) in v.iter_mut().zip(&m[j..]) {
                *vi = r[j];
            }
            v[0] -= alpha;
            let v_used = &v[..rows - j];
            let vv: f64 = v_used.iter().map(|x| x * x).sum();
            if vv == 0.0 {
                continue;
            }
            for col in j..cols {
                let d: f64 = m[j..].iter().zip(v_used).map(|(r, vi)| r[col] * vi).sum();
                let f = 2.0 * d / vv;
                for (r, vi) in m[j..].iter_mut().zip(v_used) {
                    r[col] -= f * vi;
                }
            }
            out.v[j] = Some((v, vv));
        }
        for (j, row) in out.r.iter_mut().enumerate().take(cols) {
            row[..cols].copy_from_slice(&m[j][..cols]);
        }
        out
    }

    /// Least-squares coefficients for three right-hand sides (`ys[i]` at time `us[i]`).
    fn solve(&self, ys: &[Vec3]) -> [Vec3; 3] {
        let rows = self.rows.min(ys.len());
        let mut y = [[0.0; 3]; LS_ROWS];
        y[..rows].copy_from_slice(&ys[..rows]);
        let y = &mut y[..rows];
        for (j, reflection) in self.v.iter().enumerate().take(self.cols) {
            let Some((v, vv)) = reflection else {
                continue;
            };
            let v_used = &v[..rows.saturating_sub(j)];
            for col in 0..3 {
                let d: f64 = y[j..].iter().zip(v_used).map(|(r, vi)| r[col] * vi).sum();
                let f = 2.0 * d / vv;
                for (r, vi) in y[j..].iter_mut().zip(v_used) {
                    r[col] -= f * vi;
                }
            }
        }
        // Back substitution R x = Qᵀy, per right-hand side.
        let cols = self.cols.min(rows);
        let mut out = [[0.0; 3]; 3];
        for axis in 0..3 {
            for j in (0..cols).rev() {
                let mut acc = y[j][axis];
                for (r_jl, out_l) in self.r[j][j + 1..cols].iter().zip(&out[j + 1..cols]) {
                    acc -= r_jl * out_l[axis];
                }
                let d = self.r[j][j];
                out[j][axis] = if d.abs() > 1e-300 && acc.is_finite() {
                    acc / d
                } else {
                    0.0
                };
            }
        }
        out
    }
}

/// Least squares `y_u ≈ Σ_j coef_j·u^{p_j}` for three right-hand sides at once, by Householder QR
/// (the authors fit with QR, citing Golub & Van Loan). `powers` lists the exponents (0, 1, 2) of
/// the basis; returns one coefficient vector per power, zero where the system is rank-deficient.
/// At most [`LS_ROWS`] rows are used.
#[cfg(test)]
fn least_squares(rows: &[(f64, Vec3)], powers: &[i32]) -> [Vec3; 3] {
    let us: Vec<f64> = rows.iter().map(|r| r.0).collect();
    let ys: Vec<Vec3> = rows.iter().map(|r| r.1).collect();
    BasisQr::new(&us, powers).solve(&ys)
}

/// A least-squares fit over fixed sample times as a matrix: `coef_j = Σ_r P[j][r]·y_r`, with `P`
/// the pseudo-inverse of the basis, computed once by QR. Every fit inside the fit window uses one
/// of a few dozen such bases, so a refit is three short dot products per axis.
#[derive(Debug, Clone, Copy)]
struct Projector {
    rows: usize,
    p: [[f64; LS_ROWS]; 3],
}

impl Projector {
    fn new(us: &[f64], powers: &[i32]) -> Self {
        let qr = BasisQr::new(us, powers);
        let rows = qr.rows;
        let mut p = [[0.0; LS_ROWS]; 3];
        for r in 0..rows {
            let mut e = [[0.0; 3]; LS_ROWS];
            e[r] = [1.0, 0.0, 0.0];
            let col = qr.solve(&e[..rows]);
            for (j, row) in p.iter_mut().enumerate() {
                row[r] = col[j][0];
            }
        }
        Self { rows, p }
    }

    fn solve(&self, ys: &[Vec3]) -> [Vec3; 3] {
        let rows = self.rows.min(ys.len());
        std::array::from_fn(|j| {
            let mut acc = [0.0; 3];
            for (pj, y) in self.p[j][..rows].iter().zip(ys) {
                for i in 0..3 {
                    acc[i] += pj * y[i];
                }
            }
            acc
        })
    }
}

/// Basis variants: anchored (times `1..=n`, powers `[1]` / `[1, 2]`) and free start (times
/// `0..n`, powers `[0, 1]` / `[0, 1, 2]`).
const ANCHORED_LINEAR: usize = 0;
const ANCHORED_QUADRATIC: usize = 1;
const FREE_LINEAR: usize = 2;
const FREE_QUADRATIC: usize = 3;

/// The projectors of every basis variant for every row count `n ≤ LS_ROWS`, built once.
struct WindowBases {
    proj: [[Projector; LS_ROWS + 1]; 4],
}

fn window_bases() -> &'static WindowBases {
    static BASES: std::sync::OnceLock<WindowBases> = std::sync::OnceLock::new();
    BASES.get_or_init(|| {
        let powers: [&[i32]; 4] = [&[1], &[1, 2], &[0, 1], &[0, 1, 2]];
        WindowBases {
            proj: std::array::from_fn(|variant| {
                std::array::from_fn(|n| {
                    let first = if variant < 2 { 1 } else { 0 };
                    let us: Vec<f64> = (first..first + n).map(|u| u as f64).collect();
                    Projector::new(&us, powers[variant])
                })
            }),
        }
    })
}

/// `(b, a)` of a position segment of kind `kind` starting at `c` (decoded) over data frames
/// `s..=s+len`; `a` is only meaningful for [`PositionKind::Quadratic`].
fn position_coefficients(
    x: &[Vec3],
    s: usize,
    len: usize,
    c: Vec3,
    kind: PositionKind,
    g: Vec3,
    correction: StartCorrection,
) -> (Vec3, Vec3) {
    // Remove the known gravity term so that only unknown coefficients are fitted.
    let data = |u: usize| -> Vec3 {
        if kind == PositionKind::Gravity {
            let uu = (u * u) as f64;
            std::array::from_fn(|i| x[s + u][i] - g[i] * uu)
        } else {
            x[s + u]
        }
    };
    let quadratic = kind == PositionKind::Quadratic && len >= 2;
    let bases = window_bases();
    let mut ys = [[0.0; 3]; LS_ROWS];
    match correction {
        StartCorrection::Anchored => {
            let n = len.min(LS_ROWS);
            for (u, y) in (1..=n).zip(&mut ys) {
                let d = data(u);
                *y = std::array::from_fn(|i| d[i] - c[i]);
            }
            let variant = if quadratic {
                ANCHORED_QUADRATIC
            } else {
                ANCHORED_LINEAR
            };
            let [b, a, _] = bases.proj[variant][n].solve(&ys[..n]);
            (b, a)
        }
        StartCorrection::Horizon(h) => {
            let n = (len + 1).min(LS_ROWS);
            for (u, y) in (0..n).zip(&mut ys) {
                *y = data(u);
            }
            let variant = if quadratic {
                FREE_QUADRATIC
            } else {
                FREE_LINEAR
            };
            let [c_fit, b, a] = bases.proj[variant][n].solve(&ys[..n]);
            let b = std::array::from_fn(|i| b[i] - (c[i] - c_fit[i]) / h);
            (b, a)
        }
    }
}

/// Figure 4.6 for positions: the longest segment of kind `kind` from frame `s` whose quantised
/// curve keeps every frame within `e_max`, or `None` if it covers fewer than `min_len` frames
/// (≥ 1; see [`WindowProbe`]).
#[allow(clippy::too_many_arguments)]
pub(crate) fn fit_position(
    x: &[Vec3],
    s: usize,
    c: Vec3,
    kind: PositionKind,
    correction: StartCorrection,
    coding: &PositionCoding,
    e_max: f64,
    min_len: usize,
) -> Option<PositionFit> {
    let g = match kind {
        PositionKind::Gravity => coding.gravity_term?,
        _ => [0.0; 3],
    };
    let max_len = (x.len() - 1 - s).min(MAX_SEGMENT_LEN);
    let within = |curve: &PositionCurve, u: usize| dist(curve.eval(c, u as f64), x[s + u]) <= e_max;
    let mut best: Option<PositionFit> = None;
    let (mut b, mut a) = ([0.0; 3], [0.0; 3]);
    let mut current: Option<(u32, QuadraticQ, PositionCurve)> = None;
    // Where the current coefficients' curve breaks the bound, lattice points next to them may
    // not: the coefficients nearest the least-squares fit are not always those that stay within
    // the bound longest. Any lattice point is a valid choice: every candidate's curve is checked
    // on all its frames.
    // `(curve, u)`: the tried curve and a frame it misses.
    let rescue = |len: usize,
                  k: u32,
                  b: Vec3,
                  a: Vec3,
                  tried: QuadraticQ,
                  (curve, u): (PositionCurve, usize)| {
        let (sb, sa) = (step_linear(coding.step, k), step_quadratic(coding.step, k));
        let second = match tried.term {
            QuadraticTerm::Fitted(aq) => Some((aq, a, sa)),
            _ => None,
        };
        let miss = Miss::position(&curve, c, x[s + u], u, e_max);
        rescue(coding.lattice, (tried.bq, b, sb), second, miss, |bq, aq| {
            let coeffs = QuadraticQ {
                bq,
                term: aq.map_or(tried.term, QuadraticTerm::Fitted),
            };
            let curve = coeffs.curve(coding, k);
            (1..=len)
                .rev()
                .all(|u| within(&curve, u))
                .then_some((k, coeffs, curve))
        })
    };
    let mut probe = WindowProbe::new(min_len, max_len)?;
    for len in probe.lengths(max_len) {
        let refit = len < FIT_WINDOW;
        if refit {
            (b, a) = position_coefficients(x, s, len, c, kind, g, correction);
        }
        let k = bucket(len as u32);
        let requantise = refit || current.is_none_or(|(ck, _, _)| ck != k);
        if requantise {
            let Some(bq) = coding.lattice.quantise(b, step_linear(coding.step, k)) else {
                break;
            };
            let term = match kind {
                PositionKind::Gravity => QuadraticTerm::Gravity,
                PositionKind::Linear => QuadraticTerm::Zero,
                PositionKind::Quadratic => {
                    match coding.lattice.quantise(a, step_quadratic(coding.step, k)) {
                        Some(aq) => QuadraticTerm::Fitted(aq),
                        None => break,
                    }
                }
            };
            let coeffs = QuadraticQ { bq, term };
            // A refit that quantises to the curve already verified on 1..len−1 (the common case
            // once the window has a few points) needs only the new point checked.
            if let Some((_, _, curve)) = current.filter(|&(ck, cq, _)| (ck, cq) == (k, coeffs)) {
                if !within(&curve, len) {
                    match rescue(len, k, b, a, coeffs, (curve, len)) {
                        Some(r) => current = Some(r),
                        None => break,
                    }
                }
            } else {
                let curve = coeffs.curve(coding, k);
                // The newest point first: where a refitted curve most often fails.
                match (1..=len).rev().find(|&u| !within(&curve, u)) {
                    None => current = Some((k, coeffs, curve)),
                    Some(u) => match rescue(len, k, b, a, coeffs, (curve, u)) {
                        Some(r) => current = Some(r),
                        None => break,
                    },
                }
            }
        } else if let Some((ck, coeffs, curve)) = current
            && !within(&curve, len)
        {
            match rescue(len, ck, b, a, coeffs, (curve, len)) {
                Some(r) => current = Some(r),
                None => break,
            }
        }
        let (_, coeffs, curve) = current?;
        if probe.passed() {
            // Start again from one frame (the probe's curve is not the one-frame fit's).
            current = None;
            continue;
        }
        best = Some(PositionFit {
            len: len as u32,
            coeffs,
            curve,
        });
    }
    probe.finish(best, |f| f.len)
}

/// Deciding first whether a fit reaches the shortest length its caller can use.
///
/// Inside the fit window (lengths below [`FIT_WINDOW`]) the curve a fit tries at length `L` is
/// a function of `L` alone — the least-squares fit of frames `1..=L`, its nearest lattice point,
/// else the first of the lattice search's alternatives that keeps frames `1..=L` within the
/// bound — not of the lengths tried before it. The fit ends at the first length where none does.
/// So a fit the caller would discard as shorter than `min_len` (a quadratic below
/// `MIN_QUADRATIC_LEN`) is recognised by trying length `min_len` first: measured on pachinko
/// at Standard, 82 % of the rotation quadratics and half of the position ones end shorter, and
/// each of them used to be grown frame by frame, with a lattice search at its end. When the probe
/// passes the fit runs as before from one frame (the verdicts it cached stay true), so every
/// fit, and every byte, is what it was.
struct WindowProbe {
    min_len: usize,
    /// The probe's length, while it is being tried.
    pending: Option<usize>,
}

impl WindowProbe {
    /// `None` if no fit of at most `max_len` frames can reach `min_len`.
    fn new(min_len: usize, max_len: usize) -> Option<Self> {
        (min_len <= max_len).then_some(Self {
            min_len,
            pending: (min_len > 1 && min_len < FIT_WINDOW).then_some(min_len),
        })
    }

    /// The lengths a fit tries: the probe's, then `1..=max_len`.
    fn lengths(&self, max_len: usize) -> impl Iterator<Item = usize> + use<> {
        self.pending.into_iter().chain(1..=max_len)
    }

    /// Called where a length has passed: `true` (once) if it was the probe's.
    fn passed(&mut self) -> bool {
        self.pending.take().is_some()
    }

    /// The fit's result: `None` if the probe failed (the loop ended on it) or the fit is
    /// shorter than `min_len`.
    fn finish<F>(self, best: Option<F>, len: impl Fn(&F) -> u32) -> Option<F> {
        if self.pending.is_some() {
            return None;
        }
        best.filter(|f| len(f) as usize >= self.min_len)
    }
}

/// How many lattice points near a fit's nearest one are tried where its curve breaks the bound.
const RESCUE_CANDIDATES: usize = 4;

/// The lattice search of a fit whose nearest coefficients break the bound: `attempt(first,
/// second)` is asked, in this order, about the [`RESCUE_CANDIDATES`] points nearest the first
/// coefficient's unquantised value `(nearest point, value, step)` with the second kept, the
/// second's with the first kept, and both first alternatives together; the first answer is
/// returned. The second's alternatives are ranked only if the first's all fail.
///
/// `miss` says by how much the tried curve misses the bound at one of its frames: an
/// alternative that moves the curve there by less cannot meet it and is not attempted, and
/// when even the farthest neighbours move it too little the alternatives are not ranked at all
/// (see [`Miss`]). The answer is the one the unpruned search gives.
fn rescue<T>(
    lattice: Lattice,
    first: ([i64; 3], Vec3, f64),
    second: Option<([i64; 3], Vec3, f64)>,
    miss: Miss,
    mut attempt: impl FnMut([i64; 3], Option<[i64; 3]>) -> Option<T>,
) -> Option<T> {
    // A change of `d` in the doubled lattice coordinates of a coefficient moves its value by
    // `d · h` (h = half the cell spacing), so the curve at `u` by `|d₁·h₁·u + d₂·h₂·u²|`.
    let h1 = lattice.point([1, 0, 0], first.2)[0];
    let h2 = second.map_or(0.0, |(_, _, step)| lattice.point([1, 0, 0], step)[0]);
    let (u1, u2) = (miss.u, miss.u * miss.u);
    let moves_enough = |d1: [i64; 3], d2: [i64; 3]| {
        let shift: Vec3 = std::array::from_fn(|i| d1[i] as f64 * h1 * u1 + d2[i] as f64 * h2 * u2);
        rotation::norm3(shift) >= miss.excess
    };
    // The farthest of the 14 neighbours is an axial one, d = ±2 along one axis.
    if !moves_enough([2, 0, 0], if second.is_some() { [2, 0, 0] } else { [0; 3] }) {
        return None;
    }
    let minus = |a: [i64; 3], b: [i64; 3]| -> [i64; 3] { std::array::from_fn(|i| a[i] - b[i]) };
    let first_alts = lattice.alternatives(first.0, first.1, first.2, RESCUE_CANDIDATES);
    let kept = second.map(|(q, _, _)| q);
    if let Some(t) = first_alts
        .as_slice()
        .iter()
        .filter(|&&q| moves_enough(minus(q, first.0), [0; 3]))
        .find_map(|&q| attempt(q, kept))
    {
        return Some(t);
    }
    let (q, x, step) = second?;
    let second_alts = lattice.alternatives(q, x, step, RESCUE_CANDIDATES);
    if let Some(t) = second_alts
        .as_slice()
        .iter()
        .filter(|&&a| moves_enough([0; 3], minus(a, q)))
        .find_map(|&a| attempt(first.0, Some(a)))
    {
        return Some(t);
    }
    let (&f, &a) = first_alts
        .as_slice()
        .first()
        .zip(second_alts.as_slice().first())?;
    moves_enough(minus(f, first.0), minus(a, q))
        .then(|| attempt(f, Some(a)))
        .flatten()
}

/// By how much a quantised curve misses the bound at one of its frames (`excess`, at local time
/// `u`), less a margin for rounding: a curve within the bound there differs from it by more.
///
/// Positions: by the triangle inequality, a curve whose point at `u` is `δ` away is at least
/// `err − |δ|` from the data. Rotations: the residual angle is a distance on the rotation group
/// and `exp` does not lengthen paths (its differential has singular values 1 and
/// `sin(θ/2)/(θ/2) ≤ 1`), so curves `exp(r(u)) ⊗ q₀` and `exp(r(u) + δ) ⊗ q₀` are at most
/// `|δ|` apart and the same holds. The margin (10⁻¹² of the magnitudes involved, plus 10⁻⁹
/// of the bound) dwarfs the rounding of the evaluations, so a pruned alternative is one the
/// full check would refuse: the search returns what it returned without pruning (measured on
/// tumble at Standard: 3 % of the encoder's instructions).
#[derive(Debug, Clone, Copy)]
struct Miss {
    u: f64,
    /// ≥ 0; 0 prunes nothing.
    excess: f64,
}

impl Miss {
    fn new(u: usize, err: f64, bound: f64, scale: f64) -> Self {
        let excess = err - bound - (1e-9 * bound + 1e-12 * (1.0 + scale));
        Self {
            u: u as f64,
            excess: if excess.is_finite() && excess > 0.0 {
                excess
            } else {
                0.0
            },
        }
    }

    /// The magnitude of the terms of `first·u + second·u²`, for the margin.
    fn terms(first: Vec3, second: Vec3, u: f64) -> f64 {
        rotation::norm3(first) * u + rotation::norm3(second) * (u * u)
    }

    fn position(curve: &PositionCurve, c: Vec3, x: Vec3, u: usize, e_max: f64) -> Self {
        let at = curve.eval(c, u as f64);
        let terms = match *curve {
            PositionCurve::Quadratic { b, a } => Self::terms(b, a, u as f64),
            PositionCurve::Key { .. } | PositionCurve::Rest => 0.0,
        };
        let scale = rotation::norm3(c) + rotation::norm3(x) + terms;
        Self::new(u, dist(at, x), e_max, scale)
    }

    /// From the lower bound of [`AngleTest::log_verdict`] on the curve's angle at `u` (`y` as
    /// there), which needs no `sin`, `cos` or `atan2`.
    fn rotation(test: &AngleTest, curve: &RotationCurve, u: usize, y: Vec3) -> Self {
        let (below, size) = test.angle_below(curve, u as f64, y);
        Self::new(u, below, test.theta_lim, size)
    }
}

/// How many frames from `s` on stay within `e_max` of the start point `c` (a [`PositionCurve::Rest`]
/// segment of that length meets the bound; 0: not even the next frame).
pub(crate) fn rest_length(x: &[Vec3], s: usize, c: Vec3, e_max: f64) -> usize {
    let max_len = (x.len() - 1 - s).min(MAX_SEGMENT_LEN);
    (1..=max_len)
        .take_while(|&u| dist(c, x[s + u]) <= e_max)
        .count()
}

/// The rotation bound test `angle(exp(u·ω) ⊗ q₀, q) ≤ θ_lim`, decided without `atan2` and
/// without normalising where that is safe — with exactly the verdict of the full computation.
///
/// For the residual `d = eval ⊗ q⁻¹` the angle is `2·atan2(|d_xyz|, |d_w|)`: monotone in
/// `|d_xyz| / |d_w|` and independent of the scale of `d`, so in real arithmetic `angle ≤ θ_lim`
/// exactly when `|d_xyz|² ≤ T²·d_w²` with `T = tan(θ_lim/2)`. The fast test compares against
/// `T²·(1 ∓ band)` and leaves everything inside the band to the full computation (the one the
/// decoder and the self-check perform).
///
/// Why the verdicts agree: both computations start from the same unit quaternions (components
/// ≤ 1); the fast test's `exp` ([`rotation::exp_approx`], polynomial `sin`/`cos`) is within
/// 10⁻¹⁵ of the full one's. Each Hamilton product adds at most ≈5 ulp(1) per component
/// (Cauchy–Schwarz bounds the sum of the four products' magnitudes by 1), normalising ≈2 ulp.
/// The fast test multiplies in the other order, `exp(r) ⊗ (q₀ ⊗ q⁻¹)` (the bracket is shared by
/// every curve a segment's fits try; the product is associative in real arithmetic), so each
/// residual is within 10⁻¹⁵ + 12 ulp ≈ 4·10⁻¹⁵ of the exact one and the two differ by at most
/// δa ≈ 10⁻¹⁴ per component, of `|d_xyz|` by less than 10⁻¹³ = [`ANGLE_TEST_ABS`].
/// Near the boundary `|d_w| ≥ cos(1) > 0.54` (θ_lim ≤ 2), so a relative band
/// `b = 10⁻⁹ + 16·δa/T` on the squared ratio is more than twice what rounding can move it, and
/// the angle gap it leaves (≥ 0.2·b relative) dwarfs the ulp errors of `tan` and `atan2`.
/// Whenever the fast test decides, the full computation decides the same: same segments, same
/// bytes, same guarantee. Bounds above 2 rad always take the full computation.
#[derive(Debug, Clone, Copy)]
pub(crate) struct AngleTest {
    theta_lim: f64,
    /// `(inside, outside)` thresholds on `|d_xyz|² / d_w²`; `None` disables the fast test.
    ratio2: Option<(f64, f64)>,
}

/// What [`AngleTest::log_verdict`] needs of a curve's rotation vector `r` and the data's `y`.
struct LogBounds {
    /// `|r − y|²`.
    d2: f64,
    /// A lower bound on `s(Φ)` (0: none, `Φ` may reach π).
    shrink: f64,
    /// `1 + |r|₁ + |y|₁`, and 10⁻¹² of it for rounding.
    size: f64,
    margin: f64,
}

impl LogBounds {
    fn new(r: Vec3, y: Vec3) -> Self {
        let d = [r[0] - y[0], r[1] - y[1], r[2] - y[2]];
        let l1 = |v: Vec3| v[0].abs() + v[1].abs() + v[2].abs();
        let (r1, y1) = (l1(r), l1(y));
        let size = 1.0 + r1 + y1;
        // Φ ≤ max(|r|, |y|) + |r − y|/2, each norm at most the sum of absolute values.
        let phi = r1.max(y1) + 0.5 * l1(d);
        Self {
            d2: rotation::dot3(d, d),
            shrink: if phi < 3.0 {
                1.0 - phi * phi / 24.0
            } else {
                0.0
            },
            size,
            margin: 1e-12 * size,
        }
    }
}

/// Absolute bound used for the difference of `|d_xyz|` between the two computations.
const ANGLE_TEST_ABS: f64 = 1e-13;

impl AngleTest {
    /// The test for bound `theta_lim`. Every rotation fit and every rest test of a segment
    /// start asks for one, always with the world's bound, and building it takes a `tan`
    /// (measured on `tests/measure.rs`'s tumbling tracks: 2 % of the encoder's instructions):
    /// the last one built on this thread is kept and handed out again for the same bound (the
    /// value `build` computes for it).
    pub(crate) fn new(theta_lim: f64) -> Self {
        thread_local! {
            static LAST: std::cell::Cell<Option<AngleTest>> = const { std::cell::Cell::new(None) };
        }
        LAST.with(|last| match last.get() {
            Some(t) if t.theta_lim.to_bits() == theta_lim.to_bits() => t,
            _ => {
                let t = Self::build(theta_lim);
                last.set(Some(t));
                t
            }
        })
    }

    fn build(theta_lim: f64) -> Self {
        let ratio2 = (theta_lim > 0.0 && theta_lim <= 2.0)
            .then(|| {
                let t = (0.5 * theta_lim).tan();
                let band = 1e-9 + 16.0 * ANGLE_TEST_ABS / t;
                (band < 0.25).then_some((t * t * (1.0 - band), t * t * (1.0 + band)))
            })
            .flatten();
        Self { theta_lim, ratio2 }
    }

    /// `angle_between(a, q) ≤ θ_lim` for an orientation `a` already computed (a simulated
    /// free-flight frame), exactly as [`rotation::angle_between`] decides: the residual is the
    /// same product, so only `atan2` is saved where the ratio is clear of the band.
    pub(crate) fn within_rotation(&self, a: Quat, q: Quat) -> bool {
        self.ratio_verdict(rotation::mul(a, rotation::conj(q)))
            .unwrap_or_else(|| rotation::angle_between(a, q) <= self.theta_lim)
    }

    /// The fast test's verdict on a residual `d` (any scale), or `None` inside the band or when
    /// the fast test is off.
    pub(crate) fn ratio_verdict(&self, d: Quat) -> Option<bool> {
        let (inside, outside) = self.ratio2?;
        let s2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
        let c2 = d[3] * d[3];
        if s2 < inside * c2 {
            Some(true)
        } else if s2 > outside * c2 {
            Some(false)
        } else {
            None
        }
    }

    /// `angle_between(curve.eval(q0, u), q) ≤ θ_lim`, exactly as the full computation decides.
    pub(crate) fn within(&self, curve: &RotationCurve, q0: Quat, u: f64, q: Quat) -> bool {
        let relative = rotation::mul(q0, rotation::conj(q));
        self.within_relative(curve, q0, u, q, relative)
    }

    /// [`AngleTest::within`] of a log-map curve decided from `y`, a logarithm of `q ⊗ q₀⁻¹`
    /// with `exp(y) = ±q ⊗ q₀⁻¹`, where that is safe; `None` leaves the frame to
    /// [`AngleTest::within_relative`]. Decides only where the full computation decides the same.
    ///
    /// The angle `d` between `exp(r) ⊗ q₀` and `q` is the distance of `exp(r)` and `exp(y)` on
    /// the rotation group. Above: `exp` does not lengthen paths (its differential has singular
    /// values 1 and `s(|v|) = sin(|v|/2)/(|v|/2) ≤ 1`), so `d ≤ |r − y|`. Below: where `|r|` and
    /// `|y|` are less than π, `log` maps the shortest path between the two rotations — whose
    /// points turn by at most `Φ = max(|r|, |y|) + d/2 < π` — onto a path from `y` to `r`,
    /// lengthening it by at most `1/s(Φ)`, so `d ≥ s(Φ)·|r − y|`, and `s(Φ) ≥ 1 − Φ²/24`.
    /// Norms are bounded by sums of absolute values (no square roots). The margins (10⁻⁹ of
    /// θ_lim and 10⁻¹² of the magnitudes involved) are far beyond the rounding of either
    /// computation. A subtraction and a dot product instead of a polynomial `exp` and a Hamilton
    /// product: measured on tumble at Standard, 4 % of the encoder's instructions (most of the
    /// lattice search's tries miss by more than the band).
    fn log_verdict(&self, curve: &RotationCurve, u: f64, y: Vec3) -> Option<bool> {
        let b = LogBounds::new(curve.log_at(u)?, y);
        let inside = self.theta_lim * (1.0 - 1e-9) - b.margin;
        if inside > 0.0 && b.d2 <= inside * inside {
            return Some(true);
        }
        let outside = self.theta_lim * (1.0 + 1e-9) + b.margin;
        (b.shrink > 0.0 && b.d2 * (b.shrink * b.shrink) > outside * outside).then_some(false)
    }

    /// A lower bound on the angle of a log-map curve at `u` (0 where none is known) and the
    /// magnitude of the numbers involved, by the argument of [`AngleTest::log_verdict`].
    fn angle_below(&self, curve: &RotationCurve, u: f64, y: Vec3) -> (f64, f64) {
        let Some(r) = curve.log_at(u) else {
            return (0.0, f64::INFINITY);
        };
        let b = LogBounds::new(r, y);
        let below = if b.shrink > 0.0 {
            b.d2.sqrt() * b.shrink - b.margin
        } else {
            0.0
        };
        (below, b.size)
    }

    /// [`AngleTest::within`] given `relative = q₀ ⊗ q⁻¹` (as computed by
    /// [`RotationScratch::extend_relative`]).
    fn within_relative(
        &self,
        curve: &RotationCurve,
        q0: Quat,
        u: f64,
        q: Quat,
        relative: Quat,
    ) -> bool {
        if self.ratio2.is_some() && u != 0.0 {
            let d = match curve {
                RotationCurve::Rest => Some(relative),
                _ => curve
                    .log_at(u)
                    .map(|r| rotation::mul(rotation::exp_approx(r), relative)),
            };
            if let Some(verdict) = d.and_then(|d| self.ratio_verdict(d)) {
                return verdict;
            }
        }
        rotation::angle_between(curve.eval(q0, u), q) <= self.theta_lim
    }
}

/// What the candidate rotation fits of one segment (same start frame, same decoded start
/// orientation) share, so that each is computed once: the unwrapped logarithms of the data
/// against each reference, the start offset, the bound test's `q₀ ⊗ q⁻¹` per frame, and the
/// verdicts of the bound test per quantised curve. Every cached value is the value the uncached computation would produce, so fits and
/// bytes are unchanged.
#[derive(Debug, Default)]
pub(crate) struct RotationScratch {
    /// `(s, q₀)` the cache belongs to.
    key: Option<(usize, Quat)>,
    /// Unwrapped `log(q_{s+u} ⊗ ref⁻¹)` for u = 1, 2, …: `[0]` with ref = q₀ (anchored),
    /// `[1]` with ref = q_s (horizon).
    logs: [Vec<Vec3>; 2],
    /// `log(q₀ ⊗ q_s⁻¹)`.
    offset: Option<Vec3>,
    /// Verdicts per quantised curve.
    verdicts: VerdictList,
    /// `q₀ ⊗ q_{s+u}⁻¹` for u = 1, 2, … (index u − 1): the fast bound test's right factor.
    relative: Vec<Quat>,
}

/// What is known of each quantised curve a segment's fits have tried.
#[derive(Debug, Default)]
struct VerdictList(Vec<Verdicts>);

/// A quantised rotation curve: bucket, angular velocity, angular acceleration.
type CurveKey = (u32, [i64; 3], Option<[i64; 3]>);

/// What is known of one quantised curve: every frame in `1..=good` is within the bound, frame
/// `bad` is not (`usize::MAX`: none known).
#[derive(Debug, Clone, Copy)]
struct Verdicts {
    key: CurveKey,
    good: usize,
    bad: usize,
}

impl RotationScratch {
    fn reset(&mut self, s: usize, q0: Quat) {
        if self.key != Some((s, q0)) {
            self.key = Some((s, q0));
            self.logs.iter_mut().for_each(Vec::clear);
            self.offset = None;
            self.verdicts.clear();
            self.relative.clear();
        }
    }

    /// Makes `relative` available for frames `1..=n` (after [`RotationScratch::reset`] with the
    /// same `s` and `q0`).
    fn extend_relative(&mut self, q: &[Quat], s: usize, q0: Quat, n: usize) {
        while self.relative.len() < n {
            let u = self.relative.len() + 1;
            self.relative
                .push(rotation::mul(q0, rotation::conj(q[s + u])));
        }
    }

    /// Makes the first `n` unwrapped logarithms against reference `which` available.
    fn log(&mut self, which: usize, q: &[Quat], s: usize, reference: Quat, n: usize) {
        let logs = &mut self.logs[which];
        let inv_ref = rotation::conj(reference);
        while logs.len() < n {
            let last = logs.last().copied().unwrap_or([0.0; 3]);
            let r = rotation::log(rotation::mul(q[s + logs.len() + 1], inv_ref));
            logs.push(rotation::unwrap_near(r, last));
        }
    }
}

impl VerdictList {
    fn clear(&mut self) {
        self.0.clear();
    }

    /// Records that frames `1..=len` of curve `key` are within the bound.
    fn record_good(&mut self, key: CurveKey, len: usize) {
        let v = self.verdicts(key);
        v.good = v.good.max(len);
    }

    fn verdicts(&mut self, key: CurveKey) -> &mut Verdicts {
        // Newest first: the curve asked about is most often the one just added.
        let list = &mut self.0;
        let i = match list.iter().rposition(|v| v.key == key) {
            Some(i) => i,
            None => {
                list.push(Verdicts {
                    key,
                    good: 0,
                    bad: usize::MAX,
                });
                list.len() - 1
            }
        };
        &mut list[i]
    }

    /// A frame of `1..=len` outside the bound for curve `key`, or `None` if all are within.
    /// `within(u)` decides one frame; it is asked only about frames not already known.
    fn frame_outside(
        &mut self,
        key: CurveKey,
        len: usize,
        mut within: impl FnMut(usize) -> bool,
    ) -> Option<usize> {
        let v = self.verdicts(key);
        if len <= v.good {
            return None;
        }
        if v.bad <= len {
            return Some(v.bad);
        }
        // The newest frame first: it is where a refitted curve most often fails (the verdict
        // does not depend on the order).
        for u in (v.good + 1..=len).rev() {
            if !within(u) {
                v.bad = u;
                return Some(u);
            }
        }
        v.good = len;
        None
    }
}

/// Figure 4.6 for rotations (§4.3: "essentially unchanged, except that we replace FIT-SEGMENT"):
/// ω (and, for [`RotationKind::Quadratic`], α) fitted by least squares to unwrapped logarithms
/// `log(q_u ⊗ q_ref⁻¹) ≈ u·ω + u²·α`, error = angle of the residual rotation. `q_ref` is the
/// decoded start (anchored) or the data's own start (horizon, then ω corrected by the start
/// offset / H). `scratch` carries what the candidate fits of one segment share (any scratch may
/// be passed; it resets itself for a new segment). `None` if the fit covers fewer than `min_len`
/// frames (≥ 1; see [`WindowProbe`]).
#[allow(clippy::too_many_arguments)]
pub(crate) fn fit_rotation(
    q: &[Quat],
    s: usize,
    q0: Quat,
    kind: RotationKind,
    correction: StartCorrection,
    step: f64,
    lattice: Lattice,
    theta_lim: f64,
    min_len: usize,
    scratch: &mut RotationScratch,
) -> Option<RotationFit> {
    scratch.reset(s, q0);
    let max_len = (q.len() - 1 - s).min(MAX_SEGMENT_LEN);
    let test = AngleTest::new(theta_lim);
    let (which, reference, correction_rate) = match correction {
        StartCorrection::Anchored => (0, q0, [0.0; 3]),
        StartCorrection::Horizon(h) => {
            let offset = *scratch
                .offset
                .get_or_insert_with(|| rotation::log(rotation::mul(q0, rotation::conj(q[s]))));
            (1, q[s], rotation::scale3(offset, 1.0 / h))
        }
    };
    let bases = window_bases();
    let (mut w, mut acc) = ([0.0; 3], [0.0; 3]);
    let mut best: Option<RotationFit> = None;
    let mut current: Option<(CurveKey, RotationCurve)> = None;
    let mut probe = WindowProbe::new(min_len, max_len)?;
    for len in probe.lengths(max_len) {
        let refit = len < FIT_WINDOW;
        if refit {
            let n = len.min(LS_ROWS);
            scratch.log(which, q, s, reference, n);
            let ys = &scratch.logs[which][..n];
            let quadratic = kind == RotationKind::Quadratic && len >= 2;
            let [w_fit, a_fit, _] = if quadratic {
                bases.proj[ANCHORED_QUADRATIC][n].solve(ys)
            } else {
                bases.proj[ANCHORED_LINEAR][n].solve(ys)
            };
            w = std::array::from_fn(|i| w_fit[i] - correction_rate[i]);
            acc = a_fit;
        }
        let k = bucket(len as u32);
        let requantise = refit || current.is_none_or(|((ck, _, _), _)| ck != k);
        if requantise {
            let sw = step_linear(step, k);
            let Some(wq) = lattice.quantise(w, sw) else {
                break;
            };
            let aq = match kind {
                RotationKind::Linear => None,
                RotationKind::Quadratic => {
                    match lattice.quantise(acc, step_angular_acceleration(step, k)) {
                        Some(aq) => Some(aq),
                        None => break,
                    }
                }
            };
            let key = (k, wq, aq);
            // An unchanged quantised curve keeps its verdicts (only the new point is checked).
            let curve = match current.filter(|&(ck, _)| ck == key) {
                Some((_, curve)) => curve,
                None => {
                    let w = lattice.point(wq, sw);
                    match aq {
                        None => RotationCurve::Linear { w },
                        Some(aq) => RotationCurve::Quadratic {
                            w,
                            a: lattice.point(aq, step_angular_acceleration(step, k)),
                        },
                    }
                }
            };
            current = Some((key, curve));
        }
        let Some((mut key, mut curve)) = current else {
            break;
        };
        scratch.extend_relative(q, s, q0, len);
        let (relative, logs) = (&scratch.relative, &scratch.logs[0]);
        // Inside the fit window the anchored fits have computed the logarithms the shortcut
        // needs; past it a logarithm (an `atan2`) costs about as much as the full test.
        let within = |curve: &RotationCurve, u: usize| {
            logs.get(u - 1)
                .and_then(|&y| test.log_verdict(curve, u as f64, y))
                .unwrap_or_else(|| {
                    test.within_relative(curve, q0, u as f64, q[s + u], relative[u - 1])
                })
        };
        let verdicts = &mut scratch.verdicts;
        if let Some(u) = verdicts.frame_outside(key, len, |u| within(&curve, u)) {
            // As for positions: lattice points next to the current ones may stay within longer.
            let (k, wq, aq) = key;
            let (sw, sa) = (step_linear(step, k), step_angular_acceleration(step, k));
            let rescued = rescue(
                lattice,
                (wq, w, sw),
                aq.map(|aq| (aq, acc, sa)),
                Miss::rotation(
                    &test,
                    &curve,
                    u,
                    logs.get(u - 1).copied().unwrap_or_else(|| {
                        rotation::log(rotation::mul(q[s + u], rotation::conj(q0)))
                    }),
                ),
                |wq, aq| {
                    let w = lattice.point(wq, sw);
                    let c = match aq {
                        None => RotationCurve::Linear { w },
                        Some(aq) => RotationCurve::Quadratic {
                            w,
                            a: lattice.point(aq, sa),
                        },
                    };
                    let alt = (k, wq, aq);
                    // Checked directly (most candidates fail on the newest frame, and caching each
                    // would lengthen the verdict list every lookup scans); a winner's verdict is
                    // recorded.
                    (1..=len).rev().all(|u| within(&c, u)).then(|| {
                        verdicts.record_good(alt, len);
                        (alt, c)
                    })
                },
            );
            match rescued {
                Some((k2, c2)) => (key, curve) = (k2, c2),
                None => break,
            }
            current = Some((key, curve));
        }
        if probe.passed() {
            current = None;
            continue;
        }
        best = Some(RotationFit {
            len: len as u32,
            wq: key.1,
            aq: key.2,
            curve,
        });
    }
    probe.finish(best, |f| f.len)
}

/// The quick test before a free-flight fit: frames simulated from the first frame's rotation,
/// and how far (× θ_lim) the last may be off for the fit to be tried. The guess ignores
/// precession and the start error, which the fit corrects. Measured on the shipped scenes: on
/// tumble it skips about half of the fits; 100 × θ_lim found no more free segments, 8 × lost
/// 1.5 % of tumble's size.
pub(crate) const MIN_FREE_PROBE: u32 = 8;
const FREE_PROBE_SLACK: f64 = 30.0;
/// Nor is the fit tried for a body that turns less than this many θ_lim over the probe.
const FREE_MIN_TURN: f64 = 4.0;

/// Gauss–Newton iterations of the free-flight fit, and its finite-difference step (rad/frame).
const FREE_FIT_ITERATIONS: usize = 2;
const FREE_FIT_EPS: f64 = 1e-7;

/// The longest torque-free flight ([`RotationCurve::Free`]) from frame `s` (decoded
/// start orientation `q0`) that stays within `θ_lim`, or `None`. `flight`: how many frames on
/// the positions fly freely (a hint for the fit's window).
///
/// The start angular velocity is fitted by Gauss–Newton to the first [`FIT_WINDOW`] frames (the
/// free-flight counterpart of Figure 4.6's least squares; the simulation is non-linear in it),
/// starting from the first frame's rotation, and again over the whole flight if it reaches past
/// them; each fit is quantised like a linear segment's (bucket of the length, `Δθ·2⁻ᵏ`) and
/// simulated frame by frame until a frame leaves the bound. Every verdict is on the simulated
/// frames the decoder reproduces bit for bit.
#[allow(clippy::too_many_arguments)]
pub(crate) fn fit_free(
    q: &[Quat],
    s: usize,
    q0: Quat,
    dynamics: &FreeDynamics,
    step: f64,
    lattice: Lattice,
    theta_lim: f64,
    flight: usize,
) -> Option<RotationFit> {
    let max_len = (q.len() - 1 - s).min(MAX_FREE_LEN as usize);
    if max_len == 0 {
        return None;
    }
    // The first frame's rotation is the first guess; each window's fit starts from the last.
    let mut w = rotation::log(rotation::mul(q[s + 1], rotation::conj(q0)));
    // In contact the model is off within a few frames: if the guess, run for the shortest flight
    // worth writing, ends far outside the bound, the fit is not tried (each of its windows costs
    // five simulations of the window).
    let probe = (MIN_FREE_PROBE as usize).min(max_len);
    let (mut qs, mut ws) = (q0, FreeDynamics::body(q0, w));
    for _ in 0..probe {
        dynamics.frame(&mut qs, &mut ws);
    }
    if rotation::angle_between(qs, q[s + probe]) > FREE_PROBE_SLACK * theta_lim {
        return None;
    }
    // A body that hardly turns is followed as far by a linear curve, which decodes faster.
    if rotation::angle_between(q0, q[s + probe]) < FREE_MIN_TURN * theta_lim {
        return None;
    }
    let mut best: Option<RotationFit> = None;
    let mut window = FIT_WINDOW.min(max_len);
    loop {
        w = free_least_squares(q, s, q0, dynamics, w, window)?;
        let fit = extend_free(q, s, q0, dynamics, w, step, lattice, theta_lim, max_len);
        let reached = fit.map_or(0, |f| f.len as usize);
        if fit.is_some_and(|f| best.is_none_or(|b| f.len > b.len)) {
            best = fit;
        }
        // A flight longer than the window: fit again over a longer one — at least twice the
        // window, at once the whole flight the positions show (the start velocity that fits the
        // first frames best is not the one that stays within the bound longest).
        // (A fit that already reaches the end of the flight cannot gain from a longer window.)
        if reached < window || window == max_len || (flight > 0 && reached >= flight) {
            break;
        }
        window = (2 * window).max(flight).min(max_len);
    }
    best
}

/// Gauss–Newton for the start angular velocity of a free flight from `q0` over frames
/// `s+1..=s+n`, from the guess `w`.
fn free_least_squares(
    q: &[Quat],
    s: usize,
    q0: Quat,
    dynamics: &FreeDynamics,
    mut w: Vec3,
    n: usize,
) -> Option<Vec3> {
    // Residual rotation vectors of the simulated frames against the data, and their derivatives
    // by the three components of w (finite differences).
    let residuals = |w: Vec3, out: &mut Vec<f64>| {
        out.clear();
        let (mut qs, mut ws) = (q0, FreeDynamics::body(q0, w));
        for u in 1..=n {
            dynamics.frame(&mut qs, &mut ws);
            let d = rotation::log(rotation::mul(qs, rotation::conj(q[s + u])));
            out.extend_from_slice(&d);
        }
    };
    // The residuals at `w` and at its three finite-difference neighbours, simulated side by side
    // (`FreeDynamics::frames`; the same numbers as four calls of `residuals`).
    let residuals4 = |w: Vec3, out: &mut [Vec<f64>; 4]| {
        let starts: [Vec3; 4] = std::array::from_fn(|j| {
            let mut wj = w;
            if j > 0 {
                wj[j - 1] += FREE_FIT_EPS;
            }
            FreeDynamics::body(q0, wj)
        });
        let (mut qs, mut ws) = ([q0; 4], starts);
        out.iter_mut().for_each(Vec::clear);
        for u in 1..=n {
            dynamics.frames(&mut qs, &mut ws);
            let inv = rotation::conj(q[s + u]);
            for (o, qk) in out.iter_mut().zip(&qs) {
                o.extend_from_slice(&rotation::log(rotation::mul(*qk, inv)));
            }
        }
    };
    let mut r = Vec::with_capacity(3 * n);
    let mut four: [Vec<f64>; 4] = std::array::from_fn(|_| Vec::with_capacity(3 * n));
    let mut jac = [vec![0.0; 3 * n], vec![0.0; 3 * n], vec![0.0; 3 * n]];
    // The Jacobian hardly changes over the few iterations: it is computed once (a chord
    // method: each further iteration costs one simulation, not four).
    let mut a = [[0.0; 3]; 3];
    for it in 0..FREE_FIT_ITERATIONS {
        if it == 0 {
            residuals4(w, &mut four);
            let [r0, rest @ ..] = &mut four;
            std::mem::swap(&mut r, r0);
            for (col, rd) in jac.iter_mut().zip(rest.iter()) {
                for (c, (a, b)) in col.iter_mut().zip(rd.iter().zip(&r)) {
                    *c = (a - b) / FREE_FIT_EPS;
                }
            }
            for i in 0..3 {
                for j in 0..3 {
                    a[i][j] = jac[i].iter().zip(&jac[j]).map(|(x, y)| x * y).sum();
                }
            }
        } else {
            residuals(w, &mut r);
        }
        // Normal equations JᵀJ δ = −Jᵀr, 3 × 3.
        let b: [f64; 3] =
            std::array::from_fn(|i| -jac[i].iter().zip(&r).map(|(x, y)| x * y).sum::<f64>());
        let Some(delta) = solve3(a, b) else {
            break;
        };
        w = std::array::from_fn(|i| w[i] + delta[i]);
        if !w.iter().all(|v| v.is_finite()) {
            return None;
        }
    }
    Some(w)
}

/// The longest free flight from `q0` with start velocity `w` quantised for its length (the bucket
/// of the length, `Δθ·2⁻ᵏ`, as linear segments) that keeps every frame within `θ_lim`.
///
/// The bucket comes from the flight `w` itself reaches unquantised.
#[allow(clippy::too_many_arguments)]
fn extend_free(
    q: &[Quat],
    s: usize,
    q0: Quat,
    dynamics: &FreeDynamics,
    w: Vec3,
    step: f64,
    lattice: Lattice,
    theta_lim: f64,
    max_len: usize,
) -> Option<RotationFit> {
    // How many frames from `q0` at velocity `w` stay within the bound (up to `limit`).
    let test = AngleTest::new(theta_lim);
    let reach = |w: Vec3, limit: usize| {
        let (mut qs, mut ws) = (q0, FreeDynamics::body(q0, w));
        (1..=limit)
            .take_while(|&u| {
                dynamics.frame(&mut qs, &mut ws);
                test.within_rotation(qs, q[s + u])
            })
            .count()
    };
    let exact = reach(w, max_len).max(1);
    // The decoder derives the bucket from the length: the fit's length must lie in the bucket
    // its velocity was quantised for. A flight that ends in a shorter bucket is requantised for
    // that one (a coarser step) and followed again; the bucket shrinks every time.
    let mut k = bucket(exact as u32);
    loop {
        let sw = step_linear(step, k);
        let limit = max_len.min(1usize << k.min(30));
        let wq = lattice.quantise(w, sw)?;
        let wd = lattice.point(wq, sw);
        let mut best = (reach(wd, limit), wq, wd);
        // Points near the nearest may follow the flight longer.
        if best.0 < limit {
            for &alt in lattice
                .alternatives(wq, w, sw, RESCUE_CANDIDATES)
                .as_slice()
            {
                let ad = lattice.point(alt, sw);
                let n = reach(ad, limit);
                if n > best.0 {
                    best = (n, alt, ad);
                }
            }
        }
        let (len, wq, wd) = best;
        if len == 0 {
            return None;
        }
        let kl = bucket(len as u32);
        if kl == k {
            return Some(RotationFit {
                len: len as u32,
                wq,
                aq: None,
                curve: RotationCurve::Free {
                    w: wd,
                    dynamics: *dynamics,
                },
            });
        }
        k = kl;
    }
}

/// `a x = b` for a 3 × 3 system by Gaussian elimination with partial pivoting; `None` if singular.
fn solve3(mut a: [[f64; 3]; 3], mut b: [f64; 3]) -> Option<[f64; 3]> {
    for c in 0..3 {
        let p = (c..3).max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))?;
        let pivot = a[p][c];
        if !pivot.is_finite() || pivot.abs() <= 1e-300 {
            return None;
        }
        a.swap(c, p);
        b.swap(c, p);
        let row = a[c];
        for r in c + 1..3 {
            let f = a[r][c] / row[c];
            for (x, y) in a[r][c..].iter_mut().zip(&row[c..]) {
                *x -= f * y;
            }
            b[r] -= f * b[c];
        }
    }
    let mut x = [0.0; 3];
    for c in (0..3).rev() {
        let s: f64 = (c + 1..3).map(|k| a[c][k] * x[k]).sum();
        x[c] = (b[c] - s) / a[c][c];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// How many frames from `s` on stay within `θ_lim` of the start orientation `q0` (a
/// [`RotationCurve::Rest`] segment of that length meets the bound).
pub(crate) fn rotation_rest_length(q: &[Quat], s: usize, q0: Quat, theta_lim: f64) -> usize {
    let max_len = (q.len() - 1 - s).min(MAX_SEGMENT_LEN);
    let test = AngleTest::new(theta_lim);
    (1..=max_len)
        .take_while(|&u| test.within(&RotationCurve::Rest, q0, u as f64, q[s + u]))
        .count()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn least_squares_recovers_an_exact_quadratic() {
        let y: Vec<Vec3> = (1..=9)
            .map(|u| {
                let u = u as f64;
                [0.5 * u - 0.25 * u * u, 3.0 * u, -1e-4 * u * u]
            })
            .collect();
        let rows: Vec<(f64, Vec3)> = y
            .iter()
            .enumerate()
            .map(|(i, v)| ((i + 1) as f64, *v))
            .collect();
        let [b, a, _] = least_squares(&rows, &[1, 2]);
        for (got, want) in b.iter().zip([0.5, 3.0, 0.0]) {
            assert!((got - want).abs() < 1e-12, "{b:?}");
        }
        for (got, want) in a.iter().zip([-0.25, 0.0, -1e-4]) {
            assert!((got - want).abs() < 1e-12, "{a:?}");
        }
        // One point: the linear term alone interpolates it.
        let [b, a, _] = least_squares(&[(1.0, [2.0, -1.0, 0.5])], &[1, 2]);
        assert_eq!((b, a), ([2.0, -1.0, 0.5], [0.0; 3]));
        // A free constant term as well: y = 1 + 2u − u².
        let rows: Vec<(f64, Vec3)> = (0..6)
            .map(|u| (u as f64, [1.0 + 2.0 * u as f64 - (u * u) as f64; 3]))
            .collect();
        let [c, b, a] = least_squares(&rows, &[0, 1, 2]);
        assert!(
            (c[0] - 1.0).abs() < 1e-12 && (b[1] - 2.0).abs() < 1e-12 && (a[2] + 1.0).abs() < 1e-12
        );
    }

    /// The interleaved Householder QR the fitter used before the basis factorisations were kept
    /// (reference for bit-for-bit equality).
    fn interleaved_least_squares(rows: &[(f64, Vec3)], powers: &[i32]) -> [Vec3; 3] {
        let cols = powers.len().min(rows.len()).min(3);
        const RHS: usize = 3;
        let mut m: Vec<[f64; 6]> = rows
            .iter()
            .map(|&(u, y)| {
                let mut r = [0.0; 6];
                for (j, &p) in powers.iter().take(cols).enumerate() {
                    r[j] = u.powi(p);
                }
                r[RHS..].copy_from_slice(&y);
                r
            })
            .collect();
        for j in 0..cols {
            let norm = m[j..].iter().map(|r| r[j] * r[j]).sum::<f64>().sqrt();
            if norm == 0.0 {
                continue;
            }
            let alpha = if m[j][j] > 0.0 { -norm } else { norm };
            let mut v: Vec<f64> = m[j..].iter().map(|r| r[j]).collect();
            v[0] -= alpha;
            let vv: f64 = v.iter().map(|x| x * x).sum();
            if vv == 0.0 {
                continue;
            }
            for col in (j..cols).chain(RHS..RHS + 3) {
                let d: f64 = m[j..].iter().zip(&v).map(|(r, vi)| r[col] * vi).sum();
                let f = 2.0 * d / vv;
                for (r, vi) in m[j..].iter_mut().zip(&v) {
                    r[col] -= f * vi;
                }
            }
        }
        let mut out = [[0.0; 3]; 3];
        for axis in 0..3 {
            for j in (0..cols).rev() {
                let mut acc = m[j][RHS + axis];
                for (m_jl, out_l) in m[j][j + 1..cols].iter().zip(&out[j + 1..cols]) {
                    acc -= m_jl * out_l[axis];
                }
                let d = m[j][j];
                out[j][axis] = if d.abs() > 1e-300 && acc.is_finite() {
                    acc / d
                } else {
                    0.0
                };
            }
        }
        out
    }

    #[test]
    fn projectors_agree_with_interleaved_qr() {
        let mut seed = 0x1234_5678_9abc_def0_u64;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 10f64.powi((seed % 7) as i32 - 3)
        };
        let powers: [&[i32]; 4] = [&[1], &[1, 2], &[0, 1], &[0, 1, 2]];
        for (variant, p) in powers.iter().enumerate() {
            for n in 0..=LS_ROWS {
                for _ in 0..20 {
                    let first = if variant < 2 { 1 } else { 0 };
                    let rows: Vec<(f64, Vec3)> = (first..first + n)
                        .map(|u| (u as f64, [rnd(), rnd(), rnd()]))
                        .collect();
                    let ys: Vec<Vec3> = rows.iter().map(|r| r.1).collect();
                    let got = window_bases().proj[variant][n].solve(&ys);
                    let want = interleaved_least_squares(&rows, p);
                    let scale = ys.iter().flatten().fold(1e-300f64, |m, v| m.max(v.abs()));
                    for (g, w) in got.iter().flatten().zip(want.iter().flatten()) {
                        assert!(
                            (g - w).abs() <= 1e-10 * scale,
                            "variant {variant}, {n} rows"
                        );
                    }
                }
            }
        }
    }

    /// A seeded stream of numbers in [0, 1) (a 64-bit LCG's top 53 bits): the same every run.
    fn uniform(mut seed: u64) -> impl FnMut() -> f64 {
        move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    #[test]
    fn the_fast_angle_test_agrees_with_the_full_computation() {
        let mut rnd = uniform(42u64);
        for theta_lim in [1e-9, 1e-6, 1e-4, 1e-3, 5e-3, 0.1, 1.0, 2.0, 3.0] {
            let test = AngleTest::new(theta_lim);
            for _ in 0..2000 {
                let q0 = rotation::exp([rnd() * 6.0 - 3.0, rnd() * 6.0 - 3.0, rnd() * 6.0 - 3.0]);
                let w = [rnd() - 0.5, rnd() - 0.5, rnd() - 0.5];
                let u = (1 + (rnd() * 40.0) as u32) as f64;
                let curve = RotationCurve::Linear { w };
                let at = curve.eval(q0, u);
                // A data point at a random angle close to the bound (either side, sometimes
                // within a few ulp of it).
                let axis = rotation::exp([rnd() * 6.0, rnd() * 6.0, rnd() * 6.0]);
                let n = rotation::norm3([axis[0], axis[1], axis[2]]).max(1e-300);
                let rel = [1e-3, 1e-9, 1e-14][(rnd() * 3.0) as usize] * (rnd() * 2.0 - 1.0);
                let angle = theta_lim * (1.0 + rel);
                let d = rotation::exp(rotation::scale3(
                    [axis[0] / n, axis[1] / n, axis[2] / n],
                    angle,
                ));
                let data = rotation::normalise(rotation::mul(rotation::conj(d), at)).unwrap();
                let exact = rotation::angle_between(at, data) <= theta_lim;
                assert_eq!(test.within(&curve, q0, u, data), exact, "θ {theta_lim}");
                assert_eq!(test.within_rotation(at, data), exact, "θ {theta_lim}");
            }
        }
    }

    /// The log-space shortcut decides only where the full computation decides the same, and the
    /// lower bound it gives the lattice search's pruning is one: on data near the bound (either
    /// side), at angles from 10⁻⁹ to 1 rad, with `y` the logarithm the fitter would use.
    #[test]
    fn the_log_space_verdicts_agree_with_the_full_computation() {
        let mut rnd = uniform(7u64);
        let mut decided = 0;
        for theta_lim in [1e-9, 1e-6, 1e-4, 1e-3, 5e-3, 0.1, 1.0] {
            let test = AngleTest::new(theta_lim);
            for _ in 0..4000 {
                let q0 = rotation::exp([rnd() * 6.0 - 3.0, rnd() * 6.0 - 3.0, rnd() * 6.0 - 3.0]);
                let scale = [0.01, 0.1, 0.5][(rnd() * 3.0) as usize];
                let (w, a) = (
                    [rnd() - 0.5, rnd() - 0.5, rnd() - 0.5].map(|v| v * scale),
                    [rnd() - 0.5, rnd() - 0.5, rnd() - 0.5].map(|v| v * scale * 0.01),
                );
                let u = (1 + (rnd() * 12.0) as u32) as f64;
                let curve = RotationCurve::Quadratic { w, a };
                let at = curve.eval(q0, u);
                let axis = rotation::exp([rnd() * 6.0, rnd() * 6.0, rnd() * 6.0]);
                let n = rotation::norm3([axis[0], axis[1], axis[2]]).max(1e-300);
                let rel = [0.5, 1e-3, 1e-9, 1e-14][(rnd() * 4.0) as usize] * (rnd() * 2.0 - 1.0);
                let d = rotation::exp(rotation::scale3(
                    [axis[0] / n, axis[1] / n, axis[2] / n],
                    theta_lim * (1.0 + rel),
                ));
                let data = rotation::normalise(rotation::mul(rotation::conj(d), at)).unwrap();
                let y = rotation::log(rotation::mul(data, rotation::conj(q0)));
                let angle = rotation::angle_between(at, data);
                if let Some(verdict) = test.log_verdict(&curve, u, y) {
                    assert_eq!(verdict, angle <= theta_lim, "θ {theta_lim}");
                    decided += 1;
                }
                let (below, _) = test.angle_below(&curve, u, y);
                assert!(below <= angle, "θ {theta_lim}: {below} > {angle}");
            }
        }
        // It decides at least the quarter of the cases half a bound away (the others are within
        // 10⁻³ of the bound, mostly left to the full computation).
        assert!(decided > 7 * 4000 / 5, "{decided}");
    }

    /// Probing the shortest useful length first changes nothing but the work: a fit told its
    /// minimum is the fit without it, or `None` where that one is shorter.
    #[test]
    fn a_fit_with_a_minimum_length_is_the_fit_without_it_or_none() {
        let mut u = uniform(11);
        let mut rnd = || u() - 0.5;
        let coding = PositionCoding::new(1.1e-3, Some([0.0, -9.81, 0.0]), 1.0 / 120.0);
        let (mut kept, mut refused) = (0, 0);
        for case in 0..300 {
            // Smooth motion with kicks every few frames (contact-like), so that fits end at all
            // lengths.
            let kick = 2 + case % 9;
            let (mut x, mut q) = (vec![[0.0; 3]], vec![rotation::IDENTITY]);
            let (mut v, mut w) = ([0.01, 0.02, 0.0], [0.01, 0.0, 0.005]);
            for i in 1..40 {
                if i % kick == 0 {
                    v = v.map(|c| c + 3e-3 * rnd());
                    w = w.map(|c| c + 4e-3 * rnd());
                }
                let p = x[i - 1];
                x.push(std::array::from_fn(|k| p[k] + v[k] + 1e-4 * rnd()));
                q.push(rotation::mul(rotation::exp(w), q[i - 1]));
            }
            for min_len in [2, 5, 7, 9] {
                let full = fit_position(
                    &x,
                    0,
                    x[0],
                    PositionKind::Quadratic,
                    StartCorrection::Anchored,
                    &coding,
                    1e-3,
                    1,
                );
                let probed = fit_position(
                    &x,
                    0,
                    x[0],
                    PositionKind::Quadratic,
                    StartCorrection::Anchored,
                    &coding,
                    1e-3,
                    min_len,
                );
                let expect = full.filter(|f| f.len as usize >= min_len);
                assert_eq!(
                    probed.map(|f| (f.len, f.coeffs)),
                    expect.map(|f| (f.len, f.coeffs))
                );
                for correction in CORRECTIONS {
                    let rotation = |min_len| {
                        fit_rotation(
                            &q,
                            0,
                            q[0],
                            RotationKind::Quadratic,
                            correction,
                            1.1e-3,
                            Lattice,
                            1e-3,
                            min_len,
                            &mut RotationScratch::default(),
                        )
                        .map(|f| (f.len, f.wq, f.aq))
                    };
                    let expect = rotation(1).filter(|f| f.0 as usize >= min_len);
                    assert_eq!(rotation(min_len), expect);
                    if expect.is_some() {
                        kept += 1;
                    } else {
                        refused += 1;
                    }
                }
            }
        }
        // Both outcomes occur.
        assert!(kept > 50 && refused > 50, "{kept} kept, {refused} refused");
    }

    #[test]
    fn a_gravity_parabola_is_one_segment() {
        let dt = 1.0 / 120.0;
        let coding = PositionCoding::new(1e-3, Some([0.0, -9.81, 0.0]), dt);
        let x: Vec<Vec3> = (0..400)
            .map(|i| {
                let t = i as f64 * dt;
                [1.0 + 2.0 * t, 3.0 + 5.0 * t - 4.905 * t * t, -0.5 * t]
            })
            .collect();
        let fit = fit_position(
            &x,
            0,
            x[0],
            PositionKind::Gravity,
            StartCorrection::Anchored,
            &coding,
            1e-3,
            1,
        )
        .unwrap();
        assert_eq!(fit.len, 399);
        assert_eq!(fit.coeffs.term, QuadraticTerm::Gravity);
    }

    #[test]
    fn a_constant_angular_acceleration_is_one_quadratic_segment() {
        // A box tipping over an edge: angular speed growing 1 mrad/frame per frame.
        let (w, a) = ([0.01, 0.0, 0.002], [1e-3, 0.0, -2e-4]);
        let q: Vec<Quat> = (0..60)
            .map(|i| {
                let u = i as f64;
                rotation::exp(std::array::from_fn(|k| w[k] * u + a[k] * u * u))
            })
            .collect();
        let fit = |kind| {
            fit_rotation(
                &q,
                0,
                q[0],
                kind,
                StartCorrection::Anchored,
                1e-3,
                Lattice,
                1e-3,
                1,
                &mut RotationScratch::default(),
            )
            .unwrap()
            .len
        };
        assert_eq!(fit(RotationKind::Quadratic), 59);
        assert!(fit(RotationKind::Linear) < 15);
    }

    #[test]
    fn a_constant_spin_beyond_half_a_turn_is_one_segment() {
        let w = [0.0, 0.3, 0.1]; // rad per frame: > π within 11 frames
        let q: Vec<Quat> = (0..200)
            .map(|i| rotation::exp(rotation::scale3(w, i as f64)))
            .collect();
        let fit = fit_rotation(
            &q,
            0,
            q[0],
            RotationKind::Linear,
            StartCorrection::Anchored,
            1e-3,
            Lattice,
            1e-3,
            1,
            &mut RotationScratch::default(),
        )
        .unwrap();
        assert_eq!(fit.len, 199);
    }
}
