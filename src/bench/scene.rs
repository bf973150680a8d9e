//! `mwb bench scene`: validating big scene files (issue 18) — [`SceneTemplate::parse`] and one
//! [`SceneTemplate::instantiate`], what `mwb scene` does, on
//! [`many_bodies`](mwb_core::scene::builtin::many_bodies) scenes (one `[[body]]` table a body,
//! as an exporter writes them). Time should grow linearly with the body count.

use crate::output::{json_line, number, out};
use anyhow::Result;
use mwb_core::scene::SceneTemplate;
use mwb_core::scene::builtin::many_bodies;
use std::time::Instant;

/// Arguments of `mwb bench scene`.
#[derive(Debug, Clone, clap::Args)]
pub struct SceneArgs {
    /// Body counts to measure (at most the scene limit, 100 000).
    #[arg(long, value_delimiter = ',', default_value = "10000,40000,100000")]
    pub bodies: Vec<usize>,
    /// Print one JSON line per body count instead of the table.
    #[arg(long)]
    pub json: bool,
}

/// One body count's line.
#[derive(Debug, Clone, serde::Serialize)]
pub struct SceneBench {
    pub bodies: usize,
    pub bytes: usize,
    pub parse_seconds: f64,
    pub instantiate_seconds: f64,
    /// Parse throughput, MB (10⁶ bytes) of TOML per second.
    pub parse_mb_per_s: f64,
}

/// Runs `mwb bench scene`: one line per body count, printed as soon as it is measured.
pub fn run(args: SceneArgs) -> Result<()> {
    if !args.json {
        out(&format!(
            "{:>8} {:>10} {:>9} {:>9} {:>8}\n",
            "BODIES", "BYTES", "PARSE S", "INST S", "MB/S"
        ))?;
    }
    for &bodies in &args.bodies {
        let text = many_bodies(bodies);
        let start = Instant::now();
        let template = SceneTemplate::parse(&text, "many_bodies.toml")?;
        let parse_seconds = start.elapsed().as_secs_f64();
        let start = Instant::now();
        let scene = template.instantiate(0);
        let instantiate_seconds = start.elapsed().as_secs_f64();
        anyhow::ensure!(scene.bodies.len() == bodies, "expected {bodies} bodies");
        let line = SceneBench {
            bodies,
            bytes: text.len(),
            parse_seconds,
            instantiate_seconds,
            parse_mb_per_s: text.len() as f64 / 1e6 / parse_seconds,
        };
        if args.json {
            json_line(&line)?;
        } else {
            out(&format!(
                "{:>8} {:>10} {:>9} {:>9} {:>8}\n",
                line.bodies,
                line.bytes,
                number(line.parse_seconds),
                number(line.instantiate_seconds),
                number(line.parse_mb_per_s)
            ))?;
        }
    }
    Ok(())
}
