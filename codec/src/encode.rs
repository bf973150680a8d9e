//! Encoding a world: validate, fit segments per object (positions and rotations separately, §4.3),
//! Rice-code them, assemble header + index + payloads, then decode the result and check the bound
//! on every frame before handing it out.

use crate::bits::{BitWriter, RICE_K_BITS, best_rice_k, zigzag};
use crate::decode::{DecodeLimits, WorldReader, start_orientation};
use crate::error::CodecError;
use crate::fit::{CORRECTIONS, RotationScratch, fit_position, fit_rotation};
use crate::format::{
    Header, INDEX_ENTRY_LEN, S_POS_LEN, S_POS_LINEAR, S_POS_QUADRATIC, S_POS_START, S_ROT_LEN,
    S_ROT_START, S_ROT_W, STREAMS,
};
use crate::lowres::LowResPath;
use crate::params::{EncodeParams, MAX_TRACK_FRAMES, MotionModel, ROT_BOUND_MARGIN};
use crate::rotation::{self, Quat, Vec3};
use crate::segment::{
    PositionCoding, PositionCurve, PositionPredictor, RotationCurve, RotationPredictor, bucket,
    dequantise3, quantise3, residual,
};

/// One object's motion, sampled every `frame_dt`: centre-of-mass positions and unit quaternions
/// `[x, y, z, w]`. Both vectors have the same length.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Track {
    pub positions: Vec<[f64; 3]>,
    pub rotations: Vec<[f64; 4]>,
}

impl Track {
    /// Number of frames.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// `true` for a track without frames.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }
}

/// What [`encode_world`] produces.
#[derive(Debug, Clone, PartialEq)]
pub struct EncodedWorld {
    /// The versioned bitstream (read it with [`WorldReader`]).
    pub bytes: Vec<u8>,
    /// One uncompressed low-rate polyline per object, in object order.
    pub lowres: Vec<LowResPath>,
    /// Sizes, segment counts and the errors measured on the decoded stream.
    pub stats: EncodeStats,
}

/// Measurements of one encode. The errors are measured by decoding the produced bytes.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct EncodeStats {
    pub objects: usize,
    /// Σ frames over objects.
    pub object_frames: u64,
    /// Encoded size, header and index included.
    pub bytes: usize,
    /// Size of the same motion as 7 × f32 per object-frame.
    pub raw_f32_bytes: u64,
    pub position_segments: u64,
    pub rotation_segments: u64,
    /// Segments that fell back to an exactly stored frame.
    pub key_segments: u64,
    /// Largest Euclidean position error over all decoded frames (metres).
    pub max_position_error: f64,
    /// Largest rotation angle error over all decoded frames (radians).
    pub max_rotation_error: f64,
}

impl EncodeStats {
    /// Compression ratio against raw f32 frames.
    pub fn ratio(&self) -> f64 {
        self.raw_f32_bytes as f64 / self.bytes.max(1) as f64
    }

    /// Encoded bytes per second of motion of one object.
    pub fn bytes_per_object_second(&self, frame_dt: f64) -> f64 {
        self.bytes as f64 / (self.object_frames as f64 * frame_dt).max(f64::MIN_POSITIVE)
    }
}

/// Encodes all tracks of one world. Guarantees, for every object and frame, a decoded position
/// within `e_max` (Euclidean) and a decoded orientation within `theta_max` (angle of the residual
/// rotation) of the input, with input quaternions normalised and `q ≡ −q`.
pub fn encode_world(tracks: &[Track], p: &EncodeParams) -> Result<EncodedWorld, CodecError> {
    p.validate()?;
    let object_count = u32::try_from(tracks.len()).map_err(|_| CodecError::InvalidParam {
        name: "tracks.len()",
        value: tracks.len() as f64,
        expected: "at most 2^32 − 1 objects",
    })?;
    let header = Header {
        version: crate::format::FORMAT_VERSION,
        header_len: crate::format::HEADER_LEN_V1,
        model: p.model,
        object_count,
        frame_dt: p.frame_dt,
        e_max: p.e_max,
        theta_max: p.theta_max,
        pos_step: p.pos_step(),
        rot_step: p.rot_step(),
    };
    let gravity = match p.model {
        MotionModel::General => None,
        MotionModel::FreeFlightGravity { g } => Some(g),
    };
    let coding = PositionCoding::new(header.pos_step, gravity, p.frame_dt);
    let theta_lim = p.theta_max * (1.0 - ROT_BOUND_MARGIN);

    let mut stats = EncodeStats {
        objects: tracks.len(),
        ..EncodeStats::default()
    };
    let mut payload = Vec::new();
    let mut index = Vec::with_capacity(tracks.len() * INDEX_ENTRY_LEN);
    for (object, track) in tracks.iter().enumerate() {
        let rotations = validate_track(object, track)?;
        let offset = u32::try_from(payload.len()).map_err(|_| CodecError::TooLarge {
            bytes: payload.len(),
            max: u32::MAX as usize,
        })?;
        index.extend_from_slice(&offset.to_le_bytes());
        index.extend_from_slice(&(track.len() as u32).to_le_bytes());
        stats.object_frames += track.len() as u64;
        if track.is_empty() {
            continue;
        }
        let mut tokens = Tokens::default();
        encode_positions(&track.positions, &coding, p.e_max, &mut tokens, &mut stats);
        encode_rotations(
            &rotations,
            header.rot_step,
            theta_lim,
            &mut tokens,
            &mut stats,
        );
        payload.extend_from_slice(&tokens.into_bytes());
    }
    let mut bytes = Vec::with_capacity(header.header_len + index.len() + payload.len());
    header.write(&mut bytes);
    bytes.extend_from_slice(&index);
    bytes.extend_from_slice(&payload);
    stats.bytes = bytes.len();
    stats.raw_f32_bytes = stats.object_frames * crate::baseline::RAW_BYTES_PER_OBJECT_FRAME as u64;

    // Self-check through the public reader: what we measure is what every reader will see.
    let reader = WorldReader::with_limits(&bytes, DecodeLimits::unlimited())?;
    let mut lowres = Vec::with_capacity(tracks.len());
    for (object, track) in tracks.iter().enumerate() {
        let decoded = reader.decode_object(object)?;
        for (frame, ((d, x), (dq, q))) in decoded
            .positions
            .iter()
            .zip(&track.positions)
            .zip(decoded.rotations.iter().zip(&track.rotations))
            .enumerate()
        {
            let e = rotation::norm3(std::array::from_fn(|i| d[i] - x[i]));
            // Validated above, so normalisation succeeds.
            let q = rotation::normalise(*q).unwrap_or(rotation::IDENTITY);
            let a = rotation::angle_between(*dq, q);
            for (what, found, bound) in [("position", e, p.e_max), ("rotation", a, p.theta_max)] {
                if found > bound || found.is_nan() {
                    return Err(CodecError::BoundViolated {
                        object,
                        frame,
                        what,
                        found,
                        bound,
                    });
                }
            }
            stats.max_position_error = stats.max_position_error.max(e);
            stats.max_rotation_error = stats.max_rotation_error.max(a);
        }
        lowres.push(LowResPath::from_positions(
            &decoded.positions,
            p.frame_dt,
            p.lowres_hz,
        ));
    }
    Ok(EncodedWorld {
        bytes,
        lowres,
        stats,
    })
}

/// Checks lengths and finiteness; returns the normalised rotations.
fn validate_track(object: usize, track: &Track) -> Result<Vec<Quat>, CodecError> {
    if track.positions.len() != track.rotations.len() {
        return Err(CodecError::TrackLengthMismatch {
            object,
            positions: track.positions.len(),
            rotations: track.rotations.len(),
        });
    }
    if track.len() > MAX_TRACK_FRAMES {
        return Err(CodecError::TooManyFrames {
            object,
            frames: track.len(),
            max: MAX_TRACK_FRAMES,
        });
    }
    if let Some(frame) = track
        .positions
        .iter()
        .position(|p| !p.iter().all(|v| v.is_finite()))
    {
        return Err(CodecError::NonFinite {
            object,
            frame,
            what: "position",
        });
    }
    track
        .rotations
        .iter()
        .enumerate()
        .map(|(frame, q)| {
            if !q.iter().all(|v| v.is_finite()) {
                return Err(CodecError::NonFinite {
                    object,
                    frame,
                    what: "rotation",
                });
            }
            rotation::normalise(*q).ok_or(CodecError::DegenerateQuaternion { object, frame })
        })
        .collect()
}

/// A symbol of an object's bit stream, collected first so that each Rice stream's parameter can
/// be chosen from all of its values before anything is written.
#[derive(Debug, Clone, Copy)]
enum Token {
    Rice { stream: usize, value: u64 },
    Bits { value: u64, n: u32 },
}

#[derive(Default)]
struct Tokens {
    position: Vec<Token>,
    rotation: Vec<Token>,
}

impl Tokens {
    fn into_bytes(self) -> Vec<u8> {
        let mut per_stream: [Vec<u64>; STREAMS] = Default::default();
        for t in self.position.iter().chain(&self.rotation) {
            if let Token::Rice { stream, value } = *t {
                per_stream[stream].push(value);
            }
        }
        let ks: [u32; STREAMS] = std::array::from_fn(|s| best_rice_k(&per_stream[s]));
        let write = |tokens: &[Token]| {
            let mut w = BitWriter::new();
            for t in tokens {
                match *t {
                    Token::Rice { stream, value } => w.write_rice(value, ks[stream]),
                    Token::Bits { value, n } => w.write_bits(value, n),
                }
            }
            w
        };
        let pos = write(&self.position);
        let rot = write(&self.rotation);
        let mut out = BitWriter::new();
        for k in ks {
            out.write_bits(u64::from(k), RICE_K_BITS);
        }
        out.write_gamma(pos.bit_len());
        out.append(&pos);
        out.append(&rot);
        out.into_bytes()
    }
}

fn raw3(tokens: &mut Vec<Token>, v: Vec3) {
    for x in v {
        tokens.push(Token::Bits {
            value: x.to_bits(),
            n: 64,
        });
    }
}

fn encode_positions(
    x: &[Vec3],
    coding: &PositionCoding,
    e_max: f64,
    tokens: &mut Tokens,
    stats: &mut EncodeStats,
) {
    let out = &mut tokens.position;
    // The constant term, stored once per object (C⁰ continuity, §4.3).
    let start_step = coding.start_step();
    let quantised =
        quantise3(x[0], start_step).filter(|&q| dist(dequantise3(q, start_step), x[0]) <= e_max);
    let mut c = match quantised {
        Some(q) => {
            out.push(Token::Bits { value: 0, n: 1 });
            for v in q {
                out.push(Token::Rice {
                    stream: S_POS_START,
                    value: zigzag(v),
                });
            }
            dequantise3(q, start_step)
        }
        None => {
            out.push(Token::Bits { value: 1, n: 1 });
            raw3(out, x[0]);
            x[0]
        }
    };
    let mut predictor = PositionPredictor::new(coding);
    let mut s = 0;
    while s + 1 < x.len() {
        // Longest wins; on a tie the gravity segment, which stores three coefficients fewer.
        let chosen = [false, true]
            .into_iter()
            .flat_map(|gravity| {
                CORRECTIONS
                    .iter()
                    .filter_map(move |&k| fit_position(x, s, c, gravity, k, coding, e_max))
            })
            .max_by_key(|f| (f.len, f.coeffs.aq.is_none()));
        let (len, curve) = match chosen {
            Some(f) => {
                let k = bucket(f.len);
                let (pb, pa) = predictor.predict(coding, k);
                out.push(Token::Rice {
                    stream: S_POS_LEN,
                    value: u64::from(f.len),
                });
                if coding.gravity_term.is_some() {
                    out.push(Token::Bits {
                        value: u64::from(f.coeffs.aq.is_none()),
                        n: 1,
                    });
                }
                for (q, p) in f.coeffs.bq.into_iter().zip(pb) {
                    out.push(Token::Rice {
                        stream: S_POS_LINEAR,
                        value: residual(q, p),
                    });
                }
                if let Some(aq) = f.coeffs.aq {
                    for (q, p) in aq.into_iter().zip(pa) {
                        out.push(Token::Rice {
                            stream: S_POS_QUADRATIC,
                            value: residual(q, p),
                        });
                    }
                }
                (f.len, f.curve)
            }
            None => {
                // No quantised curve reaches even the next frame: store it exactly.
                out.push(Token::Rice {
                    stream: S_POS_LEN,
                    value: 0,
                });
                raw3(out, x[s + 1]);
                stats.key_segments += 1;
                (1, PositionCurve::Key { end: x[s + 1] })
            }
        };
        stats.position_segments += 1;
        predictor.advance(c, len, &curve);
        c = curve.eval(c, f64::from(len));
        s += len as usize;
    }
}

fn encode_rotations(
    q: &[Quat],
    rot_step: f64,
    theta_lim: f64,
    tokens: &mut Tokens,
    stats: &mut EncodeStats,
) {
    let out = &mut tokens.rotation;
    let start_step = rot_step / crate::params::START_STEP_DIVISOR;
    let quantised = quantise3(rotation::log(q[0]), start_step)
        .filter(|&v| rotation::angle_between(start_orientation(v, rot_step), q[0]) <= theta_lim);
    let mut q0 = match quantised {
        Some(v) => {
            out.push(Token::Bits { value: 0, n: 1 });
            for x in v {
                out.push(Token::Rice {
                    stream: S_ROT_START,
                    value: zigzag(x),
                });
            }
            start_orientation(v, rot_step)
        }
        None => {
            out.push(Token::Bits { value: 1, n: 1 });
            raw_quat(out, q[0])
        }
    };
    let mut predictor = RotationPredictor::default();
    let mut scratch = RotationScratch::default();
    let mut s = 0;
    while s + 1 < q.len() {
        let fit = CORRECTIONS
            .iter()
            .filter_map(|&k| fit_rotation(q, s, q0, k, rot_step, theta_lim, &mut scratch))
            .max_by_key(|f| f.len);
        let (len, curve) = match fit {
            Some(f) => {
                let pred = predictor.predict(rot_step, bucket(f.len));
                out.push(Token::Rice {
                    stream: S_ROT_LEN,
                    value: u64::from(f.len),
                });
                for (v, p) in f.wq.into_iter().zip(pred) {
                    out.push(Token::Rice {
                        stream: S_ROT_W,
                        value: residual(v, p),
                    });
                }
                (f.len, f.curve)
            }
            None => {
                out.push(Token::Rice {
                    stream: S_ROT_LEN,
                    value: 0,
                });
                stats.key_segments += 1;
                (
                    1,
                    RotationCurve::Key {
                        end: raw_quat(out, q[s + 1]),
                    },
                )
            }
        };
        stats.rotation_segments += 1;
        predictor.advance(&curve);
        q0 = curve.eval(q0, f64::from(len));
        s += len as usize;
    }
}

/// Stores `q` raw and returns what the decoder will read back (it re-normalises).
fn raw_quat(out: &mut Vec<Token>, q: Quat) -> Quat {
    for x in q {
        out.push(Token::Bits {
            value: x.to_bits(),
            n: 64,
        });
    }
    rotation::normalise(q).unwrap_or(rotation::IDENTITY)
}

fn dist(a: Vec3, b: Vec3) -> f64 {
    rotation::norm3([a[0] - b[0], a[1] - b[1], a[2] - b[2]])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Quality;

    #[test]
    fn bad_tracks_are_refused_with_the_culprit_named() {
        let p = EncodeParams::from_quality(Quality::Standard, 0.01, MotionModel::General);
        let good = Track {
            positions: vec![[0.0; 3]; 3],
            rotations: vec![[0.0, 0.0, 0.0, 1.0]; 3],
        };
        let mut short = good.clone();
        short.rotations.pop();
        assert!(matches!(
            encode_world(&[good.clone(), short], &p),
            Err(CodecError::TrackLengthMismatch { object: 1, .. })
        ));
        let mut nan = good.clone();
        nan.positions[2][1] = f64::NAN;
        assert!(matches!(
            encode_world(&[nan], &p),
            Err(CodecError::NonFinite {
                frame: 2,
                what: "position",
                ..
            })
        ));
        let mut zero = good.clone();
        zero.rotations[1] = [0.0; 4];
        assert!(matches!(
            encode_world(&[zero], &p),
            Err(CodecError::DegenerateQuaternion { frame: 1, .. })
        ));
    }
}
