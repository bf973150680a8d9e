//! The greedy segment fitter of §4.3, Figure 4.6, for positions and rotations.
//!
//! For the first `k = 10` points of a segment (start included) the curve is re-fitted by least
//! squares each time a point is added and *every* point is checked; after that the fit is frozen
//! and only extended, checking each new point — the thesis' O(n) compromise between refitting
//! everything (O(n²), Fig. 4.5 centre) and a poor fit (Fig. 4.5 left, i–j). All checks are made on
//! the *quantised* curve. Because the quantisation step depends on the length bucket (see
//! `segment`), the coefficients are re-quantised and all points re-checked whenever the length
//! crosses a power of two; that costs O(L) per doubling, so the fitter stays linear.

use crate::params::{FIT_WINDOW, MAX_SEGMENT_LEN};
use crate::rotation::{self, Quat, Vec3};
use crate::segment::{
    PositionCoding, PositionCurve, QuadraticQ, RotationCurve, bucket, quantise3, step_linear,
    step_quadratic,
};

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
/// thesis).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum StartCorrection {
    /// Least squares with the start point fixed (Figure 4.6).
    Anchored,
    /// Trend fitted with a free start; the inherited offset δ is removed at a rate δ/H
    /// (`f64::INFINITY`: kept).
    Horizon(f64),
}

/// Strategies tried for every segment; the longest result wins.
pub(crate) const CORRECTIONS: [StartCorrection; 3] = [
    StartCorrection::Anchored,
    StartCorrection::Horizon(f64::INFINITY),
    StartCorrection::Horizon(4.0 * FIT_WINDOW as f64),
];

/// Least squares `y_u ≈ Σ_j coef_j·u^{p_j}` for three right-hand sides at once, by Householder QR
/// (the thesis fits with QR, citing Golub & Van Loan). `powers` lists the exponents (0, 1, 2) of
/// the basis; returns one coefficient vector per power, zero where the system is rank-deficient.
fn least_squares(rows: &[(f64, Vec3)], powers: &[i32]) -> [Vec3; 3] {
    let cols = powers.len().min(rows.len()).min(3);
    const RHS: usize = 3;
    // Augmented rows [basis (3) | rhs (3)].
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
        // Apply H = I − 2vvᵀ/vᵀv to the remaining basis columns and to all right-hand sides.
        for col in (j..cols).chain(RHS..RHS + 3) {
            let d: f64 = m[j..].iter().zip(&v).map(|(r, vi)| r[col] * vi).sum();
            let f = 2.0 * d / vv;
            for (r, vi) in m[j..].iter_mut().zip(&v) {
                r[col] -= f * vi;
            }
        }
    }
    // Back substitution R x = Qᵀy, per right-hand side.
    let mut out = [[0.0; 3]; 3];
    for axis in 0..3 {
        for j in (0..cols).rev() {
            let mut acc = m[j][RHS + axis];
            for l in j + 1..cols {
                acc -= m[j][l] * out[l][axis];
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

/// `(b, a)` of a position segment starting at `c` (decoded) over data frames `s..=s+len`.
fn position_coefficients(
    x: &[Vec3],
    s: usize,
    len: usize,
    c: Vec3,
    g: Option<Vec3>,
    correction: StartCorrection,
) -> (Vec3, Vec3) {
    // Remove the known gravity term so that only unknown coefficients are fitted.
    let data = |u: usize| -> Vec3 {
        let uu = (u * u) as f64;
        let gu = g.map_or([0.0; 3], |g| rotation::scale3(g, uu));
        std::array::from_fn(|i| x[s + u][i] - gu[i])
    };
    let quadratic = g.is_none();
    match correction {
        StartCorrection::Anchored => {
            let rows: Vec<(f64, Vec3)> = (1..=len)
                .map(|u| {
                    let d = data(u);
                    (u as f64, std::array::from_fn(|i| d[i] - c[i]))
                })
                .collect();
            let powers: &[i32] = if quadratic && len >= 2 { &[1, 2] } else { &[1] };
            let [b, a, _] = least_squares(&rows, powers);
            (b, if quadratic { a } else { g.unwrap_or([0.0; 3]) })
        }
        StartCorrection::Horizon(h) => {
            let rows: Vec<(f64, Vec3)> = (0..=len).map(|u| (u as f64, data(u))).collect();
            let powers: &[i32] = if quadratic && len >= 2 {
                &[0, 1, 2]
            } else {
                &[0, 1]
            };
            let [c_fit, b, a] = least_squares(&rows, powers);
            let b = std::array::from_fn(|i| b[i] - (c[i] - c_fit[i]) / h);
            (b, if quadratic { a } else { g.unwrap_or([0.0; 3]) })
        }
    }
}

/// Figure 4.6 for positions: the longest segment from frame `s` whose quantised curve keeps every
/// frame within `e_max`, or `None` if not even one frame can be covered. `gravity = true` fixes
/// the quadratic term to the model's `h²g/2` (the one-bit case); otherwise all of it is fitted.
pub(crate) fn fit_position(
    x: &[Vec3],
    s: usize,
    c: Vec3,
    gravity: bool,
    correction: StartCorrection,
    coding: &PositionCoding,
    e_max: f64,
) -> Option<PositionFit> {
    let g = if gravity {
        Some(coding.gravity_term?)
    } else {
        None
    };
    let max_len = (x.len() - 1 - s).min(MAX_SEGMENT_LEN);
    let within = |curve: &PositionCurve, u: usize| dist(curve.eval(c, u as f64), x[s + u]) <= e_max;
    let mut best: Option<PositionFit> = None;
    let (mut b, mut a) = ([0.0; 3], [0.0; 3]);
    let mut current: Option<(u32, QuadraticQ, PositionCurve)> = None;
    for len in 1..=max_len {
        let refit = len < FIT_WINDOW;
        if refit {
            (b, a) = position_coefficients(x, s, len, c, g, correction);
        }
        let k = bucket(len as u32);
        let requantise = refit || current.is_none_or(|(ck, _, _)| ck != k);
        if requantise {
            let Some(bq) = quantise3(b, step_linear(coding.step, k)) else {
                break;
            };
            let aq = match g {
                Some(_) => None,
                None => match quantise3(a, step_quadratic(coding.step, k)) {
                    Some(aq) => Some(aq),
                    None => break,
                },
            };
            let coeffs = QuadraticQ { bq, aq };
            // A refit that quantises to the curve already verified on 1..len−1 (the common case
            // once the window has a few points) needs only the new point checked: same decisions
            // and bytes, without re-evaluating the window.
            if let Some((_, _, curve)) = current.filter(|&(ck, cq, _)| (ck, cq) == (k, coeffs)) {
                if !within(&curve, len) {
                    break;
                }
            } else {
                let curve = coeffs.curve(coding, k);
                if !(1..=len).all(|u| within(&curve, u)) {
                    break;
                }
                current = Some((k, coeffs, curve));
            }
        } else if let Some((_, _, curve)) = &current
            && !within(curve, len)
        {
            break;
        }
        let (_, coeffs, curve) = current?;
        best = Some(PositionFit {
            len: len as u32,
            coeffs,
            curve,
        });
    }
    best
}

/// Figure 4.6 for rotations (§4.3: "essentially unchanged, except that we replace FIT-SEGMENT"):
/// a constant angular velocity ω fitted by least squares to unwrapped logarithms
/// `log(q_u ⊗ q_ref⁻¹) ≈ u·ω`, error = angle of the residual rotation. `q_ref` is the decoded
/// start (anchored) or the data's own start (horizon, then corrected by the start offset / H).
pub(crate) fn fit_rotation(
    q: &[Quat],
    s: usize,
    q0: Quat,
    correction: StartCorrection,
    step: f64,
    theta_lim: f64,
) -> Option<RotationFit> {
    let max_len = (q.len() - 1 - s).min(MAX_SEGMENT_LEN);
    let within = |curve: &RotationCurve, u: usize| {
        rotation::angle_between(curve.eval(q0, u as f64), q[s + u]) <= theta_lim
    };
    let (reference, correction_rate) = match correction {
        StartCorrection::Anchored => (q0, [0.0; 3]),
        StartCorrection::Horizon(h) => {
            let offset = rotation::log(rotation::mul(q0, rotation::conj(q[s])));
            (q[s], rotation::scale3(offset, 1.0 / h))
        }
    };
    let inv_ref = rotation::conj(reference);
    let mut last_log = [0.0; 3];
    // Running sums for ω = Σ u·r_u / Σ u².
    let (mut sur, mut suu) = ([0.0; 3], 0.0);
    let mut w = [0.0; 3];
    let mut best: Option<RotationFit> = None;
    let mut current: Option<(u32, [i64; 3], RotationCurve)> = None;
    for len in 1..=max_len {
        let refit = len < FIT_WINDOW;
        if refit {
            let r = rotation::log(rotation::mul(q[s + len], inv_ref));
            let r = rotation::unwrap_near(r, last_log);
            last_log = r;
            let u = len as f64;
            sur = std::array::from_fn(|i| sur[i] + u * r[i]);
            suu += u * u;
            w = std::array::from_fn(|i| sur[i] / suu - correction_rate[i]);
        }
        let k = bucket(len as u32);
        let requantise = refit || current.is_none_or(|(ck, _, _)| ck != k);
        if requantise {
            let sw = step_linear(step, k);
            let Some(wq) = quantise3(w, sw) else {
                break;
            };
            // As for positions: an unchanged quantised curve needs only the new point checked.
            if let Some((_, _, curve)) = current.filter(|&(ck, cq, _)| (ck, cq) == (k, wq)) {
                if !within(&curve, len) {
                    break;
                }
            } else {
                let curve = RotationCurve::Linear {
                    w: crate::segment::dequantise3(wq, sw),
                };
                if !(1..=len).all(|u| within(&curve, u)) {
                    break;
                }
                current = Some((k, wq, curve));
            }
        } else if let Some((_, _, curve)) = &current
            && !within(curve, len)
        {
            break;
        }
        let (_, wq, curve) = current?;
        best = Some(RotationFit {
            len: len as u32,
            wq,
            curve,
        });
    }
    best
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
        let fit =
            fit_position(&x, 0, x[0], true, StartCorrection::Anchored, &coding, 1e-3).unwrap();
        assert_eq!(fit.len, 399);
        assert_eq!(fit.coeffs.aq, None);
    }

    #[test]
    fn a_constant_spin_beyond_half_a_turn_is_one_segment() {
        let w = [0.0, 0.3, 0.1]; // rad per frame: > π within 11 frames
        let q: Vec<Quat> = (0..200)
            .map(|i| rotation::exp(rotation::scale3(w, i as f64)))
            .collect();
        let fit = fit_rotation(&q, 0, q[0], StartCorrection::Anchored, 1e-3, 1e-3).unwrap();
        assert_eq!(fit.len, 199);
    }
}
