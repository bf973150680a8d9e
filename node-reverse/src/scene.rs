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
    /// 3037 balls resting in square bins spelling "LOREM IPSUM DOLOR SIT AMET..." (§5.4.1).
    pub const LOREM: &str = include_str!("../../scenes/reverse/lorem.toml");
    /// [`CRASH`] with a `[reverse]` table asking for a mixed run (§5.4.4). Not in [`ALL`]: the
    /// plain scene parser refuses the table; [`crate::ReverseScene::prepare`] reads it.
    pub const CRASH_MIXED: &str = include_str!("../../scenes/reverse/crash_mixed.toml");

    /// `(name, source)` of every shipped reverse scene.
    pub const ALL: &[(&str, &str)] = &[
        ("word", WORD),
        ("stack", STACK),
        ("balls", BALLS),
        ("balls_small", BALLS_SMALL),
        ("crash", CRASH),
        ("gate", GATE),
        ("lorem", LOREM),
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
    /// A dynamic body made of several shapes: our stepper's bodies have one convex shape
    /// centred on their centre of mass (compound statics are fine: each part is a static).
    #[error(
        "body {name:?}: compound shapes are not supported by the backward stepper (mwb reverse); use a single shape"
    )]
    Compound {
        /// Its name.
        name: String,
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
            Shape::Compound { .. } => {
                return Err(SceneConvertError::Compound {
                    name: b.name.clone(),
                });
            }
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
        // A compound static is its parts, each a static of its own (immovable geometry needs
        // no common centre of mass), at the static's pose composed with the part's.
        let (at, turn) = (v3(&s.position), quat(&s.rotation));
        let compound = matches!(s.shape, Shape::Compound { .. });
        for part in s.shape.placed_parts(s.material) {
            let (pos, rot) = if compound {
                (at + turn * v3(&part.position), turn * quat(&part.rotation))
            } else {
                (at, turn) // exactly as before compounds: the same statics, bit for bit
            };
            world.add_static(static_from_scene(scene, &s.name, part, pos, rot)?);
        }
    }
    for j in &scene.joints {
        let joint = joint_from_scene(j, &centres)?;
        world
            .add_joint(joint)
            .map_err(|source| joint_error(&j.name, source))?;
    }
    Ok(world)
}

/// One static shape (a whole static, or a part of a compound static) at its world pose.
fn static_from_scene(
    scene: &Scene,
    name: &str,
    part: core_scene::PlacedPart<'_>,
    pos: Vector3<f64>,
    rot: UnitQuaternion<f64>,
) -> Result<StaticBody, SceneConvertError> {
    let m = material(scene, part.material, "static", name)?;
    let err = |source| SceneConvertError::Static {
        name: name.to_owned(),
        source,
    };
    let st = match part.shape {
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
        // The parser never nests compounds.
        Shape::Compound { .. } => Err(BodyError::InvalidParameter {
            what: "compound nested in a compound",
            value: f64::NAN,
        }),
    }
    .map_err(err)?;
    Ok(st.with_material(Material {
        friction: m.friction,
        restitution: m.restitution,
    }))
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

#[cfg(test)]
mod tests {
    use super::*;

    const LETTER_ON_A_SHELF: &str = r#"
name = "letters"
[[material]]
name = "wood"
[[material]]
name = "ice"
friction = 0.05
[[static]]
name = "ground"
shape = "plane"
material = "wood"
[[static]]
name = "shelf"
shape = "compound"
material = "wood"
position = [1, 0, 0]
rotation_deg = [0, 90, 0]
part = [
  { shape = "box", size = [1, 0.1, 0.4], position = [0, 0.5, 0] },
  { shape = "box", size = [0.1, 0.5, 0.4], position = [0.45, 0.25, 0], material = "ice" },
]
[[body]]
name = "ball"
shape = "sphere"
radius = 0.1
material = "wood"
position = [0, 0.1, 0]
"#;

    #[test]
    fn a_compound_static_becomes_a_static_per_part_at_its_pose() {
        let world =
            world_from_toml(LETTER_ON_A_SHELF, "letters.toml").unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            world.statics.len(),
            3,
            "the ground and the shelf's two parts"
        );
        let foot = &world.statics[2];
        // 90° about y turns the part's offset +x onto −z: (1, 0.25, −0.45).
        let want = Vector3::new(1.0, 0.25, -0.45);
        assert!((foot.position - want).norm() < 1e-12, "{}", foot.position);
        assert_eq!(foot.material.friction, 0.05, "the part's own material");
        assert_eq!(world.statics[1].material.friction, 0.5);
    }

    #[test]
    fn a_compound_body_is_refused_by_name_without_a_panic() {
        let src = LETTER_ON_A_SHELF.replace(
            "[[body]]\nname = \"ball\"\nshape = \"sphere\"\nradius = 0.1\n",
            "[[body]]\nname = \"letter_s\"\nshape = \"compound\"\npart = [{ shape = \"sphere\", radius = 0.1 }]\n",
        );
        let err = match world_from_toml(&src, "letters.toml") {
            Ok(_) => panic!("a compound body was accepted"),
            Err(e) => e,
        };
        assert_eq!(
            err,
            SceneConvertError::Compound {
                name: "letter_s".to_owned()
            }
        );
        assert_eq!(
            err.to_string(),
            "body \"letter_s\": compound shapes are not supported by the backward stepper \
             (mwb reverse); use a single shape"
        );
    }
}
