//! The reverse benchmark, opt-in (release):
//! `CARGO_TARGET_DIR=/tmp/tgt-lcp cargo test --release -p mwb-reverse --test bench -- --ignored --nocapture`

use mwb_reverse::{BenchOptions, bench};

#[test]
#[ignore = "benchmark: minutes in release; run with --ignored --nocapture"]
fn reverse_bench() {
    let b = match bench(&BenchOptions::default()) {
        Ok(b) => b,
        Err(e) => panic!("{e}"),
    };
    eprintln!("{b:#?}");
    assert!(b.forward_step_us > 0.0 && b.backward_step_us > 0.0);
}

/// The per-scene plausibility part alone, for tuning (release):
/// `cargo test --release -p mwb-reverse --test bench plausibility -- --ignored --nocapture`;
/// `MWB_BENCH_WORLDS` (default 20) worlds a scene, `MWB_BENCH_SCENES` (comma-separated names)
/// to choose scenes, `MWB_BENCH_LOREM=1` to add the lorem world.
#[test]
#[ignore = "benchmark: minutes in release; run with --ignored --nocapture"]
fn plausibility_by_scene() {
    let worlds = std::env::var("MWB_BENCH_WORLDS")
        .ok()
        .and_then(|w| w.parse().ok())
        .unwrap_or(20);
    let only = std::env::var("MWB_BENCH_SCENES").ok();
    let opts = BenchOptions {
        timing_steps: 1,
        worlds: 0,
        balls_scene: None,
        scenes: mwb_reverse::bench::shipped_scenes()
            .into_iter()
            .filter(|(n, _)| only.as_ref().is_none_or(|o| o.split(',').any(|x| x == n)))
            .collect(),
        scene_worlds: worlds,
        big_scene_worlds: worlds.min(2),
        lorem_scene: std::env::var("MWB_BENCH_LOREM")
            .is_ok_and(|v| v == "1")
            .then(|| mwb_reverse::scene::builtin::LOREM.to_owned()),
        ..Default::default()
    };
    let b = match bench(&opts) {
        Ok(b) => b,
        Err(e) => panic!("{e}"),
    };
    for (name, s) in &b.scenes {
        eprintln!("{name:12} {s:?}");
    }
    eprintln!("{:?}", b.lorem);
    assert!(
        b.scenes
            .values()
            .all(|s| s.worlds == worlds || s.worlds == worlds.min(2))
    );
}

/// Tuning aid: the worst body of the worst of `MWB_TRACE_WORLDS` worlds of `MWB_TRACE_SCENE`,
/// its energy height traced from the frames (played forward).
#[test]
#[ignore = "tuning aid; run with --ignored --nocapture"]
fn trace_worst_body() {
    use mwb_reverse::sample::{ReverseScene, run_world};
    let name = std::env::var("MWB_TRACE_SCENE").unwrap_or_else(|_| "word".into());
    let worlds: u64 = std::env::var("MWB_TRACE_WORLDS")
        .ok()
        .and_then(|w| w.parse().ok())
        .unwrap_or(5);
    let Some((_, text)) = mwb_reverse::bench::shipped_scenes()
        .into_iter()
        .chain([(
            "lorem".to_owned(),
            mwb_reverse::scene::builtin::LOREM.to_owned(),
        )])
        .find(|(n, _)| *n == name)
    else {
        panic!("no scene {name}")
    };
    let scene = ReverseScene::prepare(&text, &name).unwrap_or_else(|e| panic!("{e}"));
    let dt = scene.settings().dt;
    for seed in 1..=worlds {
        let run = run_world(&scene, seed).unwrap_or_else(|e| panic!("{e}"));
        let p = run.report.plausibility;
        assert_eq!(p.plausible, p.excess_m <= 0.0, "{p:?}");
        eprintln!(
            "seed {seed}: plausible {} excess {:.4} worst {:?} {:?} bad {}",
            p.plausible, p.excess_m, p.worst_body, p.worst_clause, p.implausible_bodies
        );
        // Lowest centre of any body in any frame, and of the worst body.
        let lowest = run
            .frames
            .iter()
            .flat_map(|f| f.poses.iter().map(|q| q.position.y))
            .fold(f64::INFINITY, f64::min);
        eprintln!(
            "   lowest centre {lowest:.4} resteps {}",
            run.report.budget_resteps
        );
        let Some(b) = p.worst_body else { continue };
        eprintln!("   peaks {:?}", run.report.plausibility_bodies[b]);
        eprintln!(
            "   unsolved {} disabled {} resteps {} approaching {} held {}",
            run.report.unsolved_islands,
            run.report.disabled_bodies,
            run.report.budget_resteps,
            run.report.approaching_contacts,
            run.report.held_contacts
        );
        let stride = ((0.1 / dt).round() as usize).max(1);
        for (k, pair) in run.frames.windows(2).enumerate().step_by(stride) {
            let (a, c) = (&pair[0].poses[b], &pair[1].poses[b]);
            let v = (c.position - a.position) / dt;
            let w = (c.orientation * a.orientation.inverse()).scaled_axis() / dt;
            eprintln!(
                "   t {:.2} y {:.3} v [{:.2} {:.2} {:.2}] |w| {:.1} ke_h {:.4}",
                k as f64 * dt,
                c.position.y,
                v.x,
                v.y,
                v.z,
                w.norm(),
                v.norm_squared() / (2.0 * 9.81)
            );
        }
    }
}
