//! Small meshes built in code for the `mesh_*` integration tests.
#![allow(dead_code)] // each test crate uses a different subset

use std::f64::consts::PI;

/// Axis-aligned unit cube, 12 triangles wound outward.
pub fn cube() -> (Vec<[f64; 3]>, Vec<[usize; 3]>) {
    let p = vec![
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
        [1.0, 0.0, 1.0],
        [1.0, 1.0, 1.0],
        [0.0, 1.0, 1.0],
    ];
    let t = vec![
        [0, 2, 1],
        [0, 3, 2], // z = 0, normal -z
        [4, 5, 6],
        [4, 6, 7], // z = 1, normal +z
        [0, 1, 5],
        [0, 5, 4], // y = 0, normal -y
        [2, 3, 7],
        [2, 7, 6], // y = 1, normal +y
        [1, 2, 6],
        [1, 6, 5], // x = 1, normal +x
        [0, 4, 7],
        [0, 7, 3], // x = 0, normal -x
    ];
    (p, t)
}

/// A flat disk: a centre vertex and a ring of `n` vertices, fanned.
pub fn disk(n: usize) -> (Vec<[f64; 3]>, Vec<[usize; 3]>) {
    let mut p = vec![[0.0, 0.0, 0.0]];
    for i in 0..n {
        let a = 2.0 * PI * i as f64 / n as f64;
        p.push([a.cos(), a.sin(), 0.0]);
    }
    let t = (0..n).map(|i| [0, 1 + i, 1 + (i + 1) % n]).collect();
    (p, t)
}

/// An open cylinder (a tube) with `rings` rings of `n` vertices: two boundary loops.
pub fn cylinder(n: usize, rings: usize) -> (Vec<[f64; 3]>, Vec<[usize; 3]>) {
    let mut p = Vec::new();
    for r in 0..rings {
        for i in 0..n {
            let a = 2.0 * PI * i as f64 / n as f64;
            p.push([a.cos(), a.sin(), r as f64 * 0.5]);
        }
    }
    let mut t = Vec::new();
    for r in 0..rings - 1 {
        for i in 0..n {
            let (a, b) = (r * n + i, r * n + (i + 1) % n);
            let (c, d) = (a + n, b + n);
            t.push([a, b, d]);
            t.push([a, d, c]);
        }
    }
    (p, t)
}

/// A Möbius strip of `n` quads: non-orientable, one boundary loop.
pub fn mobius(n: usize) -> (Vec<[f64; 3]>, Vec<[usize; 3]>) {
    let mut p = Vec::new();
    for i in 0..n {
        let u = 2.0 * PI * i as f64 / n as f64;
        for w in [-0.3, 0.3] {
            let r = 1.0 + w * (u / 2.0).cos();
            p.push([r * u.cos(), r * u.sin(), w * (u / 2.0).sin()]);
        }
    }
    let mut t = Vec::new();
    for i in 0..n {
        let (a, b) = (2 * i, 2 * i + 1);
        // After a full turn the strip comes back upside down: w = -0.3 meets w = +0.3.
        let (c, d) = if i + 1 < n {
            (2 * (i + 1), 2 * (i + 1) + 1)
        } else {
            (1, 0)
        };
        t.push([a, c, d]);
        t.push([a, d, b]);
    }
    (p, t)
}

/// Signed volume (positive when wound outward).
pub fn signed_volume(p: &[[f64; 3]], t: &[[usize; 3]]) -> f64 {
    t.iter()
        .map(|&[a, b, c]| {
            let (a, b, c) = (p[a], p[b], p[c]);
            a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
                + a[2] * (b[0] * c[1] - b[1] * c[0])
        })
        .sum::<f64>()
        / 6.0
}

/// True if every interior edge is traversed in opposite directions by its two faces.
pub fn consistently_wound(t: &[[usize; 3]]) -> bool {
    let mut directed = std::collections::HashSet::new();
    for tri in t {
        for k in 0..3 {
            if !directed.insert((tri[k], tri[(k + 1) % 3])) {
                return false;
            }
        }
    }
    true
}

/// Where the shared test meshes live: `$WILLOW_SHARED_MESHES`, else `../shared/meshes` beside
/// the checkout, else `/work/shared/meshes`. A test that needs one fails when it is missing,
/// saying where it looked: it never passes having checked nothing (issue 41).
pub fn shared_mesh(name: &str) -> std::path::PathBuf {
    let candidates = match std::env::var_os("WILLOW_SHARED_MESHES") {
        Some(dir) => vec![std::path::PathBuf::from(dir)],
        None => vec![
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/meshes"),
            std::path::PathBuf::from("/work/shared/meshes"),
        ],
    };
    let found = candidates
        .iter()
        .map(|dir| dir.join(name))
        .find(|path| path.is_file());
    match found {
        Some(path) => path,
        None => panic!(
            "{name} is needed by this test and is not in {candidates:?}; set \
             WILLOW_SHARED_MESHES to the shared meshes' folder"
        ),
    }
}

/// One of the shared OBJ meshes as a validated surface; fails as [`shared_mesh`] does.
pub fn shared_surface(name: &str) -> willow::mesh::Mesh {
    use willow::mesh::io::{Asset, Format, Limits};
    let path = shared_mesh(name);
    let bytes =
        std::fs::read(&path).unwrap_or_else(|e| panic!("{} should read: {e}", path.display()));
    let asset = Asset::read(&bytes, Format::Obj, &Limits::default())
        .unwrap_or_else(|e| panic!("{name} should read: {e}"));
    asset.surface().clone()
}

/// A 1×1 RGBA PNG: a real image so the glTF validator accepts the embedded texture.
pub const TINY_PNG_BASE64: &str =
    "iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mNk+M9QDwADhgGAWjR9awAAAABJRU5ErkJggg==";

/// Assembles a GLB from a JSON document and a BIN chunk (padding both to 4 bytes).
pub fn glb_bytes(json: &serde_json::Value, bin: &[u8]) -> Vec<u8> {
    let mut j = serde_json::to_vec(json).unwrap();
    while !j.len().is_multiple_of(4) {
        j.push(b' ');
    }
    let mut b = bin.to_vec();
    while !b.len().is_multiple_of(4) {
        b.push(0);
    }
    let total = 12 + 8 + j.len() + 8 + b.len();
    let mut out = Vec::new();
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(j.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&j);
    out.extend_from_slice(&(b.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&b);
    out
}

/// A textured unit cube as glTF: 24 vertices (4 per face, split at every UV seam and crease),
/// flat normals, u16 indices, an embedded PNG, and a two-level node hierarchy: the parent
/// scales by 2 and translates by (10, 0, 0), the child (holding the mesh) scales by 0.5 along z.
/// Returns (json, bin, local positions, image bytes).
pub fn textured_cube_gltf() -> (serde_json::Value, Vec<u8>, Vec<[f32; 3]>, Vec<u8>) {
    use base64::Engine as _;
    let faces: [([f32; 3], [f32; 3], [f32; 3]); 6] = [
        // (normal, u axis, v axis): corners are n/2 ± u/2 ± v/2, wound counter-clockwise.
        ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]),
        ([-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]),
        ([0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]),
        ([0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
        ([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
        ([0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]),
    ];
    let mut pos = Vec::new();
    let mut nrm = Vec::new();
    let mut uv = Vec::new();
    let mut idx: Vec<u16> = Vec::new();
    for (f, (n, u, v)) in faces.iter().enumerate() {
        let base = pos.len() as u16;
        for (su, sv) in [(-1.0f32, -1.0f32), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
            pos.push([0, 1, 2].map(|k| 0.5 * n[k] + 0.5 * su * u[k] + 0.5 * sv * v[k]));
            nrm.push(*n);
            uv.push([(f as f32 + (su + 1.0) / 2.0) / 6.0, (1.0 - sv) / 2.0]);
        }
        idx.extend_from_slice(&[base, base + 1, base + 2, base, base + 2, base + 3]);
    }
    let png = base64::engine::general_purpose::STANDARD
        .decode(TINY_PNG_BASE64)
        .unwrap();
    let mut bin = Vec::new();
    let mut views = Vec::new();
    let mut push = |bin: &mut Vec<u8>, data: Vec<u8>, target: Option<u32>| {
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        let mut v =
            serde_json::json!({"buffer": 0, "byteOffset": bin.len(), "byteLength": data.len()});
        if let Some(t) = target {
            v["target"] = serde_json::json!(t);
        }
        views.push(v);
        bin.extend_from_slice(&data);
        views.len() - 1
    };
    let f32s =
        |v: &[[f32; 3]]| -> Vec<u8> { v.iter().flatten().flat_map(|x| x.to_le_bytes()).collect() };
    let vp = push(&mut bin, f32s(&pos), Some(34962));
    let vn = push(&mut bin, f32s(&nrm), Some(34962));
    let vt = push(
        &mut bin,
        uv.iter().flatten().flat_map(|x| x.to_le_bytes()).collect(),
        Some(34962),
    );
    let vi = push(
        &mut bin,
        idx.iter().flat_map(|x| x.to_le_bytes()).collect(),
        Some(34963),
    );
    let vimg = push(&mut bin, png.clone(), None);
    let json = serde_json::json!({
        "asset": {"version": "2.0", "generator": "willow test"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [
            {"name": "parent", "scale": [2.0, 2.0, 2.0], "translation": [10.0, 0.0, 0.0], "children": [1]},
            {"name": "child", "mesh": 0, "scale": [1.0, 1.0, 0.5]}
        ],
        "meshes": [{"primitives": [{
            "attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2},
            "indices": 3, "material": 0, "mode": 4
        }]}],
        "materials": [{"name": "checker", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
        "textures": [{"sampler": 0, "source": 0}],
        "samplers": [{"magFilter": 9729, "minFilter": 9987}],
        "images": [{"bufferView": vimg, "mimeType": "image/png"}],
        "accessors": [
            {"bufferView": vp, "componentType": 5126, "count": 24, "type": "VEC3",
             "min": [-0.5, -0.5, -0.5], "max": [0.5, 0.5, 0.5]},
            {"bufferView": vn, "componentType": 5126, "count": 24, "type": "VEC3"},
            {"bufferView": vt, "componentType": 5126, "count": 24, "type": "VEC2"},
            {"bufferView": vi, "componentType": 5123, "count": 36, "type": "SCALAR"}
        ],
        "bufferViews": views,
        "buffers": [{"byteLength": bin.len()}]
    });
    (json, bin, pos, png)
}

// ---------------------------------------------------------------------------------------
// Khronos glTF-Validator

pub fn tools_dir() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/tools")
}

/// Runs the Khronos validator on `bytes`; fails on any error. Skipped only with
/// WILLOW_SKIP_NODE=1.
pub fn validate_with_khronos(bytes: &[u8], ext: &str) {
    if std::env::var("WILLOW_SKIP_NODE").as_deref() == Ok("1") {
        eprintln!("note: WILLOW_SKIP_NODE=1, skipping the Khronos glTF validator");
        return;
    }
    assert!(
        tools_dir().join("node_modules/gltf-validator").is_dir(),
        "tests/tools/node_modules is missing: run scripts/test.sh (it runs `npm ci --prefix \
         tests/tools`) or set WILLOW_SKIP_NODE=1"
    );
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join(format!("out.{ext}"));
    std::fs::write(&file, bytes).unwrap();
    let out = std::process::Command::new("node")
        .arg(tools_dir().join("validate_gltf.js"))
        .arg(&file)
        .output()
        .expect("node must be installed to run the glTF validator (or set WILLOW_SKIP_NODE=1)");
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "validator gave no report ({e}): {}",
            String::from_utf8_lossy(&out.stderr)
        )
    });
    let errors = report["issues"]["numErrors"].as_u64().unwrap();
    assert_eq!(
        errors,
        0,
        "Khronos validator errors: {}",
        serde_json::to_string_pretty(&report["issues"]["messages"]).unwrap()
    );
    assert!(out.status.success());
}

/// Runs `tests/tools/node_modules/.bin/<name>` and fails with its output if it fails.
pub fn gltf_tool(name: &str, args: &[&str], dir: &std::path::Path) {
    let bin = tools_dir().join("node_modules/.bin").join(name);
    assert!(
        bin.is_file(),
        "{} is missing: run scripts/test.sh (it runs `npm ci --prefix tests/tools`)",
        bin.display()
    );
    let out = std::process::Command::new(&bin)
        .args(args)
        .current_dir(dir)
        .output()
        .unwrap_or_else(|e| panic!("{name} does not run (node must be installed): {e}"));
    assert!(
        out.status.success(),
        "{name} {args:?} failed: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}
