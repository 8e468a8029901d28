//! Preconditioned conjugate gradients with a factor of a nearby matrix as the preconditioner.
//!
//! The absorbing rounds of a region's λ solve (`pinned.rs`) change X (through ρ) and the
//! δ-system (through λ) by a little each round. Refactoring both every round made a region
//! step cost 29% of a whole-mesh step on nefertiti (issue 29 asks ≤ 15%); solving the changed
//! system to a tight residual with the step's first factor as the preconditioner gives the
//! same answer (to the tolerance) at the cost of a few triangular solves and products.

use faer::c64;
use std::ops::{Add, Mul, Sub};

/// The relative residual `|A x − b| / |b|` a refined solve stops at when its result is the
/// step's: far below what the step's own error allows, so the result is the direct solve's
/// to rounding.
pub(super) const REFINE_TOLERANCE: f64 = 1e-11;
/// The same for a λ that only steers the next absorbing round's δ (`pinned.rs`): δ is
/// linear in it, so a relative error of 1e-7 moves δ by as little, far below the step's
/// own first-order error; measured on nefertiti's 5% region, it halves the iterations
/// (4–5 instead of 7–10 per solve).
pub(super) const STEER_TOLERANCE: f64 = 1e-7;
/// A nearby factor needs a handful of iterations; more means the matrix moved too far, and
/// the caller refactors.
pub(super) const REFINE_MAX_ITERATIONS: usize = 40;

/// A scalar of a Hermitian positive definite system: real or complex.
pub(super) trait Field:
    Copy + Default + Add<Output = Self> + Sub<Output = Self> + Mul<f64, Output = Self>
{
    /// `Re(conj(a) b)`.
    fn re_dot(a: Self, b: Self) -> f64;
}

impl Field for f64 {
    fn re_dot(a: f64, b: f64) -> f64 {
        a * b
    }
}

impl Field for c64 {
    fn re_dot(a: c64, b: c64) -> f64 {
        a.re * b.re + a.im * b.im
    }
}

/// The work vectors of [`refine`], allocated once per flow (no allocation per step).
#[derive(Default)]
pub(super) struct Scratch<T> {
    b: Vec<T>,
    r: Vec<T>,
    z: Vec<T>,
    p: Vec<T>,
    q: Vec<T>,
}

impl<T: Field> Scratch<T> {
    pub(super) fn new(len: usize) -> Self {
        let zero = || vec![T::default(); len];
        Self {
            b: zero(),
            r: zero(),
            z: zero(),
            p: zero(),
            q: zero(),
        }
    }
}

fn dot<T: Field>(a: &[T], b: &[T]) -> f64 {
    a.iter().zip(b).map(|(&x, &y)| T::re_dot(x, y)).sum()
}

/// Solves `A x = b` in place (`x` holds b on entry, the solution on return) by conjugate
/// gradients preconditioned with `solve` (a factor of a matrix near A), starting from
/// `solve(b)`. Returns false when the residual is not below `tolerance` (relative) after
/// [`REFINE_MAX_ITERATIONS`]; x then holds b again, for a direct solve.
pub(super) fn refine<T: Field>(
    matvec: impl FnMut(&[T], &mut [T]),
    solve: impl FnMut(&mut [T]),
    x: &mut [T],
    s: &mut Scratch<T>,
    tolerance: f64,
) -> bool {
    s.b.copy_from_slice(x);
    let converged = iterate(matvec, solve, x, s, tolerance);
    if !converged {
        x.copy_from_slice(&s.b);
    }
    converged
}

/// [`refine`]'s iteration, with b in `s.b`.
fn iterate<T: Field>(
    mut matvec: impl FnMut(&[T], &mut [T]),
    mut solve: impl FnMut(&mut [T]),
    x: &mut [T],
    s: &mut Scratch<T>,
    tolerance: f64,
) -> bool {
    let b_norm = dot(&s.b, &s.b).sqrt();
    if b_norm == 0.0 {
        return true;
    }
    solve(x);
    matvec(x, &mut s.q);
    for ((r, &b), &q) in s.r.iter_mut().zip(&s.b).zip(&s.q) {
        *r = b - q;
    }
    s.z.copy_from_slice(&s.r);
    solve(&mut s.z);
    s.p.copy_from_slice(&s.z);
    let mut rz = dot(&s.r, &s.z);
    for _ in 0..=REFINE_MAX_ITERATIONS {
        let r_norm = dot(&s.r, &s.r).sqrt();
        if !r_norm.is_finite() {
            return false;
        }
        if r_norm <= tolerance * b_norm {
            return true;
        }
        matvec(&s.p, &mut s.q);
        let pq = dot(&s.p, &s.q);
        // Not positive (or NaN): the matrix is not the SPD one the factor preconditions.
        if pq.is_nan() || pq <= 0.0 {
            return false;
        }
        let alpha = rz / pq;
        for ((xi, &p), (ri, &q)) in x.iter_mut().zip(&s.p).zip(s.r.iter_mut().zip(&s.q)) {
            *xi = *xi + p * alpha;
            *ri = *ri - q * alpha;
        }
        s.z.copy_from_slice(&s.r);
        solve(&mut s.z);
        let rz_next = dot(&s.r, &s.z);
        let beta = rz_next / rz;
        rz = rz_next;
        for (p, &z) in s.p.iter_mut().zip(&s.z) {
            *p = z + *p * beta;
        }
    }
    false
}

/// `y = A x` for a matrix stored on a full (both triangles) pattern.
pub(super) fn matvec<T: Field + Mul<T, Output = T>>(
    pattern: &crate::linalg::solver::BlockPattern,
    values: &[T],
    x: &[T],
    y: &mut [T],
) {
    y.fill(T::default());
    let col_ptr = pattern.symbolic.col_ptr();
    let row_idx = pattern.symbolic.row_idx();
    for (col, &xc) in x.iter().enumerate() {
        for idx in col_ptr[col]..col_ptr[col + 1] {
            y[row_idx[idx]] = y[row_idx[idx]] + values[idx] * xc;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 1-D Laplacian plus a diagonal, preconditioned by the exact inverse of a perturbed
    /// copy (dense, written here): the refined solution satisfies the original system.
    #[test]
    fn refine_solves_the_system_a_nearby_factor_preconditions() {
        let n = 12;
        let a = |i: usize, j: usize, d: f64| -> f64 {
            if i == j {
                2.0 + d * (1.0 + i as f64 / n as f64)
            } else if i.abs_diff(j) == 1 {
                -1.0
            } else {
                0.0
            }
        };
        // Dense inverse of the perturbed matrix (d = 0.3 instead of 0.2) by Gauss–Jordan.
        let mut m: Vec<Vec<f64>> = (0..n)
            .map(|i| {
                let mut row: Vec<f64> = (0..n).map(|j| a(i, j, 0.3)).collect();
                row.extend((0..n).map(|j| f64::from(u8::from(i == j))));
                row
            })
            .collect();
        for c in 0..n {
            let pivot = m[c][c];
            for v in m[c].iter_mut() {
                *v /= pivot;
            }
            for r in 0..n {
                if r != c {
                    let f = m[r][c];
                    let pivot_row = m[c].clone();
                    for (v, p) in m[r].iter_mut().zip(pivot_row) {
                        *v -= f * p;
                    }
                }
            }
        }
        let inverse: Vec<Vec<f64>> = m.iter().map(|row| row[n..].to_vec()).collect();
        let b: Vec<f64> = (0..n).map(|i| (i as f64 * 0.7).sin() + 0.1).collect();
        let mut x = b.clone();
        let mut scratch = Scratch::new(n);
        let ok = refine(
            |x: &[f64], y: &mut [f64]| {
                for (i, yi) in y.iter_mut().enumerate() {
                    *yi = (0..n).map(|j| a(i, j, 0.2) * x[j]).sum();
                }
            },
            |v: &mut [f64]| {
                let w: Vec<f64> = (0..n)
                    .map(|i| (0..n).map(|j| inverse[i][j] * v[j]).sum())
                    .collect();
                v.copy_from_slice(&w);
            },
            &mut x,
            &mut scratch,
            REFINE_TOLERANCE,
        );
        assert!(ok);
        for (i, bi) in b.iter().enumerate() {
            let ax: f64 = (0..n).map(|j| a(i, j, 0.2) * x[j]).sum();
            assert!((ax - bi).abs() < 1e-9, "row {i}: {ax} vs {bi}");
        }
    }
}
