//! The quaternionic path for X (the Dirac matrix's complex form): only even columns are factored and solved, the odd ones are their quaternion partners; small descendant updates run as products of quaternion lanes.

use super::*;

/// The entry of odd column `2w + 1` at row `i` of a quaternionic supernode block, from the even
/// column `2w` (`even`): `[[a, b], [−b̄, ā]]` puts `b = −conj(L[2u + 1, 2w])` at row `2u`
/// and `ā = conj(L[2u, 2w])` at row `2u + 1`. Local rows have their global rows' parity
/// (supernodes start on even columns, their row lists come in pairs).
pub(super) fn quaternion_partner<T: Scalar>(even: &[T], i: usize) -> T {
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
pub(super) fn factor_quaternionic_supernode<T: Scalar>(
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
pub(super) fn quaternionic_diagonal_cholesky<T: Scalar>(
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
pub(super) fn panel_product<T: Scalar>(
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
pub(super) fn copy_odd_columns_from<T: Scalar>(
    even: &[T],
    odd: &mut [T],
    start: usize,
    end: usize,
) {
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
pub(super) fn odd_columns_are_copies<T: Scalar>(block: &[T], nrows: usize, ncols: usize) -> bool {
    (1..ncols).step_by(2).all(|c| {
        let even = &block[(c - 1) * nrows..c * nrows];
        (c..nrows).all(|i| block[c * nrows + i] == quaternion_partner(even, i))
    })
}

/// How many supernodes ahead the quaternionic solve prefetches the factor's columns: a
/// supernode's work is shorter than a memory round trip (nefertiti's X: 17.0–17.4 ms a solve at
/// 2, 17.4–17.7 at 1, 17.4–17.9 at 3, same process and matrix).
pub(super) const SOLVE_PREFETCH_AHEAD: usize = 2;

/// Asks the CPU to bring the even columns of a supernode's `block` (`width` columns) into
/// cache before a quaternionic solve reads them: the solves visit the factor in runs of a few
/// cache lines, one run a column, too short for the hardware prefetcher to follow.
#[inline(always)]
pub(super) fn prefetch_even_columns<T>(block: &[T], width: usize) {
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
pub(super) fn prefetch_pairs<T>(x: &[T], pairs: &[u32]) {
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
pub(super) fn gather_pairs<T: Scalar>(
    x: &[T],
    pairs: impl Iterator<Item = usize>,
    lanes: &mut [[f64; 4]],
) {
    for (lane, p) in lanes.iter_mut().zip(pairs) {
        *lane = pair_lanes(&x[2 * p..2 * p + 2]);
    }
}

/// The inverse of [`gather_pairs`].
#[inline(always)]
pub(super) fn scatter_pairs<T: Scalar>(
    x: &mut [T],
    pairs: impl Iterator<Item = usize>,
    lanes: &[[f64; 4]],
) {
    for (lane, p) in lanes.iter().zip(pairs) {
        let pair = &mut x[2 * p..2 * p + 2];
        pair[0] = T::from_parts(lane[0], lane[1]);
        pair[1] = T::from_parts(lane[2], lane[3]);
    }
}

/// `(L[2u, 2w], L[2u + 1, 2w]) = (p, q)` as four lanes `[p.re, p.im, q.re, q.im]`.
#[inline(always)]
pub(super) fn pair_lanes<T: Scalar>(pair: &[T]) -> [f64; 4] {
    [pair[0].re(), pair[0].im(), pair[1].re(), pair[1].im()]
}

/// `out[u] −= (p x₀ − q̄ x₁, q x₀ + p̄ x₁)` over the row pairs `(p, q)` of an even factor
/// column: its product, and its odd partner's, with `(x₀, x₁)` (the quaternionic forward
/// solve). Lane by lane, so that it compiles to four fused multiply-adds and three shuffles
/// per pair.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
pub(super) fn quaternion_column_product<T: Scalar>(
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
pub(super) fn product_coefficients(x0: (f64, f64), x1: (f64, f64)) -> [[f64; 4]; 4] {
    [
        [-x0.0; 4],
        [x0.1, -x0.1, x0.1, -x0.1],
        [x1.0, -x1.0, -x1.0, x1.0],
        [x1.1, x1.1, -x1.1, -x1.1],
    ]
}

/// `o −= (p x₀ − q̄ x₁, q x₀ + p̄ x₁)` for the pair lanes `v` and [`product_coefficients`].
#[inline(always)]
pub(super) fn apply_product(v: [f64; 4], c: &[[f64; 4]; 4], o: &mut [f64; 4]) {
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
pub(super) const LANE_UPDATE_MAX_MACS: usize = 4096;

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
pub(super) fn quaternion_update<T: Scalar>(
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
pub(super) fn quaternion_column_adjoint<T: Scalar>(
    column: &[T],
    t: &[[f64; 4]],
) -> ((f64, f64), (f64, f64)) {
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
