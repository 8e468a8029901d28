//! Every format in and out: generated and shared meshes, GLB from STL, PLY and OFF.

use super::*;

#[test]
fn generated_meshes_can_be_written_in_every_format() {
    let torus = willow::mesh::generate::torus(2.0, 0.7, 16, 8);
    let a = Asset::from_mesh(torus.clone(), &Limits::default()).unwrap();
    assert_eq!(
        a.surface(),
        &torus,
        "already valid: unchanged, same vertex order"
    );
    let moved = wobble(&torus.positions);
    for fmt in [Format::Obj, Format::Gltf, Format::Glb] {
        let out = a.write(&moved, fmt).unwrap();
        if fmt != Format::Obj {
            validate_with_khronos(&out, fmt.extension());
        }
        // Re-reading numbers vertices in order of first use: compare corner by corner.
        let b = read(&out, fmt);
        assert_eq!(b.surface().face_count(), torus.face_count(), "{fmt:?}");
        assert_eq!(b.surface().vertex_count(), torus.vertex_count(), "{fmt:?}");
        for (tb, ta) in b.surface().triangles.iter().zip(&torus.triangles) {
            for k in 0..3 {
                let (p, q) = (b.surface().positions[tb[k]], moved[ta[k]]);
                for c in 0..3 {
                    assert!((p[c] - q[c]).abs() < 1e-6, "{fmt:?}: {p:?} vs {q:?}");
                }
            }
        }
        assert_eq!(Topology::new(b.surface()).genus(), 1);
    }
}

#[test]
fn shared_meshes_round_trip_through_every_format() {
    let names = [
        "cheburashka.obj",
        "bob_small.obj",
        "genus2_24.obj",
        "alligator.obj",
        "cat_head.obj",
        "stanford-bunny.obj",
        "Duck.glb",
    ];
    for name in names {
        let path = shared_mesh(name);
        let bytes = std::fs::read(&path).unwrap();
        let a = read(&bytes, Format::from_path(&path).unwrap());
        let topo = Topology::new(a.surface());
        let moved = wobble(&a.surface().positions);
        for fmt in [Format::Obj, Format::Glb, Format::Gltf] {
            let out = a.write(&moved, fmt).unwrap();
            if fmt != Format::Obj {
                validate_with_khronos(&out, fmt.extension());
            }
            let b = read(&out, fmt);
            assert_eq!(
                b.surface().vertex_count(),
                a.surface().vertex_count(),
                "{name} {fmt:?}"
            );
            assert_eq!(
                b.surface().face_count(),
                a.surface().face_count(),
                "{name} {fmt:?}"
            );
            // Across formats the numbering changes (OBJ `v` lines vs glTF split vertices).
            if Some(fmt) == Format::from_path(&path) {
                assert_eq!(
                    b.file_vertex_count(),
                    a.file_vertex_count(),
                    "{name} {fmt:?}"
                );
            }
            let t = Topology::new(b.surface());
            assert_eq!(
                (t.genus(), t.boundary_loops.len(), t.components.len()),
                (
                    topo.genus(),
                    topo.boundary_loops.len(),
                    topo.components.len()
                ),
                "{name} {fmt:?}"
            );
        }
    }
}

#[test]
fn glb_from_stl_ply_off_and_far_from_the_origin_validates() {
    let sphere = willow::mesh::generate::bumpy_sphere(2, 0.1);
    let code = Asset::from_mesh(sphere.clone(), &Limits::default()).unwrap();
    for f in [Format::Stl, Format::Ply, Format::Off] {
        let bytes = code.write(&code.surface().positions, f).unwrap();
        let a = read(&bytes, f);
        for (to, ext) in [(Format::Glb, "glb"), (Format::Gltf, "gltf")] {
            validate_with_khronos(&a.write(&a.surface().positions, to).unwrap(), ext);
        }
    }
    // At map-grid coordinates the document carries a node translation.
    let far: Vec<[f64; 3]> = sphere
        .positions
        .iter()
        .map(|p| [p[0] + 5e6, p[1] - 5e6, p[2] + 1e9])
        .collect();
    let far = Asset::from_mesh(
        willow::mesh::Mesh::new(far, sphere.triangles.clone()).unwrap(),
        &Limits::default(),
    )
    .unwrap();
    validate_with_khronos(
        &far.write(&far.surface().positions, Format::Glb).unwrap(),
        "glb",
    );
}
