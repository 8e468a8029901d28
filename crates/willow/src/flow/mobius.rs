//! Möbius balancing (§6.2, Appendix E.1): a sphere inversion that moves the surface's area
//! distribution toward the input's, added to the flow direction after the inversion
//! constraint has been projected out.
//!
//! Per component, with vertex areas `A_i`, desired areas `A*_i` (the input's), normals `N_i`:
//! `u_i = ½ log(A_i / A*_i)`, `u⁰ = u − mean_A(u)`, `v = Σ A_i f_i u⁰_i`, `B = 4 Σ A_i N_i N_iᵀ`,
//! `B a = v`, `a ← a / √(aᵀBa)`. The inversion with centre velocity `a` changes curvature by
//! `ρ̇ = −2⟨a, N⟩` (App. D) and log-scale by `u̇ = −2⟨a, f⟩` (App. E). We take the step `t` along
//! it that best cancels `u⁰` to first order, `t = −⟨⟨u⁰, u̇⁰⟩⟩ / ⟨⟨u̇⁰, u̇⁰⟩⟩`, clamped to
//! `|t| ≤ 1` (one unit of the normalized direction) because the relation is only first order.
//! Positions are taken relative to each component's centroid: the scale policy keeps it fixed.
//! (Centring changes neither `v`, since `Σ A_i u⁰_i = 0`, nor `u̇⁰`, since a constant `⟨a, c⟩`
//! in `u̇` is a uniform scale and is removed with the mean.)
//!
//! Sign: §6.2 says "add ⟨a, N⟩ to ρ̇", but App. D/E give `ρ̇ = −2⟨a, N⟩ ↔ u̇ = −2⟨a, f⟩`, and
//! with `a ∝ B⁻¹ ∫ u⁰ f` only `−⟨a, N⟩` lowers `u⁰`. We do not rely on either: `t` comes from
//! the predicted `u̇`, and in this discretization (`D λ̇ = ρ̇` with X = D*MD, outward normals)
//! the realized change of `u` per step has correlation 0.999 with the predicted one, at 0.9 of
//! its size (measured on the asymmetric dumbbell of tests/flow_mobius.rs once W has settled).
//!
//! Rate: the term is added to the direction *before* it is scaled by τ, so a step cancels a
//! fraction τ of the inversion part of `u⁰` (to first order): a relaxation `u̇ = −u` on that
//! part, converging over a few steps rather than in one.
//!
//! Fixed point: `v = 0` with the *current* areas as weights. That is not the minimum of the
//! current-area-weighted spread of `u⁰` ([`log_area_spread`]): moving area into a compressed
//! region also raises its weight. Balancing lowers the largest/smallest area ratio and drives
//! `v` to 0, the improvement Figure 13 shows, while that spread can rise slightly.

use crate::geometry::cache::GeometryCache;

/// Largest step along the normalized balancing direction per flow step.
const MAX_STEP: f64 = 1.0;

pub struct MobiusBalancing {
    target_areas: Vec<f64>,
    u: Vec<f64>,
    per_component: Vec<Sums>,
}

#[derive(Clone, Copy, Default)]
struct Sums {
    area: f64,
    weighted_u: f64,
    centroid: [f64; 3],
    v: [f64; 3],
    b: [[f64; 3]; 3],
    a: [f64; 3],
    u_dot_udot: f64,
    udot_udot: f64,
    udot_mean: f64,
    u_mean: f64,
}

impl MobiusBalancing {
    pub fn new(input_vertex_areas: &[f64], n_components: usize) -> Self {
        MobiusBalancing {
            target_areas: input_vertex_areas.to_vec(),
            u: vec![0.0; input_vertex_areas.len()],
            per_component: vec![Sums::default(); n_components],
        }
    }

    /// Add the balancing term to the flow direction `direction` (before it is scaled by τ).
    pub fn add_direction(
        &mut self,
        positions: &[[f64; 3]],
        geometry: &GeometryCache,
        vertex_component: &[usize],
        _tau: f64,
        direction: &mut [f64],
    ) {
        let areas = &geometry.vertex_areas;
        self.per_component.fill(Sums::default());
        // I. scale factors; area-weighted means and centroids.
        for i in 0..positions.len() {
            let s = &mut self.per_component[vertex_component[i]];
            let ratio = areas[i] / self.target_areas[i];
            self.u[i] = if ratio > 0.0 && ratio.is_finite() {
                0.5 * ratio.ln()
            } else {
                0.0
            };
            s.area += areas[i];
            s.weighted_u += areas[i] * self.u[i];
            for k in 0..3 {
                s.centroid[k] += areas[i] * positions[i][k];
            }
        }
        for s in &mut self.per_component {
            if s.area > 0.0 {
                s.u_mean = s.weighted_u / s.area;
                for k in 0..3 {
                    s.centroid[k] /= s.area;
                }
            }
        }
        // II–IV. u⁰, v and B.
        for i in 0..positions.len() {
            let s = &mut self.per_component[vertex_component[i]];
            let u0 = self.u[i] - s.u_mean;
            let n = geometry.normals[i];
            for k in 0..3 {
                s.v[k] += areas[i] * (positions[i][k] - s.centroid[k]) * u0;
                for l in 0..3 {
                    s.b[k][l] += 4.0 * areas[i] * n[k] * n[l];
                }
            }
        }
        // IV–V. Solve B a = v and normalize in the B norm.
        for s in &mut self.per_component {
            s.a = solve3(s.b, s.v).unwrap_or([0.0; 3]);
            let ba = mat_vec(s.b, s.a);
            let norm2 = s.a[0] * ba[0] + s.a[1] * ba[1] + s.a[2] * ba[2];
            s.a = if norm2 > 0.0 && norm2.is_finite() {
                let inv = 1.0 / norm2.sqrt();
                [s.a[0] * inv, s.a[1] * inv, s.a[2] * inv]
            } else {
                [0.0; 3]
            };
        }
        // The step: first-order best cancellation of u⁰ along u̇ = −2⟨a, f − centroid⟩.
        for i in 0..positions.len() {
            let s = &mut self.per_component[vertex_component[i]];
            let udot = -2.0 * dot_rel(s.a, positions[i], s.centroid);
            s.udot_mean += areas[i] * udot;
        }
        for s in &mut self.per_component {
            if s.area > 0.0 {
                s.udot_mean /= s.area;
            }
        }
        for i in 0..positions.len() {
            let s = &mut self.per_component[vertex_component[i]];
            let udot = -2.0 * dot_rel(s.a, positions[i], s.centroid) - s.udot_mean;
            let u0 = self.u[i] - s.u_mean;
            s.u_dot_udot += areas[i] * u0 * udot;
            s.udot_udot += areas[i] * udot * udot;
        }
        for i in 0..positions.len() {
            let s = &self.per_component[vertex_component[i]];
            if s.udot_udot <= 0.0 {
                continue;
            }
            let t = (-s.u_dot_udot / s.udot_udot).clamp(-MAX_STEP, MAX_STEP);
            let n = geometry.normals[i];
            direction[i] += t * -2.0 * (s.a[0] * n[0] + s.a[1] * n[1] + s.a[2] * n[2]);
        }
    }

    /// Largest over smallest `A_i / A*_i`: how far the area distribution is from the input's,
    /// up to global scale (1 when it matches).
    pub fn area_distortion(&self, vertex_areas: &[f64]) -> f64 {
        area_distortion(vertex_areas, &self.target_areas)
    }
}

/// Largest over smallest ratio `A_i / A*_i`.
pub fn area_distortion(vertex_areas: &[f64], target_areas: &[f64]) -> f64 {
    let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
    for (a, t) in vertex_areas.iter().zip(target_areas) {
        let r = a / t;
        lo = lo.min(r);
        hi = hi.max(r);
    }
    hi / lo
}

/// Area-weighted standard deviation of `½ log(A_i / A*_i)`: the L² size of the scale factor
/// `u⁰` that balancing reduces (0 when the distribution matches up to global scale).
pub fn log_area_spread(vertex_areas: &[f64], target_areas: &[f64]) -> f64 {
    let total: f64 = vertex_areas.iter().sum();
    let u = |a: f64, t: f64| 0.5 * (a / t).ln();
    let mean = vertex_areas
        .iter()
        .zip(target_areas)
        .map(|(&a, &t)| a * u(a, t))
        .sum::<f64>()
        / total;
    let var = vertex_areas
        .iter()
        .zip(target_areas)
        .map(|(&a, &t)| a * (u(a, t) - mean).powi(2))
        .sum::<f64>()
        / total;
    var.sqrt()
}

fn dot_rel(a: [f64; 3], p: [f64; 3], c: [f64; 3]) -> f64 {
    a[0] * (p[0] - c[0]) + a[1] * (p[1] - c[1]) + a[2] * (p[2] - c[2])
}

fn mat_vec(m: [[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    [
        m[0][0] * v[0] + m[0][1] * v[1] + m[0][2] * v[2],
        m[1][0] * v[0] + m[1][1] * v[1] + m[1][2] * v[2],
        m[2][0] * v[0] + m[2][1] * v[1] + m[2][2] * v[2],
    ]
}

/// Cramer's rule for a 3×3 system; `None` when it is (numerically) singular.
fn solve3(m: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let det = |m: [[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(m);
    let scale: f64 = m.iter().flatten().map(|x| x.abs()).fold(0.0, f64::max);
    if d.is_nan() || d.abs() <= 1e-12 * scale * scale * scale {
        return None;
    }
    let mut x = [0.0; 3];
    for (col, xc) in x.iter_mut().enumerate() {
        let mut mc = m;
        for row in 0..3 {
            mc[row][col] = b[row];
        }
        *xc = det(mc) / d;
    }
    Some(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn solve3_solves() {
        let m = [[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]];
        let x = solve3(m, [1.0, 2.0, 3.0]).expect("regular");
        let b = mat_vec(m, x);
        assert!((b[0] - 1.0).abs() + (b[1] - 2.0).abs() + (b[2] - 3.0).abs() < 1e-12);
        assert!(solve3(
            [[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 0.0, 1.0]],
            [1.0, 1.0, 1.0]
        )
        .is_none());
    }
}
