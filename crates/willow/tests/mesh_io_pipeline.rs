//! glTF as pipelines write it: the real tools (`gltfpack` and `@gltf-transform/cli`, npm,
//! pinned in tests/tools/package-lock.json) make meshopt-compressed variants of a shared mesh
//! (`EXT_meshopt_compression` and `KHR_meshopt_compression`) and Draco-compressed ones
//! (`KHR_draco_mesh_compression`); each is read exactly like its
//! uncompressed twin, faired for a few steps, and written as a validator-clean document whose
//! UVs and indices are the input's, with no byte the document does not describe, and the job
//! told so in its notes: meshopt input keeps the extension for POSITION (re-encoded), Draco's
//! is written plain. Morph targets are dropped with a note.

mod mesh_support;

use mesh_support::*;
use willow::flow::{new_flow, FlowParams, Method};
use willow::mesh::io::{Asset, Format, Limits};

use mesh_support::gltf_tool as tool;

fn read(bytes: &[u8]) -> Asset {
    Asset::read(bytes, Format::Glb, &Limits::default()).unwrap()
}

fn json_of(glb: &[u8]) -> serde_json::Value {
    let n = u32::from_le_bytes([glb[12], glb[13], glb[14], glb[15]]) as usize;
    serde_json::from_slice(&glb[20..20 + n]).unwrap()
}

/// Bytes of a GLB's BIN chunk that no buffer view covers, less up to 3 bytes of alignment
/// padding before each view: the compressed data of a decoded input, if it were left behind.
fn undescribed_bytes(glb: &[u8]) -> usize {
    let json = json_of(glb);
    let n = u32::from_le_bytes([glb[12], glb[13], glb[14], glb[15]]) as usize;
    let bin_len = u32::from_le_bytes([glb[20 + n], glb[21 + n], glb[22 + n], glb[23 + n]]);
    let mut covered = vec![false; bin_len as usize];
    let views = json["bufferViews"].as_array().cloned().unwrap_or_default();
    for v in &views {
        // A meshopt-compressed view's bytes in the BIN chunk are its extension's range; the
        // view itself describes the decoded data in a fallback buffer.
        let compressed = ["EXT_meshopt_compression", "KHR_meshopt_compression"]
            .iter()
            .find_map(|e| v["extensions"].get(e));
        let range = compressed.unwrap_or(v);
        assert_eq!(range["buffer"].as_u64().unwrap_or(0), 0, "{v}");
        let at = range["byteOffset"].as_u64().unwrap_or(0) as usize;
        let len = range["byteLength"].as_u64().unwrap() as usize;
        covered[at..at + len].iter_mut().for_each(|c| *c = true);
    }
    let bare = covered.iter().filter(|c| !**c).count();
    bare.saturating_sub(3 * (views.len() + 1))
}

fn extensions(json: &serde_json::Value, key: &str) -> Vec<String> {
    json[key]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|e| e.as_str().map(String::from))
        .collect()
}

/// Where two lists first differ (asserting on whole meshes would print thousands of lines).
fn first_difference<T: PartialEq + std::fmt::Debug>(a: &[T], b: &[T]) -> Option<String> {
    if a.len() != b.len() {
        return Some(format!("lengths {} and {}", a.len(), b.len()));
    }
    let i = a.iter().zip(b).position(|(x, y)| x != y)?;
    Some(format!("item {i}: {:?} vs {:?}", a[i], b[i]))
}

/// Each triangle as its three corners (file position, UV) by bits, rotated to start at its
/// smallest corner (winding kept), all sorted: the geometry independent of vertex order and
/// of the rotation the meshopt index codec may apply to each triangle.
fn corner_triangles(a: &Asset) -> Vec<[([u32; 3], [u32; 2]); 3]> {
    let p = a.file_positions(&a.surface().positions);
    let uvs = a.corner_uvs().unwrap_or_default();
    let mut out: Vec<_> = a
        .file_triangles()
        .iter()
        .enumerate()
        .map(|(t, tri)| {
            let c: [([u32; 3], [u32; 2]); 3] = std::array::from_fn(|k| {
                let uv = uvs.get(t).map_or([0.0; 2], |u| u[k]);
                (p[tri[k]].map(f32::to_bits), uv.map(f32::to_bits))
            });
            let first = (0..3).min_by_key(|&k| c[k]).unwrap_or(0);
            std::array::from_fn(|k| c[(first + k) % 3])
        })
        .collect();
    out.sort_unstable();
    out
}

/// The same triangles with the same corner positions and UVs, bit for bit.
fn assert_same_geometry(a: &Asset, b: &Asset, what: &str) {
    assert!(a.corner_uvs().is_some(), "{what}: UVs were lost");
    assert_eq!(
        a.file_vertex_count(),
        b.file_vertex_count(),
        "{what}: vertices"
    );
    let diff = first_difference(&corner_triangles(a), &corner_triangles(b));
    assert!(diff.is_none(), "{what}: triangles differ at {diff:?}");
}

/// A few conformal steps, the written GLB validated, and its indices and UVs the input's;
/// every byte of its buffer described by a view; `note` (an extension name) in the notes. A
/// meshopt input's output keeps the extension, with its POSITION view compressed (mode
/// ATTRIBUTES, no filter); Draco's is plain. Returns the output.
fn fair_and_check_output(a: &Asset, what: &str, note: &str) -> Vec<u8> {
    assert!(
        a.notes().iter().any(|n| n.starts_with(note)),
        "{what}: no note on {note}: {:?}",
        a.notes()
    );
    let ext_left = |l: &[String]| {
        l.iter()
            .any(|e| e.contains("meshopt") || e.contains("draco"))
    };
    let params = FlowParams {
        method: Method::Conformal,
        ..FlowParams::default()
    };
    let mut flow = new_flow(a.surface(), &params).expect("flow");
    for _ in 0..2 {
        flow.step().unwrap_or_else(|e| panic!("{what}: step: {e}"));
    }
    let moved = flow.positions().to_vec();
    let moved_by = moved
        .iter()
        .zip(&a.surface().positions)
        .map(|(p, q)| (0..3).map(|k| (p[k] - q[k]).abs()).fold(0.0, f64::max))
        .fold(0.0, f64::max);
    assert!(moved_by > 0.0, "{what}: the flow did not move the surface");
    let out = a.write(&moved, Format::Glb).unwrap();
    validate_with_khronos(&out, "glb");
    assert_eq!(
        undescribed_bytes(&out),
        0,
        "{what}: bytes no view describes"
    );
    let json = json_of(&out);
    let meshopt = note.contains("meshopt");
    for key in ["extensionsUsed", "extensionsRequired"] {
        let mut listed = extensions(&json, key);
        if meshopt {
            assert!(
                listed.iter().any(|e| e == note),
                "{what}: {key}: {listed:?}"
            );
            listed.retain(|e| e != note);
        }
        assert!(!ext_left(&listed), "{what}: {key} still lists {listed:?}");
    }
    if meshopt {
        let pos = json["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
            .as_u64()
            .unwrap() as usize;
        let view =
            &json["bufferViews"][json["accessors"][pos]["bufferView"].as_u64().unwrap() as usize];
        let e = &view["extensions"][note];
        assert_eq!(e["mode"], "ATTRIBUTES", "{what}: POSITION view {view}");
        assert!(e.get("filter").is_none(), "{what}: {view}");
        let fallback = &json["buffers"][view["buffer"].as_u64().unwrap() as usize];
        assert_eq!(
            fallback["extensions"][note]["fallback"], true,
            "{what}: {fallback}"
        );
        assert!(fallback.get("uri").is_none(), "{what}: {fallback}");
    }
    let b = read(&out);
    let diff = first_difference(&b.file_triangles(), &a.file_triangles());
    assert!(diff.is_none(), "{what}: written indices differ at {diff:?}");
    assert!(
        b.corner_uvs().is_some() && b.corner_uvs() == a.corner_uvs(),
        "{what}: UVs"
    );
    // Positions are the faired ones: float32 in the file, or re-quantized (KHR_mesh_quantization
    // inputs) within half a step of the output's own grid.
    let tol = |e: f64| match quantization_step(&json) {
        Some(step) => 0.5 * step * (1.0 + 1e-6),
        None => 1e-5 * (1.0 + e.abs()),
    };
    let err = max_world_error(a, &moved, &b, tol);
    assert!(err.is_none(), "{what}: {err:?}");
    out
}

/// The world-space distance between each file vertex of `b` (as willow reads it) and the same
/// file vertex of `a` at `moved`, checked per axis against `tol(expected)`; the first failure.
fn max_world_error(
    a: &Asset,
    moved: &[[f64; 3]],
    b: &Asset,
    tol: impl Fn(f64) -> f64,
) -> Option<String> {
    let (wa, wb) = (a.file_to_welded(), b.file_to_welded());
    assert_eq!(wa.len(), wb.len());
    for (i, (x, y)) in wa.iter().zip(&wb).enumerate() {
        let (Some(x), Some(y)) = (x, y) else {
            continue;
        };
        let (e, g) = (moved[*x], b.surface().positions[*y]);
        if let Some(k) = (0..3).find(|&k| (e[k] - g[k]).abs() > tol(e[k])) {
            return Some(format!("file vertex {i} axis {k}: {} vs {}", g[k], e[k]));
        }
    }
    None
}

/// One step of the output's integer POSITION grid in world units (the glTF has one mesh
/// node, at the root, with a uniform scale): the node's scale over the normalized type's
/// divisor; `None` for float POSITION.
fn quantization_step(json: &serde_json::Value) -> Option<f64> {
    let acc = json["meshes"][0]["primitives"][0]["attributes"]["POSITION"].as_u64()? as usize;
    let acc = &json["accessors"][acc];
    let divisor = match (acc["componentType"].as_u64()?, acc["normalized"] == true) {
        (5126, _) => return None,
        (_, false) => 1.0,
        (5120, true) => 127.0,
        (5121, true) => 255.0,
        (5122, true) => 32767.0,
        (5123, true) => 65535.0,
        (c, _) => panic!("componentType {c}"),
    };
    let node = json["nodes"]
        .as_array()?
        .iter()
        .find(|n| n.get("mesh").is_some())?;
    let s: Vec<f64> = node["scale"]
        .as_array()?
        .iter()
        .filter_map(|x| x.as_f64())
        .collect();
    assert!(
        s.iter().all(|x| (x - s[0]).abs() <= 1e-12 * s[0].abs()),
        "scale {s:?}"
    );
    Some(s[0].abs() / divisor)
}

#[test]
fn gltfpack_meshopt_variants_read_like_their_twin_and_fair() {
    let obj = shared_mesh("spot_triangulated.obj");
    let dir = tempfile::tempdir().unwrap();
    let obj = obj.to_str().unwrap();
    let make = |name: &str, extra: &[&str]| -> Vec<u8> {
        let mut args = vec!["-i", obj, "-o", name, "-kv"];
        args.extend_from_slice(extra);
        tool("gltfpack", &args, dir.path());
        std::fs::read(dir.path().join(name)).unwrap()
    };
    // The twin: gltfpack's default (quantized, not compressed), the same data before the
    // meshopt codec; the compressed variants must decode to it exactly.
    let twin = read(&make("q.glb", &[]));
    fair_and_check_output(&twin, "q.glb", "KHR_mesh_quantization");
    for (file, args, ext) in [
        ("ext.glb", &["-cc"][..], "EXT_meshopt_compression"),
        (
            "khr.glb",
            &["-cc", "-ce", "khr"][..],
            "KHR_meshopt_compression",
        ),
        ("c.glb", &["-c"][..], "EXT_meshopt_compression"),
    ] {
        let bytes = make(file, args);
        let json = json_of(&bytes);
        assert!(
            extensions(&json, "extensionsRequired").contains(&ext.to_string()),
            "{file} should require {ext}"
        );
        let a = read(&bytes);
        assert_same_geometry(&a, &twin, file);
        fair_and_check_output(&a, file, ext);
    }
}

#[test]
fn gltf_transform_meshopt_reads_like_its_twin_and_fairs() {
    let obj = shared_mesh("spot_triangulated.obj");
    let dir = tempfile::tempdir().unwrap();
    let obj = obj.to_str().unwrap();
    tool(
        "gltfpack",
        &["-i", obj, "-o", "plain.glb", "-noq", "-kv"],
        dir.path(),
    );
    // gltf-transform's `meshopt` is reorder + quantize + the codec; the twin is the first two.
    tool(
        "gltf-transform",
        &["meshopt", "plain.glb", "m.glb"],
        dir.path(),
    );
    tool(
        "gltf-transform",
        &["reorder", "plain.glb", "r.glb"],
        dir.path(),
    );
    tool(
        "gltf-transform",
        &["quantize", "r.glb", "rq.glb"],
        dir.path(),
    );
    let bytes = std::fs::read(dir.path().join("m.glb")).unwrap();
    assert!(extensions(&json_of(&bytes), "extensionsRequired")
        .contains(&"EXT_meshopt_compression".to_string()));
    let a = read(&bytes);
    let twin = read(&std::fs::read(dir.path().join("rq.glb")).unwrap());
    assert_same_geometry(&a, &twin, "gltf-transform meshopt");
    fair_and_check_output(&a, "gltf-transform meshopt", "EXT_meshopt_compression");
}

#[test]
fn gltf_transform_draco_decodes_like_googles_decoder_and_fairs() {
    let obj = shared_mesh("spot_triangulated.obj");
    let dir = tempfile::tempdir().unwrap();
    let obj = obj.to_str().unwrap();
    tool(
        "gltfpack",
        &["-i", obj, "-o", "plain.glb", "-noq", "-kv"],
        dir.path(),
    );
    tool(
        "gltf-transform",
        &["draco", "plain.glb", "d.glb"],
        dir.path(),
    );
    // The twin: the same file decoded by Google's Draco decoder (draco3dgltf) and written
    // without the extension, by tests/tools/draco_to_plain.mjs.
    let script = tools_dir().join("draco_to_plain.mjs");
    let out = std::process::Command::new("node")
        .arg(&script)
        .args(["d.glb", "twin.glb"])
        .current_dir(dir.path())
        .output()
        .expect("node runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let bytes = std::fs::read(dir.path().join("d.glb")).unwrap();
    assert!(extensions(&json_of(&bytes), "extensionsRequired")
        .contains(&"KHR_draco_mesh_compression".to_string()));
    let a = read(&bytes);
    let twin = read(&std::fs::read(dir.path().join("twin.glb")).unwrap());
    assert_same_geometry(&a, &twin, "gltf-transform draco");
    // And it is spot: the same triangle count as the uncompressed file.
    let plain = read(&std::fs::read(dir.path().join("plain.glb")).unwrap());
    assert_eq!(a.file_triangles().len(), plain.file_triangles().len());
    fair_and_check_output(&a, "gltf-transform draco", "KHR_draco_mesh_compression");

    // The same file with its Draco stream cut to 16 bytes: an error naming the primitive and
    // the extension, not a panic or an empty mesh.
    let mut json = json_of(&bytes);
    let view = json["meshes"][0]["primitives"][0]["extensions"]["KHR_draco_mesh_compression"]
        ["bufferView"]
        .as_u64()
        .unwrap() as usize;
    json["bufferViews"][view]["byteLength"] = 16.into();
    let json_len = u32::from_le_bytes([bytes[12], bytes[13], bytes[14], bytes[15]]) as usize;
    let bin = &bytes[20 + json_len + 8..];
    let e = Asset::read(&glb_bytes(&json, bin), Format::Glb, &Limits::default()).unwrap_err();
    assert!(
        e.to_string().starts_with(&format!(
            "cannot parse glTF: mesh 0 primitive 0: KHR_draco_mesh_compression: the Draco \
             stream in bufferView {view} does not decode"
        )),
        "{e}"
    );
}

/// A glTF with a morph target (on POSITION), mesh and node weights and an animation of the
/// weights beside one of the node's translation: the written file has no targets, weights or
/// weight channel (the translation animation stays), validates, and the asset notes the drop.
#[test]
fn morph_targets_are_dropped_with_a_note() {
    let m = willow::mesh::generate::icosphere(1);
    let plain = Asset::from_mesh(m.clone(), &Limits::default()).unwrap();
    let glb = plain
        .write(&plain.surface().positions, Format::Glb)
        .unwrap();
    let mut json = json_of(&glb);
    let n = u32::from_le_bytes([glb[12], glb[13], glb[14], glb[15]]) as usize;
    let mut bin = glb[20 + n + 8..].to_vec();
    let mut add = |json: &mut serde_json::Value, bytes: Vec<u8>, acc: serde_json::Value| {
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        let views = json["bufferViews"].as_array_mut().unwrap();
        views.push(
            serde_json::json!({"buffer": 0, "byteOffset": bin.len(), "byteLength": bytes.len()}),
        );
        let mut acc = acc;
        acc["bufferView"] = (views.len() - 1).into();
        bin.extend_from_slice(&bytes);
        let accs = json["accessors"].as_array_mut().unwrap();
        accs.push(acc);
        accs.len() - 1
    };
    let f32s = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    // Every vertex pushed out by 0.2 along its radius: a "bloat" target.
    let offsets: Vec<f32> = m
        .positions
        .iter()
        .flat_map(|p| p.map(|x| (0.2 * x) as f32))
        .collect();
    let target = add(
        &mut json,
        f32s(&offsets),
        serde_json::json!({"componentType": 5126, "count": m.positions.len(), "type": "VEC3",
            "min": [-0.2, -0.2, -0.2], "max": [0.2, 0.2, 0.2]}),
    );
    let times = add(
        &mut json,
        f32s(&[0.0, 1.0]),
        serde_json::json!({"componentType": 5126, "count": 2, "type": "SCALAR", "min": [0.0], "max": [1.0]}),
    );
    let weights = add(
        &mut json,
        f32s(&[0.0, 1.0]),
        serde_json::json!({"componentType": 5126, "count": 2, "type": "SCALAR"}),
    );
    let moves = add(
        &mut json,
        f32s(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0]),
        serde_json::json!({"componentType": 5126, "count": 2, "type": "VEC3"}),
    );
    json["meshes"][0]["primitives"][0]["targets"] = serde_json::json!([{"POSITION": target}]);
    json["meshes"][0]["weights"] = serde_json::json!([0.5]);
    json["meshes"][0]["extras"] = serde_json::json!({"targetNames": ["bloat"]});
    json["nodes"][0]["weights"] = serde_json::json!([0.25]);
    json["animations"] = serde_json::json!([{
        "samplers": [{"input": times, "output": weights}, {"input": times, "output": moves}],
        "channels": [
            {"sampler": 0, "target": {"node": 0, "path": "weights"}},
            {"sampler": 1, "target": {"node": 0, "path": "translation"}}
        ]
    }]);
    json["buffers"][0]["byteLength"] = bin.len().into();
    let input = glb_bytes(&json, &bin);
    validate_with_khronos(&input, "glb");
    let a = read(&input);
    assert!(
        a.notes()
            .iter()
            .any(|n| n.starts_with("morph targets dropped: 1 targets on 1 primitives")),
        "{:?}",
        a.notes()
    );
    let moved: Vec<[f64; 3]> = a
        .surface()
        .positions
        .iter()
        .map(|p| p.map(|x| 1.1 * x))
        .collect();
    let out = a.write(&moved, Format::Glb).unwrap();
    validate_with_khronos(&out, "glb");
    let out_json = json_of(&out);
    let prim = &out_json["meshes"][0]["primitives"][0];
    assert!(prim.get("targets").is_none(), "{prim}");
    assert!(out_json["meshes"][0].get("weights").is_none());
    assert!(out_json["meshes"][0]["extras"].get("targetNames").is_none());
    assert!(out_json["nodes"][0].get("weights").is_none());
    let channels = out_json["animations"][0]["channels"].as_array().unwrap();
    assert_eq!(channels.len(), 1);
    assert_eq!(channels[0]["target"]["path"], "translation");
    // The base shape is the faired one.
    let b = read(&out);
    let got = b.file_positions(&b.surface().positions);
    for (g, e) in got.iter().zip(a.file_positions(&moved)) {
        assert_eq!(*g, e);
    }
    // Without targets there is nothing to note.
    assert!(read(&glb).notes().is_empty());
}

/// Positions of mesh 0's first primitive in world space, read with the `gltf` crate (not
/// willow's reader): POSITION's integers dequantized as glTF says, then the node's T·R·S
/// applied here. `KHR_mesh_quantization` is taken out of `extensionsRequired` first, since
/// the gltf crate refuses extensions it does not implement.
fn world_positions_by_gltf_crate(glb: &[u8]) -> Vec<[f64; 3]> {
    let n = u32::from_le_bytes([glb[12], glb[13], glb[14], glb[15]]) as usize;
    let mut root = gltf::json::Root::from_slice(&glb[20..20 + n]).unwrap();
    root.extensions_required.clear();
    let doc = gltf::Document::from_json(root).unwrap();
    let bin = &glb[20 + n + 8..];
    let node = doc.nodes().find(|n| n.mesh().is_some()).unwrap();
    let prim = node.mesh().unwrap().primitives().next().unwrap();
    let acc = prim.get(&gltf::Semantic::Positions).unwrap();
    let view = acc.view().unwrap();
    let size = acc.data_type().size();
    let stride = view.stride().unwrap_or(3 * size);
    let divisor = match (acc.data_type(), acc.normalized()) {
        (_, false) => 1.0,
        (gltf::accessor::DataType::U16, true) => 65535.0,
        (gltf::accessor::DataType::I16, true) => 32767.0,
        (gltf::accessor::DataType::U8, true) => 255.0,
        (gltf::accessor::DataType::I8, true) => 127.0,
        (t, _) => panic!("{t:?}"),
    };
    let (t, r, s) = node.transform().decomposed();
    let rotate = |v: [f64; 3]| -> [f64; 3] {
        // v + 2w(q×v) + 2q×(q×v), q = (x, y, z), w = r[3]
        let q = [r[0] as f64, r[1] as f64, r[2] as f64];
        let w = r[3] as f64;
        let cross = |a: [f64; 3], b: [f64; 3]| {
            [
                a[1] * b[2] - a[2] * b[1],
                a[2] * b[0] - a[0] * b[2],
                a[0] * b[1] - a[1] * b[0],
            ]
        };
        let c1 = cross(q, v);
        let c2 = cross(q, c1);
        [0, 1, 2].map(|k| v[k] + 2.0 * w * c1[k] + 2.0 * c2[k])
    };
    (0..acc.count())
        .map(|i| {
            let at = view.offset() + acc.offset() + i * stride;
            let c: [f64; 3] = std::array::from_fn(|k| {
                let b = &bin[at + k * size..at + (k + 1) * size];
                let raw = match acc.data_type() {
                    gltf::accessor::DataType::U16 => u16::from_le_bytes([b[0], b[1]]) as f64,
                    gltf::accessor::DataType::I16 => i16::from_le_bytes([b[0], b[1]]) as f64,
                    gltf::accessor::DataType::U8 => b[0] as f64,
                    gltf::accessor::DataType::I8 => b[0] as i8 as f64,
                    gltf::accessor::DataType::F32 => {
                        f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64
                    }
                    t => panic!("{t:?}"),
                };
                if acc.normalized() {
                    (raw / divisor).max(-1.0)
                } else {
                    raw
                }
            });
            let scaled = [0, 1, 2].map(|k| c[k] * s[k] as f64);
            let p = rotate(scaled);
            [0, 1, 2].map(|k| p[k] + t[k] as f64)
        })
        .collect()
}

/// gltfpack's default output (unsigned short POSITION over 14 bits, a node scale and
/// translation to dequantize it), faired and then grown by 1.3 past the input's box: written
/// back with POSITION still unsigned short on 14 bits over the new box, the node's transform
/// updated, validator-clean, and every vertex within half a step of the new grid of the f64
/// result, read with willow's reader and with the gltf crate. A node that also has a child
/// (whose transform the node's would move) gets float32 POSITION and says so in the note.
#[test]
fn gltfpack_quantized_output_is_requantized_over_the_new_box() {
    let obj = shared_mesh("spot_triangulated.obj");
    let dir = tempfile::tempdir().unwrap();
    let obj = obj.to_str().unwrap();
    tool("gltfpack", &["-i", obj, "-o", "q.glb", "-kv"], dir.path());
    let input = std::fs::read(dir.path().join("q.glb")).unwrap();
    let in_json = json_of(&input);
    assert_eq!(in_json["accessors"][0]["componentType"], 5123);
    let a = read(&input);
    let note = a.notes().join("\n");
    assert!(
        note.starts_with(
            "KHR_mesh_quantization input: glTF/GLB results keep it; POSITION re-quantized to \
             its own type (unsigned short over 14 bits (node 0))"
        ),
        "{note}"
    );
    let mut flow = new_flow(a.surface(), &FlowParams::default()).expect("flow");
    for _ in 0..2 {
        flow.step().unwrap();
    }
    let faired = flow.positions().to_vec();
    let n = faired.len() as f64;
    let c: [f64; 3] = [0, 1, 2].map(|k| faired.iter().map(|p| p[k]).sum::<f64>() / n);
    let moved: Vec<[f64; 3]> = faired
        .iter()
        .map(|p| [0, 1, 2].map(|k| c[k] + 1.3 * (p[k] - c[k])))
        .collect();
    let out = a.write(&moved, Format::Glb).unwrap();
    validate_with_khronos(&out, "glb");
    let json = json_of(&out);
    let pos = &json["accessors"][json["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
        .as_u64()
        .unwrap() as usize];
    assert_eq!(pos["componentType"], 5123, "{pos}");
    assert!(pos.get("normalized").is_none(), "{pos}");
    let (lo, hi) = (&pos["min"], &pos["max"]);
    assert_eq!(lo, &serde_json::json!([0, 0, 0]), "the box starts at 0");
    let top = (0..3).map(|k| hi[k].as_u64().unwrap()).max();
    assert_eq!(
        top,
        Some(16383),
        "the largest side spans 14 bits, as the input's did"
    );
    assert!(extensions(&json, "extensionsRequired").contains(&"KHR_mesh_quantization".into()));
    // The grown shape leaves the input's box (which its grid could not hold), and the step
    // grew with it.
    let old_scale = in_json["nodes"][0]["scale"][0].as_f64().unwrap();
    let outside = (0..3).any(|k| {
        let t = in_json["nodes"][0]["translation"][k].as_f64().unwrap();
        let top = t + old_scale * in_json["accessors"][0]["max"][k].as_f64().unwrap();
        moved.iter().any(|p| p[k] < t || p[k] > top)
    });
    assert!(outside, "the test shape should leave the input's box");
    let step = quantization_step(&json).unwrap();
    assert!(step > old_scale, "step {step} vs the input's {old_scale}");

    let b = read(&out);
    let err = max_world_error(&a, &moved, &b, |_| 0.5 * step * (1.0 + 1e-9));
    assert!(err.is_none(), "willow's reader: {err:?}");
    // The gltf crate's f32 node transform adds ~1e-7 of the model's size (spot is ~1.7).
    let by_crate = world_positions_by_gltf_crate(&out);
    let expected: Vec<[f64; 3]> = a
        .file_to_welded()
        .iter()
        .map(|w| moved[w.expect("gltfpack keeps only used vertices")])
        .collect();
    assert_eq!(by_crate.len(), expected.len());
    for (i, (g, e)) in by_crate.iter().zip(&expected).enumerate() {
        for k in 0..3 {
            assert!(
                (g[k] - e[k]).abs() <= 0.5 * step + 1e-6,
                "gltf crate: vertex {i} axis {k}: {} vs {} (step {step})",
                g[k],
                e[k]
            );
        }
    }

    // The same file with a child under the mesh node: re-quantizing would move the child.
    let mut json = in_json.clone();
    json["nodes"][0]["children"] = serde_json::json!([1]);
    json["nodes"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::json!({"name": "lamp"}));
    let bin = &input
        [20 + u32::from_le_bytes([input[12], input[13], input[14], input[15]]) as usize + 8..];
    let child = read(&glb_bytes(&json, bin));
    let note = child.notes().join("\n");
    assert!(
        note.contains(
            "POSITION stored as float32 in the node's unchanged space where a new node \
             transform would move something else: mesh 0 (node 0 has children)"
        ),
        "{note}"
    );
    let out = child.write(&moved, Format::Glb).unwrap();
    validate_with_khronos(&out, "glb");
    let json = json_of(&out);
    assert_eq!(json["accessors"][0]["componentType"], 5126);
    assert_eq!(json["nodes"][0]["scale"], in_json["nodes"][0]["scale"]);
    let b = read(&out);
    let err = max_world_error(&child, &moved, &b, |e| 1e-5 * (1.0 + e.abs()));
    assert!(err.is_none(), "float32 fallback: {err:?}");
}

/// The length of a GLB's BIN chunk.
fn bin_chunk_len(glb: &[u8]) -> usize {
    let n = u32::from_le_bytes([glb[12], glb[13], glb[14], glb[15]]) as usize;
    u32::from_le_bytes([glb[20 + n], glb[21 + n], glb[22 + n], glb[23 + n]]) as usize
}

/// gltfpack `-cc` spot (quantized and meshopt-compressed), faired 2 steps: the GLB written
/// back keeps `EXT_meshopt_compression` for POSITION, laid out as gltfpack does (checked in
/// `fair_and_check_output`: validator-clean, positions within half a quantization step), and
/// its BIN chunk is smaller than the same result written decoded, which is what its
/// uncompressed twin (gltfpack's default output, the same data before the codec) gives. The
/// glTF (JSON) output is validator-clean too.
#[test]
fn gltfpack_cc_output_keeps_meshopt_and_is_smaller_than_decoded() {
    let obj = shared_mesh("spot_triangulated.obj");
    let dir = tempfile::tempdir().unwrap();
    let obj = obj.to_str().unwrap();
    tool("gltfpack", &["-i", obj, "-o", "q.glb", "-kv"], dir.path());
    tool(
        "gltfpack",
        &["-i", obj, "-o", "cc.glb", "-kv", "-cc"],
        dir.path(),
    );
    let input = std::fs::read(dir.path().join("cc.glb")).unwrap();
    let a = read(&input);
    let twin = read(&std::fs::read(dir.path().join("q.glb")).unwrap());
    assert_same_geometry(&a, &twin, "cc.glb");
    let note = a.notes().join("\n");
    assert!(
        note.starts_with(
            "EXT_meshopt_compression input: glTF/GLB results keep it for the rewritten \
             POSITION and NORMAL views"
        ),
        "{note}"
    );
    let compressed = fair_and_check_output(&a, "cc.glb", "EXT_meshopt_compression");
    let decoded = fair_and_check_output(&twin, "q.glb", "KHR_mesh_quantization");
    let json = json_of(&decoded);
    assert!(
        !extensions(&json, "extensionsUsed")
            .iter()
            .any(|e| e.contains("meshopt")),
        "the twin's output is plain"
    );
    let (n_in, n_dec, n_enc) = (
        bin_chunk_len(&input),
        bin_chunk_len(&decoded),
        bin_chunk_len(&compressed),
    );
    eprintln!("BIN bytes: input {n_in}, written decoded {n_dec}, written re-encoded {n_enc}");
    assert!(n_enc < n_dec, "re-encoded {n_enc} vs decoded {n_dec}");
    // An independent decoder (gltf-transform's, meshoptimizer's JavaScript build; the Khronos
    // validator does not check this extension's data) reads the same positions willow does.
    std::fs::write(dir.path().join("out.glb"), &compressed).unwrap();
    tool(
        "gltf-transform",
        &["copy", "out.glb", "copy.glb"],
        dir.path(),
    );
    let copy = read(&std::fs::read(dir.path().join("copy.glb")).unwrap());
    assert!(
        !extensions(
            &json_of(&std::fs::read(dir.path().join("copy.glb")).unwrap()),
            "extensionsUsed"
        )
        .iter()
        .any(|e| e.contains("meshopt")),
        "gltf-transform writes what it decoded"
    );
    let ours = read(&compressed);
    let diff = first_difference(
        &copy.file_positions(&copy.surface().positions),
        &ours.file_positions(&ours.surface().positions),
    );
    assert!(
        diff.is_none(),
        "gltf-transform's decoding differs at {diff:?}"
    );

    let mut flow = new_flow(a.surface(), &FlowParams::default()).expect("flow");
    flow.step().unwrap();
    let gltf = a.write(flow.positions(), Format::Gltf).unwrap();
    validate_with_khronos(&gltf, "gltf");
}
