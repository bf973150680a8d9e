//! `mwb-reverse`: the velocity-level LCP time-stepper of node-reverse (Twigg and James, SIGGRAPH 2008; ch. 3 and ch. 5),
//! stepping rigid bodies forward *and* backward in time.
//!
//! Everything but [`node`] is pure computation, with no I/O and no async:
//!
//! * [`World`] ([`world`]): dynamic [`Body`]s (box, sphere, capsule, cylinder, convex hull),
//!   [`StaticBody`]s (plane, box, triangle mesh), [`Joint`]s, gravity and [`StepParams`]
//!   (restitution cutoff `ε`, rest threshold `δ`, prediction distance, joint Baumgarte factor,
//!   LCP options).
//! * [`contact`]: parry3d contact manifolds kept per pair across steps, the contact Jacobian
//!   (normal + two tangents, one aligned with the slip) and islands (one LCP per connected
//!   component of the graph of contacts and joints).
//! * [`joint`]: spherical, revolute and fixed joints (§5.3.4) as equality rows of the same LCP
//!   as the contacts, with a Baumgarte term on their position error whose sign is reversed when
//!   stepping backward.
//! * [`step`]: the forward Stewart–Trinkle / Anitescu–Potra step (§3.3–3.6):
//!   [`World::step_forward`], and [`World::step_forward_with`] to replay a given contact set.
//! * [`backward`]: the backward step of §5.2 (Figure 5.5): [`World::step_backward`], whose
//!   [`BackwardReport`] carries the contact set, Jacobian directions and impulses, so that a
//!   forward replay can check it, and the forward-LCP residual of its impulses.
//! * [`lcp`]: a pivoting solver for the bounded mixed LCP `w = A x + b` of §3.4–3.7, with
//!   normal rows (`x ≥ 0`), equality rows (joints), constant bounds, and friction rows whose
//!   bounds `±μ x_normal` follow their normal impulse *inside the same LCP* (the coupled model of
//!   §3.6.1, not ODE's two-phase approximation). Per-row goal velocities (restitution, the
//!   backward stepper's targets) go into `b`.
//! * [`qr`]: the dense QR factorisation with Givens-rotation updates (§3.7.1) that the solver
//!   keeps of its active-set matrix as rows enter and leave the clamped set.
//!
//! * [`broad_phase`]: sweep and prune over bounding boxes (half-spaces tested per body), so a
//!   scene of thousands of bodies costs `O(n log n)` per step before the narrow phase; bodies
//!   without contacts form no island and cost no LCP.
//! * [`chain`]: the contact-count Markov chain of §5.3.6, learned per scene from forward runs.
//! * [`run`]: backward runs with seeded free choices, the §5.3 heuristics (reverse damping,
//!   rattling, stacking, user hints) and per-world plausibility measurements
//!   ([`BackwardRunReport`]); mixed runs from an intermediate frame (§5.4.4).
//! * [`plausible`]: the stated plausibility test of a world (no body moves faster than a fall
//!   from the highest point it reaches could make it), computed for every backward and mixed
//!   run ([`Plausibility`]).
//! * [`scene`]: the ordinary scene format read as a final state, and `scenes/reverse/`.
//! * [`validate`]: bad input caught before a run — overlapping bodies and violated joints are
//!   refused, a body at rest in mid-air is warned about, each by name.
//! * [`settings_toml`]: a reverse scene's optional `[reverse]` table: backward or mixed run,
//!   per-body user hints by body name.
//! * [`bench`]: the numbers of `mwb bench reverse`.
//! * [`sample`]: one backward (or mixed) world as a stored world — time-reversed so that
//!   playback runs forward, cut into self-contained codec segments, with the per-body summary
//!   (impacts, rest) of the world as played forward and its plausibility numbers. Pure.
//! * [`node`]: the bus node around it: takes `JOB_KIND_REVERSE` jobs and publishes their
//!   worlds exactly as a forward sampler publishes its own (the only part with I/O).
//!
//! Round bodies (balls, capsules, cylinders) get rolling-friction rows (5.15)–(5.18), bounded by
//! [`Body::rolling_resistance`] times the normal impulse, forward and backward.
//!
//! Bodies joined by a joint do not collide with each other (their contacts would repeat the
//! joint rows). Joint rows are always active in the pivoting solver; an island whose active
//! contact rows are redundant with them (several boxes, four coplanar corners each, settling
//! while chained) can still come back `Degenerate` (flagged in the report, never a panic).
//!
//! Not in this round: any position correction of penetration (as in the papers, contact
//! conditions are on velocities; only joints have a Baumgarte term), joint limits and motors,
//! and the §5.3.4 heuristics for articulated bodies (restitution 1 along a jointed chain).
//!
//! # Example: a backward step and its forward check (§5.2)
//!
//! A box slides along a plane at 1 m/s. One step backward gives the state `Δt` earlier (faster:
//! friction was slowing it) and the impulses; a forward step from there with the same contact
//! set gives back the state we started from.
//!
//! ```
//! use mwb_reverse::{BackwardChoices, Body, Material, StaticBody, World};
//! use nalgebra::{UnitQuaternion, Vector3};
//!
//! # fn main() -> Result<(), mwb_reverse::BodyError> {
//! let mat = Material { friction: 0.5, restitution: 0.3 };
//! let mut world = World::new(); // gravity (0, 0, −9.81)
//! world.add_static(StaticBody::plane(Vector3::z(), 0.0)?.with_material(mat));
//! world.add_body(
//!     Body::cuboid(Vector3::new(0.5, 0.5, 0.5), 1.0)?
//!         .with_material(mat)
//!         .at(Vector3::new(0.0, 0.0, 0.5), UnitQuaternion::identity())
//!         .moving(Vector3::new(1.0, 0.0, 0.0), Vector3::zeros()),
//! );
//! let dt = 1.0 / 240.0;
//! let now = world.clone();
//!
//! let back = world.step_backward(dt, &BackwardChoices::default());
//! assert!(back.all_solved());
//! assert!(back.forward_residual < 1e-12); // the impulses solve the forward LCP
//! let earlier_speed = world.bodies[0].linvel.x;
//! assert!((earlier_speed - (1.0 + 0.5 * 9.81 * dt)).abs() < 1e-9);
//!
//! let mut replay = world.clone();
//! let fwd = replay.step_forward_with(&back.contacts, dt);
//! assert!(fwd.all_solved());
//! assert!((replay.bodies[0].linvel - now.bodies[0].linvel).norm() < 1e-12);
//! assert!((replay.bodies[0].position - now.bodies[0].position).norm() < 1e-12);
//!
//! // Ordinary forward stepping detects contacts itself.
//! let report = world.step_forward(dt);
//! assert_eq!(report.contacts.len(), 4);
//! # Ok(())
//! # }
//! ```
//!
//! # Example: a box resting on the ground, with friction
//!
//! One contact point under the centre of a unit-mass box (to keep it short): a normal row and two
//! friction rows. `A = Δt J M⁻¹ Jᵀ` and `b` is the contact velocity before contact impulses
//! (3.34)–(3.35); here the box slides along x at 2 m/s and falls at 0.1 m/s.
//!
//! ```
//! use mwb_reverse::lcp::{self, LcpOptions, LcpProblem, LcpStatus, RowKind};
//! use nalgebra::{DMatrix, DVector};
//!
//! # fn main() -> Result<(), mwb_reverse::LcpError> {
//! let mu = 0.4;
//! let mut problem = LcpProblem::new(
//!     DMatrix::identity(3, 3),                // J M⁻¹ Jᵀ for a point mass of 1 kg, impulses
//!     DVector::from_vec(vec![-0.1, 2.0, 0.0]), // normal, tangent u, tangent w velocities
//!     vec![
//!         RowKind::Normal,
//!         RowKind::Friction { normal: 0, mu },
//!         RowKind::Friction { normal: 0, mu },
//!     ],
//! )?;
//! // A goal velocity (restitution (3.20), or a backward-step target (5.5)) just shifts b (3.37):
//! // ask for the contact to separate at 0.05 m/s after the step.
//! problem.subtract_goal(&DVector::from_vec(vec![0.05, 0.0, 0.0]))?;
//!
//! let solution = lcp::solve(&problem, &LcpOptions::default())?;
//! assert_eq!(solution.status, LcpStatus::Solved);
//! let (normal, friction) = (solution.x[0], solution.x[1]);
//! assert!((normal - 0.15).abs() < 1e-12);            // stops the fall, adds the goal speed
//! assert!((friction + mu * normal).abs() < 1e-12);   // sliding: friction is maximal, opposing
//! assert!(solution.w[1] > 0.0);                      // … and the box still slides afterwards
//! assert!(solution.residual < 1e-12);
//!
//! // Conflicting goals (Figure 5.4) do not hang or panic: they come back flagged.
//! let squeezed = LcpProblem::new(
//!     DMatrix::from_row_slice(2, 2, &[1.0, -1.0, -1.0, 1.0]),
//!     DVector::from_vec(vec![-1.0, -1.0]),
//!     vec![RowKind::Normal; 2],
//! )?;
//! let flagged = lcp::solve(&squeezed, &LcpOptions::default())?;
//! assert_eq!(flagged.status, LcpStatus::Infeasible);
//! assert!(!flagged.status.is_solution());
//! # Ok(())
//! # }
//! ```
//!
//! # Example: updating a QR factorisation
//!
//! ```
//! use mwb_reverse::qr::Qr;
//! use nalgebra::{DMatrix, DVector};
//!
//! # fn main() -> Result<(), mwb_reverse::QrError> {
//! let a = DMatrix::from_row_slice(2, 2, &[4.0, 1.0, 1.0, 3.0]);
//! let mut qr = Qr::new(&a)?;
//! // Grow to 3 × 3 by a trailing column and row, O(n²) each (3.42).
//! qr.push_column(&DVector::from_vec(vec![0.5, 0.0]))?;
//! qr.push_row(&DVector::from_vec(vec![0.0, 0.5, 2.0]))?;
//! let x = qr.solve(&DVector::from_vec(vec![1.0, 2.0, 3.0]))?;
//! let grown = DMatrix::from_row_slice(3, 3, &[4.0, 1.0, 0.5, 1.0, 3.0, 0.0, 0.0, 0.5, 2.0]);
//! assert!((&grown * &x - DVector::from_vec(vec![1.0, 2.0, 3.0])).amax() < 1e-12);
//! // Remove a row/column pair from the middle (3.43) and replace a column (3.44).
//! qr.remove_row(1)?;
//! qr.remove_column(1)?;
//! qr.replace_column(0, &DVector::from_vec(vec![1.0, 1.0]))?;
//! assert!((qr.reconstruct() - DMatrix::from_row_slice(2, 2, &[1.0, 0.5, 1.0, 2.0])).amax() < 1e-12);
//! // A singular matrix is reported, not divided by.
//! qr.replace_column(1, &DVector::from_vec(vec![2.0, 2.0]))?;
//! assert!(qr.solve(&DVector::from_vec(vec![1.0, 0.0])).is_err());
//! # Ok(())
//! # }
//! ```

pub mod backward;
pub mod bench;
pub mod body;
pub mod broad_phase;
pub mod chain;
pub mod contact;
pub mod joint;
pub mod lcp;
pub mod node;
pub mod plausible;
pub mod qr;
pub mod run;
pub mod sample;
pub mod scene;
pub mod settings_toml;
pub mod step;
pub mod validate;
pub mod world;

pub use backward::{
    ApexFinish, BackwardChoices, BackwardReport, BodyHint, ContactChoice, FrictionCase, LiftPlan,
    NormalCase, free_to_bounce,
};
pub use bench::{BenchError, BenchOptions, LoremBench, ReverseBench, ScenePlausibility, bench};
pub use body::{Body, Material, StaticBody};
pub use chain::{ChainLearning, ContactChain};
pub use contact::{Contact, ContactSet, Island, Partner};
pub use joint::{Joint, JointError, JointKind, JointRow, JointType};
pub use node::{Backward, ReverseConfig, ReverseHandle, ReverseNodeError, run_reverse};
pub use plausible::{
    MAX_ENERGY_GROWTH_M, MAX_PENETRATION_M, PLAUSIBILITY_ALLOWANCE_M, Plausibility,
    PlausibilityLimits, PlausibilityMeter,
};
pub use run::{
    BackwardRun, BackwardRunReport, Frame, Heuristics, HintMotion, MixedRun, Pose, ReverseSettings,
    Sampling, UserHint, run_backward, run_mixed,
};
pub use sample::{ReverseScene, ReverseWorldSummary, SampleError, sample_world};
pub use scene::{SceneConvertError, world_from_scene};
pub use settings_toml::{ReverseTable, RunMode, parse_reverse_scene};
pub use world::{ContactImpulse, IslandSolve, StepParams, StepReport, World};

/// Errors building a [`Body`] or [`StaticBody`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BodyError {
    /// A parameter that must be finite and positive was not.
    #[error("{what} must be finite and > 0, got {value}")]
    InvalidParameter {
        /// Which parameter.
        what: &'static str,
        /// The value given.
        value: f64,
    },
    /// The inertia tensor could not be inverted.
    #[error("the inertia tensor is singular or not finite")]
    SingularInertia,
    /// The points of a convex hull span no volume.
    #[error("the convex hull of the points is degenerate")]
    DegenerateHull,
    /// parry refused the triangle mesh.
    #[error("invalid triangle mesh")]
    InvalidMesh,
}

/// Errors of [`qr::Qr`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum QrError {
    /// A vector had the wrong length for the update or solve.
    #[error("{what} has {found} entries, expected {expected}")]
    DimensionMismatch {
        /// Which argument.
        what: &'static str,
        /// Length required by the factorisation.
        expected: usize,
        /// Length given.
        found: usize,
    },
    /// A row or column index past the end.
    #[error("index {index} is out of range (length {len})")]
    IndexOutOfRange {
        /// Index given.
        index: usize,
        /// Number of valid positions.
        len: usize,
    },
    /// NaN or ±∞ in the input.
    #[error("{what} entry {index} is not finite")]
    NonFinite {
        /// Which argument.
        what: &'static str,
        /// Position (column-major for matrices).
        index: usize,
    },
    /// A diagonal entry of `R` too small to divide by: the matrix is (numerically) singular.
    #[error(
        "rank deficient: |R[{index},{index}]| = {pivot:e} is not above the tolerance {tolerance:e}"
    )]
    RankDeficient {
        /// Diagonal position.
        index: usize,
        /// The entry found.
        pivot: f64,
        /// The tolerance it failed.
        tolerance: f64,
    },
    /// A square matrix was required.
    #[error("matrix is {rows}×{cols}, a square matrix is required")]
    NotSquare {
        /// Rows.
        rows: usize,
        /// Columns.
        cols: usize,
    },
    /// Fewer rows than columns: `A x = b` has no unique solution.
    #[error("matrix is {rows}×{cols}: fewer rows than columns, the solve is underdetermined")]
    Underdetermined {
        /// Rows.
        rows: usize,
        /// Columns.
        cols: usize,
    },
}

/// Errors of [`lcp::solve`] and [`lcp::LcpProblem`]: invalid input only; numerical trouble is a
/// [`lcp::LcpStatus`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LcpError {
    /// `A` is not `n × n` for `n = b.len()`.
    #[error("A is {rows}×{cols}, expected {n}×{n} to match b")]
    Shape {
        /// Rows of `A`.
        rows: usize,
        /// Columns of `A`.
        cols: usize,
        /// Length of `b`.
        n: usize,
    },
    /// A vector or list had the wrong length.
    #[error("{what} has {found} entries, expected {expected}")]
    DimensionMismatch {
        /// Which argument.
        what: &'static str,
        /// Required length.
        expected: usize,
        /// Given length.
        found: usize,
    },
    /// NaN or ±∞ in `A`, `b` or a goal.
    #[error("{what}[{row},{col}] = {value} is not finite")]
    NonFinite {
        /// Which argument.
        what: &'static str,
        /// Row.
        row: usize,
        /// Column (0 for vectors).
        col: usize,
        /// The value found.
        value: f64,
    },
    /// A friction row with a bad `μ` or a coupling to a row that is not a normal row.
    #[error("friction row {row} (coupled to row {normal}): {reason}")]
    InvalidFriction {
        /// The friction row.
        row: usize,
        /// The row it names as its normal.
        normal: usize,
        /// What is wrong.
        reason: &'static str,
    },
    /// Constant bounds with `lo > hi`, NaN, or no finite room.
    #[error("row {row} has invalid bounds [{lo}, {hi}]")]
    InvalidBounds {
        /// The row.
        row: usize,
        /// Lower bound given.
        lo: f64,
        /// Upper bound given.
        hi: f64,
    },
    /// Tolerances must be finite and positive.
    #[error("LcpOptions tolerances must be finite and > 0")]
    InvalidOptions,
}
