//! Bad input, caught before a backward run: a final state the backward stepper cannot start
//! from honestly. Pure: [`check_state`] looks at the world built from a scene and names the
//! scene's bodies and joints.
//!
//! * **Overlapping bodies** (refused): a backward step works on velocities only (Twigg and
//!   James, SIGGRAPH 2008, §5.2); it never pushes bodies apart, so a penetration in the final
//!   state stays in every frame of the world, and no forward world ends in it.
//! * **A violated joint** (refused): the backward Baumgarte term *shrinks* a joint's error going
//!   back (§5.3.4), so played forward the joint would come apart by itself.
//! * **A body at rest in mid-air** (warned): nothing under it, and no velocity. As a last frame
//!   that is a body that stopped in the air; as an intermediate frame (a mixed run, §5.4.4) it may
//!   be the top of a throw, so it is only a warning.
//! * **A tall stack** (warned): a column of more than [`MAX_STACK`] bodies resting on one
//!   another. Four coplanar corner rows per face make the column's LCP degenerate for the
//!   pivoting solver: measured (release build), 20 boxes take 18 ms a step; from 30 backward
//!   steps go unsolved, and 50 take seconds a step with forward steps unsolved too.

use mwb_core::scene::Scene;

use crate::contact::Partner;
use crate::scene::{SceneConvertError, world_from_scene};
use crate::world::World;

/// Penetration (m) beyond which two bodies overlap. Scene positions are written to 0.1 mm.
pub const OVERLAP_TOLERANCE: f64 = 1e-4;
/// A body with no contact within this distance (m) touches nothing.
pub const SUPPORT_DISTANCE: f64 = 1e-3;
/// Joint anchor separation (m) or angle (rad) beyond which a joint is violated.
pub const JOINT_TOLERANCE: f64 = 1e-3;
/// Below this speed (m/s, rad/s) a body is at rest.
pub const REST_SPEED: f64 = 1e-6;
/// Bodies in one column above which [`StateWarning::TallStack`] warns: the tallest stack our
/// stepper was measured to solve every step of (node-reverse/tests/extremes.rs).
pub const MAX_STACK: usize = 20;
/// A contact whose normal is within 45° of the vertical holds the body above it up.
const RESTING_COS: f64 = std::f64::consts::FRAC_1_SQRT_2;

/// What the other side of an overlap is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Other {
    /// A dynamic body, by name.
    Body(String),
    /// A static shape (index among the world's static shapes; a compound static gives several).
    Static(usize),
}

impl std::fmt::Display for Other {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Other::Body(n) => write!(f, "body {n:?}"),
            Other::Static(k) => write!(f, "static shape #{k}"),
        }
    }
}

/// A final state refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StateError {
    /// Two bodies (or a body and a static) interpenetrate.
    #[error(
        "body {body:?} overlaps {other} by {depth:.4} m (more than {OVERLAP_TOLERANCE} m): a backward run cannot separate them"
    )]
    Overlap {
        /// The body.
        body: String,
        /// What it overlaps.
        other: Other,
        /// Penetration depth (m).
        depth: f64,
    },
    /// A joint's anchors are apart, or its axes not aligned, in the given state.
    #[error(
        "joint {joint:?} is violated in the given state: anchors {separation:.4} m apart, axes {angle:.4} rad off (tolerance {JOINT_TOLERANCE})"
    )]
    JointViolated {
        /// The joint.
        joint: String,
        /// Anchor separation (m).
        separation: f64,
        /// Angular error (rad).
        angle: f64,
    },
}

/// A final state accepted with a remark.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StateWarning {
    /// A body at rest touching nothing.
    #[error(
        "body {body:?} is at rest {height:.3} m up with nothing under it: a last frame's bodies should rest on something (fine as a mixed run's intermediate frame)"
    )]
    Floating {
        /// The body.
        body: String,
        /// Its centre's height (m) along `−gravity`.
        height: f64,
    },
    /// A column of more bodies resting on one another than the stepper solves reliably.
    #[error(
        "body {top:?} tops a column of {bodies} bodies resting on one another (more than {MAX_STACK}): the backward stepper's LCP may go unsolved and take seconds a step"
    )]
    TallStack {
        /// The column's top body.
        top: String,
        /// Bodies in the column.
        bodies: usize,
    },
}

/// Why [`check_scene`] refused a scene.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CheckError {
    /// The scene does not convert for the reverse stepper.
    #[error(transparent)]
    Convert(#[from] SceneConvertError),
    /// The given state is not one a backward run may start from.
    #[error(transparent)]
    State(#[from] StateError),
}

/// [`check_state`] of a concrete scene (a template instantiated with one seed), names included.
pub fn check_scene(scene: &Scene) -> Result<Vec<StateWarning>, CheckError> {
    let world = world_from_scene(scene)?;
    let bodies: Vec<String> = scene.bodies.iter().map(|b| b.name.clone()).collect();
    let joints: Vec<String> = scene.joints.iter().map(|j| j.name.clone()).collect();
    Ok(check_state(&world, &bodies, &joints)?)
}

/// Checks `world` as the given state of a backward or mixed run. `body_names[i]` and
/// `joint_names[j]` name `world.bodies[i]` and `world.joints[j]` (as
/// [`crate::scene::world_from_scene`] builds them); a missing name is shown as `#i`.
/// Returns the warnings, or the first refusal (overlaps before joints, lowest body first).
pub fn check_state(
    world: &World,
    body_names: &[String],
    joint_names: &[String],
) -> Result<Vec<StateWarning>, StateError> {
    let name =
        |names: &[String], i: usize| names.get(i).cloned().unwrap_or_else(|| format!("#{i}"));
    let mut probe = world.clone();
    probe.params.prediction = SUPPORT_DISTANCE;
    let (set, _) = probe.detect_contacts();

    // Overlaps: the deepest one per body, lowest body first.
    let mut deepest: Option<(usize, Partner, f64)> = None;
    for c in &set.contacts {
        let depth = -c.dist;
        if depth > OVERLAP_TOLERANCE && deepest.is_none_or(|(b, _, d)| (c.body, -depth) < (b, -d)) {
            deepest = Some((c.body, c.partner, depth));
        }
    }
    if let Some((b, partner, depth)) = deepest {
        return Err(StateError::Overlap {
            body: name(body_names, b),
            other: match partner {
                Partner::Body(p) => Other::Body(name(body_names, p)),
                Partner::Static(k) => Other::Static(k),
            },
            depth,
        });
    }

    for (i, j) in world.joints.iter().enumerate() {
        let rows = j.rows(i, &world.bodies);
        let norm = |r: &[crate::JointRow]| r.iter().map(|r| r.error * r.error).sum::<f64>().sqrt();
        let separation = norm(rows.get(..3).unwrap_or(&[]));
        let angle = norm(rows.get(3..).unwrap_or(&[]));
        if !(separation <= JOINT_TOLERANCE && angle <= JOINT_TOLERANCE) {
            return Err(StateError::JointViolated {
                joint: name(joint_names, i),
                separation,
                angle,
            });
        }
    }

    // Bodies at rest that touch nothing and hang on no joint.
    let mut supported = vec![false; world.bodies.len()];
    for c in &set.contacts {
        if let Some(s) = supported.get_mut(c.body) {
            *s = true;
        }
        if let Partner::Body(p) = c.partner
            && let Some(s) = supported.get_mut(p)
        {
            *s = true;
        }
    }
    for j in &world.joints {
        for b in std::iter::once(j.body1).chain(j.body2) {
            if let Some(s) = supported.get_mut(b) {
                *s = true;
            }
        }
    }
    let up = (-world.gravity)
        .try_normalize(1e-12)
        .unwrap_or(nalgebra::Vector3::z());
    let mut warnings: Vec<StateWarning> = world
        .bodies
        .iter()
        .enumerate()
        .filter(|(i, b)| {
            !supported[*i] && b.linvel.norm() < REST_SPEED && b.angvel.norm() < REST_SPEED
        })
        .map(|(i, b)| StateWarning::Floating {
            body: name(body_names, i),
            height: up.dot(&b.position),
        })
        .collect();
    if let Some((top, bodies)) = tallest_column(world, &set.contacts, &up)
        && bodies > MAX_STACK
    {
        warnings.push(StateWarning::TallStack {
            top: name(body_names, top),
            bodies,
        });
    }
    Ok(warnings)
}

/// The top body of the tallest column of bodies resting on one another (contacts within 45°
/// of `up` between bodies, the higher centre resting on the lower), and how many bodies it
/// holds, itself included. `None` without bodies.
fn tallest_column(
    world: &World,
    contacts: &[crate::contact::Contact],
    up: &nalgebra::Vector3<f64>,
) -> Option<(usize, usize)> {
    let n = world.bodies.len();
    let height = |b: usize| {
        world
            .bodies
            .get(b)
            .map_or(0.0, |body| up.dot(&body.position))
    };
    // Per body, the bodies it rests on.
    let mut below: Vec<Vec<usize>> = vec![Vec::new(); n];
    for c in contacts {
        let Partner::Body(p) = c.partner else {
            continue;
        };
        if c.normal.dot(up).abs() < RESTING_COS || c.body >= n || p >= n {
            continue;
        }
        let (upper, lower) = if height(c.body) > height(p) {
            (c.body, p)
        } else {
            (p, c.body)
        };
        below[upper].push(lower);
    }
    // Lowest first, so a body's supports are counted before it.
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| height(a).total_cmp(&height(b)));
    let mut depth = vec![1usize; n];
    for &b in &order {
        let d = below[b].iter().map(|&l| depth[l] + 1).max().unwrap_or(1);
        depth[b] = d;
    }
    (0..n)
        .max_by_key(|&b| (depth[b], std::cmp::Reverse(b)))
        .map(|b| (b, depth[b]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{builtin, world_from_toml};
    use mwb_core::scene::SceneTemplate;

    fn names(text: &str) -> (Vec<String>, Vec<String>) {
        match SceneTemplate::parse(text, "t.toml") {
            Ok(t) => {
                let s = t.instantiate(0);
                (
                    s.bodies.iter().map(|b| b.name.clone()).collect(),
                    s.joints.iter().map(|j| j.name.clone()).collect(),
                )
            }
            Err(e) => panic!("{e}"),
        }
    }

    fn check(text: &str) -> Result<Vec<StateWarning>, StateError> {
        match SceneTemplate::parse(text, "t.toml") {
            Ok(t) => match check_scene(&t.instantiate(0)) {
                Ok(w) => Ok(w),
                Err(CheckError::State(e)) => Err(e),
                Err(e) => panic!("{e}"),
            },
            Err(e) => panic!("{e}"),
        }
    }

    const HEAD: &str = r#"
name = "t"
[[material]]
name = "m"
[[static]]
name = "ground"
shape = "plane"
normal = [0, 1, 0]
material = "m"
"#;

    fn boxes(a: f64, b: f64) -> String {
        format!(
            "{HEAD}
[[body]]
name = \"a\"
shape = \"box\"
size = [0.2, 0.2, 0.2]
material = \"m\"
position = [{a}, 0.1, 0]

[[body]]
name = \"b\"
shape = \"box\"
size = [0.2, 0.2, 0.2]
material = \"m\"
position = [{b}, 0.1, 0]
"
        )
    }

    #[test]
    fn shipped_final_states_pass_without_warnings() {
        for (name, text) in builtin::ALL
            .iter()
            .filter(|(n, _)| *n != "lorem" && *n != "balls")
        {
            let world = match world_from_toml(text, name) {
                Ok(w) => w,
                Err(e) => panic!("{name}: {e}"),
            };
            let (b, j) = names(text);
            let warnings = check_state(&world, &b, &j);
            assert_eq!(warnings, Ok(vec![]), "{name}");
        }
    }

    #[test]
    fn overlapping_bodies_are_refused_by_name() {
        assert_eq!(check(&boxes(0.0, 0.3)), Ok(vec![]));
        match check(&boxes(0.0, 0.15)) {
            Err(StateError::Overlap { body, other, depth }) => {
                assert_eq!(body, "a");
                assert_eq!(other, Other::Body("b".into()));
                assert!((depth - 0.05).abs() < 1e-6, "{depth}");
            }
            other => panic!("{other:?}"),
        }
        // Sunk 5 cm into the ground.
        let sunk =
            boxes(0.0, 0.3).replacen("position = [0.3, 0.1, 0]", "position = [0.3, 0.05, 0]", 1);
        match check(&sunk) {
            Err(e @ StateError::Overlap { .. }) => {
                let text = e.to_string();
                assert!(
                    text.contains("\"b\"") && text.contains("static shape #0"),
                    "{text}"
                );
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_body_at_rest_in_mid_air_is_warned_by_name() {
        let floating =
            boxes(0.0, 0.3).replacen("position = [0.3, 0.1, 0]", "position = [0.3, 0.5, 0]", 1);
        assert_eq!(
            check(&floating),
            Ok(vec![StateWarning::Floating {
                body: "b".into(),
                height: 0.5
            }])
        );
        // Moving, it is an intermediate frame: no warning.
        let moving = floating.replacen(
            "position = [0.3, 0.5, 0]",
            "position = [0.3, 0.5, 0]\nlinvel = [0, 1, 0]",
            1,
        );
        assert_eq!(check(&moving), Ok(vec![]));
    }

    /// `count` boxes of 0.2 m stacked on the ground, named "k0" (bottom) … .
    fn column(count: usize) -> String {
        let mut text = HEAD.to_owned();
        for k in 0..count {
            text += &format!(
                "\n[[body]]\nname = \"k{k}\"\nshape = \"box\"\nsize = [0.2, 0.2, 0.2]\nmaterial = \"m\"\nposition = [0, {}, 0]\n",
                0.1 + 0.2 * k as f64
            );
        }
        text
    }

    #[test]
    fn a_stack_taller_than_the_stepper_solves_is_warned_by_its_top() {
        assert_eq!(check(&column(MAX_STACK)), Ok(vec![]));
        assert_eq!(
            check(&column(MAX_STACK + 1)),
            Ok(vec![StateWarning::TallStack {
                top: format!("k{MAX_STACK}"),
                bodies: MAX_STACK + 1
            }])
        );
        // Side by side, touching, they are no column.
        let mut row = HEAD.to_owned();
        for k in 0..=MAX_STACK {
            row += &format!(
                "\n[[body]]\nname = \"r{k}\"\nshape = \"box\"\nsize = [0.2, 0.2, 0.2]\nmaterial = \"m\"\nposition = [{}, 0.1, 0]\n",
                0.2 * k as f64
            );
        }
        assert_eq!(check(&row), Ok(vec![]));
    }

    #[test]
    fn a_violated_joint_is_refused_by_name() {
        let joined = |y: f64| {
            format!(
                "{}
[[joint]]
name = \"pin\"
kind = \"spherical\"
body1 = \"a\"
body2 = \"b\"
anchor1 = [0.15, 0, 0]
anchor2 = [-0.15, {y}, 0]
",
                boxes(0.0, 0.3)
            )
        };
        assert_eq!(check(&joined(0.0)), Ok(vec![]));
        match check(&joined(0.02)) {
            Err(StateError::JointViolated {
                joint, separation, ..
            }) => {
                assert_eq!(joint, "pin");
                assert!((separation - 0.02).abs() < 1e-9, "{separation}");
            }
            other => panic!("{other:?}"),
        }
    }
}
