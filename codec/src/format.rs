//! The versioned byte layout of an encoded world. This build writes version 6 and reads 1 to 6.
//!
//! # Version 6
//!
//! Version 5 (below) with a compact header: the 4-byte magic, the 2-byte version, the 2-byte
//! header length and the model byte become one version byte and a flag, 8 bytes less on every
//! stream. A world segment restates its header every ~1 s; for a one-body object group that was
//! 8 B/(obj·s) of ~96.
//!
//! ```text
//! offset  size  field
//!      0     1  format version (6); versions 1–5 start with the magic b"MWBM" (0x4D), so a
//!               first byte below 0x40 is a version-6-or-later header and anything else with
//!               the wrong magic is not a world
//!      1     1  flags: version 5's, plus 64 = the motion model is FreeFlightGravity
//!      2        version 5's header fields from the bounds on (preset byte or bounds, frame rate,
//!               steps, gravity, start Rice parameters, object count, common frame count,
//!               dynamics); the header ends with its last field (no length: a reader of a later
//!               version's header refuses it by its version byte)
//!               the object index and payloads as in version 5
//! ```
//!
//! The magic's job — telling a world from other bytes — is the bus envelope's: a
//! `MotionSegment` names its encoding and carries a CRC32 of the payload (DESIGN.md), and a
//! recording keeps the envelope.
//!
//! # Version 5
//!
//! Version 4 (below, with the version field 5) with two changes.
//!
//! **Lattice vectors.** Every quantised 3-vector — start values, one-frame steps, the linear and
//! quadratic coefficients of position and rotation segments, free-flight velocities — is a point
//! of the body-centred cubic lattice instead of the cubic one (`segment::Lattice`): for a step s
//! the lattice with the same covering radius √3/2·s, spacing a = s·2√3/√5. Its lattice
//! coordinates K (doubled: the point is K·a/2, the three of one parity c) are written as the
//! coset bit c (equiprobable), then k = (K − c)/2: start values Rice-coded with the header's
//! parameter as before, other vectors as residuals against `round(p/a − c/2)` per axis, p the
//! predicted vector (the previous segment's end velocity, quadratic term, angular velocity or
//! angular acceleration as a point of space; 0 for steps). Start orientations are quantised at
//! Δθ/4 (positions still Δ/8).
//!
//! **Decimal header numbers**: a world segment restates its header every ~1 s, and a one-body
//! scene at bounds other than a preset paid 16 bytes a second for them (chute at e_max = 2 mm:
//! 37.8 B/(obj·s) of header, against 21.5 at the 1 mm preset).
//!
//! * **Bounds** (header flag 32, not with flag 1): e_max then θ_max, each a *decimal*: varint m
//!   (1 ≤ m ≤ 2⁵³), then a byte k (0–22); the value is the f64 division m / 10ᵏ. Both operands
//!   are exact in f64, so the division is the correctly rounded decimal: what a settings file's
//!   `0.002` parses to. An encoder writes it only when the division gives the bound back bit for
//!   bit (else the two f64s, as before).
//! * **Gravity** (model 1, gravity byte with bit 0x40): bits 0–2 mark the non-zero components as
//!   before, bits 3–5 their negative signs; each non-zero component follows as a decimal of its
//!   magnitude.
//!
//! # Version 4
//!
//! Version 3 (below, with the version field 4) plus:
//!
//! * **Derived steps** (no stored steps, flag 4 clear): Δ = 1.1·e_max, Δθ = 1.1·θ_max (versions
//!   2–3: 1.0); start values in steps of Δ/8 and Δθ/8 (versions 1–3: /16).
//! * **Rotation dynamics** (header flag 16), after the common frame count: varint substeps per
//!   frame (1–16), then the angular damping `c`: a byte 0 (none), 1 + varint n (c = n/1000) or
//!   2 + f64. A world written with them has a sixth rotation type, *free flight* (rank 5, after
//!   Key), coded with the others' type model; without the flag there are five.
//! * **Free-flight segment**: length (on the rotation length stream, at most 4096 frames), then —
//!   before the object's first free flight only — its three principal moments as 12-bit integers
//!   (equiprobable bits; moments relative to the largest, which is 4095), then three
//!   angular-velocity residuals on their own stream (`S_ROT_FREE`, prior of `S_ROT_W`) against
//!   the predicted angular velocity, in steps of Δθ·2⁻ᵏ (k = ⌈log₂ L⌉, as a linear segment). The
//!   decoded curve is `segment::FreeDynamics` simulated from the start orientation q₀, in the
//!   body frame (ω_b = q₀⁻¹ ω q₀ once): per frame, `substeps` times (h = 1/substeps: the explicit
//!   gyroscopic step L = I ω_b, L' = L − h·(ω_b × L), ω_b = I⁻¹ L'·|L|/|L'|; then
//!   `q ← normalise(q ⊗ (h·ω_b/2, 1))`), then ω_b × 1/(1 + dt·c). Bit-exact decoding needs these
//!   operations in this order (`FreeDynamics::frame`).
//!
//! # Version 3
//!
//! The header, the index and the symbols of a payload are version 2's (below, with the version
//! field 3); what differs is how a payload codes its symbols. It is one range-coded stream per
//! object (`arith`: the LZMA binary coder, its always-zero first byte and up to 8 trailing zero
//! bytes not stored — the reader reads zeros past the end), every model starting afresh at the
//! object's first byte (objects stay independently decodable):
//!
//! ```text
//! flag bits        (start raw/quantised and at rest, for positions and for rotations) one
//!                  adaptive context each
//! start values     the version-2 Rice code with the header's parameter, as equiprobable bits
//! raw f64          64 equiprobable bits
//! segment type     a bit "not the previous type" (context: the previous type), then the rank
//!                  among the other types as 3 bits of a context tree (one tree per previous
//!                  type); positions and rotations have their own models
//! integers         per stream (the version-2 streams, plus two for the lengths of rest
//!                  segments, `S_POS_REST_LEN` and `S_ROT_REST_LEN`): m = v + 1 as the bit
//!                  length n of m in unary — bit j's context is j − k + 3 clamped to 0..=7,
//!                  k the stream's version-2 adaptive Rice parameter (starting from
//!                  `PRIORS_V3`), one set for k = 0 and one for k > 0 — then the two bits below
//!                  m's leading one with contexts (by n capped at 19, the second also by the
//!                  first), then the other n − 2 bits equiprobable
//! ```
//!
//! Contexts start at probability ½ (the unary ones at `arith::PREFIX_INIT`) and adapt at rate
//! 1/2, 1/4, … settling at 1/32 (`arith::Bit`).
//!
//! # Version 2
//!
//! ```text
//! offset  size  field (little endian; "varint" = unsigned LEB128)
//!      0     4  magic  b"MWBM"
//!      4     2  format version (2)
//!      6     2  header length H in bytes (readers skip fields they do not know)
//!      8     1  motion model: 0 = General, 1 = FreeFlightGravity
//!      9     1  flags: 1 = bounds are a preset, 2 = frame_dt is 1/n, 4 = steps stored,
//!               8 = every object has the same frame count
//!     10        bounds: preset byte (0 draft, 1 standard, 2 final) | e_max f64, θ_max f64
//!               frame_dt: varint n (frame_dt = 1.0 / n) | f64
//!               steps (flag 4): Δ f64, Δθ f64; otherwise Δ = e_max, Δθ = θ_max
//!               gravity (model 1): a byte with bit i set for a non-zero g[i], then those f64s;
//!               or 0x80 | i for the i-th of the well-known vectors (`KNOWN_GRAVITY`)
//!               2 bytes: Rice parameters of the start positions and of the start orientations
//!               varint object count N; varint common frame count (flag 8)
//!      H        object index: N × (varint payload length in bytes [, varint frame count])
//!               payloads, object after object, each a whole number of bytes
//! ```
//!
//! An object's payload is one bit stream (most significant bit first). Every integer is an
//! adaptive Rice code ([`crate::bits::AdaptiveRice`]) of its own stream, starting from the prior
//! in [`ADAPTIVE_PRIORS`], except the start values, which use the header's Rice parameters;
//! signed values are zig-zag mapped.
//!
//! ```text
//! position start   1 bit: 0 → 3 × Rice(c₀ / (Δ/16)), 1 → 3 × raw f64
//! at rest          (tracks of two or more frames) 1 bit: 1 → the start point holds for the
//!                  whole track, no segments follow
//! position segments until the track is covered, each:
//!   type           1 bit "same type as the previous segment", else the new type's rank
//!                  among the others (truncated binary; the first previous type is Gravity in
//!                  FreeFlightGravity worlds, Quadratic otherwise)
//!   length         (not for Step, Key) 0 = to the end of the track, else L frames
//!   Gravity        3 × linear residual (the quadratic term is h²g/2)
//!   Quadratic      3 × linear, 3 × quadratic residuals
//!   Linear         3 × linear residual (no quadratic term)
//!   Rest           nothing: the segment holds its start point
//!   Step           no length (one frame): 3 × step residual, the frame minus its prediction
//!                  from the two frames before (see `segment::position_step_prediction`), in Δ
//!   Key            3 × raw f64: one frame, stored exactly
//! rotation start   1 bit: 0 → 3 × Rice(log q₀ / (Δθ/16)), 1 → 4 × raw f64
//! at rest          as for positions
//! rotation segments: type (first previous: Linear), length as above, then
//!   Linear         3 × angular-velocity residual
//!   Quadratic      3 × angular-velocity, 3 × angular-acceleration residual
//!   Rest           nothing
//!   Step           no length: 3 × residual of the frame's rotation vector against the last
//!                  frame-to-frame rotation, in Δθ
//!   Key            4 × raw f64
//! ```
//!
//! Residuals are quantised coefficients minus a prediction from the previous segment (see
//! `segment`). Every segment consumes at least one bit and covers at least one frame, so a hostile
//! stream ends in an error after at most as many segments as it has bits. (Version 3: a symbol
//! consumes at least ~1/1400 bit, no probability being above 1 − 2⁻¹¹, and the reader fails 8
//! bytes past the end, so a hostile stream ends after a number of segments proportional to its
//! length.)
//!
//! # Version 1
//!
//! ```text
//!      0     4  magic  b"MWBM"
//!      4     2  format version (1)
//!      6     2  header length H in bytes (80)
//!      8     1  motion model          9   3  reserved, zero       12  4  object count N
//!     16     8  frame_dt (s)          24  8  e_max (m)            32  8  θ_max (rad)
//!     40     8  position step Δ (m)   48  8  rotation step Δθ (rad)
//!     56    24  gravity g (3 × f64; zero for General)
//!      H   8·N  object index: N × (payload byte offset u32, frame count u32)
//!   H+8N        payloads, object after object
//! ```
//!
//! A version-1 payload starts with 7 × 6-bit Rice parameters (one per stream: pos length, pos
//! linear, pos quadratic, pos start, rot length, rot angular velocity, rot start) and the
//! Elias-gamma bit length of the position stream; segments are `Rice length L (0 = key)`, a
//! gravity flag bit (FreeFlightGravity only), linear and (unless gravity) quadratic residuals;
//! rotation segments are a length and three angular-velocity residuals.
//!
//! The quantisation steps are part of the header (stored, or a fixed derivation of the bounds), so
//! a future encoder may choose them differently and old readers still decode its output. Per-
//! segment CRCs live one layer up, on the bus (DESIGN.md).

use crate::arith::ValueModel;
use crate::bits::{AdaptiveRice, read_varint, write_varint};
use crate::error::CodecError;
use crate::params::{MotionModel, Quality, step_ratio};

/// First four bytes of an encoded world of versions 1 to 5 (from version 6 a world starts with
/// its version byte; see "Version 6" above).
pub const MAGIC: [u8; 4] = *b"MWBM";
/// The format version this build writes (and the newest it reads).
pub const FORMAT_VERSION: u16 = 6;
/// The first version with the compact header (no magic, no header length).
pub(crate) const COMPACT_HEADER_VERSION: u16 = 6;
/// A first byte below this is a compact header's version; every older world starts with `M`
/// (0x4D, above it).
const COMPACT_VERSION_LIMIT: u8 = 0x40;
pub(crate) const HEADER_LEN_V1: usize = 80;
pub(crate) const INDEX_ENTRY_LEN_V1: usize = 8;

/// Number of Rice-coded streams per object in version 1, each with its own parameter.
pub(crate) const STREAMS_V1: usize = 7;
pub(crate) const S_POS_LEN: usize = 0;
pub(crate) const S_POS_LINEAR: usize = 1;
pub(crate) const S_POS_QUADRATIC: usize = 2;
pub(crate) const S_POS_START: usize = 3;
pub(crate) const S_ROT_LEN: usize = 4;
pub(crate) const S_ROT_W: usize = 5;
pub(crate) const S_ROT_START: usize = 6;
/// Version 2 adds streams for angular accelerations and for one-frame steps.
pub(crate) const S_ROT_ACC: usize = 7;
pub(crate) const S_POS_STEP: usize = 8;
pub(crate) const S_ROT_STEP: usize = 9;
pub(crate) const STREAMS_V2: usize = 10;
/// Version 3 codes the lengths of rest segments apart from those of curves (a rest lasts until
/// the next impact; a curve until the bound breaks). In version 2 they are `S_POS_LEN`, `S_ROT_LEN`.
pub(crate) const S_POS_REST_LEN: usize = 10;
pub(crate) const S_ROT_REST_LEN: usize = 11;
pub(crate) const STREAMS_V3: usize = 12;

/// Version 4: the start angular velocities of free-flight rotation segments (their own
/// statistics: a flight starts after an impact, where the last velocity predicts little).
pub(crate) const S_ROT_FREE: usize = 12;

/// The number of integer streams of versions 3 and 4 (every axis of a triple on its stream, as
/// in version 2; separate streams per axis measured no better). Version 3 leaves `S_ROT_FREE`
/// unused.
pub(crate) const STREAMS_V3_ALL: usize = STREAMS_V3 + 1;

pub(crate) fn axis_stream(stream: usize, _axis: usize) -> usize {
    stream
}

/// The version-2 stream that codes what version 3 codes on `stream` (for version 4's free
/// flights: the stream whose prior they start from).
pub(crate) fn v2_stream(stream: usize) -> usize {
    match stream {
        S_POS_REST_LEN => S_POS_LEN,
        S_ROT_REST_LEN => S_ROT_LEN,
        S_ROT_FREE => S_ROT_W,
        s => s,
    }
}

/// Version 3: the priors of the value models' magnitude classes (by stream index).
pub(crate) const PRIORS_V3: [u64; STREAMS_V3] = [24, 6, 6, 0, 12, 12, 0, 6, 3, 3, 24, 24];

/// Version 2: the expected value of each stream before it has seen any (by stream index above).
/// Only a prior — the parameter adapts within a few values — chosen from the shipped scenes at
/// Standard quality.
/// (The start streams, 3 and 6, use the header's parameters instead.)
pub(crate) const ADAPTIVE_PRIORS: [u64; STREAMS_V2] = [24, 6, 6, 0, 12, 12, 0, 6, 3, 3];

/// The adaptive coders of one object's payload (version 2), all at their priors.
pub(crate) fn adaptive_streams() -> [AdaptiveRice; STREAMS_V2] {
    ADAPTIVE_PRIORS.map(AdaptiveRice::new)
}

/// The value models of one object's payload (version 3), all at their priors.
pub(crate) fn value_models() -> Box<[ValueModel; STREAMS_V3_ALL]> {
    Box::new(std::array::from_fn(|s| {
        ValueModel::new(PRIORS_V3[v2_stream(s)])
    }))
}

/// Largest start Rice parameter a version-2 header may hold.
pub(crate) const MAX_START_K: u32 = 60;

const FLAG_PRESET: u8 = 1;
const FLAG_RATE: u8 = 2;
const FLAG_STEPS: u8 = 4;
const FLAG_COMMON_FRAMES: u8 = 8;
/// Version 4: the world carries rotation dynamics (free-flight rotation segments).
const FLAG_DYNAMICS: u8 = 16;
/// Version 5: the bounds are decimals (see the module doc).
const FLAG_DECIMAL_BOUNDS: u8 = 32;
/// Version 6: the motion model is FreeFlightGravity (the model byte of versions 2–5).
const FLAG_GRAVITY_MODEL: u8 = 64;
/// Most substeps per frame a version-4 header may hold (each costs decoding time per simulated
/// frame; rapier's default is 4).
pub(crate) const MAX_SUBSTEPS: u32 = 16;
const PRESETS: [Quality; 3] = [Quality::Draft, Quality::Standard, Quality::Final];

/// Gravity vectors a version-2 header names by number (the gravity byte is `0x80 | i`) instead
/// of storing them: y-up and z-up at 9.81 and at standard gravity 9.80665 m/s². A ~1 s segment
/// of a one-body scene restates its header every second, so 8 bytes matter.
const KNOWN_GRAVITY: [[f64; 3]; 4] = [
    [0.0, -9.81, 0.0],
    [0.0, 0.0, -9.81],
    [0.0, -9.80665, 0.0],
    [0.0, 0.0, -9.80665],
];
const GRAVITY_KNOWN: u8 = 0x80;
/// Version 5: the gravity byte's non-zero components are decimals, bits 3–5 their signs.
const GRAVITY_DECIMAL: u8 = 0x40;

/// The powers of ten a version-5 decimal divides by; every one is exact in f64.
const POW10: [f64; 23] = [
    1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16,
    1e17, 1e18, 1e19, 1e20, 1e21, 1e22,
];
/// Largest mantissa of a version-5 decimal: integers up to 2⁵³ are exact in f64.
const MAX_DECIMAL_MANTISSA: u64 = 1 << 53;

/// `x > 0` as a version-5 decimal `(m, k)`, `x = m / 10ᵏ` with the smallest k, if the division
/// gives `x` back bit for bit; else `None` (the caller stores the f64).
pub(crate) fn as_decimal(x: f64) -> Option<(u64, u8)> {
    if !(x.is_finite() && x > 0.0) {
        return None;
    }
    POW10.iter().enumerate().find_map(|(k, &p)| {
        let m = (x * p).round();
        (m >= 1.0 && m <= MAX_DECIMAL_MANTISSA as f64 && m / p == x).then_some((m as u64, k as u8))
    })
}

/// [`as_decimal`] where it is shorter than an f64: a mantissa below 2⁴² (a varint of at most six
/// bytes). Every f64 has a decimal form of at most 17 digits, most need 16 or 17.
pub(crate) fn short_decimal(x: f64) -> Option<(u64, u8)> {
    as_decimal(x).filter(|&(m, _)| m < 1 << 42)
}

fn write_decimal(out: &mut Vec<u8>, (m, k): (u64, u8)) {
    write_varint(out, m);
    out.push(k);
}

/// Reads a version-5 decimal; a zero or too large mantissa or exponent is an error naming `field`.
fn read_decimal(h: &[u8], at: &mut usize, field: &'static str) -> Result<f64, CodecError> {
    let m = read_varint(h, at)?;
    let k = *h.get(*at).ok_or(CodecError::Truncated {
        at_bit: *at as u64 * 8,
        needed_bits: 8,
    })?;
    *at += 1;
    match POW10.get(usize::from(k)) {
        Some(p) if (1..=MAX_DECIMAL_MANTISSA).contains(&m) => Ok(m as f64 / p),
        _ => Err(CodecError::BadHeaderField {
            field,
            value: if m == 0 { 0.0 } else { f64::from(k) },
        }),
    }
}

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
    /// Version 2: the frame count shared by every object (then the index omits it).
    pub common_frames: Option<u32>,
    /// Version 2: the Rice parameters of the start positions and start orientations, chosen for
    /// the whole world (three values per object are too few to adapt to).
    pub start_k: [u32; 2],
    /// Version 4: the simulator's rotation integration, for free-flight rotation segments.
    pub dynamics: Option<HeaderDynamics>,
}

/// Version 4: what every free-flight rotation segment of a world shares (the per-object part,
/// the principal moments, is in the object's payload).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct HeaderDynamics {
    /// Integration substeps per frame, `1..=MAX_SUBSTEPS`.
    pub substeps: u32,
    /// Angular damping coefficient `c` (1/s): angular velocity × `1/(1 + dt·c)` per frame.
    pub angular_damping: f64,
}

/// The steps a header derives from the bounds when it does not store them (version 2 on).
pub(crate) fn derived_steps(version: u16, e_max: f64, theta_max: f64) -> (f64, f64) {
    let r = step_ratio(version);
    (r * e_max, r * theta_max)
}

impl Header {
    /// Writes a header of the current version (the compact layout of version 6).
    pub(crate) fn write(&self, out: &mut Vec<u8>) {
        out.push(FORMAT_VERSION as u8);
        let preset = PRESETS
            .iter()
            .position(|q| q.bounds() == (self.e_max, self.theta_max));
        let rate = (1.0 / self.frame_dt).round();
        let rate = (rate >= 1.0 && rate <= f64::from(u32::MAX) && 1.0 / rate == self.frame_dt)
            .then_some(rate as u64);
        let steps_stored = derived_steps(self.version, self.e_max, self.theta_max)
            != (self.pos_step, self.rot_step);
        let decimal_bounds = match (
            preset,
            short_decimal(self.e_max),
            short_decimal(self.theta_max),
        ) {
            (None, Some(e), Some(t)) => Some((e, t)),
            _ => None,
        };
        let mut flags = 0;
        flags |= if preset.is_some() { FLAG_PRESET } else { 0 };
        flags |= if decimal_bounds.is_some() {
            FLAG_DECIMAL_BOUNDS
        } else {
            0
        };
        flags |= if rate.is_some() { FLAG_RATE } else { 0 };
        flags |= if steps_stored { FLAG_STEPS } else { 0 };
        flags |= if self.common_frames.is_some() {
            FLAG_COMMON_FRAMES
        } else {
            0
        };
        flags |= if self.dynamics.is_some() {
            FLAG_DYNAMICS
        } else {
            0
        };
        flags |= if self.model.wire_id() == 1 {
            FLAG_GRAVITY_MODEL
        } else {
            0
        };
        out.push(flags);
        match (preset, decimal_bounds) {
            (Some(i), _) => out.push(i as u8),
            (None, Some((e, t))) => {
                write_decimal(out, e);
                write_decimal(out, t);
            }
            (None, None) => {
                out.extend_from_slice(&self.e_max.to_le_bytes());
                out.extend_from_slice(&self.theta_max.to_le_bytes());
            }
        }
        match rate {
            Some(n) => write_varint(out, n),
            None => out.extend_from_slice(&self.frame_dt.to_le_bytes()),
        }
        if steps_stored {
            out.extend_from_slice(&self.pos_step.to_le_bytes());
            out.extend_from_slice(&self.rot_step.to_le_bytes());
        }
        if let MotionModel::FreeFlightGravity { g } = self.model {
            match KNOWN_GRAVITY.iter().position(|&k| k == g) {
                Some(i) => out.push(GRAVITY_KNOWN | i as u8),
                None => {
                    let mask = (0..3).fold(0u8, |m, i| m | (u8::from(g[i] != 0.0) << i));
                    let decimals: Option<Vec<(u64, u8)>> = g
                        .into_iter()
                        .filter(|&v| v != 0.0)
                        .map(|v| short_decimal(v.abs()))
                        .collect();
                    match decimals {
                        Some(d) => {
                            let signs =
                                (0..3).fold(0u8, |m, i| m | (u8::from(g[i] < 0.0) << (3 + i)));
                            out.push(GRAVITY_DECIMAL | signs | mask);
                            for v in d {
                                write_decimal(out, v);
                            }
                        }
                        None => {
                            out.push(mask);
                            for v in g.into_iter().filter(|&v| v != 0.0) {
                                out.extend_from_slice(&v.to_le_bytes());
                            }
                        }
                    }
                }
            }
        }
        out.push(self.start_k[0] as u8);
        out.push(self.start_k[1] as u8);
        write_varint(out, u64::from(self.object_count));
        if let Some(f) = self.common_frames {
            write_varint(out, u64::from(f));
        }
        if let Some(d) = self.dynamics {
            write_varint(out, u64::from(d.substeps));
            // 0: no damping; 1: varint n, c = n / 1000 (scene files write decimals); 2: an f64.
            let c = d.angular_damping;
            let milli = (c * 1000.0).round();
            if c == 0.0 {
                out.push(0);
            } else if (1.0..1e15).contains(&milli) && milli / 1000.0 == c {
                out.push(1);
                write_varint(out, milli as u64);
            } else {
                out.push(2);
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
    }

    pub(crate) fn parse(bytes: &[u8]) -> Result<Self, CodecError> {
        need(bytes, 1)?;
        let first = bytes[0];
        if first < COMPACT_VERSION_LIMIT {
            let version = u16::from(first);
            if !(COMPACT_HEADER_VERSION..=FORMAT_VERSION).contains(&version) {
                return Err(CodecError::UnsupportedVersion {
                    found: version,
                    supported: FORMAT_VERSION,
                });
            }
            return Self::parse_fields(bytes, None, version)?.validate();
        }
        need(bytes, 8)?;
        if bytes[..4] != MAGIC {
            return Err(CodecError::BadMagic {
                expected: MAGIC,
                found: bytes[..4].to_vec(),
            });
        }
        let version = u16::from_le_bytes([bytes[4], bytes[5]]);
        let header_len = usize::from(u16::from_le_bytes([bytes[6], bytes[7]]));
        let header = match version {
            1 => Self::parse_v1(bytes, header_len)?,
            2..=5 => Self::parse_fields(bytes, Some(header_len), version)?,
            _ => {
                return Err(CodecError::UnsupportedVersion {
                    found: version,
                    supported: FORMAT_VERSION,
                });
            }
        };
        header.validate()
    }

    fn parse_v1(bytes: &[u8], header_len: usize) -> Result<Self, CodecError> {
        if header_len < HEADER_LEN_V1 {
            return Err(CodecError::BadHeaderField {
                field: "header_len",
                value: header_len as f64,
            });
        }
        need(bytes, header_len)?;
        let f = |at: usize| f64_at(bytes, at);
        let g = [f(56), f(64), f(72)];
        Ok(Header {
            version: 1,
            header_len,
            model: model(bytes[8], g)?,
            object_count: u32::from_le_bytes([bytes[12], bytes[13], bytes[14], bytes[15]]),
            frame_dt: f(16),
            e_max: f(24),
            theta_max: f(32),
            pos_step: f(40),
            rot_step: f(48),
            common_frames: None,
            start_k: [0; 2],
            dynamics: None,
        })
    }

    /// The fields of versions 2 to 5 (after magic, version and header length H; `header_len`
    /// is H) or of version 6 (after the version byte; `header_len` is `None`: the header ends
    /// where its fields do).
    fn parse_fields(
        bytes: &[u8],
        header_len: Option<usize>,
        version: u16,
    ) -> Result<Self, CodecError> {
        // Every field is read from the header's own bytes: a field running past H is corrupt.
        let (h, mut at) = match header_len {
            Some(n) => {
                need(bytes, n)?;
                (&bytes[..n], 8)
            }
            None => (bytes, 1),
        };
        let byte = |at: &mut usize| -> Result<u8, CodecError> {
            let b = *h.get(*at).ok_or(CodecError::Truncated {
                at_bit: *at as u64 * 8,
                needed_bits: 8,
            })?;
            *at += 1;
            Ok(b)
        };
        let float = |at: &mut usize| -> Result<f64, CodecError> {
            need(h, *at + 8)?;
            let v = f64_at(h, *at);
            *at += 8;
            Ok(v)
        };
        let (model_id, flags) = match header_len {
            Some(_) => (byte(&mut at)?, byte(&mut at)?),
            None => {
                let flags = byte(&mut at)?;
                (u8::from(flags & FLAG_GRAVITY_MODEL != 0), flags)
            }
        };
        let (e_max, theta_max) = if flags & FLAG_PRESET != 0 {
            let i = byte(&mut at)?;
            PRESETS
                .get(usize::from(i))
                .ok_or(CodecError::BadHeaderField {
                    field: "preset",
                    value: f64::from(i),
                })?
                .bounds()
        } else if version >= 5 && flags & FLAG_DECIMAL_BOUNDS != 0 {
            (
                read_decimal(h, &mut at, "e_max")?,
                read_decimal(h, &mut at, "theta_max")?,
            )
        } else {
            (float(&mut at)?, float(&mut at)?)
        };
        let frame_dt = if flags & FLAG_RATE != 0 {
            let n = read_varint(h, &mut at)?;
            if n == 0 {
                return Err(CodecError::BadHeaderField {
                    field: "frame rate",
                    value: 0.0,
                });
            }
            1.0 / n as f64
        } else {
            float(&mut at)?
        };
        let (pos_step, rot_step) = if flags & FLAG_STEPS != 0 {
            (float(&mut at)?, float(&mut at)?)
        } else {
            derived_steps(version, e_max, theta_max)
        };
        let mut g = [0.0; 3];
        if model_id == 1 {
            let mask = byte(&mut at)?;
            if mask & GRAVITY_KNOWN != 0 {
                g = *KNOWN_GRAVITY
                    .get(usize::from(mask & !GRAVITY_KNOWN))
                    .ok_or(CodecError::BadHeaderField {
                        field: "gravity",
                        value: f64::from(mask),
                    })?;
            } else if version >= 5 && mask & GRAVITY_DECIMAL != 0 {
                for (i, v) in g.iter_mut().enumerate() {
                    if mask & (1 << i) != 0 {
                        let magnitude = read_decimal(h, &mut at, "gravity")?;
                        *v = if mask & (8 << i) != 0 {
                            -magnitude
                        } else {
                            magnitude
                        };
                    }
                }
            } else {
                for (i, v) in g.iter_mut().enumerate() {
                    if mask & (1 << i) != 0 {
                        *v = float(&mut at)?;
                    }
                }
            }
        }
        let mut start_k = [0u32; 2];
        for k in &mut start_k {
            *k = u32::from(byte(&mut at)?);
            if *k > MAX_START_K {
                return Err(CodecError::BadHeaderField {
                    field: "start Rice parameter",
                    value: f64::from(*k),
                });
            }
        }
        let object_count =
            u32::try_from(read_varint(h, &mut at)?).map_err(|_| CodecError::BadHeaderField {
                field: "object count",
                value: f64::INFINITY,
            })?;
        let common_frames = if flags & FLAG_COMMON_FRAMES != 0 {
            Some(u32::try_from(read_varint(h, &mut at)?).map_err(|_| {
                CodecError::BadHeaderField {
                    field: "frame count",
                    value: f64::INFINITY,
                }
            })?)
        } else {
            None
        };
        let dynamics = if version >= 4 && flags & FLAG_DYNAMICS != 0 {
            let substeps = read_varint(h, &mut at)?;
            if !(1..=u64::from(MAX_SUBSTEPS)).contains(&substeps) {
                return Err(CodecError::BadHeaderField {
                    field: "substeps",
                    value: substeps as f64,
                });
            }
            let angular_damping = match byte(&mut at)? {
                0 => 0.0,
                1 => read_varint(h, &mut at)? as f64 / 1000.0,
                2 => float(&mut at)?,
                other => {
                    return Err(CodecError::BadHeaderField {
                        field: "angular damping kind",
                        value: f64::from(other),
                    });
                }
            };
            Some(HeaderDynamics {
                substeps: substeps as u32,
                angular_damping,
            })
        } else {
            None
        };
        Ok(Header {
            version,
            header_len: header_len.unwrap_or(at),
            model: model(model_id, g)?,
            object_count,
            frame_dt,
            e_max,
            theta_max,
            pos_step,
            rot_step,
            common_frames,
            start_k,
            dynamics,
        })
    }

    fn validate(self) -> Result<Self, CodecError> {
        let positive = [
            ("frame_dt", self.frame_dt),
            ("e_max", self.e_max),
            ("theta_max", self.theta_max),
            ("pos_step", self.pos_step),
            ("rot_step", self.rot_step),
        ];
        // Steps must stay in the normal range after scaling by 4^-32 (the smallest bucket step).
        for (field, value) in positive {
            if !(value.is_finite() && value > 1e-280 && value < 1e280) {
                return Err(CodecError::BadHeaderField { field, value });
            }
        }
        let g = self.model.gravity();
        for (field, value) in [("g.x", g[0]), ("g.y", g[1]), ("g.z", g[2])] {
            if !value.is_finite() {
                return Err(CodecError::BadHeaderField { field, value });
            }
        }
        if let Some(d) = self.dynamics {
            let c = d.angular_damping;
            if !(c.is_finite() && c >= 0.0 && c * self.frame_dt < 1e12) {
                return Err(CodecError::BadHeaderField {
                    field: "angular damping",
                    value: c,
                });
            }
        }
        Ok(self)
    }
}

fn need(bytes: &[u8], n: usize) -> Result<(), CodecError> {
    if bytes.len() < n {
        Err(CodecError::Truncated {
            at_bit: bytes.len() as u64 * 8,
            needed_bits: (n - bytes.len()) as u64 * 8,
        })
    } else {
        Ok(())
    }
}

/// The f64 at `at` (the caller has checked the length).
fn f64_at(bytes: &[u8], at: usize) -> f64 {
    let mut b = [0u8; 8];
    b.copy_from_slice(&bytes[at..at + 8]);
    f64::from_le_bytes(b)
}

fn model(id: u8, g: [f64; 3]) -> Result<MotionModel, CodecError> {
    match id {
        0 => Ok(MotionModel::General),
        1 => Ok(MotionModel::FreeFlightGravity { g }),
        other => Err(CodecError::BadHeaderField {
            field: "model",
            value: f64::from(other),
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(
        model: MotionModel,
        frame_dt: f64,
        bounds: (f64, f64),
        common: Option<u32>,
    ) -> Header {
        let (pos_step, rot_step) = derived_steps(FORMAT_VERSION, bounds.0, bounds.1);
        Header {
            version: FORMAT_VERSION,
            header_len: 0,
            model,
            object_count: 300,
            frame_dt,
            e_max: bounds.0,
            theta_max: bounds.1,
            pos_step,
            rot_step,
            common_frames: common,
            start_k: [13, 15],
            dynamics: None,
        }
    }

    #[test]
    fn bad_dynamics_fields_are_errors() {
        let base = Header {
            dynamics: Some(HeaderDynamics {
                substeps: 4,
                angular_damping: 0.5,
            }),
            ..header(
                MotionModel::General,
                1.0 / 120.0,
                Quality::Standard.bounds(),
                None,
            )
        };
        let mut out = Vec::new();
        base.write(&mut out);
        // The dynamics fields are the header's last four bytes: substeps, kind, and 500 (the
        // damping in thousandths) as a two-byte varint.
        let n = out.len();
        assert_eq!(out[n - 4..], [4, 1, 0xf4, 0x03]);
        for (at, byte, field) in [
            (n - 4, 0u8, "substeps"),
            (n - 4, 17, "substeps"),
            (n - 3, 3, "angular damping kind"),
        ] {
            let mut bad = out.clone();
            bad[at] = byte;
            match Header::parse(&bad) {
                Err(CodecError::BadHeaderField { field: f, .. }) => assert_eq!(f, field),
                other => panic!("{field}: {other:?}"),
            }
        }
        // A negative damping (stored as an f64) is refused too.
        let mut out = Vec::new();
        Header {
            dynamics: Some(HeaderDynamics {
                substeps: 4,
                angular_damping: -0.3,
            }),
            ..base
        }
        .write(&mut out);
        assert!(matches!(
            Header::parse(&out),
            Err(CodecError::BadHeaderField {
                field: "angular damping",
                ..
            })
        ));
    }

    /// `out`, written from `h`, parses back to `h` (with its length).
    fn reads_back(h: &Header, out: &[u8]) {
        let back = Header::parse(out).unwrap();
        assert_eq!(
            back,
            Header {
                header_len: out.len(),
                ..*h
            }
        );
    }

    #[test]
    fn decimals_are_exact_or_not_used() {
        for (x, want) in [
            (0.002, Some((2, 3))),
            (0.007, Some((7, 3))),
            (0.01, Some((1, 2))),
            (1.5e-4, Some((15, 5))),
            (9.8, Some((98, 1))),
            (9.80665, Some((980_665, 5))),
            (3.0, Some((3, 0))),
            (1.0 / 3.0, Some((3_333_333_333_333_333, 16))),
            (std::f64::consts::PI, Some((3_141_592_653_589_793, 15))),
            (0.0, None),
            (-0.002, None),
            (f64::NAN, None),
            (5e-324, None),
        ] {
            assert_eq!(as_decimal(x), want, "{x}");
            // The header stores a decimal only where it is shorter than the f64.
            assert_eq!(short_decimal(x), want.filter(|&(m, _)| m < 1 << 42));
        }
    }

    proptest::proptest! {
        /// Any decimal of up to 15 significant digits, exponents down to 10⁻²², is one, and a
        /// decimal always reads back as the f64 it was made from.
        #[test]
        fn decimal_bounds_read_back_bit_for_bit(
            m in 1u64..1_000_000_000_000_000,
            k in 0u8..=22,
            x in 1e-12f64..1e6,
        ) {
            let from_text: f64 = format!("{m}e-{k}").parse().unwrap();
            let d = as_decimal(from_text);
            proptest::prop_assert!(d.is_some(), "{from_text}");
            for v in [Some(from_text), Some(x)] {
                let v = v.unwrap();
                if let Some(d) = as_decimal(v) {
                    let mut out = Vec::new();
                    write_decimal(&mut out, d);
                    let mut at = 0;
                    let back = read_decimal(&out, &mut at, "e_max").unwrap();
                    proptest::prop_assert_eq!(back.to_bits(), v.to_bits());
                    proptest::prop_assert_eq!(at, out.len());
                }
            }
        }
    }

    /// Version 5: bounds other than a preset and gravities other than the well-known vectors cost
    /// a few bytes when they are decimals, and read back exactly; bad decimals are errors naming
    /// the field.
    #[test]
    fn decimal_header_numbers_roundtrip_and_are_short() {
        let g = MotionModel::FreeFlightGravity {
            g: [0.5, -9.8, -0.25],
        };
        let h = header(g, 1.0 / 120.0, (0.002, 0.003), Some(120));
        let mut out = Vec::new();
        h.write(&mut out);
        // Version 1, flags 1, bounds 2 × 2, rate 1, gravity 1 + 3 × 2, start parameters 2, object
        // count 2, frame count 1 (versions 2–5: 8 bytes more, magic, a two-byte version, the
        // header length and the model).
        assert_eq!(out.len(), 19);
        assert_eq!(out[1] & FLAG_DECIMAL_BOUNDS, FLAG_DECIMAL_BOUNDS);
        reads_back(&h, &out);
        // Not decimals: the f64s, as in version 4 (16 + 24 bytes more).
        let third = 1.0 / 3.0;
        let mut f = Vec::new();
        Header {
            model: MotionModel::FreeFlightGravity {
                g: [0.0, -third, 0.0],
            },
            ..header(g, 1.0 / 120.0, (third * 1e-2, 0.003), Some(120))
        }
        .write(&mut f);
        assert_eq!(f[1] & FLAG_DECIMAL_BOUNDS, 0);
        assert_eq!(f.len(), 2 + 16 + 1 + 1 + 8 + 2 + 2 + 1);
        // Offsets of the bounds' exponents and of the first gravity exponent.
        for (at, byte, field) in [(3, 23u8, "e_max"), (9, 99, "gravity")] {
            let mut bad = out.clone();
            bad[at] = byte;
            match Header::parse(&bad) {
                Err(CodecError::BadHeaderField { field: f, .. }) => assert_eq!(f, field),
                other => panic!("{field}: {other:?}"),
            }
        }
        let mut zero = out.clone();
        zero[4] = 0; // θ_max's mantissa
        assert!(matches!(
            Header::parse(&zero),
            Err(CodecError::BadHeaderField {
                field: "theta_max",
                ..
            })
        ));
    }

    #[test]
    fn headers_roundtrip_and_are_small_for_presets() {
        let g = MotionModel::FreeFlightGravity {
            g: [0.0, -9.81, 0.0],
        };
        for (h, max_len) in [
            (
                header(g, 1.0 / 120.0, Quality::Standard.bounds(), Some(120)),
                10,
            ),
            (
                header(
                    MotionModel::FreeFlightGravity {
                        g: [0.1, -9.0, 0.0],
                    },
                    1.0 / 120.0,
                    Quality::Draft.bounds(),
                    Some(7),
                ),
                26,
            ),
            (header(MotionModel::General, 0.013, (2e-3, 7e-4), None), 32),
            (
                Header {
                    pos_step: 0.5e-3,
                    ..header(g, 1.0 / 60.0, Quality::Final.bounds(), Some(0))
                },
                52,
            ),
            // Version 4's dynamics: no damping (2 bytes more), a decimal damping (4), any
            // other (10).
            (
                Header {
                    dynamics: Some(HeaderDynamics {
                        substeps: 4,
                        angular_damping: 0.0,
                    }),
                    ..header(g, 1.0 / 120.0, Quality::Standard.bounds(), Some(120))
                },
                12,
            ),
            (
                Header {
                    dynamics: Some(HeaderDynamics {
                        substeps: 16,
                        angular_damping: 0.5,
                    }),
                    ..header(g, 1.0 / 120.0, Quality::Standard.bounds(), Some(120))
                },
                14,
            ),
            (
                Header {
                    dynamics: Some(HeaderDynamics {
                        substeps: 1,
                        angular_damping: 0.1234567,
                    }),
                    ..header(g, 1.0 / 120.0, Quality::Standard.bounds(), Some(120))
                },
                20,
            ),
        ] {
            let mut out = Vec::new();
            h.write(&mut out);
            assert!(out.len() <= max_len, "{} bytes", out.len());
            reads_back(&h, &out);
            // Any truncation is an error, never a panic.
            for n in 0..out.len() {
                assert!(Header::parse(&out[..n]).is_err());
            }
        }
    }
}
