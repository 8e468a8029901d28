use super::*;
use crate::linalg::solver::tests::{assert_solves_hermitian_system, hermitian_block_values};
use crate::linalg::solver::{BlockPattern, Cholesky};
use crate::mesh::generate::icosphere;
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::{cholesky_in_place, cholesky_in_place_scratch};
use faer::linalg::matmul::matmul;
use faer::{c32, c64, Par};
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

/// A solve split over independent subtrees equals the unsplit solve up to rounding, in
/// double and single precision, and is bitwise the same on one, two and three threads (the
/// parts run one after the other, or concurrently).
#[test]
fn split_solves_match_the_sequential_solve() {
    use crate::linalg::ordering::Ordering;
    let (mesh, pattern, values) = crate::flow::dirac::tests::assembled_dirac(5, 0.3, 2.0);
    let n = mesh.vertex_count();
    let x: Vec<c64> = (0..2 * n)
        .map(|i| c64::new((i as f64).sin(), (0.3 * i as f64).cos()))
        .collect();
    let mut b = vec![c64::new(0.0, 0.0); 2 * n];
    crate::flow::dirac::sparse_matvec(&pattern, &values, &x, &mut b);
    let apart = |a: &[c64], b: &[c64]| {
        a.iter()
            .zip(b)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).norm()))
    };
    let mut one =
        Cholesky::<c64>::analyze_with(&pattern, 1, Ordering::NestedDissection).expect("analyze");
    if !one.set_quaternionic() {
        return; // no kernel on this CPU: faer's solve, nothing of ours to split
    }
    one.factorize(&pattern, &values).expect("factorize");
    let mut by_one = b.clone();
    one.solve_in_place(&mut by_one, 1);
    assert!(apart(&by_one, &x) < 1e-9);
    let single: Vec<c32> = values
        .iter()
        .map(|z| c32::new(z.re as f32, z.im as f32))
        .collect();
    let b32: Vec<c32> = b
        .iter()
        .map(|z| c32::new(z.re as f32, z.im as f32))
        .collect();
    let mut one32 =
        Cholesky::<c32>::analyze_with(&pattern, 1, Ordering::NestedDissection).expect("analyze");
    assert!(one32.set_quaternionic());
    one32.factorize(&pattern, &single).expect("factorize");
    let mut by_one32 = b32.clone();
    one32.solve_in_place(&mut by_one32, 1);
    let mut first_split: Option<(Vec<c64>, Vec<c32>)> = None;
    for threads in [1, 2, 3] {
        let mut split = Cholesky::<c64>::analyze_with(&pattern, 1, Ordering::NestedDissection)
            .expect("analyze");
        assert!(split.set_quaternionic());
        assert_eq!(split.split_solves_of_any_size(threads), (2, threads > 1));
        split.factorize(&pattern, &values).expect("factorize");
        let mut by_split = b.clone();
        split.solve_in_place(&mut by_split, 1);
        let d = apart(&by_split, &by_one);
        assert!(
            d < 1e-12,
            "{threads} threads: {d:e} from one thread's solve"
        );
        // Twice: the scratch is reused, and the result is the same bit for bit.
        let mut again = b.clone();
        split.solve_in_place(&mut again, 1);
        assert!(
            again == by_split,
            "{threads} threads: a second solve differs"
        );

        let mut split32 = Cholesky::<c32>::analyze_with(&pattern, 1, Ordering::NestedDissection)
            .expect("analyze");
        assert!(split32.set_quaternionic());
        assert_eq!(split32.split_solves_of_any_size(threads), (2, threads > 1));
        split32.factorize(&pattern, &single).expect("factorize");
        let mut by_split32 = b32.clone();
        split32.solve_in_place(&mut by_split32, 1);
        let scale = by_one32.iter().fold(0.0f32, |m, z| m.max(z.norm()));
        let d = by_one32
            .iter()
            .zip(&by_split32)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).norm()));
        assert!(
            d < 1e-5 * scale,
            "{threads} threads, single: {d:e} of {scale:e}"
        );
        // The parts and their merge are the same whether they run apart or in turn.
        match &first_split {
            None => first_split = Some((by_split, by_split32)),
            Some((double, single)) => {
                assert!(*double == by_split, "{threads} threads: not bitwise one's");
                assert!(
                    *single == by_split32,
                    "{threads} threads, single: not bitwise"
                );
            }
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
