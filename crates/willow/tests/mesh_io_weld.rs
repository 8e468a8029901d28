//! Welding never makes a surface non-manifold, and every surface error names the file's own
//! vertices and faces (issue 27, item 3).

use willow::mesh::io::{Asset, Format, Limits};
use willow::mesh::MeshError;

fn read(text: &str) -> Result<Asset, MeshError> {
    Asset::read(text.as_bytes(), Format::Obj, &Limits::default())
}

/// A closed tetrahedron's `v` lines, shifted by `o`, as OBJ text.
fn tetra_v(o: [f64; 3]) -> String {
    [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
    ]
    .iter()
    .map(|p| format!("v {} {} {}\n", p[0] + o[0], p[1] + o[1], p[2] + o[2]))
    .collect()
}

/// Its faces over `v` lines `base+1..=base+4`.
fn tetra_f(base: usize) -> String {
    [[1, 3, 2], [1, 2, 4], [2, 3, 4], [1, 4, 3]]
        .iter()
        .map(|t| format!("f {} {} {}\n", t[0] + base, t[1] + base, t[2] + base))
        .collect()
}

#[test]
fn coincident_vertices_of_separate_fans_stay_apart() {
    // pymeshlab's cow.obj in small: two closed tetrahedra whose first vertices are distinct
    // `v` lines at one position. Joining them would make a bowtie.
    let text = tetra_v([0.0; 3])
        + &tetra_v([0.0; 3])
            .replace("v 1 0 0", "v -1 0 0")
            .replace("v 0 1 0", "v 0 -1 0")
            .replace("v 0 0 1", "v 0 0 -1")
        + &tetra_f(0)
        + &tetra_f(4);
    let a = read(&text).expect("closed and manifold by its indices");
    assert_eq!(
        a.surface().vertex_count(),
        8,
        "v lines 1 and 5 stay two vertices"
    );
    let map = a.file_to_welded();
    assert_ne!(map[0], map[4]);
    assert_eq!(
        a.surface().positions[map[0].unwrap()],
        a.surface().positions[map[4].unwrap()]
    );
    // They move independently: the written file gives each `v` line its own vertex.
    let mut moved = a.surface().positions.clone();
    moved[map[4].unwrap()] = [0.0, 0.0, -0.25];
    let out = String::from_utf8(a.write(&moved, Format::Obj).unwrap()).unwrap();
    let v: Vec<&str> = out.lines().filter(|l| l.starts_with("v ")).collect();
    assert_eq!((v[0], v[4]), ("v 0 0 0", "v 0 0 -0.25"));
    let topo = willow::mesh::Topology::new(a.surface());
    assert_eq!(topo.components.len(), 2);
}

#[test]
fn seams_of_duplicate_v_lines_still_close_when_another_part_touches() {
    // Each tetrahedron face has its own three `v` lines (a fully split file, like flat-shaded
    // exports), and a second such tetrahedron touches the first at one corner. Position
    // welding alone makes a bowtie there; welding by corners closes each tetrahedron's seams
    // and keeps the touching corners apart.
    let corners = |o: f64, s: f64| -> Vec<[f64; 3]> {
        vec![[o, 0.0, 0.0], [o + s, 0.0, 0.0], [o, s, 0.0], [o, 0.0, s]]
    };
    let faces = [[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]];
    let mut v = String::new();
    let mut f = String::new();
    let mut n = 0;
    for p in [corners(0.0, 1.0), corners(0.0, -1.0)] {
        for t in faces {
            for k in t {
                v += &format!("v {} {} {}\n", p[k][0], p[k][1], p[k][2]);
            }
            f += &format!("f {} {} {}\n", n + 1, n + 2, n + 3);
            n += 3;
        }
    }
    let a = read(&(v + &f)).expect("two closed tetrahedra");
    assert_eq!(a.surface().vertex_count(), 8);
    let topo = willow::mesh::Topology::new(a.surface());
    assert_eq!(topo.components.len(), 2);
    assert!(topo.boundary_loops.is_empty(), "every seam closed");
}

#[test]
fn a_fin_on_a_tetrahedron_names_the_files_v_lines() {
    // v lines 1-4 and a fifth vertex; faces on lines 6-10, the fin on the edge v1-v2.
    let text = tetra_v([0.0; 3]) + "v 0.5 -1 0\n" + &tetra_f(0) + "f 1 2 5\n";
    let e = read(&text).unwrap_err();
    assert_eq!(e.code(), "non_manifold_edge");
    let msg = e.to_string();
    assert!(msg.contains("first: [0, 1]"), "file vertex numbers: {msg}");
    assert!(
        msg.contains("in the file: the edge between `v` on line 1 and `v` on line 2"),
        "{msg}"
    );
}

#[test]
fn a_bowtie_in_one_file_vertex_and_degenerate_faces_name_lines() {
    let text = "# two triangles sharing only their first vertex\n\
                v 0 0 0\nv 1 0 0\nv 0 1 0\nv -1 0 0\nv 0 -1 0\nf 1 2 3\nf 1 4 5\n";
    let e = read(text).unwrap_err();
    assert_eq!(e.code(), "non_manifold_vertex");
    assert!(e.to_string().ends_with("in the file: `v` on line 2"), "{e}");

    let text = "v 0 0 0\nv 1 0 0\nv 2 0 0\nv 0 1 0\nf 1 2 4\n\n# flat\nf 1 2 3\n";
    let e = read(text).unwrap_err();
    assert_eq!(e.code(), "degenerate_face");
    assert!(e.to_string().contains("first: 1;"), "the second face: {e}");
    assert!(
        e.to_string().ends_with("in the file: the face on line 8"),
        "{e}"
    );
}

#[test]
fn ply_and_stl_errors_use_their_own_numbering() {
    let ply = "ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\n\
               property float z\nelement face 2\nproperty list uchar int vertex_indices\n\
               end_header\n9 9 9\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n4 1 2 3 4\n3 1 2 3\n";
    let e = Asset::read(ply.as_bytes(), Format::Ply, &Limits::default()).unwrap_err();
    // The quad 1-2-3-4 (face 0) is fanned into (1 2 3) and (1 3 4); face 1 repeats (1 2 3),
    // so the diagonal 1-3 has three triangles. Named by PLY vertex records (record 0 unused).
    assert_eq!(
        e.to_string(),
        "1 edges are shared by more than two triangles (non-manifold edges); first: [1, 3]; \
         in the file: the edge between vertex 1 and vertex 3"
    );

    // STL: a triangle with two corners at one position is named by its triangle number.
    let stl = "solid s\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\n\
               endloop\nendfacet\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n\
               vertex 1 0 0\nendloop\nendfacet\nendsolid s\n";
    let e = Asset::read(stl.as_bytes(), Format::Stl, &Limits::default()).unwrap_err();
    assert_eq!(e.code(), "degenerate_face");
    assert!(e.to_string().ends_with("in the file: triangle 1"), "{e}");
}

fn repaired(text: &str, format: Format) -> Asset {
    Asset::read_repaired(text.as_bytes(), format, &Limits::default()).expect("repairable")
}

#[test]
fn repair_splits_a_fin_and_a_bowtie_and_says_so() {
    let fin = tetra_v([0.0; 3]) + "v 0.5 -1 0\n" + &tetra_f(0) + "f 1 2 5\n";
    let a = repaired(&fin, Format::Obj);
    let r = a.repairs();
    assert_eq!(r.split_vertices.first, vec![0, 1], "v lines 1 and 2: {r}");
    assert_eq!(r.added_vertices, 2);
    assert!(r.dropped_faces.is_empty());
    assert_eq!(a.surface().vertex_count(), 7);
    let topo = willow::mesh::Topology::new(a.surface());
    assert_eq!(
        topo.components.len(),
        2,
        "the tetrahedron and the fin, cut apart"
    );
    assert_eq!(
        topo.boundary_loops.len(),
        1,
        "the fin's edge is now a boundary"
    );
    assert_eq!(
        r.to_string(),
        "split 2 non-manifold vertices into 2 more (first: 0, 1)"
    );

    let bowtie = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv -1 0 0\nv 0 -1 0\nf 1 2 3\nf 1 4 5\n";
    let a = repaired(bowtie, Format::Obj);
    assert_eq!(a.repairs().split_vertices.first, vec![0]);
    assert_eq!(a.surface().vertex_count(), 6);
    // The split survives into another format and reads back without repair.
    let ply = a.write(&a.surface().positions, Format::Ply).unwrap();
    let b = Asset::read(&ply, Format::Ply, &Limits::default()).expect("manifold now");
    assert_eq!(b.surface().vertex_count(), 6);
    // File numbering still counts the file's own vertices.
    assert_eq!(a.file_vertex_count(), 5);
    assert_eq!(a.file_triangles(), vec![[0, 1, 2], [0, 3, 4]]);
}

#[test]
fn repair_drops_degenerate_faces_by_file_number_and_leaves_good_files_alone() {
    let text = "v 0 0 0\nv 1 0 0\nv 2 0 0\nv 0 1 0\nf 1 2 4\nf 1 2 3\nf 2 3 4\n";
    let a = repaired(text, Format::Obj);
    assert_eq!(
        a.repairs().dropped_faces.first,
        vec![1],
        "the second `f` line"
    );
    assert_eq!(a.surface().face_count(), 2);
    assert!(a.repairs().split_vertices.is_empty());

    let stl = "solid s\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\n\
               endloop\nendfacet\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n\
               vertex 1 0 0\nendloop\nendfacet\nendsolid s\n";
    let a = repaired(stl, Format::Stl);
    assert_eq!(a.repairs().dropped_faces.first, vec![1]);
    // Written back, the kept triangle gets the new positions; the dropped one is untouched.
    let moved: Vec<[f64; 3]> = a
        .surface()
        .positions
        .iter()
        .map(|p| p.map(|x| x * 3.0))
        .collect();
    let out = String::from_utf8(a.write(&moved, Format::Stl).unwrap()).unwrap();
    assert!(out.contains("vertex 3 0 0\nvertex 0 3 0"), "{out}");
    assert!(
        out.contains("vertex 0 0 0\nvertex 1 0 0\nvertex 1 0 0"),
        "{out}"
    );

    let good = tetra_v([0.0; 3]) + &tetra_f(0);
    let (a, b) = (repaired(&good, Format::Obj), read(&good).unwrap());
    assert!(a.repairs().is_empty());
    assert_eq!(a.repairs().to_string(), "nothing to repair");
    assert_eq!(a.surface(), b.surface());
}
