//! The two Poisson systems behind the harmonic 1-forms (App. C.1 steps I–II): the dual-face
//! system that makes a random 1-form closed ([`DualPoisson`], factored once per connectivity)
//! and the vertex system that removes its exact part ([`VertexPoisson`], refilled per step).

use super::super::operators::corner_cotangents_into;
use super::{face_edge_signs, HodgeError, PoissonSystem, POISSON_TOLERANCE};
use crate::linalg::solver::{BlockPattern, Cholesky};
use crate::mesh::{Mesh, Topology};

/// Number of independent harmonic 1-forms of one component: its first Betti number. For a
/// closed surface of genus g that is `2g` (App. C); a surface with `b ≥ 1` boundary loops has
/// `2g + b − 1` (the annulus of §6.2 has one), represented by the closed forms that are
/// co-closed with natural (Neumann) conditions at the boundary vertices.
pub(super) fn betti_1(component: &crate::mesh::topology::Component) -> usize {
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
pub(super) struct DualPoisson {
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
    pub(super) fn new(mesh: &Mesh, topology: &Topology, nrhs: usize) -> Result<Self, HodgeError> {
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
    pub(super) fn project_closed(
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
pub(super) struct VertexPoisson {
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
    pub(super) weights: Vec<f64>,
    /// Matrix values, plus one trailing sink slot.
    values: Vec<f64>,
    /// Column-major `|V| × nrhs` right-hand sides, overwritten by the solutions φ.
    rhs: Vec<f64>,
    rhs_norms: Vec<f64>,
    scratch: Vec<f64>,
    nrhs: usize,
}

impl VertexPoisson {
    pub(super) fn new(mesh: &Mesh, topology: &Topology, nrhs: usize) -> Result<Self, HodgeError> {
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

    pub(super) fn vertex_count(&self) -> usize {
        self.pinned.len()
    }

    /// Cotangents, `⋆1` and the numeric factorization of the pinned `L` at `positions`.
    pub(super) fn refill(&mut self, positions: &[[f64; 3]]) -> Result<(), HodgeError> {
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
    pub(super) fn remove_exact(
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
