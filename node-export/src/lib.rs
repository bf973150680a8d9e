//! A chosen world out of manyworlds: its scene and decoded motion as a glTF 2.0 binary (`.glb`)
//! for Blender, Maya and Houdini, as a Foxglove MCAP (`foxglove.SceneUpdate` +
//! `foxglove.FrameTransforms`) for Foxglove's 3D panel, or as CSV / JSON rows for scripts.
//!
//! Pure: bytes in memory in, bytes in memory out; no files, no bus, no clock. The `mwb export`
//! command fetches a world (from a store, a recording, or by simulating its seed) and writes
//! the bytes.
//!
//! * [`motion`] — a world's segments (codec streams or quantised frames) decoded into one
//!   [`Motion`]: per body, every frame's position and unit quaternion.
//! * [`mesh`] — every scene shape as a triangle mesh in the body's local frame (boxes, spheres,
//!   capsules, cylinders, convex hulls triangulated, planes as a finite square, triangle meshes).
//! * [`glb`] — glTF 2.0 binary: a node and a mesh per body and per static, a material per scene
//!   material, one animation (translation and rotation, LINEAR, one key per frame).
//! * [`foxglove`] — MCAP with Foxglove's own protobuf schemas.
//! * [`table`] — CSV and JSON rows (frame, time, body index and name, position, quaternion), and
//!   reading them back.
//!
//! Coordinates: scenes are right-handed, y up, metres, quaternions `[x, y, z, w]`
//! (`mwb_core::scene::model`) — exactly glTF's convention, so the glTF export writes them
//! unchanged. Foxglove's 3D panel is z up: the MCAP export adds one fixed transform
//! `world → scene` (+90° about x) and keeps every body in scene coordinates below it.
//!
//! ```
//! use mwb_core::scene::{SceneTemplate, builtin};
//! use mwb_export::{ExportWorld, Motion, glb, table};
//!
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let scene = SceneTemplate::parse(builtin::TUMBLE, "tumble.toml")?.instantiate(7);
//! // Two frames of motion: every body where the scene puts it, then 1 cm higher.
//! let mut motion = Motion::at_rest(&scene, 2, scene.settings.dt);
//! for track in &mut motion.tracks {
//!     track.positions[1][1] += 0.01;
//! }
//! let world = ExportWorld { index: Some(3), seed: 7, scene: &scene, motion: &motion };
//! let bytes = glb::write(&world)?;
//! let doc = gltf::Gltf::from_slice(&bytes)?;
//! assert_eq!(doc.animations().count(), 1);
//! assert_eq!(doc.nodes().count(), 1 + scene.statics.len() + scene.bodies.len());
//!
//! let csv = table::write_csv(&[world])?;
//! let rows = table::read_csv(&csv)?;
//! assert_eq!(rows.len(), 2 * scene.bodies.len());
//! assert_eq!(rows[5].frame, 1); // frame-major: every body of frame 0, then frame 1
//! # Ok(())
//! # }
//! ```

pub mod foxglove;
pub mod glb;
pub mod instance;
pub mod mesh;
pub mod motion;
pub mod table;

pub use instance::world_instance;
pub use motion::{
    Motion, MotionError, SegmentPayload, decode_payload, decode_segments, decode_world, is_layered,
};

use mwb_core::scene::Scene;

/// One world to export: its instantiated scene (the template instantiated with the world's
/// seed: bodies in scene order, their shapes and materials) and its decoded motion.
#[derive(Debug, Clone, Copy)]
pub struct ExportWorld<'a> {
    /// The store's global index of the world, when it came from a store or a recording;
    /// `None` for a world simulated from its seed alone.
    pub index: Option<u32>,
    pub seed: u64,
    pub scene: &'a Scene,
    pub motion: &'a Motion,
}

impl ExportWorld<'_> {
    /// `"tumble world 3"`, or `"tumble seed 7"` for a world without an index.
    pub fn label(&self) -> String {
        match self.index {
            Some(i) => format!("{} world {i}", self.scene.name),
            None => format!("{} seed {}", self.scene.name, self.seed),
        }
    }

    /// The motion must have one track per scene body, every track the same length.
    pub fn check(&self) -> Result<(), ExportError> {
        if self.motion.tracks.len() != self.scene.bodies.len() {
            return Err(ExportError::BodyCount {
                motion: self.motion.tracks.len(),
                scene: self.scene.bodies.len(),
            });
        }
        let frames = self.motion.frame_count();
        for (body, t) in self.motion.tracks.iter().enumerate() {
            if t.positions.len() != frames || t.rotations.len() != frames {
                return Err(ExportError::TrackLength {
                    body,
                    frames: t.positions.len().min(t.rotations.len()),
                    expected: frames,
                });
            }
        }
        if frames == 0 {
            return Err(ExportError::NoFrames);
        }
        if !(self.motion.frame_dt.is_finite() && self.motion.frame_dt > 0.0) {
            return Err(ExportError::FrameDt(self.motion.frame_dt));
        }
        Ok(())
    }
}

/// Why an export failed.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error("the motion has {motion} bodies, the scene {scene}")]
    BodyCount { motion: usize, scene: usize },
    #[error("body {body}: {frames} frames, the world has {expected}")]
    TrackLength {
        body: usize,
        frames: usize,
        expected: usize,
    },
    #[error("the world has no frames")]
    NoFrames,
    #[error("frame_dt {0} is not a positive number of seconds")]
    FrameDt(f64),
    #[error("{what} {name:?}: {reason}")]
    Shape {
        what: &'static str,
        name: String,
        reason: String,
    },
    #[error("glTF: {0}")]
    Gltf(String),
    #[error("MCAP: {0}")]
    Mcap(#[from] mcap::McapError),
    #[error("protobuf encoding: {0}")]
    Protobuf(#[from] prost::EncodeError),
    #[error("JSON: {0}")]
    Json(#[from] serde_json::Error),
    #[error("CSV line {line}: {reason}")]
    Csv { line: usize, reason: String },
}
