//! Joints as equality rows of the step's LCP, forward and backward (§5.3.4).
//!
//! * a ball on a spherical joint swings with the small-angle period of a compound pendulum,
//!   conserves its energy, and keeps its joint together over long runs forward and backward;
//! * the round trip of §5.2 with joints active: a backward step, replayed forward with the
//!   same contacts, joint rows, Jacobian and recorded joint goals, returns the state it
//!   started from;
//! * a hinge keeps its axis, a weld keeps the relative pose;
//! * a jointed chain lying on the ground: contacts and joints in one LCP.

use mwb_core::scene::{BodyRef, SceneTemplate};
use mwb_reverse::scene::{builtin, world_from_scene, world_from_toml};
use mwb_reverse::{
    BackwardChoices, Body, JointType, Material, SceneConvertError, StaticBody, World,
};
use nalgebra::{UnitQuaternion, Vector3};
use std::f64::consts::PI;

const DT: f64 = 1.0 / 240.0;
const G: f64 = 9.81;

/// A ball of radius `r` hanging from the world point at the origin on a massless rod of length
/// `l` (a spherical joint at the rod's top, the rod's bottom at the ball's centre), pulled
/// aside by `theta` in the x–z plane.
fn pendulum(l: f64, r: f64, theta: f64) -> World {
    let mut world = World::new();
    let ball = world.add_body(Body::ball(r, 1000.0).unwrap().at(
        Vector3::new(l * theta.sin(), 0.0, -l * theta.cos()),
        UnitQuaternion::identity(),
    ));
    let joint = world
        .joint_at(JointType::Spherical, ball, None, Vector3::zeros())
        .unwrap();
    world.add_joint(joint).unwrap();
    world
}

/// Times at which `x` crosses zero going down, linearly interpolated, over `steps` steps.
fn downward_crossings(world: &mut World, steps: usize, dt: f64) -> Vec<f64> {
    let mut out = Vec::new();
    let mut prev = world.bodies[0].position.x;
    for k in 0..steps {
        let report = world.step_forward(dt);
        assert!(report.all_solved(), "step {k}: {:?}", report.islands);
        let x = world.bodies[0].position.x;
        if prev > 0.0 && x <= 0.0 {
            out.push((k as f64 + prev / (prev - x)) * dt);
        }
        prev = x;
    }
    out
}

#[test]
fn pendulum_period_matches_small_angle_formula() {
    let (l, r, theta) = (1.0, 0.05, 0.02);
    let mut world = pendulum(l, r, theta);
    let crossings = downward_crossings(&mut world, 240 * 25, DT);
    assert!(crossings.len() >= 10, "{crossings:?}");
    let periods = crossings.len() - 1;
    let measured = (crossings[periods] - crossings[0]) / periods as f64;
    // Compound pendulum (the ball turns with the rod): I_pivot = m (L² + 2 r² / 5).
    let compound = 2.0 * PI * ((l * l + 0.4 * r * r) / (G * l)).sqrt();
    let simple = 2.0 * PI * (l / G).sqrt();
    let err = (measured - compound).abs() / compound;
    eprintln!(
        "pendulum period {measured:.6} s, compound {compound:.6} s (rel err {err:.2e}), \
         2π√(L/g) = {simple:.6} s (rel {:.2e})",
        (measured - simple).abs() / simple
    );
    // Finite amplitude adds θ²/16 = 2.5e-5; the symplectic step O((ω Δt)²) ~ 1e-5.
    assert!(err < 1e-4, "period rel err {err:e}");
    assert!(world.joint_separation() < 1e-6);
}

#[test]
fn pendulum_energy_and_joint_drift_forward_and_backward() {
    let (l, r, theta) = (1.0, 0.05, 0.6);
    let mut world = pendulum(l, r, theta);
    let m = 1.0 / world.bodies[0].inv_mass;
    let e0 = world.energy();
    let scale = m * G * l * (1.0 - theta.cos());
    let steps = 240 * 30;
    let (mut max_de, mut max_sep) = (0.0f64, 0.0f64);
    for k in 0..steps {
        assert!(world.step_forward(DT).all_solved(), "forward step {k}");
        max_de = max_de.max((world.energy() - e0).abs() / scale);
        max_sep = max_sep.max(world.joint_separation());
    }
    eprintln!("forward 30 s: energy drift {max_de:.2e} of the swing, separation {max_sep:.2e} m");
    assert!(max_de < 0.02, "energy drift {max_de:e}");
    assert!(max_sep < 2e-4, "separation {max_sep:e}");

    let e1 = world.energy();
    let (mut back_de, mut back_sep, mut residual) = (0.0f64, 0.0f64, 0.0f64);
    for k in 0..steps {
        let report = world.step_backward(DT, &BackwardChoices::default());
        assert!(
            report.all_solved(),
            "backward step {k}: {:?}",
            report.islands
        );
        back_de = back_de.max((world.energy() - e1).abs() / scale);
        back_sep = back_sep.max(world.joint_separation());
        residual = residual.max(report.forward_residual);
    }
    eprintln!(
        "backward 30 s: energy drift {back_de:.2e} of the swing, separation {back_sep:.2e} m, \
         forward residual {residual:.2e} m/s"
    );
    assert!(back_de < 0.02, "backward energy drift {back_de:e}");
    assert!(back_sep < 2e-4, "backward separation {back_sep:e}");
    // The reversed Baumgarte sign leaves ≈ 2 β |e| / Δt per row (module docs of `backward`).
    assert!(residual < 0.1, "forward residual {residual:e}");
    // Backward for as long as forward: back near the release point, at rest.
    let b = &world.bodies[0];
    assert!(
        (b.position.x - l * theta.sin()).abs() < 0.05,
        "{:?}",
        b.position
    );
    assert!(b.linvel.norm() < 0.1, "{:?}", b.linvel);
}

/// Without Baumgarte the drift grows; with the reversed sign backward it is held; with the
/// forward sign backward it would grow — the point of §5.3.4.
#[test]
fn backward_baumgarte_sign_matters() {
    // Forward with the usual β, then backward with `back` as β: negative is the forward
    // sign used backward, which makes the error grow as time runs back.
    let run = |back: f64| {
        let mut world = pendulum(1.0, 0.05, 1.0);
        for _ in 0..240 * 5 {
            assert!(world.step_forward(DT).all_solved());
        }
        world.params.joint_erp = back;
        let mut sep = 0.0f64;
        for _ in 0..240 * 5 {
            if !world
                .step_backward(DT, &BackwardChoices::default())
                .all_solved()
            {
                return f64::INFINITY; // the run came apart
            }
            sep = sep.max(world.joint_separation());
        }
        sep
    };
    let reversed = run(0.2);
    let none = run(0.0);
    let wrong = run(-0.2);
    eprintln!(
        "backward separation: reversed sign {reversed:.2e}, none {none:.2e}, forward sign {wrong:.2e}"
    );
    assert!(reversed < 1e-3);
    assert!(none > 10.0 * reversed);
    assert!(wrong > none);
}

/// Checks the round trip of §5.2 at every step of a backward run of `steps` steps; returns the
/// largest relative velocity error, position error and forward residual.
fn round_trip(name: &str, world: &mut World, steps: usize) -> (f64, f64, f64) {
    let (mut vel, mut pos, mut res) = (0.0f64, 0.0f64, 0.0f64);
    for k in 0..steps {
        let at_t = world.clone();
        let back = world.step_backward(DT, &BackwardChoices::default());
        assert!(back.all_solved(), "{name} step {k}: {:?}", back.islands);
        assert_eq!(back.joint_impulses.len(), back.contacts.joints.len());
        // The recorded goals make the replay end at v_t exactly (see `backward` docs); the
        // residual against the forward Baumgarte goals is measured separately.
        let mut replay = world.clone();
        let fwd = replay.step_forward_with(&back.contacts, DT);
        assert!(
            fwd.all_solved(),
            "{name} step {k}: forward {:?}",
            fwd.islands
        );
        let scale = at_t
            .bodies
            .iter()
            .flat_map(|b| b.linvel.iter().chain(b.angvel.iter()))
            .fold(G * DT, |m, v| m.max(v.abs()));
        for (i, (want, got)) in at_t.bodies.iter().zip(&replay.bodies).enumerate() {
            let dv = (want.linvel - got.linvel)
                .amax()
                .max((want.angvel - got.angvel).amax());
            let dx = (want.position - got.position).amax();
            let dq = want.orientation.angle_to(&got.orientation);
            assert!(dv / scale < 1e-6, "{name} step {k} body {i}: dv {dv:e}");
            assert!(
                dx < 1e-12 && dq < 1e-12,
                "{name} step {k} body {i}: {dx:e} {dq:e}"
            );
            vel = vel.max(dv / scale);
            pos = pos.max(dx).max(dq);
        }
        res = res.max(back.forward_residual);
    }
    (vel, pos, res)
}

#[test]
fn round_trip_with_joints() {
    // A double pendulum: a box on a hinge to the world, a ball on a spherical joint below it.
    let mut world = World::new();
    let upper = world.add_body(
        Body::cuboid(Vector3::new(0.05, 0.05, 0.4), 500.0)
            .unwrap()
            .at(Vector3::new(0.0, 0.0, -0.4), UnitQuaternion::identity())
            .moving(Vector3::zeros(), Vector3::new(0.0, 2.0, 0.0)),
    );
    let lower = world.add_body(
        Body::ball(0.1, 500.0)
            .unwrap()
            .at(Vector3::new(0.0, 0.0, -1.0), UnitQuaternion::identity()),
    );
    let hinge = world
        .joint_at(
            JointType::Revolute { axis: Vector3::y() },
            upper,
            None,
            Vector3::zeros(),
        )
        .unwrap();
    world.add_joint(hinge).unwrap();
    let ball = world
        .joint_at(
            JointType::Spherical,
            lower,
            Some(upper),
            Vector3::new(0.0, 0.0, -0.8),
        )
        .unwrap();
    world.add_joint(ball).unwrap();
    // Let it swing a while forward so that the state at t came from a forward step.
    for _ in 0..240 {
        assert!(world.step_forward(DT).all_solved());
    }
    let (vel, pos, res) = round_trip("double pendulum", &mut world, 480);
    eprintln!("double pendulum round trip: vel rel {vel:.2e}, pos {pos:.2e}, residual {res:.2e}");
    assert!(world.joint_separation() < 1e-3);
    assert!(world.joint_angular_error() < 1e-3);
}

#[test]
fn first_backward_step_of_a_forward_state_is_forward_valid() {
    let mut world = pendulum(1.0, 0.05, 0.8);
    for _ in 0..100 {
        world.step_forward(DT);
    }
    let back = world.step_backward(DT, &BackwardChoices::default());
    // x_{t−Δt} is exactly where the forward step started, so J v_t met its Baumgarte goal.
    assert!(
        back.forward_residual < 1e-9,
        "residual {:e}",
        back.forward_residual
    );
}

#[test]
fn hinge_keeps_its_axis_and_weld_keeps_its_pose() {
    // A gate: a box hinged to the world about z at one edge, kicked with an off-axis spin.
    let mut world = World::new();
    world.gravity = Vector3::new(0.0, 0.0, -G);
    let gate = world.add_body(
        Body::cuboid(Vector3::new(0.5, 0.05, 0.5), 300.0)
            .unwrap()
            .at(Vector3::new(0.5, 0.0, 1.0), UnitQuaternion::identity())
            .moving(Vector3::new(0.0, 1.0, 0.3), Vector3::new(0.7, -0.4, 2.0)),
    );
    let hinge = world
        .joint_at(
            JointType::Revolute { axis: Vector3::z() },
            gate,
            None,
            Vector3::new(0.0, 0.0, 1.0),
        )
        .unwrap();
    world.add_joint(hinge).unwrap();
    // Two boxes welded together, tumbling in free flight.
    let a = world.add_body(
        Body::cuboid(Vector3::new(0.2, 0.1, 0.1), 500.0)
            .unwrap()
            .at(Vector3::new(5.0, 0.0, 10.0), UnitQuaternion::identity())
            .moving(Vector3::new(1.0, 0.0, 2.0), Vector3::new(3.0, 1.0, -2.0)),
    );
    let b = world.add_body(
        Body::cuboid(Vector3::new(0.1, 0.1, 0.3), 500.0)
            .unwrap()
            .at(
                Vector3::new(5.3, 0.0, 10.2),
                UnitQuaternion::from_euler_angles(0.3, 0.2, 0.1),
            )
            .moving(Vector3::new(1.0, 0.0, 2.0), Vector3::new(3.0, 1.0, -2.0)),
    );
    let weld = world
        .joint_at(JointType::Fixed, a, Some(b), Vector3::new(5.2, 0.0, 10.1))
        .unwrap();
    world.add_joint(weld).unwrap();
    let rel = |w: &World| {
        let (p, q) = (&w.bodies[a], &w.bodies[b]);
        (
            p.orientation.inverse() * (q.position - p.position),
            p.orientation.inverse() * q.orientation,
        )
    };
    let (d0, q0) = rel(&world);
    let check = |w: &World, when: &str| {
        let axis = w.bodies[gate].orientation * Vector3::z();
        let tilt = axis.cross(&Vector3::z()).norm();
        let (d, q) = rel(w);
        let dd = (d - d0).norm();
        let dq = q.angle_to(&q0);
        assert!(tilt < 2e-3, "{when}: hinge tilt {tilt:e}");
        assert!(dd < 2e-3 && dq < 2e-3, "{when}: weld {dd:e} {dq:e}");
        (tilt, dd, dq)
    };
    let mut worst = (0.0f64, 0.0f64, 0.0f64);
    for k in 0..240 * 4 {
        let report = world.step_forward(DT);
        assert!(report.all_solved(), "forward {k}: {:?}", report.islands);
        // The first steps project the off-axis spin away; judge after them.
        if k > 10 {
            let (t, d, q) = check(&world, "forward");
            worst = (worst.0.max(t), worst.1.max(d), worst.2.max(q));
        }
    }
    let spin = world.bodies[gate].angvel;
    assert!(spin.x.abs() < 1e-6 && spin.y.abs() < 1e-6, "{spin:?}");
    for k in 0..240 * 4 {
        let report = world.step_backward(DT, &BackwardChoices::default());
        assert!(report.all_solved(), "backward {k}");
        let (t, d, q) = check(&world, "backward");
        worst = (worst.0.max(t), worst.1.max(d), worst.2.max(q));
    }
    eprintln!(
        "hinge tilt {:.2e} rad, weld offset {:.2e} m / {:.2e} rad",
        worst.0, worst.1, worst.2
    );
}

/// Three balls joined by spherical joints (rods of 5 cm between their surfaces), dropped onto
/// the ground: the contacts and the joint rows of the chain are one island and one LCP.
/// (Boxes, with four coplanar corners each, add redundant rows the pivoting solver does not
/// always get through with the joint rows forced active; see the crate docs.)
fn chain_on_ground() -> World {
    let mut world = World::new();
    let mat = Material {
        friction: 0.5,
        restitution: 0.0,
    };
    world.add_static(
        StaticBody::plane(Vector3::z(), 0.0)
            .unwrap()
            .with_material(mat),
    );
    let mut prev = None;
    for i in 0..3 {
        let x = 0.25 * i as f64;
        let z = 0.1 + 0.01 * i as f64;
        let body = world.add_body(
            Body::ball(0.1, 500.0)
                .unwrap()
                .with_material(mat)
                .at(Vector3::new(x, 0.0, z), UnitQuaternion::identity()),
        );
        if let Some(p) = prev {
            let joint = world
                .joint_at(
                    JointType::Spherical,
                    body,
                    Some(p),
                    Vector3::new(x - 0.125, 0.0, z),
                )
                .unwrap();
            world.add_joint(joint).unwrap();
        }
        prev = Some(body);
    }
    world
}

#[test]
fn jointed_chain_rests_on_the_ground_in_one_lcp() {
    let mut world = chain_on_ground();
    let mut joined = false;
    for k in 0..240 * 2 {
        let report = world.step_forward(DT);
        assert!(report.all_solved(), "step {k}: {:?}", report.islands);
        if !report.contacts.contacts.is_empty() {
            // One island holding every body, the contacts and all six joint rows.
            assert_eq!(report.contacts.islands.len(), 1, "step {k}");
            let island = &report.contacts.islands[0];
            assert_eq!(island.bodies, vec![0, 1, 2]);
            assert_eq!(island.joints.len(), 6);
            joined = true;
        }
    }
    assert!(joined);
    for b in &world.bodies {
        assert!(b.linvel.norm() < 1e-3, "{:?}", b.linvel);
        assert!((b.position.z - 0.1).abs() < 2e-3, "{:?}", b.position);
    }
    let sep = world.joint_separation();
    eprintln!("chain at rest: joint separation {sep:.2e} m");
    assert!(sep < 1e-3);
    // Backward from rest: contacts and joints together, round trip at every step.
    let (vel, pos, res) = round_trip("chain", &mut world, 240);
    eprintln!("chain round trip: vel rel {vel:.2e}, pos {pos:.2e}, residual {res:.2e}");
    assert!(res < 1e-6, "residual {res:e}");
}

#[test]
fn islands_join_jointed_bodies_without_contacts() {
    let mut world = chain_on_ground();
    for b in &mut world.bodies {
        b.position.z += 5.0; // far above the ground
    }
    let (set, _) = world.detect_contacts();
    assert!(set.contacts.is_empty());
    assert_eq!(set.islands.len(), 1);
    assert_eq!(set.islands[0].bodies, vec![0, 1, 2]);
    assert_eq!(set.joints.len(), 6);
}

#[test]
fn add_joint_refuses_bad_references() {
    let mut world = pendulum(1.0, 0.1, 0.0);
    let bad = mwb_reverse::Joint::spherical(3, None, Vector3::zeros(), Vector3::zeros());
    assert!(world.add_joint(bad).is_err());
    let same = mwb_reverse::Joint::spherical(0, Some(0), Vector3::zeros(), Vector3::zeros());
    assert!(world.add_joint(same).is_err());
    assert!(
        world
            .joint_at(
                JointType::Revolute {
                    axis: Vector3::zeros()
                },
                0,
                None,
                Vector3::zeros()
            )
            .is_err()
    );
    assert!(
        world
            .joint_at(JointType::Spherical, 0, Some(7), Vector3::zeros())
            .is_err()
    );
}

#[test]
fn gate_scene_runs_backward() {
    let mut world = world_from_toml(builtin::GATE, "scenes/reverse/gate.toml").unwrap();
    let (vel, pos, res) = round_trip("gate", &mut world, 120);
    eprintln!("gate round trip: vel rel {vel:.2e}, pos {pos:.2e}, residual {res:.2e}");
    assert!(world.joint_separation() < 1e-6);
}

#[test]
fn scene_joints_convert_and_bad_references_name_the_field() {
    let world = world_from_toml(builtin::GATE, "scenes/reverse/gate.toml").unwrap();
    assert!(!world.joints.is_empty());
    // The shipped final state satisfies its joints.
    assert!(
        world.joint_separation() < 1e-9,
        "{}",
        world.joint_separation()
    );
    assert!(world.joint_angular_error() < 1e-9);

    let template = SceneTemplate::parse(builtin::GATE, "gate.toml").unwrap();
    let mut scene = template.instantiate(0);
    scene.joints[0].body1 = BodyRef::Body(99);
    match world_from_scene(&scene) {
        Err(SceneConvertError::Joint { field, .. }) => assert_eq!(field, "body1"),
        other => panic!("{other:?}"),
    }
    let mut scene = template.instantiate(0);
    scene.joints[0].body1 = BodyRef::World;
    scene.joints[0].body2 = BodyRef::World;
    match world_from_scene(&scene) {
        Err(SceneConvertError::Joint { field, .. }) => assert_eq!(field, "body2"),
        other => panic!("{other:?}"),
    }
    let mut scene = template.instantiate(0);
    scene.joints[0].anchor2 = [f64::NAN, 0.0, 0.0];
    match world_from_scene(&scene) {
        Err(SceneConvertError::Joint { field, .. }) => assert_eq!(field, "anchor2"),
        other => panic!("{other:?}"),
    }
}
