use super::*;
use crate::mesh::generate::icosphere;

#[test]
fn hole_sizes_parse_as_counts_lengths_or_all() {
    assert_eq!(HoleSize::parse("all"), Ok(HoleSize::Any));
    assert_eq!(HoleSize::parse("120"), Ok(HoleSize::Vertices(120)));
    assert_eq!(HoleSize::parse("0.25"), Ok(HoleSize::Extent(0.25)));
    assert_eq!(HoleSize::parse("2e-3"), Ok(HoleSize::Extent(2e-3)));
    for bad in ["2", "-1", "0.0", "nan", "inf", "", "ten"] {
        assert!(HoleSize::parse(bad).is_err(), "{bad:?} parsed");
    }
}

#[test]
fn hole_sizes_read_json_numbers_as_counts_or_lengths_and_round_trip() {
    let read = |j: &str| serde_json::from_str::<HoleSize>(j);
    assert_eq!(read("\"all\"").unwrap(), HoleSize::Any);
    assert_eq!(read("50").unwrap(), HoleSize::Vertices(50));
    assert_eq!(read("0.25").unwrap(), HoleSize::Extent(0.25));
    assert_eq!(read("\"0.25\"").unwrap(), HoleSize::Extent(0.25));
    for bad in ["2", "-3", "0.0", "\"ten\"", "null", "[]"] {
        assert!(read(bad).is_err(), "{bad} read");
    }
    for size in [HoleSize::Any, HoleSize::Vertices(7), HoleSize::Extent(1.0)] {
        let text = serde_json::to_string(&size).unwrap();
        assert_eq!(read(&text).unwrap(), size, "{text}");
    }
}

#[test]
fn a_planar_loop_is_closed_flat_with_its_minimal_triangulation() {
    // A square annulus' inner square: the dynamic program closes it with two triangles in the
    // plane (dihedral 0 against the flat surround).
    let (mesh, inner) = square_frame();
    let filled = fill_holes(&mesh, HoleSize::Vertices(4), &Limits::default()).unwrap();
    assert_eq!(
        filled.holes.len(),
        1,
        "the outer loop has 8 vertices and stays open"
    );
    assert_eq!(filled.left_open, vec![12]);
    let hole = &filled.holes[0];
    assert!(hole.minimal_dihedral);
    assert_eq!(
        hole.vertex_count, 0,
        "a unit square at edge 1 needs no new vertex"
    );
    assert_eq!(hole.triangle_count, 2);
    let mut b = hole.boundary.clone();
    b.sort_unstable();
    assert_eq!(b, inner);
    for t in &filled.mesh.triangles[hole.first_triangle..] {
        let n = face_normal(&filled.mesh.positions, *t);
        assert!(
            (n[2] - 1.0).abs() < 1e-12,
            "patch normal {n:?} leaves the plane or flips"
        );
    }
}

#[test]
fn filling_a_cut_sphere_makes_it_closed_again_and_keeps_its_vertices() {
    let sphere = icosphere(4);
    let cut = cut_ball(&sphere, sphere.positions[0], 0.45).unwrap();
    let before = Topology::new(&cut.mesh);
    assert_eq!(before.boundary_loops.len(), 1);
    let filled = fill_holes(&cut.mesh, HoleSize::Any, &Limits::default()).unwrap();
    let after = Topology::new(&filled.mesh);
    assert!(
        after.is_closed(),
        "still {} loops",
        after.boundary_loops.len()
    );
    assert_eq!(after.genus(), 0);
    assert_eq!(
        &filled.mesh.positions[..cut.mesh.vertex_count()],
        &cut.mesh.positions[..]
    );
    assert_eq!(
        &filled.mesh.triangles[..cut.mesh.face_count()],
        &cut.mesh.triangles[..]
    );
    // Refinement brings the patch to the surrounding edge length: the cut took 1 + 5 + 10 +
    // … vertices; the patch must have inner vertices, and its edges be within 2× the mesh's.
    let hole = &filled.holes[0];
    assert!(
        hole.vertex_count > 3,
        "only {} new vertices",
        hole.vertex_count
    );
    let mean = crate::mesh::generate::mean_edge_length(&cut.mesh);
    for t in &filled.mesh.triangles[hole.first_triangle..] {
        for k in 0..3 {
            let l = norm(sub(
                filled.mesh.positions[t[k]],
                filled.mesh.positions[t[(k + 1) % 3]],
            ));
            assert!(l < 2.5 * mean, "patch edge {l} against mean {mean}");
        }
    }
}

#[test]
fn a_long_loop_is_closed_by_a_fan_and_refined() {
    // A disk's rim of 400 vertices, past the dynamic program's length.
    let n = 400;
    let mut positions = vec![[0.0, 0.0, 0.0]];
    for i in 0..n {
        let a = std::f64::consts::TAU * i as f64 / n as f64;
        positions.push([a.cos(), a.sin(), 0.0]);
        let r = 1.05;
        positions.push([r * a.cos(), r * a.sin(), 0.0]);
    }
    // An annulus between radius 1 and 1.05: the hole is the unit disk.
    let mut triangles = Vec::new();
    for i in 0..n {
        let (a, b) = (1 + 2 * i, 1 + 2 * ((i + 1) % n));
        triangles.push([a, a + 1, b + 1]);
        triangles.push([a, b + 1, b]);
    }
    positions.remove(0);
    for t in &mut triangles {
        for v in t.iter_mut() {
            *v -= 1;
        }
    }
    let mesh = Mesh::new(positions, triangles).unwrap();
    let filled = fill_holes(&mesh, HoleSize::Extent(2.9), &Limits::default()).unwrap();
    assert_eq!(filled.holes.len(), 1);
    assert!(!filled.holes[0].minimal_dihedral);
    assert!(Topology::new(&filled.mesh).boundary_loops.len() == 1);
}

/// A flat 3×3 grid of unit squares with the middle one missing; returns the inner loop's
/// vertices, sorted.
fn square_frame() -> (Mesh, Vec<usize>) {
    let mut positions = Vec::new();
    for y in 0..4 {
        for x in 0..4 {
            positions.push([x as f64, y as f64, 0.0]);
        }
    }
    let id = |x: usize, y: usize| y * 4 + x;
    let mut triangles = Vec::new();
    for y in 0..3 {
        for x in 0..3 {
            if (x, y) == (1, 1) {
                continue;
            }
            triangles.push([id(x, y), id(x + 1, y), id(x + 1, y + 1)]);
            triangles.push([id(x, y), id(x + 1, y + 1), id(x, y + 1)]);
        }
    }
    let mesh = Mesh::new(positions, triangles).unwrap();
    (mesh, vec![id(1, 1), id(2, 1), id(1, 2), id(2, 2)])
}

#[test]
fn half_edges_grouped_by_edge_match_a_map_of_every_edge() {
    let sphere = icosphere(2);
    let mut triangles = sphere.triangles.clone();
    triangles.remove(7);
    let mesh = Mesh {
        positions: sphere.positions,
        triangles,
    };
    let mut expected: std::collections::BTreeMap<(usize, usize), Vec<u64>> = Default::default();
    for (f, t) in mesh.triangles.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            let halves = expected.entry((a.min(b), a.max(b))).or_default();
            halves.push((3 * f + k) as u64);
        }
    }
    let mut seen = Vec::new();
    HalfEdgesByEdge::new(&mesh).for_each_edge(|a, b, halves| {
        let low: Vec<u64> = halves.iter().map(|h| h & 0xffff_ffff).collect();
        seen.push(((a, b), low));
    });
    let expected: Vec<_> = expected.into_iter().collect();
    assert_eq!(
        seen, expected,
        "every edge once, in order, with its half-edges"
    );
    let alone = seen.iter().filter(|(_, h)| h.len() == 1).count();
    assert_eq!(alone, 3, "the removed face leaves three border edges");
}
