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

mod harmonic;
mod poisson;

pub use harmonic::{
    harmonic_basis, harmonic_component, harmonic_vector_field_into, harmonic_vector_fields,
    HarmonicBasisSolver,
};

use faer::sparse::{SparseColMat, Triplet};

use super::operators::{barycentric_vertex_areas, corner_cotangents};
use crate::linalg::solver::SolverError;
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
