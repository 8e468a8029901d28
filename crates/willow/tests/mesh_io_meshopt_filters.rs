//! meshopt's filters (issue 27, item 1), with the pinned gltfpack (tests/tools): spot with
//! vertex normals and colours computed here and a rotation animation, compressed with `-cc`,
//! decodes to the plain file within each attribute's quantization step: normals through the
//! OCTAHEDRAL filter, rotations through QUATERNION, colours through COLOR (`-ce khr`).

mod mesh_support;

use mesh_support::*;
use serde_json::{json, Value};
use willow::mesh::io::{Asset, Format, Limits};

fn read(bytes: &[u8]) -> Asset {
    Asset::read(bytes, Format::Glb, &Limits::default()).unwrap()
}

/// The JSON and BIN chunks of a GLB.
fn chunks(glb: &[u8]) -> (Value, Vec<u8>) {
    let n = u32::from_le_bytes([glb[12], glb[13], glb[14], glb[15]]) as usize;
    let json = serde_json::from_slice(&glb[20..20 + n]).unwrap();
    (json, glb.get(20 + n + 8..).unwrap_or_default().to_vec())
}

/// Accessor `index` as f64 rows: floats as they are, normalized integers mapped as glTF 2.0
/// §3.11 says (written independently of the crate's reader).
fn accessor(json: &Value, bin: &[u8], index: usize) -> Vec<Vec<f64>> {
    let a = &json["accessors"][index];
    let view = &json["bufferViews"][a["bufferView"].as_u64().unwrap() as usize];
    let width = match a["type"].as_str().unwrap() {
        "SCALAR" => 1,
        "VEC2" => 2,
        "VEC3" => 3,
        "VEC4" => 4,
        t => panic!("type {t}"),
    };
    let ct = a["componentType"].as_u64().unwrap();
    let size = match ct {
        5120 | 5121 => 1,
        5122 | 5123 => 2,
        5126 => 4,
        c => panic!("componentType {c}"),
    };
    let stride = view["byteStride"]
        .as_u64()
        .map_or(width * size, |s| s as usize);
    let start = view["byteOffset"].as_u64().unwrap_or(0) as usize
        + a["byteOffset"].as_u64().unwrap_or(0) as usize;
    let normalized = a["normalized"].as_bool().unwrap_or(false);
    (0..a["count"].as_u64().unwrap() as usize)
        .map(|i| {
            (0..width)
                .map(|k| {
                    let at = start + i * stride + k * size;
                    let b = &bin[at..at + size];
                    let (x, scale) = match ct {
                        5120 => (f64::from(b[0] as i8), 127.0),
                        5121 => (f64::from(b[0]), 255.0),
                        5122 => (f64::from(i16::from_le_bytes([b[0], b[1]])), 32767.0),
                        5123 => (f64::from(u16::from_le_bytes([b[0], b[1]])), 65535.0),
                        _ => (f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])), 1.0),
                    };
                    if normalized && ct != 5126 {
                        (x / scale).max(-1.0)
                    } else {
                        x
                    }
                })
                .collect()
        })
        .collect()
}

/// Appends `values` (f32) to `bin` behind a new view and accessor; returns the accessor.
fn push_f32(json: &mut Value, bin: &mut Vec<u8>, values: &[f32], extra: Value) -> usize {
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let views = json["bufferViews"].as_array_mut().unwrap();
    views.push(json!({"buffer": 0, "byteOffset": bin.len(), "byteLength": values.len() * 4}));
    let view = views.len() - 1;
    bin.extend(values.iter().flat_map(|x| x.to_le_bytes()));
    let mut acc = extra;
    acc["bufferView"] = view.into();
    acc["componentType"] = 5126.into();
    let accs = json["accessors"].as_array_mut().unwrap();
    accs.push(acc);
    accs.len() - 1
}

fn unit(v: [f64; 3]) -> [f64; 3] {
    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    v.map(|x| x / l)
}

/// A plain GLB and the attribute values it holds, per file vertex (rotations per key).
struct Plain {
    glb: Vec<u8>,
    normals: Vec<[f64; 3]>,
    colours: Vec<[f64; 4]>,
    rotations: Vec<[f64; 4]>,
}

/// spot as a plain GLB with area-weighted vertex normals, a colour per vertex made from its
/// normal, and a node rotation animated over four keys.
fn spot_with_attributes() -> Plain {
    let obj = include_bytes!("data/spot_triangulated.obj");
    let spot = Asset::read(obj, Format::Obj, &Limits::default()).unwrap();
    let (mut json, mut bin) = chunks(&spot.write(&spot.surface().positions, Format::Glb).unwrap());
    let plain = read(&glb_bytes(&json, &bin));
    // Normals of the welded surface (sum of face normals, i.e. area-weighted), per file vertex.
    let s = plain.surface();
    let mut n = vec![[0.0; 3]; s.vertex_count()];
    for t in &s.triangles {
        let [a, b, c] = t.map(|i| s.positions[i]);
        let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let w = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
        let f = [
            u[1] * w[2] - u[2] * w[1],
            u[2] * w[0] - u[0] * w[2],
            u[0] * w[1] - u[1] * w[0],
        ];
        for i in t {
            (0..3).for_each(|k| n[*i][k] += f[k]);
        }
    }
    let normals: Vec<[f64; 3]> = plain
        .file_to_welded()
        .iter()
        .map(|w| unit(n[w.expect("every vertex is used")]))
        .collect();
    let colours: Vec<[f64; 4]> = normals
        .iter()
        .map(|n| [0.5 + 0.5 * n[0], 0.5 + 0.5 * n[1], 0.5 + 0.5 * n[2], 1.0])
        .collect();
    let to_f32 = |rows: &[f64]| rows.iter().map(|&x| x as f32).collect::<Vec<f32>>();
    let flat_n: Vec<f64> = normals.iter().flatten().copied().collect();
    let flat_c: Vec<f64> = colours.iter().flatten().copied().collect();
    let count = normals.len();
    let na = push_f32(
        &mut json,
        &mut bin,
        &to_f32(&flat_n),
        json!({"count": count, "type": "VEC3"}),
    );
    let ca = push_f32(
        &mut json,
        &mut bin,
        &to_f32(&flat_c),
        json!({"count": count, "type": "VEC4"}),
    );
    let attrs = &mut json["meshes"][0]["primitives"][0]["attributes"];
    attrs["NORMAL"] = na.into();
    attrs["COLOR_0"] = ca.into();
    // Rotations about a tilted axis by 0, 60, 150 and 270 degrees.
    let axis = unit([1.0, 2.0, 0.5]);
    let rotations: Vec<[f64; 4]> = [0.0f64, 60.0, 150.0, 270.0]
        .iter()
        .map(|d| {
            let h = d.to_radians() / 2.0;
            [
                axis[0] * h.sin(),
                axis[1] * h.sin(),
                axis[2] * h.sin(),
                h.cos(),
            ]
        })
        .collect();
    let times = push_f32(
        &mut json,
        &mut bin,
        &[0.0, 1.0, 2.0, 3.0],
        json!({"count": 4, "type": "SCALAR", "min": [0.0], "max": [3.0]}),
    );
    let flat_r: Vec<f64> = rotations.iter().flatten().copied().collect();
    let rot = push_f32(
        &mut json,
        &mut bin,
        &to_f32(&flat_r),
        json!({"count": 4, "type": "VEC4"}),
    );
    json["animations"] = json!([{
        "samplers": [{"input": times, "output": rot, "interpolation": "LINEAR"}],
        "channels": [{"sampler": 0, "target": {"node": 0, "path": "rotation"}}]
    }]);
    json["buffers"][0]["byteLength"] = bin.len().into();
    Plain {
        glb: glb_bytes(&json, &bin),
        normals,
        colours,
        rotations,
    }
}

/// The filters named in a GLB's compressed buffer views.
fn filters(json: &Value, ext: &str) -> Vec<String> {
    let views = json["bufferViews"].as_array().cloned().unwrap_or_default();
    views
        .iter()
        .filter_map(|v| v["extensions"][ext]["filter"].as_str().map(String::from))
        .collect()
}

/// The input row nearest `p` (vertices are matched by position: gltfpack reorders them).
fn nearest(p: [f64; 3], of: &[[f64; 3]]) -> usize {
    let d = |q: &[f64; 3]| (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f64>();
    (0..of.len())
        .min_by(|&i, &j| d(&of[i]).total_cmp(&d(&of[j])))
        .unwrap()
}

#[test]
fn octahedral_quaternion_and_color_filters_decode_within_their_step() {
    let Plain {
        glb: input,
        normals,
        colours,
        rotations,
    } = spot_with_attributes();
    validate_with_khronos(&input, "glb");
    let plain = read(&input);
    let world = |a: &Asset| -> Vec<[f64; 3]> {
        let w = a.file_to_welded();
        w.iter()
            .map(|w| a.surface().positions[w.expect("used")])
            .collect()
    };
    let plain_world = world(&plain);
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("in.glb"), &input).unwrap();
    // 12-bit normals, 8-bit colours, 12-bit rotations (gltfpack's default), animations as
    // they are (no resampling).
    let bits_n = 12;
    let bits_c = 8;
    let bits_r = 12;
    let (n_arg, c_arg, r_arg) = (bits_n.to_string(), bits_c.to_string(), bits_r.to_string());
    for (ext, extra) in [
        ("EXT_meshopt_compression", &[][..]),
        ("KHR_meshopt_compression", &["-ce", "khr"][..]),
    ] {
        let mut args = vec![
            "-i", "in.glb", "-o", "c.glb", "-cc", "-kv", "-af", "0", "-vn", &n_arg, "-vc", &c_arg,
            "-ar", &r_arg,
        ];
        args.extend_from_slice(extra);
        gltf_tool("gltfpack", &args, dir.path());
        let packed = std::fs::read(dir.path().join("c.glb")).unwrap();
        let (json, _) = chunks(&packed);
        let used = filters(&json, ext);
        for f in ["OCTAHEDRAL", "QUATERNION"] {
            assert!(
                used.iter().any(|u| u == f),
                "{ext}: no {f} view in {used:?}"
            );
        }
        let a = read(&packed);
        // Normals: the octahedral encoding's step is 2 / (2^(bits-1) - 1) per coordinate of the
        // octahedron, which moves a unit normal by at most about that much.
        let got = a.file_normals().expect("normals");
        let tol_n = 2.0 / f64::from((1 << (bits_n - 1)) - 1);
        let mut worst = 0.0f64;
        for (k, p) in world(&a).iter().enumerate() {
            let want = normals[nearest(*p, &plain_world)];
            let g = unit(got[k].expect("a normal"));
            worst = worst.max((0..3).map(|i| (g[i] - want[i]).abs()).fold(0.0, f64::max));
        }
        assert!(
            worst <= tol_n,
            "{ext}: normals off by {worst}, step {tol_n}"
        );
        assert!(
            worst > 0.0,
            "{ext}: normals bit-exact: were they compressed?"
        );

        // Colours and rotations: written back decoded (plain views), read here by hand.
        let out = a.write(&a.surface().positions, Format::Glb).unwrap();
        validate_with_khronos(&out, "glb");
        let (oj, ob) = chunks(&out);
        // NORMAL, rewritten by the flow, stays compressed: its OCTAHEDRAL view (12 bits, in
        // shorts) comes back as plain normalized shorts through the codec with filter NONE.
        let n_acc = &oj["accessors"][oj["meshes"][0]["primitives"][0]["attributes"]["NORMAL"]
            .as_u64()
            .expect("NORMAL kept") as usize];
        assert_eq!(
            (n_acc["componentType"].as_u64(), &n_acc["normalized"]),
            (Some(5122), &serde_json::json!(true)),
            "{ext}: {n_acc}"
        );
        let n_view = &oj["bufferViews"][n_acc["bufferView"].as_u64().unwrap() as usize];
        assert_eq!(
            n_view["extensions"][ext]["mode"], "ATTRIBUTES",
            "{ext}: {n_view}"
        );
        assert!(
            n_view["extensions"][ext].get("filter").is_none(),
            "{n_view}"
        );
        let c_acc = oj["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"]
            .as_u64()
            .expect("COLOR_0 kept") as usize;
        let got_c = accessor(&oj, &ob, c_acc);
        // Without a filter a colour is rounded once: half a step. The COLOR filter stores
        // YCoCg, each rounded to its bits, and R = Y + Co − Cg adds three such roundings:
        // 1.5 steps (and one more half step for the 8-bit output the filter decodes to).
        let color_filter = used.iter().any(|u| u == "COLOR");
        // The COLOR filter is the ratified extension's addition.
        assert_eq!(color_filter, ext.starts_with("KHR_"), "{ext}: {used:?}");
        let step = 1.0 / f64::from((1 << bits_c) - 1);
        let tol_c = if color_filter { 2.0 * step } else { step };
        let mut worst_c = 0.0f64;
        for (k, p) in world(&a).iter().enumerate() {
            let want = colours[nearest(*p, &plain_world)];
            for i in 0..got_c[k].len().min(4) {
                let e = (got_c[k][i] - want[i]).abs();
                assert!(
                    e <= tol_c,
                    "{ext}: colour {k}[{i}] off by {e}, allowed {tol_c}"
                );
                worst_c = worst_c.max(e);
            }
        }
        eprintln!("{ext}: normals within {worst:.2e}, colours within {worst_c:.2e}");
        let sampler = &oj["animations"][0]["samplers"][oj["animations"][0]["channels"][0]["sampler"]
            .as_u64()
            .unwrap() as usize];
        let got_r = accessor(&oj, &ob, sampler["output"].as_u64().unwrap() as usize);
        assert_eq!(got_r.len(), rotations.len(), "{ext}: rotation keys");
        // gltfpack's quaternion filter keeps `bits_r` bits of the three smallest components,
        // each in [-1/√2, 1/√2]; the largest is rebuilt from the unit length.
        let tol_r = 2.0 / f64::from((1 << (bits_r - 1)) - 1);
        for (g, w) in got_r.iter().zip(&rotations) {
            let same = (0..4).map(|i| (g[i] - w[i]).abs()).fold(0.0, f64::max);
            let flip = (0..4).map(|i| (g[i] + w[i]).abs()).fold(0.0, f64::max);
            assert!(same.min(flip) <= tol_r, "{ext}: rotation {g:?} vs {w:?}");
        }
    }
}
