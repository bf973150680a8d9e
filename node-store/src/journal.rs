//! The store's journal, and loading recordings into a store.
//!
//! A journal is a directory of MCAP files written by `mwb-record`'s writer
//! (`journal-000001.mcap`, `journal-000002.mcap`, …), so every journal file is also a
//! recording: `mwb replay` and `mwb store --load` read it, and a damaged one is read up to the
//! damage by the same reader (which names the byte offset and hands out nothing past it).
//!
//! What is written, in the order the store applied it: every job announcement that changed
//! the table, every stored world (its segments, then its `WorldDone`, under their bus keys),
//! and every job state the store is about to publish. A world is written only once it is
//! complete and verified, so reading a journal back stores the same worlds under the same
//! indices (in order); rejected and partial worlds never reach the disk. A world's `WorldDone`
//! carries the index the store browses it by (`WorldDone.index`: the one its sampler sent, or
//! the store's own where it built one), so a restart takes it as a sent index — its form
//! checked, one in [`crate::StoreConfig::verify_index_every`] rebuilt and compared — instead of
//! decoding and indexing every world again. The store holds the summary without it, as it
//! holds every summary.
//!
//! **Acknowledged, and when it is durable.** A world is *acknowledged* when a job state that
//! counts it is published (`job/<id>/state`: samplers stop at it, `mwb job submit --wait`
//! follows it). The store applies its ingest in batches (group commit: whatever is queued, up
//! to [`MAX_BATCH`] messages), appends the batch's records, ends the MCAP chunk, and calls
//! `fdatasync` on the file — and only then publishes the batch's job states. A store killed
//! at any moment therefore finds, on restart, every world it had acknowledged. With several
//! shards, each publishes its own count of a job's worlds (`ShardCount`) only after the commit
//! that made them durable, and the authority's job state counts the sum of those counts and its
//! own: a world is acknowledged only once the shard that keeps it has synced it (see
//! [`crate::assembly`]). The job states in the journal carry every shard's count as the store
//! had it (`shard_worlds`), so a restarted authority starts from what the others had told it,
//! and learns the rest as they send their counts again. Queries read
//! the live table, so a world can be fetched (or counted in a queried job state) up to one
//! group commit before it is durable; a crash inside that window loses only worlds nobody was
//! told were kept. New files are created beside the old ones, and the directory is synced
//! after each creation.
//!
//! **Rotation and restart.** A file grows to [`DEFAULT_ROTATE_BYTES`] and is then finished
//! (summary and footer) and a new one started; a restart always starts a new file and never
//! appends to one a crash may have cut. Every new file begins with a checkpoint — every job
//! and its state — so a file is readable without the ones before it.
//!
//! A store that is stopped finishes its file as the writer is dropped (summary, footer); a
//! killed one leaves it cut after its last commit.
//!
//! **Damage.** On start every file is read in order. A file cut short (the normal end of a
//! killed store's last file) or damaged (a CRC mismatch, garbage) gives what precedes the
//! damage; the rest of that file is skipped, the next file is read, and the [`FileReport`]
//! says where and how much was skipped. A damaged journal never stops the store from starting.

use crate::assembly::Assembler;
use mwb_core::keys::Keys;
use mwb_proto::v1::{Job, JobState, Message, MotionSegment, Scene, WorldDone, WorldIndex};
use mwb_record::reader::Damage;
use mwb_record::{
    BusMessage, Family, RecordingInfo, RecordingReader, RecordingWriter, WriteError, WriterOptions,
    unix_ns,
};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

/// A journal file is finished and a new one started past this size.
pub const DEFAULT_ROTATE_BYTES: u64 = 256 << 20;
/// At most this many ingest messages are applied between two commits.
pub const MAX_BATCH: usize = 1024;
/// Name of journal file `n`.
pub fn file_name(n: u64) -> String {
    format!("journal-{n:06}.mcap")
}

fn file_number(name: &str) -> Option<u64> {
    name.strip_prefix("journal-")?
        .strip_suffix(".mcap")?
        .parse()
        .ok()
}

/// A message the store applies (the families a store takes from a recording).
#[derive(Debug, Clone, PartialEq)]
pub enum StoreInput {
    Job(Job),
    State(JobState),
    Segment(MotionSegment),
    Done(WorldDone),
    /// A scene revision put on `scene/<rev>` (the store keeps every revision).
    Scene(Scene),
}

/// What one file gave back.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct FileReport {
    pub path: PathBuf,
    /// File length, bytes.
    pub bytes: u64,
    /// Messages read intact.
    pub messages: u64,
    /// Jobs, job states, segments and world summaries handed to the store.
    pub applied: u64,
    /// Job states not applied (a recording's states are another store's; a store makes its
    /// own from the worlds).
    pub states_ignored: u64,
    /// Intact messages of families a store does not take (stats, browse, …), by topic.
    pub other_families: BTreeMap<String, u64>,
    /// Messages on channels the reader does not know, by topic: skipped.
    pub unknown_channels: BTreeMap<String, u64>,
    /// Messages whose record did not decode: skipped.
    pub malformed: u64,
    /// Where reading stopped early: the reader's error (file, byte offset, what).
    pub damage: Option<String>,
    pub damage_offset: Option<u64>,
    /// The damage is only an unfinished end (cut short, no footer): what a killed writer
    /// leaves, not corruption.
    pub cut_short: bool,
    /// Bytes from the damage to the end of the file: not read.
    pub skipped_bytes: u64,
    /// Footer read and every CRC matched.
    pub complete: bool,
}

impl FileReport {
    /// One line for a log.
    pub fn describe(&self) -> String {
        let mut s = format!(
            "{}: {} messages intact, {} applied",
            self.path.display(),
            self.messages,
            self.applied
        );
        let unknown: u64 = self.unknown_channels.values().sum();
        if unknown > 0 {
            s += &format!(", {unknown} on unknown channels skipped");
        }
        if self.malformed > 0 {
            s += &format!(", {} malformed skipped", self.malformed);
        }
        if let Some(d) = &self.damage {
            s += &format!("; stopped at {d} ({} bytes not read)", self.skipped_bytes);
        }
        s
    }
}

/// Reads `path` in order and hands each store message to `sink`; never fails: a file that
/// cannot be opened or is damaged gives what it can, and the report says what was skipped.
/// `states`: whether job states are store input (a journal's are; a recording's are not).
pub fn read_store_input(path: &Path, states: bool, mut sink: impl FnMut(StoreInput)) -> FileReport {
    let bytes = std::fs::metadata(path).map_or(0, |m| m.len());
    let mut r = FileReport {
        path: path.to_owned(),
        bytes,
        ..Default::default()
    };
    let stop = |r: &mut FileReport, e: mwb_record::ReadError| {
        r.cut_short = matches!(e.damage, Damage::Truncated { .. } | Damage::NoFooter);
        r.damage_offset = Some(e.offset);
        r.skipped_bytes = bytes.saturating_sub(e.offset);
        r.damage = Some(e.to_string());
    };
    let mut reader = match RecordingReader::open(path) {
        Ok(reader) => reader,
        Err(e) => {
            stop(&mut r, e);
            return r;
        }
    };
    for m in reader.by_ref() {
        let m = match m {
            Ok(m) => m,
            Err(e) => {
                stop(&mut r, e);
                break;
            }
        };
        r.messages += 1;
        let p = m.payload.as_slice();
        let input = match m.family {
            Family::Job => Job::decode(p).ok().map(StoreInput::Job),
            Family::Segment => MotionSegment::decode(p).ok().map(StoreInput::Segment),
            Family::Done => WorldDone::decode(p).ok().map(StoreInput::Done),
            Family::Scene => Scene::decode(p).ok().map(StoreInput::Scene),
            Family::JobState if states => JobState::decode(p).ok().map(StoreInput::State),
            Family::JobState => {
                r.states_ignored += 1;
                continue;
            }
            other => {
                *r.other_families.entry(other.topic().into()).or_default() += 1;
                continue;
            }
        };
        match input {
            Some(input) => {
                r.applied += 1;
                sink(input);
            }
            // The writer files a payload under its family only if it decodes as that type.
            None => r.malformed += 1,
        }
    }
    let st = reader.stats();
    r.unknown_channels = st.skipped_unknown.clone();
    r.malformed += st.skipped_malformed;
    r.complete = st.complete;
    r
}

/// Why the journal cannot be written.
#[derive(Debug, thiserror::Error)]
pub enum JournalError {
    #[error("journal {}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("journal {}", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: WriteError,
    },
}

/// A file whose `flush` also reaches the disk: the MCAP writer flushes when a chunk ends
/// (`RecordingWriter::flush`) and when the file is finished, and those are exactly the
/// moments the journal needs on disk.
struct SyncedFile(BufWriter<File>);

impl Write for SyncedFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.write(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.0.flush()?;
        self.0.get_ref().sync_data()
    }
}

impl Seek for SyncedFile {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        self.0.seek(pos)
    }
}

/// Counts of a journal's writing.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct JournalCounters {
    pub messages: u64,
    pub payload_bytes: u64,
    pub commits: u64,
    pub files_started: u64,
    /// Commits that failed (logged): their worlds were published without being durable.
    pub failures: u64,
}

/// The journal being written.
pub struct Journal {
    dir: PathBuf,
    space: String,
    next_number: u64,
    current: Option<(PathBuf, RecordingWriter<SyncedFile>)>,
    rotate_bytes: u64,
    pending: Vec<BusMessage>,
    pub counters: JournalCounters,
}

impl std::fmt::Debug for Journal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Journal")
            .field("dir", &self.dir)
            .field("file", &self.current.as_ref().map(|(p, _)| p))
            .field("counters", &self.counters)
            .finish_non_exhaustive()
    }
}

impl Journal {
    /// Opens (creating) `dir`; returns the journal, not yet writing, and the files already
    /// there in the order they were written.
    pub fn open(dir: &Path, space: &str) -> Result<(Self, Vec<PathBuf>), JournalError> {
        let io = |source| JournalError::Io {
            path: dir.to_owned(),
            source,
        };
        std::fs::create_dir_all(dir).map_err(io)?;
        let mut files: Vec<(u64, PathBuf)> = Vec::new();
        for entry in std::fs::read_dir(dir).map_err(io)? {
            let entry = entry.map_err(io)?;
            if let Some(n) = entry.file_name().to_str().and_then(file_number) {
                files.push((n, entry.path()));
            }
        }
        files.sort();
        let next_number = files.last().map_or(1, |(n, _)| n + 1);
        let j = Self {
            dir: dir.to_owned(),
            space: space.to_owned(),
            next_number,
            current: None,
            rotate_bytes: DEFAULT_ROTATE_BYTES,
            pending: Vec::new(),
            counters: JournalCounters::default(),
        };
        Ok((j, files.into_iter().map(|(_, p)| p).collect()))
    }

    /// Files past this size are finished and a new one started (default
    /// [`DEFAULT_ROTATE_BYTES`]).
    pub fn set_rotate_bytes(&mut self, bytes: u64) {
        self.rotate_bytes = bytes.max(1);
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The file being written.
    pub fn current_file(&self) -> Option<&Path> {
        self.current.as_ref().map(|(p, _)| p.as_path())
    }

    /// Queues a message for the next [`commit`](Self::commit).
    pub fn append(&mut self, key: String, payload: Vec<u8>) {
        self.pending.push(BusMessage {
            key,
            payload,
            log_time_ns: unix_ns(),
            publish_time_ns: None,
        });
    }

    /// Messages queued and not yet committed.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }

    /// Queues a stored world: its segments, then its summary carrying `index`, the paths and
    /// metrics the store browses it by (nothing if the world's own encoding does not decode,
    /// which only a bug can cause).
    pub fn append_world(
        &mut self,
        keys: &Keys,
        w: &crate::StoredWorld,
        index: Option<WorldIndex>,
    ) -> Result<(), crate::assembly::StoredDecodeError> {
        let (mut d, segments) = w.decode()?;
        d.index = index;
        for s in &segments {
            let key = keys.segment(&s.job_id, &s.node_id, s.world_counter, s.seq);
            self.append(key, s.encode_to_vec());
        }
        let key = keys.done(&d.job_id, &d.node_id, d.world_counter);
        self.append(key, d.encode_to_vec());
        Ok(())
    }

    /// Writes what is queued, ends the chunk and syncs the file; then, if the file has grown
    /// past the rotation size, finishes it and starts the next with `checkpoint()` (every
    /// job and its state). Without a current file, one is started first.
    pub fn commit(
        &mut self,
        checkpoint: impl FnOnce() -> Vec<(String, Vec<u8>)>,
    ) -> Result<(), JournalError> {
        let mut checkpoint = Some(checkpoint);
        if self.current.is_none() {
            let cp = checkpoint.take().map(|f| f()).unwrap_or_default();
            self.start_file(cp)?;
        }
        let pending = std::mem::take(&mut self.pending);
        let Some((path, w)) = self.current.as_mut() else {
            return Ok(());
        };
        let path = path.clone();
        let werr = |source| JournalError::Write {
            path: path.clone(),
            source,
        };
        for m in &pending {
            w.write(m).map_err(werr)?;
            self.counters.messages += 1;
            self.counters.payload_bytes += m.payload.len() as u64;
        }
        w.flush().map_err(werr)?;
        self.counters.commits += 1;
        let size = std::fs::metadata(&path).map_or(0, |m| m.len());
        if size >= self.rotate_bytes
            && let Some(cp) = checkpoint.take()
        {
            self.finish()?;
            self.start_file(cp())?;
        }
        Ok(())
    }

    /// Leaves the current file as it is (after a failed write); the next commit starts a new
    /// one.
    pub fn abandon_file(&mut self) {
        self.current = None;
        self.pending.clear();
    }

    /// Finishes the current file (summary, footer, synced).
    pub fn finish(&mut self) -> Result<(), JournalError> {
        if let Some((path, w)) = self.current.take() {
            w.finish(BTreeMap::new())
                .map_err(|source| JournalError::Write { path, source })?;
        }
        Ok(())
    }

    fn start_file(&mut self, checkpoint: Vec<(String, Vec<u8>)>) -> Result<(), JournalError> {
        let path = self.dir.join(file_name(self.next_number));
        self.next_number += 1;
        let io = |path: &Path| {
            let path = path.to_owned();
            move |source| JournalError::Io { path, source }
        };
        let file = File::create(&path).map_err(io(&path))?;
        // The new file's name must survive a crash too.
        File::open(&self.dir)
            .and_then(|d| d.sync_all())
            .map_err(io(&self.dir))?;
        let info = RecordingInfo {
            space: self.space.clone(),
            ..RecordingInfo::now("store-journal")
        };
        let opts = WriterOptions {
            // Chunks end at every commit; this only bounds one commit's chunk.
            chunk_size: 4 << 20,
            ..WriterOptions::default()
        };
        let mut w = RecordingWriter::new(
            SyncedFile(BufWriter::with_capacity(1 << 20, file)),
            &info,
            &opts,
        )
        .map_err(|source| JournalError::Write {
            path: path.clone(),
            source,
        })?;
        for (key, payload) in checkpoint {
            let m = BusMessage {
                key,
                payload,
                log_time_ns: unix_ns(),
                publish_time_ns: None,
            };
            w.write(&m).map_err(|source| JournalError::Write {
                path: path.clone(),
                source,
            })?;
        }
        w.flush().map_err(|source| JournalError::Write {
            path: path.clone(),
            source,
        })?;
        self.counters.files_started += 1;
        self.current = Some((path, w));
        Ok(())
    }
}

/// Every job and its state, as journal records (the start of every journal file).
pub fn checkpoint(table: &Assembler, keys: &Keys) -> Vec<(String, Vec<u8>)> {
    let mut v = Vec::new();
    for (job, state) in table.jobs() {
        v.push((keys.job(&job.id), job.encode_to_vec()));
        v.push((keys.job_state(&job.id), state.encode_to_vec()));
    }
    v
}

/// What the store read at start: its journal files and the recordings it was asked to load.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct StartReport {
    pub journal: Vec<FileReport>,
    pub recordings: Vec<FileReport>,
    /// Worlds stored from the journal and from the recordings.
    pub worlds_from_journal: u64,
    pub worlds_from_recordings: u64,
    /// Worlds read whole but refused (duplicate seed, memory cap, job closed, …).
    pub worlds_refused: u64,
    /// Worlds still partial (or held for a job never read) when all was read: discarded.
    pub partial_discarded: u64,
    /// Seconds spent reading and indexing.
    pub seconds: f64,
}

impl StartReport {
    /// Files whose reading stopped at damage other than an unfinished end.
    pub fn damaged_files(&self) -> usize {
        self.journal
            .iter()
            .chain(&self.recordings)
            .filter(|f| f.damage.is_some() && !f.cut_short)
            .count()
    }
    /// Bytes not read because of damage, over all files.
    pub fn skipped_bytes(&self) -> u64 {
        self.journal
            .iter()
            .chain(&self.recordings)
            .map(|f| f.skipped_bytes)
            .sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_names_sort_by_number() {
        assert_eq!(file_name(7), "journal-000007.mcap");
        assert_eq!(file_number("journal-000007.mcap"), Some(7));
        assert_eq!(file_number("journal-1234567.mcap"), Some(1_234_567));
        for bad in ["journal-.mcap", "journal-1.txt", "x-000001.mcap"] {
            assert_eq!(file_number(bad), None, "{bad}");
        }
    }
}
