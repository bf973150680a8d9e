//! `mwb status`: live nodes, job progress and throughput.

use crate::bus::BusArgs;
use crate::client::{self, Status};
use crate::output::Summary;
use anyhow::Result;
use mwb_core::keys::Keys;
use std::fmt::Write as _;
use std::time::Duration;

/// Arguments of `mwb status`.
#[derive(Debug, Clone, clap::Args)]
pub struct StatusArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// Print the status as one JSON line.
    #[arg(long)]
    pub json: bool,
}

/// Gathers the status over the bus and prints it.
pub async fn run(args: StatusArgs) -> Result<()> {
    let keys = Keys::new(&args.bus.space)?;
    let session = args.bus.open(args.bus.client_default()).await?;
    let st = client::status(&session, &keys, Duration::from_millis(1500)).await;
    crate::bus::close(session).await;
    crate::output::print(&st?, args.json)
}

impl Summary for Status {
    fn table(&self) -> String {
        let mut t = format!(
            "{:<8} {:<40} {:>8} {:>9} {:>12}\n",
            "ROLE", "NODE", "WORLDS", "WORLDS/S", "MEMORY MiB"
        );
        for n in &self.nodes {
            let _ = writeln!(
                t,
                "{:<8} {:<40} {:>8} {:>9.1} {:>12.1}",
                n.role,
                n.node,
                n.worlds,
                n.worlds_per_s,
                n.memory_bytes as f64 / f64::from(1u32 << 20)
            );
        }
        let _ = writeln!(t);
        let _ = writeln!(
            t,
            "{:<40} {:>12} {:>8} {:>9}",
            "JOB", "DONE", "STATE", "WORLDS/S"
        );
        for j in &self.jobs {
            let _ = writeln!(
                t,
                "{:<40} {:>5}/{:<6} {:>8} {:>9.1}",
                j.job,
                j.done,
                j.target,
                client::state_name(j.closed, j.cancelled),
                j.worlds_per_s
            );
            if let Some(why) = &j.stalled {
                let _ = writeln!(t, "  cannot complete: {why}");
            }
        }
        t
    }
}
