//! node-query: the browsing coordinator (§4.4).
//!
//! It serves `mwb/<space>/browse/<session>` (JSON [`Request`] → merged JSON [`Reply`]) to the
//! viewer and to `mwb query`, and keeps no worlds of its own: every request fans out to all
//! live store shards (`q/browse/*/<session>`), whose answers are merged with
//! [`mwb_core::browse::api::merge`] — counts add, world lists unite, top-k lists merge.
//!
//! Every edit it applies is published on `browse/<session>/edit` ([`EditRecord`]: the request
//! and the merged answer), so that a recording of the bus keeps the browsing session.
//!
//! Per session it keeps the numbered list of edits (add, remove, undo, redo). A shard that
//! answers with fewer edits than the list has — it joined late, restarted, or missed a request —
//! is sent the missing edits in order before its answer is used, so every shard ends up with
//! the same constraints and merged answers are consistent.

use mwb_core::browse::api::{
    EditRecord, MergeError, Reply, Request, ShardReply, ShardRequest, merge,
};
use mwb_core::keys::{Keys, check_identifier, last_chunk, role};
use mwb_node::bus::{self, Queries, Subscription};
use mwb_node::{Node, NodeError};
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
    /// Browsing space (`mwb/<space>/…`); default [`mwb_core::keys::DEFAULT_SPACE`].
    pub space: String,
    /// Node id; default: the session's zenoh id.
    pub node_id: Option<String>,
    /// How long to wait for the shards' answers to one request; default 5 s.
    pub shard_timeout: Duration,
}

impl Default for QueryConfig {
    fn default() -> Self {
        Self {
            space: mwb_core::keys::DEFAULT_SPACE.into(),
            node_id: None,
            shard_timeout: Duration::from_secs(5),
        }
    }
}

/// Why a browsing request (or the coordinator's start) failed.
#[derive(Debug, thiserror::Error)]
pub enum QueryError {
    /// The coordinator could not start.
    #[error(transparent)]
    Start(#[from] NodeError),
    /// The session is not a valid key chunk.
    #[error(transparent)]
    Key(#[from] mwb_core::keys::BadIdentifier),
    /// zenoh refused a query.
    #[error("zenoh refused the query")]
    Zenoh(#[from] zenoh::Error),
    /// A request could not be serialised.
    #[error("serialising a request")]
    Encode(#[source] serde_json::Error),
    #[error("no store shard is alive")]
    NoShards,
    #[error("shard(s) {0} did not answer")]
    Missing(String),
    /// An answer that is not the JSON it should be.
    #[error("shard {shard} sent a malformed answer")]
    Malformed {
        shard: String,
        #[source]
        source: serde_json::Error,
    },
    #[error("shard {shard} stays behind: it has {edits} edits, the session {expected}")]
    Behind {
        shard: String,
        edits: u64,
        expected: u64,
    },
    #[error(transparent)]
    Merge(#[from] MergeError),
}

/// `e` and its sources on one line, for a reply's error message (the client sees no error
/// chain) and for clients that show an error in one line (the viewer's status bar).
pub fn error_chain(e: &dyn std::error::Error) -> String {
    let mut m = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        m.push_str(": ");
        m.push_str(&s.to_string());
        source = s.source();
    }
    m
}

/// The coordinator's state: the live shards and every session's edit log.
struct Inner {
    node: Arc<Node>,
    cfg: QueryConfig,
    shards: Mutex<BTreeSet<String>>,
    /// One async lock per browsing session: its requests are handled one at a time, in order.
    logs: Mutex<HashMap<String, Arc<tokio::sync::Mutex<Vec<Request>>>>>,
}

/// A running coordinator.
pub struct QueryHandle {
    inner: Arc<Inner>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

impl QueryHandle {
    pub fn node_id(&self) -> &str {
        self.inner.node.id()
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
    fn keys(&self) -> &Keys {
        self.node.keys()
    }

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
            Some(node) => self.keys().shard_browse(node, &req.session),
            None => self.keys().shards_browse(&req.session),
        };
        let payload = serde_json::to_vec(req).map_err(QueryError::Encode)?;
        let replies = self
            .node
            .session()
            .get(key)
            .payload(payload)
            .consolidation(ConsolidationMode::None)
            .target(QueryTarget::All)
            .timeout(self.cfg.shard_timeout)
            .await?;
        let mut out = BTreeMap::new();
        while let Ok(reply) = replies.recv_async().await {
            let Ok(sample) = reply.result() else {
                continue;
            };
            let Some(node) = self
                .keys()
                .split(sample.key_expr().as_str())
                .and_then(|c| c.get(2).map(|s| (*s).to_owned()))
            else {
                continue;
            };
            let parsed: ShardReply =
                serde_json::from_slice(&sample.payload().to_bytes()).map_err(|source| {
                    QueryError::Malformed {
                        shard: node.clone(),
                        source,
                    }
                })?;
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
            .node
            .session()
            .liveliness()
            .get(self.keys().alive_role(role::STORE))
            .timeout(bus::QUERY_TIMEOUT)
            .await?;
        while let Ok(reply) = replies.recv_async().await {
            if let Ok(sample) = reply.result() {
                let node = last_chunk(sample.key_expr().as_str());
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
        if is_edit {
            // Published under the session's lock, so in the session's order: recorders keep
            // the browsing session this way (queries and their answers are not puts).
            let record = EditRecord {
                session: session.to_owned(),
                edit: expected,
                request,
                reply: merged.clone(),
            };
            match serde_json::to_vec(&record) {
                Ok(bytes) => {
                    self.node
                        .put(&self.keys().browse_edits(session), bytes)
                        .await
                }
                Err(e) => warn!(error = %e, "serialising an edit record"),
            }
        }
        Ok(merged)
    }
}

/// Starts a coordinator on `session` (in the current tokio runtime).
pub async fn run_query(session: Session, cfg: QueryConfig) -> Result<QueryHandle, QueryError> {
    let node = Node::new(&session, &cfg.space, cfg.node_id.as_deref(), role::QUERY)?;
    let stores = node
        .session()
        .liveliness()
        .declare_subscriber(node.keys().alive_role(role::STORE))
        .history(true)
        .await?;
    let api = node.queryable(node.keys().browse_all()).await?;
    let token = node.declare_alive().await?;
    let inner = Arc::new(Inner {
        node: node.clone(),
        cfg: cfg.clone(),
        shards: Mutex::new(BTreeSet::new()),
        logs: Mutex::new(HashMap::new()),
    });
    let stats = {
        let node = node.clone();
        move || node.stats()
    };
    let tasks = vec![
        tokio::spawn(bus::hold(token)),
        tokio::spawn(follow_shards(inner.clone(), stores)),
        tokio::spawn(serve(inner.clone(), api)),
        tokio::spawn(bus::publish_stats(node.clone(), stats)),
    ];
    info!(node = %node.id(), space = %cfg.space, "query coordinator started");
    Ok(QueryHandle { inner, tasks })
}

/// The live store shards, from their liveliness tokens.
async fn follow_shards(inner: Arc<Inner>, stores: Subscription) {
    while let Ok(s) = stores.recv_async().await {
        let node = last_chunk(s.key_expr().as_str());
        let mut shards = inner.shards.lock().unwrap_or_else(|p| p.into_inner());
        if s.kind() == SampleKind::Delete {
            info!(%node, "store shard left");
            shards.remove(node);
        } else if shards.insert(node.to_owned()) {
            info!(%node, "store shard joined");
        }
    }
}

/// The browsing API. Each request gets its own task: a slow session must not hold up the
/// others (requests of one session still run one at a time, under its lock).
async fn serve(inner: Arc<Inner>, api: Queries) {
    while let Ok(q) = api.recv_async().await {
        tokio::spawn(answer(inner.clone(), q));
    }
}

async fn answer(inner: Arc<Inner>, q: zenoh::query::Query) {
    let session = last_chunk(q.key_expr().as_str()).to_owned();
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
                message: error_chain(&e),
            },
        },
    };
    match serde_json::to_vec(&reply) {
        Ok(bytes) => {
            let key = inner.keys().browse(&session);
            inner.node.reply(&q, &key, bytes).await;
        }
        Err(e) => warn!(error = %e, "serialising a reply"),
    }
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
    let payload = serde_json::to_vec(request).map_err(QueryError::Encode)?;
    let replies = session
        .get(keys.browse(browse_session))
        .payload(payload)
        .timeout(timeout)
        .await?;
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result() {
            return serde_json::from_slice(&sample.payload().to_bytes()).map_err(|source| {
                QueryError::Malformed {
                    shard: "node-query".into(),
                    source,
                }
            });
        }
    }
    Err(QueryError::Missing(
        "node-query (is `mwb query serve` running?)".into(),
    ))
}
