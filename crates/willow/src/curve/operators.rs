//! Discrete operators on a polyline (§5): edge and dual lengths, turning angles, curvature, the dual inner product, the closure constraints, tangents and the divergence.

use super::*;

/// Axis-aligned bounding box `(min, max)` of finite points.
pub(super) fn bounding_box(points: &[[f64; 2]]) -> ([f64; 2], [f64; 2]) {
    let mut lo = [f64::INFINITY; 2];
    let mut hi = [f64::NEG_INFINITY; 2];
    for p in points {
        for c in 0..2 {
            lo[c] = lo[c].min(p[c]);
            hi[c] = hi[c].max(p[c]);
        }
    }
    (lo, hi)
}

/// Edge vector `T_i = f_{i+1} − f_i` (cyclic index for the closing edge).
#[inline]
pub(super) fn edge_vector(points: &[[f64; 2]], i: usize) -> [f64; 2] {
    let a = points[i];
    let b = points[if i + 1 == points.len() { 0 } else { i + 1 }];
    [b[0] - a[0], b[1] - a[1]]
}

/// Number of edges of a polyline with `point_count` points: `n` if closed, `n − 1` if open.
pub fn edge_count(point_count: usize, closed: bool) -> usize {
    if closed {
        point_count
    } else {
        point_count.saturating_sub(1)
    }
}

/// Turning number `round(total_curvature / 2π)`.
pub fn turning_number(total_curvature: f64) -> i64 {
    (total_curvature / std::f64::consts::TAU).round() as i64
}

/// Edge lengths `ℓ_{i,i+1} = |f_{i+1} − f_i|` (§5.2) into `out` (length [`edge_count`]).
pub fn edge_lengths(points: &[[f64; 2]], closed: bool, out: &mut [f64]) {
    debug_assert_eq!(out.len(), edge_count(points.len(), closed));
    for (l, w) in out.iter_mut().zip(points.windows(2)) {
        let e = [w[1][0] - w[0][0], w[1][1] - w[0][1]];
        *l = (e[0] * e[0] + e[1] * e[1]).sqrt();
    }
    if closed && !points.is_empty() {
        let e = edge_vector(points, points.len() - 1);
        out[points.len() - 1] = (e[0] * e[0] + e[1] * e[1]).sqrt();
    }
}

/// Dual lengths `ℓ*_i = ½(ℓ_{i−1,i} + ℓ_{i,i+1})` (§5.2), the length element of the vertex
/// inner product `⟨⟨a, b⟩⟩ = Σ a_i b_i ℓ*_i`. An open curve's endpoints get half of their one
/// edge, so `Σ ℓ* = Σ ℓ` in both cases. `out` has one entry per vertex.
pub fn dual_lengths(edge_lengths: &[f64], closed: bool, out: &mut [f64]) {
    let n = out.len();
    let m = edge_lengths.len();
    debug_assert_eq!(m, edge_count(n, closed));
    for (i, d) in out.iter_mut().enumerate() {
        let before = if i > 0 {
            edge_lengths[i - 1]
        } else if closed {
            edge_lengths[m - 1]
        } else {
            0.0
        };
        let after = if i < m { edge_lengths[i] } else { 0.0 };
        *d = 0.5 * (before + after);
    }
}

/// Signed turning angles `φ_i = atan2(T_{i−1} × T_i, T_{i−1} · T_i) ∈ (−π, π]` from edge
/// `i − 1` to edge `i`, positive for a counter-clockwise turn (§5.2: `φ_i = κ_i ℓ*_i` is the
/// exterior angle). An open curve's endpoints get 0. For a closed curve `Σ φ = 2π k` exactly,
/// k the turning number.
pub fn turning_angles(points: &[[f64; 2]], closed: bool, out: &mut [f64]) {
    let n = points.len();
    debug_assert_eq!(out.len(), n);
    if n < 2 {
        out.fill(0.0);
        return;
    }
    let (first, last) = if closed { (0, n) } else { (1, n - 1) };
    if !closed {
        out[0] = 0.0;
        out[n - 1] = 0.0;
    }
    // `prev` is the edge into vertex i; walking forward reuses each edge vector once.
    let mut prev = edge_vector(points, if first == 0 { n - 1 } else { first - 1 });
    for (i, phi) in out.iter_mut().enumerate().take(last).skip(first) {
        let next = edge_vector(points, i);
        let cross = prev[0] * next[1] - prev[1] * next[0];
        let dot = prev[0] * next[0] + prev[1] * next[1];
        *phi = cross.atan2(dot);
        prev = next;
    }
}

/// Pointwise curvature `κ_i = φ_i / ℓ*_i` (§5.2: turning angle over dual length).
pub fn curvature(turning_angles: &[f64], dual_lengths: &[f64], out: &mut [f64]) {
    for ((k, &phi), &d) in out.iter_mut().zip(turning_angles).zip(dual_lengths) {
        *k = phi / d;
    }
}

/// Weighted inner product `⟨⟨a, b⟩⟩ = Σ a_i b_i ℓ*_i` (§4, §5), the discrete `∫ a b dl`.
#[inline]
pub fn dual_inner(a: &[f64], b: &[f64], dual_lengths: &[f64]) -> f64 {
    let n = a.len().min(b.len()).min(dual_lengths.len());
    let (a, b, w) = (&a[..n], &b[..n], &dual_lengths[..n]);
    sum4(n, |i| a[i] * b[i] * w[i])
}

/// Curve fairing energy `E_C = Σ κ_i² ℓ*_i = ‖κ‖²` (§5).
pub fn curvature_energy(kappa: &[f64], dual_lengths: &[f64]) -> f64 {
    dual_inner(kappa, kappa, dual_lengths)
}

/// Length-weighted standard deviation of κ over its length-weighted mean, `σ(κ) / |κ̄|`:
/// 0 for a circle. A straight curve (σ = 0) gives 0; a curve with κ̄ = 0 but σ > 0 (an open
/// wiggle, a figure-eight) gives `+∞`.
pub fn curvature_std_over_mean(kappa: &[f64], dual_lengths: &[f64]) -> f64 {
    let n = kappa.len().min(dual_lengths.len());
    let (k, w) = (&kappa[..n], &dual_lengths[..n]);
    let total = sum4(n, |i| w[i]);
    let mean = sum4(n, |i| w[i] * k[i]) / total;
    // Two passes: `E/L − κ̄²` would cancel catastrophically near a circle, where σ/κ̄ ~ 1e-8.
    let variance = sum4(n, |i| w[i] * (k[i] - mean) * (k[i] - mean)) / total;
    let std = variance.sqrt();
    if std == 0.0 {
        0.0
    } else {
        std / mean.abs()
    }
}

/// Orthonormal basis (in `⟨⟨·,·⟩⟩`) of the closed-curve constraint functions `{1, fˣ, fʸ}`
/// (§5, Appendix A): the flow keeps `∫ κ̇ dl = 0` (tangents close up: total curvature stays
/// `2πk`) and `∫ κ̇ f dl = 0` (positions close up, to first order). Built by modified
/// Gram–Schmidt in that order (Table 1 step III); buffers are allocated once.
#[derive(Clone, Debug)]
pub struct ConstraintBasis {
    vectors: [Vec<f64>; 3],
    len: usize,
}

impl ConstraintBasis {
    /// Buffers for curves of `n` vertices, fallibly allocated.
    pub fn with_len(n: usize) -> Result<Self, CurveError> {
        Ok(ConstraintBasis {
            vectors: [zeroed(n)?, zeroed(n)?, zeroed(n)?],
            len: 0,
        })
    }

    /// Refill from the current positions (Table 1 step III). A function that is (numerically)
    /// in the span of the earlier ones is dropped (relative norm below 1e-10), which cannot
    /// happen for a valid closed curve but keeps the projection exact if it does.
    pub fn rebuild(&mut self, points: &[[f64; 2]], dual_lengths: &[f64]) {
        self.len = 0;
        for candidate in 0..3 {
            let (done, rest) = self.vectors.split_at_mut(self.len);
            let c = &mut rest[0];
            for (ci, p) in c.iter_mut().zip(points) {
                *ci = match candidate {
                    0 => 1.0,
                    1 => p[0],
                    _ => p[1],
                };
            }
            let before = dual_inner(c, c, dual_lengths).sqrt();
            for q in done.iter() {
                let a = dual_inner(c, q, dual_lengths);
                for (ci, qi) in c.iter_mut().zip(q) {
                    *ci -= a * qi;
                }
            }
            let after = dual_inner(c, c, dual_lengths).sqrt();
            if after > GRAM_SCHMIDT_DROP_RTOL * before {
                let inv = 1.0 / after;
                c.iter_mut().for_each(|ci| *ci *= inv);
                self.len += 1;
            }
        }
    }

    /// Number of basis functions kept (3 for any valid closed curve).
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether no function was kept (only before the first [`ConstraintBasis::rebuild`]).
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The i-th orthonormal function.
    pub fn vector(&self, i: usize) -> &[f64] {
        &self.vectors[i][..]
    }

    /// `v ← v − Σ_i ⟨⟨v, ĉ_i⟩⟩ ĉ_i` (§4; Table 1 step IV), applied one function at a time.
    pub fn project_out(&self, v: &mut [f64], dual_lengths: &[f64]) {
        for q in &self.vectors[..self.len] {
            let a = dual_inner(v, q, dual_lengths);
            for (vi, qi) in v.iter_mut().zip(q) {
                *vi -= a * qi;
            }
        }
    }
}

/// Table 1 steps III–IV for a closed curve in closed form: `v ← v − Σ ⟨⟨v, ĉ_i⟩⟩ ĉ_i` with
/// `{ĉ_i}` the Gram–Schmidt orthonormalization of `{1, fˣ, fʸ}` in that order, as
/// [`ConstraintBasis`] builds it, but from weighted moments instead of stored basis vectors:
///
/// - `ĉ_0 = 1/√L` (L = Σ ℓ*);
/// - `ĉ_1 = x̂/σ_x` with the centred `x̂ = fˣ − x̄`, `σ_x² = ⟨⟨x̂, x̂⟩⟩`;
/// - `ĉ_2 = (ŷ − β x̂)/σ_2` with `β = ⟨⟨ŷ, x̂⟩⟩/σ_x²`, `σ_2² = ⟨⟨ŷ, ŷ⟩⟩ − β ⟨⟨ŷ, x̂⟩⟩`.
///
/// Three passes (means; centred moments; update) instead of about twenty. Centring first
/// keeps the moments free of the cancellation `Σ x² − L x̄²` would suffer far from the origin.
/// A function whose norm falls below 1e-10 of its centred size is skipped, as in
/// [`ConstraintBasis::rebuild`]. The tests check this against [`ConstraintBasis`].
pub fn project_out_closure_constraints(points: &[[f64; 2]], dual_lengths: &[f64], v: &mut [f64]) {
    let n = points.len().min(dual_lengths.len()).min(v.len());
    if n == 0 {
        return;
    }
    let (p, w, v) = (&points[..n], &dual_lengths[..n], &mut v[..n]);
    // Pass 1: L and the weighted means. Pass 2: the six centred moments, each its own
    // accumulator, so the additions overlap.
    let (mut total, mut sx, mut sy) = (0.0, 0.0, 0.0);
    for (q, wi) in p.iter().zip(w) {
        total += wi;
        sx += wi * q[0];
        sy += wi * q[1];
    }
    let (mx, my) = (sx / total, sy / total);
    let (mut sxx, mut sxy, mut syy, mut sv, mut svx, mut svy) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    for ((q, wi), vi) in p.iter().zip(w).zip(v.iter()) {
        let (x, y) = (q[0] - mx, q[1] - my);
        let (wx, wy, wv) = (wi * x, wi * y, wi * vi);
        sxx += wx * x;
        sxy += wx * y;
        syy += wy * y;
        sv += wv;
        svx += wv * x;
        svy += wv * y;
    }
    // v −= a_0 + a_x x̂ + a_y ŷ, collecting the three projections.
    let a0 = sv / total;
    let (mut ax, mut ay) = (0.0, 0.0);
    if sxx > (GRAM_SCHMIDT_DROP_RTOL * GRAM_SCHMIDT_DROP_RTOL) * (sxx + syy) {
        // ⟨⟨v, ĉ_1⟩⟩ ĉ_1 = (svx/sxx) x̂.
        ax = svx / sxx;
        let beta = sxy / sxx;
        let s2 = syy - beta * sxy;
        if s2 > (GRAM_SCHMIDT_DROP_RTOL * GRAM_SCHMIDT_DROP_RTOL) * syy {
            // ⟨⟨v, ŷ − βx̂⟩⟩/σ_2² · (ŷ − βx̂).
            let c = (svy - beta * svx) / s2;
            ay = c;
            ax -= c * beta;
        }
    } else if syy > 0.0 {
        ay = svy / syy;
    }
    for (vi, q) in v.iter_mut().zip(p) {
        *vi -= a0 + ax * (q[0] - mx) + ay * (q[1] - my);
    }
}

/// Edge tangent angles by the cumulative sum of §5.2,
/// `θ_k = θ_0 + Σ_{i=1}^{k} ½(ℓ_{i−1,i} + ℓ_{i,i+1}) κ_i` for `k = 0..out.len()` (one per
/// edge; the angle of edge k, from vertex k to k + 1). For a closed curve vertex 0's curvature
/// does not enter: it is the closing turn, fixed by the total curvature.
pub fn tangent_angles(theta0: f64, kappa: &[f64], dual_lengths: &[f64], out: &mut [f64]) {
    let mut theta = theta0;
    for (k, t) in out.iter_mut().enumerate() {
        if k > 0 {
            theta += dual_lengths[k] * kappa[k];
        }
        *t = theta;
    }
}

/// New edge vectors `T̃_ij = ℓ_ij (cos θ_i, sin θ_i)` (§5.2) with the input lengths ℓ.
pub fn tangents(theta: &[f64], edge_lengths: &[f64], out: &mut [[f64; 2]]) {
    for ((t, &th), &l) in out.iter_mut().zip(theta).zip(edge_lengths) {
        let (s, c) = th.sin_cos();
        *t = [l * c, l * s];
    }
}

/// Discrete divergence `b_i = T̃_{i−1,i}/ℓ_{i−1,i} − T̃_{i,i+1}/ℓ_{i,i+1}` (§5.2), the right-hand
/// side of `L f̃ = b`; an open curve's endpoints keep only their one edge. `Σ b = 0` in both
/// cases, so the singular system is consistent. `inv_edge_lengths` holds `1/ℓ`.
pub fn divergence(
    tangents: &[[f64; 2]],
    inv_edge_lengths: &[f64],
    closed: bool,
    out: &mut [[f64; 2]],
) {
    let n = out.len();
    let m = tangents.len();
    debug_assert_eq!(m, edge_count(n, closed));
    if n == 0 || m == 0 {
        out.fill([0.0, 0.0]);
        return;
    }
    let unit = |e: usize| {
        [
            tangents[e][0] * inv_edge_lengths[e],
            tangents[e][1] * inv_edge_lengths[e],
        ]
    };
    // Interior vertices 1..m have an edge on both sides; vertex 0 and, for open curves,
    // vertex n − 1 are handled after.
    let mut before = unit(0);
    for (i, b) in out.iter_mut().enumerate().take(m).skip(1) {
        let after = unit(i);
        *b = [before[0] - after[0], before[1] - after[1]];
        before = after;
    }
    let first = unit(0);
    let last = unit(m - 1);
    if closed {
        out[0] = [last[0] - first[0], last[1] - first[1]];
    } else {
        out[0] = [-first[0], -first[1]];
        out[n - 1] = last;
    }
}
