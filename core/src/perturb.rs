//! §4.1.2 impact perturbations, as pure functions.
//!
//! Per step and body the contact part of the velocity change is Δv = (v⁺ − v⁻ − gΔt)/Δt (free
//! flight under gravity is not an impact). Where ‖Δv‖ exceeds C_v we add m·d̂ to v⁺, with d̂
//! drawn from a cosⁿ lobe about Δv and m uniform in ±α‖Δv‖Δt — α times the *velocity change*
//! of the impact, the plausibility bound of §4.1.1. Angular velocity is treated the same way
//! with C_ω and no gravity term.

use crate::rng::WorldRng;

pub type V3 = [f64; 3];

#[inline]
pub fn norm(v: V3) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

#[inline]
fn scale(v: V3, s: f64) -> V3 {
    [v[0] * s, v[1] * s, v[2] * s]
}

#[inline]
fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Two unit vectors completing `n` (unit) to a right-handed orthonormal basis.
fn basis(n: V3) -> (V3, V3) {
    // Duff et al.'s branchless construction (numerically safe for all unit n).
    let sign = if n[2] >= 0.0 { 1.0 } else { -1.0 };
    let a = -1.0 / (sign + n[2]);
    let b = n[0] * n[1] * a;
    let t = [1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]];
    let u = [b, sign + n[1] * n[1] * a, -n[1]];
    debug_assert!((norm(cross(t, u)) - 1.0).abs() < 1e-9);
    (t, u)
}

/// A unit direction drawn from the cosⁿ lobe about the unit `axis`: density ∝ cosⁿθ on the
/// hemisphere around `axis` (the Phong lobe of §4.1.2). Sampled by inversion: cos θ = u^(1/(n+1)).
pub fn sample_cos_lobe(axis: V3, n: f64, rng: &mut WorldRng) -> V3 {
    let cos_t = rng.next_f64().powf(1.0 / (n + 1.0));
    let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
    let phi = std::f64::consts::TAU * rng.next_f64();
    let (t, u) = basis(axis);
    let (s, c) = phi.sin_cos();
    [
        axis[0] * cos_t + (t[0] * c + u[0] * s) * sin_t,
        axis[1] * cos_t + (t[1] * c + u[1] * s) * sin_t,
        axis[2] * cos_t + (t[2] * c + u[2] * s) * sin_t,
    ]
}

/// The contact part of a velocity change, as a rate: (v⁺ − v⁻ − gΔt)/Δt (4.3 with gravity
/// removed). For angular velocity pass `g = [0; 3]` (4.4).
#[inline]
pub fn impact_rate(before: V3, after: V3, g: V3, dt: f64) -> V3 {
    [
        (after[0] - before[0] - g[0] * dt) / dt,
        (after[1] - before[1] - g[1] * dt) / dt,
        (after[2] - before[2] - g[2] * dt) / dt,
    ]
}

/// The perturbation to add to the post-impact velocity, or `None` when ‖rate‖ ≤ threshold.
///
/// `rate` is Δv from [`impact_rate`]; the result is m·d̂ with d̂ ~ cosⁿ lobe about rate and
/// m ~ U[−α‖rate‖Δt, α‖rate‖Δt]. Draws exactly three numbers from `rng` when it fires and none
/// otherwise (so a world's draws depend only on its impacts).
pub fn perturbation(
    rate: V3,
    threshold: f64,
    dt: f64,
    alpha: f64,
    n: f64,
    rng: &mut WorldRng,
) -> Option<V3> {
    let r = norm(rate);
    if r.is_nan() || r <= threshold || !r.is_finite() {
        return None;
    }
    let axis = scale(rate, 1.0 / r);
    let d = sample_cos_lobe(axis, n, rng);
    let bound = alpha * r * dt;
    let m = rng.uniform(-bound, bound);
    Some(scale(d, m))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Stream;
    use proptest::prelude::*;

    fn dot(a: V3, b: V3) -> f64 {
        a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    }

    #[test]
    fn lobe_matches_cos_n_statistically() {
        // For density ∝ cosⁿθ on the hemisphere, E[cos θ] = (n+1)/(n+2).
        for n in [1.0, 5.0, 20.0, 100.0] {
            let mut rng = WorldRng::new(99, Stream::Perturbation);
            let axis = [0.6, 0.0, 0.8];
            let k = 50_000;
            let mut mean = 0.0;
            for _ in 0..k {
                let d = sample_cos_lobe(axis, n, &mut rng);
                assert!((norm(d) - 1.0).abs() < 1e-12);
                let c = dot(d, axis);
                assert!(c >= -1e-12, "direction left the hemisphere");
                mean += c;
            }
            mean /= k as f64;
            let expect = (n + 1.0) / (n + 2.0);
            assert!((mean - expect).abs() < 0.005, "n={n}: {mean} vs {expect}");
        }
    }

    #[test]
    fn lobe_is_symmetric_about_axis() {
        // The azimuth is uniform: the mean tangential component vanishes.
        let mut rng = WorldRng::new(5, Stream::Perturbation);
        let axis = [0.0, 1.0, 0.0];
        let mut sx = 0.0;
        let mut sz = 0.0;
        let k = 50_000;
        for _ in 0..k {
            let d = sample_cos_lobe(axis, 3.0, &mut rng);
            sx += d[0];
            sz += d[2];
        }
        assert!((sx / k as f64).abs() < 0.01 && (sz / k as f64).abs() < 0.01);
    }

    #[test]
    fn free_flight_and_resting_are_not_impacts() {
        let g = [0.0, -9.81, 0.0];
        let dt = 1.0 / 120.0;
        let mut rng = WorldRng::new(1, Stream::Perturbation);
        // Free flight: v⁺ = v⁻ + gΔt exactly.
        let before = [1.0, 2.0, 3.0];
        let after = [1.0, 2.0 - 9.81 * dt, 3.0];
        assert!(norm(impact_rate(before, after, g, dt)) < 1e-9);
        // Resting: the contact cancels gravity, ‖Δv‖ = g, below the default C_v.
        let rate = impact_rate([0.0; 3], [0.0; 3], g, dt);
        assert!(perturbation(rate, 30.0, dt, 0.1, 20.0, &mut rng).is_none());
    }

    #[test]
    fn magnitude_is_uniform_within_bound() {
        let dt = 1.0 / 120.0;
        let rate = [0.0, 600.0, 0.0]; // a 5 m/s bounce in one step
        let bound = 0.1 * 600.0 * dt;
        let mut rng = WorldRng::new(3, Stream::Perturbation);
        let k = 40_000;
        let mut abs_mean = 0.0;
        let mut max = 0.0f64;
        for _ in 0..k {
            let p = perturbation(rate, 30.0, dt, 0.1, 20.0, &mut rng)
                .unwrap_or_else(|| panic!("must fire"));
            let m = norm(p);
            max = max.max(m);
            abs_mean += m;
        }
        abs_mean /= k as f64;
        assert!(max <= bound * (1.0 + 1e-12));
        assert!(max > 0.99 * bound, "the bound should be approached");
        // |m| for m ~ U[-b, b] has mean b/2.
        assert!(
            (abs_mean / bound - 0.5).abs() < 0.01,
            "{}",
            abs_mean / bound
        );
    }

    proptest! {
        #[test]
        fn perturbation_never_exceeds_alpha_times_change(
            rx in -1e4f64..1e4, ry in -1e4f64..1e4, rz in -1e4f64..1e4,
            alpha in 0.0f64..0.5, n in 0.0f64..200.0, seed in any::<u64>(),
        ) {
            let dt = 1.0 / 120.0;
            let mut rng = WorldRng::new(seed, Stream::Perturbation);
            let rate = [rx, ry, rz];
            if let Some(p) = perturbation(rate, 30.0, dt, alpha, n, &mut rng) {
                prop_assert!(norm(p) <= alpha * norm(rate) * dt * (1.0 + 1e-12));
                prop_assert!(norm(rate) > 30.0);
            } else {
                prop_assert!(norm(rate) <= 30.0);
            }
        }
    }
}
