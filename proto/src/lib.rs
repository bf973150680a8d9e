//! The manyworlds wire format, `mwb.v1` (protobuf, see `proto/mwb/v1/mwb.proto`).
//!
//! ```
//! use mwb_proto::v1::{JobState, Message};
//! let state = JobState { job_id: "j1".into(), worlds_done: 3, target_worlds: 10, ..Default::default() };
//! let bytes = state.encode_to_vec();
//! let back = JobState::decode(bytes.as_slice()).unwrap();
//! assert_eq!(back, state);
//! ```

/// Generated `mwb.v1` types.
pub mod v1 {
    include!(concat!(env!("OUT_DIR"), "/mwb.v1.rs"));
    pub use prost::Message;
}

/// The encoded `FileDescriptorSet` of `mwb.v1` (for recordings that embed their schema).
pub const DESCRIPTOR_SET: &[u8] =
    include_bytes!(concat!(env!("OUT_DIR"), "/mwb_v1_descriptor.bin"));
