//! Tests of the scene format: shipped scenes, determinism, every class of refusal, and
//! property tests of the distribution rules and of `parse` on garbage.

use super::builtin;
use super::model::{BodyRef, JointKind, Shape};
use super::{MAX_INSTANCES, SceneError, SceneTemplate};
use proptest::prelude::*;

fn parse(src: &str) -> Result<SceneTemplate, SceneError> {
    SceneTemplate::parse(src, "test.toml")
}

fn parse_ok(src: &str) -> SceneTemplate {
    match parse(src) {
        Ok(t) => t,
        Err(e) => panic!("expected a valid scene, got: {e}"),
    }
}

// ---------------------------------------------------------------- shipped scenes

#[test]
fn every_shipped_scene_parses_and_instantiates() {
    assert_eq!(builtin::NAMES.len(), 4);
    for name in builtin::NAMES {
        let src = builtin::get(name).unwrap_or_else(|| panic!("builtin {name} missing"));
        let file = format!("scenes/{name}.toml");
        let t = SceneTemplate::parse(src, &file).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(t.name(), *name);
        assert!(!t.description().is_empty(), "{name} has no description");
        assert!(t.has_distributions(), "{name} should randomise something");
        let s = t.instantiate(1);
        assert_eq!(s.bodies.len(), t.body_count());
        assert!(!s.bodies.is_empty());
        // Every shipped scene has the ground plane at y = 0, facing up.
        let ground = s
            .statics
            .iter()
            .find(|b| matches!(b.shape, Shape::Plane { .. }))
            .unwrap_or_else(|| panic!("{name} has no ground plane"));
        assert_eq!(ground.position, [0.0, 0.0, 0.0]);
        assert_eq!(
            ground.shape,
            Shape::Plane {
                normal: [0.0, 1.0, 0.0]
            }
        );
        // Every dynamic body starts above the ground.
        for b in &s.bodies {
            assert!(
                lowest_point(b) > -1e-9,
                "{name}: {} starts below the ground",
                b.name
            );
        }
        assert!(t.settings().end_time >= 6.0 && t.settings().end_time <= 8.0);
    }
    assert_eq!(builtin::get("tower.toml"), Some(builtin::TOWER));
    assert_eq!(builtin::get("nope"), None);
}

/// Height of the lowest point of a body's shape (boxes and hulls exactly, others by their
/// bounding radius).
fn lowest_point(b: &super::Body) -> f64 {
    let corners: Vec<[f64; 3]> = match &b.shape {
        Shape::Box { half_extents: h } => (0..8)
            .map(|i| {
                let s = |bit: i32| if i & bit == 0 { -1.0 } else { 1.0 };
                [s(1) * h[0], s(2) * h[1], s(4) * h[2]]
            })
            .collect(),
        Shape::ConvexHull { points } => points.clone(),
        other => return b.position[1] - other.bounding_radius(),
    };
    corners
        .into_iter()
        .map(|c| b.position[1] + rotate(b.rotation, c)[1])
        .fold(f64::INFINITY, f64::min)
}

#[test]
fn tower_has_192_blocks_and_a_projectile() {
    let t = parse_ok(builtin::TOWER);
    assert_eq!(t.body_count(), 193);
    let s = t.instantiate(7);
    let blocks: Vec<_> = s
        .bodies
        .iter()
        .filter(|b| b.name.starts_with("block["))
        .collect();
    assert_eq!(blocks.len(), 192);
    let idx = s
        .body_index("block[3,1,2]")
        .unwrap_or_else(|| panic!("block[3,1,2] missing"));
    let b = &s.bodies[idx];
    assert!((b.position[0] - (-0.303 + 3.0 * 0.202)).abs() < 1e-12);
    assert!((b.position[1] - 0.3).abs() < 1e-12);
    assert!((b.position[2] - (-0.303 + 2.0 * 0.202)).abs() < 1e-12);
    let ball = &s.bodies[s
        .body_index("projectile")
        .unwrap_or_else(|| panic!("projectile missing"))];
    assert!(matches!(ball.shape, Shape::Box { .. }));
    let speed = ball.linvel.iter().map(|v| v * v).sum::<f64>().sqrt();
    assert!((15.0..=26.0).contains(&speed), "{speed}");
    // The tower is 12 blocks of 0.2 m: top at 2.4 m.
    let top = blocks.iter().map(|b| b.position[1]).fold(0.0, f64::max);
    assert!((top - 2.3).abs() < 1e-12);
}

#[test]
fn pachinko_and_chute_have_their_parts() {
    let p = parse_ok(builtin::PACHINKO);
    assert_eq!(p.body_count(), 8);
    let s = p.instantiate(3);
    let pegs = s
        .statics
        .iter()
        .filter(|b| b.name.starts_with("peg_"))
        .count();
    assert_eq!(pegs, 28 + 24);
    assert!(s.statics.iter().any(|b| b.name == "glass[1]"));
    // Bodies fit between the glass panes (inner faces at z = ±0.06).
    for b in &s.bodies {
        assert!(b.shape.bounding_radius() < 0.06, "{}", b.name);
    }
    let c = parse_ok(builtin::CHUTE);
    assert_eq!(c.body_count(), 1);
    let s = c.instantiate(3);
    assert_eq!(s.bodies[0].name, "marble");
    assert!(s.statics.iter().any(|b| b.name == "cup_side[1]"));
}

#[test]
fn same_seed_same_scene_different_seed_differs() {
    for name in builtin::NAMES {
        let t = parse_ok(builtin::get(name).unwrap_or_default());
        assert_eq!(t.instantiate(99), t.instantiate(99), "{name}");
        let (a, b) = (t.instantiate(1), t.instantiate(2));
        assert_ne!(a, b, "{name}: seeds 1 and 2 gave the same world");
        // Only randomised quantities differ: body names and the static geometry stay.
        assert_eq!(a.statics, b.statics, "{name}");
        let names = |s: &super::Scene| s.bodies.iter().map(|b| b.name.clone()).collect::<Vec<_>>();
        assert_eq!(names(&a), names(&b));
    }
    // Tower blocks are fixed, only the ball varies.
    let t = parse_ok(builtin::TOWER);
    let (a, b) = (t.instantiate(1), t.instantiate(2));
    assert_eq!(a.bodies[..192], b.bodies[..192]);
    assert_ne!(a.bodies[192], b.bodies[192]);
}

#[test]
fn scene_without_distributions_is_the_same_for_every_seed() {
    let t = parse_ok(BASE);
    assert!(!t.has_distributions());
    assert_eq!(t.instantiate(1), t.instantiate(2));
}

// ---------------------------------------------------------------- format details

const BASE: &str = r#"
name = "t"

[[material]]
name = "wood"
friction = 0.5
restitution = 0.2
density = 600

[[static]]
name = "ground"
shape = "plane"
material = "wood"

[[body]]
name = "ball"
shape = "sphere"
radius = 0.1
material = "wood"
position = [0, 1, 0]
"#;

#[test]
fn defaults_fill_in_settings_and_materials() {
    let t = parse_ok(
        r#"name = "d"
[[material]]
name = "m"
[[body]]
name = "b"
shape = "box"
half_extents = [0.1, 0.2, 0.3]
material = "m"
"#,
    );
    assert_eq!(*t.settings(), super::Settings::default());
    let s = t.instantiate(0);
    assert_eq!(s.materials[0].friction, 0.5);
    assert_eq!(s.materials[0].restitution, 0.0);
    assert_eq!(s.materials[0].density, 1000.0);
    assert_eq!(
        s.bodies[0].shape,
        Shape::Box {
            half_extents: [0.1, 0.2, 0.3]
        }
    );
    assert_eq!(s.bodies[0].rotation, super::IDENTITY);
    assert_eq!(s.bodies[0].linvel, [0.0; 3]);
}

#[test]
fn settings_are_read() {
    let t = parse_ok(&format!(
        "{BASE}\n[settings]\ndt = 0.005\nend_time = 3\ngravity = [0, -3.7, 0]\nrest_linear = 0.01\n\
         rest_angular = 0.02\nrest_hold = 1\nsolver_iterations = 8\nalpha = 0.01\ncos_exponent = 5\n\
         c_v = 20\nc_omega = 40\nsegment_seconds = 0.5\nlinear_damping = 0.1\nangular_damping = 0.2\n"
    ));
    let s = t.settings();
    assert_eq!(s.dt, 0.005);
    assert_eq!(s.end_time, 3.0);
    assert_eq!(s.gravity, [0.0, -3.7, 0.0]);
    assert_eq!(
        (s.rest_linear, s.rest_angular, s.rest_hold),
        (0.01, 0.02, 1.0)
    );
    assert_eq!(s.solver_iterations, 8);
    assert_eq!(
        (s.alpha, s.cos_exponent, s.c_v, s.c_omega),
        (0.01, 5.0, 20.0, 40.0)
    );
    assert_eq!(s.segment_seconds, 0.5);
    assert_eq!((s.linear_damping, s.angular_damping), (0.1, 0.2));
}

#[test]
fn presets_are_read_and_written_keys_win() {
    use super::{CcdPolicy, SimPreset};
    let d = parse_ok(BASE);
    assert_eq!(d.settings().sim, SimPreset::Standard);
    assert_eq!(
        (d.settings().solver_iterations, d.settings().pgs_iterations),
        (4, 1)
    );
    let at = |lines: &str| {
        parse_ok(&format!("{BASE}\n[settings]\n{lines}\n"))
            .settings()
            .clone()
    };
    let draft = at("sim = \"draft\"");
    assert_eq!(
        (draft.sim, draft.solver_iterations, draft.ccd),
        (SimPreset::Draft, 1, CcdPolicy::Auto)
    );
    let fin = at("sim = \"final\"");
    assert_eq!(
        (fin.solver_iterations, fin.pgs_iterations, fin.ccd),
        (8, 2, CcdPolicy::All)
    );
    let reference = at("sim = \"reference\"");
    assert_eq!(
        (
            reference.solver_iterations,
            reference.pgs_iterations,
            reference.stabilization_iterations,
            reference.sleep
        ),
        (8, 8, 4, false)
    );
    assert_eq!(reference.dt, draft.dt / 8.0);
    let custom = at(
        "sim = \"final\"\nsolver_iterations = 6\nccd = \"off\"\nsleep = false\nprediction_distance = 0.01\n\
         length_unit = 0.1\nmax_speed = 900\ntolerance = 0.005\npgs_iterations = 3\nstabilization_iterations = 2",
    );
    assert_eq!(custom.sim, SimPreset::Final);
    assert_eq!(
        (
            custom.solver_iterations,
            custom.pgs_iterations,
            custom.stabilization_iterations
        ),
        (6, 3, 2)
    );
    assert_eq!((custom.ccd, custom.sleep), (CcdPolicy::Off, false));
    assert_eq!(custom.prediction_distance, Some(0.01));
    assert_eq!(
        (custom.length_unit, custom.max_speed, custom.tolerance),
        (Some(0.1), Some(900.0), Some(0.005))
    );
    // `auto` parses; it is resolved by calibration before a job is sampled.
    assert_eq!(at("sim = \"auto\"").sim, SimPreset::Auto);
}

fn body_with(fields: &str) -> super::Body {
    let src = format!(
        "name = \"r\"\n[[material]]\nname = \"m\"\n[[body]]\nname = \"b\"\nshape = \"box\"\n\
         size = [2, 4, 6]\nmaterial = \"m\"\n{fields}\n"
    );
    parse_ok(&src).instantiate(0).bodies.remove(0)
}

fn rotate(q: [f64; 4], v: [f64; 3]) -> [f64; 3] {
    super::template::rotate(q, v)
}

fn close(a: [f64; 3], b: [f64; 3]) -> bool {
    a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-12)
}

#[test]
fn rotations_in_human_form_become_unit_quaternions() {
    let b = body_with("");
    assert_eq!(
        b.shape,
        Shape::Box {
            half_extents: [1.0, 2.0, 3.0]
        }
    );
    // 90° about z takes x to y.
    let q = body_with("rotation_deg = [0, 0, 90]").rotation;
    assert!(close(rotate(q, [1.0, 0.0, 0.0]), [0.0, 1.0, 0.0]), "{q:?}");
    // Extrinsic X then Y: x-rotation first. [90, 90, 0]: y → z (about x) → x (about y).
    let q = body_with("rotation_deg = [90, 90, 0]").rotation;
    assert!(close(rotate(q, [0.0, 1.0, 0.0]), [1.0, 0.0, 0.0]), "{q:?}");
    let q2 = body_with("axis_angle = { axis = [0, 0, 2], deg = 90 }").rotation;
    assert!(close(rotate(q2, [1.0, 0.0, 0.0]), [0.0, 1.0, 0.0]));
    let q3 = body_with("quat = [0, 0, 2, 0]").rotation;
    assert_eq!(q3, [0.0, 0.0, 1.0, 0.0]);
    for q in [q, q2, q3] {
        let n: f64 = q.iter().map(|c| c * c).sum();
        assert!((n - 1.0).abs() < 1e-12);
    }
}

#[test]
fn generators_expand_with_names_and_per_instance_samples() {
    let t = parse_ok(
        r#"name = "g"
[[material]]
name = "m"
[[body]]
name = "link"
shape = "capsule"
height = 0.4
radius = 0.05
material = "m"
position = [{ uniform = [-0.01, 0.01] }, 1, 0]
row = { count = 3, spacing = [0.5, 0, 0] }
[[body]]
name = "jenga"
shape = "box"
size = [0.25, 0.15, 0.75]
material = "m"
stack = { layers = 2, per_layer = 3, spacing = 0.25, layer_height = 0.15 }
[[joint]]
name = "hinge"
kind = "revolute"
body1 = "link[0]"
body2 = "link[1]"
anchor1 = [0.25, 0, 0]
anchor2 = [-0.25, 0, 0]
axis = [0, 0, 3]
[[joint]]
name = "pin"
kind = "spherical"
body1 = "world"
body2 = "link[0]"
anchor1 = [0, 1, 0]
"#,
    );
    assert_eq!(t.body_count(), 9);
    let names: Vec<&str> = t.body_names().collect();
    assert_eq!(names[..4], ["link[0]", "link[1]", "link[2]", "jenga[0,0]"]);
    let s = t.instantiate(5);
    assert_eq!(
        s.bodies[1].shape,
        Shape::Capsule {
            half_height: 0.2,
            radius: 0.05
        }
    );
    // Each instance draws its own jitter.
    let dx = s.bodies[1].position[0] - 0.5 - s.bodies[0].position[0];
    assert!(dx != 0.0 && dx.abs() <= 0.02);
    // Second stack layer is turned 90° about y: its long axis (local z) lies along x.
    let top = &s.bodies[s.body_index("jenga[1,0]").unwrap_or(0)];
    assert!(close(
        rotate(top.rotation, [0.0, 0.0, 1.0]).map(f64::abs),
        [1.0, 0.0, 0.0]
    ));
    assert!((top.position[1] - 0.15).abs() < 1e-12);
    assert_eq!(
        s.joints[0].kind,
        JointKind::Revolute {
            axis: [0.0, 0.0, 1.0]
        }
    );
    assert_eq!(
        (s.joints[0].body1, s.joints[0].body2),
        (BodyRef::Body(0), BodyRef::Body(1))
    );
    assert_eq!(s.joints[1].body1, BodyRef::World);
    assert_eq!(s.joints[1].anchor1, [0.0, 1.0, 0.0]);
}

#[test]
fn fixed_numbers_draw_nothing_from_the_stream() {
    // Documented sampling rule: turning a distribution into a plain number (or adding plain
    // numbers) leaves every other sample where it was.
    let a = parse_ok(&format!("{BASE}linvel = [{{ uniform = [0, 1] }}, 0, 0]\n"));
    let b = parse_ok(&format!(
        "{BASE}linvel = [{{ uniform = [0, 1] }}, 0, 0]\nangvel = [1, 2, 3]\nrotation_deg = [1, 2, 3]\n"
    ));
    let (sa, sb) = (a.instantiate(11), b.instantiate(11));
    assert_eq!(sa.bodies[0].linvel, sb.bodies[0].linvel);
}

#[test]
fn statics_trimesh_convex_and_sizes() {
    let t = parse_ok(
        r#"name = "shapes"
[[material]]
name = "m"
[[static]]
name = "bowl"
shape = "trimesh"
material = "m"
vertices = [[0, 0, 0], [1, 0, 0], [0, 0, 1], [1, 0, 1]]
indices = [[0, 2, 1], [1, 2, 3]]
[[static]]
name = "post"
shape = "cylinder"
half_height = 0.5
radius = 0.1
material = "m"
[[body]]
name = "rock"
shape = "convex"
material = "m"
points = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
position = [0, 2, 0]
"#,
    );
    let s = t.instantiate(0);
    assert_eq!(t.static_count(), 2);
    assert!(matches!(&s.statics[0].shape, Shape::TriMesh { indices, .. } if indices.len() == 2));
    assert_eq!(
        s.statics[1].shape,
        Shape::Cylinder {
            half_height: 0.5,
            radius: 0.1
        }
    );
    assert!(matches!(&s.bodies[0].shape, Shape::ConvexHull { points } if points.len() == 4));
}

// ---------------------------------------------------------------- refusals

/// One bad input: the TOML (the offending line carries the marker `#<`, unless `line` is given
/// explicitly), and what the error must name.
struct Bad {
    what: &'static str,
    src: String,
    item: &'static str,
    field: &'static str,
    message: &'static str,
}

fn bad(
    what: &'static str,
    src: impl Into<String>,
    item: &'static str,
    field: &'static str,
    message: &'static str,
) -> Bad {
    Bad {
        what,
        src: src.into(),
        item,
        field,
        message,
    }
}

/// The base scene with one line of the body replaced or added.
fn body_line(line: &str) -> String {
    format!("{BASE}{line} #<\n")
}

fn bad_cases() -> Vec<Bad> {
    let material = |line: &str| {
        format!(
            "name = \"t\"\n[[material]]\nname = \"wood\"\n{line} #<\n[[body]]\nname = \"b\"\nshape = \"sphere\"\nradius = 1\nmaterial = \"wood\"\n"
        )
    };
    let settings = |line: &str| format!("{BASE}[settings]\n{line} #<\n");
    let shape = |shape_lines: &str| {
        format!(
            "name = \"t\"\n[[material]]\nname = \"wood\"\n[[body]]\nname = \"b\"\nmaterial = \"wood\"\n{shape_lines}\n"
        )
    };
    let stat = |shape_lines: &str| {
        format!(
            "name = \"t\"\n[[material]]\nname = \"wood\"\n[[static]]\nname = \"s\"\nmaterial = \"wood\"\n{shape_lines}\n"
        )
    };
    vec![
        bad(
            "nan",
            body_line("radius = nan").replace("radius = 0.1\n", ""),
            "body \"ball\"",
            "radius",
            "finite",
        ),
        bad(
            "inf component",
            body_line("linvel = [0, inf, 0]"),
            "body \"ball\"",
            "linvel[1]",
            "finite",
        ),
        bad(
            "negative radius",
            body_line("radius = -0.1").replace("radius = 0.1\n", ""),
            "body \"ball\"",
            "radius",
            "> 0",
        ),
        bad(
            "zero size",
            shape("shape = \"box\"\nsize = [1, 0, 1] #<"),
            "body \"b\"",
            "size[1]",
            "> 0",
        ),
        bad(
            "bad density",
            material("density = 0"),
            "material \"wood\"",
            "density",
            "> 0",
        ),
        bad(
            "negative friction",
            material("friction = -0.1"),
            "material \"wood\"",
            "friction",
            ">= 0",
        ),
        bad(
            "restitution > 1",
            material("restitution = 1.5"),
            "material \"wood\"",
            "restitution",
            "in [0, 1]",
        ),
        bad(
            "unknown material",
            body_line("material = \"wod\"").replace("material = \"wood\"\nposition", "position"),
            "body \"ball\"",
            "material",
            "unknown material \"wod\" (did you mean \"wood\"?)",
        ),
        bad(
            "unknown shape",
            shape("shape = \"cube\" #<\nsize = [1, 1, 1]"),
            "body \"b\"",
            "shape",
            "unknown shape \"cube\"",
        ),
        bad(
            "plane on a body",
            shape("shape = \"plane\" #<"),
            "body \"b\"",
            "shape",
            "can only be static",
        ),
        bad(
            "trimesh on a body",
            shape("shape = \"trimesh\" #<"),
            "body \"b\"",
            "shape",
            "can only be static",
        ),
        bad(
            "hull with 3 points",
            shape("shape = \"convex\"\npoints = [[0, 0, 0], [1, 0, 0], [0, 1, 0]] #<"),
            "body \"b\"",
            "points",
            "at least 4 points",
        ),
        bad(
            "coplanar hull",
            shape("shape = \"convex\"\npoints = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]] #<"),
            "body \"b\"",
            "points",
            "coplanar",
        ),
        bad(
            "trimesh index",
            stat(
                "shape = \"trimesh\"\nvertices = [[0, 0, 0], [1, 0, 0], [0, 0, 1]]\nindices = [[0, 1, 2],\n [0, 1, 3]] #<",
            ),
            "static \"s\"",
            "indices[1]",
            "out of range",
        ),
        bad(
            "duplicate name",
            format!(
                "{BASE}[[body]]\nname = \"ball\" #<\nshape = \"sphere\"\nradius = 1\nmaterial = \"wood\"\n"
            ),
            "body \"ball\"",
            "name",
            "duplicate name \"ball\"",
        ),
        bad(
            "static/body name clash",
            format!(
                "{BASE}[[body]]\nname = \"ground\" #<\nshape = \"sphere\"\nradius = 1\nmaterial = \"wood\"\n"
            ),
            "body \"ground\"",
            "name",
            "duplicate",
        ),
        bad(
            "joint to unknown body",
            format!(
                "{BASE}[[joint]]\nname = \"j\"\nkind = \"fixed\"\nbody1 = \"world\"\nbody2 = \"bal\" #<\n"
            ),
            "joint \"j\"",
            "body2",
            "unknown body \"bal\" (did you mean \"ball\"?)",
        ),
        bad(
            "joint to a static",
            format!(
                "{BASE}[[joint]]\nname = \"j\"\nkind = \"fixed\"\nbody1 = \"ground\" #<\nbody2 = \"ball\"\n"
            ),
            "joint \"j\"",
            "body1",
            "static",
        ),
        bad(
            "joint to itself",
            format!(
                "{BASE}[[joint]]\nname = \"j\"\nkind = \"fixed\"\nbody1 = \"ball\"\nbody2 = \"ball\" #<\n"
            ),
            "joint \"j\"",
            "body2",
            "two different bodies",
        ),
        bad(
            "unknown joint kind",
            format!(
                "{BASE}[[joint]]\nname = \"j\"\nkind = \"hinge\" #<\nbody1 = \"world\"\nbody2 = \"ball\"\n"
            ),
            "joint \"j\"",
            "kind",
            "unknown joint kind",
        ),
        bad(
            "zero hinge axis",
            format!(
                "{BASE}[[joint]]\nname = \"j\"\nkind = \"revolute\"\nbody1 = \"world\"\nbody2 = \"ball\"\naxis = [0, 0, 0] #<\n"
            ),
            "joint \"j\"",
            "axis",
            "non-zero",
        ),
        bad("zero dt", settings("dt = 0"), "settings", "dt", "> 0"),
        bad(
            "huge dt",
            settings("dt = 1"),
            "settings",
            "dt",
            "at most 0.1",
        ),
        bad(
            "negative end_time",
            settings("end_time = -1"),
            "settings",
            "end_time",
            "> 0",
        ),
        bad(
            "end_time shorter than a step",
            settings("end_time = 0.001"),
            "settings",
            "end_time",
            "at least one step",
        ),
        bad(
            "unknown preset",
            settings("sim = \"fnial\""),
            "settings",
            "sim",
            "unknown preset \"fnial\": one of draft, standard, final, reference, auto (did you mean \"final\"?)",
        ),
        bad(
            "preset not a string",
            settings("sim = 2"),
            "settings",
            "sim",
            "expected a string",
        ),
        bad(
            "unknown ccd policy",
            settings("ccd = \"some\""),
            "settings",
            "ccd",
            "one of auto, all, off",
        ),
        bad(
            "sleep not a boolean",
            settings("sleep = \"yes\""),
            "settings",
            "sleep",
            "expected true or false",
        ),
        bad(
            "zero length unit",
            settings("length_unit = 0"),
            "settings",
            "length_unit",
            "> 0",
        ),
        bad(
            "negative tolerance",
            settings("tolerance = -1"),
            "settings",
            "tolerance",
            "> 0",
        ),
        bad(
            "float iterations",
            settings("solver_iterations = 4.5"),
            "settings",
            "solver_iterations",
            "expected an integer",
        ),
        bad(
            "alpha > 1",
            settings("alpha = 2"),
            "settings",
            "alpha",
            "in [0, 1]",
        ),
        bad(
            "distribution in settings",
            settings("end_time = { uniform = [1, 2] }"),
            "settings",
            "end_time",
            "distributions are not allowed",
        ),
        bad(
            "unknown settings key",
            settings("dtt = 0.01"),
            "settings",
            "dtt",
            "unknown field (did you mean \"dt\"?)",
        ),
        bad(
            "typo in body key",
            body_line("possition = [0, 1, 0]"),
            "body \"ball\"",
            "possition",
            "did you mean \"position\"",
        ),
        bad(
            "key of another shape",
            body_line("size = [1, 1, 1]"),
            "body \"ball\"",
            "size",
            "does not apply to shape \"sphere\"",
        ),
        bad(
            "velocity on a static",
            stat("shape = \"sphere\"\nradius = 1\nlinvel = [1, 0, 0] #<"),
            "static \"s\"",
            "linvel",
            "statics do not move",
        ),
        bad(
            "uniform a > b",
            body_line("linvel = [{ uniform = [1, 0] }, 0, 0]"),
            "body \"ball\"",
            "linvel[0]",
            "a <= b",
        ),
        bad(
            "uniform outside range",
            material("restitution = { uniform = [0.5, 1.2] }"),
            "material \"wood\"",
            "restitution",
            "in [0, 1]",
        ),
        bad(
            "normal tail outside range",
            material("friction = { normal = [0.3, 0.1] }"),
            "material \"wood\"",
            "friction",
            "mu ± 4 sigma",
        ),
        bad(
            "negative sigma",
            body_line("linvel = [{ normal = [0, -1] }, 0, 0]"),
            "body \"ball\"",
            "linvel[0]",
            "sigma must be >= 0",
        ),
        bad(
            "unknown distribution",
            body_line("linvel = [{ gauss = [0, 1] }, 0, 0]"),
            "body \"ball\"",
            "linvel[0]",
            "unknown distribution \"gauss\"",
        ),
        bad(
            "two rotations",
            body_line("rotation_deg = [0, 0, 0]\nquat = [0, 0, 0, 1]"),
            "body \"ball\"",
            "quat",
            "only one of",
        ),
        bad(
            "wrong vector length",
            body_line("position = [0, 1]").replace("position = [0, 1, 0]\n", ""),
            "body \"ball\"",
            "position",
            "expected 3 numbers",
        ),
        bad(
            "string for a number",
            body_line("radius = \"big\"").replace("radius = 0.1\n", ""),
            "body \"ball\"",
            "radius",
            "expected a number",
        ),
        bad(
            "zero generator count",
            format!(
                "{BASE}[[body]]\nname = \"block\"\nshape = \"box\"\nsize = [1, 1, 1]\nmaterial = \"wood\"\ngrid = {{ count = [4, 0, 4], spacing = [1, 1, 1] }} #<\n"
            ),
            "body \"block[i,j,k]\"",
            "grid.count[1]",
            "integer in [1, 100000]",
        ),
        bad(
            "generator template error",
            format!(
                "{BASE}[[body]]\nname = \"block\"\nshape = \"box\"\nsize = [1, 1, 1]\nmaterial = \"wod\" #<\ngrid = {{ count = [4, 2, 4], spacing = [1, 1, 1] }}\n"
            ),
            "body \"block[i,j,k]\"",
            "material",
            "unknown material",
        ),
        bad(
            "too many instances",
            format!(
                "{BASE}[[body]]\nname = \"block\"\nshape = \"box\"\nsize = [1, 1, 1]\nmaterial = \"wood\"\ngrid = {{ count = [1000, 1000, 1000], spacing = [1, 1, 1] }} #<\n"
            ),
            "body \"block[i,j,k]\"",
            "grid",
            "more than 100000",
        ),
        bad(
            "bracket in a name",
            format!(
                "{BASE}[[body]]\nname = \"b[1]\" #<\nshape = \"sphere\"\nradius = 1\nmaterial = \"wood\"\n"
            ),
            "body \"b[1]\"",
            "name",
            "reserved",
        ),
        bad(
            "plural table",
            format!("{BASE}[[bodies]] #<\nname = \"x\"\n"),
            "scene",
            "bodies",
            "tables are singular",
        ),
        bad(
            "missing scene name",
            "[[material]] #<\nname = \"m\"\n".replace("[[material]] #<", "#<\n[[material]]"),
            "scene",
            "name",
            "missing",
        ),
    ]
}

#[test]
fn every_bad_input_names_line_item_and_field() {
    let cases = bad_cases();
    assert!(cases.len() >= 40);
    for case in &cases {
        assert_refused(case);
    }
}

/// Parses `case.src` and checks the refusal names the file, the marked line, the item, the field
/// and the message.
fn assert_refused(case: &Bad) {
    let line = case
        .src
        .lines()
        .position(|l| l.contains("#<"))
        .map(|i| i + 1)
        .unwrap_or_else(|| panic!("{}: no #< marker", case.what));
    let err = match parse(&case.src) {
        Ok(_) => panic!("{}: accepted:\n{}", case.what, case.src),
        Err(e) => e,
    };
    let shown = err.to_string();
    assert_eq!(err.file, "test.toml");
    assert_eq!(
        err.item.as_deref(),
        Some(case.item),
        "{}: {shown}",
        case.what
    );
    assert_eq!(
        err.field.as_deref(),
        Some(case.field),
        "{}: {shown}",
        case.what
    );
    assert!(err.message.contains(case.message), "{}: {shown}", case.what);
    let prefix = format!("test.toml:{line}: {}: field `{}`: ", case.item, case.field);
    assert!(
        shown.starts_with(&prefix),
        "{}: expected prefix {prefix:?}, got {shown:?}\n{}",
        case.what,
        case.src
    );
}

#[test]
fn missing_fields_point_at_the_item() {
    // The body table starts on line 4 ([[body]]) or 5 (its first key): either identifies it.
    let src = "name = \"t\"\n[[material]]\nname = \"m\"\n[[body]]\nname = \"b\"\nshape = \"sphere\"\nmaterial = \"m\"\n";
    let err = parse(src).err().unwrap_or_else(|| panic!("accepted"));
    assert_eq!(err.field.as_deref(), Some("radius"));
    assert_eq!(err.item.as_deref(), Some("body \"b\""));
    assert!(matches!(err.line, Some(4 | 5)), "{err}");
    assert!(err.message.contains("missing"));
}

#[test]
fn toml_syntax_errors_carry_file_and_line() {
    let src = "name = \"t\"\n[[material]]\nname = \"m\"\nfriction = = 3\n";
    let err = parse(src).err().unwrap_or_else(|| panic!("accepted"));
    assert_eq!(err.line, Some(4), "{err}");
    assert!(
        err.to_string().starts_with("test.toml:4: invalid TOML"),
        "{err}"
    );
    let err = parse("name = \"t\"\nname = \"u\"\n")
        .err()
        .unwrap_or_else(|| panic!("accepted"));
    assert_eq!(err.line, Some(2), "{err}");
}

#[test]
fn error_display_matches_the_documented_form() {
    let e = SceneError {
        file: "scenes/tower.toml".into(),
        line: Some(42),
        item: Some("body \"block[3,1,2]\"".into()),
        field: Some("material".into()),
        message: "unknown material \"wod\"".into(),
    };
    assert_eq!(
        e.to_string(),
        "scenes/tower.toml:42: body \"block[3,1,2]\": field `material`: unknown material \"wod\""
    );
    let e = SceneError {
        line: None,
        item: None,
        field: None,
        ..e
    };
    assert_eq!(e.to_string(), "scenes/tower.toml: unknown material \"wod\"");
}

#[test]
fn instance_limit_is_the_documented_one() {
    assert_eq!(MAX_INSTANCES, 100_000);
}

// ---------------------------------------------------------------- properties

fn friction_scene(dist: &str) -> String {
    format!("name = \"p\"\n[[material]]\nname = \"m\"\nfriction = {dist}\n")
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]

    #[test]
    fn uniform_samples_lie_in_their_interval(a in -1e3f64..1e3, w in 0.0f64..1e3, seed in any::<u64>()) {
        let b = a + w;
        let src = format!("name = \"p\"\n[[material]]\nname = \"m\"\n[[body]]\nname = \"b\"\nshape = \"sphere\"\nradius = 1\nmaterial = \"m\"\nlinvel = [{{ uniform = [{a:?}, {b:?}] }}, 0, 0]\n");
        let t = parse(&src).map_err(|e| TestCaseError::fail(e.to_string()))?;
        for k in 0..8u64 {
            let v = t.instantiate(seed.wrapping_add(k)).bodies[0].linvel[0];
            prop_assert!(a <= v && v <= b, "{} not in [{}, {}]", v, a, b);
        }
    }

    #[test]
    fn uniform_on_a_bounded_field_stays_valid(a in 0.0f64..1.0, w in 0.0f64..1.0, seed in any::<u64>()) {
        let b = (a + w).min(1.0);
        let src = format!("name = \"p\"\n[[material]]\nname = \"m\"\nrestitution = {{ uniform = [{a:?}, {b:?}] }}\n");
        let t = parse(&src).map_err(|e| TestCaseError::fail(e.to_string()))?;
        let r = t.instantiate(seed).materials[0].restitution;
        prop_assert!((a..=b).contains(&r) && (0.0..=1.0).contains(&r));
    }

    #[test]
    fn normal_samples_are_clamped_to_4_sigma_inside_the_valid_range(mu in 0.01f64..10.0, frac in 0.0f64..1.0, seed in any::<u64>()) {
        // The largest sigma the rule admits for friction >= 0 is mu / 4.
        let sigma = frac * mu / 4.0;
        let t = parse(&friction_scene(&format!("{{ normal = [{mu:?}, {sigma:?}] }}")))
            .map_err(|e| TestCaseError::fail(e.to_string()))?;
        for k in 0..16u64 {
            let f = t.instantiate(seed.wrapping_add(k)).materials[0].friction;
            prop_assert!(f >= 0.0);
            prop_assert!(f >= mu - 4.0 * sigma && f <= mu + 4.0 * sigma, "{} vs {} ± 4·{}", f, mu, sigma);
        }
        // One step past the rule is refused.
        let too_wide = mu / 4.0 * 1.01 + 1e-9;
        let wide = friction_scene(&format!("{{ normal = [{mu:?}, {too_wide:?}] }}"));
        prop_assert!(parse(&wide).is_err());
    }

    #[test]
    fn garbage_never_panics(src in "\\PC{0,200}") {
        let _ = parse(&src);
    }

    #[test]
    fn toml_shaped_garbage_never_panics(
        lines in proptest::collection::vec(
            "(name|shape|size|radius|material|position|grid|row|stack|count|spacing|kind|body1|axis|points|indices|dt|friction) = (\"[a-z]{0,4}\"|-?[0-9]{1,3}(\\.[0-9])?|\\[[0-9, -]{0,12}\\]|\\{ ?(uniform|normal|count|axis) = \\[[0-9, .-]{0,9}\\] ?\\}|nan|inf)|\\[\\[(body|static|material|joint)\\]\\]|\\[settings\\]",
            0..24,
        )
    ) {
        let _ = parse(&lines.join("\n"));
    }

    #[test]
    fn mutated_shipped_scenes_never_panic(which in 0usize..4, pos in any::<prop::sample::Index>(), byte in any::<u8>(), cut in any::<bool>()) {
        let src = builtin::get(builtin::NAMES[which]).unwrap_or_default();
        let mut bytes = src.as_bytes().to_vec();
        let i = pos.index(bytes.len());
        if cut { bytes.truncate(i) } else { bytes[i] = byte }
        let text = String::from_utf8_lossy(&bytes);
        if let Ok(t) = parse(&text) {
            // Whatever parses must instantiate to a scene with finite, valid numbers.
            let s = t.instantiate(1);
            for b in &s.bodies {
                prop_assert!(b.position.iter().chain(&b.linvel).chain(&b.rotation).all(|x| x.is_finite()));
            }
            for m in &s.materials {
                prop_assert!(m.density > 0.0 && m.friction >= 0.0 && (0.0..=1.0).contains(&m.restitution));
            }
        }
    }
}

#[test]
fn examples_in_the_format_reference_parse() {
    let doc = include_str!("../../../docs/scene-format.md");
    let mut checked = 0;
    for block in doc.split("```toml\n").skip(1) {
        let block = block.split("```").next().unwrap_or_default();
        if !block.contains("[[") {
            continue; // a fragment of one item, not a scene
        }
        if block.contains("shape = \"mesh\"") {
            continue; // reads files: resolved and parsed in mesh/tests/mesh.rs
        }
        let src = if block.trim_start().starts_with("name =") {
            block.to_owned()
        } else {
            format!("name = \"doc\"\n[[material]]\nname = \"wood\"\n{block}")
        };
        let t = SceneTemplate::parse(&src, "docs/scene-format.md")
            .unwrap_or_else(|e| panic!("{e}\n{src}"));
        let _ = t.instantiate(0);
        checked += 1;
    }
    assert!(checked >= 3, "{checked}");
    let example = parse_ok(
        doc.split("```toml\n")
            .nth(1)
            .unwrap_or_default()
            .split("```")
            .next()
            .unwrap_or_default(),
    );
    assert_eq!(example.body_count(), 193);
}

/// A final-state scene's `[reverse]` table belongs to mwb-reverse: every other reader ignores
/// it, and the rest of the scene is read exactly as without it.
#[test]
fn a_reverse_table_is_ignored_by_the_core_reader() {
    let base = "name = \"r\"\n[[material]]\nname = \"m\"\n[[body]]\nname = \"b\"\nshape = \"sphere\"\nradius = 0.1\nmaterial = \"m\"\nposition = [0, 1, 0]\n";
    let with = format!(
        "{base}[reverse]\nmode = \"mixed\"\nforward_time = 1.0\n[[reverse.hint]]\nbody = \"b\"\nmotion = \"stay\"\n"
    );
    assert_eq!(
        parse_ok(&with).instantiate(7),
        parse_ok(base).instantiate(7)
    );
    // Other unknown tables are still refused.
    assert!(parse(&format!("{base}[reverso]\nmode = 1\n")).is_err());
}

// ---------------------------------------------------------------- big scenes, bytes

/// [`builtin::many_bodies`] with a chain of `joints` fixed joints between consecutive bodies.
fn big_scene(bodies: usize, joints: usize) -> String {
    use std::fmt::Write as _;
    let mut s = builtin::many_bodies(bodies);
    for j in 0..joints {
        let _ = write!(
            s,
            "\n[[joint]]\nname = \"j{j}\"\nkind = \"fixed\"\nbody1 = \"b{j}\"\nbody2 = \"b{}\"\n",
            j + 1
        );
    }
    s
}

/// Issue 18: a big scene parses (its speed is measured by `mwb bench scene`, not here), every
/// body in file order, every joint resolved.
#[test]
fn a_scene_of_20k_single_bodies_parses() {
    let t = parse_ok(&big_scene(20_000, 1_000));
    assert_eq!(t.body_count(), 20_000);
    assert!(t.body_names().eq((0..20_000).map(|i| format!("b{i}"))));
    let s = t.instantiate(0);
    assert_eq!(s.joints.len(), 1_000);
    assert_eq!(s.bodies[12_345].position, [45.0, 1.0, 23.0]);
    assert_eq!(s.joints[999].body2, BodyRef::Body(1_000));
}

/// One body past the limit, written out one table each, is refused at that body's name.
#[test]
fn single_bodies_past_the_instance_limit_are_refused_at_the_first_one_too_many() {
    let limit = usize::try_from(MAX_INSTANCES).unwrap_or(usize::MAX);
    assert_eq!(parse_ok(&builtin::many_bodies(limit)).body_count(), limit);
    let src = builtin::many_bodies(limit + 1);
    let line = src.lines().count() - 4;
    let err = parse(&src).err().unwrap_or_else(|| panic!("accepted"));
    assert_eq!(
        err.to_string(),
        format!(
            "test.toml:{line}: body \"b{limit}\": field `name`: the scene would expand to more \
             than {MAX_INSTANCES} bodies and statics"
        )
    );
}

/// Lines of names are worked out only for the error (issue 18); the line they name is the
/// right one however far apart the two uses are.
#[test]
fn a_duplicate_far_down_a_big_scene_names_both_lines() {
    let mut src = big_scene(5_000, 0);
    let first = 1 + src
        .lines()
        .position(|l| l == "name = \"b1234\"")
        .unwrap_or_else(|| panic!("b1234 not written"));
    src.push_str(
        "\n[[body]]\nname = \"b1234\"\nshape = \"sphere\"\nradius = 1\nmaterial = \"wood\"\n",
    );
    let again = src.lines().count() - 3;
    let err = parse(&src).err().unwrap_or_else(|| panic!("accepted"));
    assert_eq!(
        err.to_string(),
        format!(
            "test.toml:{again}: body \"b1234\": field `name`: duplicate name \"b1234\" (first used on line {first})"
        )
    );
    let mut src = big_scene(10, 3);
    src.push_str(
        "\n[[joint]]\nname = \"j1\"\nkind = \"fixed\"\nbody1 = \"b7\"\nbody2 = \"world\"\n",
    );
    let err = parse(&src).err().unwrap_or_else(|| panic!("accepted"));
    assert_eq!(err.line, Some(src.lines().count() - 3), "{err}");
    assert!(err.message.contains("duplicate joint \"j1\""), "{err}");
}

#[test]
fn a_file_that_is_not_utf8_is_refused_with_line_column_and_byte_offset() {
    use super::decode_utf8;
    let ok = "name = \"café\" # ünïcode\n".as_bytes().to_vec();
    assert_eq!(
        decode_utf8("s.toml", ok).as_deref(),
        Ok("name = \"café\" # ünïcode\n")
    );

    // Latin-1 "é" (0xE9) on line 3, after two characters that take three bytes.
    let latin1 = [
        b"name = \"x\"\n\n".as_slice(),
        "ü#".as_bytes(),
        b"\xe9 = 1\n",
    ]
    .concat();
    let err = decode_utf8("s.toml", latin1)
        .err()
        .unwrap_or_else(|| panic!("accepted"));
    assert_eq!(err.line, Some(3));
    assert_eq!((err.item.as_deref(), err.field.as_deref()), (None, None));
    assert_eq!(
        err.to_string(),
        "s.toml:3: not UTF-8: byte 0xe9 at column 3 (byte offset 15 of the file); \
         scene files must be saved as UTF-8"
    );

    // A character cut off by the end of the file; a file on one line.
    let cut = [b"name = \"".as_slice(), &"€".as_bytes()[..2]].concat();
    let err = decode_utf8("s.toml", cut)
        .err()
        .unwrap_or_else(|| panic!("accepted"));
    assert_eq!(
        err.to_string(),
        "s.toml:1: not UTF-8: byte 0xe2 at column 9 (byte offset 8 of the file), which starts \
         a character the file ends in the middle of; scene files must be saved as UTF-8"
    );

    // UTF-16 (as Windows editors save "Unicode"), refused at its byte-order mark.
    let utf16: Vec<u8> = [0xff, 0xfe]
        .into_iter()
        .chain("name".encode_utf16().flat_map(u16::to_le_bytes))
        .collect();
    let err = decode_utf8("s.toml", utf16)
        .err()
        .unwrap_or_else(|| panic!("accepted"));
    assert_eq!(
        err.to_string(),
        "s.toml:1: not UTF-8: byte 0xff at column 1 (byte offset 0 of the file); \
         the file looks like UTF-16; scene files must be saved as UTF-8"
    );
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    /// `line_of` against a table of line starts (what an editor numbers): the line of an
    /// offset is the number of line starts at or before it, and offsets past the end are on the
    /// last line.
    #[test]
    fn line_of_agrees_with_a_table_of_line_starts(
        text in "[a-c\n\r é€]{0,300}",
        offsets in proptest::collection::vec(0usize..320, 1..16),
    ) {
        let src = super::toml_span::Source { text: &text, file: "p.toml" };
        let starts: Vec<usize> = std::iter::once(0)
            .chain(text.match_indices('\n').map(|(i, _)| i + 1))
            .collect();
        for offset in offsets {
            let expected = starts.partition_point(|s| *s <= offset.min(text.len()));
            prop_assert_eq!(src.line_of(offset), expected, "offset {}", offset);
        }
    }

    /// Any bytes: decoded unchanged when they are UTF-8; else refused at the first bad byte,
    /// whose line is the number of newlines before it plus one.
    #[test]
    fn decode_utf8_finds_the_first_bad_byte(bytes in proptest::collection::vec(
        prop_oneof![Just(b'\n'), Just(b'a'), Just(0xc3u8), Just(0xa9u8), Just(0xe9u8)], 0..64,
    )) {
        match (super::decode_utf8("p.toml", bytes.clone()), std::str::from_utf8(&bytes)) {
            (Ok(text), Ok(expected)) => prop_assert_eq!(text, expected),
            (Err(err), Err(e)) => {
                let offset = e.valid_up_to();
                let newlines = bytes[..offset].iter().filter(|b| **b == b'\n').count();
                prop_assert_eq!(err.line, Some(newlines + 1));
                let at = format!("(byte offset {offset} of the file)");
                prop_assert!(err.message.contains(&at), "{}", err);
            }
            (got, expected) => prop_assert!(false, "{:?} vs {:?}", got, expected),
        }
    }
}

// ---------------------------------------------------------------- compound bodies (issue 18)

/// An "L" of two boxes, the foot of another material and turned about y; a compound static
/// beside it.
const COMPOUND: &str = r#"
name = "c"

[[material]]
name = "wood"
density = 600

[[material]]
name = "steel"
density = 7800

[[static]]
name = "ground"
shape = "plane"
material = "wood"

[[static]]
name = "shelf"
shape = "compound"
material = "wood"

[[static.part]]
shape = "box"
size = [1, 0.1, 0.3]

[[static.part]]
shape = "trimesh"
vertices = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
indices = [[0, 1, 2]]
position = [0, 0.05, 0]

[[body]]
name = "letter_l"
shape = "compound"
material = "wood"
position = [0, 1, 0]
angvel = [0, 1, 0]

[[body.part]]
shape = "box"
size = [0.1, 0.5, 0.1]
position = [0, 0.25, 0]

[[body.part]]
shape = "box"
half_extents = [0.15, 0.05, 0.05]
position = [0.1, 0, 0]
rotation_deg = [0, 90, 0]
material = "steel"
"#;

fn parts_of(shape: &Shape) -> &[super::Part] {
    match shape {
        Shape::Compound { parts } => parts,
        other => panic!("expected a compound, got {other:?}"),
    }
}

#[test]
fn a_compound_body_is_one_body_with_posed_parts_and_their_materials() {
    let t = parse_ok(COMPOUND);
    assert_eq!(t.body_count(), 1);
    assert!(!t.has_distributions());
    let s = t.instantiate(5);
    let b = &s.bodies[0];
    assert_eq!(b.name, "letter_l");
    assert_eq!(b.position, [0.0, 1.0, 0.0]);
    assert_eq!(b.angvel, [0.0, 1.0, 0.0]);
    assert_eq!(b.material, 0);
    let parts = parts_of(&b.shape);
    assert_eq!(parts.len(), 2);
    assert_eq!(
        parts[0].shape,
        Shape::Box {
            half_extents: [0.05, 0.25, 0.05]
        }
    );
    assert_eq!(parts[0].position, [0.0, 0.25, 0.0]);
    assert_eq!(parts[0].rotation, super::IDENTITY);
    assert_eq!(
        parts[0].material, 0,
        "a part without material takes its body's"
    );
    assert_eq!(parts[1].material, 1);
    assert_eq!(parts[1].position, [0.1, 0.0, 0.0]);
    // 90° about y turns local x onto world −z.
    assert!(close(
        rotate(parts[1].rotation, [1.0, 0.0, 0.0]),
        [0.0, 0.0, -1.0]
    ));
    // The static may hold a mesh part; it keeps its pose.
    let shelf = parts_of(&s.statics[1].shape);
    assert!(matches!(shelf[1].shape, Shape::TriMesh { .. }));
    assert_eq!(shelf[1].position, [0.0, 0.05, 0.0]);
    assert!(!s.statics[1].shape.can_be_dynamic());
    assert!(b.shape.can_be_dynamic());
    assert_eq!(b.shape.kind(), "compound");
    // The parts seen uniformly, a single shape as its own one part.
    let placed = b.shape.placed_parts(b.material);
    assert_eq!(placed.len(), 2);
    assert_eq!(placed[1].material, 1);
    let ball = Shape::Sphere { radius: 1.0 };
    let single = ball.placed_parts(7);
    assert_eq!((single.len(), single[0].material), (1, 7));
    assert_eq!(single[0].shape, &ball);
}

#[test]
fn a_compound_reaches_as_far_as_its_farthest_part_and_is_as_thin_as_its_thinnest() {
    let s = parse_ok(COMPOUND).instantiate(0);
    let shape = &s.bodies[0].shape;
    // Upright box: centre 0.25 up, corner sqrt(0.05² + 0.25² + 0.05²) further; foot: 0.1 out,
    // corner sqrt(0.15² + 0.05² + 0.05²) further.
    let upright = 0.25 + (0.05f64 * 0.05 + 0.25 * 0.25 + 0.05 * 0.05).sqrt();
    let foot = 0.1 + (0.15f64 * 0.15 + 0.05 * 0.05 + 0.05 * 0.05).sqrt();
    assert!((shape.bounding_radius() - upright.max(foot)).abs() < 1e-12);
    assert!((shape.min_half_thickness() - 0.05).abs() < 1e-12);
}

#[test]
fn compound_parts_may_be_written_inline_and_repeated_by_a_generator() {
    let inline = COMPOUND
        .replace(
            "angvel = [0, 1, 0]\n",
            "angvel = [0, 1, 0]\npart = [\n  { shape = \"box\", size = [0.1, 0.5, 0.1], position = [0, 0.25, 0] },\n  { shape = \"box\", half_extents = [0.15, 0.05, 0.05], position = [0.1, 0, 0], rotation_deg = [0, 90, 0], material = \"steel\" },\n]\n",
        );
    let inline = inline
        .split("[[body.part]]")
        .next()
        .unwrap_or_default()
        .to_owned();
    assert_eq!(
        parse_ok(&inline).instantiate(3),
        parse_ok(COMPOUND).instantiate(3)
    );

    // A grid of compounds, a part's size randomised per instance.
    let grid = COMPOUND
        .replace(
            "position = [0, 1, 0]\n",
            "position = [0, 1, 0]\nrow = { count = 3, spacing = [1, 0, 0] }\n",
        )
        .replace(
            "size = [0.1, 0.5, 0.1]",
            "size = [0.1, { uniform = [0.4, 0.6] }, 0.1]",
        );
    let t = parse_ok(&grid);
    assert!(t.has_distributions());
    assert_eq!(t.body_count(), 3);
    let s = t.instantiate(11);
    assert_eq!(s.bodies[2].name, "letter_l[2]");
    assert_eq!(s.bodies[2].position, [2.0, 1.0, 0.0]);
    let heights: Vec<f64> = s
        .bodies
        .iter()
        .map(|b| match parts_of(&b.shape)[0].shape {
            Shape::Box { half_extents } => half_extents[1],
            _ => f64::NAN,
        })
        .collect();
    assert!(
        heights.iter().all(|h| (0.2..=0.3).contains(h)),
        "{heights:?}"
    );
    assert!(heights[0] != heights[1], "each instance draws its own");
    assert_eq!(t.instantiate(11), s);
}

#[test]
fn a_compound_whose_parts_all_name_materials_needs_none_of_its_own() {
    let src = COMPOUND
        .replace(
            "material = \"wood\"\nposition = [0, 1, 0]",
            "position = [0, 1, 0]",
        )
        .replace(
            "position = [0, 0.25, 0]\n",
            "position = [0, 0.25, 0]\nmaterial = \"steel\"\n",
        );
    let s = parse_ok(&src).instantiate(0);
    assert_eq!(s.bodies[0].material, 1, "the first part's material");
    // Without it, a part that names none has nothing to fall back on.
    let src = COMPOUND.replace(
        "material = \"wood\"\nposition = [0, 1, 0]",
        "position = [0, 1, 0]",
    );
    let err = parse(&src).err().unwrap_or_else(|| panic!("accepted"));
    assert_eq!(err.field.as_deref(), Some("material"));
    assert!(err.message.contains("every part that names none"), "{err}");
}

#[test]
fn a_part_quaternion_is_normalised_as_a_body_quaternion_is() {
    let src = COMPOUND.replace("rotation_deg = [0, 90, 0]", "quat = [0, 0, 0, 2]");
    let s = parse_ok(&src).instantiate(0);
    assert_eq!(parts_of(&s.bodies[0].shape)[1].rotation, super::IDENTITY);
}

/// Every refusal of a compound names the body, the part's index and its field, at the line of
/// the offending value (marked `#<`).
#[test]
fn every_bad_compound_names_the_body_the_part_and_the_field() {
    let body = |part_lines: &str| {
        format!(
            "name = \"t\"\n[[material]]\nname = \"wood\"\n[[body]]\nname = \"s\"\nshape = \"compound\"\nmaterial = \"wood\"\n[[body.part]]\nshape = \"sphere\"\nradius = 0.1\n[[body.part]]\n{part_lines}\n"
        )
    };
    let cases = vec![
        bad(
            "nested compound",
            body("shape = \"compound\" #<"),
            "body \"s\"",
            "part[1].shape",
            "compounds do not nest",
        ),
        bad(
            "plane part",
            body("shape = \"plane\" #<"),
            "body \"s\"",
            "part[1].shape",
            "a plane cannot be a part",
        ),
        bad(
            "plane part of a static",
            body("shape = \"plane\" #<")
                .replace("[[body]]", "[[static]]")
                .replace("[[body.part]]", "[[static.part]]"),
            "static \"s\"",
            "part[1].shape",
            "a plane cannot be a part",
        ),
        bad(
            "trimesh part of a dynamic body",
            body(
                "shape = \"trimesh\" #<\nvertices = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]\nindices = [[0, 1, 2]]",
            ),
            "body \"s\"",
            "part[1].shape",
            "can only be static",
        ),
        bad(
            "unknown part shape",
            body("shape = \"bx\" #<"),
            "body \"s\"",
            "part[1].shape",
            "did you mean \"box\"",
        ),
        bad(
            "NaN in a part position",
            body("shape = \"box\"\nsize = [1, 1, 1]\nposition = [0, nan, 0] #<"),
            "body \"s\"",
            "part[1].position[1]",
            "must be finite",
        ),
        bad(
            "zero part quaternion",
            body("shape = \"box\"\nsize = [1, 1, 1]\nquat = [0, 0, 0, 0] #<"),
            "body \"s\"",
            "part[1].quat",
            "non-zero direction",
        ),
        bad(
            "two part rotations",
            body(
                "shape = \"box\"\nsize = [1, 1, 1]\nrotation_deg = [0, 0, 0]\nquat = [0, 0, 0, 1] #<",
            ),
            "body \"s\"",
            "part[1].quat",
            "give only one of",
        ),
        bad(
            "bad part size",
            body("shape = \"box\"\nsize = [1, -1, 1] #<"),
            "body \"s\"",
            "part[1].size[1]",
            "must be > 0",
        ),
        bad(
            "key of another shape in a part",
            body("shape = \"box\"\nsize = [1, 1, 1]\nradius = 1 #<"),
            "body \"s\"",
            "part[1].radius",
            "does not apply to shape \"box\"",
        ),
        bad(
            "velocity in a part",
            body("shape = \"box\"\nsize = [1, 1, 1]\nlinvel = [1, 0, 0] #<"),
            "body \"s\"",
            "part[1].linvel",
            "velocities belong to the body",
        ),
        bad(
            "generator in a part",
            body("shape = \"box\"\nsize = [1, 1, 1]\nrow = { count = 2, spacing = [1, 0, 0] } #<"),
            "body \"s\"",
            "part[1].row",
            "a part cannot be a generator",
        ),
        bad(
            "unknown material in a part",
            body("shape = \"box\"\nsize = [1, 1, 1]\nmaterial = \"wod\" #<"),
            "body \"s\"",
            "part[1].material",
            "did you mean \"wood\"",
        ),
        bad(
            "missing part shape",
            body("#<\nsize = [1, 1, 1]").replace("[[body.part]]\n#<", "[[body.part]] #<"),
            "body \"s\"",
            "part[1].shape",
            "missing",
        ),
        bad(
            "empty compound",
            "name = \"t\"\n[[material]]\nname = \"wood\"\n[[body]]\nname = \"s\"\nshape = \"compound\"\nmaterial = \"wood\"\npart = [] #<\n",
            "body \"s\"",
            "part",
            "at least one part",
        ),
        bad(
            "compound without parts",
            "name = \"t\"\n[[material]]\nname = \"wood\"\n[[body]] #<\nname = \"s\"\nshape = \"compound\"\nmaterial = \"wood\"\n",
            "body \"s\"",
            "part",
            "missing",
        ),
        bad(
            "a part that is not a table",
            "name = \"t\"\n[[material]]\nname = \"wood\"\n[[body]]\nname = \"s\"\nshape = \"compound\"\nmaterial = \"wood\"\npart = [1] #<\n",
            "body \"s\"",
            "part[0]",
            "expected a table",
        ),
        bad(
            "shape key on the compound body itself",
            "name = \"t\"\n[[material]]\nname = \"wood\"\n[[body]]\nname = \"s\"\nshape = \"compound\"\nmaterial = \"wood\"\nradius = 1 #<\n[[body.part]]\nshape = \"sphere\"\nradius = 0.1\n",
            "body \"s\"",
            "radius",
            "written in its parts",
        ),
        bad(
            "parts on a single shape",
            "name = \"t\"\n[[material]]\nname = \"wood\"\n[[body]]\nname = \"s\"\nshape = \"sphere\"\nradius = 1\nmaterial = \"wood\"\n[[body.part]] #<\nshape = \"sphere\"\nradius = 0.1\n",
            "body \"s\"",
            "part",
            "does not apply to shape \"sphere\"",
        ),
        bad(
            "error in a generated compound's part",
            body("shape = \"box\"\nsize = [1, 0, 1] #<").replace(
                "material = \"wood\"\n[[body.part]]",
                "material = \"wood\"\nrow = { count = 2, spacing = [1, 0, 0] }\n[[body.part]]",
            ),
            "body \"s[i]\"",
            "part[1].size[1]",
            "must be > 0",
        ),
    ];
    for case in &cases {
        assert_refused(case);
    }
}

/// The example of docs/scene-format.md "Compound bodies" is what it says it is.
#[test]
fn the_documented_compound_example_is_one_body_of_two_parts_beside_a_compound_static() {
    let doc = include_str!("../../../docs/scene-format.md");
    let block = doc
        .split("### Compound bodies")
        .nth(1)
        .and_then(|s| s.split("```toml\n").nth(1))
        .and_then(|s| s.split("```").next())
        .unwrap_or_else(|| panic!("no compound example in the format reference"));
    let s = parse_ok(&format!(
        "name = \"doc\"\n[[material]]\nname = \"wood\"\n{block}"
    ))
    .instantiate(0);
    assert_eq!(s.bodies.len(), 1);
    let parts = parts_of(&s.bodies[0].shape);
    assert_eq!(parts.len(), 2);
    assert_eq!(s.materials[parts[0].material].name, "wood");
    assert_eq!(s.materials[parts[1].material].name, "steel");
    assert!(matches!(parts[1].shape, Shape::Cylinder { .. }));
    assert_eq!(parts_of(&s.statics[0].shape).len(), 2);
}
