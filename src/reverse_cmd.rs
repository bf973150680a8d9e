//! `mwb reverse`: backward worlds (ch. 5) over the bus.
//!
//! * `mwb reverse [--connect …] [--workers N]` runs a reverse node until Ctrl-C: it takes
//!   reverse jobs (and only those) from the bus and publishes their worlds to the stores.
//! * `mwb reverse --scene word --worlds 20 [--connect …]` runs a node *and* submits a reverse
//!   job of the final-state scene, follows it until the store holds the worlds, prints a
//!   summary and exits.
//! * `mwb reverse --scene word --worlds 20 --submit [--wait]` only submits the job, for reverse
//!   nodes that run elsewhere.
//!
//! Every form needs a store on the bus (`mwb store`); the worlds are browsed like any others.
//! A scene's optional `[reverse]` table (`mwb_reverse::settings_toml`) asks for a mixed run
//! (`mode = "mixed"`, `forward_time`: the state is an intermediate frame, §5.4.4) and per-body
//! hints (`[[reverse.hint]]`); the nodes read it from the job's scene text.

use crate::bus::BusArgs;
use crate::client::{self, QualityArg};
use crate::output::Summary;
use anyhow::{Context, Result, bail};
use mwb_core::keys::Keys;
use mwb_proto::v1::{Job, JobKind, JobState, Quality};
use mwb_reverse::scene::builtin;
use mwb_reverse::settings_toml::parse_reverse_scene;
use std::time::{Duration, Instant};

/// Arguments of `mwb reverse`.
#[derive(Debug, Clone, clap::Args)]
pub struct ReverseArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// Final-state scene: a TOML file, or a shipped reverse scene (word, stack, balls,
    /// balls_small, crash, crash_mixed, gate, lorem). The run goes back `[settings] end_time` seconds; a `[reverse]`
    /// table may make it mixed and add hints. Without it, the node serves reverse jobs from the
    /// bus until Ctrl-C.
    #[arg(long)]
    pub scene: Option<String>,
    /// Worlds to sample.
    #[arg(long, default_value_t = 20)]
    pub worlds: u32,
    /// Only submit the job (reverse nodes elsewhere run it) and print its id.
    #[arg(long, requires = "scene")]
    pub submit: bool,
    /// With --submit: follow the job until it closes.
    #[arg(long, requires = "submit")]
    pub wait: bool,
    /// Give up waiting after this many seconds.
    #[arg(long)]
    pub timeout: Option<u64>,
    /// Worker threads of the node [default: all cores].
    #[arg(long)]
    pub workers: Option<usize>,
    #[arg(long, default_value_t = 0)]
    pub priority: i32,
    /// Job id [default: <scene name>-<time>].
    #[arg(long)]
    pub id: Option<String>,
    /// Codec error bounds: draft 5 mm / 5 mrad, standard 1 mm / 1 mrad, final 0.1 mm / 0.1 mrad.
    #[arg(long, value_enum, default_value_t = QualityArg::Standard)]
    pub quality: QualityArg,
    /// Print the result as one JSON line.
    #[arg(long)]
    pub json: bool,
}

/// Shipped reverse scenes with a `[reverse]` table, which the plain scene parser (and so
/// `builtin::ALL`'s users) refuses: only `mwb reverse` and the reverse nodes read them.
pub const WITH_REVERSE_TABLE: &[(&str, &str)] = &[("crash_mixed", builtin::CRASH_MIXED)];

/// Reads a final-state scene argument: a path to a TOML file, or the name of a shipped
/// reverse scene (`scenes/reverse/`).
pub fn load_reverse_scene(arg: &str) -> Result<(String, String)> {
    let path = std::path::Path::new(arg);
    if path.exists() {
        let bytes =
            std::fs::read(path).with_context(|| format!("reading scene {}", path.display()))?;
        let text = mwb_core::scene::decode_utf8(arg, bytes)?;
        // Mesh statics become triangle meshes the stepper takes; mesh bodies become compounds,
        // which it refuses by name.
        let dir = path.parent().unwrap_or(std::path::Path::new("."));
        let resolved = mwb_mesh::resolve(arg, &text, dir)?;
        return Ok((arg.to_owned(), resolved.text));
    }
    let name = arg.trim_end_matches(".toml");
    let name = name.rsplit('/').next().unwrap_or(name);
    let shipped = || builtin::ALL.iter().chain(WITH_REVERSE_TABLE);
    match shipped().find(|(n, _)| *n == name) {
        Some((n, text)) => Ok((format!("scenes/reverse/{n}.toml"), (*text).to_owned())),
        None => bail!(
            "scene {arg:?}: no such file, and not a shipped reverse scene ({})",
            shipped().map(|(n, _)| *n).collect::<Vec<_>>().join(", ")
        ),
    }
}

/// A reverse job for `target` worlds of the final-state scene text. Checks first that the
/// reverse stepper can build the scene, that its `[reverse]` table is valid and that its state
/// is one a backward run may start from (`mwb_reverse::validate`: overlapping bodies and violated
/// joints are refused, a body at rest in mid-air is warned about, by name), so a bad scene fails
/// here and not on every node.
pub fn make_reverse_job(
    file: &str,
    text: &str,
    target: u32,
    priority: i32,
    id: Option<String>,
    quality: QualityArg,
) -> Result<Job> {
    let (template, _) =
        parse_reverse_scene(text, file).with_context(|| format!("{file}: not a reverse scene"))?;
    let warnings = mwb_reverse::validate::check_scene(&template.instantiate(0))
        .with_context(|| format!("{file}: refused as the given state of a backward run"))?;
    for w in warnings {
        eprintln!("mwb reverse: {file}: warning: {w}");
    }
    // The job carries the whole text, `[reverse]` table included, for the nodes.
    let mut job = client::make_job(file, text, target, priority, id)?;
    job.kind = JobKind::Reverse as i32;
    job.quality = Quality::from(quality) as i32;
    Ok(job)
}

/// The node's configuration for these arguments.
fn node_config(args: &ReverseArgs) -> mwb_reverse::ReverseConfig {
    let mut cfg = mwb_reverse::ReverseConfig {
        space: args.bus.space.clone(),
        ..Default::default()
    };
    if let Some(w) = args.workers {
        cfg.workers = w.max(1);
    }
    cfg
}

/// What `mwb reverse --scene` prints.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ReverseSummary {
    pub job: String,
    pub scene: String,
    pub worlds: u32,
    pub target: u32,
    pub rejected: u32,
    pub seconds: f64,
    pub worlds_per_s: f64,
}

fn summary(job: &Job, file: &str, st: &JobState, seconds: f64) -> ReverseSummary {
    ReverseSummary {
        job: job.id.clone(),
        scene: file.to_owned(),
        worlds: st.worlds_done,
        target: st.target_worlds,
        rejected: st.worlds_rejected,
        seconds,
        worlds_per_s: f64::from(st.worlds_done) / seconds.max(1e-9),
    }
}

impl Summary for ReverseSummary {
    fn table(&self) -> String {
        format!(
            "job {}: {}/{} backward worlds of {} in {:.2} s ({:.2} worlds/s), {} rejected\n",
            self.job,
            self.worlds,
            self.target,
            self.scene,
            self.seconds,
            self.worlds_per_s,
            self.rejected
        )
    }
}

/// What `mwb reverse --submit` prints without `--wait`: the job to follow.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Submitted {
    pub job: String,
}

impl Summary for Submitted {
    fn table(&self) -> String {
        format!("{}\n", self.job)
    }
}

/// Runs `mwb reverse`.
pub async fn run(args: ReverseArgs) -> Result<()> {
    let keys = Keys::new(&args.bus.space)?;
    let Some(scene) = &args.scene else {
        // Node only.
        let session = args.bus.open(args.bus.client_default()).await?;
        let node = mwb_reverse::run_reverse(session.clone(), node_config(&args)).await?;
        eprintln!(
            "mwb reverse: node {} serving reverse jobs in space {:?}; Ctrl-C stops it",
            node.node_id(),
            args.bus.space
        );
        crate::bus::until_ctrl_c().await;
        node.stop().await;
        crate::bus::close(session).await;
        return Ok(());
    };
    let (file, text) = load_reverse_scene(scene)?;
    let job = make_reverse_job(
        &file,
        &text,
        args.worlds,
        args.priority,
        args.id.clone(),
        args.quality,
    )?;
    let session = args.bus.open(args.bus.client_default()).await?;
    let result = with_scene(&args, &session, &keys, &job, &file).await;
    crate::bus::close(session).await;
    result
}

/// `mwb reverse --scene …`: submit (and follow) the job, with a node in this process unless
/// `--submit`.
async fn with_scene(
    args: &ReverseArgs,
    session: &zenoh::Session,
    keys: &Keys,
    job: &Job,
    file: &str,
) -> Result<()> {
    let timeout = args.timeout.map(Duration::from_secs);
    let started = Instant::now();
    if args.submit {
        client::submit_job(session, keys, job).await?;
        if !args.wait {
            let submitted = Submitted {
                job: job.id.clone(),
            };
            return crate::output::print(&submitted, args.json);
        }
        let st = client::wait_job(session, keys, &job.id, timeout, |_| {}).await?;
        let s = summary(job, file, &st, started.elapsed().as_secs_f64());
        return crate::output::print(&s, args.json);
    }
    let node = mwb_reverse::run_reverse(session.clone(), node_config(args)).await?;
    let st = async {
        client::submit_job(session, keys, job).await?;
        client::wait_job(session, keys, &job.id, timeout, |_| {}).await
    }
    .await;
    let seconds = started.elapsed().as_secs_f64();
    node.stop().await;
    crate::output::print(&summary(job, file, &st?, seconds), args.json)
}
