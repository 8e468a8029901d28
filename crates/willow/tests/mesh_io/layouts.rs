//! Layout variants: several primitives and accessors, several buffers, interleaving, strips.

use super::*;

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
