//! `mwb refine`: re-sample the part of an almost-right world that goes wrong (§4.5).
//!
//! The animator names a stored world, the bodies to change and a box over the part of their
//! path that must change (a screen rectangle seen by a camera, as `mwb query add` takes it, or a
//! world-space box). This command fetches the world and its job's scene from the stores,
//! regenerates the world exactly from its lineage, finds the branch frame t_min (the first frame
//! at which any picked body's centre is inside the box) and submits a REFINE job whose worlds
//! are children of it. Everything that can be wrong with the request is found here, before
//! anything is submitted, and named: an unknown world, a body that is not in the scene, a box
//! the picked bodies never enter, a world this binary does not regenerate.

use crate::bus::BusArgs;
use crate::client;
use crate::output::Summary;
use crate::query::numbers;
use anyhow::{Context, Result, anyhow, bail};
use mwb_core::browse::{Camera, Frustum, ScreenRect};
use mwb_core::keys::Keys;
use mwb_sampler::request::{RequestError, plan};
use std::path::PathBuf;
use std::time::Duration;

/// Arguments of `mwb refine`.
#[derive(Debug, Clone, clap::Args)]
pub struct RefineArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// The stored world to refine (its global index, as `mwb query` and the viewer show it).
    #[arg(long)]
    pub world: u32,
    /// The bodies to re-simulate: indices or names (`projectile`, `block[3,11,0]`, `block` for
    /// every instance), comma-separated.
    #[arg(long)]
    pub objects: String,
    /// Screen rectangle in pixels: X0,Y0,X1,Y1 (needs --camera).
    #[arg(long)]
    pub rect: Option<String>,
    /// Camera JSON file: {"position":[..],"rotation":[x,y,z,w],"intrinsics":{..},"viewport":{..}}.
    #[arg(long)]
    pub camera: Option<PathBuf>,
    /// World-space box instead of a rectangle: MINX,MINY,MINZ,MAXX,MAXY,MAXZ (metres).
    #[arg(long, allow_hyphen_values = true)]
    pub aabb: Option<String>,
    /// Refined worlds wanted.
    #[arg(long, default_value_t = 50)]
    pub worlds: u32,
    /// Job id [default: <parent job>-w<world>-<time>].
    #[arg(long)]
    pub id: Option<String>,
    #[command(flatten)]
    pub follow: client::FollowArgs,
}

/// What `mwb refine` did.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Refined {
    pub job: String,
    pub parent_world: u32,
    pub parent_job: String,
    /// The picked bodies, as scene indices.
    pub objects: Vec<u32>,
    /// t_min as a frame of the parent, and in seconds.
    pub branch_frame: u32,
    pub branch_time_s: f64,
    pub target: u32,
    pub done: u32,
    pub closed: bool,
}

impl Summary for Refined {
    fn table(&self) -> String {
        format!(
            "job {}: {}/{} worlds refined from world {} (job {}), bodies {:?} from frame {} \
             (t = {:.3} s){}\n",
            self.job,
            self.done,
            self.target,
            self.parent_world,
            self.parent_job,
            self.objects,
            self.branch_frame,
            self.branch_time_s,
            if self.closed { ", closed" } else { "" }
        )
    }
}

/// The box: `--aabb`, or `--rect` through `--camera`.
fn region(args: &RefineArgs) -> Result<Frustum> {
    if let Some(b) = &args.aabb {
        let v = numbers("aabb", b, 6)?;
        return Frustum::aabb([v[0], v[1], v[2]], [v[3], v[4], v[5]])
            .map_err(|e| anyhow!("--aabb: {e}"));
    }
    let Some(rect) = &args.rect else {
        bail!("no box: give --rect X0,Y0,X1,Y1 with --camera FILE, or --aabb");
    };
    let v = numbers("rect", rect, 4)?;
    let Some(path) = &args.camera else {
        bail!("--rect needs a camera (--camera FILE)");
    };
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("--camera: reading {}", path.display()))?;
    let camera: Camera = serde_json::from_str(&text)
        .with_context(|| format!("--camera: {} is not a camera", path.display()))?;
    camera
        .frustum(&ScreenRect {
            x0: v[0],
            y0: v[1],
            x1: v[2],
            y1: v[3],
        })
        .map_err(|e| anyhow!("--rect: {e}"))
}

/// Runs `mwb refine`.
pub async fn run(args: RefineArgs) -> Result<()> {
    let keys = Keys::new(&args.bus.space)?;
    if args.worlds == 0 {
        bail!("--worlds: at least 1");
    }
    let frustum = region(&args)?;
    let session = args.bus.open(args.bus.client_default()).await?;
    let result = refine(&session, &keys, &args, frustum).await;
    crate::bus::close(session).await;
    crate::output::print(&result?, args.follow.json)
}

async fn refine(
    session: &zenoh::Session,
    keys: &Keys,
    args: &RefineArgs,
    frustum: Frustum,
) -> Result<Refined> {
    client::wait_for_store(session, keys, Duration::from_secs(10)).await?;
    let world = client::fetch_world(session, keys, args.world)
        .await?
        .ok_or_else(|| anyhow!("--world {}: no store holds it", args.world))?;
    let parent_job = client::held_job(session, keys, &world.job_id)
        .await?
        .ok_or_else(|| {
            anyhow!(
                "--world {}: no store serves its job {:?} (its scene is needed)",
                args.world,
                world.job_id
            )
        })?;
    // t_min on the parent's exact motion (one regeneration, off the async threads).
    let objects = args.objects.clone();
    let plan = tokio::task::spawn_blocking(move || plan(&world, &parent_job, &objects, frustum))
        .await?
        .map_err(|e| match e {
            // These start with "world N": the flag that named it.
            RequestError::NoSummary { .. }
            | RequestError::Backward { .. }
            | RequestError::Regenerate { .. }
            | RequestError::NotRegenerated { .. }
            | RequestError::Lineage { .. } => anyhow!("--{e}"),
            e => anyhow!("{e}"),
        })?;
    let id = match &args.id {
        Some(id) => id.clone(),
        None => format!(
            "{}-w{}-{:x}",
            plan.parent_job,
            args.world,
            client::unix_ms()
        ),
    };
    mwb_core::keys::check_identifier("job id", &id)?;
    let job = plan.job(
        id.clone(),
        args.worlds,
        args.follow.priority,
        client::unix_ms(),
    );
    let branch_frame = plan.branch_frame;
    let mut state = client::submit_job(session, keys, &job).await?;
    if !args.follow.json {
        eprintln!(
            "submitted job {id}: {} worlds refining world {} from frame {branch_frame} \
             (t = {:.3} s)",
            args.worlds,
            args.world,
            plan.branch_time_s()
        );
    }
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
    Ok(Refined {
        job: id,
        parent_world: args.world,
        branch_time_s: plan.branch_time_s(),
        parent_job: plan.parent_job,
        objects: plan.objects,
        branch_frame,
        target: args.worlds,
        done: state.worlds_done,
        closed: state.closed,
    })
}
