//! The versioned byte layout of an encoded world.
//!
//! ```text
//! offset  size  field (little endian)
//!      0     4  magic  b"MWBM"
//!      4     2  format version (1)
//!      6     2  header length H in bytes (80 for version 1; readers skip fields they do not know)
//!      8     1  motion model: 0 = General, 1 = FreeFlightGravity
//!      9     3  reserved, zero
//!     12     4  object count N
//!     16     8  frame_dt (s)          24  8  e_max (m)      32  8  θ_max (rad)
//!     40     8  position step Δ (m)   48  8  rotation step Δθ (rad)
//!     56    24  gravity g (3 × f64; zero for General)
//!      H   8·N  object index: N × (payload byte offset u32, frame count u32)
//!   H+8N        payloads, object after object
//! ```
//!
//! The quantisation steps are stored, not re-derived from the bounds, so a future encoder may
//! choose them differently and old readers still decode its output, and old recordings stay
//! readable when today's derivation changes. A reader accepts every version up to
//! [`FORMAT_VERSION`] and dispatches on it.
//!
//! An object's payload is a bit stream (most significant bit first):
//!
//! ```text
//! 7 × 6 bits   Rice parameters: pos length, pos linear, pos quadratic, pos start,
//!              rot length, rot angular velocity, rot start
//! γ            bit length of the position stream (Elias gamma), so that the rotation stream
//!              can be reached without decoding positions
//! position stream
//!   1 bit      start flag: 0 → 3 × Rice(zigzag(round(c₀ / (Δ/16)))), 1 → 3 × raw f64
//!   segments until the track is covered:
//!     Rice     length L in frames (0 = key: one frame, 3 × raw f64 end point)
//!     1 bit    only for FreeFlightGravity: quadratic term is gravity's
//!     3 × Rice linear residuals, then (unless gravity) 3 × Rice quadratic residuals
//! rotation stream
//!   1 bit      start flag: 0 → 3 × Rice(zigzag(round(log q₀ / (Δθ/16)))), 1 → 4 × raw f64
//!   segments: Rice length L (0 = key: 4 × raw f64), then 3 × Rice angular-velocity residuals
//! ```
//!
//! Residuals are quantised coefficients minus a prediction from the previous segment (see
//! `segment`), zig-zag mapped. Per-segment CRCs live one layer up, on the bus (DESIGN.md).

use crate::error::CodecError;
use crate::params::MotionModel;

/// First four bytes of every encoded world.
pub const MAGIC: [u8; 4] = *b"MWBM";
/// The format version this build writes (and the newest it reads).
pub const FORMAT_VERSION: u16 = 1;
pub(crate) const HEADER_LEN_V1: usize = 80;
pub(crate) const INDEX_ENTRY_LEN: usize = 8;

/// Number of Rice-coded streams per object, each with its own parameter.
pub(crate) const STREAMS: usize = 7;
pub(crate) const S_POS_LEN: usize = 0;
pub(crate) const S_POS_LINEAR: usize = 1;
pub(crate) const S_POS_QUADRATIC: usize = 2;
pub(crate) const S_POS_START: usize = 3;
pub(crate) const S_ROT_LEN: usize = 4;
pub(crate) const S_ROT_W: usize = 5;
pub(crate) const S_ROT_START: usize = 6;

#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Header {
    pub version: u16,
    pub header_len: usize,
    pub model: MotionModel,
    pub object_count: u32,
    pub frame_dt: f64,
    pub e_max: f64,
    pub theta_max: f64,
    pub pos_step: f64,
    pub rot_step: f64,
}

impl Header {
    pub(crate) fn write(&self, out: &mut Vec<u8>) {
        out.extend_from_slice(&MAGIC);
        out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        out.extend_from_slice(&(HEADER_LEN_V1 as u16).to_le_bytes());
        out.push(self.model.wire_id());
        out.extend_from_slice(&[0; 3]);
        out.extend_from_slice(&self.object_count.to_le_bytes());
        for v in [
            self.frame_dt,
            self.e_max,
            self.theta_max,
            self.pos_step,
            self.rot_step,
        ]
        .into_iter()
        .chain(self.model.gravity())
        {
            out.extend_from_slice(&v.to_le_bytes());
        }
        debug_assert_eq!(out.len(), HEADER_LEN_V1);
    }

    pub(crate) fn parse(bytes: &[u8]) -> Result<Self, CodecError> {
        let need = |n: usize| {
            if bytes.len() < n {
                Err(CodecError::Truncated {
                    at_bit: bytes.len() as u64 * 8,
                    needed_bits: (n - bytes.len()) as u64 * 8,
                })
            } else {
                Ok(())
            }
        };
        need(8)?;
        if bytes[..4] != MAGIC {
            return Err(CodecError::BadMagic {
                expected: MAGIC,
                found: bytes[..4].to_vec(),
            });
        }
        let version = u16::from_le_bytes([bytes[4], bytes[5]]);
        if version == 0 || version > FORMAT_VERSION {
            return Err(CodecError::UnsupportedVersion {
                found: version,
                supported: FORMAT_VERSION,
            });
        }
        let header_len = usize::from(u16::from_le_bytes([bytes[6], bytes[7]]));
        if header_len < HEADER_LEN_V1 {
            return Err(CodecError::BadHeaderField {
                field: "header_len",
                value: header_len as f64,
            });
        }
        need(header_len)?;
        let f = |at: usize| {
            let mut b = [0u8; 8];
            b.copy_from_slice(&bytes[at..at + 8]);
            f64::from_le_bytes(b)
        };
        let g = [f(56), f(64), f(72)];
        let model = match bytes[8] {
            0 => MotionModel::General,
            1 => MotionModel::FreeFlightGravity { g },
            other => {
                return Err(CodecError::BadHeaderField {
                    field: "model",
                    value: f64::from(other),
                });
            }
        };
        let header = Header {
            version,
            header_len,
            model,
            object_count: u32::from_le_bytes([bytes[12], bytes[13], bytes[14], bytes[15]]),
            frame_dt: f(16),
            e_max: f(24),
            theta_max: f(32),
            pos_step: f(40),
            rot_step: f(48),
        };
        let positive = [
            ("frame_dt", header.frame_dt),
            ("e_max", header.e_max),
            ("theta_max", header.theta_max),
            ("pos_step", header.pos_step),
            ("rot_step", header.rot_step),
        ];
        // Steps must stay in the normal range after scaling by 4^-32 (the smallest bucket step).
        for (field, value) in positive {
            if !(value.is_finite() && value > 1e-280 && value < 1e280) {
                return Err(CodecError::BadHeaderField { field, value });
            }
        }
        for (field, value) in [("g.x", g[0]), ("g.y", g[1]), ("g.z", g[2])] {
            if !value.is_finite() {
                return Err(CodecError::BadHeaderField { field, value });
            }
        }
        Ok(header)
    }
}
