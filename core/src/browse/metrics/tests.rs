use super::*;
use crate::browse::geom::{normalize, quat_mul};
use proptest::prelude::*;

const DT: f64 = 1.0 / 120.0;

fn axis_angle(axis: Vec3, angle: f64) -> Quat {
    let (s, c) = (angle / 2.0).sin_cos();
    let a = normalize(axis).unwrap_or([1.0, 0.0, 0.0]);
    [a[0] * s, a[1] * s, a[2] * s, c]
}

fn rest() -> RestThresholds {
    RestThresholds::from(&Settings::default())
}

fn metrics(positions: &[Vec3], rotations: &[Quat], goal: Option<Quat>) -> ObjectMetrics {
    ObjectMetrics::compute(
        &Track {
            frame_dt: DT,
            positions,
            rotations,
        },
        3,
        rest(),
        goal,
    )
    .expect("valid track")
}

#[test]
fn constant_spin_integrates_to_omega_t() {
    // ω = 5 rad/s about a tilted axis for T = 4 s: ∫‖ω‖dt = 20 rad (many full turns).
    let (omega, t_end) = (5.0, 4.0);
    let start = axis_angle([0.2, 1.0, 0.0], 0.4);
    let frames = (t_end / DT).round() as usize;
    let rotations: Vec<Quat> = (0..=frames)
        .map(|i| quat_mul(axis_angle([1.0, 1.0, 0.5], omega * i as f64 * DT), start))
        .collect();
    let positions = vec![[0.0; 3]; rotations.len()];
    let m = metrics(&positions, &rotations, None);
    assert!(
        (m.angular_travel_rad - omega * t_end).abs() < 1e-9,
        "{}",
        m.angular_travel_rad
    );
    // Spinning until the end: never rests.
    assert!(!m.came_to_rest);
    assert!((m.time_to_rest_s - t_end).abs() < 1e-9);
    // 20 rad = 3 turns + 1.150… rad: the error is the angle of the leftover rotation.
    let leftover = (omega * t_end) % std::f64::consts::TAU;
    let want = if leftover > std::f64::consts::PI {
        std::f64::consts::TAU - leftover
    } else {
        leftover
    };
    assert!((m.orientation_error_rad - want).abs() < 1e-9);
    assert_eq!(m.impacts, 3);
}

#[test]
fn a_body_stopping_at_two_seconds_rests_at_two_seconds() {
    // Slides at 1 m/s while spinning at 2 rad/s until t = 2 s, then lies still until t = 5 s.
    let frames = (5.0 / DT).round() as usize;
    let stop = (2.0 / DT).round() as usize;
    let positions: Vec<Vec3> = (0..=frames)
        .map(|i| [i.min(stop) as f64 * DT, 0.0, 0.0])
        .collect();
    let rotations: Vec<Quat> = (0..=frames)
        .map(|i| axis_angle([0.0, 1.0, 0.0], 2.0 * i.min(stop) as f64 * DT))
        .collect();
    let m = metrics(&positions, &rotations, None);
    assert!(m.came_to_rest);
    assert!(
        (m.time_to_rest_s - 2.0).abs() < 1e-9,
        "{}",
        m.time_to_rest_s
    );
    assert!((m.angular_travel_rad - 4.0).abs() < 1e-9);
    assert!((m.orientation_error_rad - 4.0_f64.min(std::f64::consts::TAU - 4.0)).abs() < 1e-9);
    // A goal equal to the final orientation gives no error.
    let m = metrics(&positions, &rotations, rotations.last().copied());
    assert!(m.orientation_error_rad < 1e-12);
    // Slow creep below the thresholds after the stop does not count as motion.
    let creep: Vec<Vec3> = positions
        .iter()
        .enumerate()
        .map(|(i, p)| {
            [
                p[0] + if i > stop {
                    0.001 * (i - stop) as f64 * DT
                } else {
                    0.0
                },
                0.0,
                0.0,
            ]
        })
        .collect();
    let m = metrics(&creep, &rotations, None);
    assert!((m.time_to_rest_s - 2.0).abs() < 1e-9);
    // A body that never moves rests at once.
    let still = metrics(&[[1.0, 2.0, 3.0]; 10], &[[0.0, 0.0, 0.0, 1.0]; 10], None);
    assert_eq!((still.time_to_rest_s, still.came_to_rest), (0.0, true));
    assert_eq!(still.angular_travel_rad, 0.0);
}

#[test]
fn bad_tracks_are_refused() {
    let ok = [[0.0; 3]; 2];
    let q = [[0.0, 0.0, 0.0, 1.0]; 2];
    let run = |frame_dt: f64, p: &[Vec3], r: &[Quat]| {
        ObjectMetrics::compute(
            &Track {
                frame_dt,
                positions: p,
                rotations: r,
            },
            0,
            rest(),
            None,
        )
    };
    assert!(matches!(
        run(0.0, &ok, &q),
        Err(BrowseError::OutOfRange {
            field: "frame_dt",
            ..
        })
    ));
    assert!(matches!(
        run(DT, &ok, &q[..1]),
        Err(BrowseError::LengthMismatch { .. })
    ));
    assert!(matches!(run(DT, &[], &[]), Err(BrowseError::Empty { .. })));
    assert!(matches!(
        run(DT, &ok, &[[0.0; 4]; 2]),
        Err(BrowseError::ZeroVector { .. })
    ));
    assert!(matches!(
        run(DT, &[[f64::NAN, 0.0, 0.0], [0.0; 3]], &q),
        Err(BrowseError::NonFinite { .. })
    ));
}

fn object(angular: f64, rest_s: f64) -> ObjectMetrics {
    ObjectMetrics {
        angular_travel_rad: angular,
        time_to_rest_s: rest_s,
        came_to_rest: true,
        impacts: 1,
        orientation_error_rad: 0.0,
        final_rotation: axis_angle([0.0, 0.0, 1.0], angular),
    }
}

#[test]
fn score_sums_or_maxes_over_the_chosen_objects() {
    let objs = [object(1.0, 2.0), object(3.0, 1.0), object(5.0, 4.0)];
    assert_eq!(
        score(&objs, &[0, 2], Metric::AngularTravel, Aggregate::Sum),
        Some(6.0)
    );
    assert_eq!(
        score(&objs, &[0, 1], Metric::TimeToRest, Aggregate::Max),
        Some(2.0)
    );
    assert_eq!(
        score(&objs, &[0, 1, 2], Metric::Impacts, Aggregate::Sum),
        Some(3.0)
    );
    assert_eq!(score(&objs, &[], Metric::Impacts, Aggregate::Sum), None);
    assert_eq!(score(&objs, &[0, 9], Metric::Impacts, Aggregate::Sum), None);
    let key = RankKey::ConstraintsSatisfied;
    assert_eq!(key.score(&objs, 4), Some(4.0));
    let key = RankKey::Metric {
        metric: Metric::TimeToRest,
        objects: vec![2],
        aggregate: Aggregate::Max,
    };
    assert_eq!(key.score(&objs, 4), Some(4.0));
    let text = toml::to_string(&key).expect("serialises");
    assert_eq!(toml::from_str::<RankKey>(&text).expect("parses"), key);
}

/// A goal chosen at query time: the angle from each object's final orientation to it.
#[test]
fn orientation_to_a_goal_chosen_at_query_time() {
    // Final orientations: 1, 3 and 5 rad about z (the helper's `angular`).
    let objs = [object(1.0, 2.0), object(3.0, 1.0), object(5.0, 4.0)];
    let goal = axis_angle([0.0, 0.0, 1.0], 3.0);
    let key = |objects: Vec<u32>, aggregate| RankKey::OrientationTo {
        goal,
        objects,
        aggregate,
    };
    let close = |a: Option<f64>, b: f64| a.is_some_and(|a| (a - b).abs() < 1e-9);
    assert!(close(key(vec![1], Aggregate::Sum).score(&objs, 0), 0.0));
    assert!(close(key(vec![0], Aggregate::Sum).score(&objs, 0), 2.0));
    // 5 rad about z is 2 rad from 3 rad (less than π: the short way).
    assert!(close(key(vec![0, 2], Aggregate::Max).score(&objs, 0), 2.0));
    assert!(close(
        key(vec![0, 1, 2], Aggregate::Sum).score(&objs, 0),
        4.0
    ));
    // An unnormalised goal is normalised; a missing object has no score.
    let doubled = RankKey::OrientationTo {
        goal: goal.map(|v| 2.0 * v),
        objects: vec![0],
        aggregate: Aggregate::Sum,
    };
    assert!(close(doubled.score(&objs, 0), 2.0));
    assert_eq!(key(vec![7], Aggregate::Sum).score(&objs, 0), None);
    assert!(key(vec![0], Aggregate::Sum).validate().is_ok());
    // A zero or non-finite goal is refused by name.
    for bad in [[0.0; 4], [f64::NAN, 0.0, 0.0, 1.0]] {
        let k = RankKey::OrientationTo {
            goal: bad,
            objects: vec![0],
            aggregate: Aggregate::Sum,
        };
        let err = k.validate().expect_err("refused");
        assert!(err.to_string().contains("goal"), "{err}");
    }
    // JSON (the bus API) round trip.
    let k = key(vec![0, 2], Aggregate::Max);
    let text = serde_json::to_string(&k).expect("serialises");
    assert!(text.contains("orientation_to"), "{text}");
    assert_eq!(serde_json::from_str::<RankKey>(&text).expect("parses"), k);
    // Metrics serialised before the field existed read as the identity.
    let old = r#"{"angular_travel_rad":1.0,"time_to_rest_s":1.0,"came_to_rest":true,"impacts":0,"orientation_error_rad":0.5}"#;
    let m: ObjectMetrics = serde_json::from_str(old).expect("parses");
    assert_eq!(m.final_rotation, [0.0, 0.0, 0.0, 1.0]);
}

#[test]
fn top_k_orders_ties_by_world_and_unscored_last() {
    let scores = [
        (7, Some(1.0)),
        (3, Some(2.0)),
        (5, Some(1.0)),
        (1, None),
        (2, Some(f64::NAN)),
        (9, Some(-0.0)),
        (4, Some(0.0)),
    ];
    let lookup = |w: u32| scores.iter().find(|(x, _)| *x == w).and_then(|(_, s)| *s);
    let all: Vec<u32> = scores.iter().map(|(w, _)| *w).collect();
    let asc = top_k(all.iter().copied(), 10, Order::Ascending, lookup);
    assert_eq!(
        asc.iter().map(|r| r.world).collect::<Vec<_>>(),
        vec![4, 9, 5, 7, 3, 1, 2],
        "−0 ties with +0; NaN and missing go last, by index"
    );
    let desc = top_k(all.iter().copied(), 3, Order::Descending, lookup);
    assert_eq!(
        desc.iter().map(|r| r.world).collect::<Vec<_>>(),
        vec![3, 5, 7]
    );
    assert!(top_k(all.iter().copied(), 0, Order::Ascending, lookup).is_empty());
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]

    /// top-k is the prefix of a stable sort by (score, world), whatever the input order, and
    /// merging per-shard top-k lists gives the global top-k.
    #[test]
    fn top_k_is_stable_and_mergeable(
        raw in prop::collection::vec(prop::option::of(0u8..6), 0..200),
        k in 0usize..40,
        rotate in 0usize..200,
        descending in any::<bool>(),
        shards in 1u32..5,
    ) {
        let order = if descending { Order::Descending } else { Order::Ascending };
        let score = |w: u32| raw.get(w as usize).copied().flatten().map(f64::from);
        let worlds: Vec<u32> = (0..raw.len() as u32).collect();
        // Reference: stable sort of worlds (already in index order) by score.
        let mut reference = worlds.clone();
        reference.sort_by(|&a, &b| match (score(a), score(b)) {
            (Some(x), Some(y)) => if descending { y.total_cmp(&x) } else { x.total_cmp(&y) },
            (Some(_), None) => std::cmp::Ordering::Less,
            (None, Some(_)) => std::cmp::Ordering::Greater,
            (None, None) => std::cmp::Ordering::Equal,
        });
        reference.truncate(k);
        let mut shuffled = worlds.clone();
        if !shuffled.is_empty() {
            let r = rotate % shuffled.len();
            shuffled.rotate_left(r);
            shuffled.reverse();
        }
        let got: Vec<u32> = top_k(shuffled, k, order, score).iter().map(|r| r.world).collect();
        prop_assert_eq!(&got, &reference);
        // Shard by world % shards, take each shard's top-k, merge.
        let lists: Vec<Vec<Ranked>> = (0..shards)
            .map(|s| top_k(worlds.iter().copied().filter(|w| w % shards == s), k, order, score))
            .collect();
        let merged: Vec<u32> = merge_top_k(lists, k, order).iter().map(|r| r.world).collect();
        prop_assert_eq!(&merged, &reference);
    }
}

/// Per-world plausibility: scored where measured, unscored (sorted last) where not.
#[test]
fn world_metrics_rank_backward_worlds_and_leave_forward_ones_unscored() {
    let objs = [object(1.0, 2.0)];
    let key = RankKey::World {
        metric: WorldMetric::EnergyGrowth,
    };
    let forward = WorldMetrics::default();
    let backward = WorldMetrics {
        energy_growth: Some(0.7),
        angular_speed_growth: Some(3.0),
        plausible: Some(false),
        plausibility_excess: Some(0.25),
    };
    assert_eq!(key.score_with(&objs, &forward, 0), None);
    assert_eq!(key.score_with(&objs, &backward, 0), Some(0.7));
    let key = RankKey::World {
        metric: WorldMetric::AngularSpeedGrowth,
    };
    assert_eq!(key.score_with(&objs, &backward, 0), Some(3.0));
    let key = RankKey::World {
        metric: WorldMetric::PlausibilityExcess,
    };
    assert_eq!(key.score_with(&objs, &backward, 0), Some(0.25));
    assert_eq!(key.score_with(&objs, &forward, 0), None);
    // Per-object keys ignore the world's measurements.
    let by_object = RankKey::Metric {
        metric: Metric::AngularTravel,
        objects: vec![0],
        aggregate: Aggregate::Sum,
    };
    assert_eq!(by_object.score_with(&objs, &backward, 0), Some(1.0));
    let text = serde_json::to_string(&key).expect("serialises");
    assert_eq!(serde_json::from_str::<RankKey>(&text).expect("parses"), key);
    // Absent measurements are not written (forward summaries stay as they were).
    assert_eq!(serde_json::to_string(&forward).expect("serialises"), "{}");
}

/// Issue 24: a world whose chosen bodies were still moving when it ended has no time to rest, so
/// "rests soonest" never puts it first — whatever its (end-time) value — and it is counted.
#[test]
fn time_to_rest_has_no_value_for_bodies_still_moving_and_those_sort_last() {
    let moving = ObjectMetrics {
        came_to_rest: false,
        ..object(0.0, 0.5)
    };
    let worlds = [
        vec![object(0.0, 2.0), object(0.0, 3.0)], // rests at 3 s (max), 5 s (sum)
        vec![moving, object(0.0, 0.1)],           // never rests: no value, even at 0.5 s
        vec![object(0.0, 1.0), object(0.0, 1.5)], // rests at 1.5 s, soonest
    ];
    assert_eq!(moving.get(Metric::TimeToRest), None);
    assert_eq!(moving.get(Metric::AngularTravel), Some(0.0));
    let agg = Metric::TimeToRest.default_aggregate();
    assert_eq!(agg, Aggregate::Max);
    assert_eq!(Metric::Impacts.default_aggregate(), Aggregate::Sum);
    assert_eq!(Metric::TimeToRest.unit(), "s");
    let (rows, unscored) = top_k_counted(0..3, 3, Order::Ascending, |w| {
        score(&worlds[w as usize], &[0, 1], Metric::TimeToRest, agg)
    });
    assert_eq!(unscored, 1);
    assert_eq!(
        rows,
        vec![
            Ranked {
                world: 2,
                score: Some(1.5)
            },
            Ranked {
                world: 0,
                score: Some(3.0)
            },
            Ranked {
                world: 1,
                score: None
            },
        ]
    );
    // Only the resting body chosen: world 1 has a value again.
    assert_eq!(score(&worlds[1], &[1], Metric::TimeToRest, agg), Some(0.1));
    // Descending ("rests latest") still puts the unscored last, and NaN counts as no value.
    let (rows, unscored) = top_k_counted(0..3, 1, Order::Descending, |w| {
        if w == 2 {
            Some(f64::NAN)
        } else {
            score(&worlds[w as usize], &[0, 1], Metric::TimeToRest, agg)
        }
    });
    assert_eq!((rows[0].world, unscored), (0, 2));
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    /// Packing keeps each value to f32 rounding (half an ulp of it), the counts and the flag
    /// exactly; unpacking and packing again changes nothing.
    #[test]
    fn packed_metrics_round_to_f32_and_nothing_else(
        travel in 0.0f64..1e4,
        rest in 0.0f64..600.0,
        came in any::<bool>(),
        impacts in any::<u32>(),
        err in 0.0f64..std::f64::consts::PI,
        q in prop::array::uniform4(-1.0f64..1.0),
    ) {
        let m = ObjectMetrics {
            angular_travel_rad: travel,
            time_to_rest_s: rest,
            came_to_rest: came,
            impacts,
            orientation_error_rad: err,
            final_rotation: q,
        };
        let p = PackedMetrics::pack(&m);
        let u = p.unpack();
        let close = |a: f64, b: f64| (a - b).abs() <= a.abs() * f64::from(f32::EPSILON) / 2.0;
        prop_assert!(close(travel, u.angular_travel_rad));
        prop_assert!(close(rest, u.time_to_rest_s));
        prop_assert!(close(err, u.orientation_error_rad));
        for (a, b) in q.iter().zip(u.final_rotation) {
            prop_assert!(close(*a, b));
        }
        prop_assert_eq!(u.came_to_rest, came);
        prop_assert_eq!(u.impacts, impacts);
        prop_assert_eq!(PackedMetrics::pack(&u), p);
        // A ranking reads the packed values as it would the unpacked ones.
        for metric in [
            Metric::AngularTravel,
            Metric::TimeToRest,
            Metric::Impacts,
            Metric::OrientationError,
        ] {
            prop_assert_eq!(MetricValues::get(&p, metric), u.get(metric));
            let key = RankKey::Metric { metric, objects: vec![0, 0], aggregate: Aggregate::Sum };
            let world = WorldMetrics::default();
            prop_assert_eq!(key.score_with(&[p], &world, 0), key.score_with(&[u], &world, 0));
        }
        prop_assert_eq!(MetricValues::final_rotation(&p), u.final_rotation);
    }
}

#[test]
fn packed_metrics_take_36_bytes() {
    assert!(std::mem::size_of::<PackedMetrics>() <= 36);
    assert_eq!(std::mem::size_of::<ObjectMetrics>(), 64);
}
