//! A sampled world and a refined child of it (§4.5) as samplers send them, for the tests of
//! refined worlds stored as differences (`refined.rs`, `journal.rs`).
#![allow(dead_code)]

use mwb_core::scene::{SceneTemplate, builtin};
use mwb_proto::v1::{Job, JobKind, MotionSegment, Refinement, Scene, WorldDone};
use mwb_sampler::node::{lineage_to_wire, refined_done};
use mwb_sampler::refine::{BranchAt, Lineage, regenerate};
use mwb_sampler::{RunOptions, run_world, segment_message, world_done};
use std::ops::ControlFlow;

pub const ROOT_SEED: u64 = 0x5eed;
pub const BRANCH: u32 = 150;

pub fn template() -> SceneTemplate {
    SceneTemplate::parse(builtin::TUMBLE, "tumble.toml").unwrap_or_else(|e| panic!("{e}"))
}

pub fn job(id: &str, kind: JobKind, refine: Option<Refinement>) -> Job {
    Job {
        id: id.into(),
        revision: 1,
        kind: kind as i32,
        target_worlds: 10,
        scene: Some(Scene {
            toml: builtin::TUMBLE.into(),
            ..Default::default()
        }),
        refine,
        ..Default::default()
    }
}

/// The root world (job `s`, seed [`ROOT_SEED`]) as a sampler sends it.
pub fn root() -> (Vec<MotionSegment>, WorldDone) {
    let mut segs = Vec::new();
    let summary = run_world(&template(), ROOT_SEED, RunOptions::default(), &mut |s| {
        segs.push(segment_message("s", "n", 0, ROOT_SEED, s));
        ControlFlow::Continue(())
    })
    .unwrap_or_else(|e| panic!("{e}"));
    (segs, world_done("s", "n", 0, &summary))
}

/// Child `seed` of the root world refining the crate (body 0) from [`BRANCH`]: as a sampler
/// sends it (a difference), and the same world recorded whole.
pub fn child(seed: u64) -> ((Vec<MotionSegment>, WorldDone), Vec<MotionSegment>) {
    let parent = regenerate(
        &template(),
        &Lineage::root(ROOT_SEED),
        &BranchAt::Frame(BRANCH),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let mut own = Vec::new();
    let refined = parent
        .refine(&[0], seed, RunOptions::default(), &mut |s| {
            own.push(segment_message("r", "n", seed, seed, s));
            ControlFlow::Continue(())
        })
        .unwrap_or_else(|e| panic!("{e}"));
    let mut whole = Vec::new();
    parent
        .refine_whole(&[0], seed, RunOptions::default(), &mut |s| {
            whole.push(segment_message("w", "n", seed, seed, s));
            ControlFlow::Continue(())
        })
        .unwrap_or_else(|e| panic!("{e}"));
    ((own, refined_done("r", "n", seed, "s", &refined)), whole)
}

pub fn refine_job(parent_world: u32) -> Job {
    job(
        "r",
        JobKind::Refine,
        Some(Refinement {
            parent_job: "s".into(),
            parent_world,
            parent: Some(lineage_to_wire("s", &Lineage::root(ROOT_SEED))),
            objects: vec![0],
            branch_frame: BRANCH,
        }),
    )
}
