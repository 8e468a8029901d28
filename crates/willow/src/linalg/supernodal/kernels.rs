//! The dense kernels: faer's fused gather/scatter gemm behind a view type, and the vectorized off-diagonal solve `L₂₁ ← A₂₁ L₁₁⁻ᴴ` by narrow panels.

use super::*;

/// A column-major or transposed view into a slice for [`gemm`]: entry `(i, j)` is
/// `data[i * row_stride + j * col_stride]`, conjugated when `conj`.
#[cfg(target_arch = "x86_64")]
pub(super) struct View<'a, T> {
    pub(super) data: &'a [T],
    pub(super) nrows: usize,
    pub(super) ncols: usize,
    pub(super) row_stride: usize,
    pub(super) col_stride: usize,
    pub(super) conj: bool,
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
pub(super) fn gemm<T: Scalar>(
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
pub(super) fn kernel_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    return gemm_instructions().is_some();
    #[cfg(not(target_arch = "x86_64"))]
    return false;
}

#[cfg(target_arch = "x86_64")]
pub(super) fn gemm_instructions() -> Option<private_gemm_x86::InstrSet> {
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
pub(super) fn solve_right_lower_adjoint<T: Scalar>(
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
pub(super) const NARROW: usize = 32;

/// Rows of the off-diagonal block solved together by [`solve_narrow`].
pub(super) const TILE_ROWS: usize = 16;

/// Scratch of [`solve_narrow`], kept across supernodes and steps: conj(L[j, k]) split in
/// real and imaginary rows, 1 / L[j, j], and one tile of `X` in split form.
pub(super) struct NarrowScratch {
    pub(super) c_re: Vec<[f64; NARROW]>,
    pub(super) c_im: Vec<[f64; NARROW]>,
    pub(super) inverse: [f64; NARROW],
    pub(super) t_re: Vec<[f64; TILE_ROWS]>,
    pub(super) t_im: Vec<[f64; TILE_ROWS]>,
}

impl NarrowScratch {
    pub(super) fn new() -> Self {
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
pub(super) fn solve_narrow<T: Scalar>(
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
