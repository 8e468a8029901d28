//! Conformal Willmore flow in curvature space: Table 1, right column.
//!
//! One step, on the current surface `f`, numbered as Table 1's steps (the code of each is in
//! `step.rs`, which uses the same numbers):
//! - I. mean curvature `H ← ½⟨N, Δf⟩` (§6.1), refilled in the geometry cache after the last
//!   step moved the positions;
//! - II. flow direction `v = −2H` (§6.1: `μ̇ = −2μ`), spectrally filtered when asked (§4);
//! - III. the constraint basis (§6.2), Gram–Schmidt in the area inner product: normals
//!   `N^{x,y,z}` (no sphere inversions, App. D) and `1` (total curvature, App. B) per closed
//!   component, and on genus g > 0 the exactness constraints (App. C);
//! - IV. `v` projected onto them, `P(v)` (Möbius balancing, App. E.1, is added after it);
//! - V. the explicit Euler step `ρ = τ·P(v) = −2τ·P(H)` (docs/algorithm.md §2: with this
//!   convention τ has the paper's §4 meaning, `u ← (1 − 2τ)u`, stable for τ < 1);
//! - VI. recover tangents: the smallest eigenvector of `(D − ρ)λ = γλ` (Eq. 5) by inverse
//!   iteration on `X(ρ)` (App. G), starting from `λ ≡ 1` because the previous surface is the
//!   reference; then the new edges `ẽ = λ̄ e λ`, averaged over each face so every face closes;
//! - VII. recover positions from `L f̃ = ∇·ẽ` (Eq. 6);
//! - after Table 1, the scale policy: each component's centroid and area restored
//!   (docs/algorithm.md §6).
//!
//! The sparsity patterns and symbolic factorizations of X and L are built once per flow;
//! every buffer is allocated in [`ConformalFlow::new`], so the step loop does not allocate.

use super::constraints::ConstraintBasis;
use super::dirac::TriangleAssembly;
use super::exactness::Exactness;
use super::feature::{self, band_energy, feature_filter, remove_low_frequency, FeatureDetail};
use super::filter::FilterSolver;
use super::mobius::MobiusBalancing;
use super::prescribed::{PrescribedError, PrescribedSolver};
use super::scale::ScalePolicy;
use super::{Boundary, Flow, FlowError, FlowParams, PrescribedVectors, Preserve, StepProfile};
use crate::geometry::cache::GeometryCache;
use crate::geometry::Quaternion;
use crate::linalg::ordering::{self, Ordering};
use crate::linalg::solver::{BlockPattern, Cholesky, Mixed, SolverError};
use crate::mesh::topology::Topology;
use crate::mesh::Mesh;
use crate::metrics::{StepMetrics, StepReporter};
use crate::parallel::join;
use faer::c64;
use std::time::Instant;

mod factor;
use factor::*;
mod pcg;
mod pinned;
mod seam;
mod step;

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
    /// Per component: it holds no pinned vertex, so it flows as a free surface, with its
    /// constraints and scale policy (all of them without pinned vertices; `pinned.rs`).
    free_component: Vec<bool>,
    /// Some pinned vertex lies on a closed component.
    pinned_closed: bool,
    /// Prescribed boundary vectors (§6.3.1, CMC with `V = B`); `None` otherwise.
    prescribed: Option<PrescribedSolver>,
    /// Prescribed boundary vectors (not CMC) on a surface with boundary: W may rise while the
    /// boundary turns to its targets, so the safeguard does not require descent.
    turns_boundary: bool,
    /// [`Flow::willmore_lower_bound`] of the input's topology; `None` when the boundary turns
    /// (W then rises on purpose).
    willmore_lower_bound: Option<f64>,
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
    /// The feature scale's state (`FlowParams::feature_size`, [`crate::flow::feature`]).
    feature: Option<FeatureScale>,
    /// Per-vertex weight of each step's motion (a region's falloff); `None`: full motion.
    blend: Option<Vec<f64>>,
    /// The mean curvature the flow drives toward, `ρ = −2τ(H − H̃)` (a region's smooth seam,
    /// [`Self::continue_pinned_curvature`]); `None`: toward 0.
    curvature_target: Option<Vec<f64>>,
    /// With pinned vertices, the vertices whose curvature change the λ solve may *not*
    /// adjust (pinned ones and free components; `pinned.rs`,
    /// [`Self::absorb_unrealizable_curvature`]), and scratch for the change; empty: ρ is
    /// taken as it is.
    absorb_held: Vec<bool>,
    absorb_delta: Vec<f64>,
    /// The absorbed change per unit τ, carried between steps (`pinned.rs`, ABSORB_MEMORY),
    /// and its value on the accepted surface the current try started from: a rejected try
    /// puts it back ([`super::safeguard::Retry::restore`]), so a retry starts from what the
    /// accepted steps absorbed, not from what the refused try added.
    absorb_offset: Vec<f64>,
    absorb_offset_accepted: Vec<f64>,
    /// [`Flow::kept_share`] of the last try (`None` until a try absorbed).
    absorb_kept: Option<f64>,
    /// Work vectors of the absorbing rounds' refined solves (`pcg.rs`), sized once.
    absorb_refine_real: pcg::Scratch<f64>,
    absorb_refine_complex: pcg::Scratch<c64>,
    /// The surface a step started from, kept when the step's motion is filtered or blended.
    step_start: Vec<[f64; 3]>,
    /// The filtered flow direction of the current surface, when the end of the last step
    /// already computed it (a feature scale measures its band there): the next step starts
    /// from it instead of filtering again. Cleared whenever the surface is set from outside.
    direction: Vec<f64>,
    direction_ready: bool,

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
    ///
    /// `blend`, when given, weighs each vertex's motion in every step (1 moves fully, 0 not
    /// at all): a region's falloff toward its border ([`super::region::falloff_weights`]).
    pub(crate) fn with_pinned(
        mesh: &Mesh,
        params: &FlowParams,
        pinned: Vec<bool>,
        blend: Option<Vec<f64>>,
    ) -> Result<Self, FlowError> {
        let mut flow = Self::build(mesh, params, Some(pinned))?;
        if let Some(weights) = blend {
            if weights.len() != flow.positions.len() {
                return Err(FlowError::InvalidParameter {
                    name: "falloff",
                    reason: format!(
                        "{} weights for {} vertices",
                        weights.len(),
                        flow.positions.len()
                    ),
                });
            }
            flow.step_start = flow.positions.clone();
            flow.blend = Some(weights);
        }
        Ok(flow)
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
        let willmore_lower_bound = super::willmore_lower_bound(&topology);
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
        let mut free_component = vec![true; n_components];
        let mut pinned_closed = false;
        for (v, _) in fixed.iter().flatten().enumerate().filter(|(_, &p)| p) {
            free_component[vertex_component[v]] = false;
            pinned_closed |= closed_vertex[v];
        }

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
            params.deviation_threads(),
        );
        let mut scale = ScalePolicy::new(
            feature::scale_policy(params.preserve, params.feature_size),
            &topology,
            &mesh.positions,
            &mesh.triangles,
            &geometry.vertex_areas,
        );
        // Pinned vertices already fix their components' position and size.
        scale.hold(&free_component.iter().map(|&f| !f).collect::<Vec<bool>>());
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
        // Held vertices: a region's submesh, small beside the mesh, whose X is factored twice a
        // step and solved in every refining round, where faer's size rule would pick its
        // simplicial kernel ([`Cholesky::analyze_supernodal_with_vertex_order`]). Not L: real
        // and scalar, its simplicial factor is as fast, and faer's supernodal solve of one
        // right-hand side is slower (nefertiti's 5% region: 0.31 against 0.13 ms a solve, which
        // the δ-system's refining rounds repeat).
        let supernodal = fixed.is_some();
        let vertex_fwd_ref = &vertex_fwd;
        let analyze_dirac = move || -> Result<_, SolverError> {
            let vertex_fwd = vertex_fwd_ref;
            let mut dirac = if mixed {
                let mut mixed = Mixed::analyze(&dirac_pattern, vertex_fwd)?;
                mixed.set_quaternionic();
                DiracFactor::Mixed(Box::new(mixed))
            } else {
                let nrhs = form_count.max(1);
                let mut double = if supernodal {
                    Cholesky::<c64>::analyze_supernodal_with_vertex_order(
                        &dirac_pattern,
                        nrhs,
                        vertex_fwd,
                    )?
                } else {
                    Cholesky::<c64>::analyze_with_vertex_order(&dirac_pattern, nrhs, vertex_fwd)?
                };
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
        if let Some(length) = params.feature_size {
            feature::check_resolution(length, crate::mesh::generate::mean_edge_length(mesh))?;
        }
        // A feature scale derives the filter from its length and the surface's size (an
        // explicit `filter` overrides the derived σ and k: the expert's choice).
        let filter_params = match (params.filter, params.feature_size) {
            (Some(f), _) => Some(f),
            (None, Some(length)) => Some(feature_filter(
                length,
                (geometry.total_area() / (4.0 * std::f64::consts::PI)).sqrt(),
            )),
            (None, None) => None,
        };
        let filter = match filter_params {
            Some(f) => Some(FilterSolver::new(&laplace_pattern, f).map_err(|e| {
                FlowError::InvalidParameter {
                    name: "filter",
                    reason: e.to_string(),
                }
            })?),
            None => None,
        };
        let initial = reporter.initial(&mesh.positions, &mesh.triangles, &geometry);
        let mut flow = ConformalFlow {
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
            free_component,
            pinned_closed,
            turns_boundary: prescribed.is_some()
                && matches!(params.boundary, Boundary::Prescribed(_)),
            willmore_lower_bound: (!(prescribed.is_some()
                && matches!(params.boundary, Boundary::Prescribed(_))))
            .then_some(willmore_lower_bound),
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
            blend: None,
            curvature_target: None,
            absorb_held: Vec::new(),
            absorb_delta: Vec::new(),
            absorb_offset: Vec::new(),
            absorb_offset_accepted: Vec::new(),
            absorb_kept: None,
            absorb_refine_real: pcg::Scratch::default(),
            absorb_refine_complex: pcg::Scratch::default(),
            step_start: if params.feature_size.is_some() {
                vec![[0.0; 3]; n]
            } else {
                Vec::new()
            },
            feature: params.feature_size.map(|_| FeatureScale {
                column: vec![0.0; n],
                detail: FeatureDetail {
                    initial: 0.0,
                    current: 0.0,
                },
            }),
            direction: vec![0.0; n],
            direction_ready: false,
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
        };
        if flow.feature.is_some() {
            let energy = flow.measure_feature_band()?;
            if let Some(f) = &mut flow.feature {
                f.detail = FeatureDetail {
                    initial: energy,
                    current: energy,
                };
            }
        }
        Ok(flow)
    }

    /// The filtered direction and its band energy on the current surface (which the next
    /// step then starts from: see `direction`).
    fn measure_feature_band(&mut self) -> Result<f64, FlowError> {
        self.assemble_laplacian();
        self.flow_direction()?;
        self.direction.copy_from_slice(&self.rho);
        self.direction_ready = true;
        Ok(band_energy(
            &self.rho,
            &self.geometry.vertex_areas,
            self.fixed.as_deref(),
        ))
    }
}

/// What a feature scale keeps between steps ([`crate::flow::feature`]).
struct FeatureScale {
    /// Scratch: one coordinate of the motion.
    column: Vec<f64>,
    detail: FeatureDetail,
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
        self.direction_ready = false;
        self.absorb_offset
            .copy_from_slice(&self.absorb_offset_accepted);
        // The retry runs at a smaller τ: its X is not the rejected try's.
        if let DiracFactor::Mixed(m) = &mut self.dirac {
            m.refactor_next();
        }
    }

    fn resist_damage(&mut self) -> bool {
        // Non-negative Poisson weights on crowded faces from now on (docs/cheburashka-collapse.md,
        // "A fallback"); `restore` refreshes the cotangents with it.
        let first = !self.geometry.clamp_crowded;
        self.geometry.clamp_crowded = true;
        first
    }

    fn descends(&self) -> bool {
        !self.turns_boundary
    }

    fn pins_vertices(&self) -> bool {
        self.free_component.iter().any(|&f| !f)
    }

    fn carried(&self) -> super::Carried {
        super::Carried {
            absorbed: self.absorb_offset.clone(),
            resists_damage: self.geometry.clamp_crowded,
            ..super::Carried::default()
        }
    }

    fn carry(&mut self, carried: &super::Carried) -> Result<(), FlowError> {
        self.carry_absorbed(&carried.absorbed)?;
        self.geometry.clamp_crowded = carried.resists_damage;
        Ok(())
    }
}

impl Flow for ConformalFlow {
    fn step(&mut self) -> Result<StepMetrics, FlowError> {
        let start = Instant::now();
        self.profile.start();
        // What the accepted steps absorbed, for a refused try to put back (`restore`).
        self.absorb_offset_accepted
            .copy_from_slice(&self.absorb_offset);
        self.curvature_change()?;
        self.profile.lap("curvature");
        let eigen_residual = self.solve_lambda()?;
        if !self.step_start.is_empty() {
            self.step_start.copy_from_slice(&self.positions);
        }
        let closure_residual = self.integrate()?;
        self.profile.lap("closure");
        if let (Some(f), Some(filter)) = (&mut self.feature, &mut self.filter) {
            // docs/algorithm.md §11: the step's low-frequency motion is a second-order
            // side effect of removing the detail; take it back with the filter's operator
            // on the surface the step started from (still factored).
            remove_low_frequency(
                filter,
                &self.geometry.vertex_areas,
                &self.step_start,
                &mut self.positions,
                self.fixed.as_deref(),
                &mut f.column,
            )
            .map_err(|e| FlowError::Numerical {
                step: self.step + 1,
                reason: e.to_string(),
            })?;
            self.profile.lap("feature scale");
        }
        if let Some(weights) = &self.blend {
            // A region's falloff: the motion fades to zero toward the border.
            for ((p, b), &w) in self.positions.iter_mut().zip(&self.step_start).zip(weights) {
                for axis in 0..3 {
                    p[axis] = b[axis] + w * (p[axis] - b[axis]);
                }
            }
        }
        // New geometry, then the scale policy on it, then the geometry again for the metrics
        // and the next step (the rescale changes areas and H).
        self.geometry.refresh(&self.positions, &self.triangles);
        if self.free_component.iter().any(|&f| f) {
            // Components with pinned vertices are held by them (`ScalePolicy::hold`).
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
        if self.feature.is_some() {
            let energy = self.measure_feature_band()?;
            if let Some(f) = &mut self.feature {
                f.detail.current = energy;
            }
            self.profile.lap("feature band");
        }
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

    fn willmore_lower_bound(&self) -> Option<f64> {
        self.willmore_lower_bound
    }

    fn initial_metrics(&self) -> StepMetrics {
        self.initial
    }

    fn feature_detail(&self) -> Option<FeatureDetail> {
        self.feature.as_ref().map(|f| f.detail)
    }

    fn kept_share(&self) -> Option<f64> {
        self.absorb_kept
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::flow::Precision;
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
