//! Dirichlet conditions on a fixed pattern (§6.3.2): "moving boundary columns to the
//! right-hand side" without changing the sparsity pattern. For every fixed vertex `b`, its
//! off-diagonal blocks are zeroed (their products with the prescribed value go to the
//! right-hand side of the free rows), its diagonal block becomes the identity, and its
//! right-hand side becomes the prescribed value. The matrix stays Hermitian positive
//! definite, the free block is exactly the original one, and the solve returns the
//! prescribed values unchanged at fixed vertices.

use crate::linalg::solver::BlockPattern;
use faer::c64;

/// Apply to a block-2 complex matrix whose unknowns are quaternions in complex form:
/// `prescribed(b)` is the complex column of the fixed value at vertex `b`. The right-hand side
/// is updated only when given (a refactorization with a new diagonal shift reuses it: the
/// shift never touches the off-diagonal blocks that are moved).
pub fn apply_complex(
    pattern: &BlockPattern,
    values: &mut [c64],
    fixed: &[bool],
    prescribed: impl Fn(usize) -> [c64; 2],
    mut rhs: Option<&mut [c64]>,
) {
    let col_ptr = pattern.symbolic.col_ptr();
    let row_idx = pattern.symbolic.row_idx();
    for col in 0..pattern.dim() {
        let vc = col / 2;
        for idx in col_ptr[col]..col_ptr[col + 1] {
            let row = row_idx[idx];
            let vr = row / 2;
            if !(fixed[vc] || fixed[vr]) {
                continue;
            }
            if let Some(rhs) = rhs.as_deref_mut() {
                if fixed[vc] && !fixed[vr] {
                    rhs[row] -= values[idx] * prescribed(vc)[col % 2];
                }
            }
            values[idx] = if row == col {
                c64::new(1.0, 0.0)
            } else {
                c64::new(0.0, 0.0)
            };
        }
    }
    if let Some(rhs) = rhs {
        for (v, &f) in fixed.iter().enumerate() {
            if f {
                let z = prescribed(v);
                rhs[2 * v] = z[0];
                rhs[2 * v + 1] = z[1];
            }
        }
    }
}

/// Apply to a block-1 real matrix solved for `k` column-major right-hand sides of length `n`:
/// `prescribed(b, j)` is the fixed value of column `j` at vertex `b`.
pub fn apply_real(
    pattern: &BlockPattern,
    values: &mut [f64],
    fixed: &[bool],
    prescribed: impl Fn(usize, usize) -> f64,
    mut rhs: Option<&mut [f64]>,
    k: usize,
) {
    let n = pattern.dim();
    let col_ptr = pattern.symbolic.col_ptr();
    let row_idx = pattern.symbolic.row_idx();
    for col in 0..n {
        for idx in col_ptr[col]..col_ptr[col + 1] {
            let row = row_idx[idx];
            if !(fixed[col] || fixed[row]) {
                continue;
            }
            if let Some(rhs) = rhs.as_deref_mut() {
                if fixed[col] && !fixed[row] {
                    for j in 0..k {
                        rhs[j * n + row] -= values[idx] * prescribed(col, j);
                    }
                }
            }
            values[idx] = if row == col { 1.0 } else { 0.0 };
        }
    }
    if let Some(rhs) = rhs {
        for (v, &f) in fixed.iter().enumerate() {
            if f {
                for j in 0..k {
                    rhs[j * n + v] = prescribed(v, j);
                }
            }
        }
    }
}
