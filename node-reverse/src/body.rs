//! Rigid bodies and static geometry (the state of §5.2: position, orientation, linear and
//! angular velocity per body).
//!
//! Our own state and dynamics are `f64` nalgebra; shapes are parry3d's (`f32`, glam math), used
//! only by contact generation ([`crate::contact`]). A body's reference point is its centre of
//! mass, so the shape is centred on it (primitives are; [`Body::convex_hull`] recentres the
//! points).

use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use parry3d::math::{Pose, Rot3, Vec3};
use parry3d::shape::{SharedShape, TriMesh};

use crate::BodyError;

/// Surface properties of a body or static object. Pairs combine them in
/// [`Material::combine`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Material {
    /// Coulomb friction coefficient `μ ≥ 0` (§3.6).
    pub friction: f64,
    /// Newton coefficient of restitution `α ∈ [0, 1]` (§3.5).
    pub restitution: f64,
}

impl Default for Material {
    fn default() -> Self {
        Self {
            friction: 0.5,
            restitution: 0.0,
        }
    }
}

impl Material {
    /// The pair's coefficients: the geometric mean of the frictions (so a frictionless surface
    /// wins) and the mean of the restitutions (two equal materials keep their own value).
    pub fn combine(self, other: Material) -> Material {
        Material {
            friction: (self.friction * other.friction).max(0.0).sqrt(),
            restitution: (0.5 * (self.restitution + other.restitution)).clamp(0.0, 1.0),
        }
    }
}

/// A dynamic rigid body.
#[derive(Debug, Clone)]
pub struct Body {
    /// Centre of mass, world frame.
    pub position: Vector3<f64>,
    /// Orientation (body → world).
    pub orientation: UnitQuaternion<f64>,
    /// Linear velocity of the centre of mass.
    pub linvel: Vector3<f64>,
    /// Angular velocity, world frame.
    pub angvel: Vector3<f64>,
    /// `1 / m`.
    pub inv_mass: f64,
    /// Inverse inertia tensor in the body frame.
    pub local_inv_inertia: Matrix3<f64>,
    /// Collision shape, centred on the centre of mass.
    pub shape: SharedShape,
    /// Friction and restitution.
    pub material: Material,
    /// False once a step produced a non-finite state for this body: it is then frozen and left
    /// out of contact handling instead of poisoning its island.
    pub enabled: bool,
    /// Rolling resistance arm `b` (m) of a round body (§5.3.5): a contact may resist the
    /// relative rotation with a torque impulse of at most `b` times its normal impulse about
    /// each of three axes, (5.15)–(5.18). Zero (no rolling rows) for bodies that do not roll;
    /// [`Body::ball`], [`Body::capsule`] and [`Body::cylinder`] start at
    /// [`DEFAULT_ROLLING_RESISTANCE`] times their radius.
    pub rolling_resistance: f64,
}

/// Default rolling-resistance coefficient of round bodies: the resistance arm is this fraction
/// of the radius (a hard ball on a hard floor is 0.001–0.01, on cloth or grass a few 0.01).
pub const DEFAULT_ROLLING_RESISTANCE: f64 = 0.01;

fn check_positive(what: &'static str, value: f64) -> Result<(), BodyError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(BodyError::InvalidParameter { what, value })
    }
}

impl Body {
    /// A body with explicit mass properties (`mass > 0`, `local_inertia` symmetric positive
    /// definite, body frame).
    pub fn with_mass_properties(
        shape: SharedShape,
        mass: f64,
        local_inertia: Matrix3<f64>,
    ) -> Result<Self, BodyError> {
        check_positive("mass", mass)?;
        let local_inv_inertia = local_inertia
            .try_inverse()
            .filter(|m| m.iter().all(|v| v.is_finite()))
            .ok_or(BodyError::SingularInertia)?;
        Ok(Self {
            position: Vector3::zeros(),
            orientation: UnitQuaternion::identity(),
            linvel: Vector3::zeros(),
            angvel: Vector3::zeros(),
            inv_mass: 1.0 / mass,
            local_inv_inertia,
            shape,
            material: Material::default(),
            enabled: true,
            rolling_resistance: 0.0,
        })
    }

    /// A box with the given half extents and density.
    pub fn cuboid(half_extents: Vector3<f64>, density: f64) -> Result<Self, BodyError> {
        check_positive("density", density)?;
        for &h in half_extents.iter() {
            check_positive("half extent", h)?;
        }
        let [hx, hy, hz] = [half_extents.x, half_extents.y, half_extents.z];
        let m = 8.0 * hx * hy * hz * density;
        let inertia = Matrix3::from_diagonal(&Vector3::new(
            m * (hy * hy + hz * hz) / 3.0,
            m * (hx * hx + hz * hz) / 3.0,
            m * (hx * hx + hy * hy) / 3.0,
        ));
        Self::with_mass_properties(
            SharedShape::cuboid(hx as f32, hy as f32, hz as f32),
            m,
            inertia,
        )
    }

    /// A solid sphere.
    pub fn ball(radius: f64, density: f64) -> Result<Self, BodyError> {
        check_positive("density", density)?;
        check_positive("radius", radius)?;
        let m = 4.0 / 3.0 * std::f64::consts::PI * radius.powi(3) * density;
        let i = 0.4 * m * radius * radius;
        Self::with_mass_properties(
            SharedShape::ball(radius as f32),
            m,
            Matrix3::from_diagonal_element(i),
        )
        .map(|b| b.with_rolling_resistance(DEFAULT_ROLLING_RESISTANCE * radius))
    }

    /// A solid cylinder whose axis is the body's y axis.
    pub fn cylinder(half_height: f64, radius: f64, density: f64) -> Result<Self, BodyError> {
        check_positive("density", density)?;
        check_positive("half height", half_height)?;
        check_positive("radius", radius)?;
        let h = 2.0 * half_height;
        let m = std::f64::consts::PI * radius * radius * h * density;
        let side = m * (3.0 * radius * radius + h * h) / 12.0;
        let inertia = Matrix3::from_diagonal(&Vector3::new(side, 0.5 * m * radius * radius, side));
        Self::with_mass_properties(
            SharedShape::cylinder(half_height as f32, radius as f32),
            m,
            inertia,
        )
        .map(|b| b.with_rolling_resistance(DEFAULT_ROLLING_RESISTANCE * radius))
    }

    /// A capsule whose axis is the body's y axis (segment of half length `half_height`).
    pub fn capsule(half_height: f64, radius: f64, density: f64) -> Result<Self, BodyError> {
        check_positive("density", density)?;
        check_positive("half height", half_height)?;
        check_positive("radius", radius)?;
        let (r, h) = (radius, 2.0 * half_height);
        let pi = std::f64::consts::PI;
        let m_cyl = pi * r * r * h * density;
        let m_hemis = 4.0 / 3.0 * pi * r.powi(3) * density; // both caps together
        let m = m_cyl + m_hemis;
        let iy = m_cyl * r * r / 2.0 + m_hemis * 0.4 * r * r;
        // Caps: sphere inertia about its own centre, shifted by the parallel-axis theorem (each
        // cap's centre of mass sits 3r/8 beyond the segment end).
        let cap_offset = half_height + 3.0 * r / 8.0;
        let ix = m_cyl * (3.0 * r * r + h * h) / 12.0
            + m_hemis * (0.4 * r * r - (3.0 * r / 8.0).powi(2) + cap_offset * cap_offset);
        Self::with_mass_properties(
            SharedShape::capsule_y(half_height as f32, radius as f32),
            m,
            Matrix3::from_diagonal(&Vector3::new(ix, iy, ix)),
        )
        .map(|b| b.with_rolling_resistance(DEFAULT_ROLLING_RESISTANCE * radius))
    }

    /// The convex hull of `points` (body frame), recentred on its centre of mass: the returned
    /// body's `position` is the centre of mass in the frame of the given points.
    pub fn convex_hull(points: &[Vector3<f64>], density: f64) -> Result<Self, BodyError> {
        check_positive("density", density)?;
        let pts: Vec<Vec3> = points.iter().map(to_vec3).collect();
        let hull = SharedShape::convex_hull(&pts).ok_or(BodyError::DegenerateHull)?;
        let props = hull.mass_properties(density as f32);
        let com = Vector3::new(
            props.local_com.x as f64,
            props.local_com.y as f64,
            props.local_com.z as f64,
        );
        let centred: Vec<Vec3> = points.iter().map(|p| to_vec3(&(p - com))).collect();
        let shape = SharedShape::convex_hull(&centred).ok_or(BodyError::DegenerateHull)?;
        let props = shape.mass_properties(density as f32);
        let inertia = props.reconstruct_inertia_matrix();
        let inertia = Matrix3::from_fn(|r, c| inertia.col(c)[r] as f64);
        let mut body = Self::with_mass_properties(shape, props.mass() as f64, inertia)?;
        body.position = com;
        Ok(body)
    }

    /// Builder: place the body.
    pub fn at(mut self, position: Vector3<f64>, orientation: UnitQuaternion<f64>) -> Self {
        self.position = position;
        self.orientation = orientation;
        self
    }

    /// Builder: set the rolling resistance arm (m, see [`Body::rolling_resistance`]); values
    /// that are not finite and positive turn rolling resistance off.
    pub fn with_rolling_resistance(mut self, arm: f64) -> Self {
        self.rolling_resistance = if arm.is_finite() && arm > 0.0 {
            arm
        } else {
            0.0
        };
        self
    }

    /// Builder: set the velocities.
    pub fn moving(mut self, linvel: Vector3<f64>, angvel: Vector3<f64>) -> Self {
        self.linvel = linvel;
        self.angvel = angvel;
        self
    }

    /// Builder: set the material.
    pub fn with_material(mut self, material: Material) -> Self {
        self.material = material;
        self
    }

    /// Inverse inertia in the world frame, `R I⁻¹ Rᵀ` (§3.2: stored in the body frame and
    /// transformed every step).
    pub fn world_inv_inertia(&self) -> Matrix3<f64> {
        let r = self.orientation.to_rotation_matrix();
        r.matrix() * self.local_inv_inertia * r.matrix().transpose()
    }

    /// Velocity of the material point at world position `p`.
    pub fn point_velocity(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.linvel + self.angvel.cross(&(p - self.position))
    }

    /// Kinetic energy `½ m v² + ½ ωᵀ I ω`.
    pub fn kinetic_energy(&self) -> f64 {
        let inertia = self
            .world_inv_inertia()
            .try_inverse()
            .unwrap_or_else(Matrix3::zeros);
        0.5 * self.linvel.norm_squared() / self.inv_mass
            + 0.5 * self.angvel.dot(&(inertia * self.angvel))
    }

    /// True when every state component is finite.
    pub fn is_finite(&self) -> bool {
        self.position.iter().all(|v| v.is_finite())
            && self.orientation.coords.iter().all(|v| v.is_finite())
            && self.linvel.iter().all(|v| v.is_finite())
            && self.angvel.iter().all(|v| v.is_finite())
    }

    /// The parry pose of the shape.
    pub fn pose(&self) -> Pose {
        to_pose(&self.position, &self.orientation)
    }
}

/// Immovable geometry: a plane (half-space), a box, a triangle mesh, or any parry shape.
#[derive(Debug, Clone)]
pub struct StaticBody {
    /// Position of the shape's frame.
    pub position: Vector3<f64>,
    /// Orientation of the shape's frame.
    pub orientation: UnitQuaternion<f64>,
    /// The shape.
    pub shape: SharedShape,
    /// Friction and restitution.
    pub material: Material,
}

impl StaticBody {
    /// Any parry shape at a pose.
    pub fn new(
        shape: SharedShape,
        position: Vector3<f64>,
        orientation: UnitQuaternion<f64>,
    ) -> Self {
        Self {
            position,
            orientation,
            shape,
            material: Material::default(),
        }
    }

    /// The half-space `{x : n·x ≤ offset}` whose surface is the plane `n·x = offset`; `normal`
    /// points out of the solid (is normalised; a zero normal is an error).
    pub fn plane(normal: Vector3<f64>, offset: f64) -> Result<Self, BodyError> {
        let n = normal
            .try_normalize(1e-12)
            .ok_or(BodyError::InvalidParameter {
                what: "plane normal length",
                value: normal.norm(),
            })?;
        if !offset.is_finite() {
            return Err(BodyError::InvalidParameter {
                what: "plane offset",
                value: offset,
            });
        }
        Ok(Self::new(
            SharedShape::halfspace(to_vec3(&n)),
            n * offset,
            UnitQuaternion::identity(),
        ))
    }

    /// A box.
    pub fn cuboid(
        half_extents: Vector3<f64>,
        position: Vector3<f64>,
        orientation: UnitQuaternion<f64>,
    ) -> Result<Self, BodyError> {
        for &h in half_extents.iter() {
            check_positive("half extent", h)?;
        }
        Ok(Self::new(
            SharedShape::cuboid(
                half_extents.x as f32,
                half_extents.y as f32,
                half_extents.z as f32,
            ),
            position,
            orientation,
        ))
    }

    /// A triangle mesh (static only: a trimesh has no volume to give it mass).
    pub fn trimesh(vertices: &[Vector3<f64>], indices: Vec<[u32; 3]>) -> Result<Self, BodyError> {
        let verts = vertices.iter().map(to_vec3).collect();
        let mesh = TriMesh::new(verts, indices).map_err(|_| BodyError::InvalidMesh)?;
        Ok(Self::new(
            SharedShape::new(mesh),
            Vector3::zeros(),
            UnitQuaternion::identity(),
        ))
    }

    /// Builder: set the material.
    pub fn with_material(mut self, material: Material) -> Self {
        self.material = material;
        self
    }

    /// The parry pose of the shape.
    pub fn pose(&self) -> Pose {
        to_pose(&self.position, &self.orientation)
    }
}

/// `f64` nalgebra vector → parry (`f32` glam) vector.
pub fn to_vec3(v: &Vector3<f64>) -> Vec3 {
    Vec3::new(v.x as f32, v.y as f32, v.z as f32)
}

/// parry (`f32` glam) vector → `f64` nalgebra vector.
pub fn from_vec3(v: Vec3) -> Vector3<f64> {
    Vector3::new(v.x as f64, v.y as f64, v.z as f64)
}

/// A parry pose from our position and orientation.
pub fn to_pose(position: &Vector3<f64>, orientation: &UnitQuaternion<f64>) -> Pose {
    let q = orientation.coords; // (i, j, k, w)
    let rot = Rot3::from_xyzw(q.x as f32, q.y as f32, q.z as f32, q.w as f32).normalize();
    Pose::from_parts(to_vec3(position), rot)
}
