//! Mixed precision: a single-precision factor of X, kept across steps while it preconditions
//! well, and conjugate gradients to double-precision accuracy.

use super::*;
use faer::sparse::SymbolicSparseColMat;
use faer::{c32, c64};

/// Conjugate-gradient iterations [`Mixed::solve_in_place`] allows before it gives up on the
/// single-precision factor (measured: 2–4 reach [`MIXED_TOLERANCE`] on the flows' X).
pub const MIXED_MAX_ITERATIONS: usize = 12;

/// Normwise backward error `‖b − Ax‖ / (‖A‖‖x‖ + ‖b‖)` at which [`Mixed`] stops: within a
/// small multiple of what the double-precision direct solve leaves.
pub const MIXED_TOLERANCE: f64 = 1e-13;

/// Whether conjugate gradients on a kept factor, at backward error `best` after
/// `iterations` from `start`, would need more than twice [`REUSE_GIVE_UP_ITERATIONS`] in all
/// at the rate seen so far: then the factor is replaced at once instead of after the limit.
/// The best error, not the last, sets the rate: CG's backward error is not monotone (the
/// bumpy icosphere's kept solves went 3e-7, 8e-10, 3e-8, 5e-11, 3e-13, 8e-16). Measured on
/// nefertiti (`--precision mixed`), where X moves too far in a step for any kept factor:
/// the stalled solves fell by 2–5× an iteration from 1e-6–1e-5 and ended at 2e-11–2e-8
/// after the 6 allowed; the rule stops two of three such solves after 2 iterations. The
/// icosphere:7's successful kept solves (5 iterations) are predicted at 4.3–7.4 after 2–4.
pub(super) fn kept_factor_is_hopeless(start: f64, best: f64, iterations: usize) -> bool {
    if !(best > 0.0 && start > best) {
        return best > 0.0 && iterations >= 2;
    }
    let rate = (best / start).powf(1.0 / iterations as f64);
    let remaining = (MIXED_TOLERANCE / best).ln() / rate.ln();
    iterations as f64 + remaining > 2.0 * REUSE_GIVE_UP_ITERATIONS as f64
}

/// Why a [`Mixed`] solve gave up.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("conjugate gradients on the single-precision factor stalled at backward error {backward_error:.1e} after {iterations} iterations")]
pub struct NotConverged {
    pub iterations: usize,
    pub backward_error: f64,
}

/// A Hermitian positive definite system held in double precision and factored in single
/// precision (issue 14): the factor takes half the memory and about half the time of the
/// double one, and conjugate gradients preconditioned with it (the factor is an exact
/// inverse up to single-precision rounding, so a few iterations suffice) return the solution
/// to double precision. The caller assembles into [`Mixed::triangle_values_mut`], in the
/// layout of [`Mixed::triangle_slots`], exactly as for [`Cholesky`].
pub struct Mixed {
    single: Cholesky<c32>,
    /// The pattern of the factor's triangle, which the products with the double-precision
    /// matrix read (taken from `single`, whose own kernel does not need it).
    triangle: SymbolicSparseColMat<usize>,
    /// The matrix, double precision, in the factor's triangle layout.
    values: Vec<c64>,
    /// `‖A‖_∞` of the last factorization (for the backward error).
    norm: f64,
    x: Vec<c64>,
    r: Vec<c64>,
    z: Vec<c64>,
    p: Vec<c64>,
    ap: Vec<c64>,
    single_rhs: Vec<c32>,
    /// Iterations and backward error of the last solve.
    pub last_iterations: usize,
    /// Where the last solve gave up early on a kept factor (`kept_factor_is_hopeless`).
    pub gave_up_after: Option<usize>,
    pub last_backward_error: f64,
    /// Whether the factor is of a matrix that was (`factored`), whether it is of an earlier
    /// matrix than the values (`reused`), and how many refreshes have kept it (`age`).
    factored: bool,
    reused: bool,
    age: usize,
    /// Whether `x` holds the last solution (the next solve starts from it).
    has_solution: bool,
    /// Refreshes left before a factor may be kept again, and the next such pause.
    blocked: usize,
    /// The next refresh factors afresh ([`Mixed::refactor_next`]).
    fresh_next: bool,
    backoff: usize,
}

/// The longest pause in keeping factors after kept factors failed in a row.
pub const REUSE_MAX_BACKOFF: usize = 16;

/// A kept factor is replaced once the solve it preconditions needs more iterations than
/// this: about where the iterations cost as much as the factorization they avoid on a large
/// mesh (one iteration is a solve, roughly a tenth of a factorization at a million faces).
pub const REUSE_MAX_ITERATIONS: usize = 6;

/// Iterations after which a solve gives up on a kept factor and refactors (a fresh factor gets
/// [`MIXED_MAX_ITERATIONS`]).
pub const REUSE_GIVE_UP_ITERATIONS: usize = 6;

/// Refreshes a factor may be kept for before it is replaced anyway.
pub const REUSE_MAX_AGE: usize = 8;

impl Mixed {
    /// See [`Cholesky::set_quaternionic`]: the single-precision factor keeps the structure
    /// (rounding commutes with negation and conjugation).
    pub fn set_quaternionic(&mut self) -> bool {
        self.single.set_quaternionic()
    }

    pub fn analyze(pattern: &BlockPattern, vertex_fwd: &[usize]) -> Result<Self, SolverError> {
        let mut single = Cholesky::<c32>::analyze_with_vertex_order(pattern, 1, vertex_fwd)?;
        let triangle = single.take_triangle().ok_or_else(|| {
            SolverError::Symbolic("a fresh analysis holds its triangle's pattern".into())
        })?;
        let n = pattern.dim();
        let zeros = zeroed::<c64>;
        let single_rhs = zeroed::<c32>(n)?;
        Ok(Mixed {
            values: zeros(single.gather.len())?,
            single,
            triangle,
            norm: 0.0,
            x: zeros(n)?,
            r: zeros(n)?,
            z: zeros(n)?,
            p: zeros(n)?,
            ap: zeros(n)?,
            single_rhs,
            last_iterations: 0,
            gave_up_after: None,
            last_backward_error: 0.0,
            factored: false,
            reused: false,
            age: 0,
            has_solution: false,
            blocked: 0,
            fresh_next: false,
            backoff: 1,
        })
    }

    /// See [`Cholesky::triangle_slots`].
    pub fn triangle_slots(&self, nnz: usize) -> Vec<Option<(u32, bool)>> {
        self.single.triangle_slots(nnz)
    }

    /// See [`Cholesky::release_gather`] (the matrix is only ever assembled into
    /// [`Mixed::triangle_values_mut`]).
    pub fn release_gather(&mut self) {
        self.single.release_gather();
    }

    /// The matrix (double precision) in the layout of [`Mixed::triangle_slots`].
    pub fn triangle_values_mut(&mut self) -> &mut [c64] {
        &mut self.values
    }

    /// Take the matrix now in [`Mixed::triangle_values_mut`]: factor it, or, when
    /// `may_reuse` and the factor of an earlier matrix still preconditioned the last solve in
    /// at most [`REUSE_MAX_ITERATIONS`] iterations, keep that factor (issue 14: the flow's X
    /// changes little from step to step, and a few more iterations cost far less than a
    /// factorization). Fails where rounding to single precision leaves a pivot that is not
    /// positive (a matrix too close to singular for it).
    /// The next [`Mixed::refresh`] factors afresh, whatever the last solve took, without
    /// counting toward a pause after failed kept factors. For a matrix known to be far from
    /// the kept factor's: after the flow's safeguard rejects a try, the retry's X differs from
    /// the rejected one's by half of its ρ, and a kept factor stalled there.
    pub fn refactor_next(&mut self) {
        self.fresh_next = true;
    }

    pub fn refresh(&mut self, may_reuse: bool) -> Result<(), SolverError> {
        self.update_norm();
        if std::mem::take(&mut self.fresh_next) {
            return self.factorize();
        }
        let paused = self.blocked > 0;
        self.blocked = self.blocked.saturating_sub(1);
        if may_reuse
            && self.factored
            && !paused
            && self.age < REUSE_MAX_AGE
            && self.last_iterations <= REUSE_MAX_ITERATIONS
        {
            self.age += 1;
            self.reused = true;
            return Ok(());
        }
        self.factorize()
    }

    /// Whether the last [`Mixed::refresh`] kept an earlier factor.
    pub fn reused(&self) -> bool {
        self.reused
    }

    /// Factor the matrix now in [`Mixed::triangle_values_mut`] in single precision.
    pub fn factorize(&mut self) -> Result<(), SolverError> {
        self.factored = false;
        self.reused = false;
        self.age = 0;
        for (s, d) in self.single.triangle_values.iter_mut().zip(&self.values) {
            *s = c32::new(d.re as f32, d.im as f32);
        }
        self.single.factorize_triangle()?;
        self.factored = true;
        Ok(())
    }

    /// `‖A‖_∞` of the matrix now in the values (for the backward error).
    fn update_norm(&mut self) {
        let n = self.x.len();
        // ‖A‖_∞ from the triangle: every off-diagonal entry counts in its row and column.
        let row_sums = &mut self.z;
        row_sums.fill(c64::new(0.0, 0.0));
        let col_ptr = self.triangle.col_ptr();
        let row_idx = self.triangle.row_idx();
        for col in 0..n {
            for (&row, v) in row_idx[col_ptr[col]..col_ptr[col + 1]]
                .iter()
                .zip(&self.values[col_ptr[col]..col_ptr[col + 1]])
            {
                let m = v.norm();
                row_sums[row].re += m;
                if row != col {
                    row_sums[col].re += m;
                }
            }
        }
        self.norm = row_sums.iter().map(|s| s.re).fold(0.0, f64::max);
    }

    /// `x = P⁻¹ v` through the single-precision factor, in double precision.
    fn precondition(single: &mut Cholesky<c32>, buffer: &mut [c32], v: &[c64], x: &mut [c64]) {
        for (b, v) in buffer.iter_mut().zip(v) {
            *b = c32::new(v.re as f32, v.im as f32);
        }
        single.solve_in_place(buffer, 1);
        for (x, b) in x.iter_mut().zip(buffer.iter()) {
            *x = c64::new(f64::from(b.re), f64::from(b.im));
        }
    }

    /// Solve `A x = rhs` in place, to [`MIXED_TOLERANCE`], by conjugate gradients
    /// preconditioned with the single-precision factor. A kept factor that no longer does
    /// (see [`Mixed::refresh`]) is replaced by the factor of `A` and the solve run again.
    pub fn solve_in_place(&mut self, rhs: &mut [c64]) -> Result<(), NotConverged> {
        self.gave_up_after = None;
        // A stalled solve leaves `rhs` as it was.
        match self.conjugate_gradients(rhs) {
            Err(stalled) if self.reused => {
                // Where X moves too fast for a kept factor (large steps, retried steps), the
                // tries cost more than they save: skip the next 1, 2, 4, … refreshes.
                self.blocked = self.backoff;
                self.backoff = (2 * self.backoff).min(REUSE_MAX_BACKOFF);
                self.factorize().map_err(|_| stalled)?;
                self.conjugate_gradients(rhs)
            }
            Ok(()) if self.reused => {
                self.backoff = 1;
                Ok(())
            }
            other => other,
        }
    }

    fn conjugate_gradients(&mut self, rhs: &mut [c64]) -> Result<(), NotConverged> {
        if !self.factored {
            return Err(NotConverged {
                iterations: 0,
                backward_error: f64::INFINITY,
            });
        }
        let Mixed {
            single,
            triangle,
            values,
            norm,
            x,
            r,
            z,
            p,
            ap,
            single_rhs,
            has_solution,
            reused,
            gave_up_after,
            ..
        } = self;
        let dot = |a: &[c64], b: &[c64]| -> f64 {
            a.iter()
                .zip(b)
                .map(|(a, b)| a.re * b.re + a.im * b.im)
                .sum()
        };
        let b_norm = dot(rhs, rhs).sqrt();
        let backward_error = |r: &[c64], x: &[c64]| {
            let denominator = *norm * dot(x, x).sqrt() + b_norm;
            if denominator > 0.0 {
                dot(r, r).sqrt() / denominator
            } else {
                0.0
            }
        };
        // The start: with a kept factor, the last solution, scaled to fit this system best in
        // the energy norm (α = ⟨x, b⟩ / ⟨x, Ax⟩), where there is one: the flow solves nearly
        // the same system every step, and the start costs a product where P⁻¹b costs a solve.
        // A fresh factor's P⁻¹b is the solution to single precision, which the last one is
        // not: nefertiti's fresh factors took 2–3 iterations from the last solution, 1–2
        // from P⁻¹b.
        let warm = *has_solution && *reused && {
            triangle_matvec(triangle, &single.fwd, values, x, ap);
            let (xb, xax) = (dot(x, rhs), dot(x, ap));
            let alpha = xb / xax;
            let usable = xax > 0.0 && alpha.is_finite();
            if usable {
                for ((x, a), (r, b)) in x
                    .iter_mut()
                    .zip(ap.iter())
                    .zip(r.iter_mut().zip(rhs.iter()))
                {
                    *x *= alpha;
                    *r = b - a * alpha;
                }
            }
            usable
        };
        if !warm {
            Self::precondition(single, single_rhs, rhs, x);
            triangle_matvec(triangle, &single.fwd, values, x, ap);
            for ((r, b), a) in r.iter_mut().zip(rhs.iter()).zip(ap.iter()) {
                *r = b - a;
            }
        }
        let mut error = backward_error(r, x);
        let (start_error, mut best) = (error, error);
        let mut iterations = 0;
        if error > MIXED_TOLERANCE {
            Self::precondition(single, single_rhs, r, z);
            p.copy_from_slice(z);
            let mut rz = dot(r, z);
            // A kept factor that needs more than this is replaced at once: the iterations it
            // would still take cost more than a factorization.
            let limit = if *reused {
                REUSE_GIVE_UP_ITERATIONS
            } else {
                MIXED_MAX_ITERATIONS
            };
            while iterations < limit {
                iterations += 1;
                triangle_matvec(triangle, &single.fwd, values, p, ap);
                let pap = dot(p, ap);
                if !(pap > 0.0 && rz.is_finite()) {
                    break;
                }
                let alpha = rz / pap;
                for ((x, r), (p, ap)) in x.iter_mut().zip(r.iter_mut()).zip(p.iter().zip(ap.iter()))
                {
                    *x += p * alpha;
                    *r -= ap * alpha;
                }
                error = backward_error(r, x);
                if error <= MIXED_TOLERANCE {
                    break;
                }
                best = best.min(error);
                if *reused
                    && iterations >= 2
                    && kept_factor_is_hopeless(start_error, best, iterations)
                {
                    *gave_up_after = Some(iterations);
                    break;
                }
                Self::precondition(single, single_rhs, r, z);
                let rz_next = dot(r, z);
                let beta = rz_next / rz;
                rz = rz_next;
                for (p, z) in p.iter_mut().zip(z.iter()) {
                    *p = z + *p * beta;
                }
            }
        }
        self.last_iterations = iterations;
        self.last_backward_error = error;
        self.has_solution = error <= MIXED_TOLERANCE;
        if error <= MIXED_TOLERANCE {
            rhs.copy_from_slice(&self.x);
            Ok(())
        } else {
            Err(NotConverged {
                iterations,
                backward_error: error,
            })
        }
    }

    /// `y = A x` with the double-precision matrix.
    pub fn hermitian_matvec(&self, x: &[c64], y: &mut [c64]) {
        triangle_matvec(&self.triangle, &self.single.fwd, &self.values, x, y);
    }

    /// Free the factor and the matrix (before a double-precision factor takes their place).
    pub fn release(&mut self) {
        self.single.factor = Vec::new();
        self.single.triangle_values = Vec::new();
        self.values = Vec::new();
    }

    /// See [`Cholesky::set_threads`].
    pub fn set_threads(&mut self, threads: usize) {
        self.single.set_threads(threads);
    }

    /// Entries of the (single-precision) factor.
    pub fn factor_len(&self) -> usize {
        self.single.factor_len()
    }
}
