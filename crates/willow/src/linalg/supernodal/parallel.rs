//! The factorization's jobs: Geist and Ng's subtree-to-thread mapping and the per-job loop over supernodes (descendant updates, the diagonal block, the off-diagonal solve).

use super::*;
use faer::dyn_stack::MemStack;
use faer::linalg::cholesky::llt::factor::cholesky_in_place;
use faer::{MatMut, Par};

/// A subtree's supernodes, the first factor value it owns, and those values.
pub(super) type Run<'a, T> = (std::ops::Range<usize>, usize, &'a mut [T]);

/// Geist and Ng's subtree-to-thread mapping: starting from the roots, the heaviest subtree
/// is replaced by its children (its root joins the sequential top) until the subtrees, dealt
/// longest first to the least loaded thread, keep every thread within 10% of an even share.
/// Returns each subtree's root with its thread, and the top supernodes, ascending. `cost`
/// is a subtree's work (flops for the factorization, factor values for a solve).
pub(super) fn subtree_mapping(
    cost: impl Fn(usize) -> f64,
    child_ptr: &[usize],
    children: &[usize],
    roots: &[usize],
    threads: usize,
) -> (Vec<(usize, usize)>, Vec<usize>) {
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
        let kids = &children[child_ptr[heaviest]..child_ptr[heaviest + 1]];
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
    pub(super) fn factor_range(
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
