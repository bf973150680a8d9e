//! Mesh import for scenes: `shape = "mesh"` bodies and statics read from OBJ or glTF binary
//! files, checked, and turned into shapes the scene format already has — a static mesh into a
//! triangle mesh, a dynamic one into a compound of convex pieces by approximate convex
//! decomposition (VHACD, as shipped by parry3d).
//!
//! The scene parser (`mwb-core`) does no I/O, and a sampler on another machine has no access to
//! the author's files, so meshes are **resolved** before a scene leaves the machine it was
//! written on: [`resolve`] reads every mesh a scene names and rewrites the scene into
//! self-contained TOML (each mesh body becomes a `compound` with inline parts, the source file
//! and its content hash recorded in a comment). Jobs carry that text; nothing downstream reads a
//! mesh file. Decompositions are cached next to the mesh ([`decompose::cache_path`]), keyed by
//! the mesh's content hash and the decomposition parameters.
//!
//! ```
//! use mwb_mesh::{Mesh, obj};
//!
//! // A unit tetrahedron, wound counter-clockwise seen from outside.
//! let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n";
//! let mesh: Mesh = obj::parse("tet.obj", text.as_bytes())?;
//! assert_eq!((mesh.vertices.len(), mesh.triangles.len()), (4, 4));
//! let solid = mesh.check_solid("tet.obj")?; // closed, consistently wound, positive volume
//! assert!((solid.volume - 1.0 / 6.0).abs() < 1e-12);
//! # Ok::<(), mwb_mesh::MeshError>(())
//! ```

pub mod check;
pub mod decompose;
pub mod glb;
pub mod obj;
pub mod resolve;

pub use check::Solid;
pub use decompose::{Decomposition, Params};
pub use resolve::{Resolved, resolve, resolve_file};

/// The most triangles a mesh file may have. A studio's hero prop can have millions; as physics
/// geometry that costs memory and time in every world of every job, so we refuse it and ask for
/// a simplified collision mesh instead.
pub const MAX_TRIANGLES: usize = 1_000_000;

/// A triangle mesh as read from a file: positions in the file's units and axes, triangles as
/// 0-based vertex indices (polygons already fan-triangulated).
#[derive(Debug, Clone, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<[f64; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

/// Why a mesh file cannot be used. Every variant names the file; the message says what is wrong
/// and, where it helps, where in the file.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MeshError {
    /// The file could not be read (missing, unreadable). The I/O error's text is kept in the
    /// message: the error travels as one line to the author.
    #[error("{file}: cannot read the mesh file: {error}")]
    Read { file: String, error: String },
    /// The file was read but is not a usable mesh.
    #[error("{file}{}: {problem}", line.map(|l| format!(":{l}")).unwrap_or_default())]
    Bad {
        file: String,
        /// 1-based line of a text format (OBJ), when the problem is on one line.
        line: Option<usize>,
        problem: String,
    },
}

impl MeshError {
    pub(crate) fn bad(file: &str, problem: impl Into<String>) -> Self {
        MeshError::Bad {
            file: file.to_owned(),
            line: None,
            problem: problem.into(),
        }
    }

    pub(crate) fn at_line(file: &str, line: usize, problem: impl Into<String>) -> Self {
        MeshError::Bad {
            file: file.to_owned(),
            line: Some(line),
            problem: problem.into(),
        }
    }
}

/// 64-bit content hash of a file's bytes (FNV-1a, then a final mix): names a mesh in a resolved
/// scene and keys its cached decomposition. Not cryptographic — it detects edits, not attacks.
pub fn content_hash(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in bytes {
        h ^= u64::from(*b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    // splitmix64's finaliser: nearby inputs give unrelated hashes.
    h = (h ^ (h >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    h = (h ^ (h >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    h ^ (h >> 31)
}
