//! The reverse node: a [`mwb_node`] worker node that takes `JOB_KIND_REVERSE` jobs (and only
//! those) and samples backward worlds ([`crate::sample`]). It publishes them exactly as a
//! forward sampler does — `MotionSegment`s on `seg/<job>/<node>/<n>/<seq>` (SPLINE_V1 payload,
//! CRC32 over the payload, low-res path beside it), then a `WorldDone` on
//! `done/<job>/<node>/<n>` — so the store assembles, indexes and serves them like any world.
//! Liveliness token `alive/reverse/<node>`, statistics on `stats/reverse/<node>` every second.
//!
//! Joining and leaving, the job board and the publisher are the skeleton's (§4.2). A job's
//! scene is prepared (parsed, chain learned) once, by the first worker that needs it; its
//! `[reverse]` table ([`crate::settings_toml`]) makes the job's worlds mixed (§5.4.4) and/or
//! hinted. `WorldDone` carries each world's §5.3.1 plausibility numbers (`energy_growth`,
//! `angular_speed_growth`).

use crate::sample::{ReverseScene, SampleError, Segment, provenance, sample_world};
use mwb_core::keys::role;
use mwb_node::{SegmentBody, WorkerKind, WorldTask, codec_quality};
use mwb_proto::v1::{Encoding, Job, JobKind, MotionSegment, Scene, WorldDone};
use std::ops::ControlFlow;
use tracing::debug;
use zenoh::Session;

/// A job whose worlds fail this many times in a row (non-finite state, codec refusal) is
/// given up locally: the scene, not the seed, is the problem.
pub const MAX_CONSECUTIVE_FAILURES: u32 = 8;

/// Reverse node settings (the worker node's; every field's default is documented there).
pub type ReverseConfig = mwb_node::WorkerConfig;
/// A running reverse node. Dropping it does not stop it; call `stop`.
pub type ReverseHandle = mwb_node::WorkerHandle;
/// Why the node could not start.
pub type ReverseNodeError = mwb_node::NodeError;

/// Backward (and mixed) worlds: a job's scene is a [`ReverseScene`], a world one
/// [`sample_world`] of it.
#[derive(Debug, Clone, Copy, Default)]
pub struct Backward;

impl WorkerKind for Backward {
    const ROLE: &'static str = role::REVERSE;
    const GIVE_UP_AFTER: u32 = MAX_CONSECUTIVE_FAILURES;
    type Scene = ReverseScene;
    type SceneError = SampleError;
    type WorldError = SampleError;

    fn takes(kind: JobKind) -> bool {
        kind == JobKind::Reverse
    }

    fn prepare(&self, job: &Job, scene: &Scene) -> Result<ReverseScene, SampleError> {
        ReverseScene::prepare(&scene.toml, &format!("job {} scene", job.id))
    }

    fn run(
        &self,
        w: &WorldTask<'_>,
        scene: &ReverseScene,
        emit: &mut dyn FnMut(MotionSegment) -> ControlFlow<()>,
    ) -> Result<WorldDone, SampleError> {
        let quality = codec_quality(w.job.quality());
        let mut emit =
            |seg: Segment| emit(segment_message(&w.job.id, w.node, w.counter, w.seed, seg));
        let summary = sample_world(scene, w.seed, quality, &mut emit)?;
        debug!(
            job = %w.job.id,
            counter = w.counter,
            energy_growth = summary.report.energy_growth,
            angular_speed_growth = summary.report.angular_speed_growth,
            plausible = summary.report.plausibility.plausible,
            plausibility_excess = summary.report.plausibility.excess_m,
            "backward world done"
        );
        Ok(summary.world_done(&w.job.id, w.node, w.counter))
    }

    fn stopped(e: &SampleError) -> bool {
        matches!(e, SampleError::Stopped)
    }

    fn provenance(&self) -> String {
        provenance()
    }
}

/// Starts a reverse node on `session` (in the current tokio runtime).
pub async fn run_reverse(
    session: Session,
    cfg: ReverseConfig,
) -> Result<ReverseHandle, ReverseNodeError> {
    mwb_node::run_workers(session, cfg, Backward).await
}

/// The wire form of a segment of world `(job, node, counter)` (the sampler's
/// `segment_message`, for backward worlds; always `SPLINE_V1`).
pub fn segment_message(
    job_id: &str,
    node: &str,
    counter: u64,
    seed: u64,
    seg: Segment,
) -> MotionSegment {
    let body = SegmentBody {
        bodies: Vec::new(),
        seq: seg.seq,
        first_frame: seg.first_frame,
        frame_count: seg.frame_count,
        body_count: seg.body_count,
        encoding: Encoding::SplineV1,
        payload: seg.payload,
    };
    mwb_node::segment_message(job_id, node, counter, seed, body)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job(toml: &str) -> Job {
        Job {
            id: "r".into(),
            kind: JobKind::Reverse as i32,
            scene: Some(Scene {
                toml: toml.into(),
                ..Default::default()
            }),
            target_worlds: 1,
            ..Default::default()
        }
    }

    #[test]
    fn only_reverse_jobs_are_taken() {
        assert!(Backward::takes(JobKind::Reverse));
        for other in [JobKind::Sample, JobKind::Refine, JobKind::Unspecified] {
            assert!(!Backward::takes(other), "{other:?}");
        }
    }

    #[test]
    fn a_scene_the_stepper_cannot_run_is_refused_with_its_reason() {
        let j = job("not = [valid");
        let err = Backward
            .prepare(&j, &j.scene.clone().unwrap_or_default())
            .err()
            .unwrap_or_else(|| panic!("an invalid scene was accepted"));
        assert!(matches!(err, SampleError::Scene(_)), "{err}");
        assert!(err.to_string().contains("job r scene"), "{err}");
    }

    #[test]
    fn a_backward_world_is_published_as_spline_segments_and_stops_when_emit_breaks() {
        let j = job(crate::scene::builtin::WORD);
        let scene = Backward
            .prepare(&j, &j.scene.clone().unwrap_or_default())
            .unwrap_or_else(|e| panic!("{e}"));
        let w = WorldTask {
            job: &j,
            node: "n",
            counter: 2,
            seed: 5,
        };
        let mut segs = Vec::new();
        let done = Backward
            .run(&w, &scene, &mut |s| {
                segs.push(s);
                ControlFlow::Continue(())
            })
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((done.seed, done.world_counter), (5, 2));
        assert_eq!(done.segment_count as usize, segs.len());
        assert!(done.energy_growth.is_some());
        assert!(done.plausible.is_some() && done.plausibility_excess.is_some());
        assert_eq!(done.plausible, done.plausibility_excess.map(|x| x <= 0.0));
        assert!(
            segs.iter()
                .all(|s| s.encoding == Encoding::SplineV1 as i32 && s.job_id == "r")
        );
        assert!(matches!(
            Backward.run(&w, &scene, &mut |_| ControlFlow::Break(())),
            Err(SampleError::Stopped)
        ));
    }
}
