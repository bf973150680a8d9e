//! Scene shapes as triangle meshes in the body's local frame (y up; capsules and cylinders
//! along local y, as the scene format defines them), triangles wound counter-clockwise seen
//! from outside (glTF's front face).
//!
//! Boxes, hulls, cylinder caps and triangle meshes are flat-shaded (a vertex per face corner);
//! spheres, capsules and cylinder sides are smooth. A plane is an infinite half-space in the
//! scene; here it is a square of a given half size, centred on the plane's point. A compound is
//! all its parts, each placed at its pose in the body's frame ([`part_meshes`] keeps them apart,
//! with their materials; [`shape_mesh`] merges them).

use mwb_core::scene::{Quat, Shape, Vec3};
use std::f64::consts::PI;

/// Slices around the axis of round shapes.
pub const ROUND_SLICES: usize = 32;
/// Rings from pole to pole of spheres and capsules (even, so a capsule splits at the equator).
pub const ROUND_STACKS: usize = 16;

/// An indexed triangle mesh, `f32` as glTF stores it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TriangleMesh {
    pub positions: Vec<[f32; 3]>,
    /// Unit length, one per position.
    pub normals: Vec<[f32; 3]>,
    /// Three per triangle.
    pub indices: Vec<u32>,
}

impl TriangleMesh {
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }

    /// Componentwise minimum and maximum of the positions (glTF's accessor `min`/`max`).
    pub fn bounds(&self) -> ([f32; 3], [f32; 3]) {
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for p in &self.positions {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        (lo, hi)
    }

    /// The volume the triangles enclose (divergence theorem; positive when they face out).
    pub fn enclosed_volume(&self) -> f64 {
        self.indices
            .chunks_exact(3)
            .map(|t| {
                let p = |i: u32| f64x3(self.positions[i as usize]);
                dot(p(t[0]), cross(p(t[1]), p(t[2]))) / 6.0
            })
            .sum()
    }

    /// Appends `other` placed at `position`, `rotation` (its triangles keep their winding).
    pub fn append_placed(&mut self, other: &TriangleMesh, position: Vec3, rotation: Quat) {
        let base = self.positions.len() as u32;
        for (p, n) in other.positions.iter().zip(&other.normals) {
            let p = rotate(rotation, f64x3(*p));
            self.positions.push(f32x3([
                p[0] + position[0],
                p[1] + position[1],
                p[2] + position[2],
            ]));
            self.normals
                .push(f32x3(normalize(rotate(rotation, f64x3(*n)))));
        }
        self.indices.extend(other.indices.iter().map(|i| base + i));
    }

    fn vertex(&mut self, p: Vec3, n: Vec3) -> u32 {
        let i = self.positions.len() as u32;
        self.positions.push(f32x3(p));
        self.normals.push(f32x3(normalize(n)));
        i
    }

    /// A flat triangle (its own three vertices, the face normal).
    fn flat_triangle(&mut self, a: Vec3, b: Vec3, c: Vec3) {
        let n = cross(sub(b, a), sub(c, a));
        if norm(n) == 0.0 {
            return; // degenerate: contributes nothing visible
        }
        let i = self.vertex(a, n);
        self.vertex(b, n);
        self.vertex(c, n);
        self.indices.extend([i, i + 1, i + 2]);
    }

    /// Winds every triangle counter-clockwise seen from outside a convex mesh around `centre`.
    fn orient_outward(&mut self, centre: Vec3) {
        for t in self.indices.chunks_exact_mut(3) {
            let p = |i: u32| f64x3(self.positions[i as usize]);
            let (a, b, c) = (p(t[0]), p(t[1]), p(t[2]));
            let n = cross(sub(b, a), sub(c, a));
            let mid = [
                (a[0] + b[0] + c[0]) / 3.0 - centre[0],
                (a[1] + b[1] + c[1]) / 3.0 - centre[1],
                (a[2] + b[2] + c[2]) / 3.0 - centre[2],
            ];
            if dot(n, mid) < 0.0 {
                t.swap(1, 2);
            }
        }
    }
}

/// The mesh of every part of `shape` in the body's frame, with the part's material (the body's
/// `material` for a single shape, which is its one part): a glTF primitive each. Errors name the
/// part of a compound (`part 1: convex hull …`).
pub fn part_meshes(
    shape: &Shape,
    material: usize,
    plane_half_size: f64,
) -> Result<Vec<(usize, TriangleMesh)>, String> {
    let compound = matches!(shape, Shape::Compound { .. });
    shape
        .placed_parts(material)
        .into_iter()
        .enumerate()
        .map(|(i, part)| {
            let local = shape_mesh(part.shape, plane_half_size).map_err(|e| {
                if compound {
                    format!("part {i}: {e}")
                } else {
                    e
                }
            })?;
            if !compound {
                return Ok((part.material, local));
            }
            let mut m = TriangleMesh::default();
            m.append_placed(&local, part.position, part.rotation);
            Ok((part.material, m))
        })
        .collect()
}

/// The mesh of `shape` (a compound's parts merged into one). `plane_half_size` is the half side
/// of the square drawn for a plane. Errors (as text, for the caller to name the body) for a
/// degenerate hull or a triangle mesh with an index out of range.
pub fn shape_mesh(shape: &Shape, plane_half_size: f64) -> Result<TriangleMesh, String> {
    let mut m = TriangleMesh::default();
    match shape {
        Shape::Compound { parts } => {
            for (i, part) in parts.iter().enumerate() {
                let local = shape_mesh(&part.shape, plane_half_size)
                    .map_err(|e| format!("part {i}: {e}"))?;
                m.append_placed(&local, part.position, part.rotation);
            }
        }
        Shape::Box { half_extents: h } => {
            box_mesh(&mut m, *h);
            m.orient_outward([0.0; 3]);
        }
        Shape::Sphere { radius } => {
            round_mesh(&mut m, *radius, 0.0);
            m.orient_outward([0.0; 3]);
        }
        Shape::Capsule {
            half_height,
            radius,
        } => {
            round_mesh(&mut m, *radius, *half_height);
            m.orient_outward([0.0; 3]);
        }
        Shape::Cylinder {
            half_height,
            radius,
        } => {
            cylinder_mesh(&mut m, *radius, *half_height);
            m.orient_outward([0.0; 3]);
        }
        Shape::ConvexHull { points } => {
            let pts: Vec<parry3d::math::Vector3> = points
                .iter()
                .map(|p| parry3d::math::Vector3::new(p[0] as f32, p[1] as f32, p[2] as f32))
                .collect();
            let (verts, faces) = parry3d::transformation::try_convex_hull(&pts)
                .map_err(|e| format!("convex hull: {e:?}"))?;
            if faces.is_empty() {
                return Err("convex hull has no faces (points coplanar?)".into());
            }
            let v = |i: u32| {
                let p = verts[i as usize];
                [f64::from(p.x), f64::from(p.y), f64::from(p.z)]
            };
            for f in &faces {
                m.flat_triangle(v(f[0]), v(f[1]), v(f[2]));
            }
            let n = verts.len() as f64;
            let centre = verts.iter().fold([0.0; 3], |c, p| {
                [
                    c[0] + f64::from(p.x) / n,
                    c[1] + f64::from(p.y) / n,
                    c[2] + f64::from(p.z) / n,
                ]
            });
            m.orient_outward(centre);
            if m.enclosed_volume() <= 1e-12 {
                return Err("convex hull has no volume (points coplanar?)".into());
            }
        }
        Shape::Plane { normal } => plane_mesh(&mut m, *normal, plane_half_size)?,
        Shape::TriMesh { vertices, indices } => {
            for (t, tri) in indices.iter().enumerate() {
                let get = |i: u32| {
                    vertices.get(i as usize).copied().ok_or_else(|| {
                        format!(
                            "triangle {t}: vertex index {i} out of range ({} vertices)",
                            vertices.len()
                        )
                    })
                };
                m.flat_triangle(get(tri[0])?, get(tri[1])?, get(tri[2])?);
            }
        }
    }
    if m.indices.is_empty() {
        return Err("the shape has no area".into());
    }
    if m.positions.iter().flatten().any(|x| !x.is_finite()) {
        return Err("non-finite dimensions".into());
    }
    Ok(m)
}

fn box_mesh(m: &mut TriangleMesh, h: Vec3) {
    // Per axis and sign: the face's two tangent axes.
    for axis in 0..3 {
        for sign in [-1.0, 1.0] {
            let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
            let corner = |a: f64, b: f64| {
                let mut p = [0.0; 3];
                p[axis] = sign * h[axis];
                p[u] = a * h[u];
                p[v] = b * h[v];
                p
            };
            let mut n = [0.0; 3];
            n[axis] = sign;
            let i = m.vertex(corner(-1.0, -1.0), n);
            m.vertex(corner(1.0, -1.0), n);
            m.vertex(corner(1.0, 1.0), n);
            m.vertex(corner(-1.0, 1.0), n);
            m.indices.extend([i, i + 1, i + 2, i, i + 2, i + 3]);
        }
    }
}

/// A sphere (`half_height` 0) or a capsule: rings from the top pole down; a capsule's upper
/// hemisphere is lifted by `half_height`, its lower one lowered, and the two equator rings
/// joined by the cylindrical band (normals horizontal there, as on the true surface).
fn round_mesh(m: &mut TriangleMesh, r: f64, half_height: f64) {
    let half = ROUND_STACKS / 2;
    let mut rings: Vec<(f64, f64)> = (0..=half).map(|i| (i as f64, half_height)).collect();
    let lower = if half_height > 0.0 { half } else { half + 1 };
    rings.extend((lower..=ROUND_STACKS).map(|i| (i as f64, -half_height)));
    let cols = ROUND_SLICES + 1;
    let base = m.positions.len() as u32;
    for &(i, offset) in &rings {
        let phi = PI * i / ROUND_STACKS as f64;
        for j in 0..cols {
            let theta = 2.0 * PI * j as f64 / ROUND_SLICES as f64;
            let n = [phi.sin() * theta.cos(), phi.cos(), phi.sin() * theta.sin()];
            m.vertex([r * n[0], r * n[1] + offset, r * n[2]], n);
        }
    }
    let last = rings.len() - 1;
    for ring in 0..last {
        for j in 0..ROUND_SLICES {
            let a = base + (ring * cols + j) as u32;
            let b = a + 1;
            let c = a + cols as u32;
            let d = c + 1;
            // The pole rings have zero radius: one triangle per quad there.
            if ring != 0 {
                m.indices.extend([a, b, c]);
            }
            if ring + 1 != last {
                m.indices.extend([b, d, c]);
            }
        }
    }
}

fn cylinder_mesh(m: &mut TriangleMesh, r: f64, hh: f64) {
    let at = |j: usize| {
        let t = 2.0 * PI * j as f64 / ROUND_SLICES as f64;
        (t.cos(), t.sin())
    };
    // Side: smooth, two rings.
    let base = m.positions.len() as u32;
    for y in [hh, -hh] {
        for j in 0..=ROUND_SLICES {
            let (c, s) = at(j);
            m.vertex([r * c, y, r * s], [c, 0.0, s]);
        }
    }
    let cols = (ROUND_SLICES + 1) as u32;
    for j in 0..ROUND_SLICES as u32 {
        let (a, b) = (base + j, base + j + 1);
        let (c, d) = (a + cols, b + cols);
        m.indices.extend([a, b, c, b, d, c]);
    }
    // Caps: flat fans.
    for (y, ny) in [(hh, 1.0), (-hh, -1.0)] {
        let centre = m.vertex([0.0, y, 0.0], [0.0, ny, 0.0]);
        for j in 0..=ROUND_SLICES {
            let (c, s) = at(j);
            m.vertex([r * c, y, r * s], [0.0, ny, 0.0]);
        }
        for j in 0..ROUND_SLICES as u32 {
            m.indices.extend([centre, centre + 1 + j, centre + 2 + j]);
        }
    }
}

fn plane_mesh(m: &mut TriangleMesh, normal: Vec3, half: f64) -> Result<(), String> {
    let n = normalize(normal);
    if norm(n) == 0.0 || !half.is_finite() || half <= 0.0 {
        return Err("plane: zero normal or size".into());
    }
    // Any tangent: cross with the axis least aligned with the normal.
    let helper = if n[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let u = normalize(cross(helper, n));
    let v = cross(n, u);
    let corner = |a: f64, b: f64| {
        [
            half * (a * u[0] + b * v[0]),
            half * (a * u[1] + b * v[1]),
            half * (a * u[2] + b * v[2]),
        ]
    };
    // u × v = n: (−,−) (+,−) (+,+) (−,+) is counter-clockwise seen from the normal's side.
    let i = m.vertex(corner(-1.0, -1.0), n);
    m.vertex(corner(1.0, -1.0), n);
    m.vertex(corner(1.0, 1.0), n);
    m.vertex(corner(-1.0, 1.0), n);
    m.indices.extend([i, i + 1, i + 2, i, i + 2, i + 3]);
    Ok(())
}

/// `v` rotated by the unit quaternion `q` (`[x, y, z, w]`): v + 2w(u × v) + 2u × (u × v).
pub(crate) fn rotate(q: Quat, v: Vec3) -> Vec3 {
    let u = [q[0], q[1], q[2]];
    let t = cross(u, v).map(|x| 2.0 * x);
    let r = cross(u, t);
    [0, 1, 2].map(|i| v[i] + q[3] * t[i] + r[i])
}

fn f32x3(p: Vec3) -> [f32; 3] {
    [p[0] as f32, p[1] as f32, p[2] as f32]
}
fn f64x3(p: [f32; 3]) -> Vec3 {
    [f64::from(p[0]), f64::from(p[1]), f64::from(p[2])]
}
fn sub(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn norm(a: Vec3) -> f64 {
    dot(a, a).sqrt()
}
fn normalize(a: Vec3) -> Vec3 {
    let n = norm(a);
    if n > 0.0 {
        [a[0] / n, a[1] / n, a[2] / n]
    } else {
        a
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn volume(m: &TriangleMesh) -> f64 {
        m.enclosed_volume()
    }

    fn closed_and_outward(m: &TriangleMesh) {
        for t in m.indices.chunks_exact(3) {
            assert!(t.iter().all(|&i| (i as usize) < m.positions.len()));
        }
        for n in &m.normals {
            let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            assert!((l - 1.0).abs() < 1e-5, "normal length {l}");
        }
        assert!(volume(m) > 0.0);
    }

    #[test]
    fn volumes_match_the_shapes() {
        let b = shape_mesh(
            &Shape::Box {
                half_extents: [0.5, 0.1, 0.2],
            },
            1.0,
        )
        .unwrap();
        closed_and_outward(&b);
        assert_eq!(b.triangle_count(), 12);
        assert!((volume(&b) - 8.0 * 0.5 * 0.1 * 0.2).abs() < 1e-6);
        assert_eq!(b.bounds(), ([-0.5, -0.1, -0.2], [0.5, 0.1, 0.2]));

        let r = 0.3;
        let s = shape_mesh(&Shape::Sphere { radius: r }, 1.0).unwrap();
        closed_and_outward(&s);
        let exact = 4.0 / 3.0 * PI * r * r * r;
        assert!((volume(&s) - exact).abs() / exact < 0.03, "{}", volume(&s));

        let c = shape_mesh(
            &Shape::Capsule {
                half_height: 0.4,
                radius: r,
            },
            1.0,
        )
        .unwrap();
        closed_and_outward(&c);
        let exact = exact + PI * r * r * 0.8;
        assert!((volume(&c) - exact).abs() / exact < 0.03);
        assert!((c.bounds().1[1] - 0.7).abs() < 1e-6);

        let y = shape_mesh(
            &Shape::Cylinder {
                half_height: 0.4,
                radius: r,
            },
            1.0,
        )
        .unwrap();
        closed_and_outward(&y);
        let exact = PI * r * r * 0.8;
        assert!((volume(&y) - exact).abs() / exact < 0.03);
    }

    #[test]
    fn hull_is_triangulated_outward_whatever_the_point_order() {
        // A unit cube's corners plus an interior point, which the hull drops.
        let mut points: Vec<Vec3> = (0..8)
            .map(|i| {
                [
                    f64::from(i & 1),
                    f64::from((i >> 1) & 1),
                    f64::from((i >> 2) & 1),
                ]
            })
            .collect();
        points.push([0.5, 0.5, 0.5]);
        let m = shape_mesh(&Shape::ConvexHull { points }, 1.0).unwrap();
        closed_and_outward(&m);
        assert_eq!(m.triangle_count(), 12);
        assert!((volume(&m) - 1.0).abs() < 1e-6);
        let flat = Shape::ConvexHull {
            points: vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]],
        };
        assert!(shape_mesh(&flat, 1.0).is_err());
    }

    #[test]
    fn plane_faces_its_normal_and_bad_meshes_are_named() {
        let m = shape_mesh(
            &Shape::Plane {
                normal: [0.0, 2.0, 0.0],
            },
            10.0,
        )
        .unwrap();
        assert_eq!(m.triangle_count(), 2);
        let p = |i: u32| f64x3(m.positions[i as usize]);
        let n = cross(
            sub(p(m.indices[1]), p(m.indices[0])),
            sub(p(m.indices[2]), p(m.indices[0])),
        );
        assert!(n[1] > 0.0 && n[0].abs() < 1e-9 && n[2].abs() < 1e-9);
        assert_eq!(m.bounds(), ([-10.0, 0.0, -10.0], [10.0, 0.0, 10.0]));
        let bad = Shape::TriMesh {
            vertices: vec![[0.0; 3], [1.0, 0.0, 0.0]],
            indices: vec![[0, 1, 2]],
        };
        let e = shape_mesh(&bad, 1.0).unwrap_err();
        assert!(e.contains("vertex index 2"), "{e}");
    }

    #[test]
    fn a_compound_is_all_its_parts_placed_in_the_body_frame() {
        use mwb_core::scene::{IDENTITY, Part};
        let s = std::f64::consts::FRAC_1_SQRT_2;
        let compound = Shape::Compound {
            parts: vec![
                Part {
                    shape: Shape::Box {
                        half_extents: [0.1, 0.1, 0.1],
                    },
                    position: [0.0; 3],
                    rotation: IDENTITY,
                    material: 0,
                },
                // 90° about z: the bar's long x side lies along y, centred 1 m up.
                Part {
                    shape: Shape::Box {
                        half_extents: [0.3, 0.05, 0.05],
                    },
                    position: [0.0, 1.0, 0.0],
                    rotation: [0.0, 0.0, s, s],
                    material: 2,
                },
            ],
        };
        let parts = part_meshes(&compound, 0, 1.0).unwrap();
        assert_eq!(parts.len(), 2);
        assert_eq!((parts[0].0, parts[1].0), (0, 2));
        for (_, m) in &parts {
            closed_and_outward(m);
            assert_eq!(m.triangle_count(), 12);
        }
        let (lo, hi) = parts[1].1.bounds();
        assert!(
            (lo[1] - 0.7).abs() < 1e-6 && (hi[1] - 1.3).abs() < 1e-6,
            "{lo:?} {hi:?}"
        );
        assert!((lo[0] + 0.05).abs() < 1e-6 && (hi[0] - 0.05).abs() < 1e-6);
        // Merged: every part's triangles, the volumes of both (they do not overlap).
        let merged = shape_mesh(&compound, 1.0).unwrap();
        assert_eq!(merged.triangle_count(), 24);
        closed_and_outward(&merged);
        let want = 8.0 * (0.1 * 0.1 * 0.1 + 0.3 * 0.05 * 0.05);
        assert!((volume(&merged) - want).abs() < 1e-6, "{}", volume(&merged));
        // A single shape is its own one part, untouched, in the body's material.
        let single = Shape::Sphere { radius: 0.2 };
        let one = part_meshes(&single, 4, 1.0).unwrap();
        assert_eq!(one.len(), 1);
        assert_eq!(one[0], (4, shape_mesh(&single, 1.0).unwrap()));
        // A bad part is named.
        let bad = Shape::Compound {
            parts: vec![Part {
                shape: Shape::ConvexHull {
                    points: vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]],
                },
                position: [0.0; 3],
                rotation: IDENTITY,
                material: 0,
            }],
        };
        let e = part_meshes(&bad, 0, 1.0).unwrap_err();
        assert!(e.starts_with("part 0: "), "{e}");
    }
}
