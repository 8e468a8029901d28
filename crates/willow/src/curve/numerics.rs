//! Small-angle trigonometry and the edge rotations of a step, with the compensated sums they need: what keeps edge lengths exact to rounding over thousands of steps.

use super::*;

/// Wrap an angle into (−π, π], the range of [`turning_angles`].
#[inline]
pub(super) fn wrap_angle(a: f64) -> f64 {
    use std::f64::consts::{PI, TAU};
    if a > PI {
        a - TAU
    } else if a <= -PI {
        a + TAU
    } else {
        a
    }
}

/// `atan x = x − x³/3 + x⁵/5 − … − x¹⁵/15` for |x| ≤ 1/16, where the first omitted term is
/// below `2⁻⁶⁴|x|`. No branch, so a loop of it vectorizes.
#[inline(always)]
pub(super) fn atan_small(x: f64) -> f64 {
    // 1/(2j + 1), j = 1..=7: multiplications, since a division per term would cost more than
    // the whole series.
    const INV_ODD: [f64; 7] = [
        1.0 / 3.0,
        1.0 / 5.0,
        1.0 / 7.0,
        1.0 / 9.0,
        1.0 / 11.0,
        1.0 / 13.0,
        1.0 / 15.0,
    ];
    let x2 = x * x;
    let mut p = INV_ODD[6];
    for &a in INV_ODD[..6].iter().rev() {
        p = a - x2 * p;
    }
    x * (1.0 - x2 * p)
}

/// `(sin x, cos x)` by their Taylor series through x¹⁷ and x¹⁶, for |x| ≤ π/4, where the first
/// omitted terms are below 1e-19. No branch, so a loop of it vectorizes.
#[inline(always)]
pub(super) fn sin_cos_small(x: f64) -> (f64, f64) {
    // (−1)ʲ/(2j + 1)! and (−1)ʲ/(2j)!, j = 1..=8.
    const SIN: [f64; 8] = [
        -1.0 / 6.0,
        1.0 / 120.0,
        -1.0 / 5040.0,
        1.0 / 362_880.0,
        -1.0 / 39_916_800.0,
        1.0 / 6_227_020_800.0,
        -1.0 / 1_307_674_368_000.0,
        1.0 / 355_687_428_096_000.0,
    ];
    const COS: [f64; 8] = [
        -1.0 / 2.0,
        1.0 / 24.0,
        -1.0 / 720.0,
        1.0 / 40_320.0,
        -1.0 / 3_628_800.0,
        1.0 / 479_001_600.0,
        -1.0 / 87_178_291_200.0,
        1.0 / 20_922_789_888_000.0,
    ];
    let z = x * x;
    let (mut s, mut c) = (SIN[7], COS[7]);
    for j in (0..7).rev() {
        s = SIN[j] + z * s;
        c = COS[j] + z * c;
    }
    (x + x * z * s, 1.0 + z * c)
}

/// Largest |x| for which [`sin_cos_small`] is used.
pub(super) const SIN_COS_SMALL_MAX: f64 = std::f64::consts::FRAC_PI_4;

/// New tangents `T̃_k = ℓ_k R(Δ_k) e_k/|e_k|`: each current edge, rotated by its change of
/// angle Δ_k and scaled to its input length ℓ_k. Equal to [`tangents`] of the §5.2 angles
/// `θ_k = arg e_k + Δ_k`. A first pass uses Taylor series of sin and cos for every edge;
/// edges with |Δ_k| > π/4 (common in the first steps of a noisy curve, rare later) are redone
/// with the library `sin_cos`.
pub fn rotate_edges(
    points: &[[f64; 2]],
    angle_changes: &[f64],
    edge_lengths: &[f64],
    out: &mut [[f64; 2]],
) {
    let m = out.len().min(angle_changes.len()).min(edge_lengths.len());
    let (delta, ell, out) = (&angle_changes[..m], &edge_lengths[..m], &mut out[..m]);
    let rotate = |e: [f64; 2], l: f64, (s, c): (f64, f64)| {
        let scale = l / (e[0] * e[0] + e[1] * e[1]).sqrt();
        [scale * (c * e[0] - s * e[1]), scale * (s * e[0] + c * e[1])]
    };
    let mut all_small = true;
    for (k, (t, w)) in out.iter_mut().zip(points.windows(2)).enumerate() {
        all_small &= delta[k].abs() <= SIN_COS_SMALL_MAX;
        let e = [w[1][0] - w[0][0], w[1][1] - w[0][1]];
        *t = rotate(e, ell[k], sin_cos_small(delta[k]));
    }
    // The closing edge of a closed curve (windows stop at the last point).
    if m == points.len() && m > 0 {
        let e = edge_vector(points, m - 1);
        out[m - 1] = rotate(e, ell[m - 1], delta[m - 1].sin_cos());
    }
    if !all_small {
        for (k, t) in out.iter_mut().enumerate() {
            if delta[k].abs() > SIN_COS_SMALL_MAX {
                *t = rotate(edge_vector(points, k), ell[k], delta[k].sin_cos());
            }
        }
    }
}

/// Largest |x| = |tan α| for which [`atan_small`] is used.
pub(super) const ATAN_SMALL_MAX: f64 = 0.0625;

/// Signed angle `α_k` from the target tangent `T̃_k` to the edge `f̃_{k+1} − f̃_k` the Poisson
/// solve produced: how much the projection onto closed curves (§5.1) rotated each edge. These
/// are small (of the order of the length distortion), so a first pass uses [`atan_small`] on
/// `tan α = (T̃ × e)/(T̃ · e)` for every edge, and only edges outside its range (rare) are
/// redone with the library `atan2`.
pub(super) fn edge_rotations(tangents: &[[f64; 2]], points: &[[f64; 2]], out: &mut [f64]) {
    let m = out.len().min(tangents.len());
    let (t, out) = (&tangents[..m], &mut out[..m]);
    let sine_cosine = |k: usize, e: [f64; 2]| {
        (
            t[k][0] * e[1] - t[k][1] * e[0],
            t[k][0] * e[0] + t[k][1] * e[1],
        )
    };
    let mut all_small = true;
    for (k, (a, w)) in out.iter_mut().zip(points.windows(2)).enumerate() {
        let (s, c) = sine_cosine(k, [w[1][0] - w[0][0], w[1][1] - w[0][1]]);
        let x = s / c;
        all_small &= c > 0.0 && x.abs() <= ATAN_SMALL_MAX;
        *a = atan_small(x);
    }
    // The closing edge of a closed curve (windows stop at the last point).
    if m == points.len() && m > 0 {
        let (s, c) = sine_cosine(m - 1, edge_vector(points, m - 1));
        out[m - 1] = s.atan2(c);
    }
    if !all_small {
        for (k, a) in out.iter_mut().enumerate() {
            let (s, c) = sine_cosine(k, edge_vector(points, k));
            if !(c > 0.0 && s.abs() <= ATAN_SMALL_MAX * c) {
                *a = s.atan2(c);
            }
        }
    }
}

/// Turning angles of the curve the Poisson solve produced, from the target ones: the turn
/// from edge `i − 1` to edge `i` is the turn back to the target tangent, the target turn, and
/// the turn out to the new edge, `φ_i = φ̃_i + α_i − α_{i−1}` (mod 2π, wrapped into (−π, π]),
/// with `φ̃_i = ℓ*_i κ̃_i` (the cumulative sum of §5.2 advances θ by exactly this). This is an
/// identity of angles, not an approximation; it replaces an atan2 per vertex by a short
/// series per edge (debug builds check it against [`turning_angles`]). For a closed curve the
/// target turn at vertex 0 is the closing one, `2πk − Σ_{i≥1} φ̃_i`, k the turning number.
pub(super) fn update_turning_angles(
    kappa: &[f64],
    dual_lengths: &[f64],
    edge_rotations: &[f64],
    closed: bool,
    out: &mut [f64],
) {
    let n = out.len();
    let m = edge_rotations.len();
    if closed {
        let rest: f64 = (1..n).map(|i| dual_lengths[i] * kappa[i]).sum();
        let k = turning_number(rest + dual_lengths[0] * kappa[0]);
        let closing = std::f64::consts::TAU * k as f64 - rest;
        out[0] = wrap_angle(closing + edge_rotations[0] - edge_rotations[m - 1]);
    } else {
        out[0] = 0.0;
        out[n - 1] = 0.0;
    }
    let last = if closed { n } else { n - 1 };
    for i in 1..last {
        let target = dual_lengths[i] * kappa[i];
        out[i] = wrap_angle(target + edge_rotations[i] - edge_rotations[i - 1]);
    }
}

/// `Σ_{i<n} g(i)` in four interleaved partial sums. A plain left fold is one chain of
/// dependent additions, each waiting for the last (about 4 cycles per element); four chains
/// overlap, and the per-step reductions are most of the flow's time at a few thousand
/// vertices. The result differs from the sequential sum only by rounding.
#[inline(always)]
pub(super) fn sum4(n: usize, g: impl Fn(usize) -> f64) -> f64 {
    let mut acc = [0.0f64; 4];
    let full = n - n % 4;
    let mut i = 0;
    while i < full {
        acc[0] += g(i);
        acc[1] += g(i + 1);
        acc[2] += g(i + 2);
        acc[3] += g(i + 3);
        i += 4;
    }
    while i < n {
        acc[0] += g(i);
        i += 1;
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3])
}

/// `max(a, b)` by one comparison. `f64::max` also orders NaN, which costs a compare-unordered
/// and a blend per element in the hot reductions; here a NaN `b` is skipped. The flow cannot
/// produce NaN from a validated curve (finite input, positive definite factor).
#[inline(always)]
pub(super) fn larger(a: f64, b: f64) -> f64 {
    if b > a {
        b
    } else {
        a
    }
}

/// `max_{i<n} g(i)` (0 when n = 0 or all values are negative), four chains like [`sum4`].
#[inline(always)]
pub(super) fn max4(n: usize, g: impl Fn(usize) -> f64) -> f64 {
    let mut acc = [0.0f64; 4];
    let full = n - n % 4;
    let mut i = 0;
    while i < full {
        acc[0] = larger(acc[0], g(i));
        acc[1] = larger(acc[1], g(i + 1));
        acc[2] = larger(acc[2], g(i + 2));
        acc[3] = larger(acc[3], g(i + 3));
        i += 4;
    }
    while i < n {
        acc[0] = larger(acc[0], g(i));
        i += 1;
    }
    acc[0].max(acc[1]).max(acc[2].max(acc[3]))
}

/// Fallibly allocate `n` zeros (STYLE: user-sized buffers use `try_reserve`).
pub(super) fn zeroed<T: Copy + Default>(n: usize) -> Result<Vec<T>, CurveError> {
    let mut v = Vec::new();
    v.try_reserve_exact(n)
        .map_err(|_| CurveError::OutOfMemory { points: n })?;
    v.resize(n, T::default());
    Ok(v)
}
