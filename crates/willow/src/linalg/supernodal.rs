//! Numeric supernodal `LLᴴ` on faer's symbolic structure, with a vectorized off-diagonal solve.
//!
//! faer 0.24's `factorize_supernodal_numeric_llt` finishes every supernode with
//! `L₂₁ ← A₂₁ L₁₁⁻ᴴ`, which it hands to its triangular solver as the row-major view `L₂₁ᵀ`;
//! that view runs the solver's scalar base case. This kernel runs faer's algorithm loop for
//! loop, on faer's symbolic factorization and into faer's storage (so faer's supernodal solve
//! reads the result), and differs in two places:
//! - the off-diagonal block is solved from the right on its own column-major storage
//!   ([`solve_right_lower_adjoint`]: panels of at most [`NARROW`] columns, each a register-tile
//!   substitution compiled for AVX2/FMA after one matrix product for the earlier panels);
//! - the lower triangle of `A` is written into the factor through positions computed at
//!   analysis, one supernode at a time (zeroing that supernode's block just before), instead
//!   of a memset of the whole factor and a per-entry index lookup.
//!
//! The descendant updates `L_s −= L_d L_dᴴ` (gathered rows, scattered into the target columns)
//! and the dense Cholesky of each diagonal block are faer's own: the fused kernel
//! `private_gemm_x86::gemm` (the one faer's `spicy_matmul` calls) and `cholesky_in_place`.
//! The kernel needs AVX2 and FMA, so [`SupernodalLlt::new`] returns `None` without them and
//! the caller keeps faer's numeric factorization.
//!
//! Measured on the Dirac matrix of cheburashka (13k triangles), both kernels timed in one
//! process on the same steps: the refactorization takes 16–21% less time than faer's
//! (20.2 vs 24.0 ms, 23.1 vs 29.2 ms, 28.9 vs 35.2 ms).

use std::ops::Sub;

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::{cholesky_in_place, cholesky_in_place_scratch};
use faer::sparse::linalg::cholesky::supernodal::SymbolicSupernodalCholesky;
use faer::sparse::SymbolicSparseColMatRef;
use faer::traits::ComplexField;
use faer::{c32, c64, MatMut, Par};

mod sealed {
    /// Types whose all-zero bit pattern is their zero (IEEE floats and pairs of them), so a
    /// buffer of them may come zeroed from the allocator.
    ///
    /// # Safety
    /// The all-zero bit pattern must be a valid value of the type, and its zero.
    pub unsafe trait ZeroBits {}
    // SAFETY: IEEE 754 +0.0 is all zero bits; a complex number is two such floats.
    unsafe impl ZeroBits for f64 {}
    // SAFETY: as above.
    unsafe impl ZeroBits for faer::c64 {}
    // SAFETY: as above.
    unsafe impl ZeroBits for faer::c32 {}
}

/// The scalars the flows factor: real Laplacians and the complex form of the Dirac matrix.
/// Sealed: f64, c64 and c32 only.
pub trait Scalar: ComplexField + Copy + Sub<Output = Self> + sealed::ZeroBits {
    #[cfg(target_arch = "x86_64")]
    const GEMM_TYPE: private_gemm_x86::DType;
    /// The real part of a diagonal entry of a Cholesky factor (real and positive).
    fn diagonal(self) -> f64;
    fn modulus(self) -> f64;
    /// Complex scalars carry an imaginary part.
    const COMPLEX: bool;
    fn re(self) -> f64;
    fn im(self) -> f64;
    fn from_parts(re: f64, im: f64) -> Self;
}

impl Scalar for f64 {
    #[cfg(target_arch = "x86_64")]
    const GEMM_TYPE: private_gemm_x86::DType = private_gemm_x86::DType::F64;
    fn diagonal(self) -> f64 {
        self
    }
    fn modulus(self) -> f64 {
        self.abs()
    }
    const COMPLEX: bool = false;
    fn re(self) -> f64 {
        self
    }
    fn im(self) -> f64 {
        0.0
    }
    fn from_parts(re: f64, _: f64) -> Self {
        re
    }
}

impl Scalar for c64 {
    #[cfg(target_arch = "x86_64")]
    const GEMM_TYPE: private_gemm_x86::DType = private_gemm_x86::DType::C64;
    fn diagonal(self) -> f64 {
        self.re
    }
    fn modulus(self) -> f64 {
        self.norm()
    }
    const COMPLEX: bool = true;
    fn re(self) -> f64 {
        self.re
    }
    fn im(self) -> f64 {
        self.im
    }
    fn from_parts(re: f64, im: f64) -> Self {
        c64::new(re, im)
    }
}

/// Single-precision complex: the Dirac factor of large meshes, a preconditioner that
/// conjugate gradients in double precision turn back into exact solves (`solver::Mixed`).
impl Scalar for c32 {
    #[cfg(target_arch = "x86_64")]
    const GEMM_TYPE: private_gemm_x86::DType = private_gemm_x86::DType::C32;
    fn diagonal(self) -> f64 {
        f64::from(self.re)
    }
    fn modulus(self) -> f64 {
        f64::from(self.norm())
    }
    const COMPLEX: bool = true;
    fn re(self) -> f64 {
        f64::from(self.re)
    }
    fn im(self) -> f64 {
        f64::from(self.im)
    }
    fn from_parts(re: f64, im: f64) -> Self {
        c32::new(re as f32, im as f32)
    }
}

const UNMAPPED: usize = usize::MAX;

/// Everything the numeric factorization needs besides faer's symbolic structure, computed once.
pub struct SupernodalLlt {
    #[cfg(target_arch = "x86_64")]
    instructions: private_gemm_x86::InstrSet,
    /// The supernodes that update supernode `s` (those with a row in its columns), ascending:
    /// `descendants[descendant_ptr[s]..descendant_ptr[s + 1]]`.
    descendant_ptr: Vec<usize>,
    descendants: Vec<usize>,
    /// The entries of `A`'s lower triangle of supernode `s`'s columns are
    /// `a_ptr[s]..a_ptr[s + 1]` (CSC order); entry `k` goes to `a_position[k]` within the
    /// supernode's block of factor values (32 bits: one per entry of `A`'s triangle, 3 MB
    /// saved on X at 100k triangles; a block too large for them keeps faer's kernel).
    a_ptr: Vec<usize>,
    a_position: Vec<u32>,
    /// The supernodal elimination tree: `children[child_ptr[s]..child_ptr[s + 1]]`, ascending,
    /// and the first supernode of each subtree. The supernodes are in postorder (checked),
    /// so the subtree of `s` is the range `first[s]..=s`, and the subtrees of its children
    /// follow each other in that range.
    child_ptr: Vec<usize>,
    children: Vec<usize>,
    first: Vec<usize>,
    /// Flops of each subtree's factorization, `Σ_columns (rows below the diagonal)²` (the
    /// count that balances the threads).
    subtree_cost: Vec<f64>,
    roots: Vec<usize>,
    postordered: bool,
    /// Scratch, one per thread that factors a subtree.
    workspaces: Vec<Workspace>,
    max_pattern: usize,
    max_width: usize,
    /// Subtrees the last factorization ran concurrently (1: sequential).
    last_pieces: usize,
    /// The matrices are complex forms of quaternion Hermitian ones, on a structure that keeps
    /// each vertex's two columns together ([`SupernodalLlt::set_quaternionic`]).
    quaternionic: bool,
    /// For a quaternionic structure, the vertex of each row pair below each supernode
    /// (`rows[2k] / 2`): supernode `s`'s pairs are `pair_rows[row_ptr[s] / 2..row_ptr[s + 1] / 2]`.
    /// The solve's gathers and scatters read these (a quarter of the bytes of faer's row
    /// indices) and move each pair as one 32-byte value.
    pair_rows: Vec<u32>,
}

/// The scratch of one thread of the numeric factorization.
struct Workspace {
    /// Local row of a global row in the current supernode, and the gathered row/column
    /// indices of one update.
    global_to_local: Vec<usize>,
    update_rows: Vec<usize>,
    update_cols: Vec<usize>,
    dense_mem: MemBuffer,
    /// Scratch of the off-diagonal solve (see [`solve_right_lower_adjoint`]).
    narrow: NarrowScratch,
    /// One update's column of vertex pairs ([`quaternion_update`]).
    lanes: Vec<[f64; 4]>,
}

impl Workspace {
    fn new<T: Scalar>(n: usize, max_pattern: usize, max_width: usize) -> Option<Self> {
        Some(Workspace {
            global_to_local: vec![UNMAPPED; n],
            update_rows: vec![0; max_pattern],
            update_cols: vec![0; max_pattern],
            dense_mem: MemBuffer::try_new(cholesky_in_place_scratch::<T>(
                max_width,
                Par::Seq,
                Default::default(),
            ))
            .ok()?,
            narrow: NarrowScratch::new(),
            lanes: vec![[0.0; 4]; max_pattern.div_ceil(2)],
        })
    }
}

/// Below this many flops a subtree is not worth a thread of its own (a thread costs tens of
/// microseconds to start; this is a few milliseconds of work).
const PARALLEL_MIN_FLOPS: f64 = 2e7;

/// What one factorization call needs besides its own slice of the factor: the symbolic
/// structure and the matrix.
struct Job<'a, T> {
    kernel: &'a Shared<'a>,
    symbolic: &'a SymbolicSupernodalCholesky<usize>,
    a: &'a [T],
}

/// The read-only part of [`SupernodalLlt`], shared by the threads.
struct Shared<'a> {
    #[cfg(target_arch = "x86_64")]
    instructions: private_gemm_x86::InstrSet,
    descendant_ptr: &'a [usize],
    descendants: &'a [usize],
    a_ptr: &'a [usize],
    a_position: &'a [u32],
    child_ptr: &'a [usize],
    children: &'a [usize],
    first: &'a [usize],
    subtree_cost: &'a [f64],
    quaternionic: bool,
}

/// A pivot that was not positive, by column of the permuted matrix.
#[derive(Debug)]
pub struct NotPositive(pub usize);

impl SupernodalLlt {
    /// Precomputes the update lists and `A`'s positions in the factor for the lower triangle
    /// `lower` (the pattern `symbolic` was analyzed for). `None` when the CPU lacks the
    /// fused update kernel's instructions (or on non-x86_64), or on allocation failure.
    pub fn new<T: Scalar>(
        symbolic: &SymbolicSupernodalCholesky<usize>,
        lower: SymbolicSparseColMatRef<'_, usize>,
    ) -> Option<Self> {
        #[cfg(target_arch = "x86_64")]
        let instructions = gemm_instructions()?;
        #[cfg(not(target_arch = "x86_64"))]
        return None;

        let n = symbolic.nrows();
        let n_supernodes = symbolic.n_supernodes();
        let begin = symbolic.supernode_begin();
        let end = symbolic.supernode_end();
        let row_ptr = symbolic.col_ptr_for_row_idx();
        let row_idx = symbolic.row_idx();
        let mut supernode_of = vec![0usize; n];
        for s in 0..n_supernodes {
            supernode_of[begin[s]..end[s]].fill(s);
        }
        let pattern = |s: usize| &row_idx[row_ptr[s]..row_ptr[s + 1]];

        // Descendant lists: d updates every supernode its off-diagonal rows fall in.
        let targets = |d: usize| {
            let mut last = UNMAPPED;
            pattern(d)
                .iter()
                .map(|&row| supernode_of[row])
                .filter(move |&s| {
                    let new = s != last;
                    last = s;
                    new
                })
        };
        let mut descendant_ptr = vec![0usize; n_supernodes + 1];
        for d in 0..n_supernodes {
            for s in targets(d) {
                descendant_ptr[s + 1] += 1;
            }
        }
        for s in 0..n_supernodes {
            descendant_ptr[s + 1] += descendant_ptr[s];
        }
        let mut next = descendant_ptr.clone();
        let mut descendants = vec![0usize; descendant_ptr[n_supernodes]];
        for d in 0..n_supernodes {
            for s in targets(d) {
                descendants[next[s]] = d;
                next[s] += 1;
            }
        }

        // Positions of A's lower triangle inside each supernode's column-major block, in
        // the triangle's own (CSC) order.
        let col_ptr = lower.col_ptr();
        let a_rows = lower.row_idx();
        let mut global_to_local = vec![UNMAPPED; n];
        let mut a_position = Vec::with_capacity(a_rows.len());
        let mut max_pattern = 0;
        let mut max_width = 0;
        for s in 0..n_supernodes {
            let (start, stop) = (begin[s], end[s]);
            let width = stop - start;
            let s_pattern = pattern(s);
            let height = width + s_pattern.len();
            max_pattern = max_pattern.max(s_pattern.len());
            max_width = max_width.max(width);
            for (i, &row) in s_pattern.iter().enumerate() {
                global_to_local[row] = width + i;
            }
            for j in start..stop {
                for &i in &a_rows[col_ptr[j]..col_ptr[j + 1]] {
                    let local = match i {
                        i if i < j => return None,
                        i if i < stop => i - start,
                        i => global_to_local[i],
                    };
                    if local == UNMAPPED {
                        return None;
                    }
                    a_position.push(u32::try_from(local + (j - start) * height).ok()?);
                }
            }
            for &row in s_pattern {
                global_to_local[row] = UNMAPPED;
            }
        }
        let a_ptr = begin
            .iter()
            .map(|&column| col_ptr[column])
            .chain([col_ptr[n]])
            .collect();
        drop(global_to_local);

        // The supernodal elimination tree: the parent of `s` holds the first row below it.
        let parent: Vec<usize> = (0..n_supernodes)
            .map(|s| {
                pattern(s)
                    .first()
                    .map_or(UNMAPPED, |&row| supernode_of[row])
            })
            .collect();
        let mut child_ptr = vec![0usize; n_supernodes + 1];
        for &p in &parent {
            if p != UNMAPPED {
                child_ptr[p + 1] += 1;
            }
        }
        for s in 0..n_supernodes {
            child_ptr[s + 1] += child_ptr[s];
        }
        let mut next = child_ptr.clone();
        let mut children = vec![0usize; child_ptr[n_supernodes]];
        for (s, &p) in parent.iter().enumerate() {
            if p != UNMAPPED {
                children[next[p]] = s;
                next[p] += 1;
            }
        }
        // Children come before their parent, so one ascending pass sees whole subtrees.
        let mut first: Vec<usize> = (0..n_supernodes).collect();
        let mut size = vec![1usize; n_supernodes];
        let mut subtree_cost = vec![0f64; n_supernodes];
        let mut postordered = true;
        for s in 0..n_supernodes {
            let height = (end[s] - begin[s]) + pattern(s).len();
            subtree_cost[s] += (0..end[s] - begin[s])
                .map(|k| ((height - k - 1) as f64).powi(2))
                .sum::<f64>();
            if parent[s] != UNMAPPED {
                if parent[s] <= s {
                    postordered = false;
                    continue;
                }
                let p = parent[s];
                first[p] = first[p].min(first[s]);
                size[p] += size[s];
                subtree_cost[p] += subtree_cost[s];
            }
        }
        postordered &= (0..n_supernodes).all(|s| s + 1 - first[s] == size[s]);
        let roots = (0..n_supernodes)
            .filter(|&s| parent[s] == UNMAPPED)
            .collect();
        let workspaces = vec![Workspace::new::<T>(n, max_pattern, max_width)?];
        Some(SupernodalLlt {
            #[cfg(target_arch = "x86_64")]
            instructions,
            descendant_ptr,
            descendants,
            a_ptr,
            a_position,
            child_ptr,
            children,
            first,
            subtree_cost,
            roots,
            postordered,
            workspaces,
            max_pattern,
            max_width,
            last_pieces: 1,
            quaternionic: false,
            pair_rows: Vec::new(),
        })
    }

    /// Declares that every matrix factored from now on is the complex form of a quaternion
    /// Hermitian matrix: vertex `u`'s rows `2u, 2u + 1` and vertex `w`'s columns `2w, 2w + 1`
    /// hold `[[a, b], [−b̄, ā]]` ([`crate::geometry::Quaternion::to_complex`]), as the Dirac
    /// matrix X of Appendix G does. Its Cholesky factor is then the complex form of the
    /// quaternionic factor `X = R Rᴴ` (R lower triangular with a real diagonal: unique, as the
    /// complex factor is), so each odd column is a copy of the even one before it, conjugated
    /// and with its row pairs swapped. The descendant updates — most of the work — then run on
    /// the even columns only, half the multiply-adds, and each supernode's odd columns are
    /// copied from its even ones before its diagonal block is factored. The copy is exact, the
    /// factor equal to the full update's up to rounding.
    ///
    /// Returns whether the structure allows it: every supernode must start and end on a vertex
    /// boundary and its rows come in vertex pairs (what [`BlockPattern::expand_order`] and
    /// faer's fundamental supernodes give); otherwise nothing changes.
    ///
    /// [`BlockPattern::expand_order`]: super::solver::BlockPattern::expand_order
    pub fn set_quaternionic(&mut self, symbolic: &SymbolicSupernodalCholesky<usize>) -> bool {
        let begin = symbolic.supernode_begin();
        let end = symbolic.supernode_end();
        let row_ptr = symbolic.col_ptr_for_row_idx();
        let row_idx = symbolic.row_idx();
        let paired = |rows: &[usize]| {
            rows.len().is_multiple_of(2)
                && rows
                    .chunks_exact(2)
                    .all(|pair| pair[0].is_multiple_of(2) && pair[1] == pair[0] + 1)
        };
        self.quaternionic = symbolic.nrows().is_multiple_of(2)
            && u32::try_from(symbolic.nrows() / 2).is_ok()
            && (0..symbolic.n_supernodes()).all(|s| {
                begin[s].is_multiple_of(2)
                    && end[s].is_multiple_of(2)
                    && paired(&row_idx[row_ptr[s]..row_ptr[s + 1]])
            });
        // Every pattern has an even length, so pair `k` of supernode `s` is entry
        // `row_ptr[s] / 2 + k`; the vertex fits in 32 bits (checked above).
        self.pair_rows = if self.quaternionic {
            row_idx.iter().step_by(2).map(|&r| (r / 2) as u32).collect()
        } else {
            Vec::new()
        };
        self.quaternionic
    }

    /// Calls `visit(row, column, k)` for every entry `k` of the lower triangle given to
    /// [`SupernodalLlt::new`], in its order, from the positions the factorization scatters
    /// them to: the triangle's own row indices can be freed once this structure exists.
    pub fn for_each_lower_entry(
        &self,
        symbolic: &SymbolicSupernodalCholesky<usize>,
        mut visit: impl FnMut(usize, usize, usize),
    ) {
        let begin = symbolic.supernode_begin();
        let end = symbolic.supernode_end();
        let row_ptr = symbolic.col_ptr_for_row_idx();
        let row_idx = symbolic.row_idx();
        for s in 0..symbolic.n_supernodes() {
            let width = end[s] - begin[s];
            let below = &row_idx[row_ptr[s]..row_ptr[s + 1]];
            let height = width + below.len();
            for k in self.a_ptr[s]..self.a_ptr[s + 1] {
                let position = self.a_position[k] as usize;
                let (local, column) = (position % height, position / height);
                let row = match local.checked_sub(width) {
                    None => begin[s] + local,
                    Some(i) => below[i],
                };
                visit(row, begin[s] + column, k);
            }
        }
    }

    /// Whether the factorization can run subtrees on threads of their own (the supernodes
    /// are in postorder, so every subtree is a contiguous range of the factor).
    pub fn parallel(&self) -> bool {
        self.postordered
    }

    /// Whether [`SupernodalLlt::set_quaternionic`] took.
    pub fn quaternionic(&self) -> bool {
        self.quaternionic
    }

    /// The length of the scratch [`SupernodalLlt::solve_quaternionic`] needs: the widest
    /// supernode and the most rows below one, in vertex pairs.
    pub fn solve_scratch_len(&self) -> usize {
        (self.max_pattern + self.max_width).div_ceil(2)
    }

    /// `x ← (L Lᴴ)⁻¹ x` for a quaternionic factor `l` (in faer's supernodal storage, of the
    /// matrix this kernel was analyzed for), one right-hand side. Below the diagonal blocks it
    /// reads the even columns only: with `(p, q) = (L[2u, 2w], L[2u + 1, 2w])` the odd column
    /// holds `(−q̄, p̄)` ([`SupernodalLlt::set_quaternionic`]). A solve streams the factor
    /// through memory twice, so half the columns is about half the time. `scratch` holds at
    /// least [`SupernodalLlt::solve_scratch_len`] lanes.
    pub fn solve_quaternionic<T: Scalar>(
        &self,
        symbolic: &SymbolicSupernodalCholesky<usize>,
        l: &[T],
        x: &mut [T],
        scratch: &mut [[f64; 4]],
    ) {
        assert!(self.quaternionic && x.len() == symbolic.nrows());
        assert!(2 * scratch.len() >= self.max_pattern + self.max_width);
        let begin = symbolic.supernode_begin();
        let end = symbolic.supernode_end();
        let row_ptr = symbolic.col_ptr_for_row_idx();
        let val_ptr = symbolic.col_ptr_for_val();
        let pairs_of = |s: usize| &self.pair_rows[row_ptr[s] / 2..row_ptr[s + 1] / 2];
        // L y = b: each vertex pair of a supernode is divided by its real diagonal, then its
        // even column (and with it the odd one) is taken off the rows below, in the
        // supernode and under it. The diagonal blocks' (2w + 1, 2w) entries are the zeros
        // of the quaternionic factor (rounding in the computed one) and are not read.
        let n_supernodes = symbolic.n_supernodes();
        for s in 0..n_supernodes {
            let (start, width) = (begin[s], end[s] - begin[s]);
            let nrows = width + (row_ptr[s + 1] - row_ptr[s]);
            let block = &l[val_ptr[s]..val_ptr[s + 1]];
            let pairs = pairs_of(s);
            let ahead = s + SOLVE_PREFETCH_AHEAD;
            if ahead < n_supernodes {
                prefetch_even_columns(
                    &l[val_ptr[ahead]..val_ptr[ahead + 1]],
                    end[ahead] - begin[ahead],
                );
            }
            if s + 1 < n_supernodes {
                prefetch_pairs(x, pairs_of(s + 1));
            }
            // The supernode's own pairs, then the pairs below it: the rows of its columns.
            let lanes = &mut scratch[..nrows / 2];
            gather_pairs(x, start / 2..(start + width) / 2, &mut lanes[..width / 2]);
            gather_pairs(
                x,
                pairs.iter().map(|&p| p as usize),
                &mut lanes[width / 2..],
            );
            for w in 0..width / 2 {
                let column = &block[2 * w * nrows..][..nrows];
                let inverse = 1.0 / column[2 * w].diagonal();
                let (lane, after_w) = lanes[w..].split_at_mut(1);
                let lane = lane[0].map(|v| v * inverse);
                // SAFETY: the kernel is only built on CPUs with AVX2 and FMA.
                unsafe {
                    quaternion_column_product(
                        &column[2 * w + 2..],
                        (lane[0], lane[1]),
                        (lane[2], lane[3]),
                        after_w,
                    );
                }
                lanes[w] = lane;
            }
            scatter_pairs(x, start / 2..(start + width) / 2, &lanes[..width / 2]);
            scatter_pairs(x, pairs.iter().map(|&p| p as usize), &lanes[width / 2..]);
        }
        // Lᴴ x = y, in reverse: each pair takes the adjoint products of its even column with
        // the rows below, then is divided by its diagonal.
        for s in (0..n_supernodes).rev() {
            let (start, width) = (begin[s], end[s] - begin[s]);
            let nrows = width + (row_ptr[s + 1] - row_ptr[s]);
            let block = &l[val_ptr[s]..val_ptr[s + 1]];
            let pairs = pairs_of(s);
            if let Some(ahead) = s.checked_sub(SOLVE_PREFETCH_AHEAD) {
                prefetch_even_columns(
                    &l[val_ptr[ahead]..val_ptr[ahead + 1]],
                    end[ahead] - begin[ahead],
                );
            }
            if s > 0 {
                prefetch_pairs(x, pairs_of(s - 1));
            }
            let lanes = &mut scratch[..nrows / 2];
            gather_pairs(x, start / 2..(start + width) / 2, &mut lanes[..width / 2]);
            gather_pairs(
                x,
                pairs.iter().map(|&p| p as usize),
                &mut lanes[width / 2..],
            );
            for w in (0..width / 2).rev() {
                let column = &block[2 * w * nrows..][..nrows];
                let (to_w, after_w) = lanes.split_at_mut(w + 1);
                // SAFETY: as above.
                let (a0, a1) = unsafe { quaternion_column_adjoint(&column[2 * w + 2..], after_w) };
                let inverse = 1.0 / column[2 * w].diagonal();
                let lane = &mut to_w[w];
                *lane = [
                    (lane[0] - a0.0) * inverse,
                    (lane[1] - a0.1) * inverse,
                    (lane[2] - a1.0) * inverse,
                    (lane[3] - a1.1) * inverse,
                ];
            }
            scatter_pairs(x, start / 2..(start + width) / 2, &lanes[..width / 2]);
        }
    }

    /// Subtrees the last factorization ran concurrently (1: it ran on one thread).
    pub fn last_pieces(&self) -> usize {
        self.last_pieces
    }

    /// Factors the matrix whose lower triangle has `a` as values (in the order of the
    /// pattern given to [`SupernodalLlt::new`]) into `l` (faer's supernodal storage), on up to
    /// `threads` threads: independent subtrees of the elimination tree (nested dissection's
    /// two halves, then theirs) factor concurrently, each supernode still left-looking and
    /// sequential, so the factor is bitwise the same for any thread count.
    pub fn factorize<T: Scalar>(
        &mut self,
        symbolic: &SymbolicSupernodalCholesky<usize>,
        l: &mut [T],
        a: &[T],
        threads: usize,
    ) -> Result<(), NotPositive> {
        let n_supernodes = symbolic.n_supernodes();
        let threads = if self.postordered { threads.max(1) } else { 1 };
        // A thread's scratch that cannot be allocated leaves the work to fewer threads.
        while self.workspaces.len() < threads {
            match Workspace::new::<T>(symbolic.nrows(), self.max_pattern, self.max_width) {
                Some(ws) => self.workspaces.push(ws),
                None => break,
            }
        }
        let threads = threads.min(self.workspaces.len());
        let shared = Shared {
            #[cfg(target_arch = "x86_64")]
            instructions: self.instructions,
            descendant_ptr: &self.descendant_ptr,
            descendants: &self.descendants,
            a_ptr: &self.a_ptr,
            a_position: &self.a_position,
            child_ptr: &self.child_ptr,
            children: &self.children,
            first: &self.first,
            subtree_cost: &self.subtree_cost,
            quaternionic: self.quaternionic,
        };
        let job = Job {
            kernel: &shared,
            symbolic,
            a,
        };
        let workspaces = &mut self.workspaces[..threads];
        let total: f64 = self.roots.iter().map(|&r| self.subtree_cost[r]).sum();
        if threads == 1 || total < PARALLEL_MIN_FLOPS {
            self.last_pieces = 1;
            return job.factor_range(0..n_supernodes, l, 0, &mut workspaces[0]);
        }
        let (pieces, top) = subtree_mapping(&shared, &self.roots, threads);
        self.last_pieces = pieces.len();
        let val_ptr = symbolic.col_ptr_for_val();
        // Each piece's subtree owns a contiguous run of the factor; cut `l` into those runs.
        let mut runs: Vec<(usize, std::ops::Range<usize>, usize, &mut [T])> = Vec::new();
        let mut rest: &mut [T] = l;
        let mut offset = 0;
        let mut by_position = pieces.clone();
        by_position.sort_unstable_by_key(|&(root, _)| shared.first[root]);
        for (root, thread) in by_position {
            let (start, end) = (val_ptr[shared.first[root]], val_ptr[root + 1]);
            let (_, tail) = std::mem::take(&mut rest).split_at_mut(start - offset);
            let (run, tail) = tail.split_at_mut(end - start);
            rest = tail;
            offset = end;
            runs.push((thread, shared.first[root]..root + 1, start, run));
        }
        let mut per_thread: Vec<Vec<Run<'_, T>>> = (0..threads).map(|_| Vec::new()).collect();
        for (thread, range, base, run) in runs {
            per_thread[thread].push((range, base, run));
        }
        let job = &job;
        std::thread::scope(|scope| {
            let mut handles = Vec::new();
            let mut lists = per_thread.into_iter();
            let mut spaces = workspaces.iter_mut();
            let own = (lists.next(), spaces.next());
            for (list, ws) in lists.zip(spaces) {
                handles.push(scope.spawn(move || {
                    list.into_iter()
                        .try_for_each(|(range, base, run)| job.factor_range(range, run, base, ws))
                }));
            }
            let mut result = Ok(());
            if let (Some(list), Some(ws)) = own {
                result = list
                    .into_iter()
                    .try_for_each(|(range, base, run)| job.factor_range(range, run, base, ws));
            }
            for h in handles {
                // A panic in a thread is this call's panic, as it would be on one thread.
                let r = h
                    .join()
                    .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
                result = result.and(r);
            }
            result
        })?;
        // The separators above the pieces, in order (descendants first), on this thread.
        for s in top {
            job.factor_range(s..s + 1, l, 0, &mut workspaces[0])?;
        }
        Ok(())
    }
}

/// A subtree's supernodes, the first factor value it owns, and those values.
type Run<'a, T> = (std::ops::Range<usize>, usize, &'a mut [T]);

/// Geist and Ng's subtree-to-thread mapping: starting from the roots, the heaviest subtree
/// is replaced by its children (its root joins the sequential top) until the subtrees, dealt
/// longest first to the least loaded thread, keep every thread within 10% of an even share.
/// Returns each subtree's root with its thread, and the top supernodes, ascending.
fn subtree_mapping(
    shared: &Shared<'_>,
    roots: &[usize],
    threads: usize,
) -> (Vec<(usize, usize)>, Vec<usize>) {
    let cost = |r: usize| shared.subtree_cost[r];
    let mut pieces: Vec<usize> = roots.to_vec();
    let mut top = Vec::new();
    // A separator splits into a few children at most; this bounds the loop on any tree.
    for _ in 0..4096 {
        pieces.sort_unstable_by(|&a, &b| cost(b).total_cmp(&cost(a)));
        let total: f64 = pieces.iter().map(|&r| cost(r)).sum();
        let mut loads = vec![0f64; threads];
        for &r in &pieces {
            let least = (0..threads)
                .min_by(|&a, &b| loads[a].total_cmp(&loads[b]))
                .unwrap_or(0);
            loads[least] += cost(r);
        }
        let makespan = loads.iter().copied().fold(0.0, f64::max);
        let Some(&heaviest) = pieces.first() else {
            break;
        };
        let kids = &shared.children[shared.child_ptr[heaviest]..shared.child_ptr[heaviest + 1]];
        if makespan <= 1.1 * total / threads as f64 || kids.is_empty() {
            break;
        }
        pieces.remove(0);
        top.push(heaviest);
        pieces.extend_from_slice(kids);
    }
    pieces.sort_unstable_by(|&a, &b| cost(b).total_cmp(&cost(a)));
    let mut loads = vec![0f64; threads];
    let mut mapping = Vec::with_capacity(pieces.len());
    for r in pieces {
        let least = (0..threads)
            .min_by(|&a, &b| loads[a].total_cmp(&loads[b]))
            .unwrap_or(0);
        loads[least] += cost(r);
        mapping.push((r, least));
    }
    top.sort_unstable();
    (mapping, top)
}

impl<T: Scalar> Job<'_, T> {
    /// Factors the supernodes `range` in order, sequentially; `l` holds their values and
    /// their descendants' (factor value `base` onwards).
    fn factor_range(
        &self,
        range: std::ops::Range<usize>,
        l: &mut [T],
        base: usize,
        ws: &mut Workspace,
    ) -> Result<(), NotPositive> {
        let k = self.kernel;
        let symbolic = self.symbolic;
        let begin = symbolic.supernode_begin();
        let end = symbolic.supernode_end();
        let row_ptr = symbolic.col_ptr_for_row_idx();
        let val_ptr = symbolic.col_ptr_for_val();
        let row_idx = symbolic.row_idx();
        let pattern = |s: usize| &row_idx[row_ptr[s]..row_ptr[s + 1]];
        for s in range {
            let (s_start, s_end) = (begin[s], end[s]);
            let s_pattern = pattern(s);
            let s_ncols = s_end - s_start;
            let s_nrows = s_ncols + s_pattern.len();
            for (i, &row) in s_pattern.iter().enumerate() {
                ws.global_to_local[row] = s_ncols + i;
            }
            let (head, tail) = l.split_at_mut(val_ptr[s] - base);
            let block = &mut tail[..val_ptr[s + 1] - val_ptr[s]];
            block.fill(T::zero_impl());
            for (&position, &value) in k.a_position[k.a_ptr[s]..k.a_ptr[s + 1]]
                .iter()
                .zip(&self.a[k.a_ptr[s]..k.a_ptr[s + 1]])
            {
                block[position as usize] = value;
            }
            debug_assert!(
                !k.quaternionic || odd_columns_are_copies(block, s_nrows, s_ncols),
                "supernode {s}: the matrix is not quaternionic, set_quaternionic does not apply"
            );

            for &d in &k.descendants[k.descendant_ptr[s]..k.descendant_ptr[s + 1]] {
                let d_pattern = pattern(d);
                let d_ncols = end[d] - begin[d];
                let d_nrows = d_ncols + d_pattern.len();
                // d is in s's subtree, so its values lie in this call's slice.
                let ld = &head[val_ptr[d] - base..val_ptr[d + 1] - base];
                let first = d_pattern.partition_point(|&r| r < s_start);
                let below = &d_pattern[first..];
                let mid = below.partition_point(|&r| r < s_end);
                let rows = &mut ws.update_rows[..below.len()];
                for (i, (local, &row)) in rows.iter_mut().zip(below).enumerate() {
                    *local = if i < mid {
                        row - s_start
                    } else {
                        ws.global_to_local[row]
                    };
                }
                // Quaternionic: the even columns only (every other row of `below[..mid]`,
                // which comes in vertex pairs), the odd ones are copied below.
                let step = if k.quaternionic { 2 } else { 1 };
                let cols = &mut ws.update_cols[..mid.div_ceil(step)];
                for (local, &row) in cols.iter_mut().zip(below.iter().step_by(step)) {
                    *local = row - s_start;
                }
                // L_s[rows, cols] −= L_d[below] · L_d[below[..mid]]ᴴ, lower part only.
                debug_assert!(
                    rows.iter().all(|&r| r < s_nrows) && cols.iter().all(|&c| c < s_ncols)
                );
                let ld_below = &ld[d_ncols + first..];
                #[cfg(target_arch = "x86_64")]
                if k.quaternionic && rows.len() * cols.len() * d_ncols <= LANE_UPDATE_MAX_MACS {
                    // SAFETY: the kernel is only built on CPUs with AVX2 and FMA.
                    unsafe {
                        quaternion_update(
                            block,
                            s_nrows,
                            ld_below,
                            d_nrows,
                            d_ncols,
                            rows,
                            cols,
                            &mut ws.lanes,
                        )
                    };
                    continue;
                }
                #[cfg(target_arch = "x86_64")]
                gemm(
                    k.instructions,
                    block,
                    s_nrows,
                    s_nrows,
                    s_ncols,
                    Some(rows),
                    Some(cols),
                    true,
                    true,
                    View {
                        data: ld_below,
                        nrows: below.len(),
                        ncols: d_ncols,
                        row_stride: 1,
                        col_stride: d_nrows,
                        conj: false,
                    },
                    // L_d[below[..mid]]ᴴ: entry (p, j) is conj(L_d[below[step·j], p]).
                    View {
                        data: ld_below,
                        nrows: d_ncols,
                        ncols: cols.len(),
                        row_stride: d_nrows,
                        col_stride: step,
                        conj: true,
                    },
                    T::zero_impl() - T::one_impl(),
                );
            }
            #[cfg(target_arch = "x86_64")]
            if k.quaternionic {
                factor_quaternionic_supernode(
                    k.instructions,
                    block,
                    s_nrows,
                    s_ncols,
                    &mut ws.narrow,
                )
                .map_err(|column| NotPositive(column + s_start))?;
                for &row in s_pattern {
                    ws.global_to_local[row] = UNMAPPED;
                }
                continue;
            }

            let ls = MatMut::from_column_major_slice_mut(block, s_nrows, s_ncols);
            let (top, _) = ls.split_at_row_mut(s_ncols);
            cholesky_in_place(
                top,
                Default::default(),
                Par::Seq,
                MemStack::new(&mut ws.dense_mem),
                Default::default(),
            )
            .map_err(|e| match e {
                faer::linalg::cholesky::llt::factor::LltError::NonPositivePivot { index } => {
                    NotPositive(index + s_start)
                }
            })?;
            #[cfg(target_arch = "x86_64")]
            solve_right_lower_adjoint(k.instructions, block, s_nrows, s_ncols, &mut ws.narrow);
            for &row in s_pattern {
                ws.global_to_local[row] = UNMAPPED;
            }
        }
        Ok(())
    }
}

/// The entry of odd column `2w + 1` at row `i` of a quaternionic supernode block, from the even
/// column `2w` (`even`): `[[a, b], [−b̄, ā]]` puts `b = −conj(L[2u + 1, 2w])` at row `2u`
/// and `ā = conj(L[2u, 2w])` at row `2u + 1`. Local rows have their global rows' parity
/// (supernodes start on even columns, their row lists come in pairs).
fn quaternion_partner<T: Scalar>(even: &[T], i: usize) -> T {
    if i.is_multiple_of(2) {
        T::zero_impl() - T::conj_impl(&even[i + 1])
    } else {
        T::conj_impl(&even[i - 1])
    }
}

/// Factors a quaternionic supernode whose even columns hold `A − Σ L_d L_dᴴ` (the descendant
/// updates done): left-looking over panels of [`NARROW`] columns, each panel's even columns
/// take the earlier panels' product (`L[first.., ..first] L[panel, ..first]ᴴ`, half the
/// multiply-adds of the full panel), its diagonal block is factored by
/// [`quaternionic_diagonal_cholesky`] and the rows below it are solved by [`solve_narrow`],
/// both writing each odd column as the copy of its even one (so the odd columns' values of
/// `A` are never read, nor copied first). This replaces the dense Cholesky of the whole
/// diagonal block and the off-diagonal solve of the general path, which would spend the full
/// count on the diagonal block.
/// Returns the column (in the supernode) of a pivot that is not positive.
#[cfg(target_arch = "x86_64")]
fn factor_quaternionic_supernode<T: Scalar>(
    instructions: private_gemm_x86::InstrSet,
    block: &mut [T],
    nrows: usize,
    width: usize,
    narrow: &mut NarrowScratch,
) -> Result<(), usize> {
    for first in (0..width).step_by(NARROW) {
        let panel = NARROW.min(width - first);
        let (done, rest) = block.split_at_mut(first * nrows);
        if first > 0 {
            // L[first.., even panel columns] −= L[first.., ..first] L[first + 2j, ..first]ᴴ
            let (rows, c) = (nrows - first, &mut rest[first..]);
            panel_product(instructions, c, done, nrows, first, rows, first, panel, 2);
        }
        quaternionic_diagonal_cholesky(rest, nrows, first, panel).map_err(|j| first + j)?;
        // SAFETY: `SupernodalLlt::new` only builds this kernel on CPUs with AVX2 and FMA.
        unsafe { solve_narrow(rest, nrows, first, panel, first + panel, true, narrow) };
    }
    Ok(())
}

/// `LLᴴ` of a panel's quaternionic diagonal block in place: the `width × width` block at rows
/// `diagonal..` of the first `width` columns of `block` (column-major, `nrows` rows), lower
/// triangle (only its even columns are read). Computes the even columns by left-looking
/// substitution and copies each into the odd column after it before the next reads it: half the
/// multiply-adds of a full Cholesky, and none of a dense library call's setup, which cost more than
/// the work on blocks this small (most panels of a mesh's X are 2–10 columns; faer's
/// `cholesky_in_place` took 3.4 ms of nefertiti's 85 ms factorization). The `(2w + 1, 2w)` entries
/// come out as rounding, as in the full factorization: the quaternionic factor's zeros, never read.
/// Returns the column of a pivot that is not positive (or not finite).
fn quaternionic_diagonal_cholesky<T: Scalar>(
    block: &mut [T],
    nrows: usize,
    diagonal: usize,
    width: usize,
) -> Result<(), usize> {
    debug_assert!(width.is_multiple_of(2) && diagonal.is_multiple_of(2));
    let at = |i: usize, j: usize| diagonal + i + j * nrows;
    for j in (0..width).step_by(2) {
        // v[i] = A[i, j] − Σ_{k<j} L[i, k] conj(L[j, k]), i ≥ j; L[j, j] = √v[j].
        let mut pivot = block[at(j, j)].re();
        for k in 0..j {
            let l = block[at(j, k)];
            pivot -= l.re() * l.re() + l.im() * l.im();
        }
        if !(pivot > 0.0 && pivot.is_finite()) {
            return Err(j);
        }
        let d = pivot.sqrt();
        let inverse = 1.0 / d;
        block[at(j, j)] = T::from_parts(d, 0.0);
        for i in j + 1..width {
            let (mut re, mut im) = (block[at(i, j)].re(), block[at(i, j)].im());
            for k in 0..j {
                // L[i, k] · conj(L[j, k])
                let (a, b) = (block[at(i, k)], block[at(j, k)]);
                re -= a.re() * b.re() + a.im() * b.im();
                im -= a.im() * b.re() - a.re() * b.im();
            }
            block[at(i, j)] = T::from_parts(re * inverse, im * inverse);
        }
        // The odd column: L[j + 1, j + 1] = conj(L[j, j]), then the row pairs below.
        let (even, odd) = block[at(0, j)..].split_at_mut(nrows);
        copy_odd_columns_from(even, odd, j + 1, width);
    }
    Ok(())
}

/// The earlier columns' product on one panel of a supernode's own factorization (the block
/// is column-major with `nrows` rows; `done` holds its columns `..first`):
/// `C[:, j] −= L[x_start..x_start + x_rows, ..first] · conj(L[first + step·j, ..first])ᵀ`
/// for the panel's columns `first + step·j` (`step` 2: its even columns only), into `c` with
/// column stride `step · nrows`.
#[cfg(target_arch = "x86_64")]
#[allow(clippy::too_many_arguments)]
fn panel_product<T: Scalar>(
    instructions: private_gemm_x86::InstrSet,
    c: &mut [T],
    done: &[T],
    nrows: usize,
    x_start: usize,
    x_rows: usize,
    first: usize,
    panel: usize,
    step: usize,
) {
    let ncols = panel.div_ceil(step);
    gemm(
        instructions,
        c,
        step * nrows,
        x_rows,
        ncols,
        None,
        None,
        false,
        true,
        View {
            data: &done[x_start..],
            nrows: x_rows,
            ncols: first,
            row_stride: 1,
            col_stride: nrows,
            conj: false,
        },
        // Entry (k, j) is conj(L[first + step·j, k]).
        View {
            data: &done[first..],
            nrows: first,
            ncols,
            row_stride: nrows,
            col_stride: step,
            conj: true,
        },
        T::zero_impl() - T::one_impl(),
    );
}

/// Rows `start..end` of an odd column as the partner of the even column before it
/// ([`quaternion_partner`]); `start` is the odd column's diagonal row (odd), so the rest come
/// in whole row pairs.
#[inline(always)]
fn copy_odd_columns_from<T: Scalar>(even: &[T], odd: &mut [T], start: usize, end: usize) {
    // The diagonal entry (odd row), then whole row pairs: branch-free, so it vectorizes.
    odd[start] = quaternion_partner(even, start);
    for (o, e) in odd[start + 1..end]
        .chunks_exact_mut(2)
        .zip(even[start + 1..end].chunks_exact(2))
    {
        o[0] = T::zero_impl() - T::conj_impl(&e[1]);
        o[1] = T::conj_impl(&e[0]);
    }
}

/// Whether the odd columns of a block of `A` (on and below the diagonal) are already the
/// copies [`copy_odd_columns_from`] writes, bit for bit.
fn odd_columns_are_copies<T: Scalar>(block: &[T], nrows: usize, ncols: usize) -> bool {
    (1..ncols).step_by(2).all(|c| {
        let even = &block[(c - 1) * nrows..c * nrows];
        (c..nrows).all(|i| block[c * nrows + i] == quaternion_partner(even, i))
    })
}

/// How many supernodes ahead the quaternionic solve prefetches the factor's columns: a
/// supernode's work is shorter than a memory round trip (nefertiti's X: 17.0–17.4 ms a solve at
/// 2, 17.4–17.7 at 1, 17.4–17.9 at 3, same process and matrix).
const SOLVE_PREFETCH_AHEAD: usize = 2;

/// Asks the CPU to bring the even columns of a supernode's `block` (`width` columns) into
/// cache before a quaternionic solve reads them: the solves visit the factor in runs of a few
/// cache lines, one run a column, too short for the hardware prefetcher to follow.
#[inline(always)]
fn prefetch_even_columns<T>(block: &[T], width: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let nrows = block.len() / width.max(1);
        for w in (0..width).step_by(2) {
            let column = &block[w * nrows..(w + 1) * nrows];
            let ptr = column.as_ptr().cast::<i8>();
            for offset in (0..std::mem::size_of_val(column)).step_by(64) {
                // SAFETY: SSE is part of the x86_64 baseline, and a prefetch never faults.
                unsafe { _mm_prefetch::<_MM_HINT_T0>(ptr.wrapping_add(offset)) };
            }
        }
    }
}

/// Asks the CPU to bring the vertex pairs `x[2p..2p + 2]` of the next supernode into cache:
/// they are scattered over the whole right-hand side.
#[inline(always)]
fn prefetch_pairs<T>(x: &[T], pairs: &[u32]) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        for &p in pairs {
            let at = x.as_ptr().wrapping_add(2 * p as usize).cast::<i8>();
            // SAFETY: SSE is part of the x86_64 baseline, and a prefetch never faults.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(at) };
        }
    }
}

/// The vertex pairs `x[2p..2p + 2]` as lanes `[x₀.re, x₀.im, x₁.re, x₁.im]` (for c64, one
/// 32-byte load each).
#[inline(always)]
fn gather_pairs<T: Scalar>(x: &[T], pairs: impl Iterator<Item = usize>, lanes: &mut [[f64; 4]]) {
    for (lane, p) in lanes.iter_mut().zip(pairs) {
        *lane = pair_lanes(&x[2 * p..2 * p + 2]);
    }
}

/// The inverse of [`gather_pairs`].
#[inline(always)]
fn scatter_pairs<T: Scalar>(x: &mut [T], pairs: impl Iterator<Item = usize>, lanes: &[[f64; 4]]) {
    for (lane, p) in lanes.iter().zip(pairs) {
        let pair = &mut x[2 * p..2 * p + 2];
        pair[0] = T::from_parts(lane[0], lane[1]);
        pair[1] = T::from_parts(lane[2], lane[3]);
    }
}

/// `(L[2u, 2w], L[2u + 1, 2w]) = (p, q)` as four lanes `[p.re, p.im, q.re, q.im]`.
#[inline(always)]
fn pair_lanes<T: Scalar>(pair: &[T]) -> [f64; 4] {
    [pair[0].re(), pair[0].im(), pair[1].re(), pair[1].im()]
}

/// `out[u] −= (p x₀ − q̄ x₁, q x₀ + p̄ x₁)` over the row pairs `(p, q)` of an even factor
/// column: its product, and its odd partner's, with `(x₀, x₁)` (the quaternionic forward
/// solve). Lane by lane, so that it compiles to four fused multiply-adds and three shuffles
/// per pair.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn quaternion_column_product<T: Scalar>(
    column: &[T],
    x0: (f64, f64),
    x1: (f64, f64),
    out: &mut [[f64; 4]],
) {
    let c = product_coefficients(x0, x1);
    for (pair, o) in column.chunks_exact(2).zip(out) {
        apply_product(pair_lanes(pair), &c, o);
    }
}

/// The negated coefficients of `(p x₀ − q̄ x₁, q x₀ + p̄ x₁)` on the lanes of `v`, `vb`, `vc`,
/// `vd` ([`apply_product`]).
#[inline(always)]
fn product_coefficients(x0: (f64, f64), x1: (f64, f64)) -> [[f64; 4]; 4] {
    [
        [-x0.0; 4],
        [x0.1, -x0.1, x0.1, -x0.1],
        [x1.0, -x1.0, -x1.0, x1.0],
        [x1.1, x1.1, -x1.1, -x1.1],
    ]
}

/// `o −= (p x₀ − q̄ x₁, q x₀ + p̄ x₁)` for the pair lanes `v` and [`product_coefficients`].
#[inline(always)]
fn apply_product(v: [f64; 4], c: &[[f64; 4]; 4], o: &mut [f64; 4]) {
    let vb = [v[1], v[0], v[3], v[2]];
    let vc = [v[2], v[3], v[0], v[1]];
    let vd = [v[3], v[2], v[1], v[0]];
    for l in 0..4 {
        o[l] = v[l].mul_add(
            c[0][l],
            vb[l].mul_add(
                c[1][l],
                vc[l].mul_add(c[2][l], vd[l].mul_add(c[3][l], o[l])),
            ),
        );
    }
}

/// The largest quaternionic descendant update (rows × even columns × descendant columns, in
/// complex multiply-adds) that [`quaternion_update`] does instead of the packed gemm. Most
/// updates of a mesh's X are a few pairs wide, where the gemm's packing and call cost more
/// than the products; measured on nefertiti's X (min of 20 factorizations each, one process):
/// 91–94 ms with this bound anywhere in 4096–16384, 99–102 ms with the gemm alone, 105 ms with
/// the lanes alone (they lose on the wide updates).
const LANE_UPDATE_MAX_MACS: usize = 4096;

/// One descendant's update of a quaternionic supernode, `L_s[rows, cols] −= L_d[below]
/// L_d[below[..mid]]ᴴ` on the lower part, vertex pair by vertex pair: for each target pair
/// `j` (even column `cols[j]`), the first column of `Σ_K Q_uK Q_jKᴴ` over the descendant's
/// column pairs `K` and the pairs `u ≥ j` below, where the first column of `Q_jKᴴ` is
/// `(p̄, −q)` for `Q_jK`'s `(p, q)`. `rows` maps the descendant's rows below to the target's
/// local rows (pairs stay adjacent); `ld_below` is the descendant's block from its first
/// row below.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[allow(clippy::too_many_arguments)]
fn quaternion_update<T: Scalar>(
    block: &mut [T],
    s_nrows: usize,
    ld_below: &[T],
    d_nrows: usize,
    d_ncols: usize,
    rows: &[usize],
    cols: &[usize],
    lanes: &mut [[f64; 4]],
) {
    let pairs = rows.len() / 2;
    for (j, &c) in cols.iter().enumerate() {
        let acc = &mut lanes[j..pairs];
        acc.fill([0.0; 4]);
        let coefficients = |column: &[T]| {
            let (p, q) = (column[2 * j], column[2 * j + 1]);
            product_coefficients((p.re(), -p.im()), (-q.re(), -q.im()))
        };
        let mut k = 0;
        // Two column pairs a pass: the accumulators are loaded and stored half as often.
        while k + 4 <= d_ncols {
            let first = &ld_below[k * d_nrows..][..rows.len()];
            let second = &ld_below[(k + 2) * d_nrows..][..rows.len()];
            let (cf, cs) = (coefficients(first), coefficients(second));
            for ((f, s), o) in first[2 * j..]
                .chunks_exact(2)
                .zip(second[2 * j..].chunks_exact(2))
                .zip(acc.iter_mut())
            {
                apply_product(pair_lanes(f), &cf, o);
                apply_product(pair_lanes(s), &cs, o);
            }
            k += 4;
        }
        if k < d_ncols {
            let column = &ld_below[k * d_nrows..][..rows.len()];
            let c = coefficients(column);
            for (f, o) in column[2 * j..].chunks_exact(2).zip(acc.iter_mut()) {
                apply_product(pair_lanes(f), &c, o);
            }
        }
        let target = &mut block[c * s_nrows..][..s_nrows];
        for (u, lane) in (j..pairs).zip(acc.iter()) {
            let r = rows[2 * u];
            target[r] = T::from_parts(target[r].re() + lane[0], target[r].im() + lane[1]);
            target[r + 1] =
                T::from_parts(target[r + 1].re() + lane[2], target[r + 1].im() + lane[3]);
        }
    }
}

/// `(Σ p̄ t₀ + q̄ t₁, Σ −q t₀ + p t₁)` over the row pairs `(p, q)` of an even factor column
/// and `t = [t₀, t₁]` (lanes as [`pair_lanes`]): the adjoint products of the column and its
/// odd partner (the quaternionic backward solve).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn quaternion_column_adjoint<T: Scalar>(column: &[T], t: &[[f64; 4]]) -> ((f64, f64), (f64, f64)) {
    // With v = [p.re, p.im, q.re, q.im] and t = [t₀.re, t₀.im, t₁.re, t₁.im], each part of
    // the result is a signed sum of the lanes of v ⊙ t, of v ⊙ t with the parts of each
    // complex number swapped, with its halves swapped, and reversed: four fused multiply-adds
    // and three permutes a pair, the signs once at the end.
    let mut acc = [[0.0f64; 4]; 4];
    for (pair, w) in column.chunks_exact(2).zip(t) {
        let v = pair_lanes(pair);
        let ws = [
            *w,
            [w[1], w[0], w[3], w[2]],
            [w[2], w[3], w[0], w[1]],
            [w[3], w[2], w[1], w[0]],
        ];
        for (acc, w) in acc.iter_mut().zip(&ws) {
            for l in 0..4 {
                acc[l] = v[l].mul_add(w[l], acc[l]);
            }
        }
    }
    let [a, b, c, d] = acc;
    (
        ((a[0] + a[1]) + (a[2] + a[3]), (b[0] - b[1]) + (b[2] - b[3])),
        ((c[0] - c[1]) - (c[2] - c[3]), (d[0] + d[1]) - (d[2] + d[3])),
    )
}

/// A column-major or transposed view into a slice for [`gemm`]: entry `(i, j)` is
/// `data[i * row_stride + j * col_stride]`, conjugated when `conj`.
#[cfg(target_arch = "x86_64")]
struct View<'a, T> {
    data: &'a [T],
    nrows: usize,
    ncols: usize,
    row_stride: usize,
    col_stride: usize,
    conj: bool,
}

#[cfg(target_arch = "x86_64")]
impl<T> View<'_, T> {
    fn fits(&self) -> bool {
        self.nrows == 0
            || self.ncols == 0
            || (self.nrows - 1) * self.row_stride + (self.ncols - 1) * self.col_stride
                < self.data.len()
    }
}

/// `C[rows, cols] (+)= alpha · A · B` (`+` when `add`) on the lower part (`lower`) or all of
/// the column-major `c_nrows × c_ncols` matrix `C` stored in `c` with column stride
/// `c_stride`; `rows`/`cols` gather the destination (the identity when `None`). faer's
/// fused kernel, through checked views.
#[cfg(target_arch = "x86_64")]
#[allow(clippy::too_many_arguments)]
fn gemm<T: Scalar>(
    instructions: private_gemm_x86::InstrSet,
    c: &mut [T],
    c_stride: usize,
    c_nrows: usize,
    c_ncols: usize,
    rows: Option<&[usize]>,
    cols: Option<&[usize]>,
    lower: bool,
    add: bool,
    a: View<'_, T>,
    b: View<'_, T>,
    alpha: T,
) {
    assert!(c_nrows <= c_stride || c_ncols <= 1);
    assert!(c_nrows == 0 || c_ncols == 0 || (c_ncols - 1) * c_stride + c_nrows <= c.len());
    assert!(a.ncols == b.nrows && a.fits() && b.fits());
    match rows {
        Some(rows) => assert!(rows.len() == a.nrows && rows.iter().all(|&r| r < c_nrows)),
        None => assert!(a.nrows <= c_nrows),
    }
    match cols {
        Some(cols) => assert!(cols.len() == b.ncols && cols.iter().all(|&j| j < c_ncols)),
        None => assert!(b.ncols <= c_ncols),
    }
    if a.nrows == 0 || b.ncols == 0 {
        return;
    }
    // SAFETY: every entry the kernel reads lies in `a.data` or `b.data` (`fits`), and every
    // entry it writes, `(rows[i], cols[j])` or `(i, j)`, lies in the `c_nrows × c_ncols`
    // column-major `c` (checked above); the index arrays, when given, have the lengths of the
    // product's rows and columns. This is the call faer's supernodal kernel makes
    // (`spicy_matmul`).
    unsafe {
        private_gemm_x86::gemm(
            T::GEMM_TYPE,
            private_gemm_x86::IType::U64,
            instructions,
            a.nrows,
            b.ncols,
            a.ncols,
            c.as_mut_ptr() as *mut (),
            1,
            c_stride as isize,
            rows.map_or(std::ptr::null(), |r| r.as_ptr() as *const ()),
            cols.map_or(std::ptr::null(), |j| j.as_ptr() as *const ()),
            if lower {
                private_gemm_x86::DstKind::Lower
            } else {
                private_gemm_x86::DstKind::Full
            },
            if add {
                private_gemm_x86::Accum::Add
            } else {
                private_gemm_x86::Accum::Replace
            },
            a.data.as_ptr() as *const (),
            a.row_stride as isize,
            a.col_stride as isize,
            a.conj,
            std::ptr::null(),
            0,
            b.data.as_ptr() as *const (),
            b.row_stride as isize,
            b.col_stride as isize,
            b.conj,
            &alpha as *const T as *const (),
            1,
        );
    }
}

/// Whether this CPU runs [`SupernodalLlt`] (AVX2 and FMA, or AVX-512, on x86_64).
#[cfg(test)]
fn kernel_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    return gemm_instructions().is_some();
    #[cfg(not(target_arch = "x86_64"))]
    return false;
}

#[cfg(target_arch = "x86_64")]
fn gemm_instructions() -> Option<private_gemm_x86::InstrSet> {
    if std::arch::is_x86_feature_detected!("avx512f") {
        Some(private_gemm_x86::InstrSet::Avx512)
    } else if std::arch::is_x86_feature_detected!("avx2")
        && std::arch::is_x86_feature_detected!("fma")
    {
        Some(private_gemm_x86::InstrSet::Avx256)
    } else {
        None
    }
}

/// `X ← X L⁻ᴴ` for lower triangular `L` (the factor of a supernode's diagonal block, the top
/// `width` rows of the column-major `nrows × width` block) and `X` (the rows below it).
///
/// Column `j` of `X Lᴴ = B` reads `Σ_{k ≤ j} X[:, k] conj(L[j, k])`, so the columns are solved
/// left to right, in panels of [`NARROW`] columns: a panel first takes the contribution of
/// all earlier columns as one matrix product, `X_p −= X_{<p} L[p, <p]ᴴ`, then is solved
/// against its own diagonal block by [`solve_narrow`]. Supernodes here are mostly narrow (at
/// cheburashka's size 96% are at most 16 columns wide, over ~20 rows on average), where
/// faer's solve (handed the row-major view `Xᵀ`) spent its time in a scalar base case.
#[cfg(target_arch = "x86_64")]
fn solve_right_lower_adjoint<T: Scalar>(
    instructions: private_gemm_x86::InstrSet,
    block: &mut [T],
    nrows: usize,
    width: usize,
    narrow: &mut NarrowScratch,
) {
    let rows = nrows - width;
    if rows == 0 || width == 0 {
        return;
    }
    for first in (0..width).step_by(NARROW) {
        let panel = NARROW.min(width - first);
        let (done, rest) = block.split_at_mut(first * nrows);
        if first > 0 {
            // X[:, panel] −= X[:, ..first] L[first..first + panel, ..first]ᴴ
            panel_product(
                instructions,
                &mut rest[width..],
                done,
                nrows,
                width,
                rows,
                first,
                panel,
                1,
            );
        }
        // SAFETY: `SupernodalLlt::new` only builds this kernel on CPUs with AVX2 and FMA.
        unsafe { solve_narrow(rest, nrows, first, panel, width, false, narrow) };
    }
}

/// Width of the panels of the off-diagonal solve: each is a substitution on register tiles
/// ([`solve_narrow`]).
const NARROW: usize = 32;

/// Rows of the off-diagonal block solved together by [`solve_narrow`].
const TILE_ROWS: usize = 16;

/// Scratch of [`solve_narrow`], kept across supernodes and steps: conj(L[j, k]) split in
/// real and imaginary rows, 1 / L[j, j], and one tile of `X` in split form.
struct NarrowScratch {
    c_re: Vec<[f64; NARROW]>,
    c_im: Vec<[f64; NARROW]>,
    inverse: [f64; NARROW],
    t_re: Vec<[f64; TILE_ROWS]>,
    t_im: Vec<[f64; TILE_ROWS]>,
}

impl NarrowScratch {
    fn new() -> Self {
        NarrowScratch {
            c_re: vec![[0.0; NARROW]; NARROW],
            c_im: vec![[0.0; NARROW]; NARROW],
            inverse: [0.0; NARROW],
            t_re: vec![[0.0; TILE_ROWS]; NARROW],
            t_im: vec![[0.0; TILE_ROWS]; NARROW],
        }
    }
}

/// `X ← X L⁻ᴴ` for `L` at most [`NARROW`] wide, by substitution. `columns` holds `width`
/// (and possibly more) columns of height `nrows` (column-major); `L` is their rows
/// `diagonal..diagonal + width`, `X` their rows `below..nrows`. The substitution is
/// `X[:, j] = (X[:, j] − Σ_{k<j} X[:, k] conj(L[j, k])) / L[j, j]`, on tiles of [`TILE_ROWS`] rows held in split real/imaginary form: every operation is then a plain
/// vertical multiply-add the compiler vectorizes (compiled for AVX2 and FMA, which every
/// caller has checked), and `X` is read and written once. `quaternionic`: each odd column
/// is the copy of the even one before it ([`quaternion_partner`]); tiles start on even rows,
/// whose parity is their global rows'.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn solve_narrow<T: Scalar>(
    block: &mut [T],
    nrows: usize,
    diagonal: usize,
    width: usize,
    below: usize,
    quaternionic: bool,
    scratch: &mut NarrowScratch,
) {
    assert!(width <= NARROW && diagonal + width <= below && below <= nrows);
    assert!(
        !quaternionic
            || (width.is_multiple_of(2) && below.is_multiple_of(2) && nrows.is_multiple_of(2))
    );
    assert!(width == 0 || block.len() >= (width - 1) * nrows + nrows);
    let rows = nrows - below;
    let NarrowScratch {
        c_re,
        c_im,
        inverse,
        t_re,
        t_im,
    } = scratch;
    // Quaternionic: only the even columns are solved (the odd ones are copied), so only
    // their rows of L and their entries of X are read.
    let solved = if quaternionic { 2 } else { 1 };
    for j in (0..width).step_by(solved) {
        for k in 0..j {
            let v = block[k * nrows + diagonal + j];
            c_re[j][k] = v.re();
            c_im[j][k] = -v.im();
        }
        inverse[j] = 1.0 / block[j * nrows + diagonal + j].diagonal();
    }
    for first in (0..rows).step_by(TILE_ROWS) {
        let count = TILE_ROWS.min(rows - first);
        for j in (0..width).step_by(solved) {
            let column = &block[j * nrows + below + first..][..count];
            for (i, v) in column.iter().enumerate() {
                t_re[j][i] = v.re();
                t_im[j][i] = v.im();
            }
        }
        // Lanes past `count` hold an earlier tile's (finite) values: computed, never stored.
        for j in 0..width {
            if quaternionic && j % 2 == 1 {
                // Row pair (2u, 2u + 1) of the even column holds (a, −b̄): the odd column
                // holds (b, ā).
                for i in (0..TILE_ROWS).step_by(2) {
                    t_re[j][i] = -t_re[j - 1][i + 1];
                    t_im[j][i] = t_im[j - 1][i + 1];
                    t_re[j][i + 1] = t_re[j - 1][i];
                    t_im[j][i + 1] = -t_im[j - 1][i];
                }
                continue;
            }
            let (mut x_re, mut x_im) = (t_re[j], t_im[j]);
            for k in 0..j {
                let (cr, ci) = (c_re[j][k], c_im[j][k]);
                let (s_re, s_im) = (&t_re[k], &t_im[k]);
                for i in 0..TILE_ROWS {
                    // Fused multiply-adds (the caller enables FMA): x −= s·c.
                    if T::COMPLEX {
                        x_re[i] = (-s_re[i]).mul_add(cr, s_im[i].mul_add(ci, x_re[i]));
                        x_im[i] = (-s_re[i]).mul_add(ci, (-s_im[i]).mul_add(cr, x_im[i]));
                    } else {
                        x_re[i] = (-s_re[i]).mul_add(cr, x_re[i]);
                    }
                }
            }
            for i in 0..TILE_ROWS {
                x_re[i] *= inverse[j];
                x_im[i] *= inverse[j];
            }
            t_re[j] = x_re;
            t_im[j] = x_im;
        }
        for j in 0..width {
            let column = &mut block[j * nrows + below + first..][..count];
            for (i, v) in column.iter_mut().enumerate() {
                *v = T::from_parts(t_re[j][i], t_im[j][i]);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::linalg::solver::tests::{assert_solves_hermitian_system, hermitian_block_values};
    use crate::linalg::solver::{BlockPattern, Cholesky};
    use crate::mesh::generate::icosphere;
    use faer::linalg::matmul::matmul;
    use faer::{Accum, Mat};

    /// A deterministic, well-conditioned lower triangular matrix.
    fn lower<T: Scalar>(width: usize, entry: impl Fn(usize, usize) -> T) -> Mat<T> {
        Mat::from_fn(width, width, |i, j| {
            if i == j {
                T::from_parts(2.0 + (i % 3) as f64, 0.0)
            } else if i > j {
                entry(i, j)
            } else {
                T::zero_impl()
            }
        })
    }

    /// `solve_right_lower_adjoint` leaves `X` with `X Lᴴ` equal to the old `X`, for widths
    /// inside one panel, at a panel edge and over several panels (where the earlier panels
    /// enter through the matrix product), with and without rows below.
    #[cfg(target_arch = "x86_64")]
    fn right_solve_inverts_the_product<T: Scalar>(entry: impl Fn(usize, usize) -> T + Copy) {
        // Only CPUs with the instructions ever run this solve (see `SupernodalLlt::new`).
        let Some(instructions) = gemm_instructions() else {
            return;
        };
        let mut narrow = NarrowScratch::new();
        for width in [1, 3, 16, NARROW, NARROW + 1, 2 * NARROW + 7] {
            for rows in [0, 1, 7, 16, 41] {
                let nrows = width + rows;
                let l = lower(width, entry);
                let x = Mat::from_fn(rows, width, |i, j| entry(i + 3 * j + 1, j));
                let mut block = vec![T::zero_impl(); nrows * width];
                for j in 0..width {
                    for i in 0..width {
                        block[j * nrows + i] = l[(i, j)];
                    }
                    for i in 0..rows {
                        block[j * nrows + width + i] = x[(i, j)];
                    }
                }
                solve_right_lower_adjoint(instructions, &mut block, nrows, width, &mut narrow);
                let solved = Mat::from_fn(rows, width, |i, j| block[j * nrows + width + i]);
                let mut product = Mat::zeros(rows, width);
                matmul(
                    product.as_mut(),
                    Accum::Replace,
                    solved.as_ref(),
                    l.adjoint(),
                    T::one_impl(),
                    Par::Seq,
                );
                for j in 0..width {
                    for i in 0..width {
                        assert!(block[j * nrows + i] == l[(i, j)], "L was changed");
                    }
                    for i in 0..rows {
                        let error = (product[(i, j)] - x[(i, j)]).modulus();
                        assert!(
                            error < 1e-12,
                            "width {width}, rows {rows}: ({i}, {j}) off by {error:e}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    #[cfg(target_arch = "x86_64")]
    fn right_solve_inverts_the_product_real_and_complex() {
        right_solve_inverts_the_product(|i, j| 0.3 * ((i * 7 + j * 3) as f64).sin());
        right_solve_inverts_the_product(|i, j| {
            c64::new(
                0.3 * ((i * 7 + j * 3) as f64).sin(),
                0.2 * ((i + 5 * j) as f64).cos(),
            )
        });
    }

    /// A Hermitian positive definite system on the 2×2-block pattern of an icosphere's
    /// vertex graph (the solver tests' matrix): its size, pattern and values.
    fn hermitian_system(subdivisions: usize) -> (usize, BlockPattern, Vec<c64>) {
        let mesh = icosphere(subdivisions);
        let n = mesh.vertex_count();
        let pattern = BlockPattern::new(n, &mesh.triangles, 2);
        let values = hermitian_block_values(&pattern, &mesh.triangles);
        (n, pattern, values)
    }

    /// On a mesh big enough for separators wider than one panel, the system is solved through
    /// our factor (with faer's supernodal solve) to the solver tests' residual.
    #[test]
    fn factor_of_a_large_hermitian_block_matrix_solves_it() {
        assert_solves_hermitian_system(4, |chol| {
            // Ours wherever the CPU has the instructions (this VM and CI do); faer's elsewhere.
            assert_eq!(chol.uses_own_kernel(), kernel_available());
            assert!(
                chol.widest_supernode() > NARROW,
                "no multi-panel supernode to test"
            );
        });
    }

    /// The factor is bitwise the same on two threads as on one: only independent subtrees
    /// run concurrently, each supernode in the same order. Nested dissection (postordered)
    /// gives the threads separate subtrees; the test checks that they were used.
    #[test]
    fn quaternionic_factor_of_the_dirac_matrix_matches_the_full_factor() {
        use crate::linalg::ordering::Ordering;
        // X(ρ) of Appendix G with a potential and a diagonal shift that keep it definite.
        let (mesh, pattern, values) = crate::flow::dirac::tests::assembled_dirac(4, 0.3, 2.0);
        let n = mesh.vertex_count();
        for ordering in [Ordering::NestedDissection, Ordering::Amd] {
            let mut full = Cholesky::<c64>::analyze_with(&pattern, 1, ordering).expect("analyze");
            let mut quaternionic =
                Cholesky::<c64>::analyze_with(&pattern, 1, ordering).expect("analyze");
            assert_eq!(quaternionic.set_quaternionic(), kernel_available());
            full.factorize(&pattern, &values).expect("factorize");
            quaternionic
                .factorize(&pattern, &values)
                .expect("factorize");
            // And it solves X: x from X x = b, against the x that made b.
            let x: Vec<c64> = (0..2 * n)
                .map(|i| c64::new((i as f64).sin(), (0.3 * i as f64).cos()))
                .collect();
            let mut b = vec![c64::new(0.0, 0.0); 2 * n];
            crate::flow::dirac::sparse_matvec(&pattern, &values, &x, &mut b);
            let mut by_full = b.clone();
            quaternionic.solve_in_place(&mut b, 1);
            full.solve_in_place(&mut by_full, 1);
            let error = x
                .iter()
                .zip(&b)
                .fold(0.0f64, |m, (a, b)| m.max((a - b).norm()));
            assert!(error < 1e-9, "{ordering:?}: solve error {error:e}");
            // The same factor up to rounding: the two solves agree far below that error.
            let apart = by_full
                .iter()
                .zip(&b)
                .fold(0.0f64, |m, (a, b)| m.max((a - b).norm()));
            assert!(apart < 1e-12, "{ordering:?}: solves differ by {apart:e}");

            // In single precision (the preconditioner of `Mixed`): the same up to its rounding.
            let single: Vec<c32> = values
                .iter()
                .map(|z| c32::new(z.re as f32, z.im as f32))
                .collect();
            let mut full = Cholesky::<c32>::analyze_with(&pattern, 1, ordering).expect("analyze");
            let mut quaternionic =
                Cholesky::<c32>::analyze_with(&pattern, 1, ordering).expect("analyze");
            assert_eq!(quaternionic.set_quaternionic(), kernel_available());
            full.factorize(&pattern, &single).expect("factorize");
            quaternionic
                .factorize(&pattern, &single)
                .expect("factorize");
            let rhs: Vec<c32> = x
                .iter()
                .map(|z| c32::new(z.re as f32, z.im as f32))
                .collect();
            let (mut a, mut b) = (rhs.clone(), rhs);
            full.solve_in_place(&mut a, 1);
            quaternionic.solve_in_place(&mut b, 1);
            let scale = a.iter().fold(0.0f32, |m, z| m.max(z.norm()));
            let apart = a
                .iter()
                .zip(&b)
                .fold(0.0f32, |m, (a, b)| m.max((a - b).norm()));
            assert!(
                apart < 1e-5 * scale,
                "{ordering:?}: single: {apart:e} of {scale:e}"
            );
        }
    }

    #[test]
    fn set_quaternionic_needs_vertex_pairs() {
        // Scalar columns (an odd dimension among them) cannot be paired.
        let mesh = icosphere(2);
        let pattern = BlockPattern::new(mesh.vertex_count(), &mesh.triangles, 1);
        let mut scalar = Cholesky::<c64>::analyze(&pattern, 1).expect("analyze");
        assert!(!scalar.set_quaternionic());
    }

    #[test]
    fn a_matrix_without_quaternion_blocks_fails_the_debug_check() {
        // hermitian_block_values' 2×2 blocks are Hermitian but not of the form [[a, b], [−b̄, ā]].
        let (_, pattern, values) = hermitian_system(3);
        let mut chol = Cholesky::<c64>::analyze(&pattern, 1).expect("analyze");
        if !chol.set_quaternionic() || !cfg!(debug_assertions) {
            return;
        }
        let refused = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            chol.factorize(&pattern, &values)
        }));
        assert!(refused.is_err(), "a non-quaternionic matrix was factored");
    }

    #[test]
    fn threads_give_the_same_factor_bit_for_bit() {
        use crate::linalg::ordering::Ordering;
        let (_, pattern, values) = hermitian_system(5);
        for ordering in [Ordering::NestedDissection, Ordering::Amd] {
            let mut one = Cholesky::<c64>::analyze_with(&pattern, 1, ordering).expect("analyze");
            let mut two = Cholesky::<c64>::analyze_with(&pattern, 1, ordering).expect("analyze");
            two.set_threads(2);
            one.factorize(&pattern, &values).expect("factorize");
            two.factorize(&pattern, &values).expect("factorize");
            assert!(one.factor_values() == two.factor_values(), "{ordering:?}");
            if ordering == Ordering::NestedDissection && kernel_available() {
                assert!(two.last_parallel_pieces() > 1, "no subtree ran on a thread");
            }
        }
    }

    /// A quaternion Hermitian positive definite matrix of `pairs` vertex pairs in complex form,
    /// `C Cᴴ + 2·pairs·I` for a deterministic quaternion matrix `C` (products of complex forms
    /// are complex forms).
    fn quaternionic_spd(pairs: usize) -> Mat<c64> {
        use crate::geometry::Quaternion;
        let w = 2 * pairs;
        let mut c = Mat::<c64>::zeros(w, w);
        for u in 0..pairs {
            for v in 0..pairs {
                let t = (7 * u + 3 * v) as f64;
                let block = Quaternion::new(
                    t.sin(),
                    (0.7 * t).cos(),
                    (1.3 * t).sin(),
                    0.4 - 0.1 * t.cos(),
                )
                .to_complex();
                for (r, row) in block.iter().enumerate() {
                    for (k, z) in row.iter().enumerate() {
                        c[(2 * u + r, 2 * v + k)] = *z;
                    }
                }
            }
        }
        let mut a = Mat::<c64>::zeros(w, w);
        matmul(
            a.as_mut(),
            Accum::Replace,
            c.as_ref(),
            c.adjoint(),
            c64::new(1.0, 0.0),
            Par::Seq,
        );
        for i in 0..w {
            a[(i, i)] += c64::new(w as f64, 0.0);
        }
        a
    }

    #[test]
    fn quaternionic_diagonal_block_matches_the_dense_cholesky() {
        let pairs = 5;
        let w = 2 * pairs;
        let a = quaternionic_spd(pairs);
        // The block sits at rows 4.. of columns with 16 rows, as a panel of a supernode.
        let (nrows, diagonal) = (w + 6, 4);
        // Odd columns hold NaN: the kernel must read only the even columns of A.
        let mut block = vec![c64::new(f64::NAN, f64::NAN); nrows * w];
        for j in (0..w).step_by(2) {
            for i in j..w {
                block[diagonal + i + j * nrows] = a[(i, j)];
            }
        }
        quaternionic_diagonal_cholesky(&mut block, nrows, diagonal, w).expect("definite");

        let mut dense = a.clone();
        let mut mem = MemBuffer::new(cholesky_in_place_scratch::<c64>(
            w,
            Par::Seq,
            Default::default(),
        ));
        cholesky_in_place(
            dense.as_mut(),
            Default::default(),
            Par::Seq,
            MemStack::new(&mut mem),
            Default::default(),
        )
        .expect("definite");
        for j in 0..w {
            for i in j..w {
                let got = block[diagonal + i + j * nrows];
                if j % 2 == 0 && i == j + 1 {
                    // The quaternionic factor's zero, computed as rounding.
                    assert!(got.norm() < 1e-13, "({i}, {j}): {got}");
                    continue;
                }
                let want = dense[(i, j)];
                assert!(
                    (got - want).norm() < 1e-12 * (1.0 + want.norm()),
                    "({i}, {j}): {got} vs {want}"
                );
            }
        }
        // Rows outside the block are not touched.
        assert!(block[..diagonal].iter().all(|z| z.re.is_nan()));
    }

    #[test]
    fn quaternionic_diagonal_block_reports_its_pivot() {
        let pairs = 5;
        let mut a = quaternionic_spd(pairs);
        // Vertex 3's diagonal block made negative: the leading six columns stay definite.
        for i in [6, 7] {
            a[(i, i)] -= c64::new(1e3, 0.0);
        }
        let w = 2 * pairs;
        let mut block = vec![c64::new(0.0, 0.0); w * w];
        for j in 0..w {
            for i in j..w {
                block[i + j * w] = a[(i, j)];
            }
        }
        assert_eq!(quaternionic_diagonal_cholesky(&mut block, w, 0, w), Err(6));
        // A NaN on the diagonal is not a positive pivot either.
        let mut block = vec![c64::new(0.0, 0.0); 4];
        block[0] = c64::new(f64::NAN, 0.0);
        assert_eq!(quaternionic_diagonal_cholesky(&mut block, 2, 0, 2), Err(0));
    }

    /// An indefinite matrix is refused with the column of the failed pivot, not factored.
    #[test]
    fn indefinite_matrix_reports_its_pivot() {
        let (n, pattern, mut values) = hermitian_system(4);
        let slot = pattern.diagonal_slot(n / 2);
        values[pattern.entry(slot, n / 2, 1, 1)] = c64::new(-1000.0, 0.0);
        let mut chol = Cholesky::<c64>::analyze(&pattern, 1).expect("analyze");
        assert_eq!(chol.uses_own_kernel(), kernel_available());
        let error = chol.factorize(&pattern, &values).expect_err("indefinite");
        assert!(
            format!("{error}").contains("non-positive pivot at column"),
            "{error}"
        );
    }
}
