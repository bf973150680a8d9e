//! `mwb certs`: a certificate authority and one TLS bundle per machine, for the TLS + access
//! control configurations in `deploy/` ([`crate::certs`] does the work).

use crate::certs::{self, Overwrite, Plan};
use anyhow::{Context, Result};
use std::path::PathBuf;

/// Arguments of `mwb certs`.
#[derive(Debug, Clone, clap::Args)]
pub struct CertsArgs {
    /// Directory to write into (created if missing): ca.pem, ca-key.pem (keep it off the
    /// nodes), and one directory per machine to install as /etc/mwb/tls/.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// A name or address the store is reached at (repeatable; every shard's host). Clients
    /// check the one they connect to against these.
    #[arg(long = "store-host", value_name = "HOST", required = true)]
    pub store_host: Vec<String>,
    /// Also accept the store at 127.0.0.1, ::1 and localhost (one-machine trials).
    #[arg(long)]
    pub loopback: bool,
    /// Worker bundles (samplers and reverse nodes): worker-0 … worker-(N-1).
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub nodes: u32,
    /// Client bundles (CLI and viewer): client-0 … client-(N-1).
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub clients: u32,
    /// Validity of the node certificates in days (the authority lives at least 10 years).
    #[arg(long, default_value_t = certs::DEFAULT_DAYS)]
    pub days: u32,
    /// Replace files that exist (otherwise the first one found is named and nothing is
    /// written).
    #[arg(long)]
    pub force: bool,
}

/// Issues the certificates and writes them.
pub fn run(args: CertsArgs) -> Result<()> {
    let mut store_hosts = args.store_host;
    if args.loopback {
        for h in ["127.0.0.1", "::1", "localhost"] {
            if !store_hosts.iter().any(|s| s == h) {
                store_hosts.push(h.to_owned());
            }
        }
    }
    let plan = Plan {
        store_hosts,
        workers: args.nodes,
        clients: args.clients,
        days: args.days,
    };
    let bundle = certs::generate(&plan)?;
    let overwrite = if args.force {
        Overwrite::Replace
    } else {
        Overwrite::Refuse
    };
    let written = certs::write_bundle(&bundle, &args.out, overwrite)
        .with_context(|| format!("writing certificates into {}", args.out.display()))?;
    crate::output::out(&format!(
        "wrote {} files into {}: copy each machine's directory (store, worker-K, client-K, query, \
         recorder) to its {}; keep ca-key.pem off the nodes\n",
        written.len(),
        args.out.display(),
        certs::INSTALL_DIR
    ))
}
