//! What makes a mesh usable as physics geometry. A static mesh only needs triangles; a dynamic
//! one is a solid with a mass, so it must enclose a volume: closed, every edge shared by exactly
//! two triangles wound opposite ways (a manifold, consistently oriented), with a positive signed
//! volume (counter-clockwise seen from outside — a negative one means the normals point in).

use std::collections::HashMap;

use crate::{Mesh, MeshError};

/// The file's up axis: scenes are y up, many modelling tools (Blender, 3ds Max) are z up.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UpAxis {
    Y,
    Z,
}

/// A mesh checked to be a closed, consistently wound solid.
#[derive(Debug, Clone, PartialEq)]
pub struct Solid {
    pub mesh: Mesh,
    /// Enclosed volume, positive (in the mesh's units cubed).
    pub volume: f64,
}

impl Mesh {
    /// Scaled and turned into the scene's axes (y up, right-handed). z up → y up maps
    /// (x, y, z) to (x, z, −y), a rotation, so windings and volumes keep their sign.
    pub fn to_scene_axes(mut self, scale: f64, up: UpAxis) -> Mesh {
        for v in &mut self.vertices {
            let [x, y, z] = *v;
            *v = match up {
                UpAxis::Y => [x * scale, y * scale, z * scale],
                UpAxis::Z => [x * scale, z * scale, -y * scale],
            };
        }
        self
    }

    /// Vertices at exactly the same position merged into one (OBJ exporters split vertices
    /// wherever normals or texture coordinates differ, which would make a closed surface look
    /// open), and triangles that then repeat a corner dropped. Deterministic: the first
    /// occurrence of a position keeps its place.
    pub fn welded(&self) -> Mesh {
        let mut index: HashMap<[u64; 3], u32> = HashMap::new();
        let mut vertices = Vec::new();
        let mut remap = Vec::with_capacity(self.vertices.len());
        for v in &self.vertices {
            // +0.0 for −0.0, so the two zeros weld.
            let key = v.map(|c| (c + 0.0).to_bits());
            let next = u32::try_from(vertices.len()).unwrap_or(u32::MAX);
            let i = *index.entry(key).or_insert_with(|| {
                vertices.push(*v);
                next
            });
            remap.push(i);
        }
        let triangles = self
            .triangles
            .iter()
            .map(|t| t.map(|i| remap[i as usize]))
            .filter(|[a, b, c]| a != b && b != c && a != c)
            .collect();
        Mesh {
            vertices,
            triangles,
        }
    }

    /// Checks what a static triangle mesh needs: at least one triangle left after welding.
    pub fn check_static(&self, file: &str) -> Result<Mesh, MeshError> {
        let welded = self.welded();
        if welded.triangles.is_empty() {
            return Err(MeshError::bad(
                file,
                "every triangle is degenerate (repeats a corner): no surface",
            ));
        }
        Ok(welded)
    }

    /// Checks that the mesh is a solid a dynamic body can be made of: closed, manifold,
    /// consistently wound outward, with a volume.
    pub fn check_solid(&self, file: &str) -> Result<Solid, MeshError> {
        let mesh = self.welded();
        if mesh.triangles.len() < 4 {
            return Err(MeshError::bad(
                file,
                format!(
                    "{} triangles cannot enclose a volume (a dynamic body needs a closed mesh)",
                    mesh.triangles.len()
                ),
            ));
        }
        let at = |i: u32| {
            let [x, y, z] = mesh.vertices[i as usize];
            format!("[{x}, {y}, {z}]")
        };
        // Each directed edge once, and its reverse once: closed, 2-manifold, consistently wound.
        let mut directed: HashMap<(u32, u32), u32> = HashMap::new();
        for t in &mesh.triangles {
            for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                *directed.entry((a, b)).or_insert(0) += 1;
            }
        }
        // Sorted, so the edge an error names does not depend on hash order.
        let mut edges: Vec<(&(u32, u32), &u32)> = directed.iter().collect();
        edges.sort_unstable();
        for (&(a, b), &n) in edges {
            if n > 1 {
                let both = directed.get(&(b, a)).copied().unwrap_or(0) + n;
                return Err(MeshError::bad(
                    file,
                    if both > 2 {
                        format!(
                            "non-manifold: the edge {}–{} borders {both} triangles (a dynamic body needs a closed surface where every edge borders two)",
                            at(a),
                            at(b)
                        )
                    } else {
                        format!(
                            "inconsistently wound: the two triangles at the edge {}–{} face opposite ways (flip one so all wind counter-clockwise seen from outside)",
                            at(a),
                            at(b)
                        )
                    },
                ));
            }
            if !directed.contains_key(&(b, a)) {
                return Err(MeshError::bad(
                    file,
                    format!(
                        "open mesh: the edge {}–{} borders one triangle only (a dynamic body needs a closed surface; close the hole, or make it a [[static]])",
                        at(a),
                        at(b)
                    ),
                ));
            }
        }
        let volume = signed_volume(&mesh);
        let (lo, hi) = bounds(&mesh.vertices);
        let extent = (0..3).map(|k| hi[k] - lo[k]).fold(0.0, f64::max);
        // A volume below a billionth of the bounding cube is a flat (or folded) sheet.
        if volume.abs() <= 1e-9 * extent * extent * extent {
            return Err(MeshError::bad(
                file,
                format!(
                    "zero volume ({volume:e}): the closed surface encloses nothing (flat, or folded onto itself)"
                ),
            ));
        }
        if volume < 0.0 {
            return Err(MeshError::bad(
                file,
                format!(
                    "inverted normals: the signed volume is {volume:e} (< 0): triangles wind clockwise seen from outside; flip the normals in the modelling tool"
                ),
            ));
        }
        Ok(Solid { mesh, volume })
    }
}

/// Sum of the signed tetrahedra (origin, a, b, c): the enclosed volume of a closed mesh wound
/// counter-clockwise seen from outside, negative when wound the other way.
pub fn signed_volume(mesh: &Mesh) -> f64 {
    mesh.triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
            a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
                + a[2] * (b[0] * c[1] - b[1] * c[0])
        })
        .sum::<f64>()
        / 6.0
}

fn bounds(points: &[[f64; 3]]) -> ([f64; 3], [f64; 3]) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in points {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    (lo, hi)
}
