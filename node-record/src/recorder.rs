//! The recorder node: every put on `mwb/<space>/**` into an MCAP file.
//!
//! What it sees: puts — jobs, job states, segments, world summaries, node stats (and scene or
//! browse puts, should anyone publish them). What it cannot see: queries and their replies
//! (`q/world`, `q/stats`, the browse requests to node-query and the shards, the open-job
//! queries of late joiners) go from querier to queryable only, and answering them itself would
//! make the recorder part of every query; liveliness tokens live in their own key space.
//! Deletes are counted, not recorded (nothing on the bus deletes today).
//!
//! The subscriber's callback only copies the sample into a bounded queue; a writer thread
//! compresses and writes. When the queue is full the recorder either drops the message — the
//! default: a recorder must not slow the cluster down — or, with [`Overflow::Block`], makes the
//! bus wait (publishers use blocking congestion control, so the cluster then runs at disk
//! speed). Either way it says so: a warning at most once a second with the running totals,
//! the counts in the end metadata record and in the [`RecordSummary`].

use crate::family::Family;
use crate::queue::{BoundedQueue, Overflow, Pushed};
use crate::writer::{RecordingWriter, WriteError, WriteStats, WriterOptions};
use crate::{BusMessage, RecordingInfo, unix_ns};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tracing::{info, warn};
use zenoh::Session;
use zenoh::sample::{Sample, SampleKind};

/// The recorder's role in `alive/<role>/<node>` (so `mwb status` lists it).
pub const ROLE: &str = "recorder";
/// A put that waited longer than this for room in the queue is reported.
const SLOW_PUSH: Duration = Duration::from_millis(100);
/// Warnings about drops or waits: at most one per this many ms.
const WARN_EVERY_MS: u64 = 1000;

/// Recorder settings.
#[derive(Debug, Clone)]
pub struct RecorderConfig {
    pub space: String,
    pub out: PathBuf,
    pub writer: WriterOptions,
    /// Queue bounds between the bus and the writer thread.
    pub queue_messages: usize,
    pub queue_bytes: usize,
    /// What a full queue does (default: drop and count).
    pub overflow: Overflow,
    /// A chunk that has been open this long is closed and flushed, so a crash loses at most
    /// this much.
    pub flush_interval: Duration,
    /// Version of the recording binary (metadata `mwb_version`).
    pub mwb_version: String,
    /// More start metadata (e.g. `recorder_build`).
    pub extra_metadata: BTreeMap<String, String>,
    /// Node id; defaults to the session's zenoh id.
    pub node_id: Option<String>,
}

impl Default for RecorderConfig {
    fn default() -> Self {
        Self {
            space: mwb_core::keys::DEFAULT_SPACE.into(),
            out: PathBuf::from("session.mcap"),
            writer: WriterOptions::default(),
            queue_messages: 1 << 16,
            queue_bytes: 256 << 20,
            overflow: Overflow::Drop,
            flush_interval: Duration::from_secs(2),
            mwb_version: env!("CARGO_PKG_VERSION").into(),
            extra_metadata: BTreeMap::new(),
            node_id: None,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error(transparent)]
    Key(#[from] mwb_core::keys::BadIdentifier),
    #[error("zenoh: {what}")]
    Zenoh {
        what: &'static str,
        #[source]
        source: zenoh::Error,
    },
    #[error(transparent)]
    Write(#[from] WriteError),
    #[error("starting the writer thread")]
    Thread(#[source] std::io::Error),
    #[error("the writer thread panicked")]
    WriterPanicked,
}

/// What the bus side counted.
#[derive(Default)]
struct Counters {
    received: AtomicU64,
    /// Not written: the queue was full, or the writer had stopped.
    dropped: AtomicU64,
    dropped_bytes: AtomicU64,
    dropped_by_family: Mutex<BTreeMap<Family, u64>>,
    /// Time the bus spent waiting for room ([`Overflow::Block`]).
    waited_ns: AtomicU64,
    deletes: AtomicU64,
    written: AtomicU64,
    last_warn_ms: AtomicU64,
    writer_failed: AtomicBool,
}

impl Counters {
    fn dropped_by_family(&self) -> BTreeMap<Family, u64> {
        self.dropped_by_family
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// True at most once per [`WARN_EVERY_MS`].
    fn may_warn(&self, start: Instant) -> bool {
        let now = start.elapsed().as_millis() as u64 + WARN_EVERY_MS;
        let last = self.last_warn_ms.load(Ordering::Relaxed);
        now >= last + WARN_EVERY_MS
            && self
                .last_warn_ms
                .compare_exchange(last, now, Ordering::Relaxed, Ordering::Relaxed)
                .is_ok()
    }
}

/// The end of a recording.
#[derive(Debug)]
pub struct RecordSummary {
    pub path: PathBuf,
    pub written: WriteStats,
    /// Puts received from the bus.
    pub received: u64,
    /// Puts not written (queue full or writer stopped), in all and by family.
    pub dropped: u64,
    pub dropped_bytes: u64,
    pub dropped_by_family: BTreeMap<Family, u64>,
    /// Time the bus waited for the disk ([`Overflow::Block`]).
    pub bus_waited: Duration,
    pub deletes_ignored: u64,
    pub file_bytes: u64,
    /// Why writing stopped early, if it did (the file then ends at its last whole chunk).
    pub write_error: Option<WriteError>,
}

/// A running recorder.
pub struct RecorderHandle {
    subscriber: zenoh::pubsub::Subscriber<()>,
    token: zenoh::liveliness::LivelinessToken,
    queue: Arc<BoundedQueue<BusMessage>>,
    counters: Arc<Counters>,
    writer: std::thread::JoinHandle<(WriteStats, Option<WriteError>)>,
    path: PathBuf,
}

impl RecorderHandle {
    pub fn received(&self) -> u64 {
        self.counters.received.load(Ordering::Relaxed)
    }
    pub fn written(&self) -> u64 {
        self.counters.written.load(Ordering::Relaxed)
    }
    pub fn dropped(&self) -> u64 {
        self.counters.dropped.load(Ordering::Relaxed)
    }

    /// Stops listening, writes what is queued, finishes the file.
    pub async fn finish(self) -> Result<RecordSummary, RecordError> {
        self.subscriber
            .undeclare()
            .await
            .map_err(|source| RecordError::Zenoh {
                what: "undeclaring the subscriber",
                source,
            })?;
        // The token goes with the recorder; an error here changes nothing about the file.
        if let Err(e) = self.token.undeclare().await {
            warn!(error = %e, "recorder: undeclaring the liveliness token");
        }
        self.queue.close();
        let writer = self.writer;
        let (written, write_error) = tokio::task::spawn_blocking(move || writer.join())
            .await
            .map_err(|_| RecordError::WriterPanicked)?
            .map_err(|_| RecordError::WriterPanicked)?;
        let c = &self.counters;
        let file_bytes = std::fs::metadata(&self.path).map_or(0, |m| m.len());
        Ok(RecordSummary {
            path: self.path,
            written,
            received: c.received.load(Ordering::Relaxed),
            dropped: c.dropped.load(Ordering::Relaxed),
            dropped_bytes: c.dropped_bytes.load(Ordering::Relaxed),
            dropped_by_family: c.dropped_by_family(),
            bus_waited: Duration::from_nanos(c.waited_ns.load(Ordering::Relaxed)),
            deletes_ignored: c.deletes.load(Ordering::Relaxed),
            file_bytes,
            write_error,
        })
    }
}

/// Starts recording `mwb/<space>/**` on `session` into `cfg.out` (created or truncated).
/// Messages published before this returns are not in the recording.
pub async fn run_recorder(
    session: &Session,
    cfg: RecorderConfig,
) -> Result<RecorderHandle, RecordError> {
    let keys = mwb_core::keys::Keys::new(&cfg.space)?;
    let node_id = cfg
        .node_id
        .clone()
        .unwrap_or_else(|| session.zid().to_string());
    mwb_core::keys::check_identifier("node id", &node_id)?;
    let info = RecordingInfo {
        mwb_version: cfg.mwb_version.clone(),
        space: cfg.space.clone(),
        start_unix_ns: unix_ns(),
        recorder: node_id.clone(),
        extra: cfg.extra_metadata.clone(),
    };
    // Created here, so that a path that cannot be written fails the command at once.
    let writer = RecordingWriter::create(&cfg.out, &info, &cfg.writer)?;
    let queue = Arc::new(BoundedQueue::new(cfg.queue_messages, cfg.queue_bytes));
    let counters = Arc::new(Counters::default());
    let writer = spawn_writer(writer, queue.clone(), counters.clone(), cfg.flush_interval)?;
    let token = session
        .liveliness()
        .declare_token(keys.alive(ROLE, &node_id))
        .await
        .map_err(|source| RecordError::Zenoh {
            what: "declaring the liveliness token",
            source,
        })?;
    let subscriber = session
        .declare_subscriber(keys.all())
        .callback(on_sample(queue.clone(), counters.clone(), cfg.overflow))
        .await
        .map_err(|source| RecordError::Zenoh {
            what: "subscribing",
            source,
        })?;
    info!(space = %cfg.space, out = %cfg.out.display(), overflow = ?cfg.overflow, "recording");
    Ok(RecorderHandle {
        subscriber,
        token,
        queue,
        counters,
        writer,
        path: cfg.out,
    })
}

/// The subscriber's callback: copy, timestamp, queue. It runs on zenoh's receive path, so it
/// does nothing slow (no decoding, no I/O) unless told to wait for room.
fn on_sample(
    queue: Arc<BoundedQueue<BusMessage>>,
    counters: Arc<Counters>,
    overflow: Overflow,
) -> impl Fn(Sample) + Send + Sync + 'static {
    let start = Instant::now();
    move |sample: Sample| {
        if sample.kind() != SampleKind::Put {
            counters.deletes.fetch_add(1, Ordering::Relaxed);
            return;
        }
        let log_time_ns = unix_ns();
        let msg = BusMessage {
            key: sample.key_expr().as_str().to_owned(),
            payload: sample.payload().to_bytes().into_owned(),
            log_time_ns,
            publish_time_ns: sample
                .timestamp()
                .map(|t| u64::try_from(t.get_time().to_duration().as_nanos()).unwrap_or(u64::MAX)),
        };
        counters.received.fetch_add(1, Ordering::Relaxed);
        let bytes = msg.key.len() + msg.payload.len();
        let family = Family::of_key(&msg.key);
        match queue.push(msg, bytes, overflow) {
            Pushed::Queued { waited } => {
                let ns = u64::try_from(waited.as_nanos()).unwrap_or(u64::MAX);
                let total = counters.waited_ns.fetch_add(ns, Ordering::Relaxed) + ns;
                if waited > SLOW_PUSH && counters.may_warn(start) {
                    warn!(
                        waited_ms = waited.as_millis() as u64,
                        total_waited_s = total as f64 * 1e-9,
                        "RECORDER IS SLOWING THE BUS: the disk cannot keep up; publishers wait for it"
                    );
                }
            }
            Pushed::Dropped | Pushed::Closed => {
                let n = counters.dropped.fetch_add(1, Ordering::Relaxed) + 1;
                counters
                    .dropped_bytes
                    .fetch_add(bytes as u64, Ordering::Relaxed);
                *counters
                    .dropped_by_family
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .entry(family)
                    .or_default() += 1;
                if counters.may_warn(start) {
                    let why = if counters.writer_failed.load(Ordering::Relaxed) {
                        "the writer stopped"
                    } else {
                        "the disk cannot keep up"
                    };
                    warn!(
                        not_written = n,
                        received = counters.received.load(Ordering::Relaxed),
                        "RECORDING IS LOSING MESSAGES: {why}; they are counted and reported at the end"
                    );
                }
            }
        }
    }
}

fn spawn_writer(
    mut writer: RecordingWriter<std::io::BufWriter<std::fs::File>>,
    queue: Arc<BoundedQueue<BusMessage>>,
    counters: Arc<Counters>,
    flush_interval: Duration,
) -> Result<std::thread::JoinHandle<(WriteStats, Option<WriteError>)>, RecordError> {
    std::thread::Builder::new()
        .name("mwb-record-writer".into())
        .spawn(move || {
            let mut error = None;
            let mut dirty_since: Option<Instant> = None;
            let tick = flush_interval.clamp(Duration::from_millis(10), Duration::from_millis(250));
            loop {
                match queue.pop_timeout(tick) {
                    Ok(msg) => {
                        if let Err(e) = writer.write(&msg) {
                            error = Some(e);
                            break;
                        }
                        counters.written.fetch_add(1, Ordering::Relaxed);
                        dirty_since.get_or_insert_with(Instant::now);
                    }
                    Err(closed) => {
                        if closed {
                            break;
                        }
                    }
                }
                if dirty_since.is_some_and(|t| t.elapsed() >= flush_interval) {
                    if let Err(e) = writer.flush() {
                        error = Some(e);
                        break;
                    }
                    dirty_since = None;
                }
            }
            if let Some(e) = &error {
                // Everything from now on is counted as not written by the callback.
                counters.writer_failed.store(true, Ordering::Relaxed);
                warn!(error = %e, "RECORDING STOPPED: cannot write; the file ends at its last whole chunk");
                for msg in queue.abandon() {
                    counters.dropped.fetch_add(1, Ordering::Relaxed);
                    counters
                        .dropped_bytes
                        .fetch_add((msg.key.len() + msg.payload.len()) as u64, Ordering::Relaxed);
                    *counters
                        .dropped_by_family
                        .lock()
                        .unwrap_or_else(|p| p.into_inner())
                        .entry(Family::of_key(&msg.key))
                        .or_default() += 1;
                }
                return (writer.stats().clone(), error);
            }
            let mut end = BTreeMap::new();
            end.insert("end_unix_ns".into(), unix_ns().to_string());
            end.insert(
                "received".into(),
                counters.received.load(Ordering::Relaxed).to_string(),
            );
            end.insert(
                "not_written".into(),
                counters.dropped.load(Ordering::Relaxed).to_string(),
            );
            for (f, n) in counters.dropped_by_family() {
                end.insert(format!("not_written.{}", f.topic()), n.to_string());
            }
            end.insert(
                "bus_waited_ns".into(),
                counters.waited_ns.load(Ordering::Relaxed).to_string(),
            );
            let stats = writer.stats().clone();
            match writer.finish(end) {
                Ok(stats) => (stats, None),
                Err(e) => (stats, Some(e)),
            }
        })
        .map_err(RecordError::Thread)
}
