//! Discrete exterior calculus (DEC) on a triangle mesh, and the harmonic 1-forms and harmonic
//! vector fields the exactness constraint needs (paper §6.2, Appendix C.1 steps I–IV).
//!
//! Conventions (as in Desbrun, Kanso, Tong 2008, "Discrete differential forms for computational
//! modeling", and Crane's DDG notes):
//!
//! - a 0-form lives on vertices, a 1-form on edges, a 2-form on faces;
//! - edge `e` of [`Topology::edges`] is `[a, b]` with `a < b` and is oriented `a → b`, so a
//!   1-form value `ω_e` is the integral of ω from `a` to `b`;
//! - faces are oriented by their winding (counter-clockwise seen from outside);
//! - [`star1`] is the diagonal cotan Hodge star, so `d0ᵀ ⋆1 d0` is the positive semidefinite
//!   cotan Laplacian of [`super::cotan_laplacian`].
//!
//! The harmonic forms are computed by [`HarmonicBasisSolver`], built once per connectivity and
//! refilled per flow step; [`harmonic_basis`] is the one-shot wrapper.

use faer::sparse::{SparseColMat, Triplet};

use super::operators::{barycentric_vertex_areas, corner_cotangents, corner_cotangents_into};
use super::vec3::{add, cross, dot, norm, scale, sub};
use crate::linalg::solver::{BlockPattern, Cholesky, SolverError};
use crate::mesh::generate::SplitMix64;
use crate::mesh::{Mesh, Topology};

/// Largest accepted relative residual of either Poisson solve. A healthy Cholesky solve lands
/// near 1e-13; anything above this means the mesh is numerically degenerate (needle or
/// zero-area faces) and the forms would not be harmonic, which silently breaks exactness.
pub const POISSON_TOLERANCE: f64 = 1e-8;

/// A form whose ⋆1 norm drops below this fraction of its norm before Gram–Schmidt is treated as
/// linearly dependent on the earlier ones (random forms are independent with probability one,
/// so hitting this means a broken mesh, not bad luck).
const DEPENDENCE_TOLERANCE: f64 = 1e-10;

/// Why the harmonic forms could not be computed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum HodgeError {
    #[error("{got} positions given, the connectivity has {expected} vertices")]
    PositionCount { got: usize, expected: usize },
    #[error("1-form {index} has {got} values, expected {expected} (one per edge)")]
    FormLength {
        index: usize,
        got: usize,
        expected: usize,
    },
    #[error("vertex Poisson system: {0}")]
    Solver(#[from] SolverError),
    #[error("dual-face Poisson system could not be factored: {0}")]
    DualFactorization(String),
    #[error("{system} Poisson solve left relative residual {relative:e}")]
    Residual {
        system: PoissonSystem,
        relative: f64,
    },
    #[error(
        "harmonic form {form} of component {component} is numerically dependent on the others"
    )]
    DependentForms { component: usize, form: usize },
}

/// Which of the two Poisson systems of the Hodge decomposition a residual belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PoissonSystem {
    /// `d1 d1ᵀ β̃ = d1 α` on dual vertices (faces): removes the co-exact part.
    DualFaces,
    /// `d0ᵀ ⋆1 d0 φ = d0ᵀ ⋆1 α` on vertices: removes the exact part.
    Vertices,
}

impl std::fmt::Display for PoissonSystem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            PoissonSystem::DualFaces => "dual-face",
            PoissonSystem::Vertices => "vertex",
        })
    }
}

// ---------------------------------------------------------------------------------------------
// Exterior derivatives
// ---------------------------------------------------------------------------------------------

/// Exterior derivative on 0-forms, `d0 ∈ {−1, 0, 1}^{|E|×|V|}`: `(d0 f)_e = f_b − f_a` for edge
/// `e = [a, b]` (`a < b`, oriented `a → b`). Its transpose is minus the divergence, and
/// `d0ᵀ ⋆1 d0` is the positive semidefinite cotan Laplacian.
///
/// ```
/// use willow::geometry::hodge::d0;
/// use willow::mesh::{Mesh, Topology};
/// let tet = Mesh {
///     positions: vec![[0., 0., 0.], [1., 0., 0.], [0., 1., 0.], [0., 0., 1.]],
///     triangles: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
/// };
/// let d = d0(&Topology::new(&tet)).to_dense();
/// assert_eq!((d.nrows(), d.ncols()), (6, 4));
/// // Edge 0 is [0, 1], oriented 0 → 1: (d0 f)_0 = f_1 − f_0.
/// assert_eq!((d[(0, 0)], d[(0, 1)], d[(0, 2)]), (-1.0, 1.0, 0.0));
/// // Every row is a difference: d0 kills constants.
/// for e in 0..6 {
///     assert_eq!((0..4).map(|v| d[(e, v)]).sum::<f64>(), 0.0);
/// }
/// ```
pub fn d0(topology: &Topology) -> SparseColMat<usize, f64> {
    let n_vertices = topology.vertex_component.len();
    let mut triplets = Vec::with_capacity(2 * topology.edges.len());
    for (e, &[a, b]) in topology.edges.iter().enumerate() {
        triplets.push(Triplet::new(e, a, -1.0));
        triplets.push(Triplet::new(e, b, 1.0));
    }
    // Indices are in range by construction (Topology sizes vertex arrays by the largest index),
    // so the only possible failure is an allocation failure, which aborts anyway.
    SparseColMat::try_new_from_triplets(topology.edges.len(), n_vertices, &triplets)
        .expect("d0 triplets index edges and vertices of the same topology")
}

/// Exterior derivative on 1-forms, `d1 ∈ {−1, 0, 1}^{|F|×|E|}`: `(d1 ω)_f = Σ_k s_fk ω_{e_k}`
/// over the three edges of face `f`, with `s_fk = +1` when the face's winding traverses edge
/// `e_k` in its own direction `a → b` and `−1` otherwise (Stokes: the circulation of ω around
/// the counter-clockwise boundary of `f`). `d1 · d0 = 0` exactly.
///
/// The face winding is recovered from [`Topology::face_edges`] alone: edge `k` runs from corner
/// `k` to corner `k + 1`, and corner `k + 1` is the vertex edge `k` shares with edge `k + 1`.
///
/// ```
/// use willow::geometry::hodge::{d0, d1};
/// use willow::mesh::{Mesh, Topology};
/// let tet = Mesh {
///     positions: vec![[0., 0., 0.], [1., 0., 0.], [0., 1., 0.], [0., 0., 1.]],
///     triangles: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
/// };
/// let topology = Topology::new(&tet);
/// let (d1, d0) = (d1(&topology).to_dense(), d0(&topology).to_dense());
/// assert_eq!((d1.nrows(), d1.ncols()), (4, 6));
/// // d1 d0 = 0 (the circulation of a gradient vanishes) ...
/// assert!((&d1 * &d0).norm_max() == 0.0);
/// // ... and on a closed surface every edge has one +1 and one −1 (1ᵀ d1 = 0).
/// for e in 0..6 {
///     assert_eq!((0..4).map(|f| d1[(f, e)]).sum::<f64>(), 0.0);
/// }
/// ```
pub fn d1(topology: &Topology) -> SparseColMat<usize, f64> {
    let signs = face_edge_signs_from_topology(topology);
    let mut triplets = Vec::with_capacity(3 * topology.face_edges.len());
    for (f, (fe, s)) in topology.face_edges.iter().zip(&signs).enumerate() {
        for k in 0..3 {
            triplets.push(Triplet::new(f, fe[k], s[k]));
        }
    }
    // Face and edge indices come from the same topology; a face listing an edge twice (a
    // degenerate triangle, refused by Mesh::new) would merely sum the duplicates.
    SparseColMat::try_new_from_triplets(topology.face_edges.len(), topology.edges.len(), &triplets)
        .expect("d1 triplets index faces and edges of the same topology")
}

/// `s_fk` of [`d1`] from the topology alone (see there).
fn face_edge_signs_from_topology(topology: &Topology) -> Vec<[f64; 3]> {
    topology
        .face_edges
        .iter()
        .map(|fe| {
            let mut s = [0.0; 3];
            for k in 0..3 {
                let edge = topology.edges[fe[k]];
                let next = topology.edges[fe[(k + 1) % 3]];
                // The head of edge k (corner k + 1) is the endpoint it shares with edge k + 1.
                let head_is_b = edge[1] == next[0] || edge[1] == next[1];
                s[k] = if head_is_b { 1.0 } else { -1.0 };
            }
            s
        })
        .collect()
}

/// `s_fk` of [`d1`] from the winding: edge `k` of face `f` runs `tri[k] → tri[k + 1]`, which
/// agrees with the edge's own orientation `a → b`, `a < b`, exactly when `tri[k] < tri[k + 1]`.
#[inline]
fn face_edge_signs(tri: &[usize; 3]) -> [f64; 3] {
    let s = |k: usize| {
        if tri[k] < tri[(k + 1) % 3] {
            1.0
        } else {
            -1.0
        }
    };
    [s(0), s(1), s(2)]
}

// ---------------------------------------------------------------------------------------------
// Hodge stars (diagonal)
// ---------------------------------------------------------------------------------------------

/// Hodge star on 0-forms: the diagonal of barycentric vertex areas, `(⋆0)_ii = A_i = Σ_{f∋i}
/// A_f / 3` (docs/algorithm.md §1: the flow's lumped mass matrix and inner product).
pub fn star0(mesh: &Mesh) -> Vec<f64> {
    barycentric_vertex_areas(mesh)
}

/// Hodge star on 1-forms, the diagonal cotan weights: `(⋆1)_e = ½(cot α_e + cot β_e)` with
/// `α_e, β_e` the angles opposite edge `e`; a boundary edge gets its single term `½ cot α_e`.
/// `⋆1` is the ratio of dual to primal edge length (circumcentric dual); it is negative on
/// non-Delaunay edges, so it is an inner product only on closed 1-forms (see
/// [`HarmonicBasisSolver`]).
pub fn star1(mesh: &Mesh, topology: &Topology) -> Vec<f64> {
    let mut out = vec![0.0; topology.edges.len()];
    star1_into(topology, &corner_cotangents(mesh), &mut out);
    out
}

/// [`star1`] from precomputed corner cotangents (`cotangents[f][c]` is the angle at corner `c`,
/// opposite edge `face_edges[f][(c + 1) % 3]`, which runs corner `c + 1 → c + 2`).
pub fn star1_into(topology: &Topology, cotangents: &[[f64; 3]], out: &mut [f64]) {
    out.fill(0.0);
    for (fe, cots) in topology.face_edges.iter().zip(cotangents) {
        for c in 0..3 {
            out[fe[(c + 1) % 3]] += 0.5 * cots[c];
        }
    }
}

/// Hodge star on 2-forms: `(⋆2)_f = 1 / A_f`. A zero-area face (refused by validation) gets a
/// huge finite value instead of infinity, so products stay free of NaN.
pub fn star2(mesh: &Mesh) -> Vec<f64> {
    super::face_areas(mesh)
        .into_iter()
        .map(|a| 1.0 / a.max(f64::MIN_POSITIVE))
        .collect()
}

// ---------------------------------------------------------------------------------------------
// Harmonic 1-forms (App. C.1 steps I–III)
// ---------------------------------------------------------------------------------------------

/// Number of independent harmonic 1-forms of one component: its first Betti number. For a
/// closed surface of genus g that is `2g` (App. C); a surface with `b ≥ 1` boundary loops has
/// `2g + b − 1` (the annulus of §6.2 has one), represented by the closed forms that are
/// co-closed with natural (Neumann) conditions at the boundary vertices.
fn betti_1(component: &crate::mesh::topology::Component) -> usize {
    if component.is_closed() {
        2 * component.genus
    } else {
        2 * component.genus + component.boundary_loops.len() - 1
    }
}

/// The dual-face Poisson system `d1 d1ᵀ β̃ = d1 α` that removes the co-exact part of a 1-form.
///
/// Formulation (a deliberate deviation from the `d1 ⋆1⁻¹ d1ᵀ` of Desbrun et al. 2008): the
/// ⋆1-orthogonal co-exact projection needs `⋆1⁻¹`, which is infinite on right-angled and
/// negative on non-Delaunay edges (botijo has many), making the dual matrix indefinite. We only
/// need *some* closed form in each cohomology class, not the ⋆1-orthogonal projection, because
/// step `h = α_c − d0 φ` then yields the unique ⋆1-harmonic representative of that class and
/// Gram–Schmidt only keeps the span. So we project in the plain ℓ² inner product
/// (`⋆1 = I` here): `α_c = α − d1ᵀ β̃` with `d1 d1ᵀ β̃ = d1 α`. Then `d1 α_c = 0`, and
/// `d1 d1ᵀ` (diagonal 3, `−1` between faces sharing an edge) is purely combinatorial: it is
/// factored once per connectivity, never per step.
///
/// Kernel: on a closed component `d1ᵀ β̃ = 0` for constant `β̃`, so the system is singular; the
/// component's first face is pinned (`β̃ = 0` there, its row and column replaced by the
/// identity). This is exact, not a shift: the right-hand side `d1 α` sums to zero over a closed
/// component (each edge enters two faces with opposite signs), so the pinned equation holds
/// automatically. A component with boundary has no kernel.
struct DualPoisson {
    /// Pattern of the dual graph: faces are the "vertices", and each interior edge `e` between
    /// faces `f`, `g` enters [`BlockPattern::new`] as the degenerate triple `[f, g, g]`, which
    /// contributes exactly the pair `(f, g)`. This reuses the AMD + supernodal path of
    /// [`Cholesky`]: botijo's setup (factor + three 10-column solves) took 1.3 s this way
    /// against 2.2 s with faer's default high-level `Llt`, on a loaded 2-core machine.
    pattern: BlockPattern,
    cholesky: Cholesky<f64>,
    /// `pinned[f]`: the face whose value is fixed to zero (one per closed component).
    pinned: Vec<bool>,
}

impl DualPoisson {
    fn new(mesh: &Mesh, topology: &Topology, nrhs: usize) -> Result<Self, HodgeError> {
        let n_faces = mesh.triangles.len();
        let mut pinned = vec![false; n_faces];
        for comp in &topology.components {
            if let (true, Some(&f)) = (comp.is_closed(), comp.faces.first()) {
                pinned[f] = true;
            }
        }
        // Off-diagonal (f, g) = s_f(e) s_g(e) for the edge e the two faces share (−1 on a
        // consistently oriented surface); skipped in a pinned row or column.
        let sign_in = |f: usize, e: usize| -> f64 {
            let k = topology.face_edges[f].iter().position(|&x| x == e);
            k.map_or(0.0, |k| face_edge_signs(&mesh.triangles[f])[k])
        };
        let mut pairs = Vec::with_capacity(topology.edges.len());
        let mut couplings = Vec::with_capacity(topology.edges.len());
        for (e, around) in topology.edge_faces.iter().enumerate() {
            if let [Some(f), Some(g)] = *around {
                if f != g {
                    pairs.push([f, g, g]);
                    let pinned_pair = pinned[f] || pinned[g];
                    couplings.push(if pinned_pair {
                        0.0
                    } else {
                        sign_in(f, e) * sign_in(g, e)
                    });
                }
            }
        }
        let pattern = BlockPattern::new(n_faces, &pairs, 1);
        let mut values = vec![0.0; pattern.nnz()];
        for ((&[f, g, _], slots), &v) in pairs.iter().zip(&pattern.face_slots).zip(&couplings) {
            // slots[3a + b] is the block at row pair[a], column pair[b].
            values[pattern.entry(slots[1], g, 0, 0)] += v;
            values[pattern.entry(slots[3], f, 0, 0)] += v;
        }
        for (f, &p) in pinned.iter().enumerate() {
            // Diagonal of d1 d1ᵀ: every face has three edges.
            values[pattern.entry(pattern.diagonal_slot(f), f, 0, 0)] = if p { 1.0 } else { 3.0 };
        }
        let mut cholesky = Cholesky::analyze(&pattern, nrhs)
            .map_err(|e| HodgeError::DualFactorization(e.to_string()))?;
        cholesky
            .factorize(&pattern, &values)
            .map_err(|e| HodgeError::DualFactorization(e.to_string()))?;
        Ok(DualPoisson {
            pattern,
            cholesky,
            pinned,
        })
    }

    /// Replaces each form by its closed part `α − d1ᵀ β̃`; checks `‖d1 α_c‖ / ‖d1 α‖`.
    ///
    /// Two rounds of iterative refinement follow the first solve: its relative residual is
    /// ~1e-13 on botijo (80k faces), and since the harmonic part is only ~2% of `α_c` there,
    /// that would leave `|d1 h| / |h|` near 1e-9 after normalization. The residual `d1 α_c` is
    /// computed from O(1) values, so refinement drives it to roundoff (~1e-16). Runs once per
    /// connectivity, so the extra solves are cheap.
    fn project_closed(
        &mut self,
        mesh: &Mesh,
        topology: &Topology,
        forms: &mut [Vec<f64>],
    ) -> Result<(), HodgeError> {
        const REFINEMENTS: usize = 2;
        let n_faces = mesh.triangles.len();
        let k = forms.len();
        if k == 0 || n_faces == 0 {
            return Ok(());
        }
        let curl = |form: &[f64], f: usize| -> f64 {
            let s = face_edge_signs(&mesh.triangles[f]);
            let fe = topology.face_edges[f];
            s[0] * form[fe[0]] + s[1] * form[fe[1]] + s[2] * form[fe[2]]
        };
        let mut rhs = vec![0.0; n_faces * k];
        let mut rhs_norm = vec![0.0f64; k];
        for pass in 0..=REFINEMENTS + 1 {
            // rhs = d1 α (first pass) or the residual d1 α_c (later passes), zero where pinned.
            let mut relative = 0.0f64;
            for (i, form) in forms.iter().enumerate() {
                let mut norm2 = 0.0;
                for f in 0..n_faces {
                    let c = curl(form, f);
                    norm2 += c * c;
                    rhs[i * n_faces + f] = if self.pinned[f] { 0.0 } else { c };
                }
                if pass == 0 {
                    rhs_norm[i] = norm2.sqrt();
                } else {
                    relative = relative.max(norm2.sqrt() / rhs_norm[i].max(f64::MIN_POSITIVE));
                }
            }
            if pass == REFINEMENTS + 1 {
                if relative.is_nan() || relative > POISSON_TOLERANCE {
                    return Err(HodgeError::Residual {
                        system: PoissonSystem::DualFaces,
                        relative,
                    });
                }
                break;
            }
            debug_assert_eq!(self.pattern.dim(), n_faces);
            self.cholesky.solve_in_place(&mut rhs, k);
            for (i, form) in forms.iter_mut().enumerate() {
                let beta = &rhs[i * n_faces..(i + 1) * n_faces];
                for (f, (fe, tri)) in topology.face_edges.iter().zip(&mesh.triangles).enumerate() {
                    let s = face_edge_signs(tri);
                    for c in 0..3 {
                        form[fe[c]] -= s[c] * beta[f];
                    }
                }
            }
        }
        Ok(())
    }
}

/// The vertex Poisson system `d0ᵀ ⋆1 d0 φ = d0ᵀ ⋆1 α` that removes the exact part of a closed
/// 1-form, on a fixed pattern: pattern, AMD ordering, symbolic Cholesky and buffers are built
/// once; [`VertexPoisson::refill`] redoes cotangents, `⋆1` and the numeric factorization.
///
/// `d0ᵀ ⋆1 d0` is the cotan Laplacian `L`: the stiffness matrix of linear finite elements, so
/// positive semidefinite with only the constants in its kernel (per component) even where cotan
/// weights are negative. The kernel is removed by pinning the lowest vertex of each component
/// (row and column replaced by the identity, right-hand side zero there). This is exact, since
/// `d0ᵀ x` sums to zero over each component; no shift perturbs the solution.
struct VertexPoisson {
    triangles: Vec<[usize; 3]>,
    face_edges: Vec<[usize; 3]>,
    edges: Vec<[usize; 2]>,
    pattern: BlockPattern,
    cholesky: Cholesky<f64>,
    /// Per face and corner `c` (opposite edge `a → b`): the value slots of `(a, b)`, `(b, a)`,
    /// `(a, a)`, `(b, b)`. Entries in a pinned row or column point at the sink slot `nnz`, so
    /// the refill loop has no branches.
    corner_slots: Vec<[[usize; 4]; 3]>,
    /// Value slot of the diagonal of each pinned vertex (set to 1 after the scatter).
    pinned_diagonals: Vec<usize>,
    pinned: Vec<bool>,
    cotangents: Vec<[f64; 3]>,
    /// `⋆1` of the current positions.
    weights: Vec<f64>,
    /// Matrix values, plus one trailing sink slot.
    values: Vec<f64>,
    /// Column-major `|V| × nrhs` right-hand sides, overwritten by the solutions φ.
    rhs: Vec<f64>,
    rhs_norms: Vec<f64>,
    scratch: Vec<f64>,
    nrhs: usize,
}

impl VertexPoisson {
    fn new(mesh: &Mesh, topology: &Topology, nrhs: usize) -> Result<Self, HodgeError> {
        let n_vertices = topology.vertex_component.len().max(mesh.positions.len());
        let mut pinned = vec![false; n_vertices];
        for comp in &topology.components {
            if let Some(&v) = comp.vertices.first() {
                pinned[v] = true;
            }
        }
        // A vertex no face uses (refused by Mesh::new) has an empty row: pin it too.
        for (v, &c) in topology.vertex_component.iter().enumerate() {
            if c == usize::MAX {
                pinned[v] = true;
            }
        }
        let pattern = BlockPattern::new(n_vertices, &mesh.triangles, 1);
        let cholesky = Cholesky::analyze(&pattern, nrhs)?;
        let sink = pattern.nnz();
        let slot = |a: usize, b: usize, base: usize| -> usize {
            if pinned[a] || pinned[b] {
                sink
            } else {
                pattern.entry(base, b, 0, 0)
            }
        };
        let corner_slots = mesh
            .triangles
            .iter()
            .zip(&pattern.face_slots)
            .map(|(tri, slots)| {
                let mut out = [[0usize; 4]; 3];
                for (c, o) in out.iter_mut().enumerate() {
                    let (ia, ib) = ((c + 1) % 3, (c + 2) % 3);
                    let (a, b) = (tri[ia], tri[ib]);
                    *o = [
                        slot(a, b, slots[3 * ia + ib]),
                        slot(b, a, slots[3 * ib + ia]),
                        slot(a, a, slots[3 * ia + ia]),
                        slot(b, b, slots[3 * ib + ib]),
                    ];
                }
                out
            })
            .collect();
        let pinned_diagonals = (0..n_vertices)
            .filter(|&v| pinned[v])
            .map(|v| pattern.entry(pattern.diagonal_slot(v), v, 0, 0))
            .collect();
        Ok(VertexPoisson {
            triangles: mesh.triangles.clone(),
            face_edges: topology.face_edges.clone(),
            edges: topology.edges.clone(),
            corner_slots,
            pinned_diagonals,
            pinned,
            cotangents: vec![[0.0; 3]; mesh.triangles.len()],
            weights: vec![0.0; topology.edges.len()],
            values: vec![0.0; sink + 1],
            rhs: vec![0.0; n_vertices * nrhs],
            rhs_norms: vec![0.0; nrhs],
            scratch: vec![0.0; n_vertices],
            nrhs,
            pattern,
            cholesky,
        })
    }

    fn vertex_count(&self) -> usize {
        self.pinned.len()
    }

    /// Cotangents, `⋆1` and the numeric factorization of the pinned `L` at `positions`.
    fn refill(&mut self, positions: &[[f64; 3]]) -> Result<(), HodgeError> {
        if positions.len() != self.vertex_count() {
            return Err(HodgeError::PositionCount {
                got: positions.len(),
                expected: self.vertex_count(),
            });
        }
        corner_cotangents_into(positions, &self.triangles, &mut self.cotangents);
        self.weights.fill(0.0);
        self.values.fill(0.0);
        for ((fe, cots), slots) in self
            .face_edges
            .iter()
            .zip(&self.cotangents)
            .zip(&self.corner_slots)
        {
            for c in 0..3 {
                let w = 0.5 * cots[c];
                self.weights[fe[(c + 1) % 3]] += w;
                let [ab, ba, aa, bb] = slots[c];
                self.values[ab] -= w;
                self.values[ba] -= w;
                self.values[aa] += w;
                self.values[bb] += w;
            }
        }
        for &d in &self.pinned_diagonals {
            self.values[d] = 1.0;
        }
        let nnz = self.pattern.nnz();
        self.cholesky
            .factorize(&self.pattern, &self.values[..nnz])?;
        Ok(())
    }

    /// `out[i] = α_i − d0 φ_i` with `L φ_i = d0ᵀ ⋆1 α_i` for the closed forms `alphas` (at most
    /// `nrhs`), using the last [`VertexPoisson::refill`]. The vertex-system residual is exactly
    /// `−d0ᵀ ⋆1 h`, so it is checked as `‖d0ᵀ ⋆1 h‖ / ‖d0ᵀ ⋆1 α‖ ≤` [`POISSON_TOLERANCE`].
    fn remove_exact(
        &mut self,
        alphas: &[Vec<f64>],
        out: &mut [Vec<f64>],
    ) -> Result<(), HodgeError> {
        let n = self.vertex_count();
        let k = alphas.len();
        debug_assert!(k <= self.nrhs && out.len() == k);
        for (i, alpha) in alphas.iter().enumerate() {
            let b = &mut self.rhs[i * n..(i + 1) * n];
            codifferential_into(&self.edges, &self.weights, alpha, b);
            self.rhs_norms[i] = b.iter().map(|x| x * x).sum::<f64>().sqrt();
            for (x, &p) in b.iter_mut().zip(&self.pinned) {
                if p {
                    *x = 0.0;
                }
            }
        }
        self.cholesky.solve_in_place(&mut self.rhs[..n * k], k);
        for (i, (h, alpha)) in out.iter_mut().zip(alphas).enumerate() {
            let phi = &self.rhs[i * n..(i + 1) * n];
            h.clear();
            h.extend(
                self.edges
                    .iter()
                    .zip(alpha)
                    .map(|(&[a, b], &x)| x - (phi[b] - phi[a])),
            );
            codifferential_into(&self.edges, &self.weights, h, &mut self.scratch);
            let residual = self.scratch.iter().map(|x| x * x).sum::<f64>().sqrt();
            let relative = residual / self.rhs_norms[i].max(f64::MIN_POSITIVE);
            if relative.is_nan() || relative > POISSON_TOLERANCE {
                return Err(HodgeError::Residual {
                    system: PoissonSystem::Vertices,
                    relative,
                });
            }
        }
        Ok(())
    }
}

/// `out = d0ᵀ ⋆1 ω`: `(d0ᵀ ⋆1 ω)_v = Σ_{e = a→v} w_e ω_e − Σ_{e = v→b} w_e ω_e`, minus the
/// integrated divergence of ω at `v`. Zero exactly when ω is co-closed.
fn codifferential_into(edges: &[[usize; 2]], weights: &[f64], form: &[f64], out: &mut [f64]) {
    out.fill(0.0);
    for ((&[a, b], &w), &x) in edges.iter().zip(weights).zip(form) {
        let flux = w * x;
        out[a] -= flux;
        out[b] += flux;
    }
}

/// Harmonic 1-forms of a mesh, built once per connectivity and recomputed per flow step.
///
/// For each component `c` it returns `b1(c)` forms supported on that component only (`2g` on a
/// closed genus-g component, `2g + b − 1` with `b ≥ 1` boundary loops; see
/// [`HarmonicBasisSolver::form_ranges`]), each
///
/// - closed, `d1 h = 0`, and co-closed, `d0ᵀ ⋆1 h = 0` (harmonic for the cotan star; natural
///   Neumann condition at boundary vertices),
/// - orthonormal in `⟨a, b⟩ = aᵀ ⋆1 b = Σ_e w_e a_e b_e`.
///
/// Steps (App. C.1 I–III, docs/algorithm.md §7), Hodge decomposition `α = d0 φ + δβ + h` after
/// Desbrun et al. 2008:
///
/// 1. (`new`, once) random 1-forms `α_i`, uniform in `[−1, 1)` per edge from a SplitMix64
///    stream seeded by `seed`, each supported on one component; their closed parts
///    `α_c = α − d1ᵀ β̃` from the combinatorial dual Poisson system `d1 d1ᵀ β̃ = d1 α` (the
///    co-exact part is removed in the ℓ² rather than the ⋆1 inner product: `⋆1⁻¹` is infinite
///    or negative on non-Delaunay edges, and any closed representative serves, see below).
///    `d1` does not depend on positions, so `α_c` is fixed per connectivity.
/// 2. (`compute`, per step) the exact part: `L φ = d0ᵀ ⋆1 α_c` with the current cotan
///    Laplacian `L = d0ᵀ ⋆1 d0`, one vertex pinned per component; `h = α_c − d0 φ` is then the
///    unique ⋆1-harmonic form cohomologous to `α_c`. Residual checked against
///    [`POISSON_TOLERANCE`].
/// 3. Modified Gram–Schmidt in ⋆1, each form orthogonalized twice ("twice is enough"). `⋆1` is
///    indefinite on non-Delaunay meshes, but on *closed* forms `ωᵀ ⋆1 ω = Σ_f A_f |v_f|²` with
///    `v_f` the per-face vector of [`harmonic_vector_fields`] (the cotan formula is the exact
///    Dirichlet energy of a linear function), so it is a true inner product on harmonic forms.
///
/// The harmonic forms are therefore not the ⋆1-orthogonal projections of the random `α_i`, but
/// they span the same space (all harmonic forms), which is all the exactness constraint uses.
///
/// Reused between steps: the fixed closed forms `α_c` (the dual system is factored and solved
/// once, in `new`), the vertex-graph [`BlockPattern`], its AMD ordering and symbolic Cholesky,
/// the factor and solve workspaces, and every buffer (cotangents, ⋆1, matrix values,
/// right-hand sides, and `out`'s vectors). Per `compute`: one numeric Cholesky of `L`, one
/// solve with `k = form_count()` right-hand sides, `O(k |E|)` residual checks and `O(k² |E|)`
/// Gram–Schmidt; no allocation once `out` has its final shape. A genus-0 mesh builds no
/// vertex system at all and `compute` returns an empty basis.
pub struct HarmonicBasisSolver {
    /// Closed parts `α_c` of the random forms, one `Vec` of length `|E|` per form.
    closed_forms: Vec<Vec<f64>>,
    /// `forms[ranges[c].clone()]` belong to component `c`.
    ranges: Vec<std::ops::Range<usize>>,
    /// `None` when there is no harmonic form to compute.
    vertex: Option<VertexPoisson>,
    vertex_count: usize,
}

impl HarmonicBasisSolver {
    /// Analyses the connectivity (`topology` must be built from `mesh`; its positions are not
    /// used) and draws the random closed forms from `seed`.
    pub fn new(mesh: &Mesh, topology: &Topology, seed: u64) -> Result<Self, HodgeError> {
        // Step I: random 1-forms, per component, from one deterministic stream.
        let edge_component: Vec<usize> = topology
            .edge_faces
            .iter()
            .map(|around| around[0].map_or(usize::MAX, |f| topology.face_component[f]))
            .collect();
        let mut rng = SplitMix64(seed);
        let mut closed_forms = Vec::new();
        let mut ranges = Vec::with_capacity(topology.components.len());
        for (c, comp) in topology.components.iter().enumerate() {
            let start = closed_forms.len();
            for _ in 0..betti_1(comp) {
                let form: Vec<f64> = edge_component
                    .iter()
                    .map(|&ec| if ec == c { rng.signed() } else { 0.0 })
                    .collect();
                closed_forms.push(form);
            }
            ranges.push(start..closed_forms.len());
        }
        let vertex = if closed_forms.is_empty() {
            None
        } else {
            // Step II, co-exact part: once per connectivity.
            DualPoisson::new(mesh, topology, closed_forms.len())?.project_closed(
                mesh,
                topology,
                &mut closed_forms,
            )?;
            Some(VertexPoisson::new(mesh, topology, closed_forms.len())?)
        };
        Ok(HarmonicBasisSolver {
            closed_forms,
            ranges,
            vertex,
            vertex_count: topology.vertex_component.len().max(mesh.positions.len()),
        })
    }

    /// Total number of harmonic forms, `Σ_c b1(c)` (`2g` for one closed genus-g surface).
    pub fn form_count(&self) -> usize {
        self.closed_forms.len()
    }

    /// `forms[form_ranges()[c].clone()]` are the forms supported on component `c` of the
    /// topology (an empty range for a sphere or a disk).
    pub fn form_ranges(&self) -> &[std::ops::Range<usize>] {
        &self.ranges
    }

    /// The cotan weights `⋆1` of the last [`HarmonicBasisSolver::compute`], the inner product
    /// the forms are orthonormal in (empty when there are no forms).
    pub fn star1(&self) -> &[f64] {
        self.vertex.as_ref().map_or(&[], |v| &v.weights)
    }

    /// The harmonic basis of the surface at `positions` (same connectivity as in `new`) into
    /// `out`: `out.len() == form_count()`, each form of length `|E|`, ordered by component.
    /// Reuses `out`'s allocations.
    pub fn compute(
        &mut self,
        positions: &[[f64; 3]],
        out: &mut Vec<Vec<f64>>,
    ) -> Result<(), HodgeError> {
        if positions.len() != self.vertex_count {
            return Err(HodgeError::PositionCount {
                got: positions.len(),
                expected: self.vertex_count,
            });
        }
        out.resize_with(self.closed_forms.len(), Vec::new);
        let Some(vertex) = self.vertex.as_mut() else {
            return Ok(());
        };
        // Step II, exact part.
        vertex.refill(positions)?;
        vertex.remove_exact(&self.closed_forms, out)?;

        // Step III: modified Gram–Schmidt in ⋆1, per component (forms of different components
        // have disjoint support, hence are orthogonal already).
        let w = &vertex.weights;
        let inner = |a: &[f64], b: &[f64]| -> f64 {
            w.iter().zip(a).zip(b).map(|((w, a), b)| w * a * b).sum()
        };
        for (c, range) in self.ranges.iter().enumerate() {
            for i in range.clone() {
                let (done, rest) = out.split_at_mut(i);
                let h = &mut rest[0];
                let before = inner(h, h).max(0.0).sqrt();
                for _pass in 0..2 {
                    for q in &done[range.start..] {
                        let p = inner(h, q);
                        h.iter_mut().zip(q).for_each(|(x, y)| *x -= p * y);
                    }
                }
                let after = inner(h, h).max(0.0).sqrt();
                // Also catches NaN: every comparison with NaN is false.
                let independent = after > DEPENDENCE_TOLERANCE * before && after > 0.0;
                if !independent {
                    return Err(HodgeError::DependentForms {
                        component: c,
                        form: i - range.start,
                    });
                }
                let inv = 1.0 / after;
                h.iter_mut().for_each(|x| *x *= inv);
            }
        }
        Ok(())
    }
}

/// A ⋆1-orthonormal basis of harmonic 1-forms (App. C.1 steps I–III), `2g` per closed component
/// of genus g, at the current positions of `mesh`. One-shot wrapper around
/// [`HarmonicBasisSolver`]; a flow should keep the solver and call `compute` each step.
pub fn harmonic_basis(
    mesh: &Mesh,
    topology: &Topology,
    seed: u64,
) -> Result<Vec<Vec<f64>>, HodgeError> {
    let mut solver = HarmonicBasisSolver::new(mesh, topology, seed)?;
    let mut out = Vec::new();
    solver.compute(&mesh.positions, &mut out)?;
    Ok(out)
}

/// The harmonic part `h = α − d1ᵀ β̃ − d0 φ` of an arbitrary 1-form `α`, by the same two Poisson
/// systems as [`HarmonicBasisSolver`] (not normalized): ≈ 0 on a sphere; on a surface of genus
/// g the ⋆1-harmonic form cohomologous to α's closed part. For tests and one-off use: it
/// factors both systems.
pub fn harmonic_component(
    mesh: &Mesh,
    topology: &Topology,
    alpha: &[f64],
) -> Result<Vec<f64>, HodgeError> {
    let n_edges = topology.edges.len();
    if alpha.len() != n_edges {
        return Err(HodgeError::FormLength {
            index: 0,
            got: alpha.len(),
            expected: n_edges,
        });
    }
    let mut closed = vec![alpha.to_vec()];
    DualPoisson::new(mesh, topology, 1)?.project_closed(mesh, topology, &mut closed)?;
    let mut vertex = VertexPoisson::new(mesh, topology, 1)?;
    vertex.refill(&mesh.positions)?;
    let mut out = vec![Vec::new()];
    vertex.remove_exact(&closed, &mut out)?;
    Ok(out.pop().unwrap_or_default())
}

// ---------------------------------------------------------------------------------------------
// Harmonic vector fields (App. C.1 step IV)
// ---------------------------------------------------------------------------------------------

/// Per face, the tangent vector `v` with `⟨v, e1⟩ = ω(e1)` and `⟨v, e2⟩ = ω(e2)` (App. C.1
/// step IV) for the edge vectors `e1 = p1 − p0`, `e2 = p2 − p0` of the face's corners: with
/// `v = a1 e1 + a2 e2`,
///
/// ```text
/// [ |e1|²      ⟨e1, e2⟩ ] [a1]   [ω(e1)]
/// [ ⟨e1, e2⟩   |e2|²    ] [a2] = [ω(e2)]
/// ```
///
/// `ω(e1) = s_0 ω_{e_0}` (edge 0 runs corner 0 → 1) and `ω(e2) = −s_2 ω_{e_2}` (edge 2 runs
/// corner 2 → 0), with `s` the orientation signs of [`d1`]. For a closed ω the third edge is
/// matched too, and `Σ_f A_f ⟨v_f, v'_f⟩ = ωᵀ ⋆1 ω'` (`v_f` is the Whitney interpolant).
/// The system is solved in an orthonormal frame of the face (same solution, better
/// conditioned); a zero-area face gets `v = 0`.
pub fn harmonic_vector_field_into(
    positions: &[[f64; 3]],
    triangles: &[[usize; 3]],
    topology: &Topology,
    form: &[f64],
    out: &mut [[f64; 3]],
) {
    for ((v, tri), fe) in out.iter_mut().zip(triangles).zip(&topology.face_edges) {
        let s = face_edge_signs(tri);
        let p0 = positions[tri[0]];
        let e1 = sub(positions[tri[1]], p0);
        let e2 = sub(positions[tri[2]], p0);
        let w1 = s[0] * form[fe[0]];
        let w2 = -s[2] * form[fe[2]];
        // Solve the Gram system through an orthonormal frame (u1, u2) of the face plane, i.e.
        // a QR factorization of [e1 e2], instead of the normal equations: those square the
        // condition number and lose ~5e-9 relative accuracy on botijo's slivers. In the frame,
        // e1 = (|e1|, 0) and e2 = (x2, y2), so v = (ω1/|e1|) u1 + ((ω2 − x2 v_x)/y2) u2.
        let len1 = norm(e1);
        let u2 = cross(cross(e1, e2), e1);
        let len_u2 = norm(u2);
        *v = if len1 > 0.0 && len_u2 > 0.0 {
            let u1 = scale(e1, 1.0 / len1);
            let u2 = scale(u2, 1.0 / len_u2);
            // Dot products rather than |e1 × e2|/|e1|, so ⟨v, e2⟩ reproduces ω2 even when u2
            // carries rounding error.
            let (x2, y2) = (dot(e2, u1), dot(e2, u2));
            let vx = w1 / len1;
            let vy = if y2 > 0.0 { (w2 - x2 * vx) / y2 } else { 0.0 };
            add(scale(u1, vx), scale(u2, vy))
        } else {
            [0.0; 3]
        };
    }
}

/// [`harmonic_vector_field_into`] for every form (one vector per face and form), at the
/// positions of `mesh`. These are the `v_i` of App. C.1 step IV that the flow feeds to
/// `X Z_i = v_i`.
pub fn harmonic_vector_fields(
    mesh: &Mesh,
    topology: &Topology,
    forms: &[Vec<f64>],
) -> Result<Vec<Vec<[f64; 3]>>, HodgeError> {
    let n_edges = topology.edges.len();
    forms
        .iter()
        .enumerate()
        .map(|(index, form)| {
            if form.len() != n_edges {
                return Err(HodgeError::FormLength {
                    index,
                    got: form.len(),
                    expected: n_edges,
                });
            }
            let mut out = vec![[0.0; 3]; mesh.triangles.len()];
            harmonic_vector_field_into(&mesh.positions, &mesh.triangles, topology, form, &mut out);
            Ok(out)
        })
        .collect()
}
