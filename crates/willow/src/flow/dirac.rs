//! The quaternionic Dirac matrix with potential, `X(ρ)` of Appendix G, in complex form.
//!
//! For every face `k` (area `A_k`) and every ordered pair of its corners `(i, j)`:
//!
//! `X_ij += −e_i e_j / (4 A_k) + (ρ_i e_j − ρ_j e_i) / 6 + A_k ρ_i ρ_j / 9`
//!
//! with `e_i` the edge opposite corner `i` as an imaginary quaternion, oriented cyclically
//! (`e_i = p_{i+2} − p_{i+1}`). Per face this is `A_k · c̄_i c_j` with `c_i = −e_i/(2A_k) − ρ_i/3`,
//! i.e. `X = (D − ρ)* M (D − ρ)`: quaternion-Hermitian and positive semidefinite, with the
//! constant quaternions as kernel at `ρ = 0`. `X_ij` acts on `λ_j` by left multiplication.
//!
//! Each quaternion entry is stored as its 2×2 complex matrix ([`Quaternion::to_complex`]), so
//! X is a complex Hermitian `2|V| × 2|V|` matrix: half the factorization time and memory of the
//! real `4|V|` form with identical λ (docs/solver.md, "the complex form").

use crate::geometry::vec3::sub;
use crate::geometry::Quaternion;
#[cfg(doc)]
use crate::linalg::solver::Cholesky;
use crate::linalg::solver::{BlockPattern, SolverError};
use faer::c64;

/// The per-face quaternion `X_ij` of Appendix G.
#[inline]
pub fn dirac_face_entry(
    e_i: Quaternion,
    e_j: Quaternion,
    rho_i: f64,
    rho_j: f64,
    area: f64,
) -> Quaternion {
    (e_i * e_j).scale(-1.0 / (4.0 * area))
        + (e_j.scale(rho_i) - e_i.scale(rho_j)).scale(1.0 / 6.0)
        + Quaternion::real(area * rho_i * rho_j / 9.0)
}

/// The three edge vectors of a face opposite its corners, as imaginary quaternions.
#[inline]
pub fn opposite_edges(positions: &[[f64; 3]], tri: &[usize; 3]) -> [Quaternion; 3] {
    let p = [positions[tri[0]], positions[tri[1]], positions[tri[2]]];
    [
        Quaternion::imaginary(sub(p[2], p[1])),
        Quaternion::imaginary(sub(p[0], p[2])),
        Quaternion::imaginary(sub(p[1], p[0])),
    ]
}

/// Refill `values` (on a block-2 `pattern`) with `X(ρ) + diag(shift_i)`; returns the mean
/// real diagonal of `X(ρ)` without the shift (the scale a relative shift refers to).
///
/// Each unordered corner pair is computed once: `X_ji = conj(X_ij)`, whose complex block is
/// the conjugate transpose of `X_ij`'s.
pub fn assemble_dirac_into(
    pattern: &BlockPattern,
    positions: &[[f64; 3]],
    triangles: &[[usize; 3]],
    face_areas: &[f64],
    rho: &[f64],
    shift: &[f64],
    values: &mut [c64],
) -> f64 {
    debug_assert_eq!(pattern.block, 2);
    values.fill(c64::new(0.0, 0.0));
    let mut trace = 0.0;
    for ((tri, slots), &area) in triangles.iter().zip(&pattern.face_slots).zip(face_areas) {
        let e = opposite_edges(positions, tri);
        let stride = [
            pattern.column_stride(tri[0]),
            pattern.column_stride(tri[1]),
            pattern.column_stride(tri[2]),
        ];
        for a in 0..3 {
            for b in a..3 {
                let q = dirac_face_entry(e[a], e[b], rho[tri[a]], rho[tri[b]], area);
                let m = q.to_complex();
                // Block (a, b): column vertex tri[b].
                let (slot, st) = (slots[3 * a + b], stride[b]);
                values[slot] += m[0][0];
                values[slot + 1] += m[1][0];
                values[slot + st] += m[0][1];
                values[slot + st + 1] += m[1][1];
                if a == b {
                    trace += q.w;
                } else {
                    // Block (b, a) = conjugate transpose, in column vertex tri[a].
                    let (slot, st) = (slots[3 * b + a], stride[a]);
                    values[slot] += m[0][0].conj();
                    values[slot + 1] += m[0][1].conj();
                    values[slot + st] += m[1][0].conj();
                    values[slot + st + 1] += m[1][1].conj();
                }
            }
        }
    }
    for (v, &s) in shift.iter().enumerate() {
        let slot = pattern.diagonal_slot(v);
        values[pattern.entry(slot, v, 0, 0)] += c64::new(s, 0.0);
        values[pattern.entry(slot, v, 1, 1)] += c64::new(s, 0.0);
    }
    if shift.is_empty() {
        0.0
    } else {
        trace / shift.len() as f64
    }
}

/// Marks a [`TriangleAssembly`] target that receives the conjugate of the assembled value.
const CONJ_BIT: u32 = 1 << 31;

/// `X(ρ)` assembled straight into the permuted triangle a [`Cholesky`] factors, skipping the
/// full (both triangles) storage.
///
/// The faces first sum their quaternion entries `X_ij` per vertex pair and per vertex (one
/// quaternion per edge, one real per vertex: `X_ii` is real), a working set small enough to
/// stay in L2; one pass then writes every entry of the triangle exactly once, in the order of
/// its storage. Scattering each face's 21 complex entries into the triangle directly (1.6 MB
/// at 13k faces, larger than L2) was bound by cache misses. Each entry receives the same
/// contributions in the same (face) order as a full-storage assembly, and the complex form
/// and conjugation are exact, so the triangle, and with it the factor, is bit for bit the
/// same.
pub struct TriangleAssembly {
    /// Per face, for the corner pairs (0,1), (0,2), (1,2): the edge index, with [`CONJ_BIT`]
    /// set when the edge accumulates `conj(X_ab)` (its reference block is `X_ba`).
    face_edges: Vec<[u32; 3]>,
    /// Per edge, the triangle positions of the entries `00, 10, 01, 11` of its reference block
    /// `X_uv` (`u > v`), with [`CONJ_BIT`] set where the triangle holds the conjugate.
    edge_targets: Vec<[u32; 4]>,
    /// Per vertex, the positions of its diagonal block's `00`, `10`, `11`.
    diagonal_targets: Vec<[u32; 3]>,
    edge_sums: Vec<Quaternion>,
    diagonal_sums: Vec<f64>,
}

impl TriangleAssembly {
    /// `slots` is the factor's [`Cholesky::triangle_slots`] for `pattern`.
    pub fn new(
        pattern: &BlockPattern,
        triangles: &[[usize; 3]],
        slots: &[Option<(u32, bool)>],
    ) -> Result<Self, SolverError> {
        debug_assert_eq!(pattern.block, 2);
        let target = |k: usize| -> Result<u32, SolverError> {
            let (t, conj) = slots[k].ok_or_else(|| {
                SolverError::Symbolic(format!("entry {k} is not in the factored triangle"))
            })?;
            if t >= CONJ_BIT {
                return Err(SolverError::OutOfMemory);
            }
            Ok(if conj { t | CONJ_BIT } else { t })
        };
        // Edges numbered in the order their reference blocks first appear; the block's base
        // index in the full pattern identifies the vertex pair.
        // Indexed by the vertex pair's position in the vertex-level pattern (a hash map here
        // took 2.6 s of the setup at 1.3M triangles).
        let mut edge_of_pair = vec![u32::MAX; pattern.vertex_nnz()];
        let mut edge_targets = Vec::new();
        let mut face_edges = Vec::with_capacity(triangles.len());
        for (tri, face_slots) in triangles.iter().zip(&pattern.face_slots) {
            let mut edges = [0u32; 3];
            for (k, (a, b)) in [(0, 1), (0, 2), (1, 2)].into_iter().enumerate() {
                // The reference block is the one in the caller's lower triangle (u > v),
                // whose four entries the factor gathers.
                let (u, v, conj) = if tri[a] > tri[b] {
                    (a, b, false)
                } else {
                    (b, a, true)
                };
                let slot = face_slots[3 * u + v];
                let next = u32::try_from(edge_targets.len())
                    .ok()
                    .filter(|&e| e < CONJ_BIT)
                    .ok_or(SolverError::OutOfMemory)?;
                let pair = &mut edge_of_pair[pattern.pair_index(slot, tri[v])];
                if *pair == u32::MAX {
                    *pair = next;
                }
                let edge = *pair;
                if edge == next {
                    let j = tri[v];
                    edge_targets.push([
                        target(pattern.entry(slot, j, 0, 0))?,
                        target(pattern.entry(slot, j, 1, 0))?,
                        target(pattern.entry(slot, j, 0, 1))?,
                        target(pattern.entry(slot, j, 1, 1))?,
                    ]);
                }
                edges[k] = if conj { edge | CONJ_BIT } else { edge };
            }
            face_edges.push(edges);
        }
        let n = pattern.dim() / 2;
        let mut diagonal_targets = Vec::with_capacity(n);
        for v in 0..n {
            let slot = pattern.diagonal_slot(v);
            diagonal_targets.push([
                target(pattern.entry(slot, v, 0, 0))?,
                target(pattern.entry(slot, v, 1, 0))?,
                target(pattern.entry(slot, v, 1, 1))?,
            ]);
        }
        let edge_count = edge_targets.len();
        Ok(TriangleAssembly {
            face_edges,
            edge_targets,
            diagonal_targets,
            edge_sums: vec![Quaternion::default(); edge_count],
            diagonal_sums: vec![0.0; n],
        })
    }

    /// Refill `values` (the factor's triangle) with `X(ρ)`; returns the mean real diagonal
    /// (see [`assemble_dirac_into`]).
    pub fn assemble(
        &mut self,
        positions: &[[f64; 3]],
        triangles: &[[usize; 3]],
        face_areas: &[f64],
        rho: &[f64],
        values: &mut [c64],
    ) -> f64 {
        self.edge_sums.fill(Quaternion::default());
        self.diagonal_sums.fill(0.0);
        // Summed face by face in the full assembly's order, so the mean is the same too.
        let mut trace = 0.0;
        for ((tri, edges), &area) in triangles.iter().zip(&self.face_edges).zip(face_areas) {
            let e = opposite_edges(positions, tri);
            for a in 0..3 {
                // X_aa is real: e_a e_a = −|e_a|², and the ρ terms cancel.
                let d = dirac_face_entry(e[a], e[a], rho[tri[a]], rho[tri[a]], area).w;
                self.diagonal_sums[tri[a]] += d;
                trace += d;
            }
            for (&edge, (a, b)) in edges.iter().zip([(0, 1), (0, 2), (1, 2)]) {
                let q = dirac_face_entry(e[a], e[b], rho[tri[a]], rho[tri[b]], area);
                if edge & CONJ_BIT == 0 {
                    self.edge_sums[edge as usize] += q;
                } else {
                    self.edge_sums[(edge & !CONJ_BIT) as usize] += q.conj();
                }
            }
        }
        #[inline(always)]
        fn set(values: &mut [c64], target: u32, z: c64) {
            if target & CONJ_BIT == 0 {
                values[target as usize] = z;
            } else {
                values[(target & !CONJ_BIT) as usize] = z.conj();
            }
        }
        for (targets, q) in self.edge_targets.iter().zip(&self.edge_sums) {
            let m = q.to_complex();
            set(values, targets[0], m[0][0]);
            set(values, targets[1], m[1][0]);
            set(values, targets[2], m[0][1]);
            set(values, targets[3], m[1][1]);
        }
        for (targets, &d) in self.diagonal_targets.iter().zip(&self.diagonal_sums) {
            let m = Quaternion::real(d).to_complex();
            set(values, targets[0], m[0][0]);
            set(values, targets[1], m[1][0]);
            set(values, targets[2], m[1][1]);
        }
        if self.diagonal_targets.is_empty() {
            0.0
        } else {
            trace / self.diagonal_targets.len() as f64
        }
    }

    /// Add the real `value` to both diagonal entries of vertex `v`'s block.
    #[inline]
    pub fn add_to_diagonal(&self, v: usize, value: f64, values: &mut [c64]) {
        let [d0, _, d1] = self.diagonal_targets[v];
        for t in [d0, d1] {
            values[(t & !CONJ_BIT) as usize] += c64::new(value, 0.0);
        }
    }
}

/// `y = A x` for a matrix stored on the full (both triangles) pattern.
pub fn sparse_matvec(pattern: &BlockPattern, values: &[c64], x: &[c64], y: &mut [c64]) {
    y.fill(c64::new(0.0, 0.0));
    let col_ptr = pattern.symbolic.col_ptr();
    let row_idx = pattern.symbolic.row_idx();
    for (col, &xc) in x.iter().enumerate() {
        for idx in col_ptr[col]..col_ptr[col + 1] {
            y[row_idx[idx]] += values[idx] * xc;
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::mesh::generate::bumpy_sphere;

    fn dense(pattern: &BlockPattern, values: &[c64]) -> Vec<Vec<c64>> {
        let n = pattern.dim();
        let mut m = vec![vec![c64::new(0.0, 0.0); n]; n];
        let cp = pattern.symbolic.col_ptr();
        let ri = pattern.symbolic.row_idx();
        for col in 0..n {
            for idx in cp[col]..cp[col + 1] {
                m[ri[idx]][col] += values[idx];
            }
        }
        m
    }

    fn assembled(rho_scale: f64) -> (crate::mesh::Mesh, BlockPattern, Vec<c64>) {
        assembled_dirac(1, rho_scale, 0.0)
    }

    /// X(ρ) on a bumpy sphere of `subdivisions`, with `ρ_i = rho_scale · sin(0.7 i)` and the
    /// diagonal shift `shift` on every vertex.
    pub(crate) fn assembled_dirac(
        subdivisions: usize,
        rho_scale: f64,
        shift: f64,
    ) -> (crate::mesh::Mesh, BlockPattern, Vec<c64>) {
        let mesh = bumpy_sphere(subdivisions, 0.2);
        let n = mesh.vertex_count();
        let pattern = BlockPattern::new(n, &mesh.triangles, 2);
        let areas = crate::geometry::face_areas(&mesh);
        let rho: Vec<f64> = (0..n).map(|i| rho_scale * (i as f64 * 0.7).sin()).collect();
        let mut values = vec![c64::new(0.0, 0.0); pattern.nnz()];
        assemble_dirac_into(
            &pattern,
            &mesh.positions,
            &mesh.triangles,
            &areas,
            &rho,
            &vec![shift; n],
            &mut values,
        );
        (mesh, pattern, values)
    }

    #[test]
    fn triangle_assembly_is_bitwise_the_gathered_full_assembly() {
        // Small: a simplicial factor (upper triangle); larger: supernodal (lower triangle).
        for subdivisions in [1, 4] {
            triangle_assembly_matches(&bumpy_sphere(subdivisions, 0.2));
        }
    }

    fn triangle_assembly_matches(mesh: &crate::mesh::Mesh) {
        use crate::linalg::solver::Cholesky;
        let n = mesh.vertex_count();
        let pattern = BlockPattern::new(n, &mesh.triangles, 2);
        let areas = crate::geometry::face_areas(mesh);
        let rho: Vec<f64> = (0..n).map(|i| 1.3 * (i as f64 * 0.7).sin()).collect();
        let shift: Vec<f64> = (0..n).map(|i| 0.01 * (1.0 + (i % 3) as f64)).collect();
        let mut full = vec![c64::new(0.0, 0.0); pattern.nnz()];
        let mean = assemble_dirac_into(
            &pattern,
            &mesh.positions,
            &mesh.triangles,
            &areas,
            &rho,
            &shift,
            &mut full,
        );
        let mut reference = Cholesky::<c64>::analyze(&pattern, 1).expect("analyze");
        reference.factorize(&pattern, &full).expect("factor");
        let expected = reference.triangle_values_mut().to_vec();

        let mut direct = Cholesky::<c64>::analyze(&pattern, 1).expect("analyze");
        let mut assembly = TriangleAssembly::new(
            &pattern,
            &mesh.triangles,
            &direct.triangle_slots(pattern.nnz()),
        )
        .expect("targets");
        let direct_mean = assembly.assemble(
            &mesh.positions,
            &mesh.triangles,
            &areas,
            &rho,
            direct.triangle_values_mut(),
        );
        for (v, &s) in shift.iter().enumerate() {
            assembly.add_to_diagonal(v, s, direct.triangle_values_mut());
        }
        assert_eq!(mean, direct_mean);
        assert!(direct.triangle_values_mut().to_vec() == expected);

        // The Hermitian product from the triangle matches the full-storage product.
        let x: Vec<c64> = (0..2 * n)
            .map(|i| c64::new((i as f64 * 0.3).sin(), (i as f64 * 0.8).cos()))
            .collect();
        let (mut y_full, mut y_tri) = (
            vec![c64::new(0.0, 0.0); 2 * n],
            vec![c64::new(0.0, 0.0); 2 * n],
        );
        sparse_matvec(&pattern, &full, &x, &mut y_full);
        direct.factorize_triangle().expect("factor");
        direct.hermitian_matvec(&x, &mut y_tri);
        for (a, b) in y_full.iter().zip(&y_tri) {
            assert!((a - b).norm() < 1e-12 * (1.0 + a.norm()), "{a} vs {b}");
        }
    }

    #[test]
    fn dirac_matrix_is_hermitian() {
        let (_, pattern, values) = assembled(1.3);
        let m = dense(&pattern, &values);
        for (r, row) in m.iter().enumerate() {
            for (c, z) in row.iter().enumerate() {
                assert!((z - m[c][r].conj()).norm() < 1e-13);
            }
        }
    }

    #[test]
    fn constants_are_the_kernel_at_zero_potential() {
        let (mesh, pattern, values) = assembled(0.0);
        let q = Quaternion::new(0.3, -0.2, 0.9, 0.4);
        let x: Vec<c64> = (0..mesh.vertex_count())
            .flat_map(|_| q.to_complex_column())
            .collect();
        let mut y = vec![c64::new(0.0, 0.0); x.len()];
        sparse_matvec(&pattern, &values, &x, &mut y);
        assert!(y.iter().all(|z| z.norm() < 1e-12));
    }

    #[test]
    fn complex_and_real_forms_agree() {
        // Build X densely as quaternions, apply it to a random quaternion vector through the
        // 4×4 real left-multiplication form, and compare with the complex form's product.
        let mesh = bumpy_sphere(1, 0.2);
        let n = mesh.vertex_count();
        let areas = crate::geometry::face_areas(&mesh);
        let rho: Vec<f64> = (0..n).map(|i| 0.8 * (i as f64 * 1.3).cos()).collect();
        let mut xq = vec![vec![Quaternion::default(); n]; n];
        for (tri, &area) in mesh.triangles.iter().zip(&areas) {
            let e = opposite_edges(&mesh.positions, tri);
            for a in 0..3 {
                for b in 0..3 {
                    xq[tri[a]][tri[b]] +=
                        dirac_face_entry(e[a], e[b], rho[tri[a]], rho[tri[b]], area);
                }
            }
        }
        let lambda: Vec<Quaternion> = (0..n)
            .map(|i| {
                let t = i as f64;
                Quaternion::new(
                    t.sin(),
                    (2.0 * t).cos(),
                    (0.5 * t).sin(),
                    1.0 - (0.3 * t).cos(),
                )
            })
            .collect();
        let mut real = vec![[0.0f64; 4]; n];
        for i in 0..n {
            for j in 0..n {
                let m = xq[i][j].to_real();
                let v = [lambda[j].w, lambda[j].x, lambda[j].y, lambda[j].z];
                for r in 0..4 {
                    real[i][r] += (0..4).map(|c| m[r][c] * v[c]).sum::<f64>();
                }
            }
        }
        let pattern = BlockPattern::new(n, &mesh.triangles, 2);
        let mut values = vec![c64::new(0.0, 0.0); pattern.nnz()];
        assemble_dirac_into(
            &pattern,
            &mesh.positions,
            &mesh.triangles,
            &areas,
            &rho,
            &vec![0.0; n],
            &mut values,
        );
        let x: Vec<c64> = lambda.iter().flat_map(|q| q.to_complex_column()).collect();
        let mut y = vec![c64::new(0.0, 0.0); 2 * n];
        sparse_matvec(&pattern, &values, &x, &mut y);
        for i in 0..n {
            let q = Quaternion::from_complex_column([y[2 * i], y[2 * i + 1]]);
            let d = (q.w - real[i][0]).abs()
                + (q.x - real[i][1]).abs()
                + (q.y - real[i][2]).abs()
                + (q.z - real[i][3]).abs();
            assert!(d < 1e-12, "vertex {i}: {d}");
        }
    }
}
