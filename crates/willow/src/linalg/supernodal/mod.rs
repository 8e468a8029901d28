//! Numeric supernodal `LLᴴ` on faer's symbolic structure, with a vectorized off-diagonal solve.
//!
//! faer 0.24's `factorize_supernodal_numeric_llt` finishes every supernode with
//! `L₂₁ ← A₂₁ L₁₁⁻ᴴ`, which it hands to its triangular solver as the row-major view `L₂₁ᵀ`;
//! that view runs the solver's scalar base case. This kernel runs faer's algorithm loop for
//! loop, on faer's symbolic factorization and into faer's storage (so faer's supernodal solve
//! reads the result), and differs in two places:
//! - the off-diagonal block is solved from the right on its own column-major storage
//!   (`solve_right_lower_adjoint`: panels of at most `NARROW` columns, each a register-tile
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
//!
//! Since then (issue 14) three things differ from the description above:
//! - **The quaternionic path** (`quaternionic.rs`, [`SupernodalLlt::set_quaternionic`] through
//!   `Cholesky::set_quaternionic`): X is quaternion Hermitian, so each odd column of its
//!   complex factor is the quaternion partner of the even one before it. The kernel updates,
//!   factors and solves the even columns only (half the multiply-adds), factors each diagonal
//!   block by panels with a small quaternionic Cholesky of its own instead of faer's dense one,
//!   and runs the descendant updates of a few vertex pairs as products of quaternion lanes
//!   rather than packed gemm calls.
//! - **Threads** (`parallel.rs`): independent subtrees of the elimination tree are factored
//!   on their own threads (Geist and Ng's subtree mapping), bitwise the same for any count.
//! - **Memory**: the factor comes zeroed from the allocator and is committed by the first
//!   factorization; the permuted triangle's pattern is released once the positions are known.
//!
//! The dense kernels (faer's gemm behind a strided view, the narrow off-diagonal
//! solve) are in `kernels.rs`; figures are in `docs/performance.md`.

use std::ops::{AddAssign, Sub};

use faer::dyn_stack::MemBuffer;
use faer::linalg::cholesky::llt::factor::cholesky_in_place_scratch;
use faer::sparse::linalg::cholesky::supernodal::SymbolicSupernodalCholesky;
use faer::sparse::SymbolicSparseColMatRef;
use faer::traits::ComplexField;
use faer::{c32, c64, Par};

mod parallel;
use parallel::*;
mod solve;
use solve::SolvePlan;
pub use solve::SolveScratch;
mod quaternionic;
use quaternionic::*;
mod kernels;
use kernels::*;
#[cfg(test)]
mod tests;

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
pub trait Scalar: ComplexField + Copy + AddAssign + Sub<Output = Self> + sealed::ZeroBits {
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
    /// How a quaternionic solve splits over threads ([`SupernodalLlt::plan_solves`]); `None`:
    /// on the calling thread.
    solve_plan: Option<SolvePlan>,
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
    first: &'a [usize],
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
            solve_plan: None,
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
    /// boundary and its rows come in vertex pairs (what `BlockPattern::expand_order` and
    /// faer's fundamental supernodes give); otherwise nothing changes.
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
            first: &self.first,
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
        let (pieces, top) = subtree_mapping(
            |r| self.subtree_cost[r],
            &self.child_ptr,
            &self.children,
            &self.roots,
            threads,
        );
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
