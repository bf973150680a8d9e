//! The `mwb` command line: one binary for every role. Each command is a module here (its
//! arguments and its `run`); the nodes are libraries (`mwb-sampler`, `mwb-store`, …), and
//! `bus`, `client`, `check` and `output` are what the commands share.

pub mod bench;
pub mod bus;
pub mod certs;
pub mod certs_cmd;
pub mod check;
pub mod cli;
pub mod client;
pub mod demo;
pub mod export_cmd;
pub mod job;
pub mod output;
pub mod query;
pub mod record_cmd;
pub mod refine_cmd;
pub mod reverse_cmd;
pub mod sampler;
pub mod scene;
pub mod scene_edit_cmd;
pub mod sim;
pub mod stall;
pub mod status;
pub mod store;
pub mod viewer_cmd;
pub mod world_cmd;
