//! One object's payload: a range-coded stream, positions then rotations (layout in `format`).

use super::{PositionSegment, RotationSegment, finite_position, start_orientation};
use crate::arith::{Bit, RangeDecoder, TypeModel, ValueModel, decode_rice_direct};
use crate::error::CodecError;
use crate::format::{
    FLAG_POS_RAW, FLAG_POS_REST, FLAG_ROT_RAW, FLAG_ROT_REST, Header, S_POS_LEN, S_POS_LINEAR,
    S_POS_QUADRATIC, S_POS_REST_LEN, S_POS_STEP, S_ROT_ACC, S_ROT_FREE, S_ROT_LEN, S_ROT_REST_LEN,
    S_ROT_STEP, S_ROT_W, STREAMS, value_models,
};
use crate::params::MotionModel;
use crate::rotation::{Quat, Vec3};
use crate::segment::{
    FreeDynamics, INERTIA_BITS, Lattice, MAX_FREE_LEN, PositionCoding, PositionCurve,
    PositionPredictor, PositionType, QuadraticQ, QuadraticTerm, RotationCurve, RotationPredictor,
    RotationType, bucket, position_step_prediction, position_types, rotation_step_prediction,
    rotation_types, step_angular_acceleration, step_end, step_linear, step_quadratic, unresidual,
};

/// The symbols of a payload: the range decoder and the context models (the encoder's
/// `ObjectWriter` mirrors them).
pub(crate) struct Symbols<'a> {
    d: RangeDecoder<'a>,
    values: Box<[ValueModel; STREAMS]>,
    types: [TypeModel; 2],
    flags: [Bit; 4],
}

impl<'a> Symbols<'a> {
    pub(crate) fn new(bytes: &'a [u8]) -> Result<Self, CodecError> {
        Ok(Self {
            d: RangeDecoder::new(bytes)?,
            values: value_models(),
            types: Default::default(),
            flags: Default::default(),
        })
    }

    /// A flag bit; `which`: the `FLAG_*` constants (each its own context).
    fn flag(&mut self, which: usize) -> Result<bool, CodecError> {
        self.d.bit(&mut self.flags[which])
    }

    /// A segment type among `n` after `prev` (positions or rotations).
    fn kind(&mut self, rotation: bool, n: usize, prev: usize) -> Result<usize, CodecError> {
        self.types[usize::from(rotation)].decode(&mut self.d, n, prev)
    }

    /// The next value of integer stream `stream`.
    fn value(&mut self, stream: usize) -> Result<u64, CodecError> {
        self.values[stream].decode(&mut self.d)
    }

    /// A start value, Rice-coded with the header's parameter `k`.
    fn start_value(&mut self, k: u32) -> Result<u64, CodecError> {
        decode_rice_direct(&mut self.d, k)
    }

    /// A raw `f64`.
    fn float(&mut self) -> Result<f64, CodecError> {
        Ok(f64::from_bits(self.d.direct(64)?))
    }

    /// `n` equiprobable bits (coset bits, principal moments).
    fn bits(&mut self, n: u32) -> Result<u64, CodecError> {
        self.d.direct(n)
    }
}

/// The decoding state of one object.
pub(crate) struct ObjectStream<'a> {
    r: Symbols<'a>,
    coding: PositionCoding,
    rot_step: f64,
    /// Rice parameter of the start orientation (from the header).
    start_k: u32,
    /// The world's rotation dynamics, and the frame time they need.
    dynamics: Option<crate::format::HeaderDynamics>,
    frame_dt: f64,
    /// Free-flight frames this object may still simulate.
    free_budget: u64,
    /// Frames after the first (segments cover exactly this many).
    steps: u32,
    pub position_start: Vec3,
    positions: PositionState,
    rotations: Option<RotationState>,
}

struct PositionState {
    predictor: PositionPredictor,
    /// The whole track is one rest segment (not yet returned).
    at_rest: bool,
    c: Vec3,
    /// The decoded frame before `c` (for step segments).
    before: Option<Vec3>,
    covered: u32,
    prev_type: usize,
}

struct RotationState {
    predictor: RotationPredictor,
    /// The object's free-flight dynamics, once its first free segment has stored them.
    free: Option<FreeDynamics>,
    at_rest: bool,
    q: Quat,
    before: Option<Quat>,
    covered: u32,
    prev_type: usize,
}

/// Reads three residuals of `stream` against `pred`.
fn residuals(
    r: &mut Symbols<'_>,
    stream: usize,
    pred: [i64; 3],
    what: &'static str,
) -> Result<[i64; 3], CodecError> {
    let mut q = [0i64; 3];
    for (v, p) in q.iter_mut().zip(pred) {
        *v = unresidual(r.value(stream)?, p).ok_or(CodecError::Corrupt { what })?;
    }
    Ok(q)
}

/// A lattice vector of `stream` (its coset bit first, see [`Lattice`]) against the prediction
/// `pred`, a point of space, for the lattice of `step`; returns lattice coordinates.
fn lattice_vector(
    r: &mut Symbols<'_>,
    lattice: Lattice,
    stream: usize,
    pred: Vec3,
    step: f64,
    what: &'static str,
) -> Result<[i64; 3], CodecError> {
    let coset = r.bits(1)?;
    let k = residuals(r, stream, lattice.prediction(coset, pred, step), what)?;
    lattice.join(coset, k).ok_or(CodecError::Corrupt { what })
}

/// A start vector's lattice coordinates: its coset bit, then three zig-zagged start values,
/// Rice-coded with the header's parameter `k`.
fn start_values(
    r: &mut Symbols<'_>,
    lattice: Lattice,
    k: u32,
    what: &'static str,
) -> Result<[i64; 3], CodecError> {
    let coset = r.bits(1)?;
    let mut q = [0i64; 3];
    for v in &mut q {
        *v = unresidual(r.start_value(k)?, 0).ok_or(CodecError::Corrupt { what })?;
    }
    lattice.join(coset, q).ok_or(CodecError::Corrupt { what })
}

/// Three raw f64s.
fn floats(r: &mut Symbols<'_>) -> Result<Vec3, CodecError> {
    Ok([r.float()?, r.float()?, r.float()?])
}

fn quat(r: &mut Symbols<'_>) -> Result<Quat, CodecError> {
    let q = [r.float()?, r.float()?, r.float()?, r.float()?];
    crate::rotation::normalise(q).ok_or(CodecError::Corrupt {
        what: "stored quaternion cannot be normalised",
    })
}

/// Segment length: 0 = the rest of the track, else `L ≤ remaining`.
fn length(r: &mut Symbols<'_>, stream: usize, remaining: u32) -> Result<u32, CodecError> {
    match r.value(stream)? {
        0 => Ok(remaining),
        l if l <= u64::from(remaining) => Ok(l as u32),
        _ => Err(CodecError::Corrupt {
            what: "segment runs past the end of the track",
        }),
    }
}

impl<'a> ObjectStream<'a> {
    /// `free_budget`: most free-flight frames this object's segments may simulate.
    pub(crate) fn open(
        bytes: &'a [u8],
        frames: u32,
        header: &Header,
        free_budget: u64,
    ) -> Result<Self, CodecError> {
        let mut r = Symbols::new(bytes)?;
        let gravity = match header.model {
            MotionModel::General => None,
            MotionModel::FreeFlightGravity { g } => Some(g),
        };
        let coding = PositionCoding::new(header.pos_step, gravity, header.frame_dt);
        let start = if r.flag(FLAG_POS_RAW)? {
            floats(&mut r)?
        } else {
            let what = "start position out of range";
            let q = start_values(&mut r, coding.lattice, header.start_k[0], what)?;
            coding.lattice.point(q, coding.start_step())
        };
        let start = finite_position(start)?;
        let steps = frames - 1;
        // A track at rest throughout: one rest segment, no codes.
        let at_rest = steps > 0 && r.flag(FLAG_POS_REST)?;
        Ok(Self {
            r,
            coding,
            rot_step: header.rot_step,
            start_k: header.start_k[1],
            dynamics: header.dynamics,
            frame_dt: header.frame_dt,
            free_budget,
            steps,
            position_start: start,
            positions: PositionState {
                predictor: PositionPredictor::new(&coding),
                c: start,
                before: None,
                covered: 0,
                prev_type: 0,
                at_rest,
            },
            rotations: None,
        })
    }

    /// The next position segment, `None` once the track is covered.
    pub(crate) fn next_position(&mut self) -> Result<Option<PositionSegment>, CodecError> {
        let p = &mut self.positions;
        if p.covered == self.steps {
            return Ok(None);
        }
        let remaining = self.steps - p.covered;
        if p.at_rest {
            p.covered = self.steps;
            return Ok(Some(PositionSegment {
                start: 0,
                len: remaining,
                c: p.c,
                curve: PositionCurve::Rest,
            }));
        }
        let types = position_types(self.coding.gravity_term.is_some());
        let rank = self.r.kind(false, types.len(), p.prev_type)?;
        p.prev_type = rank;
        let (len, curve) = match types[rank] {
            PositionType::Key => {
                let end = floats(&mut self.r)?;
                (
                    1,
                    PositionCurve::Key {
                        end: finite_position(end)?,
                    },
                )
            }
            PositionType::Rest => (
                length(&mut self.r, S_POS_REST_LEN, remaining)?,
                PositionCurve::Rest,
            ),
            PositionType::Step => {
                let pred = position_step_prediction(p.c, p.before, p.predictor.velocity());
                let what = "position step out of range";
                let (lattice, step) = (self.coding.lattice, self.coding.step);
                let q = lattice_vector(&mut self.r, lattice, S_POS_STEP, [0.0; 3], step, what)?;
                let end = step_end(pred, q, step, lattice);
                (
                    1,
                    PositionCurve::Key {
                        end: finite_position(end)?,
                    },
                )
            }
            kind => {
                let len = length(&mut self.r, S_POS_LEN, remaining)?;
                let k = bucket(len);
                let lattice = self.coding.lattice;
                let (sb, sa) = (
                    step_linear(self.coding.step, k),
                    step_quadratic(self.coding.step, k),
                );
                let what = "position coefficient out of range";
                let pb = p.predictor.velocity();
                let bq = lattice_vector(&mut self.r, lattice, S_POS_LINEAR, pb, sb, what)?;
                let term = match kind {
                    PositionType::Gravity => QuadraticTerm::Gravity,
                    PositionType::Linear => QuadraticTerm::Zero,
                    _ => {
                        let pa = p.predictor.quadratic();
                        QuadraticTerm::Fitted(lattice_vector(
                            &mut self.r,
                            lattice,
                            S_POS_QUADRATIC,
                            pa,
                            sa,
                            what,
                        )?)
                    }
                };
                (len, QuadraticQ { bq, term }.curve(&self.coding, k))
            }
        };
        let seg = PositionSegment {
            start: p.covered,
            len,
            c: p.c,
            curve,
        };
        p.predictor.advance(p.c, len, &curve);
        p.before = Some(curve.eval(p.c, f64::from(len - 1)));
        p.c = finite_position(curve.eval(p.c, f64::from(len)))?;
        p.covered += len;
        Ok(Some(seg))
    }

    /// Reads past the remaining position segments and the rotation start (the rotation stream
    /// follows the position stream); returns the first orientation.
    pub(crate) fn start_rotations(&mut self) -> Result<Quat, CodecError> {
        if let Some(rot) = &self.rotations {
            return Ok(rot.q);
        }
        while self.next_position()?.is_some() {}
        let start = if self.r.flag(FLAG_ROT_RAW)? {
            quat(&mut self.r)?
        } else {
            let (lattice, what) = (self.coding.lattice, "start orientation out of range");
            let q = start_values(&mut self.r, lattice, self.start_k, what)?;
            start_orientation(q, self.rot_step / self.coding.rot_start_divisor, lattice)
        };
        let at_rest = self.steps > 0 && self.r.flag(FLAG_ROT_REST)?;
        self.rotations = Some(RotationState {
            free: None,
            at_rest,
            predictor: RotationPredictor::default(),
            q: start,
            before: None,
            covered: 0,
            prev_type: 0,
        });
        Ok(start)
    }

    /// The next rotation segment, `None` once the track is covered. A free flight's frames are
    /// pushed onto `frames`, if given (see [`RotationPredictor::follow_into`]).
    pub(crate) fn next_rotation(
        &mut self,
        frames: Option<&mut Vec<Quat>>,
    ) -> Result<Option<RotationSegment>, CodecError> {
        self.start_rotations()?;
        let Some(rot) = &mut self.rotations else {
            return Ok(None);
        };
        if rot.covered == self.steps {
            return Ok(None);
        }
        let remaining = self.steps - rot.covered;
        if rot.at_rest {
            rot.covered = self.steps;
            return Ok(Some(RotationSegment {
                start: 0,
                len: remaining,
                q0: rot.q,
                curve: RotationCurve::Rest,
            }));
        }
        let types = rotation_types(self.dynamics.is_some());
        let rank = self.r.kind(true, types.len(), rot.prev_type)?;
        rot.prev_type = rank;
        let (len, curve) = match types[rank] {
            RotationType::Key => (
                1,
                RotationCurve::Key {
                    end: quat(&mut self.r)?,
                },
            ),
            RotationType::Rest => (
                length(&mut self.r, S_ROT_REST_LEN, remaining)?,
                RotationCurve::Rest,
            ),
            RotationType::Step => {
                let pred =
                    rotation_step_prediction(rot.q, rot.before, rot.predictor.angular_velocity());
                let what = "rotation step out of range";
                let (lattice, step) = (self.coding.lattice, self.rot_step);
                let q = lattice_vector(&mut self.r, lattice, S_ROT_STEP, [0.0; 3], step, what)?;
                (
                    1,
                    RotationCurve::Linear {
                        w: step_end(pred, q, step, lattice),
                    },
                )
            }
            RotationType::Free => {
                let len = length(&mut self.r, S_ROT_LEN, remaining)?;
                if len > MAX_FREE_LEN {
                    return Err(CodecError::Corrupt {
                        what: "free-flight segment longer than the format allows",
                    });
                }
                // A reader simulates a segment's frames at most about twice (to its end, then
                // to a sampled frame).
                let cost = 2 * u64::from(len);
                if cost > self.free_budget {
                    return Err(CodecError::LimitExceeded {
                        what: "free-flight frames simulated",
                        requested: cost,
                        limit: self.free_budget,
                    });
                }
                self.free_budget -= cost;
                let dynamics = match (rot.free, self.dynamics) {
                    (Some(d), _) => d,
                    (None, Some(h)) => {
                        let mut code = [0u16; 3];
                        for c in &mut code {
                            // `INERTIA_BITS` (12) fit in a u16.
                            *c = self.r.bits(INERTIA_BITS)? as u16;
                            if *c == 0 {
                                return Err(CodecError::Corrupt {
                                    what: "principal moment of inertia is zero",
                                });
                            }
                        }
                        let d =
                            FreeDynamics::new(code, h.substeps, h.angular_damping, self.frame_dt);
                        rot.free = Some(d);
                        d
                    }
                    // `rotation_types` offers the type only with dynamics.
                    (None, None) => {
                        return Err(CodecError::Corrupt {
                            what: "free-flight segment without dynamics",
                        });
                    }
                };
                let what = "angular velocity residual out of range";
                let (lattice, sw) = (self.coding.lattice, step_linear(self.rot_step, bucket(len)));
                let pred = rot.predictor.angular_velocity();
                let wq = lattice_vector(&mut self.r, lattice, S_ROT_FREE, pred, sw, what)?;
                let w = lattice.point(wq, sw);
                (len, RotationCurve::Free { w, dynamics })
            }
            kind => {
                let len = length(&mut self.r, S_ROT_LEN, remaining)?;
                let k = bucket(len);
                let what = "angular velocity residual out of range";
                let (lattice, sw) = (self.coding.lattice, step_linear(self.rot_step, k));
                let pred = rot.predictor.angular_velocity();
                let wq = lattice_vector(&mut self.r, lattice, S_ROT_W, pred, sw, what)?;
                let w = lattice.point(wq, sw);
                let curve = if kind == RotationType::Quadratic {
                    let sa = step_angular_acceleration(self.rot_step, k);
                    let pred = rot.predictor.angular_acceleration();
                    let aq = lattice_vector(&mut self.r, lattice, S_ROT_ACC, pred, sa, what)?;
                    RotationCurve::Quadratic {
                        w,
                        a: lattice.point(aq, sa),
                    }
                } else {
                    RotationCurve::Linear { w }
                };
                (len, curve)
            }
        };
        let seg = RotationSegment {
            start: rot.covered,
            len,
            q0: rot.q,
            curve,
        };
        let (before, end) = rot.predictor.follow_into(&curve, len, rot.q, frames);
        rot.before = Some(before);
        rot.q = end;
        rot.covered += len;
        Ok(Some(seg))
    }
}
