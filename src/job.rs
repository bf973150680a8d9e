//! `mwb job submit|list|cancel`: sampling jobs over the bus.

use crate::bus::BusArgs;
use crate::client;
use crate::output::Summary;
use anyhow::{Result, bail};
use clap::Subcommand;
use mwb_core::keys::Keys;
use mwb_proto::v1::JobState;
use std::fmt::Write as _;
use std::time::Duration;

#[derive(Debug, Subcommand)]
pub enum JobCommand {
    /// Submit a sampling job.
    Submit(SubmitArgs),
    /// List jobs known to the stores.
    List {
        #[command(flatten)]
        bus: BusArgs,
        /// Print the jobs as one JSON line (an array).
        #[arg(long)]
        json: bool,
    },
    /// Cancel a job.
    Cancel {
        #[command(flatten)]
        bus: BusArgs,
        id: String,
    },
}

/// Arguments of `mwb job submit`.
#[derive(Debug, Clone, clap::Args)]
pub struct SubmitArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// Scene file or shipped scene name.
    pub scene: String,
    #[arg(long, default_value_t = 100)]
    pub worlds: u32,
    /// Job id [default: <scene name>-<time>].
    #[arg(long)]
    pub id: Option<String>,
    #[command(flatten)]
    pub follow: client::FollowArgs,
    #[command(flatten)]
    pub motion: client::MotionArgs,
}

/// Runs `mwb job …`.
pub async fn run(command: JobCommand) -> Result<()> {
    match command {
        JobCommand::Submit(args) => submit(args).await,
        JobCommand::List { bus, json } => list(&bus, json).await,
        JobCommand::Cancel { bus, id } => cancel(&bus, &id).await,
    }
}

/// A submitted job's state, as `mwb job submit --json` prints it (fields in the order that
/// line has always had).
#[derive(Debug, Clone, serde::Serialize)]
pub struct Submitted {
    pub closed: bool,
    pub done: u32,
    pub job: String,
    pub rejected: u32,
    pub target: u32,
    pub worlds_per_s: f64,
}

impl Submitted {
    fn new(job: &str, st: &JobState) -> Self {
        Self {
            closed: st.closed,
            done: st.worlds_done,
            job: job.to_owned(),
            rejected: st.worlds_rejected,
            target: st.target_worlds,
            worlds_per_s: client::job_rate(st),
        }
    }
}

impl Summary for Submitted {
    fn table(&self) -> String {
        format!(
            "job {}: {}/{} worlds, {:.1} worlds/s, {} rejected\n",
            self.job, self.done, self.target, self.worlds_per_s, self.rejected
        )
    }
}

async fn submit(args: SubmitArgs) -> Result<()> {
    let keys = Keys::new(&args.bus.space)?;
    let (file, text) = client::load_scene(&args.scene)?;
    let text = args.motion.resolve_scene(&file, &text)?;
    let mut job = client::make_job(&file, &text, args.worlds, args.follow.priority, args.id)?;
    args.motion.apply(&mut job);
    let session = args.bus.open(args.bus.client_default()).await?;
    let mut state = client::submit_job(&session, &keys, &job).await?;
    if !args.follow.json {
        eprintln!(
            "submitted job {} ({} worlds of {})",
            job.id, args.worlds, file
        );
    }
    // Said at once, not after a timeout: a job nobody takes waits for ever.
    let role = crate::stall::worker_role(job.kind());
    let alive = client::alive_nodes(&session, &keys).await?;
    if !alive.iter().any(|(r, _)| r == role) {
        eprintln!(
            "warning: no {role} node is alive in space {:?}: the job waits until one joins \
             (`mwb {role} --connect <store endpoint>`){}",
            args.bus.space,
            if args.follow.wait {
                format!(
                    "; --wait gives up in {} s",
                    crate::stall::STALL_GRACE.as_secs()
                )
            } else {
                String::new()
            }
        );
    }
    if args.follow.wait {
        let bar = (!args.follow.json && std::io::IsTerminal::is_terminal(&std::io::stderr()))
            .then(|| client::progress_bar(args.worlds));
        let waited = client::wait_job(
            &session,
            &keys,
            &job.id,
            args.follow.timeout.map(Duration::from_secs),
            |st| {
                if let Some(b) = &bar {
                    b.set_position(u64::from(st.worlds_done));
                }
            },
        )
        .await;
        if let Some(b) = bar {
            b.finish_and_clear();
        }
        state = match waited {
            Ok(st) => st,
            Err(e) => {
                crate::bus::close(session).await;
                return Err(e);
            }
        };
    }
    crate::bus::close(session).await;
    let submitted = Submitted::new(&job.id, &state);
    if args.follow.json || args.follow.wait {
        crate::output::print(&submitted, args.follow.json)
    } else {
        // Without --wait the id is the result, for scripts to follow the job by.
        crate::output::out(&format!("{}\n", job.id))
    }
}

/// One job in `mwb job list --json` (fields in the order that line has always had).
#[derive(Debug, Clone, serde::Serialize)]
pub struct Listed {
    pub cancelled: bool,
    pub closed: bool,
    pub done: u32,
    pub job: String,
    pub target: u32,
}

/// The jobs the stores know.
#[derive(Debug, Clone, serde::Serialize)]
#[serde(transparent)]
pub struct JobList(pub Vec<Listed>);

impl Summary for JobList {
    fn table(&self) -> String {
        let mut t = String::new();
        for j in &self.0 {
            let _ = writeln!(
                t,
                "{:<40} {:>6}/{:<6} {}",
                j.job,
                j.done,
                j.target,
                client::state_name(j.closed, j.cancelled)
            );
        }
        t
    }
}

async fn list(bus: &BusArgs, json: bool) -> Result<()> {
    let keys = Keys::new(&bus.space)?;
    let session = bus.open(bus.client_default()).await?;
    let jobs = client::list_jobs(&session, &keys).await;
    crate::bus::close(session).await;
    let list = JobList(
        jobs?
            .into_iter()
            .map(|s| Listed {
                cancelled: s.cancelled,
                closed: s.closed,
                done: s.worlds_done,
                job: s.job_id,
                target: s.target_worlds,
            })
            .collect(),
    );
    crate::output::print(&list, json)
}

async fn cancel(bus: &BusArgs, id: &str) -> Result<()> {
    let keys = Keys::new(&bus.space)?;
    let session = bus.open(bus.client_default()).await?;
    let st = client::cancel_job(&session, &keys, id).await;
    crate::bus::close(session).await;
    let st = st?;
    if !st.cancelled {
        bail!("job {id} closed before the cancel arrived");
    }
    crate::output::out(&format!(
        "cancelled {id} at {}/{} worlds\n",
        st.worlds_done, st.target_worlds
    ))
}
