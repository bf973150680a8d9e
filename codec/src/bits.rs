//! Bit-level I/O and the entropy code: zig-zag mapping and Golomb–Rice codes (§4.3: "the resulting
//! residuals are stored using … Rice codes, which use fewer bits for smaller numbers").
//!
//! Format 1 chooses one Rice parameter per stream and object and stores it; format 2 adapts the
//! parameter as it goes ([`AdaptiveRice`], the rule of LOCO-I / JPEG-LS: the smallest `k` with
//! `n·2ᵏ ≥ Σ|v|` over a decaying window), so that nothing is stored and a stream that changes
//! character half-way (flight, then rest) is coded with a parameter that follows it.
//!
//! Bits are written most-significant first. Every read is bounds-checked against the slice, so a
//! hostile stream can only make a read fail, never panic or loop forever: each successful read
//! consumes at least one bit.

use crate::error::CodecError;

/// Largest Rice parameter a format-1 stream may declare (6 bits on the wire).
#[cfg(test)]
pub(crate) const MAX_RICE_K: u32 = 63;
/// Width of a Rice parameter on the wire.
pub(crate) const RICE_K_BITS: u32 = 6;
/// A unary quotient this long is an escape: the value follows as 64 raw bits. This caps the
/// length of any single code word at `RICE_ESCAPE + 64` bits, even for outliers (teleports).
pub(crate) const RICE_ESCAPE: u64 = 32;

/// Maps signed to unsigned so that small magnitudes get small codes: 0,−1,1,−2,… → 0,1,2,3,…
pub(crate) fn zigzag(v: i64) -> u64 {
    ((v << 1) ^ (v >> 63)) as u64
}

pub(crate) fn unzigzag(u: u64) -> i64 {
    ((u >> 1) as i64) ^ -((u & 1) as i64)
}

/// Length in bits of `v` Rice-coded with parameter `k` (format 1; this build only reads format 1,
/// the writing side is kept for the tests of the reader).
#[cfg(test)]
pub(crate) fn rice_len(v: u64, k: u32) -> u64 {
    let q = v >> k;
    if q < RICE_ESCAPE {
        q + 1 + u64::from(k)
    } else {
        RICE_ESCAPE + 64
    }
}

/// The Rice parameter that minimises the stream's exact coded size (a refinement of the usual
/// "log₂ of the mean" rule: with at most 64 candidates the exact optimum is cheap).
#[cfg(test)]
pub(crate) fn best_rice_k(values: &[u64]) -> u32 {
    if values.is_empty() {
        return 0;
    }
    // Beyond log2(max)+1 a larger k only adds bits, so the search range is small in practice.
    let max = values.iter().copied().max().unwrap_or(0);
    let upper = (64 - max.leading_zeros()).min(MAX_RICE_K);
    (0..=upper)
        .min_by_key(|&k| values.iter().map(|&v| rice_len(v, k)).sum::<u64>())
        .unwrap_or(0)
}

/// Format 2: a unary quotient this long is an escape, followed by the value's bit length − 1
/// (6 bits) and the value without its leading one. Caps a code word at 16 + 6 + 63 bits.
pub(crate) const RICE2_ESCAPE: u64 = 16;

/// Length in bits of `v` coded by `BitWriter::write_rice2` (the format-2 writer) with parameter `k`.
pub(crate) fn rice2_len(v: u64, k: u32) -> u64 {
    let q = v >> k;
    if q < RICE2_ESCAPE {
        q + 1 + u64::from(k)
    } else {
        RICE2_ESCAPE + 6 + u64::from(63 - v.leading_zeros())
    }
}

/// The parameter `≤ max_k` that codes `values` in the fewest bits with `BitWriter::write_rice2`.
pub(crate) fn best_rice2_k(values: &[u64], max_k: u32) -> u32 {
    (0..=max_k)
        .min_by_key(|&k| values.iter().map(|&v| rice2_len(v, k)).sum::<u64>())
        .unwrap_or(0)
}

/// Largest parameter [`AdaptiveRice`] picks (values above `2⁴⁸·16` take the escape).
const ADAPTIVE_MAX_K: u32 = 48;
/// The running sums are halved once this many values have been seen, so that the parameter
/// follows the recent values rather than the whole stream.
const ADAPTIVE_WINDOW: u32 = 4;
/// One value's contribution to the running sum is capped (an escape-sized outlier must not
/// dominate the parameter for the rest of the window).
const ADAPTIVE_CAP: u64 = 1 << 40;

/// The adaptive Rice parameter of one stream (format 2). Encoder and decoder update it with the
/// same integers, so they always agree on `k`.
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

    /// Bits `v` would take now.
    #[cfg(test)]
    pub(crate) fn cost(&self, v: u64) -> u64 {
        rice2_len(v, self.k())
    }
}

/// Format 2 segment types: "same type as before" costs one bit; another type costs one bit and
/// its rank among the `n − 1` others in truncated binary. Returns the code length for `rank`
/// after `prev` (both `< n`).
#[cfg(test)]
pub(crate) fn type_code_len(n: usize, prev: usize, rank: usize) -> u64 {
    if rank == prev {
        return 1;
    }
    let m = n - 1;
    let (k, u) = truncated_binary(m);
    let other = if rank < prev { rank } else { rank - 1 };
    1 + if other < u { k } else { k + 1 } as u64
}

/// `(k, u)` of the truncated binary code for `m ≥ 1` symbols: the first `u` symbols take `k`
/// bits, the others `k + 1`.
fn truncated_binary(m: usize) -> (u32, usize) {
    let k = usize::BITS - 1 - m.leading_zeros(); // ⌊log₂ m⌋
    let u = (1usize << (k + 1)) - m;
    (k, u)
}

/// Unsigned LEB128, the byte-aligned integers of the format-2 header and index.
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

/// The format-2 writer (this build writes format 3; kept for the tests of the reader).
#[cfg(test)]
#[derive(Default, Debug, Clone)]
pub(crate) struct BitWriter {
    bytes: Vec<u8>,
    acc: u128,
    nacc: u32,
}

#[cfg(test)]
impl BitWriter {
    pub(crate) fn new() -> Self {
        Self::default()
    }

    pub(crate) fn bit_len(&self) -> u64 {
        self.bytes.len() as u64 * 8 + u64::from(self.nacc)
    }

    /// Writes the low `n` bits of `v` (n ≤ 64), most significant first.
    pub(crate) fn write_bits(&mut self, v: u64, n: u32) {
        debug_assert!(n <= 64);
        if n == 0 {
            return;
        }
        let v = if n == 64 { v } else { v & ((1u64 << n) - 1) };
        self.acc = (self.acc << n) | u128::from(v);
        self.nacc += n;
        while self.nacc >= 8 {
            self.nacc -= 8;
            self.bytes.push((self.acc >> self.nacc) as u8);
        }
        self.acc &= (1u128 << self.nacc) - 1;
    }

    #[cfg(test)]
    pub(crate) fn write_bit(&mut self, b: bool) {
        self.write_bits(u64::from(b), 1);
    }

    /// Format-1 Rice code (tests only, see [`rice_len`]).
    #[cfg(test)]
    pub(crate) fn write_rice(&mut self, v: u64, k: u32) {
        let q = v >> k;
        if q < RICE_ESCAPE {
            // q ones then a zero, written in chunks of at most 64 bits.
            let ones = q as u32;
            self.write_bits(u64::MAX, ones);
            self.write_bits(0, 1);
            self.write_bits(v, k);
        } else {
            self.write_bits(u64::MAX, RICE_ESCAPE as u32);
            self.write_bits(v, 64);
        }
    }

    /// Format-2 Rice code (escape after [`RICE2_ESCAPE`] ones, see [`rice2_len`]).
    pub(crate) fn write_rice2(&mut self, v: u64, k: u32) {
        let q = v >> k;
        if q < RICE2_ESCAPE {
            self.write_bits(u64::MAX, q as u32);
            self.write_bits(0, 1);
            self.write_bits(v, k);
        } else {
            let n = 64 - v.leading_zeros();
            self.write_bits(u64::MAX, RICE2_ESCAPE as u32);
            self.write_bits(u64::from(n - 1), 6);
            self.write_bits(v, n - 1);
        }
    }

    /// Writes `v` with the stream's adaptive parameter, then updates it.
    pub(crate) fn write_adaptive(&mut self, v: u64, state: &mut AdaptiveRice) {
        self.write_rice2(v, state.k());
        state.update(v);
    }

    /// Writes segment type `rank` after type `prev` (see [`type_code_len`]).
    pub(crate) fn write_type(&mut self, n: usize, prev: usize, rank: usize) {
        if rank == prev {
            self.write_bits(0, 1);
            return;
        }
        self.write_bits(1, 1);
        let (k, u) = truncated_binary(n - 1);
        let other = if rank < prev { rank } else { rank - 1 };
        if other < u {
            self.write_bits(other as u64, k);
        } else {
            self.write_bits((other + u) as u64, k + 1);
        }
    }

    /// Elias-gamma code of `v + 1` (format 1's position-stream length; tests only).
    #[cfg(test)]
    pub(crate) fn write_gamma(&mut self, v: u64) {
        let v1 = v.saturating_add(1);
        let n = 64 - v1.leading_zeros();
        self.write_bits(0, n - 1);
        self.write_bits(v1, n);
    }

    #[cfg(test)]
    pub(crate) fn append(&mut self, other: &BitWriter) {
        for &b in &other.bytes {
            self.write_bits(u64::from(b), 8);
        }
        self.write_bits(other.acc as u64, other.nacc);
    }

    /// Pads the last byte with zero bits.
    pub(crate) fn into_bytes(mut self) -> Vec<u8> {
        if self.nacc > 0 {
            let pad = 8 - self.nacc;
            self.write_bits(0, pad);
        }
        self.bytes
    }
}

#[derive(Debug, Clone)]
pub(crate) struct BitReader<'a> {
    data: &'a [u8],
    pos: usize,
    end: usize,
}

impl<'a> BitReader<'a> {
    pub(crate) fn new(data: &'a [u8]) -> Self {
        Self {
            data,
            pos: 0,
            end: data.len().saturating_mul(8),
        }
    }

    pub(crate) fn pos(&self) -> usize {
        self.pos
    }

    pub(crate) fn end(&self) -> usize {
        self.end
    }

    /// A reader over the bit range `[start, end)` of the same data.
    pub(crate) fn sub(&self, start: usize, end: usize) -> Result<Self, CodecError> {
        if start > end || end > self.data.len().saturating_mul(8) {
            return Err(CodecError::Corrupt {
                what: "stream offset outside the object",
            });
        }
        Ok(Self {
            data: self.data,
            pos: start,
            end,
        })
    }

    pub(crate) fn read_bits(&mut self, n: u32) -> Result<u64, CodecError> {
        debug_assert!(n <= 64);
        if n == 0 {
            return Ok(0);
        }
        if self.end - self.pos < n as usize {
            return Err(CodecError::Truncated {
                at_bit: self.pos as u64,
                needed_bits: u64::from(n),
            });
        }
        let mut v = 0u64;
        let mut left = n;
        while left > 0 {
            let byte = u32::from(self.data[self.pos / 8]);
            let off = (self.pos % 8) as u32;
            let avail = 8 - off;
            let take = avail.min(left);
            let bits = (byte >> (avail - take)) & ((1u32 << take) - 1);
            v = (v << take) | u64::from(bits);
            self.pos += take as usize;
            left -= take;
        }
        Ok(v)
    }

    pub(crate) fn read_bit(&mut self) -> Result<bool, CodecError> {
        Ok(self.read_bits(1)? == 1)
    }

    pub(crate) fn read_rice(&mut self, k: u32) -> Result<u64, CodecError> {
        let mut q = 0u64;
        while q < RICE_ESCAPE && self.read_bit()? {
            q += 1;
        }
        if q == RICE_ESCAPE {
            return self.read_bits(64);
        }
        let low = self.read_bits(k)?;
        // k ≤ 63 and q < 32: a legal code never overflows; a forged one is rejected.
        q.checked_shl(k)
            .filter(|&hi| hi >> k == q)
            .map(|hi| hi | low)
            .ok_or(CodecError::Corrupt {
                what: "Rice code overflows 64 bits",
            })
    }

    pub(crate) fn read_rice2(&mut self, k: u32) -> Result<u64, CodecError> {
        let mut q = 0u64;
        while q < RICE2_ESCAPE && self.read_bit()? {
            q += 1;
        }
        if q == RICE2_ESCAPE {
            let n = self.read_bits(6)? as u32 + 1;
            let low = self.read_bits(n - 1)?;
            return Ok((1u64 << (n - 1)) | low);
        }
        let low = self.read_bits(k)?;
        // k ≤ 48 and q < 16: cannot overflow.
        Ok((q << k) | low)
    }

    pub(crate) fn read_adaptive(&mut self, state: &mut AdaptiveRice) -> Result<u64, CodecError> {
        let v = self.read_rice2(state.k())?;
        state.update(v);
        Ok(v)
    }

    /// Reads a segment type written by `BitWriter::write_type`; always `< n`.
    pub(crate) fn read_type(&mut self, n: usize, prev: usize) -> Result<usize, CodecError> {
        if !self.read_bit()? {
            return Ok(prev);
        }
        let (k, u) = truncated_binary(n - 1);
        let mut x = self.read_bits(k)? as usize;
        if x >= u {
            x = ((x << 1) | usize::from(self.read_bit()?)) - u;
        }
        Ok(if x < prev { x } else { x + 1 })
    }

    pub(crate) fn read_gamma(&mut self) -> Result<u64, CodecError> {
        let mut zeros = 0u32;
        while !self.read_bit()? {
            zeros += 1;
            if zeros > 63 {
                return Err(CodecError::Corrupt {
                    what: "Elias-gamma prefix longer than 63 bits",
                });
            }
        }
        let rest = self.read_bits(zeros)?;
        let v1 = (1u64 << zeros) | rest;
        Ok(v1 - 1)
    }
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
    fn rice_gamma_and_raw_bits_roundtrip() {
        let values = [0u64, 1, 2, 7, 100, 1 << 20, u64::MAX, (1 << 40) + 3];
        let mut w = BitWriter::new();
        for (i, &v) in values.iter().enumerate() {
            let k = (i as u32 * 7) % 64;
            w.write_rice(v, k);
            w.write_gamma(v.min(u64::MAX - 1));
            w.write_bits(v, 64);
            w.write_bit(i % 2 == 0);
        }
        let expected_len = w.bit_len();
        let bytes = w.into_bytes();
        assert_eq!(bytes.len() as u64, expected_len.div_ceil(8));
        let mut r = BitReader::new(&bytes);
        for (i, &v) in values.iter().enumerate() {
            let k = (i as u32 * 7) % 64;
            assert_eq!(r.read_rice(k).unwrap(), v);
            assert_eq!(r.read_gamma().unwrap(), v.min(u64::MAX - 1));
            assert_eq!(r.read_bits(64).unwrap(), v);
            assert_eq!(r.read_bit().unwrap(), i % 2 == 0);
        }
    }

    #[test]
    fn rice_len_matches_written_bits() {
        for k in [0, 1, 5, 63] {
            for v in [0u64, 1, 31, 32, 1000, u64::MAX] {
                let mut w = BitWriter::new();
                w.write_rice(v, k);
                assert_eq!(w.bit_len(), rice_len(v, k), "v={v} k={k}");
            }
        }
    }

    #[test]
    fn best_k_is_the_exact_minimum() {
        let values: Vec<u64> = (0..200).map(|i| (i * 37 % 1000) as u64).collect();
        let k = best_rice_k(&values);
        let cost = |k| values.iter().map(|&v| rice_len(v, k)).sum::<u64>();
        for other in 0..=MAX_RICE_K {
            assert!(cost(k) <= cost(other));
        }
    }

    #[test]
    fn append_concatenates_bit_exactly() {
        let mut a = BitWriter::new();
        a.write_bits(0b101, 3);
        let mut b = BitWriter::new();
        b.write_bits(0xABCD, 16);
        b.write_bits(0b11, 2);
        a.append(&b);
        assert_eq!(a.bit_len(), 21);
        let bytes = a.into_bytes();
        let mut r = BitReader::new(&bytes);
        assert_eq!(r.read_bits(3).unwrap(), 0b101);
        assert_eq!(r.read_bits(16).unwrap(), 0xABCD);
        assert_eq!(r.read_bits(2).unwrap(), 0b11);
    }

    #[test]
    fn adaptive_rice_roundtrips_and_follows_the_values() {
        let values: Vec<u64> = (0..300u64)
            .map(|i| {
                if i < 100 {
                    i % 5
                } else if i < 200 {
                    1000 + i
                } else {
                    u64::MAX - i
                }
            })
            .collect();
        let mut w = BitWriter::new();
        let mut s = AdaptiveRice::new(4);
        for &v in &values {
            let before = w.bit_len();
            let cost = s.cost(v);
            w.write_adaptive(v, &mut s);
            assert_eq!(w.bit_len() - before, cost);
        }
        assert!(s.k() >= 40, "k follows large values: {}", s.k());
        let bytes = w.into_bytes();
        let mut r = BitReader::new(&bytes);
        let mut s = AdaptiveRice::new(4);
        for &v in &values {
            assert_eq!(r.read_adaptive(&mut s).unwrap(), v);
        }
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
    fn type_codes_roundtrip_with_their_lengths() {
        for n in 2..=6 {
            for prev in 0..n {
                let mut w = BitWriter::new();
                let mut total = 0;
                for rank in 0..n {
                    w.write_type(n, prev, rank);
                    total += type_code_len(n, prev, rank);
                }
                assert_eq!(w.bit_len(), total);
                let bytes = w.into_bytes();
                let mut r = BitReader::new(&bytes);
                for rank in 0..n {
                    assert_eq!(r.read_type(n, prev).unwrap(), rank);
                }
            }
        }
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

    #[test]
    fn reads_past_the_end_fail() {
        let mut r = BitReader::new(&[0xFF]);
        assert!(r.read_rice(0).is_err(), "8 ones then end of data");
        let mut r = BitReader::new(&[0x00]);
        assert!(r.read_gamma().is_err());
        let mut r = BitReader::new(&[]);
        assert!(r.read_bit().is_err());
    }
}
