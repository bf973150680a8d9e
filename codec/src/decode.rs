//! Reading encoded worlds: the whole world, one object, or one object at one time — the last two
//! touch only that object's bytes (found through the index), never the rest of the world.
//!
//! Robustness contract: any byte string yields `Ok` or `Err`, never a panic. Every read is
//! bounds-checked; every loop consumes input or ends; allocations are bounded by
//! [`DecodeLimits`] (a compressed resting body legitimately expands thousands of times, so the
//! bound cannot come from the input length alone) and are only made once the header and index
//! have been validated against the input length.

use crate::Track;
use crate::bits::{BitReader, RICE_K_BITS};
use crate::error::CodecError;
use crate::format::{
    Header, INDEX_ENTRY_LEN, S_POS_LEN, S_POS_LINEAR, S_POS_QUADRATIC, S_POS_START, S_ROT_LEN,
    S_ROT_START, S_ROT_W, STREAMS,
};
use crate::params::{MotionModel, Quality};
use crate::rotation::{self, Quat, Vec3};
use crate::segment::{
    PositionCoding, PositionCurve, PositionPredictor, QuadraticQ, RotationCurve, RotationPredictor,
    bucket, dequantise3, step_linear, unresidual,
};

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
        let header = Header::parse(bytes)?;
        let n = header.object_count as usize;
        let rest = &bytes[header.header_len..];
        let index_len = n
            .checked_mul(INDEX_ENTRY_LEN)
            .filter(|&l| l <= rest.len())
            .ok_or(CodecError::Truncated {
                at_bit: bytes.len() as u64 * 8,
                needed_bits: (n as u64 * INDEX_ENTRY_LEN as u64)
                    .saturating_sub(rest.len() as u64)
                    .saturating_mul(8),
            })?;
        let (index, payload) = rest.split_at(index_len);
        let mut reader = Self {
            header,
            index,
            payload,
            max_frames: 0,
            limits,
        };
        let mut prev = 0usize;
        for i in 0..n {
            let (offset, frames) = reader.entry(i);
            if offset < prev || offset > payload.len() {
                return Err(CodecError::Corrupt {
                    what: "object offsets must be increasing and inside the payload",
                });
            }
            prev = offset;
            reader.max_frames = reader.max_frames.max(frames);
        }
        Ok(reader)
    }

    fn entry(&self, i: usize) -> (usize, u32) {
        let e = &self.index[i * INDEX_ENTRY_LEN..(i + 1) * INDEX_ENTRY_LEN];
        let offset = u32::from_le_bytes([e[0], e[1], e[2], e[3]]) as usize;
        let frames = u32::from_le_bytes([e[4], e[5], e[6], e[7]]);
        (offset, frames)
    }

    fn object(&self, i: usize) -> Result<(&'a [u8], u32), CodecError> {
        let count = self.object_count();
        if i >= count {
            return Err(CodecError::ObjectOutOfRange { index: i, count });
        }
        let (start, frames) = self.entry(i);
        let end = if i + 1 < count {
            self.entry(i + 1).0
        } else {
            self.payload.len()
        };
        Ok((&self.payload[start..end], frames))
    }

    /// Format version of the input.
    pub fn version(&self) -> u16 {
        self.header.version
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

    fn open(&self, i: usize) -> Result<Option<ObjectStreams<'a>>, CodecError> {
        let (bytes, frames) = self.object(i)?;
        if frames == 0 {
            return Ok(None);
        }
        ObjectStreams::open(bytes, frames, &self.header).map(Some)
    }

    /// Decodes every frame of object `i`.
    pub fn decode_object(&self, i: usize) -> Result<Track, CodecError> {
        let frames = self.object(i)?.1;
        if u64::from(frames) > self.limits.max_object_frames {
            return Err(CodecError::LimitExceeded {
                what: "decode_object",
                requested: u64::from(frames),
                limit: self.limits.max_object_frames,
            });
        }
        let Some(streams) = self.open(i)? else {
            return Ok(Track::default());
        };
        let ObjectStreams {
            mut positions,
            mut rotations,
        } = streams;
        let mut track = Track {
            positions: Vec::with_capacity(frames as usize),
            rotations: Vec::with_capacity(frames as usize),
        };
        track.positions.push(positions.start);
        while let Some(seg) = positions.next_segment()? {
            for u in 1..=seg.len {
                track
                    .positions
                    .push(finite_position(seg.curve.eval(seg.c, f64::from(u)))?);
            }
        }
        track.rotations.push(rotations.start);
        while let Some(seg) = rotations.next_segment()? {
            for u in 1..=seg.len {
                track.rotations.push(seg.curve.eval(seg.q0, f64::from(u)));
            }
        }
        Ok(track)
    }

    /// Decodes every object. Fails before decoding anything if the world exceeds
    /// [`DecodeLimits::max_total_frames`].
    pub fn decode_all(&self) -> Result<Vec<Track>, CodecError> {
        let total: u64 = (0..self.object_count())
            .map(|i| u64::from(self.entry(i).1))
            .sum();
        if total > self.limits.max_total_frames {
            return Err(CodecError::LimitExceeded {
                what: "decode_all",
                requested: total,
                limit: self.limits.max_total_frames,
            });
        }
        (0..self.object_count())
            .map(|i| self.decode_object(i))
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
        let Some(ObjectStreams {
            mut positions,
            mut rotations,
        }) = self.open(i)?
        else {
            return Err(CodecError::Corrupt {
                what: "object has no frames",
            });
        };
        let mut pos = positions.start;
        while let Some(seg) = positions.next_segment()? {
            let s = f64::from(seg.start);
            if f <= s + f64::from(seg.len) {
                pos = seg.curve.eval(seg.c, f - s);
                break;
            }
        }
        let mut rot = rotations.start;
        while let Some(seg) = rotations.next_segment()? {
            let s = f64::from(seg.start);
            if f <= s + f64::from(seg.len) {
                rot = seg.curve.eval(seg.q0, f - s);
                break;
            }
        }
        Ok((finite_position(pos)?, rot))
    }
}

fn finite_position(p: Vec3) -> Result<Vec3, CodecError> {
    if p.iter().all(|v| v.is_finite()) {
        Ok(p)
    } else {
        Err(CodecError::Corrupt {
            what: "decoded position is not finite",
        })
    }
}

fn read_f64(r: &mut BitReader<'_>) -> Result<f64, CodecError> {
    Ok(f64::from_bits(r.read_bits(64)?))
}

/// The two independent bit streams of one object.
struct ObjectStreams<'a> {
    positions: PositionStream<'a>,
    rotations: RotationStream<'a>,
}

impl<'a> ObjectStreams<'a> {
    fn open(bytes: &'a [u8], frames: u32, header: &Header) -> Result<Self, CodecError> {
        let mut r = BitReader::new(bytes);
        let mut ks = [0u32; STREAMS];
        for k in &mut ks {
            *k = r.read_bits(RICE_K_BITS)? as u32;
        }
        let pos_bits = r.read_gamma()?;
        let pos_start = r.pos();
        let rot_start = usize::try_from(pos_bits)
            .ok()
            .and_then(|b| pos_start.checked_add(b))
            .filter(|&e| e <= r.end())
            .ok_or(CodecError::Corrupt {
                what: "position stream longer than the object",
            })?;
        let gravity = match header.model {
            MotionModel::General => None,
            MotionModel::FreeFlightGravity { g } => Some(g),
        };
        let coding = PositionCoding::new(header.pos_step, gravity, header.frame_dt);
        let positions = PositionStream::open(r.sub(pos_start, rot_start)?, ks, coding, frames)?;
        let rotations =
            RotationStream::open(r.sub(rot_start, r.end())?, ks, header.rot_step, frames)?;
        Ok(Self {
            positions,
            rotations,
        })
    }
}

pub(crate) struct PositionSegment {
    pub start: u32,
    pub len: u32,
    pub c: Vec3,
    pub curve: PositionCurve,
}

struct PositionStream<'a> {
    r: BitReader<'a>,
    ks: [u32; STREAMS],
    coding: PositionCoding,
    predictor: PositionPredictor,
    start: Vec3,
    c: Vec3,
    covered: u32,
    steps: u32,
}

impl<'a> PositionStream<'a> {
    fn open(
        mut r: BitReader<'a>,
        ks: [u32; STREAMS],
        coding: PositionCoding,
        frames: u32,
    ) -> Result<Self, CodecError> {
        let start = if r.read_bit()? {
            [read_f64(&mut r)?, read_f64(&mut r)?, read_f64(&mut r)?]
        } else {
            let mut q = [0i64; 3];
            for v in &mut q {
                *v = unresidual(r.read_rice(ks[S_POS_START])?, 0).ok_or(CodecError::Corrupt {
                    what: "start position out of range",
                })?;
            }
            dequantise3(q, coding.start_step())
        };
        let start = finite_position(start)?;
        Ok(Self {
            r,
            ks,
            predictor: PositionPredictor::new(&coding),
            coding,
            start,
            c: start,
            covered: 0,
            steps: frames - 1,
        })
    }

    fn next_segment(&mut self) -> Result<Option<PositionSegment>, CodecError> {
        if self.covered == self.steps {
            return Ok(None);
        }
        let len = self.r.read_rice(self.ks[S_POS_LEN])?;
        let curve = if len == 0 {
            let end = [
                read_f64(&mut self.r)?,
                read_f64(&mut self.r)?,
                read_f64(&mut self.r)?,
            ];
            PositionCurve::Key {
                end: finite_position(end)?,
            }
        } else {
            if len > u64::from(self.steps - self.covered) {
                return Err(CodecError::Corrupt {
                    what: "position segment runs past the end of the track",
                });
            }
            let k = bucket(len as u32);
            let gravity = self.coding.gravity_term.is_some() && self.r.read_bit()?;
            let (pb, pa) = self.predictor.predict(&self.coding, k);
            let bq = self.read_residuals(S_POS_LINEAR, pb)?;
            let aq = if gravity {
                None
            } else {
                Some(self.read_residuals(S_POS_QUADRATIC, pa)?)
            };
            QuadraticQ { bq, aq }.curve(&self.coding, k)
        };
        let len = len.max(1) as u32;
        let seg = PositionSegment {
            start: self.covered,
            len,
            c: self.c,
            curve,
        };
        self.predictor.advance(self.c, len, &curve);
        self.c = finite_position(curve.eval(self.c, f64::from(len)))?;
        self.covered += len;
        Ok(Some(seg))
    }

    fn read_residuals(&mut self, stream: usize, pred: [i64; 3]) -> Result<[i64; 3], CodecError> {
        let mut q = [0i64; 3];
        for (v, p) in q.iter_mut().zip(pred) {
            *v = unresidual(self.r.read_rice(self.ks[stream])?, p).ok_or(CodecError::Corrupt {
                what: "coefficient residual out of range",
            })?;
        }
        Ok(q)
    }
}

pub(crate) struct RotationSegment {
    pub start: u32,
    pub len: u32,
    pub q0: Quat,
    pub curve: RotationCurve,
}

struct RotationStream<'a> {
    r: BitReader<'a>,
    ks: [u32; STREAMS],
    step: f64,
    predictor: RotationPredictor,
    start: Quat,
    q: Quat,
    covered: u32,
    steps: u32,
}

fn read_quat(r: &mut BitReader<'_>) -> Result<Quat, CodecError> {
    let q = [read_f64(r)?, read_f64(r)?, read_f64(r)?, read_f64(r)?];
    rotation::normalise(q).ok_or(CodecError::Corrupt {
        what: "stored quaternion cannot be normalised",
    })
}

impl<'a> RotationStream<'a> {
    fn open(
        mut r: BitReader<'a>,
        ks: [u32; STREAMS],
        step: f64,
        frames: u32,
    ) -> Result<Self, CodecError> {
        let start = if r.read_bit()? {
            read_quat(&mut r)?
        } else {
            let mut q = [0i64; 3];
            for v in &mut q {
                *v = unresidual(r.read_rice(ks[S_ROT_START])?, 0).ok_or(CodecError::Corrupt {
                    what: "start orientation out of range",
                })?;
            }
            start_orientation(q, step)
        };
        Ok(Self {
            r,
            ks,
            step,
            predictor: RotationPredictor::default(),
            start,
            q: start,
            covered: 0,
            steps: frames - 1,
        })
    }

    fn next_segment(&mut self) -> Result<Option<RotationSegment>, CodecError> {
        if self.covered == self.steps {
            return Ok(None);
        }
        let len = self.r.read_rice(self.ks[S_ROT_LEN])?;
        let curve = if len == 0 {
            RotationCurve::Key {
                end: read_quat(&mut self.r)?,
            }
        } else {
            if len > u64::from(self.steps - self.covered) {
                return Err(CodecError::Corrupt {
                    what: "rotation segment runs past the end of the track",
                });
            }
            let k = bucket(len as u32);
            let pred = self.predictor.predict(self.step, k);
            let mut wq = [0i64; 3];
            for (v, p) in wq.iter_mut().zip(pred) {
                *v = unresidual(self.r.read_rice(self.ks[S_ROT_W])?, p).ok_or(
                    CodecError::Corrupt {
                        what: "angular velocity residual out of range",
                    },
                )?;
            }
            RotationCurve::Linear {
                w: dequantise3(wq, step_linear(self.step, k)),
            }
        };
        let len = len.max(1) as u32;
        let seg = RotationSegment {
            start: self.covered,
            len,
            q0: self.q,
            curve,
        };
        self.predictor.advance(&curve);
        self.q = curve.eval(self.q, f64::from(len));
        self.covered += len;
        Ok(Some(seg))
    }
}

/// The decoded first orientation from its quantised rotation vector (shared with the encoder).
pub(crate) fn start_orientation(q: [i64; 3], rot_step: f64) -> Quat {
    let r = dequantise3(q, rot_step / crate::params::START_STEP_DIVISOR);
    rotation::normalise(rotation::exp(r)).unwrap_or(rotation::IDENTITY)
}
