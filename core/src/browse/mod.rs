//! §4.4 interactive browsing, the pure-logic half: screen-space constraints, the per-object path
//! index, constraint bitsets with undo/redo, and ranking metrics. No I/O, no async; node-store
//! and node-query wrap these types with the bus.
//!
//! The flow of one query (DESIGN.md "Store and queries"):
//!
//! 1. The viewer turns a rectangle drawn on screen into a world-space [`Frustum`] with
//!    [`Camera::frustum`]; §4.4.1 draws queries in screen space because it is fast for the user,
//!    and a screen box seen from a pinhole camera is a frustum in the world.
//! 2. A [`Constraint`] pairs the frustum with a [`Polarity`] (passes through / never passes
//!    through), the objects it applies to ("any of these", or with [`Quantifier::All`] "every
//!    one of these") and an optional [`TimeWindow`], or asks about the final pose only
//!    ([`Scope::FinalPose`]). A world that has ended holds its final pose for ever, so windows
//!    past its end see where its bodies came to rest.
//! 3. Each store evaluates it against every world's [`PathTree`]s (an OBB tree of depth ≤ 3 over
//!    the low-resolution centre-of-mass polyline, §4.4.2), inflated so that no world whose true
//!    path enters the frustum is ever missed, and records the answer in a [`WorldSet`] bitset.
//! 4. A [`ConstraintSet`] keeps one bitset per live constraint; the result is their AND, so
//!    removing any constraint (undo, or click-to-remove) re-evaluates no geometry (§4.4.2).
//! 5. Survivors are ordered with [`top_k`] by a per-object metric ([`ObjectMetrics`], computed
//!    once at ingest, §4.4.3) summed or maxed over chosen objects, or by the number of
//!    constraints each world satisfies.
//!
//! ```
//! use mwb_core::browse::{
//!     Camera, Constraint, ConstraintId, ConstraintSet, Intrinsics, PathTree, Polarity,
//!     Polyline, Quantifier, Scope, ScreenRect, Viewport,
//! };
//!
//! // A camera at z = 10 looking down −z at the origin, a box around the middle of the screen.
//! let camera = Camera {
//!     position: [0.0, 0.0, 10.0],
//!     rotation: [0.0, 0.0, 0.0, 1.0],
//!     intrinsics: Intrinsics::VerticalFov { fov_y_rad: 1.0 },
//!     viewport: Viewport { width: 640, height: 480 },
//!     near: 0.1,
//!     far: 100.0,
//! };
//! let rect = ScreenRect { x0: 300.0, y0: 220.0, x1: 340.0, y1: 260.0 };
//! let frustum = camera.frustum(&rect)?;
//!
//! // World 0's object 0 flies through the origin; world 1's passes 5 m to the side.
//! let through = PathTree::build(Polyline::new(
//!     vec![0.0, 1.0],
//!     vec![[-3.0, 0.0, 0.0], [3.0, 0.0, 0.0]],
//! )?);
//! let beside = PathTree::build(Polyline::new(
//!     vec![0.0, 1.0],
//!     vec![[-3.0, 5.0, 0.0], [3.0, 5.0, 0.0]],
//! )?);
//! let worlds = [through, beside];
//!
//! let constraint = Constraint {
//!     id: ConstraintId(1),
//!     polarity: Polarity::Positive,
//!     frustum,
//!     objects: vec![0],
//!     quantifier: Quantifier::Any,
//!     window: None,
//!     scope: Scope::Motion,
//! };
//! let mut session = ConstraintSet::new();
//! session.on_new_world(0, |_, _| unreachable!("no constraints yet"));
//! session.on_new_world(1, |_, _| unreachable!("no constraints yet"));
//! // The radius is the codec's e_max plus the low-res path's deviation (here: exact paths).
//! session.add(constraint, |c, world| {
//!     c.evaluate(|_object| worlds.get(world as usize).map(|tree| (tree, 0.0)))
//! })?;
//! assert_eq!(session.result().iter().collect::<Vec<_>>(), vec![0]);
//! session.undo(|_, _| unreachable!("no new worlds"));
//! assert_eq!(session.result().len(), 2);
//! # Ok::<(), mwb_core::browse::BrowseError>(())
//! ```

pub mod api;
mod bitset;
mod bodies;
mod constraint;
mod frustum;
mod geom;
mod metrics;
mod path;
pub mod sample;
mod session;

pub use bitset::{WorldSet, WorldSetIter};
pub use bodies::{ObjectsError, object_label, resolve_objects, split_items};
pub use constraint::{Constraint, ConstraintId, Polarity, Quantifier, Scope, TimeWindow};
pub use frustum::{
    ALL_PLANES, Camera, DEFAULT_FAR_M, DEFAULT_NEAR_M, Frustum, Intrinsics, Plane, Projection,
    ProjectionMatrix, RegionCache, ScreenRect, Viewport,
};
pub use geom::{Quat, Vec3, quat_angle_between};
pub use metrics::{
    Aggregate, Metric, MetricValues, ObjectMetrics, Order, PackedMetrics, RankKey, Ranked,
    RestThresholds, Track, WorldMetric, WorldMetrics, merge_top_k, score, top_k, top_k_counted,
};
pub use path::{
    MAX_TREE_DEPTH, MIN_SPLIT_SEGMENTS, Obb, PathTree, Polyline, rest_entry, segment_entry,
};
pub use session::ConstraintSet;

use thiserror::Error;

/// What can be wrong with the input to the browsing logic. Every variant names the field.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum BrowseError {
    #[error("{field}: expected a finite number, found {value}")]
    NonFinite { field: &'static str, value: f64 },
    #[error("{field}: expected {expected}, found {value}")]
    OutOfRange {
        field: &'static str,
        value: f64,
        expected: &'static str,
    },
    #[error("{field}: must not be the zero vector")]
    ZeroVector { field: &'static str },
    #[error("screen rectangle is empty: {width} × {height} px")]
    EmptyRect { width: f64, height: f64 },
    #[error(
        "{field}: the screen rectangle lies entirely outside the {width} × {height} px viewport \
         (pixels from the top-left corner, x right, y down; {field} = {value})"
    )]
    RectOutsideViewport {
        field: &'static str,
        value: f64,
        width: u32,
        height: u32,
    },
    #[error("{field}: cannot be combined with {with}")]
    Conflict {
        field: &'static str,
        with: &'static str,
    },
    #[error("{field}: expected {expected} entries, found {found}")]
    LengthMismatch {
        field: &'static str,
        expected: usize,
        found: usize,
    },
    #[error("{field}: must not be empty")]
    Empty { field: &'static str },
    #[error("{field}: times must increase strictly, but t[{at}] = {value} does not")]
    TimesNotIncreasing {
        field: &'static str,
        at: usize,
        value: f64,
    },
    #[error("time window: start {start} is after end {end}")]
    InvertedWindow { start: f64, end: f64 },
    #[error("constraint {0} is already live")]
    DuplicateConstraint(u64),
    #[error("no live constraint with id {0}")]
    UnknownConstraint(u64),
}

/// `Ok(value)` if finite, else the error naming `field`.
pub(crate) fn finite(field: &'static str, value: f64) -> Result<f64, BrowseError> {
    if value.is_finite() {
        Ok(value)
    } else {
        Err(BrowseError::NonFinite { field, value })
    }
}
