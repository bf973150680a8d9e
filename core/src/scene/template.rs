//! The scene template: a parsed, validated scene whose numbers may still be distributions, and
//! its instantiation into a concrete [`Scene`] from a world seed.
//!
//! §4.1: "users can randomize the initial conditions of objects (or any other property in the
//! system)". Each world draws its own values from one deterministic stream
//! (`WorldRng::new(seed, Stream::Scene)`), so a world is regenerable from its seed alone
//! (DESIGN.md "World identity").

use super::error::SceneError;
use super::generators::Placement;
use super::model::{
    Body, BodyRef, IDENTITY, Joint, JointKind, Material, Part, Quat, Scene, Settings, Shape,
    StaticBody, Vec3,
};
use super::toml_span::Source;
use crate::rng::{Stream, WorldRng};

/// How one number of the scene is chosen per world.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Dist {
    /// Written as a plain number: the same in every world, draws nothing from the stream.
    Fixed(f64),
    /// `{ uniform = [a, b] }`, a ≤ b.
    Uniform(f64, f64),
    /// `{ normal = [mu, sigma] }`, sigma ≥ 0.
    Normal(f64, f64),
}

/// A number of the scene: its distribution and the interval every sample is clamped into.
///
/// The parser only builds a `Num` whose clamp interval lies inside the field's valid range, so
/// every sample is valid and [`SceneTemplate::instantiate`] cannot fail.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Num {
    pub dist: Dist,
    pub lo: f64,
    pub hi: f64,
}

impl Num {
    pub fn fixed(v: f64) -> Self {
        Self {
            dist: Dist::Fixed(v),
            lo: v,
            hi: v,
        }
    }

    pub fn is_random(&self) -> bool {
        !matches!(self.dist, Dist::Fixed(_))
    }

    /// One draw for a distribution, none for a fixed number. Clamping matters for `normal`
    /// (its tails are cut at ±4σ) and guards `uniform` against rounding at the upper end.
    pub fn sample(&self, rng: &mut WorldRng) -> f64 {
        let x = match self.dist {
            Dist::Fixed(v) => return v,
            Dist::Uniform(a, b) => rng.uniform(a, b),
            Dist::Normal(mu, sigma) => rng.normal(mu, sigma),
        };
        x.clamp(self.lo, self.hi)
    }
}

pub(crate) type NumVec3 = [Num; 3];

fn sample3(v: &NumVec3, rng: &mut WorldRng) -> Vec3 {
    // Components in x, y, z order (the documented sampling order).
    let x = v[0].sample(rng);
    let y = v[1].sample(rng);
    let z = v[2].sample(rng);
    [x, y, z]
}

/// Shape of a body or static before sampling. Point lists of hulls and meshes are fixed: a hull
/// is checked for degeneracy once, which a sampled point set could not guarantee.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum ShapeT {
    /// `full`: the file gave `size` (full extents) rather than `half_extents`.
    Box {
        extents: NumVec3,
        full: bool,
    },
    Sphere {
        radius: Num,
    },
    /// `full`: the file gave `height` rather than `half_height`.
    Capsule {
        height: Num,
        radius: Num,
        full: bool,
    },
    Cylinder {
        height: Num,
        radius: Num,
        full: bool,
    },
    ConvexHull {
        points: Vec<Vec3>,
    },
    Plane {
        normal: NumVec3,
    },
    TriMesh {
        vertices: Vec<Vec3>,
        indices: Vec<[u32; 3]>,
    },
    /// `shape = "compound"` with its `[[body.part]]` tables (never nested: the parser refuses).
    Compound {
        parts: Vec<PartT>,
    },
}

/// One part of a compound before sampling. `material` is resolved at parse time (the part's
/// own, else its body's).
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct PartT {
    pub shape: ShapeT,
    pub position: NumVec3,
    pub rotation: RotationT,
    pub material: usize,
}

impl ShapeT {
    fn nums(&self) -> Vec<&Num> {
        match self {
            ShapeT::Box { extents, .. } => extents.iter().collect(),
            ShapeT::Sphere { radius } => vec![radius],
            ShapeT::Capsule { height, radius, .. } | ShapeT::Cylinder { height, radius, .. } => {
                vec![height, radius]
            }
            ShapeT::Plane { normal } => normal.iter().collect(),
            ShapeT::ConvexHull { .. } | ShapeT::TriMesh { .. } => Vec::new(),
            ShapeT::Compound { parts } => parts
                .iter()
                .flat_map(|p| {
                    p.shape
                        .nums()
                        .into_iter()
                        .chain(&p.position)
                        .chain(p.rotation.nums())
                })
                .collect(),
        }
    }

    /// Sampling order: the fields in the order they are listed in the enum; a compound's parts
    /// in file order, each its shape, then `position`, then rotation.
    fn sample(&self, rng: &mut WorldRng) -> Shape {
        let half = |full: bool, v: f64| if full { 0.5 * v } else { v };
        match self {
            ShapeT::Box { extents, full } => {
                let e = sample3(extents, rng);
                Shape::Box {
                    half_extents: e.map(|v| half(*full, v)),
                }
            }
            ShapeT::Sphere { radius } => Shape::Sphere {
                radius: radius.sample(rng),
            },
            ShapeT::Capsule {
                height,
                radius,
                full,
            } => {
                let h = height.sample(rng);
                let radius = radius.sample(rng);
                Shape::Capsule {
                    half_height: half(*full, h),
                    radius,
                }
            }
            ShapeT::Cylinder {
                height,
                radius,
                full,
            } => {
                let h = height.sample(rng);
                let radius = radius.sample(rng);
                Shape::Cylinder {
                    half_height: half(*full, h),
                    radius,
                }
            }
            ShapeT::ConvexHull { points } => Shape::ConvexHull {
                points: points.clone(),
            },
            ShapeT::Plane { normal } => Shape::Plane {
                normal: normalize3(sample3(normal, rng)),
            },
            ShapeT::TriMesh { vertices, indices } => Shape::TriMesh {
                vertices: vertices.clone(),
                indices: indices.clone(),
            },
            ShapeT::Compound { parts } => Shape::Compound {
                parts: parts
                    .iter()
                    .map(|p| {
                        let shape = p.shape.sample(rng);
                        let position = sample3(&p.position, rng);
                        let rotation = p.rotation.sample(rng);
                        Part {
                            shape,
                            position,
                            rotation,
                            material: p.material,
                        }
                    })
                    .collect(),
            },
        }
    }
}

/// Orientation before sampling, in whichever human form the file used.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum RotationT {
    Identity,
    /// `rotation_deg = [rx, ry, rz]`: about the fixed X, then Y, then Z axes, in degrees.
    EulerXyzDeg(NumVec3),
    /// `axis_angle = { axis = [x, y, z], deg = a }`.
    AxisAngleDeg {
        axis: NumVec3,
        deg: Num,
    },
    /// `quat = [x, y, z, w]`, normalised after sampling.
    Quat([Num; 4]),
}

impl RotationT {
    fn nums(&self) -> Vec<&Num> {
        match self {
            RotationT::Identity => Vec::new(),
            RotationT::EulerXyzDeg(v) => v.iter().collect(),
            RotationT::AxisAngleDeg { axis, deg } => axis.iter().chain([deg]).collect(),
            RotationT::Quat(q) => q.iter().collect(),
        }
    }

    fn sample(&self, rng: &mut WorldRng) -> Quat {
        match self {
            RotationT::Identity => IDENTITY,
            RotationT::EulerXyzDeg(v) => {
                let [rx, ry, rz] = sample3(v, rng);
                euler_xyz_deg(rx, ry, rz)
            }
            RotationT::AxisAngleDeg { axis, deg } => {
                let axis = sample3(axis, rng);
                let deg = deg.sample(rng);
                axis_angle(normalize3(axis), deg.to_radians())
            }
            RotationT::Quat(q) => {
                let x = q[0].sample(rng);
                let y = q[1].sample(rng);
                let z = q[2].sample(rng);
                let w = q[3].sample(rng);
                normalize4([x, y, z, w])
            }
        }
    }
}

/// A `[[body]]` or `[[static]]` entry: one body, or a generator's template with its placements.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct BodyT {
    pub shape: ShapeT,
    pub material: usize,
    pub position: NumVec3,
    pub rotation: RotationT,
    /// Always zero for statics.
    pub linvel: NumVec3,
    pub angvel: NumVec3,
    /// One per instance (a single body has one placement with its own name).
    pub placements: Vec<Placement>,
}

impl BodyT {
    fn nums(&self) -> impl Iterator<Item = &Num> {
        self.shape
            .nums()
            .into_iter()
            .chain(&self.position)
            .chain(self.rotation.nums())
            .chain(&self.linvel)
            .chain(&self.angvel)
    }

    /// One instance; sampling order: shape, position, rotation, linvel, angvel.
    fn sample(&self, at: &Placement, rng: &mut WorldRng) -> Body {
        let shape = self.shape.sample(rng);
        let p = sample3(&self.position, rng);
        let rotation = normalize4(quat_mul(at.turn, self.rotation.sample(rng)));
        let linvel = sample3(&self.linvel, rng);
        let angvel = sample3(&self.angvel, rng);
        Body {
            name: at.name.clone(),
            shape,
            material: self.material,
            position: [
                p[0] + at.offset[0],
                p[1] + at.offset[1],
                p[2] + at.offset[2],
            ],
            rotation,
            linvel,
            angvel,
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub(crate) struct MaterialT {
    pub name: String,
    pub friction: Num,
    pub restitution: Num,
    pub density: Num,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum JointKindT {
    Revolute { axis: NumVec3 },
    Spherical,
    Fixed,
}

#[derive(Debug, Clone, PartialEq)]
pub(crate) struct JointT {
    pub name: String,
    pub kind: JointKindT,
    pub body1: BodyRef,
    pub body2: BodyRef,
    pub anchor1: NumVec3,
    pub anchor2: NumVec3,
}

impl JointT {
    fn nums(&self) -> impl Iterator<Item = &Num> {
        let axis: &[Num] = match &self.kind {
            JointKindT::Revolute { axis } => axis,
            _ => &[],
        };
        self.anchor1.iter().chain(&self.anchor2).chain(axis)
    }
}

/// A parsed and validated scene whose numbers may still be distributions.
///
/// Build it with [`SceneTemplate::parse`]; draw one world's concrete [`Scene`] with
/// [`SceneTemplate::instantiate`].
#[derive(Debug, Clone, PartialEq)]
pub struct SceneTemplate {
    pub(crate) name: String,
    pub(crate) description: String,
    pub(crate) settings: Settings,
    pub(crate) materials: Vec<MaterialT>,
    pub(crate) statics: Vec<BodyT>,
    pub(crate) bodies: Vec<BodyT>,
    pub(crate) joints: Vec<JointT>,
}

impl SceneTemplate {
    /// Parse and validate a TOML scene (format: `docs/scene-format.md`). `file` is only used in
    /// error messages.
    pub fn parse(src: &str, file: &str) -> Result<SceneTemplate, SceneError> {
        super::parse::parse(Source { text: src, file })
    }

    /// Instance `seed` of this template as an edit of `parent`, the same instance of the
    /// template `before` the edit was made from: a body whose definition did not change (its
    /// entry's shape, pose and velocity distributions, its material's, and its placement, matched
    /// by instance name) keeps the state `parent` sampled for it, and so does a material whose
    /// definition did not change; the rest is sampled from `seed`. Draws are sequential, so a
    /// plain [`instantiate`](Self::instantiate) of the edited template would give every body
    /// after a removed or added one other random draws — another world, not this one edited.
    pub fn instantiate_edit(&self, seed: u64, before: &SceneTemplate, parent: &Scene) -> Scene {
        let mut out = self.instantiate(seed);
        for (m, t) in out.materials.iter_mut().zip(&self.materials) {
            let old = before.materials.iter().position(|o| o == t);
            if let Some(p) = old.and_then(|i| parent.materials.get(i)) {
                *m = p.clone();
            }
        }
        let old_defs = before.instance_definitions();
        for ((b, at), body) in self.instance_definitions().into_iter().zip(&mut out.bodies) {
            let same = old_defs.iter().any(|(ob, oat)| {
                *oat == at
                    && ob.shape == b.shape
                    && ob.position == b.position
                    && ob.rotation == b.rotation
                    && ob.linvel == b.linvel
                    && ob.angvel == b.angvel
                    && before.materials.get(ob.material) == self.materials.get(b.material)
            });
            let old = parent.bodies.iter().find(|p| p.name == at.name);
            let Some(old) = old.filter(|_| same) else {
                continue;
            };
            // The parent's draws; the material index is this scene's.
            *body = Body {
                material: body.material,
                ..old.clone()
            };
        }
        out
    }

    /// Every body instance in order: its entry and its placement.
    fn instance_definitions(&self) -> Vec<(&BodyT, &Placement)> {
        self.bodies
            .iter()
            .flat_map(|t| t.placements.iter().map(move |at| (t, at)))
            .collect()
    }

    /// The concrete scene of the world with this seed.
    ///
    /// Distributions are drawn from `WorldRng::new(seed, Stream::Scene)` in this order:
    /// materials, then statics, then bodies, then joints, each in file order (generator
    /// instances in index order); within an item in the order of `docs/scene-format.md`
    /// ("Sampling order"). Fixed numbers draw nothing. Infallible: parsing guaranteed that
    /// every possible sample is valid.
    pub fn instantiate(&self, seed: u64) -> Scene {
        let mut rng = WorldRng::new(seed, Stream::Scene);
        let materials = self
            .materials
            .iter()
            .map(|m| {
                let friction = m.friction.sample(&mut rng);
                let restitution = m.restitution.sample(&mut rng);
                let density = m.density.sample(&mut rng);
                Material {
                    name: m.name.clone(),
                    friction,
                    restitution,
                    density,
                }
            })
            .collect();
        let mut statics = Vec::new();
        for t in &self.statics {
            for at in &t.placements {
                let b = t.sample(at, &mut rng);
                statics.push(StaticBody {
                    name: b.name,
                    shape: b.shape,
                    material: b.material,
                    position: b.position,
                    rotation: b.rotation,
                });
            }
        }
        let mut bodies = Vec::with_capacity(self.body_count());
        for t in &self.bodies {
            for at in &t.placements {
                bodies.push(t.sample(at, &mut rng));
            }
        }
        let joints = self
            .joints
            .iter()
            .map(|j| {
                let anchor1 = sample3(&j.anchor1, &mut rng);
                let anchor2 = sample3(&j.anchor2, &mut rng);
                let kind = match &j.kind {
                    JointKindT::Revolute { axis } => JointKind::Revolute {
                        axis: normalize3(sample3(axis, &mut rng)),
                    },
                    JointKindT::Spherical => JointKind::Spherical,
                    JointKindT::Fixed => JointKind::Fixed,
                };
                Joint {
                    name: j.name.clone(),
                    kind,
                    body1: j.body1,
                    body2: j.body2,
                    anchor1,
                    anchor2,
                }
            })
            .collect();
        Scene {
            name: self.name.clone(),
            settings: self.settings.clone(),
            materials,
            statics,
            bodies,
            joints,
        }
    }

    /// The scene's `name`.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The scene's optional `description` (empty if absent).
    pub fn description(&self) -> &str {
        &self.description
    }

    /// Simulation settings (plain numbers: never sampled).
    pub fn settings(&self) -> &Settings {
        &self.settings
    }

    /// Number of dynamic bodies after generator expansion (the same in every world).
    pub fn body_count(&self) -> usize {
        self.bodies.iter().map(|b| b.placements.len()).sum()
    }

    /// Number of static bodies after generator expansion.
    pub fn static_count(&self) -> usize {
        self.statics.iter().map(|b| b.placements.len()).sum()
    }

    /// Names of the dynamic bodies, in object-index order (the same in every world).
    pub fn body_names(&self) -> impl Iterator<Item = &str> {
        self.bodies
            .iter()
            .flat_map(|b| b.placements.iter().map(|p| p.name.as_str()))
    }

    /// Whether any number is a distribution, i.e. whether worlds differ in their initial
    /// conditions (and not only through §4.1.2 impact perturbations).
    pub fn has_distributions(&self) -> bool {
        let materials = self
            .materials
            .iter()
            .flat_map(|m| [&m.friction, &m.restitution, &m.density]);
        let items = self
            .statics
            .iter()
            .chain(&self.bodies)
            .flat_map(BodyT::nums);
        let joints = self.joints.iter().flat_map(JointT::nums);
        materials.chain(items).chain(joints).any(Num::is_random)
    }
}

// ---- rotation helpers ([x, y, z, w] quaternions) ----

/// Hamilton product `a * b` (apply `b` first, then `a`).
pub(crate) fn quat_mul(a: Quat, b: Quat) -> Quat {
    let [ax, ay, az, aw] = a;
    let [bx, by, bz, bw] = b;
    [
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ]
}

/// Rotation by `angle` radians about the unit vector `axis`.
pub(crate) fn axis_angle(axis: Vec3, angle: f64) -> Quat {
    let (s, c) = (0.5 * angle).sin_cos();
    [axis[0] * s, axis[1] * s, axis[2] * s, c]
}

/// Extrinsic X-then-Y-then-Z rotation in degrees (`q = qz · qy · qx`), the same rotation as
/// intrinsic Z, Y′, X″.
pub(crate) fn euler_xyz_deg(rx: f64, ry: f64, rz: f64) -> Quat {
    let qx = axis_angle([1.0, 0.0, 0.0], rx.to_radians());
    let qy = axis_angle([0.0, 1.0, 0.0], ry.to_radians());
    let qz = axis_angle([0.0, 0.0, 1.0], rz.to_radians());
    normalize4(quat_mul(qz, quat_mul(qy, qx)))
}

/// Rotate a vector by a unit quaternion.
pub(crate) fn rotate(q: Quat, v: Vec3) -> Vec3 {
    let p = quat_mul(
        quat_mul(q, [v[0], v[1], v[2], 0.0]),
        [-q[0], -q[1], -q[2], q[3]],
    );
    [p[0], p[1], p[2]]
}

/// Parsing guarantees a direction has a component bounded away from zero, so the norm is
/// positive; the fallback only keeps this total.
pub(crate) fn normalize3(v: Vec3) -> Vec3 {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if n > 0.0 && n.is_finite() {
        v.map(|c| c / n)
    } else {
        [0.0, 1.0, 0.0]
    }
}

pub(crate) fn normalize4(q: Quat) -> Quat {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    if n > 0.0 && n.is_finite() {
        q.map(|c| c / n)
    } else {
        IDENTITY
    }
}
