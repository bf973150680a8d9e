//! `mwb sampler`: a sampler node; it joins open jobs at any time.

use crate::bus::BusArgs;
use anyhow::Result;

/// Arguments of `mwb sampler`.
#[derive(Debug, Clone, clap::Args)]
pub struct SamplerArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// Worker threads [default: all cores].
    #[arg(long)]
    pub workers: Option<usize>,
    /// This node's id, unique in the space [default: the session's random zenoh id]. World
    /// seeds are derived from (job id, node id, the node's world counter): a named sampler
    /// gives the same seeds to the same job id every time.
    #[arg(long)]
    pub node_id: Option<String>,
}

/// Runs the sampler until Ctrl-C.
pub async fn run(args: SamplerArgs) -> Result<()> {
    let bus = args.bus;
    let session = bus.open(bus.client_default()).await?;
    let mut cfg = mwb_sampler::SamplerConfig {
        space: bus.space.clone(),
        ..Default::default()
    };
    if let Some(w) = args.workers {
        cfg.workers = w.max(1);
    }
    if let Some(id) = args.node_id {
        mwb_core::keys::check_identifier("--node-id", &id)?;
        cfg.node_id = Some(id);
    }
    let sampler = mwb_sampler::run_sampler(session.clone(), cfg).await?;
    crate::bus::until_ctrl_c().await;
    sampler.stop().await;
    crate::bus::close(session).await;
    Ok(())
}
