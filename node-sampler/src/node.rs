//! The sampler node (§4.2 "opportunistic computing"): a [`mwb_node`] worker node whose worlds
//! are forward rapier3d runs ([`run_world`]). It takes sample and refine jobs (reverse jobs
//! belong to reverse nodes); joining, leaving, the job board and the publisher are the
//! skeleton's.

use crate::world::{PayloadEncoding, RunError, RunOptions, Segment, provenance, run_world};
use mwb_core::keys::role;
use mwb_core::scene::{SceneError, SceneTemplate};
use mwb_node::{SegmentBody, WorkerKind, WorldTask, codec_quality};
use mwb_proto::v1::{Encoding, Job, JobKind, MotionSegment, Scene, WorldDone};
use std::ops::ControlFlow;
use zenoh::Session;

pub use mwb_node::cpu_time;

/// Sampler settings (the worker node's; every field's default is documented there).
pub type SamplerConfig = mwb_node::WorkerConfig;
/// A running sampler. Dropping it does not stop it; call `stop`.
pub type SamplerHandle = mwb_node::WorkerHandle;
/// Why a sampler could not start.
pub type SamplerError = mwb_node::NodeError;

/// Forward worlds: a job's scene is a validated template, a world one rapier3d run of it.
#[derive(Debug, Clone, Copy, Default)]
pub struct Forward;

impl WorkerKind for Forward {
    const ROLE: &'static str = role::SAMPLER;
    /// A forward world fails only when the scene cannot be built or encoded, which no other
    /// seed will mend.
    const GIVE_UP_AFTER: u32 = 1;
    type Scene = SceneTemplate;
    type SceneError = SceneError;
    type WorldError = RunError;

    fn takes(kind: JobKind) -> bool {
        kind != JobKind::Reverse
    }

    fn prepare(&self, job: &Job, scene: &Scene) -> Result<SceneTemplate, SceneError> {
        SceneTemplate::parse(&scene.toml, &format!("job {} scene", job.id))
    }

    fn run(
        &self,
        w: &WorldTask<'_>,
        template: &SceneTemplate,
        emit: &mut dyn FnMut(MotionSegment) -> ControlFlow<()>,
    ) -> Result<WorldDone, RunError> {
        let opts = RunOptions {
            quality: codec_quality(w.job.quality()),
            encoding: match w.job.encoding() {
                Encoding::QuantisedFramesV1 => PayloadEncoding::QuantisedFrames,
                Encoding::SplineV1 | Encoding::Unspecified => PayloadEncoding::Spline,
            },
            ..RunOptions::default()
        };
        let mut emit =
            |seg: Segment| emit(segment_message(&w.job.id, w.node, w.counter, w.seed, seg));
        let summary = run_world(template, w.seed, opts, &mut emit)?;
        Ok(world_done(&w.job.id, w.node, w.counter, &summary))
    }

    fn stopped(e: &RunError) -> bool {
        matches!(e, RunError::Stopped)
    }

    fn provenance(&self) -> String {
        provenance()
    }
}

/// Starts a sampler node on `session` (in the current tokio runtime).
pub async fn run_sampler(
    session: Session,
    cfg: SamplerConfig,
) -> Result<SamplerHandle, SamplerError> {
    mwb_node::run_workers(session, cfg, Forward).await
}

/// The wire summary of world `(job, node, counter)` (CPU time, provenance and scene hash are
/// the caller's to add).
pub fn world_done(
    job_id: &str,
    node: &str,
    counter: u64,
    summary: &crate::WorldSummary,
) -> WorldDone {
    WorldDone {
        job_id: job_id.to_owned(),
        node_id: node.to_owned(),
        world_counter: counter,
        seed: summary.seed,
        frame_count: summary.frame_count,
        segment_count: summary.segment_count,
        frame_dt: summary.frame_dt,
        rested: summary.rested,
        impacts: summary.impacts.clone(),
        rest_time_s: summary.rest_time_s.clone(),
        body_rested: summary.body_rested.clone(),
        perturbations: summary.perturbations,
        sim_steps: summary.steps,
        ..Default::default()
    }
}

/// The wire form of a recorded segment of world `(job, node, counter)`: the payload (codec or
/// quantised frames, as the job asked) with its CRC and, beside it, the low-resolution paths.
pub fn segment_message(
    job_id: &str,
    node: &str,
    counter: u64,
    seed: u64,
    seg: Segment,
) -> MotionSegment {
    let Segment {
        seq,
        first_frame,
        frame_count,
        body_count,
        payload,
        lowres,
        encoding,
    } = seg;
    let encoding = match encoding {
        PayloadEncoding::Spline => Encoding::SplineV1,
        PayloadEncoding::QuantisedFrames => Encoding::QuantisedFramesV1,
    };
    let body = SegmentBody {
        seq,
        first_frame,
        frame_count,
        body_count,
        encoding,
        payload,
        lowres,
    };
    mwb_node::segment_message(job_id, node, counter, seed, body)
}

#[cfg(test)]
mod tests {
    use super::*;
    use mwb_core::scene::builtin::TUMBLE;

    fn job(kind: JobKind, toml: &str) -> Job {
        Job {
            id: "j".into(),
            kind: kind as i32,
            scene: Some(Scene {
                toml: toml.into(),
                ..Default::default()
            }),
            target_worlds: 1,
            ..Default::default()
        }
    }

    #[test]
    fn sample_and_refine_jobs_are_ours_reverse_jobs_are_not() {
        assert!(Forward::takes(JobKind::Sample));
        assert!(Forward::takes(JobKind::Refine));
        assert!(Forward::takes(JobKind::Unspecified));
        assert!(!Forward::takes(JobKind::Reverse));
    }

    #[test]
    fn a_scene_that_does_not_validate_is_refused_naming_the_job() {
        let j = job(JobKind::Sample, "not = [valid");
        let err = Forward
            .prepare(&j, &j.scene.clone().unwrap_or_default())
            .err()
            .unwrap_or_else(|| panic!("an invalid scene was accepted"));
        assert!(err.to_string().contains("job j scene"), "{err}");
    }

    #[test]
    fn a_world_runs_to_its_summary_and_stops_when_emit_breaks() {
        let j = job(JobKind::Sample, TUMBLE);
        let scene = j.scene.clone().unwrap_or_default();
        let template = Forward
            .prepare(&j, &scene)
            .unwrap_or_else(|e| panic!("{e}"));
        let w = WorldTask {
            job: &j,
            node: "n",
            counter: 4,
            seed: 17,
        };
        let mut segs = Vec::new();
        let done = Forward
            .run(&w, &template, &mut |s| {
                segs.push(s);
                ControlFlow::Continue(())
            })
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(done.seed, 17);
        assert_eq!((done.job_id.as_str(), done.world_counter), ("j", 4));
        assert_eq!(done.segment_count as usize, segs.len());
        assert!(segs.iter().all(|s| s.node_id == "n" && s.seed == 17));
        assert!(matches!(
            Forward.run(&w, &template, &mut |_| ControlFlow::Break(())),
            Err(RunError::Stopped)
        ));
    }
}
