//! glTF 2.0 binary (`.glb`): the triangles of one node's mesh, placed by that node's own local
//! transform. Only the file's binary chunk is read (no external `.bin` or image files, so no
//! file system access beyond the one file); positions and indices of every triangle primitive
//! of the mesh are concatenated.

use crate::{MAX_TRIANGLES, Mesh, MeshError};

/// The mesh of the node named `node` (or, without a name, the file's only mesh-bearing node).
pub fn parse(file: &str, bytes: &[u8], node: Option<&str>) -> Result<Mesh, MeshError> {
    let gltf = gltf::Gltf::from_slice(bytes)
        .map_err(|e| MeshError::bad(file, format!("not a valid glTF binary: {e}")))?;
    let blob = gltf.blob.as_deref();
    let with_mesh: Vec<gltf::Node<'_>> = gltf.nodes().filter(|n| n.mesh().is_some()).collect();
    let names = || {
        with_mesh
            .iter()
            .map(|n| format!("\"{}\"", n.name().unwrap_or("(unnamed)")))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let chosen = match node {
        Some(name) => with_mesh
            .iter()
            .find(|n| n.name() == Some(name))
            .ok_or_else(|| {
                MeshError::bad(
                    file,
                    format!(
                        "no node \"{name}\" with a mesh (nodes with meshes: {})",
                        names()
                    ),
                )
            })?,
        None => match with_mesh.as_slice() {
            [only] => only,
            [] => return Err(MeshError::bad(file, "no node has a mesh")),
            _ => {
                return Err(MeshError::bad(
                    file,
                    format!(
                        "several nodes have meshes: name one as \"{file}#node\" ({})",
                        names()
                    ),
                ));
            }
        },
    };
    let Some(gmesh) = chosen.mesh() else {
        return Err(MeshError::bad(file, "the node has no mesh"));
    };
    let m = chosen.transform().matrix(); // column-major 4×4
    let mut mesh = Mesh {
        vertices: Vec::new(),
        triangles: Vec::new(),
    };
    for prim in gmesh.primitives() {
        if prim.mode() != gltf::mesh::Mode::Triangles {
            return Err(MeshError::bad(
                file,
                format!(
                    "primitive {} is {:?}, not triangles",
                    prim.index(),
                    prim.mode()
                ),
            ));
        }
        let reader = prim.reader(|buffer| match buffer.source() {
            gltf::buffer::Source::Bin => blob,
            // External buffers would need more files: a scene's meshes must be one file each.
            gltf::buffer::Source::Uri(_) => None,
        });
        let positions: Vec<[f32; 3]> = reader
            .read_positions()
            .ok_or_else(|| {
                MeshError::bad(
                    file,
                    format!(
                        "primitive {}: no positions in the binary chunk (external .bin buffers are not read: export as a single .glb)",
                        prim.index()
                    ),
                )
            })?
            .collect();
        let base = u32::try_from(mesh.vertices.len())
            .map_err(|_| MeshError::bad(file, "too many vertices"))?;
        let count = u32::try_from(positions.len())
            .map_err(|_| MeshError::bad(file, "too many vertices"))?;
        for p in &positions {
            let [x, y, z] = p.map(f64::from);
            let t = |r: usize| {
                f64::from(m[0][r]) * x
                    + f64::from(m[1][r]) * y
                    + f64::from(m[2][r]) * z
                    + f64::from(m[3][r])
            };
            let v = [t(0), t(1), t(2)];
            if v.iter().any(|c| !c.is_finite()) {
                return Err(MeshError::bad(
                    file,
                    format!("primitive {}: a vertex is not finite", prim.index()),
                ));
            }
            mesh.vertices.push(v);
        }
        let indices: Vec<u32> = match reader.read_indices() {
            Some(i) => i.into_u32().collect(),
            None => (0..count).collect(),
        };
        if !indices.len().is_multiple_of(3) {
            return Err(MeshError::bad(
                file,
                format!(
                    "primitive {}: index count not a multiple of 3",
                    prim.index()
                ),
            ));
        }
        if mesh.triangles.len() + indices.len() / 3 > MAX_TRIANGLES {
            return Err(MeshError::bad(
                file,
                format!("more than {MAX_TRIANGLES} triangles: make a simplified collision mesh"),
            ));
        }
        for t in indices.chunks_exact(3) {
            if t.iter().any(|&i| i >= count) {
                return Err(MeshError::bad(
                    file,
                    format!("primitive {}: index out of range", prim.index()),
                ));
            }
            mesh.triangles.push([base + t[0], base + t[1], base + t[2]]);
        }
    }
    if mesh.triangles.is_empty() {
        return Err(MeshError::bad(file, "the mesh has no triangles"));
    }
    Ok(mesh)
}
