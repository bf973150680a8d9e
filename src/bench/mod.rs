//! `mwb bench …`: the benchmarks, one module each.

pub mod codec;
pub mod query;
pub mod sampler;
pub mod stepper;

pub use sampler::free_port;
