//! Reading a recording in order, with recovery.
//!
//! The reader walks the file's records itself (MCAP is a flat list of `opcode, u64 length,
//! body` after an 8-byte magic), so that damage is reported at the byte offset of the record
//! where it is found, and so that nothing from a damaged chunk reaches the caller: a chunk's
//! messages are handed out only after the whole chunk decompressed and its CRC matched. On the
//! first damage — a record cut short, a CRC mismatch (chunk, data section, summary), a record
//! that does not parse, garbage where a record should start — iteration yields one
//! [`ReadError`] naming the file and offset and then ends; every message before it has been
//! yielded and [`RecordingReader::stats`] says how many. Nothing past the damage is read: a
//! replay or a load must not jump over a hole in the middle of a world.
//!
//! To find damage where it is rather than at the next CRC, every record is checked against
//! what its contents imply: its length, a chunk's time bounds, the message index records after
//! a chunk against the messages in it, the opcodes that may appear in each section. A flipped
//! bit that changes no message (in metadata text, in a redundant bit of zstd's tables, in the
//! summary) is found by the data or summary section's CRC at the section's end.
//!
//! Channels the reader does not know (another topic, or a known topic with another schema)
//! are skipped and counted by topic.

use crate::family::{Family, decode_record};
use crate::{END_METADATA, INFO_METADATA, RecordingInfo};
use mcap::records::{Record, op};
use std::collections::{BTreeMap, HashMap, VecDeque};
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};

/// Opcode and length of every record.
const RECORD_HEADER: u64 = 1 + 8;
/// A chunk that claims to decompress to more than this is damage, not data (the writer's
/// chunks are ~1 MiB; a flipped high bit in the size field must not allocate gigabytes).
const MAX_CHUNK_UNCOMPRESSED: u64 = 1 << 30;

/// One recorded bus message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RecordedMessage {
    pub family: Family,
    /// The full zenoh key it was published on.
    pub key: String,
    /// The bus payload, byte for byte.
    pub payload: Vec<u8>,
    /// Receive time at the recorder, ns since the Unix epoch.
    pub log_time_ns: u64,
    /// The message's own time (see [`crate::RecordingWriter::write`]).
    pub publish_time_ns: u64,
    pub sequence: u32,
}

/// Per channel, the (log time, offset in the chunk's records) of each message, sorted: what
/// the message index records after a chunk must say.
type MessagePlaces = HashMap<u16, Vec<(u64, u64)>>;

/// What is wrong at [`ReadError::offset`].
#[derive(Debug, thiserror::Error)]
pub enum Damage {
    #[error("cannot read the file")]
    Io(#[source] std::io::Error),
    #[error("not an MCAP file (bad magic)")]
    BadMagic,
    #[error("cut short: the record needs {needed} bytes, {available} remain")]
    Truncated { needed: u64, available: u64 },
    #[error("file ends without a footer (the recorder did not finish it)")]
    NoFooter,
    #[error("record (opcode {opcode:#04x}) does not parse")]
    BadRecord {
        opcode: u8,
        #[source]
        source: mcap::McapError,
    },
    #[error("chunk does not decompress ({compression})")]
    Decompress {
        compression: String,
        #[source]
        source: std::io::Error,
    },
    #[error("chunk compression {0:?} is not supported")]
    Compression(String),
    #[error("chunk decompresses to {got} bytes, its header says {expected}")]
    ChunkSize { expected: u64, got: u64 },
    #[error("chunk CRC mismatch: saved {saved:08x}, computed {computed:08x}")]
    ChunkCrc { saved: u32, computed: u32 },
    #[error("record {at} bytes into the chunk's contents: {detail}")]
    ChunkContents { at: u64, detail: String },
    #[error("record (opcode {opcode:#04x}) has no place here")]
    Unexpected { opcode: u8 },
    #[error("record (opcode {opcode:#04x}) is {len} bytes long, its contents make {expected}")]
    Length { opcode: u8, len: u64, expected: u64 },
    #[error("chunk header: {field} is {saved}, the chunk's contents say {computed}")]
    ChunkHeader {
        field: &'static str,
        saved: u64,
        computed: u64,
    },
    #[error("message index of channel {channel} does not match the chunk before it")]
    MessageIndex { channel: u16 },
    #[error("data section CRC mismatch: saved {saved:08x}, computed {computed:08x}")]
    DataCrc { saved: u32, computed: u32 },
    #[error("summary section CRC mismatch: saved {saved:08x}, computed {computed:08x}")]
    SummaryCrc { saved: u32, computed: u32 },
}

/// A damaged recording: where, and what.
#[derive(Debug, thiserror::Error)]
#[error("{}: byte {offset}: {damage}", path.display())]
pub struct ReadError {
    pub path: PathBuf,
    pub offset: u64,
    #[source]
    pub damage: Damage,
}

/// Counts of a read so far.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ReadStats {
    /// Messages yielded.
    pub messages: u64,
    pub by_family: BTreeMap<Family, u64>,
    /// Messages on channels this reader does not know, by topic: skipped.
    pub skipped_unknown: BTreeMap<String, u64>,
    /// Messages on known channels whose wrapper does not decode (inside a chunk whose CRC
    /// matched, so written that way): skipped.
    pub skipped_malformed: u64,
    pub chunks: u64,
    /// Footer and end magic read, every CRC matched.
    pub complete: bool,
}

#[derive(Debug, Clone)]
struct SchemaInfo {
    name: String,
    encoding: String,
}

enum State {
    Data,
    Summary,
    Finished,
}

/// Reads a recording from start to end (an iterator of messages).
pub struct RecordingReader {
    path: PathBuf,
    file: BufReader<std::fs::File>,
    len: u64,
    /// Offset of the next record.
    offset: u64,
    data_crc: crc32fast::Hasher,
    summary_crc: crc32fast::Hasher,
    state: State,
    schemas: HashMap<u16, SchemaInfo>,
    /// `Err(topic)`: a channel this reader skips (its topic, for the count).
    channels: HashMap<u16, Result<Family, String>>,
    pending: VecDeque<RecordedMessage>,
    /// Per channel, the (log time, offset) of every message in the chunk just read: the
    /// message index records that follow it must say exactly this.
    chunk_index: Option<MessagePlaces>,
    /// Records read in the data section (the first must be the header).
    data_records: u64,
    /// Written by `mwb-record` (the header's library): then every schema, channel and message
    /// is inside a chunk, and one outside is damage (a message index's opcode with one bit
    /// flipped reads as a message).
    ours: bool,
    stats: ReadStats,
    info: Option<RecordingInfo>,
    end: Option<BTreeMap<String, String>>,
}

impl RecordingReader {
    /// Opens `path` and checks its magic.
    pub fn open(path: &Path) -> Result<Self, ReadError> {
        let err = |offset, damage| ReadError {
            path: path.to_owned(),
            offset,
            damage,
        };
        let file = std::fs::File::open(path).map_err(|e| err(0, Damage::Io(e)))?;
        let len = file.metadata().map_err(|e| err(0, Damage::Io(e)))?.len();
        let mut r = Self {
            path: path.to_owned(),
            file: BufReader::with_capacity(1 << 20, file),
            len,
            offset: 0,
            data_crc: crc32fast::Hasher::new(),
            summary_crc: crc32fast::Hasher::new(),
            state: State::Data,
            schemas: HashMap::new(),
            channels: HashMap::new(),
            pending: VecDeque::new(),
            chunk_index: None,
            data_records: 0,
            ours: false,
            stats: ReadStats::default(),
            info: None,
            end: None,
        };
        let magic = r.read_exact_at(mcap::MAGIC.len() as u64)?;
        if magic != mcap::MAGIC {
            return Err(err(0, Damage::BadMagic));
        }
        r.data_crc.update(&magic);
        r.offset = magic.len() as u64;
        Ok(r)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn stats(&self) -> &ReadStats {
        &self.stats
    }

    /// The start metadata (space, version, start time), once read (it is the first record).
    pub fn info(&self) -> Option<&RecordingInfo> {
        self.info.as_ref()
    }

    /// The end metadata (counts, provenance, scene hashes, what the recorder could not write),
    /// once read: only a finished recording has it.
    pub fn end(&self) -> Option<&BTreeMap<String, String>> {
        self.end.as_ref()
    }

    fn error(&self, offset: u64, damage: Damage) -> ReadError {
        ReadError {
            path: self.path.clone(),
            offset,
            damage,
        }
    }

    /// Reads `n` bytes at the current offset (not advancing it), or a truncation error there.
    fn read_exact_at(&mut self, n: u64) -> Result<Vec<u8>, ReadError> {
        let available = self.len.saturating_sub(self.offset);
        if n > available {
            return Err(self.error(
                self.offset,
                Damage::Truncated {
                    needed: n,
                    available,
                },
            ));
        }
        let mut buf = vec![0u8; n as usize];
        self.file
            .read_exact(&mut buf)
            .map_err(|e| self.error(self.offset, Damage::Io(e)))?;
        Ok(buf)
    }

    /// Reads and handles the next top-level record.
    fn step(&mut self) -> Result<(), ReadError> {
        let at = self.offset;
        if at == self.len {
            return Err(self.error(at, Damage::NoFooter));
        }
        let head = self.read_exact_at(RECORD_HEADER)?;
        let opcode = head[0];
        let mut len_bytes = [0u8; 8];
        len_bytes.copy_from_slice(&head[1..9]);
        let body_len = u64::from_le_bytes(len_bytes);
        let available = self.len - at - RECORD_HEADER;
        if body_len > available {
            return Err(self.error(
                at,
                Damage::Truncated {
                    needed: RECORD_HEADER.saturating_add(body_len),
                    available: available + RECORD_HEADER,
                },
            ));
        }
        self.offset += RECORD_HEADER;
        let body = self.read_exact_at(body_len)?;
        self.offset += body_len;
        let parse_err = |source| Damage::BadRecord { opcode, source };
        match self.state {
            State::Data if opcode == op::DATA_END => {
                let computed = self.data_crc.clone().finalize();
                let rec =
                    mcap::parse_record(opcode, &body).map_err(|e| self.error(at, parse_err(e)))?;
                self.check_len(at, opcode, &rec, body.len())?;
                if let Record::DataEnd(end) = rec
                    && end.data_section_crc != 0
                    && end.data_section_crc != computed
                {
                    return Err(self.error(
                        at,
                        Damage::DataCrc {
                            saved: end.data_section_crc,
                            computed,
                        },
                    ));
                }
                self.state = State::Summary;
            }
            State::Data => {
                self.data_crc.update(&head);
                self.data_crc.update(&body);
                self.data_record(at, opcode, &body)?;
            }
            State::Summary if opcode == op::FOOTER => {
                let rec =
                    mcap::parse_record(opcode, &body).map_err(|e| self.error(at, parse_err(e)))?;
                self.check_len(at, opcode, &rec, body.len())?;
                self.summary_crc.update(&head);
                self.summary_crc.update(&body[..body.len().min(16)]);
                let computed = self.summary_crc.clone().finalize();
                if let Record::Footer(f) = rec
                    && f.summary_crc != 0
                    && f.summary_crc != computed
                {
                    return Err(self.error(
                        at,
                        Damage::SummaryCrc {
                            saved: f.summary_crc,
                            computed,
                        },
                    ));
                }
                let magic_at = self.offset;
                let magic = self.read_exact_at(mcap::MAGIC.len() as u64)?;
                if magic != mcap::MAGIC {
                    return Err(self.error(magic_at, Damage::BadMagic));
                }
                self.offset += magic.len() as u64;
                self.state = State::Finished;
                self.stats.complete = true;
            }
            State::Summary => {
                // Summary records repeat what the data section held (schemas, channels) or
                // index it; reading in order needs none of them, but their CRC is checked, and
                // their lengths as in the data section, so that damage is named where it is.
                self.summary_crc.update(&head);
                self.summary_crc.update(&body);
                let rec =
                    mcap::parse_record(opcode, &body).map_err(|e| self.error(at, parse_err(e)))?;
                let allowed = matches!(
                    rec,
                    Record::Schema { .. }
                        | Record::Channel(_)
                        | Record::ChunkIndex(_)
                        | Record::AttachmentIndex(_)
                        | Record::MetadataIndex(_)
                        | Record::Statistics(_)
                        | Record::SummaryOffset(_)
                );
                if !allowed {
                    return Err(self.error(at, Damage::Unexpected { opcode }));
                }
                self.check_len(at, opcode, &rec, body.len())?;
            }
            State::Finished => {}
        }
        Ok(())
    }

    /// One record of the data section. Every record our writer puts there has a length its
    /// contents determine, and each is checked against it: a flipped length or opcode is found
    /// at the record it hits, instead of shifting every later record boundary (which could
    /// skip a whole chunk and find the damage only at the data section's CRC, after later
    /// messages had been handed out with a hole before them).
    fn data_record(&mut self, at: u64, opcode: u8, body: &[u8]) -> Result<(), ReadError> {
        let first = self.data_records == 0;
        self.data_records += 1;
        let rec = mcap::parse_record(opcode, body)
            .map_err(|source| self.error(at, Damage::BadRecord { opcode, source }))?;
        if first != matches!(rec, Record::Header(_)) {
            return Err(self.error(at, Damage::Unexpected { opcode }));
        }
        self.check_len(at, opcode, &rec, body.len())?;
        let chunk_index = self.chunk_index.take();
        match rec {
            Record::Header(h) => self.ours = h.library.starts_with(crate::writer::LIBRARY),
            Record::Chunk { header, data } => {
                let contents = self.decompress(at, &header, &data)?;
                let mut out = VecDeque::new();
                let index =
                    self.chunk_records(&contents, &mut out)
                        .map_err(|(inner, detail)| {
                            self.error(at, Damage::ChunkContents { at: inner, detail })
                        })?;
                let bounds = index
                    .values()
                    .flatten()
                    .fold(None, |b: Option<(u64, u64)>, &(t, _)| {
                        Some(b.map_or((t, t), |(lo, hi)| (lo.min(t), hi.max(t))))
                    })
                    .unwrap_or((0, 0));
                for (field, saved, computed) in [
                    ("message_start_time", header.message_start_time, bounds.0),
                    ("message_end_time", header.message_end_time, bounds.1),
                ] {
                    if saved != computed {
                        return Err(self.error(
                            at,
                            Damage::ChunkHeader {
                                field,
                                saved,
                                computed,
                            },
                        ));
                    }
                }
                self.stats.chunks += 1;
                self.pending.append(&mut out);
                self.chunk_index = Some(index);
            }
            Record::MessageIndex(mi) => {
                // Only right after a chunk, once per channel, saying what the chunk holds.
                let mut index =
                    chunk_index.ok_or_else(|| self.error(at, Damage::Unexpected { opcode }))?;
                let mut saved: Vec<(u64, u64)> =
                    mi.records.iter().map(|e| (e.log_time, e.offset)).collect();
                saved.sort_unstable();
                if index.remove(&mi.channel_id) != Some(saved) {
                    return Err(self.error(
                        at,
                        Damage::MessageIndex {
                            channel: mi.channel_id,
                        },
                    ));
                }
                self.chunk_index = Some(index);
            }
            Record::Metadata(m) if m.name == INFO_METADATA => {
                self.info = Some(RecordingInfo::from_metadata(&m.metadata));
            }
            Record::Metadata(m) if m.name == END_METADATA => self.end = Some(m.metadata),
            Record::Metadata(_) | Record::Attachment { .. } => {}
            // Valid MCAP from other writers; never outside a chunk in our files.
            rec @ (Record::Schema { .. } | Record::Channel(_) | Record::Message { .. })
                if !self.ours =>
            {
                let mut out = VecDeque::new();
                self.record(rec, &mut out);
                self.pending.append(&mut out);
            }
            // Summary records, a footer, or an opcode nobody defined: not in a data section.
            _ => return Err(self.error(at, Damage::Unexpected { opcode })),
        }
        Ok(())
    }

    fn check_len(
        &self,
        at: u64,
        opcode: u8,
        rec: &Record<'_>,
        len: usize,
    ) -> Result<(), ReadError> {
        match sized_len(rec) {
            Some(expected) if expected != len as u64 => Err(self.error(
                at,
                Damage::Length {
                    opcode,
                    len: len as u64,
                    expected,
                },
            )),
            _ => Ok(()),
        }
    }

    fn decompress(
        &self,
        at: u64,
        header: &mcap::records::ChunkHeader,
        data: &[u8],
    ) -> Result<Vec<u8>, ReadError> {
        let expected = header.uncompressed_size;
        if expected > MAX_CHUNK_UNCOMPRESSED {
            return Err(self.error(at, Damage::ChunkSize { expected, got: 0 }));
        }
        let contents = match header.compression.as_str() {
            "" => data.to_vec(),
            "zstd" => {
                let decoder = zstd::stream::read::Decoder::with_buffer(data).map_err(|source| {
                    self.error(
                        at,
                        Damage::Decompress {
                            compression: "zstd".into(),
                            source,
                        },
                    )
                })?;
                let mut out = Vec::with_capacity(expected as usize);
                // One byte more than promised, to tell "longer than the header says".
                decoder
                    .take(expected + 1)
                    .read_to_end(&mut out)
                    .map_err(|source| {
                        self.error(
                            at,
                            Damage::Decompress {
                                compression: "zstd".into(),
                                source,
                            },
                        )
                    })?;
                out
            }
            other => return Err(self.error(at, Damage::Compression(other.to_owned()))),
        };
        if contents.len() as u64 != expected {
            return Err(self.error(
                at,
                Damage::ChunkSize {
                    expected,
                    got: contents.len() as u64,
                },
            ));
        }
        if header.uncompressed_crc != 0 {
            let computed = crc32fast::hash(&contents);
            if computed != header.uncompressed_crc {
                return Err(self.error(
                    at,
                    Damage::ChunkCrc {
                        saved: header.uncompressed_crc,
                        computed,
                    },
                ));
            }
        }
        Ok(contents)
    }

    /// The records inside a chunk's (verified) contents, and per channel the (log time,
    /// offset) of its messages; `Err((offset, what))` if they do not parse.
    fn chunk_records(
        &mut self,
        contents: &[u8],
        out: &mut VecDeque<RecordedMessage>,
    ) -> Result<MessagePlaces, (u64, String)> {
        let mut index: MessagePlaces = HashMap::new();
        let mut pos = 0usize;
        while pos < contents.len() {
            let rest = &contents[pos..];
            if rest.len() < RECORD_HEADER as usize {
                return Err((pos as u64, "record header cut short".into()));
            }
            let opcode = rest[0];
            let mut len_bytes = [0u8; 8];
            len_bytes.copy_from_slice(&rest[1..9]);
            let len = u64::from_le_bytes(len_bytes);
            let body_end = usize::try_from(len)
                .ok()
                .and_then(|l| l.checked_add(RECORD_HEADER as usize))
                .filter(|&e| e <= rest.len())
                .ok_or_else(|| {
                    (
                        pos as u64,
                        format!("record of {len} bytes overruns the chunk"),
                    )
                })?;
            let rec = mcap::parse_record(opcode, &rest[RECORD_HEADER as usize..body_end])
                .map_err(|e| (pos as u64, format!("opcode {opcode:#04x}: {e}")))?;
            if let Record::Message { header, .. } = &rec {
                index
                    .entry(header.channel_id)
                    .or_default()
                    .push((header.log_time, pos as u64));
            }
            self.record(rec, out);
            pos += body_end;
        }
        for entries in index.values_mut() {
            entries.sort_unstable();
        }
        Ok(index)
    }

    /// Schemas, channels and messages (in a chunk or not).
    fn record(&mut self, rec: Record<'_>, out: &mut VecDeque<RecordedMessage>) {
        match rec {
            Record::Schema { header, .. } => {
                self.schemas.insert(
                    header.id,
                    SchemaInfo {
                        name: header.name,
                        encoding: header.encoding,
                    },
                );
            }
            Record::Channel(c) => {
                let known = Family::from_topic(&c.topic).filter(|f| {
                    c.message_encoding == f.message_encoding()
                        && self.schemas.get(&c.schema_id).is_some_and(|s| {
                            s.name == f.schema_name() && s.encoding == f.schema_encoding()
                        })
                });
                self.channels.insert(c.id, known.ok_or(c.topic));
            }
            Record::Message { header, data } => match self.channels.get(&header.channel_id) {
                Some(Ok(family)) => match decode_record(*family, &data) {
                    Ok((key, payload)) => {
                        self.stats.messages += 1;
                        *self.stats.by_family.entry(*family).or_default() += 1;
                        out.push_back(RecordedMessage {
                            family: *family,
                            key,
                            payload,
                            log_time_ns: header.log_time,
                            publish_time_ns: header.publish_time,
                            sequence: header.sequence,
                        });
                    }
                    Err(_) => self.stats.skipped_malformed += 1,
                },
                Some(Err(topic)) => {
                    *self.stats.skipped_unknown.entry(topic.clone()).or_default() += 1;
                }
                None => {
                    *self
                        .stats
                        .skipped_unknown
                        .entry(format!("<channel {}>", header.channel_id))
                        .or_default() += 1;
                }
            },
            _ => {}
        }
    }
}

/// The body length a record's contents determine, for the records whose length does not
/// simply run to the end of the body (a message's data does).
fn sized_len(rec: &Record<'_>) -> Option<u64> {
    let s = |x: &str| 4 + x.len() as u64;
    let map = |m: &BTreeMap<String, String>| 4 + m.iter().map(|(k, v)| s(k) + s(v)).sum::<u64>();
    Some(match rec {
        Record::Header(h) => s(&h.profile) + s(&h.library),
        Record::Metadata(m) => s(&m.name) + map(&m.metadata),
        Record::MessageIndex(mi) => 2 + 4 + 16 * mi.records.len() as u64,
        Record::Chunk { header, .. } => {
            8 + 8 + 8 + 4 + s(&header.compression) + 8 + header.compressed_size
        }
        Record::Schema { header, data } => {
            2 + s(&header.name) + s(&header.encoding) + 4 + data.len() as u64
        }
        Record::Channel(c) => 2 + 2 + s(&c.topic) + s(&c.message_encoding) + map(&c.metadata),
        Record::Attachment { header, data, .. } => {
            8 + 8 + s(&header.name) + s(&header.media_type) + 8 + data.len() as u64 + 4
        }
        Record::ChunkIndex(c) => {
            8 * 4 + 4 + 10 * c.message_index_offsets.len() as u64 + 8 + s(&c.compression) + 8 + 8
        }
        Record::AttachmentIndex(a) => 8 * 5 + s(&a.name) + s(&a.media_type),
        Record::Statistics(st) => {
            8 + 2 + 4 * 4 + 8 + 8 + 4 + 10 * st.channel_message_counts.len() as u64
        }
        Record::MetadataIndex(m) => 8 + 8 + s(&m.name),
        Record::SummaryOffset(_) => 1 + 8 + 8,
        Record::Footer(_) => 8 + 8 + 4,
        Record::DataEnd(_) => 4,
        _ => return None,
    })
}

impl Iterator for RecordingReader {
    type Item = Result<RecordedMessage, ReadError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            if let Some(m) = self.pending.pop_front() {
                return Some(Ok(m));
            }
            if matches!(self.state, State::Finished) {
                return None;
            }
            if let Err(e) = self.step() {
                // One error, then the end: nothing past damage is trusted.
                self.state = State::Finished;
                return Some(Err(e));
            }
        }
    }
}

/// A whole recording read into memory: every message before any damage, and the damage.
#[derive(Debug)]
pub struct Recovered {
    pub messages: Vec<RecordedMessage>,
    pub info: Option<RecordingInfo>,
    pub end: Option<BTreeMap<String, String>>,
    pub stats: ReadStats,
    /// Where and why reading stopped early; `None` for an intact file.
    pub error: Option<ReadError>,
}

/// Reads `path` to the end or to the first damage. `Err` only if the file cannot be opened or
/// is not an MCAP file at all.
pub fn read_recording(path: &Path) -> Result<Recovered, ReadError> {
    let mut r = RecordingReader::open(path)?;
    let mut messages = Vec::new();
    let mut error = None;
    for m in r.by_ref() {
        match m {
            Ok(m) => messages.push(m),
            Err(e) => error = Some(e),
        }
    }
    Ok(Recovered {
        messages,
        info: r.info.take(),
        end: r.end.take(),
        stats: r.stats.clone(),
        error,
    })
}

impl RecordingInfo {
    pub(crate) fn from_metadata(m: &BTreeMap<String, String>) -> Self {
        let get = |k: &str| m.get(k).cloned().unwrap_or_default();
        let own = [
            "format",
            "mwb_version",
            "space",
            "start_unix_ns",
            "recorder",
        ];
        Self {
            mwb_version: get("mwb_version"),
            space: get("space"),
            start_unix_ns: m
                .get("start_unix_ns")
                .and_then(|s| s.parse().ok())
                .unwrap_or(0),
            recorder: get("recorder"),
            extra: m
                .iter()
                .filter(|(k, _)| !own.contains(&k.as_str()))
                .map(|(k, v)| (k.clone(), v.clone()))
                .collect(),
        }
    }
}
