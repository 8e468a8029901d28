//! `Mesh::new`: every refusal names its rule, count and first indices; orientation is fixed
//! and made outward.

mod mesh_support;

use mesh_support::*;
use willow::mesh::generate::icosphere;
use willow::mesh::{Limits, Mesh, MeshError};

fn tri_ok() -> Vec<[f64; 3]> {
    vec![
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [1.0, 1.0, 0.0],
    ]
}

#[test]
fn empty_mesh_is_refused() {
    let e = Mesh::new(vec![], vec![]).unwrap_err();
    assert_eq!(
        e,
        MeshError::Empty {
            vertices: 0,
            faces: 0
        }
    );
    assert_eq!(e.code(), "empty_mesh");
    let e = Mesh::new(tri_ok(), vec![]).unwrap_err();
    assert!(e.to_string().contains("4 vertices and 0 triangles"), "{e}");
}

#[test]
fn nan_and_infinite_coordinates_are_refused_with_their_vertices() {
    let mut p = tri_ok();
    p[1][2] = f64::NAN;
    p[3][0] = f64::INFINITY;
    let e = Mesh::new(p, vec![[0, 1, 2], [1, 3, 2]]).unwrap_err();
    match &e {
        MeshError::NonFinite { vertices } => {
            assert_eq!(vertices.count, 2);
            assert_eq!(vertices.first, vec![1, 3]);
        }
        other => panic!("wrong error {other:?}"),
    }
    assert_eq!(
        e.to_string(),
        "2 vertices have non-finite (NaN or infinite) coordinates; first: 1, 3"
    );
    assert_eq!(e.code(), "non_finite_coordinate");
}

#[test]
fn out_of_range_index_is_refused() {
    let e = Mesh::new(tri_ok(), vec![[0, 1, 2], [1, 7, 2]]).unwrap_err();
    assert_eq!(
        e.to_string(),
        "1 triangles reference vertices out of range (the mesh has 4 vertices); first: 1"
    );
    assert_eq!(e.code(), "index_out_of_range");
}

#[test]
fn zero_area_face_is_degenerate() {
    let mut p = tri_ok();
    p.push([2.0, 0.0, 0.0]); // collinear with 0 and 1
    let e = Mesh::new(p, vec![[0, 1, 2], [1, 3, 2], [0, 1, 4]]).unwrap_err();
    match &e {
        MeshError::DegenerateFaces { faces } => assert_eq!(faces.first, vec![2]),
        other => panic!("wrong error {other:?}"),
    }
    assert!(
        e.to_string().starts_with("1 triangles are degenerate"),
        "{e}"
    );
    assert_eq!(e.code(), "degenerate_face");
}

#[test]
fn repeated_index_is_degenerate() {
    let e = Mesh::new(tri_ok(), vec![[0, 1, 2], [3, 3, 2], [1, 3, 2]]).unwrap_err();
    assert!(e.to_string().ends_with("first: 1"), "{e}");
    assert_eq!(e.code(), "degenerate_face");
}

#[test]
fn tiny_sliver_is_legal() {
    let p = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 1e-9, 0.0]];
    let m = Mesh::new(p, vec![[0, 1, 2]]).unwrap();
    assert_eq!(m.face_count(), 1);
}

#[test]
fn unreferenced_vertex_is_refused() {
    let mut p = tri_ok();
    p.push([5.0, 5.0, 5.0]);
    let e = Mesh::new(p, vec![[0, 1, 2], [1, 3, 2]]).unwrap_err();
    assert_eq!(
        e.to_string(),
        "1 vertices are not used by any triangle; first: 4"
    );
}

#[test]
fn edge_with_three_faces_is_non_manifold() {
    let p = vec![
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.5, 1.0, 0.0],
        [0.5, -1.0, 0.0],
        [0.5, 0.0, 1.0],
    ];
    let e = Mesh::new(p, vec![[0, 1, 2], [1, 0, 3], [0, 1, 4]]).unwrap_err();
    assert_eq!(
        e.to_string(),
        "1 edges are shared by more than two triangles (non-manifold edges); first: [0, 1]"
    );
    assert_eq!(e.code(), "non_manifold_edge");
}

#[test]
fn bowtie_vertex_is_non_manifold() {
    let p = vec![
        [0.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [1.0, -1.0, 0.0],
        [-1.0, 1.0, 0.0],
        [-1.0, -1.0, 0.0],
    ];
    let e = Mesh::new(p, vec![[0, 2, 1], [0, 3, 4]]).unwrap_err();
    match &e {
        MeshError::NonManifoldVertices { vertices } => assert_eq!(vertices.first, vec![0]),
        other => panic!("wrong error {other:?}"),
    }
    assert!(e.to_string().ends_with("first: 0"), "{e}");
    assert_eq!(e.code(), "non_manifold_vertex");
}

#[test]
fn two_cones_touching_at_the_apex_are_non_manifold() {
    // Two closed square pyramids sharing only their apex: every edge has two faces and both
    // fans around the apex are closed cycles, so only counting fans catches this.
    let mut p = vec![[0.0, 0.0, 0.0]];
    let mut t = Vec::new();
    for (side, z) in [(0usize, 1.0), (1, -1.0)] {
        let base = 1 + 4 * side;
        for i in 0..4 {
            let a = std::f64::consts::FRAC_PI_2 * i as f64;
            p.push([a.cos(), a.sin(), z]);
        }
        for i in 0..4 {
            t.push([0, base + i, base + (i + 1) % 4]);
        }
        t.push([base, base + 2, base + 1]);
        t.push([base, base + 3, base + 2]);
    }
    let e = Mesh::new(p, t).unwrap_err();
    match &e {
        MeshError::NonManifoldVertices { vertices } => assert_eq!(vertices.first, vec![0]),
        other => panic!("wrong error {other:?}"),
    }
}

#[test]
fn cube_with_one_face_flipped_comes_out_consistent_and_outward() {
    let (p, t) = cube();
    let mut bad = t.clone();
    bad[4].swap(0, 1);
    bad[5].swap(1, 2);
    assert!(!consistently_wound(&bad));
    let m = Mesh::new(p.clone(), bad).unwrap();
    assert!(consistently_wound(&m.triangles));
    assert!((signed_volume(&m.positions, &m.triangles) - 1.0).abs() < 1e-12);
    // Same triangles as the outward cube up to rotation of corners.
    for (got, want) in m.triangles.iter().zip(&t) {
        let rotations = [
            *want,
            [want[1], want[2], want[0]],
            [want[2], want[0], want[1]],
        ];
        assert!(rotations.contains(got), "{got:?} vs {want:?}");
    }
}

#[test]
fn inward_closed_surfaces_are_turned_outward() {
    let (p, t) = cube();
    let inward: Vec<[usize; 3]> = t.iter().map(|&[a, b, c]| [a, c, b]).collect();
    let m = Mesh::new(p, inward).unwrap();
    assert_eq!(m.triangles, t);

    let s = icosphere(2);
    let inward: Vec<[usize; 3]> = s.triangles.iter().map(|&[a, b, c]| [c, b, a]).collect();
    let far: Vec<[f64; 3]> = s
        .positions
        .iter()
        .map(|q| [q[0] + 1e6, q[1] - 3e5, q[2]])
        .collect();
    let m = Mesh::new(far.clone(), inward).unwrap();
    assert!(signed_volume(&far, &m.triangles) > 0.0);
}

#[test]
fn open_surface_keeps_majority_winding() {
    let (p, t) = disk(8);
    let mut bad = t.clone();
    bad[3].swap(1, 2);
    let m = Mesh::new(p.clone(), bad).unwrap();
    assert_eq!(m.triangles, t);
    let reversed: Vec<[usize; 3]> = t.iter().map(|&[a, b, c]| [a, c, b]).collect();
    let m = Mesh::new(p, reversed.clone()).unwrap();
    assert_eq!(m.triangles, reversed);
}

#[test]
fn mobius_strip_is_non_orientable() {
    let (p, t) = mobius(12);
    let e = Mesh::new(p, t).unwrap_err();
    assert!(
        matches!(e, MeshError::NonOrientable { component: 0, .. }),
        "{e:?}"
    );
    assert!(e.to_string().contains("not orientable"), "{e}");
    assert_eq!(e.code(), "non_orientable");
}

#[test]
fn limits_refuse_too_many_vertices_and_faces() {
    let s = icosphere(1);
    let limits = Limits {
        max_vertices: 10,
        ..Limits::default()
    };
    let e = Mesh::with_limits(s.positions.clone(), s.triangles.clone(), &limits).unwrap_err();
    assert_eq!(
        e,
        MeshError::TooLarge {
            what: "vertices",
            value: 42,
            limit: 10
        }
    );
    assert_eq!(
        e.to_string(),
        "too large: 42 vertices exceeds the limit of 10"
    );
    let limits = Limits {
        max_faces: 79,
        ..Limits::default()
    };
    let e = Mesh::with_limits(s.positions, s.triangles, &limits).unwrap_err();
    assert_eq!(e.code(), "too_large");
    assert!(e.to_string().contains("80 faces"), "{e}");
}
