//! Writing a recording: bus messages → MCAP (zstd chunks, schemas embedded, one channel per
//! family created on first use, a metadata record at the start and one at the end).

use crate::family::{Family, RecordFormatError, encode_record, schema_data};
use crate::{BusMessage, END_METADATA, INFO_METADATA, RecordingInfo};
use mcap::records::Metadata;
use mwb_proto::v1::{Job, Message, WorldDone};
use std::collections::{BTreeMap, BTreeSet};
use std::io::{BufWriter, Seek, Write};
use std::path::{Path, PathBuf};

/// Distinct provenance strings and scene hashes kept for the end record (a recording of one
/// session has one or two; a flood of distinct ones must not grow the record without bound).
const MAX_DISTINCT: usize = 32;

/// The MCAP header's `library` of our files starts with this (the reader relies on what this
/// writer does: everything but metadata inside chunks).
pub const LIBRARY: &str = "mwb-record";

/// How the MCAP file is written.
#[derive(Debug, Clone)]
pub struct WriterOptions {
    /// Uncompressed bytes per chunk (default 1 MiB, the mcap crate's). Smaller chunks lose
    /// less on a crash and cost a little compression.
    pub chunk_size: u64,
    /// zstd level (0 = zstd's default, 3).
    pub compression_level: u32,
    /// zstd worker threads (0 = compress on the writer thread: the recorder runs beside the
    /// samplers and should not take their cores).
    pub compression_threads: u32,
}

impl Default for WriterOptions {
    fn default() -> Self {
        Self {
            chunk_size: mcap::WriteOptions::DEFAULT_CHUNK_SIZE,
            compression_level: 0,
            compression_threads: 0,
        }
    }
}

/// A recording that cannot be written.
#[derive(Debug, thiserror::Error)]
pub enum WriteError {
    #[error("creating {}", path.display())]
    Create {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("writing the recording ({what})")]
    Mcap {
        what: &'static str,
        #[source]
        source: mcap::McapError,
    },
    #[error(transparent)]
    Format(#[from] RecordFormatError),
}

fn mcap_err(what: &'static str) -> impl FnOnce(mcap::McapError) -> WriteError {
    move |source| WriteError::Mcap { what, source }
}

/// What has been written so far.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct WriteStats {
    pub messages: u64,
    pub by_family: BTreeMap<Family, u64>,
    /// Bus payload bytes (before wrapping and compression).
    pub payload_bytes: u64,
    /// `WorldDone.provenance` values seen (binary and physics build of the worlds).
    pub provenance: BTreeSet<String>,
    /// `Job.scene.content_hash` and `WorldDone.scene_hash` values seen.
    pub scene_hashes: BTreeSet<u64>,
    pub first_log_time_ns: Option<u64>,
    pub last_log_time_ns: Option<u64>,
}

/// An MCAP recording being written.
pub struct RecordingWriter<W: Write + Seek> {
    mcap: mcap::Writer<W>,
    channels: BTreeMap<Family, u16>,
    sequence: u32,
    stats: WriteStats,
}

impl RecordingWriter<BufWriter<std::fs::File>> {
    /// Creates (or truncates) `path`.
    pub fn create(
        path: &Path,
        info: &RecordingInfo,
        opts: &WriterOptions,
    ) -> Result<Self, WriteError> {
        let file = std::fs::File::create(path).map_err(|source| WriteError::Create {
            path: path.to_owned(),
            source,
        })?;
        Self::new(BufWriter::with_capacity(1 << 20, file), info, opts)
    }
}

impl<W: Write + Seek> RecordingWriter<W> {
    pub fn new(w: W, info: &RecordingInfo, opts: &WriterOptions) -> Result<Self, WriteError> {
        let mut mcap = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .compression_level(opts.compression_level)
            .compression_threads(opts.compression_threads)
            .chunk_size(Some(opts.chunk_size.max(1)))
            .profile("")
            .library(format!("{LIBRARY} {}", env!("CARGO_PKG_VERSION")))
            .create(w)
            .map_err(mcap_err("header"))?;
        mcap.write_metadata(&info.to_metadata())
            .map_err(mcap_err("metadata"))?;
        Ok(Self {
            mcap,
            channels: BTreeMap::new(),
            sequence: 0,
            stats: WriteStats::default(),
        })
    }

    fn channel(&mut self, family: Family) -> Result<u16, WriteError> {
        if let Some(&id) = self.channels.get(&family) {
            return Ok(id);
        }
        let schema = self
            .mcap
            .add_schema(
                family.schema_name(),
                family.schema_encoding(),
                &schema_data(family),
            )
            .map_err(mcap_err("schema"))?;
        let id = self
            .mcap
            .add_channel(
                schema,
                family.topic(),
                family.message_encoding(),
                &BTreeMap::new(),
            )
            .map_err(mcap_err("channel"))?;
        self.channels.insert(family, id);
        Ok(id)
    }

    /// Writes one bus message to its family's channel (`Raw` if its payload is not of the
    /// family's type). `publish_time` is the message's own time where it has one: the
    /// sender's zenoh timestamp, else a job's creation time, else the receive time.
    pub fn write(&mut self, msg: &BusMessage) -> Result<Family, WriteError> {
        let family = Family::classify(&msg.key, &msg.payload);
        let mut publish_ns = msg.publish_time_ns;
        match family {
            Family::Job => {
                if let Ok(job) = Job::decode(msg.payload.as_slice()) {
                    if let Some(scene) = &job.scene {
                        self.note_scene(scene.content_hash);
                    }
                    if publish_ns.is_none() && job.created_unix_ms > 0 {
                        publish_ns = Some(job.created_unix_ms.saturating_mul(1_000_000));
                    }
                }
            }
            Family::Done => {
                if let Ok(done) = WorldDone::decode(msg.payload.as_slice()) {
                    self.note_scene(done.scene_hash);
                    if !done.provenance.is_empty() && self.stats.provenance.len() < MAX_DISTINCT {
                        self.stats.provenance.insert(done.provenance);
                    }
                }
            }
            _ => {}
        }
        let channel_id = self.channel(family)?;
        let data = encode_record(family, &msg.key, &msg.payload)?;
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence: self.sequence,
            log_time: msg.log_time_ns,
            publish_time: publish_ns.unwrap_or(msg.log_time_ns),
        };
        self.mcap
            .write_to_known_channel(&header, &data)
            .map_err(mcap_err("message"))?;
        self.sequence = self.sequence.wrapping_add(1);
        let s = &mut self.stats;
        s.messages += 1;
        *s.by_family.entry(family).or_default() += 1;
        s.payload_bytes += msg.payload.len() as u64;
        s.first_log_time_ns.get_or_insert(msg.log_time_ns);
        s.last_log_time_ns = Some(msg.log_time_ns);
        Ok(family)
    }

    fn note_scene(&mut self, hash: u64) {
        if hash != 0 && self.stats.scene_hashes.len() < MAX_DISTINCT {
            self.stats.scene_hashes.insert(hash);
        }
    }

    /// Ends the current chunk and flushes it to the file, so a crash later loses nothing
    /// written so far.
    pub fn flush(&mut self) -> Result<(), WriteError> {
        self.mcap.flush().map_err(mcap_err("flush"))
    }

    pub fn stats(&self) -> &WriteStats {
        &self.stats
    }

    /// Writes the end metadata (`end` plus what the writer counted), the summary and the
    /// footer.
    pub fn finish(mut self, end: BTreeMap<String, String>) -> Result<WriteStats, WriteError> {
        let mut meta = end;
        let s = &self.stats;
        meta.insert("messages".into(), s.messages.to_string());
        for (f, n) in &s.by_family {
            meta.insert(format!("messages.{}", f.topic()), n.to_string());
        }
        meta.insert("payload_bytes".into(), s.payload_bytes.to_string());
        if !s.provenance.is_empty() {
            let p: Vec<&str> = s.provenance.iter().map(String::as_str).collect();
            meta.insert("provenance".into(), p.join("\n"));
        }
        if !s.scene_hashes.is_empty() {
            let h: Vec<String> = s.scene_hashes.iter().map(|h| format!("{h:016x}")).collect();
            meta.insert("scene_hashes".into(), h.join(","));
        }
        self.mcap
            .write_metadata(&Metadata {
                name: END_METADATA.into(),
                metadata: meta,
            })
            .map_err(mcap_err("end metadata"))?;
        self.mcap.finish().map_err(mcap_err("summary"))?;
        Ok(self.stats.clone())
    }
}

impl RecordingInfo {
    pub(crate) fn to_metadata(&self) -> Metadata {
        let mut m = self.extra.clone();
        m.insert("format".into(), crate::FORMAT.into());
        m.insert("mwb_version".into(), self.mwb_version.clone());
        m.insert("space".into(), self.space.clone());
        m.insert("start_unix_ns".into(), self.start_unix_ns.to_string());
        m.insert("recorder".into(), self.recorder.clone());
        Metadata {
            name: INFO_METADATA.into(),
            metadata: m,
        }
    }
}
