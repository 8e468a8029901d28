//! The spectral filter of §4: `v ← v − (id + σ(−Δ)^k)⁻¹ v`, which damps the low-frequency part
//! of the flow direction so large features shrink more slowly than small bumps (Figure 19;
//! k = 2 approximates position-based Willmore flow).
//!
//! With the PSD cotan Laplacian `L` and lumped mass `M` (`−Δ = M⁻¹L`), the weak form is
//! `(M + σ L (M⁻¹L)^{k−1}) x = M v`, an SPD system (docs/algorithm.md §8); a mode of `−Δ` with
//! eigenvalue μ keeps the fraction `σμ^k / (1 + σμ^k)` of its speed. σ is given unitless:
//! internally it is `σ · R^{2k}` with `R² = area / 4π`, so on a unit sphere (where the
//! eigenvalues of −Δ are l(l+1)) σ = (l(l+1))^{−k} puts the crossover at spherical degree l,
//! whatever the mesh's size or resolution.
//!
//! The products `L (M⁻¹L)^{j}` have fixed patterns (the j-ring): their symbolic products and
//! the Cholesky analysis are done once, the numeric products and factorization every step.

use crate::linalg::solver::{BlockPattern, Cholesky};
use faer::sparse::linalg::matmul::{
    sparse_sparse_matmul_numeric, sparse_sparse_matmul_symbolic, SparseMatMulInfo,
};
use faer::sparse::{SparseColMatMut, SparseColMatRef, SymbolicSparseColMat};
use faer::{Accum, Par};
use serde::{Deserialize, Serialize};

/// Largest filter order k: [`FilterSolver`] builds `L (M⁻¹L)^{k−1}` for k ≤ 3.
pub const MAX_K: u32 = 3;

/// Filter parameters (§4): strength σ (unitless, see the module docs) and shape k ∈ 0..=3.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SpectralFilter {
    pub sigma: f64,
    pub k: u32,
}

/// Why a filter could not be set up or applied.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FilterError {
    #[error("filter k must be 0, 1, 2 or 3, got {0}")]
    BadOrder(u32),
    #[error("filter sigma must be a positive finite number, got {0}")]
    BadSigma(f64),
    #[error("filter system: {0}")]
    Solver(String),
}

struct Product {
    symbolic: SymbolicSparseColMat<usize>,
    info: SparseMatMulInfo,
    values: Vec<f64>,
}

pub struct FilterSolver {
    filter: SpectralFilter,
    /// `L` and `M⁻¹L` on the one-ring pattern.
    laplacian: Vec<f64>,
    scaled: Vec<f64>,
    /// `L (M⁻¹L)^j` for j = 1..k−1.
    products: Vec<Product>,
    /// The system matrix `M + σ P_k` on P_k's pattern, and where its diagonal lives.
    system: Vec<f64>,
    diagonal: Vec<usize>,
    cholesky: Option<Cholesky<f64>>,
    rhs: Vec<f64>,
    scratch: faer::dyn_stack::MemBuffer,
    /// σ in model units (`σ · R^{2k}`) of the last [`FilterSolver::apply`].
    sigma_used: f64,
}

impl FilterSolver {
    pub fn new(pattern: &BlockPattern, filter: SpectralFilter) -> Result<Self, FilterError> {
        if filter.k > MAX_K {
            return Err(FilterError::BadOrder(filter.k));
        }
        if !(filter.sigma.is_finite() && filter.sigma > 0.0) {
            return Err(FilterError::BadSigma(filter.sigma));
        }
        debug_assert_eq!(pattern.block, 1);
        let n = pattern.dim();
        let one_ring = pattern.symbolic.clone();
        let mut products: Vec<Product> = Vec::new();
        for _ in 1..filter.k.max(1) {
            let lhs = products
                .last()
                .map_or(one_ring.as_ref(), |p| p.symbolic.as_ref());
            let (symbolic, info) = sparse_sparse_matmul_symbolic(lhs, one_ring.as_ref())
                .map_err(|e| FilterError::Solver(format!("{e:?}")))?;
            let values = vec![0.0; symbolic.row_idx().len()];
            products.push(Product {
                symbolic,
                info,
                values,
            });
        }
        let final_pattern = products
            .last()
            .map_or(one_ring.as_ref(), |p| p.symbolic.as_ref());
        let mut diagonal = Vec::with_capacity(n);
        for j in 0..n {
            let range = final_pattern.col_ptr()[j]..final_pattern.col_ptr()[j + 1];
            let rows = &final_pattern.row_idx()[range.clone()];
            let k = rows
                .binary_search(&j)
                .map_err(|_| FilterError::Solver("pattern misses a diagonal entry".into()))?;
            diagonal.push(range.start + k);
        }
        let cholesky = if filter.k == 0 {
            None
        } else {
            Some(
                Cholesky::analyze_pattern(final_pattern, 1)
                    .map_err(|e| FilterError::Solver(e.to_string()))?,
            )
        };
        let max_nrows = n;
        let scratch = faer::dyn_stack::MemBuffer::try_new(
            faer::sparse::linalg::matmul::sparse_sparse_matmul_numeric_scratch::<usize, f64>(
                final_pattern,
                Par::Seq,
            ),
        )
        .map_err(|_| FilterError::Solver("out of memory".into()))?;
        let system_len = final_pattern.row_idx().len();
        Ok(FilterSolver {
            filter,
            laplacian: vec![0.0; pattern.nnz()],
            scaled: vec![0.0; pattern.nnz()],
            products,
            system: vec![0.0; system_len],
            diagonal,
            cholesky,
            rhs: vec![0.0; max_nrows],
            scratch,
            sigma_used: filter.sigma,
        })
    }

    /// Filter `v` in place on the current surface: `laplacian_values` is L on `pattern`
    /// (unshifted), `areas` the lumped mass.
    pub fn apply(
        &mut self,
        pattern: &BlockPattern,
        laplacian_values: &[f64],
        areas: &[f64],
        v: &mut [f64],
    ) -> Result<(), FilterError> {
        let k = self.filter.k as i32;
        let total_area: f64 = areas.iter().sum();
        let radius2 = total_area / (4.0 * std::f64::consts::PI);
        let sigma = self.filter.sigma * radius2.powi(k);
        if k == 0 {
            // Δ⁰ = id: the filter only rescales, v ← σ/(1+σ) v.
            for x in v.iter_mut() {
                *x *= sigma / (1.0 + sigma);
            }
            return Ok(());
        }
        self.laplacian.copy_from_slice(laplacian_values);
        // M⁻¹L: row i scaled by 1/A_i.
        let rows = pattern.symbolic.row_idx();
        for (s, (&l, &r)) in self.scaled.iter_mut().zip(self.laplacian.iter().zip(rows)) {
            *s = l / areas[r];
        }
        let one_ring = pattern.symbolic.as_ref();
        let scaled = SparseColMatRef::new(one_ring, &self.scaled);
        for j in 0..self.products.len() {
            let (done, rest) = self.products.split_at_mut(j);
            let p = &mut rest[0];
            let lhs = match done.last() {
                Some(prev) => SparseColMatRef::new(prev.symbolic.as_ref(), &prev.values),
                None => SparseColMatRef::new(one_ring, &self.laplacian),
            };
            sparse_sparse_matmul_numeric(
                SparseColMatMut::new(p.symbolic.as_ref(), &mut p.values),
                Accum::Replace,
                lhs,
                scaled,
                1.0,
                &p.info,
                Par::Seq,
                faer::dyn_stack::MemStack::new(&mut self.scratch),
            );
        }
        let (final_pattern, final_values) = match self.products.last() {
            Some(p) => (p.symbolic.as_ref(), p.values.as_slice()),
            None => (one_ring, self.laplacian.as_slice()),
        };
        for (s, &p) in self.system.iter_mut().zip(final_values) {
            *s = sigma * p;
        }
        for (i, &d) in self.diagonal.iter().enumerate() {
            self.system[d] += areas[i];
        }
        let cholesky = self
            .cholesky
            .as_mut()
            .ok_or_else(|| FilterError::Solver("no factorization for k ≥ 1".into()))?;
        cholesky
            .factorize_matrix(SparseColMatRef::new(final_pattern, &self.system))
            .map_err(|e| FilterError::Solver(e.to_string()))?;
        for ((r, x), &a) in self.rhs.iter_mut().zip(v.iter()).zip(areas) {
            *r = a * x;
        }
        cholesky.solve_in_place(&mut self.rhs, 1);
        for (x, r) in v.iter_mut().zip(&self.rhs) {
            *x -= r;
        }
        self.sigma_used = sigma;
        Ok(())
    }

    /// The regularized (low-frequency) part `(id + σ(−Δ)^k)⁻¹ v` of `v`, in place, with the
    /// operator of the last [`FilterSolver::apply`] (its factorization is reused).
    pub fn low_pass(&mut self, areas: &[f64], v: &mut [f64]) -> Result<(), FilterError> {
        if self.filter.k == 0 {
            for x in v.iter_mut() {
                *x /= 1.0 + self.sigma_used;
            }
            return Ok(());
        }
        let cholesky = self
            .cholesky
            .as_mut()
            .ok_or_else(|| FilterError::Solver("no factorization for k ≥ 1".into()))?;
        for (x, &a) in v.iter_mut().zip(areas) {
            *x *= a;
        }
        cholesky.solve_in_place(v, 1);
        Ok(())
    }
}
