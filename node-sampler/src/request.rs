//! A refinement request (§4.5) turned into a REFINE job, without the bus: the stored world and
//! its job as the stores serve them, the bodies the animator picked and the box they drew. The
//! parent is regenerated here (pure computation, about one world's simulation) to find the
//! branch frame t_min, so that a request that cannot be done is refused before anything is
//! submitted, naming what is wrong. `mwb refine` and the viewer both use it.

use crate::edit::{BodyEdit, EditError, SceneDiff, body_changes, diff};
use crate::node::{LineageError, lineage_from_wire};
use crate::refine::{BranchAt, RefineError, regenerate};
use mwb_core::browse::api::SceneBodies;
use mwb_core::browse::{Frustum, ObjectsError, object_label, resolve_objects};
use mwb_core::scene::{SceneError, SceneTemplate};
use mwb_proto::v1::{Job, JobKind, Lineage, Refinement, Scene, World};

/// Requests that cannot be done.
#[derive(Debug, thiserror::Error)]
pub enum RequestError {
    #[error("world {world}: the store sent no summary")]
    NoSummary { world: u32 },
    #[error("world {world}: a backward world (job {job}); refinement re-simulates forward worlds")]
    Backward { world: u32, job: String },
    #[error("job {job}: announced without its scene")]
    NoScene { job: String },
    #[error(transparent)]
    Scene(#[from] SceneError),
    #[error(transparent)]
    Objects(#[from] ObjectsError),
    #[error(
        "the box: the centre of {objects} is never inside it in world {world}'s {frames} frames"
    )]
    NeverInside {
        objects: String,
        world: u32,
        frames: u32,
    },
    #[error("world {world}: {source}")]
    Regenerate {
        world: u32,
        #[source]
        source: RefineError,
    },
    #[error("world {world}: {source}")]
    Lineage {
        world: u32,
        #[source]
        source: LineageError,
    },
    #[error("world {world}: the edit: {source}")]
    Edit {
        world: u32,
        #[source]
        source: EditError,
    },
    #[error(
        "world {world}: this binary regenerates it with {ours} frames, the store holds {stored} \
         (made by {made_by:?}, this is {this:?}): refine it with the binary that sampled it"
    )]
    NotRegenerated {
        world: u32,
        ours: u32,
        stored: u32,
        made_by: String,
        this: String,
    },
}

/// A checked request: what a REFINE job needs.
#[derive(Debug, Clone, PartialEq)]
pub struct RefinePlan {
    pub parent_world: u32,
    pub parent_job: String,
    pub scene: Scene,
    pub lineage: Lineage,
    /// The picked bodies, as scene indices.
    pub objects: Vec<u32>,
    pub branch_frame: u32,
    /// The scene's frame time, seconds.
    pub frame_dt: f64,
    /// Encoding and quality of the parent's job, which the refined worlds keep.
    pub encoding: i32,
    pub quality: i32,
}

impl RefinePlan {
    /// The branch time, seconds.
    pub fn branch_time_s(&self) -> f64 {
        f64::from(self.branch_frame) * self.frame_dt
    }

    /// The REFINE job for `worlds` children.
    pub fn job(&self, id: String, worlds: u32, priority: i32, created_unix_ms: u64) -> Job {
        Job {
            id,
            scene: Some(self.scene.clone()),
            target_worlds: worlds,
            priority,
            created_unix_ms,
            encoding: self.encoding,
            quality: self.quality,
            refine: Some(Refinement {
                parent_job: self.parent_job.clone(),
                parent_world: self.parent_world,
                parent: Some(self.lineage.clone()),
                objects: self.objects.clone(),
                branch_frame: self.branch_frame,
                parent_scene: None,
            }),
            ..refine_job()
        }
    }
}

/// What a request needs of the stored world it starts from.
struct Stored<'w> {
    index: u32,
    done: &'w mwb_proto::v1::WorldDone,
    scene: Scene,
    template: SceneTemplate,
    lineage: Lineage,
    /// `lineage` as this binary regenerates it (refused when it holds a scene edit).
    wire_lineage: crate::refine::Lineage,
}

/// Stored world `world` of job `parent_job` as a parent: a forward world, its job's scene, its
/// lineage (a root world's is its job and seed).
fn stored<'w>(world: &'w World, parent_job: &Job) -> Result<Stored<'w>, RequestError> {
    let index = world.index;
    let done = world
        .done
        .as_ref()
        .ok_or(RequestError::NoSummary { world: index })?;
    if parent_job.kind() == JobKind::Reverse || done.energy_growth.is_some() {
        return Err(RequestError::Backward {
            world: index,
            job: parent_job.id.clone(),
        });
    }
    let scene = parent_job
        .scene
        .clone()
        .ok_or_else(|| RequestError::NoScene {
            job: parent_job.id.clone(),
        })?;
    let template = SceneTemplate::parse(&scene.toml, &format!("job {} scene", parent_job.id))?;
    let lineage = done.lineage.clone().unwrap_or_else(|| Lineage {
        root_job: world.job_id.clone(),
        root_seed: done.seed,
        steps: Vec::new(),
    });
    let wire_lineage = lineage_from_wire(&lineage).map_err(|source| RequestError::Lineage {
        world: index,
        source,
    })?;
    Ok(Stored {
        index,
        done,
        scene,
        template,
        lineage,
        wire_lineage,
    })
}

/// Checks a request against stored world `world` (as fetched, `q/world/<i>`) of job
/// `parent_job` (as served, `q/job/<job>`): resolves `objects` (indices or names) in its scene,
/// regenerates it and finds the first frame any picked body's centre is inside `frustum`.
pub fn plan(
    world: &World,
    parent_job: &Job,
    objects: &str,
    frustum: Frustum,
) -> Result<RefinePlan, RequestError> {
    let Stored {
        index,
        done,
        scene,
        template,
        lineage,
        wire_lineage,
    } = stored(world, parent_job)?;
    let instance = template.instantiate(lineage.root_seed);
    let names: Vec<String> = instance.bodies.iter().map(|b| b.name.clone()).collect();
    let objects = resolve_objects(
        objects,
        &[SceneBodies {
            objects: names.len() as u32,
            names: names.clone(),
            worlds: 1,
        }],
    )?;
    let at = BranchAt::FirstInside {
        objects: objects.clone(),
        frustum: Box::new(frustum),
    };
    let parent = regenerate(&template, &wire_lineage, &at).map_err(|e| match e {
        RefineError::NeverInside { frames, .. } => RequestError::NeverInside {
            objects: objects
                .iter()
                .map(|&o| object_label(&names, o))
                .collect::<Vec<_>>()
                .join(", "),
            world: index,
            frames,
        },
        source => RequestError::Regenerate {
            world: index,
            source,
        },
    })?;
    same_world(index, done, parent.motion().frame_count())?;
    Ok(RefinePlan {
        parent_world: index,
        parent_job: world.job_id.clone(),
        scene,
        lineage,
        objects,
        branch_frame: parent.branch_frame(),
        frame_dt: instance.settings.dt,
        encoding: parent_job.encoding,
        quality: parent_job.quality,
    })
}

/// What every REFINE job (refinement or scene edit) announces the same way: its first revision,
/// not cancelled.
fn refine_job() -> Job {
    Job {
        revision: 1,
        kind: JobKind::Refine as i32,
        cancelled: false,
        ..Job::default()
    }
}

/// A parent this binary regenerated to `ours` frames is the stored one (`done`).
fn same_world(index: u32, done: &mwb_proto::v1::WorldDone, ours: u32) -> Result<(), RequestError> {
    if ours != done.frame_count {
        return Err(RequestError::NotRegenerated {
            world: index,
            ours,
            stored: done.frame_count,
            made_by: done.provenance.clone(),
            this: crate::provenance(),
        });
    }
    Ok(())
}

/// A checked scene edit of one stored world: what its REFINE job (with the parent's scene)
/// needs.
#[derive(Debug, Clone)]
pub struct EditPlan {
    pub parent_world: u32,
    pub parent_job: String,
    /// The parent's own (root) scene, which regenerates it.
    pub parent_scene: Scene,
    pub lineage: Lineage,
    /// The edited scene's text.
    pub toml: String,
    pub name: String,
    /// How the edited scene's bodies match the parent's.
    pub diff: SceneDiff,
    /// Per body of the edited scene: its name and, for a modified one, what changed.
    pub bodies: Vec<(String, BodyEdit, Vec<&'static str>)>,
    /// Names of the parent's bodies the edit removes.
    pub removed: Vec<String>,
    pub encoding: i32,
    pub quality: i32,
}

impl EditPlan {
    /// The edited scene as revision `revision`.
    pub fn scene(&self, revision: u64) -> Scene {
        Scene {
            revision,
            name: self.name.clone(),
            toml: self.toml.clone(),
            content_hash: mwb_core::content_hash(&self.toml),
        }
    }

    /// The scene-edit job for `worlds` children, of the edited scene's revision `revision`.
    pub fn job(
        &self,
        id: String,
        revision: u64,
        worlds: u32,
        priority: i32,
        created_unix_ms: u64,
    ) -> Job {
        Job {
            id,
            scene: Some(self.scene(revision)),
            target_worlds: worlds,
            priority,
            created_unix_ms,
            encoding: self.encoding,
            quality: self.quality,
            refine: Some(Refinement {
                parent_job: self.parent_job.clone(),
                parent_world: self.parent_world,
                parent: Some(self.lineage.clone()),
                objects: Vec::new(),
                branch_frame: 0,
                parent_scene: Some(self.parent_scene.clone()),
            }),
            ..refine_job()
        }
    }
}

/// Checks a scene edit of stored world `world` (as fetched) of job `parent_job` (as served):
/// the edited scene `toml` (named `file` in errors) parses, the world regenerates, and the
/// edit is one of its bodies only (`edit::diff`: statics, settings and joints refused by name).
pub fn plan_edit(
    world: &World,
    parent_job: &Job,
    toml: &str,
    file: &str,
) -> Result<EditPlan, RequestError> {
    let Stored {
        index,
        done,
        scene,
        template,
        lineage,
        wire_lineage,
    } = stored(world, parent_job)?;
    let edited = SceneTemplate::parse(toml, file)?;
    let parent = regenerate(&template, &wire_lineage, &BranchAt::Frame(0)).map_err(|source| {
        RequestError::Regenerate {
            world: index,
            source,
        }
    })?;
    same_world(index, done, parent.motion().frame_count())?;
    let old = parent.scene();
    let new = edited.instantiate_edit(lineage.root_seed, &template, old);
    let diff = diff(old, &new).map_err(|source| RequestError::Edit {
        world: index,
        source,
    })?;
    let bodies = new
        .bodies
        .iter()
        .zip(&diff.bodies)
        .map(|(b, e)| {
            let changed = match *e {
                BodyEdit::Modified(j) => body_changes(old, &old.bodies[j], &new, b),
                BodyEdit::Same(_) | BodyEdit::Added => Vec::new(),
            };
            (b.name.clone(), *e, changed)
        })
        .collect();
    let removed = diff
        .removed
        .iter()
        .map(|&j| old.bodies[j].name.clone())
        .collect();
    Ok(EditPlan {
        parent_world: index,
        parent_job: world.job_id.clone(),
        parent_scene: scene,
        lineage,
        toml: toml.to_owned(),
        name: new.name.clone(),
        diff,
        bodies,
        removed,
        encoding: parent_job.encoding,
        quality: parent_job.quality,
    })
}
