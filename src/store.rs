//! `mwb store`: a store node (by default the zenoh router other nodes connect to) and, on the
//! shard that answers job states, the browsing coordinator.

use crate::bus::{BusArgs, Mode};
use anyhow::Result;

/// Arguments of `mwb store`.
#[derive(Debug, Clone, clap::Args)]
pub struct StoreArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// Refuse new worlds past this many MiB in memory.
    #[arg(long, default_value_t = mwb_store::DEFAULT_MEMORY_CAP_MIB)]
    pub memory_cap_mib: u64,
    /// This store's shard when several split the worlds: INDEX/COUNT, e.g. 1/3. Start every
    /// shard before submitting jobs; shard 0 answers job states.
    #[arg(long, default_value = "0/1")]
    pub shard: String,
    /// Do not run the browsing coordinator (node-query) in this process. By default shard 0
    /// runs it; with `mwb query serve` elsewhere, pass this.
    #[arg(long)]
    pub no_query: bool,
}

/// Runs the store (and node-query) until Ctrl-C.
pub async fn run(args: StoreArgs) -> Result<()> {
    let StoreArgs {
        bus,
        memory_cap_mib,
        shard,
        no_query,
    } = args;
    let shard = mwb_store::ShardSpec::parse(&shard)?;
    let session = bus.open(Mode::Router).await?;
    let store = mwb_store::run_store(
        session.clone(),
        mwb_store::StoreConfig {
            space: bus.space.clone(),
            memory_cap_bytes: memory_cap_mib << 20,
            shard,
            ..Default::default()
        },
    )
    .await?;
    let query = if shard.is_authority() && !no_query {
        Some(
            mwb_query::run_query(
                session.clone(),
                mwb_query::QueryConfig {
                    space: bus.space.clone(),
                    node_id: Some(format!("{}-query", store.node_id())),
                    ..Default::default()
                },
            )
            .await?,
        )
    } else {
        None
    };
    tracing::info!(
        node = store.node_id(),
        shard = %format!("{}/{}", shard.index, shard.count),
        query = query.is_some(),
        "store running; Ctrl-C stops it"
    );
    crate::bus::until_ctrl_c().await;
    if let Some(q) = query {
        q.stop();
    }
    store.stop();
    crate::bus::close(session).await;
    Ok(())
}
