//! The crate's one error type. Messages say what was expected and what was found.

/// Everything that can go wrong while encoding or decoding motion.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum CodecError {
    /// An encoder parameter is out of range (names the field).
    #[error("invalid parameter `{name}` = {value}: {expected}")]
    InvalidParam {
        name: &'static str,
        value: f64,
        expected: &'static str,
    },
    /// A track's position and rotation sequences differ in length.
    #[error("object {object}: {positions} positions but {rotations} rotations")]
    TrackLengthMismatch {
        object: usize,
        positions: usize,
        rotations: usize,
    },
    /// A NaN or infinite sample.
    #[error("object {object}, frame {frame}: non-finite {what}")]
    NonFinite {
        object: usize,
        frame: usize,
        what: &'static str,
    },
    /// A quaternion of (near) zero length cannot be normalised.
    #[error("object {object}, frame {frame}: quaternion has zero length")]
    DegenerateQuaternion { object: usize, frame: usize },
    /// A track longer than the format can index.
    #[error("object {object}: {frames} frames, the format allows at most {max}")]
    TooManyFrames {
        object: usize,
        frames: usize,
        max: usize,
    },
    /// The encoded world does not fit the 32-bit offset index.
    #[error("encoded world payload is {bytes} bytes, the format allows at most {max}")]
    TooLarge { bytes: usize, max: usize },
    /// The first byte is no format version (versions are below 0x40): the input is not an
    /// encoded world (text, another container, a corrupted stream).
    #[error("not an encoded world: the first byte {found:#04x} is no format version")]
    NotAWorld { found: u8 },
    /// A stream of a format version this build does not read (a newer one, or none that exists).
    #[error("unsupported format version {found} (this build reads version {supported})")]
    UnsupportedVersion { found: u8, supported: u8 },
    /// The input ends before a field that must be there.
    #[error("truncated input: {needed_bits} more bits needed at bit {at_bit}")]
    Truncated { at_bit: u64, needed_bits: u64 },
    /// A field holds a value no encoder writes.
    #[error("corrupt stream: {what}")]
    Corrupt { what: &'static str },
    /// A header field holds a value no encoder writes.
    #[error("corrupt header: `{field}` = {value}")]
    BadHeaderField { field: &'static str, value: f64 },
    /// An object index beyond the world.
    #[error("object {index} out of range: the world has {count} objects")]
    ObjectOutOfRange { index: usize, count: usize },
    /// A sample time outside the object's track (or not a number).
    #[error("time {t} s is outside object {object}'s track [0, {duration}] s")]
    TimeOutOfRange {
        object: usize,
        t: f64,
        duration: f64,
    },
    /// Decoding would allocate more than the reader's [`crate::DecodeLimits`] allow.
    #[error("{what}: {requested} frames requested, the decode limit is {limit}")]
    LimitExceeded {
        what: &'static str,
        requested: u64,
        limit: u64,
    },
    /// The encoder's self-check found a decoded frame outside the error bound. This is a bug in
    /// the codec, reported instead of silently storing bad motion.
    #[error(
        "internal: object {object}, frame {frame}: decoded {what} error {found} exceeds the bound {bound}"
    )]
    BoundViolated {
        object: usize,
        frame: usize,
        what: &'static str,
        found: f64,
        bound: f64,
    },
}
