//! The harmonic 1-forms and vector fields of a mesh (App. C.1 steps I–IV): built once per
//! connectivity by [`HarmonicBasisSolver`] over the two systems of [`super::poisson`], and
//! refilled per flow step.

use super::super::vec3::{add, cross, dot, norm, scale, sub};
use super::poisson::{betti_1, DualPoisson, VertexPoisson};
use super::{face_edge_signs, HodgeError, DEPENDENCE_TOLERANCE};
use crate::mesh::generate::SplitMix64;
use crate::mesh::{Mesh, Topology};

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
///    [`POISSON_TOLERANCE`](super::POISSON_TOLERANCE).
/// 3. Modified Gram–Schmidt in ⋆1, each form orthogonalized twice ("twice is enough"). `⋆1` is
///    indefinite on non-Delaunay meshes, but on *closed* forms `ωᵀ ⋆1 ω = Σ_f A_f |v_f|²` with
///    `v_f` the per-face vector of [`harmonic_vector_fields`] (the cotan formula is the exact
///    Dirichlet energy of a linear function), so it is a true inner product on harmonic forms.
///
/// The harmonic forms are therefore not the ⋆1-orthogonal projections of the random `α_i`, but
/// they span the same space (all harmonic forms), which is all the exactness constraint uses.
///
/// Reused between steps: the fixed closed forms `α_c` (the dual system is factored and solved
/// once, in `new`), the vertex-graph [`BlockPattern`](crate::linalg::solver::BlockPattern), its AMD ordering and symbolic Cholesky,
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
/// corner 2 → 0), with `s` the orientation signs of [`d1`](super::d1). For a closed ω the
/// third edge is matched too, and `Σ_f A_f ⟨v_f, v'_f⟩ = ωᵀ ⋆1 ω'` (`v_f` is the Whitney
/// interpolant). The system is solved in an orthonormal frame of the face (same solution, better
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
