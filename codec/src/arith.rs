//! The entropy code: a binary adaptive range coder (the LZMA coder: 32-bit range, carry
//! propagation through a cached byte) with context-modelled binarisations of every integer.
//!
//! Rice codes (§4.3 names them) spend at least one bit on every value and every segment type; in
//! contact phases most residuals are 0 or ±1 and most types repeat the previous one, so a coder
//! that spends a fraction of a bit on a likely symbol codes the same residuals in fewer bits.
//!
//! * **Bits** ([`Bit`]) carry the probability of a 0 in 1/65536, adapted after every use with a
//!   rate that starts at 1/2 and settles at 1/2^[`RATE_LIMIT`] (fast learning for the few hundred
//!   symbols of one object's ~1 s track, then a moving average).
//! * **Values** ([`ValueModel`]): `m = v + 1` is written as the bit length of `m` in unary (each
//!   unary position its own context, counted from the magnitude of the stream's recent values as
//!   the [`AdaptiveRice`] rule tracks it: few contexts, learnt within a ~1 s track),
//!   then the two bits below the leading one with contexts, then the rest as equiprobable bits.
//! * **Types** ([`TypeModel`]): "same as the previous type" (a context per previous type), else
//!   the rank among the others as three tree-coded bits.
//!
//! Robustness: the decoder reads zeros past the end of its bytes, up to [`OVERRUN_LIMIT`] of them,
//! then fails; no probability reaches 0 or 1, so every decoded symbol consumes some of the input
//! and a hostile stream ends in an error after a number of symbols proportional to its length.

use std::sync::LazyLock;

use crate::bits::{AdaptiveRice, RICE_ESCAPE};
use crate::error::CodecError;

/// Probabilities are of a 0 bit, in units of 2⁻¹⁶.
const PROB_BITS: u32 = 16;
const PROB_ONE: i32 = 1 << PROB_BITS;
/// Slowest adaptation rate (as a shift).
const RATE_LIMIT: u8 = 5;
/// Zero bytes the decoder may read past its input (the encoder drops at most this many trailing
/// zero bytes).
pub(crate) const OVERRUN_LIMIT: usize = 8;
const TOP: u32 = 1 << 24;

/// Costs are in 1/256 bit.
pub(crate) const COST_SCALE: u64 = 256;

/// `-log₂(p / 2¹⁶) · 256` for `p = i · 16 + 8`, `i < 4096`.
static COST: LazyLock<[u32; 4096]> = LazyLock::new(|| {
    let mut t = [0u32; 4096];
    for (i, c) in t.iter_mut().enumerate() {
        let p = (i as f64 * 16.0 + 8.0) / 65536.0;
        *c = (-p.log2() * COST_SCALE as f64).round() as u32;
    }
    t
});

/// One adaptive binary context.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Bit {
    /// Probability of a 0, in 1/65536 (never 0 or 65536).
    p: u16,
    /// Adaptation shift for the next update (grows to `RATE_LIMIT`).
    rate: u8,
}

impl Default for Bit {
    fn default() -> Self {
        Self {
            p: 1 << (PROB_BITS - 1),
            rate: 1,
        }
    }
}

impl Bit {
    /// A context whose probability of a 0 starts at `p0 / 65536`, adapting first at rate
    /// `2^-rate` (a prior worth about `2^(rate−1)` observations).
    const fn with(p0: u16, rate: u8) -> Self {
        Self { p: p0, rate }
    }

    fn update(&mut self, bit: bool) {
        let p = i32::from(self.p);
        let target = if bit { 0 } else { PROB_ONE };
        let p = p + ((target - p) >> self.rate);
        // Keep both outcomes possible: every symbol costs the decoder some input.
        self.p = p.clamp(32, PROB_ONE - 32) as u16;
        if self.rate < RATE_LIMIT {
            self.rate += 1;
        }
    }

    /// Cost of `bit` in 1/256 bit.
    pub(crate) fn cost(&self, bit: bool) -> u64 {
        let p0 = u32::from(self.p);
        let p = if bit { (1 << PROB_BITS) - p0 } else { p0 };
        u64::from(COST[(p >> 4) as usize])
    }
}

/// The encoding half.
#[derive(Debug, Clone)]
pub(crate) struct RangeEncoder {
    low: u64,
    range: u32,
    cache: u8,
    cache_size: u64,
    out: Vec<u8>,
    /// Whether the first (always zero) byte has been dropped.
    first: bool,
}

impl Default for RangeEncoder {
    fn default() -> Self {
        Self {
            low: 0,
            range: u32::MAX,
            cache: 0,
            cache_size: 1,
            out: Vec::new(),
            first: true,
        }
    }
}

impl RangeEncoder {
    fn shift_low(&mut self) {
        if (self.low as u32) < 0xFF00_0000 || (self.low >> 32) != 0 {
            let carry = (self.low >> 32) as u8;
            let mut temp = self.cache;
            loop {
                let byte = temp.wrapping_add(carry);
                // The coder's first byte is always 0 (the interval starts inside [0, 2³²)).
                if self.first {
                    self.first = false;
                } else {
                    self.out.push(byte);
                }
                temp = 0xFF;
                self.cache_size -= 1;
                if self.cache_size == 0 {
                    break;
                }
            }
            self.cache = (self.low >> 24) as u8;
        }
        self.cache_size += 1;
        self.low = (self.low & 0x00FF_FFFF) << 8;
    }

    fn normalise(&mut self) {
        while self.range < TOP {
            self.range <<= 8;
            self.shift_low();
        }
    }

    pub(crate) fn bit(&mut self, ctx: &mut Bit, bit: bool) {
        let bound = (self.range >> PROB_BITS) * u32::from(ctx.p);
        if bit {
            self.low += u64::from(bound);
            self.range -= bound;
        } else {
            self.range = bound;
        }
        ctx.update(bit);
        self.normalise();
    }

    /// The low `n` bits of `v` (n ≤ 64), most significant first, each with probability ½.
    pub(crate) fn direct(&mut self, v: u64, n: u32) {
        for i in (0..n).rev() {
            self.range >>= 1;
            if (v >> i) & 1 != 0 {
                self.low += u64::from(self.range);
            }
            self.normalise();
        }
    }

    /// The bytes: the final interval's value with the most trailing zero bits, trailing zero
    /// bytes dropped (at most `OVERRUN_LIMIT`; the decoder reads zeros past the end).
    pub(crate) fn finish(mut self) -> Vec<u8> {
        // The value in [low, low + range) with the most trailing zeros.
        let hi = self.low + u64::from(self.range) - 1;
        let mut mask = u64::MAX >> 1;
        while mask != 0 {
            let v = (self.low + mask) & !mask;
            if v >= self.low && v <= hi {
                self.low = v;
                break;
            }
            mask >>= 1;
        }
        for _ in 0..5 {
            self.shift_low();
        }
        let mut dropped = 0;
        while dropped < OVERRUN_LIMIT && self.out.last() == Some(&0) {
            self.out.pop();
            dropped += 1;
        }
        self.out
    }
}

/// The decoding half.
#[derive(Debug, Clone)]
pub(crate) struct RangeDecoder<'a> {
    data: &'a [u8],
    at: usize,
    range: u32,
    code: u32,
}

impl<'a> RangeDecoder<'a> {
    pub(crate) fn new(data: &'a [u8]) -> Result<Self, CodecError> {
        let mut d = Self {
            data,
            at: 0,
            range: u32::MAX,
            code: 0,
        };
        for _ in 0..4 {
            d.code = (d.code << 8) | u32::from(d.byte()?);
        }
        // An encoder's code is always below the range (u32::MAX); this one is not.
        if d.code == u32::MAX {
            return Err(CodecError::Corrupt {
                what: "range coder start value",
            });
        }
        Ok(d)
    }

    fn byte(&mut self) -> Result<u8, CodecError> {
        let b = self.data.get(self.at).copied();
        self.at += 1;
        match b {
            Some(b) => Ok(b),
            None if self.at <= self.data.len() + OVERRUN_LIMIT => Ok(0),
            None => Err(CodecError::Truncated {
                at_bit: self.data.len() as u64 * 8,
                needed_bits: 8,
            }),
        }
    }

    fn normalise(&mut self) -> Result<(), CodecError> {
        while self.range < TOP {
            self.range <<= 8;
            self.code = (self.code << 8) | u32::from(self.byte()?);
        }
        Ok(())
    }

    pub(crate) fn bit(&mut self, ctx: &mut Bit) -> Result<bool, CodecError> {
        let bound = (self.range >> PROB_BITS) * u32::from(ctx.p);
        let bit = if self.code < bound {
            self.range = bound;
            false
        } else {
            self.code -= bound;
            self.range -= bound;
            true
        };
        ctx.update(bit);
        self.normalise()?;
        Ok(bit)
    }

    pub(crate) fn direct(&mut self, n: u32) -> Result<u64, CodecError> {
        let mut v = 0u64;
        for _ in 0..n {
            self.range >>= 1;
            let bit = self.code >= self.range;
            if bit {
                self.code -= self.range;
            }
            v = (v << 1) | u64::from(bit);
            self.normalise()?;
        }
        Ok(v)
    }
}

/// A Rice code with parameter `k` (escape after [`RICE_ESCAPE`] ones, see `bits::rice_len`) as
/// equiprobable bits: the start values, three per object, are too few to adapt to (the header
/// holds their parameter).
pub(crate) fn encode_rice_direct(e: &mut RangeEncoder, v: u64, k: u32) {
    let q = v >> k;
    if q < RICE_ESCAPE {
        e.direct(u64::MAX, q as u32);
        e.direct(0, 1);
        e.direct(v, k);
    } else {
        let n = 64 - v.leading_zeros();
        e.direct(u64::MAX, RICE_ESCAPE as u32);
        e.direct(u64::from(n - 1), 6);
        e.direct(v, n - 1);
    }
}

pub(crate) fn decode_rice_direct(d: &mut RangeDecoder<'_>, k: u32) -> Result<u64, CodecError> {
    let mut q = 0u64;
    while q < RICE_ESCAPE && d.direct(1)? == 1 {
        q += 1;
    }
    if q == RICE_ESCAPE {
        let n = d.direct(6)? as u32 + 1;
        let low = d.direct(n - 1)?;
        return Ok((1u64 << (n - 1)) | low);
    }
    // k ≤ 60 and q < 16: cannot overflow.
    Ok((q << k) | d.direct(k)?)
}

/// Unary positions with their own contexts (longer prefixes share the last).
const PREFIX_CTX: usize = 20;
/// Magnitude classes: Rice parameter 0, and the others.
const MAGNITUDE_CTX: usize = 2;
/// Unary contexts are by position relative to the Rice parameter `k` (the bit length of values
/// scales with it, the shape of its distribution much less): `j − k + REL_OFF`, clamped.
const REL_CTX: usize = 8;
const REL_OFF: i64 = 3;

/// Where the unary bits start: before the Rice parameter a value's bit length likely goes on,
/// after it likely stops.
const PREFIX_INIT: [Bit; REL_CTX] = {
    let p = [9830u16, 9830, 13107, 29491, 39321, 42598, 42598, 42598];
    let mut t = [Bit::with(0, 0); REL_CTX];
    let mut i = 0;
    while i < REL_CTX {
        t[i] = Bit::with(p[i], PRIOR_RATE);
        i += 1;
    }
    t
};
const PRIOR_RATE: u8 = 2;

fn rel(k: u32, j: u32) -> usize {
    (i64::from(j) - i64::from(k) + REL_OFF).clamp(0, REL_CTX as i64 - 1) as usize
}
/// Longest unary prefix: the bit length of `v + 1` is at most 65.
const MAX_PREFIX: u32 = 64;

/// The model of one integer stream.
#[derive(Debug, Clone)]
pub(crate) struct ValueModel {
    magnitude: AdaptiveRice,
    prefix: [[Bit; REL_CTX]; MAGNITUDE_CTX],
    /// Per bit length: the first mantissa bit, then the second given the first.
    mantissa: [[Bit; 3]; PREFIX_CTX],
}

impl ValueModel {
    pub(crate) fn new(prior: u64) -> Self {
        Self {
            magnitude: AdaptiveRice::new(prior),
            prefix: [PREFIX_INIT; MAGNITUDE_CTX],
            mantissa: [[Bit::default(); 3]; PREFIX_CTX],
        }
    }

    fn class(&self) -> (u32, usize) {
        let k = self.magnitude.k();
        (k, (k as usize).min(MAGNITUDE_CTX - 1))
    }

    /// `(bit length − 1 of v + 1, v + 1)`.
    fn split(v: u64) -> (u32, u128) {
        let m = u128::from(v) + 1;
        (127 - m.leading_zeros(), m)
    }

    pub(crate) fn encode(&mut self, e: &mut RangeEncoder, v: u64) {
        let (n, m) = Self::split(v);
        let (k, class) = self.class();
        let ctx = &mut self.prefix[class];
        for j in 0..n {
            e.bit(&mut ctx[rel(k, j)], true);
        }
        if n < MAX_PREFIX {
            e.bit(&mut ctx[rel(k, n)], false);
        }
        if n > 0 {
            let mc = &mut self.mantissa[(n as usize).min(PREFIX_CTX - 1)];
            let b1 = (m >> (n - 1)) & 1 != 0;
            e.bit(&mut mc[0], b1);
            if n > 1 {
                let b2 = (m >> (n - 2)) & 1 != 0;
                e.bit(&mut mc[1 + usize::from(b1)], b2);
                if n > 2 {
                    e.direct(m as u64, n - 2);
                }
            }
        }
        self.magnitude.update(v);
    }

    /// Cost of `v` now, in 1/256 bit.
    pub(crate) fn cost(&self, v: u64) -> u64 {
        let (n, m) = Self::split(v);
        let (k, class) = self.class();
        let ctx = &self.prefix[class];
        let mut c = 0;
        for j in 0..n {
            c += ctx[rel(k, j)].cost(true);
        }
        if n < MAX_PREFIX {
            c += ctx[rel(k, n)].cost(false);
        }
        if n > 0 {
            let mc = &self.mantissa[(n as usize).min(PREFIX_CTX - 1)];
            let b1 = (m >> (n - 1)) & 1 != 0;
            c += mc[0].cost(b1);
            if n > 1 {
                let b2 = (m >> (n - 2)) & 1 != 0;
                c += mc[1 + usize::from(b1)].cost(b2);
                c += u64::from(n - 2) * COST_SCALE;
            }
        }
        c
    }

    pub(crate) fn decode(&mut self, d: &mut RangeDecoder<'_>) -> Result<u64, CodecError> {
        let (k, class) = self.class();
        let ctx = &mut self.prefix[class];
        let mut n = 0u32;
        while n < MAX_PREFIX && d.bit(&mut ctx[rel(k, n)])? {
            n += 1;
        }
        let mut m: u128 = 1;
        if n > 0 {
            let mc = &mut self.mantissa[(n as usize).min(PREFIX_CTX - 1)];
            let b1 = d.bit(&mut mc[0])?;
            m = (m << 1) | u128::from(b1);
            if n > 1 {
                let b2 = d.bit(&mut mc[1 + usize::from(b1)])?;
                m = (m << 1) | u128::from(b2);
                if n > 2 {
                    m = (m << (n - 2)) | u128::from(d.direct(n - 2)?);
                }
            }
        }
        let v = u64::try_from(m - 1).map_err(|_| CodecError::Corrupt {
            what: "value above 2^64 − 1",
        })?;
        self.magnitude.update(v);
        Ok(v)
    }
}

/// Segment types: up to 8 types.
pub(crate) const MAX_TYPES: usize = 8;

/// The model of one segment-type sequence.
#[derive(Debug, Clone, Default)]
pub(crate) struct TypeModel {
    same: [Bit; MAX_TYPES],
    other: [[Bit; 8]; MAX_TYPES],
}

impl TypeModel {
    fn other(prev: usize, rank: usize) -> usize {
        if rank < prev { rank } else { rank - 1 }
    }

    pub(crate) fn encode(&mut self, e: &mut RangeEncoder, prev: usize, rank: usize) {
        e.bit(&mut self.same[prev], rank != prev);
        if rank != prev {
            let o = Self::other(prev, rank);
            let tree = &mut self.other[prev];
            let mut node = 1;
            for i in (0..3).rev() {
                let b = (o >> i) & 1 != 0;
                e.bit(&mut tree[node], b);
                node = 2 * node + usize::from(b);
            }
        }
    }

    pub(crate) fn cost(&self, prev: usize, rank: usize) -> u64 {
        let mut c = self.same[prev].cost(rank != prev);
        if rank != prev {
            let o = Self::other(prev, rank);
            let tree = &self.other[prev];
            let mut node = 1;
            for i in (0..3).rev() {
                let b = (o >> i) & 1 != 0;
                c += tree[node].cost(b);
                node = 2 * node + usize::from(b);
            }
        }
        c
    }

    /// The rank after `prev` among `n ≤ MAX_TYPES` types.
    pub(crate) fn decode(
        &mut self,
        d: &mut RangeDecoder<'_>,
        n: usize,
        prev: usize,
    ) -> Result<usize, CodecError> {
        if !d.bit(&mut self.same[prev])? {
            return Ok(prev);
        }
        let tree = &mut self.other[prev];
        let mut node = 1;
        for _ in 0..3 {
            node = 2 * node + usize::from(d.bit(&mut tree[node])?);
        }
        let o = node - 8;
        let rank = if o < prev { o } else { o + 1 };
        if rank < n {
            Ok(rank)
        } else {
            Err(CodecError::Corrupt {
                what: "segment type out of range",
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lcg(seed: &mut u64) -> u64 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        *seed >> 33
    }

    #[test]
    fn values_bits_and_types_roundtrip() {
        let mut seed = 5u64;
        let mut values = Vec::new();
        for i in 0..5000u64 {
            let r = lcg(&mut seed);
            values.push(match i % 7 {
                0 => r % 3,
                1 => r % 1000,
                2 => 0,
                3 => u64::MAX - r % 3,
                4 => 1 << (r % 64),
                _ => r % 5,
            });
        }
        let mut e = RangeEncoder::default();
        let mut vm = ValueModel::new(3);
        let mut tm = TypeModel::default();
        let mut ctx = Bit::default();
        let mut prev = 0;
        let mut cost = 0;
        for (i, &v) in values.iter().enumerate() {
            cost += vm.cost(v);
            vm.encode(&mut e, v);
            let rank = (v % 6) as usize;
            tm.encode(&mut e, prev, rank);
            prev = rank;
            e.bit(&mut ctx, i % 3 == 0);
            e.direct(v, (i % 65) as u32);
        }
        let bytes = e.finish();
        let mut d = RangeDecoder::new(&bytes).unwrap();
        let mut vm = ValueModel::new(3);
        let mut tm = TypeModel::default();
        let mut ctx = Bit::default();
        let mut prev = 0;
        for (i, &v) in values.iter().enumerate() {
            assert_eq!(vm.decode(&mut d).unwrap(), v, "value {i}");
            let rank = tm.decode(&mut d, 6, prev).unwrap();
            assert_eq!(rank, (v % 6) as usize);
            prev = rank;
            assert_eq!(d.bit(&mut ctx).unwrap(), i % 3 == 0);
            let n = (i % 65) as u32;
            let mask = if n == 64 { u64::MAX } else { (1 << n) - 1 };
            assert_eq!(d.direct(n).unwrap(), v & mask);
        }
        assert!(cost > 0);
    }

    /// Start values: every value, escapes included, reads back, in the bits `rice_len` counts.
    #[test]
    fn direct_rice_codes_roundtrip_in_their_length() {
        let values = [0u64, 1, 2, 7, 100, 1 << 20, u64::MAX, (1 << 40) + 3];
        for k in [0u32, 1, 5, 13, 60] {
            let mut e = RangeEncoder::default();
            let mut bits = 0;
            for &v in &values {
                encode_rice_direct(&mut e, v, k);
                bits += crate::bits::rice_len(v, k);
            }
            let bytes = e.finish();
            // Equiprobable bits cost one bit each (plus the coder's flush).
            assert!((bytes.len() as u64 * 8).abs_diff(bits) <= 40, "k = {k}");
            let mut d = RangeDecoder::new(&bytes).unwrap();
            for &v in &values {
                assert_eq!(decode_rice_direct(&mut d, k).unwrap(), v, "k = {k}");
            }
        }
    }

    #[test]
    fn short_streams_roundtrip_and_likely_symbols_cost_little() {
        for n in 0..40usize {
            let mut e = RangeEncoder::default();
            let mut ctx = Bit::default();
            for i in 0..n {
                e.bit(&mut ctx, i % 11 == 10);
            }
            let bytes = e.finish();
            assert!(bytes.len() <= 1 + n / 8, "{n}: {}", bytes.len());
            let mut d = RangeDecoder::new(&bytes).unwrap();
            let mut ctx = Bit::default();
            for i in 0..n {
                assert_eq!(d.bit(&mut ctx).unwrap(), i % 11 == 10);
            }
        }
    }

    #[test]
    fn hostile_bytes_end_in_errors() {
        let mut seed = 9u64;
        for len in 0..64 {
            let bytes: Vec<u8> = (0..len).map(|_| lcg(&mut seed) as u8).collect();
            let Ok(mut d) = RangeDecoder::new(&bytes) else {
                continue;
            };
            let mut vm = ValueModel::new(0);
            let mut n = 0u64;
            while vm.decode(&mut d).is_ok() {
                n += 1;
                assert!(n < 10_000_000);
            }
        }
    }
}
