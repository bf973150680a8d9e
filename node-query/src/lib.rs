//! node-query: the browsing coordinator (§4.4, DESIGN.md "Store and queries").
//!
//! It serves `mwb/<space>/browse/<session>` (JSON [`Request`] → merged JSON [`Reply`]) to the
//! viewer and to `mwb query`, and keeps no worlds of its own: every request fans out to all
//! live store shards (`q/browse/*/<session>`), whose answers are merged with
//! [`mwb_core::browse::api::merge`] — counts add, world lists unite, top-k lists merge.
//!
//! Per session it keeps the numbered list of edits (add, remove, undo, redo). A shard that
//! answers with fewer edits than the list has — it joined late, restarted, or missed a request —
//! is sent the missing edits in order before its answer is used, so every shard ends up with
//! the same constraints and merged answers are consistent.

use mwb_core::browse::api::{MergeError, Reply, Request, ShardReply, ShardRequest, merge};
use mwb_core::keys::{Keys, check_identifier, role};
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tracing::{debug, info, warn};
use zenoh::Session;
use zenoh::query::{ConsolidationMode, QueryTarget};
use zenoh::sample::SampleKind;

/// Coordinator settings.
#[derive(Debug, Clone)]
pub struct QueryConfig {
    pub space: String,
    pub node_id: Option<String>,
    /// How long to wait for the shards' answers to one request.
    pub shard_timeout: Duration,
}

impl Default for QueryConfig {
    fn default() -> Self {
        Self {
            space: "default".into(),
            node_id: None,
            shard_timeout: Duration::from_secs(5),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum QueryError {
    #[error(transparent)]
    Key(#[from] mwb_core::keys::BadIdentifier),
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("no store shard is alive")]
    NoShards,
    #[error("shard(s) {0} did not answer")]
    Missing(String),
    #[error("shard {0} sent a malformed answer: {1}")]
    Malformed(String, String),
    #[error("shard {shard} stays behind: it has {edits} edits, the session {expected}")]
    Behind {
        shard: String,
        edits: u64,
        expected: u64,
    },
    #[error(transparent)]
    Merge(#[from] MergeError),
}

fn zerr(e: impl std::fmt::Display) -> QueryError {
    QueryError::Zenoh(e.to_string())
}

/// The coordinator's state: the live shards and every session's edit log.
struct Inner {
    session: Session,
    keys: Keys,
    cfg: QueryConfig,
    shards: Mutex<BTreeSet<String>>,
    /// One async lock per browsing session: its requests are handled one at a time, in order.
    logs: Mutex<HashMap<String, Arc<tokio::sync::Mutex<Vec<Request>>>>>,
}

/// A running coordinator.
pub struct QueryHandle {
    inner: Arc<Inner>,
    node_id: String,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

impl QueryHandle {
    pub fn node_id(&self) -> &str {
        &self.node_id
    }

    /// Handles a request in-process (what the bus queryable does).
    pub async fn request(&self, session: &str, request: Request) -> Result<Reply, QueryError> {
        self.inner.handle(session, request).await
    }

    /// The shards currently alive.
    pub fn shards(&self) -> Vec<String> {
        self.inner.live_shards().into_iter().collect()
    }

    pub fn stop(self) {
        for t in self.tasks {
            t.abort();
        }
    }
}

impl Inner {
    fn live_shards(&self) -> BTreeSet<String> {
        self.shards
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    fn log(&self, session: &str) -> Arc<tokio::sync::Mutex<Vec<Request>>> {
        self.logs
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .entry(session.to_owned())
            .or_default()
            .clone()
    }

    /// Sends one request to every shard (`target = None`) or to one, and collects the answers
    /// by shard node id.
    async fn ask(
        &self,
        target: Option<&str>,
        req: &ShardRequest,
    ) -> Result<BTreeMap<String, ShardReply>, QueryError> {
        let key = match target {
            Some(node) => self.keys.shard_browse(node, &req.session),
            None => self.keys.shards_browse(&req.session),
        };
        let payload = serde_json::to_vec(req).map_err(|e| QueryError::Zenoh(e.to_string()))?;
        let replies = self
            .session
            .get(key)
            .payload(payload)
            .consolidation(ConsolidationMode::None)
            .target(QueryTarget::All)
            .timeout(self.cfg.shard_timeout)
            .await
            .map_err(zerr)?;
        let mut out = BTreeMap::new();
        while let Ok(reply) = replies.recv_async().await {
            let Ok(sample) = reply.result() else {
                continue;
            };
            let Some(node) = self
                .keys
                .split(sample.key_expr().as_str())
                .and_then(|c| c.get(2).map(|s| (*s).to_owned()))
            else {
                continue;
            };
            let parsed: ShardReply = serde_json::from_slice(&sample.payload().to_bytes())
                .map_err(|e| QueryError::Malformed(node.clone(), e.to_string()))?;
            out.insert(node, parsed);
        }
        Ok(out)
    }

    /// Brings one shard up to `log.len()` edits by replaying the ones it lacks.
    async fn catch_up(
        &self,
        shard: &str,
        session: &str,
        mut edits: u64,
        log: &[Request],
    ) -> Result<(), QueryError> {
        let expected = log.len() as u64;
        info!(%shard, %session, from = edits, to = expected, "replaying edits to a shard");
        while edits < expected {
            let req = ShardRequest {
                session: session.to_owned(),
                seq: Some(edits + 1),
                request: log[edits as usize].clone(),
            };
            let answer = self.ask(Some(shard), &req).await?;
            edits = match answer.get(shard) {
                Some(ShardReply::Ok { edits, .. } | ShardReply::OutOfSync { edits }) => *edits,
                None => return Err(QueryError::Missing(shard.to_owned())),
            };
            if edits < req.seq.unwrap_or(0) {
                return Err(QueryError::Behind {
                    shard: shard.to_owned(),
                    edits,
                    expected,
                });
            }
        }
        Ok(())
    }

    /// Adds every store whose liveliness token is up right now.
    async fn refresh_shards(&self) -> Result<(), QueryError> {
        let replies = self
            .session
            .liveliness()
            .get(self.keys.alive_role(role::STORE))
            .timeout(Duration::from_secs(2))
            .await
            .map_err(zerr)?;
        while let Ok(reply) = replies.recv_async().await {
            if let Ok(sample) = reply.result()
                && let Some(node) = sample.key_expr().as_str().rsplit('/').next()
            {
                self.shards
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .insert(node.to_owned());
            }
        }
        Ok(())
    }

    async fn handle(&self, session: &str, request: Request) -> Result<Reply, QueryError> {
        check_identifier("session", session)?;
        let log = self.log(session);
        let mut log = log.lock().await;
        let mut expected_shards = self.live_shards();
        if expected_shards.is_empty() {
            // Just started (the liveliness subscription may not have caught up yet): ask.
            self.refresh_shards().await?;
            expected_shards = self.live_shards();
        }
        if expected_shards.is_empty() {
            return Err(QueryError::NoShards);
        }
        if request == Request::Close {
            let answers = self
                .ask(
                    None,
                    &ShardRequest {
                        session: session.to_owned(),
                        seq: None,
                        request: Request::Close,
                    },
                )
                .await?;
            debug!(%session, shards = answers.len(), "session closed");
            log.clear();
            self.logs
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .remove(session);
            return Ok(Reply::Closed);
        }
        let is_edit = request.is_edit();
        if is_edit {
            log.push(request.clone());
        }
        let expected = log.len() as u64;
        let req = ShardRequest {
            session: session.to_owned(),
            seq: is_edit.then_some(expected),
            request: request.clone(),
        };
        let mut answers = self.ask(None, &req).await?;
        // Shards behind the log (late joiners, restarts) catch up, then answer again.
        let behind: Vec<(String, u64)> = answers
            .iter()
            .filter_map(|(node, a)| match a {
                ShardReply::OutOfSync { edits } => Some((node.clone(), *edits)),
                ShardReply::Ok { edits, .. } if *edits < expected => Some((node.clone(), *edits)),
                ShardReply::Ok { .. } => None,
            })
            .collect();
        for (node, edits) in behind {
            let upto = if is_edit { expected - 1 } else { expected };
            self.catch_up(&node, session, edits, &log[..upto as usize])
                .await?;
            let again = self.ask(Some(&node), &req).await?;
            match again.get(&node) {
                Some(a @ ShardReply::Ok { edits, .. }) if *edits >= expected => {
                    answers.insert(node, a.clone());
                }
                Some(ShardReply::Ok { edits, .. } | ShardReply::OutOfSync { edits }) => {
                    return Err(QueryError::Behind {
                        shard: node,
                        edits: *edits,
                        expected,
                    });
                }
                None => return Err(QueryError::Missing(node)),
            }
        }
        let missing: Vec<&String> = expected_shards
            .iter()
            .filter(|s| !answers.contains_key(*s))
            .collect();
        if !missing.is_empty() {
            // A shard that is alive but silent would make every count wrong; say so.
            return Err(QueryError::Missing(
                missing
                    .iter()
                    .map(|s| s.as_str())
                    .collect::<Vec<_>>()
                    .join(", "),
            ));
        }
        let replies = answers
            .into_values()
            .filter_map(|a| match a {
                ShardReply::Ok { reply, .. } => Some(reply),
                ShardReply::OutOfSync { .. } => None,
            })
            .collect();
        let merged = merge(&request, replies)?;
        if is_edit && let Reply::Error { .. } = merged {
            // Every shard refused the edit the same way (it is numbered already); keep the
            // log in step with them.
            debug!(%session, "edit refused by the shards");
        }
        Ok(merged)
    }
}

/// Starts a coordinator on `session` (in the current tokio runtime).
pub async fn run_query(session: Session, cfg: QueryConfig) -> Result<QueryHandle, QueryError> {
    let keys = Keys::new(&cfg.space)?;
    let node_id = cfg
        .node_id
        .clone()
        .unwrap_or_else(|| session.zid().to_string());
    check_identifier("node id", &node_id)?;
    let inner = Arc::new(Inner {
        session: session.clone(),
        keys: keys.clone(),
        cfg: cfg.clone(),
        shards: Mutex::new(BTreeSet::new()),
        logs: Mutex::new(HashMap::new()),
    });
    let alive = session
        .liveliness()
        .declare_subscriber(keys.alive_role(role::STORE))
        .history(true)
        .await
        .map_err(zerr)?;
    let api = session
        .declare_queryable(keys.browse_all())
        .await
        .map_err(zerr)?;
    let token = session
        .liveliness()
        .declare_token(keys.alive(role::QUERY, &node_id))
        .await
        .map_err(zerr)?;
    let mut tasks = Vec::new();
    {
        let inner = inner.clone();
        tasks.push(tokio::spawn(async move {
            let _token = token;
            while let Ok(s) = alive.recv_async().await {
                let Some(node) = s.key_expr().as_str().rsplit('/').next() else {
                    continue;
                };
                let mut shards = inner.shards.lock().unwrap_or_else(|p| p.into_inner());
                if s.kind() == SampleKind::Delete {
                    info!(%node, "store shard left");
                    shards.remove(node);
                } else if shards.insert(node.to_owned()) {
                    info!(%node, "store shard joined");
                }
            }
        }));
    }
    {
        let inner = inner.clone();
        tasks.push(tokio::spawn(async move {
            while let Ok(q) = api.recv_async().await {
                // Each request gets its own task: a slow session must not hold up the others
                // (requests of one session still run one at a time, under its lock).
                let inner = inner.clone();
                tokio::spawn(async move {
                    let session = mwb_core::keys::last_chunk(q.key_expr().as_str()).to_owned();
                    let request = q
                        .payload()
                        .map(|p| serde_json::from_slice::<Request>(&p.to_bytes()));
                    let reply = match request {
                        None => Reply::Error {
                            message: "empty request: send a JSON browse request".into(),
                        },
                        Some(Err(e)) => Reply::Error {
                            message: format!("malformed request: {e}"),
                        },
                        Some(Ok(req)) => match inner.handle(&session, req).await {
                            Ok(r) => r,
                            Err(e) => Reply::Error {
                                message: e.to_string(),
                            },
                        },
                    };
                    match serde_json::to_vec(&reply) {
                        Ok(bytes) => {
                            let _ = q.reply(inner.keys.browse(&session), bytes).await;
                        }
                        Err(e) => warn!(error = %e, "serialising a reply"),
                    }
                });
            }
        }));
    }
    info!(node = %node_id, space = %cfg.space, "query coordinator started");
    Ok(QueryHandle {
        inner,
        node_id,
        tasks,
    })
}

/// Sends one browsing request to node-query over the bus and returns its reply (for the CLI,
/// tests and scripts).
pub async fn send(
    session: &Session,
    keys: &Keys,
    browse_session: &str,
    request: &Request,
    timeout: Duration,
) -> Result<Reply, QueryError> {
    check_identifier("session", browse_session)?;
    let payload = serde_json::to_vec(request).map_err(|e| QueryError::Zenoh(e.to_string()))?;
    let replies = session
        .get(keys.browse(browse_session))
        .payload(payload)
        .timeout(timeout)
        .await
        .map_err(zerr)?;
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result() {
            return serde_json::from_slice(&sample.payload().to_bytes())
                .map_err(|e| QueryError::Malformed("node-query".into(), e.to_string()));
        }
    }
    Err(QueryError::Missing(
        "node-query (is `mwb query serve` running?)".into(),
    ))
}
