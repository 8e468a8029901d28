//! Conformal Willmore flow in curvature space: Table 1, right column.
//!
//! One step, on the current surface `f` with mean curvature `H`:
//! 1. flow direction `v = −2H` (§6.1: `μ̇ = −2μ`), projected onto the constraints (Table 1
//!    III–IV; §6.2): normals `N^{x,y,z}` (no sphere inversions, App. D) and `1` (total
//!    curvature, App. B), per closed component;
//! 2. `ρ = τ·P(v) = −2τ·P(H)` (docs/algorithm.md §2: with this convention τ has the paper's §4
//!    meaning, `u ← (1 − 2τ)u`, stable for τ < 1);
//! 3. smallest eigenvector of `(D − ρ)λ = γλ` (Eq. 5) by inverse iteration on `X(ρ)`
//!    (App. G), starting from `λ ≡ 1` because the previous surface is the reference;
//! 4. new edges `ẽ = λ̄ e λ`, averaged over each face so every face closes (Table 1 VI);
//! 5. new positions from `L f̃ = ∇·ẽ` (Eq. 6, Table 1 VII);
//! 6. scale policy: each component's centroid and area restored.
//!
//! The sparsity patterns and symbolic factorizations of X and L are built once per flow;
//! every buffer is allocated in [`ConformalFlow::new`], so the step loop does not allocate.

use super::constraints::ConstraintBasis;
use super::dirac::{assemble_dirac_into, sparse_matvec, TriangleAssembly};
use super::dirichlet;
use super::exactness::Exactness;
use super::filter::FilterSolver;
use super::mobius::MobiusBalancing;
use super::prescribed::{PrescribedError, PrescribedSolver, SurfaceState};
use super::scale::ScalePolicy;
use super::{
    Boundary, Flow, FlowError, FlowParams, Precision, PrescribedVectors, Preserve, StepProfile,
};
use crate::geometry::cache::GeometryCache;
use crate::geometry::vec3::{norm2, sub};
use crate::geometry::Quaternion;
use crate::linalg::ordering::{self, Ordering};
use crate::linalg::solver::{
    add_diagonal, assemble_cotan_laplacian_into, BlockPattern, Cholesky, Mixed, NotConverged,
    SolverError,
};
use crate::mesh::topology::Topology;
use crate::mesh::Mesh;
use crate::metrics::{StepMetrics, StepReporter};
use faer::c64;
use std::time::Instant;

/// The factor of the Dirac matrix X: double precision, or single precision solved to double
/// precision by preconditioned conjugate gradients ([`Mixed`]) on large closed surfaces.
enum DiracFactor {
    Double(Box<Cholesky<c64>>),
    Mixed(Box<Mixed>),
}

impl DiracFactor {
    fn set_threads(&mut self, threads: usize) {
        match self {
            DiracFactor::Double(d) => d.set_threads(threads),
            DiracFactor::Mixed(m) => m.set_threads(threads),
        }
    }

    fn triangle_values_mut(&mut self) -> &mut [c64] {
        match self {
            DiracFactor::Double(d) => d.triangle_values_mut(),
            DiracFactor::Mixed(m) => m.triangle_values_mut(),
        }
    }

    fn triangle_slots(&self, nnz: usize) -> Vec<Option<(u32, bool)>> {
        match self {
            DiracFactor::Double(d) => d.triangle_slots(nnz),
            DiracFactor::Mixed(m) => m.triangle_slots(nnz),
        }
    }

    /// Once the assembly has its slots: see [`Cholesky::release_gather`].
    fn release_gather(&mut self) {
        match self {
            DiracFactor::Double(d) => d.release_gather(),
            DiracFactor::Mixed(m) => m.release_gather(),
        }
    }

    fn factorize_triangle(&mut self) -> Result<(), SolverError> {
        match self {
            DiracFactor::Double(d) => d.factorize_triangle(),
            // X changes little from step to step: its last factor may precondition this one.
            DiracFactor::Mixed(m) => m.refresh(true),
        }
    }

    /// One right-hand side.
    fn solve_in_place(&mut self, rhs: &mut [c64]) -> Result<(), NotConverged> {
        match self {
            DiracFactor::Double(d) => {
                d.solve_in_place(rhs, 1);
                Ok(())
            }
            DiracFactor::Mixed(m) => m.solve_in_place(rhs),
        }
    }

    #[cfg(test)]
    fn hermitian_matvec(&self, x: &[c64], y: &mut [c64]) {
        match self {
            DiracFactor::Double(d) => d.hermitian_matvec(x, y),
            DiracFactor::Mixed(m) => m.hermitian_matvec(x, y),
        }
    }

    /// The double-precision factor, which the exactness constraints and the fixed boundary
    /// need (they are never given the mixed one).
    fn double_mut(&mut self) -> Option<&mut Cholesky<c64>> {
        match self {
            DiracFactor::Double(d) => Some(&mut **d),
            DiracFactor::Mixed(_) => None,
        }
    }
}

/// `(a(), b())`, on two threads when `parallel` (a panic in either is re-raised here, as it
/// would be sequentially).
fn join<A: Send, B: Send>(
    parallel: bool,
    a: impl FnOnce() -> A + Send,
    b: impl FnOnce() -> B + Send,
) -> (A, B) {
    if !parallel {
        return (a(), b());
    }
    std::thread::scope(|scope| {
        let first = scope.spawn(a);
        let second = b();
        match first.join() {
            Ok(first) => (first, second),
            Err(panic) => std::panic::resume_unwind(panic),
        }
    })
}

/// Whether X is factored in single precision ([`Mixed`]) on a surface of `n` vertices.
fn mixed_precision_for(n: usize, precision: Precision) -> bool {
    match precision {
        Precision::Auto => n >= MIXED_MIN_VERTICES,
        Precision::Double => false,
        Precision::Mixed => true,
    }
}

/// From this many vertices on, X is factored in single precision ([`Mixed`]) by default.
/// Measured with `willow bench` (issue 14), per try of a step at τ = 0.5: nefertiti (50k
/// vertices, 5 of 9 steps retried) 273 ms mixed against 240 ms double (retried steps move X
/// too far for a kept factor, and a double factor costs only about 4 solves there); the bumpy
/// icosphere of 164k vertices 0.82 s against 2.6 s, of 655k 3.2 s against 20 s.
/// Re-measured at nefertiti with the give-up limits lifted: a factor kept for one step needs
/// 9 or 17 CG iterations (about 24 ms each; over 40 after a rejected try), 14–30 later,
/// against 1–3 for a fresh one, where the single-precision factorization costs about 100 ms;
/// so keeping never pays there, and the fresh mixed step (103 ms factor + 81 ms λ solve)
/// loses to the double one (135 + 34 ms).
pub const MIXED_MIN_VERTICES: usize = 100_000;

/// Diagonal shift of X relative to its mean diagonal, scaled per vertex by relative area:
/// large enough that LLᴴ never meets a non-positive pivot on the constant-quaternion kernel at
/// ρ ≈ 0, small enough that inverse iteration still amplifies the near-null direction
/// (docs/algorithm.md §5, pitfall 4).
const DIRAC_SHIFT: f64 = 1e-9;
/// The same for the Poisson system `L + εM`, whose kernel is the constants per component.
const POISSON_SHIFT: f64 = 1e-10;
/// How many times a failed factorization is retried with a 100× larger shift before the step
/// is reported as a numerical failure.
const SHIFT_RETRIES: usize = 3;
/// Seed of the random 1-forms of Appendix C.1 step I: fixed, so runs are reproducible.
const HARMONIC_SEED: u64 = 0x5749_4C4C_4F57;

pub struct ConformalFlow {
    triangles: Vec<[usize; 3]>,
    positions: Vec<[f64; 3]>,
    tau: f64,
    iterations: usize,
    step: usize,
    vertex_component: Vec<usize>,

    /// The mesh's topology, for the exactness constraints (the only step-time user; dropped
    /// after the setup otherwise: 11 MB at 100k triangles).
    topology: Option<Topology>,
    /// Exactness constraints and period projection (App. C); `None` for genus 0 or when
    /// switched off.
    exactness: Option<Exactness>,
    mobius: Option<MobiusBalancing>,
    /// Vertices of closed components: the total-curvature constraint (App. B) holds there only.
    closed_vertex: Vec<bool>,
    /// Boundary vertices held in place (§6.3.2), with their positions; `None` for a free boundary.
    fixed: Option<Vec<bool>>,
    fixed_positions: Vec<[f64; 3]>,
    /// Prescribed boundary vectors (§6.3.1, CMC with `V = B`); `None` otherwise.
    prescribed: Option<PrescribedSolver>,
    /// Prescribed boundary vectors (not CMC) on a surface with boundary: W may rise while the
    /// boundary turns to its targets, so the safeguard does not require descent.
    turns_boundary: bool,
    /// The Dirichlet right-hand side of the λ solve, kept for its residual.
    solve_rhs: Vec<c64>,
    /// Boundary vertices (any boundary condition), and scratch for averaging onto them.
    boundary_vertex: Option<Vec<bool>>,
    boundary_sums: Vec<f64>,

    geometry: GeometryCache,
    reporter: StepReporter,
    scale: ScalePolicy,
    constraints: ConstraintBasis,
    initial: StepMetrics,

    /// X's full block pattern, kept only for a fixed boundary, which assembles into it: every
    /// other step assembles straight into the factor's triangle, so the pattern (23 MB at
    /// 100k triangles) goes after the setup (the rare fall-back from the mixed factor
    /// rebuilds it).
    dirac_pattern: Option<BlockPattern>,
    /// X on the full pattern, for the Dirichlet solve of a fixed boundary only; every other
    /// solve assembles X straight into the factor's triangle through `dirac_assembly`.
    dirac_values: Vec<c64>,
    dirac_assembly: TriangleAssembly,
    dirac: DiracFactor,
    laplace_pattern: BlockPattern,
    laplace_values: Vec<f64>,
    /// L without its shift, assembled once per step for the filter and the Poisson solve.
    laplace_unshifted: Vec<f64>,
    laplace: Cholesky<f64>,
    filter: Option<FilterSolver>,

    rho: Vec<f64>,
    shift: Vec<f64>,
    lambda: Vec<Quaternion>,
    rhs: Vec<c64>,
    product: Vec<c64>,
    new_edges: Vec<[[f64; 3]; 3]>,
    divergence: Vec<f64>,
    component_norms: Vec<f64>,
    component_areas: Vec<f64>,
    profile: StepProfile,
    /// Where the construction spent its time.
    setup: StepProfile,
    /// The fill-reducing ordering of the vertex graph every factor here uses.
    vertex_fwd: Vec<usize>,
    threads: usize,
}

impl ConformalFlow {
    pub fn new(mesh: &Mesh, params: &FlowParams) -> Result<Self, FlowError> {
        Self::build(mesh, params, None)
    }

    /// The flow with the vertices of `pinned` held exactly where they are, by the Dirichlet
    /// conditions of a fixed boundary (§6.3.2: λ = 1 and the input position there) wherever
    /// the pinned vertices lie: what a region of a larger surface flows with
    /// ([`super::region`]), its surroundings pinned.
    pub(crate) fn with_pinned(
        mesh: &Mesh,
        params: &FlowParams,
        pinned: Vec<bool>,
    ) -> Result<Self, FlowError> {
        Self::build(mesh, params, Some(pinned))
    }

    fn build(
        mesh: &Mesh,
        params: &FlowParams,
        pinned: Option<Vec<bool>>,
    ) -> Result<Self, FlowError> {
        params.validate()?;
        let mut setup = StepProfile::default();
        setup.start();
        let parallel = params.threads > 1;
        let n = mesh.vertex_count();
        // One ordering of the vertex graph for X and L (and the fallback's double X). It is
        // the longest part of the setup on large meshes, and needs only the graph: with
        // threads to spare it runs while the rest is built.
        let laplace_pattern = BlockPattern::new(n, &mesh.triangles, 1);
        let (graph_ptr, graph_rows) = laplace_pattern.vertex_graph();
        let pending_order = ordering::Pending::start(
            Ordering::for_vertices(n),
            graph_ptr.to_vec(),
            graph_rows.to_vec(),
            parallel,
        );
        setup.lap("L pattern, ordering started");
        let topology = Topology::new(mesh);
        setup.lap("topology");
        let nf = mesh.face_count();
        let n_components = topology.components.len();
        let vertex_component = topology.vertex_component.clone();
        let exactness = if params.exactness {
            Exactness::new(mesh, &topology, HARMONIC_SEED).map_err(|e| FlowError::Numerical {
                step: 0,
                reason: e.to_string(),
            })?
        } else {
            None
        };
        setup.lap("exactness");
        let form_count = exactness.as_ref().map_or(0, |h| h.form_count());
        let closed_vertex: Vec<bool> = vertex_component
            .iter()
            .map(|&c| topology.components[c].is_closed())
            .collect();
        let fixed = pinned.or_else(|| {
            (params.boundary == Boundary::Fixed && !topology.boundary_loops.is_empty())
                .then(|| topology.boundary_vertex_mask(n))
        });
        let boundary_vertex =
            (!topology.boundary_loops.is_empty()).then(|| topology.boundary_vertex_mask(n));

        let geometry = GeometryCache::new(&mesh.positions, &mesh.triangles);
        setup.lap("geometry");
        let prescribed = match (&params.boundary, topology.boundary_loops.is_empty()) {
            (_, true) | (Boundary::Free | Boundary::Fixed, _) => None,
            (Boundary::Prescribed(spec), false) => Some(spec.clone()),
            (Boundary::Cmc, false) => Some(PrescribedVectors::default()),
        };
        let prescribed = match prescribed {
            Some(spec) => Some(
                PrescribedSolver::new(
                    &spec,
                    &topology,
                    &mesh.positions,
                    &mesh.triangles,
                    &geometry.normals,
                    n_components,
                )
                .map_err(|e| match e {
                    PrescribedError::Solver(reason) => FlowError::Numerical { step: 0, reason },
                    other => FlowError::InvalidParameter {
                        name: "boundary",
                        reason: other.to_string(),
                    },
                })?,
            ),
            None => None,
        };
        // A fixed boundary pins its components' position and size, and the step skips the
        // scale policy altogether (see `step`): a volume asked for alongside would silently
        // not be kept on the closed components either.
        if fixed.is_some() && params.preserve == Preserve::Volume {
            return Err(FlowError::Unsupported(
                "preserve `volume` with a fixed boundary: the fixed boundary already pins \
                 position and size, and the flow does not rescale"
                    .into(),
            ));
        }
        let mut reporter = StepReporter::new(
            &mesh.positions,
            &mesh.triangles,
            &topology,
            params.measures_deviation(),
        );
        let scale = ScalePolicy::new(
            params.preserve,
            &topology,
            &mesh.positions,
            &mesh.triangles,
            &geometry.vertex_areas,
        );
        let topology = exactness.is_some().then_some(topology);
        setup.lap("reporter, scale");
        let numerical = |e: SolverError| FlowError::Numerical {
            step: 0,
            reason: e.to_string(),
        };
        let dirac_pattern = BlockPattern::new(n, &mesh.triangles, 2);
        setup.lap("X pattern");
        let (vertex_fwd, _) = pending_order.finish().map_err(|e| FlowError::Numerical {
            step: 0,
            reason: e.to_string(),
        })?;
        setup.lap("vertex ordering (rest)");
        // The two analyses are independent once the vertex graph is ordered: with threads to
        // spare they run side by side (at 1.3M triangles the setup is mostly these; issue 14).
        // Single precision only where X is the one matrix factored: the exactness constraints
        // solve with X₀ (singular up to the shift) and a fixed boundary factors a modified X.
        let mixed = exactness.is_none()
            && fixed.is_none()
            && prescribed.is_none()
            && mixed_precision_for(n, params.precision);
        // X's full pattern serves the analysis and the assembly's slots; only a fixed boundary
        // assembles into it later, so elsewhere it (and the factor's gather table) goes as
        // soon as the assembly is built, before L's analysis on one thread.
        let keep_pattern = fixed.is_some();
        let vertex_fwd_ref = &vertex_fwd;
        let analyze_dirac = move || -> Result<_, SolverError> {
            let vertex_fwd = vertex_fwd_ref;
            let mut dirac = if mixed {
                let mut mixed = Mixed::analyze(&dirac_pattern, vertex_fwd)?;
                mixed.set_quaternionic();
                DiracFactor::Mixed(Box::new(mixed))
            } else {
                let mut double = Cholesky::<c64>::analyze_with_vertex_order(
                    &dirac_pattern,
                    form_count.max(1),
                    vertex_fwd,
                )?;
                double.set_quaternionic();
                double.release_triangle();
                DiracFactor::Double(Box::new(double))
            };
            dirac.set_threads(params.threads);
            let assembly = TriangleAssembly::new(
                &dirac_pattern,
                &mesh.triangles,
                &dirac.triangle_slots(dirac_pattern.nnz()),
            )?;
            if !keep_pattern {
                dirac.release_gather();
            }
            Ok((dirac, assembly, keep_pattern.then_some(dirac_pattern)))
        };
        let analyze_laplace = || -> Result<Cholesky<f64>, SolverError> {
            let mut laplace =
                Cholesky::<f64>::analyze_with_vertex_order(&laplace_pattern, 3, &vertex_fwd)?;
            laplace.set_threads(params.threads);
            laplace.release_triangle();
            Ok(laplace)
        };
        let (dirac_parts, laplace) = join(parallel, analyze_dirac, analyze_laplace);
        let (dirac, dirac_assembly, dirac_pattern) = dirac_parts.map_err(numerical)?;
        let laplace = laplace.map_err(numerical)?;
        let dirac_values = match &dirac_pattern {
            Some(pattern) => vec![c64::new(0.0, 0.0); pattern.nnz()],
            None => Vec::new(),
        };
        setup.lap("X and L analysis");
        let filter = match params.filter {
            Some(f) => Some(FilterSolver::new(&laplace_pattern, f).map_err(|e| {
                FlowError::InvalidParameter {
                    name: "filter",
                    reason: e.to_string(),
                }
            })?),
            None => None,
        };
        let initial = reporter.initial(&mesh.positions, &mesh.triangles, &geometry);
        Ok(ConformalFlow {
            triangles: mesh.triangles.clone(),
            positions: mesh.positions.clone(),
            tau: params.tau,
            threads: params.threads,
            iterations: params.iterations,
            step: 0,
            constraints: ConstraintBasis::new(
                vertex_component.clone(),
                n_components,
                4 + 3 * form_count,
            ),
            mobius: params
                .mobius_balancing
                .then(|| MobiusBalancing::new(&geometry.vertex_areas, n_components)),
            exactness,
            topology,
            closed_vertex,
            fixed_positions: if fixed.is_some() {
                mesh.positions.clone()
            } else {
                Vec::new()
            },
            solve_rhs: if fixed.is_some() {
                vec![c64::new(0.0, 0.0); 2 * n]
            } else {
                Vec::new()
            },
            fixed,
            turns_boundary: prescribed.is_some()
                && matches!(params.boundary, Boundary::Prescribed(_)),
            prescribed,
            boundary_sums: if boundary_vertex.is_some() {
                vec![0.0; 2 * n]
            } else {
                Vec::new()
            },
            boundary_vertex,
            vertex_component,
            geometry,
            reporter,
            scale,
            initial,
            dirac_values,
            dirac_assembly,
            dirac_pattern,
            dirac,
            laplace_values: vec![0.0; laplace_pattern.nnz()],
            laplace_unshifted: vec![0.0; laplace_pattern.nnz()],
            filter,
            laplace_pattern,
            laplace,
            rho: vec![0.0; n],
            shift: vec![0.0; n],
            lambda: vec![Quaternion::ONE; n],
            rhs: vec![c64::new(0.0, 0.0); 2 * n],
            product: vec![c64::new(0.0, 0.0); 2 * n],
            new_edges: vec![[[0.0; 3]; 3]; nf],
            divergence: vec![0.0; 3 * n],
            component_norms: vec![0.0; n_components],
            component_areas: vec![0.0; n_components],
            profile: StepProfile::default(),
            setup,
            vertex_fwd,
        })
    }

    /// Table 1 steps I–V: `ρ = −2τ·P(H)`, plus Möbius balancing when asked.
    fn curvature_change(&mut self) -> Result<(), FlowError> {
        self.constraints.clear();
        if self.fixed.is_none() {
            let g = &self.geometry;
            let closed = &self.closed_vertex;
            // Prescribed boundary vectors (§6.3.1) change which curvature changes can be
            // integrated on a component with boundary. The constant one cannot: with `V = B`
            // fixed along the boundary, a uniform ρ would change the annulus' or disk's
            // conformal shape, so the λ problem has no good solution and the flow drifts
            // (measured: W rising step after step on a bumpy hemisphere). Projecting `1` out
            // there too, as App. B does for closed surfaces, leaves the flow only the
            // non-constant part of H to remove, so its fixed points are the CMC surfaces the
            // paper promises for `V = B`. Sphere inversions, which `N` excludes on closed
            // components (App. D), do not respect the prescribed boundary anyway; keeping
            // `N` out there too held H away from constant (std/mean 0.089 vs 0.055 after 10
            // steps on the same hemisphere).
            let prescribed = self.prescribed.is_some();
            for axis in 0..3 {
                self.constraints.push_with(&g.vertex_areas, |f| {
                    for ((fi, n), &c) in f.iter_mut().zip(&g.normals).zip(closed) {
                        *fi = if c || !prescribed { n[axis] } else { 0.0 };
                    }
                });
            }
            // Total curvature is conserved on closed components (App. B integrates over a
            // surface without boundary), and held under prescribed boundary vectors (above).
            self.constraints.push_with(&g.vertex_areas, |f| {
                for (fi, &c) in f.iter_mut().zip(closed) {
                    *fi = if c || prescribed { 1.0 } else { 0.0 };
                }
            });
        }
        self.exactness_constraints()?;
        let g = &self.geometry;
        assemble_cotan_laplacian_into(
            &self.laplace_pattern,
            &self.triangles,
            &g.cotangents,
            1.0,
            &mut self.laplace_unshifted,
        );
        for (r, h) in self.rho.iter_mut().zip(&g.mean_curvature) {
            *r = -2.0 * h;
        }
        if let Some(boundary) = &self.boundary_vertex {
            // At a boundary vertex the cotan formula measures the boundary curve's bending
            // (the conormal term), not the surface's mean curvature; a curved boundary then
            // gets a spurious, large H that blows the flow up. Take the average over the
            // vertex's interior neighbours instead.
            let (sums, counts) = self.boundary_sums.split_at_mut(self.rho.len());
            sums.fill(0.0);
            counts.fill(0.0);
            for tri in &self.triangles {
                for &b in tri {
                    if boundary[b] {
                        for &i in tri {
                            if !boundary[i] {
                                sums[b] += self.rho[i];
                                counts[b] += 1.0;
                            }
                        }
                    }
                }
            }
            for ((r, (&s, &c)), &is_boundary) in self
                .rho
                .iter_mut()
                .zip(sums.iter().zip(counts.iter()))
                .zip(boundary)
            {
                if is_boundary {
                    *r = if c > 0.0 { s / c } else { 0.0 };
                }
            }
        }
        if let Some(filter) = &mut self.filter {
            // §4 / docs/algorithm.md §3: filter the direction before projecting it.
            filter
                .apply(
                    &self.laplace_pattern,
                    &self.laplace_unshifted,
                    &g.vertex_areas,
                    &mut self.rho,
                )
                .map_err(|e| FlowError::Numerical {
                    step: self.step + 1,
                    reason: e.to_string(),
                })?;
        }
        self.constraints.project(&mut self.rho, &g.vertex_areas);
        if let Some(mobius) = &mut self.mobius {
            // App. E: added after the inversion constraint has been projected out (otherwise
            // it would be removed again); it lies in span{N^x, N^y, N^z}, which is orthogonal
            // to the remaining constraints, so projecting those again would change nothing.
            mobius.add_direction(
                &self.positions,
                g,
                &self.vertex_component,
                self.tau,
                &mut self.rho,
            );
        }
        for r in &mut self.rho {
            *r *= self.tau;
        }
        Ok(())
    }

    /// Appendix C.1 on the current surface (see [`Exactness::push_constraints`]): X₀ is
    /// factored once for the 2g solves, in the same factor storage that X(ρ) uses next.
    fn exactness_constraints(&mut self) -> Result<(), FlowError> {
        if self.exactness.is_none() {
            return Ok(());
        }
        self.rho.fill(0.0);
        self.factor_dirac(false)?;
        let step = self.step + 1;
        let g = &self.geometry;
        if let Some(exactness) = self.exactness.as_mut() {
            exactness
                .push_constraints(
                    &self.positions,
                    &self.triangles,
                    self.topology.as_ref().ok_or_else(|| FlowError::Numerical {
                        step,
                        reason: "the exactness constraints need the topology".into(),
                    })?,
                    &g.face_areas,
                    &g.vertex_areas,
                    self.dirac
                        .double_mut()
                        .ok_or_else(|| FlowError::Numerical {
                            step,
                            reason: "the exactness constraints need the double-precision factor"
                                .into(),
                        })?,
                    &mut self.constraints,
                )
                .map_err(|e| FlowError::Numerical {
                    step,
                    reason: e.to_string(),
                })?;
        }
        Ok(())
    }

    /// Assemble `X(ρ)` for the current `ρ` with its diagonal shift and factor it, retrying
    /// with a larger shift if a pivot is not positive.
    fn factor_dirac(&mut self, dirichlet: bool) -> Result<(), FlowError> {
        let g = &self.geometry;
        let n = self.positions.len();
        let mean_area = g.total_area() / n as f64;
        self.shift.fill(0.0);
        // A fixed boundary: its mask, and X's full pattern (kept for it).
        let fixed = match (dirichlet, self.fixed.as_deref()) {
            (true, Some(fixed)) => Some((
                fixed,
                self.dirac_pattern
                    .as_ref()
                    .ok_or_else(|| FlowError::Numerical {
                        step: self.step + 1,
                        reason: "a fixed boundary needs the full pattern of X".into(),
                    })?,
            )),
            _ => None,
        };
        let mean_diagonal = match fixed {
            None => self.dirac_assembly.assemble(
                &self.positions,
                &self.triangles,
                &g.face_areas,
                &self.rho,
                self.dirac.triangle_values_mut(),
            ),
            Some((fixed, pattern)) => {
                let mean_diagonal = assemble_dirac_into(
                    pattern,
                    &self.positions,
                    &self.triangles,
                    &g.face_areas,
                    &self.rho,
                    &self.shift,
                    &mut self.dirac_values,
                );
                // λ = 1 on the boundary: the boundary keeps its tangents (§6.3.2 with the
                // input boundary as target).
                self.solve_rhs.fill(c64::new(0.0, 0.0));
                dirichlet::apply_complex(
                    pattern,
                    &mut self.dirac_values,
                    fixed,
                    |_| Quaternion::ONE.to_complex_column(),
                    Some(&mut self.solve_rhs[..]),
                );
                mean_diagonal
            }
        };
        self.profile.lap("X assembly");
        // X is dimensionless (|e|²/A and Aρ² are scale-free), so the shift is relative to its
        // mean diagonal; weighting by relative vertex area makes it a multiple of the mass M.
        // A failed factorization adds more shift on the diagonal, without reassembling.
        let mut attempt = 0;
        loop {
            let eps = DIRAC_SHIFT * 100f64.powi(attempt as i32) * mean_diagonal;
            for (v, (s, &a)) in self.shift.iter_mut().zip(&g.vertex_areas).enumerate() {
                let target = eps * a / mean_area;
                let add = target - *s;
                match fixed {
                    None => {
                        self.dirac_assembly.add_to_diagonal(
                            v,
                            add,
                            self.dirac.triangle_values_mut(),
                        );
                    }
                    Some((fixed, pattern)) if !fixed[v] => {
                        let slot = pattern.diagonal_slot(v);
                        let add = c64::new(add, 0.0);
                        self.dirac_values[pattern.entry(slot, v, 0, 0)] += add;
                        self.dirac_values[pattern.entry(slot, v, 1, 1)] += add;
                    }
                    Some(_) => continue,
                }
                *s = target;
            }
            let factored = match (fixed, self.dirac.double_mut()) {
                (None, _) => self.dirac.factorize_triangle(),
                (Some((_, pattern)), Some(double)) => double.factorize(pattern, &self.dirac_values),
                (Some(_), None) => Err(SolverError::Symbolic(
                    "a fixed boundary needs the double-precision factor".into(),
                )),
            };
            match factored {
                Ok(()) => {
                    self.profile.lap("X factor");
                    return Ok(());
                }
                // Rounded to single precision, X may lose a pivot that double precision keeps:
                // the double factor decides, before any extra shift changes the problem.
                Err(_) if matches!(self.dirac, DiracFactor::Mixed(_)) => {
                    self.fall_back_to_double()?;
                    return self.factor_dirac(dirichlet);
                }
                Err(e) if attempt >= SHIFT_RETRIES => {
                    return Err(FlowError::Numerical {
                        step: self.step + 1,
                        reason: format!("Dirac matrix X: {e}"),
                    })
                }
                Err(_) => attempt += 1,
            }
        }
    }

    /// Replace the mixed-precision factor of X by the double-precision one for the rest of the
    /// flow (same ordering and triangle layout, so the assembly is rebuilt identically).
    fn fall_back_to_double(&mut self) -> Result<(), FlowError> {
        let numerical = |e: SolverError| FlowError::Numerical {
            step: self.step + 1,
            reason: e.to_string(),
        };
        // Rebuilt where the setup did not keep it (once a flow at most: tens of milliseconds
        // at 100k triangles).
        let rebuilt;
        let pattern = match &self.dirac_pattern {
            Some(pattern) => pattern,
            None => {
                rebuilt = BlockPattern::new(self.positions.len(), &self.triangles, 2);
                &rebuilt
            }
        };
        if let DiracFactor::Mixed(m) = &mut self.dirac {
            m.release();
        }
        let threads = self.threads;
        let mut double = Cholesky::<c64>::analyze_with_vertex_order(pattern, 1, &self.vertex_fwd)
            .map_err(numerical)?;
        double.set_quaternionic();
        double.release_triangle();
        self.dirac = DiracFactor::Double(Box::new(double));
        self.dirac.set_threads(threads);
        self.dirac_assembly = TriangleAssembly::new(
            pattern,
            &self.triangles,
            &self.dirac.triangle_slots(pattern.nnz()),
        )
        .map_err(numerical)?;
        if self.fixed.is_none() {
            self.dirac.release_gather();
        }
        self.profile.count("fell back to double", 1.0);
        Ok(())
    }

    /// Table 1 step VI: λ by inverse iteration on `X(ρ)`; returns the eigen-residual.
    fn solve_lambda(&mut self) -> Result<f64, FlowError> {
        if self.fixed.is_some() {
            return self.solve_lambda_dirichlet();
        }
        if let Some(prescribed) = &mut self.prescribed {
            let g = &self.geometry;
            let state = SurfaceState {
                positions: &self.positions,
                triangles: &self.triangles,
                face_areas: &g.face_areas,
                vertex_areas: &g.vertex_areas,
                normals: &g.normals,
                vertex_component: &self.vertex_component,
            };
            return prescribed
                .solve(
                    &state,
                    &self.rho,
                    self.iterations,
                    DIRAC_SHIFT,
                    SHIFT_RETRIES,
                    &mut self.lambda,
                )
                .map_err(|e| FlowError::Numerical {
                    step: self.step + 1,
                    reason: format!("prescribed boundary: {e}"),
                });
        }
        self.factor_dirac(false)?;
        self.lambda.fill(Quaternion::ONE);
        for _ in 0..self.iterations.max(1) {
            let g = &self.geometry;
            // Generalized inverse iteration X λ' = M λ: X integrates over faces, so the mass
            // matrix M (barycentric areas) is the matching right-hand side.
            for (i, (l, &a)) in self.lambda.iter().zip(&g.vertex_areas).enumerate() {
                let [z0, z1] = l.scale(a).to_complex_column();
                self.rhs[2 * i] = z0;
                self.rhs[2 * i + 1] = z1;
            }
            // M λ, kept: it gives X λ' for the residual below without a product with X.
            self.product.copy_from_slice(&self.rhs);
            if self.dirac.solve_in_place(&mut self.rhs).is_err() {
                // The single-precision factor is too far from X for CG: solve this step and
                // the rest of the flow with the double one.
                self.fall_back_to_double()?;
                self.factor_dirac(false)?;
                self.rhs.copy_from_slice(&self.product);
                self.solve_rhs_with_dirac()?;
            }
            if let DiracFactor::Mixed(m) = &self.dirac {
                self.profile
                    .count("CG iterations", m.last_iterations as f64);
                self.profile
                    .count("X factor kept", f64::from(u8::from(m.reused())));
            }
            for (i, l) in self.lambda.iter_mut().enumerate() {
                *l = Quaternion::from_complex_column([self.rhs[2 * i], self.rhs[2 * i + 1]]);
            }
            normalize_per_component(
                &mut self.lambda,
                &self.geometry.vertex_areas,
                &self.vertex_component,
                &mut self.component_norms,
                &mut self.component_areas,
            );
        }
        if self.lambda.iter().any(|l| !l.norm2().is_finite()) {
            return Err(FlowError::Numerical {
                step: self.step + 1,
                reason: "the eigenvector λ is not finite".into(),
            });
        }
        let residual = self.eigen_residual();
        self.profile.lap("λ solve");
        if let Some(exactness) = self.exactness.as_mut() {
            // App. C's constraint holds to first order only: cancel the rest of the periods.
            exactness.project_periods(&self.triangles, &self.geometry.face_areas, &mut self.lambda);
            self.profile.lap("period projection");
        }
        Ok(residual)
    }

    /// Eigen-residual `|Xλ − γMλ| / |Xλ|` of the last inverse iteration, with the Rayleigh
    /// quotient γ, on X without its shift. The last solve gave `(X + S) λ' = M λ_prev`, and
    /// λ is λ' scaled by `c` on each component (X does not couple components), so
    /// `X λ = c (M λ_prev − S λ')` up to the solve's rounding, far below any residual the
    /// iteration leaves: no product with X is needed (`rhs` holds λ', `product` M λ_prev).
    fn eigen_residual(&mut self) -> f64 {
        for (i, &c) in self.vertex_component.iter().enumerate() {
            let scale = if self.component_norms[c] > 0.0 {
                (self.component_areas[c] / self.component_norms[c]).sqrt()
            } else {
                1.0
            };
            for k in [2 * i, 2 * i + 1] {
                let x_lambda = (self.product[k] - self.rhs[k] * self.shift[i]) * scale;
                self.rhs[k] *= scale;
                self.product[k] = x_lambda;
            }
        }
        relative_eigen_residual(&self.rhs, &self.product, &self.geometry.vertex_areas)
    }

    /// The same residual from an explicit product with X, to check [`Self::eigen_residual`].
    #[cfg(test)]
    fn eigen_residual_by_product(&mut self) -> f64 {
        for (i, l) in self.lambda.iter().enumerate() {
            let [z0, z1] = l.to_complex_column();
            self.rhs[2 * i] = z0;
            self.rhs[2 * i + 1] = z1;
        }
        self.dirac.hermitian_matvec(&self.rhs, &mut self.product);
        for (i, &s) in self.shift.iter().enumerate() {
            for k in [2 * i, 2 * i + 1] {
                self.product[k] -= self.rhs[k] * s;
            }
        }
        relative_eigen_residual(&self.rhs, &self.product, &self.geometry.vertex_areas)
    }

    /// `rhs ← X⁻¹ rhs` with the factor as it is.
    fn solve_rhs_with_dirac(&mut self) -> Result<(), FlowError> {
        self.dirac
            .solve_in_place(&mut self.rhs)
            .map_err(|e| FlowError::Numerical {
                step: self.step + 1,
                reason: e.to_string(),
            })
    }

    /// §6.3.2: minimize `|(D − ρ)λ|²` with λ fixed on the boundary, a linear least-squares
    /// problem `X_II λ_I = −X_IB λ_B` rather than an eigenproblem. Returns its relative residual.
    fn solve_lambda_dirichlet(&mut self) -> Result<f64, FlowError> {
        self.factor_dirac(true)?;
        self.rhs.copy_from_slice(&self.solve_rhs);
        self.solve_rhs_with_dirac()?;
        for (i, l) in self.lambda.iter_mut().enumerate() {
            *l = Quaternion::from_complex_column([self.rhs[2 * i], self.rhs[2 * i + 1]]);
        }
        if self.lambda.iter().any(|l| !l.norm2().is_finite()) {
            return Err(FlowError::Numerical {
                step: self.step + 1,
                reason: "the boundary-value solve for λ is not finite".into(),
            });
        }
        let pattern = self
            .dirac_pattern
            .as_ref()
            .ok_or_else(|| FlowError::Numerical {
                step: self.step + 1,
                reason: "a fixed boundary needs the full pattern of X".into(),
            })?;
        sparse_matvec(pattern, &self.dirac_values, &self.rhs, &mut self.product);
        let (mut res, mut norm) = (0.0, 0.0);
        for (p, b) in self.product.iter().zip(&self.solve_rhs) {
            res += (p - b).norm_sqr();
            norm += b.norm_sqr();
        }
        Ok(if norm > 0.0 { (res / norm).sqrt() } else { 0.0 })
    }

    /// Table 1 step VII: new edges, their divergence, and the Poisson solve. Returns the closure
    /// residual `|d f̃ − ẽ| / |ẽ|` over all half-edges (unweighted), with `ẽ = ∫ λ̄ e λ` along
    /// the edge: the integrability of the new edges, whichever quadrature feeds the solve.
    fn integrate(&mut self) -> Result<f64, FlowError> {
        let n = self.positions.len();
        let g = &self.geometry;
        self.divergence.fill(0.0);
        for ((tri, cots), edges) in self
            .triangles
            .iter()
            .zip(&g.cotangents)
            .zip(self.new_edges.iter_mut())
        {
            // Each face maps its edges by the face average of λ̄ e λ with λ linear on the face,
            // `T_f(e) = (1/A)∫_f λ̄ e λ dA = (1/12)(s̄ e s + Σ_i λ̄_i e λ_i)`, `s = Σ_i λ_i`
            // (∫ φ_i φ_j = A(1 + δ_ij)/12). With the cotan weights below this is the Galerkin
            // (P1 finite element) weak form of Eq. (6): the L² projection of the target
            // differential λ̄ df λ onto gradients of piecewise linear maps (the cotan matrix is
            // the P1 stiffness matrix; Wardetzky et al. 2007, "Discrete Laplace operators: no
            // free lunch"). T_f is linear in e, so every face closes exactly (Σ e = 0).
            // The edge integral ∫_edge λ̄ e λ (weights ⅓, ⅙, ⅙, ⅓; docs/algorithm.md §6) does
            // not close a face, and on needles the gap is far wider than the face: on
            // botijo_genus5_irregular (a 0.005°/179.6° face, width 1e-4 of its length) it
            // folded the needle out of its plane in one step at τ = 0.02 (one vertex's H
            // 0.7 → −57, W 557 → 628), so W rose at any τ. With T_f, W falls there. (Closing
            // each face's edge integrals with a least-change correction does not help:
            // W 557 → 601 in one step at τ = 0.0125.)
            let l = [
                self.lambda[tri[0]],
                self.lambda[tri[1]],
                self.lambda[tri[2]],
            ];
            // Both maps are linear in e and every λ̄ e λ is `λ.sandwich_matrix()·e`, so each
            // is summed as 3×3 matrices once per face and applied to the three edges.
            let r = [
                l[0].sandwich_matrix(),
                l[1].sandwich_matrix(),
                l[2].sandwich_matrix(),
            ];
            let face_map = mat3_scaled_sum(
                &[(l[0] + l[1] + l[2]).sandwich_matrix(), r[0], r[1], r[2]],
                1.0 / 12.0,
            );
            for c in 0..3 {
                let (ca, cb) = ((c + 1) % 3, (c + 2) % 3);
                let (a, b) = (tri[ca], tri[cb]);
                let e = sub(self.positions[b], self.positions[a]);
                let new_edge = mat3_apply(&face_map, e);
                // The closure residual keeps measuring the edge integral ∫ λ̄ e λ (λ linear:
                // weights ⅓, ⅙, ⅙, ⅓), the paper's new edge: with T_f it would also count
                // the O(h|∇λ|) spread between neighbouring faces' averages. With
                // `s = λ_a + λ_b` the cross terms are `s̄ e s − λ̄_a e λ_a − λ̄_b e λ_b`, so the
                // integral is `(λ̄_a e λ_a + λ̄_b e λ_b + s̄ e s) / 6`.
                let edge_map = mat3_scaled_sum(
                    &[r[ca], r[cb], (l[ca] + l[cb]).sandwich_matrix()],
                    1.0 / 6.0,
                );
                edges[c] = mat3_apply(&edge_map, e);
                let w = 0.5 * cots[c];
                for k in 0..3 {
                    self.divergence[k * n + a] -= w * new_edge[k];
                    self.divergence[k * n + b] += w * new_edge[k];
                }
            }
        }

        self.profile.lap("new edges");
        // L f̃ = ω with the current L, shifted by εM so the constant kernel is harmless
        // (ω sums to zero per component by construction).
        let mean_area = g.total_area() / n as f64;
        let trace: f64 = g.cotangents.iter().map(|c| c[0] + c[1] + c[2]).sum();
        let mut attempt = 0;
        loop {
            self.laplace_values.copy_from_slice(&self.laplace_unshifted);
            let eps = POISSON_SHIFT * 100f64.powi(attempt as i32) * trace / n as f64;
            add_diagonal(
                &self.laplace_pattern,
                g.vertex_areas.iter().map(|&a| eps * a / mean_area),
                &mut self.laplace_values,
            );
            if let Some(fixed) = &self.fixed {
                // Dirichlet Poisson: the boundary stays exactly at its input positions.
                let targets = &self.fixed_positions;
                dirichlet::apply_real(
                    &self.laplace_pattern,
                    &mut self.laplace_values,
                    fixed,
                    |v, axis| targets[v][axis],
                    (attempt == 0).then_some(&mut self.divergence[..]),
                    3,
                );
            }
            match self
                .laplace
                .factorize(&self.laplace_pattern, &self.laplace_values)
            {
                Ok(()) => break,
                Err(e) if attempt >= SHIFT_RETRIES => {
                    return Err(FlowError::Numerical {
                        step: self.step + 1,
                        reason: format!("Laplacian: {e}"),
                    })
                }
                Err(_) => attempt += 1,
            }
        }
        self.profile.lap("L factor");
        self.laplace.solve_in_place(&mut self.divergence, 3);
        self.profile.lap("L solve");
        for (i, p) in self.positions.iter_mut().enumerate() {
            *p = [
                self.divergence[i],
                self.divergence[n + i],
                self.divergence[2 * n + i],
            ];
        }
        if self
            .positions
            .iter()
            .any(|p| !(p[0].is_finite() && p[1].is_finite() && p[2].is_finite()))
        {
            return Err(FlowError::Numerical {
                step: self.step + 1,
                reason: "the Poisson solve produced non-finite positions".into(),
            });
        }

        let (mut gap, mut total) = (0.0, 0.0);
        for (tri, edges) in self.triangles.iter().zip(&self.new_edges) {
            for c in 0..3 {
                let (a, b) = (tri[(c + 1) % 3], tri[(c + 2) % 3]);
                gap += norm2(sub(sub(self.positions[b], self.positions[a]), edges[c]));
                total += norm2(edges[c]);
            }
        }
        Ok(if total > 0.0 {
            (gap / total).sqrt()
        } else {
            0.0
        })
    }
}

/// `|Xλ − γMλ| / |Xλ|` with the Rayleigh quotient `γ = ⟨λ, Xλ⟩ / ⟨λ, Mλ⟩`, for λ and Xλ in
/// complex form (two entries per vertex) and M the vertex areas.
fn relative_eigen_residual(lambda: &[c64], x_lambda: &[c64], areas: &[f64]) -> f64 {
    let (mut x_dot, mut m_dot) = (0.0, 0.0);
    for (k, (l, xl)) in lambda.iter().zip(x_lambda).enumerate() {
        x_dot += (l.conj() * xl).re;
        m_dot += l.norm_sqr() * areas[k / 2];
    }
    let gamma = if m_dot > 0.0 { x_dot / m_dot } else { 0.0 };
    let (mut res, mut xnorm) = (0.0, 0.0);
    for (k, (l, xl)) in lambda.iter().zip(x_lambda).enumerate() {
        res += (xl - l * (gamma * areas[k / 2])).norm_sqr();
        xnorm += xl.norm_sqr();
    }
    if xnorm > 0.0 {
        (res / xnorm).sqrt()
    } else {
        0.0
    }
}

/// `s · Σ m` for 3×3 matrices.
fn mat3_scaled_sum(ms: &[[[f64; 3]; 3]], s: f64) -> [[f64; 3]; 3] {
    let mut out = [[0.0; 3]; 3];
    for m in ms {
        for r in 0..3 {
            for c in 0..3 {
                out[r][c] += m[r][c];
            }
        }
    }
    for row in &mut out {
        for v in row {
            *v *= s;
        }
    }
    out
}

fn mat3_apply(m: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    [
        m[0][0] * v[0] + m[0][1] * v[1] + m[0][2] * v[2],
        m[1][0] * v[0] + m[1][1] * v[1] + m[1][2] * v[2],
        m[2][0] * v[0] + m[2][1] * v[1] + m[2][2] * v[2],
    ]
}

/// Scale λ on each component so that `Σ |λ_i|² A_i = Σ A_i` there: λ is defined up to a
/// quaternion factor per component, and a unit mean keeps edge lengths of the order of the
/// input's before the scale policy restores the area exactly. `norms` and `component_areas`
/// are per-component scratch.
fn normalize_per_component(
    lambda: &mut [Quaternion],
    areas: &[f64],
    vertex_component: &[usize],
    norms: &mut [f64],
    component_areas: &mut [f64],
) {
    norms.fill(0.0);
    component_areas.fill(0.0);
    for ((l, &a), &c) in lambda.iter().zip(areas).zip(vertex_component) {
        norms[c] += l.norm2() * a;
        component_areas[c] += a;
    }
    for (l, &c) in lambda.iter_mut().zip(vertex_component) {
        let factor = if norms[c] > 0.0 {
            (component_areas[c] / norms[c]).sqrt()
        } else {
            1.0
        };
        *l = l.scale(factor);
    }
}

impl super::safeguard::Retry for ConformalFlow {
    fn tau(&self) -> f64 {
        self.tau
    }

    fn set_tau(&mut self, tau: f64) {
        self.tau = tau;
    }

    fn restore(&mut self, positions: &[[f64; 3]], step: usize) {
        self.positions.copy_from_slice(positions);
        self.geometry.refresh(&self.positions, &self.triangles);
        self.step = step;
        // The retry runs at a smaller τ: its X is not the rejected try's.
        if let DiracFactor::Mixed(m) = &mut self.dirac {
            m.refactor_next();
        }
    }

    fn descends(&self) -> bool {
        !self.turns_boundary
    }

    fn conformal(&self) -> bool {
        true
    }
}

impl Flow for ConformalFlow {
    fn step(&mut self) -> Result<StepMetrics, FlowError> {
        let start = Instant::now();
        self.profile.start();
        self.curvature_change()?;
        self.profile.lap("curvature");
        let eigen_residual = self.solve_lambda()?;
        let closure_residual = self.integrate()?;
        self.profile.lap("closure");
        // New geometry, then the scale policy on it, then the geometry again for the metrics
        // and the next step (the rescale changes areas and H).
        self.geometry.refresh(&self.positions, &self.triangles);
        if self.fixed.is_none() {
            // A fixed boundary already pins position and size.
            let scales = self.scale.restore(
                &mut self.positions,
                &self.triangles,
                &self.geometry.vertex_areas,
            );
            self.geometry
                .rescale(&self.triangles, &self.vertex_component, scales);
        }
        self.step += 1;
        self.profile.lap("geometry");
        let metrics = self.reporter.report(
            self.step,
            &self.positions,
            &self.triangles,
            &self.geometry,
            closure_residual,
            eigen_residual,
            start,
        );
        self.profile.lap("metrics");
        Ok(metrics)
    }

    fn positions(&self) -> &[[f64; 3]] {
        &self.positions
    }

    fn profile(&self) -> Option<&StepProfile> {
        Some(&self.profile)
    }

    fn setup_profile(&self) -> Option<&StepProfile> {
        Some(&self.setup)
    }

    fn initial_metrics(&self) -> StepMetrics {
        self.initial
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate::bumpy_sphere;

    /// A try the safeguard rejects is retried at a smaller τ from the restored surface: its
    /// X is not the rejected try's, so the retry factors afresh instead of keeping the
    /// rejected try's single-precision factor (which stalled there). A step that follows
    /// an accepted one may keep its factor.
    #[test]
    fn a_retry_after_a_restore_does_not_keep_the_factor() {
        use super::super::safeguard::Retry;
        let mesh = bumpy_sphere(4, 0.15);
        let params = FlowParams {
            tau: 0.001,
            precision: Precision::Mixed,
            ..FlowParams::default()
        };
        let kept = |flow: &ConformalFlow| {
            flow.profile
                .counts()
                .iter()
                .find(|(name, _)| *name == "X factor kept")
                .map(|&(_, kept)| kept)
        };
        let mut flow = ConformalFlow::new(&mesh, &params).expect("flow");
        flow.step().expect("step");
        let before = flow.positions.clone();
        flow.step().expect("step");
        assert_eq!(kept(&flow), Some(1.0), "a small step keeps the factor");
        // As the safeguard does when it rejects a try: restore, halve τ, try again. (At
        // this τ the kept factor would still precondition the retry: only the restore
        // makes it factor afresh.)
        flow.restore(&before, 1);
        flow.set_tau(0.0005);
        flow.step().expect("retry");
        assert_eq!(
            kept(&flow),
            Some(0.0),
            "the retry kept the rejected try's factor"
        );
        flow.step().expect("step");
        assert_eq!(
            kept(&flow),
            Some(1.0),
            "the step after the retry keeps again"
        );
    }

    /// The switch from the single-precision factor to the double one (taken where single
    /// precision cannot factor or precondition X) continues the same flow: after it, steps
    /// match a flow that was double all along.
    #[test]
    fn falling_back_to_double_precision_continues_the_same_flow() {
        use crate::mesh::generate::{bumpy_sphere, with_noise};
        let mesh = with_noise(bumpy_sphere(4, 0.15), 0.1, 3);
        assert!(mesh.vertex_count() < MIXED_MIN_VERTICES);
        let params = |precision| FlowParams {
            tau: 0.2,
            precision,
            ..FlowParams::default()
        };
        let mut double = ConformalFlow::new(&mesh, &params(Precision::Double)).expect("flow");
        let mut mixed = ConformalFlow::new(&mesh, &params(Precision::Mixed)).expect("flow");
        assert!(matches!(mixed.dirac, DiracFactor::Mixed(_)));
        for step in 0..3 {
            if step == 1 {
                mixed.fall_back_to_double().expect("fall back");
                assert!(matches!(mixed.dirac, DiracFactor::Double(_)));
            }
            let d = double.step().expect("step");
            let m = mixed.step().expect("step");
            let rel = (d.willmore_energy - m.willmore_energy).abs() / d.willmore_energy;
            assert!(
                rel < 1e-8,
                "step {step}: W {} vs {}",
                d.willmore_energy,
                m.willmore_energy
            );
        }
    }

    #[test]
    fn eigen_residual_without_a_product_matches_the_product() {
        // Two components of different size, so the per-component scale of λ matters, and
        // two inverse iterations.
        let mut mesh = bumpy_sphere(2, 0.3);
        let other = bumpy_sphere(1, 0.2);
        let offset = mesh.vertex_count();
        mesh.positions.extend(
            other
                .positions
                .iter()
                .map(|p| [p[0] * 0.5 + 3.0, p[1] * 0.5, p[2] * 0.5]),
        );
        mesh.triangles.extend(
            other
                .triangles
                .iter()
                .map(|t| [t[0] + offset, t[1] + offset, t[2] + offset]),
        );
        for iterations in [1, 2] {
            let params = FlowParams {
                iterations,
                ..FlowParams::default()
            };
            let mut flow = ConformalFlow::new(&mesh, &params).expect("flow");
            flow.curvature_change().expect("curvature");
            let fast = flow.solve_lambda().expect("solve");
            let direct = flow.eigen_residual_by_product();
            assert!(direct > 1e-3, "a nontrivial residual: {direct}");
            assert!(
                (fast - direct).abs() < 1e-9 * direct,
                "{iterations} iterations: {fast} vs {direct}"
            );
        }
    }
}
