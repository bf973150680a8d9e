//! Refinement (§4.5): a regenerated parent is the sampled world bit for bit; a child is its
//! parent until the branch frame; bodies no active one reaches keep the parent's exact motion;
//! Figure 4.11a (the new motion hits an inactive body, which responds) and 4.11b (a body the
//! parent's motion hit is no longer hit, and stays put); refinements of refinements; determinism
//! byte for byte; and every refusal names its field.

use mwb_codec::{Track, WorldReader};
use mwb_core::browse::Frustum;
use mwb_core::scene::{SceneTemplate, builtin};
use mwb_sampler::refine::{BranchAt, ExactMotion, Kick, Lineage, RefineError, regenerate};
use mwb_sampler::world::{RunOptions, Segment, run_world_observed};
use std::ops::ControlFlow;

fn parse(src: &str) -> SceneTemplate {
    SceneTemplate::parse(src, "test.toml").unwrap_or_else(|e| panic!("{e}"))
}

/// Two 0.2 m boxes on the ground, 0.8 m apart along x (`a` at 0, `o` at 1), and a third far
/// away that nothing reaches. `a` starts with velocity `vx`.
fn pair(vx: f64) -> SceneTemplate {
    parse(&format!(
        r#"
name = "pair"
[settings]
end_time = 3.0
[[material]]
name = "m"
friction = 0.5
restitution = 0.1
density = 500.0
[[static]]
name = "ground"
shape = "plane"
normal = [0, 1, 0]
material = "m"
[[body]]
name = "a"
shape = "box"
size = [0.2, 0.2, 0.2]
material = "m"
position = [0.0, 0.1, 0.0]
linvel = [{vx}, 0, 0]
[[body]]
name = "o"
shape = "box"
size = [0.2, 0.2, 0.2]
material = "m"
position = [1.0, 0.1, 0.0]
[[body]]
name = "far"
shape = "box"
size = [0.2, 0.2, 0.2]
material = "m"
position = [-4.0, 1.0, 0.0]
linvel = [0, 2, 0]
"#
    ))
}

const A: usize = 0;
const O: usize = 1;
const FAR: usize = 2;

fn keep(segs: &mut Vec<Segment>) -> impl FnMut(Segment) -> ControlFlow<()> + '_ {
    |s| {
        segs.push(s);
        ControlFlow::Continue(())
    }
}

fn bits(m: &ExactMotion, frame: u32, body: usize) -> ([u64; 3], [u64; 4]) {
    let p = m
        .pose(frame, body)
        .unwrap_or_else(|| panic!("no pose at frame {frame}, body {body}"));
    (p.position.map(f64::to_bits), p.rotation.map(f64::to_bits))
}

#[test]
fn a_regenerated_parent_is_the_sampled_world_bit_for_bit() {
    let template = parse(builtin::TUMBLE);
    let seed = 0xfeed;
    let mut sampled: Vec<Track> = Vec::new();
    let summary = run_world_observed(
        &template,
        seed,
        RunOptions::default(),
        &mut |_| ControlFlow::Continue(()),
        &mut |tracks| {
            if sampled.is_empty() {
                sampled = tracks.to_vec();
            } else {
                for (all, t) in sampled.iter_mut().zip(tracks) {
                    all.positions.extend_from_slice(&t.positions);
                    all.rotations.extend_from_slice(&t.rotations);
                }
            }
        },
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let parent = regenerate(&template, &Lineage::root(seed), &BranchAt::Frame(40))
        .unwrap_or_else(|e| panic!("{e}"));
    let m = parent.motion();
    assert_eq!(m.frame_count(), summary.frame_count);
    for (b, t) in sampled.iter().enumerate() {
        for f in 0..summary.frame_count {
            let p = m.pose(f, b).unwrap_or_else(|| panic!("frame {f}"));
            assert_eq!(p.position, t.positions[f as usize], "body {b} frame {f}");
            assert_eq!(p.rotation, t.rotations[f as usize], "body {b} frame {f}");
        }
    }
}

/// (a) and (b), and Figure 4.11a: `a`, kicked towards `o` at the branch, hits it; `o` becomes
/// active just before the contact and is pushed; `far` keeps the parent's exact motion.
#[test]
fn a_kicked_body_hits_an_inactive_one_which_responds() {
    let template = pair(0.0);
    let k = 6;
    let parent = regenerate(&template, &Lineage::root(1), &BranchAt::Frame(k))
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(parent.branch_frame(), k);
    let kick = Kick {
        body: A as u32,
        linvel: [4.0, 0.0, 0.0],
        angvel: [0.0; 3],
    };
    let mut segs = Vec::new();
    let (child, m) = parent
        .refine_traced(
            &[A as u32],
            7,
            RunOptions::default(),
            &[kick],
            &mut keep(&mut segs),
        )
        .unwrap_or_else(|e| panic!("{e}"));
    let pm = parent.motion();

    // (a) The parent, bit for bit, up to and including the branch frame.
    for f in 0..=k {
        for b in 0..3 {
            assert_eq!(bits(&m, f, b), bits(pm, f, b), "frame {f} body {b}");
        }
    }
    assert_eq!(child.branch_frame, k);
    assert_eq!(child.active_from[A], Some(k));

    // Figure 4.11a: `o` joins when `a` is about to reach it, not before, and moves.
    let joined = child.active_from[O].unwrap_or_else(|| panic!("o never became active"));
    assert!(
        joined > k + 10,
        "o joined at {joined}, long before a could reach it"
    );
    let (o0, o1) = (
        pm.pose(0, O).map(|p| p.position[0]),
        m.pose(m.frame_count() - 1, O).map(|p| p.position[0]),
    );
    let (Some(o0), Some(o1)) = (o0, o1) else {
        panic!("no poses")
    };
    assert!(o1 > o0 + 0.05, "o was not pushed: x {o0} → {o1}");
    // Until it joined, `o` was exactly where the parent had it.
    for f in k..joined {
        assert_eq!(bits(&m, f, O), bits(pm, f, O), "o, frame {f}");
    }

    // (b) Nothing reached `far`: the parent's exact motion, every frame, as the simulator
    // replayed it.
    assert_eq!(child.active_from[FAR], None);
    for f in 0..m.frame_count() {
        assert_eq!(bits(&m, f, FAR), bits(pm, f, FAR), "far, frame {f}");
    }
    // … and the impacts the sampled world counted for it.
    let sampled = mwb_sampler::run_world(&template, 1, RunOptions::default(), &mut |_| {
        ControlFlow::Continue(())
    })
    .unwrap_or_else(|e| panic!("{e}"));
    assert!(sampled.impacts[FAR] >= 1, "far lands");
    assert_eq!(child.summary.impacts[FAR], sampled.impacts[FAR]);

    // The child sends only what it re-simulated, on the parent's segment grid.
    assert_eq!(segs[0].seq, child.first_segment);
    assert!(segs[0].first_frame <= k);
    for s in &segs {
        assert!(!s.bodies.contains(&(FAR as u32)), "segment {}", s.seq);
        assert!(s.bodies.contains(&(A as u32)));
        assert_eq!(s.body_count as usize, s.bodies.len());
    }
    assert!(segs.iter().any(|s| s.bodies.contains(&(O as u32))));
    // Its first segment's frames before the branch decode to the parent's, within the codec's
    // bound.
    let tracks = WorldReader::new(&segs[0].payload)
        .and_then(|r| r.decode_all())
        .unwrap_or_else(|e| panic!("{e}"));
    let a_track = &tracks[segs[0]
        .bodies
        .iter()
        .position(|&b| b == A as u32)
        .unwrap_or(0)];
    for f in segs[0].first_frame..=k {
        let want = pm.pose(f, A).map(|p| p.position).unwrap_or_default();
        let got = a_track.positions[(f - segs[0].first_frame) as usize];
        let d = (0..3)
            .map(|i| (got[i] - want[i]).powi(2))
            .sum::<f64>()
            .sqrt();
        assert!(d < 2e-3, "frame {f}: decoded {d} m from the parent");
    }
}

/// Figure 4.11b: in the parent `a` slides into `o` and pushes it; a child where `a` stops at the
/// branch must not leave `o` moving as if hit: `o` becomes active (through `a`'s ghost) and
/// stays put.
#[test]
fn a_body_the_parent_hit_and_the_child_misses_stays_put() {
    let template = pair(4.0);
    let parent = regenerate(&template, &Lineage::root(3), &BranchAt::Frame(2))
        .unwrap_or_else(|e| panic!("{e}"));
    let pm = parent.motion();
    let last = |m: &ExactMotion, b| {
        m.pose(m.frame_count() - 1, b)
            .map(|p| p.position[0])
            .unwrap_or(f64::NAN)
    };
    assert!(
        last(pm, O) > 1.05,
        "the parent should push o: x {}",
        last(pm, O)
    );
    let stop = Kick {
        body: A as u32,
        linvel: [0.0; 3],
        angvel: [0.0; 3],
    };
    let (child, m) = parent
        .refine_traced(&[A as u32], 9, RunOptions::default(), &[stop], &mut |_| {
            ControlFlow::Continue(())
        })
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(
        child.active_from[O].is_some(),
        "o must leave the inactive set"
    );
    assert!(
        (last(&m, O) - 1.0).abs() < 0.01,
        "o moved without being hit: x {}",
        last(&m, O)
    );
    let a_at_branch = pm.pose(2, A).map(|p| p.position[0]).unwrap_or(f64::NAN);
    assert!(
        (last(&m, A) - a_at_branch).abs() < 0.01,
        "a was stopped at x {a_at_branch} and ended at {}",
        last(&m, A)
    );
}

/// (g) A refined world regenerates exactly from its lineage and refines again, also from a
/// frame before its own branch (the grandparent's part of its history).
#[test]
fn a_refined_world_regenerates_exactly_and_refines_again() {
    let template = pair(0.0);
    let root = regenerate(&template, &Lineage::root(5), &BranchAt::Frame(6))
        .unwrap_or_else(|e| panic!("{e}"));
    let kick = Kick {
        body: A as u32,
        linvel: [4.0, 0.0, 0.0],
        angvel: [0.0; 3],
    };
    let run = |p: &mwb_sampler::refine::Parent, objects: &[u32], seed, kicks: &[Kick]| {
        let mut segs = Vec::new();
        let (w, m) = p
            .refine_traced(
                objects,
                seed,
                RunOptions::default(),
                kicks,
                &mut keep(&mut segs),
            )
            .unwrap_or_else(|e| panic!("{e}"));
        (w, m, segs)
    };
    let (child, child_motion, child_segs) = run(&root, &[A as u32], 11, &[kick]);

    // Deterministic in (lineage, seed): the same bytes again.
    let (again, again_motion, again_segs) = run(&root, &[A as u32], 11, &[kick]);
    assert_eq!(again, child);
    assert_eq!(again_motion, child_motion);
    assert_eq!(again_segs, child_segs);

    // Regenerated from its lineage, the child is what was just computed, bit for bit.
    let k2 = 40;
    let as_parent = regenerate(&template, &child.lineage, &BranchAt::Frame(k2))
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(as_parent.motion(), &child_motion);
    let (grandchild, gm, _) = run(&as_parent, &[O as u32], 13, &[]);
    assert_eq!(grandchild.lineage.steps.len(), 2);
    assert_eq!(grandchild.branch_frame, k2);
    for f in 0..=k2 {
        assert_eq!(bits(&gm, f, O), bits(&child_motion, f, O), "frame {f}");
    }

    // A box around where `a` sat before the first branch: t_min is frame 0, in the root's part
    // of the child's history.
    let p0 = root
        .motion()
        .pose(0, A)
        .map(|p| p.position)
        .unwrap_or_default();
    let near =
        Frustum::aabb(p0.map(|x| x - 0.05), p0.map(|x| x + 0.05)).unwrap_or_else(|e| panic!("{e}"));
    let early = regenerate(
        &template,
        &child.lineage,
        &BranchAt::FirstInside {
            objects: vec![A as u32],
            frustum: Box::new(near),
        },
    )
    .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(early.branch_frame(), 0);
    assert_eq!(early.motion(), &child_motion);
}

#[test]
fn the_branch_frame_is_the_first_frame_a_picked_centre_is_inside() {
    let template = pair(4.0);
    let parent = regenerate(&template, &Lineage::root(3), &BranchAt::Frame(0))
        .unwrap_or_else(|e| panic!("{e}"));
    let m = parent.motion();
    // A slab x ∈ [0.3, 0.5]: `a` crosses it sliding right.
    let slab = Frustum::aabb([0.3, -1.0, -1.0], [0.5, 1.0, 1.0]).unwrap_or_else(|e| panic!("{e}"));
    let want = (0..m.frame_count())
        .find(|&f| m.pose(f, A).is_some_and(|p| p.position[0] >= 0.3))
        .unwrap_or_else(|| panic!("a never reaches the slab"));
    let at = regenerate(
        &template,
        &Lineage::root(3),
        &BranchAt::FirstInside {
            objects: vec![A as u32, FAR as u32],
            frustum: Box::new(slab),
        },
    )
    .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(at.branch_frame(), want);
}

#[test]
fn bad_refinements_are_refused_naming_the_field() {
    let template = pair(4.0);
    let lineage = Lineage::root(3);
    fn err<T>(r: Result<T, RefineError>) -> String {
        match r {
            Ok(_) => panic!("accepted"),
            Err(e) => e.to_string(),
        }
    }
    let far_away =
        Frustum::aabb([50.0, 50.0, 50.0], [51.0, 51.0, 51.0]).unwrap_or_else(|e| panic!("{e}"));
    let msg = err(regenerate(
        &template,
        &lineage,
        &BranchAt::FirstInside {
            objects: vec![A as u32],
            frustum: Box::new(far_away),
        },
    ));
    assert!(msg.starts_with("frustum:"), "{msg}");
    let msg = err(regenerate(
        &template,
        &lineage,
        &BranchAt::FirstInside {
            objects: vec![7],
            frustum: Box::new(far_away),
        },
    ));
    assert!(msg.starts_with("objects: body 7 out of range"), "{msg}");
    let msg = err(regenerate(&template, &lineage, &BranchAt::Frame(1_000_000)));
    assert!(msg.starts_with("frame: 1000000 is past"), "{msg}");

    let parent =
        regenerate(&template, &lineage, &BranchAt::Frame(3)).unwrap_or_else(|e| panic!("{e}"));
    let none = |_: Segment| ControlFlow::Continue(());
    let msg = err(parent.refine(&[], 1, RunOptions::default(), &mut none.clone()));
    assert!(msg.starts_with("objects: none"), "{msg}");
    let msg = err(parent.refine(&[3], 1, RunOptions::default(), &mut none.clone()));
    assert!(msg.starts_with("objects: body 3"), "{msg}");
    let kick = Kick {
        body: O as u32,
        linvel: [0.0; 3],
        angvel: [0.0; 3],
    };
    let msg = err(parent.refine_with(
        &[A as u32],
        1,
        RunOptions::default(),
        &[kick],
        &mut none.clone(),
    ));
    assert!(msg.starts_with("kicks: body 1"), "{msg}");
    // A lineage whose step branches past its parent's end names the step.
    let bad = lineage.child(mwb_sampler::refine::Branch {
        frame: 1_000_000,
        objects: vec![0],
        seed: 1,
        kicks: Vec::new(),
    });
    let msg = err(regenerate(&template, &bad, &BranchAt::Frame(0)));
    assert!(msg.starts_with("lineage step 0: frame:"), "{msg}");
}

/// A request against a stored world (as the stores serve it) becomes a REFINE job, or is
/// refused naming what is wrong.
#[test]
fn a_refinement_request_becomes_a_refine_job_or_is_refused() {
    use mwb_proto::v1::{Job, JobKind, Scene, World, WorldDone};
    use mwb_sampler::request::{RequestError, plan};
    let text = builtin::TUMBLE;
    let template = parse(text);
    let seed = 0xfeed;
    let (frames, _) = {
        let p = regenerate(&template, &Lineage::root(seed), &BranchAt::Frame(0))
            .unwrap_or_else(|e| panic!("{e}"));
        (p.motion().frame_count(), ())
    };
    let world = World {
        index: 7,
        job_id: "j".into(),
        done: Some(WorldDone {
            seed,
            frame_count: frames,
            ..Default::default()
        }),
        segments: Vec::new(),
        parent: None,
    };
    let job = Job {
        id: "j".into(),
        kind: JobKind::Sample as i32,
        scene: Some(Scene {
            toml: text.into(),
            ..Default::default()
        }),
        quality: 3,
        ..Default::default()
    };
    let everywhere = Frustum::aabb([-50.0; 3], [50.0; 3]).unwrap_or_else(|e| panic!("{e}"));
    let p = plan(&world, &job, "crate", everywhere).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((p.objects.clone(), p.branch_frame), (vec![0], 0));
    assert_eq!(p.lineage.root_seed, seed);
    let j = p.job("r".into(), 12, 1, 5);
    assert_eq!(
        (j.kind(), j.target_worlds, j.quality),
        (JobKind::Refine, 12, 3)
    );
    let r = j.refine.unwrap_or_default();
    assert_eq!((r.parent_world, r.objects, r.branch_frame), (7, vec![0], 0));

    let nowhere = Frustum::aabb([50.0; 3], [51.0; 3]).unwrap_or_else(|e| panic!("{e}"));
    let e = plan(&world, &job, "crate", nowhere)
        .err()
        .map(|e| e.to_string());
    assert!(
        e.as_deref()
            .is_some_and(|e| e.starts_with("the box: the centre of crate")),
        "{e:?}"
    );
    let e = plan(&world, &job, "anvil", everywhere).err();
    assert!(matches!(e, Some(RequestError::Objects(_))), "{e:?}");
    let reverse = Job {
        kind: JobKind::Reverse as i32,
        ..job.clone()
    };
    let e = plan(&world, &reverse, "0", everywhere).err();
    assert!(matches!(e, Some(RequestError::Backward { .. })), "{e:?}");
    let other_build = World {
        done: Some(WorldDone {
            seed,
            frame_count: frames + 1,
            ..Default::default()
        }),
        ..world.clone()
    };
    let e = plan(&other_build, &job, "0", everywhere).err();
    assert!(
        matches!(e, Some(RequestError::NotRegenerated { .. })),
        "{e:?}"
    );
}
