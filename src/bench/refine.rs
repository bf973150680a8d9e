//! `mwb bench refine`: what refinement (§4.5) saves over sampling a fresh world, per scene.
//!
//! For each of `--parents` root worlds, the refined object's first impact is found on the
//! parent's exact motion, the parent is regenerated and forked just after it (timed:
//! `parent_regen_s`), and `--children` children re-simulate the object from there, recorded and
//! encoded as a sampler would (timed one by one: `refine_core_s_per_world`). Fresh worlds of the
//! same scene, recorded and encoded the same way, give `full_core_s_per_world`. All times are
//! this thread's CPU seconds, medians over the worlds; `speedup` is the ratio of the two medians
//! of one run.

use crate::output::{Summary, fields_table};
use anyhow::{Context, Result, bail};
use mwb_core::perturb;
use mwb_core::scene::SceneTemplate;
use mwb_node::cpu_time;
use mwb_sampler::refine::{BranchAt, Lineage, regenerate};
use mwb_sampler::{RunOptions, run_world};
use std::ops::ControlFlow;

/// Arguments of `mwb bench refine`.
#[derive(Debug, Clone, clap::Args)]
pub struct RefineArgs {
    /// Scene files or shipped scene names [default: tower and pachinko].
    #[arg(long = "scene")]
    pub scenes: Vec<String>,
    /// The body to refine: a name, an index, `fastest` (the fastest at the start), `farthest`
    /// (the one that ends farthest from where it started, in each root world) or `stray` (the
    /// farthest of those that start at rest: a block knocked out of the tower)
    /// [default: two cases per scene, `fastest` from its first impact and `stray` once it is
    /// 1 m from its start].
    #[arg(long)]
    pub object: Option<String>,
    /// Where the children branch: `first-impact` (just after the object's first impact) or
    /// `away:<metres>` (the first frame its centre is that far from its start).
    #[arg(long)]
    pub branch: Option<String>,
    /// Root worlds (seeds 1..=N) to refine.
    #[arg(long, default_value_t = 3)]
    pub parents: u64,
    /// Children per root world.
    #[arg(long, default_value_t = 8)]
    pub children: u64,
    /// Print one JSON line per scene instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// One scene's line.
#[derive(Debug, Clone, serde::Serialize)]
pub struct RefineBench {
    pub scene: String,
    /// How the object was chosen (`fastest`, `farthest`, or as given) and where the children
    /// branch.
    pub case: String,
    /// The refined body of the first root world.
    pub object: String,
    pub bodies: usize,
    pub parents: u64,
    pub refined_worlds: u64,
    /// Median frame at which the children branch (just after the object's first impact).
    pub branch_frame_median: u32,
    pub frames_median: u32,
    pub refine_core_s_per_world: f64,
    pub full_core_s_per_world: f64,
    pub speedup: f64,
    /// Bodies re-simulated ÷ bodies, mean over the children.
    pub active_fraction_mean: f64,
    pub stored_bytes_per_refined_world: f64,
    pub stored_bytes_per_full_world: f64,
    pub parent_regen_s: f64,
    /// Median length of the refined and of the fresh worlds (they end when every body has
    /// rested for the scene's `rest_hold`, or at its end time): a refinement that left bodies
    /// jittering against replayed neighbours would show here.
    pub refined_world_s_median: f64,
    pub full_world_s_median: f64,
    /// Refined worlds that came to rest before the end time, ÷ refined worlds.
    pub refined_rested_fraction: f64,
}

impl Summary for RefineBench {
    fn table(&self) -> String {
        fields_table(self)
    }
}

/// Runs `mwb bench refine`: one line per scene and case, printed as soon as it is measured.
pub async fn run(args: RefineArgs) -> Result<()> {
    let scenes = if args.scenes.is_empty() {
        vec!["tower".to_owned(), "pachinko".to_owned()]
    } else {
        args.scenes.clone()
    };
    if args.parents == 0 || args.children == 0 {
        bail!("--parents and --children must be at least 1");
    }
    let cases = match (&args.object, &args.branch) {
        (None, None) => vec![
            Case::parse("fastest", "first-impact")?,
            Case::parse("stray", "away:1")?,
        ],
        (o, b) => vec![Case::parse(
            o.as_deref().unwrap_or("fastest"),
            b.as_deref().unwrap_or("first-impact"),
        )?],
    };
    for scene in scenes {
        for case in &cases {
            let (a, scene, case) = (args.clone(), scene.clone(), case.clone());
            let line = tokio::task::spawn_blocking(move || measure(&scene, &case, &a)).await??;
            crate::output::print(&line, args.json)?;
        }
    }
    Ok(())
}

/// Which body is refined, and from where.
#[derive(Debug, Clone)]
struct Case {
    object: Object,
    branch: Branch,
}

#[derive(Debug, Clone)]
enum Object {
    Fastest,
    Farthest,
    Stray,
    Named(String),
}

#[derive(Debug, Clone, Copy)]
enum Branch {
    FirstImpact,
    Away(f64),
}

impl Case {
    fn parse(object: &str, branch: &str) -> Result<Self> {
        let object = match object {
            "fastest" => Object::Fastest,
            "farthest" => Object::Farthest,
            "stray" => Object::Stray,
            other => Object::Named(other.to_owned()),
        };
        let branch = match branch.split_once(':') {
            None if branch == "first-impact" => Branch::FirstImpact,
            Some(("away", m)) => match m.parse::<f64>() {
                Ok(m) if m > 0.0 && m.is_finite() => Branch::Away(m),
                _ => bail!("--branch {branch:?}: away:<metres> needs a positive distance"),
            },
            _ => bail!("--branch {branch:?}: expected first-impact or away:<metres>"),
        };
        Ok(Self { object, branch })
    }

    fn label(&self) -> String {
        let o = match &self.object {
            Object::Fastest => "fastest".to_owned(),
            Object::Farthest => "farthest".to_owned(),
            Object::Stray => "stray".to_owned(),
            Object::Named(n) => n.clone(),
        };
        match self.branch {
            Branch::FirstImpact => format!("{o}, from its first impact"),
            Branch::Away(m) => format!("{o}, from {m} m away from its start"),
        }
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => v[n / 2],
        n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

/// The refined body of one root world (`motion`: its exact motion).
fn pick_object(
    scene: &mwb_core::scene::Scene,
    object: &Object,
    motion: &mwb_sampler::refine::ExactMotion,
) -> Result<usize> {
    let n = scene.bodies.len();
    Ok(match object {
        Object::Named(arg) => match scene.bodies.iter().position(|b| &b.name == arg) {
            Some(i) => i,
            None => match arg.parse::<usize>() {
                Ok(i) if i < n => i,
                _ => bail!(
                    "--object {arg:?}: no such body (the scene has {n} bodies; give a name, an \
                     index, fastest or farthest)"
                ),
            },
        },
        Object::Fastest => {
            let speed = |i: usize| perturb::norm(scene.bodies[i].linvel);
            (0..n).fold(0, |best, i| if speed(i) > speed(best) { i } else { best })
        }
        Object::Farthest | Object::Stray => {
            let candidate = |i: usize| {
                !matches!(object, Object::Stray)
                    || (perturb::norm(scene.bodies[i].linvel) == 0.0
                        && perturb::norm(scene.bodies[i].angvel) == 0.0)
            };
            let last = motion.frame_count().saturating_sub(1);
            let moved = |i: usize| match (motion.pose(0, i), motion.pose(last, i)) {
                (Some(a), Some(b)) => {
                    perturb::norm(std::array::from_fn(|k| b.position[k] - a.position[k]))
                }
                _ => 0.0,
            };
            let Some(first) = (0..n).find(|&i| candidate(i)) else {
                bail!("--object stray: every body of the scene starts moving");
            };
            (0..n).filter(|&i| candidate(i)).fold(first, |best, i| {
                if moved(i) > moved(best) { i } else { best }
            })
        }
    })
}

fn measure(scene_arg: &str, case: &Case, args: &RefineArgs) -> Result<RefineBench> {
    let (file, text) = mwb_node::job::load_scene(scene_arg)?;
    let template = SceneTemplate::parse(&text, &file)?;
    let opts = RunOptions::default();
    let (mut full_s, mut full_bytes) = (Vec::new(), Vec::new());
    let (mut refine_s, mut refine_bytes, mut regen_s) = (Vec::new(), Vec::new(), Vec::new());
    let (mut active, mut branch, mut frames) = (Vec::new(), Vec::new(), Vec::new());
    let (mut refined_len, mut rested) = (Vec::new(), 0u64);
    let mut first_object = None;
    let bodies = template.instantiate(1).bodies.len();
    for seed in 1..=args.parents {
        // A fresh world, as a sampler computes it.
        let t = cpu_time();
        let full = run_world(&template, seed, opts, &mut |_| ControlFlow::Continue(()))
            .with_context(|| format!("{file}: world {seed}"))?;
        full_s.push(cpu_time() - t);
        full_bytes.push(full.payload_bytes as f64);
        frames.push(f64::from(full.frame_count));

        // Its exact motion, to pick the object and the branch frame.
        let lineage = Lineage::root(seed);
        let whole = regenerate(&template, &lineage, &BranchAt::Frame(0))?;
        let object = pick_object(whole.scene(), &case.object, whole.motion())?;
        let name = whole.scene().bodies[object].name.clone();
        first_object.get_or_insert_with(|| name.clone());
        let s = &whole.scene().settings;
        let m = whole.motion();
        let at = match case.branch {
            Branch::FirstImpact => (1..m.frame_count())
                .find(|&f| {
                    let (Some((a, _)), Some((b, _))) =
                        (m.velocities(f - 1, object), m.velocities(f, object))
                    else {
                        return false;
                    };
                    perturb::norm(perturb::impact_rate(a, b, s.gravity, s.dt)) > s.c_v
                })
                .map(|f| (f + 1).min(m.frame_count() - 1)),
            Branch::Away(metres) => {
                let start = m.pose(0, object).map(|p| p.position).unwrap_or_default();
                (0..m.frame_count()).find(|&f| {
                    m.pose(f, object).is_some_and(|p| {
                        perturb::norm(std::array::from_fn(|k| p.position[k] - start[k])) >= metres
                    })
                })
            }
        };
        let Some(at) = at else {
            bail!(
                "{file}: world {seed}: {name} never reaches the branch ({}); pick another \
                 --object or --branch",
                case.label()
            );
        };
        drop(whole);

        let t = cpu_time();
        let parent = regenerate(&template, &lineage, &BranchAt::Frame(at))?;
        regen_s.push(cpu_time() - t);
        branch.push(f64::from(at));
        for c in 0..args.children {
            let t = cpu_time();
            let child = parent.refine(
                &[object as u32],
                seed.wrapping_mul(1_000_003).wrapping_add(c + 1),
                opts,
                &mut |_| ControlFlow::Continue(()),
            )?;
            refine_s.push(cpu_time() - t);
            refine_bytes.push(child.summary.payload_bytes as f64);
            active.push(child.active_fraction());
            refined_len.push(f64::from(child.summary.frame_count - 1) * child.summary.frame_dt);
            rested += u64::from(child.summary.rested);
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let (refine, full) = (median(refine_s), median(full_s));
    let dt = template.instantiate(1).settings.dt;
    let full_len: Vec<f64> = frames.iter().map(|f| (f - 1.0) * dt).collect();
    Ok(RefineBench {
        scene: file,
        case: case.label(),
        object: first_object.unwrap_or_default(),
        bodies,
        parents: args.parents,
        refined_worlds: args.parents * args.children,
        branch_frame_median: median(branch) as u32,
        frames_median: median(frames) as u32,
        refine_core_s_per_world: refine,
        full_core_s_per_world: full,
        speedup: full / refine,
        active_fraction_mean: mean(&active),
        stored_bytes_per_refined_world: mean(&refine_bytes),
        stored_bytes_per_full_world: mean(&full_bytes),
        parent_regen_s: median(regen_s),
        refined_world_s_median: median(refined_len),
        full_world_s_median: median(full_len),
        refined_rested_fraction: rested as f64 / (args.parents * args.children) as f64,
    })
}
