//! What every flow step reports.
//!
//! - Willmore energy `W = Σ_i H_i² A_i` with *barycentric* vertex areas `A_i` (one third of the
//!   incident triangle areas) and `H_i = ⟨(L f)_i, N_i⟩ / (2 A_i)`; a round sphere gives 4π.
//! - Quasi-conformal error Q of each triangle's affine map from the *input* surface to the
//!   current one: the ratio of the larger to the smaller singular value (paper §6.4.2, after
//!   Sander et al. 2001). Q = 1 for a similarity.
//! - Closure residual `|d f̃ − ẽ| / |ẽ|` over all half-edges: how far the edges produced by λ
//!   (Table 1 step VI) are from integrable; the Poisson solve (step VII) spreads this error.
//! - Enclosed volume: the sum over *closed* components of `Σ_f det(p0, p1, p2) / 6` (the
//!   divergence theorem, [`enclosed_volume`]); a component with boundary encloses nothing and
//!   adds 0, so a disk reports 0 and a sphere beside a disk reports the sphere's volume.
//! - Deviation from the input: the two-sided sampled distance between the current surface
//!   and the input (vertices, edge midpoints and face centroids of each, to the nearest point
//!   of the other's triangles): its maximum and its area-weighted mean
//!   ([`crate::geometry::distance`] says exactly what is measured). In model units.

use crate::geometry::cache::GeometryCache;
use crate::geometry::distance::Deviation;
#[cfg(doc)]
use crate::geometry::operators::enclosed_volume;
use crate::geometry::operators::{component_volumes_into, face_areas_into};
use crate::mesh::topology::Topology;
use serde::{Deserialize, Serialize};

/// The metrics of the surface after one step (step 0 describes the input).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct StepMetrics {
    /// Steps taken so far; 0 is the input.
    pub step: usize,
    /// `Σ H² A` with barycentric areas (4π for a round sphere).
    pub willmore_energy: f64,
    /// Mean of the per-triangle quasi-conformal error Q against the input mesh.
    pub q_mean: f64,
    /// Area-weighted mean of Q (weights: current triangle areas).
    pub q_area_mean: f64,
    /// 95th percentile of Q over triangles.
    pub q_p95: f64,
    /// Largest Q over triangles.
    pub q_max: f64,
    /// `|d f̃ − ẽ| / |ẽ|` over all half-edges (0 for flows that do not integrate edges).
    pub closure_residual: f64,
    /// `|X λ − γ λ| / |λ|` of the inverse iteration, relative to the largest diagonal entry of
    /// X (0 for flows without an eigenproblem).
    pub eigen_residual: f64,
    /// Total surface area after the step.
    pub area: f64,
    /// Wall time of the step in milliseconds, metrics included (rejected tries too).
    pub step_ms: f64,
    /// The time step this step was taken with: the requested τ, or less where the safeguard
    /// ([`crate::flow::safeguard`]) had to retry (0 for step 0). Rows stored before it
    /// existed read as 0.
    #[serde(default)]
    pub tau: f64,
    /// Tries of this step the safeguard rejected before the one taken.
    #[serde(default)]
    pub rejected: u32,
    /// Enclosed volume summed over the closed components (open ones add 0: see the module
    /// docs). Every flow reports it; `None` only where it was not kept (a metrics row the
    /// service stored without it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub volume: Option<f64>,
    /// Largest sampled distance between this surface and the input, either way (a sampled
    /// symmetric Hausdorff distance; [`crate::geometry::distance`]). 0 for step 0. `None`
    /// where the flow does not measure it (`FlowParams::measure_deviation` off and no
    /// `max_deviation`): see `FlowParams::measure_deviation` for its cost.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub deviation_max: Option<f64>,
    /// Mean of the two one-sided area-weighted mean distances to the input: within 1% at 95%
    /// confidence on large meshes (a stratified estimate), exact over every sample on small
    /// ones (`Deviation::mean_bound`). 0 for step 0; `None` where not measured, as
    /// `deviation_max`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub deviation_mean: Option<f64>,
    /// `Σ_i |(L f)_i|² / (4 A_i)`: the Willmore energy of the whole mean-curvature *vector*
    /// (libigl's form), where [`StepMetrics::willmore_energy`] keeps only its normal part. The
    /// two agree on a smooth, well-sampled surface; a surface rough *along* itself (crumpled
    /// triangles, tangential jitter) has a vector form far above its signed one (issue 26).
    /// `None` in rows stored before it existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub willmore_energy_vector: Option<f64>,
    /// Scale distortion against the input: the 1st and 99th percentiles over triangles of
    /// `ln(s_f / s_f⁰)`, `s_f` the triangle's share of the total area now and `s_f⁰` in the
    /// input (0 and 0 for a similarity; Q, which measures angles only, cannot see a triangle
    /// shrinking uniformly). `None` in rows stored before they existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub log_area_ratio_p1: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub log_area_ratio_p99: Option<f64>,
    /// Triangles whose area share fell below [`COLLAPSED_SHARE`] of their input share (or
    /// whose area is not finite): collapsed, whatever their angles say.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub collapsed_triangles: Option<u32>,
    /// Crease edges the flow holds sharp (the conformal flow) or found sharpened (`denoise`)
    /// at this step ([`crate::flow::creases`], [`crate::flow::Flow::creases`]); `None` where
    /// the flow keeps no creases.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crease_edges: Option<u32>,
}

/// A triangle whose share of the total area is below this fraction of its share in the input
/// has collapsed (the soundness bound: a billionth of its input share is invisible).
pub const COLLAPSED_SHARE: f64 = 1e-8;

/// `Σ_i |(L f)_i|² / (4 A_i)` over vertices of positive area ([`StepMetrics::willmore_energy_vector`]).
pub fn willmore_energy_vector(laplacian_f: &[[f64; 3]], vertex_areas: &[f64]) -> f64 {
    laplacian_f
        .iter()
        .zip(vertex_areas)
        .filter(|(_, &a)| a > 0.0)
        .map(|(l, &a)| (l[0] * l[0] + l[1] * l[1] + l[2] * l[2]) / (4.0 * a))
        .sum()
}

/// Scale distortion of `face_areas` against `input_shares` (each input triangle's share of
/// the input's total area): `(p1, p99, collapsed)` of `ln(s_f / s_f⁰)` as
/// [`StepMetrics::log_area_ratio_p1`] describes. `scratch` has one entry per triangle.
/// An input triangle of zero area is left out (validation refuses them; regions may not).
pub fn scale_distortion(
    face_areas: &[f64],
    input_shares: &[f64],
    scratch: &mut Vec<f64>,
) -> (f64, f64, u32) {
    let total: f64 = face_areas.iter().sum();
    scratch.clear();
    let mut collapsed = 0u32;
    for (&a, &s0) in face_areas.iter().zip(input_shares) {
        if s0 <= 0.0 {
            continue;
        }
        let ratio = a / total / s0;
        // A NaN ratio (a non-finite area) counts as collapsed.
        if ratio.is_nan() || ratio < COLLAPSED_SHARE {
            collapsed += 1;
        }
        // ln 0 = −∞ would poison nothing (the percentile sorts it first) but cannot be sent
        // as JSON: floor at the smallest positive double's logarithm.
        scratch.push(if ratio.is_finite() {
            ratio.max(f64::MIN_POSITIVE).ln()
        } else {
            f64::MIN_POSITIVE.ln()
        });
    }
    if scratch.is_empty() {
        return (0.0, 0.0, collapsed);
    }
    let n = scratch.len();
    let rank = |p: f64| ((p * n as f64).ceil() as usize).clamp(1, n) - 1;
    let (_, &mut p1, _) = scratch.select_nth_unstable_by(rank(0.01), |a, b| a.total_cmp(b));
    let (_, &mut p99, _) = scratch.select_nth_unstable_by(rank(0.99), |a, b| a.total_cmp(b));
    (p1, p99, collapsed)
}

/// The input surface's per-triangle metric, kept to measure the quasi-conformal error of every
/// later surface against it.
pub struct ConformalReference {
    /// Inverse first fundamental form `G⁻¹` of each input triangle in the basis of its edges
    /// `(p1 − p0, p2 − p0)`, as `[g11, g12, g22]`, and `det G`.
    inverse_gram: Vec<[f64; 3]>,
    gram_det: Vec<f64>,
}

/// The largest value Q is reported as: a triangle collapsed to zero area has Q = ∞, which
/// JSON cannot carry.
pub const Q_CAP: f64 = 1e15;

impl ConformalReference {
    pub fn new(positions: &[[f64; 3]], triangles: &[[usize; 3]]) -> Self {
        let mut inverse_gram = Vec::with_capacity(triangles.len());
        let mut gram_det = Vec::with_capacity(triangles.len());
        for tri in triangles {
            let [g11, g12, g22] = gram(positions, tri);
            let det = g11 * g22 - g12 * g12;
            let inv = if det > 0.0 {
                [g22 / det, -g12 / det, g11 / det]
            } else {
                [0.0; 3]
            };
            inverse_gram.push(inv);
            gram_det.push(det);
        }
        ConformalReference {
            inverse_gram,
            gram_det,
        }
    }

    /// Q of every triangle of `positions` against the reference (paper §6.4.2): the ratio of
    /// the singular values `σ1 ≥ σ2` of the affine map between the two triangles. The squared
    /// singular values are the eigenvalues of `G_in⁻¹ G_now`, so with `t` its trace and `d` the
    /// square root of its determinant, `σ1/σ2 + σ2/σ1 = t/d` and `Q = r + √(r² − 1)`, `r = t/2d`.
    pub fn quasi_conformal_errors_into(
        &self,
        positions: &[[f64; 3]],
        triangles: &[[usize; 3]],
        out: &mut [f64],
    ) {
        for (((q, tri), inv), &det_in) in out
            .iter_mut()
            .zip(triangles)
            .zip(&self.inverse_gram)
            .zip(&self.gram_det)
        {
            let [h11, h12, h22] = gram(positions, tri);
            let det_now = h11 * h22 - h12 * h12;
            let trace = inv[0] * h11 + 2.0 * inv[1] * h12 + inv[2] * h22;
            *q = if det_in > 0.0 && det_now > 0.0 {
                let r = (trace / (2.0 * (det_now / det_in).sqrt())).max(1.0);
                (r + (r * r - 1.0).sqrt()).min(Q_CAP)
            } else {
                Q_CAP
            };
        }
    }
}

/// The per-step report every flow shares: Q against the input (with its buffers allocated
/// once), and the geometry's energy, area and enclosed volume.
pub struct StepReporter {
    reference: ConformalReference,
    q: Vec<f64>,
    scratch: Vec<f64>,
    /// Per face its component, and per component a vertex of it (the apex of the volume's
    /// cones: on the surface, so rounding sees the surface's size, not its distance from the
    /// origin) or `None` for a component with boundary.
    face_component: Vec<usize>,
    volume_apex: Vec<Option<usize>>,
    apexes: Vec<[f64; 3]>,
    volumes: Vec<f64>,
    /// The input's distance structure, when the flow measures the deviation.
    deviation: Option<Deviation>,
    /// Each input triangle's share of the input's total area, and scratch for the log ratios
    /// ([`scale_distortion`]).
    input_shares: Vec<f64>,
    log_ratios: Vec<f64>,
}

impl StepReporter {
    /// `deviation_threads`: whether each step reports its distance from the input (see
    /// [`StepMetrics::deviation_max`]), measured on how many threads
    /// ([`Deviation::with_threads`]).
    pub fn new(
        positions: &[[f64; 3]],
        triangles: &[[usize; 3]],
        topology: &Topology,
        deviation_threads: Option<usize>,
    ) -> Self {
        let volume_apex: Vec<Option<usize>> = topology
            .components
            .iter()
            .map(|c| c.is_closed().then(|| c.vertices.first().copied()).flatten())
            .collect();
        let mut face_areas = vec![0.0; triangles.len()];
        face_areas_into(positions, triangles, &mut face_areas);
        let total: f64 = face_areas.iter().sum();
        let input_shares = face_areas
            .iter()
            .map(|&a| if total > 0.0 { a / total } else { 0.0 })
            .collect();
        StepReporter {
            input_shares,
            log_ratios: Vec::with_capacity(triangles.len()),
            deviation: deviation_threads.map(|threads| {
                Deviation::new(positions, triangles, topology, &face_areas).with_threads(threads)
            }),
            reference: ConformalReference::new(positions, triangles),
            q: vec![1.0; triangles.len()],
            scratch: vec![1.0; triangles.len()],
            face_component: topology.face_component.clone(),
            apexes: vec![[0.0; 3]; volume_apex.len()],
            volumes: vec![0.0; volume_apex.len()],
            volume_apex,
        }
    }

    /// Step 0: the input itself (Q = 1 everywhere, no residuals).
    pub fn initial(
        &mut self,
        positions: &[[f64; 3]],
        triangles: &[[usize; 3]],
        geometry: &GeometryCache,
    ) -> StepMetrics {
        StepMetrics {
            step: 0,
            willmore_energy: geometry.willmore_energy(),
            q_mean: 1.0,
            q_area_mean: 1.0,
            q_p95: 1.0,
            q_max: 1.0,
            closure_residual: 0.0,
            eigen_residual: 0.0,
            area: geometry.total_area(),
            step_ms: 0.0,
            tau: 0.0,
            rejected: 0,
            volume: Some(self.closed_volume(positions, triangles)),
            deviation_max: self.deviation.as_ref().map(|_| 0.0),
            deviation_mean: self.deviation.as_ref().map(|_| 0.0),
            willmore_energy_vector: Some(willmore_energy_vector(
                &geometry.laplacian_f,
                &geometry.vertex_areas,
            )),
            log_area_ratio_p1: Some(0.0),
            log_area_ratio_p99: Some(0.0),
            collapsed_triangles: Some(0),
            crease_edges: None,
        }
    }

    /// The enclosed volume of the closed components (module docs).
    pub fn closed_volume(&mut self, positions: &[[f64; 3]], triangles: &[[usize; 3]]) -> f64 {
        if self.volume_apex.iter().all(Option::is_none) {
            return 0.0;
        }
        for (apex, v) in self.apexes.iter_mut().zip(&self.volume_apex) {
            *apex = v.map_or([0.0; 3], |v| positions[v]);
        }
        component_volumes_into(
            positions,
            triangles,
            &self.face_component,
            &self.apexes,
            &mut self.volumes,
        );
        self.volumes
            .iter()
            .zip(&self.volume_apex)
            .filter(|(_, apex)| apex.is_some())
            .map(|(v, _)| v)
            .sum()
    }

    /// The metrics of the surface at `positions` (whose geometry is `geometry`) after `step`.
    #[allow(clippy::too_many_arguments)]
    pub fn report(
        &mut self,
        step: usize,
        positions: &[[f64; 3]],
        triangles: &[[usize; 3]],
        geometry: &GeometryCache,
        closure_residual: f64,
        eigen_residual: f64,
        started: std::time::Instant,
    ) -> StepMetrics {
        self.reference
            .quasi_conformal_errors_into(positions, triangles, &mut self.q);
        let (q_mean, q_area_mean, q_p95, q_max) =
            summarize_q(&self.q, &geometry.face_areas, &mut self.scratch);
        let volume = self.closed_volume(positions, triangles);
        let (deviation_max, deviation_mean) = match &mut self.deviation {
            Some(d) => {
                let (max, mean) = d.measure(positions, triangles, &geometry.face_areas);
                (Some(max), Some(mean))
            }
            None => (None, None),
        };
        let (p1, p99, collapsed) = scale_distortion(
            &geometry.face_areas,
            &self.input_shares,
            &mut self.log_ratios,
        );
        StepMetrics {
            step,
            willmore_energy: geometry.willmore_energy(),
            q_mean,
            q_area_mean,
            q_p95,
            q_max,
            closure_residual,
            eigen_residual,
            area: geometry.total_area(),
            step_ms: started.elapsed().as_secs_f64() * 1e3,
            tau: 0.0,
            rejected: 0,
            volume: Some(volume),
            deviation_max,
            deviation_mean,
            willmore_energy_vector: Some(willmore_energy_vector(
                &geometry.laplacian_f,
                &geometry.vertex_areas,
            )),
            log_area_ratio_p1: Some(p1),
            log_area_ratio_p99: Some(p99),
            collapsed_triangles: Some(collapsed),
            crease_edges: None,
        }
    }
}

/// `[|u|², ⟨u, v⟩, |v|²]` for the edges `u = p1 − p0`, `v = p2 − p0` of a triangle.
fn gram(positions: &[[f64; 3]], tri: &[usize; 3]) -> [f64; 3] {
    let (p0, p1, p2) = (positions[tri[0]], positions[tri[1]], positions[tri[2]]);
    let u = [p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]];
    let v = [p2[0] - p0[0], p2[1] - p0[1], p2[2] - p0[2]];
    [
        u[0] * u[0] + u[1] * u[1] + u[2] * u[2],
        u[0] * v[0] + u[1] * v[1] + u[2] * v[2],
        v[0] * v[0] + v[1] * v[1] + v[2] * v[2],
    ]
}

/// Summary statistics of per-triangle Q: `(mean, area-weighted mean, p95, max)`.
/// `scratch` must have the length of `q`; it is overwritten (the percentile needs a partial sort).
pub fn summarize_q(q: &[f64], face_areas: &[f64], scratch: &mut [f64]) -> (f64, f64, f64, f64) {
    if q.is_empty() {
        return (1.0, 1.0, 1.0, 1.0);
    }
    let n = q.len();
    let mean = q.iter().sum::<f64>() / n as f64;
    let total_area: f64 = face_areas.iter().sum();
    let area_mean = if total_area > 0.0 {
        q.iter().zip(face_areas).map(|(q, a)| q * a).sum::<f64>() / total_area
    } else {
        mean
    };
    let max = q.iter().cloned().fold(1.0, f64::max);
    scratch.copy_from_slice(q);
    let rank = ((0.95 * n as f64).ceil() as usize).clamp(1, n) - 1;
    let (_, p95, _) = scratch.select_nth_unstable_by(rank, |a, b| a.total_cmp(b));
    (mean, area_mean, *p95, max)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate::bumpy_sphere;

    #[test]
    fn similarity_has_q_one() {
        let mesh = bumpy_sphere(2, 0.2);
        let reference = ConformalReference::new(&mesh.positions, &mesh.triangles);
        // Rotate about z by 0.7 rad, scale by 2.5, translate.
        let (s, c) = (0.7f64.sin(), 0.7f64.cos());
        let moved: Vec<[f64; 3]> = mesh
            .positions
            .iter()
            .map(|p| {
                [
                    2.5 * (c * p[0] - s * p[1]) + 1.0,
                    2.5 * (s * p[0] + c * p[1]) - 3.0,
                    2.5 * p[2] + 0.5,
                ]
            })
            .collect();
        let mut q = vec![0.0; mesh.face_count()];
        reference.quasi_conformal_errors_into(&moved, &mesh.triangles, &mut q);
        assert!(
            q.iter().all(|&q| (q - 1.0).abs() < 1e-6),
            "max {:?}",
            q.iter().cloned().fold(0.0, f64::max)
        );
    }

    #[test]
    fn axis_stretch_gives_its_ratio() {
        let mesh = bumpy_sphere(2, 0.0);
        let reference = ConformalReference::new(&mesh.positions, &mesh.triangles);
        // A flat triangle in the xy plane stretched by 3 along x has Q = 3 exactly.
        let flat = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.3, 0.8, 0.0]];
        let tri = [[0usize, 1, 2]];
        let r = ConformalReference::new(&flat, &tri);
        let stretched: Vec<[f64; 3]> = flat.iter().map(|p| [3.0 * p[0], p[1], p[2]]).collect();
        let mut q = [0.0];
        r.quasi_conformal_errors_into(&stretched, &tri, &mut q);
        assert!((q[0] - 3.0).abs() < 1e-12, "Q = {}", q[0]);
        drop(reference);
    }

    #[test]
    fn summary_percentile_and_weights() {
        let q: Vec<f64> = (1..=100).map(|i| 1.0 + i as f64 / 100.0).collect();
        let areas = vec![1.0; 100];
        let mut scratch = vec![0.0; 100];
        let (mean, area_mean, p95, max) = summarize_q(&q, &areas, &mut scratch);
        assert!((mean - 1.505).abs() < 1e-12);
        assert!((area_mean - mean).abs() < 1e-12);
        assert!((p95 - 1.95).abs() < 1e-12);
        assert!((max - 2.0).abs() < 1e-12);
    }
}
