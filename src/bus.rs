//! Opening a zenoh session the way every `mwb` node does (zenoh's examples' `CommonArgs`).

use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use std::path::PathBuf;

/// zenoh session mode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Mode {
    Peer,
    Client,
    Router,
}

impl Mode {
    fn as_str(self) -> &'static str {
        match self {
            Mode::Peer => "peer",
            Mode::Client => "client",
            Mode::Router => "router",
        }
    }
}

/// Where `mwb store` and `mwb demo --stay` listen, and so where every client command connects,
/// unless told otherwise (zenoh's usual port, loopback only).
pub const DEFAULT_ENDPOINT: &str = "tcp/127.0.0.1:7447";

/// The environment variable client commands take their endpoints from when `--connect` is not
/// given (comma-separated). `mwb demo` and `mwb store` do not read it: a demo must not join
/// another bus by accident, and a store is where the others connect.
pub const CONNECT_ENV: &str = "MWB_CONNECT";

/// Bus options shared by every subcommand.
#[derive(Debug, Clone, Args)]
pub struct BusArgs {
    /// Endpoint to connect to (repeatable), e.g. tcp/10.0.0.5:7447. Client commands (job,
    /// status, query, sampler, reverse, record, replay, world) take $MWB_CONNECT
    /// (comma-separated) when it is not given, else tcp/127.0.0.1:7447.
    #[arg(short = 'e', long, value_name = "ENDPOINT")]
    pub connect: Vec<String>,
    /// Endpoint to listen on (repeatable), e.g. tcp/0.0.0.0:7447.
    #[arg(short = 'l', long, value_name = "ENDPOINT")]
    pub listen: Vec<String>,
    /// A zenoh configuration file (json5); --connect/--listen/--mode override it.
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Session mode [default: router for `mwb store`, client when --connect is given, else peer].
    #[arg(long, value_enum)]
    pub mode: Option<Mode>,
    /// Browsing space: all keys live under mwb/<space>/.
    #[arg(long, default_value = mwb_core::keys::DEFAULT_SPACE, env = "MWB_SPACE")]
    pub space: String,
    /// Enable multicast scouting (off by default: nodes find each other by --connect).
    #[arg(long)]
    pub multicast: bool,
}

/// Where a client command's endpoints came from, for the error that says nothing answered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EndpointSource {
    Flag,
    Env,
    Default,
}

impl BusArgs {
    /// The endpoints a session in `mode` connects to, and where they came from: `--connect`;
    /// for a client, else $MWB_CONNECT, else (without a config file, which has its own)
    /// [`DEFAULT_ENDPOINT`]. Peers and routers connect only where `--connect` says.
    pub fn endpoints(&self, mode: Mode) -> (Vec<String>, EndpointSource) {
        if !self.connect.is_empty() || mode != Mode::Client {
            return (self.connect.clone(), EndpointSource::Flag);
        }
        let from_env: Vec<String> = std::env::var(CONNECT_ENV)
            .unwrap_or_default()
            .split([',', ' '])
            .filter(|e| !e.is_empty())
            .map(str::to_owned)
            .collect();
        if !from_env.is_empty() {
            (from_env, EndpointSource::Env)
        } else if self.config.is_none() {
            (vec![DEFAULT_ENDPOINT.to_owned()], EndpointSource::Default)
        } else {
            (Vec::new(), EndpointSource::Flag)
        }
    }

    /// Builds the zenoh configuration. `default_mode` applies when neither --mode nor the
    /// config file chose one.
    pub fn config(&self, default_mode: Mode) -> Result<zenoh::Config> {
        let mut c = match &self.config {
            Some(p) => zenoh::Config::from_file(p)
                .map_err(|e| anyhow::anyhow!("{e}"))
                .with_context(|| format!("reading zenoh config {}", p.display()))?,
            None => zenoh::Config::default(),
        };
        let set = |c: &mut zenoh::Config, k: &str, v: String| {
            c.insert_json5(k, &v)
                .map_err(|e| anyhow::anyhow!("zenoh config {k} = {v}: {e}"))
        };
        // A config file keeps its own mode unless --mode overrides it.
        let mode = self.mode.unwrap_or(default_mode);
        if self.mode.is_some() || self.config.is_none() {
            set(&mut c, "mode", format!("{:?}", mode.as_str()))?;
        }
        let (connect, _) = self.endpoints(mode);
        if !connect.is_empty() {
            set(
                &mut c,
                "connect/endpoints",
                serde_json::to_string(&connect)?,
            )?;
        }
        // Never listen on every interface by accident: without --listen a router listens on
        // the loopback port 7447 only, a peer on an ephemeral loopback port, a client nowhere.
        let listen: Vec<String> = if !self.listen.is_empty() {
            self.listen.clone()
        } else if self.config.is_some() {
            Vec::new()
        } else {
            match mode {
                Mode::Router => vec![DEFAULT_ENDPOINT.into()],
                Mode::Peer => vec!["tcp/127.0.0.1:0".into()],
                Mode::Client => Vec::new(),
            }
        };
        if !listen.is_empty() || self.config.is_none() {
            set(&mut c, "listen/endpoints", serde_json::to_string(&listen)?)?;
        }
        if !self.multicast {
            set(&mut c, "scouting/multicast/enabled", "false".into())?;
        }
        Ok(c)
    }

    /// Opens the session. A client that reaches none of its endpoints fails here, naming them,
    /// where they came from and what to pass instead.
    pub async fn open(&self, default_mode: Mode) -> Result<zenoh::Session> {
        let config = self.config(default_mode)?;
        let mode = self.mode.unwrap_or(default_mode);
        zenoh::open(config).await.map_err(|e| {
            let (endpoints, source) = self.endpoints(mode);
            if mode == Mode::Client && !endpoints.is_empty() {
                anyhow::anyhow!("{}", unreachable(&endpoints, source, &e.to_string()))
            } else {
                anyhow::anyhow!("opening zenoh session: {e}")
            }
        })
    }

    /// The mode a client-like command (job, status, query, sampler, …) uses by default: a
    /// client of the endpoints [`BusArgs::endpoints`] names; a peer only when it is to find the
    /// others by multicast scouting.
    pub fn client_default(&self) -> Mode {
        let scouting =
            self.multicast && self.connect.is_empty() && std::env::var(CONNECT_ENV).is_err();
        if scouting { Mode::Peer } else { Mode::Client }
    }
}

/// What a client says when none of its endpoints answered.
fn unreachable(endpoints: &[String], source: EndpointSource, cause: &str) -> String {
    let from = match source {
        EndpointSource::Flag => "given with --connect".to_owned(),
        EndpointSource::Env => format!("from ${CONNECT_ENV}"),
        EndpointSource::Default => {
            format!("the default: neither --connect nor ${CONNECT_ENV} was given")
        }
    };
    format!(
        "nothing answered at {} ({from}). Start `mwb store` or `mwb demo --stay` there, or \
         pass --connect ENDPOINT (or set {CONNECT_ENV}=ENDPOINT) to reach the bus elsewhere \
         (zenoh: {cause})",
        endpoints.join(", ")
    )
}

/// Closes a session without ever hanging the process.
pub async fn close(session: zenoh::Session) {
    let _ = tokio::time::timeout(std::time::Duration::from_secs(3), session.close()).await;
}

/// Waits for Ctrl-C: how a node serving in the foreground is stopped. If the signal cannot be
/// watched the node stops at once (better than one that cannot be stopped), and says why.
pub async fn until_ctrl_c() {
    if let Err(e) = tokio::signal::ctrl_c().await {
        tracing::warn!(error = %e, "cannot watch for Ctrl-C; stopping");
    }
}
