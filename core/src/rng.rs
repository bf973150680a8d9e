//! Deterministic, counter-based randomness.
//!
//! A world is identified by `(job, seed)` and must be regenerable bit for bit from its seed
//! (DESIGN.md "World identity"). Everything random in a world — sampled scene parameters and the
//! §4.1.2 impact perturbations — is drawn from [`WorldRng`] streams derived from that seed, so the
//! output depends on nothing but the binary, the scene and the seed. We implement the generator
//! ourselves (SplitMix64) rather than depend on a crate whose stream could change between versions.

/// The SplitMix64 finaliser: a bijective 64-bit mixer with full avalanche.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

const GOLDEN: u64 = 0x9e37_79b9_7f4a_7c15;

/// FNV-1a over bytes, then mixed: a stable 64-bit hash of an identifier (job id, node id).
pub fn hash_str(s: &str) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in s.as_bytes() {
        h ^= u64::from(*b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    mix64(h)
}

/// The seed of the `counter`-th world a node samples for a job: a counter-based hash of
/// `(job, node, counter)`. For one `(job, node)` the map counter → seed is a bijection (so one
/// node never repeats a seed); across nodes a repeat needs a 64-bit collision, and the store
/// rejects a `(job, seed)` it already holds in any case.
pub fn world_seed(job: &str, node: &str, counter: u64) -> u64 {
    let key = mix64(hash_str(job) ^ hash_str(node).rotate_left(17));
    // key + counter·GOLDEN is injective in counter (GOLDEN is odd) and mix64 is a bijection.
    mix64(key.wrapping_add(counter.wrapping_mul(GOLDEN)))
}

/// Independent streams drawn from one world seed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stream {
    /// Sampling the scene's distributions (initial conditions, materials, …).
    Scene = 1,
    /// §4.1.2 perturbations at impacts.
    Perturbation = 2,
}

/// SplitMix64 generator on a `(seed, stream)` pair.
#[derive(Debug, Clone)]
pub struct WorldRng {
    state: u64,
}

impl WorldRng {
    pub fn new(seed: u64, stream: Stream) -> Self {
        Self {
            state: mix64(seed ^ mix64((stream as u64).wrapping_mul(GOLDEN))),
        }
    }

    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(GOLDEN);
        mix64(self.state)
    }

    /// Uniform in [0, 1) with 53 bits of precision.
    #[inline]
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in [a, b) (or [b, a) when b < a).
    #[inline]
    pub fn uniform(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * self.next_f64()
    }

    /// Normal(mu, sigma) by the Box–Muller transform (one draw per call; no hidden cache, so
    /// the stream position depends only on the number of calls).
    pub fn normal(&mut self, mu: f64, sigma: f64) -> f64 {
        // 1 - u lies in (0, 1], so the logarithm is finite.
        let u1 = 1.0 - self.next_f64();
        let u2 = self.next_f64();
        let r = (-2.0 * u1.ln()).sqrt();
        mu + sigma * r * (std::f64::consts::TAU * u2).cos()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashSet;

    #[test]
    fn seeds_never_repeat_within_a_node_and_rarely_across() {
        let mut seen = HashSet::new();
        for node in ["a", "b", "c", "node-17"] {
            for c in 0..20_000 {
                assert!(seen.insert(world_seed("job-1", node, c)), "{node} {c}");
            }
        }
    }

    #[test]
    fn seed_depends_on_job_node_and_counter() {
        let s = world_seed("j", "n", 3);
        assert_ne!(s, world_seed("j2", "n", 3));
        assert_ne!(s, world_seed("j", "n2", 3));
        assert_ne!(s, world_seed("j", "n", 4));
        assert_eq!(s, world_seed("j", "n", 3));
    }

    #[test]
    fn streams_are_independent_and_reproducible() {
        let mut a = WorldRng::new(42, Stream::Scene);
        let mut b = WorldRng::new(42, Stream::Perturbation);
        let mut a2 = WorldRng::new(42, Stream::Scene);
        let xa: Vec<u64> = (0..8).map(|_| a.next_u64()).collect();
        let xb: Vec<u64> = (0..8).map(|_| b.next_u64()).collect();
        let xa2: Vec<u64> = (0..8).map(|_| a2.next_u64()).collect();
        assert_eq!(xa, xa2);
        assert_ne!(xa, xb);
    }

    #[test]
    fn uniform_and_normal_moments() {
        let mut r = WorldRng::new(7, Stream::Scene);
        let n = 200_000;
        let (mut su, mut sn, mut sn2) = (0.0, 0.0, 0.0);
        for _ in 0..n {
            let u = r.uniform(2.0, 4.0);
            assert!((2.0..4.0).contains(&u));
            su += u;
            let x = r.normal(1.0, 0.5);
            sn += x;
            sn2 += x * x;
        }
        let n = n as f64;
        assert!((su / n - 3.0).abs() < 0.01);
        let mean = sn / n;
        let var = sn2 / n - mean * mean;
        assert!((mean - 1.0).abs() < 0.01, "{mean}");
        assert!((var.sqrt() - 0.5).abs() < 0.01, "{var}");
    }
}
