//! The defining test of the backward step (§5.2): a state at `t − Δt` is plausible when a
//! forward step from it gives back the state at `t`. At every step of long backward runs we
//! replay the backward step forward with the *same* contact set and Jacobian and check that
//!
//! * the backward impulses satisfy the forward LCP conditions (complementarity residual),
//! * the replayed velocities match within 1e-6 (relative to the world's speed scale),
//! * the replayed positions and orientations match to round-off.

use mwb_reverse::{
    BackwardChoices, Body, BodyHint, FrictionCase, Material, NormalCase, StaticBody, World,
};
use nalgebra::{UnitQuaternion, Vector3};

const DT: f64 = 1.0 / 240.0;

#[derive(Debug, Default)]
struct Stats {
    steps: usize,
    max_vel_rel: f64,
    max_pos: f64,
    max_residual: f64,
    contacts: usize,
    elastic: usize,
    sliding: usize,
}

/// Runs `steps` backward steps from `world`, checking the round trip at each; `choices(k)` gives
/// the choices of step `k`.
fn backward_run(
    name: &str,
    world: &mut World,
    dt: f64,
    steps: usize,
    choices: impl Fn(usize) -> BackwardChoices,
) -> Stats {
    backward_run_within(name, world, dt, steps, choices, (1e-9, 1e-12))
}

/// [`backward_run`] with given bounds on the forward residual (m/s) and on the replayed
/// positions (m, rad).
fn backward_run_within(
    name: &str,
    world: &mut World,
    dt: f64,
    steps: usize,
    choices: impl Fn(usize) -> BackwardChoices,
    (residual_tol, pos_tol): (f64, f64),
) -> Stats {
    let mut stats = Stats::default();
    for k in 0..steps {
        let at_t = world.clone();
        let report = world.step_backward(dt, &choices(k));
        if std::env::var("RT_DEBUG").is_ok()
            && (!report.all_solved() || report.forward_residual > residual_tol)
        {
            for (c, (ch, i)) in report
                .contacts
                .contacts
                .iter()
                .zip(report.choices.iter().zip(&report.impulses))
            {
                eprintln!(
                    "{} {:?} p {:?} n {:?} d {:e} {:?} {:?}",
                    c.body,
                    c.partner,
                    c.point.as_slice(),
                    c.normal.as_slice(),
                    c.dist,
                    ch,
                    i
                );
            }
            let mut probe = world.clone();
            for (pb, tb) in probe.bodies.iter_mut().zip(&at_t.bodies) {
                pb.linvel = tb.linvel;
                pb.angvel = tb.angvel;
            }
            for c in &report.contacts.contacts {
                let rel = probe.relative_velocity(c);
                eprintln!(
                    "v+_N {:e} |v+_T| {:e}",
                    c.normal.dot(&rel),
                    (rel - c.normal * c.normal.dot(&rel)).norm()
                );
            }
            for b in &at_t.bodies {
                eprintln!(
                    "body {:?} v {:?} w {:?}",
                    b.position.as_slice(),
                    b.linvel.as_slice(),
                    b.angvel.as_slice()
                );
            }
        }
        assert!(report.all_solved(), "{name} step {k}: {:?}", report.islands);
        assert_eq!(report.approaching_contacts, 0, "{name} step {k}");
        // The backward impulses solve the forward LCP at s_{t−Δt}.
        assert!(
            report.forward_residual < residual_tol,
            "{name} step {k}: forward residual {:e}",
            report.forward_residual
        );
        let residual = world.forward_residual(&report.contacts, &report.impulses, dt);
        assert_eq!(residual.to_bits(), report.forward_residual.to_bits());

        // Replay forward with the same contact set and Jacobian.
        let mut replay = world.clone();
        let fwd = replay.step_forward_with(&report.contacts, dt);
        assert!(
            fwd.all_solved(),
            "{name} step {k}: forward {:?}",
            fwd.islands
        );
        let scale = at_t
            .bodies
            .iter()
            .flat_map(|b| b.linvel.iter().chain(b.angvel.iter()))
            .fold(9.81 * dt, |m, v| m.max(v.abs()));
        for (i, (want, got)) in at_t.bodies.iter().zip(&replay.bodies).enumerate() {
            let dv = (want.linvel - got.linvel)
                .amax()
                .max((want.angvel - got.angvel).amax());
            let rel = dv / scale;
            let dx = (want.position - got.position).amax();
            let dq = want.orientation.angle_to(&got.orientation);
            assert!(
                rel < 1e-6,
                "{name} step {k} body {i}: velocity rel err {rel:e}"
            );
            assert!(
                dx < pos_tol && dq < pos_tol,
                "{name} step {k} body {i}: dx {dx:e} dq {dq:e}"
            );
            stats.max_vel_rel = stats.max_vel_rel.max(rel);
            stats.max_pos = stats.max_pos.max(dx).max(dq);
        }
        stats.max_residual = stats.max_residual.max(report.forward_residual);
        stats.contacts += report.contacts.len();
        stats.elastic += report
            .choices
            .iter()
            .zip(&report.impulses)
            .filter(|(c, i)| c.normal == NormalCase::Elastic && i.normal > 0.0)
            .count();
        stats.sliding += report
            .choices
            .iter()
            .zip(&report.impulses)
            .filter(|(c, i)| c.friction == FrictionCase::Sliding && i.normal > 0.0)
            .count();
        stats.steps += 1;
    }
    eprintln!("{name}: {stats:?}");
    stats
}

fn ground(material: Material) -> StaticBody {
    StaticBody::plane(Vector3::z(), 0.0)
        .expect("a unit plane normal is valid")
        .with_material(material)
}

/// Three 1 × 1 × 0.5 boxes stacked on the ground (z up), the top one moving at `top`.
fn stack_of_three(friction: f64, top: Vector3<f64>) -> World {
    let mat = Material {
        friction,
        restitution: 0.4,
    };
    let mut world = World::new();
    world.add_static(ground(mat));
    for k in 0..3 {
        let v = if k == 2 { top } else { Vector3::zeros() };
        world.add_body(
            Body::cuboid(Vector3::new(0.5, 0.5, 0.25), 1.0)
                .expect("positive extents")
                .with_material(mat)
                .at(
                    Vector3::new(0.0, 0.0, 0.25 + 0.5 * k as f64),
                    UnitQuaternion::identity(),
                )
                .moving(v, Vector3::zeros()),
        );
    }
    world
}

/// A box thrown spinning onto the ground, stepped forward 140 steps so it is mid-tumble.
fn tumbling_box() -> World {
    let mat = Material {
        friction: 0.5,
        restitution: 0.5,
    };
    let mut world = World::new();
    world.add_static(ground(mat));
    world.add_body(
        Body::cuboid(Vector3::new(0.3, 0.2, 0.1), 1.0)
            .expect("positive extents")
            .with_material(mat)
            .at(
                Vector3::new(0.0, 0.0, 0.6),
                UnitQuaternion::from_euler_angles(0.3, 0.2, 0.1),
            )
            .moving(Vector3::new(1.0, 0.0, 0.0), Vector3::new(1.0, 2.0, 0.0)),
    );
    for _ in 0..140 {
        world.step_forward(DT);
    }
    world
}

fn none(_: usize) -> BackwardChoices {
    BackwardChoices::default()
}

#[test]
fn sliding_box_round_trips() {
    let mat = Material {
        friction: 0.4,
        restitution: 0.5,
    };
    let mut world = World::new();
    world.add_static(ground(mat));
    world.add_body(
        Body::cuboid(Vector3::new(0.4, 0.3, 0.2), 1.0)
            .expect("positive extents")
            .with_material(mat)
            .at(
                Vector3::new(0.0, 0.0, 0.2),
                UnitQuaternion::from_euler_angles(0.0, 0.0, 0.3),
            )
            .moving(Vector3::new(1.0, 0.5, 0.0), Vector3::zeros()),
    );
    let stats = backward_run("sliding box", &mut world, DT, 300, none);
    assert!(
        stats.sliding >= 2 * 300,
        "friction should be maximal throughout"
    );
    // Backward, friction accelerates the box: v grows by μ g Δt per step.
    let speed = world.bodies[0].linvel.norm();
    let expected = 1.25f64.sqrt() + 0.4 * 9.81 * DT * 300.0;
    assert!(
        (speed - expected).abs() < 1e-6 * expected,
        "{speed} vs {expected}"
    );
}

#[test]
fn resting_box_starts_to_slide_and_lift_on_request() {
    let mat = Material {
        friction: 0.5,
        restitution: 0.5,
    };
    let mut world = World::new();
    world.add_static(ground(mat));
    world.add_body(
        Body::cuboid(Vector3::new(0.5, 0.5, 0.5), 1.0)
            .expect("positive extents")
            .with_material(mat)
            .at(Vector3::new(0.0, 0.0, 0.5), UnitQuaternion::identity()),
    );
    // Rest for 50 steps, then ask for a slide in +x (5.7) for a while, then let it run.
    let stats = backward_run("resting box", &mut world, DT, 300, |k| {
        let mut choices = BackwardChoices::default();
        if (50..60).contains(&k) {
            choices.hints.insert(
                0,
                BodyHint {
                    lift_off_speed: 0.0,
                    slide_velocity: Vector3::new(-0.05, 0.0, 0.0),
                },
            );
        }
        choices
    });
    assert!(stats.sliding > 0);
    assert!(
        world.bodies[0].linvel.x < -0.1,
        "{:?}",
        world.bodies[0].linvel
    );
}

#[test]
fn bouncing_ball_round_trips() {
    let mat = Material {
        friction: 0.3,
        restitution: 0.7,
    };
    let mut world = World::new();
    world.add_static(ground(mat));
    world.add_body(
        Body::ball(0.1, 1.0)
            .expect("positive radius")
            .with_material(mat)
            .at(Vector3::new(0.0, 0.0, 0.8), UnitQuaternion::identity())
            .moving(Vector3::new(0.8, 0.2, 0.0), Vector3::new(0.0, 0.0, 3.0)),
    );
    // Forward through two bounces, then backward through them again and beyond.
    let mut bounces = 0;
    let mut last_vz = 0.0;
    for _ in 0..400 {
        world.step_forward(DT);
        let vz = world.bodies[0].linvel.z;
        if last_vz < 0.0 && vz > 0.0 {
            bounces += 1;
        }
        last_vz = vz;
    }
    assert!(bounces >= 2, "{bounces}");
    let stats = backward_run("bouncing ball", &mut world, DT, 400, none);
    assert!(stats.elastic >= 2, "{stats:?}");
}

#[test]
fn stack_of_three_boxes_round_trips() {
    let mut world = stack_of_three(0.2, Vector3::new(0.05, 0.02, 0.0));
    // Backward, friction speeds the top box up; at 480 Hz its 300 steps (0.625 s) end before
    // its centre of mass leaves the middle box (a tipping box is not covered, see the crate
    // docs on the prediction band).
    let stats = backward_run("stack of 3", &mut world, DT / 2.0, 300, none);
    assert!(
        world.bodies[2].position.x > -0.5,
        "{:?}",
        world.bodies[2].position
    );
    assert!(stats.contacts >= 12 * 300, "{stats:?}");
    assert!(stats.sliding > 0);
}

#[test]
fn tumbling_box_round_trips() {
    let mut world = tumbling_box();
    let stats = backward_run("tumbling box", &mut world, DT, 300, none);
    assert!(stats.elastic > 0 && stats.sliding > 0, "{stats:?}");
}

/// The top box slides (backward in time) off the edge of the middle one and tips over it.
///
/// Known failure (step 132 of 300; step 104 before the look-ahead of `step_backward`): the
/// look-ahead keeps the pivoting edge contacts exactly at rest, but the velocity-level step
/// lets a pivoting body sink into its support by about `Δt² ω² r / 2` per backward step (the
/// mirror of the lift a forward step gives it), and once the tilted face is 0.5 mm inside the
/// middle box parry's face clipping produces two new contact points at the earlier poses that
/// approach at 3.8e-3 m/s. No forward step ends with an approaching contact in its set;
/// `BackwardReport::approaching_contacts` counts these. Needs a position-level answer.
#[test]
#[ignore = "known limitation: penetration drift of a pivoting box, see doc comment"]
fn box_tipping_off_a_stack_round_trips() {
    let mut world = stack_of_three(0.6, Vector3::new(0.3, 0.1, 0.0));
    let stats = backward_run("tipping stack", &mut world, DT, 300, none);
    assert!(
        world.bodies[2].orientation.angle() > 0.1,
        "{:?}",
        world.bodies[2]
    );
    assert!(stats.sliding > 0);
}

/// Backward stepping is deterministic too: same state, same choices, same bytes.
#[test]
fn backward_stepping_is_bit_deterministic() {
    let scene = tumbling_box;
    let (mut a, mut b) = (scene(), scene());
    for step in 0..200 {
        let ra = a.step_backward(DT, &BackwardChoices::default());
        let rb = b.step_backward(DT, &BackwardChoices::default());
        assert_eq!(ra, rb, "reports diverged at step {step}");
        for (x, y) in a.bodies.iter().zip(&b.bodies) {
            let bits = |body: &Body| -> Vec<u64> {
                body.position
                    .iter()
                    .chain(body.orientation.coords.iter())
                    .chain(body.linvel.iter())
                    .chain(body.angvel.iter())
                    .map(|v| v.to_bits())
                    .collect()
            };
            assert_eq!(bits(x), bits(y), "diverged at step {step}");
        }
    }
}

/// Rolling friction backward (§5.3.5): a rolling ball speeds up stepping backward (the
/// resistance run in reverse) at the analytic `(b / r) g / 1.4`, and every step round-trips.
#[test]
fn rolling_ball_round_trips() {
    let mat = Material {
        friction: 0.6,
        restitution: 0.5,
    };
    let (r, v0) = (0.1, 0.5);
    let arm = 0.02 * r;
    let mut world = World::new();
    world.add_static(ground(mat));
    world.add_body(
        Body::ball(r, 1000.0)
            .expect("positive radius")
            .with_material(mat)
            .with_rolling_resistance(arm)
            .at(Vector3::new(0.0, 0.0, r), UnitQuaternion::identity())
            .moving(Vector3::new(v0, 0.0, 0.0), Vector3::new(0.0, v0 / r, 0.0)),
    );
    // One second: the f32 noise grows with the distance from the origin.
    let steps = 240;
    // parry's f32 contact point under a spinning ball leaves 1e-8..1e-7 m/s of apparent slip, so
    // the residual bound is 1e-6 and positions match to 1e-8 (one step of that velocity
    // noise) here; velocities still round-trip to 1e-6 relative.
    let stats = backward_run_within("rolling ball", &mut world, DT, steps, none, (1e-6, 1e-8));
    assert!(stats.max_vel_rel < 1e-6, "{stats:?}");
    let expected = v0 + (arm / r) * 9.81 / 1.4 * DT * steps as f64;
    let ball = &world.bodies[0];
    assert!(
        (ball.linvel.x - expected).abs() < 1e-3 * expected,
        "{} vs {expected}",
        ball.linvel.x
    );
    // Still rolling without slipping, still on the ground.
    assert!((ball.angvel.y * r - ball.linvel.x).abs() < 1e-6 * expected);
    assert!((ball.position.z - r).abs() < 1e-6, "{:?}", ball.position);
}
