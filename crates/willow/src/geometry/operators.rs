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

/// Signed volume of the tetrahedron `(o, a, b, c)` times 6: `det(a − o, b − o, c − o)`.
/// Positive when `(a, b, c)` winds counter-clockwise seen from the side away from `o`.
#[inline]
pub fn tetrahedron_volume6(o: [f64; 3], a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> f64 {
    let (a, b, c) = (sub(a, o), sub(b, o), sub(c, o));
    dot(a, cross(b, c))
}

/// Enclosed volume of a closed, consistently oriented surface by the divergence theorem:
/// `V = Σ_f det(p0 − o, p1 − o, p2 − o) / 6` (each face's cone to the apex `o`). Positive for
/// outward (counter-clockwise from outside) faces, and independent of `o` on a closed surface;
/// taking `o` on or near the surface (its centroid, a vertex) keeps the products the size of
/// the surface rather than of its distance from the origin, which is what rounding sees. On a
/// surface with boundary the sum depends on `o` and is not a volume: callers pass closed
/// components only.
pub fn enclosed_volume<'a>(
    positions: &[[f64; 3]],
    triangles: impl IntoIterator<Item = &'a [usize; 3]>,
    origin: [f64; 3],
) -> f64 {
    triangles
        .into_iter()
        .map(|t| tetrahedron_volume6(origin, positions[t[0]], positions[t[1]], positions[t[2]]))
        .sum::<f64>()
        / 6.0
}

/// Per component `c`, `out[c] = Σ_{f in c} det(p0 − o_c, p1 − o_c, p2 − o_c) / 6` with the apex
/// `o_c = origins[c]`: the enclosed volume of every closed component ([`enclosed_volume`])
/// in one pass over the faces. Entries of open components are not volumes (see there).
pub fn component_volumes_into(
    positions: &[[f64; 3]],
    triangles: &[[usize; 3]],
    face_component: &[usize],
    origins: &[[f64; 3]],
    out: &mut [f64],
) {
    out.fill(0.0);
    for (t, &c) in triangles.iter().zip(face_component) {
        out[c] += tetrahedron_volume6(
            origins[c],
            positions[t[0]],
            positions[t[1]],
            positions[t[2]],
        );
    }
    for v in out.iter_mut() {
        *v /= 6.0;
    }
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

    /// The unit cube, 12 outward triangles: its volume is exactly 1 from any apex, and turning
    /// the faces inside out flips the sign.
    #[test]
    fn unit_cube_volume_is_one() {
        let positions: Vec<[f64; 3]> = (0..8)
            .map(|i| [(i & 1) as f64, ((i >> 1) & 1) as f64, ((i >> 2) & 1) as f64])
            .collect();
        // Quads (counter-clockwise seen from outside) split along a diagonal.
        let quads = [
            [0, 2, 3, 1], // z = 0, normal −z
            [4, 5, 7, 6], // z = 1
            [0, 1, 5, 4], // y = 0
            [2, 6, 7, 3], // y = 1
            [0, 4, 6, 2], // x = 0
            [1, 3, 7, 5], // x = 1
        ];
        let triangles: Vec<[usize; 3]> = quads
            .iter()
            .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
            .collect();
        for origin in [[0.0; 3], [0.5, 0.5, 0.5], [10.0, -3.0, 7.0]] {
            let v = enclosed_volume(&positions, &triangles, origin);
            assert!((v - 1.0).abs() < 1e-12, "apex {origin:?}: V = {v}");
        }
        let flipped: Vec<[usize; 3]> = triangles.iter().map(|t| [t[0], t[2], t[1]]).collect();
        assert!((enclosed_volume(&positions, &flipped, [0.2; 3]) + 1.0).abs() < 1e-12);
        let mut out = [0.0];
        component_volumes_into(&positions, &triangles, &[0; 12], &[[3.0; 3]], &mut out);
        assert!((out[0] - 1.0).abs() < 1e-12);
    }

    /// The icosphere is inscribed in the unit sphere: its volume is below 4/3 π and the gap is
    /// second order in the edge length, so each subdivision (half the edge) divides it by ~4.
    #[test]
    fn icosphere_volume_approaches_four_thirds_pi() {
        let ball = 4.0 / 3.0 * PI;
        let gap = |k| {
            let mesh = icosphere(k);
            ball - enclosed_volume(&mesh.positions, &mesh.triangles, [0.0; 3])
        };
        let (g3, g4) = (gap(3), gap(4));
        assert!(g4 > 0.0 && g4 < 0.005 * ball, "gap {g4}");
        let ratio = g3 / g4;
        assert!((ratio - 4.0).abs() < 0.1, "gap ratio {ratio}");
    }
}
