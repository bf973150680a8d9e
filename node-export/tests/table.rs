//! CSV and JSON rows: written, read back, equal to the decoded motion bit for bit.

mod common;

use common::{shapes, tumble};
use mwb_export::table::{Row, read_csv, read_json, rows, write_csv, write_json};
use proptest::prelude::*;

#[test]
fn csv_and_json_round_trip_two_worlds_exactly() {
    let a = tumble(0xfeed);
    let b = shapes(3);
    let worlds = [a.export(Some(12)), b.export(None)];
    let want = rows(&worlds).unwrap_or_else(|e| panic!("{e}"));
    let frames = a.motion.frame_count() * a.scene.bodies.len()
        + b.motion.frame_count() * b.scene.bodies.len();
    assert_eq!(want.len(), frames);

    let csv = write_csv(&worlds).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(read_csv(&csv).unwrap_or_else(|e| panic!("{e}")), want);
    let json = write_json(&worlds).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(read_json(&json).unwrap_or_else(|e| panic!("{e}")), want);

    // Row k · bodies + i is body i of frame k, as decoded.
    let n = a.scene.bodies.len();
    for (j, r) in want.iter().take(a.motion.frame_count() * n).enumerate() {
        let (k, i) = (j / n, j % n);
        assert_eq!(
            (r.world, r.seed, r.frame, r.body),
            (Some(12), a.seed, k as u32, i as u32)
        );
        assert_eq!(r.name, a.scene.bodies[i].name);
        assert_eq!(r.time, k as f64 * a.motion.frame_dt);
        assert_eq!(r.position, a.motion.tracks[i].positions[k]);
        assert_eq!(r.rotation, a.motion.tracks[i].rotations[k]);
    }
    let text = String::from_utf8_lossy(&csv);
    assert!(text.starts_with(mwb_export::table::CSV_HEADER));
    assert!(text.lines().nth(1).is_some_and(|l| l.starts_with("12,")));
}

proptest! {
    #[test]
    fn any_row_survives_csv(
        name in "[ -~]{0,12}",
        world in proptest::option::of(any::<u32>()),
        seed in any::<u64>(),
        xs in proptest::array::uniform7(-1.0e6f64..1.0e6),
    ) {
        let mut scene = mwb_core::scene::SceneTemplate::parse(
            mwb_core::scene::builtin::TUMBLE, "tumble.toml")
            .unwrap_or_else(|e| panic!("{e}"))
            .instantiate(seed);
        scene.bodies.truncate(1);
        scene.bodies[0].name = name.clone();
        let mut motion = mwb_export::Motion::at_rest(&scene, 1, 1.0 / 120.0);
        motion.tracks[0].positions[0] = [xs[0], xs[1], xs[2]];
        motion.tracks[0].rotations[0] = [xs[3], xs[4], xs[5], xs[6]];
        let w = mwb_export::ExportWorld { index: world, seed, scene: &scene, motion: &motion };
        let back: Vec<Row> = read_csv(&write_csv(&[w]).unwrap_or_else(|e| panic!("{e}")))
            .unwrap_or_else(|e| panic!("{e}"));
        prop_assert_eq!(back, rows(&[w]).unwrap_or_else(|e| panic!("{e}")));
    }
}
