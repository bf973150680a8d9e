//! The little vector and quaternion algebra the browsing logic needs, on plain arrays (the
//! representation of the rest of `mwb-core`: positions `[x, y, z]`, quaternions `[x, y, z, w]`).

/// A point or direction in world space, metres.
pub type Vec3 = [f64; 3];
/// A unit quaternion `[x, y, z, w]`.
pub type Quat = [f64; 4];

#[inline]
pub(crate) fn add(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

#[inline]
pub(crate) fn sub(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline]
pub(crate) fn scale(v: Vec3, s: f64) -> Vec3 {
    [v[0] * s, v[1] * s, v[2] * s]
}

#[inline]
pub(crate) fn dot(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
pub(crate) fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[inline]
pub(crate) fn norm(v: Vec3) -> f64 {
    dot(v, v).sqrt()
}

/// `a + s·(b − a)`.
#[inline]
pub(crate) fn lerp(a: Vec3, b: Vec3, s: f64) -> Vec3 {
    add(a, scale(sub(b, a), s))
}

/// `v / ‖v‖`, or `None` for a zero or non-finite vector.
pub(crate) fn normalize(v: Vec3) -> Option<Vec3> {
    let n = norm(v);
    (n > 0.0 && n.is_finite()).then(|| scale(v, 1.0 / n))
}

pub(crate) fn quat_normalize(q: Quat) -> Option<Quat> {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    (n > 0.0 && n.is_finite()).then(|| [q[0] / n, q[1] / n, q[2] / n, q[3] / n])
}

/// `v` rotated by the unit quaternion `q`: v + 2w(u×v) + 2u×(u×v), u = (x, y, z).
pub(crate) fn quat_rotate(q: Quat, v: Vec3) -> Vec3 {
    let u = [q[0], q[1], q[2]];
    let uv = cross(u, v);
    let uuv = cross(u, uv);
    add(v, add(scale(uv, 2.0 * q[3]), scale(uuv, 2.0)))
}

/// The Hamilton product `a·b` (apply `b`, then `a`).
pub(crate) fn quat_mul(a: Quat, b: Quat) -> Quat {
    [
        a[3] * b[0] + a[0] * b[3] + a[1] * b[2] - a[2] * b[1],
        a[3] * b[1] - a[0] * b[2] + a[1] * b[3] + a[2] * b[0],
        a[3] * b[2] + a[0] * b[1] - a[1] * b[0] + a[2] * b[3],
        a[3] * b[3] - a[0] * b[0] - a[1] * b[1] - a[2] * b[2],
    ]
}

pub(crate) fn quat_conj(q: Quat) -> Quat {
    [-q[0], -q[1], -q[2], q[3]]
}

/// The angle in [0, π] of the rotation taking orientation `a` to orientation `b` (unit
/// quaternions; q and −q are the same orientation). `2·atan2(‖vec‖, |w|)` stays accurate for tiny
/// angles, where `2·acos(|w|)` loses half its digits.
pub fn quat_angle_between(a: Quat, b: Quat) -> f64 {
    let d = quat_mul(quat_conj(a), b);
    2.0 * norm([d[0], d[1], d[2]]).atan2(d[3].abs())
}

/// Orthonormal eigenvectors of the symmetric 3×3 matrix `m` (cyclic Jacobi rotations; a 3×3
/// covariance converges in a handful of sweeps). The basis is right-handed and always
/// orthonormal, even for degenerate (rank-deficient) inputs, which is all an OBB needs.
pub(crate) fn sym_eigenvectors(m: [[f64; 3]; 3]) -> [Vec3; 3] {
    let mut a = m;
    // Columns of v are the eigenvectors.
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _sweep in 0..32 {
        let off = a[0][1].abs() + a[0][2].abs() + a[1][2].abs();
        let diag = a[0][0].abs() + a[1][1].abs() + a[2][2].abs();
        if off <= 1e-15 * diag || off == 0.0 || !off.is_finite() {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q] == 0.0 {
                continue;
            }
            // Rotation that zeroes a[p][q] (Numerical Recipes' stable form; signum(0) = 1).
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            // a ← Jᵀ a J, v ← v J with J the rotation in the (p, q) plane.
            for row in &mut a {
                let (akp, akq) = (row[p], row[q]);
                row[p] = c * akp - s * akq;
                row[q] = s * akp + c * akq;
            }
            let (row_p, row_q) = (a[p], a[q]);
            a[p] = std::array::from_fn(|k| c * row_p[k] - s * row_q[k]);
            a[q] = std::array::from_fn(|k| s * row_p[k] + c * row_q[k]);
            for row in &mut v {
                let vkp = row[p];
                let vkq = row[q];
                row[p] = c * vkp - s * vkq;
                row[q] = s * vkp + c * vkq;
            }
        }
    }
    let e0 = [v[0][0], v[1][0], v[2][0]];
    let e1 = [v[0][1], v[1][1], v[2][1]];
    // Re-orthonormalise against drift and make the frame right-handed.
    let e0 = normalize(e0).unwrap_or([1.0, 0.0, 0.0]);
    let e1 = normalize(sub(e1, scale(e0, dot(e0, e1)))).unwrap_or_else(|| any_perpendicular(e0));
    let e2 = cross(e0, e1);
    [e0, e1, e2]
}

/// Some unit vector perpendicular to the unit vector `n`.
pub(crate) fn any_perpendicular(n: Vec3) -> Vec3 {
    let helper = if n[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    normalize(cross(n, helper)).unwrap_or([0.0, 0.0, 1.0])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn axis_angle(axis: Vec3, angle: f64) -> Quat {
        let (s, c) = (angle / 2.0).sin_cos();
        let a = normalize(axis).unwrap_or([1.0, 0.0, 0.0]);
        [a[0] * s, a[1] * s, a[2] * s, c]
    }

    #[test]
    fn rotation_matches_axis_angle() {
        let q = axis_angle([0.0, 0.0, 1.0], std::f64::consts::FRAC_PI_2);
        let r = quat_rotate(q, [1.0, 0.0, 0.0]);
        assert!(norm(sub(r, [0.0, 1.0, 0.0])) < 1e-12, "{r:?}");
    }

    #[test]
    fn angle_between_is_the_relative_rotation_and_ignores_the_double_cover() {
        let a = axis_angle([1.0, 2.0, 3.0], 0.7);
        let b = quat_mul(a, axis_angle([0.0, 1.0, 0.0], 0.25));
        assert!((quat_angle_between(a, b) - 0.25).abs() < 1e-12);
        let neg = [-b[0], -b[1], -b[2], -b[3]];
        assert!((quat_angle_between(a, neg) - 0.25).abs() < 1e-12);
        assert!(quat_angle_between(a, a).abs() < 1e-15);
    }

    #[test]
    fn jacobi_diagonalises_a_covariance() {
        let m = [[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 1.0]];
        let e = sym_eigenvectors(m);
        for i in 0..3 {
            let me = [dot(m[0], e[i]), dot(m[1], e[i]), dot(m[2], e[i])];
            let lambda = dot(me, e[i]);
            assert!(
                norm(sub(me, scale(e[i], lambda))) < 1e-9,
                "not an eigenvector"
            );
            for j in 0..3 {
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((dot(e[i], e[j]) - want).abs() < 1e-12);
            }
        }
        assert!((dot(cross(e[0], e[1]), e[2]) - 1.0).abs() < 1e-12);
    }
}
