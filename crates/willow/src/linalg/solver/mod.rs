//! Sparse Cholesky on a pattern that never changes during a flow.
//!
//! The flows never change connectivity, so the sparsity pattern, its fill-reducing ordering and
//! faer's symbolic factorization are built once per flow; each step only scatters new values
//! into the fixed pattern and refactors numerically in place (SOLVER.md: building from
//! triplets costs more than the factorization itself).

use super::ordering::{self, Ordering, OrderingError};
use super::supernodal::{NotPositive, Scalar, SupernodalLlt};
use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::llt::factor::LltError;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, LltRef, SymbolicCholesky,
    SymbolicCholeskyRaw, SymmetricOrdering,
};
use faer::sparse::linalg::{amd, SupernodalThreshold, SymbolicSupernodalParams};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};
use faer::{c32, c64, Conj, MatMut, Par, Side};

/// The full (both triangles) sparsity pattern of a symmetric matrix over the vertex graph of a
/// triangle mesh, with every vertex-pair entry expanded to a dense `block × block` block
/// (1 for scalar Laplacians, 2 for the complex form of the quaternionic Dirac matrix).
///
/// Values are stored column-major per CSC column; for the block of row vertex `i` and column
/// vertex `j`, entry `(ri, rj)` lives at [`BlockPattern::entry`]`(slot, j, ri, rj)` where `slot`
/// is the block's base index (precomputed per face in [`BlockPattern::face_slots`]).
pub struct BlockPattern {
    pub block: usize,
    /// Vertex-level CSC: `vertex_col_ptr[j]..vertex_col_ptr[j+1]` indexes the sorted
    /// neighbours of `j` (itself included) in `vertex_row_idx`.
    vertex_col_ptr: Vec<usize>,
    vertex_row_idx: Vec<usize>,
    /// The expanded pattern handed to faer.
    pub symbolic: SymbolicSparseColMat<usize>,
    /// For face `f` and ordered corner pair `(a, b)`, `face_slots[f][3a + b]` is the base index
    /// of the block at row vertex `tri[a]`, column vertex `tri[b]`.
    pub face_slots: Vec<[usize; 9]>,
    /// Base index of each vertex's diagonal block.
    diagonal_slots: Vec<usize>,
}

impl BlockPattern {
    pub fn new(n_vertices: usize, triangles: &[[usize; 3]], block: usize) -> Self {
        // Neighbour lists (sorted, deduplicated, diagonal included).
        let mut neighbours: Vec<Vec<usize>> = (0..n_vertices).map(|v| vec![v]).collect();
        for tri in triangles {
            for a in 0..3 {
                for b in 0..3 {
                    if a != b {
                        neighbours[tri[b]].push(tri[a]);
                    }
                }
            }
        }
        let mut vertex_col_ptr = Vec::with_capacity(n_vertices + 1);
        let mut vertex_row_idx = Vec::new();
        vertex_col_ptr.push(0);
        for list in &mut neighbours {
            list.sort_unstable();
            list.dedup();
            vertex_row_idx.extend_from_slice(list);
            vertex_col_ptr.push(vertex_row_idx.len());
        }
        drop(neighbours);

        let b = block;
        let n = b * n_vertices;
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::with_capacity(b * b * vertex_row_idx.len());
        col_ptr.push(0);
        for j in 0..n_vertices {
            let rows = &vertex_row_idx[vertex_col_ptr[j]..vertex_col_ptr[j + 1]];
            for _rj in 0..b {
                for &i in rows {
                    for ri in 0..b {
                        row_idx.push(b * i + ri);
                    }
                }
                col_ptr.push(row_idx.len());
            }
        }
        let symbolic = SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx);

        let mut pattern = BlockPattern {
            block,
            vertex_col_ptr,
            vertex_row_idx,
            symbolic,
            face_slots: Vec::with_capacity(triangles.len()),
            diagonal_slots: Vec::with_capacity(n_vertices),
        };
        for v in 0..n_vertices {
            let slot = pattern.block_slot(v, v);
            pattern.diagonal_slots.push(slot);
        }
        for tri in triangles {
            let mut slots = [0usize; 9];
            for a in 0..3 {
                for bb in 0..3 {
                    slots[3 * a + bb] = pattern.block_slot(tri[a], tri[bb]);
                }
            }
            pattern.face_slots.push(slots);
        }
        pattern
    }

    /// Base index of the block at row vertex `i`, column vertex `j` (which must be adjacent).
    fn block_slot(&self, i: usize, j: usize) -> usize {
        let (start, end) = (self.vertex_col_ptr[j], self.vertex_col_ptr[j + 1]);
        let k = self.vertex_row_idx[start..end]
            .binary_search(&i)
            .expect("every face's vertex pairs are in the pattern by construction");
        self.block * self.block * start + self.block * k
    }

    /// The vertex graph (CSC, sorted, diagonal included): column pointers and rows.
    pub fn vertex_graph(&self) -> (&[usize], &[usize]) {
        (&self.vertex_col_ptr, &self.vertex_row_idx)
    }

    /// Vertex pairs (neighbours and diagonal) in the pattern: the range of
    /// [`BlockPattern::pair_index`].
    pub fn vertex_nnz(&self) -> usize {
        self.vertex_row_idx.len()
    }

    /// The position of the vertex pair whose block has base index `slot` in column vertex `j`
    /// among all vertex pairs: a dense index for per-pair tables.
    pub fn pair_index(&self, slot: usize, j: usize) -> usize {
        let start = self.vertex_col_ptr[j];
        start + (slot - self.block * self.block * start) / self.block
    }

    /// Base index of the diagonal block of vertex `v`.
    #[inline]
    pub fn diagonal_slot(&self, v: usize) -> usize {
        self.diagonal_slots[v]
    }

    /// Distance between consecutive columns of a block in column vertex `j`: entry
    /// `(ri, rj)` of a block with base index `slot` is at `slot + rj · stride + ri`.
    #[inline]
    pub fn column_stride(&self, j: usize) -> usize {
        self.block * (self.vertex_col_ptr[j + 1] - self.vertex_col_ptr[j])
    }

    /// Index of entry `(ri, rj)` of the block whose base index is `slot` in column vertex `j`.
    #[inline]
    pub fn entry(&self, slot: usize, j: usize, ri: usize, rj: usize) -> usize {
        let degree = self.vertex_col_ptr[j + 1] - self.vertex_col_ptr[j];
        slot + rj * self.block * degree + ri
    }

    pub fn nnz(&self) -> usize {
        self.symbolic.row_idx().len()
    }

    pub fn dim(&self) -> usize {
        self.symbolic.nrows()
    }

    /// A fill-reducing ordering of the vertex graph (AMD or nested dissection, see
    /// [`Ordering::for_vertices`]), expanded to blocks. Same fill as ordering the expanded
    /// pattern at a fraction of the symbolic cost (SOLVER.md).
    fn block_order(&self, ordering: Ordering) -> Result<(Vec<usize>, Vec<usize>), OrderingError> {
        let (fwd, _) = self.vertex_order(ordering)?;
        Ok(self.expand_order(&fwd))
    }

    /// A fill-reducing ordering `(fwd, inv)` of the vertex graph alone: every pattern of the
    /// same mesh shares it ([`Cholesky::analyze_with_vertex_order`]), so a flow that factors
    /// several matrices orders its graph once.
    pub fn vertex_order(
        &self,
        ordering: Ordering,
    ) -> Result<(Vec<usize>, Vec<usize>), OrderingError> {
        ordering::order(ordering, &self.vertex_col_ptr, &self.vertex_row_idx)
    }

    /// A vertex ordering expanded to this pattern's blocks.
    fn expand_order(&self, fwd: &[usize]) -> (Vec<usize>, Vec<usize>) {
        let nv = self.vertex_col_ptr.len() - 1;
        let b = self.block;
        let mut fwd_b = vec![0usize; b * nv];
        let mut inv_b = vec![0usize; b * nv];
        for k in 0..nv {
            for r in 0..b {
                fwd_b[b * k + r] = b * fwd[k] + r;
                inv_b[b * fwd[k] + r] = b * k + r;
            }
        }
        (fwd_b, inv_b)
    }
}

/// Refill `values` (on a block-1 `pattern`) with the PSD cotan Laplacian scaled by `scale`:
/// each corner with cotangent `c` adds `scale·c/2` to the diagonal entries of its opposite
/// edge's ends and subtracts it from the two off-diagonal entries.
pub fn assemble_cotan_laplacian_into(
    pattern: &BlockPattern,
    triangles: &[[usize; 3]],
    cotangents: &[[f64; 3]],
    scale: f64,
    values: &mut [f64],
) {
    values.fill(0.0);
    for ((tri, cots), slots) in triangles.iter().zip(cotangents).zip(&pattern.face_slots) {
        for c in 0..3 {
            let (a, b) = ((c + 1) % 3, (c + 2) % 3);
            let w = 0.5 * scale * cots[c];
            values[pattern.entry(slots[3 * a + b], tri[b], 0, 0)] -= w;
            values[pattern.entry(slots[3 * b + a], tri[a], 0, 0)] -= w;
            values[pattern.entry(slots[3 * a + a], tri[a], 0, 0)] += w;
            values[pattern.entry(slots[3 * b + b], tri[b], 0, 0)] += w;
        }
    }
}

/// Add `diagonal[v]` to the diagonal entry of every vertex `v` (block-1 pattern).
pub fn add_diagonal(
    pattern: &BlockPattern,
    diagonal: impl Iterator<Item = f64>,
    values: &mut [f64],
) {
    for (v, d) in diagonal.enumerate() {
        values[pattern.entry(pattern.diagonal_slot(v), v, 0, 0)] += d;
    }
}

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
    factor: Vec<T>,
    factor_mem: MemBuffer,
    solve_mem: MemBuffer,
    nrhs: usize,
    /// `fwd[new] = old` and its inverse.
    fwd: Vec<usize>,
    inv: Vec<usize>,
    /// The triangle of `P A Pᵀ` faer's numeric factorization reads (lower for supernodal,
    /// upper for simplicial). `None` once [`Cholesky::release_triangle`] freed it (our own
    /// kernel reads the values through [`SupernodalLlt`]'s positions instead).
    side: Side,
    triangle: Option<SymbolicSparseColMat<usize>>,
    /// `triangle_values[k] = values[gather[k]]`.
    gather: Vec<usize>,
    triangle_values: Vec<T>,
    /// Right-hand sides in the permuted order, `n × nrhs` column-major.
    permuted_rhs: Vec<T>,
    /// Our numeric kernel for supernodal factorizations (`None`: faer's, see
    /// [`SupernodalLlt`]).
    supernodal: Option<SupernodalLlt>,
    /// Threads the numeric factorization may use (independent subtrees run concurrently).
    threads: usize,
    /// Scratch of the quaternionic solve ([`SupernodalLlt::solve_quaternionic`]), sized by
    /// [`Cholesky::set_quaternionic`].
    solve_scratch: Vec<[f64; 4]>,
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
        if vertex_fwd.len() != pattern.vertex_col_ptr.len() - 1 {
            return Err(SolverError::Symbolic(
                "the vertex ordering is for another mesh".into(),
            ));
        }
        let (fwd, inv) = pattern.expand_order(vertex_fwd);
        Self::with_ordering(pattern.symbolic.as_ref(), pattern.block, fwd, inv, nrhs)
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
        Self::with_ordering(pattern.symbolic.as_ref(), pattern.block, fwd, inv, nrhs)
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
        Self::with_ordering(pattern, 1, fwd, inv, nrhs)
    }

    /// `block`: the pattern's columns come in groups of this many (see
    /// [`supernodal_params`]).
    fn with_ordering(
        pattern: faer::sparse::SymbolicSparseColMatRef<'_, usize>,
        block: usize,
        fwd: Vec<usize>,
        inv: Vec<usize>,
        nrhs: usize,
    ) -> Result<Self, SolverError> {
        let n = pattern.nrows();
        // Only the upper triangle is analyzed (faer's contract with the identity ordering).
        let (upper, _) = permuted_triangle(pattern, &inv, Side::Upper);
        let symbolic = factorize_symbolic_cholesky(
            upper.as_ref(),
            Side::Upper,
            SymmetricOrdering::Identity,
            CholeskySymbolicParams {
                supernodal_flop_ratio_threshold: SupernodalThreshold::AUTO,
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
            solve_scratch: Vec::new(),
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
    pub fn set_threads(&mut self, threads: usize) {
        self.threads = threads.max(1);
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
                    self.solve_scratch = vec![[0.0; 4]; kernel.solve_scratch_len()];
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
        // (SOLVER.md), and the library owns no threads.
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
    fn take_triangle(&mut self) -> Option<SymbolicSparseColMat<usize>> {
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
fn advise_huge_pages(ptr: *mut u8, bytes: usize) {
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
fn not_positive(column: usize) -> SolverError {
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
fn triangle_matvec(
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
fn kept_factor_is_hopeless(start: f64, best: f64, iterations: usize) -> bool {
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
    /// Where the last solve gave up early on a kept factor ([`kept_factor_is_hopeless`]).
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

/// Marks a [`Cholesky`] gather index whose value is conjugated.
const CONJ: usize = 1 << (usize::BITS - 1);

/// One triangle (`side`) of `P A Pᵀ` for the full (both triangles, structurally symmetric)
/// pattern `a`, with `inv[old] = new`: its CSC pattern, and for each of its entries the index
/// of its source in `a`'s values, with [`CONJ`] set when the value is the conjugate of the
/// source. This is exactly what faer's own per-call permutation (`Side::Lower` input) builds,
/// down to the order of the entries within a column (which the simplicial factorization's
/// summation order depends on), so the factor is bitwise the same as with faer's ordering.
fn permuted_triangle(
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

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::mesh::generate::icosphere;

    #[test]
    fn pattern_holds_every_face_pair_once_per_block_entry() {
        let mesh = icosphere(1);
        for block in [1, 2] {
            let p = BlockPattern::new(mesh.vertex_count(), &mesh.triangles, block);
            // V + 2E vertex-level entries (geometry-central's check), times block².
            let e = 3 * mesh.face_count() / 2;
            assert_eq!(p.nnz(), block * block * (mesh.vertex_count() + 2 * e));
            for (tri, slots) in mesh.triangles.iter().zip(&p.face_slots) {
                for a in 0..3 {
                    for b in 0..3 {
                        for ri in 0..block {
                            for rj in 0..block {
                                let idx = p.entry(slots[3 * a + b], tri[b], ri, rj);
                                assert_eq!(p.symbolic.row_idx()[idx], block * tri[a] + ri);
                                let col = block * tri[b] + rj;
                                let cp = p.symbolic.col_ptr();
                                assert!(cp[col] <= idx && idx < cp[col + 1]);
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn solves_a_shifted_laplacian_to_small_residual() {
        let mesh = icosphere(2);
        let n = mesh.vertex_count();
        let p = BlockPattern::new(n, &mesh.triangles, 1);
        let cot = crate::geometry::corner_cotangents(&mesh);
        let mut values = vec![0.0; p.nnz()];
        for ((tri, cots), slots) in mesh.triangles.iter().zip(&cot).zip(&p.face_slots) {
            for c in 0..3 {
                let (a, b) = ((c + 1) % 3, (c + 2) % 3);
                let w = 0.5 * cots[c];
                values[p.entry(slots[3 * a + b], tri[b], 0, 0)] -= w;
                values[p.entry(slots[3 * b + a], tri[a], 0, 0)] -= w;
                values[p.entry(slots[3 * a + a], tri[a], 0, 0)] += w;
                values[p.entry(slots[3 * b + b], tri[b], 0, 0)] += w;
            }
        }
        for v in 0..n {
            values[p.entry(p.diagonal_slot(v), v, 0, 0)] += 1.0;
        }
        let mut chol = Cholesky::<f64>::analyze(&p, 1).expect("analyze");
        chol.factorize(&p, &values).expect("factorize");
        let b: Vec<f64> = (0..n).map(|i| (i as f64 * 0.37).sin()).collect();
        let mut x = b.clone();
        chol.solve_in_place(&mut x, 1);
        let a = SparseColMatRef::new(p.symbolic.as_ref(), &values);
        let mut residual = 0.0f64;
        for j in 0..n {
            let (start, end) = (a.col_ptr()[j], a.col_ptr()[j + 1]);
            let mut s = 0.0;
            for idx in start..end {
                s += values[idx] * x[a.row_idx()[idx]];
            }
            residual = residual.max((s - b[j]).abs());
        }
        assert!(residual < 1e-12, "residual {residual}");
    }

    /// A Hermitian, diagonally dominant block-2 matrix on `p`: off-diagonal blocks `B` and `Bᴴ`,
    /// diagonal `100·I`.
    pub(crate) fn hermitian_block_values(
        p: &BlockPattern,
        triangles: &[[usize; 3]],
    ) -> Vec<faer::c64> {
        use faer::c64;
        let mut values = vec![c64::new(0.0, 0.0); p.nnz()];
        for (f, (tri, slots)) in triangles.iter().zip(&p.face_slots).enumerate() {
            for a in 0..3 {
                for b in 0..3 {
                    if a == b {
                        continue;
                    }
                    let (i, j) = (tri[a], tri[b]);
                    let t = (f * 9 + 3 * a + b) as f64;
                    let m = [
                        [c64::new(t.sin(), 0.3), c64::new(0.2, t.cos())],
                        [c64::new(-0.4, 0.1), c64::new(0.5, -t.sin())],
                    ];
                    for ri in 0..2 {
                        for rj in 0..2 {
                            values[p.entry(slots[3 * a + b], j, ri, rj)] += m[ri][rj];
                            values[p.entry(slots[3 * b + a], i, rj, ri)] += m[ri][rj].conj();
                        }
                    }
                }
            }
        }
        for v in 0..p.vertex_col_ptr.len() - 1 {
            for r in 0..2 {
                values[p.entry(p.diagonal_slot(v), v, r, r)] += c64::new(100.0, 0.0);
            }
        }
        values
    }

    /// Copies full-storage `values` into a [`Mixed`]'s triangle (as the Dirac assembly does).
    fn fill_mixed(mixed: &mut Mixed, values: &[faer::c64]) {
        let slots = mixed.triangle_slots(values.len());
        let triangle = mixed.triangle_values_mut();
        for (v, slot) in values.iter().zip(slots) {
            if let Some((t, conj)) = slot {
                triangle[t as usize] = if conj { v.conj() } else { *v };
            }
        }
    }

    /// `A x` from the full-storage `values` of `A` on `p`.
    fn full_storage_product(
        p: &BlockPattern,
        values: &[faer::c64],
        x: &[faer::c64],
    ) -> Vec<faer::c64> {
        let a = SparseColMatRef::new(p.symbolic.as_ref(), values);
        let mut y = vec![faer::c64::new(0.0, 0.0); p.dim()];
        for (col, &x_col) in x.iter().enumerate() {
            for idx in a.col_ptr()[col]..a.col_ptr()[col + 1] {
                y[a.row_idx()[idx]] += values[idx] * x_col;
            }
        }
        y
    }

    /// The largest entrywise distance between two complex vectors.
    fn max_distance(a: &[faer::c64], b: &[faer::c64]) -> f64 {
        a.iter()
            .zip(b)
            .map(|(a, b)| (a - b).norm())
            .fold(0.0, f64::max)
    }

    /// With its triangle's pattern released, a factorization on our kernel still factors the
    /// same matrix (bitwise the same factor), and the product with the matrix, recovered
    /// from the kernel's positions, equals the full-storage product.
    #[test]
    fn released_triangle_factors_and_multiplies_as_before() {
        use faer::c64;
        let mesh = icosphere(4);
        let p = BlockPattern::new(mesh.vertex_count(), &mesh.triangles, 2);
        let values = hermitian_block_values(&p, &mesh.triangles);
        let mut kept = Cholesky::<c64>::analyze(&p, 1).expect("analyze");
        let mut released = Cholesky::<c64>::analyze(&p, 1).expect("analyze");
        assert!(
            released.uses_own_kernel(),
            "the test needs our kernel (AVX2 and FMA)"
        );
        released.release_triangle();
        assert!(released.triangle.is_none());
        kept.factorize(&p, &values).expect("factorize");
        released.factorize(&p, &values).expect("factorize");
        assert!(kept.factor_values() == released.factor_values());

        let n = p.dim();
        let x: Vec<c64> = (0..n)
            .map(|i| c64::new((i as f64 * 0.37).sin(), (i as f64 * 0.11).cos()))
            .collect();
        let expected = full_storage_product(&p, &values, &x);
        for chol in [&kept, &released] {
            let mut y = vec![c64::new(f64::NAN, 0.0); n];
            chol.hermitian_matvec(&x, &mut y);
            let error = max_distance(&y, &expected);
            assert!(error < 1e-12, "product off by {error}");
        }
    }

    /// The single-precision factor with conjugate gradients solves to the double-precision
    /// factor's answer (to 1e-11, far below single precision's 1e-7), both freshly factored
    /// and with the factor of a neighbouring matrix kept (the flow's reuse across steps).
    #[test]
    fn mixed_precision_solves_to_double_precision() {
        use faer::c64;
        let mesh = icosphere(4);
        let p = BlockPattern::new(mesh.vertex_count(), &mesh.triangles, 2);
        let first = hermitian_block_values(&p, &mesh.triangles);
        // A neighbouring matrix on the same pattern: diagonal entries up to 5% off, vertex by
        // vertex (not a multiple of the first, which the warm start would fit exactly).
        let mut second = first.clone();
        for v in 0..mesh.vertex_count() {
            for r in 0..2 {
                second[p.entry(p.diagonal_slot(v), v, r, r)] *=
                    1.0 + 0.05 * ((v * 7 + r) % 11) as f64 / 10.0;
            }
        }
        let n = p.dim();
        let b: Vec<c64> = (0..n)
            .map(|i| c64::new((i as f64 * 0.37).sin(), (i as f64 * 0.11).cos()))
            .collect();
        let (order, _) = p.vertex_order(Ordering::Amd).expect("order");
        let mut mixed = Mixed::analyze(&p, &order).expect("analyze");
        for (values, may_reuse) in [(&first, true), (&second, true)] {
            let mut double = Cholesky::<c64>::analyze(&p, 1).expect("analyze");
            double.factorize(&p, values).expect("factorize");
            let mut exact = b.clone();
            double.solve_in_place(&mut exact, 1);

            fill_mixed(&mut mixed, values);
            mixed.refresh(may_reuse).expect("factorize");
            let mut x = b.clone();
            mixed.solve_in_place(&mut x).expect("converges");
            let scale = exact.iter().map(|v| v.norm()).fold(0.0, f64::max);
            let error = max_distance(&x, &exact);
            assert!(error < 1e-11 * scale, "off by {error:e} (scale {scale:e})");
            assert!(mixed.last_backward_error <= MIXED_TOLERANCE);
        }
        // The second matrix was solved with the first one's factor (the first solve took
        // few iterations, so the factor was kept), which needed iterations to correct.
        assert!(mixed.reused(), "the factor was not kept");
        assert!(mixed.last_iterations >= 1);
    }

    /// A factor kept for a matrix it no longer preconditions is replaced within the solve,
    /// which then still converges.
    #[test]
    fn mixed_precision_refactors_when_the_kept_factor_fails() {
        use faer::c64;
        let mesh = icosphere(3);
        let p = BlockPattern::new(mesh.vertex_count(), &mesh.triangles, 2);
        let first = hermitian_block_values(&p, &mesh.triangles);
        // A diagonal that varies by a factor of 10⁴ from vertex to vertex: the first factor
        // leaves P⁻¹A with a spectrum far too spread for a few iterations.
        let mut second = first.clone();
        for v in 0..mesh.vertex_count() {
            for r in 0..2 {
                let boost = 100.0 * 10f64.powi((v % 5) as i32);
                second[p.entry(p.diagonal_slot(v), v, r, r)] += c64::new(boost, 0.0);
            }
        }
        let (order, _) = p.vertex_order(Ordering::Amd).expect("order");
        let mut mixed = Mixed::analyze(&p, &order).expect("analyze");
        fill_mixed(&mut mixed, &first);
        mixed.refresh(true).expect("factorize");
        let b: Vec<c64> = (0..p.dim())
            .map(|i| c64::new(1.0, i as f64 * 1e-3))
            .collect();
        let mut x = b.clone();
        mixed.solve_in_place(&mut x).expect("converges");
        fill_mixed(&mut mixed, &second);
        mixed.refresh(true).expect("kept");
        assert!(mixed.reused());
        let mut x = b.clone();
        mixed
            .solve_in_place(&mut x)
            .expect("converges after refactoring");
        assert!(!mixed.reused(), "the stale factor was not replaced");
        let mut y = vec![c64::new(0.0, 0.0); p.dim()];
        mixed.hermitian_matvec(&x, &mut y);
        let residual = max_distance(&y, &b);
        assert!(residual < 1e-9, "residual {residual:e}");
        // Its rate showed within 2 iterations that the kept factor would not do.
        assert_eq!(mixed.gave_up_after, Some(2));
        // After a kept factor failed, the next refresh factors afresh (a pause of 1, then 2,
        // 4, … after further failures in a row); the one after may keep again.
        mixed.refresh(true).expect("factorize");
        assert!(!mixed.reused(), "kept right after a failure");
        mixed.solve_in_place(&mut x.clone()).expect("converges");
        mixed.refresh(true).expect("kept");
        assert!(mixed.reused(), "the pause did not end");
        // Asked to (a rejected try's retry), the next refresh factors afresh, and the
        // pause logic is untouched: the one after keeps again.
        mixed.solve_in_place(&mut x.clone()).expect("converges");
        mixed.refactor_next();
        mixed.refresh(true).expect("factorize");
        assert!(!mixed.reused(), "kept although asked to refactor");
        mixed.solve_in_place(&mut x.clone()).expect("converges");
        mixed.refresh(true).expect("kept");
        assert!(mixed.reused(), "refactor_next paused keeping");
    }

    /// The early give-up on kept factors, on the backward errors of real solves: nefertiti's
    /// stalled ones (stopped after 2 iterations where the rate says more than 12 in all,
    /// left to the limit where it says about 8) and icosphere:7's successful ones (never
    /// stopped, although their error is not monotone).
    #[test]
    fn kept_factors_are_given_up_by_their_rate() {
        let hopeless_at = |errors: &[f64]| {
            (2..errors.len()).find(|&k| {
                let best = errors[1..=k].iter().copied().fold(f64::INFINITY, f64::min);
                kept_factor_is_hopeless(errors[0], best, k)
            })
        };
        assert_eq!(hopeless_at(&[9.04e-6, 4.57e-6, 1.39e-6, 2.96e-7]), Some(2));
        assert_eq!(hopeless_at(&[3.78e-6, 1.20e-6, 8.66e-7, 1.19e-7]), Some(2));
        let slow = [
            1.23e-6, 1.21e-7, 2.26e-8, 3.22e-9, 4.90e-10, 8.99e-11, 2.39e-11,
        ];
        assert_eq!(hopeless_at(&slow), None);
        for converging in [
            [3.35e-7, 8.16e-10, 2.56e-8, 4.65e-11, 2.79e-13],
            [1.34e-7, 2.91e-9, 1.13e-8, 1.13e-10, 8.11e-13],
            [9.18e-8, 1.78e-9, 6.15e-10, 6.11e-11, 7.30e-13],
        ] {
            assert_eq!(hopeless_at(&converging), None, "{converging:?}");
        }
        // No progress at all: hopeless; no error (solved): not.
        assert!(kept_factor_is_hopeless(1e-6, 1e-6, 2));
        assert!(!kept_factor_is_hopeless(1e-6, 0.0, 2));
    }

    #[test]
    fn solves_a_hermitian_block_system_with_several_right_hand_sides() {
        assert_solves_hermitian_system(2, |_| {});
    }

    /// Factors [`hermitian_block_values`] on an icosphere's 2×2-block pattern (after `check`
    /// has seen the analysis) and solves it for two right-hand sides to a residual < 1e-12.
    pub(crate) fn assert_solves_hermitian_system(
        subdivisions: usize,
        check: impl FnOnce(&Cholesky<faer::c64>),
    ) {
        use faer::c64;
        let mesh = icosphere(subdivisions);
        let p = BlockPattern::new(mesh.vertex_count(), &mesh.triangles, 2);
        let values = hermitian_block_values(&p, &mesh.triangles);
        let n = p.dim();
        let mut chol = Cholesky::<c64>::analyze(&p, 2).expect("analyze");
        check(&chol);
        chol.factorize(&p, &values).expect("factorize");
        let b: Vec<c64> = (0..2 * n)
            .map(|i| c64::new((i as f64 * 0.37).sin(), (i as f64 * 0.11).cos()))
            .collect();
        let mut x = b.clone();
        chol.solve_in_place(&mut x, 2);
        for k in 0..2 {
            let y = full_storage_product(&p, &values, &x[k * n..(k + 1) * n]);
            let residual = max_distance(&y, &b[k * n..(k + 1) * n]);
            assert!(residual < 1e-12, "rhs {k}: residual {residual}");
        }
    }

    /// The factor equals the one faer computes when it applies the same ordering itself on
    /// every call (`SymmetricOrdering::Custom`): bit for bit with faer's numeric kernel (same
    /// entries read, same order); to rounding with ours (`SupernodalLlt`), whose off-diagonal
    /// solve sums in another order.
    fn same_factor_as_faer_ordering<T: Scalar + PartialEq + std::fmt::Debug>(
        p: &BlockPattern,
        values: &[T],
    ) {
        let mut chol = Cholesky::<T>::analyze(p, 1).expect("analyze");
        chol.factorize(p, values).expect("factorize");
        let (fwd, inv) = p.block_order(Ordering::Amd).expect("amd");
        let perm = faer::perm::PermRef::new_checked(&fwd, &inv, p.dim());
        let symbolic = factorize_symbolic_cholesky(
            p.symbolic.as_ref(),
            Side::Lower,
            SymmetricOrdering::Custom(perm),
            CholeskySymbolicParams {
                supernodal_params: supernodal_params(p.block),
                ..Default::default()
            },
        )
        .expect("symbolic");
        let mut factor = vec![T::zero_impl(); symbolic.len_val()];
        let mut mem = MemBuffer::new(
            symbolic.factorize_numeric_llt_scratch::<T>(Par::Seq, Default::default()),
        );
        symbolic
            .factorize_numeric_llt(
                &mut factor,
                SparseColMatRef::new(p.symbolic.as_ref(), values),
                Side::Lower,
                Default::default(),
                Par::Seq,
                MemStack::new(&mut mem),
                Default::default(),
            )
            .expect("numeric");
        if chol.supernodal.is_some() {
            let scale = factor.iter().map(|v| v.modulus()).fold(0.0, f64::max);
            let difference = factor
                .iter()
                .zip(&chol.factor)
                .map(|(&a, &b)| (a - b).modulus())
                .fold(0.0, f64::max);
            assert!(
                difference <= 1e-13 * scale,
                "factor differs by {difference:e} (largest entry {scale:e})"
            );
        } else {
            assert!(factor == chol.factor);
        }
    }

    #[test]
    fn factors_are_bitwise_those_of_faers_own_ordering() {
        let mesh = icosphere(3);
        let nv = mesh.vertex_count();
        let p2 = BlockPattern::new(nv, &mesh.triangles, 2);
        same_factor_as_faer_ordering(&p2, &hermitian_block_values(&p2, &mesh.triangles));
        // A shifted cotan Laplacian: simplicial at this size, where the entry order matters.
        let p1 = BlockPattern::new(nv, &mesh.triangles, 1);
        let mut values = vec![0.0; p1.nnz()];
        let cot = crate::geometry::corner_cotangents(&mesh);
        assemble_cotan_laplacian_into(&p1, &mesh.triangles, &cot, 1.0, &mut values);
        add_diagonal(&p1, (0..nv).map(|_| 0.1), &mut values);
        same_factor_as_faer_ordering(&p1, &values);
    }

    #[test]
    fn zeroed_buffers_are_zero_and_writable_at_every_size() {
        // Empty, one heap chunk, and 64 MiB: a fresh mapping, advised for huge pages.
        for len in [0, 3, 4 << 20] {
            let mut v = zeroed::<c64>(len).expect("allocates");
            assert_eq!(v.len(), len);
            assert!(v.iter().all(|z| z.re.to_bits() == 0 && z.im.to_bits() == 0));
            for (i, z) in v.iter_mut().enumerate().step_by(4096) {
                *z = c64::new(i as f64, 1.0);
            }
            assert!(v
                .iter()
                .step_by(4096)
                .enumerate()
                .all(|(k, z)| z.re == (4096 * k) as f64));
        }
        let reals = zeroed::<f64>(1 << 20).expect("allocates");
        assert!(reals.iter().all(|x| x.to_bits() == 0));
        // A length whose byte size overflows is refused, not a panic.
        assert!(matches!(
            zeroed::<c32>(usize::MAX),
            Err(SolverError::OutOfMemory)
        ));
    }
}
