//! Feeds arbitrary bytes to every decode entry point of the motion codec. The contract under
//! test: an error or a value, never a panic, never unbounded memory.
//!
//! The reader opens one format, version 1 (the first byte; any other is refused before anything
//! else is read), so inputs that reach the payload decoder start with byte 1. Good seeds for the
//! corpus: the released-format fixtures (`cp ../codec/tests/fixtures/*.mwbm corpus/decode/`) and
//! streams with free flights from the scenes measurement (`MWB_SCENE_STREAMS_OUT`, see
//! `codec/tests/scenes.rs`).
//!
//! Run: `cargo +nightly fuzz run decode -- -max_total_time=120`
#![no_main]

use libfuzzer_sys::fuzz_target;
use mwb_codec::{DecodeLimits, WorldReader};

/// Small caps so that hostile frame counts are refused instead of decoded (the default caps
/// allow hundreds of MB, which is correct for real worlds but slow for a fuzzer).
const LIMITS: DecodeLimits = DecodeLimits {
    max_object_frames: 1 << 14,
    max_total_frames: 1 << 16,
};

fuzz_target!(|data: &[u8]| {
    // Default limits: only header/index validation, which never allocates.
    let _ = WorldReader::new(data).map(|r| (r.object_count(), r.frame_count()));
    let Ok(r) = WorldReader::with_limits(data, LIMITS) else {
        return;
    };
    let _ = (
        r.frame_dt(),
        r.e_max(),
        r.theta_max(),
        r.quality(),
        r.model(),
        r.version(),
    );
    let n = r.object_count().min(16);
    for i in 0..=n {
        let _ = r.object_frame_count(i);
        if let Ok(t) = r.decode_object(i) {
            assert_eq!(t.positions.len(), t.rotations.len());
            assert!(t.positions.iter().flatten().all(|v| v.is_finite()));
        }
        for t in [0.0, 0.004, 0.5, 1.0, -0.1, f64::NAN, 1e300] {
            let _ = r.sample(i, t);
        }
        for f in [0, 1, 2, 100, u32::MAX] {
            let _ = r.sample_frame(i, f);
        }
    }
    let _ = r.decode_all();
});
