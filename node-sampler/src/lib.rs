//! Forward sampling node (§4.1, §4.2): rapier3d worlds with impact perturbations, streamed over
//! the bus as they are computed.
//!
//! * [`world`] — pure computation: one `(scene, seed)` → motion segments + summary.
//! * [`fidelity`] — pure: the speed↔accuracy study (worlds measured per preset, distances of
//!   their distributions to a reference's) and `sim = "auto"`'s calibration.
//! * [`limits`] — pure: what the simulator cannot do faithfully in a scene, found before
//!   sampling (warnings and refusals naming body, field and limit).
//! * [`plan`] — pure: what the simulator does for a scene under its preset, and what it leaves
//!   out because the scene does not need it (issue 19).
//! * [`refine`] — pure computation: §4.5 refinement, a parent regenerated exactly from its
//!   lineage and children that re-simulate only the bodies they must.
//! * [`analytic`] — pure: the analytic suite (`scenes/analytic/`), simulated quantities against
//!   their closed forms.
//! * [`edit`] — pure computation: scene edits (§4.5 from frame 0), children of kept worlds with
//!   an edit of their scene's bodies applied, re-simulating only the bodies it reaches.
//! * [`request`] — a refinement request (stored world, picked bodies, box) checked and turned
//!   into a REFINE job, for `mwb refine` and the viewer.
//! * [`node`] — the bus node: the [`Forward`] kind of `mwb-node`'s worker node (it takes sample
//!   and refine jobs; the skeleton picks them, runs the workers, publishes segments and
//!   `WorldDone`).

pub mod analytic;
pub mod edit;
pub mod fidelity;
pub mod limits;
pub mod node;
pub mod plan;
pub mod refine;
pub mod request;
pub mod world;

pub use node::{
    Forward, SamplerConfig, SamplerError, SamplerHandle, attach_index, run_sampler,
    segment_message, world_done,
};
pub use world::{
    PayloadEncoding, RunOptions, Segment, SimWorld, WorldSummary, motion_model, provenance,
    rotation_dynamics, run_world, run_world_observed,
};
