//! `mwb world`: regenerates one forward world from its scene and seed alone, the promise behind
//! "every world is `(job, seed)`": the same binary, scene text, seed, encoding and quality give
//! the same bytes. It prints the world's summary and its digest ([`mwb_node::world_digest`],
//! which covers everything the scene and seed determine and nothing that says where the world
//! was computed), so the digest equals the stored world's; `--check N` fetches stored world `N`
//! and compares the two. A refined world (§4.5) is regenerated from the lineage it was stored
//! with: its parent from the root seed and the earlier refinements, then the world itself.

use crate::bus::BusArgs;
use crate::client::{self, EncodingArg, QualityArg};
use crate::output::Summary;
use anyhow::{Context, Result, bail};
use mwb_core::keys::Keys;
use mwb_core::scene::SceneTemplate;
use mwb_proto::v1::{Encoding, Lineage, MotionSegment, World, WorldDone};
use mwb_sampler::{PayloadEncoding, RunOptions, Segment, run_world};
use std::ops::ControlFlow;

/// Arguments of `mwb world`.
#[derive(Debug, Clone, clap::Args)]
pub struct WorldArgs {
    /// Scene file or shipped scene name: the scene text of the world's job [default with
    /// --check: the shipped scene the stored world's scene hash names].
    #[arg(long, required_unless_present = "check")]
    pub scene: Option<String>,
    /// The world's seed, decimal or 0x-hex (`mwb query show N` prints it).
    #[arg(long, value_parser = parse_seed)]
    pub seed: u64,
    /// Segment payload of the world's job [default: spline; with --check: the stored world's].
    #[arg(long, value_enum)]
    pub encoding: Option<EncodingArg>,
    /// Codec error bounds of the world's job [default: standard; with --check: the stored
    /// world's].
    #[arg(long, value_enum)]
    pub quality: Option<QualityArg>,
    /// Fetch stored world N over the bus and compare digests: exits non-zero if they differ.
    #[arg(long, value_name = "N")]
    pub check: Option<u32>,
    /// Print the summary as one JSON line.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub bus: BusArgs,
}

/// A seed as the user writes it: decimal, or hex with `0x`.
pub fn parse_seed(s: &str) -> Result<u64, String> {
    let parsed = match s.strip_prefix("0x").or_else(|| s.strip_prefix("0X")) {
        Some(hex) => u64::from_str_radix(&hex.replace('_', ""), 16),
        None => s.replace('_', "").parse::<u64>(),
    };
    parsed.map_err(|e| format!("--seed {s:?}: not a 64-bit number, decimal or 0x-hex ({e})"))
}

/// What `mwb world` prints.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Regenerated {
    pub scene: String,
    /// `0x…`, as `mwb query show` prints it.
    pub seed: String,
    pub encoding: &'static str,
    pub quality: &'static str,
    pub bodies: u32,
    pub frames: u32,
    pub seconds: f64,
    pub segments: u32,
    pub rested: bool,
    pub impacts: u64,
    pub perturbations: u32,
    pub payload_bytes: u64,
    /// The simulation plan it ran with (`WorldDone.sim`: preset, substeps, CCD, …).
    pub sim: String,
    /// [`mwb_node::world_digest`] as `0x` and eight hex digits.
    pub digest: String,
    /// With `--check N`: the stored world compared with, its digest, and whether they agree.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stored_world: Option<u32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stored_digest: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub matches: Option<bool>,
}

impl Summary for Regenerated {
    fn table(&self) -> String {
        let mut t = crate::output::fields_table(self);
        if self.matches == Some(false) {
            t += "the regenerated world differs from the stored one\n";
        }
        t
    }
}

/// One regenerated world in its wire form, as a sampler would have sent it.
#[derive(Debug, Clone)]
pub struct WorldBytes {
    pub segments: Vec<MotionSegment>,
    pub done: WorldDone,
}

impl WorldBytes {
    pub fn digest(&self) -> u32 {
        mwb_node::world_digest(&self.segments, &self.done)
    }
}

/// Regenerates the forward world `seed` of the scene `text` (named `file` in errors) with the
/// job's encoding and quality; a refined world (§4.5) from its `lineage` (its last step is the
/// world itself, whose seed is `seed`). Pure: no bus, no clock.
pub fn regenerate(
    file: &str,
    text: &str,
    seed: u64,
    encoding: EncodingArg,
    quality: QualityArg,
    lineage: Option<&Lineage>,
) -> Result<WorldBytes> {
    let template = SceneTemplate::parse(text, file)?;
    let opts = RunOptions {
        quality: mwb_node::codec_quality(quality.into()),
        encoding: match encoding {
            EncodingArg::Spline => PayloadEncoding::Spline,
            EncodingArg::Frames => PayloadEncoding::QuantisedFrames,
        },
        ..RunOptions::default()
    };
    let mut segments = Vec::new();
    let mut emit = |seg: Segment| {
        segments.push(mwb_sampler::segment_message("", "", 0, seed, seg));
        ControlFlow::Continue(())
    };
    let refined = match lineage.and_then(|l| l.steps.split_last().map(|s| (l, s))) {
        None => None,
        Some((l, (last, before))) => {
            if last.seed != seed {
                bail!(
                    "--seed {seed:#x}: the world's lineage ends with seed {:#x} (a refined \
                     world's seed is its own)",
                    last.seed
                );
            }
            let parent = mwb_sampler::node::lineage_from_wire(&Lineage {
                steps: before.to_vec(),
                ..l.clone()
            })?;
            if last.scene_revision != 0 {
                bail!(
                    "--seed {seed:#x}: a world made by a scene edit (revision {}) cannot be \
                     regenerated yet",
                    last.scene_revision
                );
            }
            let parent = mwb_sampler::refine::regenerate(
                &template,
                &parent,
                &mwb_sampler::refine::BranchAt::Frame(last.frame),
            )
            .with_context(|| format!("regenerating the parent of world {seed:#x} of {file}"))?;
            let child = parent
                .refine(&last.objects, seed, opts, &mut emit)
                .with_context(|| format!("regenerating refined world {seed:#x} of {file}"))?;
            Some((l, child))
        }
    };
    let done = match refined {
        None => {
            let summary = run_world(&template, seed, opts, &mut emit)
                .with_context(|| format!("regenerating world {seed:#x} of {file}"))?;
            mwb_sampler::world_done("", "", 0, &summary)
        }
        Some((l, child)) => mwb_sampler::node::refined_done("", "", 0, &l.root_job, &child),
    };
    let done = WorldDone {
        // What the worker skeleton adds to every summary and the digest covers.
        scene_hash: mwb_core::content_hash(text),
        ..done
    };
    Ok(WorldBytes { segments, done })
}

/// A digest as printed: `0x` and eight hex digits.
pub fn digest_text(d: u32) -> String {
    format!("{d:#010x}")
}

/// The encoding and quality a stored world was made with (from its first segment).
pub fn stored_motion(w: &World) -> Result<(EncodingArg, QualityArg)> {
    let Some(first) = w.segments.first() else {
        bail!("world {}: no segments", w.index);
    };
    match Encoding::try_from(first.encoding) {
        Ok(Encoding::QuantisedFramesV1) => Ok((EncodingArg::Frames, QualityArg::Standard)),
        Ok(Encoding::SplineV1) => {
            let reader = mwb_codec::WorldReader::new(&first.payload)
                .with_context(|| format!("world {}: segment 0", w.index))?;
            let quality = match reader.quality() {
                Some(mwb_codec::Quality::Draft) => QualityArg::Draft,
                Some(mwb_codec::Quality::Standard) => QualityArg::Standard,
                Some(mwb_codec::Quality::Final) => QualityArg::Final,
                None => bail!(
                    "world {}: encoded with bounds {} m / {} rad, which no --quality preset has",
                    w.index,
                    reader.e_max(),
                    reader.theta_max()
                ),
            };
            Ok((EncodingArg::Spline, quality))
        }
        _ => bail!("world {}: unknown encoding {}", w.index, first.encoding),
    }
}

/// The command that regenerates stored world `world` of seed `seed` and compares it with the
/// stored one (what `mwb query show` prints). The scene is found from the stored world's scene
/// hash when it is a shipped one; otherwise the command asks for `--scene FILE`.
pub fn regenerate_command(world: u32, seed: u64) -> String {
    format!("mwb world --seed {seed:#x} --check {world}")
}

/// The shipped scene whose text has the scene hash `hash`.
fn shipped_scene(hash: u64) -> Option<&'static str> {
    mwb_core::scene::builtin::NAMES
        .iter()
        .copied()
        .find(|name| {
            mwb_core::scene::builtin::get(name)
                .is_some_and(|text| mwb_core::content_hash(text) == hash)
        })
}

fn encoding_name(e: EncodingArg) -> &'static str {
    match e {
        EncodingArg::Spline => "spline",
        EncodingArg::Frames => "frames",
    }
}

fn quality_name(q: QualityArg) -> &'static str {
    match q {
        QualityArg::Draft => "draft",
        QualityArg::Standard => "standard",
        QualityArg::Final => "final",
    }
}

/// Runs `mwb world`.
pub async fn run(args: WorldArgs) -> Result<()> {
    let stored = match args.check {
        Some(index) => Some(fetch(&args.bus, index).await?),
        None => None,
    };
    if let Some(w) = &stored
        && w.done.as_ref().is_some_and(|d| d.energy_growth.is_some())
    {
        bail!(
            "world {} is a backward world (ch. 5): `mwb world` regenerates forward worlds only",
            w.index
        );
    }
    let scene = match (&args.scene, &stored) {
        (Some(scene), _) => scene.clone(),
        (None, Some(w)) => {
            let done = w.done.clone().unwrap_or_default();
            match shipped_scene(done.scene_hash) {
                Some(name) => name.to_owned(),
                None => bail!(
                    "world {}'s scene (job {}) is not a shipped one: pass --scene FILE, the \
                     scene file its job was submitted with",
                    w.index,
                    w.job_id
                ),
            }
        }
        (None, None) => bail!("--scene is needed without --check"),
    };
    let (file, text) = client::load_scene(&scene)?;
    let (stored_encoding, stored_quality) = match &stored {
        Some(w) => {
            let (e, q) = stored_motion(w)?;
            (Some(e), Some(q))
        }
        None => (None, None),
    };
    let encoding = args.encoding.or(stored_encoding).unwrap_or_default();
    let quality = args.quality.or(stored_quality).unwrap_or_default();
    let seed = args.seed;
    let lineage = stored
        .as_ref()
        .and_then(|w| w.done.as_ref())
        .and_then(|d| d.lineage.clone());
    let world = {
        let (file, text) = (file.clone(), text.clone());
        tokio::task::spawn_blocking(move || {
            regenerate(&file, &text, seed, encoding, quality, lineage.as_ref())
        })
        .await
        .context("the regenerating thread failed")??
    };
    let digest = world.digest();
    let done = &world.done;
    let bodies = world.segments.first().map_or(0, |s| s.body_count);
    let mut summary = Regenerated {
        scene: file,
        seed: format!("{seed:#x}"),
        encoding: encoding_name(encoding),
        quality: quality_name(quality),
        bodies,
        frames: done.frame_count,
        seconds: f64::from(done.frame_count.saturating_sub(1)) * done.frame_dt,
        segments: done.segment_count,
        rested: done.rested,
        impacts: done.impacts.iter().map(|&i| u64::from(i)).sum(),
        perturbations: done.perturbations,
        payload_bytes: world.segments.iter().map(|s| s.payload.len() as u64).sum(),
        sim: world.done.sim.clone(),
        digest: digest_text(digest),
        stored_world: None,
        stored_digest: None,
        matches: None,
    };
    if let Some(w) = &stored {
        let theirs = mwb_node::world_digest(&w.segments, &w.done.clone().unwrap_or_default());
        summary.stored_world = Some(w.index);
        summary.stored_digest = Some(digest_text(theirs));
        summary.matches = Some(theirs == digest);
    }
    crate::output::print(&summary, args.json)?;
    if let (Some(w), Some(false)) = (&stored, summary.matches) {
        let stored_seed = w.done.as_ref().map_or(0, |d| d.seed);
        bail!(
            "world {} (seed {stored_seed:#x}) is not what scene {} and seed {seed:#x} give{}",
            w.index,
            summary.scene,
            if stored_seed == seed {
                " (another scene text, or another build: compare the provenance)"
            } else {
                ": the seeds differ"
            }
        );
    }
    Ok(())
}

/// Stored world `index`, or an error saying no store holds it.
async fn fetch(bus: &BusArgs, index: u32) -> Result<World> {
    let keys = Keys::new(&bus.space)?;
    let session = bus.open(bus.client_default()).await?;
    let world = client::fetch_world(&session, &keys, index).await;
    crate::bus::close(session).await;
    match world? {
        Some(w) => Ok(w),
        None => bail!(
            "--check {index}: no store in space {:?} holds world {index}",
            bus.space
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seeds_are_decimal_or_hex() {
        assert_eq!(parse_seed("42"), Ok(42));
        assert_eq!(parse_seed("0xfeed"), Ok(0xfeed));
        assert_eq!(parse_seed("0x00000000_0000feed"), Ok(0xfeed));
        let e = parse_seed("0xzz").err().unwrap_or_default();
        assert!(e.contains("--seed"), "{e}");
        assert!(parse_seed("-1").is_err());
    }

    #[test]
    fn a_world_regenerates_to_the_same_digest_and_its_seed_matters() {
        let text = mwb_core::scene::builtin::TUMBLE;
        let run = |seed| {
            regenerate(
                "tumble",
                text,
                seed,
                EncodingArg::Spline,
                QualityArg::Draft,
                None,
            )
            .unwrap_or_else(|e| panic!("{e:#}"))
        };
        let a = run(7);
        assert_eq!(a.digest(), run(7).digest());
        assert_ne!(a.digest(), run(8).digest());
        assert_eq!(a.done.segment_count as usize, a.segments.len());
        assert_eq!(a.done.scene_hash, mwb_core::content_hash(text));
        // A stored world names its scene and motion settings.
        let stored = World {
            index: 3,
            job_id: "j".into(),
            done: Some(a.done.clone()),
            segments: a.segments.clone(),
            parent: None,
        };
        assert_eq!(shipped_scene(a.done.scene_hash), Some("tumble"));
        assert_eq!(shipped_scene(a.done.scene_hash ^ 1), None);
        assert!(matches!(
            stored_motion(&stored),
            Ok((EncodingArg::Spline, QualityArg::Draft))
        ));
        assert_eq!(regenerate_command(3, 7), "mwb world --seed 0x7 --check 3");
    }
}
