//! Wavefront OBJ, the geometry only: `v` positions and `f` faces. Polygons are fan-triangulated
//! from their first corner; indices may be negative (relative to the vertices read so far);
//! `v/vt/vn` corners keep the position index. Texture coordinates, normals, groups, objects,
//! smoothing groups and materials are ignored — a collision shape needs none of them.

use crate::{MAX_TRIANGLES, Mesh, MeshError};

/// Parses OBJ bytes; `file` names the file in errors (with the line).
pub fn parse(file: &str, bytes: &[u8]) -> Result<Mesh, MeshError> {
    let text = std::str::from_utf8(bytes).map_err(|e| {
        let line = bytes[..e.valid_up_to()]
            .iter()
            .filter(|b| **b == b'\n')
            .count()
            + 1;
        MeshError::at_line(
            file,
            line,
            "not UTF-8 (or ASCII) text: is this an OBJ file?",
        )
    })?;
    let mut mesh = Mesh {
        vertices: Vec::new(),
        triangles: Vec::new(),
    };
    let mut corners: Vec<u32> = Vec::new();
    for (n, raw) in text.lines().enumerate() {
        let line = n + 1;
        let content = raw.split('#').next().unwrap_or("").trim();
        let mut words = content.split_ascii_whitespace();
        match words.next() {
            Some("v") => {
                let mut p = [0.0f64; 3];
                for (axis, slot) in p.iter_mut().enumerate() {
                    let word = words.next().ok_or_else(|| {
                        MeshError::at_line(file, line, "a vertex needs x, y and z")
                    })?;
                    *slot = word.parse::<f64>().map_err(|_| {
                        MeshError::at_line(
                            file,
                            line,
                            format!(
                                "vertex {}: \"{word}\" is not a number",
                                mesh.vertices.len() + 1
                            ),
                        )
                    })?;
                    if !slot.is_finite() {
                        return Err(MeshError::at_line(
                            file,
                            line,
                            format!(
                                "vertex {} is not finite ({} = {word})",
                                mesh.vertices.len() + 1,
                                ["x", "y", "z"][axis]
                            ),
                        ));
                    }
                }
                // A fourth number (w, or a vertex colour) is allowed and ignored.
                mesh.vertices.push(p);
            }
            Some("f") => {
                corners.clear();
                for word in words {
                    corners.push(corner_index(file, line, word, mesh.vertices.len())?);
                }
                if corners.len() < 3 {
                    return Err(MeshError::at_line(
                        file,
                        line,
                        format!("a face needs at least 3 corners, found {}", corners.len()),
                    ));
                }
                if mesh.triangles.len() + corners.len() - 2 > MAX_TRIANGLES {
                    return Err(MeshError::at_line(
                        file,
                        line,
                        format!(
                            "more than {MAX_TRIANGLES} triangles: make a simplified collision mesh"
                        ),
                    ));
                }
                // Fan from the first corner: exact for the convex polygons modelling tools
                // write; a concave polygon should be triangulated by the tool that made it.
                for k in 1..corners.len() - 1 {
                    mesh.triangles
                        .push([corners[0], corners[k], corners[k + 1]]);
                }
            }
            _ => {}
        }
    }
    if mesh.triangles.is_empty() {
        return Err(MeshError::bad(file, "no faces (`f` lines): not a mesh"));
    }
    Ok(mesh)
}

/// The position index of a face corner (`7`, `7/2`, `7//3`, `-1`), 0-based. Only vertices read
/// before the face may be named, as the format says.
fn corner_index(file: &str, line: usize, word: &str, n_vertices: usize) -> Result<u32, MeshError> {
    let first = word.split('/').next().unwrap_or("");
    let i: i64 = first.parse().map_err(|_| {
        MeshError::at_line(
            file,
            line,
            format!("face corner \"{word}\" is not a vertex index"),
        )
    })?;
    let n = i64::try_from(n_vertices).unwrap_or(i64::MAX);
    let zero_based = match i {
        0 => None,
        i if i > 0 && i <= n => Some(i - 1),
        i if i < 0 && -i <= n => Some(n + i),
        _ => None,
    };
    zero_based
        .and_then(|z| u32::try_from(z).ok())
        .ok_or_else(|| {
            MeshError::at_line(
                file,
                line,
                format!(
                    "face corner {i} out of range: {n_vertices} vertices read so far (indices are 1-based; negative ones count back)"
                ),
            )
        })
}
