//! `mwb export`: chosen worlds out of manyworlds (`mwb-export`), as glTF 2.0 binary, Foxglove
//! MCAP, CSV or JSON.
//!
//! Where the worlds come from:
//! * a running store (default; `--connect …` like every client): `--world N` / `--worlds a,b`
//!   by global index, fetched with `q/world/<i>`. The scene comes from the job, which the store
//!   holding the world serves (`q/job/<job>`, open or closed); `--scene FILE` overrides it and
//!   is checked against the world's scene hash;
//! * a recording (`--from session.mcap`): its jobs, segments and summaries are assembled as a
//!   fresh single store loading the file would (`mwb_store::Assembler`, in recorded order), so
//!   world `N` is the world such a store numbers `N`. A damaged recording is refused, naming
//!   the file and byte offset;
//! * the seed alone (`--scene X --seed S[,T…]`): the world is simulated here by the sampler's
//!   own code (deterministic: the same binary, scene and seed give the same world as a
//!   sampler's), encoded and decoded at `--quality` like a job's, so the export is what a
//!   store would have served.
//!
//! Several worlds: `glb` and `foxglove` write one file per world (`out-<N>.glb`, or
//! `out-seed<S>.glb` for simulated ones); `csv` and `json` write one file with every world
//! (each row names its world).

use crate::bus::BusArgs;
use crate::client::{QualityArg, fetch_world, load_scene};
use crate::output::{Summary, print};
use anyhow::{Context, Result, bail};
use mwb_core::keys::Keys;
use mwb_core::scene::{Scene, SceneTemplate};
use mwb_export::{ExportWorld, Motion, decode_world};
use mwb_proto::v1::{Job, Message, MotionSegment, World, WorldDone};
use mwb_record::Family;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Output formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// glTF 2.0 binary: a node and mesh per body, one animation (Blender, Maya, Houdini).
    Glb,
    /// MCAP with foxglove.SceneUpdate + foxglove.FrameTransforms (Foxglove's 3D panel).
    Foxglove,
    /// One row per frame and body: world, seed, frame, time, body, name, position, quaternion.
    Csv,
    /// The same rows in one JSON document.
    Json,
}

impl Format {
    fn extension(self) -> &'static str {
        match self {
            Format::Glb => "glb",
            Format::Foxglove => "mcap",
            Format::Csv => "csv",
            Format::Json => "json",
        }
    }
}

/// Arguments of `mwb export`.
#[derive(Debug, Clone, clap::Args)]
pub struct ExportArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// The world to export (global index, as `mwb query result` lists them).
    #[arg(long, conflicts_with = "worlds")]
    pub world: Option<u32>,
    /// Several worlds, comma-separated.
    #[arg(long, value_delimiter = ',')]
    pub worlds: Vec<u32>,
    /// Output format.
    #[arg(long, value_enum, default_value_t = Format::Glb)]
    pub format: Format,
    /// The file to write (with several glb/foxglove worlds, `-<world>` goes before its extension).
    #[arg(long, short = 'o', value_name = "FILE")]
    pub out: PathBuf,
    /// Take the worlds from this recording (`mwb record`) instead of a running store.
    #[arg(long, value_name = "FILE", conflicts_with = "connect")]
    pub from: Option<PathBuf>,
    /// The scene (a file, or a shipped scene's name). With --seed: simulate it here. Otherwise:
    /// the scene of worlds whose job the store or recording no longer has.
    #[arg(long)]
    pub scene: Option<String>,
    /// Simulate these seeds of --scene here (comma-separated, decimal or 0x-hex as `mwb query
    /// show` prints them), instead of fetching worlds.
    #[arg(long, value_delimiter = ',', value_parser = crate::world_cmd::parse_seed, requires = "scene", conflicts_with_all = ["world", "worlds", "from"])]
    pub seed: Vec<u64>,
    /// Codec error bounds of simulated worlds (a job's default is standard).
    #[arg(long, value_enum, default_value_t = QualityArg::Standard)]
    pub quality: QualityArg,
    /// Seconds to wait for a store.
    #[arg(long, default_value_t = 15)]
    pub timeout: u64,
    /// Print one JSON line per file written.
    #[arg(long)]
    pub json: bool,
}

/// One file written.
#[derive(Debug, Serialize)]
pub struct ExportSummary {
    pub file: String,
    pub format: String,
    /// World indices (empty for simulated worlds) and seeds, in order.
    pub worlds: Vec<Option<u32>>,
    pub seeds: Vec<u64>,
    pub frames: u64,
    pub bodies: u64,
    pub bytes: u64,
    /// Seconds to build the file's bytes (getting the worlds is not included).
    pub export_s: f64,
}

impl Summary for ExportSummary {
    fn table(&self) -> String {
        let names: Vec<String> = self
            .worlds
            .iter()
            .zip(&self.seeds)
            .map(|(w, s)| match w {
                Some(w) => format!("world {w}"),
                None => format!("seed {s}"),
            })
            .collect();
        format!(
            "wrote {} ({}): {} — {} frames, {} bodies, {} bytes in {:.3} s\n",
            self.file,
            self.format,
            names.join(", "),
            self.frames,
            self.bodies,
            self.bytes,
            self.export_s
        )
    }
}

/// A world ready to export: its instantiated scene and decoded motion.
struct Loaded {
    index: Option<u32>,
    seed: u64,
    scene: Scene,
    motion: Motion,
}

impl Loaded {
    fn export(&self) -> ExportWorld<'_> {
        ExportWorld {
            index: self.index,
            seed: self.seed,
            scene: &self.scene,
            motion: &self.motion,
        }
    }
}

pub async fn run(args: ExportArgs) -> Result<()> {
    let indices: Vec<u32> = args.world.into_iter().chain(args.worlds.clone()).collect();
    let loaded = if !args.seed.is_empty() {
        simulate(&args)?
    } else if indices.is_empty() {
        bail!("which worlds? give --world N, --worlds a,b,c, or --scene X --seed S");
    } else if let Some(path) = &args.from {
        from_recording(path, &indices, args.scene.as_deref())?
    } else {
        from_store(&args, &indices).await?
    };
    for summary in write_all(&loaded, args.format, &args.out)? {
        print(&summary, args.json)?;
    }
    Ok(())
}

/// Builds and writes the files.
fn write_all(worlds: &[Loaded], format: Format, out: &Path) -> Result<Vec<ExportSummary>> {
    let groups: Vec<(PathBuf, &[Loaded])> = match format {
        Format::Csv | Format::Json => vec![(out.to_owned(), worlds)],
        Format::Glb | Format::Foxglove if worlds.len() == 1 => vec![(out.to_owned(), worlds)],
        Format::Glb | Format::Foxglove => worlds
            .iter()
            .map(|w| (numbered(out, format, w), std::slice::from_ref(w)))
            .collect(),
    };
    let mut summaries = Vec::new();
    for (path, group) in groups {
        let exports: Vec<ExportWorld<'_>> = group.iter().map(Loaded::export).collect();
        let start = Instant::now();
        let bytes = match format {
            Format::Glb => mwb_export::glb::write(&exports[0]),
            Format::Foxglove => mwb_export::foxglove::write(&exports[0]),
            Format::Csv => mwb_export::table::write_csv(&exports),
            Format::Json => mwb_export::table::write_json(&exports),
        }
        .with_context(|| format!("exporting {}", names(group)))?;
        let export_s = start.elapsed().as_secs_f64();
        std::fs::write(&path, &bytes).with_context(|| format!("writing {}", path.display()))?;
        summaries.push(ExportSummary {
            file: path.display().to_string(),
            format: format!("{format:?}").to_lowercase(),
            worlds: group.iter().map(|w| w.index).collect(),
            seeds: group.iter().map(|w| w.seed).collect(),
            frames: group.iter().map(|w| w.motion.frame_count() as u64).sum(),
            bodies: group.iter().map(|w| w.scene.bodies.len() as u64).sum(),
            bytes: bytes.len() as u64,
            export_s,
        });
    }
    Ok(summaries)
}

fn names(group: &[Loaded]) -> String {
    group
        .iter()
        .map(|w| w.export().label())
        .collect::<Vec<_>>()
        .join(", ")
}

/// `world.glb` → `world-17.glb` (or `world-seed7.glb`).
fn numbered(out: &Path, format: Format, w: &Loaded) -> PathBuf {
    let stem = out
        .file_stem()
        .map_or_else(|| "world".into(), |s| s.to_string_lossy().into_owned());
    let ext = out.extension().map_or_else(
        || format.extension().into(),
        |e| e.to_string_lossy().into_owned(),
    );
    let tag = match w.index {
        Some(i) => i.to_string(),
        None => format!("seed{}", w.seed),
    };
    out.with_file_name(format!("{stem}-{tag}.{ext}"))
}

/// `--scene X --seed S…`: each world simulated here, in the wire form a sampler sends
/// (`mwb_sampler::segment_message`), then read like a stored one.
fn simulate(args: &ExportArgs) -> Result<Vec<Loaded>> {
    let Some(scene_arg) = &args.scene else {
        bail!("--seed needs --scene");
    };
    let (file, text) = load_scene(scene_arg)?;
    let template = SceneTemplate::parse(&text, &file)?;
    let opts = mwb_sampler::RunOptions {
        quality: mwb_node::codec_quality(args.quality.into()),
        ..Default::default()
    };
    let mut out = Vec::new();
    for &seed in &args.seed {
        let mut segments = Vec::new();
        let summary = mwb_sampler::run_world(&template, seed, opts, &mut |seg| {
            segments.push(mwb_sampler::segment_message("", "", 0, seed, seg));
            std::ops::ControlFlow::Continue(())
        })
        .with_context(|| format!("{file}: simulating seed {seed}"))?;
        let done = mwb_sampler::world_done("", "", 0, &summary);
        let source = SceneSource::Text {
            file: &file,
            text: &text,
        };
        let world = World {
            done: Some(done),
            segments,
            ..World::default()
        };
        out.push(load_world(None, &world, source)?);
    }
    Ok(out)
}

/// Where a world's scene text comes from.
enum SceneSource<'a> {
    /// Given by the user (`--scene`) or simulated from.
    Text { file: &'a str, text: &'a str },
    /// The world's job, if the store or recording has it; else what lacks it, for the error.
    Job {
        job: Option<&'a Job>,
        lacking: &'a str,
    },
}

/// A world's motion and instantiated scene. A scene text that is not the world's (its hash
/// differs from `WorldDone.scene_hash`) is refused.
fn load_world(index: Option<u32>, world: &World, source: SceneSource<'_>) -> Result<Loaded> {
    let Some(done) = &world.done else {
        bail!(
            "world {}: no summary",
            index.map_or_else(|| "?".into(), |i| i.to_string())
        );
    };
    let name = match index {
        Some(i) => format!("world {i}"),
        None => format!("seed {}", done.seed),
    };
    let (file, text, job) = match source {
        SceneSource::Text { file, text } => (file.to_owned(), text.to_owned(), None),
        SceneSource::Job {
            job: Some(job @ Job { scene: Some(s), .. }),
            ..
        } => (
            format!("job {}: scene {:?}", done.job_id, s.name),
            s.toml.clone(),
            Some(job),
        ),
        SceneSource::Job { lacking, .. } => bail!(
            "{name}: {lacking} does not have the scene of job {:?}: give it with --scene FILE",
            done.job_id
        ),
    };
    let hash = mwb_core::content_hash(&text);
    if done.scene_hash != 0 && hash != done.scene_hash {
        bail!(
            "{name}: {file} is not this world's scene (its hash is {hash:#018x}, the world was \
             made from {:#018x})",
            done.scene_hash
        );
    }
    let template = SceneTemplate::parse(&text, &file)?;
    // A refined world stored as a difference composes over its parent chain.
    let motion = decode_world(world).with_context(|| format!("{name}: decoding its motion"))?;
    // A refined world is an instance of its root world's scene (§4.5: its seed is its own); an
    // edited world the edit of its parent's instance.
    let scene = mwb_export::world_instance(&template, job, done)?;
    if scene.bodies.len() != motion.tracks.len() {
        bail!(
            "{name}: {} bodies, its scene {file} has {}",
            motion.tracks.len(),
            scene.bodies.len()
        );
    }
    Ok(Loaded {
        index,
        seed: done.seed,
        scene,
        motion,
    })
}

/// The user's `--scene`, read once, for worlds from a store or a recording.
fn user_scene(arg: Option<&str>) -> Result<Option<(String, String)>> {
    arg.map(load_scene).transpose()
}

fn scene_source<'a>(
    user: &'a Option<(String, String)>,
    job: Option<&'a Job>,
    lacking: &'a str,
) -> SceneSource<'a> {
    match user {
        Some((file, text)) => SceneSource::Text { file, text },
        None => SceneSource::Job { job, lacking },
    }
}

/// `--from session.mcap`: the worlds a fresh single store would hold after loading it.
fn from_recording(path: &Path, indices: &[u32], scene_arg: Option<&str>) -> Result<Vec<Loaded>> {
    let rec = mwb_record::read_recording(path)
        .with_context(|| format!("reading recording {}", path.display()))?;
    if let Some(e) = rec.error {
        bail!(
            "recording damaged: {e} ({} messages before the damage; export reads intact \
             recordings only)",
            rec.messages.len()
        );
    }
    let mut table = mwb_store::Assembler::new(u64::MAX);
    let mut malformed = 0u64;
    for m in &rec.messages {
        let bytes = m.payload.as_slice();
        match m.family {
            Family::Job => match Job::decode(bytes) {
                Ok(j) => {
                    table.submit_job(j);
                }
                Err(_) => malformed += 1,
            },
            Family::Segment => match MotionSegment::decode(bytes) {
                Ok(s) => {
                    table.on_segment(s, 0);
                }
                Err(_) => malformed += 1,
            },
            Family::Done => match WorldDone::decode(bytes) {
                Ok(d) => {
                    table.on_done(d, 0);
                }
                Err(_) => malformed += 1,
            },
            _ => {}
        }
    }
    if malformed > 0 {
        tracing::warn!(malformed, file = %path.display(), "messages that did not decode were skipped");
    }
    let count = table.world_count();
    let user = user_scene(scene_arg)?;
    let lacking = format!("recording {}", path.display());
    let mut out = Vec::new();
    for &index in indices {
        let Some(w) = table.world(index) else {
            bail!(
                "world {index}: {} holds {count} complete worlds (0..{count})",
                path.display()
            );
        };
        let job = table.jobs().find(|(j, _)| j.id == w.job_id).map(|(j, _)| j);
        let source = scene_source(&user, job, &lacking);
        out.push(load_world(Some(index), &w.message()?, source)?);
    }
    Ok(out)
}

/// `--connect …`: worlds fetched from the stores.
async fn from_store(args: &ExportArgs, indices: &[u32]) -> Result<Vec<Loaded>> {
    let keys = Keys::new(&args.bus.space)?;
    let session = args.bus.open(args.bus.client_default()).await?;
    let result = fetch_all(&session, &keys, args, indices).await;
    crate::bus::close(session).await;
    result
}

async fn fetch_all(
    session: &zenoh::Session,
    keys: &Keys,
    args: &ExportArgs,
    indices: &[u32],
) -> Result<Vec<Loaded>> {
    crate::client::wait_for_store(session, keys, Duration::from_secs(args.timeout)).await?;
    let user = user_scene(args.scene.as_deref())?;
    let mut out = Vec::new();
    for &index in indices {
        let Some(world): Option<World> = fetch_world(session, keys, index).await? else {
            bail!("world {index}: no store holds it (`mwb query result` lists the worlds)");
        };
        let job = crate::client::held_job(session, keys, &world.job_id).await?;
        let source = scene_source(&user, job.as_ref(), "no store");
        out.push(load_world(Some(index), &world, source)?);
    }
    Ok(out)
}
