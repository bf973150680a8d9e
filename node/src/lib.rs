//! What the manyworlds nodes share on the bus, written once.
//!
//! * [`bus`] — every node: its id and keys ([`Node`]), the liveliness token, the statistics
//!   publisher, decode-and-forward loops generic over the message type (a message that does
//!   not decode is dropped and counted), puts and replies whose failures are logged and counted.
//! * [`worker`] — the worker node skeleton: a job board fed by announcements, periodic
//!   refresh queries and job states; worker threads; one bounded publisher with blocking
//!   congestion control; giving up jobs whose worlds keep failing. A kind of worker (forward
//!   sampler, reverse stepper, refinement) implements [`WorkerKind`] — which jobs it takes,
//!   how a job's scene is prepared, how a job and a seed become segments and a summary.
//! * [`room`] — back-pressure: workers take no new world while a store is full (from the
//!   stores' statistics).
//! * [`job`] — jobs as clients make them: a scene argument read, a sampling job built.
//! * [`wire`] — the wire forms all producers of worlds share (segment messages, the job's
//!   codec preset).
//!
//! The crate knows no physics: it depends on the wire types, the key builders and the codec's
//! presets only, so the store and the query coordinator use it as well as the workers.
//!
//! A kind of worker, in full (this one records a single empty segment per world):
//!
//! ```
//! use mwb_node::{WorkerKind, WorldTask, SegmentBody, segment_message};
//! use mwb_proto::v1::{Encoding, Job, JobKind, MotionSegment, Scene, WorldDone};
//! use std::ops::ControlFlow;
//!
//! struct Empty;
//!
//! #[derive(Debug, thiserror::Error)]
//! #[error("stopped by the caller")]
//! struct Stopped;
//!
//! impl WorkerKind for Empty {
//!     const ROLE: &'static str = "sampler";
//!     const GIVE_UP_AFTER: u32 = 1;
//!     type Scene = String;
//!     type SceneError = std::convert::Infallible;
//!     type WorldError = Stopped;
//!
//!     fn takes(kind: JobKind) -> bool {
//!         kind == JobKind::Sample
//!     }
//!     fn prepare(&self, _job: &Job, scene: &Scene) -> Result<String, Self::SceneError> {
//!         Ok(scene.name.clone())
//!     }
//!     fn run(
//!         &self,
//!         w: &WorldTask<'_>,
//!         _scene: &String,
//!         emit: &mut dyn FnMut(MotionSegment) -> ControlFlow<()>,
//!     ) -> Result<WorldDone, Stopped> {
//!         let body = SegmentBody {
//!             bodies: Vec::new(),
//!             seq: 0,
//!             first_frame: 0,
//!             frame_count: 1,
//!             body_count: 0,
//!             encoding: Encoding::SplineV1,
//!             payload: Vec::new(),
//!         };
//!         if emit(segment_message(&w.job.id, w.node, w.counter, w.seed, body)).is_break() {
//!             return Err(Stopped);
//!         }
//!         Ok(WorldDone { seed: w.seed, frame_count: 1, segment_count: 1, ..Default::default() })
//!     }
//!     fn stopped(_: &Stopped) -> bool {
//!         true
//!     }
//!     fn provenance(&self) -> String {
//!         "empty-worlds".into()
//!     }
//! }
//! // `mwb_node::run_workers(session, WorkerConfig::default(), Empty).await` starts it.
//! ```

mod board;
pub mod bus;
pub mod job;
pub mod room;
pub mod wire;
pub mod worker;

pub use bus::{Node, NodeError, cpu_time};
pub use job::{JobError, load_scene, sample_job};
pub use wire::{SegmentBody, codec_quality, segment_message, world_digest};
pub use worker::{WorkerConfig, WorkerHandle, WorkerKind, WorldTask, run_workers};
