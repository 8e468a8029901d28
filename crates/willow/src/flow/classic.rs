//! Classic position-based flows, for comparison with the conformal flow (paper §6.4.2,
//! Figure 17) through the same [`Flow`] interface and the same metrics.

use super::safeguard::Retry;
use super::scale::ScalePolicy;
use super::{Flow, FlowError, FlowParams, Preserve};
use crate::geometry::cache::GeometryCache;
use crate::linalg::solver::{add_diagonal, assemble_cotan_laplacian_into, BlockPattern, Cholesky};
use crate::mesh::topology::Topology;
use crate::mesh::Mesh;
use crate::metrics::{StepMetrics, StepReporter};
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::matmul::{
    sparse_sparse_matmul_numeric, sparse_sparse_matmul_numeric_scratch,
    sparse_sparse_matmul_symbolic, SparseMatMulInfo,
};
use faer::sparse::{SparseColMatMut, SparseColMatRef, SymbolicSparseColMat};
use faer::{Accum, Par};
use std::time::Instant;

/// Implicit mean curvature flow (Desbrun et al. 1999): backward Euler on `ḟ = −HN`,
/// `(M + h L) f' = M f` with the cotan Laplacian `L` and barycentric mass `M` of the current
/// surface. The step `h = τ · A / 4π` makes τ unitless (A is the total area). The scale policy
/// of the conformal flow restores each component's area and centroid after every step, so
/// both flows report comparable shapes.
pub struct ImplicitMeanCurvatureFlow {
    surface: ClassicSurface,
    tau: f64,
    pattern: BlockPattern,
    values: Vec<f64>,
    cholesky: Cholesky<f64>,
    rhs: Vec<f64>,
}

/// The symbolic analysis of a Laplacian-like matrix on `pattern`, for 3 right-hand sides (the
/// coordinates), with the thread budget of `params`.
fn laplacian_solver(
    pattern: &BlockPattern,
    params: &FlowParams,
) -> Result<Cholesky<f64>, FlowError> {
    let mut cholesky = Cholesky::<f64>::analyze(pattern, 3).map_err(|e| FlowError::Numerical {
        step: 0,
        reason: e.to_string(),
    })?;
    cholesky.set_threads(params.threads);
    cholesky.release_triangle();
    Ok(cholesky)
}

impl ImplicitMeanCurvatureFlow {
    pub fn new(mesh: &Mesh, params: &FlowParams) -> Result<Self, FlowError> {
        params.validate()?;
        let topology = Topology::new(mesh);
        let pattern = BlockPattern::new(mesh.vertex_count(), &mesh.triangles, 1);
        let cholesky = laplacian_solver(&pattern, params)?;
        Ok(ImplicitMeanCurvatureFlow {
            surface: ClassicSurface::new(
                mesh,
                &topology,
                Some(params.preserve),
                params.deviation_threads(),
            ),
            tau: params.tau,
            values: vec![0.0; pattern.nnz()],
            pattern,
            cholesky,
            rhs: vec![0.0; 3 * mesh.vertex_count()],
        })
    }
}

impl Flow for ImplicitMeanCurvatureFlow {
    fn step(&mut self) -> Result<StepMetrics, FlowError> {
        let start = Instant::now();
        let s = &mut self.surface;
        let g = &s.geometry;
        let h = self.tau * squared_radius(g);
        assemble_cotan_laplacian_into(
            &self.pattern,
            &s.triangles,
            &g.cotangents,
            h,
            &mut self.values,
        );
        add_diagonal(
            &self.pattern,
            g.vertex_areas.iter().copied(),
            &mut self.values,
        );
        self.cholesky
            .factorize(&self.pattern, &self.values)
            .map_err(|e| s.numerical(format!("M + hL: {e}")))?;
        s.mass_times_positions(&mut self.rhs);
        self.cholesky.solve_in_place(&mut self.rhs, 3);
        s.set_positions(&self.rhs);
        s.finish_step(start, "implicit MCF")
    }

    fn positions(&self) -> &[[f64; 3]] {
        &self.surface.positions
    }

    fn initial_metrics(&self) -> StepMetrics {
        self.surface.initial
    }
}

/// [`Retry`] for the implicit flows: τ is a field, and the state is the shared surface.
macro_rules! retry_on_surface {
    ($($flow:ty),*) => {$(
        impl Retry for $flow {
            fn tau(&self) -> f64 {
                self.tau
            }

            fn set_tau(&mut self, tau: f64) {
                self.tau = tau;
            }

            fn restore(&mut self, positions: &[[f64; 3]], step: usize) {
                self.surface.restore(positions, step);
            }
        }
    )*};
}

retry_on_surface!(
    ImplicitMeanCurvatureFlow,
    ConformalizedMeanCurvatureFlow,
    ImplicitBilaplacianFlow
);

/// What the classic flows below share: the moving surface, its cached geometry, the scale
/// policy and the per-step metrics, so every method reports exactly the same quantities.
pub(super) struct ClassicSurface {
    triangles: Vec<[usize; 3]>,
    pub(super) positions: Vec<[f64; 3]>,
    pub(super) step: usize,
    geometry: GeometryCache,
    reporter: StepReporter,
    /// `None` for Taubin smoothing: not shrinking is its whole point, so rescaling it would
    /// hide what the comparison is meant to show.
    scale: Option<ScalePolicy>,
    pub(super) initial: StepMetrics,
}

impl ClassicSurface {
    /// `preserve`: the scale policy to apply after every step, `None` for none at all;
    /// `deviation_threads`: whether steps report their distance from the input, measured on
    /// how many threads ([`FlowParams::deviation_threads`]).
    pub(super) fn new(
        mesh: &Mesh,
        topology: &Topology,
        preserve: Option<Preserve>,
        deviation_threads: Option<usize>,
    ) -> Self {
        let geometry = GeometryCache::new(&mesh.positions, &mesh.triangles);
        let scale = preserve.map(|preserve| {
            ScalePolicy::new(
                preserve,
                topology,
                &mesh.positions,
                &mesh.triangles,
                &geometry.vertex_areas,
            )
        });
        let mut reporter = StepReporter::new(
            &mesh.positions,
            &mesh.triangles,
            topology,
            deviation_threads,
        );
        let initial = reporter.initial(&mesh.positions, &mesh.triangles, &geometry);
        ClassicSurface {
            triangles: mesh.triangles.clone(),
            positions: mesh.positions.clone(),
            step: 0,
            reporter,
            geometry,
            scale,
            initial,
        }
    }

    /// `M f` in the column-major `n × 3` layout the Cholesky solves take.
    fn mass_times_positions(&self, rhs: &mut [f64]) {
        let n = self.positions.len();
        for (i, (p, &a)) in self
            .positions
            .iter()
            .zip(&self.geometry.vertex_areas)
            .enumerate()
        {
            for k in 0..3 {
                rhs[k * n + i] = a * p[k];
            }
        }
    }

    /// Copy a solved column-major `n × 3` block back into the positions.
    fn set_positions(&mut self, solution: &[f64]) {
        let n = self.positions.len();
        for (i, p) in self.positions.iter_mut().enumerate() {
            *p = [solution[i], solution[n + i], solution[2 * n + i]];
        }
    }

    /// After the positions moved: refuse non-finite results, apply the scale policy, refresh
    /// the geometry and report the metrics of the new surface.
    pub(super) fn finish_step(
        &mut self,
        start: Instant,
        method: &str,
    ) -> Result<StepMetrics, FlowError> {
        if self
            .positions
            .iter()
            .any(|p| !(p[0].is_finite() && p[1].is_finite() && p[2].is_finite()))
        {
            return Err(FlowError::Numerical {
                step: self.step + 1,
                reason: format!("{method} produced non-finite positions"),
            });
        }
        self.geometry.refresh(&self.positions, &self.triangles);
        if let Some(scale) = &mut self.scale {
            scale.restore(
                &mut self.positions,
                &self.triangles,
                &self.geometry.vertex_areas,
            );
            self.geometry.refresh(&self.positions, &self.triangles);
        }
        self.step += 1;
        Ok(self.reporter.report(
            self.step,
            &self.positions,
            &self.triangles,
            &self.geometry,
            0.0,
            0.0,
            start,
        ))
    }

    /// [`Retry::restore`] for every classic flow.
    pub(super) fn restore(&mut self, positions: &[[f64; 3]], step: usize) {
        self.positions.copy_from_slice(positions);
        self.geometry.refresh(&self.positions, &self.triangles);
        self.step = step;
    }

    fn numerical(&self, reason: String) -> FlowError {
        FlowError::Numerical {
            step: self.step + 1,
            reason,
        }
    }
}

/// `R² = A / 4π`, the squared radius of the sphere with the surface's area: the length scale
/// that makes the time steps of the classic flows unitless.
fn squared_radius(geometry: &GeometryCache) -> f64 {
    geometry.total_area() / (4.0 * std::f64::consts::PI)
}

/// Conformalized mean curvature flow (Kazhdan, Solomon, Ben-Chen 2012; the paper's Figure 17
/// (E) and Figure 6): backward Euler `(M_t + h L₀) f' = M_t f`, with the cotan Laplacian `L₀`
/// of the **input** surface and the barycentric mass `M_t` of the current one. Freezing the
/// stiffness removes the pinching singularities of mean curvature flow, and for spherical
/// topology the flow converges to a conformal map onto a round sphere (conformal only in the
/// limit: intermediate steps have visible distortion, §6.4.2). τ is unitless as for
/// [`ImplicitMeanCurvatureFlow`]: `h = τ · A / 4π`. The scale policy restores each
/// component's area and centroid after every step.
///
/// Only closed genus-0 surfaces are accepted: Kazhdan et al. derive the flow for the sphere,
/// and on other topologies it has no round limit to converge to (§6.4.2: "it applies only to
/// surfaces with spherical topology").
pub struct ConformalizedMeanCurvatureFlow {
    surface: ClassicSurface,
    tau: f64,
    pattern: BlockPattern,
    /// `L₀` on `pattern`, assembled once from the input cotangents.
    initial_laplacian: Vec<f64>,
    values: Vec<f64>,
    cholesky: Cholesky<f64>,
    rhs: Vec<f64>,
}

impl ConformalizedMeanCurvatureFlow {
    pub fn new(mesh: &Mesh, params: &FlowParams) -> Result<Self, FlowError> {
        params.validate()?;
        let topology = Topology::new(mesh);
        for (index, component) in topology.components.iter().enumerate() {
            if component.genus != 0 || !component.is_closed() {
                return Err(FlowError::Unsupported(format!(
                    "conformalized mean curvature flow applies only to spherical topology \
                     (closed, genus 0); component {index} has genus {} and {} boundary loop(s)",
                    component.genus,
                    component.boundary_loops.len()
                )));
            }
        }
        let n = mesh.vertex_count();
        let surface = ClassicSurface::new(
            mesh,
            &topology,
            Some(params.preserve),
            params.deviation_threads(),
        );
        let pattern = BlockPattern::new(n, &mesh.triangles, 1);
        let cholesky = laplacian_solver(&pattern, params)?;
        let mut initial_laplacian = vec![0.0; pattern.nnz()];
        assemble_cotan_laplacian_into(
            &pattern,
            &mesh.triangles,
            &surface.geometry.cotangents,
            1.0,
            &mut initial_laplacian,
        );
        Ok(ConformalizedMeanCurvatureFlow {
            surface,
            tau: params.tau,
            values: vec![0.0; pattern.nnz()],
            initial_laplacian,
            pattern,
            cholesky,
            rhs: vec![0.0; 3 * n],
        })
    }
}

impl Flow for ConformalizedMeanCurvatureFlow {
    fn step(&mut self) -> Result<StepMetrics, FlowError> {
        let start = Instant::now();
        let s = &mut self.surface;
        let h = self.tau * squared_radius(&s.geometry);
        for (v, &l) in self.values.iter_mut().zip(&self.initial_laplacian) {
            *v = h * l;
        }
        add_diagonal(
            &self.pattern,
            s.geometry.vertex_areas.iter().copied(),
            &mut self.values,
        );
        self.cholesky
            .factorize(&self.pattern, &self.values)
            .map_err(|e| s.numerical(format!("M_t + hL_0: {e}")))?;
        s.mass_times_positions(&mut self.rhs);
        self.cholesky.solve_in_place(&mut self.rhs, 3);
        s.set_positions(&self.rhs);
        s.finish_step(start, "conformalized MCF")
    }

    fn positions(&self) -> &[[f64; 3]] {
        &self.surface.positions
    }

    fn initial_metrics(&self) -> StepMetrics {
        self.surface.initial
    }
}

/// A sparse product whose pattern is computed once per flow (connectivity never changes).
struct SparseProduct {
    symbolic: SymbolicSparseColMat<usize>,
    info: SparseMatMulInfo,
    values: Vec<f64>,
}

/// Implicit bi-Laplacian flow, the paper's Figure 17 (H): backward Euler on `ḟ = −Δ²f`
/// (§3: Willmore flow with the dependence of Δ on f ignored), `(M + h L M⁻¹ L) f' = M f` with
/// the PSD cotan Laplacian `L` and barycentric mass `M` of the current surface (`−Δ = M⁻¹L`).
/// `Δ²` has units of length⁻⁴, so `h = τ · (A / 4π)²`: on a unit sphere a degree-l spherical
/// harmonic shrinks by `1 / (1 + τ (l(l+1))²)` per step. The scale policy restores each
/// component's area and centroid after every step, as for [`ImplicitMeanCurvatureFlow`].
/// Backward Euler does not make this nonlinear flow unconditionally stable (§3): on a bumpy
/// sphere (`bumpy_sphere(3, 0.15)`) τ = 0.01 lowers W monotonically to the round sphere's in
/// 10 steps, while τ = 0.5 lowers it for two steps and then degenerates (measured).
///
/// `L M⁻¹ L` couples two-ring neighbours: its pattern (the symbolic product `L·L`) and the
/// Cholesky analysis are built once, the numeric product and factorization every step, as in
/// the spectral filter (`super::filter`).
pub struct ImplicitBilaplacianFlow {
    surface: ClassicSurface,
    tau: f64,
    /// The one-ring pattern of `L`.
    pattern: BlockPattern,
    laplacian: Vec<f64>,
    /// `M⁻¹ L` on the one-ring pattern.
    scaled: Vec<f64>,
    /// `L M⁻¹ L` on the two-ring pattern.
    product: SparseProduct,
    /// `M + h L M⁻¹ L` on the two-ring pattern, and where each diagonal entry lives in it.
    system: Vec<f64>,
    diagonal: Vec<usize>,
    cholesky: Cholesky<f64>,
    matmul_scratch: MemBuffer,
    rhs: Vec<f64>,
}

impl ImplicitBilaplacianFlow {
    pub fn new(mesh: &Mesh, params: &FlowParams) -> Result<Self, FlowError> {
        params.validate()?;
        let setup_error = |reason: String| FlowError::Numerical { step: 0, reason };
        let topology = Topology::new(mesh);
        let n = mesh.vertex_count();
        let surface = ClassicSurface::new(
            mesh,
            &topology,
            Some(params.preserve),
            params.deviation_threads(),
        );
        let pattern = BlockPattern::new(n, &mesh.triangles, 1);
        let one_ring = pattern.symbolic.as_ref();
        let (symbolic, info) = sparse_sparse_matmul_symbolic(one_ring, one_ring)
            .map_err(|e| setup_error(format!("pattern of L M⁻¹ L: {e:?}")))?;
        let two_ring = symbolic.as_ref();
        let mut diagonal = Vec::with_capacity(n);
        for j in 0..n {
            let range = two_ring.col_ptr()[j]..two_ring.col_ptr()[j + 1];
            let k = two_ring.row_idx()[range.clone()]
                .binary_search(&j)
                .map_err(|_| setup_error("L M⁻¹ L misses a diagonal entry".into()))?;
            diagonal.push(range.start + k);
        }
        let cholesky = Cholesky::<f64>::analyze_pattern(two_ring, 3)
            .map_err(|e| setup_error(e.to_string()))?;
        let matmul_scratch = MemBuffer::try_new(
            sparse_sparse_matmul_numeric_scratch::<usize, f64>(two_ring, Par::Seq),
        )
        .map_err(|_| setup_error("out of memory for the L M⁻¹ L product".into()))?;
        let product_len = two_ring.row_idx().len();
        Ok(ImplicitBilaplacianFlow {
            surface,
            tau: params.tau,
            laplacian: vec![0.0; pattern.nnz()],
            scaled: vec![0.0; pattern.nnz()],
            pattern,
            product: SparseProduct {
                symbolic,
                info,
                values: vec![0.0; product_len],
            },
            system: vec![0.0; product_len],
            diagonal,
            cholesky,
            matmul_scratch,
            rhs: vec![0.0; 3 * n],
        })
    }
}

impl ImplicitBilaplacianFlow {
    /// Refill `system` with `M + h L M⁻¹ L` on the current surface, `h = τ R⁴`.
    fn assemble_system(&mut self) {
        let s = &self.surface;
        let r2 = squared_radius(&s.geometry);
        let h = self.tau * r2 * r2;
        assemble_cotan_laplacian_into(
            &self.pattern,
            &s.triangles,
            &s.geometry.cotangents,
            1.0,
            &mut self.laplacian,
        );
        // M⁻¹L: row i divided by A_i. A vertex of zero area would make this infinite; the
        // factorization then fails and reports it instead of producing garbage.
        let rows = self.pattern.symbolic.row_idx();
        for ((m, &l), &r) in self.scaled.iter_mut().zip(&self.laplacian).zip(rows) {
            *m = l / s.geometry.vertex_areas[r];
        }
        let one_ring = self.pattern.symbolic.as_ref();
        let p = &mut self.product;
        sparse_sparse_matmul_numeric(
            SparseColMatMut::new(p.symbolic.as_ref(), &mut p.values),
            Accum::Replace,
            SparseColMatRef::new(one_ring, &self.laplacian),
            SparseColMatRef::new(one_ring, &self.scaled),
            1.0,
            &p.info,
            Par::Seq,
            MemStack::new(&mut self.matmul_scratch),
        );
        for (a, &b) in self.system.iter_mut().zip(&p.values) {
            *a = h * b;
        }
        for (&d, &area) in self.diagonal.iter().zip(&s.geometry.vertex_areas) {
            self.system[d] += area;
        }
    }
}

impl Flow for ImplicitBilaplacianFlow {
    fn step(&mut self) -> Result<StepMetrics, FlowError> {
        let start = Instant::now();
        self.assemble_system();
        let s = &mut self.surface;
        self.cholesky
            .factorize_matrix(SparseColMatRef::new(
                self.product.symbolic.as_ref(),
                &self.system,
            ))
            .map_err(|e| s.numerical(format!("M + h L M⁻¹ L: {e}")))?;
        s.mass_times_positions(&mut self.rhs);
        self.cholesky.solve_in_place(&mut self.rhs, 3);
        s.set_positions(&self.rhs);
        s.finish_step(start, "implicit bi-Laplacian flow")
    }

    fn positions(&self) -> &[[f64; 3]] {
        &self.surface.positions
    }

    fn initial_metrics(&self) -> StepMetrics {
        self.surface.initial
    }
}

/// Taubin's default pass-band frequency `k_PB = 1/λ + 1/μ` for λ = 0.5, μ = −0.53 (Taubin
/// 1995 recommends 0.01–0.1 and uses values of this size): low frequencies below it are kept,
/// which is why λ|μ smoothing does not shrink.
const TAUBIN_PASS_BAND: f64 = 1.0 / 0.5 - 1.0 / 0.53;

/// Taubin λ|μ smoothing (Taubin 1995; the paper's Figure 17 (C), explicit bi-Laplacian flow
/// when λ = −μ, §3): `f ← f + λ K f`, then `f ← f + μ K f`, with the **uniform** ("umbrella")
/// Laplacian `(K f)_i = (1/|N(i)|) Σ_{j∈N(i)} f_j − f_i`. Uniform weights are Taubin's own
/// choice; with them the eigenvalues k of `−K` lie in [0, 2] on any mesh, so stability is a
/// property of (λ, μ) alone (cotan weights can be negative and have no such bound). One
/// [`Flow::step`] is one λ pass and one μ pass; a frequency k is scaled by
/// `(1 − λk)(1 − μk)`.
///
/// Through [`FlowParams`], λ = τ (unitless: the fraction of the way to the neighbours'
/// average) and μ keeps Taubin's pass band `k_PB = 1/λ + 1/μ` fixed at its value for the
/// defaults λ = 0.5, μ = −0.53 (τ = 0.5 gives exactly those). The scale policy is **not**
/// applied: keeping the volume without rescaling is what λ|μ is for, and rescaling would
/// hide what the comparison is meant to show. So `preserve` `area` (the default) and `none`
/// both leave it alone, and `volume` is refused ([`FlowError::Unsupported`]) rather than
/// quietly ignored.
pub struct TaubinSmoothing {
    surface: ClassicSurface,
    lambda: f64,
    mu: f64,
    /// Vertex adjacency in CSR form (each neighbour once).
    neighbour_ptr: Vec<usize>,
    neighbours: Vec<usize>,
    /// `K f`, computed for all vertices before any moves (a Jacobi pass, as Taubin does).
    umbrella: Vec<[f64; 3]>,
}

/// The smallest Taubin λ (= τ) a flow takes ([`FlowParams::validate`]): below it a pass
/// moves a unit mesh by less than rounding, and μ is no longer distinguishable from −λ.
pub const MIN_TAUBIN_TAU: f64 = 1e-9;

/// MeshLab's Taubin defaults ([`TaubinSmoothing::meshlab_default`]).
pub const MESHLAB_LAMBDA: f64 = 0.5;
pub const MESHLAB_MU: f64 = -0.53;
pub const MESHLAB_ITERATIONS: usize = 10;

impl TaubinSmoothing {
    /// λ = τ and μ from the default pass band (see the type's docs).
    pub fn new(mesh: &Mesh, params: &FlowParams) -> Result<Self, FlowError> {
        // `FlowParams::validate` refuses `preserve: volume` here: λ|μ is never rescaled.
        params.validate()?;
        let lambda = params.tau;
        if lambda * TAUBIN_PASS_BAND >= 1.0 {
            return Err(FlowError::InvalidParameter {
                name: "tau",
                reason: format!(
                    "Taubin λ = τ must be below 1/k_PB = {:.3} (so that μ < 0), got {lambda}",
                    1.0 / TAUBIN_PASS_BAND
                ),
            });
        }
        let mu = -lambda / (1.0 - TAUBIN_PASS_BAND * lambda);
        Self::build(mesh, lambda, mu, params.deviation_threads())
    }

    /// Explicit factors: `λ > 0`, `μ < −λ` (Taubin's condition for a positive pass band), and
    /// `(1 − 2λ)(1 − 2μ) ≥ −1` so the highest uniform-Laplacian frequency (k = 2) is not
    /// amplified.
    pub fn with_factors(mesh: &Mesh, lambda: f64, mu: f64) -> Result<Self, FlowError> {
        Self::build(mesh, lambda, mu, None)
    }

    /// MeshLab's default Taubin smoothing (10 iterations of λ 0.5, μ −0.53) of `mesh`: the
    /// yardstick the denoising benchmarks and tests measure against (issue 39).
    pub fn meshlab_default(mesh: &Mesh) -> Result<Vec<[f64; 3]>, FlowError> {
        let mut flow = Self::with_factors(mesh, MESHLAB_LAMBDA, MESHLAB_MU)?;
        for _ in 0..MESHLAB_ITERATIONS {
            flow.step()?;
        }
        Ok(flow.positions().to_vec())
    }

    fn build(
        mesh: &Mesh,
        lambda: f64,
        mu: f64,
        deviation_threads: Option<usize>,
    ) -> Result<Self, FlowError> {
        if !(lambda.is_finite() && lambda > 0.0) {
            return Err(FlowError::InvalidParameter {
                name: "lambda",
                reason: format!("must be a positive finite number, got {lambda}"),
            });
        }
        if !(mu.is_finite() && mu < -lambda) {
            return Err(FlowError::InvalidParameter {
                name: "mu",
                reason: format!("must be finite and below −λ = {}, got {mu}", -lambda),
            });
        }
        let highest = (1.0 - 2.0 * lambda) * (1.0 - 2.0 * mu);
        if highest.abs() > 1.0 {
            return Err(FlowError::InvalidParameter {
                name: "lambda",
                reason: format!(
                    "λ = {lambda}, μ = {mu} scale the highest frequency by {highest:.3}: \
                     explicit smoothing would blow up (|(1 − 2λ)(1 − 2μ)| must be ≤ 1)"
                ),
            });
        }
        let topology = Topology::new(mesh);
        let n = mesh.vertex_count();
        let mut degree = vec![0usize; n];
        for &[a, b] in &topology.edges {
            degree[a] += 1;
            degree[b] += 1;
        }
        let mut neighbour_ptr = Vec::with_capacity(n + 1);
        neighbour_ptr.push(0);
        for d in &degree {
            neighbour_ptr.push(neighbour_ptr[neighbour_ptr.len() - 1] + d);
        }
        let mut fill = neighbour_ptr[..n].to_vec();
        let mut neighbours = vec![0usize; 2 * topology.edges.len()];
        // `Topology::edges` lists each undirected edge once, so each neighbour appears once.
        for &[a, b] in &topology.edges {
            neighbours[fill[a]] = b;
            fill[a] += 1;
            neighbours[fill[b]] = a;
            fill[b] += 1;
        }
        Ok(TaubinSmoothing {
            surface: ClassicSurface::new(mesh, &topology, None, deviation_threads),
            lambda,
            mu,
            neighbour_ptr,
            neighbours,
            umbrella: vec![[0.0; 3]; n],
        })
    }

    /// `f ← f + factor · K f` with the uniform Laplacian K.
    fn pass(&mut self, factor: f64) {
        let positions = &mut self.surface.positions;
        for (i, k) in self.umbrella.iter_mut().enumerate() {
            let ring = &self.neighbours[self.neighbour_ptr[i]..self.neighbour_ptr[i + 1]];
            let mut sum = [0.0; 3];
            for &j in ring {
                for c in 0..3 {
                    sum[c] += positions[j][c];
                }
            }
            // Every vertex of a valid mesh lies on a face, so rings are never empty; guard
            // anyway so a hand-built mesh keeps an isolated vertex in place.
            if ring.is_empty() {
                *k = [0.0; 3];
                continue;
            }
            let inv = 1.0 / ring.len() as f64;
            for c in 0..3 {
                k[c] = sum[c] * inv - positions[i][c];
            }
        }
        for (p, k) in positions.iter_mut().zip(&self.umbrella) {
            for c in 0..3 {
                p[c] += factor * k[c];
            }
        }
    }
}

impl Retry for TaubinSmoothing {
    fn tau(&self) -> f64 {
        self.lambda
    }

    /// λ = τ with the pass band `k_PB = 1/λ + 1/μ` of the constructor kept: μ = λ/(k_PB·λ − 1).
    fn set_tau(&mut self, tau: f64) {
        let pass_band = 1.0 / self.lambda + 1.0 / self.mu;
        self.lambda = tau;
        self.mu = tau / (pass_band * tau - 1.0);
    }

    fn restore(&mut self, positions: &[[f64; 3]], step: usize) {
        self.surface.restore(positions, step);
    }
}

impl Flow for TaubinSmoothing {
    fn step(&mut self) -> Result<StepMetrics, FlowError> {
        let start = Instant::now();
        self.pass(self.lambda);
        self.pass(self.mu);
        self.surface.finish_step(start, "Taubin λ|μ smoothing")
    }

    fn positions(&self) -> &[[f64; 3]] {
        &self.surface.positions
    }

    fn initial_metrics(&self) -> StepMetrics {
        self.surface.initial
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::operators::cotan_laplacian_apply_into;
    use crate::mesh::generate::bumpy_sphere;

    /// The assembled `M + h L M⁻¹ L` applied to the positions equals `M f + h L(M⁻¹(L f))`
    /// computed with the matrix-free cotan Laplacian: the product, its scaling and the
    /// diagonal shift are all right.
    #[test]
    fn bilaplacian_system_matches_the_matrix_free_operator() {
        let mesh = bumpy_sphere(2, 0.2);
        let params = FlowParams {
            tau: 0.3,
            ..FlowParams::default()
        };
        let mut flow = ImplicitBilaplacianFlow::new(&mesh, &params).expect("flow");
        flow.assemble_system();
        let g = &flow.surface.geometry;
        let r2 = squared_radius(g);
        let h = params.tau * r2 * r2;
        let n = mesh.vertex_count();
        let mut lf = vec![[0.0; 3]; n];
        cotan_laplacian_apply_into(&mesh.positions, &mesh.triangles, &g.cotangents, &mut lf);
        let scaled: Vec<[f64; 3]> = lf
            .iter()
            .zip(&g.vertex_areas)
            .map(|(v, a)| [v[0] / a, v[1] / a, v[2] / a])
            .collect();
        let mut llf = vec![[0.0; 3]; n];
        cotan_laplacian_apply_into(&scaled, &mesh.triangles, &g.cotangents, &mut llf);
        let a = SparseColMatRef::new(flow.product.symbolic.as_ref(), &flow.system);
        let mut worst = 0.0f64;
        let mut largest = 0.0f64;
        for k in 0..3 {
            let mut ax = vec![0.0; n];
            for j in 0..n {
                for idx in a.col_ptr()[j]..a.col_ptr()[j + 1] {
                    ax[a.row_idx()[idx]] += flow.system[idx] * mesh.positions[j][k];
                }
            }
            for i in 0..n {
                let expected = g.vertex_areas[i] * mesh.positions[i][k] + h * llf[i][k];
                worst = worst.max((ax[i] - expected).abs());
                largest = largest.max(expected.abs());
            }
        }
        assert!(
            worst < 1e-10 * largest,
            "‖A f − (M f + h L M⁻¹ L f)‖∞ = {worst}"
        );
    }
}
