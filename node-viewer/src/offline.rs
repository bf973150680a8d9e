//! Offline worlds: sampled in-process with the sampler library and decoded with the codec, the
//! same bytes a sampler node would put on the bus. Pure computation (threads, no I/O).

use std::ops::ControlFlow;
use std::sync::Mutex;

use mwb_core::scene::SceneTemplate;
use mwb_sampler::{RunOptions, run_world};

use crate::ViewerError;
use crate::world::{WorldData, decode_segments};

/// The seed of offline world `i` (worlds are numbered from 0 and world `i` has seed `i`, so a
/// world seen in the viewer can be re-run with `mwb bench` or a test by its number).
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

/// One offline world: sample, encode, decode, index.
pub fn sample_one(template: &SceneTemplate, i: u32) -> Result<WorldData, ViewerError> {
    let seed = offline_seed(i);
    let mut segments = Vec::new();
    let summary = run_world(template, seed, RunOptions::default(), &mut |seg| {
        segments.push(seg);
        ControlFlow::Continue(())
    })
    .map_err(|e| ViewerError::Sampling {
        world: i,
        what: e.to_string(),
    })?;
    let (tracks, e_max) = decode_segments(&segments)?;
    WorldData::new(
        i,
        seed,
        template.instantiate(seed),
        summary.frame_dt,
        tracks,
        e_max,
    )
}
