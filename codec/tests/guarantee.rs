//! The codec's promise, tested on random trajectories: for every object and every frame the
//! decoded position is within e_max and the decoded orientation within θ_max — through every
//! read path (whole world, one object, one object at one time).

mod common;

use common::{G, Rng, distance, generate, normalise, rotation_angle, torque_free};
use mwb_codec::{
    CodecError, EncodeParams, EncodedWorld, MotionModel, Quality, RotationDynamics, Search, Track,
    WorldReader, encode_world, encode_world_with_dynamics,
};
use proptest::prelude::*;

fn check_world(tracks: &[Track], p: &EncodeParams) -> Result<(), TestCaseError> {
    check_world_with(tracks, p, None).map(|_| ())
}

fn check_world_with(
    tracks: &[Track],
    p: &EncodeParams,
    dynamics: Option<&RotationDynamics>,
) -> Result<EncodedWorld, TestCaseError> {
    let world = encode_world_with_dynamics(tracks, p, dynamics)
        .map_err(|e| TestCaseError::fail(e.to_string()))?;
    let reader = WorldReader::new(&world.bytes).map_err(|e| TestCaseError::fail(e.to_string()))?;
    prop_assert_eq!(reader.object_count(), tracks.len());
    prop_assert_eq!(
        reader.frame_count(),
        tracks.iter().map(Track::len).max().unwrap_or(0)
    );
    let all = reader.decode_all().unwrap();
    for (i, (track, decoded)) in tracks.iter().zip(&all).enumerate() {
        prop_assert_eq!(decoded.len(), track.len());
        prop_assert_eq!(&reader.decode_object(i).unwrap(), decoded);
        for f in 0..track.len() {
            let e = distance(decoded.positions[f], track.positions[f]);
            prop_assert!(
                e <= p.e_max,
                "object {i} frame {f}: position error {e} > {}",
                p.e_max
            );
            let a = rotation_angle(decoded.rotations[f], normalise(track.rotations[f]));
            prop_assert!(
                a <= p.theta_max,
                "object {i} frame {f}: angle {a} > {}",
                p.theta_max
            );
        }
        // Random access agrees bit for bit with full decoding, at a few frames.
        let n = track.len();
        for f in [0, n / 3, n / 2, n.saturating_sub(1)] {
            if f < n {
                let (pos, rot) = reader.sample_frame(i, f as u32).unwrap();
                prop_assert_eq!(pos, decoded.positions[f]);
                prop_assert_eq!(rot, decoded.rotations[f]);
                let (pos, rot) = reader.sample(i, f as f64 * p.frame_dt).unwrap();
                prop_assert_eq!(pos, decoded.positions[f]);
                prop_assert_eq!(rot, decoded.rotations[f]);
            }
        }
        // The low-res path's advertised deviation holds at every frame.
        let low = &world.lowres[i];
        for (f, x) in decoded.positions.iter().enumerate() {
            let y = low.position_at(f as f64).unwrap();
            prop_assert!(distance(*x, y) <= low.max_deviation + 1e-12);
        }
    }
    prop_assert!(world.stats.max_position_error <= p.e_max);
    prop_assert!(world.stats.max_rotation_error <= p.theta_max);
    Ok(world)
}

fn frames_strategy() -> impl Strategy<Value = usize> {
    prop_oneof![
        1 => Just(1usize),
        1 => Just(2usize),
        1 => 3usize..20,
        4 => 20usize..500,
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn every_frame_is_within_the_bounds(
        objects in proptest::collection::vec((0usize..6, any::<u64>(), frames_strategy()), 1..4),
        log_e in -5.0f64..-1.0,
        log_theta in -5.0f64..-1.0,
        free_flight in any::<bool>(),
        exhaustive in any::<bool>(),
        dt in prop_oneof![Just(1.0 / 120.0), Just(1.0 / 60.0), Just(1.0 / 240.0), 0.001f64..0.05],
    ) {
        let model = if free_flight { MotionModel::FreeFlightGravity { g: G } } else { MotionModel::General };
        let p = EncodeParams {
            e_max: 10f64.powf(log_e),
            theta_max: 10f64.powf(log_theta),
            frame_dt: dt,
            model,
            lowres_hz: 4.0,
            search: if exhaustive { Search::Exhaustive } else { Search::Adaptive },
        };
        let tracks: Vec<Track> =
            objects.iter().map(|&(kind, seed, frames)| generate(kind, seed, frames, dt)).collect();
        check_world(&tracks, &p)?;
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    /// Free-flight segments keep the promise too: spinning bodies with random
    /// inertia, impacts and damping, encoded with right or wrong dynamics (the model is only a
    /// candidate; the encoder checks every frame), beside the other generators.
    #[test]
    fn free_flight_segments_keep_the_bounds(
        seed in any::<u64>(),
        inertia in (0.05f64..5.0, 0.05f64..5.0, 0.05f64..5.0),
        kicks in proptest::collection::vec(0usize..300, 0..4),
        damping in prop_oneof![Just(0.0), 0.0f64..2.0],
        wrong_inertia in any::<bool>(),
        substeps in 1u32..9,
        log_bound in -4.0f64..-2.0,
        others in proptest::collection::vec((0usize..6, any::<u64>()), 0..3),
        exhaustive in any::<bool>(),
    ) {
        let dt = 1.0 / 120.0;
        let inertia = [inertia.0, inertia.1, inertia.2];
        let mut rng = Rng::new(seed);
        let mut tracks = vec![torque_free(&mut rng, inertia, 300, dt, &kicks, 20.0, damping)];
        tracks.extend(others.iter().map(|&(kind, s)| generate(kind, s, 300, dt)));
        let told = if wrong_inertia { [inertia[2], inertia[0], inertia[1]] } else { inertia };
        let dynamics = RotationDynamics {
            substeps,
            angular_damping: damping,
            inertia: vec![Some(told); tracks.len()],
        };
        let bound = 10f64.powf(log_bound);
        let p = EncodeParams {
            e_max: bound,
            theta_max: bound,
            frame_dt: dt,
            model: MotionModel::FreeFlightGravity { g: G },
            lowres_hz: 4.0,
            search: if exhaustive { Search::Exhaustive } else { Search::Adaptive },
        };
        check_world_with(&tracks, &p, Some(&dynamics))?;
    }
}

/// What the free-flight segments are for: a wobbling box (a spin off its principal axes
/// precesses, so its angular velocity turns) is a few segments with the inertia known, and many
/// quadratics without; the stream is less than half, and a world whose objects use no free
/// flight is written without the dynamics fields.
#[test]
fn a_precessing_flight_is_a_few_free_segments() {
    let dt = 1.0 / 120.0;
    let inertia = [0.2, 1.1, 0.9];
    let mut rng = Rng::new(77);
    let track = torque_free(&mut rng, inertia, 120, dt, &[], 0.0, 0.0);
    let p = EncodeParams::from_quality(
        Quality::Standard,
        dt,
        MotionModel::FreeFlightGravity { g: G },
    );
    // The test's motion is the continuous one; 16 substeps follow it closely.
    let dynamics = RotationDynamics {
        substeps: 16,
        angular_damping: 0.0,
        inertia: vec![Some(inertia)],
    };
    let tracks = [track];
    let with = check_world_with(&tracks, &p, Some(&dynamics)).unwrap();
    let without = encode_world(&tracks, &p).unwrap();
    assert!(with.stats.free_rotation_segments >= 1);
    // Measured: 4 segments (3 free, the discrete integrator drifting from the continuous motion
    // by θ_max every ~40 frames), 61 B; without the inertia 19 segments, 140 B.
    assert!(
        with.stats.rotation_segments <= 4,
        "{} rotation segments",
        with.stats.rotation_segments
    );
    assert!(
        without.stats.rotation_segments >= 3 * with.stats.rotation_segments,
        "{} vs {} rotation segments",
        without.stats.rotation_segments,
        with.stats.rotation_segments
    );
    assert!(
        2 * with.bytes.len() < without.bytes.len(),
        "{} vs {} B",
        with.bytes.len(),
        without.bytes.len()
    );
    // An object at rest uses no free flight: the stream is what the plain encoder writes.
    let rest = [common::resting(&mut Rng::new(5), 120)];
    let dynamics = RotationDynamics {
        inertia: vec![Some(inertia)],
        ..dynamics
    };
    let a = encode_world_with_dynamics(&rest, &p, Some(&dynamics)).unwrap();
    assert_eq!(a.stats.free_rotation_segments, 0);
    assert_eq!(a.bytes, encode_world(&rest, &p).unwrap().bytes);
}

#[test]
fn bad_dynamics_are_refused_with_the_field_named() {
    let dt = 1.0 / 120.0;
    let tracks = [generate(0, 1, 10, dt)];
    let p = EncodeParams::from_quality(Quality::Standard, dt, MotionModel::General);
    for (d, field) in [
        (
            RotationDynamics {
                substeps: 0,
                angular_damping: 0.0,
                inertia: vec![],
            },
            "substeps",
        ),
        (
            RotationDynamics {
                substeps: 17,
                angular_damping: 0.0,
                inertia: vec![],
            },
            "substeps",
        ),
        (
            RotationDynamics {
                substeps: 4,
                angular_damping: f64::NAN,
                inertia: vec![],
            },
            "angular_damping",
        ),
        (
            RotationDynamics {
                substeps: 4,
                angular_damping: 0.5,
                inertia: vec![Some([1.0, -1.0, 1.0])],
            },
            "inertia",
        ),
    ] {
        match encode_world_with_dynamics(&tracks, &p, Some(&d)) {
            Err(CodecError::InvalidParam { name, .. }) => assert_eq!(name, field),
            other => panic!("{field}: {other:?}"),
        }
    }
}

#[test]
fn presets_hold_on_every_generator() {
    for quality in [Quality::Draft, Quality::Standard, Quality::Final] {
        for model in [
            MotionModel::General,
            MotionModel::FreeFlightGravity { g: G },
        ] {
            let p = EncodeParams::from_quality(quality, 1.0 / 120.0, model);
            let tracks: Vec<Track> = (0..6)
                .map(|k| generate(k, 42 + k as u64, 360, p.frame_dt))
                .collect();
            check_world(&tracks, &p).unwrap();
        }
    }
}

#[test]
fn a_very_long_track_stays_linear_and_bounded() {
    // 10 minutes at 120 Hz of bouncing-then-resting motion, then spinning: 72 000 frames.
    let dt = 1.0 / 120.0;
    let mut track = generate(0, 7, 36_000, dt);
    let spin = generate(3, 8, 36_000, dt);
    track.positions.extend(spin.positions);
    track.rotations.extend(spin.rotations);
    let p = EncodeParams::from_quality(
        Quality::Standard,
        dt,
        MotionModel::FreeFlightGravity { g: G },
    );
    check_world(std::slice::from_ref(&track), &p).unwrap();
}

#[test]
fn empty_and_single_frame_worlds() {
    let p = EncodeParams::from_quality(Quality::Standard, 0.01, MotionModel::General);
    let w = encode_world(&[], &p).unwrap();
    let r = WorldReader::new(&w.bytes).unwrap();
    assert_eq!((r.object_count(), r.frame_count()), (0, 0));
    assert!(r.decode_all().unwrap().is_empty());
    assert!(matches!(
        r.decode_object(0),
        Err(CodecError::ObjectOutOfRange { index: 0, count: 0 })
    ));

    let one = Track {
        positions: vec![[1.5, -2.0, 1e6]],
        rotations: vec![[0.0, 0.0, 0.6, 0.8]],
    };
    let w = encode_world(&[Track::default(), one.clone()], &p).unwrap();
    let r = WorldReader::new(&w.bytes).unwrap();
    assert_eq!(r.decode_object(0).unwrap(), Track::default());
    let d = r.decode_object(1).unwrap();
    assert!(distance(d.positions[0], one.positions[0]) <= 1e-3);
    assert!(matches!(
        r.sample(0, 0.0),
        Err(CodecError::TimeOutOfRange { .. })
    ));
    assert!(r.sample(1, 0.0).is_ok());
    assert!(matches!(
        r.sample(1, 0.01),
        Err(CodecError::TimeOutOfRange { .. })
    ));
    assert!(matches!(
        r.sample(1, f64::NAN),
        Err(CodecError::TimeOutOfRange { .. })
    ));
    assert_eq!(w.lowres[1].frames, vec![0]);
}

#[test]
fn sampling_between_frames_follows_the_spline() {
    let dt = 1.0 / 120.0;
    let track = generate(0, 3, 240, dt);
    let p = EncodeParams::from_quality(
        Quality::Standard,
        dt,
        MotionModel::FreeFlightGravity { g: G },
    );
    let w = encode_world(std::slice::from_ref(&track), &p).unwrap();
    let r = WorldReader::new(&w.bytes).unwrap();
    for f in 0..239 {
        let (a, _) = r.sample_frame(0, f).unwrap();
        let (b, _) = r.sample_frame(0, f + 1).unwrap();
        let (m, q) = r.sample(0, (f as f64 + 0.5) * dt).unwrap();
        // Between two frames the curve stays near both (velocities here are < 10 m/s).
        assert!(distance(a, m) < 0.1 && distance(b, m) < 0.1, "frame {f}");
        assert!((q.iter().map(|v| v * v).sum::<f64>() - 1.0).abs() < 1e-12);
    }
}

#[test]
fn free_flight_model_spends_one_bit_on_the_quadratic_term() {
    // Pure ballistic flight (no floor): the gravity model stores no quadratic coefficients, so it
    // must be smaller than the general model on the same motion.
    let dt = 1.0 / 120.0;
    let track = Track {
        positions: (0..600)
            .map(|i| {
                let t = i as f64 * dt;
                [0.3 * t, 100.0 + 20.0 * t - 4.905 * t * t, -0.7 * t]
            })
            .collect(),
        rotations: vec![[0.0, 0.0, 0.0, 1.0]; 600],
    };
    let size = |model| {
        let p = EncodeParams::from_quality(Quality::Standard, dt, model);
        encode_world(std::slice::from_ref(&track), &p).unwrap()
    };
    let gravity = size(MotionModel::FreeFlightGravity { g: G });
    let general = size(MotionModel::General);
    assert_eq!(gravity.stats.position_segments, 1);
    assert!(
        gravity.bytes.len() < general.bytes.len(),
        "{} vs {}",
        gravity.bytes.len(),
        general.bytes.len()
    );
}

#[test]
fn reader_reports_header_fields() {
    let p = EncodeParams::from_quality(
        Quality::Final,
        0.005,
        MotionModel::FreeFlightGravity { g: G },
    );
    let w = encode_world(&[generate(0, 1, 50, 0.005)], &p).unwrap();
    let r = WorldReader::new(&w.bytes).unwrap();
    assert_eq!(r.version(), mwb_codec::FORMAT_VERSION);
    assert_eq!(r.frame_dt(), 0.005);
    assert_eq!((r.e_max(), r.theta_max()), Quality::Final.bounds());
    assert_eq!(r.quality(), Some(Quality::Final));
    assert_eq!(r.model(), MotionModel::FreeFlightGravity { g: G });
    // A world starts with its version byte.
    assert_eq!(w.bytes[0], mwb_codec::FORMAT_VERSION);
}

#[test]
fn extreme_values_fall_back_to_exact_keys() {
    // Coordinates of 1e12 m jumping by 1e12 m per frame at e_max = 1 µm: no quantised coefficient
    // fits in 52 bits, so the encoder must store exact key frames and still meet the bound.
    let n = 40;
    let track = Track {
        positions: (0..n)
            .map(|i| [1e12 * (i % 3) as f64, -7.5e11, 0.25 * i as f64])
            .collect(),
        rotations: (0..n)
            .map(|i| common::quat_exp([0.0, 3.0 * i as f64, 0.1]))
            .collect(),
    };
    let p = EncodeParams {
        e_max: 1e-6,
        theta_max: mwb_codec::MIN_THETA_MAX,
        frame_dt: 1.0 / 120.0,
        model: MotionModel::General,
        lowres_hz: 4.0,
        search: Search::Exhaustive,
    };
    let w = encode_world(std::slice::from_ref(&track), &p).unwrap();
    assert!(w.stats.key_segments > 0, "{:?}", w.stats);
    check_world(std::slice::from_ref(&track), &p).unwrap();
}
