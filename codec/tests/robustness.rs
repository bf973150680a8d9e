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

/// A version-1 header (80 bytes, fixed layout) from the saved fixture.
fn v1_header() -> Vec<u8> {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/fixtures/v1_gravity_standard.mwbm"
    );
    std::fs::read(path).expect("fixture")[..80].to_vec()
}

/// A version-2 header (see `format`): Standard preset, 120 Hz, the given model and object count,
/// optionally one frame count for every object, start Rice parameters 13 and 15.
fn v2_header(model: u8, objects: u32, common_frames: Option<u32>) -> Vec<u8> {
    fn varint(out: &mut Vec<u8>, mut v: u64) {
        while v >= 0x80 {
            out.push((v as u8) | 0x80);
            v >>= 7;
        }
        out.push(v as u8);
    }
    let mut h = b"MWBM".to_vec();
    h.extend_from_slice(&2u16.to_le_bytes());
    h.extend_from_slice(&[0, 0]);
    h.push(model);
    h.push(1 | 2 | if common_frames.is_some() { 8 } else { 0 });
    h.push(1); // standard
    varint(&mut h, 120);
    if model == 1 {
        h.push(0x80); // y-up 9.81
    }
    h.extend_from_slice(&[13, 15]); // Rice parameters of the start values
    varint(&mut h, u64::from(objects));
    if let Some(f) = common_frames {
        varint(&mut h, u64::from(f));
    }
    let len = h.len() as u16;
    h[6..8].copy_from_slice(&len.to_le_bytes());
    h
}

/// The same header as format 3 (its header layout is format 2's).
fn v3_header(model: u8, objects: u32, common_frames: Option<u32>) -> Vec<u8> {
    let mut h = v2_header(model, objects, common_frames);
    h[4..6].copy_from_slice(&3u16.to_le_bytes());
    h
}

/// A format-4 header with rotation dynamics (flag 16: 4 substeps, angular damping 0.5 as 500
/// thousandths), so payloads reach the free-flight segment decoder.
fn v4_dynamics_header(model: u8, objects: u32, common_frames: Option<u32>) -> Vec<u8> {
    let mut h = v2_header(model, objects, common_frames);
    h[4..6].copy_from_slice(&4u16.to_le_bytes());
    h[9] |= 16;
    h.extend_from_slice(&[4, 1, 0xf4, 0x03]);
    let len = h.len() as u16;
    h[6..8].copy_from_slice(&len.to_le_bytes());
    h
}

/// After a version-2-to-6 header: an index whose lengths add up (the payload split between
/// `objects`, each with its own frame count unless `common`), then the payload.
fn index_and_payloads(
    bytes: &mut Vec<u8>,
    objects: u32,
    frames: &[u32],
    common: bool,
    payload: &[u8],
) {
    let per = payload.len() / objects.max(1) as usize;
    for (i, f) in frames.iter().enumerate().take(objects as usize) {
        let len = if i + 1 == objects as usize {
            payload.len() - per * i
        } else {
            per
        };
        let mut v = len as u64;
        while v >= 0x80 {
            bytes.push((v as u8) | 0x80);
            v >>= 7;
        }
        bytes.push(v as u8);
        if !common {
            bytes.push((f % 100) as u8 + 1);
        }
    }
    if objects > 0 {
        bytes.extend_from_slice(payload);
    }
}

/// The compact (version 6) form of a version-2-to-5 header: the version byte, the flags with the
/// model as flag 64, then the same fields.
fn v6_header(legacy: &[u8]) -> Vec<u8> {
    let mut h = vec![6, legacy[9] | if legacy[8] == 1 { 64 } else { 0 }];
    h.extend_from_slice(&legacy[10..]);
    h
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
    fn arbitrary_payload_behind_a_valid_v1_header(
        objects in 0u32..6,
        frames in proptest::collection::vec(any::<u32>(), 6),
        payload in proptest::collection::vec(any::<u8>(), 0..400),
        model in 0u8..2,
    ) {
        // A real header, a plausible index, random object streams: reaches the segment decoder.
        let mut bytes = v1_header();
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
    fn arbitrary_payload_behind_a_valid_v2_to_v4_header(
        version in 2u16..6,
        objects in 0u32..6,
        frames in proptest::collection::vec(any::<u32>(), 6),
        common in any::<bool>(),
        payload in proptest::collection::vec(any::<u8>(), 0..400),
        model in 0u8..2,
    ) {
        // A real header and an index whose lengths add up, so the segment decoder is reached.
        let common_frames = common.then_some(frames[0] % 3000);
        // 2, 3, 4; 5 stands for 4 with rotation dynamics.
        let mut bytes = if version == 5 {
            v4_dynamics_header(model, objects, common_frames)
        } else {
            v2_header(model, objects, common_frames)
        };
        bytes[4..6].copy_from_slice(&version.min(4).to_le_bytes());
        index_and_payloads(&mut bytes, objects, &frames, common, &payload);
        exercise(&bytes);
    }

    #[test]
    fn arbitrary_payload_behind_a_valid_v6_header(
        objects in 0u32..6,
        frames in proptest::collection::vec(any::<u32>(), 6),
        common in any::<bool>(),
        dynamics in any::<bool>(),
        payload in proptest::collection::vec(any::<u8>(), 0..400),
        model in 0u8..2,
    ) {
        // The compact header (format 6: lattice vectors, free flights with `dynamics`) and an
        // index whose lengths add up.
        let common_frames = common.then_some(frames[0] % 3000);
        let legacy = if dynamics {
            v4_dynamics_header(model, objects, common_frames)
        } else {
            v2_header(model, objects, common_frames)
        };
        let mut bytes = v6_header(&legacy);
        index_and_payloads(&mut bytes, objects, &frames, common, &payload);
        // The header and index are sound: the reader opens, and the payloads are what is tested.
        let opened = WorldReader::new(&bytes);
        proptest::prop_assert!(opened.is_ok(), "{:?}", opened.err());
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
    // One object claiming 4 billion frames, covered by a single segment — in every format
    // version.
    let mut v1 = v1_header();
    v1[12..16].copy_from_slice(&1u32.to_le_bytes());
    v1.extend_from_slice(&0u32.to_le_bytes());
    v1.extend_from_slice(&u32::MAX.to_le_bytes());
    v1.extend_from_slice(&[0xFF; 64]);
    let mut v2 = v2_header(1, 1, Some(u32::MAX));
    v2.push(64);
    v2.extend_from_slice(&[0x00; 64]);
    let mut v3 = v3_header(1, 1, Some(u32::MAX));
    v3.push(64);
    v3.extend_from_slice(&[0x00; 64]);
    let mut v6 = v6_header(&v2_header(1, 1, Some(u32::MAX)));
    v6.push(64);
    v6.extend_from_slice(&[0x00; 64]);
    for bytes in [v1, v2, v3, v6] {
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
        // Random access needs no allocation, and a stream that cannot cover the frames ends in
        // an error, not a long loop.
        let _ = r.sample_frame(0, u32::MAX - 1);
    }
}

/// Formats 3 and 4 are range-coded: a symbol may take a small fraction of a bit, so what ends a
/// hostile stream is the end of its bytes (the decoder reads a few zeros past it, then fails).
/// Random and patterned payloads under a header claiming 4 billion frames end, and quickly.
#[test]
fn hostile_range_coded_payloads_end() {
    let mut seed = 0x5EEDu64;
    let mut next = || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 33) as u8
    };
    let mut payloads: Vec<Vec<u8>> = [0x00u8, 0xFF, 0x55, 0x80, 0x7F]
        .iter()
        .map(|&b| vec![b; 200])
        .collect();
    payloads.extend((0..300).map(|i| (0..(i % 200) + 1).map(|_| next()).collect()));
    let start = std::time::Instant::now();
    // Format 4's free flights are simulated frame by frame: the reader's frame limit bounds that
    // work too (here 2¹⁶ frames, so the test stays quick).
    let limits = mwb_codec::DecodeLimits {
        max_object_frames: 1 << 16,
        max_total_frames: 1 << 16,
    };
    for payload in payloads {
        for (model, header) in [
            (0u8, v3_header as fn(u8, u32, Option<u32>) -> Vec<u8>),
            (1, v3_header),
            (0, v4_dynamics_header),
            (1, v4_dynamics_header),
        ] {
            let mut bytes = header(model, 1, Some(u32::MAX));
            let mut len = Vec::new();
            let mut v = payload.len() as u64;
            while v >= 0x80 {
                len.push((v as u8) | 0x80);
                v >>= 7;
            }
            len.push(v as u8);
            bytes.extend_from_slice(&len);
            bytes.extend_from_slice(&payload);
            let r = WorldReader::with_limits(&bytes, limits).unwrap();
            let _ = r.sample_frame(0, u32::MAX - 1);
            let _ = r.sample(0, 1e6);
        }
    }
    println!("{:?}", start.elapsed());
}

#[test]
fn unknown_versions_and_magic_are_named() {
    let mut bytes = valid_world();
    assert_eq!(
        WorldReader::new(&bytes).unwrap().version(),
        mwb_codec::FORMAT_VERSION
    );
    // Version 6 on: the version is the first byte.
    assert_eq!(u16::from(bytes[0]), mwb_codec::FORMAT_VERSION);
    for version in [9u8, 5, 0] {
        bytes[0] = version;
        assert!(matches!(
            WorldReader::new(&bytes),
            Err(mwb_codec::CodecError::UnsupportedVersion {
                found,
                supported: mwb_codec::FORMAT_VERSION,
            }) if found == u16::from(version)
        ));
    }
    bytes[0] = b'X';
    assert!(matches!(
        WorldReader::new(&bytes),
        Err(mwb_codec::CodecError::BadMagic { .. })
    ));
    // Versions 1 to 5 start with the magic, then the version.
    let mut old = v2_header(0, 0, None);
    old[4] = 9;
    assert!(matches!(
        WorldReader::new(&old),
        Err(mwb_codec::CodecError::UnsupportedVersion {
            found: 9,
            supported: mwb_codec::FORMAT_VERSION,
        })
    ));
}

#[test]
fn index_lengths_must_add_up_to_the_payload() {
    let mut bytes = v2_header(0, 2, Some(10));
    bytes.extend_from_slice(&[3, 4]);
    bytes.extend_from_slice(&[0; 6]);
    assert!(matches!(
        WorldReader::new(&bytes),
        Err(mwb_codec::CodecError::Corrupt { .. })
    ));
    bytes.push(0);
    assert!(WorldReader::new(&bytes).is_ok());
    // An object count far beyond the input ends at the end of the input.
    let mut bytes = v2_header(0, u32::MAX, None);
    bytes.extend_from_slice(&[1, 1, 0]);
    assert!(WorldReader::new(&bytes).is_err());
}
