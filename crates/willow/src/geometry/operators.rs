//! Per-face and per-vertex operators. Each `*_into` writes into a caller-owned slice so the
//! flow's step loop allocates nothing; the allocating wrappers are for tests and one-off use.

use super::vec3::{add, cross, dot, norm, scale, sub};
use crate::mesh::Mesh;

/// Area of the triangle `(a, b, c)`.
pub fn triangle_area(a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> f64 {
    0.5 * norm(cross(sub(b, a), sub(c, a)))
}

/// Areas of all faces.
pub fn face_areas_into(positions: &[[f64; 3]], triangles: &[[usize; 3]], out: &mut [f64]) {
    for (area, &[i, j, k]) in out.iter_mut().zip(triangles) {
        *area = triangle_area(positions[i], positions[j], positions[k]);
    }
}

pub fn face_areas(mesh: &Mesh) -> Vec<f64> {
    let mut out = vec![0.0; mesh.face_count()];
    face_areas_into(&mesh.positions, &mesh.triangles, &mut out);
    out
}

/// Cotangent of the interior angle at each corner: `out[f][c]` is the angle at
/// `triangles[f][c]`, opposite the edge `triangles[f][c+1] → triangles[f][c+2]`.
///
/// `cot θ = ⟨u, v⟩ / |u × v|`; a zero-area face (refused by validation) would divide by zero,
/// so the denominator is floored at a tiny positive value rather than producing NaN.
pub fn corner_cotangents_into(
    positions: &[[f64; 3]],
    triangles: &[[usize; 3]],
    out: &mut [[f64; 3]],
) {
    for (cots, tri) in out.iter_mut().zip(triangles) {
        for c in 0..3 {
            let p = positions[tri[c]];
            let u = sub(positions[tri[(c + 1) % 3]], p);
            let v = sub(positions[tri[(c + 2) % 3]], p);
            cots[c] = dot(u, v) / norm(cross(u, v)).max(f64::MIN_POSITIVE);
        }
    }
}

pub fn corner_cotangents(mesh: &Mesh) -> Vec<[f64; 3]> {
    let mut out = vec![[0.0; 3]; mesh.face_count()];
    corner_cotangents_into(&mesh.positions, &mesh.triangles, &mut out);
    out
}

/// Barycentric vertex areas: one third of the area of every incident face. These are the
/// lumped mass matrix `M` of the flow and the weights of its inner product `⟨⟨a, b⟩⟩ = Σ a_i b_i A_i`.
pub fn barycentric_vertex_areas_into(
    triangles: &[[usize; 3]],
    face_areas: &[f64],
    out: &mut [f64],
) {
    out.fill(0.0);
    for (&[i, j, k], &a) in triangles.iter().zip(face_areas) {
        let third = a / 3.0;
        out[i] += third;
        out[j] += third;
        out[k] += third;
    }
}

pub fn barycentric_vertex_areas(mesh: &Mesh) -> Vec<f64> {
    let mut out = vec![0.0; mesh.vertex_count()];
    barycentric_vertex_areas_into(&mesh.triangles, &face_areas(mesh), &mut out);
    out
}

/// Unit vertex normals, weighted by incident face area (the sum of face cross products).
/// An isolated or fully degenerate neighbourhood gets the zero vector.
pub fn vertex_normals_into(positions: &[[f64; 3]], triangles: &[[usize; 3]], out: &mut [[f64; 3]]) {
    out.fill([0.0; 3]);
    for &[i, j, k] in triangles {
        let n = cross(
            sub(positions[j], positions[i]),
            sub(positions[k], positions[i]),
        );
        out[i] = add(out[i], n);
        out[j] = add(out[j], n);
        out[k] = add(out[k], n);
    }
    for n in out.iter_mut() {
        let len = norm(*n);
        *n = if len > 0.0 {
            scale(*n, 1.0 / len)
        } else {
            [0.0; 3]
        };
    }
}

pub fn vertex_normals(mesh: &Mesh) -> Vec<[f64; 3]> {
    let mut out = vec![[0.0; 3]; mesh.vertex_count()];
    vertex_normals_into(&mesh.positions, &mesh.triangles, &mut out);
    out
}

/// `L f` for the positive semidefinite cotan Laplacian, per face: the corner with cotangent
/// `c` adds `c/2 · (f_a − f_b)` to `a` and the opposite to `b` for its opposite edge `a → b`.
pub fn cotan_laplacian_apply_into(
    positions: &[[f64; 3]],
    triangles: &[[usize; 3]],
    cotangents: &[[f64; 3]],
    out: &mut [[f64; 3]],
) {
    out.fill([0.0; 3]);
    for (tri, cots) in triangles.iter().zip(cotangents) {
        for c in 0..3 {
            let (a, b) = (tri[(c + 1) % 3], tri[(c + 2) % 3]);
            let d = scale(sub(positions[a], positions[b]), 0.5 * cots[c]);
            out[a] = add(out[a], d);
            out[b] = sub(out[b], d);
        }
    }
}

/// The cotan Laplacian as a sparse matrix (positive semidefinite, rows sum to zero):
/// `L_ij = −½(cot α_ij + cot β_ij)`, `L_ii = −Σ_j L_ij`. For tests and one-off use; the
/// flows refill a fixed pattern instead.
pub fn cotan_laplacian(mesh: &Mesh) -> faer::sparse::SparseColMat<usize, f64> {
    let cot = corner_cotangents(mesh);
    let mut triplets = Vec::with_capacity(12 * mesh.face_count());
    for (tri, cots) in mesh.triangles.iter().zip(&cot) {
        for c in 0..3 {
            let (a, b) = (tri[(c + 1) % 3], tri[(c + 2) % 3]);
            let w = 0.5 * cots[c];
            triplets.push(faer::sparse::Triplet::new(a, b, -w));
            triplets.push(faer::sparse::Triplet::new(b, a, -w));
            triplets.push(faer::sparse::Triplet::new(a, a, w));
            triplets.push(faer::sparse::Triplet::new(b, b, w));
        }
    }
    let n = mesh.vertex_count();
    // Indices come from a validated mesh, so the only failure would be an allocation
    // failure, which aborts anyway.
    faer::sparse::SparseColMat::try_new_from_triplets(n, n, &triplets)
        .expect("triplet indices are vertex indices of a valid mesh")
}

/// Pointwise mean curvature `H_i = ⟨(L f)_i, N_i⟩ / (2 A_i)` (docs/algorithm.md §1): projecting the
/// curvature normal onto N keeps the sign (H > 0 on an outward sphere).
pub fn mean_curvature_into(
    laplacian_f: &[[f64; 3]],
    normals: &[[f64; 3]],
    areas: &[f64],
    out: &mut [f64],
) {
    for (((h, lf), n), &a) in out.iter_mut().zip(laplacian_f).zip(normals).zip(areas) {
        *h = if a > 0.0 {
            dot(*lf, *n) / (2.0 * a)
        } else {
            0.0
        };
    }
}

pub fn mean_curvature(mesh: &Mesh) -> Vec<f64> {
    let n = mesh.vertex_count();
    let mut lf = vec![[0.0; 3]; n];
    cotan_laplacian_apply_into(
        &mesh.positions,
        &mesh.triangles,
        &corner_cotangents(mesh),
        &mut lf,
    );
    let mut h = vec![0.0; n];
    mean_curvature_into(
        &lf,
        &vertex_normals(mesh),
        &barycentric_vertex_areas(mesh),
        &mut h,
    );
    h
}

/// Willmore energy `W = Σ_i H_i² A_i` (paper §3, `∫ H² dA`): 4π for any round sphere.
pub fn willmore_energy(mean_curvature: &[f64], areas: &[f64]) -> f64 {
    mean_curvature
        .iter()
        .zip(areas)
        .map(|(h, a)| h * h * a)
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate::{icosphere, torus};
    use std::f64::consts::PI;

    #[test]
    fn icosphere_willmore_energy_approaches_4pi() {
        let mesh = icosphere(4);
        let w = willmore_energy(&mean_curvature(&mesh), &barycentric_vertex_areas(&mesh));
        assert!(
            (w / (4.0 * PI) - 1.0).abs() < 0.005,
            "W = {w}, 4π = {}",
            4.0 * PI
        );
    }

    #[test]
    fn unit_sphere_has_mean_curvature_one_and_scales_inversely() {
        let mesh = icosphere(4);
        let h = mean_curvature(&mesh);
        let mean = h.iter().sum::<f64>() / h.len() as f64;
        assert!((mean - 1.0).abs() < 0.01, "mean H = {mean}");
        let big = Mesh {
            positions: mesh.positions.iter().map(|&p| scale(p, 3.0)).collect(),
            triangles: mesh.triangles.clone(),
        };
        let hb = mean_curvature(&big);
        assert!((hb[7] * 3.0 - h[7]).abs() < 1e-12);
    }

    #[test]
    fn laplacian_rows_sum_to_zero_and_it_is_symmetric() {
        let mesh = icosphere(2);
        let l = cotan_laplacian(&mesh);
        let dense = l.to_dense();
        let n = mesh.vertex_count();
        for i in 0..n {
            let row: f64 = (0..n).map(|j| dense[(i, j)]).sum();
            assert!(row.abs() < 1e-12);
            for j in 0..n {
                assert!((dense[(i, j)] - dense[(j, i)]).abs() < 1e-12);
            }
            assert!(dense[(i, i)] > 0.0);
        }
        // Applying L per face agrees with the assembled matrix.
        let mut lf = vec![[0.0; 3]; n];
        cotan_laplacian_apply_into(
            &mesh.positions,
            &mesh.triangles,
            &corner_cotangents(&mesh),
            &mut lf,
        );
        for i in 0..n {
            for c in 0..3 {
                let m: f64 = (0..n).map(|j| dense[(i, j)] * mesh.positions[j][c]).sum();
                assert!((m - lf[i][c]).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn flat_grid_has_zero_curvature_inside() {
        // The torus generator's grid, flattened: interior vertices of a plane have H = 0.
        let mut mesh = torus(3.0, 1.0, 8, 8);
        for p in &mut mesh.positions {
            p[2] = 0.0;
        }
        let lf = {
            let mut lf = vec![[0.0; 3]; mesh.vertex_count()];
            cotan_laplacian_apply_into(
                &mesh.positions,
                &mesh.triangles,
                &corner_cotangents(&mesh),
                &mut lf,
            );
            lf
        };
        // Only the z component matters for a plane's normal; it is exactly zero.
        assert!(lf.iter().all(|v| v[2] == 0.0));
    }

    #[test]
    fn areas_agree_per_face_and_per_vertex() {
        let mesh = icosphere(3);
        let total_faces: f64 = face_areas(&mesh).iter().sum();
        let total_vertices: f64 = barycentric_vertex_areas(&mesh).iter().sum();
        assert!((total_faces - total_vertices).abs() < 1e-12);
        assert!((total_faces - 4.0 * PI).abs() < 0.02 * 4.0 * PI);
    }

    #[test]
    fn normals_point_outward_on_sphere() {
        let mesh = icosphere(2);
        for (n, p) in vertex_normals(&mesh).iter().zip(&mesh.positions) {
            assert!(dot(*n, *p) > 0.99);
        }
    }
}
