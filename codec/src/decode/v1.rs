//! Version-1 object payloads (kept so that old recordings stay readable): seven Rice parameters
//! stored per object, the position and rotation streams separately addressable.

use super::{
    PositionSegment, RotationSegment, finite_position, read_f64, read_quat, start_orientation,
};
use crate::bits::{BitReader, RICE_K_BITS};
use crate::error::CodecError;
use crate::format::{
    Header, S_POS_LEN, S_POS_LINEAR, S_POS_QUADRATIC, S_POS_START, S_ROT_LEN, S_ROT_START, S_ROT_W,
    STREAMS_V1,
};
use crate::params::MotionModel;
use crate::rotation::{Quat, Vec3};
use crate::segment::{
    Lattice, PositionCoding, PositionCurve, PositionPredictor, QuadraticQ, QuadraticTerm,
    RotationCurve, RotationPredictor, bucket, dequantise3, step_linear, step_quadratic, unresidual,
};

/// The two independent bit streams of one version-1 object.
pub(crate) struct ObjectStreams<'a> {
    pub positions: PositionStream<'a>,
    pub rotations: RotationStream<'a>,
}

impl<'a> ObjectStreams<'a> {
    pub(crate) fn open(bytes: &'a [u8], frames: u32, header: &Header) -> Result<Self, CodecError> {
        let mut r = BitReader::new(bytes);
        let mut ks = [0u32; STREAMS_V1];
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
        let coding = PositionCoding::new(header.pos_step, gravity, header.frame_dt, 1);
        let positions = PositionStream::open(r.sub(pos_start, rot_start)?, ks, coding, frames)?;
        let rotations =
            RotationStream::open(r.sub(rot_start, r.end())?, ks, header.rot_step, frames)?;
        Ok(Self {
            positions,
            rotations,
        })
    }
}

pub(crate) struct PositionStream<'a> {
    r: BitReader<'a>,
    ks: [u32; STREAMS_V1],
    coding: PositionCoding,
    predictor: PositionPredictor,
    pub start: Vec3,
    c: Vec3,
    covered: u32,
    steps: u32,
}

impl<'a> PositionStream<'a> {
    fn open(
        mut r: BitReader<'a>,
        ks: [u32; STREAMS_V1],
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

    pub(crate) fn next_segment(&mut self) -> Result<Option<PositionSegment>, CodecError> {
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
            let cubic = Lattice::Cubic;
            let pb = cubic.prediction(
                None,
                self.predictor.velocity(),
                step_linear(self.coding.step, k),
            );
            let pa = cubic.prediction(
                None,
                self.predictor.quadratic(),
                step_quadratic(self.coding.step, k),
            );
            let bq = self.read_residuals(S_POS_LINEAR, pb)?;
            let term = if gravity {
                QuadraticTerm::Gravity
            } else {
                QuadraticTerm::Fitted(self.read_residuals(S_POS_QUADRATIC, pa)?)
            };
            QuadraticQ { bq, term }.curve(&self.coding, k)
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

pub(crate) struct RotationStream<'a> {
    r: BitReader<'a>,
    ks: [u32; STREAMS_V1],
    step: f64,
    predictor: RotationPredictor,
    pub start: Quat,
    q: Quat,
    covered: u32,
    steps: u32,
}

impl<'a> RotationStream<'a> {
    fn open(
        mut r: BitReader<'a>,
        ks: [u32; STREAMS_V1],
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
            start_orientation(
                q,
                step / crate::params::start_step_divisors(1)[1],
                Lattice::Cubic,
            )
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

    pub(crate) fn next_segment(&mut self) -> Result<Option<RotationSegment>, CodecError> {
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
            let pred = Lattice::Cubic.prediction(
                None,
                self.predictor.angular_velocity(),
                step_linear(self.step, k),
            );
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
        self.predictor.advance(&curve, len, self.q);
        self.q = curve.eval(self.q, f64::from(len));
        self.covered += len;
        Ok(Some(seg))
    }
}
