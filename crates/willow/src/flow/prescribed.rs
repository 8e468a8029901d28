//! Prescribed boundary vectors (§6.3.1), and with `V = B` the CMC boundary condition.
//!
//! At every boundary vertex the frame `T` (boundary tangent), `N` (normal), `B = T × N`
//! (outward conormal) gives a direction `V = cos φ·B + sin φ·N`; the user prescribes a target
//! `Ṽ`. With `θ` the angle from `V` to `Ṽ` and `ŵ = V × Ṽ / |V × Ṽ|`, the unit quaternion
//! `q = cos θ/2 − ŵ sin θ/2` satisfies `q̄ V q = Ṽ` (our edges transform as `ẽ = λ̄ e λ`), and so
//! does every `λ_∂ = q (a − b Ṽ)`, `a, b ∈ ℝ`, up to the scale `a² + b²`: the paper's
//! `λ_∂ = (cos θ/2 − w sin θ/2)(a − bṼ)`. So each boundary λ lives in the real 2-plane
//! `span{q, qṼ}` of ℍ, and the step minimizes `|(D − ρ)λ|²/|λ|²` over λ with that constraint
//! (the eigenproblem of Eq. 5 restricted to a subspace, as in Crane et al. 2011, §5.7).
//!
//! That plane is not a complex line of the complex form of X (it is closed under right
//! multiplication by `Ṽ`, which varies per vertex, not by one fixed unit), so this solver uses
//! the real `4|V|` form: per boundary vertex an orthonormal basis `{q, qṼ, qu₁, qu₂}` of ℍ, the
//! first two columns kept, the last two eliminated as identity rows. The block pattern, its
//! symbolic factorization and every buffer are built once per flow.

use super::dirac::{dirac_face_entry, opposite_edges};
use super::{BoundaryAngles, PrescribedVectors, RotationAxis};
use crate::geometry::vec3::{cross, dot, norm, scale, sub};
use crate::geometry::Quaternion;
use crate::linalg::solver::{BlockPattern, Cholesky};
use crate::mesh::topology::Topology;

/// Largest |φ| accepted: `V` must stay away from `±N`, where the boundary problem stops being
/// elliptic (Bohle and Pinkall 2013, quoted in §6.3.1).
pub const MAX_FRAME_ANGLE: f64 = 1.5;

/// Why prescribed boundary data cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PrescribedError {
    #[error("frame_angle must be finite with |frame_angle| <= {MAX_FRAME_ANGLE} rad (V = ±N is not elliptic), got {0}")]
    FrameAngle(f64),
    #[error("the rotation axis must be finite and non-zero, got {0:?}")]
    Axis([f64; 3]),
    #[error("rotation angles must be finite, got {0}")]
    Angle(f64),
    #[error("{given} per-loop angles given for a mesh with {loops} boundary loops")]
    LoopCount { given: usize, loops: usize },
    #[error("vertex {0} is not a boundary vertex of the mesh")]
    NotBoundary(usize),
    #[error(
        "the boundary frame at vertex {0} is degenerate (zero tangent or normal parallel to it)"
    )]
    DegenerateFrame(usize),
    #[error("{0}")]
    Solver(String),
}

/// The boundary frame `(T, N, B)` at boundary vertex `v` whose loop neighbours are
/// `prev → v → next`: `T` the mean of the two incident boundary edges (§6.3.2: "the mean of
/// incident edge vectors"), `N` the vertex normal made orthogonal to `T`, `B = T × N`.
pub fn boundary_frame(
    positions: &[[f64; 3]],
    normals: &[[f64; 3]],
    prev: usize,
    v: usize,
    next: usize,
) -> Option<[[f64; 3]; 3]> {
    let t = sub(positions[next], positions[prev]);
    let t_len = norm(t);
    if !(t_len > 0.0 && t_len.is_finite()) {
        return None;
    }
    let t = scale(t, 1.0 / t_len);
    let n = normals[v];
    let n = sub(n, scale(t, dot(n, t)));
    let n_len = norm(n);
    if !(n_len > 1e-12 && n_len.is_finite()) {
        return None;
    }
    let n = scale(n, 1.0 / n_len);
    Some([t, n, cross(t, n)])
}

/// `V = cos φ·B + sin φ·N` of a frame `[T, N, B]`.
pub fn frame_vector(frame: &[[f64; 3]; 3], frame_angle: f64) -> [f64; 3] {
    let (s, c) = frame_angle.sin_cos();
    [
        c * frame[2][0] + s * frame[1][0],
        c * frame[2][1] + s * frame[1][1],
        c * frame[2][2] + s * frame[1][2],
    ]
}

/// The unit quaternion `q = cos θ/2 − ŵ sin θ/2` with `q̄ v q = target` for unit vectors `v`
/// and `target`; `fallback_axis` (any unit vector orthogonal to `v`) is used when they are
/// opposite.
pub fn rotation_between(v: [f64; 3], target: [f64; 3], fallback_axis: [f64; 3]) -> Quaternion {
    let c = dot(v, target).clamp(-1.0, 1.0);
    let w = cross(v, target);
    let s = norm(w);
    let axis = if s > 1e-12 {
        scale(w, 1.0 / s)
    } else if c > 0.0 {
        return Quaternion::ONE;
    } else {
        fallback_axis
    };
    let theta = s.atan2(c);
    let (sh, ch) = (0.5 * theta).sin_cos();
    Quaternion::new(ch, -sh * axis[0], -sh * axis[1], -sh * axis[2])
}

/// `v` rotated by `angle` about the unit `axis` (right hand rule; Rodrigues' formula).
pub fn rotate(v: [f64; 3], axis: [f64; 3], angle: f64) -> [f64; 3] {
    let (s, c) = angle.sin_cos();
    let k = cross(axis, v);
    let d = dot(axis, v) * (1.0 - c);
    [
        v[0] * c + k[0] * s + axis[0] * d,
        v[1] * c + k[1] * s + axis[1] * d,
        v[2] * c + k[2] * s + axis[2] * d,
    ]
}

/// Two unit vectors completing unit `v` to a right-handed orthonormal basis.
fn complete_basis(v: [f64; 3]) -> ([f64; 3], [f64; 3]) {
    let helper = if v[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let u1 = cross(v, helper);
    let u1 = scale(u1, 1.0 / norm(u1));
    (u1, cross(v, u1))
}

/// The boundary vertices of a mesh, each with its two neighbours along its loop.
#[derive(Clone, Debug)]
pub struct BoundaryVertices {
    /// `(prev, v, next)` along the loop's orientation.
    pub triples: Vec<[usize; 3]>,
    /// Loop index of each entry of `triples`.
    pub loop_of: Vec<usize>,
    /// For each mesh vertex, its index in `triples`, or `usize::MAX`.
    pub slot: Vec<usize>,
}

impl BoundaryVertices {
    pub fn new(topology: &Topology, vertex_count: usize) -> Self {
        let mut triples = Vec::new();
        let mut loop_of = Vec::new();
        let mut slot = vec![usize::MAX; vertex_count];
        for (l, lp) in topology.boundary_loops.iter().enumerate() {
            let k = lp.vertices.len();
            for i in 0..k {
                let v = lp.vertices[i];
                if slot[v] != usize::MAX {
                    // A vertex on two loops is non-manifold and refused by validation; keep
                    // its first frame if it ever happens.
                    continue;
                }
                slot[v] = triples.len();
                triples.push([lp.vertices[(i + k - 1) % k], v, lp.vertices[(i + 1) % k]]);
                loop_of.push(l);
            }
        }
        BoundaryVertices {
            triples,
            loop_of,
            slot,
        }
    }

    pub fn len(&self) -> usize {
        self.triples.len()
    }

    pub fn is_empty(&self) -> bool {
        self.triples.is_empty()
    }
}

impl PrescribedVectors {
    /// The checks that need no mesh, each with the field path that names it in a job spec:
    /// φ away from ±π/2 (§6.3.1: `V = ±N` is not elliptic), a finite non-zero fixed axis,
    /// finite angles.
    pub fn validate(&self) -> Result<(), (&'static str, PrescribedError)> {
        if !(self.frame_angle.is_finite() && self.frame_angle.abs() <= MAX_FRAME_ANGLE) {
            return Err((
                "boundary.prescribed.frame_angle",
                PrescribedError::FrameAngle(self.frame_angle),
            ));
        }
        if let RotationAxis::Fixed(a) = self.axis {
            let len = norm(a);
            if !(a.iter().all(|c| c.is_finite()) && len.is_finite() && len > 0.0) {
                return Err(("boundary.prescribed.axis.fixed", PrescribedError::Axis(a)));
            }
        }
        let bad = |a: &f64| !a.is_finite();
        match &self.angles {
            BoundaryAngles::Uniform(a) if bad(a) => Err((
                "boundary.prescribed.angles.uniform",
                PrescribedError::Angle(*a),
            )),
            BoundaryAngles::PerLoop(list) => match list.iter().find(|a| bad(a)) {
                Some(a) => Err((
                    "boundary.prescribed.angles.per_loop",
                    PrescribedError::Angle(*a),
                )),
                None => Ok(()),
            },
            BoundaryAngles::PerVertex(list) => match list.iter().find(|(_, a)| bad(a)) {
                Some((_, a)) => Err((
                    "boundary.prescribed.angles.per_vertex",
                    PrescribedError::Angle(*a),
                )),
                None => Ok(()),
            },
            BoundaryAngles::Uniform(_) => Ok(()),
        }
    }
}

/// The targets `Ṽ` of §6.3.1 on the input surface: its `V` rotated as `spec` says.
pub fn boundary_targets(
    spec: &PrescribedVectors,
    boundary: &BoundaryVertices,
    loop_count: usize,
    positions: &[[f64; 3]],
    normals: &[[f64; 3]],
) -> Result<Vec<[f64; 3]>, PrescribedError> {
    spec.validate().map_err(|(_, e)| e)?;
    let fixed_axis = match spec.axis {
        RotationAxis::Tangent => None,
        RotationAxis::Fixed(a) => {
            let len = norm(a);
            if !(len.is_finite() && len > 0.0) {
                return Err(PrescribedError::Axis(a));
            }
            Some(scale(a, 1.0 / len))
        }
    };
    let mut angles = vec![0.0; boundary.len()];
    match &spec.angles {
        BoundaryAngles::Uniform(a) => angles.fill(*a),
        BoundaryAngles::PerLoop(per_loop) => {
            if per_loop.len() != loop_count {
                return Err(PrescribedError::LoopCount {
                    given: per_loop.len(),
                    loops: loop_count,
                });
            }
            for (a, &l) in angles.iter_mut().zip(&boundary.loop_of) {
                *a = per_loop[l];
            }
        }
        BoundaryAngles::PerVertex(list) => {
            for &(v, a) in list {
                let s = boundary.slot.get(v).copied().unwrap_or(usize::MAX);
                if s == usize::MAX {
                    return Err(PrescribedError::NotBoundary(v));
                }
                angles[s] = a;
            }
        }
    }
    boundary
        .triples
        .iter()
        .zip(&angles)
        .map(|(&[prev, v, next], &angle)| {
            let frame = boundary_frame(positions, normals, prev, v, next)
                .ok_or(PrescribedError::DegenerateFrame(v))?;
            let vv = frame_vector(&frame, spec.frame_angle);
            let axis = fixed_axis.unwrap_or(frame[0]);
            Ok(rotate(vv, axis, angle))
        })
        .collect()
}

/// Whether unknown `k` (of `4|V|`) is eliminated: the last two basis directions of a
/// boundary vertex (`slot` as in [`BoundaryVertices::slot`]).
#[inline]
fn eliminated(slot: &[usize], k: usize) -> bool {
    k % 4 >= 2 && slot[k / 4] != usize::MAX
}

/// The λ solve of one step under prescribed boundary vectors (see the module docs).
pub struct PrescribedSolver {
    boundary: BoundaryVertices,
    targets: Vec<[f64; 3]>,
    frame_angle: f64,
    /// Per boundary vertex, the orthonormal basis `{q, qṼ, qu₁, qu₂}` of this step.
    basis: Vec<[Quaternion; 4]>,
    pattern: BlockPattern,
    values: Vec<f64>,
    cholesky: Cholesky<f64>,
    shift: Vec<f64>,
    x: Vec<f64>,
    product: Vec<f64>,
    norms: Vec<f64>,
    areas: Vec<f64>,
}

/// How the solver's caller describes the current surface.
pub struct SurfaceState<'a> {
    pub positions: &'a [[f64; 3]],
    pub triangles: &'a [[usize; 3]],
    pub face_areas: &'a [f64],
    pub vertex_areas: &'a [f64],
    pub normals: &'a [[f64; 3]],
    pub vertex_component: &'a [usize],
}

impl PrescribedSolver {
    pub fn new(
        spec: &PrescribedVectors,
        topology: &Topology,
        positions: &[[f64; 3]],
        triangles: &[[usize; 3]],
        normals: &[[f64; 3]],
        n_components: usize,
    ) -> Result<Self, PrescribedError> {
        let n = positions.len();
        let boundary = BoundaryVertices::new(topology, n);
        let targets = boundary_targets(
            spec,
            &boundary,
            topology.boundary_loops.len(),
            positions,
            normals,
        )?;
        let pattern = BlockPattern::new(n, triangles, 4);
        let cholesky = Cholesky::<f64>::analyze(&pattern, 1)
            .map_err(|e| PrescribedError::Solver(e.to_string()))?;
        Ok(PrescribedSolver {
            basis: vec![[Quaternion::ONE; 4]; boundary.len()],
            boundary,
            targets,
            frame_angle: spec.frame_angle,
            values: vec![0.0; pattern.nnz()],
            pattern,
            cholesky,
            shift: vec![0.0; n],
            x: vec![0.0; 4 * n],
            product: vec![0.0; 4 * n],
            norms: vec![0.0; n_components],
            areas: vec![0.0; n_components],
        })
    }

    /// The targets `Ṽ`, one per boundary vertex in [`PrescribedSolver::boundary`] order.
    pub fn targets(&self) -> &[[f64; 3]] {
        &self.targets
    }

    pub fn boundary(&self) -> &BoundaryVertices {
        &self.boundary
    }

    /// Per boundary vertex, the rotation `q` and the basis of ℍ whose first two elements span
    /// the admissible λ: `{q, qṼ, qu₁, qu₂}`.
    fn update_basis(&mut self, s: &SurfaceState<'_>) -> Result<(), PrescribedError> {
        for ((basis, &[prev, v, next]), &target) in self
            .basis
            .iter_mut()
            .zip(&self.boundary.triples)
            .zip(&self.targets)
        {
            let frame = boundary_frame(s.positions, s.normals, prev, v, next)
                .ok_or(PrescribedError::DegenerateFrame(v))?;
            let current = frame_vector(&frame, self.frame_angle);
            let q = rotation_between(current, target, frame[0]);
            let (u1, u2) = complete_basis(target);
            *basis = [
                q,
                q * Quaternion::imaginary(target),
                q * Quaternion::imaginary(u1),
                q * Quaternion::imaginary(u2),
            ];
        }
        Ok(())
    }

    /// `Qᵀ L` (rows) for a boundary row vertex, `L Q` (columns) for a boundary column vertex,
    /// with `L` the real left-multiplication matrix of `x` and `Q` the basis as columns.
    fn transformed_block(
        x: Quaternion,
        row_basis: Option<&[Quaternion; 4]>,
        col_basis: Option<&[Quaternion; 4]>,
    ) -> [[f64; 4]; 4] {
        // Entry (r, c) = ⟨b_r, x b_c⟩ with b the basis (standard basis when absent): the real
        // inner product of quaternions is Re(ā b).
        let standard = [
            Quaternion::ONE,
            Quaternion::new(0.0, 1.0, 0.0, 0.0),
            Quaternion::new(0.0, 0.0, 1.0, 0.0),
            Quaternion::new(0.0, 0.0, 0.0, 1.0),
        ];
        if row_basis.is_none() && col_basis.is_none() {
            return x.to_real();
        }
        let rows = row_basis.unwrap_or(&standard);
        let cols = col_basis.unwrap_or(&standard);
        let mut out = [[0.0; 4]; 4];
        for (c, bc) in cols.iter().enumerate() {
            let xb = x * *bc;
            for (r, br) in rows.iter().enumerate() {
                out[r][c] = br.w * xb.w + br.x * xb.x + br.y * xb.y + br.z * xb.z;
            }
        }
        out
    }

    #[inline]
    fn eliminated(&self, k: usize) -> bool {
        eliminated(&self.boundary.slot, k)
    }

    /// Assemble the reduced real `X(ρ)` (App. G, one face at a time) in the boundary bases.
    /// Returns the mean diagonal without shift.
    fn assemble(&mut self, s: &SurfaceState<'_>, rho: &[f64]) -> f64 {
        self.values.fill(0.0);
        let mut trace = 0.0;
        let slot_of = &self.boundary.slot;
        for ((tri, slots), &area) in s
            .triangles
            .iter()
            .zip(&self.pattern.face_slots)
            .zip(s.face_areas)
        {
            let e = opposite_edges(s.positions, tri);
            let basis_of = |v: usize| {
                let k = slot_of[v];
                (k != usize::MAX).then(|| &self.basis[k])
            };
            for a in 0..3 {
                for b in a..3 {
                    let q = dirac_face_entry(e[a], e[b], rho[tri[a]], rho[tri[b]], area);
                    let m = Self::transformed_block(q, basis_of(tri[a]), basis_of(tri[b]));
                    let (slot, st) = (slots[3 * a + b], self.pattern.column_stride(tri[b]));
                    for (r, row) in m.iter().enumerate() {
                        for (c, &value) in row.iter().enumerate() {
                            self.values[slot + c * st + r] += value;
                        }
                    }
                    if a == b {
                        trace += q.w;
                    } else {
                        // Block (b, a) is the transpose.
                        let (slot, st) = (slots[3 * b + a], self.pattern.column_stride(tri[a]));
                        for (r, row) in m.iter().enumerate() {
                            for (c, &value) in row.iter().enumerate() {
                                self.values[slot + r * st + c] += value;
                            }
                        }
                    }
                }
            }
        }
        // Eliminate the inadmissible directions: identity rows and columns.
        let col_ptr = self.pattern.symbolic.col_ptr();
        let row_idx = self.pattern.symbolic.row_idx();
        for col in 0..self.pattern.dim() {
            let col_out = self.eliminated(col);
            for idx in col_ptr[col]..col_ptr[col + 1] {
                let row = row_idx[idx];
                if col_out || self.eliminated(row) {
                    self.values[idx] = if row == col { 1.0 } else { 0.0 };
                }
            }
        }
        trace / s.positions.len().max(1) as f64
    }

    /// Smallest eigenvector of the reduced `X(ρ)` by `iterations` inverse iterations from
    /// `λ ≡ 1` (projected onto the admissible planes), written to `lambda`; returns the
    /// eigen-residual `|Xλ − γMλ| / |Xλ|`.
    pub fn solve(
        &mut self,
        s: &SurfaceState<'_>,
        rho: &[f64],
        iterations: usize,
        relative_shift: f64,
        retries: usize,
        lambda: &mut [Quaternion],
    ) -> Result<f64, PrescribedError> {
        let n = s.positions.len();
        self.update_basis(s)?;
        let mean_diagonal = self.assemble(s, rho);
        let mean_area = s.vertex_areas.iter().sum::<f64>() / n.max(1) as f64;
        self.shift.fill(0.0);
        let mut attempt = 0;
        loop {
            let eps = relative_shift * 100f64.powi(attempt as i32) * mean_diagonal;
            for (v, (sh, &a)) in self.shift.iter_mut().zip(s.vertex_areas).enumerate() {
                let target = eps * a / mean_area;
                let slot = self.pattern.diagonal_slot(v);
                for r in 0..4 {
                    if !eliminated(&self.boundary.slot, 4 * v + r) {
                        self.values[self.pattern.entry(slot, v, r, r)] += target - *sh;
                    }
                }
                *sh = target;
            }
            match self.cholesky.factorize(&self.pattern, &self.values) {
                Ok(()) => break,
                Err(e) if attempt >= retries => {
                    return Err(PrescribedError::Solver(format!("Dirac matrix X: {e}")))
                }
                Err(_) => attempt += 1,
            }
        }

        // Start from λ ≡ 1 expressed in each vertex's basis, inadmissible parts dropped.
        for v in 0..n {
            let k = self.boundary.slot[v];
            let coords = if k == usize::MAX {
                [1.0, 0.0, 0.0, 0.0]
            } else {
                let b = &self.basis[k];
                [b[0].w, b[1].w, 0.0, 0.0]
            };
            self.x[4 * v..4 * v + 4].copy_from_slice(&coords);
        }
        for _ in 0..iterations.max(1) {
            for (v, &a) in s.vertex_areas.iter().enumerate() {
                for r in 0..4 {
                    self.x[4 * v + r] *= a;
                }
            }
            self.cholesky.solve_in_place(&mut self.x, 1);
            self.normalize_per_component(s);
        }
        if self.x.iter().any(|c| !c.is_finite()) {
            return Err(PrescribedError::Solver(
                "the eigenvector λ is not finite".into(),
            ));
        }
        for (v, l) in lambda.iter_mut().enumerate() {
            let c = &self.x[4 * v..4 * v + 4];
            let k = self.boundary.slot[v];
            *l = if k == usize::MAX {
                Quaternion::new(c[0], c[1], c[2], c[3])
            } else {
                let b = &self.basis[k];
                b[0].scale(c[0]) + b[1].scale(c[1])
            };
        }
        Ok(self.eigen_residual(s))
    }

    fn normalize_per_component(&mut self, s: &SurfaceState<'_>) {
        self.norms.fill(0.0);
        self.areas.fill(0.0);
        for (v, (&a, &c)) in s.vertex_areas.iter().zip(s.vertex_component).enumerate() {
            let x = &self.x[4 * v..4 * v + 4];
            self.norms[c] += a * (x[0] * x[0] + x[1] * x[1] + x[2] * x[2] + x[3] * x[3]);
            self.areas[c] += a;
        }
        for (v, &c) in s.vertex_component.iter().enumerate() {
            let f = if self.norms[c] > 0.0 {
                (self.areas[c] / self.norms[c]).sqrt()
            } else {
                1.0
            };
            for r in 0..4 {
                self.x[4 * v + r] *= f;
            }
        }
    }

    /// `|Xλ − γMλ| / |Xλ|` on the reduced X without its shift, γ the Rayleigh quotient.
    fn eigen_residual(&mut self, s: &SurfaceState<'_>) -> f64 {
        self.product.fill(0.0);
        let col_ptr = self.pattern.symbolic.col_ptr();
        let row_idx = self.pattern.symbolic.row_idx();
        for (col, &xc) in self.x.iter().enumerate() {
            if self.eliminated(col) {
                continue;
            }
            for idx in col_ptr[col]..col_ptr[col + 1] {
                self.product[row_idx[idx]] += self.values[idx] * xc;
            }
        }
        let (mut x_dot, mut m_dot) = (0.0, 0.0);
        for k in 0..self.x.len() {
            if self.eliminated(k) {
                self.product[k] = 0.0;
                continue;
            }
            let v = k / 4;
            self.product[k] -= self.shift[v] * self.x[k];
            x_dot += self.x[k] * self.product[k];
            m_dot += self.x[k] * self.x[k] * s.vertex_areas[v];
        }
        let gamma = if m_dot > 0.0 { x_dot / m_dot } else { 0.0 };
        let (mut res, mut norm) = (0.0, 0.0);
        for k in 0..self.x.len() {
            let r = self.product[k] - gamma * s.vertex_areas[k / 4] * self.x[k];
            res += r * r;
            norm += self.product[k] * self.product[k];
        }
        if norm > 0.0 {
            (res / norm).sqrt()
        } else {
            0.0
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: [f64; 3], b: [f64; 3]) -> bool {
        norm(sub(a, b)) < 1e-12
    }

    #[test]
    fn the_rotation_maps_v_to_the_target_under_the_edge_transformation() {
        // q̄ V q = Ṽ, and so does q(a − bṼ) up to the scale a² + b² (§6.3.1).
        let v = [0.0, 0.6, 0.8];
        let target = rotate(v, [1.0, 0.0, 0.0], 0.7);
        let q = rotation_between(v, target, [1.0, 0.0, 0.0]);
        let moved = (q.conj() * Quaternion::imaginary(v) * q).vector();
        assert!(close(moved, target), "{moved:?} vs {target:?}");
        let (a, b) = (0.3, -1.7);
        let lambda = q * (Quaternion::real(a) - Quaternion::imaginary(target).scale(b));
        let moved = (lambda.conj() * Quaternion::imaginary(v) * lambda).vector();
        assert!(close(moved, scale(target, a * a + b * b)));
    }

    #[test]
    fn opposite_vectors_rotate_about_the_fallback_axis() {
        let q = rotation_between([0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]);
        let moved = (q.conj() * Quaternion::imaginary([0.0, 0.0, 1.0]) * q).vector();
        assert!(close(moved, [0.0, 0.0, -1.0]));
        let same = rotation_between([0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]);
        assert_eq!(same, Quaternion::ONE);
    }

    #[test]
    fn the_frame_of_a_unit_circle_has_the_outward_conormal() {
        // A disk in the xy-plane with normal +z, its boundary counter-clockwise (the surface
        // on the left): at (1, 0, 0), T = +y, N = +z and B = T × N = +x points outward.
        let positions = [[0.0, -0.1, 0.0], [1.0, 0.0, 0.0], [0.0, 0.1, 0.0]];
        let normals = [[0.0, 0.0, 1.0]; 3];
        let frame = boundary_frame(&positions, &normals, 0, 1, 2).expect("frame");
        assert!(close(frame[0], [0.0, 1.0, 0.0]));
        assert!(close(frame[1], [0.0, 0.0, 1.0]));
        assert!(close(frame[2], [1.0, 0.0, 0.0]));
        let v = frame_vector(&frame, std::f64::consts::FRAC_PI_2);
        assert!(close(v, [0.0, 0.0, 1.0]));
    }

    #[test]
    fn rodrigues_rotates_right_handed() {
        let r = rotate(
            [1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0],
            std::f64::consts::FRAC_PI_2,
        );
        assert!(close(r, [0.0, 1.0, 0.0]));
    }

    #[test]
    fn the_transformed_block_is_the_quaternion_form_in_the_new_bases() {
        // ⟨Q_i r, x Q_j s⟩ = ⟨r, (Q_iᵀ L(x) Q_j) s⟩ for any quaternion x.
        let x = Quaternion::new(0.3, -1.2, 0.5, 2.0);
        let q = rotation_between([0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [1.0, 0.0, 0.0]);
        let t = Quaternion::imaginary([0.6, 0.0, 0.8]);
        let (u1, u2) = complete_basis([0.6, 0.0, 0.8]);
        let basis = [
            q,
            q * t,
            q * Quaternion::imaginary(u1),
            q * Quaternion::imaginary(u2),
        ];
        let m = PrescribedSolver::transformed_block(x, Some(&basis), None);
        let l = x.to_real();
        for r in 0..4 {
            for c in 0..4 {
                let b = [basis[r].w, basis[r].x, basis[r].y, basis[r].z];
                let expected: f64 = (0..4).map(|k| b[k] * l[k][c]).sum();
                assert!((m[r][c] - expected).abs() < 1e-12);
            }
        }
        // The basis is orthonormal.
        for a in 0..4 {
            for b in 0..4 {
                let d = basis[a].w * basis[b].w
                    + basis[a].x * basis[b].x
                    + basis[a].y * basis[b].y
                    + basis[a].z * basis[b].z;
                assert!((d - if a == b { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
    }
}
