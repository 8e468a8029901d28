//! `KHR_draco_mesh_compression` (gltf-transform `draco`, Blender's Draco export): a primitive
//! whose attributes and indices live in one Draco stream.
//!
//! Each stream is decoded (the `draco-core` crate, pure Rust) and written out as plain
//! accessors: attributes as floats (normalized integers mapped to [0, 1] / [-1, 1] as the
//! accessor declared them; JOINTS as unsigned shorts, the only integer type they need),
//! indices as unsigned ints, appended to buffer 0 behind new buffer views. The extension is
//! then removed from the primitives and from `extensionsUsed` / `extensionsRequired`, so the
//! result is a plain, validator-clean document; re-encoding Draco is not done (the output
//! keeps the faired positions exactly rather than re-quantizing them).

use super::{Limits, MeshError};
use serde_json::{json, Value};
use std::collections::HashSet;

pub(super) const DRACO: &str = "KHR_draco_mesh_compression";

/// glTF `componentType` codes used here.
const UNSIGNED_SHORT: u64 = 5123;
const UNSIGNED_INT: u64 = 5125;
const FLOAT: u64 = 5126;

fn bad(mesh: usize, prim: usize, detail: impl std::fmt::Display) -> MeshError {
    MeshError::parse(
        "glTF",
        format!("mesh {mesh} primitive {prim}: {DRACO}: {detail}"),
    )
}

pub(super) fn used(json: &Value) -> bool {
    json.get("extensionsUsed")
        .and_then(Value::as_array)
        .is_some_and(|u| u.iter().any(|e| e.as_str() == Some(DRACO)))
}

/// Components of an accessor `type`.
fn components(kind: &str) -> Option<usize> {
    Some(match kind {
        "SCALAR" => 1,
        "VEC2" => 2,
        "VEC3" => 3,
        "VEC4" => 4,
        _ => return None,
    })
}

/// The divisor that maps a normalized integer type to [0, 1] or [-1, 1] (glTF 2.0 §3.11).
fn normalization(component_type: u64) -> Option<f32> {
    Some(match component_type {
        5120 => 127.0,
        5121 => 255.0,
        5122 => 32767.0,
        5123 => 65535.0,
        _ => return None,
    })
}

/// Appends `bytes` to buffer 0 (4-aligned) behind a new buffer view; returns its index.
fn push_view(json: &mut Value, buffer0: &mut Vec<u8>, bytes: &[u8]) -> Result<usize, MeshError> {
    while !buffer0.len().is_multiple_of(4) {
        buffer0.push(0);
    }
    let offset = buffer0.len();
    buffer0.extend_from_slice(bytes);
    let views = json
        .as_object_mut()
        .ok_or_else(|| MeshError::parse("glTF", "the document is not an object"))?
        .entry("bufferViews")
        .or_insert_with(|| json!([]));
    let views = views
        .as_array_mut()
        .ok_or_else(|| MeshError::parse("glTF", "bufferViews is not an array"))?;
    views.push(json!({"buffer": 0, "byteOffset": offset, "byteLength": bytes.len()}));
    Ok(views.len() - 1)
}

/// Decodes every Draco primitive into plain accessors (see the module docs).
pub(super) fn decompress(
    json: &mut Value,
    buffers: &mut [Vec<u8>],
    limits: &Limits,
) -> Result<(), MeshError> {
    if buffers.is_empty() {
        return Err(MeshError::truncated(format!(
            "{DRACO} is used but there is no buffer"
        )));
    }
    // Accessors already rewritten (primitives may share a stream's accessors).
    let mut done: HashSet<usize> = HashSet::new();
    let mesh_count = json
        .get("meshes")
        .and_then(Value::as_array)
        .map_or(0, Vec::len);
    for m in 0..mesh_count {
        let prim_count = json["meshes"][m]["primitives"]
            .as_array()
            .map_or(0, Vec::len);
        for p in 0..prim_count {
            let prim = json["meshes"][m]["primitives"][p].clone();
            let Some(ext) = prim.get("extensions").and_then(|e| e.get(DRACO)) else {
                continue;
            };
            decode_primitive(json, buffers, limits, &mut done, (m, p), &prim, ext)?;
            if let Some(exts) = json["meshes"][m]["primitives"][p]
                .get_mut("extensions")
                .and_then(Value::as_object_mut)
            {
                exts.remove(DRACO);
                if exts.is_empty() {
                    if let Some(o) = json["meshes"][m]["primitives"][p].as_object_mut() {
                        o.remove("extensions");
                    }
                }
            }
        }
    }
    let length = buffers[0].len();
    json["buffers"][0]["byteLength"] = json!(length);
    if let Some(root) = json.as_object_mut() {
        for key in ["extensionsUsed", "extensionsRequired"] {
            let empty = root.get_mut(key).and_then(Value::as_array_mut).map(|list| {
                list.retain(|e| e.as_str() != Some(DRACO));
                list.is_empty()
            });
            if empty == Some(true) {
                root.remove(key);
            }
        }
    }
    Ok(())
}

fn decode_primitive(
    json: &mut Value,
    buffers: &mut [Vec<u8>],
    limits: &Limits,
    done: &mut HashSet<usize>,
    (m, p): (usize, usize),
    prim: &Value,
    ext: &Value,
) -> Result<(), MeshError> {
    let view = ext
        .get("bufferView")
        .and_then(Value::as_u64)
        .ok_or_else(|| bad(m, p, "no bufferView"))? as usize;
    let v = json
        .get("bufferViews")
        .and_then(|vs| vs.get(view))
        .ok_or_else(|| bad(m, p, format!("bufferView {view} does not exist")))?;
    let field = |k: &str| v.get(k).and_then(Value::as_u64).map(|x| x as usize);
    let (buffer, offset, length) = (
        field("buffer").unwrap_or(0),
        field("byteOffset").unwrap_or(0),
        field("byteLength").unwrap_or(0),
    );
    let stream = buffers
        .get(buffer)
        .and_then(|b| b.get(offset..offset.checked_add(length)?))
        .ok_or_else(|| {
            MeshError::truncated(format!(
                "bufferView {view} (bytes {offset}..+{length}) is past the end of buffer {buffer}"
            ))
        })?;
    // The decoder's own limits, set to this job's: an absurd header stops before allocating.
    let draco_limits = draco_core::DecodeLimits::default()
        .with_max_points(limits.max_vertices as u64)
        .with_max_faces(limits.max_faces as u64)
        .with_max_decoded_bytes(limits.max_bytes as u64);
    let mut input = draco_core::DecoderBuffer::new(stream).with_limits(draco_limits);
    let mut mesh = draco_core::Mesh::new();
    draco_core::MeshDecoder::new()
        .decode(&mut input, &mut mesh)
        .map_err(|e| {
            bad(
                m,
                p,
                format!("the Draco stream in bufferView {view} does not decode: {e}"),
            )
        })?;
    let points = mesh.num_points();

    // Indices, as unsigned ints.
    if let Some(acc) = prim
        .get("indices")
        .and_then(Value::as_u64)
        .map(|a| a as usize)
    {
        let faces = mesh.faces();
        let mut bytes = Vec::with_capacity(faces.len() * 12);
        for f in faces {
            for v in f {
                bytes.extend_from_slice(&v.0.to_le_bytes());
            }
        }
        if done.insert(acc) {
            let declared = json["accessors"][acc]["count"].as_u64();
            if declared != Some(faces.len() as u64 * 3) {
                return Err(bad(
                    m,
                    p,
                    format!(
                        "indices accessor {acc} declares {declared:?} indices, the stream has {} \
                         triangles",
                        faces.len()
                    ),
                ));
            }
            let at = push_view(json, &mut buffers[0], &bytes)?;
            let a = &mut json["accessors"][acc];
            a["bufferView"] = json!(at);
            a["byteOffset"] = json!(0);
            a["componentType"] = json!(UNSIGNED_INT);
            if let Some(o) = a.as_object_mut() {
                o.remove("normalized");
                o.remove("sparse");
            }
        }
    }

    // Attributes named by the extension, by their Draco unique id.
    let attributes = ext.get("attributes").and_then(Value::as_object);
    for (semantic, id) in attributes.into_iter().flatten() {
        let id = id
            .as_u64()
            .and_then(|x| u32::try_from(x).ok())
            .ok_or_else(|| bad(m, p, format!("attribute {semantic} has a bad id")))?;
        let acc = prim["attributes"]
            .get(semantic)
            .and_then(Value::as_u64)
            .ok_or_else(|| {
                bad(
                    m,
                    p,
                    format!("{semantic} is in the extension but not the primitive"),
                )
            })? as usize;
        if !done.insert(acc) {
            continue;
        }
        let a = &json["accessors"][acc];
        let n = a["type"]
            .as_str()
            .and_then(components)
            .ok_or_else(|| bad(m, p, format!("accessor {acc} has a type Draco cannot hold")))?;
        if a["count"].as_u64() != Some(points as u64) {
            return Err(bad(
                m,
                p,
                format!(
                    "accessor {acc} ({semantic}) declares {} elements, the stream has {points} points",
                    a["count"]
                ),
            ));
        }
        let attribute = mesh.attribute_by_unique_id(id).ok_or_else(|| {
            bad(
                m,
                p,
                format!("the stream has no attribute with id {id} ({semantic})"),
            )
        })?;
        let mut values = attribute.read_f32s(points, n);
        let declared_type = a["componentType"].as_u64().unwrap_or(FLOAT);
        if a["normalized"].as_bool() == Some(true)
            && attribute.data_type() != draco_core::DataType::Float32
        {
            if let Some(d) = normalization(declared_type) {
                for x in &mut values {
                    *x = (*x / d).max(-1.0);
                }
            }
        }
        let joints = semantic.starts_with("JOINTS_");
        let bytes: Vec<u8> = if joints {
            values
                .iter()
                .flat_map(|&x| (x.clamp(0.0, 65535.0) as u16).to_le_bytes())
                .collect()
        } else {
            values.iter().flat_map(|x| x.to_le_bytes()).collect()
        };
        let at = push_view(json, &mut buffers[0], &bytes)?;
        let a = &mut json["accessors"][acc];
        a["bufferView"] = json!(at);
        a["byteOffset"] = json!(0);
        a["componentType"] = json!(if joints { UNSIGNED_SHORT } else { FLOAT });
        if let Some(o) = a.as_object_mut() {
            o.remove("normalized");
            o.remove("sparse");
        }
        // min/max describe the data now stored (the validator checks them; POSITION needs them).
        if a.get("min").is_some() || semantic == "POSITION" {
            let mut lo = vec![f64::INFINITY; n];
            let mut hi = vec![f64::NEG_INFINITY; n];
            for v in values.chunks_exact(n) {
                for k in 0..n {
                    let x = if joints {
                        v[k].clamp(0.0, 65535.0).trunc()
                    } else {
                        v[k]
                    } as f64;
                    lo[k] = lo[k].min(x);
                    hi[k] = hi[k].max(x);
                }
            }
            if points > 0 {
                a["min"] = json!(lo);
                a["max"] = json!(hi);
            }
        }
    }
    Ok(())
}
