//! Encoding a world: validate, fit segments per object (positions and rotations separately, §4.3),
//! range-code them, assemble header + index + payloads, then decode the result and check the bound
//! on every frame before handing it out.
//!
//! At every segment start the encoder gathers candidates — rest, a one-frame step, and the
//! Figure 4.6 fits of each curve kind with each start correction — prices each in bits with the
//! coders' current state, and writes the one with the fewest bits per frame (§4.3 extends the
//! segment as far as it goes; measured on the shipped scenes, pricing is 5–12 % smaller).

use crate::arith::{Bit, COST_SCALE, RangeEncoder, TypeModel, ValueModel, encode_rice_direct};
use crate::bits::{best_rice_k, rice_len, write_varint, zigzag};
use crate::decode::{DecodeLimits, ObjectStream, WorldReader, finite_position, start_orientation};
use crate::error::CodecError;
use crate::fit::{
    AngleTest, MIN_FREE_PROBE, PositionFit, PositionKind, RotationFit, RotationKind,
    RotationScratch, StartCorrection, fit_free, fit_position, fit_rotation, rest_length,
    rotation_rest_length,
};
use crate::format::{
    FLAG_POS_RAW, FLAG_POS_REST, FLAG_ROT_RAW, FLAG_ROT_REST, Header, HeaderDynamics, MAX_START_K,
    S_POS_LEN, S_POS_LINEAR, S_POS_QUADRATIC, S_POS_REST_LEN, S_POS_STEP, S_ROT_ACC, S_ROT_FREE,
    S_ROT_LEN, S_ROT_REST_LEN, S_ROT_STEP, S_ROT_W, STREAMS, value_models,
};
use crate::lowres::LowResPath;
use crate::params::{
    ADAPTIVE_MAX_SKIP, EncodeParams, MAX_TRACK_FRAMES, MotionModel, ROT_BOUND_MARGIN,
    RotationDynamics, Search,
};
use crate::rotation::{self, Quat, Vec3};
use crate::segment::{
    Coded, FreeDynamics, INERTIA_BITS, Lattice, PositionCoding, PositionCurve, PositionPredictor,
    PositionType, QuadraticTerm, RotationCurve, RotationPredictor, RotationType, bucket,
    position_step_prediction, position_types, quantise_inertia, residual, rotation_step_prediction,
    rotation_types, step_angular_acceleration, step_end, step_linear, step_quadratic,
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
    /// The encoded stream, format version [`crate::FORMAT_VERSION`] (read it with
    /// [`WorldReader`]).
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
    /// Rotation segments that are free flights (counted in `rotation_segments` too).
    pub free_rotation_segments: u64,
    /// Largest Euclidean position error over all decoded frames (metres).
    pub max_position_error: f64,
    /// Largest rotation angle error over all decoded frames (radians; the frame is found by the
    /// self-check's residuals, which rank frames as their exact angles do to ~10⁻¹³ rad, and its
    /// exact angle is reported).
    pub max_rotation_error: f64,
    /// Where the bits go.
    pub breakdown: SizeBreakdown,
}

/// The encoded size split by what the bits describe (in bits; sums to 8 × [`EncodeStats::bytes`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SizeBreakdown {
    /// World header and object index.
    pub header_and_index: u64,
    /// First position and orientation of every object.
    pub starts: u64,
    /// Position segment types and lengths.
    pub position_segments: u64,
    /// Quantised position coefficients (residuals).
    pub position_coefficients: u64,
    /// Rotation segment types and lengths.
    pub rotation_segments: u64,
    /// Quantised angular velocities and accelerations (residuals).
    pub rotation_coefficients: u64,
    /// Exactly stored key frames.
    pub keys: u64,
    /// Padding of each object's payload to a whole byte.
    pub padding: u64,
}

impl SizeBreakdown {
    fn add(&mut self, other: &SizeBreakdown) {
        self.header_and_index += other.header_and_index;
        self.starts += other.starts;
        self.position_segments += other.position_segments;
        self.position_coefficients += other.position_coefficients;
        self.rotation_segments += other.rotation_segments;
        self.rotation_coefficients += other.rotation_coefficients;
        self.keys += other.keys;
        self.padding += other.padding;
    }
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
    encode_world_with_dynamics(tracks, p, None)
}

/// [`encode_world`], also given how the simulator turns bodies in free flight: objects with a
/// known inertia may then use free-flight rotation segments ([`RotationDynamics`]).
/// The decoder needs nothing extra: what it needs travels in the stream.
pub fn encode_world_with_dynamics(
    tracks: &[Track],
    p: &EncodeParams,
    dynamics: Option<&RotationDynamics>,
) -> Result<EncodedWorld, CodecError> {
    p.validate()?;
    if let Some(d) = dynamics {
        d.validate()?;
    }
    // Per object, the quantised dynamics its free-flight segments would use.
    let free: Vec<Option<FreeDynamics>> = (0..tracks.len())
        .map(|i| {
            let d = dynamics?;
            let inertia = quantise_inertia((*d.inertia.get(i)?)?)?;
            Some(FreeDynamics::new(
                inertia,
                d.substeps,
                d.angular_damping,
                p.frame_dt,
            ))
        })
        // A body with equal moments (a sphere, a cube) turns about a fixed axis in free flight:
        // a linear curve in the log map, near enough a quadratic one under angular damping, and
        // those need no inertia and no simulation to decode. Measured at Standard: on pachinko
        // (balls and dice) the free-flight fits were 18 % of the encoder's instructions for 20
        // segments; without them the streams are as large (chute −0.3 %; at Final +0.9 % and
        // +1.3 %).
        .map(|d| d.filter(|d| d.inertia != [1.0; 3]))
        .collect();
    // The rotation types objects code with. Free flight is the last type and the type code does
    // not depend on how many there are, so a world whose objects end up using none of it is
    // written with the five-type header (no dynamics fields) and decodes the same.
    let types = rotation_types(free.iter().any(Option::is_some));
    let object_count = u32::try_from(tracks.len()).map_err(|_| CodecError::InvalidParam {
        name: "tracks.len()",
        value: tracks.len() as f64,
        expected: "at most 2^32 − 1 objects",
    })?;
    let frames0 = tracks.first().map_or(0, Track::len);
    let common_frames = tracks
        .iter()
        .all(|t| t.len() == frames0)
        .then_some(frames0 as u32);
    let gravity = match p.model {
        MotionModel::General => None,
        MotionModel::FreeFlightGravity { g } => Some(g),
    };
    let coding = PositionCoding::new(p.pos_step(), gravity, p.frame_dt);
    let theta_lim = p.theta_max * (1.0 - ROT_BOUND_MARGIN);
    // The start values first: their Rice parameters are chosen for the whole world.
    let starts: Vec<Start> = tracks
        .iter()
        .map(|t| Start::quantise(t, &coding, p.e_max, p.rot_step(), theta_lim))
        .collect();
    let start_k = [0, 1].map(|which| {
        let values: Vec<u64> = starts
            .iter()
            .filter_map(|st| if which == 0 { st.position } else { st.rotation })
            .flat_map(|q| coding.lattice.coset_and_integers(q).1)
            .map(zigzag)
            .collect();
        best_rice_k(&values, MAX_START_K)
    });
    let mut header = Header {
        model: p.model,
        object_count,
        frame_dt: p.frame_dt,
        e_max: p.e_max,
        theta_max: p.theta_max,
        pos_step: p.pos_step(),
        rot_step: p.rot_step(),
        common_frames,
        start_k,
        dynamics: None,
    };

    let mut stats = EncodeStats {
        objects: tracks.len(),
        ..EncodeStats::default()
    };
    let mut payload = Vec::new();
    let mut index = Vec::with_capacity(tracks.len() * 2);
    // The normalised input rotations, kept for the self-check.
    let mut normalised = Vec::with_capacity(tracks.len());
    for (object, track) in tracks.iter().enumerate() {
        let rotations = validate_track(object, track)?;
        stats.object_frames += track.len() as u64;
        let bytes = if track.is_empty() {
            Vec::new()
        } else {
            let mut out = ObjectWriter::new(start_k);
            let start = &starts[object];
            let flight = encode_positions(
                &track.positions,
                start.position,
                &coding,
                p.e_max,
                &mut out,
                &mut stats,
            );
            encode_rotations(
                &rotations,
                start.rotation,
                RotationCoding {
                    step: header.rot_step,
                    start_step: header.rot_step / coding.rot_start_divisor,
                    theta_lim,
                    types,
                    free: free[object],
                    flight: &flight,
                    lattice: coding.lattice,
                    search: p.search,
                },
                &mut out,
                &mut stats,
            );
            out.finish(&mut stats.breakdown)
        };
        write_varint(&mut index, bytes.len() as u64);
        if common_frames.is_none() {
            write_varint(&mut index, track.len() as u64);
        }
        payload.extend_from_slice(&bytes);
        normalised.push(rotations);
    }
    if stats.free_rotation_segments > 0 {
        header.dynamics = dynamics.map(|d| HeaderDynamics {
            substeps: d.substeps,
            angular_damping: d.angular_damping,
        });
    }
    let mut bytes = Vec::with_capacity(32 + index.len() + payload.len());
    header.write(&mut bytes);
    bytes.extend_from_slice(&index);
    stats.breakdown.header_and_index = 8 * bytes.len() as u64;
    bytes.extend_from_slice(&payload);
    stats.bytes = bytes.len();
    stats.raw_f32_bytes = stats.object_frames * crate::baseline::RAW_BYTES_PER_OBJECT_FRAME as u64;

    // Self-check: the bytes are read back through the reader's own segment decoder, and every
    // frame it produces is checked against the input.
    let reader = WorldReader::with_limits(&bytes, DecodeLimits::unlimited())?;
    let mut lowres = Vec::with_capacity(tracks.len());
    let mut check = SelfCheck::new(p);
    for (object, ((track, rotations), stream)) in tracks
        .iter()
        .zip(&normalised)
        .zip(reader.streams())
        .enumerate()
    {
        let (frames, stream) = stream?;
        let Some(stream) = stream else {
            lowres.push(LowResPath::default());
            continue;
        };
        if frames as usize != track.len() {
            return Err(CodecError::Corrupt {
                what: "self-check: the stream's frame count is not the track's",
            });
        }
        check.object(object, stream, &track.positions, rotations, &mut stats)?;
        lowres.push(LowResPath::from_positions(
            &check.positions,
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

/// The self-check's rotation test on a residual `d = decoded ⊗ input⁻¹`, whose angle is
/// `2·atan2(|d_xyz|, |d_w|)` ([`rotation::angle_between`]) and grows with `|d_xyz|² / d_w²`:
/// residuals clearly inside the bound are accepted by that ratio, without `atan2`; the rest (a
/// relative band of 10⁻⁹ around the bound, where `atan2`'s rounding could matter) take the angle.
struct RotationCheck {
    theta_max: f64,
    /// Accept without `atan2` below this ratio (`None`: always compute the angle).
    inside: Option<f64>,
}

impl RotationCheck {
    fn new(theta_max: f64) -> Self {
        let inside = (theta_max <= 2.0).then(|| {
            let t = (0.5 * theta_max).tan();
            t * t * (1.0 - 1e-9)
        });
        Self { theta_max, inside }
    }

    /// `Err(angle)` if the residual's angle exceeds the bound (or is not a number).
    fn within(&self, d: Quat) -> Result<(), f64> {
        let (s2, c2) = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2], d[3] * d[3]);
        if self.inside.is_some_and(|inside| s2 < inside * c2) {
            return Ok(());
        }
        let a = Self::angle(d);
        if a > self.theta_max || a.is_nan() {
            Err(a)
        } else {
            Ok(())
        }
    }

    fn angle(d: Quat) -> f64 {
        2.0 * rotation::norm3([d[0], d[1], d[2]]).atan2(d[3].abs())
    }

    /// Whether residual `d` rotates further than `than` (by the ratio; for the statistics).
    fn larger(d: Quat, than: Option<Quat>) -> bool {
        let Some(t) = than else {
            return true;
        };
        let ratio = |d: Quat| (d[0] * d[0] + d[1] * d[1] + d[2] * d[2], d[3] * d[3]);
        let ((s, c), (st, ct)) = (ratio(d), ratio(t));
        s * ct > st * c
    }
}

/// The encoder's self-check of one world: every object's segments are read back from the
/// written bytes by the reader's own segment decoder, and every frame they produce is compared
/// with the input. Positions are evaluated exactly as [`WorldReader`] evaluates them and checked
/// against `e_max`. Rotations: rest, key and free-flight frames are the decoder's values and are
/// checked by [`RotationCheck`]; a linear or quadratic log-map frame, which the decoder computes
/// as `normalise(exp(r(u)) ⊗ q₀)` with `sin` and `cos`, is decided by the encoder's fast bound
/// test (`fit::AngleTest`, polynomial `exp` and the residual `exp(r) ⊗ (q₀ ⊗ q⁻¹)`), which is
/// proven to give the verdict of the full computation, and takes the full computation wherever
/// it cannot decide. So every decoded frame is still checked, without collecting tracks and
/// without a `sin` and `cos` per frame: measured on tumble at Standard, the check and the low-res
/// paths went from 12 % to 8 % of the encoder's instructions (the rest is mostly the range
/// decoding and the free flights' simulation, which a check of the decoded frames needs).
struct SelfCheck {
    e_max: f64,
    theta_max: f64,
    exact: RotationCheck,
    fast: AngleTest,
    /// The largest position error so far.
    max_position_error: f64,
    /// The last object's decoded positions (for its low-res path).
    positions: Vec<Vec3>,
    /// The frames of one free-flight segment, as the decoder simulates them.
    free: Vec<Quat>,
}

/// The frame with the largest rotation residual so far: its residual (exact, or as the fast test
/// computes it for log-map frames, which ranks frames the same to ~10⁻¹³ rad), and what its exact
/// residual is computed from once the object is checked.
#[derive(Clone, Copy)]
enum WorstRotation {
    Exact(Quat),
    Log {
        ranked: Quat,
        curve: RotationCurve,
        q0: Quat,
        u: f64,
        q: Quat,
    },
}

impl WorstRotation {
    fn ranked(&self) -> Quat {
        match *self {
            WorstRotation::Exact(d) | WorstRotation::Log { ranked: d, .. } => d,
        }
    }

    fn exact(&self) -> Quat {
        match *self {
            WorstRotation::Exact(d) => d,
            WorstRotation::Log {
                curve, q0, u, q, ..
            } => rotation::mul(curve.eval(q0, u), rotation::conj(q)),
        }
    }
}

impl SelfCheck {
    fn new(p: &EncodeParams) -> Self {
        Self {
            e_max: p.e_max,
            theta_max: p.theta_max,
            exact: RotationCheck::new(p.theta_max),
            fast: AngleTest::new(p.theta_max),
            max_position_error: 0.0,
            positions: Vec::new(),
            free: Vec::new(),
        }
    }

    /// Checks one object's decoded frames against its input positions `x` and normalised
    /// rotations `q` (the same length as the stream's frame count); updates the error
    /// statistics and leaves the decoded positions in `self.positions`.
    fn object(
        &mut self,
        object: usize,
        mut stream: ObjectStream<'_>,
        x: &[Vec3],
        q: &[Quat],
        stats: &mut EncodeStats,
    ) -> Result<(), CodecError> {
        let short = CodecError::Corrupt {
            what: "self-check: the stream covers other frames than the track",
        };
        self.positions.clear();
        self.position(object, stream.position_start, x)?;
        while let Some(seg) = stream.next_position()? {
            for u in 1..=seg.len {
                let d = finite_position(seg.curve.eval(seg.c, f64::from(u)))?;
                self.position(object, d, x)?;
            }
        }
        if self.positions.len() != x.len() {
            return Err(short);
        }
        let q0 = stream.start_rotations()?;
        let mut worst = WorstRotation::Exact(self.rotation_exact(object, 0, q0, q)?);
        let mut frame = 1usize;
        loop {
            self.free.clear();
            let Some(seg) = stream.next_rotation(Some(&mut self.free))? else {
                break;
            };
            let end = frame + seg.len as usize;
            let input = q.get(frame..end).ok_or(CodecError::Corrupt {
                what: "self-check: the stream covers other frames than the track",
            })?;
            match seg.curve {
                RotationCurve::Free { .. } => {
                    for (i, (&dq, &qi)) in self.free.iter().zip(input).enumerate() {
                        let d = self.rotation_exact(object, frame + i, dq, &[qi])?;
                        if RotationCheck::larger(d, Some(worst.ranked())) {
                            worst = WorstRotation::Exact(d);
                        }
                    }
                }
                RotationCurve::Linear { .. } | RotationCurve::Quadratic { .. } => {
                    for (i, &qi) in input.iter().enumerate() {
                        let u = (i + 1) as f64;
                        let relative = rotation::mul(seg.q0, rotation::conj(qi));
                        let r = seg.curve.log_at(u).unwrap_or([0.0; 3]);
                        let d = rotation::mul(rotation::exp_approx(r), relative);
                        match self.fast.ratio_verdict(d) {
                            Some(true) => {}
                            // Outside the bound (the full computation agrees), or too close
                            // to it to tell: the full computation decides and reports.
                            _ => {
                                let dq = seg.curve.eval(seg.q0, u);
                                self.rotation_exact(object, frame + i, dq, &[qi])?;
                            }
                        }
                        if RotationCheck::larger(d, Some(worst.ranked())) {
                            worst = WorstRotation::Log {
                                ranked: d,
                                curve: seg.curve,
                                q0: seg.q0,
                                u,
                                q: qi,
                            };
                        }
                    }
                }
                RotationCurve::Rest | RotationCurve::Key { .. } => {
                    for (i, &qi) in input.iter().enumerate() {
                        let dq = seg.curve.eval(seg.q0, (i + 1) as f64);
                        let d = self.rotation_exact(object, frame + i, dq, &[qi])?;
                        if RotationCheck::larger(d, Some(worst.ranked())) {
                            worst = WorstRotation::Exact(d);
                        }
                    }
                }
            }
            frame = end;
        }
        if frame != q.len() {
            return Err(short);
        }
        stats.max_position_error = self.max_position_error;
        stats.max_rotation_error = stats
            .max_rotation_error
            .max(RotationCheck::angle(worst.exact()));
        Ok(())
    }

    /// Checks the next decoded position.
    fn position(&mut self, object: usize, d: Vec3, x: &[Vec3]) -> Result<(), CodecError> {
        let frame = self.positions.len();
        let xi = x.get(frame).ok_or(CodecError::Corrupt {
            what: "self-check: the stream covers other frames than the track",
        })?;
        let e = rotation::norm3(std::array::from_fn(|i| d[i] - xi[i]));
        if e > self.e_max || e.is_nan() {
            return Err(CodecError::BoundViolated {
                object,
                frame,
                what: "position",
                found: e,
                bound: self.e_max,
            });
        }
        self.max_position_error = self.max_position_error.max(e);
        self.positions.push(d);
        Ok(())
    }

    /// Checks decoded orientation `dq` of `frame` against `q[0]` (the input's); returns the
    /// residual.
    fn rotation_exact(
        &self,
        object: usize,
        frame: usize,
        dq: Quat,
        q: &[Quat],
    ) -> Result<Quat, CodecError> {
        let residual = rotation::mul(dq, rotation::conj(q[0]));
        self.exact
            .within(residual)
            .map_err(|found| CodecError::BoundViolated {
                object,
                frame,
                what: "rotation",
                found,
                bound: self.theta_max,
            })?;
        Ok(residual)
    }
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

/// One object's stream under construction: the range coder, the context models of
/// every stream (the decoder mirrors them) and where the bits went (in 1/256 bit while writing:
/// the coder's estimate of each symbol's cost).
struct ObjectWriter {
    e: RangeEncoder,
    values: Box<[ValueModel; STREAMS]>,
    types: [TypeModel; 2],
    flags: [Bit; 4],
    /// The world's Rice parameters for start positions and orientations.
    start_k: [u32; 2],
    breakdown: SizeBreakdown,
}

impl ObjectWriter {
    fn new(start_k: [u32; 2]) -> Self {
        Self {
            e: RangeEncoder::default(),
            values: value_models(),
            types: Default::default(),
            flags: Default::default(),
            start_k,
            breakdown: SizeBreakdown::default(),
        }
    }

    /// A flag bit; returns its cost.
    fn flag(&mut self, which: usize, bit: bool) -> u64 {
        let c = self.flags[which].cost(bit);
        self.e.bit(&mut self.flags[which], bit);
        c
    }

    /// A start (flag, then quantised values — lattice coordinates — or raw f64s); `which`: 0
    /// position, 1 rotation.
    fn start(&mut self, which: usize, quantised: Option<[i64; 3]>, raw: &[f64], lattice: Lattice) {
        let flag = if which == 0 {
            FLAG_POS_RAW
        } else {
            FLAG_ROT_RAW
        };
        let mut cost = self.flag(flag, quantised.is_none());
        match quantised {
            Some(q) => {
                let (coset, k) = lattice.coset_and_integers(q);
                self.e.direct(coset, 1);
                cost += COST_SCALE;
                for v in k {
                    let k = self.start_k[which];
                    encode_rice_direct(&mut self.e, zigzag(v), k);
                    cost += rice_len(zigzag(v), k) * COST_SCALE;
                }
            }
            None => cost += self.raw(raw),
        }
        self.breakdown.starts += cost;
    }

    /// Writes `v` on `stream`; returns its cost.
    fn code(&mut self, stream: usize, v: u64) -> u64 {
        let c = self.values[stream].cost(v);
        self.values[stream].encode(&mut self.e, v);
        c
    }

    /// Writes a segment type; returns its cost.
    fn kind(&mut self, rotation: bool, prev: usize, rank: usize) -> u64 {
        let m = &mut self.types[usize::from(rotation)];
        let c = m.cost(prev, rank);
        m.encode(&mut self.e, prev, rank);
        c
    }

    fn kind_cost(&self, rotation: bool, prev: usize, rank: usize) -> u64 {
        self.types[usize::from(rotation)].cost(prev, rank)
    }

    fn value_cost(&self, stream: usize, v: u64) -> u64 {
        self.values[stream].cost(v)
    }

    fn raw(&mut self, values: &[f64]) -> u64 {
        for v in values {
            self.e.direct(v.to_bits(), 64);
        }
        64 * COST_SCALE * values.len() as u64
    }

    /// An object's quantised principal moments (before its first free-flight segment).
    fn inertia(&mut self, code: [u16; 3]) -> u64 {
        for v in code {
            self.e.direct(u64::from(v), INERTIA_BITS);
        }
        3 * u64::from(INERTIA_BITS) * COST_SCALE
    }

    /// Three residuals against a prediction.
    fn residuals(&mut self, stream: usize, q: [i64; 3], pred: [i64; 3]) -> u64 {
        (0..3)
            .map(|i| self.code(stream, residual(q[i], pred[i])))
            .sum()
    }

    /// A lattice vector as [`Lattice::split`] writes it against its prediction (its coset bit
    /// first); returns its cost.
    fn vector(&mut self, stream: usize, c: Coded) -> u64 {
        self.e.direct(c.coset, 1);
        COST_SCALE + self.residuals(stream, c.k, c.pred)
    }

    /// Cost of [`Self::vector`] now.
    fn vector_cost(&self, stream: usize, c: Coded) -> u64 {
        COST_SCALE + self.residuals_cost(stream, c.k, c.pred)
    }

    /// Cost of three residuals now (the estimate that ranks candidate segments).
    fn residuals_cost(&self, stream: usize, q: [i64; 3], pred: [i64; 3]) -> u64 {
        (0..3)
            .map(|i| self.values[stream].cost(residual(q[i], pred[i])))
            .sum()
    }

    fn finish(self, total: &mut SizeBreakdown) -> Vec<u8> {
        let bytes = self.e.finish();
        let b = self.breakdown;
        let bits = |c: u64| (c + COST_SCALE / 2) / COST_SCALE;
        let mut b = SizeBreakdown {
            header_and_index: 0,
            starts: bits(b.starts),
            position_segments: bits(b.position_segments),
            position_coefficients: bits(b.position_coefficients),
            rotation_segments: bits(b.rotation_segments),
            rotation_coefficients: bits(b.rotation_coefficients),
            keys: bits(b.keys),
            padding: 0,
        };
        let coded = b.starts
            + b.position_segments
            + b.position_coefficients
            + b.rotation_segments
            + b.rotation_coefficients
            + b.keys;
        // The coder's flush and the estimates' rounding (signed in truth; clamped at 0).
        b.padding = (bytes.len() as u64 * 8).saturating_sub(coded);
        total.add(&b);
        bytes
    }
}

/// Shortest quadratic segment (position or rotation) the encoder writes. A quadratic over a few
/// frames is nearly an interpolation: it costs six coefficients where steps cost less, and its
/// end velocity predicts the next segment badly — which the per-frame cost of the greedy choice
/// cannot see. Measured on the shipped scenes: 1–5 % smaller at every preset (flat from 4 to 6).
/// With the lattice search making linear segments longer, 7 (0.4–1.2 % smaller than 5 at
/// Standard; 8 and 10 no better, worse at Final). The fitters are told, and decide first
/// whether a quadratic reaches it (`fit::WindowProbe`).
const MIN_QUADRATIC_LEN: usize = 7;

/// An object's first position and orientation, quantised finely (`START_STEP_DIVISORS`) if that
/// meets the bounds, else `None` (stored raw).
struct Start {
    position: Option<[i64; 3]>,
    rotation: Option<[i64; 3]>,
}

impl Start {
    fn quantise(
        track: &Track,
        coding: &PositionCoding,
        e_max: f64,
        rot_step: f64,
        theta_lim: f64,
    ) -> Self {
        let lattice = coding.lattice;
        let position = track.positions.first().and_then(|&x0| {
            let step = coding.start_step();
            lattice
                .quantise(x0, step)
                .filter(|&q| dist(lattice.point(q, step), x0) <= e_max)
        });
        let rotation = track
            .rotations
            .first()
            .and_then(|&q0| rotation::normalise(q0))
            .and_then(|q0| {
                let step = rot_step / coding.rot_start_divisor;
                lattice.quantise(rotation::log(q0), step).filter(|&v| {
                    rotation::angle_between(start_orientation(v, step, lattice), q0) <= theta_lim
                })
            });
        Self { position, rotation }
    }
}

/// Length code: 0 = to the end of the track.
fn length_code(s: usize, len: u32, last: usize) -> u64 {
    if s + len as usize == last {
        0
    } else {
        u64::from(len)
    }
}

/// Among candidate segments `(cost in bits, length)`, the index of the one with the fewest bits
/// per frame; on a tie the longer, then the first. Greedy like Figure 4.6, but a longer segment
/// that needs more coefficients no longer wins by length alone.
fn cheapest(candidates: impl Iterator<Item = (u64, u32)>) -> Option<usize> {
    let mut best: Option<(usize, u64, u32)> = None;
    for (i, (cost, len)) in candidates.enumerate() {
        let better = match best {
            None => true,
            Some((_, bc, bl)) => {
                let (a, b) = (
                    u128::from(cost) * u128::from(bl),
                    u128::from(bc) * u128::from(len),
                );
                a < b || (a == b && len > bl)
            }
        };
        if better {
            best = Some((i, cost, len));
        }
    }
    best.map(|(i, _, _)| i)
}

/// [`Search::Adaptive`]'s memory of one candidate fit (the quadratic rotation curve, anchored or
/// horizon-corrected): after its `n`-th loss in a row it is passed over at the next `n` segment
/// starts (at most [`ADAPTIVE_MAX_SKIP`]); a win clears the count. Under [`Search::Exhaustive`]
/// it is always due. A pure function of the frames, so the stream stays deterministic.
#[derive(Debug, Default, Clone, Copy)]
struct Backoff {
    losses: u32,
    skip: u32,
}

impl Backoff {
    /// Whether the candidate is fitted at this start (`adaptive`: under [`Search::Adaptive`]).
    fn due(&mut self, adaptive: bool) -> bool {
        if !adaptive || self.skip == 0 {
            return true;
        }
        self.skip -= 1;
        false
    }

    /// After a start at which the candidate was fitted: whether it was the one written.
    fn outcome(&mut self, won: bool) {
        if won {
            self.losses = 0;
        } else {
            self.losses = (self.losses + 1).min(ADAPTIVE_MAX_SKIP);
            self.skip = self.losses;
        }
    }
}

/// A position segment the encoder may write.
#[derive(Debug, Clone, Copy)]
enum PositionChoice {
    Rest(u32),
    /// One frame predicted from the two before: the quantised residual and the decoded frame.
    Step([i64; 3], Vec3),
    Fit(PositionKind, PositionFit),
}

impl PositionChoice {
    fn len(&self) -> u32 {
        match self {
            PositionChoice::Rest(len) => *len,
            PositionChoice::Step(..) => 1,
            PositionChoice::Fit(_, f) => f.len,
        }
    }

    fn ty(&self) -> PositionType {
        match self {
            PositionChoice::Rest(_) => PositionType::Rest,
            PositionChoice::Step(..) => PositionType::Step,
            PositionChoice::Fit(PositionKind::Gravity, _) => PositionType::Gravity,
            PositionChoice::Fit(PositionKind::Quadratic, _) => PositionType::Quadratic,
            PositionChoice::Fit(PositionKind::Linear, _) => PositionType::Linear,
        }
    }
}

/// Encodes an object's positions; returns, per frame, whether a gravity parabola (free flight,
/// the `Gravity` type) covers the step into it — where the rotation encoder tries free
/// flights (every frame, in a world without the gravity model).
fn encode_positions(
    x: &[Vec3],
    start: Option<[i64; 3]>,
    coding: &PositionCoding,
    e_max: f64,
    out: &mut ObjectWriter,
    stats: &mut EncodeStats,
) -> Vec<bool> {
    // Without the gravity model no segment says "free flight": every frame may be one.
    let mut flight = vec![coding.gravity_term.is_none(); x.len()];
    let lattice = coding.lattice;
    // The constant term, stored once per object (C⁰ continuity, §4.3).
    out.start(0, start, &x[0], lattice);
    let mut c = start.map_or(x[0], |q| coding.lattice.point(q, coding.start_step()));
    let last = x.len() - 1;
    if last == 0 {
        return flight;
    }
    // A body at rest for the whole track: one bit.
    let at_rest = rest_length(x, 0, c, e_max) == last;
    out.breakdown.position_segments += out.flag(FLAG_POS_REST, at_rest);
    if at_rest {
        stats.position_segments += 1;
        return flight;
    }
    let types = position_types(coding.gravity_term.is_some());
    let rank = |t: PositionType| types.iter().position(|&u| u == t).unwrap_or(0);
    let kinds: &[PositionKind] = if coding.gravity_term.is_some() {
        &[
            PositionKind::Gravity,
            PositionKind::Quadratic,
            PositionKind::Linear,
        ]
    } else {
        &[PositionKind::Quadratic, PositionKind::Linear]
    };
    let mut predictor = PositionPredictor::new(coding);
    let mut prev = 0usize;
    let mut before: Option<Vec3> = None;
    let mut candidates: Vec<PositionChoice> = Vec::with_capacity(12);
    let mut s = 0;
    while s < last {
        candidates.clear();
        let rest = rest_length(x, s, c, e_max) as u32;
        if rest > 0 {
            candidates.push(PositionChoice::Rest(rest));
        }
        let pred = position_step_prediction(c, before, predictor.velocity());
        let target: Vec3 = std::array::from_fn(|i| x[s + 1][i] - pred[i]);
        if let Some(q) = coding.lattice.quantise(target, coding.step) {
            let end = step_end(pred, q, coding.step, coding.lattice);
            if end.iter().all(|v| v.is_finite()) && dist(end, x[s + 1]) <= e_max {
                candidates.push(PositionChoice::Step(q, end));
            }
        }
        // A rest to the end of the track is as cheap as a segment gets.
        if s + (rest as usize) < last {
            for &kind in kinds {
                let min_len = match kind {
                    PositionKind::Quadratic => MIN_QUADRATIC_LEN,
                    PositionKind::Gravity | PositionKind::Linear => 1,
                };
                // The corrections in order, the anchored one first.
                let mut anchored_len = 0;
                for &corr in kind.corrections() {
                    if !corr.worth_fitting(anchored_len) {
                        continue;
                    }
                    if let Some(f) = fit_position(x, s, c, kind, corr, coding, e_max, min_len) {
                        if corr == StartCorrection::Anchored {
                            anchored_len = f.len;
                        }
                        candidates.push(PositionChoice::Fit(kind, f));
                    }
                }
            }
        }
        let cost = |ch: &PositionChoice| {
            let len = ch.len();
            // Steps are one frame by definition: no length code.
            let head = out.kind_cost(false, prev, rank(ch.ty()))
                + match ch {
                    PositionChoice::Step(..) => 0,
                    PositionChoice::Rest(_) => {
                        out.value_cost(S_POS_REST_LEN, length_code(s, len, last))
                    }
                    _ => out.value_cost(S_POS_LEN, length_code(s, len, last)),
                };
            head + match ch {
                PositionChoice::Rest(_) => 0,
                PositionChoice::Step(q, _) => {
                    out.vector_cost(S_POS_STEP, lattice.split(*q, [0.0; 3], coding.step))
                }
                PositionChoice::Fit(_, f) => {
                    let k = bucket(len);
                    let (sb, sa) = (step_linear(coding.step, k), step_quadratic(coding.step, k));
                    out.vector_cost(
                        S_POS_LINEAR,
                        lattice.split(f.coeffs.bq, predictor.velocity(), sb),
                    ) + match f.coeffs.term {
                        QuadraticTerm::Fitted(aq) => out.vector_cost(
                            S_POS_QUADRATIC,
                            lattice.split(aq, predictor.quadratic(), sa),
                        ),
                        _ => 0,
                    }
                }
            }
        };
        let chosen =
            cheapest(candidates.iter().map(|ch| (cost(ch), ch.len()))).map(|i| candidates[i]);
        let (len, curve) = match chosen {
            Some(ch) => {
                let len = ch.len();
                let r = rank(ch.ty());
                let mut head = out.kind(false, prev, r);
                prev = r;
                match ch {
                    PositionChoice::Step(..) => {}
                    PositionChoice::Rest(_) => {
                        head += out.code(S_POS_REST_LEN, length_code(s, len, last));
                    }
                    _ => head += out.code(S_POS_LEN, length_code(s, len, last)),
                }
                out.breakdown.position_segments += head;
                match ch {
                    PositionChoice::Step(q, end) => {
                        let b = out.vector(S_POS_STEP, lattice.split(q, [0.0; 3], coding.step));
                        out.breakdown.position_coefficients += b;
                        (1, PositionCurve::Key { end })
                    }
                    PositionChoice::Rest(_) => (len, PositionCurve::Rest),
                    PositionChoice::Fit(_, f) => {
                        let k = bucket(len);
                        let (sb, sa) =
                            (step_linear(coding.step, k), step_quadratic(coding.step, k));
                        let pb = predictor.velocity();
                        let mut bits = out.vector(S_POS_LINEAR, lattice.split(f.coeffs.bq, pb, sb));
                        if let QuadraticTerm::Fitted(aq) = f.coeffs.term {
                            let pa = predictor.quadratic();
                            bits += out.vector(S_POS_QUADRATIC, lattice.split(aq, pa, sa));
                        }
                        out.breakdown.position_coefficients += bits;
                        (len, f.curve)
                    }
                }
            }
            None => {
                // No quantised curve reaches even the next frame: store it exactly.
                let r = rank(PositionType::Key);
                out.breakdown.position_segments += out.kind(false, prev, r);
                prev = r;
                out.breakdown.keys += out.raw(&x[s + 1]);
                stats.key_segments += 1;
                (1, PositionCurve::Key { end: x[s + 1] })
            }
        };
        stats.position_segments += 1;
        if chosen.is_some_and(|ch| ch.ty() == PositionType::Gravity) {
            flight[s + 1..=s + len as usize].fill(true);
        }
        predictor.advance(c, len, &curve);
        before = Some(curve.eval(c, f64::from(len - 1)));
        c = curve.eval(c, f64::from(len));
        s += len as usize;
    }
    flight
}

/// A rotation segment the encoder may write.
#[derive(Debug, Clone, Copy)]
enum RotationChoice {
    Rest(u32),
    /// One frame: the quantised residual and the decoded rotation vector of the frame.
    Step([i64; 3], Vec3),
    Fit(RotationKind, RotationFit),
    /// Torque-free flight.
    Free(RotationFit),
}

impl RotationChoice {
    fn len(&self) -> u32 {
        match self {
            RotationChoice::Rest(len) => *len,
            RotationChoice::Step(..) => 1,
            RotationChoice::Fit(_, f) | RotationChoice::Free(f) => f.len,
        }
    }

    fn ty(&self) -> RotationType {
        match self {
            RotationChoice::Rest(_) => RotationType::Rest,
            RotationChoice::Step(..) => RotationType::Step,
            RotationChoice::Fit(RotationKind::Linear, _) => RotationType::Linear,
            RotationChoice::Fit(RotationKind::Quadratic, _) => RotationType::Quadratic,
            RotationChoice::Free(_) => RotationType::Free,
        }
    }
}

/// What the rotation code of one object needs besides its frames.
struct RotationCoding<'a> {
    /// Δθ.
    step: f64,
    /// The start orientation's step (Δθ over its divisor).
    start_step: f64,
    theta_lim: f64,
    /// The world's rotation types, in code order.
    types: &'static [RotationType],
    /// The object's free-flight dynamics, if its world has them and it has an inertia.
    free: Option<FreeDynamics>,
    /// Per frame, whether its position is in free flight (see `encode_positions`); in a world
    /// without the gravity model, all true.
    flight: &'a [bool],
    /// The format's lattice for steps and coefficients.
    lattice: Lattice,
    search: Search,
}

fn encode_rotations(
    q: &[Quat],
    start: Option<[i64; 3]>,
    rc: RotationCoding<'_>,
    out: &mut ObjectWriter,
    stats: &mut EncodeStats,
) {
    let (rot_step, theta_lim) = (rc.step, rc.theta_lim);
    let lattice = rc.lattice;
    let rank = |t: RotationType| rc.types.iter().position(|&u| u == t).unwrap_or(0);
    out.start(1, start, &q[0], lattice);
    let mut q0 = match start {
        Some(v) => start_orientation(v, rc.start_step, rc.lattice),
        // The decoder re-normalises what it reads.
        None => rotation::normalise(q[0]).unwrap_or(rotation::IDENTITY),
    };
    let last = q.len() - 1;
    if last == 0 {
        return;
    }
    let at_rest = rotation_rest_length(q, 0, q0, theta_lim) == last;
    out.breakdown.rotation_segments += out.flag(FLAG_ROT_REST, at_rest);
    if at_rest {
        stats.rotation_segments += 1;
        return;
    }
    let mut predictor = RotationPredictor::default();
    let mut scratch = RotationScratch::default();
    let mut prev = 0usize;
    let mut before: Option<Quat> = None;
    let mut candidates: Vec<RotationChoice> = Vec::with_capacity(8);
    // The quadratic fits' (anchored, horizon) backoffs (see `Search::Adaptive`).
    let mut quadratic = [Backoff::default(); 2];
    let adaptive = rc.search == Search::Adaptive;
    let angle_test = AngleTest::new(theta_lim);
    // The object's principal moments are written before its first free-flight segment.
    let mut inertia_written = false;
    // Where the last free flight fitted left the bound: a flight ends at a contact, whatever
    // frame it starts from, so from a start fewer than `MIN_FREE_LEN` frames before that end no
    // flight worth writing fits (measured on tumble at Standard: 7 % of the encoder's
    // instructions saved, the same bytes).
    let mut free_end = 0usize;
    let mut s = 0;
    while s < last {
        candidates.clear();
        // Per quadratic fit: whether it was fitted, and where among the candidates it is.
        let mut fitted = [false; 2];
        let mut quadratic_at = [None; 2];
        let rest = rotation_rest_length(q, s, q0, theta_lim) as u32;
        if rest > 0 {
            candidates.push(RotationChoice::Rest(rest));
        }
        let pred = rotation_step_prediction(q0, before, predictor.angular_velocity());
        let r = rotation::log(rotation::mul(q[s + 1], rotation::conj(q0)));
        let r = rotation::unwrap_near(r, pred);
        let target: Vec3 = std::array::from_fn(|i| r[i] - pred[i]);
        if let Some(v) = lattice.quantise(target, rot_step) {
            let w = step_end(pred, v, rot_step, lattice);
            if angle_test.within(&RotationCurve::Linear { w }, q0, 1.0, q[s + 1]) {
                candidates.push(RotationChoice::Step(v, w));
            }
        }
        if s + (rest as usize) < last {
            for kind in [RotationKind::Linear, RotationKind::Quadratic] {
                let min_len = match kind {
                    RotationKind::Linear => 1,
                    RotationKind::Quadratic => MIN_QUADRATIC_LEN,
                };
                let mut anchored_len = 0;
                for (i, &corr) in kind.corrections().iter().enumerate() {
                    if !corr.worth_fitting(anchored_len) {
                        continue;
                    }
                    let is_quadratic = kind == RotationKind::Quadratic;
                    if is_quadratic {
                        if !quadratic[i].due(adaptive) {
                            continue;
                        }
                        fitted[i] = true;
                    }
                    let fit = fit_rotation(
                        q,
                        s,
                        q0,
                        kind,
                        corr,
                        rot_step,
                        lattice,
                        theta_lim,
                        min_len,
                        &mut scratch,
                    );
                    if let Some(f) = fit {
                        if corr == StartCorrection::Anchored {
                            anchored_len = f.len;
                        }
                        if is_quadratic {
                            quadratic_at[i] = Some(candidates.len());
                        }
                        candidates.push(RotationChoice::Fit(kind, f));
                    }
                }
            }
            // Free flights only where the centre of mass flies too: in contact, torques act
            // (measured on the shipped scenes: 10–40 % of the encoder's time saved, for 0.2–1 %
            // larger streams).
            let flight = rc.flight[s + 1..].iter().take_while(|&&f| f).count();
            let flying = flight >= (MIN_FREE_PROBE as usize).min(last - s);
            let ends_soon = s < free_end && free_end - s < MIN_FREE_LEN as usize;
            if let Some(d) = rc.free.as_ref().filter(|_| flying && !ends_soon) {
                let fit = fit_free(q, s, q0, d, rot_step, lattice, theta_lim, flight);
                if let Some(f) = fit {
                    free_end = s + f.len as usize;
                }
                // Shorter flights are contact phases a linear curve covers as well.
                candidates.extend(
                    fit.filter(|f| f.len >= MIN_FREE_LEN)
                        .map(RotationChoice::Free),
                );
            }
        }
        let inertia_cost = if inertia_written {
            0
        } else {
            3 * u64::from(INERTIA_BITS) * COST_SCALE
        };
        let cost = |ch: &RotationChoice| {
            let len = ch.len();
            let head = out.kind_cost(true, prev, rank(ch.ty()))
                + match ch {
                    RotationChoice::Step(..) => 0,
                    RotationChoice::Rest(_) => {
                        out.value_cost(S_ROT_REST_LEN, length_code(s, len, last))
                    }
                    _ => out.value_cost(S_ROT_LEN, length_code(s, len, last)),
                };
            head + match ch {
                RotationChoice::Rest(_) => 0,
                RotationChoice::Step(v, _) => {
                    out.vector_cost(S_ROT_STEP, lattice.split(*v, [0.0; 3], rot_step))
                }
                RotationChoice::Fit(_, f) => {
                    let k = bucket(len);
                    let w = predictor.angular_velocity();
                    out.vector_cost(S_ROT_W, lattice.split(f.wq, w, step_linear(rot_step, k)))
                        + f.aq.map_or(0, |aq| {
                            let a = predictor.angular_acceleration();
                            let sa = step_angular_acceleration(rot_step, k);
                            out.vector_cost(S_ROT_ACC, lattice.split(aq, a, sa))
                        })
                }
                RotationChoice::Free(f) => {
                    let sw = step_linear(rot_step, bucket(len));
                    let w = predictor.angular_velocity();
                    inertia_cost + out.vector_cost(S_ROT_FREE, lattice.split(f.wq, w, sw))
                }
            }
        };
        let chosen_at = cheapest(candidates.iter().map(|ch| (cost(ch), ch.len())));
        for (i, b) in quadratic.iter_mut().enumerate() {
            if fitted[i] {
                b.outcome(chosen_at.is_some() && quadratic_at[i] == chosen_at);
            }
        }
        let chosen = chosen_at.map(|i| candidates[i]);
        let (len, curve) = match chosen {
            Some(ch) => {
                let len = ch.len();
                let r = rank(ch.ty());
                let mut head = out.kind(true, prev, r);
                prev = r;
                match ch {
                    RotationChoice::Step(..) => {}
                    RotationChoice::Rest(_) => {
                        head += out.code(S_ROT_REST_LEN, length_code(s, len, last));
                    }
                    _ => head += out.code(S_ROT_LEN, length_code(s, len, last)),
                }
                out.breakdown.rotation_segments += head;
                match ch {
                    RotationChoice::Step(v, w) => {
                        let b = out.vector(S_ROT_STEP, lattice.split(v, [0.0; 3], rot_step));
                        out.breakdown.rotation_coefficients += b;
                        (1, RotationCurve::Linear { w })
                    }
                    RotationChoice::Rest(_) => (len, RotationCurve::Rest),
                    RotationChoice::Fit(_, f) => {
                        let k = bucket(len);
                        let (w, sw) = (predictor.angular_velocity(), step_linear(rot_step, k));
                        let mut bits = out.vector(S_ROT_W, lattice.split(f.wq, w, sw));
                        if let Some(aq) = f.aq {
                            let a = predictor.angular_acceleration();
                            let sa = step_angular_acceleration(rot_step, k);
                            bits += out.vector(S_ROT_ACC, lattice.split(aq, a, sa));
                        }
                        out.breakdown.rotation_coefficients += bits;
                        (len, f.curve)
                    }
                    RotationChoice::Free(f) => {
                        let mut bits = 0;
                        if !inertia_written {
                            if let RotationCurve::Free { dynamics, .. } = f.curve {
                                bits += out.inertia(dynamics.inertia_code);
                            }
                            inertia_written = true;
                        }
                        let sw = step_linear(rot_step, bucket(len));
                        let w = predictor.angular_velocity();
                        bits += out.vector(S_ROT_FREE, lattice.split(f.wq, w, sw));
                        out.breakdown.rotation_coefficients += bits;
                        (len, f.curve)
                    }
                }
            }
            None => {
                let r = rank(RotationType::Key);
                out.breakdown.rotation_segments += out.kind(true, prev, r);
                prev = r;
                out.breakdown.keys += out.raw(&q[s + 1]);
                stats.key_segments += 1;
                // The decoder re-normalises what it reads.
                let end = rotation::normalise(q[s + 1]).unwrap_or(rotation::IDENTITY);
                (1, RotationCurve::Key { end })
            }
        };
        stats.rotation_segments += 1;
        if matches!(curve, RotationCurve::Free { .. }) {
            stats.free_rotation_segments += 1;
        }
        let (b, end) = predictor.follow(&curve, len, q0);
        before = Some(b);
        q0 = end;
        s += len as usize;
    }
}

/// Shortest free-flight rotation segment the encoder writes: below it a linear segment, which
/// needs no inertia and no simulation to decode, does as well.
const MIN_FREE_LEN: u32 = 8;

fn dist(a: Vec3, b: Vec3) -> f64 {
    rotation::norm3([a[0] - b[0], a[1] - b[1], a[2] - b[2]])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Quality;

    /// A one-object world whose rotations are free-flight segments of the given lengths (0: to
    /// the end), the object claiming `frames` frames — streams no honest encoder writes.
    fn free_flights(frames: u32, lengths: &[u64]) -> Vec<u8> {
        let (e, t) = Quality::Standard.bounds();
        let header = Header {
            model: MotionModel::General,
            object_count: 1,
            frame_dt: 1.0 / 120.0,
            e_max: e,
            theta_max: t,
            pos_step: 1.1 * e,
            rot_step: 1.1 * t,
            common_frames: Some(frames),
            start_k: [0, 0],
            dynamics: Some(HeaderDynamics {
                substeps: 4,
                angular_damping: 0.0,
            }),
        };
        let mut out = ObjectWriter::new([0, 0]);
        out.start(0, Some([0; 3]), &[0.0; 3], Lattice);
        out.flag(FLAG_POS_REST, true);
        out.start(1, Some([0; 3]), &[0.0; 4], Lattice);
        out.flag(FLAG_ROT_REST, false);
        let free = rotation_types(true)
            .iter()
            .position(|&t| t == RotationType::Free)
            .unwrap_or(0);
        for (i, &len) in lengths.iter().enumerate() {
            out.kind(true, if i == 0 { 0 } else { free }, free);
            out.code(S_ROT_LEN, len);
            if i == 0 {
                out.inertia([4095, 2000, 1000]);
            }
            // Lattice coordinates of one parity (a BCC point).
            let step = step_linear(1.1 * t, bucket(len.max(1) as u32));
            out.vector(S_ROT_FREE, Lattice.split([10, -4, 6], [0.0; 3], step));
        }
        let payload = out.finish(&mut SizeBreakdown::default());
        let mut bytes = Vec::new();
        header.write(&mut bytes);
        write_varint(&mut bytes, payload.len() as u64);
        bytes.extend_from_slice(&payload);
        bytes
    }

    #[test]
    fn free_flights_are_bounded_work_for_the_decoder() {
        // Four billion frames in one flight: longer than a flight may be.
        let bytes = free_flights(u32::MAX, &[0]);
        let r = WorldReader::new(&bytes).unwrap();
        assert!(matches!(
            r.sample_frame(0, u32::MAX - 1),
            Err(CodecError::Corrupt { .. })
        ));
        // Flights of the longest length, one after another: the reader's frame limit bounds
        // what they cost to simulate, for random access as for decoding.
        let bytes = free_flights(u32::MAX, &[4096; 40]);
        let limits = DecodeLimits {
            max_object_frames: 3 * 4096,
            max_total_frames: 3 * 4096,
        };
        let r = WorldReader::with_limits(&bytes, limits).unwrap();
        assert!(matches!(
            r.sample_frame(0, 39 * 4096),
            Err(CodecError::LimitExceeded { .. })
        ));
        // Within the limit the same stream decodes: 1 + 4096 frames, simulated.
        let bytes = free_flights(4097, &[4096]);
        let r = WorldReader::with_limits(&bytes, limits).unwrap();
        let t = r.decode_object(0).unwrap();
        assert_eq!(t.len(), 4097);
        assert_eq!(r.sample_frame(0, 4096).unwrap().1, t.rotations[4096]);
        assert!(t.rotations.iter().all(|q| q.iter().all(|v| v.is_finite())));
    }

    /// After the n-th loss in a row the candidate sits out n starts (at most
    /// `ADAPTIVE_MAX_SKIP`); a win brings it back at every start; the exhaustive search never
    /// skips it.
    #[test]
    fn a_losing_candidate_sits_out_one_more_start_per_loss() {
        // Which of `starts` starts fit the candidate, given its outcome whenever it is fitted.
        let run = |adaptive: bool, starts: usize, wins: &dyn Fn(usize) -> bool| {
            let mut b = Backoff::default();
            let mut fitted = Vec::new();
            for s in 0..starts {
                if b.due(adaptive) {
                    fitted.push(s);
                    b.outcome(wins(s));
                }
            }
            fitted
        };
        assert_eq!(run(true, 15, &|_| false), [0, 2, 5, 9, 14]);
        assert_eq!(run(false, 15, &|_| false), (0..15).collect::<Vec<_>>());
        // Winning from start 9 on: fitted at every start again.
        assert_eq!(run(true, 13, &|s| s >= 9), [0, 2, 5, 9, 10, 11, 12]);
        // The wait stops growing at the cap.
        let fitted = run(true, 2000, &|_| false);
        let gaps: Vec<usize> = fitted.windows(2).map(|w| w[1] - w[0]).collect();
        assert_eq!(gaps.iter().max(), Some(&(ADAPTIVE_MAX_SKIP as usize + 1)));
        assert!(gaps.ends_with(&[ADAPTIVE_MAX_SKIP as usize + 1; 8]));
    }

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
