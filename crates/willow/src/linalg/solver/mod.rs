//! Sparse Cholesky on a pattern that never changes during a flow.
//!
//! The flows never change connectivity, so the sparsity pattern, its fill-reducing ordering and
//! faer's symbolic factorization are built once per flow; each step only scatters new values
//! into the fixed pattern and refactors numerically in place (docs/solver.md: building from
//! triplets costs more than the factorization itself).
//!
//! [`BlockPattern`] (`pattern.rs`) is the fixed pattern, [`Cholesky`] (`cholesky.rs`) the
//! factorization reused across steps, [`Mixed`] (`mixed.rs`) its mixed-precision form.

mod cholesky;
mod mixed;
mod pattern;

pub use cholesky::*;
pub use mixed::*;
pub use pattern::*;

#[cfg(test)]
pub(crate) mod tests;
