//! Refined assets (issue 26 item 5) from a glTF under node transforms: positions stay in the
//! file's local space and written files read back as the refined surface.

mod mesh_support;

use willow::mesh::io::{Asset, Format, Limits};

/// A refined glTF under node transforms (issue 26 item 5): the surface is `refine`'s of the
/// welded input, frame positions stay in the accessor's local space (the node transform undone,
/// the new vertices included), and a GLB written from it reads back as the same surface with
/// its UVs.
#[test]
fn a_refined_gltf_keeps_its_local_space_and_its_uvs() {
    use willow::mesh::refine::refine;
    let (json, bin, local, _) = mesh_support::textured_cube_gltf();
    let glb = mesh_support::glb_bytes(&json, &bin);
    let limits = Limits::default();
    let asset = Asset::read(&glb, Format::Glb, &limits).expect("cube");
    let (r, how) = asset.refined(None, &limits).expect("refine");
    assert!(how.levels >= 2, "{how:?}");
    let expected = refine(asset.surface(), None, &limits).expect("refine");
    assert_eq!(r.surface(), &expected.mesh);

    // The file's 24 accessor vertices keep their numbers; every file vertex's frame position,
    // put through the nodes (parent: ×2 then +10 x; child: z ×0.5), is its surface vertex.
    let world = |p: [f32; 3]| {
        [
            10.0 + 2.0 * p[0] as f64,
            2.0 * p[1] as f64,
            2.0 * 0.5 * p[2] as f64,
        ]
    };
    let frame = r.file_positions(&r.surface().positions);
    assert_eq!(frame.len(), r.file_vertex_count());
    assert!(frame.len() > local.len());
    let to_welded = r.file_to_welded();
    for (k, p) in frame.iter().enumerate() {
        let w = to_welded[k].expect("every vertex is used");
        let (a, b) = (world(*p), r.surface().positions[w]);
        for d in 0..3 {
            assert!(
                (a[d] - b[d]).abs() < 1e-5,
                "file vertex {k}: {a:?} vs {b:?}"
            );
        }
    }

    let back = Asset::read(
        &r.write(&r.surface().positions, Format::Glb).expect("write"),
        Format::Glb,
        &limits,
    )
    .expect("read back");
    assert_eq!(back.surface().face_count(), r.surface().face_count());
    assert_eq!(back.surface().vertex_count(), r.surface().vertex_count());
    assert!(back.corner_uvs().is_some());
    let sorted = |m: &willow::mesh::Mesh| {
        let mut p = m.positions.clone();
        p.sort_by(|a, b| a.partial_cmp(b).unwrap_or(std::cmp::Ordering::Equal));
        p
    };
    for (a, b) in sorted(back.surface()).iter().zip(&sorted(r.surface())) {
        for d in 0..3 {
            assert!((a[d] - b[d]).abs() < 1e-4, "{a:?} vs {b:?}");
        }
    }
}
