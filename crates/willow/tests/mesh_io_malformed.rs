//! Malformed uploads: each is refused with a specific error (checked by code and message),
//! and none panics.

mod mesh_support;

use mesh_support::*;
use willow::mesh::io::{Asset, Format, Limits};
use willow::mesh::MeshError;

fn refuse(bytes: &[u8], format: Format) -> MeshError {
    Asset::read(bytes, format, &Limits::default()).expect_err("must be refused")
}

const QUAD_OBJ: &str = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\n";

#[test]
fn empty_files_are_refused() {
    let e = refuse(b"", Format::Obj);
    assert_eq!(e.code(), "empty_mesh", "{e}");
    let e = refuse(b"# only a comment\nv 1 2 3\n", Format::Obj);
    assert_eq!(
        e.to_string(),
        "empty mesh: 1 vertices and 0 triangles; at least one triangle is needed"
    );
    assert_eq!(refuse(b"", Format::Glb).code(), "parse_error");
    assert_eq!(refuse(b"", Format::Gltf).code(), "parse_error");
}

#[test]
fn obj_nan_and_inf_coordinates_are_refused() {
    let e = refuse(
        QUAD_OBJ.replace("v 1 0 0", "v nan 0 0").as_bytes(),
        Format::Obj,
    );
    assert_eq!(e.code(), "non_finite_coordinate");
    assert!(
        e.to_string().starts_with("1 vertices have non-finite"),
        "{e}"
    );
    let e = refuse(
        QUAD_OBJ.replace("v 0 1 0", "v 0 inf 0").as_bytes(),
        Format::Obj,
    );
    assert_eq!(
        e.to_string(),
        "1 vertices have non-finite (NaN or infinite) coordinates; first: 3"
    );
}

#[test]
fn obj_out_of_range_and_zero_indices_are_refused_without_panicking() {
    let e = refuse(format!("{QUAD_OBJ}f 1 2 9\n").as_bytes(), Format::Obj);
    assert_eq!(
        e.to_string(),
        "1 triangles reference vertices out of range (the mesh has 4 vertices); first: 2"
    );
    // Issue 42: a 0 index is a syntax error of its line (QUAD_OBJ has 6), not a face number.
    for (bad, says) in [
        (
            "f 0 1 2",
            "cannot parse OBJ: line 7: OBJ indices start at 1, got 0",
        ),
        (
            "f 1/0 2/1 3/1",
            "cannot parse OBJ: line 7: OBJ vt indices start at 1, got 0",
        ),
        (
            "f 1//0 2//1 3//1",
            "cannot parse OBJ: line 7: OBJ vn indices start at 1, got 0",
        ),
    ] {
        let e = refuse(format!("{QUAD_OBJ}{bad}\n").as_bytes(), Format::Obj);
        assert_eq!(
            (e.code(), e.to_string().as_str()),
            ("parse_error", says),
            "{bad}"
        );
    }
    for bad in [
        "f 0 1 2",
        "f 1 2 -9",
        "f 1/0 2/1 3/1",
        "f 1/99999999999999999999 2 3",
        "f 1//-5 2 3",
    ] {
        let e = refuse(format!("{QUAD_OBJ}{bad}\n").as_bytes(), Format::Obj);
        assert!(
            matches!(e.code(), "index_out_of_range" | "parse_error"),
            "{bad}: {e}"
        );
    }
}

#[test]
fn obj_zero_area_and_repeated_index_faces_are_degenerate() {
    let e = refuse(b"v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", Format::Obj);
    assert_eq!(e.code(), "degenerate_face");
    assert!(
        e.to_string()
            .ends_with("first: 0; in the file: the face on line 4"),
        "{e}"
    );
    let e = refuse(format!("{QUAD_OBJ}f 1 1 2\n").as_bytes(), Format::Obj);
    assert_eq!(e.code(), "degenerate_face");
    assert!(
        e.to_string()
            .ends_with("first: 2; in the file: the face on line 7"),
        "{e}"
    );
}

#[test]
fn obj_non_manifold_inputs_are_refused() {
    let fin = "v 0 0 0\nv 1 0 0\nv 0.5 1 0\nv 0.5 -1 0\nv 0.5 0 1\nf 1 2 3\nf 2 1 4\nf 1 2 5\n";
    let e = refuse(fin.as_bytes(), Format::Obj);
    assert_eq!(e.code(), "non_manifold_edge");
    assert!(
        e.to_string().ends_with(
            "first: [0, 1]; in the file: the edge between `v` on line 1 and `v` on line 2"
        ),
        "{e}"
    );
    let bowtie = "v 0 0 0\nv 1 1 0\nv 1 -1 0\nv -1 1 0\nv -1 -1 0\nf 1 3 2\nf 1 4 5\n";
    let e = refuse(bowtie.as_bytes(), Format::Obj);
    assert_eq!(e.code(), "non_manifold_vertex");
}

#[test]
fn obj_mobius_strip_is_refused() {
    let (p, t) = mobius(10);
    let mut s = String::new();
    for q in &p {
        s += &format!("v {} {} {}\n", q[0], q[1], q[2]);
    }
    for f in &t {
        s += &format!("f {} {} {}\n", f[0] + 1, f[1] + 1, f[2] + 1);
    }
    let e = refuse(s.as_bytes(), Format::Obj);
    assert_eq!(e.code(), "non_orientable");
}

#[test]
fn obj_with_only_points_or_lines_is_refused() {
    let e = refuse(
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\np 1\nl 1 2\nl 2 3\n",
        Format::Obj,
    );
    assert_eq!(
        e,
        MeshError::PointsOrLinesOnly {
            points: 1,
            lines: 2
        }
    );
    assert_eq!(e.code(), "no_triangles");
    assert!(e.to_string().contains("1 point and 2 line elements"), "{e}");
}

#[test]
fn limits_refuse_too_many_bytes_vertices_and_faces() {
    let small = Limits {
        max_bytes: 10,
        ..Limits::default()
    };
    let e = Asset::read(QUAD_OBJ.as_bytes(), Format::Obj, &small).unwrap_err();
    assert_eq!(
        e.to_string(),
        format!(
            "too large: {} bytes exceeds the limit of 10",
            QUAD_OBJ.len()
        )
    );
    let few_vertices = Limits {
        max_vertices: 3,
        ..Limits::default()
    };
    let e = Asset::read(QUAD_OBJ.as_bytes(), Format::Obj, &few_vertices).unwrap_err();
    assert_eq!(
        e.to_string(),
        "too large: 4 vertices exceeds the limit of 3"
    );
    let few_faces = Limits {
        max_faces: 1,
        ..Limits::default()
    };
    let e = Asset::read(QUAD_OBJ.as_bytes(), Format::Obj, &few_faces).unwrap_err();
    assert_eq!(e.to_string(), "too large: 2 faces exceeds the limit of 1");
    assert!(e.is_too_large());

    let (json, bin, _, _) = textured_cube_gltf();
    let glb = glb_bytes(&json, &bin);
    let e = Asset::read(&glb, Format::Glb, &few_vertices).unwrap_err();
    assert_eq!(
        e.to_string(),
        "too large: 24 vertices exceeds the limit of 3"
    );
    let e = Asset::read(&glb, Format::Glb, &few_faces).unwrap_err();
    assert_eq!(e.to_string(), "too large: 12 faces exceeds the limit of 1");
}

#[test]
fn garbage_bytes_are_refused_as_glb_gltf_and_obj() {
    let mut rng = 0x1234_5678_9abc_def0u64;
    let garbage: Vec<u8> = (0..4096)
        .map(|_| {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            rng as u8
        })
        .collect();
    assert_eq!(refuse(&garbage, Format::Glb).code(), "parse_error");
    assert_eq!(refuse(&garbage, Format::Gltf).code(), "parse_error");
    assert_eq!(refuse(&garbage, Format::Obj).code(), "parse_error");
    // A GLB magic followed by nonsense, and every truncation of a valid GLB.
    let mut fake = b"glTF".to_vec();
    fake.extend_from_slice(&garbage);
    assert!(Asset::read(&fake, Format::Glb, &Limits::default()).is_err());
    let (json, bin, _, _) = textured_cube_gltf();
    let glb = glb_bytes(&json, &bin);
    for cut in (0..glb.len()).step_by(7) {
        assert!(
            Asset::read(&glb[..cut], Format::Glb, &Limits::default()).is_err(),
            "cut {cut}"
        );
    }
}

#[test]
fn external_uris_are_refused_without_reading() {
    for uri in [
        "/etc/passwd",
        "http://example.com/cube.bin",
        "file:///etc/passwd",
        "cube.bin",
    ] {
        let (mut json, bin, _, _) = textured_cube_gltf();
        json["buffers"][0]["uri"] = serde_json::json!(uri);
        let e = refuse(&serde_json::to_vec(&json).unwrap(), Format::Gltf);
        assert_eq!(e, MeshError::ExternalUri { uri: uri.into() });
        assert_eq!(e.code(), "external_uri");
        assert!(e.to_string().contains(uri), "{e}");
        let _ = bin;
    }
    // An image by URI is refused too, even inside an otherwise self-contained GLB.
    let (mut json, bin, _, _) = textured_cube_gltf();
    json["images"][0] = serde_json::json!({"uri": "http://example.com/texture.png"});
    let e = refuse(&glb_bytes(&json, &bin), Format::Glb);
    assert_eq!(e.code(), "external_uri");
}

#[test]
fn truncated_bin_chunk_is_refused() {
    let (json, bin, _, _) = textured_cube_gltf();
    // The JSON still declares the full buffer, the BIN chunk holds half of it.
    let e = refuse(&glb_bytes(&json, &bin[..bin.len() / 2]), Format::Glb);
    assert_eq!(e.code(), "truncated_buffer");
    assert!(e.to_string().contains("buffer 0 declares"), "{e}");
}

#[test]
fn accessor_past_the_end_of_its_view_is_refused() {
    let (mut json, bin, _, _) = textured_cube_gltf();
    json["accessors"][0]["count"] = serde_json::json!(25); // the view holds 24
    let e = refuse(&glb_bytes(&json, &bin), Format::Glb);
    assert_eq!(e.code(), "truncated_buffer");
    assert!(e.to_string().contains("accessor 0"), "{e}");
    let (mut json, bin, _, _) = textured_cube_gltf();
    json["bufferViews"][0]["byteLength"] = serde_json::json!(1 << 30);
    let e = refuse(&glb_bytes(&json, &bin), Format::Glb);
    assert_eq!(e.code(), "truncated_buffer");
    assert!(e.to_string().contains("buffer view 0"), "{e}");
}

#[test]
fn gltf_index_out_of_range_is_refused() {
    let (mut json, mut bin, _, _) = textured_cube_gltf();
    let off = json["bufferViews"][3]["byteOffset"].as_u64().unwrap() as usize;
    bin[off..off + 2].copy_from_slice(&999u16.to_le_bytes());
    json["buffers"][0]["byteLength"] = serde_json::json!(bin.len());
    let e = refuse(&glb_bytes(&json, &bin), Format::Glb);
    assert_eq!(
        e.to_string(),
        "1 triangles reference vertices out of range (the mesh has 24 vertices); first: 0"
    );
}

#[test]
fn gltf_points_only_and_unsupported_features_are_refused() {
    let (mut json, bin, _, _) = textured_cube_gltf();
    json["meshes"][0]["primitives"][0]["mode"] = serde_json::json!(0);
    let e = refuse(&glb_bytes(&json, &bin), Format::Glb);
    assert_eq!(
        e,
        MeshError::PointsOrLinesOnly {
            points: 1,
            lines: 0
        }
    );

    let (mut json, bin, _, _) = textured_cube_gltf();
    json["extensionsUsed"] = serde_json::json!(["KHR_draco_mesh_compression"]);
    json["extensionsRequired"] = serde_json::json!(["KHR_draco_mesh_compression"]);
    json["meshes"][0]["primitives"][0]["extensions"] =
        serde_json::json!({"KHR_draco_mesh_compression": {"bufferView": 99, "attributes": {}}});
    let e = refuse(&glb_bytes(&json, &bin), Format::Glb);
    assert_eq!(
        e.to_string(),
        "cannot parse glTF: mesh 0 primitive 0: KHR_draco_mesh_compression: bufferView 99 \
         does not exist"
    );

    let (mut json, bin, _, _) = textured_cube_gltf();
    json["nodes"][0]["scale"] = serde_json::json!([0.0, 1.0, 1.0]);
    let e = refuse(&glb_bytes(&json, &bin), Format::Glb);
    assert!(e.to_string().contains("singular transform"), "{e}");

    // The same mesh drawn twice at different places cannot be written back as one mesh.
    let (mut json, bin, _, _) = textured_cube_gltf();
    json["nodes"][0]["children"] = serde_json::json!([1, 2]);
    json["nodes"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::json!({"mesh": 0, "translation": [5.0, 0.0, 0.0]}));
    let e = refuse(&glb_bytes(&json, &bin), Format::Glb);
    assert!(e.to_string().contains("instancing"), "{e}");
}

#[test]
fn writing_checks_the_positions_it_is_given() {
    let a = Asset::read(QUAD_OBJ.as_bytes(), Format::Obj, &Limits::default()).unwrap();
    let e = a.write(&[[0.0; 3]; 3], Format::Glb).unwrap_err();
    assert_eq!(
        e.to_string(),
        "expected 4 positions (one per welded vertex), got 3"
    );
    let mut p = a.surface().positions.clone();
    p[2][1] = f64::NAN;
    assert_eq!(
        a.write(&p, Format::Obj).unwrap_err().code(),
        "non_finite_coordinate"
    );
}

#[test]
fn polylines_alone_are_lines_and_next_to_faces_are_unsupported() {
    let e = refuse(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2 3 1\n", Format::Obj);
    assert_eq!(
        e,
        MeshError::PointsOrLinesOnly {
            points: 0,
            lines: 1
        }
    );
    let e = refuse(format!("{QUAD_OBJ}l 1 2 3\n").as_bytes(), Format::Obj);
    assert_eq!(e.code(), "unsupported");
    assert!(e.to_string().contains("line 7"), "{e}");
}

/// Every value in a valid document removed or replaced by awkward values (0, -1, huge,
/// fractional, wrong JSON types), one at a time: each read must return, never panic.
#[test]
fn structured_mutations_of_a_gltf_never_panic() {
    use serde_json::{json, Value};
    fn all_paths(v: &Value, path: &mut Vec<String>, out: &mut Vec<Vec<String>>) {
        if !path.is_empty() {
            out.push(path.clone());
        }
        match v {
            Value::Array(a) => {
                for (i, x) in a.iter().enumerate() {
                    path.push(i.to_string());
                    all_paths(x, path, out);
                    path.pop();
                }
            }
            Value::Object(o) => {
                for (k, x) in o {
                    path.push(k.clone());
                    all_paths(x, path, out);
                    path.pop();
                }
            }
            _ => {}
        }
    }
    let (json, bin, _, _) = textured_cube_gltf();
    let mut paths = Vec::new();
    all_paths(&json, &mut Vec::new(), &mut paths);
    assert!(paths.len() > 100);
    let values = [
        None, // remove the member / element
        Some(json!(null)),
        Some(json!(0)),
        Some(json!(1)),
        Some(json!(3)),
        Some(json!(23)),
        Some(json!(25)),
        Some(json!(-1)),
        Some(json!(65535)),
        Some(json!(4294967295u64)),
        Some(json!(18446744073709551615u64)),
        Some(json!(0.5)),
        Some(json!(1e300)),
        Some(json!("VEC3")),
        Some(json!([])),
        Some(json!({})),
    ];
    let (mut refused, mut tried) = (0, 0);
    for path in &paths {
        for value in &values {
            let mut doc = json.clone();
            let (last, parent_path) = path.split_last().unwrap();
            let mut parent = &mut doc;
            for key in parent_path {
                parent = match parent {
                    Value::Array(a) => &mut a[key.parse::<usize>().unwrap()],
                    other => &mut other[key.as_str()],
                };
            }
            match (parent, value) {
                (Value::Array(a), None) => {
                    a.remove(last.parse::<usize>().unwrap());
                }
                (Value::Object(o), None) => {
                    o.remove(last);
                }
                (Value::Array(a), Some(v)) => a[last.parse::<usize>().unwrap()] = v.clone(),
                (Value::Object(o), Some(v)) => {
                    o.insert(last.clone(), v.clone());
                }
                _ => unreachable!("paths lead through containers"),
            }
            tried += 1;
            let bytes = glb_bytes(&doc, &bin);
            match Asset::read(&bytes, Format::Glb, &Limits::default()) {
                Ok(a) => {
                    // Whatever was accepted must also write without panicking.
                    let _ = a.write(&a.surface().positions, Format::Glb);
                    let _ = a.write(&a.surface().positions, Format::Obj);
                }
                Err(_) => refused += 1,
            }
        }
    }
    assert!(
        refused > tried / 3,
        "most mutations must be refused ({refused} of {tried})"
    );
}

/// Random tokens of the hand-written OBJ replaced by awkward ones: every read returns.
#[test]
fn token_mutations_of_an_obj_never_panic() {
    let text = include_str!("data/tetra_seams.obj");
    let tokens: Vec<&str> = text.split(' ').collect();
    let awkward = [
        "0",
        "-1",
        "-5",
        "99",
        "nan",
        "inf",
        "1/2/3/4",
        "",
        "//",
        "/",
        "1//",
        "-99999999999",
        "99999999999999999999",
        "1e999",
        "f",
        "v",
        "l",
        "p",
        "vt",
        "usemtl",
        "\n",
        "1/0/1",
        "4/-13/1",
        "2/2/-5",
    ];
    let mut rng = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = |n: usize| {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        (rng % n as u64) as usize
    };
    let mut accepted = 0;
    for _ in 0..3000 {
        let mut t: Vec<String> = tokens.iter().map(|s| s.to_string()).collect();
        for _ in 0..1 + next(3) {
            let i = next(t.len());
            t[i] = awkward[next(awkward.len())].to_string();
        }
        if let Ok(a) = Asset::read(t.join(" ").as_bytes(), Format::Obj, &Limits::default()) {
            accepted += 1;
            let _ = a.write(&a.surface().positions, Format::Obj);
            let _ = a.write(&a.surface().positions, Format::Glb);
        }
    }
    assert!(
        accepted > 0,
        "some harmless mutations (e.g. in comments) must be accepted"
    );
}

#[test]
fn obj_faces_of_one_or_two_vertices_are_refused_by_line() {
    for short in ["f 1 2", "f 3", "f 1// 2//"] {
        let e = refuse(format!("{QUAD_OBJ}{short}\n").as_bytes(), Format::Obj);
        assert_eq!(e.code(), "parse_error", "{short}: {e}");
        assert!(e.to_string().contains("line 7"), "{short}: {e}");
        assert!(
            e.to_string().contains("at least 3 vertices"),
            "{short}: {e}"
        );
    }
    // `l` and `p` with one or two vertices are still lines and points.
    Asset::read(
        format!("{QUAD_OBJ}l 1 2\np 3\n").as_bytes(),
        Format::Obj,
        &Limits::default(),
    )
    .expect("lines and points next to faces are kept as text");
}

#[test]
fn obj_with_a_utf8_bom_keeps_its_first_vertex_and_the_mark() {
    let with_bom = format!("\u{feff}{QUAD_OBJ}");
    let asset = Asset::read(with_bom.as_bytes(), Format::Obj, &Limits::default())
        .expect("a BOM is accepted");
    let plain =
        Asset::read(QUAD_OBJ.as_bytes(), Format::Obj, &Limits::default()).expect("plain OBJ");
    assert_eq!(asset.file_vertex_count(), 4);
    assert_eq!(asset.surface().positions, plain.surface().positions);
    // Written back, the text (mark included) is the same, numbers in their place.
    let out = asset
        .write(&asset.surface().positions, Format::Obj)
        .expect("writes");
    let text = String::from_utf8(out).expect("UTF-8");
    assert!(text.starts_with('\u{feff}'), "{text:?}");
    let again = Asset::read(text.as_bytes(), Format::Obj, &Limits::default()).expect("rereads");
    assert_eq!(again.surface().positions, plain.surface().positions);
}

#[test]
fn huge_finite_coordinates_are_refused_at_read_time() {
    let e = refuse(
        QUAD_OBJ.replace("v 1 0 0", "v 1e300 0 0").as_bytes(),
        Format::Obj,
    );
    assert_eq!(e.code(), "coordinate_out_of_range", "{e}");
    assert!(e.to_string().contains("first: 1"), "{e}");
    // Just inside the bound is a mesh (the flow may still find it hard; it is not refused).
    Asset::read(
        QUAD_OBJ.replace("v 1 0 0", "v 1e14 0 0").as_bytes(),
        Format::Obj,
        &Limits::default(),
    )
    .expect("1e14 is in range");
    // glTF: a node scale that takes the world positions out of range.
    let (mut json, bin, _, _) = textured_cube_gltf();
    json["nodes"][0]["scale"] = serde_json::json!([1e20, 1.0, 1.0]);
    let e = refuse(&glb_bytes(&json, &bin), Format::Glb);
    assert_eq!(e.code(), "coordinate_out_of_range", "{e}");
}

#[test]
fn gltf_1_0_is_refused() {
    let (mut json, bin, _, _) = textured_cube_gltf();
    json["asset"]["version"] = serde_json::json!("1.0");
    let e = refuse(&glb_bytes(&json, &bin), Format::Glb);
    assert_eq!(e.code(), "unsupported", "{e}");
    assert!(e.to_string().contains("2.x"), "{e}");
    json["asset"]["version"] = serde_json::json!("2.1");
    Asset::read(&glb_bytes(&json, &bin), Format::Glb, &Limits::default())
        .expect("2.x minor versions are read");
}
