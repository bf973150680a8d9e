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

/// Bus options shared by every subcommand.
#[derive(Debug, Clone, Args)]
pub struct BusArgs {
    /// Endpoint to connect to (repeatable), e.g. tcp/10.0.0.5:7447.
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

impl BusArgs {
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
        if !self.connect.is_empty() {
            set(
                &mut c,
                "connect/endpoints",
                serde_json::to_string(&self.connect)?,
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
                Mode::Router => vec!["tcp/127.0.0.1:7447".into()],
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

    /// Opens the session.
    pub async fn open(&self, default_mode: Mode) -> Result<zenoh::Session> {
        let config = self.config(default_mode)?;
        let session = zenoh::open(config)
            .await
            .map_err(|e| anyhow::anyhow!("opening zenoh session: {e}"))?;
        Ok(session)
    }

    /// The mode a client-like command (job, status, sampler) uses by default.
    pub fn client_default(&self) -> Mode {
        if self.connect.is_empty() {
            Mode::Peer
        } else {
            Mode::Client
        }
    }
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
