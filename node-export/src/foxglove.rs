//! One world as an MCAP file that plays in Foxglove's 3D panel.
//!
//! Schemas: Foxglove's own protobuf definitions, taken from the `foxglove` SDK crate (its
//! `Encode` impls give the schema name — `foxglove.SceneUpdate`, `foxglove.FrameTransforms` —
//! encoding `protobuf` and the FileDescriptorSet Foxglove publishes), so the names, field
//! numbers and descriptors are exactly those the app expects; messages are encoded with the
//! same generated types. We write the MCAP ourselves (zstd chunks) to keep the bytes in memory.
//!
//! Channels:
//! * `/scene` (`foxglove.SceneUpdate`): one message at time 0 with an entity per static
//!   (frame `scene`) and per body (frame `body/<name>`, `frame_locked`, so it follows its
//!   transform), lifetime 0 (forever). Boxes, spheres and cylinders are Foxglove primitives;
//!   capsules, hulls, planes (a square, as in the glTF) and triangle meshes are triangle lists;
//!   a compound is its parts, each at its pose in the body's frame, coloured by its material.
//! * `/tf` (`foxglove.FrameTransforms`): one message per frame at `k · frame_dt` (log and
//!   publish time, ns from 0), holding the fixed `world → scene` transform (+90° about x: the
//!   scene's y up becomes Foxglove's z up) and `scene → body/<name>` for every body.

use crate::mesh::{TriangleMesh, shape_mesh};
use crate::{ExportError, ExportWorld};
use foxglove::Encode;
use foxglove::messages::{
    Color, CubePrimitive, CylinderPrimitive, Duration, FrameTransform, FrameTransforms, Point3,
    Pose, Quaternion, SceneEntity, SceneUpdate, SpherePrimitive, Timestamp, TriangleListPrimitive,
    Vector3,
};
use mwb_core::scene::Shape;
use std::collections::BTreeMap;
use std::io::Cursor;

/// Topic of the scene entities.
pub const SCENE_TOPIC: &str = "/scene";
/// Topic of the per-frame transforms.
pub const TF_TOPIC: &str = "/tf";
/// The root frame (z up, Foxglove's convention).
pub const WORLD_FRAME: &str = "world";
/// The scene's own frame (y up), child of [`WORLD_FRAME`].
pub const SCENE_FRAME: &str = "scene";

/// The frame a body's entity is drawn in.
pub fn body_frame(name: &str) -> String {
    format!("body/{name}")
}

/// Writes one world as MCAP bytes.
// Frame k indexes every body's positions and rotations at once: a range loop says it best.
#[allow(clippy::needless_range_loop)]
pub fn write(world: &ExportWorld<'_>) -> Result<Vec<u8>, ExportError> {
    world.check()?;
    let scene = world.scene;
    let motion = world.motion;
    let mut w = mcap::WriteOptions::new()
        .compression(Some(mcap::Compression::Zstd))
        .library(format!("mwb-export {}", env!("CARGO_PKG_VERSION")))
        .create(Cursor::new(Vec::new()))?;
    let scene_channel = channel::<SceneUpdate>(&mut w, SCENE_TOPIC)?;
    let tf_channel = channel::<FrameTransforms>(&mut w, TF_TOPIC)?;
    let mut meta = BTreeMap::new();
    meta.insert("world".to_owned(), world.label());
    meta.insert("seed".to_owned(), world.seed.to_string());
    if let Some(i) = world.index {
        meta.insert("index".to_owned(), i.to_string());
    }
    meta.insert("frame_dt".to_owned(), motion.frame_dt.to_string());
    w.write_metadata(&mcap::records::Metadata {
        name: "mwb.export".to_owned(),
        metadata: meta,
    })?;

    // The scene: every entity once, at time 0.
    let forever = Duration::new(0, 0);
    let mut entities = Vec::new();
    for st in &scene.statics {
        let half = crate::glb::plane_half_size(st.position, motion);
        let mut e = entity(format!("static/{}", st.name), SCENE_FRAME, forever);
        let at = (st.position, st.rotation);
        add_parts(&mut e, scene, &st.shape, st.material, at, half).map_err(|reason| {
            ExportError::Shape {
                what: "static",
                name: st.name.clone(),
                reason,
            }
        })?;
        entities.push(e);
    }
    for body in &scene.bodies {
        let mut e = entity(
            format!("body/{}", body.name),
            &body_frame(&body.name),
            forever,
        );
        e.frame_locked = true;
        let local = ([0.0; 3], mwb_core::scene::IDENTITY);
        add_parts(
            &mut e,
            scene,
            &body.shape,
            body.material,
            local,
            crate::glb::MIN_PLANE_HALF_SIZE,
        )
        .map_err(|reason| ExportError::Shape {
            what: "body",
            name: body.name.clone(),
            reason,
        })?;
        entities.push(e);
    }
    let update = SceneUpdate {
        deletions: Vec::new(),
        entities,
    };
    write_message(&mut w, scene_channel, 0, 0, &update)?;

    // The motion: one FrameTransforms per frame.
    let rotations = motion.continuous_rotations();
    let half = std::f64::consts::FRAC_1_SQRT_2;
    for k in 0..motion.frame_count() {
        let t_ns = (k as f64 * motion.frame_dt * 1e9).round() as u64;
        let stamp = timestamp(t_ns);
        let mut transforms = Vec::with_capacity(scene.bodies.len() + 1);
        transforms.push(FrameTransform {
            timestamp: Some(stamp),
            parent_frame_id: WORLD_FRAME.to_owned(),
            child_frame_id: SCENE_FRAME.to_owned(),
            translation: Some(vector([0.0; 3])),
            rotation: Some(quaternion([half, 0.0, 0.0, half])),
        });
        for (i, body) in scene.bodies.iter().enumerate() {
            transforms.push(FrameTransform {
                timestamp: Some(stamp),
                parent_frame_id: SCENE_FRAME.to_owned(),
                child_frame_id: body_frame(&body.name),
                translation: Some(vector(motion.tracks[i].positions[k])),
                rotation: Some(quaternion(rotations[i][k])),
            });
        }
        write_message(
            &mut w,
            tf_channel,
            k as u32 + 1,
            t_ns,
            &FrameTransforms { transforms },
        )?;
    }
    w.finish()?;
    Ok(w.into_inner().into_inner())
}

fn channel<T: Encode>(
    w: &mut mcap::Writer<Cursor<Vec<u8>>>,
    topic: &str,
) -> Result<u16, ExportError> {
    let schema = T::get_schema().ok_or_else(|| {
        ExportError::Gltf(format!("the foxglove crate has no schema for {topic}"))
    })?;
    let id = w.add_schema(&schema.name, &schema.encoding, &schema.data)?;
    Ok(w.add_channel(id, topic, &T::get_message_encoding(), &BTreeMap::new())?)
}

fn write_message<T: Encode>(
    w: &mut mcap::Writer<Cursor<Vec<u8>>>,
    channel_id: u16,
    sequence: u32,
    t_ns: u64,
    message: &T,
) -> Result<(), ExportError>
where
    ExportError: From<T::Error>,
{
    let mut buf = Vec::with_capacity(message.encoded_len().unwrap_or(256));
    message.encode(&mut buf)?;
    w.write_to_known_channel(
        &mcap::records::MessageHeader {
            channel_id,
            sequence,
            log_time: t_ns,
            publish_time: t_ns,
        },
        &buf,
    )?;
    Ok(())
}

fn timestamp(t_ns: u64) -> Timestamp {
    Timestamp::new((t_ns / 1_000_000_000) as u32, (t_ns % 1_000_000_000) as u32)
}

fn entity(id: String, frame: &str, lifetime: Duration) -> SceneEntity {
    SceneEntity {
        timestamp: Some(Timestamp::new(0, 0)),
        frame_id: frame.to_owned(),
        id,
        lifetime: Some(lifetime),
        ..Default::default()
    }
}

fn vector(p: [f64; 3]) -> Vector3 {
    Vector3 {
        x: p[0],
        y: p[1],
        z: p[2],
    }
}

fn quaternion(q: [f64; 4]) -> Quaternion {
    Quaternion {
        x: q[0],
        y: q[1],
        z: q[2],
        w: q[3],
    }
}

fn pose(p: [f64; 3], q: [f64; 4]) -> Pose {
    Pose {
        position: Some(vector(p)),
        orientation: Some(quaternion(q)),
    }
}

/// `a ∘ b` for quaternions `[x, y, z, w]`.
fn compose(a: [f64; 4], b: [f64; 4]) -> [f64; 4] {
    [
        a[3] * b[0] + a[0] * b[3] + a[1] * b[2] - a[2] * b[1],
        a[3] * b[1] - a[0] * b[2] + a[1] * b[3] + a[2] * b[0],
        a[3] * b[2] + a[0] * b[1] - a[1] * b[0] + a[2] * b[3],
        a[3] * b[3] - a[0] * b[0] - a[1] * b[1] - a[2] * b[2],
    ]
}

/// Every part of `shape` (one for a single shape) placed at `at` (position, rotation), each in
/// its part's material's colour.
fn add_parts(
    e: &mut SceneEntity,
    scene: &mwb_core::scene::Scene,
    shape: &Shape,
    material: usize,
    at: ([f64; 3], [f64; 4]),
    plane_half_size: f64,
) -> Result<(), String> {
    let compound = matches!(shape, Shape::Compound { .. });
    for (i, part) in shape.placed_parts(material).into_iter().enumerate() {
        let colour = crate::glb::material_colour(scene, part.material);
        if !compound {
            return add_shape(e, part.shape, pose(at.0, at.1), colour, plane_half_size);
        }
        let offset = crate::mesh::rotate(at.1, part.position);
        let position = [0, 1, 2].map(|k| at.0[k] + offset[k]);
        let rotation = compose(at.1, part.rotation);
        add_shape(
            e,
            part.shape,
            pose(position, rotation),
            colour,
            plane_half_size,
        )
        .map_err(|err| format!("part {i}: {err}"))?;
    }
    Ok(())
}

fn add_shape(
    e: &mut SceneEntity,
    shape: &Shape,
    at: Pose,
    rgb: [f32; 3],
    plane_half_size: f64,
) -> Result<(), String> {
    let color = Some(Color {
        r: f64::from(rgb[0]),
        g: f64::from(rgb[1]),
        b: f64::from(rgb[2]),
        a: 1.0,
    });
    match shape {
        Shape::Box { half_extents: h } => e.cubes.push(CubePrimitive {
            pose: Some(at),
            size: Some(vector([2.0 * h[0], 2.0 * h[1], 2.0 * h[2]])),
            color,
        }),
        Shape::Sphere { radius } => e.spheres.push(SpherePrimitive {
            pose: Some(at),
            size: Some(vector([2.0 * radius; 3])),
            color,
        }),
        Shape::Cylinder {
            half_height,
            radius,
        } => {
            // Foxglove's cylinder runs along its z axis, ours along y: turn z onto y (−90°
            // about x) inside the shape's pose.
            let h = std::f64::consts::FRAC_1_SQRT_2;
            let q0 = at
                .orientation
                .as_ref()
                .map_or(mwb_core::scene::IDENTITY, |q| [q.x, q.y, q.z, q.w]);
            let p0 = at.position.as_ref().map_or([0.0; 3], |p| [p.x, p.y, p.z]);
            e.cylinders.push(CylinderPrimitive {
                pose: Some(pose(p0, compose(q0, [-h, 0.0, 0.0, h]))),
                size: Some(vector([2.0 * radius, 2.0 * radius, 2.0 * half_height])),
                bottom_scale: 1.0,
                top_scale: 1.0,
                color,
            });
        }
        Shape::Capsule { .. }
        | Shape::ConvexHull { .. }
        | Shape::Plane { .. }
        | Shape::TriMesh { .. }
        | Shape::Compound { .. } => {
            let m: TriangleMesh = shape_mesh(shape, plane_half_size)?;
            e.triangles.push(TriangleListPrimitive {
                pose: Some(at),
                points: m
                    .positions
                    .iter()
                    .map(|p| Point3 {
                        x: f64::from(p[0]),
                        y: f64::from(p[1]),
                        z: f64::from(p[2]),
                    })
                    .collect(),
                color,
                colors: Vec::new(),
                indices: m.indices,
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cylinder_turn_maps_z_onto_y() {
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let q = compose(mwb_core::scene::IDENTITY, [-h, 0.0, 0.0, h]);
        // Rotate (0, 0, 1) by q: v' = v + 2w(u × v) + 2u × (u × v).
        let u = [q[0], q[1], q[2]];
        let v = [0.0, 0.0, 1.0];
        let c = |a: [f64; 3], b: [f64; 3]| {
            [
                a[1] * b[2] - a[2] * b[1],
                a[2] * b[0] - a[0] * b[2],
                a[0] * b[1] - a[1] * b[0],
            ]
        };
        let t = c(u, v).map(|x| 2.0 * x);
        let r = c(u, t);
        let out = [0, 1, 2].map(|i| v[i] + q[3] * t[i] + r[i]);
        assert!((out[1] - 1.0).abs() < 1e-12 && out[0].abs() < 1e-12 && out[2].abs() < 1e-12);
    }
}
