//! Dense QR factorisation `A = Q R` with O(n²) updates by Givens rotations (§3.7.1).
//!
//! The LCP solver of [`crate::lcp`] solves one linear system per pivot, and from one pivot to the
//! next its matrix changes by a single row and column (a constraint enters or leaves the clamped
//! set) or by a single column (a friction row starts or stops following its normal force). The
//! authors keep a QR factorisation of that matrix and patches it with Givens rotations instead of
//! refactoring, because the matrix is not symmetric once friction bounds are coupled to normal
//! forces (so ODE's LDLᵀ trick does not apply) and LU updates need pivoting to stay stable.
//!
//! [`Qr`] stores the *full* factorisation of an `m × n` matrix: `Q` is `m × m` orthogonal and `R`
//! is `m × n` upper trapezoidal. Both are kept explicitly (the authors does the same; the compact
//! Householder form is much harder to update). Every update costs O((m + n)·max(m, n)):
//!
//! | update | rotations | authors |
//! |---|---|---|
//! | [`Qr::insert_column`] | ≤ m − 1 on adjacent rows | (3.42), column half |
//! | [`Qr::insert_row`] | ≤ n on (row j, new row) pairs | (3.51), Figure 3.8 |
//! | [`Qr::remove_column`] | ≤ n − 1 on adjacent rows | Figure 3.9 a–e |
//! | [`Qr::remove_row`] | m − 1 on `Q`'s columns | Figure 3.9 f–k |
//! | [`Qr::replace_column`], [`Qr::add_to_column`] | ≤ 2m ("spike" then sub-diagonal) | (3.44), Figure 3.7 |
//!
//! Rotations preserve orthogonality exactly in exact arithmetic and to a few ulps per rotation in
//! floating point; the tests in this module bound the drift after long random update sequences.

use nalgebra::{DMatrix, DVector};

use crate::QrError;

/// A plane rotation acting on the pair of indices `(p, q)`: `R_p ← c R_p + s R_q`,
/// `R_q ← −s R_p + c R_q` on rows of `R`, and the same on columns of `Q` so that `Q R` is unchanged
/// (the authors' `QR = (QG)(GᵀR)`, (3.49)).
#[derive(Debug, Clone, Copy)]
struct Givens {
    c: f64,
    s: f64,
}

impl Givens {
    /// The rotation that maps `(a, b)` to `(hypot(a, b), 0)`.
    fn zeroing(a: f64, b: f64) -> Self {
        if b == 0.0 {
            return Self { c: 1.0, s: 0.0 };
        }
        let r = a.hypot(b);
        Self { c: a / r, s: b / r }
    }
}

/// A full QR factorisation with in-place updates. See the [module docs](self).
#[derive(Debug, Clone, PartialEq)]
pub struct Qr {
    q: DMatrix<f64>,
    r: DMatrix<f64>,
}

impl Qr {
    /// The factorisation of an empty `0 × 0` matrix, the usual starting point for the LCP solver's
    /// clamped set.
    pub fn empty() -> Self {
        Self {
            q: DMatrix::zeros(0, 0),
            r: DMatrix::zeros(0, 0),
        }
    }

    /// Factorises `a` from scratch (Givens, O(m²n)). Rejects NaN and infinite entries.
    pub fn new(a: &DMatrix<f64>) -> Result<Self, QrError> {
        if let Some(k) = a.iter().position(|v| !v.is_finite()) {
            return Err(QrError::NonFinite {
                what: "matrix",
                index: k,
            });
        }
        let (m, n) = a.shape();
        let mut qr = Self {
            q: DMatrix::identity(m, m),
            r: a.clone(),
        };
        for j in 0..n.min(m) {
            for k in (j + 1..m).rev() {
                qr.zero_with(k - 1, k, j);
            }
        }
        Ok(qr)
    }

    /// Number of rows of the factorised matrix.
    pub fn nrows(&self) -> usize {
        self.r.nrows()
    }

    /// Number of columns of the factorised matrix.
    pub fn ncols(&self) -> usize {
        self.r.ncols()
    }

    /// The orthogonal factor (`m × m`).
    pub fn q(&self) -> &DMatrix<f64> {
        &self.q
    }

    /// The upper-trapezoidal factor (`m × n`).
    pub fn r(&self) -> &DMatrix<f64> {
        &self.r
    }

    /// `Q R`, the matrix currently represented.
    pub fn reconstruct(&self) -> DMatrix<f64> {
        &self.q * &self.r
    }

    /// `max |QᵀQ − I|`, a measure of how far rounding has drifted `Q` from orthogonality.
    pub fn orthogonality_error(&self) -> f64 {
        let m = self.q.nrows();
        let qtq = self.q.tr_mul(&self.q);
        (qtq - DMatrix::<f64>::identity(m, m)).amax()
    }

    /// The smallest `|R_ii|`, or `+∞` for an empty matrix. For a square matrix this is zero
    /// exactly when the matrix is singular.
    pub fn min_abs_diagonal(&self) -> f64 {
        (0..self.nrows().min(self.ncols()))
            .map(|i| self.r[(i, i)].abs())
            .fold(f64::INFINITY, f64::min)
    }

    /// Numerical rank: the number of `|R_ii|` above `tolerance`. (Without column pivoting this is
    /// a rank *estimate*; it is exact for the question the LCP solver asks, "is this square matrix
    /// usable for solving".)
    pub fn rank(&self, tolerance: f64) -> usize {
        (0..self.nrows().min(self.ncols()))
            .filter(|&i| self.r[(i, i)].abs() > tolerance)
            .count()
    }

    /// Applies `rot` to rows `(p, q)` of `R` from column `from` on, and to columns `(p, q)` of `Q`.
    fn apply(&mut self, rot: Givens, p: usize, q: usize, from: usize) {
        let Givens { c, s } = rot;
        for j in from..self.r.ncols() {
            let (rp, rq) = (self.r[(p, j)], self.r[(q, j)]);
            self.r[(p, j)] = c * rp + s * rq;
            self.r[(q, j)] = -s * rp + c * rq;
        }
        for i in 0..self.q.nrows() {
            let (qp, qq) = (self.q[(i, p)], self.q[(i, q)]);
            self.q[(i, p)] = c * qp + s * qq;
            self.q[(i, q)] = -s * qp + c * qq;
        }
    }

    /// Rotates rows `(p, q)` so that `R[q, col]` becomes zero (columns left of `col` are already
    /// zero in both rows and are skipped).
    fn zero_with(&mut self, p: usize, q: usize, col: usize) {
        let b = self.r[(q, col)];
        if b == 0.0 {
            return;
        }
        let rot = Givens::zeroing(self.r[(p, col)], b);
        self.apply(rot, p, q, col);
        self.r[(q, col)] = 0.0;
    }

    fn check_len(what: &'static str, v: &DVector<f64>, expected: usize) -> Result<(), QrError> {
        if v.len() != expected {
            return Err(QrError::DimensionMismatch {
                what,
                expected,
                found: v.len(),
            });
        }
        if let Some(k) = v.iter().position(|x| !x.is_finite()) {
            return Err(QrError::NonFinite { what, index: k });
        }
        Ok(())
    }

    fn check_index(index: usize, len: usize) -> Result<(), QrError> {
        if index >= len {
            return Err(QrError::IndexOutOfRange { index, len });
        }
        Ok(())
    }

    /// Inserts column `u` so that it becomes column `j` (`j == ncols()` appends).
    ///
    /// `R` gains the column `Qᵀu`; rotations of adjacent rows, bottom up, clear it below the
    /// diagonal. The fill they cause lands exactly on the diagonal of the shifted columns.
    pub fn insert_column(&mut self, j: usize, u: &DVector<f64>) -> Result<(), QrError> {
        Self::check_len("column", u, self.nrows())?;
        Self::check_index(j, self.ncols() + 1)?;
        let qtu = self.q.tr_mul(u);
        let r = std::mem::replace(&mut self.r, DMatrix::zeros(0, 0));
        self.r = r.insert_column(j, 0.0);
        self.r.set_column(j, &qtu);
        for k in (j + 1..self.nrows()).rev() {
            self.zero_with(k - 1, k, j);
        }
        Ok(())
    }

    /// Appends column `u` (the "add a column" half of (3.42)).
    pub fn push_column(&mut self, u: &DVector<f64>) -> Result<(), QrError> {
        self.insert_column(self.ncols(), u)
    }

    /// Removes column `j`. Dropping it from `R` leaves one sub-diagonal entry in every later
    /// column (upper Hessenberg); adjacent-row rotations clear them (Figure 3.9 a–e).
    pub fn remove_column(&mut self, j: usize) -> Result<(), QrError> {
        Self::check_index(j, self.ncols())?;
        let r = std::mem::replace(&mut self.r, DMatrix::zeros(0, 0));
        self.r = r.remove_column(j);
        let (m, n) = self.r.shape();
        for c in j..n.min(m.saturating_sub(1)) {
            self.zero_with(c, c + 1, c);
        }
        Ok(())
    }

    /// Inserts row `v` so that it becomes row `i` (`i == nrows()` appends).
    ///
    /// As in (3.51), `Q` grows by one row and column holding a single 1 (so `Q R` gains the new
    /// row unchanged) and `R` gains `vᵀ` as its last row; rotating each row `j` of `R` against that
    /// last row clears it left to right (Figure 3.8).
    pub fn insert_row(&mut self, i: usize, v: &DVector<f64>) -> Result<(), QrError> {
        Self::check_len("row", v, self.ncols())?;
        Self::check_index(i, self.nrows() + 1)?;
        let (m, n) = self.r.shape();
        let q = std::mem::replace(&mut self.q, DMatrix::zeros(0, 0));
        self.q = q.insert_row(i, 0.0).insert_column(m, 0.0);
        self.q[(i, m)] = 1.0;
        let r = std::mem::replace(&mut self.r, DMatrix::zeros(0, 0));
        self.r = r.insert_row(m, 0.0);
        self.r.set_row(m, &v.transpose());
        for j in 0..n.min(m) {
            self.zero_with(j, m, j);
        }
        Ok(())
    }

    /// Appends row `v` (the "add a row" half of (3.42)).
    pub fn push_row(&mut self, v: &DVector<f64>) -> Result<(), QrError> {
        self.insert_row(self.nrows(), v)
    }

    /// Removes row `i`.
    ///
    /// Dropping a row of `Q` would break orthogonality, so first rotations between columns of `Q`
    /// (and the matching rows of `R`) fold row `i` of `Q` into a single ±1 (Figure 3.9 f–k). The
    /// authors move that 1 to the first column; we move it to the *last* one, which keeps the
    /// rows of `R` above it upper triangular when the rotations run from the bottom up, and makes
    /// the final drop a cheap truncation. Orthogonality then forces the last column of `Q` to be
    /// ±e_i, so row `i` and the last column of `Q` and the last row of `R` can go.
    pub fn remove_row(&mut self, i: usize) -> Result<(), QrError> {
        let m = self.nrows();
        Self::check_index(i, m)?;
        let last = m - 1;
        for k in (0..last).rev() {
            let b = self.q[(i, k)];
            if b == 0.0 {
                continue;
            }
            let rot = Givens::zeroing(self.q[(i, last)], b);
            // Row `k` of R has entries from column k on; the last row, by now, from k + 1 on.
            self.apply(rot, last, k, k);
            self.q[(i, k)] = 0.0;
        }
        let q = std::mem::replace(&mut self.q, DMatrix::zeros(0, 0));
        self.q = q.remove_row(i).remove_column(last);
        let r = std::mem::replace(&mut self.r, DMatrix::zeros(0, 0));
        self.r = r.remove_row(last);
        Ok(())
    }

    /// Replaces column `j` by `u` (3.44).
    pub fn replace_column(&mut self, j: usize, u: &DVector<f64>) -> Result<(), QrError> {
        Self::check_len("column", u, self.nrows())?;
        Self::check_index(j, self.ncols())?;
        let qtu = self.q.tr_mul(u);
        self.r.set_column(j, &qtu);
        self.retriangulate_spike(j);
        Ok(())
    }

    /// Adds `delta` to column `j`: `R[:, j] += Qᵀδ` (3.50), then re-triangulates.
    pub fn add_to_column(&mut self, j: usize, delta: &DVector<f64>) -> Result<(), QrError> {
        Self::check_len("column", delta, self.nrows())?;
        Self::check_index(j, self.ncols())?;
        let qtd = self.q.tr_mul(delta);
        let mut col = self.r.column_mut(j);
        col += qtd;
        self.retriangulate_spike(j);
        Ok(())
    }

    /// Column `j` of `R` is full (a "spike"). Bottom-up rotations of adjacent rows clear it below
    /// the diagonal, leaving one sub-diagonal entry in each later column; a top-down sweep clears
    /// those (Figure 3.7). At most 2m rotations.
    fn retriangulate_spike(&mut self, j: usize) {
        let (m, n) = self.r.shape();
        for k in (j + 1..m).rev() {
            self.zero_with(k - 1, k, j);
        }
        for c in j + 1..n.min(m.saturating_sub(1)) {
            self.zero_with(c, c + 1, c);
        }
    }

    fn pivot_check(&self, k: usize, tolerance: f64) -> Result<f64, QrError> {
        let pivot = self.r[(k, k)];
        if pivot.abs() <= tolerance || !pivot.is_finite() {
            return Err(QrError::RankDeficient {
                index: k,
                pivot,
                tolerance,
            });
        }
        Ok(pivot)
    }

    /// Solves `A x = b` (square `A`) or the least-squares problem `min ‖A x − b‖` (tall `A`, full
    /// column rank) by `R x = Qᵀ b` (3.45)–(3.46). A diagonal entry of `R` with `|R_kk| ≤
    /// tolerance` is reported as [`QrError::RankDeficient`] instead of being divided by.
    pub fn solve_with_tolerance(
        &self,
        b: &DVector<f64>,
        tolerance: f64,
    ) -> Result<DVector<f64>, QrError> {
        let (m, n) = self.r.shape();
        if m < n {
            return Err(QrError::Underdetermined { rows: m, cols: n });
        }
        Self::check_len("right-hand side", b, m)?;
        let y = self.q.tr_mul(b);
        let mut x = DVector::zeros(n);
        for k in (0..n).rev() {
            let pivot = self.pivot_check(k, tolerance)?;
            let mut acc = y[k];
            for j in k + 1..n {
                acc -= self.r[(k, j)] * x[j];
            }
            x[k] = acc / pivot;
        }
        Ok(x)
    }

    /// Solves `Aᵀ x = b` for square `A`: `Rᵀ z = b` by forward substitution, then `x = Q z`.
    pub fn solve_transpose_with_tolerance(
        &self,
        b: &DVector<f64>,
        tolerance: f64,
    ) -> Result<DVector<f64>, QrError> {
        let (m, n) = self.r.shape();
        if m != n {
            return Err(QrError::NotSquare { rows: m, cols: n });
        }
        Self::check_len("right-hand side", b, n)?;
        let mut z = DVector::zeros(n);
        for k in 0..n {
            let pivot = self.pivot_check(k, tolerance)?;
            let mut acc = b[k];
            for j in 0..k {
                acc -= self.r[(j, k)] * z[j];
            }
            z[k] = acc / pivot;
        }
        Ok(&self.q * z)
    }

    /// A rank tolerance scaled to this factorisation: `max(m, n) · ε · max|R_ij|` (times a small
    /// safety factor), the usual backward-error scale of Givens QR.
    pub fn default_tolerance(&self) -> f64 {
        let (m, n) = self.r.shape();
        let scale = if self.r.is_empty() {
            0.0
        } else {
            self.r.amax()
        };
        16.0 * (m.max(n) as f64) * f64::EPSILON * scale
    }

    /// [`Qr::solve_with_tolerance`] with [`Qr::default_tolerance`].
    pub fn solve(&self, b: &DVector<f64>) -> Result<DVector<f64>, QrError> {
        self.solve_with_tolerance(b, self.default_tolerance())
    }

    /// [`Qr::solve_transpose_with_tolerance`] with [`Qr::default_tolerance`].
    pub fn solve_transpose(&self, b: &DVector<f64>) -> Result<DVector<f64>, QrError> {
        self.solve_transpose_with_tolerance(b, self.default_tolerance())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tiny deterministic generator (SplitMix64) so the tests need no `rand`.
    pub(crate) struct SplitMix(pub u64);
    impl SplitMix {
        pub fn next_u64(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }
        /// Uniform in [-1, 1).
        pub fn sym(&mut self) -> f64 {
            (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        }
        pub fn below(&mut self, n: usize) -> usize {
            (self.next_u64() % n as u64) as usize
        }
    }

    fn random_matrix(rng: &mut SplitMix, m: usize, n: usize) -> DMatrix<f64> {
        DMatrix::from_fn(m, n, |_, _| rng.sym())
    }

    fn random_vector(rng: &mut SplitMix, n: usize) -> DVector<f64> {
        DVector::from_fn(n, |_, _| rng.sym())
    }

    fn assert_upper(qr: &Qr) {
        let r = qr.r();
        for j in 0..r.ncols() {
            for i in j + 1..r.nrows() {
                assert_eq!(r[(i, j)], 0.0, "R[{i},{j}] below the diagonal");
            }
        }
    }

    fn assert_factors(qr: &Qr, a: &DMatrix<f64>, tol: f64) {
        assert_eq!(qr.q().shape(), (a.nrows(), a.nrows()));
        assert_eq!(qr.r().shape(), a.shape());
        assert_upper(qr);
        let err = if a.is_empty() {
            0.0
        } else {
            (qr.reconstruct() - a).amax()
        };
        assert!(err <= tol, "‖QR − A‖ = {err:e}");
        let orth = if a.nrows() == 0 {
            0.0
        } else {
            qr.orthogonality_error()
        };
        assert!(orth <= tol, "‖QᵀQ − I‖ = {orth:e}");
    }

    #[test]
    fn fresh_factorisation_reproduces_square_tall_wide_and_empty() {
        let mut rng = SplitMix(1);
        for (m, n) in [(0, 0), (1, 1), (4, 4), (7, 3), (3, 7), (6, 0), (0, 5)] {
            let a = random_matrix(&mut rng, m, n);
            let qr = Qr::new(&a).unwrap();
            assert_factors(&qr, &a, 1e-14);
        }
    }

    #[test]
    fn each_update_type_keeps_the_factors_exact() {
        let mut rng = SplitMix(2);
        for (m, n) in [(1, 1), (5, 5), (6, 4), (4, 6)] {
            let a = random_matrix(&mut rng, m, n);
            for j in 0..=n {
                let u = random_vector(&mut rng, m);
                let mut qr = Qr::new(&a).unwrap();
                qr.insert_column(j, &u).unwrap();
                let mut want = a.clone().insert_column(j, 0.0);
                want.set_column(j, &u);
                assert_factors(&qr, &want, 1e-14);
            }
            for j in 0..n {
                let mut qr = Qr::new(&a).unwrap();
                qr.remove_column(j).unwrap();
                assert_factors(&qr, &a.clone().remove_column(j), 1e-14);

                let u = random_vector(&mut rng, m);
                let mut qr = Qr::new(&a).unwrap();
                qr.replace_column(j, &u).unwrap();
                let mut want = a.clone();
                want.set_column(j, &u);
                assert_factors(&qr, &want, 1e-14);

                let mut qr = Qr::new(&a).unwrap();
                qr.add_to_column(j, &u).unwrap();
                let mut want = a.clone();
                want.set_column(j, &(a.column(j) + &u));
                assert_factors(&qr, &want, 1e-14);
            }
            for i in 0..=m {
                let v = random_vector(&mut rng, n);
                let mut qr = Qr::new(&a).unwrap();
                qr.insert_row(i, &v).unwrap();
                let mut want = a.clone().insert_row(i, 0.0);
                want.set_row(i, &v.transpose());
                assert_factors(&qr, &want, 1e-14);
            }
            for i in 0..m {
                let mut qr = Qr::new(&a).unwrap();
                qr.remove_row(i).unwrap();
                assert_factors(&qr, &a.clone().remove_row(i), 1e-14);
            }
        }
    }

    #[test]
    fn grows_from_empty_by_appending_row_and_column_like_the_lcp() {
        // (3.42): the clamped-set matrix grows by a trailing row and column.
        let mut rng = SplitMix(3);
        let full = random_matrix(&mut rng, 8, 8);
        let mut qr = Qr::empty();
        for k in 0..8 {
            let col = DVector::from_fn(k, |i, _| full[(i, k)]);
            qr.push_column(&col).unwrap();
            let row = DVector::from_fn(k + 1, |j, _| full[(k, j)]);
            qr.push_row(&row).unwrap();
            assert_factors(&qr, &full.view((0, 0), (k + 1, k + 1)).clone_owned(), 1e-14);
        }
        // … and shrinks by removing a row/column pair anywhere (3.43).
        let mut want = full.clone();
        for idx in [3, 0, 5, 2] {
            qr.remove_row(idx).unwrap();
            qr.remove_column(idx).unwrap();
            want = want.remove_row(idx).remove_column(idx);
            assert_factors(&qr, &want, 1e-14);
        }
    }

    #[test]
    fn solves_and_transposed_solves_match_the_matrix() {
        let mut rng = SplitMix(4);
        for n in [1, 2, 5, 9] {
            let a = random_matrix(&mut rng, n, n) + DMatrix::identity(n, n) * 3.0;
            let b = random_vector(&mut rng, n);
            let qr = Qr::new(&a).unwrap();
            let x = qr.solve(&b).unwrap();
            assert!((&a * &x - &b).amax() < 1e-13);
            let y = qr.solve_transpose(&b).unwrap();
            assert!((a.tr_mul(&y) - &b).amax() < 1e-13);
        }
        // Tall: least squares; the residual is orthogonal to the column space.
        let a = random_matrix(&mut rng, 7, 3);
        let b = random_vector(&mut rng, 7);
        let x = Qr::new(&a).unwrap().solve(&b).unwrap();
        assert!(a.tr_mul(&(&a * &x - &b)).amax() < 1e-13);
    }

    #[test]
    fn rank_deficiency_is_reported_not_divided_by() {
        // Duplicate columns (two identical contact rows).
        let mut a = DMatrix::from_row_slice(3, 3, &[1.0, 2.0, 1.0, 0.5, 1.0, 0.5, 3.0, -1.0, 3.0]);
        let qr = Qr::new(&a).unwrap();
        assert_eq!(qr.rank(1e-12), 2);
        let b = DVector::from_vec(vec![1.0, 2.0, 3.0]);
        assert!(matches!(
            qr.solve(&b),
            Err(QrError::RankDeficient { index: 2, .. })
        ));
        assert!(matches!(
            qr.solve_transpose(&b),
            Err(QrError::RankDeficient { .. })
        ));
        // The zero matrix and an update that creates a dependency.
        assert!(
            Qr::new(&DMatrix::zeros(2, 2))
                .unwrap()
                .solve(&b.rows(0, 2).into())
                .is_err()
        );
        a[(0, 2)] = 5.0;
        let mut qr = Qr::new(&a).unwrap();
        assert_eq!(qr.rank(1e-12), 3);
        qr.replace_column(2, &a.column(0).into()).unwrap();
        assert_eq!(qr.rank(1e-12), 2);
        assert!(qr.solve(&b).is_err());
        // NaN is refused up front.
        a[(1, 1)] = f64::NAN;
        assert!(matches!(Qr::new(&a), Err(QrError::NonFinite { .. })));
        let mut qr = Qr::new(&DMatrix::identity(2, 2)).unwrap();
        let bad = DVector::from_vec(vec![f64::NAN, 0.0]);
        assert!(qr.push_column(&bad).is_err());
        assert!(qr.replace_column(5, &DVector::zeros(2)).is_err());
        assert!(qr.remove_row(2).is_err());
    }

    /// Bound on drift after 500 mixed updates, relative to `max|A|`: the reconstruction error and
    /// the loss of orthogonality both stay below 1e-12 (measured: ~1e-15, see the test output with
    /// `--nocapture`). A fresh factorisation of the same matrix gives the same solutions to 1e-9.
    #[test]
    fn long_random_update_sequences_stay_accurate() {
        const BOUND: f64 = 1e-12;
        for seed in 0..4 {
            let mut rng = SplitMix(100 + seed);
            let mut a = random_matrix(&mut rng, 6, 6);
            let mut qr = Qr::new(&a).unwrap();
            let mut worst = (0.0f64, 0.0f64);
            for _ in 0..500 {
                let (m, n) = a.shape();
                match rng.below(6) {
                    0 if n < 12 => {
                        let j = rng.below(n + 1);
                        let u = random_vector(&mut rng, m);
                        qr.insert_column(j, &u).unwrap();
                        a = a.insert_column(j, 0.0);
                        a.set_column(j, &u);
                    }
                    1 if m < 12 => {
                        let i = rng.below(m + 1);
                        let v = random_vector(&mut rng, n);
                        qr.insert_row(i, &v).unwrap();
                        a = a.insert_row(i, 0.0);
                        a.set_row(i, &v.transpose());
                    }
                    2 if n > 1 => {
                        let j = rng.below(n);
                        qr.remove_column(j).unwrap();
                        a = a.remove_column(j);
                    }
                    3 if m > 1 => {
                        let i = rng.below(m);
                        qr.remove_row(i).unwrap();
                        a = a.remove_row(i);
                    }
                    _ => {
                        let j = rng.below(n);
                        let u = random_vector(&mut rng, m);
                        qr.replace_column(j, &u).unwrap();
                        a.set_column(j, &u);
                    }
                }
                assert_upper(&qr);
                let rec = (qr.reconstruct() - &a).amax() / a.amax();
                worst = (worst.0.max(rec), worst.1.max(qr.orthogonality_error()));
            }
            println!(
                "seed {seed}: worst ‖QR−A‖/‖A‖ = {:.2e}, ‖QᵀQ−I‖ = {:.2e}",
                worst.0, worst.1
            );
            assert!(worst.0 < BOUND && worst.1 < BOUND, "{worst:?}");
            // Compare with a fresh factorisation on a square, well-conditioned version.
            let k = a.nrows().min(a.ncols());
            let sq = a.view((0, 0), (k, k)).clone_owned() + DMatrix::identity(k, k) * 4.0;
            let mut upd = qr.clone();
            while upd.nrows() > k {
                upd.remove_row(k).unwrap();
            }
            while upd.ncols() > k {
                upd.remove_column(k).unwrap();
            }
            for j in 0..k {
                upd.add_to_column(
                    j,
                    &(DVector::from_fn(k, |i, _| if i == j { 4.0 } else { 0.0 })),
                )
                .unwrap();
            }
            let b = random_vector(&mut rng, k);
            let fresh = sq.clone().lu().solve(&b).unwrap();
            let x = upd.solve(&b).unwrap();
            assert!((x - fresh).amax() < 1e-9);
        }
    }
}
