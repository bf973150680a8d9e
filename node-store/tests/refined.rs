//! A refined world (§4.5) sent as a difference from its parent — its segments from the one
//! holding the branch frame, each with only the bodies re-simulated by then — is composed by the
//! store from the parent it holds: indexed, served with its parent chain, decoded into the same
//! world a whole recording of it gives; only its own bytes count against the memory cap; a
//! refined world whose parent the store does not hold is refused.

use mwb_proto::v1::{JobKind, MotionSegment, WorldDone};
use mwb_store::index::DEFAULT_PATH_TOLERANCE_M;
use mwb_store::{Assembler, Outcome, Rejection, index_world};

mod common;

use common::{child, job, refine_job, root};

fn feed(a: &mut Assembler, segments: Vec<MotionSegment>, done: WorldDone) -> Outcome {
    for s in segments {
        assert_eq!(a.on_segment(s, 1), Outcome::Pending);
    }
    a.on_done(done, 2)
}

#[test]
fn a_refined_world_is_stored_as_a_difference_and_composed_over_its_parent() {
    let mut a = Assembler::new(1 << 30);
    a.submit_job(job("s", JobKind::Sample, None));
    a.submit_job(refine_job(0));
    let (segs, done) = root();
    let parent_bytes: u64 = segs.iter().map(|s| s.payload.len() as u64).sum();
    assert!(matches!(
        feed(&mut a, segs, done),
        Outcome::Stored { index: 0, .. }
    ));
    let ((own, done), whole) = child(7);
    assert!(done.first_segment >= 1, "the branch is past segment 0");
    assert_eq!(done.segment_count as usize, whole.len());
    assert_eq!(own.len(), whole.len() - done.first_segment as usize);
    assert!(own.iter().all(|s| !s.bodies.is_empty()), "only some bodies");
    let own_bytes: u64 = own.iter().map(|s| s.payload.len() as u64).sum();
    let before = a.memory_bytes();
    let Outcome::Stored { index: 1, .. } = feed(&mut a, own, done.clone()) else {
        panic!("the refined world was not stored")
    };
    // Only the new bytes count: held in memory, less than the parent (alone in the store
    // before) holds; encoded, less than the parent's payload alone.
    let added = a.memory_bytes() - before;
    assert!(added < before, "{added} ≥ the parent's {before} held");
    assert!(added >= own_bytes);
    let stored = a.world(1).unwrap_or_else(|| panic!("world 1"));
    assert!(
        stored.bytes < parent_bytes,
        "{} ≥ the parent's payload {parent_bytes}",
        stored.bytes
    );

    assert!(stored.is_layered());
    assert_eq!(stored.parent.as_ref().map(|p| p.index), Some(0));

    // Served with its parent chain, it decodes into the world a whole recording gives: the
    // parent's motion exactly where the child did not re-simulate, and within the codec's bound
    // of the whole recording everywhere.
    let msg = stored.message().unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(msg.parent.as_ref().map(|p| p.index), Some(0));
    let composed = mwb_export::decode_world(&msg).unwrap_or_else(|e| panic!("{e}"));
    let parent = mwb_export::decode_world(msg.parent.as_deref().unwrap_or_else(|| panic!("p")))
        .unwrap_or_else(|e| panic!("{e}"));
    let mut whole_msg = msg.clone();
    whole_msg.parent = None;
    whole_msg.segments = whole;
    whole_msg.done = Some(WorldDone {
        first_segment: 0,
        ..done.clone()
    });
    let reference = mwb_export::decode_world(&whole_msg).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(composed.tracks.len(), 5);
    let frames = done.frame_count as usize;
    for (b, t) in composed.tracks.iter().enumerate() {
        assert_eq!(t.len(), frames);
        let from = done.active_from[b];
        for f in 0..frames {
            let (p, r) = (&t.positions[f], &reference.tracks[b].positions[f]);
            let d = (0..3).map(|i| (p[i] - r[i]).powi(2)).sum::<f64>().sqrt();
            assert!(d < 2.5e-3, "body {b} frame {f}: {d} m from the whole world");
            // Before the segment holding its activation, the parent's decoded frame itself.
            let own_from = if from < 0 {
                frames
            } else {
                (from as usize / 120) * 120
            };
            if f < own_from {
                let q = parent.tracks[b].positions[f.min(parent.tracks[b].len() - 1)];
                assert_eq!(*p, q, "body {b} frame {f}");
            }
        }
    }

    // Indexed through the composition, with the summary's metrics.
    let scene = mwb_store::index::JobScene::of(&refine_job(0));
    let indexed =
        index_world(&stored, 1, scene, DEFAULT_PATH_TOLERANCE_M).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(indexed.objects.len(), 5);
    let crate_path = indexed.objects[0].polyline();
    let last = crate_path
        .points()
        .last()
        .unwrap_or_else(|| panic!("empty"));
    let end = composed.tracks[0].positions[frames - 1];
    let d = (0..3)
        .map(|i| (last[i] - end[i]).powi(2))
        .sum::<f64>()
        .sqrt();
    assert!(d <= indexed.objects[0].radius, "{d}");
}

#[test]
fn a_refined_world_without_its_parent_here_is_refused() {
    let mut a = Assembler::new(1 << 30);
    a.submit_job(refine_job(0));
    let ((own, done), _) = child(9);
    let out = feed(&mut a, own, done);
    assert!(
        matches!(
            out,
            Outcome::Rejected {
                reason: Rejection::NoParent,
                ..
            }
        ),
        "{out:?}"
    );
    assert_eq!(a.counters.incomplete, 1);
    // A difference sent for a job that refines nothing has no parent either.
    let mut a = Assembler::new(1 << 30);
    a.submit_job(job("r", JobKind::Sample, None));
    let ((own, done), _) = child(9);
    assert!(matches!(
        feed(&mut a, own, done),
        Outcome::Rejected {
            reason: Rejection::NoParent,
            ..
        }
    ));
}

#[test]
fn a_malformed_difference_is_refused_as_incomplete() {
    type Spoil = fn(&mut Vec<MotionSegment>, &mut WorldDone);
    let cases: [(&str, Spoil); 4] = [
        ("a body out of range", |s, _| s[0].bodies = vec![5]),
        ("a body listed twice", |s, _| {
            s[0].bodies = vec![0, 0];
            s[0].body_count = 2;
        }),
        ("a segment missing", |s, d| {
            s.remove(0);
            d.first_segment += 1;
        }),
        ("a segment more than the summary counts", |_, d| {
            d.segment_count -= 1
        }),
    ];
    for (what, spoil) in cases {
        let mut a = Assembler::new(1 << 30);
        a.submit_job(job("s", JobKind::Sample, None));
        a.submit_job(refine_job(0));
        let (segs, done) = root();
        feed(&mut a, segs, done);
        let ((mut own, mut done), _) = child(11);
        spoil(&mut own, &mut done);
        let mut out = Outcome::Pending;
        for s in own {
            out = a.on_segment(s, 1);
            if out != Outcome::Pending {
                break;
            }
        }
        if out == Outcome::Pending {
            out = a.on_done(done, 2);
        }
        assert!(
            matches!(
                out,
                Outcome::Rejected {
                    reason: Rejection::Incomplete,
                    ..
                }
            ),
            "{what}: {out:?}"
        );
    }
}
