//! `mwb store`: a store node (by default the zenoh router other nodes connect to) and, on the
//! shard that answers job states, the browsing coordinator.

use crate::bus::{BusArgs, Mode};
use anyhow::{Context, Result};

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
    /// Make the store durable: every world is written to an MCAP journal in DIR (fsync'ed
    /// before the store acknowledges it) and read back when the store starts again. Damaged
    /// journal files are read up to the damage; the log says what was skipped.
    #[arg(long, value_name = "DIR")]
    pub journal: Option<std::path::PathBuf>,
    /// Start with the worlds of a recording (`mwb record`, `mwb demo --record`, or a journal
    /// file); repeatable. A damaged recording is loaded up to the damage.
    #[arg(long, value_name = "FILE")]
    pub load: Vec<std::path::PathBuf>,
    /// Samplers send each world's browsing index with it; the store takes it after checking
    /// its form, and indexes one world in this many itself too and compares (a difference is
    /// counted in `mwb status` and logged, and the store's own index kept). 1: every world,
    /// 0: none.
    #[arg(long, default_value_t = mwb_store::DEFAULT_VERIFY_INDEX_EVERY, value_name = "N")]
    pub verify_index_every: u32,
}

/// Runs the store (and node-query) until Ctrl-C.
pub async fn run(args: StoreArgs) -> Result<()> {
    let StoreArgs {
        bus,
        memory_cap_mib,
        shard,
        no_query,
        journal,
        load,
        verify_index_every,
    } = args;
    let shard = mwb_store::ShardSpec::parse(&shard)?;
    for f in &load {
        // A missing file is a typo, not damage: refuse to start.
        std::fs::metadata(f).with_context(|| format!("--load {}", f.display()))?;
    }
    let session = bus.open(Mode::Router).await?;
    let store = mwb_store::run_store(
        session.clone(),
        mwb_store::StoreConfig {
            space: bus.space.clone(),
            memory_cap_bytes: memory_cap_mib << 20,
            shard,
            journal,
            load,
            verify_index_every,
            ..Default::default()
        },
    )
    .await?;
    report_start(store.start_report());
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

/// What the journal and the recordings gave back, on stderr (the log has it per file too).
fn report_start(r: &mwb_store::StartReport) {
    for f in r.journal.iter().chain(&r.recordings) {
        if f.damage.is_some() && !f.cut_short {
            eprintln!("damaged: {}", f.describe());
        }
    }
    if !r.journal.is_empty() || !r.recordings.is_empty() {
        let unknown: u64 = r
            .journal
            .iter()
            .chain(&r.recordings)
            .flat_map(|f| f.unknown_channels.values())
            .sum();
        eprintln!(
            "loaded {} worlds from the journal ({} files) and {} from {} recordings in {:.2} s; \
             refused {}, partial discarded {}, damaged files {}, bytes skipped {}, messages on \
             unknown channels {}",
            r.worlds_from_journal,
            r.journal.len(),
            r.worlds_from_recordings,
            r.recordings.len(),
            r.seconds,
            r.worlds_refused,
            r.partial_discarded,
            r.damaged_files(),
            r.skipped_bytes(),
            unknown
        );
    }
}
