//! Recordings as files: written, read back by this crate and by the `mcap` crate (with its CRC
//! checks), decoded from the embedded schemas alone, and damaged — truncated at many offsets and
//! bit-flipped everywhere — to check that the reader keeps exactly what precedes the damage and
//! names the offset.

use mwb_proto::v1::{Job, JobState, Message, MotionSegment, NodeStats, Scene, WorldDone};
use mwb_record::{
    BusMessage, Damage, Family, RecordingInfo, RecordingWriter, WriterOptions, read_recording,
};
use prost_reflect::{DescriptorPool, DynamicMessage, Value};
use std::collections::BTreeMap;
use std::path::Path;

/// A small session: a job, its states, two worlds of three segments, summaries, stats, a
/// browse put and one put that does not decode as its family's type.
fn session() -> Vec<BusMessage> {
    let mut out = Vec::new();
    let mut t = 1_700_000_000_000_000_000u64;
    let mut push = |key: String, payload: Vec<u8>, publish: Option<u64>| {
        t += 7_000_000;
        out.push(BusMessage {
            key,
            payload,
            log_time_ns: t,
            publish_time_ns: publish,
        });
    };
    let job = Job {
        id: "j1".into(),
        revision: 1,
        scene: Some(Scene {
            name: "tumble".into(),
            toml: "[settings]\nend_time = 3.0\n".into(),
            content_hash: 0xfeed_beef,
            ..Default::default()
        }),
        target_worlds: 2,
        created_unix_ms: 1_600_000_000_000,
        ..Default::default()
    };
    push("mwb/demo/job/j1".into(), job.encode_to_vec(), None);
    for w in 0..2u64 {
        for seq in 0..3u32 {
            // Incompressible-ish payloads, so the small test chunks fill up.
            let payload: Vec<u8> = (0..1500u32)
                .map(|i| {
                    (i.wrapping_mul(2_654_435_761) ^ (seq * 77 + w as u32 * 13)).to_le_bytes()[1]
                })
                .collect();
            let seg = MotionSegment {
                job_id: "j1".into(),
                node_id: "n1".into(),
                world_counter: w,
                seed: 100 + w,
                seq,
                crc32: crc32fast::hash(&payload),
                payload,
                ..Default::default()
            };
            push(
                format!("mwb/demo/seg/j1/n1/{w}/{seq}"),
                seg.encode_to_vec(),
                Some(1_650_000_000_000_000_000 + u64::from(seq)),
            );
        }
        let done = WorldDone {
            job_id: "j1".into(),
            node_id: "n1".into(),
            world_counter: w,
            seed: 100 + w,
            segment_count: 3,
            provenance: "mwb 0.1.0 / rapier3d 0.36.1 enhanced-determinism".into(),
            scene_hash: 0xfeed_beef,
            ..Default::default()
        };
        push(
            format!("mwb/demo/done/j1/n1/{w}"),
            done.encode_to_vec(),
            None,
        );
        let st = JobState {
            job_id: "j1".into(),
            revision: w + 2,
            worlds_done: w as u32 + 1,
            target_worlds: 2,
            closed: w == 1,
            ..Default::default()
        };
        push("mwb/demo/job/j1/state".into(), st.encode_to_vec(), None);
        let stats = NodeStats {
            node_id: "n1".into(),
            role: "sampler".into(),
            revision: w,
            worlds: w,
            ..Default::default()
        };
        push(
            "mwb/demo/stats/sampler/n1".into(),
            stats.encode_to_vec(),
            None,
        );
    }
    push(
        "mwb/demo/browse/s1".into(),
        br#"{"op":"list","k": 3}"#.to_vec(),
        None,
    );
    // A truncated varint: not a JobState.
    push("mwb/demo/job/j2/state".into(), vec![0x18, 0xff], None);
    out
}

fn info() -> RecordingInfo {
    let mut info = RecordingInfo::now("test-recorder");
    info.space = "demo".into();
    info.extra
        .insert("recorder_build".into(), "mwb test / physics test".into());
    info
}

/// Writes `msgs` with small chunks (several per file).
fn write(path: &Path, msgs: &[BusMessage], chunk_size: u64) {
    let opts = WriterOptions {
        chunk_size,
        ..Default::default()
    };
    let mut w = RecordingWriter::create(path, &info(), &opts).unwrap();
    for m in msgs {
        w.write(m).unwrap();
    }
    let mut end = BTreeMap::new();
    end.insert("not_written".into(), "0".into());
    let stats = w.finish(end).unwrap();
    assert_eq!(stats.messages, msgs.len() as u64);
}

fn expected_family(m: &BusMessage) -> Family {
    match m.key.as_str() {
        k if k.ends_with("j2/state") => Family::Raw,
        k if k.contains("/seg/") => Family::Segment,
        k if k.contains("/done/") => Family::Done,
        k if k.contains("/stats/") => Family::Stats,
        k if k.contains("/browse/") => Family::Browse,
        k if k.ends_with("/state") => Family::JobState,
        _ => Family::Job,
    }
}

#[test]
fn written_then_read_back_by_us_and_by_the_mcap_crate() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("s.mcap");
    let msgs = session();
    write(&path, &msgs, 4096);

    // Our reader.
    let back = read_recording(&path).unwrap();
    assert!(back.error.is_none(), "{:?}", back.error);
    assert!(back.stats.complete);
    assert_eq!(back.messages.len(), msgs.len());
    for (m, r) in msgs.iter().zip(&back.messages) {
        assert_eq!(r.key, m.key);
        assert_eq!(r.payload, m.payload);
        assert_eq!(r.family, expected_family(m), "{}", m.key);
        assert_eq!(r.log_time_ns, m.log_time_ns);
    }
    // publish_time: the sample's timestamp, a job's creation time, else the receive time.
    assert_eq!(back.messages[0].publish_time_ns, 1_600_000_000_000_000_000);
    assert_eq!(
        back.messages[1].publish_time_ns,
        msgs[1].publish_time_ns.unwrap()
    );
    assert_eq!(back.messages[4].publish_time_ns, msgs[4].log_time_ns);
    let info = back.info.unwrap();
    assert_eq!(info.space, "demo");
    assert_eq!(info.recorder, "test-recorder");
    assert_eq!(info.mwb_version, env!("CARGO_PKG_VERSION"));
    assert_eq!(info.extra["recorder_build"], "mwb test / physics test");
    let end = back.end.unwrap();
    assert_eq!(end["messages"], msgs.len().to_string());
    assert_eq!(end["messages.seg"], "6");
    assert_eq!(end["messages.raw"], "1");
    assert_eq!(end["not_written"], "0");
    assert_eq!(
        end["provenance"],
        "mwb 0.1.0 / rapier3d 0.36.1 enhanced-determinism"
    );
    assert_eq!(end["scene_hashes"], "00000000feedbeef");
    assert!(back.stats.chunks >= 3, "chunks: {}", back.stats.chunks);

    // The mcap crate, with chunk CRCs checked, then the summary and its statistics.
    let buf = std::fs::read(&path).unwrap();
    let mut topics: BTreeMap<String, (String, String, String)> = BTreeMap::new();
    let mut n = 0;
    for m in
        mcap::MessageStream::new_with_options(&buf, mcap::read::Options::ValidateChunkCrcs.into())
            .unwrap()
    {
        let m = m.unwrap();
        let schema = m.channel.schema.as_ref().unwrap();
        topics.insert(
            m.channel.topic.clone(),
            (
                schema.name.clone(),
                schema.encoding.clone(),
                m.channel.message_encoding.clone(),
            ),
        );
        assert_eq!(m.log_time, msgs[n].log_time_ns);
        n += 1;
    }
    assert_eq!(n, msgs.len());
    let t = |name: &str, enc: &str, menc: &str| (name.to_owned(), enc.to_owned(), menc.to_owned());
    let expected: BTreeMap<String, (String, String, String)> = [
        ("job", t("mwb.record.v1.JobRecord", "protobuf", "protobuf")),
        (
            "job/state",
            t("mwb.record.v1.JobStateRecord", "protobuf", "protobuf"),
        ),
        (
            "seg",
            t("mwb.record.v1.SegmentRecord", "protobuf", "protobuf"),
        ),
        (
            "done",
            t("mwb.record.v1.WorldDoneRecord", "protobuf", "protobuf"),
        ),
        (
            "stats",
            t("mwb.record.v1.NodeStatsRecord", "protobuf", "protobuf"),
        ),
        (
            "browse",
            t("mwb.record.v1.BrowseRecord", "jsonschema", "json"),
        ),
        ("raw", t("mwb.record.v1.RawRecord", "protobuf", "protobuf")),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_owned(), v))
    .collect();
    assert_eq!(topics, expected);
    let summary = mcap::Summary::read(&buf).unwrap().unwrap();
    let stats = summary.stats.unwrap();
    assert_eq!(stats.message_count, msgs.len() as u64);
    assert_eq!(stats.channel_count, 7);
    assert_eq!(stats.schema_count, 7);
    assert_eq!(stats.metadata_count, 2);
    assert_eq!(stats.chunk_count as u64, back.stats.chunks);
    assert_eq!(summary.chunk_indexes.len() as u64, back.stats.chunks);
    for ci in &summary.chunk_indexes {
        assert_eq!(ci.compression, "zstd");
    }
    // The streaming reader with every CRC it knows checked (data and summary sections too).
    let mut r = mcap::sans_io::LinearReader::new_with_options(
        mcap::sans_io::LinearReaderOptions::default()
            .with_validate_chunk_crcs(true)
            .with_validate_data_section_crc(true)
            .with_validate_summary_section_crc(true),
    );
    let mut rest = buf.as_slice();
    let mut records = 0;
    while let Some(ev) = r.next_event() {
        match ev.unwrap() {
            mcap::sans_io::LinearReadEvent::ReadRequest(need) => {
                let k = need.min(rest.len());
                r.insert(k).copy_from_slice(&rest[..k]);
                r.notify_read(k);
                rest = &rest[k..];
            }
            mcap::sans_io::LinearReadEvent::Record { .. } => records += 1,
        }
    }
    assert!(records > msgs.len());
}

#[test]
fn messages_decode_from_the_embedded_schemas_alone() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("s.mcap");
    let msgs = session();
    write(&path, &msgs, 1 << 20);
    let buf = std::fs::read(&path).unwrap();
    let mut seen = BTreeMap::<String, usize>::new();
    for (i, m) in mcap::MessageStream::new(&buf).unwrap().enumerate() {
        let m = m.unwrap();
        let schema = m.channel.schema.as_ref().unwrap();
        *seen.entry(m.channel.topic.clone()).or_default() += 1;
        if schema.encoding == "jsonschema" {
            let v: serde_json::Value = serde_json::from_slice(&m.data).unwrap();
            assert_eq!(v["key"], msgs[i].key.as_str());
            assert_eq!(v["message"]["k"], 3);
            continue;
        }
        // What a generic tool does: a pool from the schema's bytes, the message by name.
        let pool = DescriptorPool::decode(schema.data.as_ref()).unwrap();
        let desc = pool.get_message_by_name(&schema.name).unwrap();
        let dm = DynamicMessage::decode(desc, m.data.as_ref()).unwrap();
        let key = dm.get_field_by_name("key").unwrap();
        assert_eq!(key.as_str(), Some(msgs[i].key.as_str()));
        // The raw wrapper holds plain bytes (`payload`); the others the typed `message`.
        let field = if m.channel.topic == "raw" {
            "payload"
        } else {
            "message"
        };
        let inner = dm.get_field_by_name(field).unwrap();
        match m.channel.topic.as_str() {
            "seg" => {
                let seg = MotionSegment::decode(msgs[i].payload.as_slice()).unwrap();
                let im = inner.as_message().unwrap();
                let f = |n: &str| im.get_field_by_name(n).unwrap().into_owned();
                assert_eq!(f("job_id"), Value::String(seg.job_id.clone()));
                assert_eq!(f("seq"), Value::U32(seg.seq));
                assert_eq!(f("crc32"), Value::U32(seg.crc32));
                assert_eq!(f("payload"), Value::Bytes(seg.payload.clone().into()));
            }
            "done" => {
                let im = inner.as_message().unwrap();
                assert_eq!(
                    im.get_field_by_name("segment_count").unwrap().as_u32(),
                    Some(3)
                );
            }
            "job" => {
                let im = inner.as_message().unwrap();
                let scene = im.get_field_by_name("scene").unwrap();
                let scene = scene.as_message().unwrap();
                assert_eq!(
                    scene.get_field_by_name("content_hash").unwrap().as_u64(),
                    Some(0xfeed_beef)
                );
            }
            "raw" => assert_eq!(inner.as_bytes().map(|b| b.to_vec()), Some(vec![0x18, 0xff])),
            "job/state" | "stats" => assert!(inner.as_message().is_some()),
            other => panic!("unexpected topic {other}"),
        }
    }
    assert_eq!(seen["seg"], 6);
    assert_eq!(seen.values().sum::<usize>(), msgs.len());
}

/// Chunk layout from the summary: (start, end, compressed data start, messages inside).
fn chunks(buf: &[u8]) -> Vec<(u64, u64, u64, usize)> {
    let summary = mcap::Summary::read(buf).unwrap().unwrap();
    summary
        .chunk_indexes
        .iter()
        .map(|ci| {
            // A chunk of schema and channel records only (the schema set is large enough to
            // fill one) has no message indexes, which the mcap crate reports as BadIndex.
            let n = if ci.message_index_offsets.is_empty() {
                0
            } else {
                let idx = summary.read_message_indexes(buf, ci).unwrap();
                idx.values().map(Vec::len).sum()
            };
            (
                ci.chunk_start_offset,
                ci.chunk_start_offset + ci.chunk_length,
                ci.compressed_data_offset().unwrap(),
                n,
            )
        })
        .collect()
}

#[test]
fn a_truncated_recording_keeps_every_whole_chunk_and_names_the_offset() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("s.mcap");
    let msgs = session();
    write(&path, &msgs, 4096);
    let buf = std::fs::read(&path).unwrap();
    let layout = chunks(&buf);
    assert!(layout.len() >= 3);
    let data_end = layout.last().unwrap().1;
    let cut_path = dir.path().join("cut.mcap");
    // Every chunk boundary ±1, the middle of every chunk, the magic, the summary, the end.
    let mut cuts = vec![0, 3, 8, 9, 20, buf.len() as u64 - 1, buf.len() as u64 - 9];
    for &(s, e, _, _) in &layout {
        cuts.extend([s, s + 1, (s + e) / 2, e - 1, e, e + 1]);
    }
    cuts.push((data_end + buf.len() as u64) / 2);
    for cut in cuts {
        std::fs::write(&cut_path, &buf[..cut as usize]).unwrap();
        let r = match read_recording(&cut_path) {
            Ok(r) => r,
            Err(e) => {
                // Not even the magic: nothing to recover.
                assert!(cut < 8, "cut {cut}: {e}");
                assert_eq!(e.offset, 0);
                continue;
            }
        };
        let whole: usize = layout.iter().filter(|c| c.1 <= cut).map(|c| c.3).sum();
        let e = r
            .error
            .as_ref()
            .unwrap_or_else(|| panic!("cut {cut}: no error"));
        assert!(
            matches!(e.damage, Damage::Truncated { .. } | Damage::NoFooter),
            "cut {cut}: {e}"
        );
        assert!(e.to_string().contains("cut.mcap"), "{e}");
        assert!(e.offset <= cut, "cut {cut}: error at {}", e.offset);
        // Exactly the messages of the whole chunks before the cut, in order.
        assert_eq!(r.messages.len(), whole, "cut {cut}: {e}");
        assert_eq!(r.stats.messages as usize, whole);
        for (m, o) in r.messages.iter().zip(&msgs) {
            assert_eq!((&m.key, &m.payload), (&o.key, &o.payload));
        }
        // Cut inside a chunk: the error is at that chunk's first byte.
        if let Some(c) = layout.iter().find(|c| c.0 < cut && cut < c.1) {
            assert_eq!(e.offset, c.0, "cut {cut}");
        }
        assert!(!r.stats.complete);
    }
}

#[test]
fn every_flipped_bit_is_found_and_nothing_after_a_damaged_chunk_is_kept() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("s.mcap");
    let msgs = session();
    write(&path, &msgs, 4096);
    let buf = std::fs::read(&path).unwrap();
    let layout = chunks(&buf);
    let flipped = dir.path().join("flip.mcap");
    let mut detected_in_chunk = 0;
    let mut harmless = 0;
    // Every 7th byte (MWB_RECORD_FLIP_STEP=1: every byte, as checked by hand once).
    let step: usize = std::env::var("MWB_RECORD_FLIP_STEP")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(7);
    for (i, pos) in (0..buf.len())
        .step_by(step.max(1))
        .chain([buf.len() - 1])
        .enumerate()
    {
        let mut b = buf.clone();
        b[pos] ^= 1 << (i % 8);
        std::fs::write(&flipped, &b).unwrap();
        let r = match read_recording(&flipped) {
            Ok(r) => r,
            Err(e) => {
                assert!(pos < 8, "flip at {pos}: {e}");
                continue;
            }
        };
        let e = r
            .error
            .as_ref()
            .unwrap_or_else(|| panic!("flip at {pos} not detected"));
        assert!(!r.stats.complete);
        // Whatever was kept is the recording's beginning, unaltered and without a hole.
        assert!(r.messages.len() <= msgs.len());
        for (m, o) in r.messages.iter().zip(&msgs) {
            assert_eq!(
                (&m.key, &m.payload),
                (&o.key, &o.payload),
                "flip at {pos}: {e}"
            );
        }
        // Found at the record it hit, or only by a section's CRC (a flip that changes no
        // message: in metadata text, in redundant zstd bits, in the summary).
        assert!(
            e.offset <= pos as u64
                || matches!(e.damage, Damage::DataCrc { .. } | Damage::SummaryCrc { .. }),
            "flip at {pos}: {e}"
        );
        // A flip in a chunk's compressed records: that chunk and all after it are dropped,
        // and the error names the chunk — unless the flip changed nothing zstd reads (some
        // bits of its entropy tables are redundant: the chunk decompresses to the same bytes
        // and its CRC matches), in which case the chunk's messages are intact and kept, and the
        // data section's CRC reports the flip at its end.
        if let Some(k) = layout
            .iter()
            .position(|c| c.2 <= pos as u64 && (pos as u64) < c.1)
        {
            if let Damage::DataCrc { .. } = e.damage {
                let through: usize = layout[..=k].iter().map(|c| c.3).sum();
                assert!(r.messages.len() >= through, "flip at {pos}: {e}");
                harmless += 1;
                continue;
            }
            let before: usize = layout[..k].iter().map(|c| c.3).sum();
            assert_eq!(
                r.messages.len(),
                before,
                "flip at {pos} ({} into chunk {k}'s data): {e}",
                pos as u64 - layout[k].2
            );
            assert_eq!(e.offset, layout[k].0, "flip at {pos}: {e}");
            assert!(
                matches!(
                    e.damage,
                    Damage::ChunkCrc { .. } | Damage::Decompress { .. } | Damage::ChunkSize { .. }
                ),
                "flip at {pos}: {e}"
            );
            detected_in_chunk += 1;
        }
    }
    assert!(
        detected_in_chunk > 20 && harmless * 4 < detected_in_chunk,
        "{detected_in_chunk} flips found in chunks, {harmless} harmless"
    );
}

#[test]
fn garbage_and_foreign_channels() {
    let dir = tempfile::tempdir().unwrap();
    let garbage = dir.path().join("garbage.mcap");
    std::fs::write(&garbage, b"this is not a recording at all").unwrap();
    let e = read_recording(&garbage).unwrap_err();
    assert!(matches!(e.damage, Damage::BadMagic), "{e}");
    assert!(e.to_string().contains("garbage.mcap: byte 0"), "{e}");

    // Valid magic, then garbage.
    let mut b = mcap::MAGIC.to_vec();
    b.extend_from_slice(&[0x42; 100]);
    std::fs::write(&garbage, &b).unwrap();
    let r = read_recording(&garbage).unwrap();
    let e = r.error.unwrap();
    assert_eq!(e.offset, 8, "{e}");
    assert!(r.messages.is_empty());

    // A file by another writer: one of our channels, one foreign topic, and a `seg` topic
    // with a schema that is not ours. Only ours is read; the rest is counted.
    let path = dir.path().join("foreign.mcap");
    {
        let f = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
        let mut w = mcap::Writer::new(f).unwrap();
        let ours = w
            .add_schema(
                Family::JobState.schema_name(),
                "protobuf",
                &mwb_record::family::descriptor_set(),
            )
            .unwrap();
        let ours = w
            .add_channel(ours, "job/state", "protobuf", &BTreeMap::new())
            .unwrap();
        let tf = w.add_schema("tf2_msgs/TFMessage", "ros2msg", b"x").unwrap();
        let tf = w.add_channel(tf, "/tf", "cdr", &BTreeMap::new()).unwrap();
        let fake = w.add_schema("other.Segment", "protobuf", b"").unwrap();
        let fake = w
            .add_channel(fake, "seg", "protobuf", &BTreeMap::new())
            .unwrap();
        let st = JobState {
            job_id: "j".into(),
            ..Default::default()
        };
        let rec = mwb_record::family::encode_record(
            Family::JobState,
            "mwb/x/job/j/state",
            &st.encode_to_vec(),
        )
        .unwrap();
        for (i, (ch, data)) in [
            (ours, rec.as_slice()),
            (tf, b"ab"),
            (fake, b"cd"),
            (tf, b"ef"),
        ]
        .into_iter()
        .enumerate()
        {
            let header = mcap::records::MessageHeader {
                channel_id: ch,
                sequence: i as u32,
                log_time: i as u64,
                publish_time: i as u64,
            };
            w.write_to_known_channel(&header, data).unwrap();
        }
        w.finish().unwrap();
    }
    let r = read_recording(&path).unwrap();
    assert!(r.error.is_none(), "{:?}", r.error);
    assert_eq!(r.messages.len(), 1);
    assert_eq!(r.messages[0].key, "mwb/x/job/j/state");
    assert_eq!(r.stats.skipped_unknown.get("/tf"), Some(&2));
    assert_eq!(r.stats.skipped_unknown.get("seg"), Some(&1));
    assert!(r.info.is_none());
}

#[test]
fn a_recorder_killed_after_a_flush_leaves_everything_flushed_readable() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("killed.mcap");
    let msgs = session();
    let mut w = RecordingWriter::create(&path, &info(), &WriterOptions::default()).unwrap();
    let (flushed, rest) = msgs.split_at(7);
    for m in flushed {
        w.write(m).unwrap();
    }
    w.flush().unwrap();
    for m in rest {
        w.write(m).unwrap();
    }
    // As SIGKILL would: no finish, no drop, the open chunk never reaches the file.
    std::mem::forget(w);
    let r = read_recording(&path).unwrap();
    let e = r.error.unwrap();
    assert!(
        matches!(e.damage, Damage::NoFooter | Damage::Truncated { .. }),
        "{e}"
    );
    assert_eq!(r.messages.len(), flushed.len());
    assert_eq!(r.info.unwrap().space, "demo");
    assert!(r.end.is_none());
}
