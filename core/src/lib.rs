//! Pure domain logic of manyworlds: no I/O, no async.
//!
//! * [`scene`] — the TOML scene format, distributions, generators, validation, instantiation.
//! * [`rng`] — counter-based seeds and deterministic random streams.
//! * [`perturb`] — §4.1.2 impact detection and perturbation sampling.
//! * [`frames`] — the interim quantised-frames motion payload.
//! * [`keys`] — bus key expressions.
//! * [`browse`] — §4.4 browsing: screen-box frusta, constraints, path index, bitsets, metrics.

pub mod browse;
pub mod frames;
pub mod keys;
pub mod perturb;
pub mod rng;
pub mod scene;

/// A stable 64-bit hash of a scene's source text (the `content_hash` of a `Scene` message).
pub fn content_hash(text: &str) -> u64 {
    rng::hash_str(text)
}
