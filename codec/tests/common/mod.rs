//! Deterministic trajectory generators for the codec tests: every track is a function of a seed,
//! so a failing proptest case is reproducible from its printed inputs.
#![allow(dead_code)]

use mwb_codec::Track;

pub const G: [f64; 3] = [0.0, -9.81, 0.0];

/// SplitMix64: tiny, seedable, good enough for test data.
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [a, b).
    pub fn range(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * ((self.next_u64() >> 11) as f64 / (1u64 << 53) as f64)
    }

    pub fn vec3(&mut self, a: f64, b: f64) -> [f64; 3] {
        [self.range(a, b), self.range(a, b), self.range(a, b)]
    }

    /// Roughly normal (sum of uniforms), unit variance.
    pub fn normal(&mut self) -> f64 {
        (0..4).map(|_| self.range(-1.0, 1.0)).sum::<f64>() * (3.0f64 / 4.0).sqrt()
    }
}

pub fn quat_exp(r: [f64; 3]) -> [f64; 4] {
    let th = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
    let k = if th < 1e-9 {
        0.5
    } else {
        (0.5 * th).sin() / th
    };
    [r[0] * k, r[1] * k, r[2] * k, (0.5 * th).cos()]
}

pub fn quat_mul(a: [f64; 4], b: [f64; 4]) -> [f64; 4] {
    let [ax, ay, az, aw] = a;
    let [bx, by, bz, bw] = b;
    [
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ]
}

pub fn normalise(q: [f64; 4]) -> [f64; 4] {
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    q.map(|v| v / n)
}

/// Angle of the residual rotation between two unit quaternions (q ≡ −q).
pub fn rotation_angle(a: [f64; 4], b: [f64; 4]) -> f64 {
    let d = quat_mul(a, [-b[0], -b[1], -b[2], b[3]]);
    2.0 * (d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        .sqrt()
        .atan2(d[3].abs())
}

pub fn distance(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

fn random_orientation(rng: &mut Rng) -> [f64; 4] {
    quat_exp(rng.vec3(-3.0, 3.0))
}

/// A body thrown into the air that bounces on the floor y = r, loses energy, and comes to rest
/// (with solver-like jitter of `jitter` metres while resting). Semi-implicit Euler, like rapier.
pub fn ballistic(rng: &mut Rng, frames: usize, dt: f64, jitter: f64) -> Track {
    let r = 0.1;
    let mut x = [
        rng.range(-5.0, 5.0),
        rng.range(0.5, 4.0),
        rng.range(-5.0, 5.0),
    ];
    let mut v = [
        rng.range(-4.0, 4.0),
        rng.range(0.0, 8.0),
        rng.range(-4.0, 4.0),
    ];
    let mut w = rng.vec3(-12.0, 12.0);
    let mut q = random_orientation(rng);
    let restitution = rng.range(0.3, 0.8);
    let mut resting = false;
    let mut t = Track::default();
    for _ in 0..frames {
        if resting {
            let j = [
                rng.normal() * jitter,
                rng.normal() * jitter,
                rng.normal() * jitter,
            ];
            t.positions.push([x[0] + j[0], x[1] + j[1], x[2] + j[2]]);
        } else {
            t.positions.push(x);
        }
        t.rotations.push(q);
        if resting {
            continue;
        }
        for i in 0..3 {
            v[i] += G[i] * dt;
            x[i] += v[i] * dt;
        }
        if x[1] < r {
            x[1] = r + (r - x[1]) * restitution;
            v[1] = -v[1] * restitution;
            v[0] *= 0.8;
            v[2] *= 0.8;
            w = [
                0.6 * w[0] + rng.range(-2.0, 2.0),
                0.6 * w[1] + rng.range(-2.0, 2.0),
                0.6 * w[2] + rng.range(-2.0, 2.0),
            ];
            if v[1].abs() < 0.6 {
                resting = true;
                x[1] = r;
                w = [0.0; 3];
            }
        }
        q = normalise(quat_mul(quat_exp(w.map(|c| c * dt)), q));
    }
    t
}

/// Brownian motion: every frame an independent random step (the worst case for splines).
pub fn random_walk(rng: &mut Rng, frames: usize) -> Track {
    let sigma = 10f64.powf(rng.range(-4.0, -1.3));
    let sigma_r = 10f64.powf(rng.range(-4.0, -0.7));
    let mut x = rng.vec3(-10.0, 10.0);
    let mut q = random_orientation(rng);
    let mut t = Track::default();
    for _ in 0..frames {
        t.positions.push(x);
        t.rotations.push(q);
        for c in &mut x {
            *c += rng.normal() * sigma;
        }
        let d = [
            rng.normal() * sigma_r,
            rng.normal() * sigma_r,
            rng.normal() * sigma_r,
        ];
        q = normalise(quat_mul(quat_exp(d), q));
    }
    t
}

/// A body at rest, optionally with tiny jitter.
pub fn resting(rng: &mut Rng, frames: usize) -> Track {
    let x = rng.vec3(-10.0, 10.0);
    let q = random_orientation(rng);
    let jitter = if rng.range(0.0, 1.0) < 0.5 { 0.0 } else { 1e-6 };
    Track {
        positions: (0..frames)
            .map(|_| x.map(|c| c + rng.normal() * jitter))
            .collect(),
        rotations: vec![q; frames],
    }
}

/// Fast constant spin (up to ~0.6 rad per frame at 120 Hz) while drifting.
pub fn spinning(rng: &mut Rng, frames: usize, dt: f64) -> Track {
    let w = rng.vec3(-70.0, 70.0);
    let v = rng.vec3(-1.0, 1.0);
    let x0 = rng.vec3(-3.0, 3.0);
    let q0 = random_orientation(rng);
    Track {
        positions: (0..frames)
            .map(|i| std::array::from_fn(|k| x0[k] + v[k] * i as f64 * dt))
            .collect(),
        rotations: (0..frames)
            .map(|i| normalise(quat_mul(quat_exp(w.map(|c| c * i as f64 * dt)), q0)))
            .collect(),
    }
}

/// Torque-free asymmetric body (inertia 1 : 2 : 3): the angular velocity precesses, so constant-ω
/// segments must be short. Euler's equations integrated with small substeps.
pub fn precessing(rng: &mut Rng, frames: usize, dt: f64) -> Track {
    let inertia = [1.0, 2.0, 3.0];
    let mut wb = rng.vec3(-8.0, 8.0);
    let mut q = random_orientation(rng);
    let mut x = rng.vec3(-3.0, 3.0);
    let v = rng.vec3(-2.0, 2.0);
    let sub = 8;
    let h = dt / sub as f64;
    let energy = |w: [f64; 3]| (0..3).map(|i| inertia[i] * w[i] * w[i]).sum::<f64>();
    let e0 = energy(wb);
    let mut t = Track::default();
    for _ in 0..frames {
        t.positions.push(x);
        t.rotations.push(q);
        for _ in 0..sub {
            let l = [inertia[0] * wb[0], inertia[1] * wb[1], inertia[2] * wb[2]];
            let cross = [
                wb[1] * l[2] - wb[2] * l[1],
                wb[2] * l[0] - wb[0] * l[2],
                wb[0] * l[1] - wb[1] * l[0],
            ];
            for i in 0..3 {
                wb[i] -= h * cross[i] / inertia[i];
            }
            // Explicit Euler gains energy and, at large steps, blows up to NaN; torque-free
            // motion keeps its kinetic energy, so put it back.
            let e = energy(wb);
            if e > 0.0 {
                wb = wb.map(|c| c * (e0 / e).sqrt());
            }
            q = normalise(quat_mul(q, quat_exp(wb.map(|c| c * h))));
        }
        for i in 0..3 {
            x[i] += v[i] * dt;
        }
    }
    t
}

/// Adversarial: smooth motion with teleports, random quaternion sign flips and (sometimes) huge
/// coordinates where f64 spacing is coarse.
pub fn teleporting(rng: &mut Rng, frames: usize, dt: f64) -> Track {
    let offset = if rng.range(0.0, 1.0) < 0.3 { 1e9 } else { 0.0 };
    let mut t = spinning(rng, frames, dt);
    let mut shift = [0.0; 3];
    for i in 0..frames {
        if rng.range(0.0, 1.0) < 0.02 {
            shift = rng.vec3(-100.0, 100.0);
        }
        t.positions[i] = std::array::from_fn(|k| t.positions[i][k] + shift[k] + offset);
        if rng.range(0.0, 1.0) < 0.3 {
            t.rotations[i] = t.rotations[i].map(|c| -c);
        }
        if rng.range(0.0, 1.0) < 0.01 {
            t.rotations[i] = random_orientation(rng);
        }
    }
    t
}

pub const KINDS: usize = 6;

/// Track number `kind` of the generators above.
pub fn generate(kind: usize, seed: u64, frames: usize, dt: f64) -> Track {
    let mut rng = Rng::new(seed);
    match kind % KINDS {
        0 => {
            let jitter = if seed.is_multiple_of(2) { 0.0 } else { 2e-6 };
            ballistic(&mut rng, frames, dt, jitter)
        }
        1 => random_walk(&mut rng, frames),
        2 => resting(&mut rng, frames),
        3 => spinning(&mut rng, frames, dt),
        4 => precessing(&mut rng, frames, dt),
        _ => teleporting(&mut rng, frames, dt),
    }
}

/// A body spinning in free flight with principal moments `inertia` (body axes), its orientation
/// from Euler's equations `I·ω̇ = (I·ω) × ω` in the body frame and `q̇ = ½·q ⊗ ω`, integrated by
/// classical RK4 with 64 steps per frame — the continuous motion, independent of the codec's and
/// the simulator's discrete integrators. `kicks`: frames at which an impact adds a random change
/// of the angular velocity of up to `kick` rad/s (a contact), and `damping`: angular damping
/// coefficient (1/s). Positions follow a parabola under `G`.
pub fn torque_free(
    rng: &mut Rng,
    inertia: [f64; 3],
    frames: usize,
    dt: f64,
    kicks: &[usize],
    kick: f64,
    damping: f64,
) -> Track {
    let mut q = normalise([rng.normal(), rng.normal(), rng.normal(), rng.normal()]);
    let mut wb = rng.vec3(-12.0, 12.0);
    let x0 = rng.vec3(-2.0, 2.0);
    let v0 = rng.vec3(-3.0, 3.0);
    let deriv = |q: [f64; 4], w: [f64; 3]| -> ([f64; 4], [f64; 3]) {
        let l = [inertia[0] * w[0], inertia[1] * w[1], inertia[2] * w[2]];
        let c = [
            l[1] * w[2] - l[2] * w[1],
            l[2] * w[0] - l[0] * w[2],
            l[0] * w[1] - l[1] * w[0],
        ];
        let dw = [
            c[0] / inertia[0] - damping * w[0],
            c[1] / inertia[1] - damping * w[1],
            c[2] / inertia[2] - damping * w[2],
        ];
        let dq = quat_mul(q, [w[0], w[1], w[2], 0.0]).map(|v| 0.5 * v);
        (dq, dw)
    };
    let steps = 64;
    let h = dt / steps as f64;
    let mut track = Track::default();
    for f in 0..frames {
        let t = f as f64 * dt;
        track.positions.push(std::array::from_fn(|i| {
            x0[i] + v0[i] * t + 0.5 * G[i] * t * t
        }));
        track.rotations.push(q);
        if kicks.contains(&f) {
            let k = rng.vec3(-kick, kick);
            wb = std::array::from_fn(|i| wb[i] + k[i]);
        }
        for _ in 0..steps {
            let add4 = |a: [f64; 4], b: [f64; 4], s: f64| -> [f64; 4] {
                std::array::from_fn(|i| a[i] + s * b[i])
            };
            let add3 = |a: [f64; 3], b: [f64; 3], s: f64| -> [f64; 3] {
                std::array::from_fn(|i| a[i] + s * b[i])
            };
            let (k1q, k1w) = deriv(q, wb);
            let (k2q, k2w) = deriv(add4(q, k1q, h / 2.0), add3(wb, k1w, h / 2.0));
            let (k3q, k3w) = deriv(add4(q, k2q, h / 2.0), add3(wb, k2w, h / 2.0));
            let (k4q, k4w) = deriv(add4(q, k3q, h), add3(wb, k3w, h));
            q = normalise(std::array::from_fn(|i| {
                q[i] + h / 6.0 * (k1q[i] + 2.0 * k2q[i] + 2.0 * k3q[i] + k4q[i])
            }));
            wb = std::array::from_fn(|i| {
                wb[i] + h / 6.0 * (k1w[i] + 2.0 * k2w[i] + 2.0 * k3w[i] + k4w[i])
            });
        }
    }
    track
}
