use super::*;
use crate::mesh::io::{Format, MeshError};

#[test]
fn glb_header_lies_are_errors_not_panics() {
    // Length smaller than the header (the gltf crate underflows on this one).
    let mut b = b"glTF".to_vec();
    b.extend_from_slice(&2u32.to_le_bytes());
    b.extend_from_slice(&4u32.to_le_bytes());
    assert!(split_container(&b, Format::Glb).is_err());
    // A chunk claiming more bytes than there are.
    let mut b = b"glTF".to_vec();
    b.extend_from_slice(&2u32.to_le_bytes());
    b.extend_from_slice(&28u32.to_le_bytes());
    b.extend_from_slice(&u32::MAX.to_le_bytes());
    b.extend_from_slice(b"JSON");
    b.extend_from_slice(b"{}  ");
    let e = split_container(&b, Format::Glb).unwrap_err();
    assert_eq!(e.code(), "truncated_buffer");
    assert!(split_container(b"glTF", Format::Glb).is_err());
}

#[test]
fn only_base64_data_uris_are_decoded() {
    assert_eq!(
        decode_data_uri("data:application/octet-stream;base64,AAEC").unwrap(),
        [0, 1, 2]
    );
    for uri in [
        "/etc/passwd",
        "http://example.com/a.bin",
        "file:///etc/passwd",
        "a.bin",
    ] {
        assert!(
            matches!(decode_data_uri(uri), Err(MeshError::ExternalUri { .. })),
            "{uri}"
        );
    }
}

// --- EXT_/KHR_meshopt_compression, with data made by meshoptimizer's own encoder ---------

/// A tetrahedron's positions through the EXPONENTIAL filter and the vertex codec, its
/// indices through the TRIANGLES codec, both decoding into a fallback buffer with no data.
/// Returns the GLB and the positions the filter's words stand for, computed here from the
/// words themselves (2^e · m, e the signed top byte, m the signed low 24 bits).
fn meshopt_tetra(
    ext: &str,
    tamper: impl Fn(&mut serde_json::Value, &mut Vec<u8>),
) -> (Vec<u8>, Vec<[f32; 3]>) {
    let p: [[f32; 3]; 4] = [
        [0.0, 0.0, 0.0],
        [1.5, 0.0, 0.0],
        [0.0, 2.25, 0.0],
        [0.0, 0.0, -3.125],
    ];
    let words = ::meshopt::encode_filter_exp(&p, 15, ::meshopt::EncodeExpMode::Separate);
    let truth = words
        .iter()
        .map(|w| {
            w.map(|v| {
                let e = (v as i32) >> 24;
                let m = ((v << 8) as i32) >> 8;
                m as f32 * 2f32.powi(e)
            })
        })
        .collect();
    let vertices = ::meshopt::encode_vertex_buffer(&words).expect("encodes");
    let indices: [u32; 12] = [0, 1, 2, 0, 3, 1, 0, 2, 3, 1, 3, 2]; // wound outward
    let tri = ::meshopt::encode_index_buffer(&indices, 4).expect("encodes");
    let mut bin = vertices.clone();
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let tri_at = bin.len();
    bin.extend_from_slice(&tri);
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let mut json = serde_json::json!({
        "asset": {"version": "2.0"},
        "extensionsUsed": [ext], "extensionsRequired": [ext],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}],
        "buffers": [
            {"byteLength": bin.len()},
            {"byteLength": 48 + 24, "extensions": {ext: {"fallback": true}}}
        ],
        "bufferViews": [
            {"buffer": 1, "byteLength": 48, "byteStride": 12, "extensions": {ext: {
                "buffer": 0, "byteLength": vertices.len(), "byteStride": 12, "count": 4,
                "mode": "ATTRIBUTES", "filter": "EXPONENTIAL"}}},
            {"buffer": 1, "byteOffset": 48, "byteLength": 24, "extensions": {ext: {
                "buffer": 0, "byteOffset": tri_at, "byteLength": tri.len(), "byteStride": 2,
                "count": 12, "mode": "TRIANGLES"}}}
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
             "min": [0, 0, -3.125], "max": [1.5, 2.25, 0]},
            {"bufferView": 1, "componentType": 5123, "count": 12, "type": "SCALAR"}
        ]
    });
    tamper(&mut json, &mut bin);
    let mut json_bytes = serde_json::to_vec(&json).expect("json");
    while !json_bytes.len().is_multiple_of(4) {
        json_bytes.push(b' ');
    }
    let mut glb = b"glTF".to_vec();
    let total = 12 + 8 + json_bytes.len() + 8 + bin.len();
    for n in [2, total] {
        glb.extend_from_slice(&(n as u32).to_le_bytes());
    }
    glb.extend_from_slice(&(json_bytes.len() as u32).to_le_bytes());
    glb.extend_from_slice(b"JSON");
    glb.extend_from_slice(&json_bytes);
    glb.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    glb.extend_from_slice(b"BIN\0");
    glb.extend_from_slice(&bin);
    (glb, truth)
}

/// A change made to the test file's JSON and BIN chunk.
type Tamper<'a> = dyn Fn(&mut serde_json::Value, &mut Vec<u8>) + 'a;

fn read_asset(glb: &[u8]) -> Result<crate::mesh::io::Asset, MeshError> {
    crate::mesh::io::Asset::read(glb, Format::Glb, &crate::mesh::io::Limits::default())
}

#[test]
fn meshopt_exponential_positions_and_triangles_decode_into_the_fallback_buffer() {
    for ext in meshopt::MESHOPT {
        let (glb, truth) = meshopt_tetra(ext, |_, _| {});
        let a = read_asset(&glb).unwrap_or_else(|e| panic!("{ext}: {e}"));
        assert_eq!(a.file_positions(&a.surface().positions), truth, "{ext}");
        // The index codec may rotate a triangle (winding kept): compare each rotated to
        // start at its smallest vertex.
        let mut tris: Vec<[usize; 3]> = a
            .file_triangles()
            .iter()
            .map(|t| {
                let k = (0..3).min_by_key(|&k| t[k]).unwrap_or(0);
                [t[k], t[(k + 1) % 3], t[(k + 2) % 3]]
            })
            .collect();
        tris.sort();
        assert_eq!(tris, [[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]], "{ext}");
        // Written back: POSITION (EXPONENTIAL in the input) re-encoded as plain float32 with
        // filter NONE, the other views decoded; read back to the same positions and faces.
        let out = a
            .write(&a.surface().positions, Format::Glb)
            .expect("writes");
        let n = u32::from_le_bytes([out[12], out[13], out[14], out[15]]) as usize;
        let json: serde_json::Value = serde_json::from_slice(&out[20..20 + n]).expect("json");
        let pos = json["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
            .as_u64()
            .expect("POSITION") as usize;
        let view = &json["bufferViews"]
            [json["accessors"][pos]["bufferView"].as_u64().expect("view") as usize];
        let e = &view["extensions"][ext];
        assert_eq!(e["mode"], "ATTRIBUTES", "{ext}: {view}");
        assert!(e.get("filter").is_none(), "{ext}: {view}");
        assert_eq!(
            (e["byteStride"].as_u64(), e["count"].as_u64()),
            (Some(12), Some(4))
        );
        assert_eq!(json["buffers"][1]["extensions"][ext]["fallback"], true);
        assert!(json["extensionsRequired"]
            .as_array()
            .is_some_and(|l| l.iter().any(|x| x == ext)));
        let b = read_asset(&out).unwrap_or_else(|e| panic!("{ext}: re-read: {e}"));
        let want: Vec<[f32; 3]> = truth.to_vec();
        assert_eq!(b.file_positions(&b.surface().positions), want, "{ext}");
        assert_eq!(b.file_triangles(), a.file_triangles(), "{ext}");
    }
}

#[test]
fn meshopt_lies_are_specific_errors() {
    let ext = "EXT_meshopt_compression";
    let cases: Vec<(Box<Tamper<'_>>, &str)> = vec![
        (
            Box::new(|j, _| j["bufferViews"][0]["extensions"][ext]["count"] = 5.into()),
            "bufferView 0: EXT_meshopt_compression: count 5 × byteStride 12 = 60, but the \
             bufferView's byteLength is 48",
        ),
        (
            Box::new(|j, _| j["bufferViews"][1]["extensions"][ext]["mode"] = "STRIPS".into()),
            "bufferView 1: EXT_meshopt_compression: unknown mode Some(\"STRIPS\")",
        ),
        (
            Box::new(|j, _| j["bufferViews"][0]["extensions"][ext]["filter"] = "COLOR".into()),
            "bufferView 0: EXT_meshopt_compression: unknown filter Some(\"COLOR\")",
        ),
        (
            Box::new(|j, _| j["bufferViews"][1]["extensions"][ext]["byteStride"] = 3.into()),
            "bufferView 1: EXT_meshopt_compression: byteStride 3 is invalid for Triangles",
        ),
        (
            // The vertex stream cut short: the decoder reports it, by view.
            Box::new(|j, _| j["bufferViews"][0]["extensions"][ext]["byteLength"] = 5.into()),
            "bufferView 0: EXT_meshopt_compression: Attributes data does not decode",
        ),
        (
            Box::new(|j, _| {
                j["bufferViews"][1]["extensions"][ext]["byteOffset"] = 1_000_000.into()
            }),
            "past the end of that buffer",
        ),
    ];
    for (tamper, expect) in cases {
        let (glb, _) = meshopt_tetra(ext, tamper);
        let e = read_asset(&glb).expect_err(expect);
        assert!(e.to_string().contains(expect), "{e} should say {expect:?}");
    }
    // A small file declaring a 1 TiB fallback buffer is refused before anything is allocated.
    let (glb, _) = meshopt_tetra(ext, |j, _| {
        j["buffers"][1]["byteLength"] = (1u64 << 40).into()
    });
    let e = read_asset(&glb).expect_err("a 1 TiB fallback buffer");
    assert!(e.is_too_large(), "{e}");
}
