//! Integer codes: zig-zag mapping, the Golomb–Rice code of start values (§4.3: "the resulting
//! residuals are stored using … Rice codes, which use fewer bits for smaller numbers"), the
//! adaptive Rice parameter that steers the range coder's value models, and the LEB128 varints of
//! the header and index.
//!
//! [`AdaptiveRice`] follows the rule of LOCO-I / JPEG-LS — the smallest `k` with `n·2ᵏ ≥ Σ|v|`
//! over a decaying window — so that a stream that changes character half-way (flight, then rest)
//! is modelled by a parameter that follows it, and nothing about it is stored.

use crate::error::CodecError;

/// Maps signed to unsigned so that small magnitudes get small codes: 0,−1,1,−2,… → 0,1,2,3,…
pub(crate) fn zigzag(v: i64) -> u64 {
    ((v << 1) ^ (v >> 63)) as u64
}

pub(crate) fn unzigzag(u: u64) -> i64 {
    ((u >> 1) as i64) ^ -((u & 1) as i64)
}

/// A unary quotient this long is an escape, followed by the value's bit length − 1 (6 bits) and
/// the value without its leading one. Caps a code word at 16 + 6 + 63 bits.
pub(crate) const RICE_ESCAPE: u64 = 16;

/// Length in bits of `v` Rice-coded with parameter `k` (`arith::encode_rice_direct`).
pub(crate) fn rice_len(v: u64, k: u32) -> u64 {
    let q = v >> k;
    if q < RICE_ESCAPE {
        q + 1 + u64::from(k)
    } else {
        RICE_ESCAPE + 6 + u64::from(63 - v.leading_zeros())
    }
}

/// The parameter `≤ max_k` that codes `values` in the fewest bits.
pub(crate) fn best_rice_k(values: &[u64], max_k: u32) -> u32 {
    (0..=max_k)
        .min_by_key(|&k| values.iter().map(|&v| rice_len(v, k)).sum::<u64>())
        .unwrap_or(0)
}

/// Largest parameter [`AdaptiveRice`] picks.
const ADAPTIVE_MAX_K: u32 = 48;
/// The running sums are halved once this many values have been seen, so that the parameter
/// follows the recent values rather than the whole stream.
const ADAPTIVE_WINDOW: u32 = 4;
/// One value's contribution to the running sum is capped (an outlier must not dominate the
/// parameter for the rest of the window).
const ADAPTIVE_CAP: u64 = 1 << 40;

/// The adaptive Rice parameter of one stream. Encoder and decoder update it with the same
/// integers, so they always agree on `k`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct AdaptiveRice {
    sum: u64,
    count: u32,
    /// The parameter for the next value (kept current by `update`).
    k: u32,
}

/// The smallest `k ≤ ADAPTIVE_MAX_K` with `count·2ᵏ ≥ sum`, i.e. `⌈log₂ ⌈sum / count⌉⌉`.
const fn rice_parameter(sum: u64, count: u32) -> u32 {
    let mean = sum.div_ceil(count as u64);
    let k = if mean <= 1 {
        0
    } else {
        64 - (mean - 1).leading_zeros()
    };
    if k < ADAPTIVE_MAX_K {
        k
    } else {
        ADAPTIVE_MAX_K
    }
}

impl AdaptiveRice {
    /// A stream whose values are expected to be around `mean` (a prior worth one value).
    pub(crate) const fn new(mean: u64) -> Self {
        Self {
            sum: mean,
            count: 1,
            k: rice_parameter(mean, 1),
        }
    }

    pub(crate) fn k(&self) -> u32 {
        self.k
    }

    pub(crate) fn update(&mut self, v: u64) {
        self.sum += v.min(ADAPTIVE_CAP);
        self.count += 1;
        if self.count >= ADAPTIVE_WINDOW {
            self.sum = self.sum.div_ceil(2);
            self.count /= 2;
        }
        self.k = rice_parameter(self.sum, self.count);
    }
}

/// Unsigned LEB128, the byte-aligned integers of the header and index.
pub(crate) fn write_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

/// Reads a LEB128 integer at `*at`, advancing it; at most 10 bytes, no overflow.
pub(crate) fn read_varint(bytes: &[u8], at: &mut usize) -> Result<u64, CodecError> {
    let mut v = 0u64;
    for i in 0..10 {
        let Some(&b) = bytes.get(*at) else {
            return Err(CodecError::Truncated {
                at_bit: *at as u64 * 8,
                needed_bits: 8,
            });
        };
        *at += 1;
        let low = u64::from(b & 0x7F);
        if i == 9 && low > 1 {
            break;
        }
        v |= low << (7 * i);
        if b & 0x80 == 0 {
            return Ok(v);
        }
    }
    Err(CodecError::Corrupt {
        what: "varint longer than 64 bits",
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zigzag_roundtrip_extremes() {
        for v in [
            0,
            1,
            -1,
            2,
            -2,
            i64::MAX,
            i64::MIN,
            123_456_789,
            -987_654_321,
        ] {
            assert_eq!(unzigzag(zigzag(v)), v);
        }
        assert_eq!(zigzag(0), 0);
        assert_eq!(zigzag(-1), 1);
        assert_eq!(zigzag(1), 2);
    }

    #[test]
    fn best_k_is_the_exact_minimum() {
        let values: Vec<u64> = (0..200).map(|i| (i * 37 % 1000) as u64).collect();
        let k = best_rice_k(&values, 60);
        let cost = |k| values.iter().map(|&v| rice_len(v, k)).sum::<u64>();
        for other in 0..=60 {
            assert!(cost(k) <= cost(other));
        }
        // Small values want a small parameter, large ones a large one.
        assert_eq!(best_rice_k(&[0, 1, 0, 1], 60), 0);
        assert!(best_rice_k(&[1 << 30, 3 << 29], 60) >= 28);
    }

    #[test]
    fn adaptive_rice_follows_the_values() {
        let mut s = AdaptiveRice::new(4);
        assert_eq!(s.k(), 2);
        for v in 0..100 {
            s.update(v % 2);
        }
        assert_eq!(s.k(), 0, "small values: k = 0");
        for i in 0..100 {
            s.update(u64::MAX - i);
        }
        // Each value counts at most 2⁴⁰: the mean settles there.
        assert_eq!(s.k(), 40, "k follows large values up to the cap");
        for _ in 0..100 {
            s.update(1000);
        }
        assert_eq!(s.k(), 10, "and back down: 2¹⁰ ≥ 1000 > 2⁹");
    }

    #[test]
    fn the_rice_parameter_is_the_smallest_that_covers_the_mean() {
        for count in 1..=4u32 {
            for sum in 0..5000u64 {
                let slow = (0..ADAPTIVE_MAX_K)
                    .find(|&k| (u64::from(count) << k) >= sum)
                    .unwrap_or(ADAPTIVE_MAX_K);
                assert_eq!(rice_parameter(sum, count), slow, "{sum}/{count}");
            }
        }
        assert_eq!(rice_parameter(u64::MAX, 1), ADAPTIVE_MAX_K);
    }

    #[test]
    fn varints_roundtrip_and_refuse_overlong_input() {
        let mut out = Vec::new();
        for v in [0, 1, 127, 128, 300, u64::from(u32::MAX), u64::MAX] {
            write_varint(&mut out, v);
        }
        let mut at = 0;
        for v in [0, 1, 127, 128, 300, u64::from(u32::MAX), u64::MAX] {
            assert_eq!(read_varint(&out, &mut at).unwrap(), v);
        }
        assert_eq!(at, out.len());
        assert!(read_varint(&[0xFF; 11], &mut 0).is_err());
        assert!(read_varint(&[0x80], &mut 0).is_err());
    }
}
