//! glTF / GLB: node transforms, embedded buffers, images, stale tangents, quantized input.

use super::*;

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
    let path = shared_mesh("Duck.glb");
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
