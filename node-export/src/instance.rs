//! Which scene instance a stored world was simulated in.

use mwb_core::scene::{Scene, SceneError, SceneTemplate};
use mwb_proto::v1::{Job, WorldDone};

/// The instance of `template` (its job's scene) that stored world `done` was simulated in: the
/// instance of the world's root seed (a refined world's seed is its own, its scene its root's:
/// Twigg and James, SIGGRAPH 2007, §4.5), and for a world of a scene-edit job (`job`'s
/// `refine.parent_scene`) the edited scene instantiated as an edit of the parent's instance
/// ([`SceneTemplate::instantiate_edit`]: unchanged bodies keep the parent's draws).
pub fn world_instance(
    template: &SceneTemplate,
    job: Option<&Job>,
    done: &WorldDone,
) -> Result<Scene, SceneError> {
    let seed = done.lineage.as_ref().map_or(done.seed, |l| l.root_seed);
    match job.and_then(|j| j.refine.as_ref()?.parent_scene.as_ref().map(|s| (j, s))) {
        Some((job, parent)) => {
            let before =
                SceneTemplate::parse(&parent.toml, &format!("job {} parent scene", job.id))?;
            Ok(template.instantiate_edit(seed, &before, &before.instantiate(seed)))
        }
        None => Ok(template.instantiate(seed)),
    }
}
