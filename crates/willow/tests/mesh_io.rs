//! File I/O: round trips keep UVs, faces, indices and images; seams never open; transforms
//! are applied for the surface and undone for the file; output passes the Khronos validator.

mod mesh_support;

use mesh_support::*;
use willow::mesh::io::{Asset, Format, Limits};
use willow::mesh::Topology;

const TETRA: &str = include_str!("data/tetra_seams.obj");

fn read(bytes: &[u8], format: Format) -> Asset {
    Asset::read(bytes, format, &Limits::default()).unwrap()
}

/// Per corner of each file triangle: the UV, in surface face order.
fn corner_uvs(a: &Asset) -> Vec<[[f32; 2]; 3]> {
    a.corner_uvs().expect("file has UVs")
}

/// Moves every welded vertex differently (so a seam that opened would show).
fn wobble(p: &[[f64; 3]]) -> Vec<[f64; 3]> {
    p.iter()
        .enumerate()
        .map(|(i, q)| {
            let s = 1.0 + 0.01 * (i % 7) as f64;
            [q[0] * s + 0.25, q[1] * s - 0.5, q[2] * s + 0.125]
        })
        .collect()
}

/// Every split copy of a welded vertex carries exactly the welded vertex's new position.
fn assert_seams_closed(a: &Asset, moved: &[[f64; 3]]) {
    let file = a.file_positions(moved);
    assert_eq!(file.len(), a.file_vertex_count());
    let map = a.file_to_welded();
    let mut first: Vec<Option<[f32; 3]>> = vec![None; moved.len()];
    for (fv, w) in map.iter().enumerate() {
        if let Some(w) = *w {
            match first[w] {
                None => first[w] = Some(file[fv]),
                Some(p) => assert_eq!(p, file[fv], "split copies of vertex {w} differ"),
            }
        }
    }
}

// ---------------------------------------------------------------------------------------
// glTF inspection helpers (for well-formed outputs only)

struct Glb {
    doc: gltf::Document,
    blob: Vec<u8>,
}

fn open_glb(bytes: &[u8]) -> Glb {
    let g = gltf::Gltf::from_slice(bytes).unwrap();
    Glb {
        doc: g.document,
        blob: g.blob.unwrap(),
    }
}

impl Glb {
    fn image_bytes(&self) -> Vec<Vec<u8>> {
        self.doc
            .images()
            .map(|im| match im.source() {
                gltf::image::Source::View { view, .. } => {
                    self.blob[view.offset()..view.offset() + view.length()].to_vec()
                }
                gltf::image::Source::Uri { uri, .. } => uri.as_bytes().to_vec(),
            })
            .collect()
    }

    /// (indices, uv0, positions, normals) of every primitive, in order.
    #[allow(clippy::type_complexity)]
    fn primitives(&self) -> Vec<(Vec<u32>, Vec<[f32; 2]>, Vec<[f32; 3]>, Vec<[f32; 3]>)> {
        let blob = &self.blob;
        self.doc
            .meshes()
            .flat_map(|m| m.primitives())
            .map(|p| {
                let r = p.reader(|_| Some(&blob[..]));
                (
                    r.read_indices()
                        .map(|i| i.into_u32().collect())
                        .unwrap_or_default(),
                    r.read_tex_coords(0)
                        .map(|t| t.into_f32().collect())
                        .unwrap_or_default(),
                    r.read_positions().map(|p| p.collect()).unwrap_or_default(),
                    r.read_normals().map(|n| n.collect()).unwrap_or_default(),
                )
            })
            .collect()
    }
}

// ---------------------------------------------------------------------------------------
// OBJ

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
    let bytes = include_bytes!("data/spot_triangulated.obj");
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

// ---------------------------------------------------------------------------------------
// glTF / GLB

#[test]
fn generated_glb_applies_node_transforms_and_round_trips() {
    let (json, bin, local, png) = textured_cube_gltf();
    let input = glb_bytes(&json, &bin);
    validate_with_khronos(&input, "glb");
    let a = read(&input, Format::Glb);
    assert_eq!(a.file_vertex_count(), 24);
    assert_eq!(a.surface().vertex_count(), 8);
    assert_eq!(a.surface().face_count(), 12);
    let t = Topology::new(a.surface());
    assert!(t.is_closed() && t.genus() == 0 && t.components.len() == 1);
    // World = parent(scale 2, +10 x) ∘ child(scale z by 0.5): a 2 × 2 × 1 box around (10, 0, 0).
    for p in &a.surface().positions {
        assert_eq!((p[0] - 10.0).abs(), 1.0);
        assert_eq!(p[1].abs(), 1.0);
        assert_eq!(p[2].abs(), 0.5);
    }
    assert!(signed_volume(&a.surface().positions, &a.surface().triangles) > 3.99);
    // Undone for the file: the stored local positions come back exactly.
    assert_eq!(a.file_positions(&a.surface().positions), local);

    let out = a.write(&a.surface().positions, Format::Glb).unwrap();
    validate_with_khronos(&out, "glb");
    let (orig, new) = (open_glb(&input), open_glb(&out));
    assert_eq!(new.image_bytes(), vec![png]);
    assert_eq!(new.doc.materials().count(), 1);
    assert_eq!(new.doc.samplers().count(), 1);
    assert_eq!(new.doc.nodes().count(), 2);
    assert_eq!(
        new.doc.nodes().nth(1).unwrap().transform().matrix(),
        orig.doc.nodes().nth(1).unwrap().transform().matrix()
    );
    let (p0, p1) = (&orig.primitives()[0], &new.primitives()[0]);
    assert_eq!(p1.0, p0.0, "indices identical");
    assert_eq!(p1.1, p0.1, "UVs identical");
    assert_eq!(p1.2, p0.2, "positions unchanged when written unchanged");
    for (n1, n0) in p1.3.iter().zip(&p0.3) {
        for k in 0..3 {
            assert!(
                (n1[k] - n0[k]).abs() < 1e-6,
                "recomputed flat normal {n1:?} vs {n0:?}"
            );
        }
    }

    // Moved: world positions go back through the inverse transforms.
    let moved = wobble(&a.surface().positions);
    assert_seams_closed(&a, &moved);
    let out = a.write(&moved, Format::Glb).unwrap();
    validate_with_khronos(&out, "glb");
    let b = read(&out, Format::Glb);
    for (p, q) in b.surface().positions.iter().zip(&moved) {
        for k in 0..3 {
            assert!((p[k] - q[k]).abs() < 1e-5, "{p:?} vs {q:?}");
        }
    }
    let w = a.file_to_welded()[0].unwrap();
    let expect = [
        ((moved[w][0] - 10.0) / 2.0) as f32,
        (moved[w][1] / 2.0) as f32,
        (moved[w][2] / 2.0 / 0.5) as f32,
    ];
    assert_eq!(b.file_positions(&b.surface().positions)[0], expect);
    assert_eq!(open_glb(&out).primitives()[0].1, p0.1);
}

#[test]
fn gltf_with_embedded_buffer_round_trips_and_validates() {
    use base64::Engine as _;
    let (mut json, bin, _, _) = textured_cube_gltf();
    json["buffers"][0]["uri"] = serde_json::json!(format!(
        "data:application/octet-stream;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(&bin)
    ));
    let input = serde_json::to_vec(&json).unwrap();
    let a = read(&input, Format::Gltf);
    assert_eq!(a.surface().vertex_count(), 8);
    let out = a
        .write(&wobble(&a.surface().positions), Format::Gltf)
        .unwrap();
    assert!(out.starts_with(b"{"), "a .gltf is JSON");
    validate_with_khronos(&out, "gltf");
    let b = read(&out, Format::Gltf);
    assert_eq!(b.surface().triangles, a.surface().triangles);
    assert_eq!(b.corner_uvs(), a.corner_uvs());
    // And the same asset as GLB.
    let glb = a.write(&a.surface().positions, Format::Glb).unwrap();
    validate_with_khronos(&glb, "glb");
}

#[test]
fn obj_to_glb_and_back_keeps_uvs_and_faces() {
    let a = read(TETRA.as_bytes(), Format::Obj);
    let glb = a.write(&a.surface().positions, Format::Glb).unwrap();
    validate_with_khronos(&glb, "glb");
    let b = read(&glb, Format::Glb);
    assert_eq!(b.surface(), a.surface());
    assert_eq!(b.file_vertex_count(), 12);
    assert_eq!(corner_uvs(&b), corner_uvs(&a));
    let gltf = a.write(&a.surface().positions, Format::Gltf).unwrap();
    validate_with_khronos(&gltf, "gltf");

    let obj = b.write(&b.surface().positions, Format::Obj).unwrap();
    let c = read(&obj, Format::Obj);
    assert_eq!(c.surface(), a.surface());
    assert_eq!(corner_uvs(&c), corner_uvs(&a));
}

#[test]
fn duck_round_trips_with_transform_uvs_indices_and_image() {
    let Some(path) = shared_mesh("Duck.glb") else {
        return;
    };
    let input = std::fs::read(path).unwrap();
    let a = read(&input, Format::Glb);
    assert_eq!(a.file_vertex_count(), 2399);
    assert_eq!(a.surface().vertex_count(), 2108);
    assert_eq!(a.surface().face_count(), 4212);
    let orig = open_glb(&input);
    let local = &orig.primitives()[0].2;
    // The node matrix scales by 0.01: the surface is in world space, the file in local space.
    let extent = |ps: &mut dyn Iterator<Item = f64>| {
        let v: Vec<f64> = ps.collect();
        v.iter().cloned().fold(f64::MIN, f64::max) - v.iter().cloned().fold(f64::MAX, f64::min)
    };
    let world_x = extent(&mut a.surface().positions.iter().map(|p| p[0]));
    let local_x = extent(&mut local.iter().map(|p| p[0] as f64));
    assert!(
        (world_x / local_x - 0.01).abs() < 1e-6,
        "{world_x} vs {local_x}"
    );
    assert_eq!(&a.file_positions(&a.surface().positions), local);

    // Normals recomputed from unmoved positions agree with the file's own (outward, in local
    // space, smooth across UV seams).
    let same = open_glb(&a.write(&a.surface().positions, Format::Glb).unwrap()).primitives();
    let (n0, n1) = (&orig.primitives()[0].3, &same[0].3);
    assert_eq!(n0.len(), n1.len());
    let mean_dot = n0
        .iter()
        .zip(n1)
        .map(|(a, b)| (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]) as f64)
        .sum::<f64>()
        / n0.len() as f64;
    assert!(
        mean_dot > 0.95,
        "mean cos between old and new normals {mean_dot}"
    );

    let moved = wobble(&a.surface().positions);
    assert_seams_closed(&a, &moved);
    let out = a.write(&moved, Format::Glb).unwrap();
    validate_with_khronos(&out, "glb");
    let new = open_glb(&out);
    assert_eq!(new.image_bytes(), orig.image_bytes());
    let (p0, p1) = (&orig.primitives()[0], &new.primitives()[0]);
    assert_eq!(p1.0, p0.0, "indices identical");
    assert_eq!(p1.1, p0.1, "UVs identical");
    assert_eq!(p1.2, a.file_positions(&moved));
    let b = read(&out, Format::Glb);
    assert_eq!(b.surface().vertex_count(), 2108);
    assert_eq!(b.surface().triangles, a.surface().triangles);
}

// ---------------------------------------------------------------------------------------
// Layout variants: several primitives and accessors, several buffers, interleaving, strips

#[test]
fn primitives_with_separate_accessors_weld_into_one_surface() {
    // Two primitives over two POSITION accessors (aliasing the same data) share border
    // vertices only by position: welding must join them into one closed cube.
    let (mut json, bin, local, _) = textured_cube_gltf();
    let accessors = json["accessors"].as_array_mut().unwrap();
    accessors.push(accessors[0].clone()); // 4: POSITION copy
    accessors.push(
        serde_json::json!({"bufferView": 3, "componentType": 5123, "count": 18, "type": "SCALAR"}),
    ); // 5
    accessors.push(serde_json::json!({"bufferView": 3, "byteOffset": 36, "componentType": 5123, "count": 18, "type": "SCALAR"})); // 6
    json["meshes"][0]["primitives"] = serde_json::json!([
        {"attributes": {"POSITION": 0, "TEXCOORD_0": 2}, "indices": 5, "material": 0},
        {"attributes": {"POSITION": 4, "TEXCOORD_0": 2}, "indices": 6, "material": 0}
    ]);
    let input = glb_bytes(&json, &bin);
    let a = read(&input, Format::Glb);
    assert_eq!(a.file_vertex_count(), 48);
    // glTF file vertex order: each POSITION accessor in order of first use, each in accessor
    // order (what frames carry).
    let both: Vec<[f32; 3]> = local.iter().chain(&local).copied().collect();
    assert_eq!(a.file_positions(&a.surface().positions), both);
    // The two accessors hold the same vertices (each primitive uses some of them): moved,
    // a vertex used through both accessors gets one position.
    let file = a.file_positions(&wobble(&a.surface().positions));
    let map = a.file_to_welded();
    for fv in 0..24 {
        assert!(map[fv].or(map[fv + 24]).is_some(), "vertex {fv} is used");
        if map[fv].is_some() && map[fv + 24].is_some() {
            assert_eq!(file[fv], file[fv + 24], "vertex {fv}");
        }
    }
    assert_eq!(a.surface().vertex_count(), 8);
    assert_eq!(a.surface().face_count(), 12);
    let t = Topology::new(a.surface());
    assert_eq!((t.components.len(), t.genus(), t.is_closed()), (1, 0, true));
    let moved = wobble(&a.surface().positions);
    assert_seams_closed(&a, &moved);
    let out = a.write(&moved, Format::Glb).unwrap();
    validate_with_khronos(&out, "glb");
    let b = read(&out, Format::Glb);
    assert_eq!(b.surface().triangles, a.surface().triangles);
    let prims = open_glb(&out).primitives();
    assert_eq!(prims.len(), 2);
    assert_eq!(prims[0].0.len(), 18);
}

#[test]
fn several_data_uri_buffers_and_interleaved_vertices_are_read_and_written() {
    use base64::Engine as _;
    let b64 = |b: &[u8]| {
        format!(
            "data:application/octet-stream;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(b)
        )
    };
    let (mut json, bin, local, _) = textured_cube_gltf();
    // Interleave POSITION and NORMAL (stride 24) into a second buffer.
    let normals_off = json["bufferViews"][1]["byteOffset"].as_u64().unwrap() as usize;
    let mut inter = Vec::new();
    for (i, p) in local.iter().enumerate() {
        for x in p {
            inter.extend_from_slice(&x.to_le_bytes());
        }
        inter.extend_from_slice(&bin[normals_off + 12 * i..normals_off + 12 * i + 12]);
    }
    let views = json["bufferViews"].as_array_mut().unwrap();
    views.push(serde_json::json!({"buffer": 1, "byteOffset": 0, "byteLength": inter.len(), "byteStride": 24, "target": 34962}));
    let v = views.len() - 1;
    json["accessors"][0]["bufferView"] = serde_json::json!(v);
    json["accessors"][1]["bufferView"] = serde_json::json!(v);
    json["accessors"][1]["byteOffset"] = serde_json::json!(12);
    json["buffers"] = serde_json::json!([
        {"byteLength": bin.len(), "uri": b64(&bin)},
        {"byteLength": inter.len(), "uri": b64(&inter)}
    ]);
    let input = serde_json::to_vec(&json).unwrap();
    validate_with_khronos(&input, "gltf");
    let a = read(&input, Format::Gltf);
    assert_eq!(a.file_positions(&a.surface().positions), local);
    for fmt in [Format::Gltf, Format::Glb] {
        let out = a.write(&wobble(&a.surface().positions), fmt).unwrap();
        validate_with_khronos(&out, fmt.extension());
        let b = read(&out, fmt);
        assert_eq!(b.corner_uvs(), a.corner_uvs());
        assert_eq!(b.surface().triangles, a.surface().triangles);
    }
}

#[test]
fn triangle_strips_are_converted_for_the_surface_and_kept_in_the_file() {
    // A closed tetrahedron as one strip: 0 1 2 3 0 1 → (0 1 2) (2 1 3) (2 3 0) (0 3 1).
    let p: [[f32; 3]; 4] = [
        [1.0, 1.0, 1.0],
        [-1.0, -1.0, 1.0],
        [-1.0, 1.0, -1.0],
        [1.0, -1.0, -1.0],
    ];
    let mut bin: Vec<u8> = p.iter().flatten().flat_map(|x| x.to_le_bytes()).collect();
    let strip: [u16; 6] = [0, 1, 2, 3, 0, 1];
    bin.extend(strip.iter().flat_map(|x| x.to_le_bytes()));
    let json = serde_json::json!({
        "asset": {"version": "2.0"},
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "mode": 5}]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
             "min": [-1.0, -1.0, -1.0], "max": [1.0, 1.0, 1.0]},
            {"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"}
        ],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 48, "target": 34962},
            {"buffer": 0, "byteOffset": 48, "byteLength": 12, "target": 34963}
        ],
        "buffers": [{"byteLength": 60}]
    });
    let a = read(&glb_bytes(&json, &bin), Format::Glb);
    assert_eq!(a.surface().face_count(), 4);
    assert!(consistently_wound(&a.surface().triangles));
    assert!(signed_volume(&a.surface().positions, &a.surface().triangles) > 0.0);
    let out = a.write(&a.surface().positions, Format::Glb).unwrap();
    validate_with_khronos(&out, "glb");
    let g = open_glb(&out);
    let prim = g.doc.meshes().next().unwrap().primitives().next().unwrap();
    assert_eq!(prim.mode(), gltf::mesh::Mode::TriangleStrip);
    assert_eq!(g.primitives()[0].0, vec![0, 1, 2, 3, 0, 1]);
}

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
        let Some(path) = shared_mesh(name) else {
            continue;
        };
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
fn stale_tangents_are_dropped_from_written_gltf() {
    // The cube with a TANGENT per vertex (unit, perpendicular to its face normal, w = 1).
    let (mut json, mut bin, local, _) = textured_cube_gltf();
    let normals_view = json["accessors"][1]["bufferView"].as_u64().unwrap() as usize;
    let off = json["bufferViews"][normals_view]["byteOffset"]
        .as_u64()
        .unwrap() as usize;
    let mut tangents = Vec::new();
    for i in 0..local.len() {
        let b = &bin[off + 12 * i..off + 12 * i + 4];
        let nx = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
        let t: [f32; 4] = if nx != 0.0 {
            [0.0, 1.0, 0.0, 1.0]
        } else {
            [1.0, 0.0, 0.0, 1.0]
        };
        tangents.extend(t.iter().flat_map(|x| x.to_le_bytes()));
    }
    while bin.len() % 4 != 0 {
        bin.push(0);
    }
    let at = bin.len();
    bin.extend_from_slice(&tangents);
    json["bufferViews"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::json!(
            {"buffer": 0, "byteOffset": at, "byteLength": tangents.len(), "target": 34962}
        ));
    let view = json["bufferViews"].as_array().unwrap().len() - 1;
    json["accessors"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::json!(
            {"bufferView": view, "componentType": 5126, "count": local.len(), "type": "VEC4"}
        ));
    let acc = json["accessors"].as_array().unwrap().len() - 1;
    json["meshes"][0]["primitives"][0]["attributes"]["TANGENT"] = serde_json::json!(acc);
    json["buffers"][0]["byteLength"] = serde_json::json!(bin.len());
    let input = glb_bytes(&json, &bin);
    validate_with_khronos(&input, "glb");
    let a = read(&input, Format::Glb);
    assert!(open_glb(&input)
        .doc
        .meshes()
        .next()
        .unwrap()
        .primitives()
        .next()
        .unwrap()
        .get(&gltf::Semantic::Tangents)
        .is_some());

    for fmt in [Format::Glb, Format::Gltf] {
        let out = a.write(&wobble(&a.surface().positions), fmt).unwrap();
        validate_with_khronos(&out, fmt.extension());
        let doc = gltf::Gltf::from_slice(&out).unwrap().document;
        for prim in doc.meshes().flat_map(|m| m.primitives()) {
            assert!(
                prim.get(&gltf::Semantic::Tangents).is_none(),
                "{fmt:?}: TANGENT would be stale after the positions moved"
            );
            assert!(prim.get(&gltf::Semantic::Normals).is_some(), "{fmt:?}");
        }
        let b = read(&out, fmt);
        assert_eq!(b.corner_uvs(), a.corner_uvs());
    }
}

/// A vertex the user names by its `v` line is found on the welded surface at that line's
/// position; a number past the file is returned as the error.
#[test]
fn file_vertices_map_to_the_surface_vertex_at_their_position() {
    let bytes = include_bytes!("data/spot_triangulated.obj");
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

/// A sphere as gltfpack writes it by default (`KHR_mesh_quantization`, required): positions
/// as unnormalized u16 in [0, 65535] with the dequantization in the node's scale and
/// translation, normals as normalized i8 (padded to 4 bytes), u16 indices.
fn quantized_sphere_glb(declared: bool) -> (Vec<u8>, Vec<[f64; 3]>, f64) {
    let m = willow::mesh::generate::icosphere(2);
    let lo = -1.0f64;
    let step = 2.0 / 65535.0;
    let mut bin = Vec::new();
    let q: Vec<[u16; 3]> = m
        .positions
        .iter()
        .map(|p| p.map(|x| ((x - lo) / step).round() as u16))
        .collect();
    for v in &q {
        for c in v {
            bin.extend_from_slice(&c.to_le_bytes());
        }
        bin.extend_from_slice(&[0, 0]); // 8-byte stride, as gltfpack aligns vertices
    }
    let normals_at = bin.len();
    for p in &m.positions {
        let l = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        for x in p {
            bin.push(((x / l) * 127.0).round() as i8 as u8);
        }
        bin.push(0);
    }
    let indices_at = bin.len();
    for t in &m.triangles {
        for &i in t {
            bin.extend_from_slice(&(i as u16).to_le_bytes());
        }
    }
    let n = m.positions.len();
    let mut json = serde_json::json!({
        "asset": {"version": "2.0", "generator": "hand-made like gltfpack"},
        "extensionsUsed": ["KHR_mesh_quantization"],
        "extensionsRequired": ["KHR_mesh_quantization"],
        "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "translation": [lo, lo, lo], "scale": [step, step, step]}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 2}]}],
        "buffers": [{"byteLength": bin.len().next_multiple_of(4)}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": normals_at, "byteStride": 8, "target": 34962},
            {"buffer": 0, "byteOffset": normals_at, "byteLength": indices_at - normals_at, "byteStride": 4, "target": 34962},
            {"buffer": 0, "byteOffset": indices_at, "byteLength": bin.len() - indices_at, "target": 34963}
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5123, "count": n, "type": "VEC3",
             "min": [0, 0, 0], "max": [65535, 65535, 65535]},
            {"bufferView": 1, "componentType": 5120, "normalized": true, "count": n, "type": "VEC3"},
            {"bufferView": 2, "componentType": 5123, "count": m.triangles.len() * 3, "type": "SCALAR"}
        ]
    });
    if !declared {
        let o = json.as_object_mut().unwrap();
        o.remove("extensionsUsed");
        o.remove("extensionsRequired");
    }
    let truth = q
        .iter()
        .map(|v| v.map(|c| lo + step * f64::from(c)))
        .collect();
    (glb_bytes(&json, &bin), truth, step)
}

#[test]
fn quantized_glb_is_read_faired_written_and_validates() {
    let (glb, truth, step) = quantized_sphere_glb(true);
    validate_with_khronos(&glb, "glb");
    let a = read(&glb, Format::Glb);
    assert_eq!(a.file_vertex_count(), truth.len());
    // Every file vertex where the dequantization puts it (to f32 of the node transform).
    let file = a.file_to_welded();
    for (i, w) in file.iter().enumerate() {
        let p = a.surface().positions[w.unwrap()];
        for k in 0..3 {
            assert!(
                (p[k] - truth[i][k]).abs() < 1e-9,
                "vertex {i}: {p:?} vs {:?}",
                truth[i]
            );
        }
    }
    // Written back: a valid document whose positions re-read within a quantization step of
    // the faired (here: scaled) f64 positions.
    let moved: Vec<[f64; 3]> = a
        .surface()
        .positions
        .iter()
        .map(|p| p.map(|x| 0.9 * x))
        .collect();
    let out = a.write(&moved, Format::Glb).unwrap();
    validate_with_khronos(&out, "glb");
    let b = read(&out, Format::Glb);
    for (x, y) in b.surface().positions.iter().zip(&moved) {
        for k in 0..3 {
            assert!((x[k] - y[k]).abs() < step, "{x:?} vs {y:?}");
        }
    }
    // The input's encoding is kept: POSITION unnormalized u16 over the whole range of the
    // new box (0.9 of the old one, so the step shrinks by 0.9), NORMAL normalized i8, each
    // re-read normal within i8 rounding (√3·0.5/127) of the sphere's radial direction.
    assert!(
        a.notes()[0]
            .ends_with("; NORMAL re-quantized to its own type; other attributes kept as they were"),
        "{:?}",
        a.notes()
    );
    let json = {
        let n = u32::from_le_bytes([out[12], out[13], out[14], out[15]]) as usize;
        serde_json::from_slice::<serde_json::Value>(&out[20..20 + n]).unwrap()
    };
    let acc = |attr: &str| {
        let i = json["meshes"][0]["primitives"][0]["attributes"][attr]
            .as_u64()
            .unwrap();
        json["accessors"][i as usize].clone()
    };
    assert_eq!(acc("POSITION")["componentType"], 5123);
    assert_eq!(
        acc("POSITION")["max"],
        serde_json::json!([65535, 65535, 65535])
    );
    assert_eq!(acc("NORMAL")["componentType"], 5120);
    assert_eq!(acc("NORMAL")["normalized"], true);
    let new_step = json["nodes"][0]["scale"][0].as_f64().unwrap();
    let span = |ps: &[[f64; 3]]| {
        let xs = ps.iter().map(|p| p[0]);
        xs.clone().fold(f64::MIN, f64::max) - xs.fold(f64::MAX, f64::min)
    };
    assert!(
        (new_step - span(&moved) / 65535.0).abs() < 1e-15,
        "{new_step}"
    );
    for (x, y) in b.surface().positions.iter().zip(&moved) {
        for k in 0..3 {
            assert!(
                (x[k] - y[k]).abs() <= 0.5 * new_step * (1.0 + 1e-9),
                "{x:?} vs {y:?}"
            );
        }
    }
    // The expected normals, computed here: the unit area-weighted sum of the face normals
    // at each vertex of the moved surface.
    let mut sums = vec![[0.0f64; 3]; moved.len()];
    for t in &a.surface().triangles {
        let [p, q, r] = t.map(|v| moved[v]);
        let (u, w) = (
            [0, 1, 2].map(|k| q[k] - p[k]),
            [0, 1, 2].map(|k| r[k] - p[k]),
        );
        let c = [
            u[1] * w[2] - u[2] * w[1],
            u[2] * w[0] - u[0] * w[2],
            u[0] * w[1] - u[1] * w[0],
        ];
        for v in t {
            (0..3).for_each(|k| sums[*v][k] += c[k]);
        }
    }
    let normals = b.file_normals().unwrap();
    for (i, (n, w)) in normals.iter().zip(a.file_to_welded()).enumerate() {
        let (n, s) = (n.unwrap(), sums[w.unwrap()]);
        let l = (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt();
        for k in 0..3 {
            assert!(
                (n[k] - s[k] / l).abs() <= 0.5 / 127.0 + 1e-9,
                "vertex {i}: {n:?} vs {s:?}"
            );
        }
    }
    // The same node with its transform as a matrix: the new matrix dequantizes the new grid.
    let json_in = {
        let n = u32::from_le_bytes([glb[12], glb[13], glb[14], glb[15]]) as usize;
        let mut j: serde_json::Value = serde_json::from_slice(&glb[20..20 + n]).unwrap();
        let (t, s) = (
            j["nodes"][0]["translation"].clone(),
            j["nodes"][0]["scale"][0].clone(),
        );
        let (t, s) = (
            [0, 1, 2].map(|k| t[k].as_f64().unwrap()),
            s.as_f64().unwrap(),
        );
        j["nodes"][0] = serde_json::json!({"mesh": 0, "matrix": [
            s, 0, 0, 0, 0, s, 0, 0, 0, 0, s, 0, t[0], t[1], t[2], 1]});
        (j, glb[20 + n + 8..].to_vec())
    };
    let m = read(&glb_bytes(&json_in.0, &json_in.1), Format::Glb);
    let out = m.write(&moved, Format::Glb).unwrap();
    validate_with_khronos(&out, "glb");
    let n = u32::from_le_bytes([out[12], out[13], out[14], out[15]]) as usize;
    let j: serde_json::Value = serde_json::from_slice(&out[20..20 + n]).unwrap();
    assert_eq!(j["accessors"][0]["componentType"], 5123);
    assert_eq!(j["nodes"][0]["matrix"][0], new_step, "{}", j["nodes"][0]);
    let b = read(&out, Format::Glb);
    for (x, y) in b.surface().positions.iter().zip(&moved) {
        for k in 0..3 {
            assert!(
                (x[k] - y[k]).abs() <= 0.5 * new_step * (1.0 + 1e-9),
                "{x:?} vs {y:?}"
            );
        }
    }
    // Without the extension declared, integer positions are refused by name.
    let (plain, _, _) = quantized_sphere_glb(false);
    let e = Asset::read(&plain, Format::Glb, &Limits::default()).unwrap_err();
    assert_eq!(
        e.to_string(),
        "unsupported: POSITION accessor 0 is not float VEC3 (integer types need \
         KHR_mesh_quantization)"
    );
}
