//! Compression measurements on the reference scenario of the issue: a body thrown, bouncing and
//! coming to rest, at e_max = 1 mm, θ_max = 1 mrad, 120 Hz. Sizes are deterministic, so the ratio
//! is asserted; timings are only printed. Run with
//! `cargo test -p mwb-codec --release --test measure -- --nocapture`.

mod common;

use std::time::Instant;

use common::{G, Rng, ballistic};
use mwb_codec::{
    EncodeParams, MotionModel, Quality, Track, WorldReader, encode_world,
    quantised_frames_baseline, raw_f32_size,
};

const DT: f64 = 1.0 / 120.0;

/// 5 s per object: flight and bounces, then rest with 1 µm solver jitter.
fn scenario(objects: usize) -> Vec<Track> {
    (0..objects)
        .map(|i| ballistic(&mut Rng::new(1000 + i as u64), 600, DT, 1e-6))
        .collect()
}

fn report(name: &str, tracks: &[Track], model: MotionModel) -> f64 {
    let p = EncodeParams::from_quality(Quality::Standard, DT, model);
    let t0 = Instant::now();
    let world = encode_world(tracks, &p).unwrap();
    let encode_s = t0.elapsed().as_secs_f64();
    let reader = WorldReader::new(&world.bytes).unwrap();
    let t1 = Instant::now();
    let decoded = reader.decode_all().unwrap();
    let decode_s = t1.elapsed().as_secs_f64();
    assert_eq!(decoded.len(), tracks.len());
    let s = &world.stats;
    let frames = s.object_frames as f64;
    let baseline = quantised_frames_baseline(tracks, p.e_max, p.theta_max).unwrap();
    println!(
        "{name:<34} {:>3} obj: {:>7} B, {:>6.1} B/(object·s), ratio {:>6.1}× vs raw f32 ({} B); \
         segments pos {} rot {} key {}; max err {:.3e} m {:.3e} rad; \
         quantised-frames baseline {} B ({:.1}×, before zstd); \
         encode {:.2} Mframes/s (incl. self-check), decode {:.2} Mframes/s; lowres dev ≤ {:.3} m",
        tracks.len(),
        s.bytes,
        s.bytes_per_object_second(DT),
        s.ratio(),
        s.raw_f32_bytes,
        s.position_segments,
        s.rotation_segments,
        s.key_segments,
        s.max_position_error,
        s.max_rotation_error,
        baseline.len(),
        raw_f32_size(tracks) as f64 / baseline.len() as f64,
        frames / encode_s / 1e6,
        frames / decode_s / 1e6,
        world
            .lowres
            .iter()
            .map(|l| l.max_deviation)
            .fold(0.0, f64::max),
    );
    s.ratio()
}

#[test]
fn ballistic_bounce_rest_compresses_at_least_30x() {
    let one = scenario(1);
    let many = scenario(100);
    let gravity = MotionModel::FreeFlightGravity { g: G };
    let r1 = report("ballistic+bounce+rest, gravity", &one, gravity);
    let r100 = report("ballistic+bounce+rest, gravity", &many, gravity);
    let g100 = report(
        "ballistic+bounce+rest, general",
        &many,
        MotionModel::General,
    );
    assert!(r1 >= 30.0, "single object: {r1:.1}×");
    assert!(r100 >= 30.0, "100 objects: {r100:.1}×");
    assert!(g100 >= 30.0, "100 objects, general model: {g100:.1}×");
}
