//! The quaternionic solve `x ← (L Lᴴ)⁻¹ x`, on the calling thread or split over independent
//! subtrees of the elimination tree.
//!
//! The split is the factorization's (Geist and Ng's mapping, `parallel.rs`), balanced on the
//! factor values each subtree's sweep reads. A subtree's forward sweep writes its own rows and
//! subtracts from rows of its ancestors only, all of them in the sequential top; so each
//! thread but the caller's works on a copy of the right-hand side whose top rows start at
//! zero, and what it took off them is added to the caller's afterwards. The backward sweep
//! runs the top first, then each subtree reads the top's finished rows and writes its own.
//! The split is planned from the factor alone, never from the thread count: on one thread
//! the parts run one after the other on the same copies, so the result is bitwise the same
//! for any count (as the factorization's is); it equals the unsplit solve's up to rounding
//! (the top rows' sums are added in another order).

use super::*;
use std::ops::Range;

/// Below this many factor values a solve is not split: spawning a thread costs tens of
/// microseconds, a sweep over this many values about a millisecond.
const PARALLEL_SOLVE_MIN_VALUES: usize = 1 << 20;

/// The parts a split solve has, whatever the threads: this machine class has two cores,
/// and a fixed count keeps the result independent of the threads given.
const SOLVE_PARTS: usize = 2;

/// Where a solve's threads work ([`SupernodalLlt::plan_solves`]).
pub(super) struct SolvePlan {
    /// Per part (the caller's buffer's first), the supernode ranges of its subtrees.
    pieces: Vec<Vec<Range<usize>>>,
    /// Per part, the rows its subtrees own.
    own_rows: Vec<Vec<Range<usize>>>,
    /// The supernodes above the subtrees, ascending, and their rows, merged.
    top: Vec<usize>,
    top_rows: Vec<Range<usize>>,
    /// Whether the parts run on threads of their own (else one after the other).
    concurrent: bool,
}

/// The scratch of [`SupernodalLlt::solve_quaternionic`]: one column of vertex-pair lanes per
/// thread, and a right-hand side per thread besides the caller's. Made by
/// [`SupernodalLlt::solve_scratch`] once, reused by every solve.
pub struct SolveScratch<T> {
    lanes: Vec<Vec<[f64; 4]>>,
    copies: Vec<Vec<T>>,
}

impl<T> Default for SolveScratch<T> {
    fn default() -> Self {
        SolveScratch {
            lanes: Vec::new(),
            copies: Vec::new(),
        }
    }
}

/// `ranges` merged where one ends as the next begins (they come ascending).
fn merged(ranges: impl Iterator<Item = Range<usize>>) -> Vec<Range<usize>> {
    let mut out: Vec<Range<usize>> = Vec::new();
    for r in ranges.filter(|r| !r.is_empty()) {
        match out.last_mut() {
            Some(last) if last.end == r.start => last.end = r.end,
            _ => out.push(r),
        }
    }
    out
}

impl SupernodalLlt {
    /// Plans how [`SupernodalLlt::solve_quaternionic`] splits: into parts of subtrees as the
    /// factorization's mapping gives them, balanced on factor values, run concurrently when
    /// `threads` allows. A factor too small to be worth it, or a structure that is not
    /// postordered or not quaternionic: no split. Make the scratch afterwards.
    pub fn plan_solves(&mut self, symbolic: &SymbolicSupernodalCholesky<usize>, threads: usize) {
        self.plan_solves_above(symbolic, threads, PARALLEL_SOLVE_MIN_VALUES);
    }

    /// [`SupernodalLlt::plan_solves`] for factors of at least `min_values` values (the tests
    /// split small ones).
    pub(crate) fn plan_solves_above(
        &mut self,
        symbolic: &SymbolicSupernodalCholesky<usize>,
        threads: usize,
        min_values: usize,
    ) {
        self.solve_plan = None;
        let val_ptr = symbolic.col_ptr_for_val();
        let n_supernodes = symbolic.n_supernodes();
        if !self.postordered || !self.quaternionic || val_ptr[n_supernodes] < min_values {
            return;
        }
        let values = |r: usize| (val_ptr[r + 1] - val_ptr[self.first[r]]) as f64;
        let (mapping, top) = subtree_mapping(
            values,
            &self.child_ptr,
            &self.children,
            &self.roots,
            SOLVE_PARTS,
        );
        let begin = symbolic.supernode_begin();
        let end = symbolic.supernode_end();
        let mut pieces: Vec<Vec<Range<usize>>> = vec![Vec::new(); SOLVE_PARTS];
        for (root, thread) in mapping {
            pieces[thread].push(self.first[root]..root + 1);
        }
        if pieces.iter().filter(|p| !p.is_empty()).count() < 2 {
            return;
        }
        for p in &mut pieces {
            p.sort_unstable_by_key(|r| r.start);
        }
        let own_rows = pieces
            .iter()
            .map(|p| merged(p.iter().map(|r| begin[r.start]..end[r.end - 1])))
            .collect();
        let top_rows = merged(top.iter().map(|&s| begin[s]..end[s]));
        self.solve_plan = Some(SolvePlan {
            pieces,
            own_rows,
            top,
            top_rows,
            concurrent: threads >= 2,
        });
    }

    /// The parts a solve splits into (1: not split), and whether they run concurrently.
    pub fn solve_parts(&self) -> (usize, bool) {
        self.solve_plan
            .as_ref()
            .map_or((1, false), |p| (p.pieces.len(), p.concurrent))
    }

    /// The scratch [`SupernodalLlt::solve_quaternionic`] needs for the current plan.
    pub fn solve_scratch<T: Scalar>(
        &self,
        symbolic: &SymbolicSupernodalCholesky<usize>,
    ) -> SolveScratch<T> {
        let threads = self.solve_parts().0;
        let lanes = (self.max_pattern + self.max_width).div_ceil(2);
        SolveScratch {
            lanes: (0..threads).map(|_| vec![[0.0; 4]; lanes]).collect(),
            copies: (1..threads)
                .map(|_| vec![T::zero_impl(); symbolic.nrows()])
                .collect(),
        }
    }

    /// `x ← (L Lᴴ)⁻¹ x` for a quaternionic factor `l` (in faer's supernodal storage, of the
    /// matrix this kernel was analyzed for), one right-hand side. Below the diagonal blocks it
    /// reads the even columns only: with `(p, q) = (L[2u, 2w], L[2u + 1, 2w])` the odd column
    /// holds `(−q̄, p̄)` ([`SupernodalLlt::set_quaternionic`]). A solve streams the factor
    /// through memory twice, so half the columns is about half the time. Split as
    /// [`SupernodalLlt::plan_solves`] planned when `scratch` was made for that plan (see the
    /// module docs).
    pub fn solve_quaternionic<T: Scalar>(
        &self,
        symbolic: &SymbolicSupernodalCholesky<usize>,
        l: &[T],
        x: &mut [T],
        scratch: &mut SolveScratch<T>,
    ) {
        assert!(self.quaternionic && x.len() == symbolic.nrows());
        let lanes = (self.max_pattern + self.max_width).div_ceil(2);
        assert!(!scratch.lanes.is_empty() && scratch.lanes.iter().all(|l| l.len() >= lanes));
        let plan = self.solve_plan.as_ref().filter(|p| {
            scratch.lanes.len() >= p.pieces.len()
                && scratch.copies.len() + 1 >= p.pieces.len()
                && scratch.copies.iter().all(|c| c.len() == x.len())
        });
        let Some(plan) = plan else {
            let all = 0..symbolic.n_supernodes();
            self.forward_sweep(symbolic, l, x, &mut scratch.lanes[0], all.clone());
            self.backward_sweep(symbolic, l, x, &mut scratch.lanes[0], all);
            return;
        };
        let threads = plan.pieces.len();
        let copies = &mut scratch.copies[..threads - 1];
        // L y = b. The other threads' copies: their own rows of b, zero on the top's.
        for (c, own) in copies.iter_mut().zip(&plan.own_rows[1..]) {
            for r in own {
                c[r.clone()].copy_from_slice(&x[r.clone()]);
            }
            for r in &plan.top_rows {
                c[r.clone()].fill(T::zero_impl());
            }
        }
        self.sweep_pieces(symbolic, l, x, copies, &mut scratch.lanes, plan, true);
        for (c, own) in copies.iter().zip(&plan.own_rows[1..]) {
            for r in own {
                x[r.clone()].copy_from_slice(&c[r.clone()]);
            }
            for r in &plan.top_rows {
                for (x, &c) in x[r.clone()].iter_mut().zip(&c[r.clone()]) {
                    *x += c;
                }
            }
        }
        for &s in &plan.top {
            self.forward_sweep(symbolic, l, x, &mut scratch.lanes[0], s..s + 1);
        }
        // Lᴴ x = y: the top, then each subtree from its own rows and the top's.
        for &s in plan.top.iter().rev() {
            self.backward_sweep(symbolic, l, x, &mut scratch.lanes[0], s..s + 1);
        }
        for (c, own) in copies.iter_mut().zip(&plan.own_rows[1..]) {
            for r in own.iter().chain(&plan.top_rows) {
                c[r.clone()].copy_from_slice(&x[r.clone()]);
            }
        }
        self.sweep_pieces(symbolic, l, x, copies, &mut scratch.lanes, plan, false);
        for (c, own) in copies.iter().zip(&plan.own_rows[1..]) {
            for r in own {
                x[r.clone()].copy_from_slice(&c[r.clone()]);
            }
        }
    }

    /// One sweep (`forward`, or backward) over every part's subtrees: the first's on `x`, the
    /// others' on their copies, concurrently if the plan says so (the same arithmetic either
    /// way).
    #[allow(clippy::too_many_arguments)]
    fn sweep_pieces<T: Scalar>(
        &self,
        symbolic: &SymbolicSupernodalCholesky<usize>,
        l: &[T],
        x: &mut [T],
        copies: &mut [Vec<T>],
        lanes: &mut [Vec<[f64; 4]>],
        plan: &SolvePlan,
        forward: bool,
    ) {
        let sweep = |x: &mut [T], lanes: &mut [[f64; 4]], pieces: &[Range<usize>]| {
            for r in pieces {
                if forward {
                    self.forward_sweep(symbolic, l, x, lanes, r.clone());
                } else {
                    self.backward_sweep(symbolic, l, x, lanes, r.clone());
                }
            }
        };
        let sweep = &sweep;
        let (own_lanes, other_lanes) = lanes.split_at_mut(1);
        if !plan.concurrent {
            sweep(x, &mut own_lanes[0], &plan.pieces[0]);
            for ((c, lanes), pieces) in copies.iter_mut().zip(other_lanes).zip(&plan.pieces[1..]) {
                sweep(c, lanes, pieces);
            }
            return;
        }
        // A panic on a thread is this call's panic (the scope re-raises it).
        std::thread::scope(|scope| {
            for ((c, lanes), pieces) in copies.iter_mut().zip(other_lanes).zip(&plan.pieces[1..]) {
                scope.spawn(move || sweep(c, lanes, pieces));
            }
            sweep(x, &mut own_lanes[0], &plan.pieces[0]);
        });
    }

    /// Supernode `s` of the factor `l` as both sweeps read it.
    #[inline(always)]
    fn panel<'a, T>(
        &'a self,
        symbolic: &SymbolicSupernodalCholesky<usize>,
        l: &'a [T],
        s: usize,
    ) -> Panel<'a, T> {
        let (start, end) = (symbolic.supernode_begin()[s], symbolic.supernode_end()[s]);
        let row_ptr = symbolic.col_ptr_for_row_idx();
        let val_ptr = symbolic.col_ptr_for_val();
        let width = end - start;
        Panel {
            start,
            width,
            nrows: width + (row_ptr[s + 1] - row_ptr[s]),
            block: &l[val_ptr[s]..val_ptr[s + 1]],
            pairs: &self.pair_rows[row_ptr[s] / 2..row_ptr[s + 1] / 2],
        }
    }

    /// `L y = b` over the supernodes `range`, ascending: each vertex pair of a supernode is
    /// divided by its real diagonal, then its even column (and with it the odd one) is taken
    /// off the rows below, in the supernode and under it. The diagonal blocks' (2w + 1, 2w)
    /// entries are the zeros of the quaternionic factor (rounding in the computed one) and
    /// are not read.
    fn forward_sweep<T: Scalar>(
        &self,
        symbolic: &SymbolicSupernodalCholesky<usize>,
        l: &[T],
        x: &mut [T],
        scratch: &mut [[f64; 4]],
        range: Range<usize>,
    ) {
        let n_supernodes = symbolic.n_supernodes();
        for s in range {
            let Panel {
                start,
                width,
                nrows,
                block,
                pairs,
            } = self.panel(symbolic, l, s);
            let ahead = s + SOLVE_PREFETCH_AHEAD;
            if ahead < n_supernodes {
                let next = self.panel(symbolic, l, ahead);
                prefetch_even_columns(next.block, next.width);
            }
            if s + 1 < n_supernodes {
                prefetch_pairs(x, self.panel(symbolic, l, s + 1).pairs);
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
    }

    /// `Lᴴ x = y` over the supernodes `range`, descending: each pair takes the adjoint
    /// products of its even column with the rows below, then is divided by its diagonal.
    fn backward_sweep<T: Scalar>(
        &self,
        symbolic: &SymbolicSupernodalCholesky<usize>,
        l: &[T],
        x: &mut [T],
        scratch: &mut [[f64; 4]],
        range: Range<usize>,
    ) {
        for s in range.rev() {
            let Panel {
                start,
                width,
                nrows,
                block,
                pairs,
            } = self.panel(symbolic, l, s);
            if let Some(ahead) = s.checked_sub(SOLVE_PREFETCH_AHEAD) {
                let next = self.panel(symbolic, l, ahead);
                prefetch_even_columns(next.block, next.width);
            }
            if s > 0 {
                prefetch_pairs(x, self.panel(symbolic, l, s - 1).pairs);
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
}

/// One supernode in the factor: its first column and width, the rows of its panel (its own
/// columns and those below), its values (column-major, `nrows` a column) and the vertex pairs
/// of the rows below it.
struct Panel<'a, T> {
    start: usize,
    width: usize,
    nrows: usize,
    block: &'a [T],
    pairs: &'a [u32],
}
