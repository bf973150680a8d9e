//! Resolving a scene's meshes: `shape = "mesh"` bodies and statics rewritten into shapes the
//! scene format already has, so the scene text is self-contained — it is all a Job carries, and
//! a sampler on another machine reads no files (docs/scene-format.md "Meshes").
//!
//! The rewrite is in place and line for line: `shape = "mesh"` becomes `shape = "compound"`,
//! the `file = …` line becomes one `part = [ … ]` line (convex pieces for a body; one trimesh
//! part for a static) followed by a comment naming the mesh file and its content hash, and the
//! mesh's own keys (`scale`, `up`, `decomposition`) become comments. Every other line is kept as
//! written, so an error the scene parser reports later still points at the author's line.

use std::collections::HashMap;
use std::fmt::Write as _;
use std::ops::Range;
use std::path::{Path, PathBuf};

use mwb_core::scene::SceneError;
use mwb_core::scene::toml_span::{Source, Table, Value};
use toml::de::DeValue;

use crate::check::UpAxis;
use crate::decompose::{self, Decomposition, Params};
use crate::{Mesh, MeshError, content_hash, glb, obj};

/// A scene with its meshes resolved.
#[derive(Debug, Clone, PartialEq)]
pub struct Resolved {
    /// The self-contained scene text (the input unchanged when it has no meshes).
    pub text: String,
    /// Each distinct mesh (file, placement, parameters) the scene uses, in file order.
    pub meshes: Vec<MeshSource>,
    /// How many decompositions ran (not found in the cache).
    pub decomposed: usize,
    /// How many decompositions came from the cache.
    pub from_cache: usize,
}

/// Where a resolved mesh came from.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshSource {
    /// As written in the scene (`props/letter_b.obj`, `props/set.glb#chair`).
    pub file: String,
    /// [`content_hash`] of the file's bytes.
    pub hash: u64,
    /// Convex pieces (a dynamic body's mesh), or `None` for a static's triangle mesh.
    pub pieces: Option<usize>,
}

/// Keys a mesh body or static may have besides the ones every body has.
const MESH_KEYS: &[&str] = &["file", "scale", "up", "decomposition"];
/// Keys of the other shapes: on a mesh they are mistakes.
const OTHER_SHAPE_KEYS: &[&str] = &[
    "size",
    "half_extents",
    "radius",
    "height",
    "half_height",
    "points",
    "normal",
    "vertices",
    "indices",
    "part",
];

/// Resolves the meshes of the scene `text` read from `scene_file`; mesh paths are relative to
/// `base_dir` (the scene file's directory). Errors are [`SceneError`]s at the mesh's `file` line
/// whose message is the [`MeshError`]: `scenes/x.toml:12: body "b": field `file`: props/b.obj:
/// open mesh: …`. Cached decompositions are read from and written to `.mwb-cache` beside each
/// mesh; a cache that cannot be written is logged, not an error.
pub fn resolve(scene_file: &str, text: &str, base_dir: &Path) -> Result<Resolved, SceneError> {
    let unchanged = || Resolved {
        text: text.to_owned(),
        meshes: Vec::new(),
        decomposed: 0,
        from_cache: 0,
    };
    // Most scenes have no meshes: skip the second parse of a 10 MB scene of boxes.
    if !text.contains("mesh") {
        return Ok(unchanged());
    }
    let src = Source {
        text,
        file: scene_file,
    };
    let doc = src.parse()?;
    let mut run = Run {
        base_dir,
        edits: Vec::new(),
        done: HashMap::new(),
        out: unchanged(),
    };
    for (kind, dynamic) in [("static", false), ("body", true)] {
        let Some(v) = doc.get_ref().get(kind) else {
            continue;
        };
        let DeValue::Array(items) = v.get_ref() else {
            continue; // the scene parser reports it
        };
        for (i, e) in items.iter().enumerate() {
            let DeValue::Table(t) = e.get_ref() else {
                continue;
            };
            let name = match t.get("name").map(|n| n.get_ref()) {
                Some(DeValue::String(s)) => format!("{kind} \"{s}\""),
                _ => format!("{kind} #{}", i + 1),
            };
            let item = Table::new(src, name, e.span(), t);
            run.item(&item, kind, dynamic)?;
        }
    }
    if run.edits.is_empty() {
        return Ok(run.out);
    }
    let mut edits = run.edits;
    edits.sort_by_key(|(r, _)| std::cmp::Reverse(r.start));
    let mut out = text.to_owned();
    for (range, with) in edits {
        out.replace_range(range, &with);
    }
    run.out.text = out;
    Ok(run.out)
}

/// Reads the scene at `path` (UTF-8, checked) and resolves it relative to its directory.
pub fn resolve_file(path: &Path) -> Result<Resolved, SceneError> {
    let file = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|e| SceneError {
        file: file.clone(),
        line: None,
        item: None,
        field: None,
        message: format!("cannot read the scene: {e}"),
    })?;
    let text = mwb_core::scene::decode_utf8(&file, bytes)?;
    resolve(&file, &text, path.parent().unwrap_or(Path::new(".")))
}

struct Run<'d> {
    base_dir: &'d Path,
    edits: Vec<(Range<usize>, String)>,
    /// `part = …` text of each (file, placement, params) already resolved in this scene.
    done: HashMap<String, String>,
    out: Resolved,
}

impl Run<'_> {
    fn item(&mut self, item: &Table<'_>, kind: &str, dynamic: bool) -> Result<(), SceneError> {
        if let Some(DeValue::Array(parts)) = item.get("part").map(|p| p.get_ref()) {
            for (i, p) in parts.iter().enumerate() {
                if let DeValue::Table(pt) = p.get_ref()
                    && let Some(s) = pt.get("shape")
                    && matches!(s.get_ref(), DeValue::String(x) if x.as_ref() == "mesh")
                {
                    return Err(item.err(
                        &format!("part[{i}].shape"),
                        s.span(),
                        format!("a mesh cannot be a part of a compound: give it its own [[{kind}]] (a dynamic mesh already becomes a compound of convex pieces)"),
                    ));
                }
            }
        }
        let Some((shape, shape_span)) = item.string("shape")? else {
            return Ok(());
        };
        if shape != "mesh" {
            return Ok(());
        }
        if let Some((key, span)) = item
            .table
            .iter()
            .filter(|(k, _)| OTHER_SHAPE_KEYS.contains(&k.get_ref().as_ref()))
            .map(|(k, _)| (k.get_ref().as_ref(), k.span()))
            .min_by_key(|(_, s)| s.start)
        {
            return Err(item.err(
                key,
                span,
                format!(
                    "does not apply to shape \"mesh\" (it takes {})",
                    MESH_KEYS.join(", ")
                ),
            ));
        }
        let (file_arg, file_span) = item.string("file")?.ok_or_else(|| {
            item.missing("file", "the mesh file, relative to the scene: `file = \"props/x.obj\"` (or \"props/set.glb#node\")")
        })?;
        let scale = match item.get("scale") {
            None => 1.0,
            Some(v) => match item.number("scale", v)? {
                Some(x) if x.is_finite() && x > 0.0 && x <= mwb_core::scene::LIMIT => x,
                _ => return Err(item.err("scale", v.span(), "must be a number > 0")),
            },
        };
        let up = match item.string("up")? {
            None | Some(("y", _)) => UpAxis::Y,
            Some(("z", _)) => UpAxis::Z,
            Some((other, span)) => {
                return Err(item.err(
                    "up",
                    span,
                    format!("unknown up axis \"{other}\": \"y\" (the default) or \"z\""),
                ));
            }
        };
        let params = match item.get("decomposition") {
            None => Params::default(),
            Some(v) if !dynamic => {
                return Err(item.err(
                    "decomposition",
                    v.span(),
                    "applies to [[body]] meshes only: a static mesh is used whole, as a triangle mesh",
                ));
            }
            Some(v) => self.params(item, v)?,
        };

        let (path_part, node) = match file_arg.split_once('#') {
            Some((p, n)) => (p, Some(n)),
            None => (file_arg, None),
        };
        let up_name = if up == UpAxis::Z { "z" } else { "y" };
        let placement = format!("scale {scale:?}, up {up_name}");
        let memo = format!(
            "{file_arg}|{placement}|{}|{dynamic}",
            if dynamic {
                params.describe()
            } else {
                String::new()
            }
        );
        let part_line = match self.done.get(&memo) {
            Some(line) => line.clone(),
            None => {
                let at = |e: MeshError| item.err("file", file_span.clone(), e.to_string());
                let path = self.base_dir.join(path_part);
                let bytes = std::fs::read(&path).map_err(|e| {
                    at(MeshError::Read {
                        file: path_part.to_owned(),
                        error: e.to_string(),
                    })
                })?;
                let hash = content_hash(&bytes);
                let mesh = read_mesh(path_part, &bytes, node)
                    .map_err(at)?
                    .to_scene_axes(scale, up);
                let (line, pieces) = if dynamic {
                    let solid = mesh.check_solid(path_part).map_err(at)?;
                    let key = decompose::cache_key(hash, &placement, &params);
                    let cache = decompose::cache_path(&path, key);
                    let d = match std::fs::read(&cache)
                        .ok()
                        .and_then(|b| Decomposition::from_cache(&b, key))
                    {
                        Some(d) => {
                            self.out.from_cache += 1;
                            d
                        }
                        None => {
                            if cache.exists() {
                                tracing::warn!(cache = %cache.display(), "ignoring a damaged or stale decomposition cache; decomposing again");
                            }
                            let d = decompose::decompose(path_part, &solid, &params).map_err(at)?;
                            self.out.decomposed += 1;
                            write_cache(&cache, &d.to_cache(key));
                            d
                        }
                    };
                    (convex_parts(&d), Some(d.pieces.len()))
                } else {
                    let mesh = mesh.check_static(path_part).map_err(at)?;
                    (trimesh_part(&mesh), None)
                };
                self.out.meshes.push(MeshSource {
                    file: file_arg.to_owned(),
                    hash,
                    pieces,
                });
                let what = match pieces {
                    Some(n) => format!("{n} convex pieces ({})", params.describe()),
                    None => "triangle mesh".to_owned(),
                };
                let line = format!(
                    "{line}  # mesh \"{file_arg}\" (content hash {hash:016x}, {placement}): {what}"
                );
                self.done.insert(memo, line.clone());
                line
            }
        };
        self.edits.push((shape_span, "\"compound\"".to_owned()));
        self.edits.push((key_value_span(item, "file"), part_line));
        for key in ["scale", "up", "decomposition"] {
            if item.get(key).is_some() {
                let span = key_value_span(item, key);
                let original = &item.src.text[span.clone()];
                self.edits
                    .push((span, format!("# {original}  (applied by mesh resolution)")));
            }
        }
        Ok(())
    }

    fn params(&self, item: &Table<'_>, v: &Value<'_>) -> Result<Params, SceneError> {
        let DeValue::Table(t) = v.get_ref() else {
            return Err(item.err(
                "decomposition",
                v.span(),
                "expected an inline table `{ resolution = 64, concavity = 0.01, max_pieces = 32 }`",
            ));
        };
        // The key's line is replaced by a comment: a `[body.decomposition]` header table spans
        // lines we would have to find and remove, so only the inline form is accepted.
        if !item.src.text[v.span()].trim_start().starts_with('{') {
            return Err(item.err(
                "decomposition",
                v.span(),
                "write it inline: `decomposition = { resolution = 64, concavity = 0.01 }`",
            ));
        }
        let sub = Table {
            src: item.src,
            label: item.label.clone(),
            prefix: "decomposition.".to_owned(),
            span: v.span(),
            table: t,
        };
        if let Some((key, span)) = sub.unknown_key(&["resolution", "concavity", "max_pieces"]) {
            return Err(sub.err(
                key,
                span,
                "unknown field (decomposition takes resolution, concavity, max_pieces)",
            ));
        }
        let d = Params::default();
        let int = |key: &str, (lo, hi): (u32, u32), default: u32| -> Result<u32, SceneError> {
            match sub.get(key) {
                None => Ok(default),
                Some(v) => match (v.get_ref(), sub.number(key, v)?) {
                    (DeValue::Integer(_), Some(x)) if x >= f64::from(lo) && x <= f64::from(hi) => {
                        Ok(x as u32)
                    }
                    _ => Err(sub.err(key, v.span(), format!("must be an integer in [{lo}, {hi}]"))),
                },
            }
        };
        let concavity = match sub.get("concavity") {
            None => d.concavity,
            Some(v) => match sub.number("concavity", v)? {
                Some(x) if x.is_finite() && x > 0.0 && x <= 1.0 => x,
                _ => return Err(sub.err("concavity", v.span(), "must be in (0, 1]")),
            },
        };
        Ok(Params {
            resolution: int("resolution", Params::RESOLUTION, d.resolution)?,
            concavity,
            max_pieces: int("max_pieces", Params::MAX_PIECES, d.max_pieces)?,
        })
    }
}

/// The mesh in a file, by its extension.
fn read_mesh(file: &str, bytes: &[u8], node: Option<&str>) -> Result<Mesh, MeshError> {
    let ext = Path::new(file)
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase());
    match ext.as_deref() {
        Some("obj") if node.is_none() => obj::parse(file, bytes),
        Some("obj") => Err(MeshError::bad(
            file,
            "an OBJ file has no nodes: drop the `#…`",
        )),
        Some("glb") => glb::parse(file, bytes, node),
        Some("gltf") => Err(MeshError::bad(
            file,
            "a .gltf file keeps its data in other files: export a single binary .glb",
        )),
        _ => Err(MeshError::bad(
            file,
            "unknown mesh format: expected an .obj or a .glb file",
        )),
    }
}

/// From the start of `key` to the end of its value: the whole `key = value`.
fn key_value_span(item: &Table<'_>, key: &str) -> Range<usize> {
    item.table
        .iter()
        .find(|(k, _)| k.get_ref().as_ref() == key)
        .map_or(0..0, |(k, v)| k.span().start..v.span().end)
}

/// A cache that cannot be written costs only time: the next resolution decomposes again.
fn write_cache(path: &PathBuf, text: &str) {
    let written = path
        .parent()
        .map_or(Ok(()), std::fs::create_dir_all)
        .and_then(|()| {
            // Written aside and renamed, so a reader never sees half a file.
            let tmp = path.with_extension("hulls.tmp");
            std::fs::write(&tmp, text)?;
            std::fs::rename(&tmp, path)
        });
    if let Err(e) = written {
        tracing::warn!(cache = %path.display(), error = %e, "cannot write the decomposition cache (the next submission decomposes again)");
    }
}

fn point(s: &mut String, p: [f64; 3]) {
    // `{:?}` prints the shortest text that reads back as the same f64, always as a TOML float
    // (`1.0`, `1e-7`), so the resolved scene holds exactly the numbers computed here.
    let _ = write!(s, "[{:?}, {:?}, {:?}]", p[0], p[1], p[2]);
}

fn convex_parts(d: &Decomposition) -> String {
    let mut s = String::from("part = [");
    for (i, piece) in d.pieces.iter().enumerate() {
        s.push_str(if i == 0 { "{ " } else { ", { " });
        s.push_str("shape = \"convex\", points = [");
        for (j, p) in piece.iter().enumerate() {
            if j > 0 {
                s.push_str(", ");
            }
            point(&mut s, p.map(f64::from));
        }
        s.push_str("] }");
    }
    s.push(']');
    s
}

fn trimesh_part(mesh: &Mesh) -> String {
    let mut s = String::from("part = [{ shape = \"trimesh\", vertices = [");
    for (j, p) in mesh.vertices.iter().enumerate() {
        if j > 0 {
            s.push_str(", ");
        }
        point(&mut s, *p);
    }
    s.push_str("], indices = [");
    for (j, t) in mesh.triangles.iter().enumerate() {
        if j > 0 {
            s.push_str(", ");
        }
        let _ = write!(s, "[{}, {}, {}]", t[0], t[1], t[2]);
    }
    s.push_str("] }]");
    s
}
