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

// ---------------------------------------------------------------------------------------
// What a refined file keeps (issue 26 item 5): a glTF its document, an OBJ its statements.

use serde_json::Value;
use willow::flow::{new_flow, FlowParams, Method};

/// A GLB's JSON and BIN chunks.
fn glb_parts(glb: &[u8]) -> (Value, Vec<u8>) {
    let u32_at = |at: usize| u32::from_le_bytes([glb[at], glb[at + 1], glb[at + 2], glb[at + 3]]);
    let n = u32_at(12) as usize;
    let json: Value = serde_json::from_slice(&glb[20..20 + n]).expect("json chunk");
    let m = u32_at(20 + n) as usize;
    (json, glb[28 + n..28 + n + m].to_vec())
}

/// The bytes of buffer view `view` (buffer 0 is the BIN chunk).
fn view_bytes<'a>(json: &Value, bin: &'a [u8], view: usize) -> &'a [u8] {
    let v = &json["bufferViews"][view];
    let at = v["byteOffset"].as_u64().unwrap_or(0) as usize;
    &bin[at..at + v["byteLength"].as_u64().expect("byteLength") as usize]
}

/// Accessor `acc` as f64 numbers, `width` per element: float32, or (indices) u16/u32, tightly
/// packed (what the tests' inputs and Willow's outputs use).
fn accessor_numbers(json: &Value, bin: &[u8], acc: usize) -> (Vec<f64>, usize) {
    let a = &json["accessors"][acc];
    let width = match a["type"].as_str().expect("type") {
        "SCALAR" => 1,
        "VEC2" => 2,
        "VEC3" => 3,
        "VEC4" => 4,
        t => panic!("accessor {acc}: type {t}"),
    };
    let count = a["count"].as_u64().expect("count") as usize;
    let data = view_bytes(json, bin, a["bufferView"].as_u64().expect("view") as usize);
    let at = a["byteOffset"].as_u64().unwrap_or(0) as usize;
    let numbers = match a["componentType"].as_u64().expect("componentType") {
        5126 => data[at..at + 4 * width * count]
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64)
            .collect(),
        5125 => data[at..at + 4 * width * count]
            .chunks_exact(4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64)
            .collect(),
        5123 => data[at..at + 2 * width * count]
            .chunks_exact(2)
            .map(|b| u16::from_le_bytes([b[0], b[1]]) as f64)
            .collect(),
        5121 => data[at..at + width * count]
            .iter()
            .map(|&b| b as f64 / 255.0)
            .collect(),
        c => panic!("accessor {acc}: componentType {c}"),
    };
    (numbers, width)
}

/// Per triangle of primitive 0 of mesh 0, the attribute `name` at its three corners.
fn corner_values(json: &Value, bin: &[u8], name: &str) -> Vec<[Vec<f64>; 3]> {
    let prim = &json["meshes"][0]["primitives"][0];
    let acc = prim["attributes"][name].as_u64().expect("attribute") as usize;
    let (values, w) = accessor_numbers(json, bin, acc);
    let (idx, _) = accessor_numbers(
        json,
        bin,
        prim["indices"].as_u64().expect("indices") as usize,
    );
    idx.chunks_exact(3)
        .map(|t| [0, 1, 2].map(|k| values[t[k] as usize * w..(t[k] as usize + 1) * w].to_vec()))
        .collect()
}

/// `levels` 1-to-4 midpoint splits of triangles given by their corners' attribute values:
/// the linear interpolation a refined file must carry, computed here on its own.
fn midpoint_split(tris: Vec<[Vec<f64>; 3]>, levels: usize) -> Vec<[Vec<f64>; 3]> {
    let mid = |p: &[f64], q: &[f64]| -> Vec<f64> {
        p.iter().zip(q).map(|(a, b)| 0.5 * (a + b)).collect()
    };
    let mut tris = tris;
    for _ in 0..levels {
        tris = tris
            .iter()
            .flat_map(|[a, b, c]| {
                let (ab, bc, ca) = (mid(a, b), mid(b, c), mid(c, a));
                [
                    [a.clone(), ab.clone(), ca.clone()],
                    [ab.clone(), b.clone(), bc.clone()],
                    [ca.clone(), bc.clone(), c.clone()],
                    [ab, bc, ca],
                ]
            })
            .collect();
    }
    tris
}

/// The same triangles of attribute values to 1e-5 (f32 storage), the children of each input
/// triangle following it in order (`n` per parent) but in any order among themselves, each
/// with its corners in the parent's winding (any rotation).
fn assert_same_triangles(written: &[[Vec<f64>; 3]], expected: &[[Vec<f64>; 3]], n: usize) {
    assert_eq!(written.len(), expected.len());
    let close = |p: &[f64], q: &[f64]| p.iter().zip(q).all(|(x, y)| (x - y).abs() < 1e-5);
    let same = |a: &[Vec<f64>; 3], b: &[Vec<f64>; 3]| {
        (0..3).any(|r| (0..3).all(|k| close(&a[(k + r) % 3], &b[k])))
    };
    for (t, (w, e)) in written.chunks(n).zip(expected.chunks(n)).enumerate() {
        let mut used = vec![false; w.len()];
        for x in e {
            let found = (0..w.len()).find(|&i| !used[i] && same(&w[i], x));
            let i = found.unwrap_or_else(|| panic!("parent {t}: no written child {x:?}"));
            used[i] = true;
        }
    }
}

/// Two conformal steps on `asset`'s surface: a faired shape to write.
fn faired(asset: &Asset) -> Vec<[f64; 3]> {
    let params = FlowParams {
        method: Method::Conformal,
        ..FlowParams::default()
    };
    let mut flow = new_flow(asset.surface(), &params).expect("flow");
    for _ in 0..2 {
        flow.step().expect("step");
    }
    let moved = flow.positions().to_vec();
    assert!(moved != asset.surface().positions, "the flow moved nothing");
    moved
}

/// A refined, faired textured glTF keeps the input's document: materials, textures, samplers,
/// images (their bytes), nodes (hierarchy, transforms, names) and the primitive's material; it
/// validates; its first 24 UVs are the input's, and every child triangle's UVs are the linear
/// subdivision of its parent's, computed here.
#[test]
fn a_refined_gltf_keeps_materials_textures_and_nodes() {
    let (json, bin, _, png) = mesh_support::textured_cube_gltf();
    let glb = mesh_support::glb_bytes(&json, &bin);
    let limits = Limits::default();
    let asset = Asset::read(&glb, Format::Glb, &limits).expect("cube");
    let target = 0.3 * willow::mesh::generate::mean_edge_length(asset.surface());
    let (r, how) = asset.refined(Some(target), &limits).expect("refine");
    assert_eq!(how.levels, 2, "{how:?}");
    let moved = faired(&r);
    let out = r.write(&moved, Format::Glb).expect("write");
    mesh_support::validate_with_khronos(&out, "glb");
    let (out_json, out_bin) = glb_parts(&out);

    for key in [
        "materials",
        "textures",
        "samplers",
        "nodes",
        "scenes",
        "scene",
    ] {
        assert_eq!(out_json[key], json[key], "{key}");
    }
    assert_eq!(out_json["meshes"][0]["primitives"][0]["material"], 0);
    assert_eq!(out_json["images"].as_array().map(Vec::len), Some(1));
    let image = &out_json["images"][0];
    assert_eq!(image["mimeType"], "image/png");
    let view = image["bufferView"].as_u64().expect("image view") as usize;
    assert_eq!(
        view_bytes(&out_json, &out_bin, view),
        &png[..],
        "image bytes"
    );

    // UVs: the input's 24 first, unchanged; every child triangle's corner UVs the midpoint
    // subdivision of its parent's (as a set: the order of children is the writer's).
    let prim = &out_json["meshes"][0]["primitives"][0];
    let uv_acc = prim["attributes"]["TEXCOORD_0"].as_u64().expect("uv") as usize;
    let (uv_out, _) = accessor_numbers(&out_json, &out_bin, uv_acc);
    let (uv_in, _) = accessor_numbers(&json, &bin, 2);
    assert_eq!(
        uv_out[..48],
        uv_in[..],
        "the input's vertices keep their UVs"
    );
    assert!(uv_out.len() > 48);
    let expected = midpoint_split(corner_values(&json, &bin, "TEXCOORD_0"), 2);
    let written = corner_values(&out_json, &out_bin, "TEXCOORD_0");
    assert_eq!(written.len(), 12 * 16);
    assert_same_triangles(&written, &expected, 16);

    // The written positions are the faired ones: read back, the surface is `moved`.
    let back = Asset::read(&out, Format::Glb, &limits).expect("read back");
    assert_eq!(back.surface().face_count(), r.surface().face_count());
    let mut a = back.surface().positions.clone();
    let mut b = moved.clone();
    for v in [&mut a, &mut b] {
        v.sort_by(|p, q| p.partial_cmp(q).unwrap_or(std::cmp::Ordering::Equal));
    }
    for (p, q) in a.iter().zip(&b) {
        assert!((0..3).all(|k| (p[k] - q[k]).abs() < 1e-4), "{p:?} vs {q:?}");
    }
}

/// A unit cube as OBJ text in two groups with two materials and smoothing groups: the top
/// three quads (`g top`, `usemtl red`, `s 1`) and the bottom three (`g bottom`, `usemtl
/// blue`, `s off`), each corner with its face's own `vt` (every cube edge a UV seam).
fn two_group_cube_obj() -> String {
    let mut s = String::from("# two groups\nmtllib cube.mtl\no box\n");
    for i in 0..8 {
        let (x, y, z) = (i & 1, (i >> 1) & 1, (i >> 2) & 1);
        s += &format!("v {x} {y} {z}\n");
    }
    let quads = [
        [1, 3, 4, 2],
        [5, 6, 8, 7],
        [1, 2, 6, 5],
        [3, 7, 8, 4],
        [1, 5, 7, 3],
        [2, 4, 8, 6],
    ];
    for f in 0..6 {
        for (du, dv) in [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)] {
            s += &format!("vt {} {}\n", (f as f64 + du) / 6.0, dv);
        }
    }
    for (f, q) in quads.iter().enumerate() {
        if f == 0 {
            s += "g top\nusemtl red\ns 1\n";
        }
        if f == 3 {
            s += "# the other half\ng bottom\nusemtl blue\ns off\n";
        }
        let c = |k: usize| format!("{}/{}", q[k], 4 * f + k + 1);
        s += &format!("f {} {} {} {}\n", c(0), c(1), c(2), c(3));
    }
    s
}

/// A refined, faired OBJ keeps every statement that is not vertex data or a face, in order;
/// each parent quad's `f` line becomes its 2·4 children under the same `g`, `usemtl` and `s`;
/// the children of a group use exactly the group's own corners of the input; the `v` lines
/// are the streamed file vertices in order; and the file reads back as the refined surface
/// with the same groups.
#[test]
fn a_refined_obj_keeps_groups_materials_and_smoothing() {
    let text = two_group_cube_obj();
    let limits = Limits::default();
    let asset = Asset::read(text.as_bytes(), Format::Obj, &limits).expect("cube");
    let target = 0.5 * willow::mesh::generate::mean_edge_length(asset.surface());
    let (r, how) = asset.refined(Some(target), &limits).expect("refine");
    assert_eq!(how.levels, 1);
    let moved = faired(&r);
    let out = String::from_utf8(r.write(&moved, Format::Obj).expect("write")).expect("utf8");

    let kept = |t: &str| -> Vec<String> {
        t.lines()
            .filter(|l| !matches!(l.split_whitespace().next(), Some("v" | "vt" | "vn" | "f")))
            .map(str::to_owned)
            .collect()
    };
    assert_eq!(
        kept(&out),
        kept(&text),
        "statements other than data and faces"
    );

    // Faces under each (g, usemtl, s), as the `vt` of their corners. Input face f has the UV
    // square u in [f/6, (f+1)/6], so a child's UVs tell its parent on their own.
    let vts: Vec<f64> = out
        .lines()
        .filter(|l| l.starts_with("vt "))
        .map(|l| {
            l[3..]
                .split_whitespace()
                .next()
                .and_then(|u| u.parse().ok())
                .expect("u")
        })
        .collect();
    let mut state = (String::new(), String::new(), String::new());
    let mut faces: std::collections::BTreeMap<(String, String, String), Vec<usize>> =
        Default::default();
    for l in out.lines() {
        let mut w = l.split_whitespace();
        match w.next() {
            Some("g") => state.0 = w.collect::<Vec<_>>().join(" "),
            Some("usemtl") => state.1 = w.collect::<Vec<_>>().join(" "),
            Some("s") => state.2 = w.collect::<Vec<_>>().join(" "),
            Some("f") => {
                let us: Vec<f64> = w
                    .map(|c| {
                        let vt: usize = c
                            .split('/')
                            .nth(1)
                            .and_then(|t| t.parse().ok())
                            .expect("vt");
                        vts[vt - 1]
                    })
                    .collect();
                assert_eq!(us.len(), 3, "{l}");
                let parent = (us.iter().sum::<f64>() / 3.0 * 6.0).floor() as usize;
                for u in &us {
                    let lo = parent as f64 / 6.0;
                    assert!(
                        (lo - 1e-9..=lo + 1.0 / 6.0 + 1e-9).contains(u),
                        "{l}: {us:?}"
                    );
                }
                faces.entry(state.clone()).or_default().push(parent);
            }
            _ => {}
        }
    }
    let key = |g: &str, m: &str, s: &str| (g.to_owned(), m.to_owned(), s.to_owned());
    assert_eq!(faces.len(), 2, "{:?}", faces.keys());
    let mut top = faces[&key("top", "red", "1")].clone();
    let mut bottom = faces[&key("bottom", "blue", "off")].clone();
    top.sort_unstable();
    bottom.sort_unstable();
    // Each input quad (2 triangles) has 2·4 children, under its own group.
    let children = |fs: std::ops::Range<usize>| -> Vec<usize> {
        fs.flat_map(|f| std::iter::repeat_n(f, 8)).collect()
    };
    assert_eq!(top, children(0..3));
    assert_eq!(bottom, children(3..6));

    // `v` line k is file vertex k of the frames.
    let v_lines: Vec<[f64; 3]> = out
        .lines()
        .filter(|l| l.starts_with("v "))
        .map(|l| {
            let n: Vec<f64> = l[2..]
                .split_whitespace()
                .map(|x| x.parse().expect("number"))
                .collect();
            [n[0], n[1], n[2]]
        })
        .collect();
    let frame = r.file_positions(&moved);
    assert_eq!(v_lines.len(), frame.len());
    for (p, q) in v_lines.iter().zip(&frame) {
        assert!(
            (0..3).all(|k| (p[k] - q[k] as f64).abs() < 1e-6),
            "{p:?} vs {q:?}"
        );
    }

    let back = Asset::read(out.as_bytes(), Format::Obj, &limits).expect("read back");
    assert_eq!(back.surface().face_count(), r.surface().face_count());
    assert_eq!(back.surface().vertex_count(), r.surface().vertex_count());
    assert_eq!(back.group_names(), vec!["box", "top", "bottom"]);
    assert_eq!(r.group_names(), back.group_names());
    assert_eq!(back.group_vertices("top"), r.group_vertices("top"));
    assert!(back.corner_uvs().is_some());
}

/// Appends `data` to `bin` as a new vertex buffer view of `json`; returns the view.
fn push_view(json: &mut Value, bin: &mut Vec<u8>, data: &[u8]) -> usize {
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let views = json["bufferViews"].as_array_mut().expect("views");
    views.push(serde_json::json!({"buffer": 0, "byteOffset": bin.len(),
        "byteLength": data.len(), "target": 34962}));
    bin.extend_from_slice(data);
    views.len() - 1
}

/// Other per-vertex attributes under refine (issue 26 item 5): COLOR_0 (normalized bytes) is
/// interpolated like the UVs; TANGENT, JOINTS_0/WEIGHTS_0 are dropped with a note each, and
/// the skin is detached from the node, so the output validates.
#[test]
fn a_refined_gltf_interpolates_colours_and_drops_skins_with_a_note() {
    let (mut json, mut bin, _, _) = mesh_support::textured_cube_gltf();
    let colours: Vec<u8> = (0..24u32)
        .flat_map(|i| {
            [
                (i * 10) as u8,
                (255 - i * 7) as u8,
                (i * i % 256) as u8,
                255,
            ]
        })
        .collect();
    let tangents: Vec<u8> = (0..24)
        .flat_map(|_| [1.0f32, 0.0, 0.0, 1.0])
        .flat_map(f32::to_le_bytes)
        .collect();
    let joints: Vec<u8> = (0..24).flat_map(|_| [0u8, 0, 0, 0]).collect();
    let weights: Vec<u8> = (0..24)
        .flat_map(|_| [1.0f32, 0.0, 0.0, 0.0])
        .flat_map(f32::to_le_bytes)
        .collect();
    let vc = push_view(&mut json, &mut bin, &colours);
    let vt = push_view(&mut json, &mut bin, &tangents);
    let vj = push_view(&mut json, &mut bin, &joints);
    let vw = push_view(&mut json, &mut bin, &weights);
    let accessors = json["accessors"].as_array_mut().expect("accessors");
    for (view, ty, normalized) in [
        (vc, 5121, true),
        (vt, 5126, false),
        (vj, 5121, false),
        (vw, 5126, false),
    ] {
        let mut a = serde_json::json!({"bufferView": view, "componentType": ty, "count": 24, "type": "VEC4"});
        if normalized {
            a["normalized"] = serde_json::json!(true);
        }
        accessors.push(a);
    }
    let attrs = &mut json["meshes"][0]["primitives"][0]["attributes"];
    for (k, name) in ["COLOR_0", "TANGENT", "JOINTS_0", "WEIGHTS_0"]
        .iter()
        .enumerate()
    {
        attrs[*name] = serde_json::json!(4 + k);
    }
    json["nodes"][0]["children"] = serde_json::json!([1, 2]);
    json["nodes"]
        .as_array_mut()
        .expect("nodes")
        .push(serde_json::json!({"name": "bone"}));
    json["nodes"][1]["skin"] = serde_json::json!(0);
    json["skins"] = serde_json::json!([{"joints": [2]}]);
    json["buffers"][0]["byteLength"] = serde_json::json!(bin.len());
    let glb = mesh_support::glb_bytes(&json, &bin);

    let limits = Limits::default();
    let asset = Asset::read(&glb, Format::Glb, &limits).expect("cube");
    let target = 0.3 * willow::mesh::generate::mean_edge_length(asset.surface());
    let (r, how) = asset.refined(Some(target), &limits).expect("refine");
    assert_eq!(how.levels, 2);
    let notes = r.notes();
    assert!(notes.iter().any(|n| n.contains("TANGENT")), "{notes:?}");
    assert!(
        notes.iter().any(|n| n.contains("JOINTS_0, WEIGHTS_0")),
        "{notes:?}"
    );
    assert_eq!(notes.len(), 2, "{notes:?}");

    let out = r.write(&faired(&r), Format::Glb).expect("write");
    mesh_support::validate_with_khronos(&out, "glb");
    let (out_json, out_bin) = glb_parts(&out);
    let mut names: Vec<&str> = out_json["meshes"][0]["primitives"][0]["attributes"]
        .as_object()
        .expect("attributes")
        .keys()
        .map(String::as_str)
        .collect();
    names.sort_unstable();
    assert_eq!(names, ["COLOR_0", "NORMAL", "POSITION", "TEXCOORD_0"]);
    assert!(out_json["nodes"][1].get("skin").is_none());
    assert_eq!(out_json["nodes"][1]["name"], "child");

    let expected = midpoint_split(corner_values(&json, &bin, "COLOR_0"), 2);
    let written = corner_values(&out_json, &out_bin, "COLOR_0");
    assert_same_triangles(&written, &expected, 16);
    let col = out_json["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"]
        .as_u64()
        .expect("c");
    let (values, _) = accessor_numbers(&out_json, &out_bin, col as usize);
    for (k, &b) in colours.iter().enumerate() {
        assert!(
            (values[k] - b as f64 / 255.0).abs() < 1e-6,
            "colour component {k}"
        );
    }
}

/// The Khronos Duck (textured, one primitive, a node hierarchy with a camera) refined at the
/// default target and faired: the written GLB validates, keeps the document's materials,
/// textures, samplers, nodes, cameras and image bytes, and the input's UVs come first,
/// unchanged; each child triangle's UVs are the linear subdivision of its parent's.
#[test]
fn the_refined_duck_keeps_its_texture() {
    let path = mesh_support::shared_mesh("Duck.glb");
    let glb = std::fs::read(path).expect("read Duck.glb");
    let (json, bin) = glb_parts(&glb);
    let limits = Limits::default();
    let asset = Asset::read(&glb, Format::Glb, &limits).expect("duck");
    let (r, how) = asset.refined(None, &limits).expect("refine");
    assert!(how.levels >= 1, "{how:?}");
    let out = r.write(&faired(&r), Format::Glb).expect("write");
    mesh_support::validate_with_khronos(&out, "glb");
    let (out_json, out_bin) = glb_parts(&out);
    for key in [
        "materials",
        "textures",
        "samplers",
        "nodes",
        "cameras",
        "scenes",
    ] {
        assert_eq!(out_json[key], json[key], "{key}");
    }
    let image = |j: &Value, b: &[u8]| -> Vec<u8> {
        let view = j["images"][0]["bufferView"].as_u64().expect("image view") as usize;
        view_bytes(j, b, view).to_vec()
    };
    assert_eq!(
        image(&out_json, &out_bin),
        image(&json, &bin),
        "image bytes"
    );

    let uv_of = |j: &Value, b: &[u8]| -> Vec<f64> {
        let acc = j["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"]
            .as_u64()
            .expect("uv");
        accessor_numbers(j, b, acc as usize).0
    };
    let (uv_in, uv_out) = (uv_of(&json, &bin), uv_of(&out_json, &out_bin));
    assert_eq!(uv_out[..uv_in.len()], uv_in[..]);
    let expected = midpoint_split(corner_values(&json, &bin, "TEXCOORD_0"), how.levels);
    let written = corner_values(&out_json, &out_bin, "TEXCOORD_0");
    assert_same_triangles(&written, &expected, 1 << (2 * how.levels));
}

/// OBJ vertex colours (`v x y z r g b`) under refine: the file's `v` lines keep theirs, and
/// each new `v` line carries the mean colour of its edge's ends. Colours are an affine
/// function of the input position, so the expected set is the function at each edge
/// midpoint, over the edges of the input's fan-triangulated quads (computed here).
#[test]
fn a_refined_obj_interpolates_vertex_colours() {
    let colour = |p: [f64; 3]| p.map(|x| (x + 1.0) / 4.0);
    let mut positions = Vec::new();
    let text: String = two_group_cube_obj()
        .lines()
        .map(|l| match l.strip_prefix("v ") {
            Some(rest) => {
                let p: Vec<f64> = rest
                    .split_whitespace()
                    .map(|x| x.parse().expect("x"))
                    .collect();
                let p = [p[0], p[1], p[2]];
                positions.push(p);
                let c = colour(p);
                format!("{l} {} {} {}\n", c[0], c[1], c[2])
            }
            None => format!("{l}\n"),
        })
        .collect();
    let mut edges = std::collections::BTreeSet::new();
    for l in text.lines().filter(|l| l.starts_with("f ")) {
        let v: Vec<usize> = l[2..]
            .split_whitespace()
            .map(|c| c.split('/').next().and_then(|v| v.parse().ok()).expect("v"))
            .collect();
        for t in 1..v.len() - 1 {
            for (a, b) in [(v[0], v[t]), (v[t], v[t + 1]), (v[t + 1], v[0])] {
                edges.insert((a.min(b), a.max(b)));
            }
        }
    }
    let key = |c: [f64; 3]| c.map(|x| (x * 1e9).round() as i64);
    let mut expected: Vec<[i64; 3]> = edges
        .iter()
        .map(|&(a, b)| {
            let (p, q) = (positions[a - 1], positions[b - 1]);
            key(colour([0, 1, 2].map(|k| 0.5 * (p[k] + q[k]))))
        })
        .collect();
    expected.sort_unstable();

    let limits = Limits::default();
    let asset = Asset::read(text.as_bytes(), Format::Obj, &limits).expect("cube");
    let target = 0.5 * willow::mesh::generate::mean_edge_length(asset.surface());
    let (r, how) = asset.refined(Some(target), &limits).expect("refine");
    assert_eq!(how.levels, 1);
    let out = String::from_utf8(r.write(&faired(&r), Format::Obj).expect("write")).expect("utf8");
    let colours: Vec<[f64; 3]> = out
        .lines()
        .filter(|l| l.starts_with("v "))
        .map(|l| {
            let n: Vec<f64> = l[2..]
                .split_whitespace()
                .map(|x| x.parse().expect("n"))
                .collect();
            assert_eq!(n.len(), 6, "{l}");
            [n[3], n[4], n[5]]
        })
        .collect();
    assert_eq!(colours.len(), 8 + edges.len());
    for (c, p) in colours.iter().zip(&positions) {
        assert_eq!(*c, colour(*p), "an input v line keeps its colour");
    }
    let mut new: Vec<[i64; 3]> = colours[8..].iter().map(|&c| key(c)).collect();
    new.sort_unstable();
    assert_eq!(new, expected);
}

/// Pipelines' glTF under refine: spot packed by gltfpack (quantized, `KHR_mesh_quantization`;
/// and meshopt-compressed, `EXT_meshopt_compression`) refined and faired writes a
/// validator-clean GLB that reads back as the refined surface, its UVs first the input's.
#[test]
fn refined_quantized_and_meshopt_gltf_validate() {
    let obj = mesh_support::shared_mesh("spot_triangulated.obj");
    let dir = tempfile::tempdir().expect("tempdir");
    let obj = obj.to_str().expect("path");
    let limits = Limits::default();
    for (name, extra) in [("q.glb", &[][..]), ("cc.glb", &["-cc"][..])] {
        let mut args = vec!["-i", obj, "-o", name, "-kv"];
        args.extend_from_slice(extra);
        mesh_support::gltf_tool("gltfpack", &args, dir.path());
        let glb = std::fs::read(dir.path().join(name)).expect("packed");
        let asset = Asset::read(&glb, Format::Glb, &limits).expect("packed spot");
        let (r, how) = asset.refined(None, &limits).expect("refine");
        assert_eq!(how.levels, 1, "{name}");
        let moved = faired(&r);
        let out = r.write(&moved, Format::Glb).expect("write");
        mesh_support::validate_with_khronos(&out, "glb");
        let back = Asset::read(&out, Format::Glb, &limits).expect("read back");
        assert_eq!(
            back.surface().face_count(),
            r.surface().face_count(),
            "{name}"
        );
        assert_eq!(
            back.surface().vertex_count(),
            r.surface().vertex_count(),
            "{name}"
        );
        let (uv_in, uv_out) = (
            asset.corner_uvs().expect("uvs"),
            back.corner_uvs().expect("uvs kept"),
        );
        // Child 4t's first corner is parent t's first corner (module docs of refined.rs).
        for (t, parent) in uv_in.iter().enumerate() {
            let child = uv_out[4 * t][0];
            assert!(
                (0..2).all(|k| (child[k] - parent[0][k]).abs() < 1e-6),
                "{name}: triangle {t}: {child:?} vs {:?}",
                parent[0]
            );
        }
    }
}
