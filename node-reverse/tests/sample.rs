//! Backward worlds as stored worlds ([`mwb_reverse::sample`]): byte-for-byte determinism,
//! playback runs forward into the given final state, segments tile the frames, and the summary
//! describes the world as played forward.

use mwb_codec::{Quality, WorldReader};
use mwb_core::scene::SceneTemplate;
use mwb_reverse::sample::{ReverseScene, Segment, sample_world};
use mwb_reverse::scene::builtin;
use std::ops::ControlFlow;

/// The word scene, going back `seconds` instead of 3 s (tests stay fast).
fn word(seconds: f64) -> String {
    let text = builtin::WORD.replace("end_time = 3.0", &format!("end_time = {seconds:?}"));
    assert_ne!(
        text,
        builtin::WORD,
        "the word scene's end_time line changed"
    );
    text
}

fn prepare(text: &str) -> ReverseScene {
    ReverseScene::prepare(text, "test scene").unwrap_or_else(|e| panic!("{e}"))
}

fn sample(scene: &ReverseScene, seed: u64) -> (Vec<Segment>, mwb_reverse::ReverseWorldSummary) {
    let mut segments = Vec::new();
    let summary = sample_world(scene, seed, Quality::Standard, &mut |s| {
        segments.push(s);
        ControlFlow::Continue(())
    })
    .unwrap_or_else(|e| panic!("seed {seed}: {e}"));
    (segments, summary)
}

fn angle(a: [f64; 4], b: [f64; 4]) -> f64 {
    let d: f64 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
    2.0 * d.abs().min(1.0).acos()
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    a.iter()
        .zip(&b)
        .map(|(x, y)| (x - y).powi(2))
        .sum::<f64>()
        .sqrt()
}

#[test]
fn same_scene_and_seed_give_the_same_bytes() {
    let text = word(0.75);
    // Two independent preparations: the learned chain is part of what must repeat.
    let (a, sa) = sample(&prepare(&text), 42);
    let (b, sb) = sample(&prepare(&text), 42);
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.payload, y.payload, "segment {} payload differs", x.seq);
        assert_eq!(x, y, "segment {} differs", x.seq);
    }
    // Debug text: the report holds NaN (departure not measured), which is never == itself.
    assert_eq!(format!("{sa:?}"), format!("{sb:?}"));
    let (c, _) = sample(&prepare(&text), 43);
    assert_ne!(
        a.iter().map(|s| &s.payload).collect::<Vec<_>>(),
        c.iter().map(|s| &s.payload).collect::<Vec<_>>(),
        "another seed gave the same world"
    );
}

#[test]
fn playback_runs_forward_into_the_given_final_state() {
    let text = word(1.5);
    let scene = prepare(&text);
    let template = SceneTemplate::parse(&text, "word").unwrap_or_else(|e| panic!("{e}"));
    let (e_max, theta_max) = Quality::Standard.bounds();
    let mut moved = 0.0f64;
    for seed in [1u64, 2, 3] {
        let (segments, summary) = sample(&scene, seed);
        let final_state = template.instantiate(seed);
        let n = final_state.bodies.len();
        // 1.5 s at 1/120 s: the given state plus 180 earlier frames, in 1 s segments.
        assert_eq!(summary.frame_count, 181);
        assert_eq!(summary.segment_count, 2);
        assert_eq!(segments.len(), 2);
        let mut next = 0;
        for (i, s) in segments.iter().enumerate() {
            assert_eq!(s.seq as usize, i);
            assert_eq!(s.first_frame, next);
            assert_eq!(s.body_count as usize, n);
            next += s.frame_count;
        }
        assert_eq!(next, summary.frame_count);
        assert_eq!(segments[0].frame_count, 120);

        let decode = |s: &Segment| {
            WorldReader::new(&s.payload)
                .and_then(|r| r.decode_all())
                .unwrap_or_else(|e| panic!("seed {seed} segment {}: {e}", s.seq))
        };
        let last = decode(&segments[1]);
        let first = decode(&segments[0]);
        for (b, body) in final_state.bodies.iter().enumerate() {
            let track = &last[b];
            let (Some(p), Some(q)) = (track.positions.last(), track.rotations.last()) else {
                panic!("body {b}: empty track");
            };
            // The last decoded frame is the user's final state, within the codec bound.
            assert!(
                dist(*p, body.position) <= e_max * (1.0 + 1e-9),
                "seed {seed} body {b}: ends at {p:?}, scene says {:?}",
                body.position
            );
            assert!(
                angle(*q, body.rotation) <= theta_max * (1.0 + 1e-6),
                "seed {seed} body {b}: final rotation off by {} rad",
                angle(*q, body.rotation)
            );
            moved = moved.max(dist(first[b].positions[0], body.position));
        }
        // Played forward the boxes settle into the word: at rest at the end.
        assert!(summary.rested, "seed {seed}: {summary:?}");
        assert_eq!(summary.body_rested, vec![true; n]);
        assert_eq!(summary.impacts.len(), n);
        assert_eq!(summary.rest_time_s.len(), n);
        for &t in &summary.rest_time_s {
            assert!((0.0..=1.5).contains(&t), "rest time {t}");
        }
    }
    // The worlds are not the final state held still: something came from elsewhere.
    assert!(moved > 0.01, "no body moved in any world ({moved} m)");
}

#[test]
fn hull_bodies_are_stored_at_their_scene_origin() {
    // A hull whose points are not centred on its origin: the stepper works at the centre of
    // mass, the stored pose must be the scene's body origin (as the forward sampler stores it).
    let text = r#"
name = "wedge"

[settings]
end_time = 0.25

[[material]]
name = "wood"
friction = 0.5
restitution = 0.3

[[static]]
name = "ground"
shape = "plane"
normal = [0, 1, 0]
material = "wood"

[[body]]
name = "wedge"
shape = "convex"
points = [[0, 0, 0], [1, 0, 0], [0, 0.5, 0], [0, 0, 1], [1, 0, 1], [0, 0.5, 1]]
material = "wood"
position = [2, 0, 3]
rotation_deg = [0, 30, 0]
"#;
    let scene = prepare(text);
    let (segments, _) = sample(&scene, 5);
    let Some(last) = segments.last() else {
        panic!("no segments")
    };
    let tracks = WorldReader::new(&last.payload)
        .and_then(|r| r.decode_all())
        .unwrap_or_else(|e| panic!("{e}"));
    let Some(p) = tracks[0].positions.last() else {
        panic!("empty track")
    };
    assert!(
        dist(*p, [2.0, 0.0, 3.0]) <= Quality::Standard.e_max() * 1.0001,
        "{p:?}"
    );
}

#[test]
fn scenes_the_reverse_stepper_cannot_run_are_refused() {
    let bad_time = word(0.5).replace("end_time = 0.5", "end_time = 0.0");
    assert!(ReverseScene::prepare(&bad_time, "t").is_err());
    assert!(ReverseScene::prepare("not = [toml", "t").is_err());
}

#[test]
fn a_stopped_world_emits_nothing_more() {
    let scene = prepare(&word(1.5));
    let mut seen = 0;
    let r = sample_world(&scene, 9, Quality::Draft, &mut |_| {
        seen += 1;
        ControlFlow::Break(())
    });
    assert!(matches!(r, Err(mwb_reverse::SampleError::Stopped)));
    assert_eq!(seen, 1);
}

/// Every frame of a world, decoded: per body, positions in playback order.
fn positions(segments: &[Segment]) -> Vec<Vec<[f64; 3]>> {
    let mut out: Vec<Vec<[f64; 3]>> = Vec::new();
    for s in segments {
        let tracks = WorldReader::new(&s.payload)
            .and_then(|r| r.decode_all())
            .unwrap_or_else(|e| panic!("segment {}: {e}", s.seq));
        out.resize(tracks.len(), Vec::new());
        for (all, t) in out.iter_mut().zip(tracks) {
            all.extend(t.positions);
        }
    }
    out
}

#[test]
fn the_wire_summary_carries_the_plausibility_numbers() {
    let scene = prepare(&word(0.5));
    let (_, summary) = sample(&scene, 11);
    let done = summary.world_done("job", "node", 3);
    assert_eq!(done.frame_count, summary.frame_count);
    assert_eq!(done.sim_steps, 60);
    assert_eq!(done.body_rested, summary.body_rested);
    let (Some(energy), Some(angular)) = (done.energy_growth, done.angular_speed_growth) else {
        panic!("plausibility numbers missing: {done:?}")
    };
    assert!(energy.is_finite() && energy >= 0.0, "{energy}");
    assert!(angular.is_finite() && angular >= 0.0, "{angular}");
    assert_eq!(energy, summary.report.energy_growth);
    assert_eq!(angular, summary.report.angular_speed_growth);
    // The plausibility verdict (mwb_reverse::plausible) rides beside them.
    let p = summary.report.plausibility;
    assert_eq!(done.plausible, Some(p.plausible));
    assert_eq!(done.plausibility_excess, Some(p.excess_m));
    assert_eq!(p.plausible, p.excess_m <= 0.0);
    assert!(p.excess_m.is_finite(), "{p:?}");
    assert_eq!(p.worst_body.map(|b| b < 16), Some(true), "{p:?}");
    // They survive the wire, and a forward world (no numbers) stays distinguishable from 0.
    use mwb_proto::v1::{Message, WorldDone};
    let back = WorldDone::decode(done.encode_to_vec().as_slice()).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(back.energy_growth, Some(energy));
    assert_eq!(back.angular_speed_growth, Some(angular));
    assert_eq!(back.plausible, Some(p.plausible));
    assert_eq!(back.plausibility_excess, Some(p.excess_m));
    let forward = WorldDone {
        energy_growth: None,
        angular_speed_growth: Some(0.0),
        plausible: None,
        plausibility_excess: None,
        ..Default::default()
    };
    let forward =
        WorldDone::decode(forward.encode_to_vec().as_slice()).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(forward.energy_growth, None);
    assert_eq!(forward.angular_speed_growth, Some(0.0));
    assert_eq!(
        (forward.plausible, forward.plausibility_excess),
        (None, None)
    );
}

/// The shipped mixed crash scene, `back` s backward into the frame and `forward` s out of it.
fn crash_mixed(back: f64, forward: f64) -> String {
    let text = include_str!("../../scenes/reverse/crash_mixed.toml");
    let short = text
        .replace("end_time = 2.0", &format!("end_time = {back:?}"))
        .replace("forward_time = 2.0", &format!("forward_time = {forward:?}"));
    assert_eq!(
        short.matches(" = 2.0").count() + 2,
        text.matches(" = 2.0").count()
    );
    short
}

#[test]
fn a_mixed_world_plays_forward_through_the_given_frame() {
    let text = crash_mixed(0.5, 0.75);
    let scene = prepare(&text);
    assert_eq!(
        scene.mode(),
        mwb_reverse::RunMode::Mixed { forward_time: 0.75 }
    );
    assert_eq!(scene.settings().hints.len(), 1, "the shipped hint on A");
    let template = mwb_reverse::parse_reverse_scene(&text, "crash_mixed")
        .unwrap_or_else(|e| panic!("{e}"))
        .0;
    let (e_max, _) = Quality::Standard.bounds();
    for seed in [1u64, 2] {
        let (segments, summary) = sample(&scene, seed);
        // 0.5 s back and 0.75 s forward at 1/120 s: 60 + 1 + 90 frames, the given one at 60.
        assert_eq!(summary.frame_count, 151);
        assert_eq!(summary.join, 60);
        assert_eq!(summary.steps, 150);
        assert_eq!(segments.iter().map(|s| s.frame_count).sum::<u32>(), 151);
        assert_eq!(summary.segment_count as usize, segments.len());
        let done = summary.world_done("j", "n", 0);
        assert_eq!(done.frame_count, 151);
        assert!(done.energy_growth.is_some_and(f64::is_finite), "{done:?}");
        assert!(done.angular_speed_growth.is_some_and(f64::is_finite));
        let paths = positions(&segments);
        let given = template.instantiate(seed);
        for (b, body) in given.bodies.iter().enumerate() {
            let path = &paths[b];
            assert_eq!(path.len(), 151);
            // Frame 60 is the user's intermediate state ...
            let d = dist(path[60], body.position);
            assert!(d <= e_max * (1.0 + 1e-9), "seed {seed} body {b}: {d} m off");
            // ... and the world goes on: played forward, the boxes rise and then fall, so
            // 0.75 s later they are lower than at the frame (v_y ≤ 1.4 m/s: apex within 0.15 s).
            assert!(
                path[150][1] < body.position[1] - 0.5,
                "seed {seed} body {b}"
            );
            // Played forward it is one motion: no jump at the join.
            assert!(dist(path[59], path[60]) < 0.05 && dist(path[60], path[61]) < 0.05);
        }
    }
}

#[test]
fn a_slide_hint_brings_the_body_in_along_its_direction() {
    // M0 is the left-most box of the word: with a slide hint along +x it arrives from −x.
    let hinted = format!(
        "{}\n[reverse]\n[[reverse.hint]]\nbody = \"M0\"\nmotion = \"slide\"\ndirection = [1, 0, 0]\n",
        word(1.0)
    );
    let plain = prepare(&word(1.0));
    let scene = prepare(&hinted);
    assert_eq!(scene.mode(), mwb_reverse::RunMode::Backward);
    for seed in [1u64, 2, 3] {
        let (segments, summary) = sample(&scene, seed);
        assert_eq!(summary.frame_count, 121);
        let path = &positions(&segments)[0];
        let (Some(first), Some(last)) = (path.first(), path.last()) else {
            panic!("empty path")
        };
        let along = first[0] - last[0];
        let across = (first[2] - last[2]).abs();
        assert!(along < -0.05, "seed {seed}: M0 came from {along} m along x");
        assert!(
            across < 0.25 * along.abs(),
            "seed {seed}: {across} m across"
        );
        let (unhinted, _) = sample(&plain, seed);
        assert_ne!(
            positions(&unhinted)[0],
            *path,
            "seed {seed}: the hint changed nothing"
        );
    }
}

#[test]
fn the_scene_energy_budget_reaches_the_run() {
    let plain = prepare(&word(1.0));
    assert_eq!(
        plain.settings().heuristics.energy_budget,
        Some(mwb_reverse::run::DEFAULT_ENERGY_BUDGET)
    );
    let loose = prepare(&format!("{}\n[reverse]\nenergy_budget = 1\n", word(1.0)));
    assert_eq!(loose.settings().heuristics.energy_budget, Some(1.0));
    // A looser budget takes fewer steps again, so some seed's world differs.
    let differs = (1u64..=4)
        .any(|seed| positions(&sample(&plain, seed).0) != positions(&sample(&loose, seed).0));
    assert!(differs, "energy_budget = 1 changed no world of four");
}

#[test]
fn a_bad_reverse_table_is_refused_before_any_world() {
    let text = format!("{}\n[reverse]\nmode = \"both\"\n", word(0.5));
    match ReverseScene::prepare(&text, "word.toml") {
        Ok(_) => panic!("accepted mode = both"),
        Err(e) => {
            let e = e.to_string();
            assert!(e.contains("field `mode`"), "{e}");
        }
    }
}

/// The shipped word scene (`scenes/reverse/word.toml`, 3 s back from the boxes spelling "MWB"),
/// seed 42, standard quality, as this source tree simulates and encodes it: the
/// [`world_digest`] and the encoded size. See [`the_pinned_world_is_unchanged`] for what a
/// mismatch means. Re-minted for issue 20: the energy budget credits a rising body with the apex
/// the stepper's flight reaches (shadow term included), a body rising in the last frame with
/// the apex it flies on to, and round bodies get no sampled slide. Re-minted for issue 23:
/// Standard's encoder searches adaptively (`mwb_codec::Search`), the same backward world
/// encoded in 11 bytes fewer (11 609 → 11 598).
const WORD_42: (u32, u64) = (0xaba2_c624, 11598);

/// A CRC-32 over every segment's numbering and payload and over the summary's fields (of the
/// run report, the plausibility numbers the wire carries).
fn world_digest(segments: &[Segment], summary: &mwb_reverse::ReverseWorldSummary) -> u32 {
    let mut h = crc32fast::Hasher::new();
    for s in segments {
        for x in [s.seq, s.first_frame, s.frame_count, s.body_count] {
            h.update(&x.to_le_bytes());
        }
        h.update(&s.payload);
    }
    // Every field, by destructuring: a new one does not compile until it is digested too.
    let mwb_reverse::ReverseWorldSummary {
        seed,
        frame_count,
        join,
        segment_count,
        frame_dt,
        rested,
        impacts,
        rest_time_s,
        body_rested,
        lifts,
        steps,
        payload_bytes,
        report,
    } = summary;
    h.update(&seed.to_le_bytes());
    for x in [frame_count, join, segment_count, lifts] {
        h.update(&x.to_le_bytes());
    }
    for x in [
        frame_dt,
        &report.energy_growth,
        &report.angular_speed_growth,
        &report.plausibility.excess_m,
    ] {
        h.update(&x.to_bits().to_le_bytes());
    }
    h.update(&[u8::from(report.plausibility.plausible)]);
    h.update(&[u8::from(*rested)]);
    impacts.iter().for_each(|x| h.update(&x.to_le_bytes()));
    rest_time_s
        .iter()
        .for_each(|x| h.update(&x.to_bits().to_le_bytes()));
    body_rested.iter().for_each(|x| h.update(&[u8::from(*x)]));
    h.update(&steps.to_le_bytes());
    h.update(&payload_bytes.to_le_bytes());
    h.finalize()
}

/// Golden values, where the determinism test above only compares two runs of one binary: a change
/// of the backward worlds between builds is caught here. The stepper's nalgebra maths goes through
/// libm (parry3d's `enhanced-determinism`, on in every build since node-reverse/Cargo.toml asks for
/// it), so the value does not depend on which crates a build selects; what still comes from the
/// platform's libm are the few `f64` sin/cos/ln/powf calls of our own code (scene distributions,
/// the run's random slide directions): the value holds on x86-64 Linux (glibc) and may differ
/// under a libm that rounds one of them differently.
#[test]
fn the_pinned_world_is_unchanged() {
    let (segments, summary) = sample(&prepare(builtin::WORD), 42);
    let (crc, bytes) = (world_digest(&segments, &summary), summary.payload_bytes);
    assert!(
        (crc, bytes) == WORD_42,
        "the pinned word world (seed 42) is now ({crc:#010x}, {bytes}), pinned ({:#010x}, {}).\n\
         A dependency bump (nalgebra, parry) or a change to the reverse stepper, its heuristics, \
         the scene format or the codec altered the backward worlds: a world stored or recorded \
         by an earlier binary is not what this one regenerates from its (scene, seed). If that \
         is deliberate, re-mint: set WORD_42 in node-reverse/tests/sample.rs to the value \
         printed here (`cargo test -p mwb-reverse --test sample pinned`).",
        WORD_42.0,
        WORD_42.1
    );
}
