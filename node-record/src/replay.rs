//! Replay: a recording back onto the bus, in the order it was recorded.
//!
//! Timing follows the receive times (`log_time`): at speed 1 the gaps are the original ones,
//! at speed 4 a quarter, at `max` there are none. Keys keep everything but the space, which
//! becomes the target space (`mwb/<recorded>/…` → `mwb/<target>/…`), so a session can be
//! replayed beside the one it came from. Jobs, job states, segments and world summaries are
//! put with blocking congestion control — they must arrive, as in the live system; node stats
//! with zenoh's default (drop under congestion), as their publishers do.
//!
//! A store takes jobs and segments on separate subscribers, so at `max` speed a world can be
//! complete in the store before its job is applied; the store holds such a world (for a
//! bounded time and memory) and stores it when the job arrives, so the replay does not pause.

use crate::family::Family;
use crate::reader::{ReadError, ReadStats, RecordedMessage, RecordingReader};
use mwb_core::keys::Keys;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::{Duration, Instant};
use tokio::sync::mpsc;
use tracing::{info, warn};
use zenoh::Session;
use zenoh::qos::CongestionControl;

/// How fast to replay.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Speed {
    /// Original gaps divided by this factor (> 0).
    Factor(f64),
    /// No waiting.
    Max,
}

impl std::str::FromStr for Speed {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let t = s.trim();
        if t.eq_ignore_ascii_case("max") {
            return Ok(Speed::Max);
        }
        match t.trim_end_matches('x').parse::<f64>() {
            Ok(f) if f.is_finite() && f > 0.0 => Ok(Speed::Factor(f)),
            _ => Err(format!(
                "speed {s:?}: a factor > 0 (1 = original timing, 4 = four times as fast) or \"max\""
            )),
        }
    }
}

impl std::fmt::Display for Speed {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Speed::Factor(x) => write!(f, "{x}"),
            Speed::Max => f.write_str("max"),
        }
    }
}

impl Speed {
    /// When a message recorded at `log_ns` is due, counted from the start of the replay
    /// (whose first message was recorded at `first_ns`); `None`: at once. Receive times that
    /// go backwards (clock steps, racing receive threads) are due at once, never reordered.
    pub fn due(self, first_ns: u64, log_ns: u64) -> Option<Duration> {
        match self {
            Speed::Max => None,
            Speed::Factor(f) => {
                let gap = log_ns.saturating_sub(first_ns) as f64 * 1e-9 / f;
                Some(Duration::try_from_secs_f64(gap).unwrap_or(Duration::MAX))
            }
        }
    }
}

/// `key` in space `space`: the second chunk of `mwb/<space>/…` replaced; `None` for a key
/// that is not a manyworlds key.
pub fn retarget(key: &str, space: &str) -> Option<String> {
    let rest = key.strip_prefix("mwb/")?;
    let (recorded, tail) = rest.split_once('/')?;
    if recorded.is_empty() || tail.is_empty() {
        return None;
    }
    Some(format!("mwb/{space}/{tail}"))
}

/// Congestion control for a family on replay (see the module docs).
pub fn congestion_control(family: Family) -> CongestionControl {
    match family {
        Family::Stats | Family::QStats => CongestionControl::Drop,
        _ => CongestionControl::Block,
    }
}

/// Replay settings.
#[derive(Debug, Clone)]
pub struct ReplayConfig {
    pub path: PathBuf,
    pub speed: Speed,
    /// Target space.
    pub space: String,
    /// Before the first message, wait up to this long for subscribers of jobs, segments and
    /// world summaries in the target space (a store): zenoh routes a put only to subscribers
    /// it already knows, so a replay started beside a store that is still starting would be
    /// lost on it. Zero: do not wait.
    pub wait_for_subscribers: Duration,
}

impl Default for ReplayConfig {
    fn default() -> Self {
        Self {
            path: PathBuf::from("session.mcap"),
            speed: Speed::Factor(1.0),
            space: mwb_core::keys::DEFAULT_SPACE.into(),
            wait_for_subscribers: Duration::from_secs(10),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error(transparent)]
    Open(#[from] ReadError),
    #[error(transparent)]
    Key(#[from] mwb_core::keys::BadIdentifier),
    #[error("zenoh: {what}")]
    Zenoh {
        what: &'static str,
        #[source]
        source: zenoh::Error,
    },
    #[error("starting the reader thread")]
    Thread(#[source] std::io::Error),
}

/// What a replay did.
#[derive(Debug)]
pub struct ReplaySummary {
    pub published: u64,
    pub by_family: BTreeMap<Family, u64>,
    /// Messages whose key is not `mwb/<space>/…`, and store shards' counts
    /// ([`Family::is_shard_count`]): not published.
    pub skipped_keys: u64,
    pub put_failures: u64,
    /// The reader's counts (unknown channels skipped, chunks, complete).
    pub read: ReadStats,
    /// Damage that ended the replay early: every message before it was published.
    pub damage: Option<ReadError>,
    /// The space the recording was made in (its start metadata).
    pub recorded_space: Option<String>,
    /// Whether subscribers of the target space were seen before the first message.
    pub subscribers_seen: bool,
    /// Wall time of the replay, and the span of the recording it covered.
    pub seconds: f64,
    pub recorded_seconds: f64,
    /// Stopped by the caller before the end.
    pub stopped: bool,
}

enum Item {
    Message(RecordedMessage),
    End {
        stats: ReadStats,
        damage: Option<ReadError>,
        space: Option<String>,
    },
}

/// Replays `cfg.path` on `session` until its end, its first damage, or `stop` resolves.
pub async fn replay(
    session: &Session,
    cfg: &ReplayConfig,
    stop: impl std::future::Future<Output = ()>,
) -> Result<ReplaySummary, ReplayError> {
    let keys = Keys::new(&cfg.space)?;
    let reader = RecordingReader::open(&cfg.path)?;
    let (tx, mut rx) = mpsc::channel::<Item>(256);
    let reader_thread = std::thread::Builder::new()
        .name("mwb-replay-reader".into())
        .spawn(move || read_into(reader, tx))
        .map_err(ReplayError::Thread)?;

    let subscribers_seen = if cfg.wait_for_subscribers.is_zero() {
        false
    } else {
        wait_for_subscribers(session, &keys, cfg.wait_for_subscribers).await?
    };
    if !cfg.wait_for_subscribers.is_zero() && !subscribers_seen {
        warn!(space = %cfg.space, "replay: no store (subscriber of jobs, segments and summaries) seen; replaying anyway");
    }

    let mut s = ReplaySummary {
        published: 0,
        by_family: BTreeMap::new(),
        skipped_keys: 0,
        put_failures: 0,
        read: ReadStats::default(),
        damage: None,
        recorded_space: None,
        subscribers_seen,
        seconds: 0.0,
        recorded_seconds: 0.0,
        stopped: false,
    };
    let start = Instant::now();
    let mut first_ns: Option<u64> = None;
    let mut last_ns = 0u64;
    tokio::pin!(stop);
    loop {
        let item = tokio::select! {
            item = rx.recv() => item,
            () = &mut stop => { s.stopped = true; break; }
        };
        let m = match item {
            Some(Item::Message(m)) => m,
            Some(Item::End {
                stats,
                damage,
                space,
            }) => {
                s.read = stats;
                s.damage = damage;
                s.recorded_space = space;
                break;
            }
            None => break,
        };
        let first = *first_ns.get_or_insert(m.log_time_ns);
        last_ns = last_ns.max(m.log_time_ns);
        if let Some(at) = cfg.speed.due(first, m.log_time_ns).map(|d| start + d)
            && at > Instant::now()
        {
            tokio::select! {
                () = tokio::time::sleep_until(at.into()) => {}
                () = &mut stop => { s.stopped = true; break; }
            }
        }
        let Some(key) = retarget(&m.key, &cfg.space).filter(|_| !Family::is_shard_count(&m.key))
        else {
            s.skipped_keys += 1;
            continue;
        };
        match session
            .put(&key, m.payload)
            .congestion_control(congestion_control(m.family))
            .await
        {
            Ok(()) => {
                s.published += 1;
                *s.by_family.entry(m.family).or_default() += 1;
            }
            Err(e) => {
                s.put_failures += 1;
                warn!(%key, error = %e, "replay: put failed");
            }
        }
    }
    drop(rx);
    // The reader ends on its own once the channel is closed.
    if let Err(e) = tokio::task::spawn_blocking(move || reader_thread.join()).await {
        warn!(error = %e, "replay: reader thread");
    }
    s.seconds = start.elapsed().as_secs_f64();
    s.recorded_seconds = first_ns.map_or(0.0, |f| last_ns.saturating_sub(f) as f64 * 1e-9);
    info!(published = s.published, seconds = s.seconds, "replay done");
    Ok(s)
}

fn read_into(mut reader: RecordingReader, tx: mpsc::Sender<Item>) {
    let mut damage = None;
    for m in reader.by_ref() {
        match m {
            Ok(m) => {
                if tx.blocking_send(Item::Message(m)).is_err() {
                    return;
                }
            }
            Err(e) => damage = Some(e),
        }
    }
    let end = Item::End {
        stats: reader.stats().clone(),
        damage,
        space: reader.info().map(|i| i.space.clone()),
    };
    // The replay may have stopped already; then nobody wants the end.
    let _ = tx.blocking_send(end);
}

/// Waits until the target space has subscribers for jobs, segments and summaries.
async fn wait_for_subscribers(
    session: &Session,
    keys: &Keys,
    timeout: Duration,
) -> Result<bool, ReplayError> {
    const PROBE: &str = "replay-probe";
    let mut publishers = Vec::new();
    for key in [
        keys.job(PROBE),
        keys.segment(PROBE, PROBE, 0, 0),
        keys.done(PROBE, PROBE, 0),
    ] {
        publishers.push(session.declare_publisher(key).await.map_err(|source| {
            ReplayError::Zenoh {
                what: "declaring a probe publisher",
                source,
            }
        })?);
    }
    let deadline = Instant::now() + timeout;
    loop {
        let mut all = true;
        for p in &publishers {
            let m = p
                .matching_status()
                .await
                .map_err(|source| ReplayError::Zenoh {
                    what: "matching status",
                    source,
                })?;
            all &= m.matching();
        }
        if all {
            return Ok(true);
        }
        if Instant::now() >= deadline {
            return Ok(false);
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn speeds_parse_and_schedule() {
        assert_eq!("1".parse(), Ok(Speed::Factor(1.0)));
        assert_eq!("4x".parse(), Ok(Speed::Factor(4.0)));
        assert_eq!("MAX".parse(), Ok(Speed::Max));
        for bad in ["0", "-1", "fast", "inf", ""] {
            assert!(bad.parse::<Speed>().is_err(), "{bad}");
        }
        let s = 1_000_000_000u64;
        assert_eq!(
            Speed::Factor(1.0).due(s, 3 * s),
            Some(Duration::from_secs(2))
        );
        assert_eq!(
            Speed::Factor(4.0).due(s, 3 * s),
            Some(Duration::from_millis(500))
        );
        // Backwards receive time: due at the start, not before it.
        assert_eq!(Speed::Factor(1.0).due(3 * s, s), Some(Duration::ZERO));
        assert_eq!(Speed::Max.due(s, 3 * s), None);
    }

    #[test]
    fn keys_move_to_the_target_space() {
        assert_eq!(
            retarget("mwb/demo/seg/j/n/0/1", "other").as_deref(),
            Some("mwb/other/seg/j/n/0/1")
        );
        assert_eq!(
            retarget("mwb/demo/q/stats", "x").as_deref(),
            Some("mwb/x/q/stats")
        );
        for bad in ["mwb/demo", "mwb//seg/x", "other/demo/seg", "mwb/demo/"] {
            assert_eq!(retarget(bad, "x"), None, "{bad}");
        }
        assert_eq!(
            congestion_control(Family::Segment),
            CongestionControl::Block
        );
        assert_eq!(congestion_control(Family::Stats), CongestionControl::Drop);
    }
}
