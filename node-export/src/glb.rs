//! glTF 2.0 binary (`.glb`) of one world: what Blender, Maya and Houdini import.
//!
//! Layout of the file:
//! * one scene, named after the world (`"tumble world 3"`), with one root node of the same
//!   name; its children are a node per static (named as in the scene, placed once) and a node
//!   per dynamic body (named as in the scene, placed at frame 0), each with its own mesh (a
//!   compound's mesh has a primitive per part, each with its part's material);
//! * one material per scene material (named as in the scene; PBR, not metallic; statics-only
//!   materials grey, the others from a fixed palette);
//! * one animation, named after the world: per body a translation and a rotation channel with
//!   one key per frame at the scene's frame rate (`t = k · frame_dt`), LINEAR (rotations are
//!   slerped), the quaternions' signs made continuous ([`crate::Motion::continuous_rotations`]).
//!
//! Units and axes need no conversion: scenes are metres, right-handed, y up, like glTF.
//! Every buffer view starts on a 4-byte boundary; accessor `min`/`max` are those of the `f32`
//! values written (mesh positions and key times, as the specification requires).

use crate::mesh::{TriangleMesh, part_meshes};
use crate::{ExportError, ExportWorld};
use gltf_json as json;
use json::validation::Checked::Valid;
use json::validation::USize64;
use std::borrow::Cow;
use std::collections::BTreeMap;

/// Half side of the square drawn for a plane, at least (m); larger when bodies travel further.
pub const MIN_PLANE_HALF_SIZE: f64 = 5.0;

/// Writes one world as a `.glb`.
pub fn write(world: &ExportWorld<'_>) -> Result<Vec<u8>, ExportError> {
    world.check()?;
    let scene = world.scene;
    let motion = world.motion;
    let label = world.label();
    let mut b = Builder::default();

    let materials: Vec<json::Index<json::Material>> = scene
        .materials
        .iter()
        .enumerate()
        .map(|(i, m)| b.root.push(material(&m.name, material_colour(scene, i))))
        .collect();
    let material_of = |i: usize| materials.get(i).copied();
    // A primitive per part (one for a single shape), each with its part's material.
    let primitives = |parts: Vec<(usize, TriangleMesh)>| -> Vec<(TriangleMesh, Option<json::Index<json::Material>>)> {
        parts
            .into_iter()
            .map(|(material, m)| (m, material_of(material)))
            .collect()
    };

    let mut children = Vec::new();
    for st in &scene.statics {
        let half = plane_half_size(st.position, motion);
        let parts =
            part_meshes(&st.shape, st.material, half).map_err(|reason| ExportError::Shape {
                what: "static",
                name: st.name.clone(),
                reason,
            })?;
        let mesh = b.mesh(&st.name, &primitives(parts));
        children.push(b.root.push(node(&st.name, mesh, st.position, st.rotation)));
    }
    let rotations = motion.continuous_rotations();
    let mut body_nodes = Vec::new();
    for (i, body) in scene.bodies.iter().enumerate() {
        let parts =
            part_meshes(&body.shape, body.material, MIN_PLANE_HALF_SIZE).map_err(|reason| {
                ExportError::Shape {
                    what: "body",
                    name: body.name.clone(),
                    reason,
                }
            })?;
        let mesh = b.mesh(&body.name, &primitives(parts));
        let n = b.root.push(node(
            &body.name,
            mesh,
            motion.tracks[i].positions[0],
            rotations[i][0],
        ));
        body_nodes.push(n);
        children.push(n);
    }
    let root_node = b.root.push(json::Node {
        name: Some(label.clone()),
        children: Some(children),
        ..Default::default()
    });
    let gltf_scene = b.root.push(json::Scene {
        extensions: Default::default(),
        extras: Default::default(),
        name: Some(label.clone()),
        nodes: vec![root_node],
    });
    b.root.scene = Some(gltf_scene);

    // The animation: one shared time accessor, two samplers and channels per body.
    let frames = motion.frame_count();
    let times: Vec<f32> = (0..frames)
        .map(|k| (k as f64 * motion.frame_dt) as f32)
        .collect();
    let t_last = times[frames - 1];
    let input = b.accessor_f32(
        "time",
        &times,
        json::accessor::Type::Scalar,
        None,
        Some((vec![0.0], vec![t_last])),
    );
    let mut samplers = Vec::new();
    let mut channels = Vec::new();
    for (i, body) in scene.bodies.iter().enumerate() {
        let translation: Vec<f32> = motion.tracks[i]
            .positions
            .iter()
            .flat_map(|p| p.map(|x| x as f32))
            .collect();
        let rotation: Vec<f32> = rotations[i]
            .iter()
            .flat_map(|q| q.map(|x| x as f32))
            .collect();
        let outputs = [
            (
                json::animation::Property::Translation,
                b.accessor_f32(
                    &format!("{} translation", body.name),
                    &translation,
                    json::accessor::Type::Vec3,
                    None,
                    None,
                ),
            ),
            (
                json::animation::Property::Rotation,
                b.accessor_f32(
                    &format!("{} rotation", body.name),
                    &rotation,
                    json::accessor::Type::Vec4,
                    None,
                    None,
                ),
            ),
        ];
        for (path, output) in outputs {
            let sampler = json::Index::push(
                &mut samplers,
                json::animation::Sampler {
                    extensions: Default::default(),
                    extras: Default::default(),
                    input,
                    interpolation: Valid(json::animation::Interpolation::Linear),
                    output,
                },
            );
            channels.push(json::animation::Channel {
                sampler,
                target: json::animation::Target {
                    extensions: Default::default(),
                    extras: Default::default(),
                    node: body_nodes[i],
                    path: Valid(path),
                },
                extensions: Default::default(),
                extras: Default::default(),
            });
        }
    }
    if !channels.is_empty() {
        b.root.push(json::Animation {
            extensions: Default::default(),
            extras: Default::default(),
            channels,
            name: Some(label),
            samplers,
        });
    }
    b.finish()
}

/// Colours of the materials dynamic bodies use (linear RGB), by material index.
const PALETTE: [[f32; 3]; 6] = [
    [0.60, 0.38, 0.18], // wood
    [0.15, 0.35, 0.75],
    [0.75, 0.18, 0.15],
    [0.20, 0.55, 0.25],
    [0.80, 0.65, 0.10],
    [0.45, 0.25, 0.65],
];
/// Materials only statics use: the ground, ramps, walls.
const STATIC_GREY: [f32; 3] = [0.45, 0.45, 0.45];

/// The colour of scene material `i`: grey if only statics use it, else from the palette.
pub(crate) fn material_colour(scene: &mwb_core::scene::Scene, i: usize) -> [f32; 3] {
    let used_by_bodies = scene.bodies.iter().any(|b| {
        b.shape
            .placed_parts(b.material)
            .iter()
            .any(|p| p.material == i)
    });
    if used_by_bodies {
        PALETTE[i % PALETTE.len()]
    } else {
        STATIC_GREY
    }
}

fn material(name: &str, rgb: [f32; 3]) -> json::Material {
    json::Material {
        name: Some(name.to_owned()),
        pbr_metallic_roughness: json::material::PbrMetallicRoughness {
            base_color_factor: json::material::PbrBaseColorFactor([rgb[0], rgb[1], rgb[2], 1.0]),
            metallic_factor: json::material::StrengthFactor(0.0),
            roughness_factor: json::material::StrengthFactor(0.7),
            ..Default::default()
        },
        ..Default::default()
    }
}

fn node(
    name: &str,
    mesh: json::Index<json::Mesh>,
    position: [f64; 3],
    rotation: [f64; 4],
) -> json::Node {
    let q = crate::motion::sign_continuous(&[rotation])[0];
    json::Node {
        name: Some(name.to_owned()),
        mesh: Some(mesh),
        translation: Some(position.map(|x| x as f32)),
        rotation: Some(json::scene::UnitQuaternion(q.map(|x| x as f32))),
        ..Default::default()
    }
}

/// A plane is drawn as a square reaching `MIN_PLANE_HALF_SIZE`, or 2 m past the furthest any
/// body gets from the plane's point.
pub(crate) fn plane_half_size(origin: [f64; 3], motion: &crate::Motion) -> f64 {
    let far = motion
        .tracks
        .iter()
        .flat_map(|t| &t.positions)
        .map(|p| {
            let d = [p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]];
            (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
        })
        .filter(|d| d.is_finite())
        .fold(0.0, f64::max);
    (far + 2.0).clamp(MIN_PLANE_HALF_SIZE, 1.0e4)
}

#[derive(Default)]
struct Builder {
    root: json::Root,
    bin: Vec<u8>,
}

impl Builder {
    /// Appends `bytes` as a buffer view starting on a 4-byte boundary.
    fn view(
        &mut self,
        bytes: &[u8],
        target: Option<json::buffer::Target>,
    ) -> json::Index<json::buffer::View> {
        pad4(&mut self.bin);
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.root.push(json::buffer::View {
            buffer: json::Index::new(0),
            byte_length: USize64::from(bytes.len()),
            byte_offset: Some(USize64::from(offset)),
            byte_stride: None,
            name: None,
            target: target.map(Valid),
            extensions: Default::default(),
            extras: Default::default(),
        })
    }

    fn accessor_f32(
        &mut self,
        name: &str,
        data: &[f32],
        ty: json::accessor::Type,
        target: Option<json::buffer::Target>,
        min_max: Option<(Vec<f32>, Vec<f32>)>,
    ) -> json::Index<json::Accessor> {
        let per = ty.multiplicity();
        let bytes: Vec<u8> = data.iter().flat_map(|x| x.to_le_bytes()).collect();
        let view = self.view(&bytes, target);
        let (min, max) = match min_max {
            Some((lo, hi)) => (Some(json::Value::from(lo)), Some(json::Value::from(hi))),
            None => (None, None),
        };
        self.root.push(json::Accessor {
            buffer_view: Some(view),
            byte_offset: None,
            count: USize64::from(data.len() / per),
            component_type: Valid(json::accessor::GenericComponentType(
                json::accessor::ComponentType::F32,
            )),
            extensions: Default::default(),
            extras: Default::default(),
            type_: Valid(ty),
            min,
            max,
            name: Some(name.to_owned()),
            normalized: false,
            sparse: None,
        })
    }

    /// A mesh of triangle primitives (one per part of a compound, else one).
    fn mesh(
        &mut self,
        name: &str,
        parts: &[(TriangleMesh, Option<json::Index<json::Material>>)],
    ) -> json::Index<json::Mesh> {
        let primitives = parts
            .iter()
            .enumerate()
            .map(|(i, (m, material))| {
                // A single shape's accessors keep their names ("ball positions").
                let label = if parts.len() == 1 {
                    name.to_owned()
                } else {
                    format!("{name} part {i}")
                };
                self.primitive(&label, m, *material)
            })
            .collect();
        self.root.push(json::Mesh {
            extensions: Default::default(),
            extras: Default::default(),
            name: Some(name.to_owned()),
            primitives,
            weights: None,
        })
    }

    /// One triangle primitive: POSITION (with min/max), NORMAL, indices (u16 when every index
    /// fits below 65535, the value reserved for primitive restart, else u32).
    fn primitive(
        &mut self,
        name: &str,
        m: &TriangleMesh,
        material: Option<json::Index<json::Material>>,
    ) -> json::mesh::Primitive {
        let (lo, hi) = m.bounds();
        let flat = |v: &[[f32; 3]]| -> Vec<f32> { v.iter().flatten().copied().collect() };
        let position = self.accessor_f32(
            &format!("{name} positions"),
            &flat(&m.positions),
            json::accessor::Type::Vec3,
            Some(json::buffer::Target::ArrayBuffer),
            Some((lo.to_vec(), hi.to_vec())),
        );
        let normal = self.accessor_f32(
            &format!("{name} normals"),
            &flat(&m.normals),
            json::accessor::Type::Vec3,
            Some(json::buffer::Target::ArrayBuffer),
            None,
        );
        let small = m.positions.len() < usize::from(u16::MAX);
        let (bytes, component) = if small {
            let b: Vec<u8> = m
                .indices
                .iter()
                .flat_map(|&i| (i as u16).to_le_bytes())
                .collect();
            (b, json::accessor::ComponentType::U16)
        } else {
            let b: Vec<u8> = m.indices.iter().flat_map(|i| i.to_le_bytes()).collect();
            (b, json::accessor::ComponentType::U32)
        };
        let view = self.view(&bytes, Some(json::buffer::Target::ElementArrayBuffer));
        let indices = self.root.push(json::Accessor {
            buffer_view: Some(view),
            byte_offset: None,
            count: USize64::from(m.indices.len()),
            component_type: Valid(json::accessor::GenericComponentType(component)),
            extensions: Default::default(),
            extras: Default::default(),
            type_: Valid(json::accessor::Type::Scalar),
            min: None,
            max: None,
            name: Some(format!("{name} indices")),
            normalized: false,
            sparse: None,
        });
        let mut attributes = BTreeMap::new();
        attributes.insert(Valid(json::mesh::Semantic::Positions), position);
        attributes.insert(Valid(json::mesh::Semantic::Normals), normal);
        json::mesh::Primitive {
            attributes,
            extensions: Default::default(),
            extras: Default::default(),
            indices: Some(indices),
            material,
            mode: Valid(json::mesh::Mode::Triangles),
            targets: None,
        }
    }

    fn finish(mut self) -> Result<Vec<u8>, ExportError> {
        pad4(&mut self.bin);
        self.root.push(json::Buffer {
            byte_length: USize64::from(self.bin.len()),
            name: None,
            uri: None,
            extensions: Default::default(),
            extras: Default::default(),
        });
        self.root.asset = json::Asset {
            generator: Some(format!("mwb-export {}", env!("CARGO_PKG_VERSION"))),
            ..Default::default()
        };
        let json = self
            .root
            .to_vec()
            .map_err(|e| ExportError::Gltf(e.to_string()))?;
        let glb = gltf::binary::Glb {
            header: gltf::binary::Header {
                magic: *b"glTF",
                version: 2,
                length: 0, // computed by to_vec
            },
            json: Cow::Owned(json),
            bin: Some(Cow::Owned(self.bin)),
        };
        glb.to_vec().map_err(|e| ExportError::Gltf(e.to_string()))
    }
}

fn pad4(bin: &mut Vec<u8>) {
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
}
