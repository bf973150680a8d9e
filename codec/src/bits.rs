//! Bit-level I/O and the entropy code: zig-zag mapping and Golomb–Rice codes (§4.3: "the resulting
//! residuals are stored using … Rice codes, which use fewer bits for smaller numbers").
//!
//! Bits are written most-significant first. Every read is bounds-checked against the slice, so a
//! hostile stream can only make a read fail, never panic or loop forever: each successful read
//! consumes at least one bit.

use crate::error::CodecError;

/// Largest Rice parameter a stream may declare (6 bits on the wire).
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

/// Length in bits of `v` Rice-coded with parameter `k`.
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

#[derive(Default, Debug, Clone)]
pub(crate) struct BitWriter {
    bytes: Vec<u8>,
    acc: u128,
    nacc: u32,
}

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

    /// Elias-gamma code of `v + 1` (a parameter-free code for the rare header integers).
    pub(crate) fn write_gamma(&mut self, v: u64) {
        let v1 = v.saturating_add(1);
        let n = 64 - v1.leading_zeros();
        self.write_bits(0, n - 1);
        self.write_bits(v1, n);
    }

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
    fn reads_past_the_end_fail() {
        let mut r = BitReader::new(&[0xFF]);
        assert!(r.read_rice(0).is_err(), "8 ones then end of data");
        let mut r = BitReader::new(&[0x00]);
        assert!(r.read_gamma().is_err());
        let mut r = BitReader::new(&[]);
        assert!(r.read_bit().is_err());
    }
}
