//! Offline worlds: sampled in-process with the sampler library, in the wire form a sampler node
//! puts on the bus, indexed with the store's own `index_world` and decoded with
//! `mwb_export::decode_segments` — so a box drawn offline is tested against exactly the paths
//! and radii a store would hold. Pure computation (threads, no I/O).

use std::ops::ControlFlow;
use std::sync::{Arc, Mutex};

use mwb_core::browse::RestThresholds;
use mwb_core::scene::SceneTemplate;
use mwb_sampler::{RunOptions, run_world, segment_message, world_done};
use mwb_store::StoredWorld;
use mwb_store::index::{DEFAULT_PATH_TOLERANCE_M, JobScene, index_world};

use crate::ViewerError;
use crate::world::{Motion, WorldData};

/// The job id offline worlds carry.
pub const OFFLINE_JOB: &str = "offline";

/// The seed of offline world `i` (worlds are numbered from 0 and world `i` has seed `i`, so a
/// world seen in the viewer can be re-run with `mwb world --seed i` or a test by its number).
pub fn offline_seed(i: u32) -> u64 {
    u64::from(i)
}

/// Samples worlds `0..n` of `template` on up to `threads` threads, encodes each with the default
/// codec quality, and decodes it back. A world that fails is returned as its error, in place.
pub fn sample_worlds(
    template: &SceneTemplate,
    n: u32,
    threads: usize,
) -> Vec<Result<WorldData, ViewerError>> {
    let next = Mutex::new(0u32);
    let out: Mutex<Vec<Option<Result<WorldData, ViewerError>>>> =
        Mutex::new((0..n).map(|_| None).collect());
    std::thread::scope(|s| {
        for _ in 0..threads.max(1).min(n.max(1) as usize) {
            s.spawn(|| {
                loop {
                    let i = {
                        let Ok(mut g) = next.lock() else { return };
                        let i = *g;
                        *g += 1;
                        i
                    };
                    if i >= n {
                        return;
                    }
                    let r = sample_one(template, i);
                    if let Ok(mut g) = out.lock() {
                        g[i as usize] = Some(r);
                    }
                }
            });
        }
    });
    out.into_inner()
        .unwrap_or_default()
        .into_iter()
        .enumerate()
        .map(|(i, r)| {
            r.unwrap_or(Err(ViewerError::Sampling {
                world: i as u32,
                what: "worker thread stopped".into(),
            }))
        })
        .collect()
}

/// One offline world: sample, index as a store would, decode.
pub fn sample_one(template: &SceneTemplate, i: u32) -> Result<WorldData, ViewerError> {
    let seed = offline_seed(i);
    let mut segments = Vec::new();
    let summary = run_world(template, seed, RunOptions::default(), &mut |seg| {
        segments.push(segment_message(OFFLINE_JOB, "", 0, seed, seg));
        ControlFlow::Continue(())
    })
    .map_err(|e| ViewerError::Sampling {
        world: i,
        what: e.to_string(),
    })?;
    let done = world_done(OFFLINE_JOB, "", 0, &summary);
    let stored = StoredWorld::new(i, OFFLINE_JOB.into(), &done, &segments, 0, None);
    let scene = JobScene {
        rest: RestThresholds::from(template.settings()),
        bodies: template.body_names().map(str::to_owned).collect(),
    };
    let indexed = index_world(&stored, i, scene, DEFAULT_PATH_TOLERANCE_M).map_err(|e| {
        ViewerError::Sampling {
            world: i,
            what: e.to_string(),
        }
    })?;
    let mut world = WorldData::from_paths(&indexed.paths_message())?;
    world.metrics = indexed
        .metrics
        .iter()
        .map(mwb_core::browse::PackedMetrics::unpack)
        .collect();
    let message = mwb_proto::v1::World {
        index: i,
        job_id: OFFLINE_JOB.into(),
        done: Some(done),
        segments,
        parent: None,
    };
    let motion = Motion::decode(template.instantiate(seed), &message)?;
    world.motion = Some(Arc::new(motion));
    Ok(world)
}
