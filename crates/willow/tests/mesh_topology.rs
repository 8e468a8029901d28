//! Topology: edges, boundary loops, components, χ and genus, on generated surfaces and on the
//! shared real meshes (the test fails, saying where it looked, when they are absent).

mod mesh_support;

use mesh_support::*;
use willow::mesh::generate::{icosphere, torus};
use willow::mesh::{Mesh, Topology};

#[test]
fn icosphere_is_one_closed_genus_zero_component() {
    let m = icosphere(3);
    let t = Topology::new(&m);
    assert_eq!(t.edges.len(), 3 * m.face_count() / 2);
    assert_eq!(t.components.len(), 1);
    let c = &t.components[0];
    assert_eq!(c.euler_characteristic, 2);
    assert_eq!(c.genus, 0);
    assert!(c.is_closed() && t.is_closed());
    assert!(t.boundary_edges.is_empty());
    assert_eq!(c.vertices.len(), m.vertex_count());
    assert_eq!(c.faces.len(), m.face_count());
}

#[test]
fn torus_has_genus_one() {
    let m = Mesh::new(
        torus(2.0, 0.7, 24, 12).positions,
        torus(2.0, 0.7, 24, 12).triangles,
    )
    .unwrap();
    let t = Topology::new(&m);
    assert_eq!(t.components.len(), 1);
    assert_eq!(t.components[0].euler_characteristic, 0);
    assert_eq!(t.components[0].genus, 1);
    assert_eq!(t.genus(), 1);
}

#[test]
fn disk_has_one_ordered_boundary_loop() {
    let (p, tris) = disk(10);
    let m = Mesh::new(p, tris).unwrap();
    let t = Topology::new(&m);
    assert_eq!(t.components.len(), 1);
    let c = &t.components[0];
    assert_eq!(c.euler_characteristic, 1);
    assert_eq!(c.boundary_loops, vec![0]);
    assert_eq!(c.genus, 0);
    assert_eq!(t.boundary_edges.len(), 10);
    let l = &t.boundary_loops[0];
    assert_eq!(l.vertices.len(), 10);
    // The fan is wound counter-clockwise, so the rim is walked 1, 2, …, 10 (from its start).
    let start = l.vertices.iter().position(|&v| v == 1).unwrap();
    let walked: Vec<usize> = (0..10).map(|i| l.vertices[(start + i) % 10]).collect();
    assert_eq!(walked, (1..=10).collect::<Vec<_>>());
    for (i, &e) in l.edges.iter().enumerate() {
        let (a, b) = (l.vertices[i], l.vertices[(i + 1) % 10]);
        assert_eq!(t.edges[e], [a.min(b), a.max(b)]);
    }
    let mask = t.boundary_vertex_mask(m.vertex_count());
    assert!(!mask[0] && mask[1..].iter().all(|&b| b));
}

#[test]
fn cylinder_has_two_boundary_loops_and_genus_zero() {
    let (p, tris) = cylinder(12, 4);
    let m = Mesh::new(p, tris).unwrap();
    let t = Topology::new(&m);
    assert_eq!(t.boundary_loops.len(), 2);
    assert!(t.boundary_loops.iter().all(|l| l.vertices.len() == 12));
    let c = &t.components[0];
    assert_eq!(c.euler_characteristic, 0);
    assert_eq!(c.genus, 0);
}

#[test]
fn two_disjoint_spheres_are_two_components() {
    let a = icosphere(1);
    let n = a.vertex_count();
    let mut positions = a.positions.clone();
    positions.extend(a.positions.iter().map(|p| [p[0] + 5.0, p[1], p[2]]));
    let mut triangles = a.triangles.clone();
    triangles.extend(a.triangles.iter().map(|t| [t[0] + n, t[1] + n, t[2] + n]));
    // Interleave the faces so components are not just two contiguous halves.
    let f = a.face_count();
    let order: Vec<usize> = (0..f).flat_map(|i| [i, i + f]).collect();
    let triangles: Vec<[usize; 3]> = order.iter().map(|&i| triangles[i]).collect();
    let m = Mesh::new(positions, triangles).unwrap();
    let t = Topology::new(&m);
    assert_eq!(t.components.len(), 2);
    for (i, c) in t.components.iter().enumerate() {
        assert_eq!(c.euler_characteristic, 2);
        assert_eq!(c.genus, 0);
        assert_eq!(c.faces.len(), f);
        assert_eq!(c.vertices.len(), n);
        assert!(c.vertices.iter().all(|&v| (v < n) == (i == 0)));
        assert!(c.faces.iter().all(|&g| t.face_component[g] == i));
    }
    assert_eq!(t.euler_characteristic(), 4);
}

/// SOURCES.md's table: (file, V_raw, V, F, components, boundary loops, genus), except that
/// V_raw here is `Asset::file_vertex_count`: for OBJ the `v` lines (spot has 2930; SOURCES.md's
/// 3225 counts its distinct `v/vt` corners; the bunny's unused `v` lines count), for GLB the
/// accessor vertices.
const REAL_MESHES: [(&str, usize, usize, usize, usize, usize, usize); 11] = [
    ("spot_triangulated.obj", 2930, 2930, 5856, 1, 0, 0),
    ("cheburashka.obj", 6669, 6669, 13334, 1, 0, 0),
    ("nefertiti.obj", 49971, 49971, 99938, 1, 0, 0),
    ("irregular_sphere.obj", 3000, 3000, 5996, 1, 0, 0),
    ("bob_small.obj", 250, 250, 500, 1, 0, 1),
    ("genus2_24.obj", 766, 766, 1536, 1, 0, 2),
    ("botijo_genus5_irregular.obj", 39774, 39774, 79564, 1, 0, 5),
    ("alligator.obj", 3208, 3208, 5981, 1, 1, 0),
    ("cat_head.obj", 131, 131, 248, 1, 1, 0),
    ("stanford-bunny.obj", 35947, 34834, 69451, 1, 5, 0), // 1113 `v` lines no face uses
    ("Duck.glb", 2399, 2108, 4212, 1, 0, 0),
];

#[test]
fn real_meshes_match_the_sources_table() {
    use willow::mesh::io::{Asset, Format, Limits};
    for (name, v_raw, v, f, components, loops, genus) in REAL_MESHES {
        let path = shared_mesh(name);
        let bytes = std::fs::read(&path).unwrap();
        let format = Format::from_path(&path).unwrap();
        let a = Asset::read(&bytes, format, &Limits::default())
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        let m = a.surface();
        let t = Topology::new(m);
        let got = (
            a.file_vertex_count(),
            m.vertex_count(),
            m.face_count(),
            t.components.len(),
            t.boundary_loops.len(),
            t.genus(),
        );
        assert_eq!(got, (v_raw, v, f, components, loops, genus), "{name}");
        let c = &t.components[0];
        assert_eq!(
            c.euler_characteristic,
            2 - 2 * genus as i64 - loops as i64,
            "{name}: χ = 2 − 2g − b"
        );
        // Every boundary loop is a closed chain of boundary edges.
        let loop_edges: usize = t.boundary_loops.iter().map(|l| l.edges.len()).sum();
        assert_eq!(loop_edges, t.boundary_edges.len(), "{name}");
        if loops == 0 {
            assert!(
                signed_volume(&m.positions, &m.triangles) > 0.0,
                "{name}: closed surfaces come out outward"
            );
        }
    }
}
