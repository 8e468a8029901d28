//! The curve's Poisson problem (§5, Eq. 6 in one dimension): new positions whose edges best match the rotated tangents, and its residual.

use super::*;

/// The 1D Poisson system `L f̃ = b` of §5.2, factored once.
///
/// `L` is the positive semidefinite graph Laplacian with `L_ij = −1/ℓ_ij` on edges and
/// `L_ii = Σ_j 1/ℓ_ij`; `f̃` minimizes `Σ_ij |f̃_j − f̃_i − T̃_ij|² / ℓ_ij` (§5.1). Its kernel is
/// the constants, which we remove by **pinning** `f̃_0 = 0` (the mean translation is restored
/// afterwards anyway). Pinning vertex 0 of a path *or of a cycle* leaves a path on vertices
/// `1..n`, so the reduced matrix A is tridiagonal, symmetric positive definite and weakly
/// diagonally dominant: Gaussian elimination without pivoting is stable, costs O(n) once, and
/// each solve is O(n) with no fill, no ordering and no workspace. That is why this does not go
/// through faer's general sparse Cholesky, which would compute the same factor with symbolic
/// analysis, a permutation and a scratch stack per solve. Because `Σ b = 0`, the dropped row 0
/// is satisfied too; [`poisson_residual`] checks the full system.
///
/// The elimination is *twisted* (a "burn at both ends" factorization): it runs from vertex 1
/// down and from vertex n − 1 up, meeting at the middle vertex k. Each sweep of a tridiagonal
/// solve is one chain of dependent multiply-subtracts; two half-length chains, interleaved,
/// overlap in the CPU and halve the solve time. Row j < k becomes `P_j x_j + o_j x_{j+1} = z_j`,
/// row j > k becomes `Q_j x_j + o_{j−1} x_{j−1} = z_j`, and row k, with both neighbours
/// eliminated, `γ x_k = z_k`.
#[derive(Clone, Debug)]
pub struct CurvePoisson {
    /// The meeting vertex k.
    twist: usize,
    /// Forward multipliers: `o_{j−1}/P_{j−1}` for `2 ≤ j < k`, `o_j/Q_{j+1}` for `k < j ≤ n−2`.
    forward: Vec<f64>,
    /// The two multipliers of row k (0 where the neighbour is missing or pinned).
    twist_multipliers: [f64; 2],
    /// `1/P_j` (j < k), `1/γ` (j = k), `1/Q_j` (j > k); index 0 unused.
    inv_pivot: Vec<f64>,
    /// Back-substitution couplings: `o_j/P_j` for `1 ≤ j < k`, `o_{j−1}/Q_j` for `j > k`.
    backward: Vec<f64>,
}

impl CurvePoisson {
    /// Factor the pinned Laplacian of a curve with these edge lengths (all > 0), `n` vertices.
    pub fn new(edge_lengths: &[f64], closed: bool) -> Result<Self, CurveError> {
        let m = edge_lengths.len();
        let n = if closed { m } else { m + 1 };
        let mut forward = zeroed(n)?;
        let mut inv_pivot = zeroed(n)?;
        let mut backward = zeroed(n)?;
        let twist = (n / 2).max(1);
        let mut factor = CurvePoisson {
            twist,
            forward: Vec::new(),
            twist_multipliers: [0.0, 0.0],
            inv_pivot: Vec::new(),
            backward: Vec::new(),
        };
        if n < 2 {
            factor.inv_pivot = inv_pivot;
            return Ok(factor);
        }
        // Reduced diagonal a_j for vertex j ≥ 1: the edge into j always exists; the edge out
        // of j exists unless j is the last vertex of an open curve. Off-diagonal o_j = A_{j,j+1}
        // = −1/ℓ_j for 1 ≤ j ≤ n − 2 (edges touching the pinned vertex 0 drop out).
        let diagonal =
            |j: usize| 1.0 / edge_lengths[j - 1] + if j < m { 1.0 / edge_lengths[j] } else { 0.0 };
        let off = |j: usize| -1.0 / edge_lengths[j];
        let k = twist;
        let mut gamma = diagonal(k);
        if k > 1 {
            let mut pivot = diagonal(1);
            for j in 2..k {
                forward[j] = off(j - 1) / pivot;
                backward[j - 1] = off(j - 1) / pivot;
                inv_pivot[j - 1] = 1.0 / pivot;
                pivot = diagonal(j) - forward[j] * off(j - 1);
                debug_assert!(
                    pivot > 0.0,
                    "a pinned connected Laplacian is positive definite"
                );
            }
            inv_pivot[k - 1] = 1.0 / pivot;
            backward[k - 1] = off(k - 1) / pivot;
            factor.twist_multipliers[0] = off(k - 1) / pivot;
            gamma -= off(k - 1) * off(k - 1) / pivot;
        }
        if k < n - 1 {
            let mut pivot = diagonal(n - 1);
            for j in (k + 1..n - 1).rev() {
                forward[j] = off(j) / pivot;
                backward[j + 1] = off(j) / pivot;
                inv_pivot[j + 1] = 1.0 / pivot;
                pivot = diagonal(j) - forward[j] * off(j);
                debug_assert!(
                    pivot > 0.0,
                    "a pinned connected Laplacian is positive definite"
                );
            }
            inv_pivot[k + 1] = 1.0 / pivot;
            backward[k + 1] = off(k) / pivot;
            factor.twist_multipliers[1] = off(k) / pivot;
            gamma -= off(k) * off(k) / pivot;
        }
        debug_assert!(
            gamma > 0.0,
            "a pinned connected Laplacian is positive definite"
        );
        inv_pivot[k] = 1.0 / gamma;
        factor.forward = forward;
        factor.inv_pivot = inv_pivot;
        factor.backward = backward;
        Ok(factor)
    }

    /// Number of vertices.
    pub fn len(&self) -> usize {
        self.inv_pivot.len()
    }

    /// Whether there are no vertices (never, for a factored curve).
    pub fn is_empty(&self) -> bool {
        self.inv_pivot.is_empty()
    }

    /// Solve `L f = b` with `f_0 = 0` (both coordinates at once), writing into `f`.
    pub fn solve(&self, b: &[[f64; 2]], f: &mut [[f64; 2]]) {
        let n = self.len();
        debug_assert!(b.len() == n && f.len() == n);
        if n == 0 {
            return;
        }
        f[0] = [0.0, 0.0];
        if n < 2 {
            return;
        }
        let k = self.twist;
        let (mul, inv, back) = (&self.forward, &self.inv_pivot, &self.backward);
        // Forward elimination from both ends: rows 1..k and n−1 down to k+1, interleaved.
        f[1] = b[1];
        f[n - 1] = b[n - 1];
        let top = 2..k;
        let bottom = (k + 1..n - 1).rev();
        let common = top.len().min(bottom.len());
        for (j, i) in top.clone().zip(bottom.clone()) {
            f[j] = [
                b[j][0] - mul[j] * f[j - 1][0],
                b[j][1] - mul[j] * f[j - 1][1],
            ];
            f[i] = [
                b[i][0] - mul[i] * f[i + 1][0],
                b[i][1] - mul[i] * f[i + 1][1],
            ];
        }
        for j in top.skip(common) {
            f[j] = [
                b[j][0] - mul[j] * f[j - 1][0],
                b[j][1] - mul[j] * f[j - 1][1],
            ];
        }
        for i in bottom.skip(common) {
            f[i] = [
                b[i][0] - mul[i] * f[i + 1][0],
                b[i][1] - mul[i] * f[i + 1][1],
            ];
        }
        // The twist row; f[0] = 0 stands in for a missing upper neighbour.
        let [mu, ml] = self.twist_multipliers;
        let below = if k + 1 < n { f[k + 1] } else { [0.0, 0.0] };
        let above = if k > 1 { f[k - 1] } else { [0.0, 0.0] };
        let z = [
            b[k][0] - mu * above[0] - ml * below[0],
            b[k][1] - mu * above[1] - ml * below[1],
        ];
        f[k] = [z[0] * inv[k], z[1] * inv[k]];
        // Back substitution outwards from k, interleaved: x_j = z_j/P_j − (o_j/P_j) x_{j+1}.
        let up = (1..k).rev();
        let down = k + 1..n;
        let common = up.len().min(down.len());
        for (j, i) in up.clone().zip(down.clone()) {
            f[j] = [
                f[j][0] * inv[j] - back[j] * f[j + 1][0],
                f[j][1] * inv[j] - back[j] * f[j + 1][1],
            ];
            f[i] = [
                f[i][0] * inv[i] - back[i] * f[i - 1][0],
                f[i][1] * inv[i] - back[i] * f[i - 1][1],
            ];
        }
        for j in up.skip(common) {
            f[j] = [
                f[j][0] * inv[j] - back[j] * f[j + 1][0],
                f[j][1] * inv[j] - back[j] * f[j + 1][1],
            ];
        }
        for i in down.skip(common) {
            f[i] = [
                f[i][0] * inv[i] - back[i] * f[i - 1][0],
                f[i][1] * inv[i] - back[i] * f[i - 1][1],
            ];
        }
    }
}

/// Relative residual `max_i |(L f)_i − b_i| / max_i |b_i|` of the full (unpinned) system of
/// [`CurvePoisson`], rows of both coordinates; 0 when `b = 0` and `L f = 0`.
pub fn poisson_residual(
    inv_edge_lengths: &[f64],
    closed: bool,
    f: &[[f64; 2]],
    b: &[[f64; 2]],
) -> f64 {
    let n = f.len().min(b.len());
    let m = inv_edge_lengths.len();
    if n < 2 || m == 0 {
        return 0.0;
    }
    let (f, b, inv) = (&f[..n], &b[..n], inv_edge_lengths);
    // Row i of L f − b, for any vertex, from the edges on each side (if present).
    let row = |i: usize| {
        let mut r = [-b[i][0], -b[i][1]];
        let before = if i > 0 {
            Some((i - 1, i - 1))
        } else {
            closed.then_some((m - 1, n - 1))
        };
        if let Some((e, j)) = before {
            r[0] += (f[i][0] - f[j][0]) * inv[e];
            r[1] += (f[i][1] - f[j][1]) * inv[e];
        }
        if i < m {
            let j = if i + 1 == n { 0 } else { i + 1 };
            r[0] += (f[i][0] - f[j][0]) * inv[i];
            r[1] += (f[i][1] - f[j][1]) * inv[i];
        }
        r[0].abs().max(r[1].abs())
    };
    // Vertices 1..n−1 have both neighbours at i ± 1 on either kind of curve: branch-free,
    // with separate running maxima for x and y.
    let mut interior = [0.0f64; 2];
    for ((w, il), bi) in f.windows(3).zip(inv.windows(2)).zip(&b[1..n - 1]) {
        for c in 0..2 {
            let r = (w[1][c] - w[0][c]) * il[0] + (w[1][c] - w[2][c]) * il[1] - bi[c];
            interior[c] = larger(interior[c], r.abs());
        }
    }
    let interior = interior[0].max(interior[1]);
    let worst = interior.max(row(0)).max(row(n - 1));
    let mut scale = [0.0f64; 2];
    for bi in b {
        scale[0] = larger(scale[0], bi[0].abs());
        scale[1] = larger(scale[1], bi[1].abs());
    }
    let scale = scale[0].max(scale[1]);
    if scale > 0.0 {
        worst / scale
    } else {
        worst
    }
}
