//! `mwb scene`: check a scene file — parse, validate, instantiate one world.

use crate::client;
use anyhow::Result;

/// Arguments of `mwb scene`.
#[derive(Debug, Clone, clap::Args)]
pub struct SceneArgs {
    /// Scene file or shipped scene name.
    pub scene: String,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// Prints one line: what the scene holds, or the first error with its file and line.
pub fn run(args: SceneArgs) -> Result<()> {
    let (file, text) = client::load_scene(&args.scene)?;
    let t = mwb_core::scene::SceneTemplate::parse(&text, &file)?;
    let s = t.instantiate(args.seed);
    println!(
        "{file}: ok — scene {:?}, {} dynamic bodies, {} statics, {} joints, {} materials, distributions: {}",
        t.name(),
        s.bodies.len(),
        s.statics.len(),
        s.joints.len(),
        s.materials.len(),
        if t.has_distributions() { "yes" } else { "no" }
    );
    Ok(())
}
