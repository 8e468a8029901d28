use super::*;
use crate::geometry::operators::{corner_cotangents_into, cotan_laplacian_apply_into};
use crate::mesh::generate::icosphere;

/// A flat `n × n` grid of cells `1 × 0.25`, every vertex jittered by up to 0.3 of a cell (a
/// fixed LCG), each cell split along the same diagonal: many obtuse triangles and
/// non-Delaunay edges, and a plane, where the coordinates are linear functions.
fn flat_obtuse_grid(n: usize) -> (Vec<[f64; 3]>, Vec<[usize; 3]>, Vec<bool>) {
    let mut state = 0x1234_5678_u64;
    let mut rand = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    };
    let mut positions = Vec::new();
    let mut interior = Vec::new();
    for j in 0..=n {
        for i in 0..=n {
            let inner = i > 0 && j > 0 && i < n && j < n;
            let (dx, dy) = if inner {
                (0.6 * rand(), 0.15 * rand())
            } else {
                (0.0, 0.0)
            };
            positions.push([i as f64 + dx, 0.25 * j as f64 + dy, 0.0]);
            interior.push(inner);
        }
    }
    let id = |i: usize, j: usize| j * (n + 1) + i;
    let mut triangles = Vec::new();
    for j in 0..n {
        for i in 0..n {
            triangles.push([id(i, j), id(i + 1, j), id(i + 1, j + 1)]);
            triangles.push([id(i, j), id(i + 1, j + 1), id(i, j + 1)]);
        }
    }
    (positions, triangles, interior)
}

fn delaunay(positions: &[[f64; 3]], triangles: &[[usize; 3]]) -> IntrinsicDelaunay {
    let mut cot = vec![[0.0; 3]; triangles.len()];
    corner_cotangents_into(positions, triangles, &mut cot);
    let mut idt = IntrinsicDelaunay::new(triangles);
    idt.flip_to_delaunay(positions, &cot);
    idt
}

#[test]
fn twins_of_a_closed_mesh_pair_every_halfedge_the_other_way() {
    let mesh = icosphere(1);
    let twin = halfedge_twins(&mesh.triangles);
    for (h, &t) in twin.iter().enumerate() {
        assert_ne!(t, NONE);
        assert_eq!(twin[t], h);
        let ends = |h: usize| {
            let tri = mesh.triangles[h / 3];
            (tri[(h % 3 + 1) % 3], tri[(h % 3 + 2) % 3])
        };
        let (a, b) = ends(h);
        assert_eq!(ends(t), (b, a));
    }
}

#[test]
fn a_delaunay_mesh_is_its_own_intrinsic_delaunay_triangulation() {
    // Every edge of a subdivided icosahedron is Delaunay (its triangles are nearly
    // equilateral), and a regular grid's diagonals are exactly on the circle (cot sum 0).
    let mesh = icosphere(3);
    let idt = delaunay(&mesh.positions, &mesh.triangles);
    assert_eq!(idt.flip_count(), 0);
    assert_eq!(idt.triangles, mesh.triangles);
    let mut cot = vec![[0.0; 3]; mesh.face_count()];
    corner_cotangents_into(&mesh.positions, &mesh.triangles, &mut cot);
    assert_eq!(idt.cotangents, cot);

    let n = 6;
    let positions: Vec<[f64; 3]> = (0..=n)
        .flat_map(|j| (0..=n).map(move |i| [i as f64, j as f64, 0.0]))
        .collect();
    let id = |i: usize, j: usize| j * (n + 1) + i;
    let triangles: Vec<[usize; 3]> = (0..n)
        .flat_map(|j| {
            (0..n).flat_map(move |i| {
                [
                    [id(i, j), id(i + 1, j), id(i + 1, j + 1)],
                    [id(i, j), id(i + 1, j + 1), id(i, j + 1)],
                ]
            })
        })
        .collect();
    assert_eq!(delaunay(&positions, &triangles).flip_count(), 0);
}

#[test]
fn flipping_a_flat_obtuse_mesh_gives_non_negative_weights_and_keeps_linear_precision() {
    let (positions, triangles, interior) = flat_obtuse_grid(12);
    let mut cot = vec![[0.0; 3]; triangles.len()];
    corner_cotangents_into(&positions, &triangles, &mut cot);
    let before = IntrinsicDelaunay::new(&triangles);
    let mut unflipped = before;
    unflipped.cotangents.copy_from_slice(&cot);
    let negative = unflipped
        .interior_edge_weights()
        .iter()
        .filter(|w| w.2 < -1e-3)
        .count();
    assert!(
        negative > 10,
        "the test mesh needs negative cotan weights ({negative})"
    );

    let idt = delaunay(&positions, &triangles);
    assert!(idt.flip_count() >= negative, "{} flips", idt.flip_count());
    for (i, j, w) in idt.interior_edge_weights() {
        assert!(w >= -0.5 * DELAUNAY_TOLERANCE, "edge {i}–{j}: weight {w}");
    }
    // On a plane the intrinsic triangles are planar triangles of the same points: same total
    // area, and each intrinsic edge's length is the distance between its ends.
    let area = |tris: &[[usize; 3]]| -> f64 {
        tris.iter()
            .map(|t| {
                crate::geometry::triangle_area(positions[t[0]], positions[t[1]], positions[t[2]])
            })
            .sum()
    };
    assert!((area(&idt.triangles) - area(&triangles)).abs() < 1e-12);
    for (f, tri) in idt.triangles.iter().enumerate() {
        for c in 0..3 {
            let chord = norm(sub(
                positions[tri[(c + 2) % 3]],
                positions[tri[(c + 1) % 3]],
            ));
            assert!((idt.lengths[3 * f + c] - chord).abs() < 1e-12);
        }
    }
    // Linear precision: L applied to the coordinates (linear functions on the plane) is zero
    // at every interior vertex, for the flipped operator as for the original.
    let mut lf = vec![[0.0; 3]; positions.len()];
    cotan_laplacian_apply_into(&positions, &idt.triangles, &idt.cotangents, &mut lf);
    for (v, l) in lf.iter().enumerate().filter(|(v, _)| interior[*v]) {
        assert!(l.iter().all(|x| x.abs() < 1e-12), "vertex {v}: L f = {l:?}");
    }
}

#[test]
fn lengths_give_the_cotangents_and_the_diagonal_of_a_square() {
    // Right isosceles triangle: legs 1, hypotenuse √2; cot 90° = 0, cot 45° = 1.
    let s = 2f64.sqrt();
    let cot = corner_cotangents_from_lengths([s, 1.0, 1.0]);
    assert!(cot[0].abs() < 1e-15 && (cot[1] - 1.0).abs() < 1e-15 && (cot[2] - 1.0).abs() < 1e-15);
    assert!((triangle_area_from_lengths([s, 1.0, 1.0]) - 0.5).abs() < 1e-15);
    // Unit square split along one diagonal: the other diagonal is √2 as well.
    assert!((flipped_diagonal_length(s, 1.0, 1.0, 1.0, 1.0) - s).abs() < 1e-15);
    // A 3-4-5 triangle mirrored across its 5 side: the other diagonal is twice its height
    // 12/5; turned half way round instead (a rectangle 3 × 4), it is the other diagonal, 5.
    assert!((flipped_diagonal_length(5.0, 3.0, 4.0, 3.0, 4.0) - 4.8).abs() < 1e-12);
    assert!((flipped_diagonal_length(5.0, 3.0, 4.0, 4.0, 3.0) - 5.0).abs() < 1e-12);
}
