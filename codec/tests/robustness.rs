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

fn varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

/// A header (see `format`): Standard preset, 120 Hz, the gravity model (y-up 9.81) or the
/// general one, the object count, optionally one frame count for every object, start Rice
/// parameters 13 and 15, and with `dynamics` rotation dynamics (4 substeps, angular damping 0.5
/// as 500 thousandths), so that payloads reach the free-flight segment decoder.
fn header(gravity: bool, objects: u32, common_frames: Option<u32>, dynamics: bool) -> Vec<u8> {
    let mut flags = 1 | 2;
    flags |= if common_frames.is_some() { 8 } else { 0 };
    flags |= if dynamics { 16 } else { 0 };
    flags |= if gravity { 64 } else { 0 };
    let mut h = vec![mwb_codec::FORMAT_VERSION, flags, 1]; // version, flags, standard
    varint(&mut h, 120);
    if gravity {
        h.push(0x80); // y-up 9.81
    }
    h.extend_from_slice(&[13, 15]); // Rice parameters of the start values
    varint(&mut h, u64::from(objects));
    if let Some(f) = common_frames {
        varint(&mut h, u64::from(f));
    }
    if dynamics {
        h.extend_from_slice(&[4, 1, 0xf4, 0x03]);
    }
    h
}

/// After a header: an index whose lengths add up (the payload split between
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
        varint(bytes, len as u64);
        if !common {
            bytes.push((f % 100) as u8 + 1);
        }
    }
    if objects > 0 {
        bytes.extend_from_slice(payload);
    }
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
        common in any::<bool>(),
        dynamics in any::<bool>(),
        payload in proptest::collection::vec(any::<u8>(), 0..400),
        gravity in any::<bool>(),
    ) {
        // A real header (free flights with `dynamics`) and an index whose lengths add up, so the
        // segment decoder is reached.
        let common_frames = common.then_some(frames[0] % 3000);
        let mut bytes = header(gravity, objects, common_frames, dynamics);
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
    // One object claiming 4 billion frames, covered by a single segment.
    let mut bytes = header(true, 1, Some(u32::MAX), false);
    bytes.push(64);
    bytes.extend_from_slice(&[0x00; 64]);
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
    // Random access needs no allocation, and a stream that cannot cover the frames ends in an
    // error, not a long loop.
    let _ = r.sample_frame(0, u32::MAX - 1);
}

/// Payloads are range-coded: a symbol may take a small fraction of a bit, so what ends a hostile
/// stream is the end of its bytes (the decoder reads a few zeros past it, then fails).
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
    // Free flights are simulated frame by frame: the reader's frame limit bounds that
    // work too (here 2¹⁶ frames, so the test stays quick).
    let limits = mwb_codec::DecodeLimits {
        max_object_frames: 1 << 16,
        max_total_frames: 1 << 16,
    };
    for payload in payloads {
        for (gravity, dynamics) in [(false, false), (true, false), (false, true), (true, true)] {
            let mut bytes = header(gravity, 1, Some(u32::MAX), dynamics);
            varint(&mut bytes, payload.len() as u64);
            bytes.extend_from_slice(&payload);
            let r = WorldReader::with_limits(&bytes, limits).unwrap();
            let _ = r.sample_frame(0, u32::MAX - 1);
            let _ = r.sample(0, 1e6);
        }
    }
    println!("{:?}", start.elapsed());
}

/// The first byte is the format version: another version is refused by number (so that a
/// later build can read it beside version 1), a byte that is no version as not a world.
#[test]
fn unknown_versions_and_non_worlds_are_named() {
    let mut bytes = valid_world();
    assert_eq!(WorldReader::new(&bytes).unwrap().version(), 1);
    assert_eq!(bytes[0], mwb_codec::FORMAT_VERSION);
    for version in [0u8, 2, 6, 0x3F] {
        bytes[0] = version;
        let err = WorldReader::new(&bytes).unwrap_err();
        assert!(
            matches!(
                err,
                mwb_codec::CodecError::UnsupportedVersion { found, supported: 1 }
                    if found == version
            ),
            "{err:?}"
        );
        assert!(
            err.to_string().contains(&format!("version {version}")),
            "{err}"
        );
    }
    // Text, JSON, a container's magic: not worlds.
    for first in [0x40u8, b'M', b'{', b'X', 0xFF] {
        bytes[0] = first;
        assert!(matches!(
            WorldReader::new(&bytes),
            Err(mwb_codec::CodecError::NotAWorld { found }) if found == first
        ));
    }
    assert!(matches!(
        WorldReader::new(b"not a world"),
        Err(mwb_codec::CodecError::NotAWorld { found: b'n' })
    ));
    assert!(matches!(
        WorldReader::new(&[]),
        Err(mwb_codec::CodecError::Truncated { .. })
    ));
}

#[test]
fn index_lengths_must_add_up_to_the_payload() {
    let mut bytes = header(false, 2, Some(10), false);
    bytes.extend_from_slice(&[3, 4]);
    bytes.extend_from_slice(&[0; 6]);
    assert!(matches!(
        WorldReader::new(&bytes),
        Err(mwb_codec::CodecError::Corrupt { .. })
    ));
    bytes.push(0);
    assert!(WorldReader::new(&bytes).is_ok());
    // An object count far beyond the input ends at the end of the input.
    let mut bytes = header(false, u32::MAX, None, false);
    bytes.extend_from_slice(&[1, 1, 0]);
    assert!(WorldReader::new(&bytes).is_err());
}
