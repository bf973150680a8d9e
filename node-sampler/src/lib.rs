//! Forward sampling node (§4.1, §4.2): rapier3d worlds with impact perturbations, streamed over
//! the bus as they are computed.
//!
//! * [`world`] — pure computation: one `(scene, seed)` → motion segments + summary.
//! * [`node`] — the bus node: the [`Forward`] kind of `mwb-node`'s worker node (it takes sample
//!   and refine jobs; the skeleton picks them, runs the workers, publishes segments and
//!   `WorldDone`).

pub mod node;
pub mod world;

pub use node::{
    Forward, SamplerConfig, SamplerError, SamplerHandle, run_sampler, segment_message, world_done,
};
pub use world::{
    PayloadEncoding, RunOptions, Segment, SimWorld, WorldSummary, motion_model, provenance,
    rotation_dynamics, run_world, run_world_observed,
};
