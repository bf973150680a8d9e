//! The `mwb` command line: one binary for every role (DESIGN.md "Shape of the system").
//! Subcommands are thin: the nodes are libraries (`mwb-sampler`, `mwb-store`, …).

pub mod bench;
pub mod bench_codec;
pub mod bench_query;
pub mod bench_stepper;
pub mod bus;
pub mod check;
pub mod client;
pub mod demo;
pub mod query;
pub mod record_cmd;
pub mod reverse_cmd;
