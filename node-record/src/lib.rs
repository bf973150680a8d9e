//! Recordings of the manyworlds bus in MCAP, and their replay.
//!
//! * [`family`] — pure: which channel a message belongs to (one per key family: `job`,
//!   `job/state`, `seg`, `done`, `stats`, …), the per-message record that keeps its full zenoh
//!   key, the schemas (the `mwb.v1` descriptor set plus the wrappers; a JSON schema for the
//!   browse channel).
//! * [`queue`] — the bounded queue between the bus and the disk.
//! * [`writer`] — MCAP with zstd chunks, metadata at the start and at the end.
//! * [`reader`] — in-order reading that stops at the first damage with the file and byte
//!   offset, keeping everything before it.
//! * [`recorder`] — the bus node: subscribes to `mwb/<space>/**`, never blocks the bus silently
//!   and never drops silently.
//! * [`replay`] — a recording back onto the bus, in order, at its original pace or faster,
//!   optionally into another space.
//!
//! Writing and reading back:
//!
//! ```
//! use mwb_proto::v1::{JobState, Message};
//! use mwb_record::{BusMessage, Family, RecordingInfo, RecordingWriter, WriterOptions, read_recording};
//!
//! let dir = tempfile::tempdir().unwrap();
//! let path = dir.path().join("session.mcap");
//! let info = RecordingInfo { space: "demo".into(), ..RecordingInfo::now("example") };
//! let mut w = RecordingWriter::create(&path, &info, &WriterOptions::default()).unwrap();
//! let state = JobState { job_id: "j1".into(), worlds_done: 3, ..Default::default() };
//! let msg = BusMessage {
//!     key: "mwb/demo/job/j1/state".into(),
//!     payload: state.encode_to_vec(),
//!     log_time_ns: 1_000,
//!     publish_time_ns: None,
//! };
//! assert_eq!(w.write(&msg).unwrap(), Family::JobState);
//! w.finish(Default::default()).unwrap();
//!
//! let back = read_recording(&path).unwrap();
//! assert!(back.error.is_none() && back.stats.complete);
//! assert_eq!(back.info.unwrap().space, "demo");
//! assert_eq!(back.messages.len(), 1);
//! assert_eq!(back.messages[0].key, "mwb/demo/job/j1/state");
//! assert_eq!(back.messages[0].payload, msg.payload);
//! assert_eq!(back.messages[0].publish_time_ns, 1_000); // no time of its own: receive time
//! ```

pub mod family;
pub mod queue;
pub mod reader;
pub mod recorder;
pub mod replay;
pub mod writer;

pub use family::Family;
pub use queue::Overflow;
pub use reader::{
    Damage, ReadError, ReadStats, RecordedMessage, RecordingReader, Recovered, read_recording,
};
pub use recorder::{RecordError, RecordSummary, RecorderConfig, RecorderHandle, run_recorder};
pub use replay::{ReplayConfig, ReplayError, ReplaySummary, Speed, replay};
pub use writer::{RecordingWriter, WriteError, WriteStats, WriterOptions};

use std::collections::BTreeMap;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// The recording layout this crate writes (metadata `format`).
pub const FORMAT: &str = "mwb-record 1";
/// Name of the metadata record at the start of a recording ([`RecordingInfo`]).
pub const INFO_METADATA: &str = "mwb.recording";
/// Name of the metadata record a finished recording ends with (counts, provenance, scene
/// hashes, what could not be written).
pub const END_METADATA: &str = "mwb.recording.end";

/// One message as it came off the bus.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BusMessage {
    pub key: String,
    pub payload: Vec<u8>,
    /// Receive time, ns since the Unix epoch.
    pub log_time_ns: u64,
    /// The sender's zenoh timestamp, if the sample carried one.
    pub publish_time_ns: Option<u64>,
}

/// What a recording says about itself (the start metadata record).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct RecordingInfo {
    /// Version of the `mwb` binary that recorded.
    pub mwb_version: String,
    pub space: String,
    pub start_unix_ns: u64,
    /// The recorder's node id.
    pub recorder: String,
    /// Anything else the caller knows (e.g. `recorder_build`: the recording binary's
    /// provenance string).
    pub extra: BTreeMap<String, String>,
}

impl RecordingInfo {
    /// Started now, by `recorder`, in the default space.
    pub fn now(recorder: &str) -> Self {
        Self {
            mwb_version: env!("CARGO_PKG_VERSION").into(),
            space: mwb_core::keys::DEFAULT_SPACE.into(),
            start_unix_ns: unix_ns(),
            recorder: recorder.into(),
            extra: BTreeMap::new(),
        }
    }
}

/// Now, ns since the Unix epoch (0 if the clock is before it).
pub fn unix_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
}

/// A duration as a user writes it: `500ms`, `90s`, `10m`, `1h`, `1.5h`, or plain seconds.
pub fn parse_duration(text: &str) -> Result<Duration, String> {
    let t = text.trim();
    let split = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    let (num, unit) = t.split_at(split);
    let value: f64 = num
        .parse()
        .map_err(|_| format!("duration {text:?}: expected a number and a unit (ms, s, m, h)"))?;
    let scale = match unit.trim() {
        "ms" => 1e-3,
        "" | "s" => 1.0,
        "m" | "min" => 60.0,
        "h" => 3600.0,
        other => {
            return Err(format!(
                "duration {text:?}: unknown unit {other:?} (ms, s, m, h)"
            ));
        }
    };
    Duration::try_from_secs_f64(value * scale).map_err(|e| format!("duration {text:?}: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations() {
        assert_eq!(parse_duration("10m"), Ok(Duration::from_secs(600)));
        assert_eq!(parse_duration("90s"), Ok(Duration::from_secs(90)));
        assert_eq!(parse_duration("90"), Ok(Duration::from_secs(90)));
        assert_eq!(parse_duration("250ms"), Ok(Duration::from_millis(250)));
        assert_eq!(parse_duration("1.5h"), Ok(Duration::from_secs(5400)));
        for bad in ["", "m", "10x", "-3s", "1..2s"] {
            assert!(parse_duration(bad).is_err(), "{bad}");
        }
    }
}
