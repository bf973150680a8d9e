//! A pivoting solver for the bounded, non-symmetric mixed LCP of the velocity-level stepper
//! (§3.4–3.7).
//!
//! # The problem
//!
//! Find impulses `x` and post-step velocities `w = A x + b` such that for every row `i`,
//! `lo_i ≤ x_i ≤ hi_i` and
//!
//! * `x_i = lo_i` ⇒ `w_i ≥ 0`,
//! * `x_i = hi_i` ⇒ `w_i ≤ 0`,
//! * `lo_i < x_i < hi_i` ⇒ `w_i = 0`,
//!
//! which is the authors' (3.31)–(3.32) with its bounds `f⁻`, `f⁺`. The bounds depend on the row's
//! [`RowKind`]: a normal row is `[0, ∞)` (3.19); an equality row (a joint) is unbounded; a
//! friction row is `[−μ x_n, μ x_n]` where `x_n` is the impulse of *its own normal row in the same
//! LCP* — the coupled model the authors needed for backward simulation (§3.6.1), not ODE's
//! two-phase approximation that freezes `μ x_n` from a frictionless solve. (Each friction
//! direction is bounded separately, the box of Figure 3.4 c; the authors reduce its drawbacks by
//! aligning one direction with the slip, which is the stepper's job, not this solver's.)
//!
//! Restitution and the backward stepper's goals (3.20), (3.36), (5.5) are velocity targets; they
//! enter only through `b` (3.37), see [`LcpProblem::subtract_goal`].
//!
//! # The method
//!
//! A principal pivoting method in the style of Baraff/Dantzig and ODE's `dLCP`, which the authors
//! (§3.7) follow: rows are taken one at a time; the row being *driven* moves its impulse
//! monotonically toward its valid region while every row already handled stays valid. Handled rows
//! live in one of three sets (Figure 3.6): *clamped* (`C`, `w = 0`, impulse free inside its
//! bounds), *lower* and *upper* (`S⁻`, `S⁺`, impulse at a bound). Keeping `w_C = 0` while the
//! driven impulse changes by one unit needs the solve (3.40); friction rows at a bound ride on
//! their normal's impulse, which adds their scaled columns to the normal's column, the
//! non-symmetric system (3.41). Each step runs to the first event (a set change), and the set
//! change is applied to the factorisation of that system by the Givens updates of
//! [`crate::qr::Qr`] (§3.7.1): a row/column pair appended or removed when a row enters or leaves
//! `C`, a column replaced when a friction row starts or stops riding on a clamped normal.
//!
//! # Termination and failure
//!
//! The number of pivots is capped ([`LcpOptions::max_pivots`], default `50 n + 10`); a set
//! configuration that repeats without progress is reported as cycling; a driving direction that
//! nothing can stop (no bound, no sign change) means the conditions cannot be met along it and is
//! reported as infeasible (the conflicting goals of Figure 5.4). Because coupled friction makes
//! the active-set matrix lose the P-matrix property that guarantees Dantzig-style progress, the
//! sense of motion after each set change follows the path of valid configurations even when it
//! reverses the driven impulse, and an attempt that still gets stuck is retried with another row
//! order ([`LcpOptions::restarts`]). In every case the solver returns
//! its best effort `x` with an [`LcpStatus`] and the [`complementarity_residual`]; it never
//! panics and never loops without bound. Non-finite input is refused with [`LcpError`].

use std::collections::HashSet;

use nalgebra::{DMatrix, DVector};

use crate::LcpError;
use crate::qr::Qr;

/// What kind of constraint a row is; decides its bounds `[lo, hi]` (§3.7, Figure 3.3 right).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RowKind {
    /// A contact normal: `x ≥ 0` (no pulling), `w ≥ 0` (no approach), complementary (3.19).
    Normal,
    /// A friction direction bounded by `μ` times the impulse of the normal row `normal`:
    /// `−μ x_normal ≤ x ≤ μ x_normal` (3.23), coupled inside the same LCP.
    Friction {
        /// Index of this contact's normal row (must be a [`RowKind::Normal`] row).
        normal: usize,
        /// Friction coefficient `μ ≥ 0`.
        mu: f64,
    },
    /// A bilateral constraint (joint): `w = 0`, `x` unbounded.
    Equality,
    /// Constant bounds `lo ≤ x ≤ hi` (`lo` may be `−∞`, `hi` may be `+∞`, `lo ≤ hi`).
    Bounded {
        /// Lower bound.
        lo: f64,
        /// Upper bound.
        hi: f64,
    },
}

/// `w = A x + b` with one [`RowKind`] per row.
#[derive(Debug, Clone, PartialEq)]
pub struct LcpProblem {
    /// `n × n`; for contact problems `Δt J M⁻¹ Jᵀ` (3.35). May be non-symmetric.
    pub a: DMatrix<f64>,
    /// `n`; the velocity without contact impulses minus any goal velocity (3.35), (3.37).
    pub b: DVector<f64>,
    /// `n` row kinds.
    pub rows: Vec<RowKind>,
}

impl LcpProblem {
    /// Builds and [validates](Self::validate) a problem.
    pub fn new(a: DMatrix<f64>, b: DVector<f64>, rows: Vec<RowKind>) -> Result<Self, LcpError> {
        let p = Self { a, b, rows };
        p.validate()?;
        Ok(p)
    }

    /// Number of rows.
    pub fn len(&self) -> usize {
        self.b.len()
    }

    /// True for a problem without rows.
    pub fn is_empty(&self) -> bool {
        self.b.is_empty()
    }

    /// Checks shapes, finiteness (NaN/∞ in `A` or `b`), friction couplings and bounds.
    pub fn validate(&self) -> Result<(), LcpError> {
        let n = self.b.len();
        if self.a.shape() != (n, n) {
            return Err(LcpError::Shape {
                rows: self.a.nrows(),
                cols: self.a.ncols(),
                n,
            });
        }
        if self.rows.len() != n {
            return Err(LcpError::DimensionMismatch {
                what: "rows",
                expected: n,
                found: self.rows.len(),
            });
        }
        for ((r, c), v) in self.a.iter().enumerate().map(|(k, v)| ((k % n, k / n), v)) {
            if !v.is_finite() {
                return Err(LcpError::NonFinite {
                    what: "A",
                    row: r,
                    col: c,
                    value: *v,
                });
            }
        }
        if let Some(r) = self.b.iter().position(|v| !v.is_finite()) {
            return Err(LcpError::NonFinite {
                what: "b",
                row: r,
                col: 0,
                value: self.b[r],
            });
        }
        for (row, kind) in self.rows.iter().enumerate() {
            match *kind {
                RowKind::Friction { normal, mu } => {
                    if !(mu.is_finite() && mu >= 0.0) {
                        return Err(LcpError::InvalidFriction {
                            row,
                            normal,
                            reason: "μ must be finite and ≥ 0",
                        });
                    }
                    if normal >= n || self.rows[normal] != RowKind::Normal {
                        return Err(LcpError::InvalidFriction {
                            row,
                            normal,
                            reason: "the coupled row must be a Normal row of this problem",
                        });
                    }
                }
                RowKind::Bounded { lo, hi } => {
                    // NaN compares as unordered; equal infinite bounds leave no room.
                    let ordered = matches!(
                        lo.partial_cmp(&hi),
                        Some(std::cmp::Ordering::Less | std::cmp::Ordering::Equal)
                    );
                    if !ordered || lo == f64::INFINITY || hi == f64::NEG_INFINITY {
                        return Err(LcpError::InvalidBounds { row, lo, hi });
                    }
                }
                RowKind::Normal | RowKind::Equality => {}
            }
        }
        Ok(())
    }

    /// Moves per-row goal velocities into `b` (3.37): the solver then drives `w = A x + b − goal`,
    /// i.e. the velocity relative to its goal, to the complementarity conditions. Used for
    /// restitution (3.20) and for the backward stepper's targets (§5.2).
    pub fn subtract_goal(&mut self, goal: &DVector<f64>) -> Result<(), LcpError> {
        if goal.len() != self.b.len() {
            return Err(LcpError::DimensionMismatch {
                what: "goal",
                expected: self.b.len(),
                found: goal.len(),
            });
        }
        if let Some(r) = goal.iter().position(|v| !v.is_finite()) {
            return Err(LcpError::NonFinite {
                what: "goal",
                row: r,
                col: 0,
                value: goal[r],
            });
        }
        self.b -= goal;
        Ok(())
    }

    /// The bounds `(lo_i, hi_i)` of row `i` at impulses `x` (friction bounds follow `x_normal`).
    pub fn bounds(&self, i: usize, x: &DVector<f64>) -> (f64, f64) {
        match self.rows[i] {
            RowKind::Normal => (0.0, f64::INFINITY),
            RowKind::Friction { normal, mu } => (-mu * x[normal], mu * x[normal]),
            RowKind::Equality => (f64::NEG_INFINITY, f64::INFINITY),
            RowKind::Bounded { lo, hi } => (lo, hi),
        }
    }
}

/// Solver settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LcpOptions {
    /// Absolute tolerance on `w` and on distances to bounds, used to classify rows and to accept
    /// the result ([`LcpStatus::Solved`] means residual ≤ this).
    pub tolerance: f64,
    /// Relative (to `max|A_ij|`) size below which a pivot, a diagonal of `R` or a rate of change
    /// counts as zero.
    pub pivot_tolerance: f64,
    /// Maximum number of pivots per attempt; `None` means `50 n + 10`. A single drive (one row
    /// brought to a valid state) is further limited to `2 n + 10` pivots, beyond which it counts
    /// as cycling.
    pub max_pivots: Option<usize>,
    /// How many times to start over with another row order when an attempt ends without a
    /// solution (the best attempt is returned). Total work is at most `(1 + restarts)` times the
    /// pivot cap.
    pub restarts: usize,
}

impl Default for LcpOptions {
    fn default() -> Self {
        Self {
            tolerance: 1e-10,
            pivot_tolerance: 1e-11,
            max_pivots: None,
            restarts: 3,
        }
    }
}

/// How the solve ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum LcpStatus {
    /// All conditions hold to [`LcpOptions::tolerance`].
    Solved,
    /// All conditions hold, but not strictly: some impulse sits on a bound with zero velocity, or
    /// on the way the active-set matrix was singular or a driving rate was zero (e.g. duplicate
    /// contact rows, a box resting on four corners). `x` is valid but may be one of many.
    SolvedDegenerate,
    /// Gave up because the active-set system became singular; best effort.
    Degenerate,
    /// A driving direction could not be stopped by any bound or sign change, so the conditions
    /// cannot all hold (conflicting goals, Figure 5.4); best effort.
    Infeasible,
    /// The pivoting path ended with the driven row at the bound that the sign of its `w`
    /// forbids. Not a proof of infeasibility (the coupled problem is not a P-matrix LCP), just no
    /// way forward found; best effort.
    Blocked,
    /// The same set configuration came back without progress, or one row needed more than
    /// `2 n + 10` pivots; best effort.
    Cycling,
    /// The pivot cap was reached; best effort.
    MaxIterations,
}

impl LcpStatus {
    /// True when the returned `x` satisfies the LCP conditions.
    pub fn is_solution(self) -> bool {
        matches!(self, Self::Solved | Self::SolvedDegenerate)
    }
}

/// Where a row ended up (the sets of Figure 3.6).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum RowState {
    /// Not (successfully) handled; only after a failure.
    Unresolved,
    /// `w = 0`, impulse free between its bounds (`C`).
    Clamped,
    /// Impulse at its lower bound, `w ≥ 0` (`S⁻`).
    Lower,
    /// Impulse at its upper bound, `w ≤ 0` (`S⁺`).
    Upper,
}

/// The solver's answer.
#[derive(Debug, Clone, PartialEq)]
pub struct LcpSolution {
    /// Impulses.
    pub x: DVector<f64>,
    /// `A x + b`.
    pub w: DVector<f64>,
    /// How the solve ended; check [`LcpStatus::is_solution`].
    pub status: LcpStatus,
    /// [`complementarity_residual`] of `x`.
    pub residual: f64,
    /// Number of pivots (steps to an event) taken.
    pub pivots: usize,
    /// How often the active-set factorisation was rebuilt from scratch because the updated one
    /// had drifted or turned singular.
    pub refactorizations: usize,
    /// Final set of every row.
    pub states: Vec<RowState>,
}

/// The natural residual `max_i |x_i − mid(lo_i, x_i − w_i, hi_i)|` with `w = A x + b` and bounds
/// evaluated at `x`: zero exactly when `x` solves the LCP, and otherwise about the size of the
/// largest violation (a bound overshoot, or a `w_i` of the wrong sign or a nonzero `w_i` away
/// from the bounds). NaN in `x` gives NaN.
pub fn complementarity_residual(p: &LcpProblem, x: &DVector<f64>) -> f64 {
    let w = &p.a * x + &p.b;
    let mut worst = 0.0f64;
    for i in 0..p.len() {
        let (lo, hi) = p.bounds(i, x);
        let projected = (x[i] - w[i]).max(lo).min(hi);
        let r = (x[i] - projected).abs();
        // A friction row whose normal went negative has lo > hi; count that as well.
        let r = r.max(lo - hi);
        if r.is_nan() {
            return f64::NAN;
        }
        worst = worst.max(r);
    }
    worst
}

/// Solves the LCP. See the [module docs](self) for the method and the meaning of the result.
///
/// Errors only for invalid input (shapes, NaN/∞, bad couplings); numerical trouble is reported in
/// [`LcpSolution::status`].
pub fn solve(p: &LcpProblem, opts: &LcpOptions) -> Result<LcpSolution, LcpError> {
    p.validate()?;
    if !(opts.tolerance.is_finite()
        && opts.tolerance > 0.0
        && opts.pivot_tolerance.is_finite()
        && opts.pivot_tolerance > 0.0)
    {
        return Err(LcpError::InvalidOptions);
    }
    let mut best: Option<LcpSolution> = None;
    let mut pivots = 0;
    let mut refactorizations = 0;
    for attempt in 0..=opts.restarts {
        let mut solver = Solver::new(p, opts);
        solver.run(&processing_order(p, attempt));
        let sol = solver.finish();
        pivots += sol.pivots;
        refactorizations += sol.refactorizations;
        let better = best.as_ref().is_none_or(|b| sol.residual < b.residual);
        let done = sol.status.is_solution();
        if better {
            best = Some(sol);
        }
        if done {
            break;
        }
    }
    let mut sol = best.expect("at least one attempt");
    sol.pivots = pivots;
    sol.refactorizations = refactorizations;
    Ok(sol)
}

/// The order in which rows are driven. Unbounded rows first (they must end clamped), then normals
/// before the friction rows whose bounds they set, as ODE orders its rows. Attempt 0 takes each
/// group in index order; restarts reverse it, then shuffle it deterministically: the pivoting
/// path depends on the order, and where the coupled problem is not a P-matrix one order can get
/// blocked where another goes through.
fn processing_order(p: &LcpProblem, attempt: usize) -> Vec<usize> {
    let group = |k: &RowKind| match k {
        RowKind::Equality => 0,
        RowKind::Normal => 1,
        RowKind::Bounded { .. } => 2,
        RowKind::Friction { .. } => 3,
    };
    let mut order: Vec<usize> = (0..p.len()).collect();
    match attempt {
        0 => {}
        1 => order.reverse(),
        _ => {
            // SplitMix64 keyed by the attempt: reproducible, no `rand`.
            let mut state = 0x9E37_79B9_7F4A_7C15u64.wrapping_mul(attempt as u64 + 1);
            for i in (1..order.len()).rev() {
                state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
                let mut z = state;
                z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
                z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
                z ^= z >> 31;
                order.swap(i, (z % (i as u64 + 1)) as usize);
            }
        }
    }
    order.sort_by_key(|&i| group(&p.rows[i])); // stable: keeps the within-group order
    order
}

/// A blocking event found by the ratio test.
#[derive(Debug, Clone, Copy)]
enum Event {
    /// The driven row reached a valid state.
    Driven(RowState),
    /// The driven row hit the bound opposite to its `w` sign after a direction flip.
    DrivenStuck,
    /// Row `j` moves to `state`.
    Switch(usize, RowState),
}

struct Solver<'p> {
    p: &'p LcpProblem,
    n: usize,
    x: DVector<f64>,
    w: DVector<f64>,
    state: Vec<RowState>,
    /// Rows in `C`, in the order of the rows/columns of the factorised matrix.
    clamped: Vec<usize>,
    qr: Qr,
    /// Friction rows of each normal row.
    children: Vec<Vec<usize>>,
    tol: f64,
    /// `max|A_ij|`.
    scale: f64,
    /// `pivot_tolerance`: zero for rates of impulses per unit of the driven impulse.
    rel: f64,
    /// Absolute zero for pivots and rates of `w`: `pivot_tolerance · max|A|`.
    zero: f64,
    pivots: usize,
    max_pivots: usize,
    refactors: usize,
    degenerate: bool,
    failure: Option<LcpStatus>,
    /// Rows that could not enter `C` during the current drive (rank deficiency); ignored by the
    /// ratio test until the drive ends.
    frozen: Vec<bool>,
}

impl<'p> Solver<'p> {
    fn new(p: &'p LcpProblem, opts: &LcpOptions) -> Self {
        let n = p.len();
        let mut children = vec![Vec::new(); n];
        for (i, kind) in p.rows.iter().enumerate() {
            if let RowKind::Friction { normal, .. } = *kind {
                children[normal].push(i);
            }
        }
        // Start every impulse at the point of its bounds nearest 0 (0 for all physical rows).
        let zeros = DVector::zeros(n);
        let x = DVector::from_fn(n, |i, _| {
            let (lo, hi) = p.bounds(i, &zeros);
            0.0f64.max(lo).min(hi)
        });
        let w = &p.a * &x + &p.b;
        let scale = if n == 0 {
            1.0
        } else {
            p.a.amax().max(f64::MIN_POSITIVE)
        };
        Self {
            p,
            n,
            x,
            w,
            state: vec![RowState::Unresolved; n],
            clamped: Vec::new(),
            qr: Qr::empty(),
            children,
            tol: opts.tolerance,
            scale,
            rel: opts.pivot_tolerance,
            zero: opts.pivot_tolerance * scale,
            pivots: 0,
            max_pivots: opts.max_pivots.unwrap_or(50 * n + 10),
            refactors: 0,
            degenerate: false,
            failure: None,
            frozen: vec![false; n],
        }
    }

    fn run(&mut self, order: &[usize]) {
        for &d in order {
            if matches!(
                self.failure,
                Some(LcpStatus::MaxIterations | LcpStatus::Degenerate)
            ) {
                break;
            }
            self.drive(d);
        }
        self.polish();
    }

    fn finish(self) -> LcpSolution {
        let residual = complementarity_residual(self.p, &self.x);
        let ok = residual <= self.tol;
        let w = &self.p.a * &self.x + &self.p.b;
        // Strict complementarity fails where an impulse sits on a bound with zero velocity: the
        // row could be clamped or at the bound alike, the classic sign of a non-unique solution
        // (duplicate contacts, four corners of a resting box).
        let weak = (0..self.n).any(|i| {
            let (lo, hi) = self.bounds(i);
            let on_bound = (self.x[i] - lo).abs() <= self.tol || (hi - self.x[i]).abs() <= self.tol;
            on_bound && w[i].abs() <= self.tol
        });
        let status = match (ok, self.degenerate || weak, self.failure) {
            (true, false, None) => LcpStatus::Solved,
            (true, _, _) => LcpStatus::SolvedDegenerate,
            (false, _, Some(f)) => f,
            (false, _, None) => LcpStatus::Degenerate,
        };
        LcpSolution {
            w,
            x: self.x,
            status,
            residual,
            pivots: self.pivots,
            refactorizations: self.refactors,
            states: self.state,
        }
    }

    fn fail(&mut self, status: LcpStatus) {
        // Keep the first reason; later trouble is usually a consequence.
        self.failure.get_or_insert(status);
    }

    fn bounds(&self, i: usize) -> (f64, f64) {
        self.p.bounds(i, &self.x)
    }

    /// `Some((normal, ±μ))` when friction row `j` rides on its normal's impulse (it is at a bound).
    fn coupling(&self, j: usize) -> Option<(usize, f64)> {
        match (self.p.rows[j], self.state[j]) {
            (RowKind::Friction { normal, mu }, RowState::Upper) => Some((normal, mu)),
            (RowKind::Friction { normal, mu }, RowState::Lower) => Some((normal, -mu)),
            _ => None,
        }
    }

    /// Entry `(r, k)` of the effective matrix of (3.41): column `k` plus the columns of the
    /// friction rows riding on `k`, scaled by ±μ.
    fn effective(&self, r: usize, k: usize) -> f64 {
        let mut v = self.p.a[(r, k)];
        for &j in &self.children[k] {
            if let Some((_, f)) = self.coupling(j) {
                v += f * self.p.a[(r, j)];
            }
        }
        v
    }

    fn effective_column(&self, k: usize) -> DVector<f64> {
        DVector::from_iterator(
            self.clamped.len(),
            self.clamped.iter().map(|&r| self.effective(r, k)),
        )
    }

    fn effective_row(&self, r: usize) -> DVector<f64> {
        DVector::from_iterator(
            self.clamped.len(),
            self.clamped.iter().map(|&k| self.effective(r, k)),
        )
    }

    fn clamped_matrix(&self) -> DMatrix<f64> {
        let k = self.clamped.len();
        DMatrix::from_fn(k, k, |r, c| {
            self.effective(self.clamped[r], self.clamped[c])
        })
    }

    /// Rebuilds the factorisation from scratch. False if the data went non-finite.
    fn refactor(&mut self) -> bool {
        self.refactors += 1;
        match Qr::new(&self.clamped_matrix()) {
            Ok(qr) => {
                self.qr = qr;
                true
            }
            Err(_) => {
                self.fail(LcpStatus::Degenerate);
                false
            }
        }
    }

    /// Appends `j` to `C` (row and column pair, (3.42)). False, with `C` unchanged, when the
    /// enlarged matrix would be singular.
    fn enter_clamped(&mut self, j: usize) -> bool {
        let col = self.effective_column(j);
        let pushed = self.qr.push_column(&col).is_ok() && {
            self.clamped.push(j);
            let row = self.effective_row(j);
            self.qr.push_row(&row).is_ok()
        };
        if pushed && self.qr.min_abs_diagonal() > self.zero {
            return true;
        }
        // Undo the append with the same updates (3.43); rebuild only if that fails.
        let undone = if self.clamped.last() == Some(&j) {
            self.clamped.pop();
            let k = self.clamped.len();
            pushed && self.qr.remove_row(k).is_ok() && self.qr.remove_column(k).is_ok()
        } else {
            false
        };
        self.degenerate = true;
        if !undone {
            self.refactor();
        }
        false
    }

    /// Removes `j` from `C` (3.43).
    fn leave_clamped(&mut self, j: usize) {
        if let Some(pos) = self.clamped.iter().position(|&c| c == j) {
            self.clamped.remove(pos);
            let ok = self.qr.remove_row(pos).is_ok() && self.qr.remove_column(pos).is_ok();
            if !ok {
                self.refactor();
            }
        }
    }

    /// The column of a clamped normal changes when one of its friction rows starts or stops
    /// riding on it (3.44).
    fn refresh_column(&mut self, k: usize) {
        if let Some(pos) = self.clamped.iter().position(|&c| c == k) {
            let col = self.effective_column(k);
            if self.qr.replace_column(pos, &col).is_err() {
                self.refactor();
            }
        }
    }

    /// Moves row `j` to `new`, updating the factorisation. False (and `j` back in `old`) if `j`
    /// could not enter `C`.
    fn set_state(&mut self, j: usize, new: RowState) -> bool {
        let old = self.state[j];
        if old == new {
            return true;
        }
        if old == RowState::Clamped {
            self.leave_clamped(j);
        }
        self.state[j] = new;
        let normal = match self.p.rows[j] {
            RowKind::Friction { normal, .. } => Some(normal),
            _ => None,
        };
        if let Some(k) = normal {
            self.refresh_column(k);
        }
        if new == RowState::Clamped && !self.enter_clamped(j) {
            self.state[j] = old;
            if let Some(k) = normal {
                self.refresh_column(k);
            }
            return false;
        }
        true
    }

    /// Puts every impulse at a bound exactly on it (normals first: friction bounds follow them)
    /// and recomputes `w`, so that rounding does not accumulate over pivots.
    fn snap(&mut self) {
        for pass in 0..2 {
            for i in 0..self.n {
                let is_friction = matches!(self.p.rows[i], RowKind::Friction { .. });
                if is_friction != (pass == 1) {
                    continue;
                }
                let (lo, hi) = self.bounds(i);
                match self.state[i] {
                    RowState::Lower if lo.is_finite() => self.x[i] = lo,
                    RowState::Upper if hi.is_finite() => self.x[i] = hi,
                    _ => {}
                }
            }
        }
        self.w = &self.p.a * &self.x + &self.p.b;
    }

    /// The change of `x` and `w` per unit increase of `x_d` that keeps `w_C = 0` and keeps riding
    /// friction rows on their bounds: (3.40)/(3.41) solved with the updated QR.
    fn direction(&mut self, d: usize) -> Option<(DVector<f64>, DVector<f64>)> {
        for attempt in 0..2 {
            let rhs = -self.effective_column(d);
            let y = if self.clamped.is_empty() {
                DVector::zeros(0)
            } else {
                match self.qr.solve_with_tolerance(&rhs, self.zero) {
                    Ok(y) => y,
                    Err(_) if attempt == 0 => {
                        if !self.refactor() {
                            return None;
                        }
                        continue;
                    }
                    Err(_) => return None,
                }
            };
            let mut dx = DVector::zeros(self.n);
            dx[d] = 1.0;
            for (pos, &c) in self.clamped.iter().enumerate() {
                dx[c] = y[pos];
            }
            let movers: Vec<usize> = self.clamped.iter().copied().chain([d]).collect();
            for k in movers {
                for &j in &self.children[k] {
                    if let Some((_, f)) = self.coupling(j) {
                        dx[j] += f * dx[k];
                    }
                }
            }
            let dw = &self.p.a * &dx;
            // The updated factors should keep w_C fixed; if rounding says otherwise, rebuild.
            let drift = self
                .clamped
                .iter()
                .map(|&c| dw[c].abs())
                .fold(0.0, f64::max);
            if drift > 1e-9 * self.scale * (1.0 + dx.amax()) && attempt == 0 {
                if !self.refactor() {
                    return None;
                }
                continue;
            }
            return Some((dx, dw));
        }
        None
    }

    /// Drives row `d` into a valid state while keeping every handled row valid.
    fn drive(&mut self, d: usize) {
        self.frozen.iter_mut().for_each(|f| *f = false);
        let mut seen: HashSet<Vec<RowState>> = HashSet::new();
        let mut last_switch: Option<(usize, RowState, RowState)> = None;
        let drive_start = self.pivots;
        loop {
            let (lo, hi) = self.bounds(d);
            let (xd, wd) = (self.x[d], self.w[d]);
            if xd <= lo + self.tol && wd >= -self.tol {
                self.set_state(d, RowState::Lower);
                self.snap();
                return;
            }
            if xd >= hi - self.tol && wd <= self.tol {
                self.set_state(d, RowState::Upper);
                self.snap();
                return;
            }
            if wd.abs() <= self.tol {
                if !self.set_state(d, RowState::Clamped) {
                    // Dependent on the clamped rows and already satisfied: leave it be.
                    self.degenerate = true;
                }
                return;
            }
            if self.pivots >= self.max_pivots {
                self.fail(LcpStatus::MaxIterations);
                return;
            }
            if self.pivots - drive_start >= 2 * self.n + 10 {
                self.fail(LcpStatus::Cycling);
                return;
            }
            let Some((mut dx, mut dw)) = self.direction(d) else {
                self.degenerate = true;
                self.fail(LcpStatus::Degenerate);
                return;
            };
            self.pivots += 1;

            // Pick the sense of motion (Figure 3.3). On the first step: toward the bound that
            // agrees with the sign of w_d, which makes progress when w_d grows with x_d (always,
            // for a P-matrix); if it does not, a finite bound still ends the drive validly; with no
            // bound that way, the other sense shrinks |w_d| instead.
            let rate = dw[d];
            let preferred = if wd < 0.0 { 1.0 } else { -1.0 };
            let bound_ahead = if preferred > 0.0 { hi } else { lo };
            let room_behind = if preferred > 0.0 {
                xd > lo + self.tol
            } else {
                xd < hi - self.tol
            };
            let first_sense = if rate < -self.zero && !bound_ahead.is_finite() && room_behind {
                -preferred
            } else {
                preferred
            };
            // After a set change, the row that just changed must move into its new valid region;
            // that fixes the sense. With coupled friction the active-set matrix (3.41) is not a
            // P-matrix, and this can reverse x_d: the path of valid configurations folds back,
            // and following it (as a complementary pivoting method does) is what avoids
            // ping-ponging one row between two sets at a standstill.
            let sense = last_switch
                .and_then(|(j, old, new)| self.path_sense(j, old, new, &dx, &dw))
                .unwrap_or(first_sense);
            let flipped = sense != preferred;
            if rate.abs() <= self.zero {
                self.degenerate = true;
            }
            dx *= sense;
            dw *= sense;

            let Some((t, event)) = self.ratio_test(d, &dx, &dw, flipped) else {
                // Nothing stops this direction (§5.2, Figure 5.4): no valid state along it.
                self.fail(LcpStatus::Infeasible);
                return;
            };
            self.x.axpy(t, &dx, 1.0);
            if t <= self.tol {
                if !seen.insert(self.state.clone()) {
                    self.fail(LcpStatus::Cycling);
                    self.snap();
                    return;
                }
            } else {
                seen.clear();
            }
            match event {
                Event::Driven(state) => {
                    let ok = self.set_state(d, state);
                    self.snap();
                    if !ok {
                        self.degenerate = true;
                    }
                    return;
                }
                Event::DrivenStuck => {
                    self.fail(LcpStatus::Blocked);
                    self.snap();
                    return;
                }
                Event::Switch(j, state) => {
                    let old = self.state[j];
                    if self.set_state(j, state) {
                        last_switch = Some((j, old, state));
                    } else {
                        self.frozen[j] = true;
                        self.degenerate = true;
                        last_switch = None;
                    }
                    self.snap();
                }
            }
        }
    }

    /// The sense (±1) of the unit direction `(dx, dw)` that moves row `j`, which just went from
    /// set `old` to set `new`, into the valid region of `new`; `None` if it does not move.
    fn path_sense(
        &self,
        j: usize,
        old: RowState,
        new: RowState,
        dx: &DVector<f64>,
        dw: &DVector<f64>,
    ) -> Option<f64> {
        let (dlo, dhi) = match self.p.rows[j] {
            RowKind::Friction { normal, mu } => (-mu * dx[normal], mu * dx[normal]),
            _ => (0.0, 0.0),
        };
        let (q, eps) = match (old, new) {
            // Entered C from a bound: the impulse must leave that bound.
            (RowState::Lower, RowState::Clamped) => (dx[j] - dlo, self.rel),
            (RowState::Upper, RowState::Clamped) => (dhi - dx[j], self.rel),
            // Reached a bound: w must take the sign that bound allows.
            (_, RowState::Lower) => (dw[j], self.zero),
            (_, RowState::Upper) => (-dw[j], self.zero),
            _ => return None,
        };
        let eps = eps * (1.0 + dx.amax());
        (q.abs() > eps).then_some(q.signum())
    }

    /// Longest step along `(dx, dw)` before a set change: the first of the driven row reaching
    /// `w_d = 0` or its bound, a clamped row reaching a bound (Figure 3.6 b), or a row at a bound
    /// whose `w` reaches 0 (Figure 3.6 c–d).
    fn ratio_test(
        &self,
        d: usize,
        dx: &DVector<f64>,
        dw: &DVector<f64>,
        flipped: bool,
    ) -> Option<(f64, Event)> {
        let zx = self.rel * (1.0 + dx.amax());
        let zw = self.zero * (1.0 + dx.amax());
        let mut best: Option<(f64, Event)> = None;
        let mut offer = |t: f64, e: Event| {
            let t = t.max(0.0);
            if best.is_none_or(|(bt, _)| t < bt) {
                best = Some((t, e));
            }
        };
        // Rate of change of row i's bounds along dx (friction bounds follow the normal).
        let bound_rates = |i: usize| match self.p.rows[i] {
            RowKind::Friction { normal, mu } => (-mu * dx[normal], mu * dx[normal]),
            _ => (0.0, 0.0),
        };

        let (wd, xd) = (self.w[d], self.x[d]);
        if dw[d] * wd < 0.0 && dw[d].abs() > zw {
            offer(-wd / dw[d], Event::Driven(RowState::Clamped));
        }
        let (lo, hi) = self.bounds(d);
        let (dlo, dhi) = bound_rates(d);
        let hi_event = if flipped {
            Event::DrivenStuck
        } else {
            Event::Driven(RowState::Upper)
        };
        let lo_event = if flipped {
            Event::DrivenStuck
        } else {
            Event::Driven(RowState::Lower)
        };
        if hi.is_finite() && dhi - dx[d] < -zx {
            offer((hi - xd) / (dx[d] - dhi), hi_event);
        }
        if lo.is_finite() && dx[d] - dlo < -zx {
            offer((xd - lo) / (dlo - dx[d]), lo_event);
        }

        for j in 0..self.n {
            if j == d || self.frozen[j] {
                continue;
            }
            match self.state[j] {
                RowState::Clamped => {
                    let (lo, hi) = self.bounds(j);
                    let (dlo, dhi) = bound_rates(j);
                    if hi.is_finite() && dhi - dx[j] < -zx {
                        offer(
                            (hi - self.x[j]) / (dx[j] - dhi),
                            Event::Switch(j, RowState::Upper),
                        );
                    }
                    if lo.is_finite() && dx[j] - dlo < -zx {
                        offer(
                            (self.x[j] - lo) / (dlo - dx[j]),
                            Event::Switch(j, RowState::Lower),
                        );
                    }
                }
                RowState::Lower if dw[j] < -zw => {
                    offer(self.w[j] / -dw[j], self.release(j, RowState::Upper, dx));
                }
                RowState::Upper if dw[j] > zw => {
                    offer(-self.w[j] / dw[j], self.release(j, RowState::Lower, dx));
                }
                _ => {}
            }
        }
        best
    }

    /// Where a row at a bound goes when its `w` changes sign: into `C`, unless its bounds
    /// coincide and stay so (a friction row of a contact without normal impulse), in which case it
    /// simply counts as being at the other bound.
    fn release(&self, j: usize, other: RowState, dx: &DVector<f64>) -> Event {
        let (lo, hi) = self.bounds(j);
        let opening = match self.p.rows[j] {
            RowKind::Friction { normal, .. } => dx[normal] > 0.0,
            _ => false,
        };
        if hi - lo <= self.tol && !opening {
            Event::Switch(j, other)
        } else {
            Event::Switch(j, RowState::Clamped)
        }
    }

    /// With the final sets fixed, re-solves `w_C = 0` from scratch (one dense solve) to remove
    /// the rounding accumulated over the pivots; kept only if it lowers the residual.
    fn polish(&mut self) {
        if self.clamped.is_empty() {
            return;
        }
        let mut fixed = self.x.clone();
        for &k in &self.clamped {
            fixed[k] = 0.0;
            for &j in &self.children[k] {
                if self.coupling(j).is_some() {
                    fixed[j] = 0.0;
                }
            }
        }
        let rhs_full = &self.p.a * &fixed + &self.p.b;
        let rhs = -DVector::from_iterator(
            self.clamped.len(),
            self.clamped.iter().map(|&c| rhs_full[c]),
        );
        let Ok(qr) = Qr::new(&self.clamped_matrix()) else {
            return;
        };
        let Ok(y) = qr.solve_with_tolerance(&rhs, self.zero) else {
            return;
        };
        let mut x = fixed;
        for (pos, &k) in self.clamped.iter().enumerate() {
            x[k] = y[pos];
            for &j in &self.children[k] {
                if let Some((_, f)) = self.coupling(j) {
                    x[j] = f * y[pos];
                }
            }
        }
        let before = complementarity_residual(self.p, &self.x);
        let after = complementarity_residual(self.p, &x);
        if after <= before {
            self.x = x;
            self.w = &self.p.a * &self.x + &self.p.b;
        }
    }
}
