//! The Cholesky factorization on a [`BlockPattern`]: ordering and symbolic analysis once per
//! flow, a numeric refactorization in place each step (our supernodal kernel where the CPU has
//! AVX2 and FMA, faer's otherwise), and the solves.

use super::*;
use crate::linalg::ordering::Ordering;
use crate::linalg::supernodal::{NotPositive, Scalar, SolveScratch, SupernodalLlt};
use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::llt::factor::LltError;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, LltRef, SymbolicCholesky,
    SymbolicCholeskyRaw, SymmetricOrdering,
};
use faer::sparse::linalg::{amd, SupernodalThreshold, SymbolicSupernodalParams};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};
use faer::{c64, Conj, MatMut, Par, Side};

/// Supernode relaxation (faer's `relax` table: adjacent supernodes of `n` columns in all
/// merge while their explicit zeros stay below the given fraction) for a pattern whose
/// columns come in groups of `block`.
///
/// For scalar patterns, faer's default. For X's 2×2 blocks every fundamental supernode
/// already spans whole vertices (two columns each), and faer's default, tuned for scalar
/// columns, merges vertices up to 48 columns at up to 80% zeros: 12% of X's factor were
/// explicit zeros at nefertiti (7.00M entries against 6.13M, 14 MB; issue 14). Merging
/// only single vertices into pairs (up to 4 columns) keeps the speed of the default
/// (`willow bench`, nefertiti: X factor 143.5, 141.0 ms against 143.6, 145.9 ms, λ solve
/// 32.6, 30.1 against 34.5, 38.2), where no merging at all costs 15% (169, 161 ms).
pub fn supernodal_params(block: usize) -> SymbolicSupernodalParams<'static> {
    if block == 2 {
        SymbolicSupernodalParams {
            relax: Some(&[(4, 1.0)]),
        }
    } else {
        SymbolicSupernodalParams::default()
    }
}

/// Why a factorization failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SolverError {
    #[error("symbolic analysis failed: {0}")]
    Symbolic(String),
    #[error("matrix is not numerically positive definite ({0})")]
    NotPositiveDefinite(String),
    #[error("out of memory for the factorization workspace")]
    OutOfMemory,
}

/// A sparse LLᴴ factorization whose ordering, symbolic part and workspaces are built once.
///
/// The fill-reducing permutation is applied once, at analysis: the analysis precomputes the
/// permuted triangle (`P A Pᵀ`, the side faer's numeric kernel reads) together with the index
/// of each of its entries in the caller's full-storage values. Each refactorization is then a
/// plain gather into that triangle, and faer runs with the identity ordering, so it neither
/// permutes nor transposes the matrix per call (its per-call permutation rebuilds the whole
/// permuted pattern, indices included). The solve applies the permutation to the right-hand sides itself.
pub struct Cholesky<T> {
    symbolic: SymbolicCholesky<usize>,
    pub(super) factor: Vec<T>,
    factor_mem: MemBuffer,
    solve_mem: MemBuffer,
    nrhs: usize,
    /// `fwd[new] = old` and its inverse.
    pub(super) fwd: Vec<usize>,
    inv: Vec<usize>,
    /// The triangle of `P A Pᵀ` faer's numeric factorization reads (lower for supernodal,
    /// upper for simplicial). `None` once [`Cholesky::release_triangle`] freed it (our own
    /// kernel reads the values through [`SupernodalLlt`]'s positions instead).
    side: Side,
    pub(super) triangle: Option<SymbolicSparseColMat<usize>>,
    /// `triangle_values[k] = values[gather[k]]`.
    pub(super) gather: Vec<usize>,
    pub(super) triangle_values: Vec<T>,
    /// Right-hand sides in the permuted order, `n × nrhs` column-major.
    permuted_rhs: Vec<T>,
    /// Our numeric kernel for supernodal factorizations (`None`: faer's, see
    /// [`SupernodalLlt`]).
    pub(super) supernodal: Option<SupernodalLlt>,
    /// Threads the numeric factorization may use (independent subtrees run concurrently).
    threads: usize,
    /// Scratch of the quaternionic solve ([`SupernodalLlt::solve_quaternionic`]), sized by
    /// [`Cholesky::set_quaternionic`].
    solve_scratch: SolveScratch<T>,
}

impl<T: Scalar> Cholesky<T> {
    /// Symbolic analysis of `pattern` for up to `nrhs` right-hand sides per solve, its vertex
    /// graph ordered by the ordering that measured best at its size.
    pub fn analyze(pattern: &BlockPattern, nrhs: usize) -> Result<Self, SolverError> {
        let ordering = Ordering::for_vertices(pattern.vertex_col_ptr.len() - 1);
        Self::analyze_with(pattern, nrhs, ordering)
    }

    /// [`Cholesky::analyze`] with a vertex ordering computed beforehand
    /// ([`BlockPattern::vertex_order`], `fwd[new] = old`) for a pattern of the same mesh.
    pub fn analyze_with_vertex_order(
        pattern: &BlockPattern,
        nrhs: usize,
        vertex_fwd: &[usize],
    ) -> Result<Self, SolverError> {
        Self::analyze_with_vertex_order_as(pattern, nrhs, vertex_fwd, SupernodalThreshold::AUTO)
    }

    /// [`Cholesky::analyze_with_vertex_order`], supernodal whatever the size: faer's
    /// automatic choice (by flops per factor entry) makes the factor of a small mesh
    /// simplicial, which is faer's scalar kernel, neither our vectorized one nor the
    /// quaternionic halving ([`Cholesky::set_quaternionic`]). A region's flow (issue 29)
    /// factors X twice a step on a few thousand vertices and solves with it in every
    /// refining round: the simplicial factor of X made nefertiti's 5% region step 16–18% of
    /// the whole mesh's (`willow bench`: X factor 23–43 ms of a try, 4 ms supernodal).
    pub fn analyze_supernodal_with_vertex_order(
        pattern: &BlockPattern,
        nrhs: usize,
        vertex_fwd: &[usize],
    ) -> Result<Self, SolverError> {
        Self::analyze_with_vertex_order_as(
            pattern,
            nrhs,
            vertex_fwd,
            SupernodalThreshold::FORCE_SUPERNODAL,
        )
    }

    fn analyze_with_vertex_order_as(
        pattern: &BlockPattern,
        nrhs: usize,
        vertex_fwd: &[usize],
        threshold: SupernodalThreshold,
    ) -> Result<Self, SolverError> {
        if vertex_fwd.len() != pattern.vertex_col_ptr.len() - 1 {
            return Err(SolverError::Symbolic(
                "the vertex ordering is for another mesh".into(),
            ));
        }
        let (fwd, inv) = pattern.expand_order(vertex_fwd);
        Self::with_ordering(
            pattern.symbolic.as_ref(),
            pattern.block,
            (fwd, inv),
            nrhs,
            threshold,
        )
    }

    /// [`Cholesky::analyze`] with the vertex graph ordered by `ordering`.
    pub fn analyze_with(
        pattern: &BlockPattern,
        nrhs: usize,
        ordering: Ordering,
    ) -> Result<Self, SolverError> {
        let (fwd, inv) = pattern
            .block_order(ordering)
            .map_err(|e| SolverError::Symbolic(e.to_string()))?;
        Self::with_ordering(
            pattern.symbolic.as_ref(),
            pattern.block,
            (fwd, inv),
            nrhs,
            SupernodalThreshold::AUTO,
        )
    }

    /// Symbolic analysis of an arbitrary symmetric pattern (both triangles stored), ordered by
    /// faer's AMD, for patterns that are not one vertex ring (e.g. `L M⁻¹ L`).
    pub fn analyze_pattern(
        pattern: faer::sparse::SymbolicSparseColMatRef<'_, usize>,
        nrhs: usize,
    ) -> Result<Self, SolverError> {
        let n = pattern.nrows();
        let mut fwd = vec![0usize; n];
        let mut inv = vec![0usize; n];
        let mut mem = MemBuffer::try_new(amd::order_scratch::<usize>(n, pattern.row_idx().len()))
            .map_err(|_| SolverError::OutOfMemory)?;
        amd::order(
            &mut fwd,
            &mut inv,
            pattern,
            amd::Control::default(),
            MemStack::new(&mut mem),
        )
        .map_err(|e| SolverError::Symbolic(format!("{e:?}")))?;
        drop(mem);
        Self::with_ordering(pattern, 1, (fwd, inv), nrhs, SupernodalThreshold::AUTO)
    }

    /// `block`: the pattern's columns come in groups of this many (see
    /// [`supernodal_params`]); `threshold`: faer's choice between simplicial and supernodal.
    fn with_ordering(
        pattern: faer::sparse::SymbolicSparseColMatRef<'_, usize>,
        block: usize,
        (fwd, inv): (Vec<usize>, Vec<usize>),
        nrhs: usize,
        threshold: SupernodalThreshold,
    ) -> Result<Self, SolverError> {
        let n = pattern.nrows();
        // Only the upper triangle is analyzed (faer's contract with the identity ordering).
        let (upper, _) = permuted_triangle(pattern, &inv, Side::Upper);
        let symbolic = factorize_symbolic_cholesky(
            upper.as_ref(),
            Side::Upper,
            SymmetricOrdering::Identity,
            CholeskySymbolicParams {
                supernodal_flop_ratio_threshold: threshold,
                supernodal_params: supernodal_params(block),
                ..Default::default()
            },
        )
        .map_err(|e| SolverError::Symbolic(format!("{e:?}")))?;
        // The side faer's numeric kernel works on: anything else costs it a transpose per call.
        let (side, (triangle, gather)) = match symbolic.raw() {
            SymbolicCholeskyRaw::Supernodal(_) => {
                drop(upper);
                (Side::Lower, permuted_triangle(pattern, &inv, Side::Lower))
            }
            SymbolicCholeskyRaw::Simplicial(_) => {
                let gather = permuted_triangle(pattern, &inv, Side::Upper).1;
                (Side::Upper, (upper, gather))
            }
        };
        let solve_mem = MemBuffer::try_new(symbolic.solve_in_place_scratch::<T>(nrhs, Par::Seq))
            .map_err(|_| SolverError::OutOfMemory)?;
        let zeros = zeroed::<T>;
        let supernodal = match symbolic.raw() {
            SymbolicCholeskyRaw::Supernodal(supernodal) => {
                SupernodalLlt::new::<T>(supernodal, triangle.as_ref())
            }
            SymbolicCholeskyRaw::Simplicial(_) => None,
        };
        // faer's numeric scratch (20 MB for X at 100k triangles) only where faer factors.
        let factor_mem = MemBuffer::try_new(match supernodal {
            Some(_) => StackReq::EMPTY,
            None => symbolic.factorize_numeric_llt_scratch::<T>(Par::Seq, Default::default()),
        })
        .map_err(|_| SolverError::OutOfMemory)?;
        Ok(Cholesky {
            supernodal,
            threads: 1,
            solve_scratch: SolveScratch::default(),
            factor: zeros(symbolic.len_val())?,
            triangle_values: zeros(gather.len())?,
            permuted_rhs: zeros(n * nrhs)?,
            symbolic,
            factor_mem,
            solve_mem,
            nrhs,
            fwd,
            inv,
            side,
            triangle: Some(triangle),
            gather,
        })
    }

    /// Let numeric factorizations use up to `threads` threads (1: the calling thread only).
    /// The factor is bitwise the same for any count: only independent subtrees of the
    /// elimination tree run concurrently.
    /// Quaternionic solves of large factors run their two parts concurrently
    /// ([`SupernodalLlt::plan_solves`]), bitwise the same as on one thread.
    pub fn set_threads(&mut self, threads: usize) {
        self.threads = threads.max(1);
        self.plan_solves();
    }

    /// Splits quaternionic solves whatever the factor's size, run on `threads` (the split's
    /// tests, on meshes too small for [`Cholesky::set_threads`] to split them); returns the
    /// parts a solve now has and whether they run concurrently.
    #[cfg(test)]
    pub(crate) fn split_solves_of_any_size(&mut self, threads: usize) -> (usize, bool) {
        self.threads = threads.max(1);
        match (&mut self.supernodal, self.symbolic.raw()) {
            (Some(kernel), SymbolicCholeskyRaw::Supernodal(symbolic)) if kernel.quaternionic() => {
                kernel.plan_solves_above(symbolic, self.threads, 0);
                self.solve_scratch = kernel.solve_scratch(symbolic);
                kernel.solve_parts()
            }
            _ => (1, false),
        }
    }

    /// Plans the quaternionic solves for the current thread count, with their scratch.
    fn plan_solves(&mut self) {
        if let (Some(kernel), SymbolicCholeskyRaw::Supernodal(symbolic)) =
            (&mut self.supernodal, self.symbolic.raw())
        {
            if kernel.quaternionic() {
                kernel.plan_solves(symbolic, self.threads);
                self.solve_scratch = kernel.solve_scratch(symbolic);
            }
        }
    }

    /// The matrices factored from now on are complex forms of quaternion Hermitian ones, as
    /// the Dirac matrix X is: the factorization then updates only the even columns and copies
    /// the odd ones, half the work ([`SupernodalLlt::set_quaternionic`]). Returns whether it
    /// does; where the structure or the kernel does not allow it, the factorization stays the
    /// full one. Debug builds check every factored matrix for the structure. Solves with one
    /// right-hand side then read the even columns only ([`SupernodalLlt::solve_quaternionic`]).
    pub fn set_quaternionic(&mut self) -> bool {
        match (&mut self.supernodal, self.symbolic.raw()) {
            (Some(kernel), SymbolicCholeskyRaw::Supernodal(symbolic)) => {
                let quaternionic = kernel.set_quaternionic(symbolic);
                if quaternionic {
                    self.plan_solves();
                }
                quaternionic
            }
            _ => false,
        }
    }

    /// Numeric refactorization in place with new `values` on the fixed pattern.
    pub fn factorize(&mut self, pattern: &BlockPattern, values: &[T]) -> Result<(), SolverError> {
        self.factorize_matrix(SparseColMatRef::new(pattern.symbolic.as_ref(), values))
    }

    /// Numeric refactorization of a matrix with the pattern given to the analysis.
    pub fn factorize_matrix(
        &mut self,
        a: SparseColMatRef<'_, usize, T>,
    ) -> Result<(), SolverError> {
        if self.gather.len() != self.triangle_values.len() {
            return Err(SolverError::Symbolic(
                "the gather table was released: assemble into the triangle instead".into(),
            ));
        }
        let values = a.val();
        for (t, &k) in self.triangle_values.iter_mut().zip(&self.gather) {
            let v = &values[k & !CONJ];
            *t = if k & CONJ == 0 { *v } else { T::conj_impl(v) };
        }
        self.factorize_triangle()
    }

    /// Solve `A x = rhs` in place for a column-major `n × k` block of right-hand sides, using
    /// the last successful [`Cholesky::factorize`].
    pub fn solve_in_place(&mut self, rhs: &mut [T], k: usize) {
        assert!(k <= self.nrhs);
        let n = self.symbolic.nrows();
        let permuted = &mut self.permuted_rhs[..n * k];
        for (p, r) in permuted.chunks_exact_mut(n).zip(rhs.chunks_exact(n)) {
            for (p, &old) in p.iter_mut().zip(&self.fwd) {
                *p = r[old];
            }
        }
        // One right-hand side of a quaternionic factor: the solve that reads half of it.
        if k == 1 {
            if let (Some(kernel), SymbolicCholeskyRaw::Supernodal(symbolic)) =
                (&self.supernodal, self.symbolic.raw())
            {
                if kernel.quaternionic() {
                    kernel.solve_quaternionic(
                        symbolic,
                        &self.factor,
                        permuted,
                        &mut self.solve_scratch,
                    );
                    for (r, &new) in rhs.iter_mut().zip(&self.inv) {
                        *r = self.permuted_rhs[new];
                    }
                    return;
                }
            }
        }
        let llt = LltRef::new(&self.symbolic, &self.factor);
        // Par::Seq: parallel solves are several times slower on this class of machine
        // (docs/solver.md), and the library owns no threads.
        llt.solve_in_place_with_conj(
            Conj::No,
            MatMut::from_column_major_slice_mut(permuted, n, k),
            Par::Seq,
            MemStack::new(&mut self.solve_mem),
        );
        for (r, p) in rhs
            .chunks_exact_mut(n)
            .zip(self.permuted_rhs.chunks_exact(n))
        {
            for (r, &new) in r.iter_mut().zip(&self.inv) {
                *r = p[new];
            }
        }
    }

    /// Entries of the factor (supernodal storage, explicit zeros included).
    pub fn factor_len(&self) -> usize {
        self.factor.len()
    }

    /// The factor's values (faer's storage), for comparing factorizations.
    pub fn factor_values(&self) -> &[T] {
        &self.factor
    }

    /// Subtrees the last factorization ran concurrently (1: it ran on one thread).
    pub fn last_parallel_pieces(&self) -> usize {
        self.supernodal
            .as_ref()
            .map_or(1, SupernodalLlt::last_pieces)
    }

    /// Where each entry of the full-storage values lands in the triangle the numeric
    /// factorization reads: `Some((index, conjugated))` for the entries it gathers (the lower
    /// triangle in the caller's order), `None` for the others, whose transposed partner
    /// carries their value. Lets a caller assemble straight into
    /// [`Cholesky::triangle_values_mut`] and skip the full storage (see
    /// `dirac::TriangleAssembly`).
    /// Triangle indices are 32-bit (8 bytes an entry: the table spans the whole pattern, 18M
    /// entries for X at 1.3M triangles); a triangle too large for them leaves its entries
    /// `None`, which the assembly refuses.
    pub fn triangle_slots(&self, nnz: usize) -> Vec<Option<(u32, bool)>> {
        let mut slots = vec![None; nnz];
        for (t, &k) in self.gather.iter().enumerate() {
            slots[k & !CONJ] = u32::try_from(t).ok().map(|t| (t, k & CONJ != 0));
        }
        slots
    }

    /// For a caller that assembles straight into [`Cholesky::triangle_values_mut`] (after
    /// taking [`Cholesky::triangle_slots`]) and only calls [`Cholesky::factorize_triangle`]:
    /// frees the gather table, one index per entry of the triangle (6 MB for X at 100k
    /// triangles). [`Cholesky::factorize`] fails afterwards, and [`Cholesky::triangle_slots`]
    /// maps no entry.
    pub fn release_gather(&mut self) {
        self.gather = Vec::new();
    }

    /// Where our own kernel factors ([`Cholesky::uses_own_kernel`]): frees the row indices of
    /// the triangle's pattern (6.8 MB for X at 100k triangles, 2 MB for L), which only faer's
    /// kernel reads; ours scatters the values through [`SupernodalLlt`]'s positions, and
    /// [`Cholesky::hermitian_matvec`] recovers the entries from them. Elsewhere a no-op.
    pub fn release_triangle(&mut self) {
        if self.supernodal.is_some() {
            self.triangle = None;
        }
    }

    /// The triangle's pattern, for a caller that multiplies with the matrix ([`Mixed`]):
    /// moved out where our own kernel factors, cloned where faer's still reads it.
    pub(super) fn take_triangle(&mut self) -> Option<SymbolicSparseColMat<usize>> {
        if self.supernodal.is_some() {
            self.triangle.take()
        } else {
            self.triangle.clone()
        }
    }

    /// The values of the triangle [`Cholesky::factorize_triangle`] factors, in the order of
    /// [`Cholesky::triangle_slots`].
    pub fn triangle_values_mut(&mut self) -> &mut [T] {
        &mut self.triangle_values
    }

    /// Whether refactorizations run [`SupernodalLlt`] (supernodal structure on a CPU with
    /// AVX2 and FMA) rather than faer's numeric kernel.
    pub fn uses_own_kernel(&self) -> bool {
        self.supernodal.is_some()
    }

    /// The widest supernode of the factor, in columns (0 for a simplicial factor).
    pub fn widest_supernode(&self) -> usize {
        match self.symbolic.raw() {
            SymbolicCholeskyRaw::Supernodal(s) => s
                .supernode_begin()
                .iter()
                .zip(s.supernode_end())
                .map(|(b, e)| e - b)
                .max()
                .unwrap_or(0),
            SymbolicCholeskyRaw::Simplicial(_) => 0,
        }
    }

    /// Numeric refactorization of the triangle values as the caller left them.
    pub fn factorize_triangle(&mut self) -> Result<(), SolverError> {
        if let (Some(kernel), SymbolicCholeskyRaw::Supernodal(symbolic)) =
            (&mut self.supernodal, self.symbolic.raw())
        {
            return kernel
                .factorize(
                    symbolic,
                    &mut self.factor,
                    &self.triangle_values,
                    self.threads,
                )
                .map_err(|NotPositive(column)| not_positive(column));
        }
        let Some(triangle) = &self.triangle else {
            return Err(SolverError::Symbolic(
                "the triangle's pattern was released, but faer's kernel reads it".into(),
            ));
        };
        self.symbolic
            .factorize_numeric_llt(
                &mut self.factor,
                SparseColMatRef::new(triangle.as_ref(), &self.triangle_values),
                self.side,
                Default::default(),
                Par::Seq,
                MemStack::new(&mut self.factor_mem),
                Default::default(),
            )
            .map(|_| ())
            .map_err(|e| match e {
                LltError::NonPositivePivot { index } => not_positive(index),
            })
    }
}

/// `len` zeros, or [`SolverError::OutOfMemory`], from the allocator's zeroed memory: a
/// factor of a million vertices is gigabytes, which the kernel hands out as zero pages on
/// first touch, so filling them with zeros here would touch (commit) every page in the setup
/// and write it twice. The factorization commits the pages as it first writes them. A
/// buffer of megabytes is also advised to the kernel for transparent huge pages: the
/// factorization and the solves visit it in short runs all over.
pub(crate) fn zeroed<T: Scalar>(len: usize) -> Result<Vec<T>, SolverError> {
    let layout = std::alloc::Layout::array::<T>(len).map_err(|_| SolverError::OutOfMemory)?;
    if layout.size() == 0 {
        return Ok(Vec::new());
    }
    // SAFETY: the layout has a non-zero size.
    let ptr = unsafe { std::alloc::alloc_zeroed(layout) }.cast::<T>();
    if ptr.is_null() {
        return Err(SolverError::OutOfMemory);
    }
    advise_huge_pages(ptr.cast(), layout.size());
    // SAFETY: `ptr` was allocated by the global allocator with the layout of `len` values of
    // T, and all-zero bits are a valid T (`Scalar` is sealed to the `ZeroBits` floats).
    Ok(unsafe { Vec::from_raw_parts(ptr, len, len) })
}

/// `madvise(MADV_HUGEPAGE)` on the whole 4 KiB pages of `bytes` bytes at `ptr` (on Linux, and
/// from 4 MiB up: a smaller buffer holds at most one huge page). Advice only: where the
/// kernel has transparent huge pages off, it is refused and nothing changes.
pub(super) fn advise_huge_pages(ptr: *mut u8, bytes: usize) {
    #[cfg(target_os = "linux")]
    {
        const PAGE: usize = 4096;
        if bytes < 4 << 20 {
            return;
        }
        let start = (ptr as usize).next_multiple_of(PAGE);
        let end = (ptr as usize + bytes) / PAGE * PAGE;
        // SAFETY: the range lies within an allocation this process owns, and MADV_HUGEPAGE
        // only changes how the kernel backs it, never its contents.
        unsafe {
            libc::madvise(
                ptr.wrapping_add(start - ptr as usize).cast(),
                end - start,
                libc::MADV_HUGEPAGE,
            );
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = (ptr, bytes);
}

/// The same error from either numeric kernel.
pub(super) fn not_positive(column: usize) -> SolverError {
    SolverError::NotPositiveDefinite(format!("non-positive pivot at column {column}"))
}

impl Cholesky<c64> {
    /// `y = A x` with the Hermitian matrix whose triangle was last factored (its values are
    /// kept), in the caller's order.
    pub fn hermitian_matvec(&self, x: &[c64], y: &mut [c64]) {
        match (&self.triangle, &self.supernodal, self.symbolic.raw()) {
            (Some(triangle), _, _) => {
                triangle_matvec(triangle, &self.fwd, &self.triangle_values, x, y);
            }
            (None, Some(kernel), SymbolicCholeskyRaw::Supernodal(symbolic)) => {
                y.fill(c64::new(0.0, 0.0));
                let fwd = &self.fwd;
                kernel.for_each_lower_entry(symbolic, |row, col, k| {
                    let (old_row, old_col) = (fwd[row], fwd[col]);
                    let v = self.triangle_values[k];
                    y[old_row] += v * x[old_col];
                    if row != col {
                        y[old_col] += v.conj() * x[old_row];
                    }
                });
            }
            // `release_triangle` frees the pattern only where our kernel holds the positions.
            (None, _, _) => unreachable!("the triangle's pattern is kept without our kernel"),
        }
    }
}

/// `y = A x` for the Hermitian `A` whose permuted triangle (either side: each stored entry
/// `(row, col)` also stands for its conjugate at `(col, row)`) holds `values`, with `fwd`
/// taking permuted indices back to the caller's.
pub(super) fn triangle_matvec(
    triangle: &SymbolicSparseColMat<usize>,
    fwd: &[usize],
    values: &[c64],
    x: &[c64],
    y: &mut [c64],
) {
    y.fill(c64::new(0.0, 0.0));
    let col_ptr = triangle.col_ptr();
    let row_idx = triangle.row_idx();
    for (col, &old_col) in fwd.iter().enumerate() {
        let x_col = x[old_col];
        let mut y_col = c64::new(0.0, 0.0);
        for (&row, v) in row_idx[col_ptr[col]..col_ptr[col + 1]]
            .iter()
            .zip(&values[col_ptr[col]..col_ptr[col + 1]])
        {
            let old_row = fwd[row];
            y[old_row] += v * x_col;
            if row != col {
                y_col += v.conj() * x[old_row];
            }
        }
        y[old_col] += y_col;
    }
}

/// Marks a [`Cholesky`] gather index whose value is conjugated.
pub(super) const CONJ: usize = 1 << (usize::BITS - 1);

/// One triangle (`side`) of `P A Pᵀ` for the full (both triangles, structurally symmetric)
/// pattern `a`, with `inv[old] = new`: its CSC pattern, and for each of its entries the index
/// of its source in `a`'s values, with [`CONJ`] set when the value is the conjugate of the
/// source. This is exactly what faer's own per-call permutation (`Side::Lower` input) builds,
/// down to the order of the entries within a column (which the simplicial factorization's
/// summation order depends on), so the factor is bitwise the same as with faer's ordering.
pub(super) fn permuted_triangle(
    a: faer::sparse::SymbolicSparseColMatRef<'_, usize>,
    inv: &[usize],
    side: Side,
) -> (SymbolicSparseColMat<usize>, Vec<usize>) {
    let n = a.nrows();
    // Where the original lower entry (i, j) lands: (new row, new column, conjugated).
    let place = |i: usize, j: usize| {
        let (ni, nj) = (inv[i], inv[j]);
        let in_side = match side {
            Side::Lower => ni >= nj,
            Side::Upper => ni <= nj,
        };
        if in_side {
            (ni, nj, false)
        } else {
            (nj, ni, true)
        }
    };
    let mut col_ptr = vec![0usize; n + 1];
    for j in 0..n {
        for &i in a.row_idx_of_col_raw(j) {
            if i >= j {
                col_ptr[place(i, j).1 + 1] += 1;
            }
        }
    }
    for j in 0..n {
        col_ptr[j + 1] += col_ptr[j];
    }
    let mut entries = vec![(0usize, 0usize); col_ptr[n]];
    let mut next = col_ptr.clone();
    for j in 0..n {
        for (k, &i) in a.col_range(j).zip(a.row_idx_of_col_raw(j)) {
            if i >= j {
                let (row, col, conj) = place(i, j);
                entries[next[col]] = (row, if conj { k | CONJ } else { k });
                next[col] += 1;
            }
        }
    }
    let (row_idx, gather): (Vec<usize>, Vec<usize>) = entries.into_iter().unzip();
    (
        SymbolicSparseColMat::new_unsorted_checked(n, n, col_ptr, None, row_idx),
        gather,
    )
}
