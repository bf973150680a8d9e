//! Backward runs (§5.3–5.4): determinism, mixed runs, the learned contact chain, the energy
//! metric, the broad phase and the shipped scenes.

use mwb_reverse::bench::{bounces, first_bounce_keeps};
use mwb_reverse::broad_phase::{all_pairs, sweep_and_prune};
use mwb_reverse::chain::MAX_STATE;
use mwb_reverse::run::{ladder_seconds, shadow_energy};
use mwb_reverse::scene::{builtin, world_from_toml};
use mwb_reverse::{
    BackwardChoices, Body, ChainLearning, ContactChain, Heuristics, HintMotion, Material, Partner,
    ReverseSettings, StaticBody, UserHint, World, free_to_bounce, run_backward, run_mixed,
};
use nalgebra::{UnitQuaternion, Vector3};
use parry3d::bounding_volume::Aabb;
use parry3d::math::Vec3;

fn scene(src: &str, name: &str) -> World {
    match world_from_toml(src, name) {
        Ok(w) => w,
        Err(e) => panic!("{name}: {e}"),
    }
}

fn quick_chain(world: &World) -> ContactChain {
    let learning = ChainLearning {
        runs: 8,
        max_duration: 1.5,
        ..ChainLearning::default()
    };
    ContactChain::learn(world, &learning, 7)
}

fn frame_bits(frames: &[mwb_reverse::Frame]) -> Vec<u64> {
    frames
        .iter()
        .flat_map(|f| {
            std::iter::once(f.time.to_bits()).chain(f.poses.iter().flat_map(|p| {
                p.position
                    .iter()
                    .chain(p.orientation.coords.iter())
                    .map(|v| v.to_bits())
                    .collect::<Vec<_>>()
            }))
        })
        .collect()
}

#[test]
fn shipped_scenes_parse_and_convert() {
    let expect = [
        ("word", 16),
        ("stack", 10),
        ("balls", 2744),
        ("balls_small", 27),
        ("crash", 5),
        ("gate", 5),
        ("lorem", 3037),
    ];
    for ((name, src), (want_name, bodies)) in builtin::ALL.iter().zip(expect) {
        assert_eq!(*name, want_name);
        let world = scene(src, name);
        assert_eq!(world.bodies.len(), bodies, "{name}");
        assert!((world.gravity - Vector3::new(0.0, -9.81, 0.0)).norm() < 1e-12);
    }
    // Final states rest: every word box touches only the ground, and is free to bounce.
    let mut word = scene(builtin::WORD, "word");
    let (set, unsupported) = word.detect_contacts();
    assert_eq!(unsupported, 0);
    assert!(set.contacts.iter().all(|c| c.dist.abs() < 1e-5));
    assert_eq!(set.islands.len(), 16, "no box touches another");
    assert!(free_to_bounce(&set, 16).iter().all(|f| *f));
    // In the stack only the top brick is free to bounce (§5.3.3).
    let mut stack = scene(builtin::STACK, "stack");
    let (set, _) = stack.detect_contacts();
    let free = free_to_bounce(&set, 10);
    assert_eq!(free.iter().filter(|f| **f).count(), 1, "{free:?}");
    assert!(free[9]);
    // Balls rest on the floor, one contact each, touching no wall.
    let mut balls = scene(builtin::BALLS_SMALL, "balls_small");
    let (set, _) = balls.detect_contacts();
    assert_eq!(set.contacts.len(), 27);
    // A scene with a joint converts (§5.3.4); a world first end is turned around.
    let jointed = r#"
name = "j"
[[material]]
name = "m"
[[body]]
name = "a"
shape = "sphere"
radius = 0.1
material = "m"
[[joint]]
name = "pin"
kind = "spherical"
body1 = "world"
body2 = "a"
"#;
    let world = scene(jointed, "j");
    assert_eq!(world.joints.len(), 1);
    assert_eq!((world.joints[0].body1, world.joints[0].body2), (0, None));
}

#[test]
fn broad_phase_equals_all_pairs_on_random_scenes() {
    let mut state = 0x1234_5678_9abc_def0u64;
    let mut rnd = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f32 / (1u64 << 53) as f32
    };
    for trial in 0..60 {
        let n = 1 + (rnd() * 150.0) as usize;
        let spread = 0.5 + 10.0 * rnd();
        let boxes = |count: usize, rnd: &mut dyn FnMut() -> f32| -> Vec<Aabb> {
            (0..count)
                .map(|_| {
                    let c = Vec3::new(rnd(), rnd(), rnd()) * spread;
                    let h = Vec3::new(rnd(), rnd(), rnd()) * 0.6 + Vec3::splat(0.01);
                    Aabb::new(c - h, c + h)
                })
                .collect()
        };
        let bodies: Vec<Option<Aabb>> = boxes(n, &mut rnd)
            .into_iter()
            .enumerate()
            .map(|(i, b)| (i % 11 != 3).then_some(b)) // some disabled bodies
            .collect();
        let mut statics = boxes((rnd() * 8.0) as usize, &mut rnd);
        if trial % 2 == 0 {
            // A ground half-space: an unbounded box.
            statics.push(Aabb::new(
                Vec3::new(-1e30, -1e30, -1e30),
                Vec3::new(1e30, 0.3 * spread, 1e30),
            ));
        }
        let mut fast = sweep_and_prune(&bodies, &statics);
        let mut slow = all_pairs(&bodies, &statics);
        fast.sort();
        slow.sort();
        assert_eq!(fast, slow, "trial {trial}: {n} bodies");
    }
}

#[test]
fn learned_chain_rows_are_probabilities() {
    let world = scene(builtin::WORD, "word");
    let chain = quick_chain(&world);
    let total: u64 = chain.counts.iter().flatten().sum();
    assert!(total > 100, "learning runs recorded {total} transitions");
    assert_eq!(chain.probabilities.len(), MAX_STATE + 1);
    for (j, row) in chain.probabilities.iter().enumerate() {
        let sum: f64 = row.iter().sum();
        assert!((sum - 1.0).abs() < 1e-12, "row {j} sums to {sum}");
        assert!(row.iter().all(|p| (0.0..=1.0).contains(p)));
        // Figure 5.12: backward, only towards fewer contacts.
        assert!(row[j + 1..].iter().all(|p| *p == 0.0), "row {j}: {row:?}");
    }
    // Boxes landing flat rest on more than one contact, and leave rest sometimes.
    assert!(
        chain.counts[MAX_STATE].iter().sum::<u64>() > 0,
        "{:?}",
        chain.counts
    );
    assert!(chain.probabilities[MAX_STATE][MAX_STATE] < 1.0);
    // Sampling follows the rows.
    assert_eq!(chain.sample(0, 0.999), 0);
    let stay = ContactChain::stay();
    assert_eq!(stay.sample(3, 0.5), 3);
}

#[test]
fn backward_runs_are_deterministic_per_seed() {
    let world = scene(builtin::BALLS_SMALL, "balls_small");
    let settings = ReverseSettings {
        duration: 0.75,
        chain: Some(quick_chain(&world)),
        ..Default::default()
    };
    let a = run_backward(&mut world.clone(), 11, &settings);
    let b = run_backward(&mut world.clone(), 11, &settings);
    let c = run_backward(&mut world.clone(), 12, &settings);
    assert_eq!(a.frames.len(), 91);
    assert_eq!(frame_bits(&a.frames), frame_bits(&b.frames));
    assert_eq!(a.report.energy.len(), a.frames.len());
    assert_eq!(
        a.report
            .energy
            .iter()
            .map(|e| e.to_bits())
            .collect::<Vec<_>>(),
        b.report
            .energy
            .iter()
            .map(|e| e.to_bits())
            .collect::<Vec<_>>()
    );
    assert_ne!(
        frame_bits(&a.frames),
        frame_bits(&c.frames),
        "the seed matters"
    );
    assert!(a.report.lifts > 0, "{:?}", a.report);
    // Time-ordered, and the last frame is the given (final) state.
    assert!(a.frames.windows(2).all(|w| w[0].time < w[1].time));
    let last = a.frames.last().map(|f| f.poses.clone()).unwrap_or_default();
    for (p, body) in last.iter().zip(&world.bodies) {
        assert_eq!(p.position, body.position);
    }
}

#[test]
fn mixed_run_joins_continuously() {
    let world = scene(builtin::CRASH, "crash");
    let dt = 1.0 / 120.0;
    let settings = ReverseSettings {
        dt,
        duration: 0.25,
        ..Default::default()
    };
    let mixed = run_mixed(&mut world.clone(), 3, &settings, 0.25);
    assert_eq!(mixed.frames.len(), 30 + 1 + 30);
    assert_eq!(mixed.join, 30);
    let join = &mixed.frames[mixed.join];
    assert!((join.time - 0.25).abs() < 1e-12);
    for (p, b) in join.poses.iter().zip(&world.bodies) {
        assert_eq!(p.position, b.position, "the join is the given state");
        assert_eq!(p.orientation, b.orientation);
    }
    assert!(mixed.frames.windows(2).all(|w| w[0].time < w[1].time));
    // In free flight both halves follow one parabola through the join: the second difference of
    // positions is g Δt² on both sides, and equal across it.
    let g = world.gravity;
    for j in [mixed.join - 1, mixed.join, mixed.join + 1] {
        for i in 0..world.bodies.len() {
            let x = |k: usize| mixed.frames[k].poses[i].position;
            let second = x(j + 1) - 2.0 * x(j) + x(j - 1);
            assert!(
                (second - g * dt * dt).norm() < 1e-12,
                "frame {j} body {i}: {second:?}"
            );
            // Rotation continues at the same rate.
            let q = |k: usize| mixed.frames[k].poses[i].orientation;
            let before = q(j).rotation_to(&q(j - 1)).angle();
            let after = q(j + 1).rotation_to(&q(j)).angle();
            assert!((before - after).abs() < 1e-9, "frame {j} body {i}");
        }
    }
}

#[test]
fn free_fall_backward_gains_no_energy() {
    let mut world = World::new();
    world.add_body(
        Body::cuboid(Vector3::new(0.3, 0.2, 0.1), 700.0)
            .expect("positive extents")
            .at(
                Vector3::new(0.0, 0.0, 5.0),
                UnitQuaternion::from_euler_angles(0.2, 0.1, 0.0),
            )
            .moving(Vector3::new(1.0, -0.5, -2.0), Vector3::new(0.5, 1.0, 2.0)),
    );
    let dt = 1.0 / 120.0;
    let run = run_backward(
        &mut world,
        5,
        &ReverseSettings {
            dt,
            duration: 1.0,
            ..Default::default()
        },
    );
    let r = &run.report;
    assert_eq!(r.steps, 120);
    assert!(r.energy_growth.abs() < 1e-9, "{}", r.energy_growth);
    assert!(r.angular_speed_growth.abs() < 1e-9);
    assert!(
        r.max_departure < 1e-9 && r.max_forward_residual == 0.0,
        "{r:?}"
    );
    // Without the Δt term, semi-implicit Euler gains ½ g² Δt² per kg and step going backward.
    let plain = |w: &World| w.energy();
    let mut w2 = world.clone();
    let e0 = plain(&w2);
    let s0 = shadow_energy(&w2, dt);
    w2.step_forward(dt);
    let m = 1.0 / w2.bodies[0].inv_mass;
    assert!((e0 - plain(&w2) - 0.5 * m * 9.81f64.powi(2) * dt * dt).abs() < 1e-6 * m);
    assert!((s0 - shadow_energy(&w2, dt)).abs() < 1e-9 * m);
}

/// The friction half of the rattling heuristic (§5.3.1): the backward step undoes only the
/// scaled friction, and the departure from the material's friction is measured.
#[test]
fn friction_scale_lowers_reversed_friction_and_is_measured() {
    let mat = Material {
        friction: 0.5,
        restitution: 0.3,
    };
    let sliding = || -> Result<World, mwb_reverse::BodyError> {
        let mut w = World::new();
        w.add_static(StaticBody::plane(Vector3::z(), 0.0)?.with_material(mat));
        w.add_body(
            Body::cuboid(Vector3::new(0.5, 0.5, 0.5), 1.0)?
                .with_material(mat)
                .at(Vector3::new(0.0, 0.0, 0.5), UnitQuaternion::identity())
                .moving(Vector3::new(1.0, 0.0, 0.0), Vector3::zeros()),
        );
        Ok(w)
    };
    let dt = 1.0 / 240.0;
    for scale in [1.0, 0.25, 0.0] {
        let mut world = match sliding() {
            Ok(w) => w,
            Err(e) => panic!("{e}"),
        };
        let mut choices = BackwardChoices::default();
        choices
            .friction_scale
            .insert((0, Partner::Static(0)), scale);
        let back = world.step_backward(dt, &choices);
        assert!(back.all_solved());
        assert!(
            back.choices
                .iter()
                .all(|c| (c.mu - 0.5 * scale).abs() < 1e-15)
        );
        // Backward, sliding friction speeds the box up by (scale μ) g Δt.
        let expected = 1.0 + scale * 0.5 * 9.81 * dt;
        let speed = world.bodies[0].linvel.x;
        assert!(
            (speed - expected).abs() < 1e-9,
            "{scale}: {speed} vs {expected}"
        );
        // The contact set keeps the material's μ, so the departure is measured: the forward
        // LCP residual is nonzero and a forward replay brakes by the full μ g Δt.
        let departure = (1.0 - scale) * 0.5 * 9.81 * dt;
        if scale < 1.0 {
            assert!(back.forward_residual > 0.25 * departure, "{scale}");
        } else {
            assert!(back.forward_residual < 1e-12);
        }
        let mut replay = world.clone();
        replay.step_forward_with(&back.contacts, dt);
        let replayed = replay.bodies[0].linvel.x;
        assert!(
            (1.0 - replayed - departure).abs() < 1e-9,
            "{scale}: {replayed}"
        );
    }
}

#[test]
fn reverse_damping_slows_spin_backward() {
    let spinning = || {
        let mut w = World::new();
        w.add_body(
            Body::ball(0.1, 1000.0)
                .expect("positive radius")
                .at(Vector3::new(0.0, 0.0, 10.0), UnitQuaternion::identity())
                .moving(Vector3::zeros(), Vector3::new(0.0, 0.0, 10.0)),
        );
        w
    };
    let settings = |kd| ReverseSettings {
        duration: 0.5,
        heuristics: Heuristics {
            reverse_angular_damping: kd,
            ..Heuristics::default()
        },
        ..Default::default()
    };
    let mut off = spinning();
    let r_off = run_backward(&mut off, 1, &settings(0.0));
    assert!((off.bodies[0].angvel.z - 10.0).abs() < 1e-12);
    assert!(r_off.report.max_departure < 1e-9);
    let mut on = spinning();
    let r_on = run_backward(&mut on, 1, &settings(2.0));
    let expect = 10.0 / (1.0 + 2.0 / 120.0f64).powi(60);
    assert!((on.bodies[0].angvel.z - expect).abs() < 1e-9);
    // The damping is a departure from forward-valid steps, and it is measured.
    assert!(r_on.report.max_departure > 1e-3, "{:?}", r_on.report);
    assert_eq!(r_on.report.departed_steps, 60);
}

#[test]
fn stack_holds_while_the_top_brick_slides_away() {
    let world = scene(builtin::STACK, "stack");
    let mut hints = std::collections::BTreeMap::new();
    hints.insert(
        9,
        UserHint {
            motion: HintMotion::Slide(Vector3::new(1.0, 0.0, 0.0)),
            release_before_end: 0.1,
        },
    );
    let settings = ReverseSettings {
        duration: 0.5,
        hints,
        ..Default::default()
    };
    let mut w = world.clone();
    let run = run_backward(&mut w, 4, &settings);
    let r = &run.report;
    assert_eq!(r.unsolved_islands, 0, "{r:?}");
    // The top brick moved off along −x backward (it slid in along +x).
    let top = &w.bodies[9];
    assert!(
        top.position.x < world.bodies[9].position.x - 0.05,
        "{top:?}"
    );
    // A requested slide is exempt from the energy budget: reversed friction sped it up past
    // any sampled slide speed (played forward, it slows to its rest).
    let fastest_sampled = mwb_reverse::run::Sampling::default().slide_speed.1;
    assert!(top.linvel.norm() > fastest_sampled, "{top:?}");
    // The bricks below it stayed (held by the stacking heuristic).
    for (i, (now, then)) in w.bodies.iter().zip(&world.bodies).take(9).enumerate() {
        assert!(
            (now.position - then.position).norm() < 1e-3,
            "brick {i} moved {:?}",
            now.position - then.position
        );
    }
    assert!(r.held_contacts > 0);
}

// Contact distances come from parry in f32: positions agree to ~1e-7 m.

/// Two balls of radius 0.1 overlapping by `depth` along x, above a floor at z = 0 they do not
/// touch; `heavy` makes the second one 1000 times denser.
fn overlapping_balls(depth: f64, heavy: bool) -> World {
    let mut w = World::new();
    w.add_static(StaticBody::plane(Vector3::z(), 0.0).expect("unit normal"));
    let at = |x: f64| Vector3::new(x, 0.0, 1.0);
    w.add_body(
        Body::ball(0.1, 1000.0)
            .expect("positive radius")
            .at(at(0.0), UnitQuaternion::identity())
            .moving(Vector3::new(0.3, 0.0, 0.0), Vector3::zeros()),
    );
    w.add_body(
        Body::ball(0.1, if heavy { 1e6 } else { 1000.0 })
            .expect("positive radius")
            .at(at(0.2 - depth), UnitQuaternion::identity()),
    );
    w
}

#[test]
fn depenetration_pushes_bodies_apart_by_inverse_mass_without_touching_velocities() {
    let slop = 0.001;
    for heavy in [false, true] {
        let mut w = overlapping_balls(0.02, heavy);
        let (mut set, _) = w.detect_contacts();
        assert_eq!(set.contacts.len(), 1, "one ball-ball contact");
        assert!((set.contacts[0].dist + 0.02).abs() < 1e-6);
        let before: Vec<_> = w.bodies.iter().map(|b| (b.position, b.linvel)).collect();
        let moved = w.depenetrate(&mut set, slop, 0.0, 4);
        let gap = (w.bodies[1].position - w.bodies[0].position).norm() - 0.2;
        assert!((gap + slop).abs() < 1e-6, "gap {gap}");
        assert!((set.contacts[0].dist + slop).abs() < 1e-6, "dist updated");
        let shift: Vec<f64> = w
            .bodies
            .iter()
            .zip(&before)
            .map(|(b, (p, _))| (b.position - p).norm())
            .collect();
        if heavy {
            // 1000 times the inverse mass: the light ball takes 1000/1001 of the correction.
            assert!(
                (shift[0] - 0.019 * 1000.0 / 1001.0).abs() < 1e-6,
                "{shift:?}"
            );
        } else {
            assert!((shift[0] - shift[1]).abs() < 1e-12, "{shift:?}");
        }
        assert!((moved - shift[0].max(shift[1])).abs() < 1e-12);
        for (b, (_, v)) in w.bodies.iter().zip(&before) {
            assert_eq!(b.linvel, *v, "velocities untouched");
        }
    }
    // One step's travel of the contact point is left: the first ball moves at 0.3 m/s, so at
    // dt = 0.05 s an overlap of 1.5 cm + slop stays as it is, and a deeper one comes out to it.
    for (depth, stays) in [(0.016 - 1e-4, true), (0.02, false)] {
        let mut w = overlapping_balls(depth, false);
        let (mut set, _) = w.detect_contacts();
        let moved = w.depenetrate(&mut set, slop, 0.05, 4);
        let gap = (w.bodies[1].position - w.bodies[0].position).norm() - 0.2;
        if stays {
            assert!(moved < 1e-6, "moved {moved}");
        } else {
            assert!((gap + slop + 0.3 * 0.05).abs() < 1e-6, "gap {gap}");
        }
    }
}

#[test]
fn depenetration_lifts_a_sunken_body_out_of_a_static_and_leaves_shallow_contacts() {
    let mut w = World::new();
    w.add_static(StaticBody::plane(Vector3::z(), 0.0).expect("unit normal"));
    w.add_body(
        Body::ball(0.1, 1000.0)
            .expect("positive radius")
            .at(Vector3::new(0.0, 0.0, 0.07), UnitQuaternion::identity()),
    );
    let (mut set, _) = w.detect_contacts();
    w.depenetrate(&mut set, 0.001, 0.0, 4);
    assert!((w.bodies[0].position.z - 0.099).abs() < 1e-6);
    // Within the slop: nothing moves (but for parry's f32 rounding).
    let (mut set, _) = w.detect_contacts();
    assert!(w.depenetrate(&mut set, 0.001, 0.0, 4) < 1e-6);
    assert!((w.bodies[0].position.z - 0.099).abs() < 1e-6);
}

#[test]
fn default_heuristics_keep_the_lorem_balls_out_of_each_other() {
    // Two neighbouring bins of the lorem scene, 18 balls 2 mm apart, 1 s back: each bin's middle
    // ball is asked to slide in along x (balls get no sampled slide), which sends it into its
    // neighbours; without depenetration they sink into each other.
    let src = builtin::LOREM;
    let mut w = scene(src, "lorem.toml");
    let keep: Vec<usize> = (0..18).collect();
    w.bodies = w
        .bodies
        .iter()
        .enumerate()
        .filter(|(i, _)| keep.contains(i))
        .map(|(_, b)| b.clone())
        .collect();
    let hints = [4, 13]
        .into_iter()
        .map(|b| {
            let motion = HintMotion::Slide(Vector3::new(1.0, 0.0, 0.0));
            let hint = UserHint {
                motion,
                release_before_end: 0.0,
            };
            (b, hint)
        })
        .collect();
    let settings = ReverseSettings {
        duration: 1.0,
        chain: Some(quick_chain(&w)),
        hints,
        measure_departure: false,
        ..Default::default()
    };
    let run = run_backward(&mut w.clone(), 3, &settings);
    let deepest = run
        .report
        .plausibility_bodies
        .iter()
        .map(|p| p.max_penetration)
        .fold(0.0, f64::max);
    assert!(
        deepest <= mwb_reverse::MAX_PENETRATION_M,
        "deepest {deepest}"
    );
    assert!(run.report.max_depenetration > 0.0, "{:?}", run.report);
}

/// A ball bounced off the floor going back gains height bounce after bounce (each backward
/// bounce undoes the restitution's loss, §5.2.2) and stays plausible: played forward it falls
/// from its highest bounce and settles. The energy budget once credited a rising ball with the
/// continuous apex `h + v²/2g`, `½ Δt |v|` below the height the stepper's flight reaches; every
/// growing bounce then looked like a gain no fall explains and was taken again elastic, and the
/// ball hopped 2 mm high for the whole run.
#[test]
fn a_bounced_ball_climbs_going_back_and_stays_plausible() {
    let mut w = World::new();
    w.add_static(
        StaticBody::plane(Vector3::z(), 0.0)
            .expect("unit normal")
            .with_material(Material {
                friction: 0.4,
                restitution: 0.5,
            }),
    );
    w.add_body(
        Body::ball(0.02, 1000.0)
            .expect("positive radius")
            .with_material(Material {
                friction: 0.4,
                restitution: 0.6,
            })
            .at(Vector3::new(0.0, 0.0, 0.02), UnitQuaternion::identity()),
    );
    let hints = [(
        0,
        UserHint {
            motion: HintMotion::Bounce,
            release_before_end: 0.0,
        },
    )]
    .into_iter()
    .collect();
    let settings = ReverseSettings {
        duration: 1.5,
        hints,
        measure_departure: false,
        ..Default::default()
    };
    let run = run_backward(&mut w, 4, &settings);
    let top = run
        .frames
        .iter()
        .map(|f| f.poses[0].position.z)
        .fold(f64::MIN, f64::max);
    assert!(top > 0.2, "highest bounce {top} m");
    let p = run.report.plausibility;
    assert!(p.plausible, "{p:?}");
}

/// The balls of a tight bin (2–3 mm apart) leave it going back, and the worlds stay plausible:
/// round bodies get no sampled slide (a slide sent them into their neighbours, and the knocks
/// spread speed no fall explains), so each ball climbs out on its own bounces.
#[test]
fn balls_leave_their_bins_plausibly() {
    let world = scene(builtin::BALLS_SMALL, "balls_small");
    let settings = ReverseSettings {
        duration: 4.0,
        chain: Some(quick_chain(&world)),
        measure_departure: false,
        ..Default::default()
    };
    for seed in [1, 2] {
        let run = run_backward(&mut world.clone(), seed, &settings);
        let p = run.report.plausibility;
        assert!(p.plausible, "seed {seed}: {p:?}");
        // Above the 4 cm walls (ball centres higher than wall top + radius).
        let out = run.frames[0]
            .poses
            .iter()
            .filter(|q| q.position.y > 0.06)
            .count();
        // Every one: a ball the chain kept resting too long is sent off in time, and the last
        // rung of its ladder ends at an apex in the first frame (before both, 91.6 % of lorem's
        // balls were out).
        assert_eq!(out, world.bodies.len(), "seed {seed}: {out} out");
        // The last rung costs a deader first bounce, never below half the material pair's
        // 0.55 (less the `g Δt` a frame difference loses at a bounce).
        let keeps = first_bounce_keeps(&run.frames, &Vector3::y());
        assert_eq!(keeps.len(), world.bodies.len(), "seed {seed}: {keeps:?}");
        assert!(keeps.iter().all(|k| *k >= 0.25), "seed {seed}: {keeps:?}");
        // Played forward they bounce like their material: a ball that left too early climbed
        // to the energy cap going back, which took its bounces elastic (before lift-offs were
        // timed by their ladder: 64–66 such bounces in each world, every ball had one).
        let b = bounces(&run.frames, &Vector3::y());
        assert!(b.bounces >= world.bodies.len(), "seed {seed}: {b:?}");
        assert_eq!(b.elastic, 0, "seed {seed}: {b:?}");
    }
}

/// The ladder a bouncing ball climbs going back, checked by hand: g = 10, Δt = 0.1, α = ½, no
/// rattling. Lift-off at 0 lands at 1 m/s after a step (0.1 s) and leaves at 2; flights of
/// 0.4 s (→ 4 m/s) and 0.8 s (→ 8 m/s). A cap of 7 m/s (2.45 m) is passed at 1.3 s, one of
/// 9 m/s only at 1.3 + 1.6 s.
#[test]
fn a_bounce_ladder_reaches_the_cap_when_its_speeds_say() {
    let t = |v0, alpha, blend, headroom| ladder_seconds(v0, alpha, 10.0, 0.1, blend, headroom);
    assert!((t(0.0, 0.5, None, 2.45) - 1.3).abs() < 1e-9);
    assert!((t(0.0, 0.5, None, 4.05) - 2.9).abs() < 1e-9);
    // Past the cap at the first landing.
    assert!((t(0.0, 0.5, None, 0.1) - 0.1).abs() < 1e-9);
    // Lorem's numbers: 1.9–2.3 s over its lift-off speeds (measured: 1.76–2.47 s).
    let lorem = |v0, blend| ladder_seconds(v0, 0.55, 9.81, 1.0 / 120.0, blend, 1.6);
    // More headroom, a later cap: the same rungs, stopped later.
    let mut last = 0.0;
    for headroom in [0.0, 0.1, 0.4, 0.8, 1.6, 3.2] {
        let s = ladder_seconds(0.05, 0.55, 9.81, 1.0 / 120.0, Some(0.2), headroom);
        assert!(s >= last, "{headroom}: {s} < {last}");
        last = s;
    }
    for v0 in [0.03, 0.05, 0.07, 0.095] {
        let s = lorem(v0, Some(0.2));
        assert!((1.85..2.4).contains(&s), "{v0}: {s}");
    }
    // Bounces that never grow never reach it; bad input reads as never.
    for alpha in [0.0, 1.0, f64::NAN] {
        assert_eq!(t(0.05, alpha, None, 1.6), f64::INFINITY);
    }
    assert_eq!(t(f64::NAN, 0.5, None, 1.6), f64::INFINITY);
}
