//! Unit quaternions `[x, y, z, w]` and the exponential / logarithm maps between rotation vectors
//! and rotations (§4.3, eq. 4.8: the skew matrix [ω] is the rotation vector ω in matrix form;
//! here the same maps are written for quaternions).
//!
//! `q` and `−q` are the same rotation (the double cover); every function here treats them alike.

use std::f64::consts::TAU;

pub(crate) type Quat = [f64; 4];
pub(crate) type Vec3 = [f64; 3];

pub(crate) const IDENTITY: Quat = [0.0, 0.0, 0.0, 1.0];

pub(crate) fn norm3(v: Vec3) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

pub(crate) fn dot3(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub(crate) fn scale3(v: Vec3, s: f64) -> Vec3 {
    [v[0] * s, v[1] * s, v[2] * s]
}

/// Hamilton product `a ⊗ b` (apply `b`, then `a`).
pub(crate) fn mul(a: Quat, b: Quat) -> Quat {
    let [ax, ay, az, aw] = a;
    let [bx, by, bz, bw] = b;
    [
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ]
}

pub(crate) fn conj(q: Quat) -> Quat {
    [-q[0], -q[1], -q[2], q[3]]
}

/// `q / |q|`, or `None` for a zero, tiny or non-finite quaternion.
pub(crate) fn normalise(q: Quat) -> Option<Quat> {
    let n2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
    if !(n2.is_finite() && n2 > 1e-200) {
        return None;
    }
    let n = n2.sqrt();
    Some([q[0] / n, q[1] / n, q[2] / n, q[3] / n])
}

/// Rotation vector → unit quaternion (rotation by |r| about r/|r|).
pub(crate) fn exp(r: Vec3) -> Quat {
    let theta = norm3(r);
    let half = 0.5 * theta;
    // sin(θ/2)/θ, with its Taylor series where the quotient would lose precision.
    let k = if theta < 1e-6 {
        0.5 - theta * theta / 48.0
    } else {
        half.sin() / theta
    };
    [r[0] * k, r[1] * k, r[2] * k, half.cos()]
}

/// [`exp`] with `sin` and `cos` replaced by their Taylor polynomials for angles below 1 rad
/// (truncation < 10⁻¹⁹, so the result differs from [`exp`] by a few ulp): for the encoder's fast
/// bound test, which allows for far larger differences (`fit::AngleTest`). The decoder always
/// uses [`exp`].
pub(crate) fn exp_approx(r: Vec3) -> Quat {
    let t2 = dot3(r, r);
    if t2.is_nan() || t2 >= 1.0 {
        return exp(r);
    }
    // h = θ/2, x = h²: sin(h)/h = Σ (−x)ᵏ/(2k+1)!, cos(h) = Σ (−x)ᵏ/(2k)!, to the h¹⁶ term.
    let x = 0.25 * t2;
    const S: [f64; 8] = [
        1.0,
        -1.0 / 6.0,
        1.0 / 120.0,
        -1.0 / 5040.0,
        1.0 / 362_880.0,
        -1.0 / 39_916_800.0,
        1.0 / 6_227_020_800.0,
        -1.0 / 1_307_674_368_000.0,
    ];
    const C: [f64; 9] = [
        1.0,
        -1.0 / 2.0,
        1.0 / 24.0,
        -1.0 / 720.0,
        1.0 / 40_320.0,
        -1.0 / 3_628_800.0,
        1.0 / 479_001_600.0,
        -1.0 / 87_178_291_200.0,
        1.0 / 20_922_789_888_000.0,
    ];
    let sinc = S.iter().rev().fold(0.0, |acc, &c| acc * x + c);
    let cos = C.iter().rev().fold(0.0, |acc, &c| acc * x + c);
    // sin(h)/θ = sinc(h)/2.
    let k = 0.5 * sinc;
    [r[0] * k, r[1] * k, r[2] * k, cos]
}

/// `v` rotated by the unit quaternion `q` (`q ⊗ v ⊗ q⁻¹`), with `+`, `×` only.
pub(crate) fn rotate(q: Quat, v: Vec3) -> Vec3 {
    let u = [q[0], q[1], q[2]];
    let t = scale3(cross3(u, v), 2.0);
    let c = cross3(u, t);
    [
        v[0] + q[3] * t[0] + c[0],
        v[1] + q[3] * t[1] + c[1],
        v[2] + q[3] * t[2] + c[2],
    ]
}

pub(crate) fn cross3(a: Vec3, b: Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Unit quaternion → rotation vector with angle in [0, π] (the shorter of `q`, `−q`).
pub(crate) fn log(q: Quat) -> Vec3 {
    let q = if q[3] < 0.0 {
        [-q[0], -q[1], -q[2], -q[3]]
    } else {
        q
    };
    let v = [q[0], q[1], q[2]];
    let s = norm3(v);
    let theta = 2.0 * s.atan2(q[3]);
    let k = if s < 1e-12 {
        2.0 / q[3].max(1e-300)
    } else {
        theta / s
    };
    scale3(v, k)
}

/// Angle of the residual rotation `a ⊗ b⁻¹` in [0, π]: the rotation error of §4.3 ("the
/// quaternion argument of the rotational error"). Uses `atan2`, accurate for tiny angles.
pub(crate) fn angle_between(a: Quat, b: Quat) -> f64 {
    let d = mul(a, conj(b));
    2.0 * norm3([d[0], d[1], d[2]]).atan2(d[3].abs())
}

/// Among the rotation vectors equivalent to `r` — `(θ + 2πm)·n̂` for integer m — the one closest
/// to `prev`. Makes a sequence of logarithms continuous, so that a body spinning through more than
/// half a turn inside one segment still has logarithms growing linearly in time.
pub(crate) fn unwrap_near(r: Vec3, prev: Vec3) -> Vec3 {
    let theta = norm3(r);
    let axis = if theta > 1e-12 {
        scale3(r, 1.0 / theta)
    } else {
        let pn = norm3(prev);
        if pn > 1e-12 {
            scale3(prev, 1.0 / pn)
        } else {
            return r;
        }
    };
    let along = dot3(prev, axis);
    let m = ((along - theta) / TAU).round();
    if !m.is_finite() {
        return r;
    }
    scale3(axis, theta + TAU * m)
}

/// Normalised linear interpolation along the shorter arc (used only between frames of a raw key
/// segment; frames themselves are exact).
pub(crate) fn nlerp(a: Quat, b: Quat, u: f64) -> Quat {
    let d = a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3];
    let b = if d < 0.0 {
        [-b[0], -b[1], -b[2], -b[3]]
    } else {
        b
    };
    let q = std::array::from_fn(|i| a[i] + (b[i] - a[i]) * u);
    normalise(q).unwrap_or(a)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: Quat, b: Quat) -> bool {
        angle_between(a, b) < 1e-12
    }

    #[test]
    fn exp_log_roundtrip_and_double_cover() {
        for r in [
            [0.0, 0.0, 0.0],
            [1e-9, -2e-9, 0.0],
            [0.3, -0.2, 0.1],
            [3.0, 0.5, -0.2],
            [0.0, 3.1, 0.0],
        ] {
            let q = exp(r);
            assert!(close(exp(log(q)), q));
            let neg = [-q[0], -q[1], -q[2], -q[3]];
            assert!(close(exp(log(neg)), q), "−q is the same rotation");
            assert!(angle_between(q, neg) < 1e-12);
        }
    }

    #[test]
    fn the_polynomial_exp_agrees_with_exp_to_a_few_ulp() {
        let mut worst = 0.0f64;
        for i in 0..20_000 {
            let t = i as f64 / 20_000.0;
            let r = [
                t * 0.6 * (i as f64).sin(),
                -t * 0.5,
                t * 0.6 * (i as f64 * 0.7).cos(),
            ];
            let (a, b) = (exp(r), exp_approx(r));
            for k in 0..4 {
                worst = worst.max((a[k] - b[k]).abs());
            }
        }
        assert!(worst < 1e-15, "{worst:e}");
        assert_eq!(exp_approx([0.0; 3]), IDENTITY);
        assert_eq!(exp_approx([2.0, 0.0, 0.0]), exp([2.0, 0.0, 0.0]));
    }

    #[test]
    fn angle_between_measures_the_rotation_angle() {
        let a = exp([0.0, 0.4, 0.0]);
        let b = exp([0.0, 0.1, 0.0]);
        assert!((angle_between(a, b) - 0.3).abs() < 1e-12);
        assert!((angle_between(exp([1e-7, 0.0, 0.0]), IDENTITY) - 1e-7).abs() < 1e-18);
    }

    #[test]
    fn unwrap_continues_past_half_a_turn() {
        // A rotation of 3.5 rad about z has log −(2π − 3.5)·ẑ; near 3.4·ẑ it unwraps to 3.5·ẑ.
        let r = log(exp([0.0, 0.0, 3.5]));
        assert!(r[2] < 0.0);
        let u = unwrap_near(r, [0.0, 0.0, 3.4]);
        assert!((u[2] - 3.5).abs() < 1e-12, "{u:?}");
        // A full turn (identity) next to 6.2·ẑ becomes 2π·ẑ.
        let u = unwrap_near([0.0; 3], [0.0, 0.0, 6.2]);
        assert!((u[2] - TAU).abs() < 1e-12);
    }
}
