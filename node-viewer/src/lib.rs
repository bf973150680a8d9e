//! The manyworlds workstation viewer (§4.4 of Twigg and James, SIGGRAPH 2007): every world's
//! centre-of-mass paths in 3D, screen rectangles that become positive or negative constraints,
//! undo/redo, and playback of one world.
//!
//! * [`state`] — [`ViewerState`], pure: scene, worlds, camera, constraints, selection and
//!   playback, changed only by [`Msg`]s; constraints are evaluated with `mwb_core::browse`.
//! * [`camera`] — an orbit camera that hands out `mwb_core::browse::Camera`s, so the view is
//!   drawn and queried through one projection.
//! * [`session`] — who answers constraints: this process (offline) or node-query (live).
//! * [`world`] / [`offline`] — worlds as the store indexed them (from a store's `q/paths`, or
//!   sampled in-process and indexed with the store's own code), and their decoded motion.
//! * [`live`] — the bus task of a live viewer: worlds as they arrive, the browsing session,
//!   motion fetched for playback, the cluster's status; never on the UI thread.
//! * [`draw`] — the 3D view as egui shapes, projected on the CPU.
//! * [`ui`] — [`ViewerApp`]: panels, the 3D view's mouse and keys, the eframe app.
//! * [`preview`] — a scene as it starts, drawn with no worlds (`mwb scene preview`).
//! * [`views`] — saved views kept with the session in a small JSON file (the app reads and
//!   writes it; the state only holds the views).
//! * [`softpaint`] — a software rasteriser for egui's tessellated output: headless screenshots
//!   and image snapshots without a GPU or display.

pub mod camera;
pub mod draw;
pub mod live;
pub mod math;
pub mod offline;
pub mod preview;
pub mod screenshot;
pub mod session;
pub mod softpaint;
pub mod state;
pub mod ui;
pub mod views;
pub mod world;

pub use camera::OrbitCamera;
pub use session::{Command, ConstraintRow};
pub use state::{Goal, LinkStatus, Msg, Playback, RankSpec, Ranking, SavedView, ViewerState};
pub use ui::ViewerApp;
pub use world::WorldData;

/// What can go wrong in the viewer's logic. Every variant names what it is about.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum ViewerError {
    #[error(transparent)]
    Browse(#[from] mwb_core::browse::BrowseError),
    #[error("motion: {0}")]
    Motion(String),
    #[error("body {body}: {what}")]
    Body { body: usize, what: String },
    #[error("frame_dt {0} is not a positive number")]
    FrameDt(f64),
    #[error("the scene has {scene} bodies but the motion has {motion}")]
    BodyCount { scene: usize, motion: usize },
    #[error("world {found} is already loaded")]
    WorldIndex { found: u32 },
    #[error("world {world}: sampling failed: {what}")]
    Sampling { world: u32, what: String },
    #[error("{0} needs a live viewer (`mwb viewer --connect …`)")]
    Offline(&'static str),
    #[error("screenshot size {0}: expected WIDTHxHEIGHT, each 64..=8192")]
    Size(String),
    #[error("goal orientation: {0}")]
    Goal(String),
    #[error("refine: {0}")]
    Refine(&'static str),
}
