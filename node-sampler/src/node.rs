//! The sampler node (§4.2 "opportunistic computing"): a [`mwb_node`] worker node whose worlds
//! are forward rapier3d runs ([`run_world`]). It takes sample and refine jobs (reverse jobs
//! belong to reverse nodes); joining, leaving, the job board and the publisher are the
//! skeleton's.

use crate::refine::{Branch, BranchAt, Lineage, Parent, RefineError, regenerate};
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

/// A job as a sampler runs it: the validated scene, and for a REFINE job its parent world
/// regenerated once and forked at the branch frame (every child of the job starts from it), or
/// for a scene edit the parent regenerated and matched to the edited scene.
pub struct Prepared {
    pub template: SceneTemplate,
    pub refine: Option<RefineJob>,
    pub edit: Option<EditJob>,
}

/// What the worlds of a scene-edit job (a REFINE job with `parent_scene`) share: the parent
/// regenerated exactly in its own scene, the edited scene instantiated as the parent's root was,
/// and how their bodies match.
pub struct EditJob {
    pub parent: Parent,
    pub scene: mwb_core::scene::Scene,
    pub diff: crate::edit::SceneDiff,
    pub root_job: String,
    pub revision: u64,
}

/// What a REFINE job's worlds share.
pub struct RefineJob {
    pub parent: Parent,
    pub objects: Vec<u32>,
    pub root_job: String,
}

/// Why a sampler cannot run a job.
#[derive(Debug, thiserror::Error)]
pub enum PrepareError {
    #[error(transparent)]
    Scene(#[from] SceneError),
    #[error("job {job}: a REFINE job without its `refine` (parent, objects, branch frame)")]
    NoRefinement { job: String },
    #[error("job {job}: parent world {world}: {source}")]
    Refine {
        job: String,
        world: u32,
        #[source]
        source: RefineError,
    },
    #[error("job {job}: parent world {world}: {source}")]
    Lineage {
        job: String,
        world: u32,
        #[source]
        source: LineageError,
    },
    #[error("job {job}: editing parent world {world}: {source}")]
    Edit {
        job: String,
        world: u32,
        #[source]
        source: crate::edit::EditError,
    },
}

/// Lineages this binary cannot regenerate.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum LineageError {
    #[error(
        "lineage step {step} is a scene edit (revision {revision}): a world made by a scene edit \
         cannot be regenerated, refined or edited again yet"
    )]
    Edited { step: usize, revision: u64 },
}

/// Why one world failed.
#[derive(Debug, thiserror::Error)]
pub enum WorldError {
    #[error(transparent)]
    Run(#[from] RunError),
    #[error(transparent)]
    Refine(#[from] RefineError),
    #[error(transparent)]
    Edit(#[from] crate::edit::EditError),
}

/// A lineage from the wire (the root job's name is kept apart). A scene-edit step is refused:
/// regenerating an edited world would need the edited revision's text.
pub fn lineage_from_wire(l: &mwb_proto::v1::Lineage) -> Result<Lineage, LineageError> {
    let steps = l
        .steps
        .iter()
        .enumerate()
        .map(|(step, s)| {
            if s.scene_revision != 0 {
                return Err(LineageError::Edited {
                    step,
                    revision: s.scene_revision,
                });
            }
            Ok(Branch {
                frame: s.frame,
                objects: s.objects.clone(),
                seed: s.seed,
                kicks: Vec::new(),
            })
        })
        .collect::<Result<_, _>>()?;
    Ok(Lineage {
        root_seed: l.root_seed,
        steps,
    })
}

/// A lineage on the wire.
pub fn lineage_to_wire(root_job: &str, l: &Lineage) -> mwb_proto::v1::Lineage {
    mwb_proto::v1::Lineage {
        root_job: root_job.to_owned(),
        root_seed: l.root_seed,
        steps: l
            .steps
            .iter()
            .map(|s| mwb_proto::v1::RefineStep {
                frame: s.frame,
                objects: s.objects.clone(),
                seed: s.seed,
                scene_revision: 0,
            })
            .collect(),
    }
}

impl WorkerKind for Forward {
    const ROLE: &'static str = role::SAMPLER;
    /// A forward world fails only when the scene cannot be built or encoded, which no other
    /// seed will mend.
    const GIVE_UP_AFTER: u32 = 1;
    type Scene = Prepared;
    type SceneError = PrepareError;
    type WorldError = WorldError;

    fn takes(kind: JobKind) -> bool {
        kind != JobKind::Reverse
    }

    /// Parses the scene; for a REFINE job also regenerates the parent world from its lineage
    /// and forks it at the branch frame (§4.5), once for all the job's worlds; for a scene edit
    /// (a REFINE job with the parent's own scene) regenerates the parent in its scene and matches
    /// its bodies to the job's, the edited one.
    fn prepare(&self, job: &Job, scene: &Scene) -> Result<Prepared, PrepareError> {
        let template = SceneTemplate::parse(&scene.toml, &format!("job {} scene", job.id))?;
        if job.kind() != JobKind::Refine {
            return Ok(Prepared {
                template,
                refine: None,
                edit: None,
            });
        }
        let Some(r) = job.refine.as_ref() else {
            return Err(PrepareError::NoRefinement {
                job: job.id.clone(),
            });
        };
        let (id, world) = (job.id.clone(), r.parent_world);
        let lineage = match &r.parent {
            Some(l) => lineage_from_wire(l).map_err(|source| PrepareError::Lineage {
                job: id.clone(),
                world,
                source,
            })?,
            None => Lineage::default(),
        };
        let refine_err = |source| PrepareError::Refine {
            job: id.clone(),
            world,
            source,
        };
        let root_job = r
            .parent
            .as_ref()
            .map_or_else(|| r.parent_job.clone(), |l| l.root_job.clone());
        if let Some(parent_scene) = &r.parent_scene {
            let old =
                SceneTemplate::parse(&parent_scene.toml, &format!("job {} parent scene", job.id))?;
            let parent = regenerate(&old, &lineage, &BranchAt::Frame(0)).map_err(refine_err)?;
            let edited = template.instantiate_edit(lineage.root_seed, &old, parent.scene());
            let diff = crate::edit::diff(parent.scene(), &edited).map_err(|source| {
                PrepareError::Edit {
                    job: id.clone(),
                    world,
                    source,
                }
            })?;
            return Ok(Prepared {
                template,
                refine: None,
                edit: Some(EditJob {
                    parent,
                    scene: edited,
                    diff,
                    root_job,
                    revision: scene.revision,
                }),
            });
        }
        let parent = regenerate(&template, &lineage, &BranchAt::Frame(r.branch_frame))
            .map_err(refine_err)?;
        Ok(Prepared {
            template,
            refine: Some(RefineJob {
                parent,
                objects: r.objects.clone(),
                root_job,
            }),
            edit: None,
        })
    }

    fn run(
        &self,
        w: &WorldTask<'_>,
        prepared: &Prepared,
        emit: &mut dyn FnMut(MotionSegment) -> ControlFlow<()>,
    ) -> Result<WorldDone, WorldError> {
        let opts = RunOptions {
            quality: codec_quality(w.job.quality()),
            encoding: match w.job.encoding() {
                Encoding::QuantisedFramesV1 => PayloadEncoding::QuantisedFrames,
                Encoding::SplineV1 | Encoding::Unspecified => PayloadEncoding::Spline,
            },
            ..RunOptions::default()
        };
        // A world sent whole goes with its index (built from the segments as sent); a refined
        // difference does not (its store composes it with the parent first).
        let whole = prepared.refine.is_none();
        let mut sent = Vec::new();
        let mut emit = |seg: Segment| {
            let msg = segment_message(&w.job.id, w.node, w.counter, w.seed, seg);
            if whole {
                sent.push(msg.clone());
            }
            emit(msg)
        };
        if let Some(e) = &prepared.edit {
            // Recorded whole, as a world of the edited scene.
            let child =
                crate::edit::edit_child(&e.parent, &e.scene, &e.diff, w.seed, opts, &mut emit)?;
            let mut done = edited_done(&w.job.id, w.node, w.counter, e, &child);
            attach_index(&mut done, &sent, &prepared.template);
            return Ok(done);
        }
        let Some(r) = &prepared.refine else {
            let summary = run_world(&prepared.template, w.seed, opts, &mut emit)?;
            let mut done = world_done(&w.job.id, w.node, w.counter, &summary);
            attach_index(&mut done, &sent, &prepared.template);
            return Ok(done);
        };
        // Only what is new: the segments from the one holding the branch frame, each with the
        // bodies re-simulated by then. The store composes the rest from the parent it holds.
        let child = r.parent.refine(&r.objects, w.seed, opts, &mut emit)?;
        Ok(refined_done(
            &w.job.id,
            w.node,
            w.counter,
            &r.root_job,
            &child,
        ))
    }

    fn stopped(e: &WorldError) -> bool {
        matches!(
            e,
            WorldError::Run(RunError::Stopped)
                | WorldError::Refine(crate::refine::RefineError::Run(RunError::Stopped))
        )
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

/// Attaches to `done` the browsing index of the whole world it sums up (`segments`: every one
/// sent, in order), built exactly as a store would build it from them
/// ([`mwb_index::index_motion`], the store's path tolerance and `template`'s rest thresholds),
/// so that the store only checks and inserts it. Indexing costs the sampler about what one
/// decode of the world costs; a store could otherwise index only ~1 400 tumble worlds a second
/// on two cores. A world that cannot be indexed goes without (its store will say why).
pub fn attach_index(done: &mut WorldDone, segments: &[MotionSegment], template: &SceneTemplate) {
    let tolerance = mwb_index::DEFAULT_PATH_TOLERANCE_M;
    let rest = mwb_core::browse::RestThresholds::from(template.settings());
    match mwb_index::index_motion(done, segments, 0, std::sync::Arc::from(""), rest, tolerance) {
        Ok(indexed) => done.index = Some(indexed.to_wire(tolerance)),
        Err(e) => tracing::debug!(error = %e, "world sent without its index"),
    }
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
        sim: summary.sim.clone(),
        ..Default::default()
    }
}

/// The wire summary of refined world `(job, node, counter)` (§4.5): its lineage, from which
/// frame each body's motion is new, and the first segment it sent.
pub fn refined_done(
    job_id: &str,
    node: &str,
    counter: u64,
    root_job: &str,
    child: &crate::refine::RefinedWorld,
) -> WorldDone {
    WorldDone {
        lineage: Some(lineage_to_wire(root_job, &child.lineage)),
        active_from: child
            .active_from
            .iter()
            .map(|a| a.map_or(-1, i64::from))
            .collect(),
        first_segment: child.first_segment,
        ..world_done(job_id, node, counter, &child.summary)
    }
}

/// The wire summary of world `(job, node, counter)` of a scene-edit job: its lineage is the
/// parent's and one step more, the edit (frame 0, the edited revision, this world's seed).
pub fn edited_done(
    job_id: &str,
    node: &str,
    counter: u64,
    edit: &EditJob,
    child: &crate::edit::EditedWorld,
) -> WorldDone {
    let mut lineage = lineage_to_wire(&edit.root_job, &child.parent);
    lineage.steps.push(mwb_proto::v1::RefineStep {
        frame: 0,
        objects: Vec::new(),
        seed: child.summary.seed,
        scene_revision: edit.revision.max(1),
    });
    WorldDone {
        lineage: Some(lineage),
        active_from: child
            .active_from
            .iter()
            .map(|a| a.map_or(-1, i64::from))
            .collect(),
        ..world_done(job_id, node, counter, &child.summary)
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
        bodies,
        payload,
        encoding,
    } = seg;
    let encoding = match encoding {
        PayloadEncoding::Spline => Encoding::SplineV1,
        PayloadEncoding::QuantisedFrames => Encoding::QuantisedFramesV1,
    };
    let body = SegmentBody {
        bodies,
        seq,
        first_frame,
        frame_count,
        body_count,
        encoding,
        payload,
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

    /// A scene-edit job (REFINE with the parent's scene): its worlds are whole worlds of the
    /// edited scene whose lineage ends with the edit; an edit of a static is refused when the
    /// job is prepared, naming it; a lineage holding an edit cannot be regenerated.
    #[test]
    fn a_scene_edit_job_makes_whole_worlds_of_the_edited_scene() {
        let added = format!(
            "{TUMBLE}\n[[body]]\nname = \"ball\"\nshape = \"sphere\"\nradius = 0.1\n\
             material = \"wood\"\nposition = [9, 1, 9]\n"
        );
        let mut j = job(JobKind::Refine, &added);
        if let Some(s) = j.scene.as_mut() {
            s.revision = 4;
        }
        j.refine = Some(mwb_proto::v1::Refinement {
            parent_job: "root".into(),
            parent_world: 3,
            parent: Some(mwb_proto::v1::Lineage {
                root_job: "root".into(),
                root_seed: 5,
                steps: Vec::new(),
            }),
            parent_scene: Some(Scene {
                toml: TUMBLE.into(),
                ..Default::default()
            }),
            ..Default::default()
        });
        let (segs, done) = run_one(&j, 0, 77);
        let lineage = done.lineage.clone().unwrap_or_default();
        let last = lineage.steps.last().cloned().unwrap_or_default();
        assert_eq!((last.frame, last.seed, last.scene_revision), (0, 77, 4));
        assert_eq!(done.active_from, vec![-1, -1, -1, -1, -1, 0]);
        assert_eq!(done.first_segment, 0);
        assert!(
            segs.iter()
                .all(|s| s.bodies.is_empty() && s.body_count == 6)
        );
        assert_eq!(
            lineage_from_wire(&lineage),
            Err(LineageError::Edited {
                step: 0,
                revision: 4
            })
        );
        // The ground moved: not an edit of bodies.
        let moved = TUMBLE.replacen("[[static]]", "[[static]]\nposition = [0, -0.5, 0]", 1);
        let mut k = job(JobKind::Refine, &moved);
        k.refine = j.refine.clone();
        let err = Forward
            .prepare(&k, &k.scene.clone().unwrap_or_default())
            .err()
            .map(|e| e.to_string());
        assert!(
            err.as_deref()
                .is_some_and(|e| e.contains("statics: `ground` changed")),
            "{err:?}"
        );
    }

    /// Prepares job `j` and runs its world `seed` (counter `counter`): the segments and summary.
    fn run_one(j: &Job, counter: u64, seed: u64) -> (Vec<MotionSegment>, WorldDone) {
        let scene = j.scene.clone().unwrap_or_default();
        let prepared = Forward.prepare(j, &scene).unwrap_or_else(|e| panic!("{e}"));
        let w = WorldTask {
            job: j,
            node: "n",
            counter,
            seed,
        };
        let mut segs = Vec::new();
        let done = Forward
            .run(&w, &prepared, &mut |s| {
                segs.push(s);
                ControlFlow::Continue(())
            })
            .unwrap_or_else(|e| panic!("{e}"));
        (segs, done)
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
    fn a_refine_job_regenerates_its_parent_once_and_its_worlds_carry_their_lineage() {
        let mut j = job(JobKind::Refine, TUMBLE);
        let scene = j.scene.clone().unwrap_or_default();
        let err = Forward.prepare(&j, &scene).err().map(|e| e.to_string());
        assert!(
            err.as_deref()
                .is_some_and(|e| e.contains("without its `refine`")),
            "{err:?}"
        );
        j.refine = Some(mwb_proto::v1::Refinement {
            parent_job: "root".into(),
            parent_world: 3,
            parent: Some(mwb_proto::v1::Lineage {
                root_job: "root".into(),
                root_seed: 5,
                steps: Vec::new(),
            }),
            objects: vec![1],
            branch_frame: 30,
            parent_scene: None,
        });
        let (segs, done) = run_one(&j, 0, 99);
        let lineage = done.lineage.clone().unwrap_or_default();
        assert_eq!((lineage.root_job.as_str(), lineage.root_seed), ("root", 5));
        assert_eq!(lineage.steps.len(), 1);
        assert_eq!((lineage.steps[0].frame, lineage.steps[0].seed), (30, 99));
        assert_eq!(done.active_from[1], 30);
        // Only what is new: from the segment holding the branch frame (frame 30 is in segment 0
        // of 120 frames), the bodies re-simulated by then, each listed.
        assert_eq!((done.first_segment, segs[0].first_frame), (0, 0));
        assert!(segs.iter().all(|s| s.bodies.contains(&1)
            && s.bodies.len() < 5
            && s.body_count as usize == s.bodies.len()));
        assert_eq!(done.segment_count as usize, segs.len());
        // A parent frame past its end is refused when the job is prepared.
        if let Some(r) = j.refine.as_mut() {
            r.branch_frame = 1_000_000;
        }
        let err = Forward.prepare(&j, &scene).err().map(|e| e.to_string());
        assert!(
            err.as_deref()
                .is_some_and(|e| e.contains("parent world 3: frame: 1000000")),
            "{err:?}"
        );
    }

    #[test]
    fn a_world_runs_to_its_summary_and_stops_when_emit_breaks() {
        let j = job(JobKind::Sample, TUMBLE);
        let (segs, done) = run_one(&j, 4, 17);
        assert_eq!(done.seed, 17);
        assert_eq!((done.job_id.as_str(), done.world_counter), ("j", 4));
        assert_eq!(done.segment_count as usize, segs.len());
        assert!(segs.iter().all(|s| s.node_id == "n" && s.seed == 17));
        let template = Forward
            .prepare(&j, &j.scene.clone().unwrap_or_default())
            .unwrap_or_else(|e| panic!("{e}"));
        let w = WorldTask {
            job: &j,
            node: "n",
            counter: 4,
            seed: 17,
        };
        assert!(matches!(
            Forward.run(&w, &template, &mut |_| ControlFlow::Break(())),
            Err(WorldError::Run(RunError::Stopped))
        ));
    }
}
