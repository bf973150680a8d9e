//! Approximate convex decomposition of a solid mesh into convex pieces, by parry3d's VHACD
//! (volumetric hierarchical approximate convex decomposition: the mesh is voxelised at
//! `resolution`, the voxels split along planes until every part's concavity is below
//! `concavity`; each part's piece is the convex hull of the mesh's triangles inside it).
//!
//! A letter "B" as one convex hull fills both its holes; as convex pieces it keeps them, so a
//! peg can pass through. Decomposition takes seconds at the default resolution, so the result is
//! cached next to the mesh ([`cache_path`]), keyed by the mesh's content hash and the
//! parameters: a second submission of the scene does not wait for it.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use parry3d::math::Vector;
use parry3d::transformation::vhacd::{VHACD, VHACDParameters};

use crate::check::Solid;
use crate::{MeshError, content_hash};

/// Version of the decomposition and of its cache files: bump it when either changes, so old
/// caches are ignored rather than misread.
const CACHE_VERSION: u32 = 1;

/// The decomposition's knobs, as a scene writes them in `decomposition = { … }`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Params {
    /// Voxels along the mesh's longest side (default 64, parry's). Finer keeps smaller features
    /// (a letter's narrow counter) at a cost that grows with its cube.
    pub resolution: u32,
    /// Largest concavity a piece may keep, as a fraction of the mesh's size (default 0.01,
    /// parry's). Smaller → more, tighter pieces.
    pub concavity: f64,
    /// At most this many pieces (default 32): each piece is a collider in every world.
    pub max_pieces: u32,
}

impl Default for Params {
    fn default() -> Self {
        Self {
            resolution: 64,
            concavity: 0.01,
            max_pieces: 32,
        }
    }
}

impl Params {
    /// Resolution limits: below 8 voxels nothing is left of a shape; above 256 a decomposition
    /// takes minutes and gigabytes.
    pub const RESOLUTION: (u32, u32) = (8, 256);
    /// Limits of `max_pieces`.
    pub const MAX_PIECES: (u32, u32) = (1, 256);

    fn vhacd(&self) -> VHACDParameters {
        VHACDParameters {
            resolution: self.resolution,
            concavity: self.concavity as f32,
            max_convex_hulls: self.max_pieces,
            ..VHACDParameters::default()
        }
    }

    /// The parameters as they key a cache entry and appear in a resolved scene.
    pub fn describe(&self) -> String {
        format!(
            "resolution {}, concavity {:?}, max_pieces {}",
            self.resolution, self.concavity, self.max_pieces
        )
    }
}

/// A solid's convex pieces: each the points of a convex hull, in the solid's frame. Points are
/// parry's `f32`; they are written into the scene exactly (as the `f64` of that `f32`).
#[derive(Debug, Clone, PartialEq)]
pub struct Decomposition {
    pub pieces: Vec<Vec<[f32; 3]>>,
}

/// Decomposes `solid` (`file` names it in errors). Deterministic: the same mesh and parameters
/// give the same pieces, bit for bit (tested), as a world's determinism needs.
pub fn decompose(file: &str, solid: &Solid, params: &Params) -> Result<Decomposition, MeshError> {
    let points: Vec<Vector> = solid
        .mesh
        .vertices
        .iter()
        .map(|v| Vector::new(v[0] as f32, v[1] as f32, v[2] as f32))
        .collect();
    let vhacd = VHACD::decompose(&params.vhacd(), &points, &solid.mesh.triangles, true);
    let extent = extent(&solid.mesh.vertices);
    let mut pieces = Vec::new();
    for (hull, triangles) in vhacd.compute_exact_convex_hulls(&points, &solid.mesh.triangles) {
        let hull: Vec<[f32; 3]> = hull.iter().map(|p| [p.x, p.y, p.z]).collect();
        // A part that touched only a sliver of the surface can give a flat hull; it adds no
        // volume, and the scene format refuses flat hulls, so it is left out (parry's own
        // convex_decomposition drops the hulls it cannot build the same way).
        if hull.len() >= 4 && hull_volume(&hull, &triangles) > 1e-6 * extent * extent * extent {
            pieces.push(hull);
        }
    }
    if pieces.is_empty() {
        return Err(MeshError::bad(
            file,
            format!(
                "convex decomposition ({}) left no piece with a volume: raise the resolution",
                params.describe()
            ),
        ));
    }
    Ok(Decomposition { pieces })
}

fn extent(points: &[[f64; 3]]) -> f64 {
    (0..3)
        .map(|k| {
            let (lo, hi) = points
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
                    (lo.min(p[k]), hi.max(p[k]))
                });
            hi - lo
        })
        .fold(0.0, f64::max)
}

fn hull_volume(points: &[[f32; 3]], triangles: &[[u32; 3]]) -> f64 {
    let p = |i: u32| {
        points
            .get(i as usize)
            .map_or([0.0; 3], |v| v.map(f64::from))
    };
    triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(p);
            a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
                + a[2] * (b[0] * c[1] - b[1] * c[0])
        })
        .sum::<f64>()
        .abs()
        / 6.0
}

/// The cache key of a decomposition: the mesh file's content hash, how it was placed (scale and
/// up axis change the vertices VHACD sees), the parameters and the cache version.
pub fn cache_key(mesh_hash: u64, placement: &str, params: &Params) -> u64 {
    content_hash(
        format!(
            "mwb-hulls {CACHE_VERSION}; mesh {mesh_hash:016x}; {placement}; {}",
            params.describe()
        )
        .as_bytes(),
    )
}

/// Where the decomposition of the mesh at `mesh_path` under `key` is cached: a `.mwb-cache`
/// directory beside the mesh (`props/.mwb-cache/letter_b.obj.<key>.hulls`), so the cache moves
/// and is cleaned with the props it belongs to.
pub fn cache_path(mesh_path: &Path, key: u64) -> PathBuf {
    let name = mesh_path
        .file_name()
        .map_or_else(|| "mesh".to_owned(), |n| n.to_string_lossy().into_owned());
    mesh_path
        .parent()
        .unwrap_or(Path::new("."))
        .join(".mwb-cache")
        .join(format!("{name}.{key:016x}.hulls"))
}

impl Decomposition {
    /// The cache file's text: a header with the key, one line per piece of `f32` bit patterns in
    /// hex (exact, unlike decimal), and a CRC-32 of everything before it, so a truncated or
    /// edited file is recognised and rebuilt rather than trusted.
    pub fn to_cache(&self, key: u64) -> String {
        let mut s = format!(
            "mwb-hulls {CACHE_VERSION} {key:016x} {}\n",
            self.pieces.len()
        );
        for piece in &self.pieces {
            for p in piece {
                // Writing to a String cannot fail.
                let _ = write!(
                    s,
                    "{:08x}{:08x}{:08x} ",
                    p[0].to_bits(),
                    p[1].to_bits(),
                    p[2].to_bits()
                );
            }
            s.push('\n');
        }
        let crc = crc32fast::hash(s.as_bytes());
        let _ = writeln!(s, "crc {crc:08x}");
        s
    }

    /// Reads a cache file written by [`Self::to_cache`] for `key`; `None` if it is for another
    /// key or damaged in any way.
    pub fn from_cache(bytes: &[u8], key: u64) -> Option<Decomposition> {
        let text = std::str::from_utf8(bytes).ok()?;
        let crc_at = text.rfind("crc ")?;
        let (body, tail) = text.split_at(crc_at);
        let crc = u32::from_str_radix(tail.strip_prefix("crc ")?.trim_end(), 16).ok()?;
        if crc32fast::hash(body.as_bytes()) != crc {
            return None;
        }
        let mut lines = body.lines();
        let mut head = lines.next()?.split(' ');
        let (Some("mwb-hulls"), Some(v), Some(k), Some(n)) =
            (head.next(), head.next(), head.next(), head.next())
        else {
            return None;
        };
        if v.parse::<u32>().ok()? != CACHE_VERSION || u64::from_str_radix(k, 16).ok()? != key {
            return None;
        }
        let n: usize = n.parse().ok()?;
        let bits = |w: &str, i: usize| {
            w.get(i * 8..(i + 1) * 8)
                .and_then(|h| u32::from_str_radix(h, 16).ok())
                .map(f32::from_bits)
        };
        let mut pieces = Vec::with_capacity(n.min(1024));
        for line in lines {
            let piece = line
                .split_ascii_whitespace()
                .map(|w| {
                    (w.len() == 24)
                        .then(|| Some([bits(w, 0)?, bits(w, 1)?, bits(w, 2)?]))
                        .flatten()
                        .filter(|p| p.iter().all(|c| c.is_finite()))
                })
                .collect::<Option<Vec<[f32; 3]>>>()?;
            if piece.len() < 4 {
                return None;
            }
            pieces.push(piece);
        }
        (pieces.len() == n && n > 0).then_some(Decomposition { pieces })
    }
}
