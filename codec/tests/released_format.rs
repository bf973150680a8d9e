//! What was recorded stays readable: streams of the released format version 1, saved as
//! fixtures, decode through every read path to exactly the poses they decoded to when they were
//! written — and so stay within the bounds of the motion they were made from.
//!
//! These fixtures are the guard of every later change: an encoder change may write other bytes,
//! a format change gets a new version number (and fixtures of its own, beside these), but these
//! files are never re-minted: a build that fails this test can no longer read recordings.

mod common;

use common::{G, Rng, distance, generate, normalise, rotation_angle, torque_free};
use mwb_codec::{
    EncodeParams, MotionModel, Quality, RotationDynamics, Track, WorldReader,
    encode_world_with_dynamics,
};

const DT: f64 = 1.0 / 120.0;

/// One fixture: how its input motion and encoder parameters are made (the fixture itself is
/// what the writing build encoded; the `.poses` file what it decoded).
struct Fixture {
    name: &'static str,
    tracks: fn() -> Vec<Track>,
    params: fn() -> EncodeParams,
    dynamics: Option<fn() -> RotationDynamics>,
    /// Whether the writing build used free-flight rotation segments (checked when minting).
    free_flights: bool,
}

/// Version 1 fixtures, written by the encoder of the commit that released the format:
///
/// * `v1_gravity_standard`: six objects, one per test generator (`generate(object, 31 + object,
///   120, 1/120)`), Standard preset, gravity model (preset bounds, a well-known gravity, one frame
///   count for all objects);
/// * `v1_general_free_draft`: the same six objects with objects 0 and 1 torque-free bodies
///   ([`spinning`]), Draft preset, General model, with rotation dynamics (six free-flight
///   segments, the dynamics header fields);
/// * `v1_decimal_varied`: five generator tracks of 60, 1, 0, 25 and 90 frames at 60 Hz, bounds
///   e_max = 2 mm, θ_max = 3 mrad and gravity (0, −9.8, 0) (decimal header numbers, a frame count
///   per object, an empty and a one-frame object).
const FIXTURES: [Fixture; 3] = [
    Fixture {
        name: "v1_gravity_standard",
        tracks: generated,
        params: || EncodeParams::from_quality(Quality::Standard, DT, GRAVITY),
        dynamics: None,
        free_flights: false,
    },
    Fixture {
        name: "v1_general_free_draft",
        tracks: || (0..6).map(spinning).collect(),
        params: || EncodeParams::from_quality(Quality::Draft, DT, MotionModel::General),
        dynamics: Some(|| RotationDynamics {
            substeps: 4,
            angular_damping: 0.5,
            inertia: vec![Some(INERTIA), Some(INERTIA)],
        }),
        free_flights: true,
    },
    Fixture {
        name: "v1_decimal_varied",
        tracks: || {
            [60, 1, 0, 25, 90]
                .into_iter()
                .enumerate()
                .map(|(i, n)| generate(i, 51 + i as u64, n, 1.0 / 60.0))
                .collect()
        },
        params: || EncodeParams {
            e_max: 0.002,
            theta_max: 0.003,
            ..EncodeParams::from_quality(
                Quality::Standard,
                1.0 / 60.0,
                MotionModel::FreeFlightGravity {
                    g: [0.0, -9.8, 0.0],
                },
            )
        },
        dynamics: None,
        free_flights: false,
    },
];

const GRAVITY: MotionModel = MotionModel::FreeFlightGravity { g: G };
const INERTIA: [f64; 3] = [0.2, 1.1, 0.9];

fn generated() -> Vec<Track> {
    (0..6)
        .map(|object| generate(object, 31 + object as u64, 120, DT))
        .collect()
}

/// Objects 0 and 1: torque-free bodies with principal moments [`INERTIA`], kicked at frame 60
/// (`torque_free(Rng::new(41 + object), INERTIA, 120, 1/120, &[60], 5.0, 0.5)`); the others the
/// generators' tracks.
fn spinning(object: usize) -> Track {
    if object < 2 {
        let mut rng = Rng::new(41 + object as u64);
        torque_free(&mut rng, INERTIA, 120, DT, &[60], 5.0, 0.5)
    } else {
        generate(object, 31 + object as u64, 120, DT)
    }
}

fn path(name: &str, ext: &str) -> String {
    format!("{}/tests/fixtures/{name}.{ext}", env!("CARGO_MANIFEST_DIR"))
}

fn fixture(name: &str, ext: &str) -> Vec<u8> {
    let path = path(name, ext);
    std::fs::read(&path).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// Per object, per frame, 7 little-endian f64s (position, then quaternion x, y, z, w).
fn pose_bytes(tracks: &[Track]) -> Vec<u8> {
    tracks
        .iter()
        .flat_map(|t| t.positions.iter().zip(&t.rotations))
        .flat_map(|(p, q)| p.iter().chain(q).flat_map(|v| v.to_le_bytes()))
        .collect()
}

#[test]
fn version_1_streams_decode_to_the_recorded_poses() {
    for f in &FIXTURES {
        let name = f.name;
        let bytes = fixture(name, "mwbm");
        let reader = WorldReader::new(&bytes).unwrap();
        assert_eq!(bytes[0], 1, "{name}: the version byte");
        assert_eq!(reader.version(), 1, "{name}");
        let p = (f.params)();
        let input = (f.tracks)();
        assert_eq!((reader.e_max(), reader.theta_max()), (p.e_max, p.theta_max));
        assert_eq!(reader.frame_dt(), p.frame_dt, "{name}");
        assert_eq!(reader.model(), p.model, "{name}");
        assert_eq!(reader.object_count(), input.len(), "{name}");
        let all = reader.decode_all().unwrap();
        // Bit for bit what the writing build decoded.
        let want = fixture(name, "poses");
        assert_eq!(pose_bytes(&all).len(), want.len(), "{name}");
        for (i, (g, w)) in pose_bytes(&all).chunks(56).zip(want.chunks(56)).enumerate() {
            assert_eq!(g, w, "{name}: pose {i}");
        }
        for (object, (decoded, input)) in all.iter().zip(&input).enumerate() {
            assert_eq!(decoded.len(), input.len(), "{name}: object {object}");
            assert_eq!(reader.object_frame_count(object).unwrap(), input.len());
            assert_eq!(&reader.decode_object(object).unwrap(), decoded);
            let n = decoded.len() as u32;
            for frame in [0, 1, n / 2, n.saturating_sub(1)] {
                if frame < n {
                    let (p, q) = reader.sample_frame(object, frame).unwrap();
                    assert_eq!(p, decoded.positions[frame as usize], "{name}");
                    assert_eq!(q, decoded.rotations[frame as usize], "{name}");
                }
            }
            // Within the bounds of the motion the fixture was made from.
            for f in 0..input.len() {
                let d = distance(decoded.positions[f], input.positions[f]);
                assert!(d <= p.e_max, "{name}: object {object} frame {f}");
                let a = rotation_angle(decoded.rotations[f], normalise(input.rotations[f]));
                assert!(a <= p.theta_max, "{name}: object {object} frame {f}");
            }
        }
    }
}

/// Writes the fixtures that do not exist yet (never overwrites one: recorded streams must stay
/// as they were). Only for a new format version's fixtures:
/// `MWB_MINT_FIXTURES=1 cargo test -p mwb-codec --test released_format -- --ignored`.
#[test]
#[ignore = "writes fixtures; run only to add those of a new format version"]
fn mint_missing_fixtures() {
    if std::env::var("MWB_MINT_FIXTURES").is_err() {
        return;
    }
    for f in &FIXTURES {
        if std::path::Path::new(&path(f.name, "mwbm")).exists() {
            continue;
        }
        let d = f.dynamics.map(|d| d());
        let w = encode_world_with_dynamics(&(f.tracks)(), &(f.params)(), d.as_ref()).unwrap();
        println!(
            "{}: {} free flights",
            f.name, w.stats.free_rotation_segments
        );
        assert_eq!(
            w.stats.free_rotation_segments > 0,
            f.free_flights,
            "{}",
            f.name
        );
        let decoded = WorldReader::new(&w.bytes).unwrap().decode_all().unwrap();
        std::fs::write(path(f.name, "mwbm"), &w.bytes).unwrap();
        std::fs::write(path(f.name, "poses"), pose_bytes(&decoded)).unwrap();
    }
}
