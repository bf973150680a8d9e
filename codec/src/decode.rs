//! Reading encoded worlds: the whole world, one object, or one object at one time — the last two
//! touch only that object's bytes (found through the index), never the rest of the world.
//!
//! Robustness contract: any byte string yields `Ok` or `Err`, never a panic. Every read is
//! bounds-checked; every loop consumes input or ends; allocations are bounded by
//! [`DecodeLimits`] (a compressed resting body legitimately expands thousands of times, so the
//! bound cannot come from the input length alone) and are only made once the header and index
//! have been validated against the input length.

mod object;

use crate::Track;
use crate::bits::read_varint;
use crate::error::CodecError;
use crate::format::{FORMAT_VERSION, Header};
use crate::params::{MotionModel, Quality};
use crate::rotation::{self, Quat, Vec3};
use crate::segment::{Lattice, PositionCurve, RotationCurve};
pub(crate) use object::ObjectStream;

/// Caps on what one decode call may allocate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DecodeLimits {
    /// Most frames [`WorldReader::decode_object`] will produce (56 bytes each).
    pub max_object_frames: u64,
    /// Most object-frames [`WorldReader::decode_all`] will produce.
    pub max_total_frames: u64,
}

impl Default for DecodeLimits {
    /// 2²¹ frames per object (4.9 h at 120 Hz, 117 MB) and 2²³ object-frames per world (470 MB).
    fn default() -> Self {
        Self {
            max_object_frames: 1 << 21,
            max_total_frames: 1 << 23,
        }
    }
}

impl DecodeLimits {
    /// No caps (for trusted input, e.g. the encoder's own self-check).
    pub const fn unlimited() -> Self {
        Self {
            max_object_frames: u64::MAX,
            max_total_frames: u64::MAX,
        }
    }
}

/// Random access to an encoded world. Construction validates the header and the index (O(objects),
/// no allocation); decoding happens on demand.
#[derive(Debug, Clone)]
pub struct WorldReader<'a> {
    header: Header,
    index: &'a [u8],
    payload: &'a [u8],
    max_frames: u32,
    limits: DecodeLimits,
}

impl<'a> WorldReader<'a> {
    /// Parses and validates the header and object index with default [`DecodeLimits`].
    pub fn new(bytes: &'a [u8]) -> Result<Self, CodecError> {
        Self::with_limits(bytes, DecodeLimits::default())
    }

    /// Like [`WorldReader::new`], with explicit allocation caps.
    pub fn with_limits(bytes: &'a [u8], limits: DecodeLimits) -> Result<Self, CodecError> {
        let (header, header_len) = Header::parse(bytes)?;
        let n = header.object_count as usize;
        let rest = &bytes[header_len..];
        // Varint lengths (and frame counts): each entry takes at least one byte, so a hostile
        // object count ends at the end of the input.
        let mut at = 0usize;
        let mut total = 0u64;
        for _ in 0..n {
            total = total.saturating_add(read_varint(rest, &mut at)?);
            if header.common_frames.is_none() {
                let frames = read_varint(rest, &mut at)?;
                if frames > u64::from(u32::MAX) {
                    return Err(CodecError::Corrupt {
                        what: "object frame count above 2^32 − 1",
                    });
                }
            }
        }
        let (index, payload) = rest.split_at(at);
        if total != payload.len() as u64 {
            return Err(CodecError::Corrupt {
                what: "object payload lengths must add up to the payload",
            });
        }
        let mut reader = Self {
            header,
            index,
            payload,
            max_frames: 0,
            limits,
        };
        reader.max_frames = reader.entries().map(|e| e.frames).max().unwrap_or(0);
        Ok(reader)
    }

    /// The index entries in object order (the index has been validated).
    fn entries(&self) -> Entries<'_> {
        Entries {
            reader: self,
            i: 0,
            at: 0,
            offset: 0,
        }
    }

    fn object(&self, i: usize) -> Result<(&'a [u8], u32), CodecError> {
        let count = self.object_count();
        if i >= count {
            return Err(CodecError::ObjectOutOfRange { index: i, count });
        }
        let e = self.entries().nth(i).ok_or(CodecError::Corrupt {
            what: "object index shorter than the object count",
        })?;
        Ok((&self.payload[e.start..e.end], e.frames))
    }

    /// Format version of the input ([`FORMAT_VERSION`], the only one this build opens).
    pub fn version(&self) -> u8 {
        FORMAT_VERSION
    }

    /// Number of objects in the world.
    pub fn object_count(&self) -> usize {
        self.header.object_count as usize
    }

    /// Frames of the longest track (tracks may differ in length).
    pub fn frame_count(&self) -> usize {
        self.max_frames as usize
    }

    /// Frames of object `i`.
    pub fn object_frame_count(&self, i: usize) -> Result<usize, CodecError> {
        Ok(self.object(i)?.1 as usize)
    }

    /// Seconds between frames.
    pub fn frame_dt(&self) -> f64 {
        self.header.frame_dt
    }

    /// The encoder's position bound (metres).
    pub fn e_max(&self) -> f64 {
        self.header.e_max
    }

    /// The encoder's rotation bound (radians).
    pub fn theta_max(&self) -> f64 {
        self.header.theta_max
    }

    /// The motion model the stream was encoded with.
    pub fn model(&self) -> MotionModel {
        self.header.model
    }

    /// The preset whose bounds the stream was encoded with, if any.
    pub fn quality(&self) -> Option<Quality> {
        [Quality::Draft, Quality::Standard, Quality::Final]
            .into_iter()
            .find(|q| q.bounds() == (self.header.e_max, self.header.theta_max))
    }

    fn open(&self, i: usize) -> Result<Option<ObjectStream<'a>>, CodecError> {
        let (bytes, frames) = self.object(i)?;
        if frames == 0 {
            return Ok(None);
        }
        ObjectStream::open(bytes, frames, &self.header, self.limits.max_object_frames).map(Some)
    }

    fn decode_entry(&self, bytes: &'a [u8], frames: u32) -> Result<Track, CodecError> {
        if u64::from(frames) > self.limits.max_object_frames {
            return Err(CodecError::LimitExceeded {
                what: "decode_object",
                requested: u64::from(frames),
                limit: self.limits.max_object_frames,
            });
        }
        if frames == 0 {
            return Ok(Track::default());
        }
        let mut streams =
            ObjectStream::open(bytes, frames, &self.header, self.limits.max_object_frames)?;
        let mut track = Track {
            positions: Vec::with_capacity(frames as usize),
            rotations: Vec::with_capacity(frames as usize),
        };
        track.positions.push(streams.position_start);
        while let Some(seg) = streams.next_position()? {
            for u in 1..=seg.len {
                track
                    .positions
                    .push(finite_position(seg.curve.eval(seg.c, f64::from(u)))?);
            }
        }
        track.rotations.push(streams.start_rotations()?);
        // A free flight's frames come from the simulation that finds its end (the same steps
        // as `eval`, so the same bits); other curves are evaluated here.
        while let Some(seg) = streams.next_rotation(Some(&mut track.rotations))? {
            if matches!(seg.curve, RotationCurve::Free { .. }) {
                continue;
            }
            for u in 1..=seg.len {
                track.rotations.push(seg.curve.eval(seg.q0, f64::from(u)));
            }
        }
        Ok(track)
    }

    /// Decodes every frame of object `i`.
    pub fn decode_object(&self, i: usize) -> Result<Track, CodecError> {
        let (bytes, frames) = self.object(i)?;
        self.decode_entry(bytes, frames)
    }

    /// Every object's segment stream in turn, `None` for an object without frames, with its
    /// frame count (one pass over the index). For the encoder's self-check, which checks each
    /// decoded frame as the segments produce it instead of collecting tracks first.
    pub(crate) fn streams(
        &self,
    ) -> impl Iterator<Item = Result<(u32, Option<ObjectStream<'a>>), CodecError>> + '_ {
        self.entries().map(|e| {
            if e.frames == 0 {
                return Ok((0, None));
            }
            let bytes = &self.payload[e.start..e.end];
            ObjectStream::open(bytes, e.frames, &self.header, self.limits.max_object_frames)
                .map(|s| (e.frames, Some(s)))
        })
    }

    /// Decodes every object. Fails before decoding anything if the world exceeds
    /// [`DecodeLimits::max_total_frames`].
    pub fn decode_all(&self) -> Result<Vec<Track>, CodecError> {
        let total: u64 = self.entries().map(|e| u64::from(e.frames)).sum();
        if total > self.limits.max_total_frames {
            return Err(CodecError::LimitExceeded {
                what: "decode_all",
                requested: total,
                limit: self.limits.max_total_frames,
            });
        }
        self.entries()
            .map(|e| self.decode_entry(&self.payload[e.start..e.end], e.frames))
            .collect()
    }

    /// Position and orientation of object `i` at time `t` seconds (frame 0 at t = 0), read
    /// without allocating and without touching other objects. Between frames the spline itself is
    /// evaluated; times within 1e-9 frames of a frame return that frame exactly.
    pub fn sample(&self, i: usize, t: f64) -> Result<(Vec3, Quat), CodecError> {
        let frames = self.object(i)?.1;
        let last = f64::from(frames.saturating_sub(1));
        let duration = last * self.header.frame_dt;
        let f = t / self.header.frame_dt;
        let out_of_range = || CodecError::TimeOutOfRange {
            object: i,
            t,
            duration,
        };
        if frames == 0 || !f.is_finite() {
            return Err(out_of_range());
        }
        let r = f.round();
        let f = if (f - r).abs() <= 1e-9 * r.abs().max(1.0) {
            r
        } else {
            f
        };
        if !(0.0..=last).contains(&f) {
            return Err(out_of_range());
        }
        self.sample_at(i, f)
    }

    /// Exact decoded position and orientation of object `i` at integer `frame`.
    pub fn sample_frame(&self, i: usize, frame: u32) -> Result<(Vec3, Quat), CodecError> {
        let frames = self.object(i)?.1;
        if frame >= frames {
            return Err(CodecError::TimeOutOfRange {
                object: i,
                t: f64::from(frame) * self.header.frame_dt,
                duration: f64::from(frames.saturating_sub(1)) * self.header.frame_dt,
            });
        }
        self.sample_at(i, f64::from(frame))
    }

    fn sample_at(&self, i: usize, f: f64) -> Result<(Vec3, Quat), CodecError> {
        let Some(mut streams) = self.open(i)? else {
            return Err(CodecError::Corrupt {
                what: "object has no frames",
            });
        };
        let mut pos = streams.position_start;
        while let Some(seg) = streams.next_position()? {
            let s = f64::from(seg.start);
            if f <= s + f64::from(seg.len) {
                pos = seg.curve.eval(seg.c, f - s);
                break;
            }
        }
        let mut rot = streams.start_rotations()?;
        while let Some(seg) = streams.next_rotation(None)? {
            let s = f64::from(seg.start);
            if f <= s + f64::from(seg.len) {
                rot = seg.curve.eval(seg.q0, f - s);
                break;
            }
        }
        Ok((finite_position(pos)?, rot))
    }
}

/// One object's place in the payload.
struct Entry {
    start: usize,
    end: usize,
    frames: u32,
}

/// Walks a validated index.
struct Entries<'r> {
    reader: &'r WorldReader<'r>,
    i: usize,
    /// Byte position in the index.
    at: usize,
    /// Payload offset of object `i`.
    offset: usize,
}

impl Iterator for Entries<'_> {
    type Item = Entry;

    fn next(&mut self) -> Option<Entry> {
        let r = self.reader;
        let n = r.object_count();
        if self.i >= n {
            return None;
        }
        self.i += 1;
        let len = read_varint(r.index, &mut self.at).ok()? as usize;
        let frames = match r.header.common_frames {
            Some(f) => f,
            None => read_varint(r.index, &mut self.at).ok()? as u32,
        };
        let start = self.offset;
        self.offset += len;
        Some(Entry {
            start,
            end: self.offset,
            frames,
        })
    }
}

pub(crate) fn finite_position(p: Vec3) -> Result<Vec3, CodecError> {
    if p.iter().all(|v| v.is_finite()) {
        Ok(p)
    } else {
        Err(CodecError::Corrupt {
            what: "decoded position is not finite",
        })
    }
}

pub(crate) struct PositionSegment {
    pub start: u32,
    pub len: u32,
    pub c: Vec3,
    pub curve: PositionCurve,
}

pub(crate) struct RotationSegment {
    pub start: u32,
    pub len: u32,
    pub q0: Quat,
    pub curve: RotationCurve,
}

/// The decoded first orientation from its quantised rotation vector (lattice coordinates;
/// shared with the encoder). `start_step`: the rotation step over its start divisor.
pub(crate) fn start_orientation(q: [i64; 3], start_step: f64, lattice: Lattice) -> Quat {
    let r = lattice.point(q, start_step);
    rotation::normalise(rotation::exp(r)).unwrap_or(rotation::IDENTITY)
}
