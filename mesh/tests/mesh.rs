//! Mesh import end to end: OBJ and glTF binary parsing, every refusal naming the file and the
//! problem, decomposition determinism, the cache, and a resolved scene that samples the same
//! world twice.

use std::ops::ControlFlow;
use std::path::{Path, PathBuf};

use mwb_core::scene::{SceneTemplate, Shape};
use mwb_mesh::decompose::{self, Decomposition, Params};
use mwb_mesh::{MeshError, glb, obj, resolve};
use parry3d::math::Vector;
use parry3d::query::PointQuery;
use parry3d::shape::ConvexPolyhedron;

/// A closed box 2 × 1 × 1 written with quads (fan-triangulated), counter-clockwise outside,
/// with negative indices on the last face.
const BOX_OBJ: &str = "\
# box
v 0 0 0\nv 2 0 0\nv 2 1 0\nv 0 1 0\nv 0 0 1\nv 2 0 1\nv 2 1 1\nv 0 1 1
vt 0 0\nvn 0 0 1\nusemtl wood\ns off
f 1 4 3 2\nf 5 6 7 8\nf 1 2 6 5\nf 2/1 3/1 7/1 6/1\nf 3//1 4//1 8//1 7//1\nf -8 -4 -1 -5
";

/// An L-shaped closed prism (concave: its hull would fill the corner), cells of 1 × 1, 1 deep.
fn l_prism() -> String {
    // Outline counter-clockwise seen from +z: (0,0) (2,0) (2,1) (1,1) (1,2) (0,2).
    let outline = [
        [0.0, 0.0],
        [2.0, 0.0],
        [2.0, 1.0],
        [1.0, 1.0],
        [1.0, 2.0],
        [0.0, 2.0],
    ];
    let mut s = String::new();
    for z in [0.0, 1.0] {
        for [x, y] in outline {
            s.push_str(&format!("v {x} {y} {z}\n"));
        }
    }
    // Caps: the L split into two convex quads, back (z=0) reversed.
    s.push_str("f 1 3 2\nf 1 4 3\nf 1 6 5\nf 1 5 4\n"); // back, clockwise from +z
    s.push_str("f 7 8 9\nf 7 9 10\nf 7 10 11\nf 7 11 12\n"); // front
    for i in 0..6 {
        let (a, b) = (i + 1, (i + 1) % 6 + 1);
        s.push_str(&format!("f {a} {b} {} {}\n", b + 6, a + 6));
    }
    s
}

/// The L prism's decomposition at [`low`] parameters: piece count and digest of the bits.
const GOLDEN_PIECES: usize = 14;
const GOLDEN_DIGEST: &str = "8fdee721628e1a7e";

fn low() -> Params {
    Params {
        resolution: 16,
        ..Params::default()
    }
}

#[test]
fn obj_quads_negative_indices_and_ignored_records() {
    let m = obj::parse("box.obj", BOX_OBJ.as_bytes()).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(m.vertices.len(), 8);
    assert_eq!(m.triangles.len(), 12, "six quads, two triangles each");
    // `f -8 -4 -1 -5` is `f 1 5 8 4`, fanned from its first corner.
    assert_eq!(&m.triangles[10..], &[[0, 4, 7], [0, 7, 3]]);
    let solid = m.check_solid("box.obj").unwrap_or_else(|e| panic!("{e}"));
    assert!((solid.volume - 2.0).abs() < 1e-12, "{}", solid.volume);
}

#[test]
fn scale_and_z_up_turn_the_mesh_into_scene_axes() {
    let m = obj::parse("box.obj", BOX_OBJ.as_bytes()).unwrap_or_else(|e| panic!("{e}"));
    let m = m.to_scene_axes(0.5, mwb_mesh::check::UpAxis::Z);
    // (2, 1, 1) in a z-up file is x = 2, up = 1, towards the viewer = −1 in y-up axes.
    assert_eq!(m.vertices[6], [1.0, 0.5, -0.5]);
    let solid = m.check_solid("box.obj").unwrap_or_else(|e| panic!("{e}"));
    assert!(
        (solid.volume - 0.25).abs() < 1e-12,
        "a rotation keeps the sign"
    );
}

/// A .glb written by hand: one node "tet" with a tetrahedron (u16 indices), one node "other".
fn tetra_glb() -> Vec<u8> {
    let positions: [[f32; 3]; 4] = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
    ];
    let indices: [u16; 12] = [0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3];
    let mut bin = Vec::new();
    for p in positions {
        for c in p {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    for i in indices {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0,1]}}],
"nodes":[{{"name":"tet","mesh":0,"translation":[0,2,0]}},{{"name":"other","mesh":0}}],
"meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1}}]}}],
"buffers":[{{"byteLength":{}}}],
"bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":48}},{{"buffer":0,"byteOffset":48,"byteLength":24}}],
"accessors":[{{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":[0,0,0],"max":[1,1,1]}},
{{"bufferView":1,"componentType":5123,"count":12,"type":"SCALAR"}}]}}"#,
        bin.len()
    );
    let mut json = json.into_bytes();
    while json.len() % 4 != 0 {
        json.push(b' ');
    }
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let mut out = Vec::new();
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin);
    out
}

#[test]
fn glb_node_by_name_with_its_transform() {
    let bytes = tetra_glb();
    let m = glb::parse("set.glb", &bytes, Some("tet")).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(m.triangles.len(), 4);
    assert_eq!(
        m.vertices[2],
        [0.0, 3.0, 0.0],
        "translated by the node's transform"
    );
    let solid = m.check_solid("set.glb").unwrap_or_else(|e| panic!("{e}"));
    assert!((solid.volume - 1.0 / 6.0).abs() < 1e-7);
    let e = glb::parse("set.glb", &bytes, None)
        .expect_err("two nodes")
        .to_string();
    assert!(
        e.starts_with("set.glb: several nodes") && e.contains("\"tet\""),
        "{e}"
    );
    let e = glb::parse("set.glb", &bytes, Some("chair"))
        .expect_err("no such node")
        .to_string();
    assert!(e.contains("no node \"chair\""), "{e}");
    let e = glb::parse("set.glb", b"garbage", None)
        .expect_err("not glTF")
        .to_string();
    assert!(e.starts_with("set.glb: not a valid glTF binary"), "{e}");
}

fn bad(file: &str, text: &str, dynamic: bool) -> String {
    let r = obj::parse(file, text.as_bytes()).and_then(|m| {
        if dynamic {
            m.check_solid(file).map(|s| s.mesh)
        } else {
            m.check_static(file)
        }
    });
    match r {
        Ok(_) => panic!("{file} was accepted"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn every_bad_mesh_is_refused_naming_the_file_and_the_problem() {
    let cases: Vec<(String, bool, &str)> = vec![
        (
            "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n".into(),
            false,
            "nan.obj:2: vertex 2 is not finite",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n".into(),
            false,
            "range.obj:4: face corner 4 out of range",
        ),
        ("v 0 0 0\nv 1 0 0\n".into(), false, "nofaces.obj: no faces"),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n".into(),
            true,
            "open.obj: 1 triangles cannot enclose",
        ),
        (
            BOX_OBJ.replace("f 1 4 3 2\n", ""),
            true,
            "open2.obj: open mesh: the edge",
        ),
        // The box with its bottom face also wound outward-in: two triangles face the same way.
        (
            BOX_OBJ.replace("f 1 4 3 2", "f 1 2 3 4"),
            true,
            "wound.obj: inconsistently wound",
        ),
        // Every face reversed: closed and consistent, but inside out.
        (
            reverse_faces(BOX_OBJ),
            true,
            "inverted.obj: inverted normals",
        ),
        // A tetrahedron whose corners all lie in one plane: closed, manifold, flat.
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n".into(),
            true,
            "flat.obj: zero volume",
        ),
        // Three triangles on one edge.
        (
            format!("{BOX_OBJ}v 1 -1 0\nf 1 2 9\n"),
            true,
            "fin.obj: non-manifold: the edge",
        ),
    ];
    let names = [
        "nan.obj",
        "range.obj",
        "nofaces.obj",
        "open.obj",
        "open2.obj",
        "wound.obj",
        "inverted.obj",
        "flat.obj",
        "fin.obj",
    ];
    for ((text, dynamic, want), file) in cases.iter().zip(names) {
        let e = bad(file, text, *dynamic);
        assert!(e.starts_with(want), "{file}: got {e:?}, want {want:?}");
    }
    // Too many triangles: refused while reading, before they are all in memory.
    let mut big = String::from("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n");
    let face =
        "f 1 2 3 4 1 2 3 4 1 2 3 4 1 2 3 4 1 2 3 4 1 2 3 4 1 2 3 4 1 2 3 4 1 2 3 4 1 2 3 4\n";
    for _ in 0..(mwb_mesh::MAX_TRIANGLES / 38 + 1) {
        big.push_str(face);
    }
    let e = bad("huge.obj", &big, false);
    assert!(
        e.contains("huge.obj:") && e.contains("more than 1000000 triangles"),
        "{e}"
    );
}

fn reverse_faces(obj: &str) -> String {
    obj.lines()
        .map(|l| match l.strip_prefix("f ") {
            Some(rest) => format!("f {}", rest.split(' ').rev().collect::<Vec<_>>().join(" ")),
            None => l.to_owned(),
        })
        .collect::<Vec<_>>()
        .join("\n")
}

fn bits(d: &Decomposition) -> Vec<Vec<[u32; 3]>> {
    d.pieces
        .iter()
        .map(|p| p.iter().map(|v| v.map(f32::to_bits)).collect())
        .collect()
}

#[test]
fn decomposition_is_deterministic_and_keeps_the_concave_corner() {
    let solid = obj::parse("l.obj", l_prism().as_bytes())
        .and_then(|m| m.check_solid("l.obj"))
        .unwrap_or_else(|e| panic!("{e}"));
    assert!((solid.volume - 3.0).abs() < 1e-12);
    let a = decompose::decompose("l.obj", &solid, &low()).unwrap_or_else(|e| panic!("{e}"));
    let b = decompose::decompose("l.obj", &solid, &low()).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(
        bits(&a),
        bits(&b),
        "same mesh, same parameters: same pieces, bit for bit"
    );
    assert!(
        a.pieces.len() >= 2,
        "an L is not convex: {} pieces",
        a.pieces.len()
    );
    // Golden values, so a change in parry's VHACD (or in how we call it) is seen, not just a
    // run that disagrees with itself. Re-mint from the failure message after checking the new
    // pieces (and bump decompose's CACHE_VERSION, as old caches then hold other pieces).
    let digest = mwb_mesh::content_hash(format!("{:?}", bits(&a)).as_bytes());
    assert_eq!(
        (a.pieces.len(), format!("{digest:016x}")),
        (GOLDEN_PIECES, GOLDEN_DIGEST.to_owned()),
        "the L's decomposition at resolution 16 changed"
    );
    // No piece reaches far into the empty corner (around (1.5, 1.5)).
    for p in &a.pieces {
        let fills_corner = p.iter().any(|v| v[0] > 1.2) && p.iter().any(|v| v[1] > 1.2);
        assert!(!fills_corner, "a piece spans the concave corner: {p:?}");
    }
    // The cache text reads back to the same bits; any damage is refused.
    let text = a.to_cache(7);
    let back = Decomposition::from_cache(text.as_bytes(), 7).expect("round trip");
    assert_eq!(bits(&back), bits(&a));
    assert!(
        Decomposition::from_cache(text.as_bytes(), 8).is_none(),
        "another key"
    );
    let damaged = text.replacen('1', "2", 1);
    assert!(
        Decomposition::from_cache(damaged.as_bytes(), 7).is_none(),
        "CRC"
    );
    assert!(
        Decomposition::from_cache(&text.as_bytes()[..text.len() / 2], 7).is_none(),
        "cut"
    );
}

/// A scene directory with `props/l.obj` and a scene using it as a body and as a static.
fn scene_dir() -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let props = dir.path().join("props");
    std::fs::create_dir_all(&props).unwrap_or_else(|e| panic!("{e}"));
    std::fs::write(props.join("l.obj"), l_prism()).unwrap_or_else(|e| panic!("{e}"));
    let scene = dir.path().join("s.toml");
    std::fs::write(
        &scene,
        r#"name = "l"

[[material]]
name = "wood"

[[static]]
name = "floor"
shape = "mesh"
file = "props/l.obj"
material = "wood"
rotation_deg = [-90, 0, 0]

[[body]]
name = "l"
shape = "mesh"
file = "props/l.obj"
scale = 0.1
material = "wood"
position = [0, 1, 0]
decomposition = { resolution = 16 }
"#,
    )
    .unwrap_or_else(|e| panic!("{e}"));
    (dir, scene)
}

#[test]
fn resolved_scene_is_self_contained_and_the_cache_spares_the_second_decomposition() {
    let (dir, scene) = scene_dir();
    let first = mwb_mesh::resolve_file(&scene).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((first.decomposed, first.from_cache), (1, 0));
    let caches: Vec<PathBuf> = std::fs::read_dir(dir.path().join("props/.mwb-cache"))
        .unwrap_or_else(|e| panic!("{e}"))
        .map(|e| e.map(|e| e.path()).unwrap_or_else(|e| panic!("{e}")))
        .collect();
    assert_eq!(caches.len(), 1, "{caches:?}");
    // The text parses with no files around, line for line with the author's file.
    let t = SceneTemplate::parse(&first.text, "s.toml").unwrap_or_else(|e| panic!("{e}"));
    let world = t.instantiate(0);
    assert!(
        matches!(&world.statics[0].shape, Shape::Compound { parts } if matches!(parts[0].shape, Shape::TriMesh { .. }))
    );
    let Shape::Compound { parts } = &world.bodies[0].shape else {
        panic!("a compound")
    };
    assert!(
        parts.len() >= 2
            && parts
                .iter()
                .all(|p| matches!(p.shape, Shape::ConvexHull { .. }))
    );
    let original = std::fs::read_to_string(&scene).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(first.text.lines().count(), original.lines().count());
    assert!(
        first.text.contains("# mesh \"props/l.obj\" (content hash "),
        "{}",
        first.text
    );

    // Second time: from the cache, the same text.
    let second = mwb_mesh::resolve_file(&scene).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((second.decomposed, second.from_cache), (0, 1));
    assert_eq!(second.text, first.text);

    // A corrupted cache is ignored and rebuilt, giving the same text again.
    std::fs::write(&caches[0], "mwb-hulls 1 garbage").unwrap_or_else(|e| panic!("{e}"));
    let third = mwb_mesh::resolve_file(&scene).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((third.decomposed, third.from_cache), (1, 0));
    assert_eq!(third.text, first.text);
    let rebuilt = std::fs::read(&caches[0]).unwrap_or_else(|e| panic!("{e}"));
    assert!(rebuilt.starts_with(b"mwb-hulls 1 "));
}

#[test]
fn an_unwritable_cache_is_not_an_error() {
    let (dir, scene) = scene_dir();
    // A file where the cache directory would go.
    std::fs::write(dir.path().join("props/.mwb-cache"), "not a directory")
        .unwrap_or_else(|e| panic!("{e}"));
    let r = mwb_mesh::resolve_file(&scene).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(r.decomposed, 1);
    let again = mwb_mesh::resolve_file(&scene).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((again.decomposed, again.text), (1, r.text));
}

#[test]
fn scene_errors_name_the_scene_line_the_body_and_the_mesh_file() {
    let (dir, scene) = scene_dir();
    let text = std::fs::read_to_string(&scene).unwrap_or_else(|e| panic!("{e}"));
    let check = |text: &str, want: &str| {
        let e = resolve("s.toml", text, dir.path())
            .expect_err(want)
            .to_string();
        assert!(e.contains(want), "got {e:?}, want {want:?}");
    };
    check(
        &text.replace("props/l.obj\"\nscale", "props/missing.obj\"\nscale"),
        "s.toml:16: body \"l\": field `file`: props/missing.obj: cannot read the mesh file",
    );
    check(
        &text.replace("scale = 0.1", "scale = -1"),
        "s.toml:17: body \"l\": field `scale`: must be a number > 0",
    );
    check(
        &text.replace("resolution = 16", "resolution = 4"),
        "field `decomposition.resolution`: must be an integer in [8, 256]",
    );
    check(
        &text.replace(
            "rotation_deg = [-90, 0, 0]",
            "decomposition = { resolution = 16 }",
        ),
        "static \"floor\": field `decomposition`: applies to [[body]] meshes only",
    );
    check(
        &text.replace("scale = 0.1", "radius = 1"),
        "field `radius`: does not apply to shape \"mesh\"",
    );
    std::fs::write(
        dir.path().join("props/open.obj"),
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\n",
    )
    .unwrap_or_else(|e| panic!("{e}"));
    check(
        &text.replace("props/l.obj\"\nscale", "props/open.obj\"\nscale"),
        "s.toml:16: body \"l\": field `file`: props/open.obj: 3 triangles cannot enclose a volume",
    );
    std::fs::write(dir.path().join("props/l.stl"), "solid l\n").unwrap_or_else(|e| panic!("{e}"));
    check(
        &text.replace("props/l.obj\"\nscale", "props/l.stl\"\nscale"),
        "props/l.stl: unknown mesh format",
    );
    // An unresolved mesh reaching the pure parser is refused by name, not as an unknown shape.
    let e = SceneTemplate::parse(&text, "s.toml")
        .expect_err("unresolved")
        .to_string();
    assert!(
        e.contains("s.toml:8: static \"floor\": field `shape`: a mesh is read"),
        "{e}"
    );
}

/// The resolved geometry of a scene text (its `part = …` lines), without the author's comments.
fn parts_lines(text: &str) -> String {
    text.lines()
        .filter(|l| l.starts_with("part = "))
        .collect::<Vec<_>>()
        .join("\n")
}

fn letters() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/letters.toml")
}

#[test]
fn shipped_letters_resolve_and_sample_the_same_bytes_twice() {
    // Resolved in a copy of scenes/ so the test neither needs nor leaves a cache in the repo.
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let src = letters();
    let props = dir.path().join("props");
    std::fs::create_dir_all(&props).unwrap_or_else(|e| panic!("{e}"));
    for l in ["m", "w", "b"] {
        let name = format!("letter_{l}.obj");
        let from = src.with_file_name("props").join(&name);
        std::fs::copy(&from, props.join(&name))
            .unwrap_or_else(|e| panic!("{}: {e}", from.display()));
    }
    let scene = dir.path().join("letters.toml");
    std::fs::copy(&src, &scene).unwrap_or_else(|e| panic!("{e}"));
    let r = mwb_mesh::resolve_file(&scene).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(r.meshes.len(), 3);
    let t = SceneTemplate::parse(&r.text, "letters.toml").unwrap_or_else(|e| panic!("{e}"));
    let b = &t.instantiate(0).bodies[2];
    let Shape::Compound { parts } = &b.shape else {
        panic!("B is a compound")
    };
    assert!(
        parts.len() >= 4,
        "a B with two holes needs several pieces, got {}",
        parts.len()
    );
    // Both counters of the B stay empty (its single convex hull would fill them): the centres
    // of its two holes (props/make_letters.py: cells of 0.08 m, the glyph centred) are inside
    // no piece.
    for hole in [[-0.04, 0.08, 0.0], [0.0, -0.08, 0.0]] {
        for (i, part) in parts.iter().enumerate() {
            let Shape::ConvexHull { points } = &part.shape else {
                panic!("convex pieces")
            };
            let pts: Vec<Vector> = points
                .iter()
                .map(|p| Vector::new(p[0] as f32, p[1] as f32, p[2] as f32))
                .collect();
            let hull = ConvexPolyhedron::from_convex_hull(&pts).expect("a hull");
            assert!(
                !hull.contains_local_point(Vector::new(hole[0], hole[1], hole[2])),
                "piece {i} of the B fills its hole at {hole:?}: {points:?}"
            );
        }
    }
    let sample = || {
        let mut bytes = Vec::new();
        mwb_sampler::run_world(&t, 3, mwb_sampler::RunOptions::default(), &mut |seg| {
            bytes.extend_from_slice(&seg.payload);
            ControlFlow::Continue(())
        })
        .unwrap_or_else(|e| panic!("{e}"));
        bytes
    };
    let first = sample();
    assert!(!first.is_empty());
    assert_eq!(first, sample(), "same resolved scene and seed: same bytes");
    // Golden: the resolved text and the world's bytes, so a change anywhere from the OBJ reader
    // to the sampler shows here. Re-mint from the failure message after checking why it moved.
    // Re-minted for issue 23: Standard's encoder searches adaptively (`mwb_codec::Search`), the
    // same simulated world encoded in 19 bytes more (783 → 802).
    let golden = (
        format!(
            "{:016x}",
            mwb_mesh::content_hash(parts_lines(&r.text).as_bytes())
        ),
        first.len(),
        format!("{:016x}", mwb_mesh::content_hash(&first)),
    );
    let want = ("38a8c5f0aa0cf2c2", 802, "f50dae82d24b3ac7");
    assert_eq!(
        (golden.0.as_str(), golden.1, golden.2.as_str()),
        want,
        "letters changed: (pieces digest, world bytes, world digest)"
    );
}

#[test]
fn mesh_errors_display_the_file() {
    let e = MeshError::Bad {
        file: "a.obj".into(),
        line: Some(3),
        problem: "x".into(),
    };
    assert_eq!(e.to_string(), "a.obj:3: x");
}

#[test]
fn the_mesh_example_of_the_format_reference_resolves() {
    let doc = include_str!("../../docs/scene-format.md");
    let block = doc
        .split("```toml\n")
        .map(|b| b.split("```").next().unwrap_or_default())
        .find(|b| b.contains("shape = \"mesh\""))
        .expect("docs/scene-format.md has a mesh example");
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let props = dir.path().join("props");
    std::fs::create_dir_all(&props).unwrap_or_else(|e| panic!("{e}"));
    let b = letters().with_file_name("props").join("letter_b.obj");
    std::fs::copy(&b, props.join("letter_b.obj")).unwrap_or_else(|e| panic!("{e}"));
    std::fs::write(props.join("tray.obj"), BOX_OBJ).unwrap_or_else(|e| panic!("{e}"));
    let text = format!(
        "name = \"doc\"\n[[material]]\nname = \"wood\"\n[[material]]\nname = \"plastic\"\n{block}"
    );
    let r = resolve("doc.toml", &text, dir.path()).unwrap_or_else(|e| panic!("{e}"));
    let t = SceneTemplate::parse(&r.text, "doc.toml").unwrap_or_else(|e| panic!("{e}\n{}", r.text));
    assert_eq!((t.body_count(), r.meshes.len()), (1, 2));
}
