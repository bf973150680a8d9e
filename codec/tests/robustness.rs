//! Any byte string given to the decoder returns an error or a value — never a panic, never
//! unbounded memory. Arbitrary bytes, bytes behind a valid header, bit-flipped and truncated
//! valid streams.

mod common;

use common::{G, generate};
use mwb_codec::{DecodeLimits, EncodeParams, MotionModel, Quality, WorldReader, encode_world};
use proptest::prelude::*;

/// Small caps, so that hostile frame counts are refused quickly instead of decoded.
const LIMITS: DecodeLimits = DecodeLimits {
    max_object_frames: 1 << 14,
    max_total_frames: 1 << 16,
};

/// Calls every decode entry point; returns how many succeeded. Values that come back must be sane.
fn exercise(bytes: &[u8]) -> usize {
    let Ok(r) = WorldReader::with_limits(bytes, LIMITS) else {
        return 0;
    };
    let mut ok = 1;
    let _ = (
        r.frame_count(),
        r.frame_dt(),
        r.e_max(),
        r.quality(),
        r.model(),
        r.version(),
    );
    let n = r.object_count().min(8);
    for i in 0..=n {
        if let Ok(t) = r.decode_object(i) {
            ok += 1;
            assert_eq!(t.positions.len(), t.rotations.len());
            assert_eq!(t.positions.len(), r.object_frame_count(i).unwrap());
            assert!(t.positions.iter().flatten().all(|v| v.is_finite()));
            for q in &t.rotations {
                assert!((q.iter().map(|v| v * v).sum::<f64>() - 1.0).abs() < 1e-9);
            }
        }
        for t in [0.0, 0.013, 1.0, -1.0, f64::NAN, f64::INFINITY, 1e300] {
            ok += usize::from(r.sample(i, t).is_ok());
        }
        for f in [0, 1, 7, u32::MAX] {
            ok += usize::from(r.sample_frame(i, f).is_ok());
        }
    }
    ok += usize::from(r.decode_all().is_ok());
    ok
}

fn valid_world() -> Vec<u8> {
    let dt = 1.0 / 120.0;
    let tracks: Vec<_> = (0..4)
        .map(|k| generate(k, 100 + k as u64, 150, dt))
        .collect();
    let p = EncodeParams::from_quality(
        Quality::Standard,
        dt,
        MotionModel::FreeFlightGravity { g: G },
    );
    encode_world(&tracks, &p).unwrap().bytes
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]

    #[test]
    fn arbitrary_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..600)) {
        exercise(&bytes);
    }

    #[test]
    fn arbitrary_payload_behind_a_valid_header(
        objects in 0u32..6,
        frames in proptest::collection::vec(any::<u32>(), 6),
        payload in proptest::collection::vec(any::<u8>(), 0..400),
        model in 0u8..2,
    ) {
        // A real header, a plausible index, random object streams: reaches the segment decoder.
        let mut bytes = valid_world()[..80].to_vec();
        bytes[8] = model;
        bytes[12..16].copy_from_slice(&objects.to_le_bytes());
        let per = payload.len() as u32 / objects.max(1);
        for i in 0..objects {
            bytes.extend_from_slice(&(i * per).to_le_bytes());
            bytes.extend_from_slice(&(frames[i as usize] % 3000).to_le_bytes());
        }
        bytes.extend_from_slice(&payload);
        exercise(&bytes);
    }

    #[test]
    fn bit_flipped_valid_streams(flips in proptest::collection::vec(any::<prop::sample::Index>(), 1..8)) {
        let mut bytes = valid_world();
        let bits = bytes.len() * 8;
        for f in flips {
            let b = f.index(bits);
            bytes[b / 8] ^= 1 << (b % 8);
        }
        exercise(&bytes);
    }

    #[test]
    fn truncated_and_extended_valid_streams(cut in any::<prop::sample::Index>(), tail in proptest::collection::vec(any::<u8>(), 0..16)) {
        let mut bytes = valid_world();
        let n = cut.index(bytes.len() + 1);
        bytes.truncate(n);
        bytes.extend_from_slice(&tail);
        exercise(&bytes);
    }
}

#[test]
fn the_valid_world_passes_every_entry_point() {
    let bytes = valid_world();
    // 1 (reader) + 4 objects × (1 decode + 3 sample times in range + 3 in-range frames)
    // + decode_all; the fifth index is out of range and must fail everywhere.
    assert_eq!(exercise(&bytes), 1 + 4 * 7 + 1);
}

#[test]
fn hostile_frame_counts_are_refused_before_allocating() {
    // One object claiming 4 billion frames, covered by a single Rice-coded segment.
    let mut bytes = valid_world()[..80].to_vec();
    bytes[12..16].copy_from_slice(&1u32.to_le_bytes());
    bytes.extend_from_slice(&0u32.to_le_bytes());
    bytes.extend_from_slice(&u32::MAX.to_le_bytes());
    bytes.extend_from_slice(&[0xFF; 64]);
    let r = WorldReader::new(&bytes).unwrap();
    assert_eq!(r.frame_count(), u32::MAX as usize);
    assert!(matches!(
        r.decode_object(0),
        Err(mwb_codec::CodecError::LimitExceeded { .. })
    ));
    assert!(matches!(
        r.decode_all(),
        Err(mwb_codec::CodecError::LimitExceeded { .. })
    ));
}

#[test]
fn unknown_versions_and_magic_are_named() {
    let mut bytes = valid_world();
    bytes[4] = 9;
    assert!(matches!(
        WorldReader::new(&bytes),
        Err(mwb_codec::CodecError::UnsupportedVersion {
            found: 9,
            supported: 1
        })
    ));
    bytes[0] = b'X';
    assert!(matches!(
        WorldReader::new(&bytes),
        Err(mwb_codec::CodecError::BadMagic { .. })
    ));
}
