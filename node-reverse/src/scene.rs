//! Scenes for backward runs: the ordinary scene format (`docs/scene-format.md`, one parser for
//! forward and backward worlds) read as a *final* state, and the scenes shipped in
//! `scenes/reverse/` (§5.4).
//!
//! ```
//! use mwb_reverse::scene::{builtin, world_from_toml};
//!
//! let world = world_from_toml(builtin::STACK, "scenes/reverse/stack.toml")?;
//! assert_eq!(world.bodies.len(), 10);
//! # Ok::<(), mwb_reverse::SceneConvertError>(())
//! ```

use mwb_core::scene::{self as core_scene, BodyRef, JointKind, Scene, SceneTemplate, Shape};
use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use parry3d::shape::SharedShape;

use crate::body::to_vec3;
use crate::{Body, BodyError, Joint, JointError, Material, StaticBody, World};

/// The scenes of `scenes/reverse/`, compiled in.
pub mod builtin {
    /// About 20 boxes lying on a plane, spelling "MWB" seen from above (§5.4.2).
    pub const WORD: &str = include_str!("../../scenes/reverse/word.toml");
    /// Ten bricks in a stack (§5.4.3).
    pub const STACK: &str = include_str!("../../scenes/reverse/stack.toml");
    /// A few thousand balls resting in square bins that spell "MWB" (§5.4.1).
    pub const BALLS: &str = include_str!("../../scenes/reverse/balls.toml");
    /// The same layout with a few dozen balls, for tests.
    pub const BALLS_SMALL: &str = include_str!("../../scenes/reverse/balls_small.toml");
    /// Boxes in mid-air, for a mixed run (§5.4.4).
    pub const CRASH: &str = include_str!("../../scenes/reverse/crash.toml");
    /// A hinged gate and a chain of boxes joined by ball joints, on the ground (§5.3.4).
    pub const GATE: &str = include_str!("../../scenes/reverse/gate.toml");

    /// `(name, source)` of every shipped reverse scene.
    pub const ALL: &[(&str, &str)] = &[
        ("word", WORD),
        ("stack", STACK),
        ("balls", BALLS),
        ("balls_small", BALLS_SMALL),
        ("crash", CRASH),
        ("gate", GATE),
    ];
}

/// Why a scene could not become a [`World`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SceneConvertError {
    /// The TOML was refused by the scene parser.
    #[error(transparent)]
    Parse(#[from] core_scene::SceneError),
    /// A joint could not be built (cannot come from a parsed scene except through numbers
    /// that are not finite).
    #[error("joint {name:?}: field `{field}`: {source}")]
    Joint {
        /// Its name.
        name: String,
        /// The scene field at fault (`body1`, `body2`, `anchor1`, `anchor2`, `axis`).
        field: &'static str,
        /// Why.
        source: JointError,
    },
    /// A body could not be built.
    #[error("body {name:?}: {source}")]
    Body {
        /// Its name.
        name: String,
        /// Why.
        source: BodyError,
    },
    /// A static could not be built.
    #[error("static {name:?}: {source}")]
    Static {
        /// Its name.
        name: String,
        /// Why.
        source: BodyError,
    },
    /// A material index out of range (cannot come from a parsed scene).
    #[error("{item} {name:?}: material index {index} out of range")]
    Material {
        /// "body" or "static".
        item: &'static str,
        /// Its name.
        name: String,
        /// The index.
        index: usize,
    },
}

fn v3(v: &core_scene::Vec3) -> Vector3<f64> {
    Vector3::new(v[0], v[1], v[2])
}

fn quat(q: &core_scene::Quat) -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(Quaternion::new(q[3], q[0], q[1], q[2]))
}

fn material<'a>(
    scene: &'a Scene,
    index: usize,
    item: &'static str,
    name: &str,
) -> Result<&'a core_scene::Material, SceneConvertError> {
    scene
        .materials
        .get(index)
        .ok_or_else(|| SceneConvertError::Material {
            item,
            name: name.to_owned(),
            index,
        })
}

/// The world of a concrete scene, its bodies at the scene's poses and velocities (for a
/// backward run: the final state). Gravity comes from the scene (y up by convention).
pub fn world_from_scene(scene: &Scene) -> Result<World, SceneConvertError> {
    let mut world = World::new();
    // Per body, its centre of mass in its own frame: joint anchors are given relative to the
    // body's frame, our bodies' frames sit at the centre of mass.
    let mut centres = Vec::with_capacity(scene.bodies.len());
    world.gravity = v3(&scene.settings.gravity);
    for b in &scene.bodies {
        let m = material(scene, b.material, "body", &b.name)?;
        let err = |source| SceneConvertError::Body {
            name: b.name.clone(),
            source,
        };
        let rot = quat(&b.rotation);
        let pos = v3(&b.position);
        let body = match &b.shape {
            Shape::Box { half_extents } => Body::cuboid(v3(half_extents), m.density),
            Shape::Sphere { radius } => Body::ball(*radius, m.density),
            Shape::Capsule {
                half_height,
                radius,
            } => Body::capsule(*half_height, *radius, m.density),
            Shape::Cylinder {
                half_height,
                radius,
            } => Body::cylinder(*half_height, *radius, m.density),
            Shape::ConvexHull { points } => {
                let pts: Vec<_> = points.iter().map(v3).collect();
                Body::convex_hull(&pts, m.density)
            }
            Shape::Plane { .. } | Shape::TriMesh { .. } => Err(BodyError::InvalidParameter {
                what: "dynamic shape (planes and meshes are static only)",
                value: f64::NAN,
            }),
        }
        .map_err(err)?;
        // A hull's body position is its centre of mass in the points' frame.
        centres.push(body.position);
        let com = rot * body.position;
        world.add_body(
            body.with_material(Material {
                friction: m.friction,
                restitution: m.restitution,
            })
            .at(pos + com, rot)
            .moving(v3(&b.linvel), v3(&b.angvel)),
        );
    }
    for s in &scene.statics {
        let m = material(scene, s.material, "static", &s.name)?;
        let err = |source| SceneConvertError::Static {
            name: s.name.clone(),
            source,
        };
        let rot = quat(&s.rotation);
        let pos = v3(&s.position);
        let st = match &s.shape {
            Shape::Plane { normal } => {
                let n = rot * v3(normal);
                StaticBody::plane(n, n.dot(&pos) / n.norm().max(f64::MIN_POSITIVE))
            }
            Shape::Box { half_extents } => StaticBody::cuboid(v3(half_extents), pos, rot),
            Shape::Sphere { radius } => {
                Ok(StaticBody::new(SharedShape::ball(*radius as f32), pos, rot))
            }
            Shape::Capsule {
                half_height,
                radius,
            } => Ok(StaticBody::new(
                SharedShape::capsule_y(*half_height as f32, *radius as f32),
                pos,
                rot,
            )),
            Shape::Cylinder {
                half_height,
                radius,
            } => Ok(StaticBody::new(
                SharedShape::cylinder(*half_height as f32, *radius as f32),
                pos,
                rot,
            )),
            Shape::ConvexHull { points } => {
                let pts: Vec<_> = points.iter().map(|p| to_vec3(&v3(p))).collect();
                SharedShape::convex_hull(&pts)
                    .map(|shape| StaticBody::new(shape, pos, rot))
                    .ok_or(BodyError::DegenerateHull)
            }
            Shape::TriMesh { vertices, indices } => {
                let verts: Vec<_> = vertices.iter().map(v3).collect();
                StaticBody::trimesh(&verts, indices.clone()).map(|mut t| {
                    t.position = pos;
                    t.orientation = rot;
                    t
                })
            }
        }
        .map_err(err)?;
        world.add_static(st.with_material(Material {
            friction: m.friction,
            restitution: m.restitution,
        }));
    }
    for j in &scene.joints {
        let joint = joint_from_scene(j, &centres)?;
        world
            .add_joint(joint)
            .map_err(|source| joint_error(&j.name, source))?;
    }
    Ok(world)
}

/// The scene field a [`JointError`] is about.
fn joint_error(name: &str, source: JointError) -> SceneConvertError {
    let field = match &source {
        JointError::BodyOutOfRange { which, .. } => which,
        JointError::SameBody(_) | JointError::NoBody => "body2",
        JointError::NonFinite(what) | JointError::ZeroAxis(what) => match *what {
            "anchor1" => "anchor1",
            "anchor2" => "anchor2",
            _ => "axis",
        },
    };
    SceneConvertError::Joint {
        name: name.to_owned(),
        field,
        source,
    }
}

/// One scene joint, read as the forward sampler (rapier) reads it: anchors in each body's
/// frame (world coordinates for `"world"`), a revolute axis in both frames alike, and a weld
/// that keeps the two frames' orientations equal. A joint whose first end is the world is
/// turned around (our joints name a dynamic body first); every kind is symmetric under that.
fn joint_from_scene(
    j: &core_scene::Joint,
    centres: &[Vector3<f64>],
) -> Result<Joint, SceneConvertError> {
    let err = |source| joint_error(&j.name, source);
    let end = |r: BodyRef, anchor: &core_scene::Vec3, which: &'static str| match r {
        BodyRef::World => Ok((None, v3(anchor))),
        BodyRef::Body(i) => match centres.get(i) {
            Some(com) => Ok((Some(i), v3(anchor) - com)),
            None => Err(err(JointError::BodyOutOfRange {
                which,
                index: i,
                len: centres.len(),
            })),
        },
    };
    let first = end(j.body1, &j.anchor1, "body1")?;
    let second = end(j.body2, &j.anchor2, "body2")?;
    let ((body1, anchor1), (body2, anchor2)) = match (first, second) {
        ((Some(b1), a1), second) => ((b1, a1), second),
        (first, (Some(b2), a2)) => ((b2, a2), first),
        ((None, _), (None, _)) => {
            return Err(err(JointError::NoBody));
        }
    };
    match j.kind {
        JointKind::Spherical => Ok(Joint::spherical(body1, body2, anchor1, anchor2)),
        JointKind::Revolute { axis } => {
            let axis = v3(&axis);
            Joint::revolute(body1, body2, (anchor1, anchor2), (axis, axis)).map_err(|e| match e {
                JointError::NonFinite(_) => err(JointError::NonFinite("axis")),
                JointError::ZeroAxis(_) => err(JointError::ZeroAxis("axis")),
                other => err(other),
            })
        }
        JointKind::Fixed => Ok(Joint::fixed(
            body1,
            body2,
            (anchor1, anchor2),
            UnitQuaternion::identity(),
        )),
    }
}

/// Parses a scene (`file` names it in errors), instantiates it with seed 0 (a final state is
/// usually plain numbers) and converts it.
pub fn world_from_toml(src: &str, file: &str) -> Result<World, SceneConvertError> {
    let template = SceneTemplate::parse(src, file)?;
    world_from_scene(&template.instantiate(0))
}
