//! Classic position-based flows, for comparison with the conformal flow (paper §6.4.2,
//! Figure 17) through the same [`Flow`] interface and the same metrics.

use super::scale::ScalePolicy;
use super::solver::{BlockPattern, Cholesky};
use super::willmore::check_params;
use super::{Flow, FlowError, FlowParams};
use crate::geometry::cache::GeometryCache;
use crate::mesh::topology::Topology;
use crate::mesh::Mesh;
use crate::metrics::{summarize_q, ConformalReference, StepMetrics};
use std::time::Instant;

/// Implicit mean curvature flow (Desbrun et al. 1999): backward Euler on `ḟ = −HN`,
/// `(M + h L) f' = M f` with the cotan Laplacian `L` and barycentric mass `M` of the current
/// surface. The step `h = τ · A / 4π` makes τ unitless (A is the total area). The scale policy
/// of the conformal flow restores each component's area and centroid after every step, so
/// both flows report comparable shapes.
pub struct ImplicitMeanCurvatureFlow {
    triangles: Vec<[usize; 3]>,
    positions: Vec<[f64; 3]>,
    tau: f64,
    step: usize,
    geometry: GeometryCache,
    reference: ConformalReference,
    scale: ScalePolicy,
    initial: StepMetrics,
    pattern: BlockPattern,
    values: Vec<f64>,
    cholesky: Cholesky<f64>,
    rhs: Vec<f64>,
    q: Vec<f64>,
    q_scratch: Vec<f64>,
}

impl ImplicitMeanCurvatureFlow {
    pub fn new(mesh: &Mesh, params: &FlowParams) -> Result<Self, FlowError> {
        check_params(params)?;
        let topology = Topology::new(mesh);
        let n = mesh.vertex_count();
        let geometry = GeometryCache::new(&mesh.positions, &mesh.triangles);
        let scale = ScalePolicy::new(
            topology.vertex_component.clone(),
            topology.components.len(),
            &mesh.positions,
            &geometry.vertex_areas,
        );
        let pattern = BlockPattern::new(n, &mesh.triangles, 1);
        let cholesky = Cholesky::<f64>::analyze(&pattern, 3).map_err(|e| FlowError::Numerical {
            step: 0,
            reason: e.to_string(),
        })?;
        let initial = StepMetrics {
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
        };
        Ok(ImplicitMeanCurvatureFlow {
            triangles: mesh.triangles.clone(),
            positions: mesh.positions.clone(),
            tau: params.tau,
            step: 0,
            reference: ConformalReference::new(&mesh.positions, &mesh.triangles),
            geometry,
            scale,
            initial,
            values: vec![0.0; pattern.nnz()],
            pattern,
            cholesky,
            rhs: vec![0.0; 3 * n],
            q: vec![1.0; mesh.face_count()],
            q_scratch: vec![1.0; mesh.face_count()],
        })
    }
}

impl Flow for ImplicitMeanCurvatureFlow {
    fn step(&mut self) -> Result<StepMetrics, FlowError> {
        let start = Instant::now();
        let n = self.positions.len();
        let g = &self.geometry;
        let h = self.tau * g.total_area() / (4.0 * std::f64::consts::PI);
        self.values.fill(0.0);
        for ((tri, cots), slots) in self
            .triangles
            .iter()
            .zip(&g.cotangents)
            .zip(&self.pattern.face_slots)
        {
            for c in 0..3 {
                let (a, b) = ((c + 1) % 3, (c + 2) % 3);
                let w = 0.5 * h * cots[c];
                let p = &self.pattern;
                self.values[p.entry(slots[3 * a + b], tri[b], 0, 0)] -= w;
                self.values[p.entry(slots[3 * b + a], tri[a], 0, 0)] -= w;
                self.values[p.entry(slots[3 * a + a], tri[a], 0, 0)] += w;
                self.values[p.entry(slots[3 * b + b], tri[b], 0, 0)] += w;
            }
        }
        for (v, &a) in g.vertex_areas.iter().enumerate() {
            let p = &self.pattern;
            self.values[p.entry(p.diagonal_slot(v), v, 0, 0)] += a;
        }
        self.cholesky
            .factorize(&self.pattern, &self.values)
            .map_err(|e| FlowError::Numerical {
                step: self.step + 1,
                reason: format!("M + hL: {e}"),
            })?;
        for (i, (p, &a)) in self.positions.iter().zip(&g.vertex_areas).enumerate() {
            for k in 0..3 {
                self.rhs[k * n + i] = a * p[k];
            }
        }
        self.cholesky.solve_in_place(&mut self.rhs, 3);
        for (i, p) in self.positions.iter_mut().enumerate() {
            *p = [self.rhs[i], self.rhs[n + i], self.rhs[2 * n + i]];
        }
        if self
            .positions
            .iter()
            .any(|p| !(p[0].is_finite() && p[1].is_finite() && p[2].is_finite()))
        {
            return Err(FlowError::Numerical {
                step: self.step + 1,
                reason: "implicit MCF produced non-finite positions".into(),
            });
        }
        self.geometry.refresh(&self.positions, &self.triangles);
        self.scale
            .restore(&mut self.positions, &self.geometry.vertex_areas);
        self.geometry.refresh(&self.positions, &self.triangles);
        self.step += 1;
        self.reference
            .quasi_conformal_errors_into(&self.positions, &self.triangles, &mut self.q);
        let (q_mean, q_area_mean, q_p95, q_max) =
            summarize_q(&self.q, &self.geometry.face_areas, &mut self.q_scratch);
        Ok(StepMetrics {
            step: self.step,
            willmore_energy: self.geometry.willmore_energy(),
            q_mean,
            q_area_mean,
            q_p95,
            q_max,
            closure_residual: 0.0,
            eigen_residual: 0.0,
            area: self.geometry.total_area(),
            step_ms: start.elapsed().as_secs_f64() * 1e3,
        })
    }

    fn positions(&self) -> &[[f64; 3]] {
        &self.positions
    }

    fn initial_metrics(&self) -> StepMetrics {
        self.initial
    }
}
