//! The index a sampler sends with a world (issue 23): built from the segments it sent exactly as
//! a store builds it, taken by the store after checking its form, checked against the store's
//! own indexing on a sample, and never held twice.

use mwb_core::scene::SceneTemplate;
use mwb_proto::v1::{Job, Message, MotionSegment, WorldDone};
use mwb_sampler::{
    PayloadEncoding, RunOptions, attach_index, run_world, segment_message, world_done,
};
use mwb_store::index::{DEFAULT_PATH_TOLERANCE_M, JobScene, SentChecks, SentIndex, index_stored};
use mwb_store::{Assembler, Outcome, index_world};
use std::ops::ControlFlow;

/// One sampled world of a shipped scene as its sampler sends it: summary (with its index) and
/// segments, and the scene's facts as the store reads them from the job.
fn sampled(
    scene: &str,
    seed: u64,
    encoding: PayloadEncoding,
) -> (WorldDone, Vec<MotionSegment>, Job) {
    let path = format!("{}/../scenes/{scene}.toml", env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
    let template = SceneTemplate::parse(&text, &path).unwrap_or_else(|e| panic!("{e}"));
    let mut segments = Vec::new();
    let opts = RunOptions {
        encoding,
        ..Default::default()
    };
    let summary = run_world(&template, seed, opts, &mut |seg| {
        segments.push(segment_message("j", "n", seed, seed, seg));
        ControlFlow::Continue(())
    })
    .unwrap_or_else(|e| panic!("{e}"));
    let mut done = world_done("j", "n", seed, &summary);
    attach_index(&mut done, &segments, &template);
    let job = Job {
        id: "j".into(),
        target_worlds: 100,
        scene: Some(mwb_proto::v1::Scene {
            name: scene.into(),
            toml: text,
            ..Default::default()
        }),
        ..Default::default()
    };
    (done, segments, job)
}

/// The world through a store's assembly: the stored world and the index that came with it.
fn store(
    a: &mut Assembler,
    done: &WorldDone,
    segments: &[MotionSegment],
) -> (
    std::sync::Arc<mwb_store::StoredWorld>,
    Option<Box<mwb_proto::v1::WorldIndex>>,
) {
    for s in segments {
        assert_eq!(a.on_segment(s.clone(), 0), Outcome::Pending);
    }
    match a.on_done(done.clone(), 0) {
        Outcome::Stored {
            index, sent_index, ..
        } => (
            a.world(index).unwrap_or_else(|| panic!("world {index}")),
            sent_index,
        ),
        other => panic!("not stored: {other:?}"),
    }
}

#[test]
fn a_sent_index_is_the_one_the_store_would_build_and_is_not_held() {
    for (scene, seed, encoding) in [
        ("tumble", 1, PayloadEncoding::Spline),
        ("tumble", 2, PayloadEncoding::QuantisedFrames),
        ("pachinko", 3, PayloadEncoding::Spline),
    ] {
        let (done, segments, job) = sampled(scene, seed, encoding);
        let sent = done
            .index
            .clone()
            .unwrap_or_else(|| panic!("{scene}: no index sent"));
        assert_eq!(sent.objects.len(), done.impacts.len());
        let mut a = Assembler::new(1 << 30);
        a.submit_job(job.clone());
        let (stored, taken) = store(&mut a, &done, &segments);
        // Taken off the summary: held once (as the index), not twice.
        assert_eq!(taken.as_deref(), Some(&sent), "{scene}");
        let held = stored.done().unwrap_or_else(|e| panic!("{e}"));
        assert!(
            held.index.is_none(),
            "{scene}: the held summary kept the index"
        );
        let bare = WorldDone {
            index: None,
            ..done.clone()
        };
        assert_eq!(held, bare, "{scene}");
        assert_eq!(
            stored.bytes,
            segments.iter().map(|s| s.encoded_len() as u64).sum::<u64>()
                + bare.encoded_len() as u64,
            "{scene}: the world's bytes count the index"
        );

        let scene_facts = JobScene::of(&job);
        let own = index_world(
            &stored,
            stored.index,
            scene_facts.clone(),
            DEFAULT_PATH_TOLERANCE_M,
        )
        .unwrap_or_else(|e| panic!("{scene}: {e}"));
        // Every sent index checked: the same, byte for byte.
        let mut all = SentChecks::every(1);
        let r = index_stored(
            vec![(&*stored, taken.clone(), scene_facts.clone())],
            DEFAULT_PATH_TOLERANCE_M,
            2,
            &mut all,
        );
        let (got, what) = r.into_iter().next().unwrap_or_else(|| panic!("no result"));
        assert_eq!(what, SentIndex::Checked { same: true }, "{scene}");
        let got = got.unwrap_or_else(|e| panic!("{scene}: {e}"));
        assert!(got.same_objects(&own), "{scene}");
        // Taken unchecked: still the store's own, and the world-level fields from the summary.
        let mut none = SentChecks::every(0);
        let r = index_stored(
            vec![(&*stored, taken, scene_facts)],
            DEFAULT_PATH_TOLERANCE_M,
            2,
            &mut none,
        );
        let (got, what) = r.into_iter().next().unwrap_or_else(|| panic!("no result"));
        assert_eq!(what, SentIndex::Taken, "{scene}");
        let got = got.unwrap_or_else(|e| panic!("{scene}: {e}"));
        assert!(got.same_objects(&own), "{scene}");
        assert_eq!(
            (
                got.world,
                got.seed,
                got.frames,
                got.rested,
                &*got.job_id,
                got.bodies.len()
            ),
            (
                own.world,
                own.seed,
                own.frames,
                own.rested,
                &*own.job_id,
                own.bodies.len()
            ),
            "{scene}"
        );
        assert_eq!(got.frame_dt.to_bits(), own.frame_dt.to_bits());
    }
}

#[test]
fn a_sent_index_that_differs_or_is_malformed_gives_way_to_the_stores_own() {
    let (done, segments, job) = sampled("tumble", 5, PayloadEncoding::Spline);
    let mut a = Assembler::new(1 << 30);
    a.submit_job(job.clone());
    let (stored, sent) = store(&mut a, &done, &segments);
    let sent = sent.unwrap_or_else(|| panic!("no index sent"));
    let facts = JobScene::of(&job);
    let own = index_world(
        &stored,
        stored.index,
        facts.clone(),
        DEFAULT_PATH_TOLERANCE_M,
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let run = |sent: mwb_proto::v1::WorldIndex, every: u32| {
        let mut checks = SentChecks::every(every);
        index_stored(
            vec![(&*stored, Some(Box::new(sent)), facts.clone())],
            DEFAULT_PATH_TOLERANCE_M,
            1,
            &mut checks,
        )
        .into_iter()
        .next()
        .unwrap_or_else(|| panic!("no result"))
    };

    // A smaller radius (a path that could miss): checked, found different, the store's kept.
    let mut narrow = (*sent).clone();
    narrow.objects[0].radius *= 0.5;
    let (got, what) = run(narrow.clone(), 1);
    assert_eq!(what, SentIndex::Checked { same: false });
    assert!(got.unwrap_or_else(|e| panic!("{e}")).same_objects(&own));
    // Unchecked, it is taken as sent (why a store checks a sample).
    let (got, what) = run(narrow, 0);
    assert_eq!(what, SentIndex::Taken);
    assert!(!got.unwrap_or_else(|e| panic!("{e}")).same_objects(&own));

    // Malformed or from elsewhere: refused, naming what, and indexed here.
    let mut cases: Vec<(&str, mwb_proto::v1::WorldIndex)> = Vec::new();
    let mut c = (*sent).clone();
    c.layout = 2;
    cases.push(("index.layout", c));
    let mut c = (*sent).clone();
    c.path_tolerance_m = 0.02;
    cases.push(("index.path_tolerance_m", c));
    let mut c = (*sent).clone();
    c.objects.pop();
    cases.push(("index.objects", c));
    let mut c = (*sent).clone();
    c.objects[1].path.truncate(20);
    cases.push(("index.objects[1].path", c));
    let mut c = (*sent).clone();
    let last = c.objects[2].path.len() - 1;
    c.objects[2].path.truncate(last);
    cases.push(("index.objects[2].path", c));
    let mut c = (*sent).clone();
    c.objects[0].radius = f64::NAN;
    cases.push(("index.objects[0].path", c));
    let mut c = (*sent).clone();
    c.objects[0].angular_travel_rad = f32::INFINITY;
    cases.push(("index.objects[0].angular_travel_rad", c));
    let mut c = (*sent).clone();
    c.objects[3].final_rotation.pop();
    cases.push(("index.objects[3].final_rotation", c));
    let mut c = (*sent).clone();
    // The frame interval in the header (bytes 12..20) another world's.
    c.objects[0].path[12..20].copy_from_slice(&(1.0f64 / 30.0).to_le_bytes());
    cases.push(("index.objects[0].path", c));
    for (field, bad) in cases {
        let (got, what) = run(bad, 0);
        match &what {
            SentIndex::Refused(why) => assert!(why.contains(field), "{field}: {why}"),
            other => panic!("{field}: {other:?}"),
        }
        assert!(
            got.unwrap_or_else(|e| panic!("{e}")).same_objects(&own),
            "{field}"
        );
    }
}
