//! The store's browsing index on real sampled worlds (issue 4, "never miss"): for random boxes
//! and time windows near the motion, every object whose simulated (and decoded) full-rate path
//! enters a box is found by the OBB tree with its radius; the metrics agree with what the
//! sampler saw.

use mwb_core::browse::{Frustum, Polyline, RestThresholds, TimeWindow};
use mwb_core::rng::{Stream, WorldRng};
use mwb_core::scene::SceneTemplate;
use mwb_proto::v1::Message;
use mwb_sampler::{PayloadEncoding, RunOptions, run_world_observed, segment_message, world_done};
use mwb_store::index::{DEFAULT_PATH_TOLERANCE_M, PATH_GRID_M, PATH_RADIUS_STEP_M};
use mwb_store::{StoredWorld, index_world, index_worlds};
use std::ops::ControlFlow;

/// Samples one world and returns it as the store holds it, plus the simulated full-rate
/// positions per body.
fn sample(scene: &str, seed: u64, encoding: PayloadEncoding) -> (StoredWorld, Vec<Vec<[f64; 3]>>) {
    let path = format!("{}/../scenes/{scene}.toml", env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
    let template = SceneTemplate::parse(&text, &path).unwrap_or_else(|e| panic!("{e}"));
    let mut segments = Vec::new();
    let mut truth: Vec<Vec<[f64; 3]>> = Vec::new();
    let opts = RunOptions {
        encoding,
        ..Default::default()
    };
    let summary = run_world_observed(
        &template,
        seed,
        opts,
        &mut |seg| {
            segments.push(segment_message("j", "n", seed, seed, seg));
            ControlFlow::Continue(())
        },
        &mut |tracks| {
            truth.resize(tracks.len(), Vec::new());
            for (b, t) in tracks.iter().enumerate() {
                truth[b].extend_from_slice(&t.positions);
            }
        },
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let done = world_done("j", "n", seed, &summary);
    let bytes = segments.iter().map(|s| s.encoded_len() as u64).sum();
    (
        StoredWorld::new(0, "j".into(), &done, &segments, bytes, None),
        truth,
    )
}

#[test]
fn index_never_misses_a_simulated_path_and_keeps_the_samplers_metrics() {
    let mut rng = WorldRng::new(7, Stream::Scene);
    let mut hits = 0;
    let mut checks = 0;
    let rest = RestThresholds {
        linear: 0.02,
        angular: 0.05,
    };
    for (scene, seed, encoding) in [
        ("tumble", 1, PayloadEncoding::Spline),
        ("tumble", 2, PayloadEncoding::QuantisedFrames),
        ("pachinko", 3, PayloadEncoding::Spline),
    ] {
        let (stored, truth) = sample(scene, seed, encoding);
        let w = index_world(&stored, 0, rest, DEFAULT_PATH_TOLERANCE_M)
            .unwrap_or_else(|e| panic!("{scene}: {e}"));
        let done = stored.done().unwrap_or_else(|e| panic!("{e}"));
        let dt = done.frame_dt;
        assert_eq!(w.objects.len(), truth.len());
        for (b, obj) in w.objects.iter().enumerate() {
            // The radius is the codec's bound plus at most the simplification tolerance and the
            // grid rounding of the vertices (under a grid step: these paths span < 8 m).
            assert!(
                obj.radius <= 0.002 + DEFAULT_PATH_TOLERANCE_M + PATH_GRID_M + PATH_RADIUS_STEP_M,
                "{scene} {b}: {}",
                obj.radius
            );
            let m = &w.metrics[b].unpack();
            assert_eq!(m.impacts, done.impacts[b]);
            // The sampler's own rest time, as the store keeps it (f32, `PackedMetrics`).
            assert_eq!(m.time_to_rest_s, f64::from(done.rest_time_s[b] as f32));
            assert!(m.time_to_rest_s <= f64::from(done.frame_count) * dt + 1e-6);
            assert!(m.angular_travel_rad >= 0.0 && m.orientation_error_rad <= std::f64::consts::PI);
            let full =
                Polyline::uniform(0.0, dt, truth[b].clone()).unwrap_or_else(|e| panic!("{e}"));
            let end = f64::from(done.frame_count) * dt;
            for _ in 0..150 {
                // A box of 2–40 cm around a point near a random frame of this object's path.
                let k = (rng.next_f64() * truth[b].len() as f64) as usize % truth[b].len();
                let c = truth[b][k];
                let half = rng.uniform(0.01, 0.25);
                let off = [
                    rng.uniform(-0.2, 0.2),
                    rng.uniform(-0.2, 0.2),
                    rng.uniform(-0.2, 0.2),
                ];
                let min = [
                    c[0] + off[0] - half,
                    c[1] + off[1] - half,
                    c[2] + off[2] - half,
                ];
                let max = [
                    c[0] + off[0] + half,
                    c[1] + off[1] + half,
                    c[2] + off[2] + half,
                ];
                let frustum = Frustum::aabb(min, max).unwrap_or_else(|e| panic!("{e}"));
                let window = if rng.next_f64() < 0.5 {
                    let a = rng.uniform(0.0, end);
                    TimeWindow::new(a, a + rng.uniform(0.0, 1.0)).ok()
                } else {
                    None
                };
                checks += 1;
                if full.first_entry(&frustum, window).is_some() {
                    hits += 1;
                    assert!(
                        obj.intersects(&frustum, window),
                        "{scene} seed {seed} body {b}: missed {min:?}..{max:?} {window:?}"
                    );
                }
            }
        }
    }
    // The random boxes hit often enough for the property to mean something.
    assert!(hits * 5 > checks, "{hits} hits of {checks}");
}

/// A store indexes the worlds that reach it together on every core: the same worlds, the same
/// paths, radii and metrics as one at a time, in the order given, whatever the thread count;
/// a world that cannot be indexed fails alone, in its place.
#[test]
fn indexing_on_many_threads_gives_what_one_at_a_time_gives() {
    let rest = RestThresholds {
        linear: 0.02,
        angular: 0.05,
    };
    let mut worlds: Vec<StoredWorld> = (0..5)
        .map(|seed| sample("tumble", 10 + seed, PayloadEncoding::Spline).0)
        .collect();
    // No segments: `IndexError::Empty`.
    let done = worlds[0].done().unwrap_or_else(|e| panic!("{e}"));
    worlds.insert(2, StoredWorld::new(0, "j".into(), &done, &[], 0, None));
    let jobs: Vec<_> = worlds
        .iter()
        .enumerate()
        .map(|(i, w)| (w, 100 + i as u32, mwb_store::index::JobScene::from(rest)))
        .collect();
    let one_by_one: Vec<_> = worlds
        .iter()
        .enumerate()
        .map(|(i, w)| index_world(w, 100 + i as u32, rest, DEFAULT_PATH_TOLERANCE_M))
        .collect();
    assert!(one_by_one[2].is_err());
    assert_eq!(one_by_one.iter().filter(|r| r.is_ok()).count(), 5);
    for threads in [1, 2, 3, 8] {
        let together = index_worlds(&jobs, DEFAULT_PATH_TOLERANCE_M, threads);
        assert_eq!(together.len(), one_by_one.len(), "{threads} threads");
        for (i, (a, b)) in together.iter().zip(&one_by_one).enumerate() {
            match (a, b) {
                (Ok(a), Ok(b)) => {
                    assert_eq!(a.world, 100 + i as u32);
                    assert_eq!(
                        a.paths_message(),
                        b.paths_message(),
                        "{threads} threads, {i}"
                    );
                    assert_eq!(a.metrics, b.metrics, "{threads} threads, {i}");
                }
                (Err(a), Err(b)) => assert_eq!(a, b),
                _ => panic!("{threads} threads, world {i}: {a:?} against {b:?}"),
            }
        }
    }
}
