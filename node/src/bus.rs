//! What every node does on the bus, whatever its role: take an id, hold a liveliness token,
//! publish its statistics, decode what it subscribed to (counting what does not decode), and
//! send puts and replies without ever dropping a failure silently.

use mwb_core::keys::{BadIdentifier, Keys, check_identifier};
use mwb_proto::v1::{Connection, Message, NodeStats};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};
use tokio::sync::mpsc;
use tracing::{debug, warn};
use zenoh::Session;
use zenoh::handlers::FifoChannelHandler;
use zenoh::liveliness::LivelinessToken;
use zenoh::qos::CongestionControl;
use zenoh::query::{Query, Queryable};
use zenoh::sample::{Sample, SampleKind};

/// A subscription whose samples are read one at a time (`recv_async`).
pub type Subscription = zenoh::pubsub::Subscriber<FifoChannelHandler<Sample>>;
/// A queryable whose queries are read one at a time.
pub type Queries = Queryable<FifoChannelHandler<Query>>;

/// How often every node publishes its `NodeStats`.
pub const STATS_EVERY: Duration = Duration::from_secs(1);
/// How long a node waits for the answers to one of its own queries (open jobs, job states).
pub const QUERY_TIMEOUT: Duration = Duration::from_secs(2);

/// Why a node could not start.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    /// The space or the node id is not a valid key chunk.
    #[error(transparent)]
    Key(#[from] BadIdentifier),
    /// zenoh refused a declaration (subscriber, queryable, liveliness token).
    #[error("zenoh refused a declaration")]
    Zenoh(#[from] zenoh::Error),
    /// The operating system refused a worker thread.
    #[error("starting worker thread {name}")]
    Thread {
        /// The thread's name.
        name: String,
        /// What the system said.
        #[source]
        source: std::io::Error,
    },
}

/// One node on the bus: its identity, its keys and the counters every role reports.
#[derive(Debug)]
pub struct Node {
    session: Session,
    keys: Keys,
    id: String,
    role: &'static str,
    start: Instant,
    hostname: String,
    /// Incremented on every statistics snapshot, published or queried.
    revision: AtomicU64,
    malformed: AtomicU64,
    send_failures: AtomicU64,
}

impl Node {
    /// A node of `role` in `space`, named `node_id` or, by default, after the session's zenoh
    /// id (two nodes sharing a session, as in `mwb demo`, need distinct ids). Declares nothing:
    /// a node declares its liveliness token ([`Node::declare_alive`]) once it answers.
    pub fn new(
        session: &Session,
        space: &str,
        node_id: Option<&str>,
        role: &'static str,
    ) -> Result<Arc<Self>, NodeError> {
        let keys = Keys::new(space)?;
        let id = node_id.map_or_else(|| session.zid().to_string(), str::to_owned);
        check_identifier("node id", &id)?;
        Ok(Arc::new(Self {
            session: session.clone(),
            keys,
            id,
            role,
            start: Instant::now(),
            hostname: hostname(),
            revision: AtomicU64::new(1),
            malformed: AtomicU64::new(0),
            send_failures: AtomicU64::new(0),
        }))
    }

    pub fn session(&self) -> &Session {
        &self.session
    }
    pub fn keys(&self) -> &Keys {
        &self.keys
    }
    /// The `<node>` of this node's keys.
    pub fn id(&self) -> &str {
        &self.id
    }
    /// The `<role>` of this node's keys (`mwb_core::keys::role`).
    pub fn role(&self) -> &'static str {
        self.role
    }

    /// Bus messages that did not decode (or named an invalid id), dropped.
    pub fn malformed(&self) -> u64 {
        self.malformed.load(Ordering::Relaxed)
    }
    /// Counts one dropped bus message.
    pub fn count_malformed(&self) {
        self.malformed.fetch_add(1, Ordering::Relaxed);
    }
    /// Puts and replies zenoh refused.
    pub fn send_failures(&self) -> u64 {
        self.send_failures.load(Ordering::Relaxed)
    }

    /// Declares `alive/<role>/<node>`: the node is up as long as the token lives. Declared
    /// after the node's subscriptions and queryables, so that whoever sees it can use them.
    pub async fn declare_alive(&self) -> Result<LivelinessToken, NodeError> {
        Ok(self
            .session
            .liveliness()
            .declare_token(self.keys.alive(self.role, &self.id))
            .await?)
    }

    pub async fn subscribe(&self, key: String) -> Result<Subscription, NodeError> {
        Ok(self.session.declare_subscriber(key).await?)
    }

    /// Liveliness changes (puts when a token appears, deletes when it goes) under `key`.
    pub async fn watch_alive(&self, key: String) -> Result<Subscription, NodeError> {
        Ok(self.session.liveliness().declare_subscriber(key).await?)
    }

    pub async fn queryable(&self, key: String) -> Result<Queries, NodeError> {
        Ok(self.session.declare_queryable(key).await?)
    }

    /// The fields of `NodeStats` every role fills the same way; the role adds its own.
    pub fn stats(&self) -> NodeStats {
        NodeStats {
            node_id: self.id.clone(),
            role: self.role.into(),
            revision: self.revision.fetch_add(1, Ordering::Relaxed),
            uptime_s: self.start.elapsed().as_secs_f64(),
            malformed: self.malformed(),
            send_failures: self.send_failures(),
            pid: std::process::id(),
            hostname: self.hostname.clone(),
            ..Default::default()
        }
    }

    /// Puts `bytes` on `key` with blocking congestion control (zenoh's default, Drop, loses
    /// puts under bursts). A refused put is logged and counted.
    pub async fn put(&self, key: &str, bytes: Vec<u8>) {
        if let Err(e) = self
            .session
            .put(key, bytes)
            .congestion_control(CongestionControl::Block)
            .await
        {
            self.send_failures.fetch_add(1, Ordering::Relaxed);
            warn!(%key, error = %e, "put failed");
        }
    }

    /// Replies `bytes` on `key` to `query`. A refused reply (usually: the querier timed out and
    /// left) is counted and logged at debug level.
    pub async fn reply(&self, query: &Query, key: &str, bytes: Vec<u8>) {
        if let Err(e) = query.reply(key, bytes).await {
            self.send_failures.fetch_add(1, Ordering::Relaxed);
            debug!(%key, error = %e, "reply failed");
        }
    }

    /// Answers `query` with an error message.
    pub async fn reply_err(&self, query: &Query, message: &str) {
        if let Err(e) = query.reply_err(message.to_owned()).await {
            self.send_failures.fetch_add(1, Ordering::Relaxed);
            debug!(key = %query.key_expr(), error = %e, "error reply failed");
        }
    }

    /// Asks `key` and decodes every answer as an `M`; answers that do not decode are counted
    /// as malformed. A query zenoh refuses is logged and yields nothing (callers ask again
    /// later).
    pub async fn get<M: Message + Default>(&self, key: String) -> Vec<M> {
        let replies = match self.session.get(&key).timeout(QUERY_TIMEOUT).await {
            Ok(r) => r,
            Err(e) => {
                warn!(%key, error = %e, "query failed");
                return Vec::new();
            }
        };
        let mut out = Vec::new();
        while let Ok(reply) = replies.recv_async().await {
            if let Ok(sample) = reply.result() {
                match M::decode(sample.payload().to_bytes().as_ref()) {
                    Ok(m) => out.push(m),
                    Err(_) => self.count_malformed(),
                }
            }
        }
        out
    }

    /// The next put on `sub` decoded as an `M`, counting (and skipping) the ones that do not
    /// decode; deletes carry no message and are skipped. `None` once the subscription closed.
    pub async fn next<M: Message + Default>(&self, sub: &Subscription) -> Option<M> {
        while let Ok(sample) = sub.recv_async().await {
            if sample.kind() != SampleKind::Put {
                continue;
            }
            match M::decode(sample.payload().to_bytes().as_ref()) {
                Ok(m) => return Some(m),
                Err(_) => self.count_malformed(),
            }
        }
        None
    }
}

/// Keeps a liveliness token declared until the task holding it is aborted.
pub async fn hold(token: LivelinessToken) {
    let _token = token;
    std::future::pending::<()>().await;
}

/// Decodes every message on `sub` and sends `wrap(message)` on `tx` (waiting when the queue
/// is full: back-pressure on the subscription). A message `wrap` refuses (`None`) is counted
/// as malformed. Ends when the subscription or the receiver closes.
pub async fn forward<M, T>(
    node: Arc<Node>,
    sub: Subscription,
    tx: mpsc::Sender<T>,
    wrap: impl Fn(M) -> Option<T>,
) where
    M: Message + Default,
{
    while let Some(m) = node.next::<M>(&sub).await {
        match wrap(m) {
            Some(item) => {
                if tx.send(item).await.is_err() {
                    break;
                }
            }
            None => node.count_malformed(),
        }
    }
}

/// Decodes every message on `sub` and hands it to `apply`. Ends when the subscription closes.
pub async fn apply<M: Message + Default>(
    node: Arc<Node>,
    sub: Subscription,
    mut apply: impl FnMut(M),
) {
    while let Some(m) = node.next::<M>(&sub).await {
        apply(m);
    }
}

/// The configuration of a session that talks only to the sessions of its own process: a peer
/// with scouting off and no listener (nodes started on one session reach each other; nothing
/// outside does). For in-process tests and benches.
pub fn isolated_config() -> zenoh::Config {
    let mut c = zenoh::Config::default();
    for (k, v) in [
        ("mode", "\"peer\""),
        ("scouting/multicast/enabled", "false"),
        ("scouting/gossip/enabled", "false"),
        ("listen/endpoints", "[]"),
    ] {
        // Fixed keys and values that zenoh's schema accepts (checked by the tests that use it).
        if let Err(e) = c.insert_json5(k, v) {
            warn!(key = k, error = %e, "isolated session config");
        }
    }
    c
}

/// Publishes `stats()` on `stats/<role>/<node>` every [`STATS_EVERY`], with `worlds_per_s`
/// measured between consecutive snapshots.
pub async fn publish_stats(node: Arc<Node>, stats: impl Fn() -> NodeStats) {
    let key = node.keys().stats(node.role(), node.id());
    let mut last = (Instant::now(), 0u64);
    loop {
        tokio::time::sleep(STATS_EVERY).await;
        let mut st = stats();
        st.zid = node.session().info().zid().await.to_string();
        st.connections = connections(node.session()).await;
        let now = Instant::now();
        st.worlds_per_s =
            st.worlds.saturating_sub(last.1) as f64 / (now - last.0).as_secs_f64().max(1e-3);
        last = (now, st.worlds);
        node.put(&key, st.encode_to_vec()).await;
    }
}

/// The links of `session` to other zenoh sessions, as zenoh reports them: the other end's id,
/// kind, address and — over TLS — the common name of the certificate it proved, which is the
/// subject zenoh's access control matched (deploy/README.md). Sorted, so that statistics of an
/// unchanged cluster are identical.
pub async fn connections(session: &Session) -> Vec<Connection> {
    let kinds: std::collections::HashMap<String, String> = session
        .info()
        .transports()
        .await
        .map(|t| (t.zid().to_string(), t.whatami().to_string()))
        .collect();
    let mut out: Vec<Connection> = session
        .info()
        .links()
        .await
        .map(|link| {
            let zid = link.zid().to_string();
            Connection {
                whatami: kinds.get(&zid).cloned().unwrap_or_default(),
                address: link.dst().to_string(),
                certificate: link.auth_identifier().unwrap_or_default().to_owned(),
                zid,
            }
        })
        .collect();
    out.sort_by(|a, b| (&a.zid, &a.address).cmp(&(&b.zid, &b.address)));
    out
}

/// CPU time of the calling thread, seconds (0 where the clock is unavailable).
#[cfg(unix)]
pub fn cpu_time() -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes one timespec into the valid pointer we pass.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    if rc == 0 {
        ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
    } else {
        0.0
    }
}

/// CPU time of the calling thread: no per-thread clock is read on this platform (the
/// statistics and benchmarks that use it show 0 CPU seconds).
#[cfg(not(unix))]
pub fn cpu_time() -> f64 {
    0.0
}

/// This machine's host name, for node statistics (empty where unknown).
fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().to_owned())
        .unwrap_or_default()
}
