//! `mwb scene edit`: an edit of a scene's bodies applied to worlds kept so far (§4.5 from frame
//! 0). The edited scene becomes a new revision on `scene/<rev>` (the stores keep every revision);
//! each named world gets a scene-edit job whose worlds are its children: the bodies the edit does
//! not reach replay the world's exact motion, added and changed bodies are simulated, removed
//! and changed ones leave a ghost that frees what their old motion touched.
//!
//! Everything that can be wrong is found before anything is published: an unknown world, a
//! revision no store has, a body the scene lacks, an edit of statics, settings or joints (which
//! reach bodies the edit cannot see: a new job is the honest answer), a world made by an edit.

use crate::bus::BusArgs;
use crate::client;
use crate::output::Summary;
use anyhow::{Result, anyhow, bail};
use mwb_core::keys::{Keys, SceneRev};
use mwb_core::scene::edit_text::{self, TextEdit};
use mwb_proto::v1::{Message, Scene};
use mwb_sampler::edit::BodyEdit;
use mwb_sampler::request::{EditPlan, RequestError, plan_edit};
use std::time::Duration;
use zenoh::qos::CongestionControl;

/// Arguments of `mwb scene edit`.
#[derive(Debug, Clone, clap::Args)]
pub struct EditArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// The stored worlds to edit (global indices), each getting its own children:
    /// `--world 3 --world 17` or `--world 3,17`.
    #[arg(long, required = true, value_delimiter = ',')]
    pub world: Vec<u32>,
    /// The edited scene as a whole revision file (or shipped scene name).
    #[arg(long, conflicts_with_all = ["revision", "remove", "add_body", "set"])]
    pub file: Option<String>,
    /// Apply a revision already published (`scene/<rev>`) instead of a new one.
    #[arg(long, conflicts_with_all = ["remove", "add_body", "set"])]
    pub revision: Option<u64>,
    /// Remove a body (by name).
    #[arg(long)]
    pub remove: Vec<String>,
    /// Add a body: a TOML inline table, e.g. `{ name = "ball", shape = "sphere", radius = 0.1,
    /// material = "wood", position = [0, 2, 0] }`.
    #[arg(long)]
    pub add_body: Vec<String>,
    /// Change a body's field: `BODY.FIELD=VALUE` (a TOML value), e.g. `crate.position=[0,1,0]`.
    #[arg(long)]
    pub set: Vec<String>,
    /// Children per edited world.
    #[arg(long, default_value_t = 10)]
    pub worlds: u32,
    /// Job id (one world), or its prefix (`<id>-w<world>`) [default: edit-r<rev>-w<world>-<time>].
    #[arg(long)]
    pub id: Option<String>,
    #[command(flatten)]
    pub follow: client::FollowArgs,
}

/// What `mwb scene edit` did.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Edited {
    /// The edited scene's revision (`scene/<rev>`).
    pub revision: u64,
    /// Whether this command published it (false: `--revision`, or the same text was there).
    pub published: bool,
    pub scene: String,
    pub added: Vec<String>,
    pub removed: Vec<String>,
    /// Changed bodies, each with the fields that changed.
    pub modified: Vec<(String, Vec<&'static str>)>,
    pub jobs: Vec<EditJob>,
}

/// One edited world's job.
#[derive(Debug, Clone, serde::Serialize)]
pub struct EditJob {
    pub job: String,
    pub parent_world: u32,
    pub target: u32,
    pub done: u32,
    pub closed: bool,
}

impl Summary for Edited {
    fn table(&self) -> String {
        let list = |v: &[String]| {
            if v.is_empty() {
                "none".to_owned()
            } else {
                v.join(", ")
            }
        };
        let modified: Vec<String> = self
            .modified
            .iter()
            .map(|(name, fields)| format!("{name} ({})", fields.join(", ")))
            .collect();
        let mut t = format!(
            "scene {:?} revision {}{}: added {}; removed {}; changed {}\n",
            self.scene,
            self.revision,
            if self.published { " (published)" } else { "" },
            list(&self.added),
            list(&self.removed),
            list(&modified)
        );
        for j in &self.jobs {
            t += &format!(
                "job {}: {}/{} worlds edited from world {}{}\n",
                j.job,
                j.done,
                j.target,
                j.parent_world,
                if j.closed { ", closed" } else { "" }
            );
        }
        t
    }
}

/// Runs `mwb scene edit`.
pub async fn run(args: EditArgs) -> Result<()> {
    let keys = Keys::new(&args.bus.space)?;
    if args.worlds == 0 {
        bail!("--worlds: at least 1");
    }
    let edits = text_edits(&args)?;
    if args.file.is_none() && args.revision.is_none() && edits.is_empty() {
        bail!("no edit: give --file, --revision, --remove, --add-body or --set");
    }
    let session = args.bus.open(args.bus.client_default()).await?;
    let result = edit(&session, &keys, &args, &edits).await;
    crate::bus::close(session).await;
    crate::output::print(&result?, args.follow.json)
}

/// The text edits of `--remove`, `--add-body`, `--set`, in that order.
fn text_edits(args: &EditArgs) -> Result<Vec<TextEdit>> {
    let mut out = Vec::new();
    for b in &args.remove {
        out.push(TextEdit::parse_remove(b)?);
    }
    for t in &args.add_body {
        out.push(TextEdit::parse_add(t)?);
    }
    for s in &args.set {
        out.push(TextEdit::parse_set(s)?);
    }
    Ok(out)
}

async fn edit(
    session: &zenoh::Session,
    keys: &Keys,
    args: &EditArgs,
    edits: &[TextEdit],
) -> Result<Edited> {
    client::wait_for_store(session, keys, Duration::from_secs(10)).await?;
    // The edited text: a revision the stores have, a file, or the first world's scene edited.
    let given = match (&args.revision, &args.file) {
        (Some(rev), _) => {
            let s = client::fetch_scene(session, keys, SceneRev::Number(*rev))
                .await?
                .ok_or_else(|| anyhow!("--revision {rev}: no store has it"))?;
            Some((format!("scene revision {rev}"), s.toml))
        }
        (None, Some(file)) => Some(client::load_scene(file)?),
        (None, None) => None,
    };
    let mut plans: Vec<EditPlan> = Vec::new();
    let mut root_scene: Option<(u64, u32)> = None;
    for &index in &args.world {
        let flag = format!("--world {index}");
        let world = client::fetch_world(session, keys, index)
            .await?
            .ok_or_else(|| anyhow!("{flag}: no store holds it"))?;
        let job = client::held_job(session, keys, &world.job_id)
            .await?
            .ok_or_else(|| {
                anyhow!(
                    "{flag}: no store serves its job {:?} (its scene is needed)",
                    world.job_id
                )
            })?;
        let parent_scene = job.scene.clone().unwrap_or_default();
        let hash = mwb_core::content_hash(&parent_scene.toml);
        match root_scene {
            Some((h, first)) if h != hash => bail!(
                "{flag}: its scene is not world {first}'s: edit worlds of one scene at a time"
            ),
            _ => root_scene = Some((hash, index)),
        }
        let (file, text) = match &given {
            Some(g) => g.clone(),
            None => {
                let file = format!("scene of job {}", world.job_id);
                let text = edit_text::apply(&parent_scene.toml, &file, edits)?;
                (file, text)
            }
        };
        // One regeneration of the world, off the async threads.
        let plan = tokio::task::spawn_blocking(move || plan_edit(&world, &job, &text, &file))
            .await?
            .map_err(|e| match e {
                // These start with "world N": the flag that named it.
                RequestError::NoSummary { .. }
                | RequestError::Backward { .. }
                | RequestError::Regenerate { .. }
                | RequestError::NotRegenerated { .. }
                | RequestError::Lineage { .. }
                | RequestError::Edit { .. } => anyhow!("--{e}"),
                e => anyhow!("{e}"),
            })?;
        plans.push(plan);
    }
    let Some(first) = plans.first() else {
        bail!("--world: none given");
    };
    let (revision, published) = match args.revision {
        Some(rev) => (rev, false),
        None => publish(session, keys, &first.scene(0)).await?,
    };
    let stamp = client::unix_ms();
    let mut jobs = Vec::new();
    for plan in &plans {
        let id = match (&args.id, plans.len()) {
            (Some(id), 1) => id.clone(),
            (Some(id), _) => format!("{id}-w{}", plan.parent_world),
            (None, _) => format!("edit-r{revision}-w{}-{stamp:x}", plan.parent_world),
        };
        mwb_core::keys::check_identifier("job id", &id)?;
        let job = plan.job(
            id.clone(),
            revision,
            args.worlds,
            args.follow.priority,
            stamp,
        );
        let state = client::submit_job(session, keys, &job).await?;
        if !args.follow.json {
            eprintln!(
                "submitted job {id}: {} worlds editing world {} (scene revision {revision})",
                args.worlds, plan.parent_world
            );
        }
        jobs.push((id, plan.parent_world, state));
    }
    let mut out = Vec::new();
    for (id, parent_world, mut state) in jobs {
        if args.follow.wait {
            state = client::wait_job(
                session,
                keys,
                &id,
                args.follow.timeout.map(Duration::from_secs),
                |_| {},
            )
            .await?;
        }
        out.push(EditJob {
            job: id,
            parent_world,
            target: args.worlds,
            done: state.worlds_done,
            closed: state.closed,
        });
    }
    let names = |pick: fn(&BodyEdit) -> bool| -> Vec<String> {
        first
            .bodies
            .iter()
            .filter(|(_, e, _)| pick(e))
            .map(|(n, _, _)| n.clone())
            .collect()
    };
    Ok(Edited {
        revision,
        published,
        scene: first.name.clone(),
        added: names(|e| matches!(e, BodyEdit::Added)),
        removed: first.removed.clone(),
        modified: first
            .bodies
            .iter()
            .filter(|(_, e, _)| matches!(e, BodyEdit::Modified(_)))
            .map(|(n, _, c)| (n.clone(), c.clone()))
            .collect(),
        jobs: out,
    })
}

/// Publishes `scene` as the next revision (`scene/<latest + 1>`) and returns it once a store
/// holds it; another client's revision under that number moves ours to the next one. The same
/// text as the latest revision is not published again.
async fn publish(session: &zenoh::Session, keys: &Keys, scene: &Scene) -> Result<(u64, bool)> {
    let hash = mwb_core::content_hash(&scene.toml);
    for _ in 0..5 {
        let latest = client::fetch_scene(session, keys, SceneRev::Latest).await?;
        if let Some(l) = &latest
            && l.content_hash == hash
        {
            return Ok((l.revision, false));
        }
        let revision = latest.map_or(1, |l| l.revision + 1);
        let ours = Scene {
            revision,
            content_hash: hash,
            ..scene.clone()
        };
        session
            .put(keys.scene(revision), ours.encode_to_vec())
            .congestion_control(CongestionControl::Block)
            .await
            .map_err(|e| anyhow!("publishing scene revision {revision}: {e}"))?;
        for _ in 0..20 {
            match client::fetch_scene(session, keys, SceneRev::Number(revision)).await? {
                Some(s) if s.content_hash == hash => return Ok((revision, true)),
                // Someone else's revision `revision`: try the next number.
                Some(_) => break,
                None => tokio::time::sleep(Duration::from_millis(50)).await,
            }
        }
    }
    bail!("publishing the edited scene: no store kept it as a new revision (tried 5 times)")
}
