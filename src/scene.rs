//! `mwb scene`: check a scene file — parse, validate, instantiate one world; `mwb scene preview`
//! draws it as it starts, before any world is sampled; `mwb scene edit` edits the scene of kept
//! worlds ([`crate::scene_edit_cmd`]).

use std::path::PathBuf;

use crate::client;
use anyhow::{Context, Result, anyhow};

/// Arguments of `mwb scene`.
#[derive(Debug, Clone, clap::Args)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct SceneArgs {
    #[command(subcommand)]
    pub action: Option<SceneAction>,
    /// Scene file or shipped scene name.
    #[arg(required = true)]
    pub scene: Option<String>,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Simulation preset to check the scene under [default: the scene's own]; `auto` runs the
    /// calibration a job submission would and prints its table.
    #[arg(long, value_enum)]
    pub sim: Option<client::SimArg>,
}

/// What else `mwb scene` does.
#[derive(Debug, Clone, clap::Subcommand)]
pub enum SceneAction {
    /// Draw the scene as it starts (statics, and bodies where the instance of --seed places
    /// them) to a PNG, without sampling a world: `mwb scene preview tower --out tower.png`.
    Preview(PreviewArgs),
    /// Edit the scene of kept worlds (§4.5 from frame 0): add, remove or change bodies, or give
    /// a whole revision file; the edit is published as a new scene revision and each world gets
    /// children that re-simulate only what the edit reaches:
    /// `mwb scene edit --world 42 --remove brick --worlds 20 --wait`.
    Edit(crate::scene_edit_cmd::EditArgs),
}

/// Arguments of `mwb scene preview`.
#[derive(Debug, Clone, clap::Args)]
pub struct PreviewArgs {
    /// Scene file or shipped scene name.
    pub scene: String,
    /// The PNG to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Which instance of a scene with distributions (its bodies' start poses).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Image size, pixels.
    #[arg(long, default_value = "1280x720")]
    pub size: String,
    /// Camera JSON file (as for `mwb query` and `mwb viewer`) [default: framed on the scene].
    #[arg(long)]
    pub camera: Option<PathBuf>,
}

/// Prints one line: what the scene holds, or the first error with its file and line.
pub async fn run(args: SceneArgs) -> Result<()> {
    match args.action {
        Some(SceneAction::Preview(p)) => preview(p),
        Some(SceneAction::Edit(e)) => crate::scene_edit_cmd::run(e).await,
        None => check(
            args.scene.as_deref().unwrap_or_default(),
            args.seed,
            args.sim.map(Into::into),
        ),
    }
}

fn check(scene: &str, seed: u64, sim: Option<mwb_core::scene::SimPreset>) -> Result<()> {
    let (file, text) = client::load_scene(scene)?;
    let text = crate::sim::resolve(&file, &text, sim)?;
    let t = mwb_core::scene::SceneTemplate::parse(&text, &file)?;
    let s = t.instantiate(seed);
    println!(
        "{file}: ok — scene {:?}, {} dynamic bodies, {} statics, {} joints, {} materials, distributions: {}",
        t.name(),
        s.bodies.len(),
        s.statics.len(),
        s.joints.len(),
        s.materials.len(),
        if t.has_distributions() { "yes" } else { "no" }
    );
    println!(
        "simulation: {}",
        mwb_sampler::plan::SimPlan::of(&s).describe()
    );
    let found = crate::sim::findings(&t);
    for f in &found {
        println!("{}", crate::sim::finding_line(&file, f));
    }
    if mwb_sampler::limits::refuses(&found) {
        anyhow::bail!("{file}: the simulator cannot do this scene faithfully (see above)");
    }
    Ok(())
}

fn preview(args: PreviewArgs) -> Result<()> {
    let (file, text) = client::load_scene(&args.scene)?;
    let t = mwb_core::scene::SceneTemplate::parse(&text, &file)?;
    let size = mwb_viewer::screenshot::parse_size(&args.size).context("--size")?;
    let camera: Option<mwb_core::browse::Camera> = match &args.camera {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading camera file {}", path.display()))?;
            Some(
                serde_json::from_str(&text)
                    .with_context(|| format!("camera file {}", path.display()))?,
            )
        }
        None => None,
    };
    let img = mwb_viewer::preview::render(&t, args.seed, size, camera.as_ref())
        .map_err(|e| anyhow!("--camera: {e}"))?;
    let bytes = mwb_viewer::screenshot::png_bytes(&img).context("encoding the preview")?;
    std::fs::write(&args.out, bytes).with_context(|| format!("writing {}", args.out.display()))?;
    let s = t.instantiate(args.seed);
    println!(
        "{}: {}x{} preview of scene {:?} (seed {}): {} bodies, {} statics",
        args.out.display(),
        size[0],
        size[1],
        t.name(),
        args.seed,
        s.bodies.len(),
        s.statics.len()
    );
    Ok(())
}
