//! The concrete scene: every distribution already sampled, every generator expanded, every
//! reference resolved and validated. This is what a simulator consumes.
//!
//! Conventions: SI units (metres, seconds, kilograms, radians); right-handed, **y up** (gravity
//! defaults to `[0, -9.81, 0]`); quaternions are stored `[x, y, z, w]` (the order glam and rapier
//! use) and are unit length.

/// A 3-vector in scene space.
pub type Vec3 = [f64; 3];
/// A unit quaternion `[x, y, z, w]`.
pub type Quat = [f64; 4];

/// Identity rotation.
pub const IDENTITY: Quat = [0.0, 0.0, 0.0, 1.0];

/// A fully instantiated scene (one world's initial conditions).
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    pub name: String,
    pub settings: Settings,
    /// Indexed by [`Body::material`] / [`StaticBody::material`].
    pub materials: Vec<Material>,
    /// Immovable geometry: planes, boxes, triangle meshes, …
    pub statics: Vec<StaticBody>,
    /// Dynamic bodies, in a fixed order: the object index of every recorded frame.
    pub bodies: Vec<Body>,
    pub joints: Vec<Joint>,
}

/// Simulation and sampling settings (DESIGN.md "Forward sampling", §4.1).
#[derive(Debug, Clone, PartialEq)]
pub struct Settings {
    /// Fixed time step, seconds (default 1/120: §4.3 stores 120 frames per second).
    pub dt: f64,
    /// Simulated time after which a world stops even if not at rest, seconds.
    pub end_time: f64,
    /// Gravity, m/s².
    pub gravity: Vec3,
    /// A body rests when its speed stays below this (m/s) …
    pub rest_linear: f64,
    /// … and its angular speed below this (rad/s) …
    pub rest_angular: f64,
    /// … for this long (s). A world ends when every dynamic body rests.
    pub rest_hold: f64,
    /// Solver substeps per step (rapier's `num_solver_iterations`: each integrates `dt / n`).
    pub solver_iterations: u32,
    /// §4.1.1 plausibility bound: a perturbation is at most α times the impact's velocity change.
    pub alpha: f64,
    /// Exponent n of the cosⁿ lobe the perturbation direction is drawn from (§4.1.2).
    pub cos_exponent: f64,
    /// Impact threshold on ‖Δv‖ (m/s², contact part only, gravity removed) (§4.1.2 C_v).
    pub c_v: f64,
    /// Impact threshold on ‖Δω‖ (rad/s²) (§4.1.2 C_ω).
    pub c_omega: f64,
    /// Motion is streamed in segments of about this many seconds.
    pub segment_seconds: f64,
    /// Linear damping applied to every dynamic body (1/s). Non-zero damping changes what the
    /// motion codec may assume about free flight.
    pub linear_damping: f64,
    /// Angular damping applied to every dynamic body (1/s).
    pub angular_damping: f64,
    /// The simulation preset the numbers below started from (`sim = "…"`); keys written in the
    /// scene override it. [`SimPreset::Auto`] is resolved to a concrete preset by calibration
    /// before a job is sampled (`mwb_sampler::fidelity`).
    pub sim: SimPreset,
    /// Solver iterations inside each substep (rapier's internal PGS iterations).
    pub pgs_iterations: u32,
    /// Position-stabilisation iterations inside each substep.
    pub stabilization_iterations: u32,
    /// Which bodies get continuous collision detection.
    pub ccd: CcdPolicy,
    /// Distance (m) at which two shapes start to produce (speculative) contacts. `None`: from
    /// the scene and preset (`mwb_sampler::plan`): rapier's 2 cm, and for final and reference
    /// what the scene's fastest body can cover in a step, between 2 and 10 cm.
    pub prediction_distance: Option<f64>,
    /// Whether bodies may fall asleep (stop being simulated) once still.
    pub sleep: bool,
    /// The solver's length scale (m): its tolerances (allowed penetration 5 mm, speed cap) are
    /// multiplied by it. `None`: chosen from the scene's body sizes (1 for everyday sizes).
    pub length_unit: Option<f64>,
    /// Largest speed (m/s) the solver lets a body reach. `None`: chosen from the scene (at least
    /// 400 m/s, more if a body can go faster).
    pub max_speed: Option<f64>,
    /// The error (m) the scene tolerates in where bodies come to rest and how deep they
    /// penetrate: what `sim = "auto"` and the fidelity study hold presets to. `None`: half the
    /// smallest body's half-thickness, at least 1 cm (`mwb_sampler::fidelity::tolerance`).
    pub tolerance: Option<f64>,
}

/// A simulation preset (issue 19): how much accuracy to buy with time. The frame rate
/// (`dt`) is a storage decision and stays; a preset sets what happens inside a frame.
///
/// | preset | steps per frame | substeps per step | iterations per substep | CCD | sleeping |
/// |---|---|---|---|---|---|
/// | draft | 1 | 1 | 1 | bodies that can tunnel | yes |
/// | standard | 1 | 4 | 1 | bodies that can tunnel | yes |
/// | final | 1 | 8 | 2 | every body | yes |
/// | reference | 8 | 8 | 8 | every body | no |
///
/// `reference` is final with the step ÷ 8 (contacts found 8× as often: its `dt` is the
/// frame's ÷ 8, so its worlds have 8× the frames) and 4× its iterations: what the fidelity study
/// (`mwb bench fidelity`) measures the others against, not something to sample with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum SimPreset {
    Draft,
    Standard,
    Final,
    Reference,
    /// The cheapest of draft, standard and final whose measured error stays inside the scene's
    /// tolerance; chosen by a short calibration when the scene is loaded.
    Auto,
}

/// Steps of the reference preset per frame of the scene's `dt`.
pub const REFERENCE_STEPS_PER_FRAME: u32 = 8;

impl SimPreset {
    /// The concrete presets, cheapest first.
    pub const CONCRETE: [SimPreset; 4] = [
        SimPreset::Draft,
        SimPreset::Standard,
        SimPreset::Final,
        SimPreset::Reference,
    ];

    /// Its name in scene files and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            SimPreset::Draft => "draft",
            SimPreset::Standard => "standard",
            SimPreset::Final => "final",
            SimPreset::Reference => "reference",
            SimPreset::Auto => "auto",
        }
    }

    /// The preset of a name.
    pub fn from_name(name: &str) -> Option<Self> {
        [Self::Auto]
            .into_iter()
            .chain(Self::CONCRETE)
            .find(|p| p.name() == name)
    }

    /// The settings this preset stands for, on top of `base` (whose other fields it keeps).
    /// `Auto` gives standard's numbers until it is resolved.
    pub fn apply(self, base: &Settings) -> Settings {
        let (substeps, pgs, stab, ccd, sleep) = match self {
            SimPreset::Draft => (1, 1, 1, CcdPolicy::Auto, true),
            SimPreset::Standard | SimPreset::Auto => (4, 1, 1, CcdPolicy::Auto, true),
            SimPreset::Final => (8, 2, 1, CcdPolicy::All, true),
            SimPreset::Reference => (8, 8, 4, CcdPolicy::All, false),
        };
        // Contacts are found once per step, whatever the substeps: only a shorter step finds
        // them sooner (a body at 8 m/s moves 6.7 cm in 1/120 s, three times the contact margin).
        let steps = f64::from(REFERENCE_STEPS_PER_FRAME);
        let frame_dt = if base.sim == SimPreset::Reference {
            base.dt * steps
        } else {
            base.dt
        };
        let dt = if self == SimPreset::Reference {
            frame_dt / steps
        } else {
            frame_dt
        };
        Settings {
            sim: self,
            dt,
            solver_iterations: substeps,
            pgs_iterations: pgs,
            stabilization_iterations: stab,
            ccd,
            sleep,
            ..base.clone()
        }
    }
}

impl std::fmt::Display for SimPreset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Which bodies get continuous collision detection.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum CcdPolicy {
    /// Only bodies that could move further than their own (or the thinnest static's)
    /// half-thickness in one step (`mwb_sampler::world::ccd_bodies`).
    Auto,
    /// Every body.
    All,
    /// No body (a body fast enough may tunnel; `mwb scene` warns).
    Off,
}

impl CcdPolicy {
    /// Its name in scene files.
    pub fn name(self) -> &'static str {
        match self {
            CcdPolicy::Auto => "auto",
            CcdPolicy::All => "all",
            CcdPolicy::Off => "off",
        }
    }

    /// The policy of a name.
    pub fn from_name(name: &str) -> Option<Self> {
        [CcdPolicy::Auto, CcdPolicy::All, CcdPolicy::Off]
            .into_iter()
            .find(|p| p.name() == name)
    }
}

impl Default for Settings {
    fn default() -> Self {
        Self {
            dt: 1.0 / 120.0,
            end_time: 10.0,
            gravity: [0.0, -9.81, 0.0],
            rest_linear: 0.02,
            rest_angular: 0.05,
            rest_hold: 0.5,
            solver_iterations: 4,
            alpha: 0.1,
            cos_exponent: 20.0,
            // Resting contact removes g from Δv every step (‖Δv‖ = 9.81 m/s²), sliding friction
            // μg; 30 m/s² (≈ 3 g, a 0.25 m/s change in one 1/120 s step) is clearly an impact.
            c_v: 30.0,
            c_omega: 60.0,
            segment_seconds: 1.0,
            linear_damping: 0.0,
            angular_damping: 0.0,
            sim: SimPreset::Standard,
            pgs_iterations: 1,
            stabilization_iterations: 1,
            ccd: CcdPolicy::Auto,
            prediction_distance: None,
            sleep: true,
            length_unit: None,
            max_speed: None,
            tolerance: None,
        }
    }
}

/// A named surface/bulk material.
#[derive(Debug, Clone, PartialEq)]
pub struct Material {
    pub name: String,
    /// Coulomb friction coefficient, ≥ 0.
    pub friction: f64,
    /// Coefficient of restitution in [0, 1].
    pub restitution: f64,
    /// Density, kg/m³, > 0 (mass and inertia follow from the shape).
    pub density: f64,
}

/// Collision geometry. Dimensions are half-extents / radii in metres. Capsules and cylinders
/// are aligned with their local y axis.
#[derive(Debug, Clone, PartialEq)]
pub enum Shape {
    Box {
        half_extents: Vec3,
    },
    Sphere {
        radius: f64,
    },
    Capsule {
        half_height: f64,
        radius: f64,
    },
    Cylinder {
        half_height: f64,
        radius: f64,
    },
    /// The convex hull of these local-space points (at least 4, not coplanar).
    ConvexHull {
        points: Vec<Vec3>,
    },
    /// Static only: the half-space below the plane through the body's position with this
    /// outward unit normal (local space).
    Plane {
        normal: Vec3,
    },
    /// Static only: a triangle mesh in local space.
    TriMesh {
        vertices: Vec<Vec3>,
        indices: Vec<[u32; 3]>,
    },
    /// Several shapes rigidly joined into one body (one rigid body, one object for browsing),
    /// each at its own pose in the body's local frame. Parts are never compounds themselves and
    /// never planes; a dynamic body's parts are never triangle meshes (the parser refuses them).
    Compound {
        parts: Vec<Part>,
    },
}

/// One shape of a [`Shape::Compound`], placed in its body's local frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Part {
    pub shape: Shape,
    /// Centre of the part's local frame in the body's frame.
    pub position: Vec3,
    /// The part's orientation in the body's frame (unit).
    pub rotation: Quat,
    /// Index into [`Scene::materials`]: the part's own material, or its body's.
    pub material: usize,
}

/// A shape placed in its body's frame with its material: one part of a compound, or a whole
/// single shape (at the identity, with the body's material). See [`Shape::placed_parts`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlacedPart<'a> {
    pub shape: &'a Shape,
    pub position: Vec3,
    pub rotation: Quat,
    pub material: usize,
}

impl Shape {
    /// Whether a dynamic body may have this shape.
    pub fn can_be_dynamic(&self) -> bool {
        match self {
            Shape::Plane { .. } | Shape::TriMesh { .. } => false,
            Shape::Compound { parts } => parts.iter().all(|p| p.shape.can_be_dynamic()),
            _ => true,
        }
    }

    /// The shape's name as the scene format writes it (`"box"`, `"compound"`, …).
    pub fn kind(&self) -> &'static str {
        match self {
            Shape::Box { .. } => "box",
            Shape::Sphere { .. } => "sphere",
            Shape::Capsule { .. } => "capsule",
            Shape::Cylinder { .. } => "cylinder",
            Shape::ConvexHull { .. } => "convex",
            Shape::Plane { .. } => "plane",
            Shape::TriMesh { .. } => "trimesh",
            Shape::Compound { .. } => "compound",
        }
    }

    /// The simple shapes this shape is made of, each placed in the body's frame with its
    /// material: a compound's parts, or the shape itself at the identity with `body_material`.
    /// Whatever draws, exports or builds a body's geometry walks these.
    pub fn placed_parts(&self, body_material: usize) -> Vec<PlacedPart<'_>> {
        match self {
            Shape::Compound { parts } => parts
                .iter()
                .map(|p| PlacedPart {
                    shape: &p.shape,
                    position: p.position,
                    rotation: p.rotation,
                    material: p.material,
                })
                .collect(),
            single => vec![PlacedPart {
                shape: single,
                position: [0.0; 3],
                rotation: IDENTITY,
                material: body_material,
            }],
        }
    }

    /// Radius of the smallest ball about the local origin that contains the shape (used to
    /// decide which bodies can tunnel and need CCD). Infinite for planes.
    pub fn bounding_radius(&self) -> f64 {
        match self {
            Shape::Box { half_extents: h } => (h[0] * h[0] + h[1] * h[1] + h[2] * h[2]).sqrt(),
            Shape::Sphere { radius } => *radius,
            Shape::Capsule {
                half_height,
                radius,
            } => half_height + radius,
            Shape::Cylinder {
                half_height,
                radius,
            } => (half_height * half_height + radius * radius).sqrt(),
            Shape::ConvexHull { points }
            | Shape::TriMesh {
                vertices: points, ..
            } => points
                .iter()
                .map(|p| (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt())
                .fold(0.0, f64::max),
            Shape::Plane { .. } => f64::INFINITY,
            // Each part's ball about its own origin, moved out to where the part sits.
            Shape::Compound { parts } => parts
                .iter()
                .map(|p| {
                    let [x, y, z] = p.position;
                    (x * x + y * y + z * z).sqrt() + p.shape.bounding_radius()
                })
                .fold(0.0, f64::max),
        }
    }

    /// Half of the smallest extent across the shape (how thin it is: a body moving more than
    /// this per step can tunnel through thin geometry).
    pub fn min_half_thickness(&self) -> f64 {
        match self {
            Shape::Box { half_extents: h } => h[0].min(h[1]).min(h[2]),
            Shape::Sphere { radius } => *radius,
            Shape::Capsule { radius, .. } => *radius,
            Shape::Cylinder {
                half_height,
                radius,
            } => half_height.min(*radius),
            Shape::ConvexHull { .. } => self.bounding_radius() * 0.25,
            Shape::Plane { .. } => f64::INFINITY,
            Shape::TriMesh { .. } => 0.0,
            // The thinnest part decides what can tunnel through (or be tunnelled by) the body.
            Shape::Compound { parts } => parts
                .iter()
                .map(|p| p.shape.min_half_thickness())
                .fold(f64::INFINITY, f64::min),
        }
    }
}

/// A dynamic rigid body.
#[derive(Debug, Clone, PartialEq)]
pub struct Body {
    pub name: String,
    pub shape: Shape,
    pub material: usize,
    /// Centre of the shape's local frame in world space (a compound's parts are placed in this
    /// frame; it need not be the centre of mass). Recorded poses are this frame's.
    pub position: Vec3,
    pub rotation: Quat,
    pub linvel: Vec3,
    pub angvel: Vec3,
}

/// Immovable geometry.
#[derive(Debug, Clone, PartialEq)]
pub struct StaticBody {
    pub name: String,
    pub shape: Shape,
    pub material: usize,
    pub position: Vec3,
    pub rotation: Quat,
}

/// One end of a joint.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BodyRef {
    /// Fixed to the world frame.
    World,
    /// Index into [`Scene::bodies`].
    Body(usize),
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum JointKind {
    /// Hinge about `axis` (local to body 1 and body 2 alike).
    Revolute { axis: Vec3 },
    /// Ball and socket.
    Spherical,
    /// Rigid weld.
    Fixed,
}

/// A joint between two bodies (or a body and the world). Anchors are in each body's local
/// frame (for [`BodyRef::World`], in world space).
#[derive(Debug, Clone, PartialEq)]
pub struct Joint {
    pub name: String,
    pub kind: JointKind,
    pub body1: BodyRef,
    pub body2: BodyRef,
    pub anchor1: Vec3,
    pub anchor2: Vec3,
}

impl Scene {
    /// Index of the dynamic body with this name.
    pub fn body_index(&self, name: &str) -> Option<usize> {
        self.bodies.iter().position(|b| b.name == name)
    }
}
