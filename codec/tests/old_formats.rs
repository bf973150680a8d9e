//! Old recordings stay readable: streams written by the version-1 to -5 encoders (saved as
//! fixtures before formats 2 to 6 replaced them) still decode, through every read path, to
//! exactly the poses they decoded to when they were written — and so stay within the bounds of
//! the motion they were made from.

mod common;

use common::{G, Rng, distance, generate, normalise, rotation_angle, torque_free};
use mwb_codec::{MotionModel, Quality, Track, WorldReader};

/// `(format version, fixture, preset, model)`: six objects, one per test generator (seeds
/// 31..37), 120 frames at 120 Hz (tracks `common::generate(object, 31 + object, 120, 1/120)`),
/// encoded with `EncodeParams::from_quality(preset, 1/120, model)`; the `.poses` files are what
/// the writing build decoded. Version 1: format-1 code; version 2: the encoder of commit
/// d1ba8c1; version 3: the encoder of commit 116d0ab; version 4: the encoder of commit b13b33d;
/// version 5: the encoder of commit 1700221 (the `*_free_final` ones with rotation dynamics, see
/// [`free_input`]).
const FIXTURES: [(u16, &str, Quality, MotionModel); 10] = [
    (1, "v1_gravity_standard", Quality::Standard, GRAVITY),
    (1, "v1_general_draft", Quality::Draft, MotionModel::General),
    (2, "v2_gravity_standard", Quality::Standard, GRAVITY),
    (2, "v2_general_draft", Quality::Draft, MotionModel::General),
    (3, "v3_gravity_standard", Quality::Standard, GRAVITY),
    (3, "v3_general_draft", Quality::Draft, MotionModel::General),
    (4, "v4_gravity_standard", Quality::Standard, GRAVITY),
    (4, "v4_free_final", Quality::Final, GRAVITY),
    (5, "v5_gravity_standard", Quality::Standard, GRAVITY),
    (5, "v5_free_final", Quality::Final, GRAVITY),
];

const GRAVITY: MotionModel = MotionModel::FreeFlightGravity { g: G };

/// The motion of the `*_free_final` fixtures: objects 0 and 1 torque-free bodies with principal
/// moments `[0.2, 1.1, 0.9]` (`torque_free(Rng::new(41 + object), [0.2, 1.1, 0.9], 120, 1/120,
/// &[60], 5.0, 0.5)`), the rest the generators' tracks; encoded with `RotationDynamics {
/// substeps: 4, angular_damping: 0.5 }` and those moments for objects 0 and 1 (three free-flight
/// segments in all).
fn free_input(object: usize) -> Track {
    if object < 2 {
        let mut rng = Rng::new(41 + object as u64);
        torque_free(&mut rng, [0.2, 1.1, 0.9], 120, 1.0 / 120.0, &[60], 5.0, 0.5)
    } else {
        generated(object)
    }
}

fn generated(object: usize) -> Track {
    generate(object, 31 + object as u64, 120, 1.0 / 120.0)
}

#[test]
fn version_1_streams_decode_to_the_same_poses() {
    check(1);
}

#[test]
fn version_2_streams_decode_to_the_same_poses() {
    check(2);
}

#[test]
fn version_3_streams_decode_to_the_same_poses() {
    check(3);
}

#[test]
fn version_4_streams_decode_to_the_same_poses() {
    check(4);
}

#[test]
fn version_5_streams_decode_to_the_same_poses() {
    check(5);
}

fn fixture(name: &str, ext: &str) -> Vec<u8> {
    let path = format!("{}/tests/fixtures/{name}.{ext}", env!("CARGO_MANIFEST_DIR"));
    std::fs::read(&path).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// The poses as written beside each fixture: per object, per frame, 7 little-endian f64s.
fn poses(bytes: &[u8]) -> Vec<[f64; 7]> {
    bytes
        .chunks_exact(56)
        .map(|c| {
            std::array::from_fn(|i| f64::from_le_bytes(c[8 * i..8 * i + 8].try_into().unwrap()))
        })
        .collect()
}

/// Every fixture of format `version` reads as that format and decodes, through every read path,
/// to the saved poses bit for bit, within the bounds of the motion it was made from.
fn check(version: u16) {
    let fixtures: Vec<_> = FIXTURES.iter().filter(|f| f.0 == version).collect();
    assert!(!fixtures.is_empty(), "no fixtures of version {version}");
    for &&(_, name, quality, model) in &fixtures {
        let bytes = fixture(name, "mwbm");
        let want = poses(&fixture(name, "poses"));
        let reader = WorldReader::new(&bytes).unwrap();
        assert_eq!(reader.version(), version, "{name}");
        assert_eq!(reader.quality(), Some(quality));
        assert_eq!(reader.model(), model);
        assert_eq!((reader.object_count(), reader.frame_count()), (6, 120));
        let all = reader.decode_all().unwrap();
        let got: Vec<[f64; 7]> = all
            .iter()
            .flat_map(|t| {
                t.positions
                    .iter()
                    .zip(&t.rotations)
                    .map(|(p, q)| [p[0], p[1], p[2], q[0], q[1], q[2], q[3]])
            })
            .collect();
        assert_eq!(got.len(), want.len());
        for (i, (g, w)) in got.iter().zip(&want).enumerate() {
            assert_eq!(g.map(f64::to_bits), w.map(f64::to_bits), "{name}: pose {i}");
        }
        for (object, decoded) in all.iter().enumerate() {
            assert_eq!(&reader.decode_object(object).unwrap(), decoded);
            for f in [0u32, 1, 59, 119] {
                let (p, q) = reader.sample_frame(object, f).unwrap();
                assert_eq!(p, decoded.positions[f as usize]);
                assert_eq!(q, decoded.rotations[f as usize]);
            }
            // Within the bounds of the motion the fixture was made from.
            let input = if name.ends_with("_free_final") {
                free_input(object)
            } else {
                generated(object)
            };
            for f in 0..120 {
                assert!(distance(decoded.positions[f], input.positions[f]) <= quality.e_max());
                let a = rotation_angle(decoded.rotations[f], normalise(input.rotations[f]));
                assert!(
                    a <= quality.theta_max(),
                    "{name}: object {object} frame {f}"
                );
            }
        }
    }
}
