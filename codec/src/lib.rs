//! Error-bounded compression of rigid-body motion (the "compressed in-core representation" of
//! §4.3 of Twigg and James's account of
//! Many-Worlds Browsing, SIGGRAPH 2007).
//!
//! Each object's track — positions and unit quaternions sampled at a fixed frame rate — becomes
//! a handful of segments: C⁰ piecewise quadratics for the centre of mass (in free flight the
//! quadratic term is gravity's), linear or quadratic curves in the log map for the orientation,
//! rest segments where nothing moves, and one-frame steps predicted from the two frames before
//! where contact makes the motion change every frame; given the simulator's rotation dynamics
//! ([`encode_world_with_dynamics`]), also torque-free flights simulated from their start angular
//! velocity (a wobbling thrown box is one segment, not a quadratic every few frames).
//! Coefficients are quantised — every 3-vector a point of the body-centred cubic lattice, which
//! covers space as the cubic one does with 1.86× fewer points — predicted from the previous
//! segment and range-coded with adaptive context models. For **every object and every frame**
//! the decoded position is within `e_max` of the input (Euclidean norm, which also bounds each
//! axis) and the decoded orientation within `θ_max` (angle of the residual rotation); the encoder
//! checks this on the decoded bytes before returning them.
//!
//! The bytes are format version [`FORMAT_VERSION`] (1, the released format; `format` specifies
//! it completely), the stream's first byte. This build writes and reads that version only; a
//! later format change gets a new version, read beside this one, so what was recorded stays
//! readable (`tests/released_format.rs` holds recorded streams as the guard).
//!
//! # Writing
//!
//! ```
//! use mwb_codec::{EncodeParams, MotionModel, Quality, Track, encode_world};
//!
//! # fn main() -> Result<(), mwb_codec::CodecError> {
//! let dt = 1.0 / 120.0;
//! let g = [0.0, -9.81, 0.0];
//! // A spinning ball thrown up from 1 m, two seconds at 120 Hz (no bounce, for brevity).
//! let track = Track {
//!     positions: (0..240)
//!         .map(|i| {
//!             let t = i as f64 * dt;
//!             [0.5 * t, 1.0 + 6.0 * t + 0.5 * g[1] * t * t, 0.0]
//!         })
//!         .collect(),
//!     rotations: (0..240)
//!         .map(|i| {
//!             let half = 0.5 * 3.0 * i as f64 * dt; // 3 rad/s about y
//!             [0.0, half.sin(), 0.0, half.cos()]
//!         })
//!         .collect(),
//! };
//! let params = EncodeParams::from_quality(
//!     Quality::Standard, // e_max = 1 mm, θ_max = 1 mrad
//!     dt,
//!     MotionModel::FreeFlightGravity { g },
//! );
//! let world = encode_world(std::slice::from_ref(&track), &params)?;
//! assert!(world.stats.max_position_error <= 1e-3);
//! assert!(world.stats.ratio() > 30.0, "{} bytes", world.bytes.len());
//! // A 4 Hz polyline for display and indexing, with its measured deviation.
//! assert!(world.lowres[0].max_deviation < 0.1);
//! # Ok(())
//! # }
//! ```
//!
//! # Reading
//!
//! ```
//! use mwb_codec::{EncodeParams, MotionModel, Quality, Track, WorldReader, encode_world};
//!
//! # fn main() -> Result<(), mwb_codec::CodecError> {
//! # let resting = Track { positions: vec![[0.0, 0.5, 0.0]; 100], rotations: vec![[0.0, 0.0, 0.0, 1.0]; 100] };
//! # let params = EncodeParams::from_quality(Quality::Standard, 1.0 / 120.0, MotionModel::General);
//! # let bytes = encode_world(&[resting.clone(), resting], &params)?.bytes;
//! let reader = WorldReader::new(&bytes)?; // validates header and index only
//! assert_eq!(reader.object_count(), 2);
//! assert_eq!(reader.frame_count(), 100);
//!
//! // One object at one time: touches only that object's bytes, allocates nothing.
//! let (position, orientation) = reader.sample(1, 0.5)?;
//! assert!((position[1] - 0.5).abs() <= reader.e_max());
//!
//! // One object, every frame.
//! let track = reader.decode_object(0)?;
//! assert_eq!(track.positions.len(), 100);
//!
//! // Everything (capped by `DecodeLimits`).
//! let all = reader.decode_all()?;
//! assert_eq!(all.len(), 2);
//!
//! // Any bytes give an error or a value, never a panic.
//! assert!(WorldReader::new(b"not a world").is_err());
//! # let _ = orientation;
//! # Ok(())
//! # }
//! ```
//!
//! # Modules, in pipeline order
//! `fit` (greedy segment fitting, Figure 4.6) → `encode` (choosing the cheapest segment per
//! frame) → `segment` (quantisation, prediction, evaluation, shared by both directions) → `bits`
//! (integer codes) and `arith` (the range coder and its context models) → `format` (the byte
//! layout) → `decode` (`decode/object`: one object's payload).
//! `lowres` builds the few-Hz path; `baseline` gives the raw size and a quantised-frames reference.

mod arith;
mod baseline;
mod bits;
mod decode;
mod encode;
mod error;
mod fit;
mod format;
mod layers;
mod lowres;
mod params;
mod rotation;
mod segment;

pub use baseline::{
    BaselineRotation, RAW_BYTES_PER_OBJECT_FRAME, quantised_baseline, quantised_frames_baseline,
    raw_f32_size,
};
pub use decode::{DecodeLimits, WorldReader};
pub use encode::{
    EncodeStats, EncodedWorld, SizeBreakdown, Track, encode_world, encode_world_with_dynamics,
};
pub use error::CodecError;
pub use format::FORMAT_VERSION;
pub use layers::{LayerError, Layered};
pub use lowres::LowResPath;
pub use params::{
    ADAPTIVE_MAX_SKIP, DEFAULT_FRAME_DT, DEFAULT_LOWRES_HZ, EncodeParams, FIT_WINDOW,
    MAX_TRACK_FRAMES, MIN_THETA_MAX, MotionModel, Quality, RotationDynamics, Search,
};
