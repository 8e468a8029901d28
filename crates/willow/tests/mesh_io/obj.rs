//! OBJ: welding by position, corner UVs, names, winding, and `v` lines mapped to the surface.

use super::*;

#[test]
fn obj_with_seams_welds_by_position_and_keeps_corner_uvs() {
    let a = read(TETRA.as_bytes(), Format::Obj);
    assert_eq!(a.surface().vertex_count(), 4);
    assert_eq!(a.surface().face_count(), 4);
    assert_eq!(
        a.file_vertex_count(),
        4,
        "the file's own vertices: its `v` lines"
    );
    assert_eq!(a.file_to_welded().iter().flatten().count(), 4);
    let t = Topology::new(a.surface());
    assert_eq!((t.components.len(), t.genus()), (1, 0));
    assert!(t.is_closed());
    // First corner of the first face: v 1, vt 1 = (0, 0) → glTF convention (0, 1).
    assert_eq!(corner_uvs(&a)[0][0], [0.0, 1.0]);
    assert_eq!(corner_uvs(&a)[3][2], [0.75, 0.0]);
}

#[test]
fn obj_round_trip_keeps_faces_uvs_and_names() {
    let a = read(TETRA.as_bytes(), Format::Obj);
    let out = a.write(&a.surface().positions, Format::Obj).unwrap();
    let text = String::from_utf8(out.clone()).unwrap();
    // The file's own text: names, materials, `vt` and `f` lines as they were.
    assert!(text.contains("\nmtllib tetra.mtl\n"), "{text}");
    assert!(text.contains("\no tetra\n"), "{text}");
    assert!(
        text.contains("\nusemtl painted\nf 1/1/3 3/2/3 2/3/3\n"),
        "{text}"
    );
    assert!(text.contains("\nusemtl plain\n"), "{text}");
    // One flat normal per face in the file → each `vn` line recomputed as its face's normal.
    assert_eq!(text.lines().filter(|l| l.starts_with("vn ")).count(), 4);
    assert_eq!(text.lines().filter(|l| l.starts_with("vt ")).count(), 12);

    let b = read(&out, Format::Obj);
    assert_eq!(b.surface(), a.surface());
    assert_eq!(b.file_vertex_count(), a.file_vertex_count());
    assert_eq!(corner_uvs(&b), corner_uvs(&a));
    // Written normals are the faces' unit normals: face 0 (`vn 3`) lies opposite vertex 4
    // (1,-1,-1).
    let vn: Vec<[f64; 3]> = text
        .lines()
        .filter_map(|l| l.strip_prefix("vn "))
        .map(|l| {
            let v: Vec<f64> = l.split(' ').map(|x| x.parse().unwrap()).collect();
            [v[0], v[1], v[2]]
        })
        .collect();
    let s = 1.0 / 3f64.sqrt();
    for k in 0..3 {
        assert!((vn[2][k] - [-s, s, s][k]).abs() < 1e-12, "{:?}", vn[2]);
    }
}

#[test]
fn obj_material_names_survive_without_a_material_library() {
    let no_lib = TETRA.replace("mtllib tetra.mtl\n", "");
    let a = read(no_lib.as_bytes(), Format::Obj);
    let text = String::from_utf8(a.write(&a.surface().positions, Format::Obj).unwrap()).unwrap();
    assert!(!text.contains("mtllib"), "no library is invented: {text}");
    assert!(
        text.contains("\nusemtl painted\n") && text.contains("\nusemtl plain\n"),
        "{text}"
    );
}

#[test]
fn obj_moved_positions_keep_seams_closed() {
    let a = read(TETRA.as_bytes(), Format::Obj);
    let moved = wobble(&a.surface().positions);
    assert_seams_closed(&a, &moved);
    let b = read(&a.write(&moved, Format::Obj).unwrap(), Format::Obj);
    assert_eq!(b.surface().positions, moved);
    assert_eq!(b.surface().triangles, a.surface().triangles);
    assert_eq!(corner_uvs(&b), corner_uvs(&a));
}

#[test]
fn obj_inconsistent_winding_is_fixed_and_written_consistently() {
    let flipped = TETRA.replace("f 1/4/4 2/5/4 4/6/4", "f 1/4/4 4/6/4 2/5/4");
    let a = read(flipped.as_bytes(), Format::Obj);
    assert!(consistently_wound(&a.surface().triangles));
    assert!(signed_volume(&a.surface().positions, &a.surface().triangles) > 0.0);
    let b = read(
        &a.write(&a.surface().positions, Format::Obj).unwrap(),
        Format::Obj,
    );
    assert_eq!(b.surface().triangles, a.surface().triangles);
    // The flipped face's corners kept their UVs through the flip.
    let want = read(TETRA.as_bytes(), Format::Obj);
    assert_eq!(corner_uvs(&b), corner_uvs(&want));
}

#[test]
fn spot_round_trip_keeps_uvs_faces_and_welded_count() {
    // A public-domain copy lives in tests/data, so this runs in every checkout.
    let bytes = include_bytes!("../data/spot_triangulated.obj");
    let a = read(bytes, Format::Obj);
    assert_eq!(a.surface().vertex_count(), 2930);
    assert_eq!(a.surface().face_count(), 5856);
    assert_eq!(a.file_vertex_count(), 2930, "spot's `v` lines");
    let moved = wobble(&a.surface().positions);
    assert_seams_closed(&a, &moved);
    for positions in [&a.surface().positions, &moved] {
        let out = a.write(positions, Format::Obj).unwrap();
        let b = read(&out, Format::Obj);
        assert_eq!(b.surface().vertex_count(), 2930);
        assert_eq!(&b.surface().positions, positions);
        assert_eq!(b.surface().triangles, a.surface().triangles);
        assert_eq!(b.file_vertex_count(), 2930);
        assert_eq!(corner_uvs(&b), corner_uvs(&a));
    }
}
/// A vertex the user names by its `v` line is found on the welded surface at that line's
/// position; a number past the file is returned as the error.
#[test]
fn file_vertices_map_to_the_surface_vertex_at_their_position() {
    let bytes = include_bytes!("../data/spot_triangulated.obj");
    let asset = Asset::read(bytes, Format::Obj, &Limits::default()).expect("spot");
    let v_lines: Vec<[f64; 3]> = std::str::from_utf8(bytes)
        .expect("utf-8")
        .lines()
        .filter_map(|l| l.strip_prefix("v "))
        .map(|l| {
            let c: Vec<f64> = l
                .split_whitespace()
                .map(|t| t.parse().expect("number"))
                .collect();
            [c[0], c[1], c[2]]
        })
        .collect();
    let all: Vec<usize> = (0..v_lines.len()).collect();
    let welded = asset.surface_vertices(&all).expect("every v line is used");
    for (k, &w) in welded.iter().enumerate() {
        assert_eq!(asset.surface().positions[w], v_lines[k], "v line {k}");
    }
    assert_eq!(
        asset.surface_vertices(&[3, v_lines.len()]),
        Err(v_lines.len())
    );
}
