//! The glTF export read back with the `gltf` crate (nodes, names, meshes, the animation and its
//! every key against the decoded motion), and checked by the Khronos glTF validator.

mod common;

use common::{World, compound, shapes, tumble};
use gltf::animation::Property;
use gltf::animation::util::ReadOutputs;
use std::path::{Path, PathBuf};
use std::process::Command;

fn parse(bytes: &[u8]) -> gltf::Gltf {
    gltf::Gltf::from_slice(bytes).unwrap_or_else(|e| panic!("glb does not parse: {e}"))
}

/// Everything the export promises, for one world.
fn check_world(w: &World, index: Option<u32>) -> Vec<u8> {
    let export = w.export(index);
    let bytes = mwb_export::glb::write(&export).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(&bytes[..4], b"glTF");
    assert_eq!(bytes.len() % 4, 0);
    let doc = parse(&bytes);
    let blob = doc.blob.clone().unwrap_or_else(|| panic!("no BIN chunk"));
    let scene = &w.scene;
    let frames = w.motion.frame_count();
    assert!(frames > 100, "{frames} frames");

    // One root node named after the world; a node per static and per body, in scene order.
    let nodes: Vec<gltf::Node> = doc.nodes().collect();
    assert_eq!(nodes.len(), 1 + scene.statics.len() + scene.bodies.len());
    let root = doc
        .default_scene()
        .unwrap_or_else(|| panic!("no default scene"))
        .nodes()
        .next()
        .unwrap_or_else(|| panic!("empty scene"));
    assert_eq!(root.name(), Some(export.label().as_str()));
    let children: Vec<gltf::Node> = root.children().collect();
    let names: Vec<&str> = children.iter().filter_map(|n| n.name()).collect();
    let expected: Vec<&str> = scene
        .statics
        .iter()
        .map(|s| s.name.as_str())
        .chain(scene.bodies.iter().map(|b| b.name.as_str()))
        .collect();
    assert_eq!(names, expected);
    let body_nodes = &children[scene.statics.len()..];
    // Every node has a mesh whose POSITION bounds are the true bounds of its f32 positions.
    for n in &children {
        let mesh = n
            .mesh()
            .unwrap_or_else(|| panic!("{:?}: no mesh", n.name()));
        assert_eq!(mesh.name(), n.name());
        for p in mesh.primitives() {
            let reader = p.reader(|_| Some(&blob));
            let positions: Vec<[f32; 3]> = reader
                .read_positions()
                .unwrap_or_else(|| panic!("no positions"))
                .collect();
            let normals = reader.read_normals().map_or(0, Iterator::count);
            assert_eq!(normals, positions.len());
            let bb = p.bounding_box();
            for k in 0..3 {
                let lo = positions.iter().map(|v| v[k]).fold(f32::INFINITY, f32::min);
                let hi = positions
                    .iter()
                    .map(|v| v[k])
                    .fold(f32::NEG_INFINITY, f32::max);
                assert_eq!((bb.min[k], bb.max[k]), (lo, hi));
            }
            assert!(p.material().name().is_some());
        }
    }

    // One animation: per body a translation and a rotation channel, a key per frame.
    let anims: Vec<gltf::Animation> = doc.animations().collect();
    assert_eq!(anims.len(), 1);
    let channels: Vec<gltf::animation::Channel> = anims[0].channels().collect();
    assert_eq!(channels.len(), 2 * scene.bodies.len());
    for c in &channels {
        let node = c.target().node().index();
        let body = body_nodes
            .iter()
            .position(|n| n.index() == node)
            .unwrap_or_else(|| panic!("channel targets node {node}, not a body"));
        assert_eq!(
            c.sampler().interpolation(),
            gltf::animation::Interpolation::Linear
        );
        let reader = c.reader(|_| Some(&blob));
        let times: Vec<f32> = reader
            .read_inputs()
            .unwrap_or_else(|| panic!("no key times"))
            .collect();
        assert_eq!(times.len(), frames);
        for (k, t) in times.iter().enumerate() {
            assert_eq!(*t, (k as f64 * w.motion.frame_dt) as f32);
        }
        let track = &w.motion.tracks[body];
        match reader.read_outputs() {
            Some(ReadOutputs::Translations(it)) => {
                assert_eq!(c.target().property(), Property::Translation);
                let got: Vec<[f32; 3]> = it.collect();
                let want: Vec<[f32; 3]> = track
                    .positions
                    .iter()
                    .map(|p| p.map(|x| x as f32))
                    .collect();
                assert_eq!(got, want, "body {body}: translations");
            }
            Some(ReadOutputs::Rotations(r)) => {
                assert_eq!(c.target().property(), Property::Rotation);
                let got: Vec<[f32; 4]> = r.into_f32().collect();
                assert_eq!(got.len(), frames);
                for (k, (g, d)) in got.iter().zip(&track.rotations).enumerate() {
                    // The decoded quaternion to f32, up to the sign the export chose.
                    let same = (0..4).all(|i| (f64::from(g[i]) - d[i]).abs() <= 2e-7);
                    let negated = (0..4).all(|i| (f64::from(g[i]) + d[i]).abs() <= 2e-7);
                    assert!(same || negated, "body {body} frame {k}: {g:?} vs {d:?}");
                    if k > 0 {
                        let p = got[k - 1];
                        let dot: f32 = (0..4).map(|i| p[i] * g[i]).sum();
                        assert!(dot >= 0.0, "body {body} frame {k}: sign flips");
                    }
                }
            }
            _ => panic!("unexpected channel output"),
        }
    }
    // The nodes stand where frame 0 puts them.
    for (body, n) in body_nodes.iter().enumerate() {
        let (t, _, s) = n.transform().decomposed();
        assert_eq!(t, w.motion.tracks[body].positions[0].map(|x| x as f32));
        assert_eq!(s, [1.0; 3]);
    }
    bytes
}

#[test]
fn tumble_glb_holds_every_body_and_every_decoded_pose() {
    let w = tumble(0xfeed);
    check_world(&w, Some(3));
}

#[test]
fn every_shape_exports_and_reads_back() {
    let w = shapes(11);
    let bytes = check_world(&w, None);
    // The rotating bodies really rotate in the file (not a constant track).
    let doc = parse(&bytes);
    let blob = doc.blob.clone().unwrap_or_default();
    let anim = doc
        .animations()
        .next()
        .unwrap_or_else(|| panic!("no animation"));
    let spins = anim
        .channels()
        .filter(|c| c.target().property() == Property::Rotation)
        .filter(|c| match c.reader(|_| Some(&blob)).read_outputs() {
            Some(ReadOutputs::Rotations(r)) => {
                let q: Vec<[f32; 4]> = r.into_f32().collect();
                q.first() != q.last()
            }
            _ => false,
        })
        .count();
    assert_eq!(spins, w.scene.bodies.len());
}

/// A compound is one node (one animated body) whose mesh has a primitive per part, in the
/// part's material, its triangles in the body's frame where the part sits.
#[test]
fn a_compound_exports_every_part_under_one_node() {
    let w = compound(5);
    let bytes = check_world(&w, None);
    let doc = parse(&bytes);
    let blob = doc.blob.clone().unwrap_or_default();
    let node = |name: &str| {
        doc.nodes()
            .find(|n| n.name() == Some(name))
            .unwrap_or_else(|| panic!("no node {name}"))
    };
    let prims = |n: gltf::Node| -> Vec<(String, usize, [f32; 3], [f32; 3])> {
        n.mesh()
            .unwrap_or_else(|| panic!("no mesh"))
            .primitives()
            .map(|p| {
                let count = p
                    .reader(|_| Some(&blob))
                    .read_indices()
                    .map_or(0, |i| i.into_u32().count());
                let bb = p.bounding_box();
                let material = p.material().name().unwrap_or_default().to_owned();
                (material, count / 3, bb.min, bb.max)
            })
            .collect()
    };
    let letter = prims(node("letter_l"));
    assert_eq!(letter.len(), 2, "a primitive per part");
    // The post: a box (12 triangles) of the body's wood, 0.5 m tall from the body's origin.
    assert_eq!((letter[0].0.as_str(), letter[0].1), ("wood", 12));
    assert!(letter[0].2[1].abs() < 1e-6 && (letter[0].3[1] - 0.5).abs() < 1e-6);
    // The foot: a cylinder of its own steel, turned to lie along x, 0.15 ± 0.15 m.
    assert_eq!(letter[1].0, "steel");
    let cylinder = mwb_export::mesh::shape_mesh(
        &mwb_core::scene::Shape::Cylinder {
            half_height: 0.15,
            radius: 0.05,
        },
        1.0,
    )
    .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(letter[1].1, cylinder.triangle_count());
    assert!((letter[1].2[0] - 0.0).abs() < 1e-6 && (letter[1].3[0] - 0.3).abs() < 1e-6);
    assert!((letter[1].3[1] - 0.05).abs() < 1e-6);
    // The compound static: two boxes in the ground's material.
    let shelf = prims(node("shelf"));
    assert_eq!(shelf.len(), 2);
    assert!(shelf.iter().all(|p| p.0 == "ground" && p.1 == 12));
    assert!((shelf[1].2[0] + 0.5).abs() < 1e-6 && (shelf[1].3[0] + 0.4).abs() < 1e-6);
}

#[test]
fn a_motion_that_does_not_fit_the_scene_is_refused() {
    let w = tumble(1);
    let mut motion = w.motion.clone();
    motion.tracks.pop();
    let bad = mwb_export::ExportWorld {
        motion: &motion,
        ..w.export(None)
    };
    let e = mwb_export::glb::write(&bad).unwrap_err().to_string();
    assert!(e.contains("4 bodies") && e.contains("5"), "{e}");
    motion.tracks.push(w.motion.tracks[0].clone());
    motion.tracks[2].positions.pop();
    let bad = mwb_export::ExportWorld {
        motion: &motion,
        ..w.export(None)
    };
    let e = mwb_export::glb::write(&bad).unwrap_err().to_string();
    assert!(e.contains("body 2"), "{e}");
}

/// The validator's directory (`npm ci` there installs it; `.ci/run` does).
fn validator_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tools/gltf-validator")
}

/// Runs the Khronos validator on `bytes`; `None` if node or the validator is missing and CI
/// does not require it (`MWB_REQUIRE_GLTF_VALIDATOR=1`, set by `.ci/run`, turns that into a
/// failure).
fn validate(bytes: &[u8], name: &str) -> Option<serde_json::Value> {
    let dir = validator_dir();
    let installed = dir.join("node_modules/gltf-validator").is_dir();
    let node = Command::new("node")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success());
    if !(installed && node) {
        let required = std::env::var("MWB_REQUIRE_GLTF_VALIDATOR").is_ok_and(|v| v == "1");
        assert!(
            !required,
            "MWB_REQUIRE_GLTF_VALIDATOR=1 but the validator cannot run (node found: {node}, \
             installed in {}: {installed}; run `npm ci` there)",
            dir.display()
        );
        eprintln!("skipping the Khronos glTF validator: node {node}, installed {installed}");
        return None;
    }
    let tmp = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let file = tmp.path().join(name);
    std::fs::write(&file, bytes).unwrap_or_else(|e| panic!("{e}"));
    let out = Command::new("node")
        .arg(dir.join("validate.js"))
        .arg(&file)
        .output()
        .unwrap_or_else(|e| panic!("running node: {e}"));
    assert!(
        out.status.success(),
        "validator failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    Some(serde_json::from_str(text.trim()).unwrap_or_else(|e| panic!("{e}: {text}")))
}

#[test]
fn khronos_validator_reports_no_errors_and_no_warnings() {
    for (name, w, index) in [
        ("tumble.glb", tumble(0xfeed), Some(0)),
        ("shapes.glb", shapes(11), None),
        ("compound.glb", compound(5), None),
    ] {
        let bytes = mwb_export::glb::write(&w.export(index)).unwrap_or_else(|e| panic!("{e}"));
        let Some(report) = validate(&bytes, name) else {
            return;
        };
        assert_eq!(report["errors"], 0, "{name}: {report}");
        assert_eq!(report["warnings"], 0, "{name}: {report}");
    }
}
