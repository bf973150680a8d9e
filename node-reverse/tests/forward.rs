//! Analytic checks of the forward stepper (§3.3–3.6) and bit-exact determinism.

use mwb_reverse::{Body, Material, StaticBody, World};
use nalgebra::{UnitQuaternion, Vector3};

const G: f64 = 9.81;

fn ground(friction: f64, restitution: f64) -> StaticBody {
    StaticBody::plane(Vector3::z(), 0.0)
        .expect("a unit plane normal is valid")
        .with_material(Material {
            friction,
            restitution,
        })
}

fn unit_box(z: f64, material: Material) -> Body {
    Body::cuboid(Vector3::new(0.5, 0.5, 0.5), 1.0)
        .expect("positive extents")
        .with_material(material)
        .at(Vector3::new(0.0, 0.0, z), UnitQuaternion::identity())
}

/// A box sliding at `v` on a plane stops after `v² / (2 μ g)`.
#[test]
fn sliding_box_stops_after_v2_over_2_mu_g() {
    let mu = 0.5;
    let v0 = 2.0;
    let dt = 1.0 / 240.0;
    let mat = Material {
        friction: mu,
        restitution: 0.0,
    };
    let mut world = World::new();
    world.add_static(ground(mu, 0.0));
    let b = world.add_body(unit_box(0.5, mat).moving(Vector3::new(v0, 0.0, 0.0), Vector3::zeros()));
    let mut steps = 0;
    while world.bodies[b].linvel.norm() > 1e-9 && steps < 2000 {
        let report = world.step_forward(dt);
        assert!(report.all_solved(), "step {steps}: {:?}", report.islands);
        steps += 1;
    }
    let expected = v0 * v0 / (2.0 * mu * G);
    let got = world.bodies[b].position.x;
    let rel = (got - expected).abs() / expected;
    eprintln!(
        "sliding box: stop distance {got:.5} m, v²/2μg = {expected:.5} m, rel err {rel:.4}, {steps} steps"
    );
    assert!(rel < 0.02, "stop distance {got} vs {expected}");
    // It neither sank nor tipped.
    assert!((world.bodies[b].position.z - 0.5).abs() < 1e-6);
    assert!(world.bodies[b].orientation.angle() < 1e-6);
    assert!(world.bodies[b].position.y.abs() < 1e-9);
}

/// A ball dropped from `h` with restitution `e` rebounds to `e² h`.
#[test]
fn dropped_ball_rebounds_to_e2_h() {
    let (r, h, dt) = (0.1, 1.0, 1.0 / 1000.0);
    for e in [0.5, 0.8] {
        let mat = Material {
            friction: 0.3,
            restitution: e,
        };
        let mut world = World::new();
        world.add_static(ground(0.3, e));
        let b = world.add_body(
            Body::ball(r, 1.0)
                .expect("positive radius")
                .with_material(mat)
                .at(Vector3::new(0.0, 0.0, r + h), UnitQuaternion::identity()),
        );
        let mut bounced = false;
        let mut apex = 0.0f64;
        for _ in 0..3000 {
            let report = world.step_forward(dt);
            assert!(report.all_solved());
            let body = &world.bodies[b];
            if !bounced && body.linvel.z > 0.0 {
                bounced = true;
            }
            if bounced {
                apex = apex.max(body.position.z - r);
                if body.linvel.z < 0.0 {
                    break;
                }
            }
        }
        let expected = e * e * h;
        let rel = (apex - expected).abs() / expected;
        eprintln!("ball e = {e}: rebound {apex:.5} m, e²h = {expected:.5} m, rel err {rel:.4}");
        assert!(bounced);
        assert!(rel < 0.03, "rebound {apex} vs {expected}");
    }
}

/// A box placed on a plane stays put: no drift, no creep, no jitter.
#[test]
fn resting_box_does_not_drift() {
    let mut world = World::new();
    world.add_static(ground(0.5, 0.5));
    let start = unit_box(
        0.5,
        Material {
            friction: 0.5,
            restitution: 0.5,
        },
    );
    let b = world.add_body(start.clone());
    for _ in 0..1000 {
        let report = world.step_forward(1.0 / 240.0);
        assert!(report.all_solved());
        assert_eq!(report.contacts.len(), 4);
    }
    let body = &world.bodies[b];
    let drift = (body.position - start.position).norm();
    eprintln!(
        "resting box: drift {drift:e} m, speed {:e}",
        body.linvel.norm()
    );
    assert!(drift < 1e-9);
    assert!(body.linvel.norm() < 1e-9 && body.angvel.norm() < 1e-9);
    assert!(body.orientation.angle() < 1e-9);
}

fn busy_scene() -> World {
    let mut world = World::new();
    world.add_static(ground(0.6, 0.3));
    let mat = Material {
        friction: 0.6,
        restitution: 0.3,
    };
    for k in 0..3 {
        let q = UnitQuaternion::from_euler_angles(0.1 * k as f64, 0.2, 0.05 * k as f64);
        world.add_body(
            Body::cuboid(Vector3::new(0.3, 0.2, 0.1), 1.0)
                .expect("positive extents")
                .with_material(mat)
                .at(Vector3::new(0.05 * k as f64, 0.0, 0.3 + 0.35 * k as f64), q)
                .moving(Vector3::new(0.3, 0.0, 0.0), Vector3::new(0.0, 1.0, 0.5)),
        );
    }
    world.add_body(
        Body::ball(0.15, 1.0)
            .expect("positive radius")
            .with_material(mat)
            .at(Vector3::new(0.6, 0.1, 0.8), UnitQuaternion::identity()),
    );
    world
}

/// Same inputs, same bytes: every state component of every body, every step.
#[test]
fn forward_stepping_is_bit_deterministic() {
    let mut a = busy_scene();
    let mut b = busy_scene();
    let mut contacts = 0;
    for step in 0..400 {
        let ra = a.step_forward(1.0 / 240.0);
        let rb = b.step_forward(1.0 / 240.0);
        contacts += ra.contacts.len();
        assert_eq!(ra, rb, "reports diverged at step {step}");
        for (i, (x, y)) in a.bodies.iter().zip(&b.bodies).enumerate() {
            let bits = |body: &Body| -> Vec<u64> {
                body.position
                    .iter()
                    .chain(body.orientation.coords.iter())
                    .chain(body.linvel.iter())
                    .chain(body.angvel.iter())
                    .map(|v| v.to_bits())
                    .collect()
            };
            assert_eq!(bits(x), bits(y), "body {i} diverged at step {step}");
        }
    }
    assert!(
        contacts > 100,
        "the scene should be contact-heavy ({contacts})"
    );
}

/// Rolling friction (§5.3.5, (5.15)–(5.18)): a ball rolling without slipping at `v₀` is slowed
/// only by the rolling-resistance torque `b N`, so it decelerates at `(b / r) g / (1 + 2/5)` and
/// stops after `v₀² / 2a`; without rolling rows it would roll forever.
#[test]
fn rolling_ball_stops_after_v2_over_2a() {
    let (r, v0, dt) = (0.1, 0.5, 1.0 / 240.0);
    let arm = 0.02 * r;
    let mat = Material {
        friction: 0.6,
        restitution: 0.0,
    };
    let rolling_ball = |arm: f64| {
        Body::ball(r, 1000.0)
            .expect("positive radius")
            .with_material(mat)
            .with_rolling_resistance(arm)
            .at(Vector3::new(0.0, 0.0, r), UnitQuaternion::identity())
            // Rolling without slipping along +x: ω = v / r about +y.
            .moving(Vector3::new(v0, 0.0, 0.0), Vector3::new(0.0, v0 / r, 0.0))
    };
    let mut world = World::new();
    world.add_static(ground(0.6, 0.0));
    let b = world.add_body(rolling_ball(arm));
    let mut steps = 0;
    while world.bodies[b].linvel.norm() > 1e-9 && steps < 20_000 {
        let report = world.step_forward(dt);
        assert!(report.all_solved(), "step {steps}: {:?}", report.islands);
        steps += 1;
    }
    let a = (arm / r) * G / 1.4;
    let expected = v0 * v0 / (2.0 * a);
    let got = world.bodies[b].position.x;
    let rel = (got - expected).abs() / expected;
    eprintln!(
        "rolling ball: stop distance {got:.4} m, v0²/2a = {expected:.4} m, rel err {rel:.4}, {steps} steps"
    );
    assert!(rel < 0.02, "stop distance {got} vs {expected}");
    assert!(
        world.bodies[b].angvel.norm() < 1e-6,
        "{:?}",
        world.bodies[b].angvel
    );
    assert!((world.bodies[b].position.z - r).abs() < 1e-6);

    // The same ball without rolling resistance keeps rolling.
    let mut free = World::new();
    free.add_static(ground(0.6, 0.0));
    let b = free.add_body(rolling_ball(0.0));
    for _ in 0..steps {
        free.step_forward(dt);
    }
    // (f32 contact normals cost it a few µm/s over the run, nothing like stopping.)
    assert!(
        (free.bodies[b].linvel.x - v0).abs() < 1e-4 * v0,
        "{:?}",
        free.bodies[b].linvel
    );
}
