//! glTF 2.0 and GLB.
//!
//! Reading: the GLB container is split here (with checked lengths), the JSON is parsed and
//! index-validated by the `gltf` crate, and buffers are resolved by hand from the BIN chunk or
//! base64 `data:` URIs only. Every buffer view and accessor range is checked against the bytes
//! it lives in, so a lying file is a [`MeshError::TruncatedBuffer`], never a panic.
//!
//! Writing keeps the input document as raw JSON, so extensions and extras this crate does not
//! model survive: all original buffers are concatenated into one buffer, new POSITION (and
//! NORMAL) data is appended, and those accessors are repointed in place. TANGENT is dropped
//! from the primitives (see `drop_tangents`), and so are morph targets (`clean`). Quantized
//! POSITION and NORMAL (`KHR_mesh_quantization`) are re-quantized to their own types, with the
//! node's dequantization transform updated, where that moves nothing else (`quantize`), and
//! written as float32 elsewhere. Meshopt input keeps its compression for the rewritten
//! POSITION and NORMAL views (`reencode`); its other views, and Draco input, are written
//! decoded, as plain data (Draco's extension removed); bytes no buffer view covers any more
//! and views nothing refers to are left out (`clean::compact`).
//! The job is told each of these (`clean::notes`). Images, samplers, materials, UVs, indices
//! and nodes are untouched. A refined asset (`Asset::refined`) is written into the same
//! document, with each primitive's vertex data and indices replaced (`refined`).

use super::{format_name, Affine, FileGeometry, Format, Limits, MeshError};
use base64::Engine as _;
use serde_json::Value;
use std::collections::HashMap;

mod accessors;
use accessors::*;
mod clean;
mod draco;
mod meshopt;
mod quantize;
mod reencode;
pub(crate) mod refined;
mod write;
pub(crate) use write::*;
#[cfg(test)]
mod tests;

/// Quantized attributes (gltfpack's default output): integer and normalized-integer
/// POSITION, NORMAL and TEXCOORD accessors, read here (see `accessors::read_vec3`). The `gltf`
/// crate refuses the extension when required, so it is taken out of the copy it validates.
const MESH_QUANTIZATION: &str = "KHR_mesh_quantization";

/// glTF `target` for vertex attribute buffer views (`ARRAY_BUFFER`).
const ARRAY_BUFFER: u32 = 34962;
/// glTF `target` for index buffer views (`ELEMENT_ARRAY_BUFFER`).
const ELEMENT_ARRAY_BUFFER: u32 = 34963;
/// glTF `componentType` codes.
const FLOAT: u32 = 5126;
const UNSIGNED_INT: u32 = 5125;

/// What a glTF file has beyond the surface: its whole document and buffer bytes.
#[derive(Clone, Debug)]
pub(crate) struct GltfSource {
    /// The input JSON, untouched.
    json: Value,
    /// Each buffer's bytes (exactly `byteLength` of them).
    buffers: Vec<Vec<u8>>,
    /// POSITION accessor of each file-vertex block (same order as `FileGeometry::blocks`).
    position_accessors: Vec<usize>,
    /// NORMAL accessors to recompute, with the block whose vertices they describe.
    normal_accessors: Vec<(usize, usize)>,
    /// Nodes whose POSITION is written re-quantized (`quantize::plan`).
    requantize: Vec<quantize::Requantize>,
    /// The input's meshopt-compressed views, re-encoded on writing (`reencode`).
    compression: Option<meshopt::Compression>,
    /// The faces under each node name and each mesh name.
    pub(crate) groups: super::groups::Groups,
    /// What a written document cannot keep of the input as it was (`clean::notes`).
    pub(crate) notes: Vec<String>,
    /// NORMAL of each file vertex as read (decoded, dequantized), if the file had normals.
    pub(crate) normals: Option<Vec<Option<[f64; 3]>>>,
    /// The triangles each primitive drew, in reading order (`refined`).
    pub(crate) runs: Vec<refined::Run>,
    /// TEXCOORD_n (n ≥ 1) and COLOR_n, per vertex of their block (`refined`).
    pub(crate) varyings: Vec<refined::BlockVarying>,
}

/// The JSON and BIN chunks of a GLB, or the whole input as JSON.
fn split_container(bytes: &[u8], format: Format) -> Result<(&[u8], Option<&[u8]>), MeshError> {
    let name = format_name(format);
    if !bytes.starts_with(b"glTF") {
        // A UTF-8 byte order mark before the JSON (Windows editors write one) is accepted:
        // JSON (RFC 8259 §8.1) lets parsers ignore it, though glTF says not to write it.
        let json = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
        if format == Format::Glb && !json.trim_ascii_start().starts_with(b"{") {
            return Err(MeshError::parse(name, "missing the 'glTF' magic bytes"));
        }
        return Ok((json, None));
    }
    let u32_at = |at: usize| -> Option<usize> {
        let b = bytes.get(at..at.checked_add(4)?)?;
        Some(u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
    };
    let header = |what: &str| MeshError::parse("GLB", format!("truncated header: {what}"));
    let version = u32_at(4).ok_or_else(|| header("no version"))?;
    if version != 2 {
        return Err(MeshError::unsupported(format!("GLB version {version}")));
    }
    let length = u32_at(8).ok_or_else(|| header("no length"))?;
    if length > bytes.len() {
        return Err(MeshError::truncated(format!(
            "GLB header says {length} bytes but the file has {}",
            bytes.len()
        )));
    }
    let mut at = 12usize;
    let mut json = None;
    let mut bin = None;
    // A chunk needs at least its 8-byte header; fewer trailing bytes are ignored padding.
    while at.saturating_add(8) <= length {
        let chunk_len = u32_at(at).ok_or_else(|| header("chunk length"))?;
        let chunk_type = bytes
            .get(at + 4..at + 8)
            .ok_or_else(|| header("chunk type"))?;
        let start = at + 8;
        let end = start
            .checked_add(chunk_len)
            .filter(|&e| e <= length)
            .ok_or_else(|| {
                MeshError::truncated(format!(
                    "GLB chunk at byte {at} claims {chunk_len} bytes, past the end ({length})"
                ))
            })?;
        let data = &bytes[start..end];
        match chunk_type {
            b"JSON" if json.is_none() => json = Some(data),
            b"BIN\0" if bin.is_none() && json.is_some() => bin = Some(data),
            b"JSON" | b"BIN\0" => {
                return Err(MeshError::parse("GLB", "duplicate or misplaced chunk"))
            }
            _ => {} // unknown chunks are skipped, as the spec says
        }
        // Chunks are 4-byte aligned; tolerate a missing final pad.
        at = end.saturating_add(3) & !3;
    }
    let json = json.ok_or_else(|| MeshError::parse("GLB", "no JSON chunk"))?;
    Ok((json, bin))
}

/// Checks that every primitive's attribute, index and morph-target accessor exists.
///
/// gltf-json 1.4.1's validation indexes `accessors[POSITION]` before checking it (a panic on
/// an out-of-range index), so these references are checked on the raw JSON first.
fn check_primitive_references(json: &Value) -> Result<(), MeshError> {
    let accessor_count = json
        .get("accessors")
        .and_then(Value::as_array)
        .map_or(0, Vec::len);
    let meshes = json.get("meshes").and_then(Value::as_array);
    for (m, mesh) in meshes.into_iter().flatten().enumerate() {
        let prims = mesh.get("primitives").and_then(Value::as_array);
        for (p, prim) in prims.into_iter().flatten().enumerate() {
            let attrs = prim.get("attributes").and_then(Value::as_object);
            let targets = prim.get("targets").and_then(Value::as_array);
            let refs = attrs
                .into_iter()
                .flat_map(|a| a.values())
                .chain(prim.get("indices"))
                .chain(
                    targets
                        .into_iter()
                        .flatten()
                        .filter_map(Value::as_object)
                        .flat_map(|t| t.values()),
                );
            for r in refs {
                if r.as_u64().is_none_or(|i| i >= accessor_count as u64) {
                    return Err(MeshError::parse(
                        "glTF",
                        format!(
                            "mesh {m} primitive {p} refers to accessor {r}, but there are \
                             {accessor_count}"
                        ),
                    ));
                }
            }
        }
    }
    Ok(())
}

/// Refuses images by external URI and images with no source, on the raw JSON (the gltf
/// crate's `Image::source` unwraps a missing `uri` or `mimeType` that its validation lets
/// through).
fn check_images(json: &Value) -> Result<(), MeshError> {
    let images = json.get("images").and_then(Value::as_array);
    for (i, image) in images.into_iter().flatten().enumerate() {
        match (image.get("uri"), image.get("bufferView")) {
            (Some(uri), _) => match uri.as_str() {
                Some(u) if u.starts_with("data:") => {}
                Some(u) => {
                    return Err(MeshError::ExternalUri {
                        uri: u.chars().take(200).collect(),
                    })
                }
                None => return Err(MeshError::parse("glTF", format!("image {i}: bad uri"))),
            },
            (None, Some(_)) if image.get("mimeType").is_some_and(Value::is_string) => {}
            _ => {
                return Err(MeshError::parse(
                    "glTF",
                    format!("image {i} needs a uri, or a bufferView with a mimeType"),
                ))
            }
        }
    }
    Ok(())
}

/// Decodes a base64 `data:` URI, or refuses anything else without touching it.
fn decode_data_uri(uri: &str) -> Result<Vec<u8>, MeshError> {
    let Some(rest) = uri.strip_prefix("data:") else {
        return Err(MeshError::ExternalUri {
            uri: uri.chars().take(200).collect(),
        });
    };
    let (_, payload) = rest
        .split_once(";base64,")
        .ok_or_else(|| MeshError::unsupported("data: URIs that are not base64"))?;
    base64::engine::general_purpose::STANDARD
        .decode(payload.trim())
        .map_err(|e| MeshError::parse("glTF", format!("bad base64 in a data: URI: {e}")))
}

/// `asset.version` must be 2.x (glTF 2.0 says a reader refuses a major version it does not
/// know). glTF 1.0 is a different schema the gltf crate would half-read (a 1.0 file's
/// meshes look empty or wrong), so a 1.0 file is refused by name instead.
fn check_asset_version(json: &Value) -> Result<(), MeshError> {
    let version = json
        .get("asset")
        .and_then(|a| a.get("version"))
        .and_then(Value::as_str);
    match version {
        Some(v) if v.split('.').next() == Some("2") => Ok(()),
        Some(v) => Err(MeshError::unsupported(format!(
            "glTF asset.version {:?}: only glTF 2.x is read",
            v.chars().take(32).collect::<String>()
        ))),
        // Missing: the gltf crate's own parse error says so.
        None => Ok(()),
    }
}

pub(crate) fn read(
    bytes: &[u8],
    format: Format,
    limits: &Limits,
) -> Result<(FileGeometry, GltfSource), MeshError> {
    let name = format_name(format);
    let (json_bytes, bin) = split_container(bytes, format)?;
    let mut json: Value =
        serde_json::from_slice(json_bytes).map_err(|e| MeshError::parse(name, e.to_string()))?;
    check_asset_version(&json)?;
    check_primitive_references(&json)?;
    check_images(&json)?;
    let notes = clean::notes(&json);
    // Meshopt-compressed views and Draco primitives are decoded first, on the raw JSON, which
    // then describes plain data (see `meshopt`, `draco`); the gltf crate validates that.
    let meshopt_ext = meshopt::used(&json);
    let draco = draco::used(&json);
    let mut compression = None;
    let decoded = if meshopt_ext.is_some() || draco {
        let mut buffers = meshopt::resolve_buffers(&json, bin, meshopt_ext, limits)?;
        if let Some(ext) = meshopt_ext {
            compression = Some(meshopt::decompress(&mut json, &mut buffers, ext)?);
        }
        if draco {
            draco::decompress(&mut json, &mut buffers, limits)?;
        }
        Some(buffers)
    } else {
        None
    };
    let plain_json;
    let json_bytes = if decoded.is_some() {
        plain_json =
            serde_json::to_vec(&json).map_err(|e| MeshError::parse(name, e.to_string()))?;
        &plain_json[..]
    } else {
        json_bytes
    };
    let mut root = gltf::json::Root::from_slice(json_bytes)
        .map_err(|e| MeshError::parse(name, e.to_string()))?;
    let quantized = root.extensions_used.iter().any(|e| e == MESH_QUANTIZATION);
    root.extensions_required.retain(|e| e != MESH_QUANTIZATION);
    let doc = gltf::Document::from_json(root).map_err(|e| MeshError::parse(name, e.to_string()))?;

    // Resolve buffers: GLB BIN chunk or data: URIs; nothing else is ever opened.
    let mut buffers = decoded.unwrap_or_default();
    for b in doc.buffers().skip(buffers.len()) {
        let mut data = match b.source() {
            gltf::buffer::Source::Bin => match bin {
                Some(bin) if b.index() == 0 => bin.to_vec(),
                _ => {
                    return Err(MeshError::truncated(format!(
                        "buffer {} has no uri and there is no GLB BIN chunk for it",
                        b.index()
                    )))
                }
            },
            gltf::buffer::Source::Uri(uri) => decode_data_uri(uri)?,
        };
        if data.len() < b.length() {
            return Err(MeshError::truncated(format!(
                "buffer {} declares {} bytes but holds {}",
                b.index(),
                b.length(),
                data.len()
            )));
        }
        data.truncate(b.length());
        buffers.push(data);
    }
    for view in doc.views() {
        let len = buffers.get(view.buffer().index()).map_or(0, Vec::len);
        if view
            .offset()
            .checked_add(view.length())
            .is_none_or(|end| end > len)
        {
            return Err(MeshError::truncated(format!(
                "buffer view {} (bytes {}..+{}) is past the end of buffer {} ({len} bytes)",
                view.index(),
                view.offset(),
                view.length(),
                view.buffer().index()
            )));
        }
    }

    // The nodes to draw: the default scene, else scene 0, else every root node.
    let roots: Vec<gltf::Node<'_>> = match doc.default_scene().or_else(|| doc.scenes().next()) {
        Some(scene) => scene.nodes().collect(),
        None => {
            let mut is_child = vec![false; doc.nodes().len()];
            for n in doc.nodes() {
                for c in n.children() {
                    if let Some(x) = is_child.get_mut(c.index()) {
                        *x = true;
                    }
                }
            }
            doc.nodes().filter(|n| !is_child[n.index()]).collect()
        }
    };

    let mut b = Builder {
        buffers: &buffers,
        quantized,
        limits,
        local: Vec::new(),
        blocks: Vec::new(),
        block_of_accessor: HashMap::new(),
        position_accessors: Vec::new(),
        position_nodes: Vec::new(),
        normal_accessors: Vec::new(),
        uvs: Vec::new(),
        normals: Vec::new(),
        triangles: Vec::new(),
        non_triangle_primitives: (0, 0),
        bad_faces: Default::default(),
        runs: Vec::new(),
        varyings: Vec::new(),
    };
    let mut groups = super::groups::Groups::default();
    let mut visited = vec![false; doc.nodes().len()];
    let mut stack: Vec<(gltf::Node<'_>, Affine)> = roots
        .into_iter()
        .rev()
        .map(|n| (n, Affine::IDENTITY))
        .collect();
    while let Some((node, parent)) = stack.pop() {
        let seen = visited.get_mut(node.index()).ok_or_else(|| {
            MeshError::parse(name, format!("node {} does not exist", node.index()))
        })?;
        if *seen {
            return Err(MeshError::parse(
                name,
                format!(
                    "node {} is reached twice: the hierarchy is not a tree",
                    node.index()
                ),
            ));
        }
        *seen = true;
        let world = parent.then_after(&affine_of(&node, &json));
        if let Some(mesh) = node.mesh() {
            let first = b.triangles.len();
            for prim in mesh.primitives() {
                b.primitive(&prim, &world, node.index(), mesh.index())?;
            }
            for name in [node.name(), mesh.name()].into_iter().flatten() {
                let slot = groups.slot(name);
                groups.add(slot, first..b.triangles.len());
            }
        }
        let children: Vec<_> = node.children().collect();
        for c in children.into_iter().rev() {
            stack.push((c, world));
        }
    }
    if !b.bad_faces.is_empty() {
        return Err(MeshError::IndexOutOfRange {
            faces: b.bad_faces,
            vertex_count: b.local.len(),
        });
    }
    if b.triangles.is_empty() {
        let (points, lines) = b.non_triangle_primitives;
        return Err(if points + lines > 0 {
            MeshError::PointsOrLinesOnly { points, lines }
        } else {
            MeshError::Empty {
                vertices: b.local.len(),
                faces: 0,
            }
        });
    }

    let Builder {
        local,
        blocks,
        position_accessors,
        position_nodes,
        normal_accessors,
        uvs,
        normals,
        triangles,
        runs,
        varyings,
        ..
    } = b;
    let block_values: Vec<(usize, usize, &[[f64; 3]])> = position_accessors
        .iter()
        .zip(&position_nodes)
        .zip(&blocks)
        .map(|((&a, &n), b)| (a, n, local.get(b.start..b.start + b.len).unwrap_or(&[])))
        .collect();
    let (requantize, quantization_note) = quantize::plan(&json, &block_values, &normal_accessors);
    let mut notes = notes;
    notes.extend(quantization_note);
    let uvs = uvs.iter().any(Option::is_some).then_some(uvs);
    let read_normals = normals.iter().any(Option::is_some).then(|| normals.clone());
    let normal_keys = normals.iter().any(Option::is_some).then(|| {
        let mut ids: HashMap<[u64; 3], u64> = HashMap::new();
        normals
            .iter()
            .map(|n| match n {
                None => u64::MAX,
                Some(n) => {
                    let next = ids.len() as u64;
                    *ids.entry(n.map(f64::to_bits)).or_insert(next)
                }
            })
            .collect()
    });
    let file = FileGeometry {
        local,
        blocks,
        triangles,
        uvs,
        normal_keys,
        face_of_triangle: None,
        copies: Vec::new(),
    };
    let src = GltfSource {
        json,
        buffers,
        position_accessors,
        normal_accessors,
        requantize,
        compression,
        groups,
        notes,
        normals: read_normals,
        runs,
        varyings,
    };
    Ok((file, src))
}
