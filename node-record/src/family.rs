//! Key families: which channel a bus message goes to, its schema, and the per-message record
//! that keeps its full zenoh key (pure: no I/O).
//!
//! One channel per family, not per key: segment keys are unique per segment
//! (`seg/<job>/<node>/<n>/<seq>`), so a channel per key would put a channel record (and a
//! summary entry) beside every few kilobytes of data and make the channel list of a long session
//! unreadable. The key travels inside the message instead, in a wrapper that is itself a
//! protobuf message of the embedded descriptor set (`mwb.record.v1.*Record`), so MCAP tools
//! still decode the whole thing from the file alone.

use mwb_proto::v1::{Job, JobState, Message, MotionSegment, NodeStats, Scene, World, WorldDone};
use serde_json::value::RawValue;

/// The family of a bus message; one MCAP channel each (topic = [`Family::topic`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Family {
    Job,
    JobState,
    Segment,
    Done,
    Stats,
    Scene,
    /// `q/world/<i>` (a `World` put; stores answer queries there, which are not seen).
    QWorld,
    /// `q/stats` (`NodeStats`).
    QStats,
    /// JSON browse messages put under `browse/**` or `q/browse/**`.
    Browse,
    /// Anything else, or a message that does not decode as its family's type.
    Raw,
}

/// How a family's records are encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Encoding {
    Protobuf,
    Json,
}

impl Family {
    pub const ALL: [Family; 10] = [
        Family::Job,
        Family::JobState,
        Family::Segment,
        Family::Done,
        Family::Stats,
        Family::Scene,
        Family::QWorld,
        Family::QStats,
        Family::Browse,
        Family::Raw,
    ];

    /// The MCAP topic.
    pub fn topic(self) -> &'static str {
        match self {
            Family::Job => "job",
            Family::JobState => "job/state",
            Family::Segment => "seg",
            Family::Done => "done",
            Family::Stats => "stats",
            Family::Scene => "scene",
            Family::QWorld => "q/world",
            Family::QStats => "q/stats",
            Family::Browse => "browse",
            Family::Raw => "raw",
        }
    }

    pub fn from_topic(topic: &str) -> Option<Family> {
        Family::ALL.into_iter().find(|f| f.topic() == topic)
    }

    /// The schema record's name: the wrapper message (or the JSON schema's title).
    pub fn schema_name(self) -> &'static str {
        match self {
            Family::Job => "mwb.record.v1.JobRecord",
            Family::JobState => "mwb.record.v1.JobStateRecord",
            Family::Segment => "mwb.record.v1.SegmentRecord",
            Family::Done => "mwb.record.v1.WorldDoneRecord",
            Family::Stats | Family::QStats => "mwb.record.v1.NodeStatsRecord",
            Family::Scene => "mwb.record.v1.SceneRecord",
            Family::QWorld => "mwb.record.v1.WorldRecord",
            Family::Browse => "mwb.record.v1.BrowseRecord",
            Family::Raw => "mwb.record.v1.RawRecord",
        }
    }

    pub fn encoding(self) -> Encoding {
        match self {
            Family::Browse => Encoding::Json,
            _ => Encoding::Protobuf,
        }
    }

    /// MCAP schema encoding (`protobuf` / `jsonschema`).
    pub fn schema_encoding(self) -> &'static str {
        match self.encoding() {
            Encoding::Protobuf => "protobuf",
            Encoding::Json => "jsonschema",
        }
    }

    /// MCAP message encoding (`protobuf` / `json`).
    pub fn message_encoding(self) -> &'static str {
        match self.encoding() {
            Encoding::Protobuf => "protobuf",
            Encoding::Json => "json",
        }
    }

    /// The family a key's shape names (`mwb/<space>/<family>/…`), before looking at the payload.
    pub fn of_key(key: &str) -> Family {
        let mut chunks = key.split('/');
        if chunks.next() != Some("mwb") || chunks.next().is_none_or(str::is_empty) {
            return Family::Raw;
        }
        let rest: Vec<&str> = chunks.collect();
        match rest.as_slice() {
            ["job", _] => Family::Job,
            ["job", _, "state"] => Family::JobState,
            ["seg", _, ..] => Family::Segment,
            ["done", _, ..] => Family::Done,
            ["stats", _, ..] => Family::Stats,
            ["scene", _] => Family::Scene,
            ["q", "world", _] => Family::QWorld,
            ["q", "stats"] => Family::QStats,
            ["q", "browse", _, ..] | ["browse", _, ..] => Family::Browse,
            _ => Family::Raw,
        }
    }

    /// Whether `key` is a store shard's count of a job's durable worlds
    /// (`job/<id>/shard/<index>`): the recorded cluster's own bookkeeping, recorded (as `Raw`)
    /// but never replayed — a store that takes in a replay counts the worlds it stores itself,
    /// and a recorded count of another cluster's shard would close its jobs early.
    pub fn is_shard_count(key: &str) -> bool {
        let rest: Vec<&str> = key.split('/').skip(2).collect();
        key.starts_with("mwb/") && matches!(rest.as_slice(), ["job", _, "shard", _])
    }

    /// Whether `payload` is a valid message of this family's type (`Raw` takes anything).
    pub fn accepts(self, payload: &[u8]) -> bool {
        match self {
            Family::Job => Job::decode(payload).is_ok(),
            Family::JobState => JobState::decode(payload).is_ok(),
            Family::Segment => MotionSegment::decode(payload).is_ok(),
            Family::Done => WorldDone::decode(payload).is_ok(),
            Family::Stats | Family::QStats => NodeStats::decode(payload).is_ok(),
            Family::Scene => Scene::decode(payload).is_ok(),
            Family::QWorld => World::decode(payload).is_ok(),
            Family::Browse => serde_json::from_slice::<&RawValue>(payload).is_ok(),
            Family::Raw => true,
        }
    }

    /// The family a message is recorded in: its key's, if the payload is of that type, else
    /// `Raw` (so that every typed channel decodes with its schema).
    pub fn classify(key: &str, payload: &[u8]) -> Family {
        let f = Family::of_key(key);
        if f.accepts(payload) { f } else { Family::Raw }
    }
}

/// The wire shape of every protobuf wrapper in `record.proto`: field 2 is declared as the
/// typed message there and as bytes here; both are length-delimited, so the bytes are the
/// published message verbatim.
#[derive(Clone, PartialEq, prost::Message)]
struct Wrapper {
    #[prost(string, tag = "1")]
    key: String,
    #[prost(bytes = "vec", tag = "2")]
    message: Vec<u8>,
}

/// The JSON wrapper of the browse channel (`BROWSE_JSON_SCHEMA`).
#[derive(serde::Serialize, serde::Deserialize)]
struct JsonWrapper<'a> {
    key: String,
    #[serde(borrow)]
    message: &'a RawValue,
}

/// A record that cannot be made or read back.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum RecordFormatError {
    #[error("payload of {key:?} is not a valid {family} message")]
    Payload { key: String, family: &'static str },
    #[error("{family} record does not decode: {reason}")]
    Record {
        family: &'static str,
        reason: String,
    },
}

/// The bytes of one MCAP message: `payload` (the bus message) wrapped with its key.
pub fn encode_record(
    family: Family,
    key: &str,
    payload: &[u8],
) -> Result<Vec<u8>, RecordFormatError> {
    match family.encoding() {
        Encoding::Protobuf => {
            let w = Wrapper {
                key: key.to_owned(),
                message: payload.to_vec(),
            };
            Ok(w.encode_to_vec())
        }
        Encoding::Json => {
            let message: &RawValue =
                serde_json::from_slice(payload).map_err(|_| RecordFormatError::Payload {
                    key: key.to_owned(),
                    family: family.topic(),
                })?;
            let w = JsonWrapper {
                key: key.to_owned(),
                message,
            };
            serde_json::to_vec(&w).map_err(|e| RecordFormatError::Record {
                family: family.topic(),
                reason: e.to_string(),
            })
        }
    }
}

/// Key and bus message of one MCAP message of `family`.
pub fn decode_record(family: Family, data: &[u8]) -> Result<(String, Vec<u8>), RecordFormatError> {
    let bad = |reason: String| RecordFormatError::Record {
        family: family.topic(),
        reason,
    };
    match family.encoding() {
        Encoding::Protobuf => {
            let w = Wrapper::decode(data).map_err(|e| bad(e.to_string()))?;
            Ok((w.key, w.message))
        }
        Encoding::Json => {
            let w: JsonWrapper = serde_json::from_slice(data).map_err(|e| bad(e.to_string()))?;
            Ok((w.key, w.message.get().as_bytes().to_vec()))
        }
    }
}

/// The JSON schema of the browse channel's records.
pub const BROWSE_JSON_SCHEMA: &str = r#"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "mwb.record.v1.BrowseRecord",
  "description": "One JSON browse message put on the bus, with its full zenoh key.",
  "type": "object",
  "properties": {
    "key": { "type": "string", "description": "the zenoh key, mwb/<space>/browse/<session> or mwb/<space>/q/browse/<node>/<session>" },
    "message": { "description": "the JSON body exactly as published (mwb_core::browse::api Request, Reply, ShardRequest or ShardReply)" }
  },
  "required": ["key", "message"]
}"#;

/// The descriptor set embedded in every protobuf schema record: `mwb.v1` (as `mwb-proto`
/// builds it) followed by `mwb.record.v1`. A `FileDescriptorSet` is one repeated field, so
/// the concatenation of two encoded sets is the encoded union.
pub fn descriptor_set() -> Vec<u8> {
    const RECORD: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/mwb_record_v1_descriptor.bin"));
    let mut v = Vec::with_capacity(mwb_proto::DESCRIPTOR_SET.len() + RECORD.len());
    v.extend_from_slice(mwb_proto::DESCRIPTOR_SET);
    v.extend_from_slice(RECORD);
    v
}

/// The schema record's data for `family`.
pub fn schema_data(family: Family) -> Vec<u8> {
    match family.encoding() {
        Encoding::Protobuf => descriptor_set(),
        Encoding::Json => BROWSE_JSON_SCHEMA.as_bytes().to_vec(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A shard's count is recognised (and so never replayed); nothing else is.
    #[test]
    fn shard_counts_are_recognised() {
        assert!(Family::is_shard_count("mwb/demo/job/j1/shard/1"));
        for key in [
            "mwb/demo/job/j1",
            "mwb/demo/job/j1/state",
            "mwb/demo/job/j1/shard",
            "mwb/demo/job/j1/shard/1/x",
            "other/demo/job/j1/shard/1",
            "mwb/demo/seg/j1/shard/1",
        ] {
            assert!(!Family::is_shard_count(key), "{key}");
        }
    }

    #[test]
    fn keys_map_to_families() {
        let cases = [
            ("mwb/demo/job/j1", Family::Job),
            ("mwb/demo/job/j1/state", Family::JobState),
            ("mwb/demo/seg/j1/n1/7/2", Family::Segment),
            ("mwb/demo/done/j1/n1/7", Family::Done),
            ("mwb/demo/stats/store/n1", Family::Stats),
            ("mwb/demo/scene/3", Family::Scene),
            ("mwb/demo/q/world/12", Family::QWorld),
            ("mwb/demo/q/stats", Family::QStats),
            ("mwb/demo/browse/s1", Family::Browse),
            ("mwb/demo/q/browse/n1/s1", Family::Browse),
            ("mwb/demo/browse/s1/edit", Family::Browse),
            ("mwb/demo/alive/store/n1", Family::Raw),
            ("mwb/demo/job", Family::Raw),
            ("mwb/demo/job/j1/other", Family::Raw),
            ("other/demo/job/j1", Family::Raw),
            ("mwb//job/j1", Family::Raw),
        ];
        for (key, fam) in cases {
            assert_eq!(Family::of_key(key), fam, "{key}");
        }
        for f in Family::ALL {
            assert_eq!(Family::from_topic(f.topic()), Some(f));
        }
    }

    #[test]
    fn a_payload_that_is_not_its_familys_type_goes_to_raw() {
        let st = JobState {
            job_id: "j1".into(),
            worlds_done: 3,
            ..Default::default()
        };
        let key = "mwb/demo/job/j1/state";
        assert_eq!(Family::classify(key, &st.encode_to_vec()), Family::JobState);
        // A truncated varint is not a JobState.
        assert_eq!(Family::classify(key, &[0x18, 0xff]), Family::Raw);
        assert_eq!(
            Family::classify("mwb/demo/browse/s", b"{\"a\": 1}"),
            Family::Browse
        );
        assert_eq!(
            Family::classify("mwb/demo/browse/s", b"{not json"),
            Family::Raw
        );
    }

    #[test]
    fn records_keep_key_and_bytes_exactly() {
        let seg = MotionSegment {
            job_id: "j".into(),
            seq: 4,
            payload: vec![1, 2, 3, 250],
            ..Default::default()
        };
        let bytes = seg.encode_to_vec();
        let key = "mwb/demo/seg/j/n/0/4";
        let rec = encode_record(Family::Segment, key, &bytes).unwrap();
        // The wrapper read as its schema declares it: field 2 is the typed message.
        #[derive(Clone, PartialEq, prost::Message)]
        struct Typed {
            #[prost(string, tag = "1")]
            key: String,
            #[prost(message, optional, tag = "2")]
            message: Option<MotionSegment>,
        }
        let typed = Typed::decode(rec.as_slice()).unwrap();
        assert_eq!(typed.key, key);
        assert_eq!(typed.message.as_ref(), Some(&seg));
        assert_eq!(
            decode_record(Family::Segment, &rec),
            Ok((key.to_owned(), bytes))
        );

        let json = br#"{ "op": "add",  "x": 1.5 }"#;
        let rec = encode_record(Family::Browse, "mwb/d/browse/s", json).unwrap();
        let v: serde_json::Value = serde_json::from_slice(&rec).unwrap();
        assert_eq!(v["key"], "mwb/d/browse/s");
        assert_eq!(v["message"]["x"], 1.5);
        assert_eq!(
            decode_record(Family::Browse, &rec),
            Ok(("mwb/d/browse/s".to_owned(), json.to_vec()))
        );
        assert!(encode_record(Family::Browse, "k", b"{").is_err());
        assert!(decode_record(Family::Browse, b"[]").is_err());
        assert!(decode_record(Family::Job, &[0x12, 0x05, 1]).is_err());
    }

    #[test]
    fn the_json_schema_is_json() {
        let v: serde_json::Value = serde_json::from_str(BROWSE_JSON_SCHEMA).unwrap();
        assert_eq!(v["title"], Family::Browse.schema_name());
    }
}
