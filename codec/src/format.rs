//! The byte layout of an encoded world: **format version 1**, the released format, the one this
//! build writes and the only one it reads. A later format gets the next version number and a
//! reader of its own beside this one, so that what was recorded in version 1 stays readable.
//!
//! Notation: all multi-byte fields of the header and index are little endian; "varint" is
//! unsigned LEB128 (at most 10 bytes); "f64" is 8 bytes of an IEEE 754 double; a **decimal** is
//! a varint m (1 ≤ m ≤ 2⁵³) then a byte k (0 ≤ k ≤ 22), the value being the f64 division
//! `m / 10ᵏ` (both operands are exact in f64, so the value is the correctly rounded decimal — what
//! a settings file's `0.002` parses to; a writer uses one only where the division gives its
//! number back bit for bit). Arithmetic in the formulas below is f64, evaluated left to right as
//! written; positions use only `+ − × / √` and decode bit for bit on every IEEE 754 platform,
//! rotations also use `sin`, `cos` and `atan2` (see `rotation`), whose last bit may
//! differ between math libraries — the encoder keeps θ_max·10⁻⁹ of margin for it.
//!
//! # Stream
//!
//! ```text
//! header   byte 0: the format version (1). A first byte below 0x40 is a format version (an
//!                  unknown one is refused by number); any other first byte means the bytes are
//!                  not an encoded world.
//!          byte 1: flags   1  bounds are a preset
//!                          2  the frame time is 1/n s
//!                          4  the quantisation steps are stored
//!                          8  every object has the same frame count
//!                         16  rotation dynamics follow (free-flight rotation segments exist)
//!                         32  the bounds are decimals (ignored with flag 1)
//!                         64  the motion model is FreeFlightGravity (clear: General)
//!                        128  reserved, written 0
//!          then, in this order, each only where its flag says:
//!          bounds      flag 1: a byte, the preset: 0 Draft (e_max = 5e-3 m, θ_max = 5e-3 rad),
//!                      1 Standard (1e-3, 1e-3), 2 Final (1e-4, 1e-4); else flag 32: e_max and
//!                      θ_max as decimals; else e_max and θ_max as f64s
//!          frame time  flag 2: varint n ≥ 1, frame_dt = 1.0 / n; else f64 frame_dt
//!          steps       flag 4: f64 Δ, f64 Δθ; else Δ = 1.1·e_max, Δθ = 1.1·θ_max
//!          gravity     flag 64 only: a byte G. G & 0x80: g is the well-known vector G & 0x7F:
//!                      0 (0, −9.81, 0), 1 (0, 0, −9.81), 2 (0, −9.80665, 0),
//!                      3 (0, 0, −9.80665); else bit i (0–2) marks a non-zero g[i], and each
//!                      marked component follows in order x, y, z: with G & 0x40 as a decimal
//!                      of its magnitude, negative if bit 3 + i is set; without, as an f64
//!          start codes two bytes k_pos, k_rot (each ≤ 60): the Rice parameters of the start
//!                      values of positions and of orientations
//!          objects     varint N (< 2³²)
//!          frames      flag 8: varint F (< 2³²), every object's frame count
//!          dynamics    flag 16: varint substeps S (1–16), then the angular damping c (1/s): a
//!                      byte 0 (c = 0), or 1 and a varint n (c = n / 1000.0), or 2 and an f64
//!          The header ends with its last field: it has no length.
//! index    N entries, in object order: varint payload length in bytes, then (without flag 8)
//!          varint frame count (< 2³²). The lengths add up to exactly the rest of the stream.
//! payloads the objects' payloads, concatenated in object order
//! ```
//!
//! A reader refuses a header whose frame time, bounds or steps are not finite numbers in
//! (10⁻²⁸⁰, 10²⁸⁰), a gravity that is not finite, or a damping c that is negative, not finite or
//! has `c·frame_dt ≥ 10¹²`. The magic bytes and checksums other containers carry live one layer
//! up: a bus `MotionSegment` names its encoding and carries a CRC32 of these bytes,
//! and a recording keeps that envelope.
//!
//! # Object payload
//!
//! An object of 0 frames has an empty payload. Any other object's payload is one range-coded
//! stream, decodable without any other object's bytes (every model below starts afresh at its
//! first byte). Its symbols, in order:
//!
//! ```text
//! position start      flag POS_RAW: 1 → 3 × f64 (x, y, z); 0 → a start vector with k_pos,
//!                     step Δ/8
//! at rest             if F ≥ 2: flag POS_REST: 1 → the start point holds for the whole track and
//!                     no position segments follow
//! position segments   until frames 1 … F − 1 are covered, each: its type, then
//!   Gravity           length on POS_LEN, linear term b                     (FreeFlightGravity only)
//!   Quadratic         length on POS_LEN, linear term b, quadratic term a
//!   Step              no length (one frame): a lattice vector d on POS_STEP, step Δ, against 0
//!   Linear            length on POS_LEN, linear term b
//!   Rest              length on POS_REST_LEN
//!   Key               no length (one frame): 3 × f64, the frame stored exactly
//! rotation start      flag ROT_RAW: 1 → 4 × f64 (x, y, z, w), normalised; 0 → a start vector
//!                     with k_rot, step Δθ/4
//! at rest             if F ≥ 2: flag ROT_REST, as for positions
//! rotation segments   until frames 1 … F − 1 are covered, each: its type, then
//!   Linear            length on ROT_LEN, angular velocity ω on ROT_W
//!   Quadratic         length on ROT_LEN, ω on ROT_W, angular acceleration α on ROT_ACC
//!   Step              no length: a lattice vector d on ROT_STEP, step Δθ, against 0
//!   Rest              length on ROT_REST_LEN
//!   Key               no length: 4 × f64, normalised
//!   Free              (header flag 16 only) length on ROT_LEN, at most 4096; before the
//!                     object's first free flight only, its principal moments as 3 × 12 direct
//!                     bits (each 1–4095, the largest moment being 4095); ω on ROT_FREE
//! ```
//!
//! **Types** are listed in code order: the rank of a position type is its place among Gravity,
//! Quadratic, Step, Linear, Rest, Key (without Gravity in a General world: 5 types), that of a
//! rotation type among Linear, Quadratic, Step, Rest, Key, Free (without Free unless flag 16).
//! **Lengths** L are values: 0 means "the rest of the track", otherwise 1 ≤ L ≤ the frames not yet
//! covered. A segment of length L starting after frame s covers frames s + 1 … s + L, evaluated at
//! local times u = 1 … L from its start frame (u = 0, the previous segment's end: C⁰ continuity).
//! **Buckets**: a segment of length L has k = ⌈log₂ L⌉; its linear coefficients (b, ω) are
//! lattice vectors at step Δ·2⁻ᵏ (Δθ·2⁻ᵏ), its quadratic ones (a, α) at Δ·4⁻ᵏ (Δθ·4⁻ᵏ): over
//! u ≤ 2ᵏ each term then errs by at most the covering radius of its lattice.
//!
//! ## Symbols
//!
//! The range decoder is the LZMA binary coder. State: `range = 0xFFFF_FFFF`, `code` = the first
//! 4 bytes, big endian (the encoder's first output byte is always 0 and is not stored; a code of
//! 0xFFFF_FFFF is refused). Past the end of the payload the decoder reads zero bytes, at most 8
//! (the encoder drops up to 8 trailing zeros), then fails. *Normalise*: while range < 2²⁴,
//! `range <<= 8`, `code = code << 8 | next byte`.
//!
//! * A **context bit** with a context (p, r) — p the probability of a 0 in units of 2⁻¹⁶, r the
//!   adaptation shift: `bound = (range >> 16)·p`; if code < bound the bit is 0 and range = bound,
//!   else it is 1, code −= bound, range −= bound. Then `p += (t − p) >> r` (arithmetic shift; t =
//!   65 536 after a 0, 0 after a 1), p clamped to 32 … 65 504, r = min(r + 1, 5); then normalise.
//!   A context starts at (32 768, 1) unless said otherwise.
//! * A **direct bit**: `range >>= 1`; the bit is `code ≥ range` (then code −= range); normalise.
//!   n direct bits are an integer, most significant first; an **f64** is 64 direct bits (its IEEE
//!   754 bit pattern).
//! * A **flag** is a context bit; POS_RAW, POS_REST, ROT_RAW and ROT_REST have one context each.
//! * A **type** after the previous type `prev` (initially rank 0) among n types: a context bit of
//!   `same[prev]`; 0 → the type is prev; 1 → three context bits down a tree, `node = 1` then
//!   `node = 2·node + bit` with context `other[prev][node]`, then `o = node − 8`, and the rank is o
//!   if o < prev, else o + 1 (a rank ≥ n is an error). Positions and rotations have their own
//!   contexts (`same`: 8, `other`: 8 × 8).
//! * A **value** on a stream (below) is an unsigned integer v, coded as m = v + 1: its bit length
//!   n + 1 in unary, then the bits below its leading one. The stream's state is an adaptive Rice
//!   parameter k — from sum = the stream's prior, count = 1 — and the contexts
//!   `prefix[2][8]`, starting at p = 9830, 9830, 13107, 29491, 39321, 42598, 42598, 42598 with
//!   r = 2, and `mantissa[20][3]`. Decoding: with class = min(k, 1), n counts context bits of
//!   `prefix[class][clamp(n − k + 3, 0, 7)]` while they are 1, at most 64 (after 64 ones no 0
//!   follows); m = 1; if n ≥ 1, m = 2m + b₁ with b₁ a context bit of `mantissa[min(n, 19)][0]`;
//!   if n ≥ 2, m = 2m + b₂ with context `mantissa[min(n, 19)][1 + b₁]`; if n ≥ 3, m = m·2ⁿ⁻² +
//!   (n − 2 direct bits); v = m − 1 (v ≥ 2⁶⁴ is an error). Then sum += min(v, 2⁴⁰), count += 1;
//!   if count ≥ 4, sum = ⌈sum / 2⌉ and count = ⌊count / 2⌋; k = the smallest integer ≥ 0 with
//!   count·2ᵏ ≥ sum, at most 48.
//! * A **signed value** is a value zig-zag mapped: 0, 1, 2, 3, 4 … → 0, −1, 1, −2, 2 …
//! * A **start value** with the header's parameter k: q = the number of direct 1 bits before a
//!   direct 0, at most 16 (after 16 ones no 0 follows); if q < 16, v = q·2ᵏ + (k direct bits);
//!   else 6 direct bits are n − 1 and v = 2ⁿ⁻¹ + (n − 1 direct bits). Then zig-zag mapped.
//!
//! The streams and the priors (initial sums) of their value models:
//!
//! ```text
//! POS_LEN 24   POS_LINEAR 6   POS_QUADRATIC 6   POS_STEP 3    POS_REST_LEN 24
//! ROT_LEN 12   ROT_W 12       ROT_ACC 6         ROT_STEP 3    ROT_REST_LEN 12   ROT_FREE 12
//! ```
//!
//! ## Lattice vectors
//!
//! Every quantised 3-vector is a point of the body-centred cubic lattice with the covering
//! radius √3/2·s of the cubic lattice of step s (the BCC lattice is the thinnest covering of
//! space: 1.86× fewer points than the cubic one at the same worst-case error; see
//! `segment::Lattice`). With `a = s·B`, B = 1.5491933384829668 (2√3/√5), its points are
//! `K·(a·0.5)` per axis for integer coordinates K whose three components share one parity c.
//!
//! * A **lattice vector** on a stream at step s against a prediction p (a 3-vector): c = 1 direct
//!   bit; per axis i, P_i = round((p_i − off)/a) with off = 0.5·a if c = 1 else 0 (round half
//!   away from zero; a quotient beyond ±2⁵² clamps there, a non-finite one gives 0); then three
//!   signed values r_i on the stream; k_i = P_i + r_i (|k_i| ≤ 2⁵², else an error); K_i = 2k_i + c.
//! * A **start vector** at step s with parameter k: c = 1 direct bit, then three start values
//!   k_i (|k_i| ≤ 2⁵²), K_i = 2k_i + c.
//!
//! ## Decoding positions
//!
//! With Δ the header's step and gravity term `γ_i = g_i·(dt·dt)·0.5` (0 in a General world), the
//! decoder keeps the current point c (frame 0: the start, which must be finite), the decoded frame
//! before it (none at first), a predicted velocity v = 0 and a predicted quadratic term â = γ.
//!
//! * Quadratic, Linear, Gravity: b against v; a against â (Quadratic), a = 0 (Linear) or a = γ
//!   (Gravity). Frame u: `c_i + (b_i·u + a_i·(u·u))`. Then v_i = `b_i + 2·a_i·L` and â = a.
//! * Step: the prediction e = c + (c − before) per axis, or c + v at the start of a track; the
//!   frame is e + d. Key: the stored frame (which must be finite). Both cover one frame and set
//!   v = frame − c.
//! * Rest: every frame is c; v = 0.
//!
//! After a segment, "before" is its frame L − 1 (for L = 1 the point c itself) and c its frame L
//! (which must be finite).
//!
//! ## Decoding rotations
//!
//! Quaternions are (x, y, z, w); `exp`, `log`, `⊗` (Hamilton product), `normalise` and
//! `rotate(q, v)` are those of `rotation`; a stored quaternion whose squared norm is not
//! finite or ≤ 10⁻²⁰⁰ is an error. The start orientation from a start vector K is
//! `normalise(exp(K·((Δθ/4·B)·0.5)))` (the identity if that fails). The decoder keeps the current
//! orientation q, the frame before it, a predicted angular velocity ŵ = 0 and acceleration α̂ = 0.
//!
//! * Linear (ω against ŵ), Quadratic (and α against α̂): frame u is `normalise(exp(r) ⊗ q)` (q if
//!   that fails) with r = `ω·u` or `ω_i·u + α_i·(u·u)`. Then ŵ = ω (Linear) or `ω_i + 2·α_i·L`
//!   and α̂ = α (Quadratic).
//! * Step: the prediction e = log(q ⊗ before⁻¹), or ŵ at the start of a track; the segment is a
//!   one-frame Linear one with ω = e + d (and sets ŵ so).
//! * Key: the stored orientation, one frame; ŵ unchanged. Rest: q held; ŵ = 0.
//! * Free (torque-free flight): moments I_i = code_i / 4095.0, J_i = 1 / I_i, damping factor
//!   `d = 1 / (1 + dt·c)`; the body-frame velocity ω_b = rotate(q⁻¹, ω) once, then per frame,
//!   S times with h = 1/S: unless I = (1, 1, 1), the gyroscopic step `l = I∘ω_b`,
//!   `g = ω_b × l`, `l' = l − g·h`, and if |l'|² is finite and > 0, `σ = √(|l|²/|l'|²)` and
//!   `ω_b = (l'_i·σ·J_i)` (if all finite); then `n = q ⊗ (ω_b·(0.5·h), 1)` and, if |n|² is
//!   finite and > 0, `q = n·(1/√|n|²)`; after the S substeps `ω_b = ω_b·d`. Frame u is the
//!   orientation after u frames; ŵ = rotate(q, ω_b) at the flight's end (`segment::FreeDynamics`
//!   has the exact operation order).
//!
//! # Limits
//!
//! Every segment covers at least one frame and every symbol consumes input (no context
//! probability reaches 0 or 1), so a hostile payload ends in an error after a number of segments
//! proportional to its length. A free flight costs its length in simulated frames; readers bound
//! that work by their frame limit (`DecodeLimits`).

use crate::arith::ValueModel;
use crate::bits::{read_varint, write_varint};
use crate::error::CodecError;
use crate::params::{MotionModel, Quality, STEP_RATIO};

/// The format version this build writes and reads: the stream's first byte.
pub const FORMAT_VERSION: u8 = 1;
/// A first byte below this is a format version; any other is not an encoded world. Keeps text,
/// JSON and other containers (all starting with printable ASCII) apart from worlds.
pub(crate) const VERSION_LIMIT: u8 = 0x40;

/// The integer streams of an object's payload, each with its own value model (see the module
/// doc). Positions: segment lengths, linear and quadratic coefficients, steps, rest lengths.
pub(crate) const S_POS_LEN: usize = 0;
pub(crate) const S_POS_LINEAR: usize = 1;
pub(crate) const S_POS_QUADRATIC: usize = 2;
pub(crate) const S_POS_STEP: usize = 3;
/// A rest lasts until the next impact, a curve until the bound breaks: their lengths are coded
/// apart.
pub(crate) const S_POS_REST_LEN: usize = 4;
/// Rotations: segment lengths, angular velocities, angular accelerations, steps, rest lengths.
pub(crate) const S_ROT_LEN: usize = 5;
pub(crate) const S_ROT_W: usize = 6;
pub(crate) const S_ROT_ACC: usize = 7;
pub(crate) const S_ROT_STEP: usize = 8;
pub(crate) const S_ROT_REST_LEN: usize = 9;
/// The start angular velocities of free flights: their own statistics (a flight starts after an
/// impact, where the last velocity predicts little).
pub(crate) const S_ROT_FREE: usize = 10;
pub(crate) const STREAMS: usize = 11;

/// Each stream's prior: the expected value before it has seen any. Only a prior — the models
/// adapt within a few values — chosen from the shipped scenes at Standard quality. (Every axis
/// of a vector is on its vector's stream; separate streams per axis measured no better.)
const PRIORS: [u64; STREAMS] = [24, 6, 6, 3, 24, 12, 12, 6, 3, 12, 12];

/// The value models of one object's payload, all at their priors.
pub(crate) fn value_models() -> Box<[ValueModel; STREAMS]> {
    Box::new(PRIORS.map(ValueModel::new))
}

/// The flags of an object's payload, one context each (see the module doc).
pub(crate) const FLAG_POS_RAW: usize = 0;
pub(crate) const FLAG_POS_REST: usize = 1;
pub(crate) const FLAG_ROT_RAW: usize = 2;
pub(crate) const FLAG_ROT_REST: usize = 3;

/// Largest start Rice parameter a header may hold.
pub(crate) const MAX_START_K: u32 = 60;

const FLAG_PRESET: u8 = 1;
const FLAG_RATE: u8 = 2;
const FLAG_STEPS: u8 = 4;
const FLAG_COMMON_FRAMES: u8 = 8;
/// The world carries rotation dynamics (free-flight rotation segments).
const FLAG_DYNAMICS: u8 = 16;
/// The bounds are decimals.
const FLAG_DECIMAL_BOUNDS: u8 = 32;
/// The motion model is FreeFlightGravity.
const FLAG_GRAVITY_MODEL: u8 = 64;
/// Most substeps per frame a header may hold (each costs decoding time per simulated frame;
/// rapier's default is 4).
pub(crate) const MAX_SUBSTEPS: u32 = 16;
const PRESETS: [Quality; 3] = [Quality::Draft, Quality::Standard, Quality::Final];

/// Gravity vectors a header names by number (the gravity byte is `0x80 | i`) instead of storing
/// them: y-up and z-up at 9.81 and at standard gravity 9.80665 m/s². A ~1 s segment of a
/// one-body scene restates its header every second, so bytes matter.
const KNOWN_GRAVITY: [[f64; 3]; 4] = [
    [0.0, -9.81, 0.0],
    [0.0, 0.0, -9.81],
    [0.0, -9.80665, 0.0],
    [0.0, 0.0, -9.80665],
];
const GRAVITY_KNOWN: u8 = 0x80;
/// The gravity byte's non-zero components are decimals, bits 3–5 their signs.
const GRAVITY_DECIMAL: u8 = 0x40;

/// The powers of ten a decimal divides by; every one is exact in f64.
const POW10: [f64; 23] = [
    1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16,
    1e17, 1e18, 1e19, 1e20, 1e21, 1e22,
];
/// Largest mantissa of a decimal: integers up to 2⁵³ are exact in f64.
const MAX_DECIMAL_MANTISSA: u64 = 1 << 53;

/// `x > 0` as a decimal `(m, k)`, `x = m / 10ᵏ` with the smallest k, if the division
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

/// Reads a decimal; a zero or too large mantissa or exponent is an error naming `field`.
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
    pub model: MotionModel,
    pub object_count: u32,
    pub frame_dt: f64,
    pub e_max: f64,
    pub theta_max: f64,
    pub pos_step: f64,
    pub rot_step: f64,
    /// The frame count shared by every object (then the index omits it).
    pub common_frames: Option<u32>,
    /// The Rice parameters of the start positions and start orientations, chosen for the whole
    /// world (three values per object are too few to adapt to).
    pub start_k: [u32; 2],
    /// The simulator's rotation integration, for free-flight rotation segments.
    pub dynamics: Option<HeaderDynamics>,
}

/// What every free-flight rotation segment of a world shares (the per-object part, the
/// principal moments, is in the object's payload).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct HeaderDynamics {
    /// Integration substeps per frame, `1..=MAX_SUBSTEPS`.
    pub substeps: u32,
    /// Angular damping coefficient `c` (1/s): angular velocity × `1/(1 + dt·c)` per frame.
    pub angular_damping: f64,
}

/// The steps a header derives from the bounds when it does not store them.
pub(crate) fn derived_steps(e_max: f64, theta_max: f64) -> (f64, f64) {
    (STEP_RATIO * e_max, STEP_RATIO * theta_max)
}

impl Header {
    /// Writes the header (see the module doc).
    pub(crate) fn write(&self, out: &mut Vec<u8>) {
        out.push(FORMAT_VERSION);
        let preset = PRESETS
            .iter()
            .position(|q| q.bounds() == (self.e_max, self.theta_max));
        let rate = (1.0 / self.frame_dt).round();
        let rate = (rate >= 1.0 && rate <= f64::from(u32::MAX) && 1.0 / rate == self.frame_dt)
            .then_some(rate as u64);
        let steps_stored =
            derived_steps(self.e_max, self.theta_max) != (self.pos_step, self.rot_step);
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
        flags |= if matches!(self.model, MotionModel::FreeFlightGravity { .. }) {
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

    /// Parses and validates a header; returns it and its length in bytes.
    pub(crate) fn parse(bytes: &[u8]) -> Result<(Self, usize), CodecError> {
        need(bytes, 1)?;
        match bytes[0] {
            FORMAT_VERSION => {}
            found if found < VERSION_LIMIT => {
                return Err(CodecError::UnsupportedVersion {
                    found,
                    supported: FORMAT_VERSION,
                });
            }
            found => return Err(CodecError::NotAWorld { found }),
        }
        let (header, len) = Self::parse_fields(bytes)?;
        Ok((header.validate()?, len))
    }

    /// The fields after the version byte; the header ends where its last field does.
    fn parse_fields(h: &[u8]) -> Result<(Self, usize), CodecError> {
        let mut at = 1;
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
        let flags = byte(&mut at)?;
        let (e_max, theta_max) = if flags & FLAG_PRESET != 0 {
            let i = byte(&mut at)?;
            PRESETS
                .get(usize::from(i))
                .ok_or(CodecError::BadHeaderField {
                    field: "preset",
                    value: f64::from(i),
                })?
                .bounds()
        } else if flags & FLAG_DECIMAL_BOUNDS != 0 {
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
            derived_steps(e_max, theta_max)
        };
        let mut g = [0.0; 3];
        if flags & FLAG_GRAVITY_MODEL != 0 {
            let mask = byte(&mut at)?;
            if mask & GRAVITY_KNOWN != 0 {
                g = *KNOWN_GRAVITY
                    .get(usize::from(mask & !GRAVITY_KNOWN))
                    .ok_or(CodecError::BadHeaderField {
                        field: "gravity",
                        value: f64::from(mask),
                    })?;
            } else if mask & GRAVITY_DECIMAL != 0 {
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
        let dynamics = if flags & FLAG_DYNAMICS != 0 {
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
        let model = if flags & FLAG_GRAVITY_MODEL != 0 {
            MotionModel::FreeFlightGravity { g }
        } else {
            MotionModel::General
        };
        let header = Header {
            model,
            object_count,
            frame_dt,
            e_max,
            theta_max,
            pos_step,
            rot_step,
            common_frames,
            start_k,
            dynamics,
        };
        Ok((header, at))
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

#[cfg(test)]
mod tests {
    use super::*;

    fn header(
        model: MotionModel,
        frame_dt: f64,
        bounds: (f64, f64),
        common: Option<u32>,
    ) -> Header {
        let (pos_step, rot_step) = derived_steps(bounds.0, bounds.1);
        Header {
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
        assert_eq!(Header::parse(out).unwrap(), (*h, out.len()));
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

    /// Bounds other than a preset and gravities other than the well-known vectors cost a few
    /// bytes when they are decimals, and read back exactly; bad decimals are errors naming
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
        // count 2, frame count 1.
        assert_eq!(out.len(), 19);
        assert_eq!(out[1] & FLAG_DECIMAL_BOUNDS, FLAG_DECIMAL_BOUNDS);
        reads_back(&h, &out);
        // Not decimals: the f64s (16 + 24 bytes more).
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
            // Rotation dynamics: no damping (2 bytes more), a decimal damping (4), any other
            // (10).
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
