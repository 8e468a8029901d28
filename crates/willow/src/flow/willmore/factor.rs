//! The Dirac matrix's factor, double or mixed precision, and the choice between them.

use super::*;
use crate::flow::Precision;
use crate::linalg::solver::{Cholesky, Mixed, NotConverged, SolverError};
use faer::c64;

/// The factor of the Dirac matrix X: double precision, or single precision solved to double
/// precision by preconditioned conjugate gradients ([`Mixed`]) on large closed surfaces.
pub(super) enum DiracFactor {
    Double(Box<Cholesky<c64>>),
    Mixed(Box<Mixed>),
}

impl DiracFactor {
    pub(super) fn set_threads(&mut self, threads: usize) {
        match self {
            DiracFactor::Double(d) => d.set_threads(threads),
            DiracFactor::Mixed(m) => m.set_threads(threads),
        }
    }

    pub(super) fn triangle_values_mut(&mut self) -> &mut [c64] {
        match self {
            DiracFactor::Double(d) => d.triangle_values_mut(),
            DiracFactor::Mixed(m) => m.triangle_values_mut(),
        }
    }

    pub(super) fn triangle_slots(&self, nnz: usize) -> Vec<Option<(u32, bool)>> {
        match self {
            DiracFactor::Double(d) => d.triangle_slots(nnz),
            DiracFactor::Mixed(m) => m.triangle_slots(nnz),
        }
    }

    /// Once the assembly has its slots: see [`Cholesky::release_gather`].
    pub(super) fn release_gather(&mut self) {
        match self {
            DiracFactor::Double(d) => d.release_gather(),
            DiracFactor::Mixed(m) => m.release_gather(),
        }
    }

    pub(super) fn factorize_triangle(&mut self) -> Result<(), SolverError> {
        match self {
            DiracFactor::Double(d) => d.factorize_triangle(),
            // X changes little from step to step: its last factor may precondition this one.
            DiracFactor::Mixed(m) => m.refresh(true),
        }
    }

    /// One right-hand side.
    pub(super) fn solve_in_place(&mut self, rhs: &mut [c64]) -> Result<(), NotConverged> {
        match self {
            DiracFactor::Double(d) => {
                d.solve_in_place(rhs, 1);
                Ok(())
            }
            DiracFactor::Mixed(m) => m.solve_in_place(rhs),
        }
    }

    #[cfg(test)]
    pub(super) fn hermitian_matvec(&self, x: &[c64], y: &mut [c64]) {
        match self {
            DiracFactor::Double(d) => d.hermitian_matvec(x, y),
            DiracFactor::Mixed(m) => m.hermitian_matvec(x, y),
        }
    }

    /// The double-precision factor, which the exactness constraints and the fixed boundary
    /// need (they are never given the mixed one).
    pub(super) fn double_mut(&mut self) -> Option<&mut Cholesky<c64>> {
        match self {
            DiracFactor::Double(d) => Some(&mut **d),
            DiracFactor::Mixed(_) => None,
        }
    }
}

/// Whether X is factored in single precision ([`Mixed`]) on a surface of `n` vertices.
pub(super) fn mixed_precision_for(n: usize, precision: Precision) -> bool {
    match precision {
        Precision::Auto => n >= MIXED_MIN_VERTICES,
        Precision::Double => false,
        Precision::Mixed => true,
    }
}
