//! Worlds for the export tests: simulated by the sampler's own code, sent through the same
//! segments a sampler puts on the bus, decoded by `mwb_export::decode_segments`.

#![allow(dead_code)]

use mwb_core::scene::{Scene, SceneTemplate};
use mwb_export::{ExportWorld, Motion, SegmentPayload, decode_segments};
use mwb_proto::v1::MotionSegment;
use std::ops::ControlFlow;

/// Every shape the scene format has: a plane and a triangle mesh among the statics; a box, a
/// sphere, a capsule, a cylinder and a convex hull among the bodies, all thrown spinning.
pub const SHAPES: &str = r#"
name = "shapes"

[settings]
end_time = 1.5

[[material]]
name = "ground"
friction = 0.8
restitution = 0.2

[[material]]
name = "wood"
friction = 0.6
restitution = 0.3
density = 600.0

[[material]]
name = "steel"
friction = 0.4
restitution = 0.4
density = 7800.0

[[static]]
name = "ground"
shape = "plane"
normal = [0, 1, 0]
material = "ground"

[[static]]
name = "wedge"
shape = "trimesh"
vertices = [[-0.5, 0, -0.5], [0.5, 0, -0.5], [0, 0.4, 0.5], [0, 0, 0.5]]
indices = [[0, 2, 1], [0, 3, 2], [1, 2, 3]]
material = "wood"
position = [3, 0, 0]

[[body]]
name = "crate"
shape = "box"
size = [0.4, 0.3, 0.2]
material = "wood"
position = [-1, 1, 0]
linvel = [1, 2, 0]
angvel = [3, -2, 5]

[[body]]
name = "ball"
shape = "sphere"
radius = 0.15
material = "steel"
position = [0, 1.5, 0]
angvel = [0, 8, 0]

[[body]]
name = "pill"
shape = "capsule"
radius = 0.1
height = 0.3
material = "wood"
position = [1, 1, 0]
linvel = [0, 1, 1]
angvel = [6, 0, -4]

[[body]]
name = "can"
shape = "cylinder"
radius = 0.12
height = 0.3
material = "steel"
position = [0, 1, 1]
angvel = [-5, 2, 7]

[[body]]
name = "gem"
shape = "convex"
points = [[0, 0.2, 0], [0.15, 0, 0.15], [-0.15, 0, 0.15], [0.15, 0, -0.15], [-0.15, 0, -0.15], [0, -0.2, 0]]
material = "wood"
position = [0, 1.2, -1]
linvel = [0, 2, 0]
angvel = [9, 4, -3]
"#;

/// A simulated world: its scene, the segments a sampler would send, and the decoded motion.
pub struct World {
    pub seed: u64,
    pub scene: Scene,
    pub segments: Vec<MotionSegment>,
    pub motion: Motion,
}

impl World {
    pub fn export(&self, index: Option<u32>) -> ExportWorld<'_> {
        ExportWorld {
            index,
            seed: self.seed,
            scene: &self.scene,
            motion: &self.motion,
        }
    }
}

pub fn simulate(text: &str, file: &str, seed: u64) -> World {
    let template = SceneTemplate::parse(text, file).unwrap_or_else(|e| panic!("{e}"));
    let mut segments = Vec::new();
    let summary = mwb_sampler::run_world(&template, seed, Default::default(), &mut |seg| {
        segments.push(mwb_sampler::segment_message("job", "node", 0, seed, seg));
        ControlFlow::Continue(())
    })
    .unwrap_or_else(|e| panic!("{e}"));
    let payloads: Vec<SegmentPayload<'_>> = segments
        .iter()
        .map(|s| SegmentPayload::from_proto(s).unwrap_or_else(|e| panic!("{e}")))
        .collect();
    let motion = decode_segments(
        &payloads,
        summary.frame_dt,
        Some(u64::from(summary.frame_count)),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    World {
        seed,
        scene: template.instantiate(seed),
        segments,
        motion,
    }
}

pub fn tumble(seed: u64) -> World {
    simulate(mwb_core::scene::builtin::TUMBLE, "scenes/tumble.toml", seed)
}

pub fn shapes(seed: u64) -> World {
    simulate(SHAPES, "shapes.toml", seed)
}

/// A compound body (an "L" of a wooden post and a steel foot, turned) thrown onto the ground,
/// beside a compound static (a shelf of two boxes): the export draws every part.
pub const COMPOUND: &str = r#"
name = "compound"

[settings]
end_time = 1.5

[[material]]
name = "ground"

[[material]]
name = "wood"
density = 600.0

[[material]]
name = "steel"
density = 7800.0

[[static]]
name = "ground"
shape = "plane"
material = "ground"

[[static]]
name = "shelf"
shape = "compound"
material = "ground"
position = [2, 0, 0]
part = [
  { shape = "box", size = [1, 0.1, 0.4], position = [0, 0.5, 0] },
  { shape = "box", size = [0.1, 0.5, 0.4], position = [-0.45, 0.25, 0] },
]

[[body]]
name = "letter_l"
shape = "compound"
material = "wood"
position = [0, 1, 0]
angvel = [2, 3, -1]

[[body.part]]
shape = "box"
size = [0.1, 0.5, 0.1]
position = [0, 0.25, 0]

[[body.part]]
shape = "cylinder"
radius = 0.05
height = 0.3
position = [0.15, 0, 0]
rotation_deg = [0, 0, 90]
material = "steel"
"#;

pub fn compound(seed: u64) -> World {
    simulate(COMPOUND, "compound.toml", seed)
}
