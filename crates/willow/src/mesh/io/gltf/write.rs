//! Writing glTF and GLB: the input document kept with new positions (and bounds), or a new document for a mesh that came from OBJ.

use super::*;
use crate::mesh::io::{normalize_or_z, Affine, Asset, Block, Limits, MeshError};
use gltf::accessor::DataType;
use gltf::mesh::Mode;
use serde_json::{json, Value};
use std::collections::HashMap;

/// Accumulates file vertices and triangles while walking the scene.
pub(super) struct Builder<'a> {
    pub(super) buffers: &'a [Vec<u8>],
    /// The document uses `KHR_mesh_quantization`: integer attribute types are allowed.
    pub(super) quantized: bool,
    pub(super) limits: &'a Limits,
    pub(super) local: Vec<[f64; 3]>,
    pub(super) blocks: Vec<Block>,
    pub(super) block_of_accessor: HashMap<usize, usize>,
    pub(super) position_accessors: Vec<usize>,
    /// The node that drew each POSITION accessor first (same order).
    pub(super) position_nodes: Vec<usize>,
    pub(super) normal_accessors: Vec<(usize, usize)>,
    pub(super) uvs: Vec<Option<[f64; 2]>>,
    pub(super) normals: Vec<Option<[f64; 3]>>,
    pub(super) triangles: Vec<[usize; 3]>,
    pub(super) non_triangle_primitives: (usize, usize),
    pub(super) bad_faces: crate::mesh::error::Offenders<usize>,
    /// The triangles each primitive drew (what a refined document rewrites, `refined`).
    pub(super) runs: Vec<super::refined::Run>,
    /// TEXCOORD_n (n ≥ 1) and COLOR_n per vertex of their block (`refined`).
    pub(super) varyings: Vec<super::refined::BlockVarying>,
}

impl Builder<'_> {
    pub(super) fn primitive(
        &mut self,
        prim: &gltf::Primitive<'_>,
        world: &Affine,
        node: usize,
        mesh: usize,
    ) -> Result<(), MeshError> {
        match prim.mode() {
            Mode::Points => {
                self.non_triangle_primitives.0 += 1;
                return Ok(());
            }
            Mode::Lines | Mode::LineLoop | Mode::LineStrip => {
                self.non_triangle_primitives.1 += 1;
                return Ok(());
            }
            Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan => {}
        }
        let pos = prim
            .get(&gltf::Semantic::Positions)
            .ok_or_else(|| MeshError::parse("glTF", "a triangle primitive has no POSITION"))?;
        let count = pos.count();
        let block = match self.block_of_accessor.get(&pos.index()) {
            Some(&bi) => {
                if self.blocks.get(bi).map(|b| &b.to_world) != Some(world) {
                    return Err(MeshError::unsupported(format!(
                        "mesh data (POSITION accessor {}) drawn by several nodes with different \
                         transforms (instancing); node {node} is one of them",
                        pos.index()
                    )));
                }
                bi
            }
            None => {
                self.limits
                    .check_vertices(self.local.len().saturating_add(count))?;
                let to_local = world.inverse().ok_or_else(|| {
                    MeshError::unsupported(format!("node {node} has a singular transform"))
                })?;
                let positions = read_vec3(&pos, self.buffers, Attribute::Position, self.quantized)?;
                let start = self.local.len();
                self.local.extend(positions);
                self.uvs.resize(self.local.len(), None);
                self.normals.resize(self.local.len(), None);
                self.blocks.push(Block {
                    start,
                    len: count,
                    to_world: *world,
                    to_local,
                });
                self.position_accessors.push(pos.index());
                self.position_nodes.push(node);
                self.block_of_accessor
                    .insert(pos.index(), self.blocks.len() - 1);
                self.blocks.len() - 1
            }
        };
        let start = self.blocks.get(block).map_or(0, |b| b.start);
        for (semantic, acc) in prim.attributes() {
            let kept = matches!(semantic, gltf::Semantic::TexCoords(n) if n > 0)
                || matches!(semantic, gltf::Semantic::Colors(_));
            if kept && !self.varyings.iter().any(|v| v.accessor == acc.index()) {
                let v = super::refined::read_varying(&acc, self.buffers, block, count)?;
                self.varyings.push(v);
            }
        }
        let first_triangle = self.triangles.len();
        if let Some(uv) = prim.get(&gltf::Semantic::TexCoords(0)) {
            if uv.count() != count {
                return Err(MeshError::parse(
                    "glTF",
                    "TEXCOORD_0 and POSITION counts differ",
                ));
            }
            for (i, v) in read_uv(&uv, self.buffers, self.quantized)?
                .into_iter()
                .enumerate()
            {
                if let Some(slot) = self.uvs.get_mut(start + i) {
                    *slot = Some(v);
                }
            }
        }
        if let Some(n) = prim.get(&gltf::Semantic::Normals) {
            if n.count() != count {
                return Err(MeshError::parse(
                    "glTF",
                    "NORMAL and POSITION counts differ",
                ));
            }
            if !self.normal_accessors.iter().any(|&(a, _)| a == n.index()) {
                self.normal_accessors.push((n.index(), block));
            }
            for (i, v) in read_vec3(&n, self.buffers, Attribute::Normal, self.quantized)?
                .into_iter()
                .enumerate()
            {
                if let Some(slot) = self.normals.get_mut(start + i) {
                    *slot = Some(v);
                }
            }
        }

        let indices: Vec<usize> = match prim.indices() {
            Some(acc) => {
                self.limits
                    .check_faces(self.triangles.len().saturating_add(acc.count() / 3))?;
                read_indices(&acc, self.buffers)?
            }
            None => {
                self.limits
                    .check_faces(self.triangles.len().saturating_add(count / 3))?;
                (0..count).collect()
            }
        };
        let mut push = |t: [usize; 3], skip_repeated: bool| {
            if skip_repeated && (t[0] == t[1] || t[1] == t[2] || t[0] == t[2]) {
                return; // the zero-area triangles strips use to restart
            }
            if t.iter().any(|&i| i >= count) {
                self.bad_faces.push(self.triangles.len());
            }
            self.triangles
                .push(t.map(|i| start + i.min(count.saturating_sub(1))));
        };
        match prim.mode() {
            Mode::TriangleStrip => {
                for (i, w) in indices.windows(3).enumerate() {
                    let t = if i % 2 == 0 {
                        [w[0], w[1], w[2]]
                    } else {
                        [w[1], w[0], w[2]]
                    };
                    push(t, true);
                }
            }
            Mode::TriangleFan => {
                if let Some((&first, rest)) = indices.split_first() {
                    for w in rest.windows(2) {
                        push([first, w[0], w[1]], true);
                    }
                }
            }
            _ => {
                if !indices.len().is_multiple_of(3) {
                    return Err(MeshError::parse(
                        "glTF",
                        format!(
                            "a TRIANGLES primitive has {} indices, not a multiple of 3",
                            indices.len()
                        ),
                    ));
                }
                for t in indices.chunks_exact(3) {
                    push([t[0], t[1], t[2]], false);
                }
            }
        }
        self.runs.push(super::refined::Run {
            mesh,
            primitive: prim.index(),
            block,
            triangles: first_triangle..self.triangles.len(),
        });
        Ok(())
    }
}

/// Appends `data` to `bin` at a 4-byte aligned offset; returns the offset.
pub(super) fn append_aligned(bin: &mut Vec<u8>, data: &[u8]) -> usize {
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let at = bin.len();
    bin.extend_from_slice(data);
    at
}

pub(super) fn vec3_bytes(values: &[[f32; 3]]) -> Vec<u8> {
    values
        .iter()
        .flatten()
        .flat_map(|x| x.to_le_bytes())
        .collect()
}

/// Component-wise min and max, as JSON arrays (glTF requires them on POSITION).
pub(super) fn bounds(values: &[[f32; 3]]) -> (Value, Value) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for v in values {
        for k in 0..3 {
            lo[k] = lo[k].min(v[k]);
            hi[k] = hi[k].max(v[k]);
        }
    }
    (json!(lo), json!(hi))
}

/// The centre of `points`' bounding box when they lie farther from the origin than their own
/// size, so that f32 offsets from it keep ~1e-7 of the model's size (f32 coordinates of the
/// points themselves would keep only ~6e-8 of their distance from the origin); `None` for
/// models around the origin, which are written as they are.
pub(crate) fn far_origin(points: &[[f64; 3]]) -> Option<[f64; 3]> {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in points {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    let extent = (0..3).map(|k| hi[k] - lo[k]).fold(0.0, f64::max);
    let far = (0..3)
        .map(|k| lo[k].abs().max(hi[k].abs()))
        .fold(0.0, f64::max);
    (extent.is_finite() && far > extent).then(|| [0, 1, 2].map(|k| 0.5 * (lo[k] + hi[k])))
}

pub(super) fn malformed(what: &str) -> MeshError {
    MeshError::parse("glTF", format!("cannot rewrite the document: {what}"))
}

/// Component-wise min and max of integer values, as JSON arrays.
fn int_bounds(values: &[[i64; 3]]) -> (Value, Value) {
    let mut lo = [i64::MAX; 3];
    let mut hi = [i64::MIN; 3];
    for v in values {
        for k in 0..3 {
            lo[k] = lo[k].min(v[k]);
            hi[k] = hi[k].max(v[k]);
        }
    }
    (json!(lo), json!(hi))
}

/// Sets a buffer view's `byteStride` (padded VEC3 integer elements).
pub(super) fn set_stride(doc: &mut Value, view: usize, stride: usize) -> Result<(), MeshError> {
    let v = doc
        .get_mut("bufferViews")
        .and_then(|v| v.get_mut(view))
        .and_then(Value::as_object_mut)
        .ok_or_else(|| malformed("missing buffer view"))?;
    v.insert("byteStride".into(), json!(stride));
    Ok(())
}

/// Repoints accessor `index` at a new VEC3 buffer view of `(componentType, normalized)`.
pub(super) fn repoint_accessor(
    doc: &mut Value,
    index: usize,
    view: usize,
    count: usize,
    encoding: (u32, bool),
    min_max: Option<(Value, Value)>,
) -> Result<(), MeshError> {
    repoint_accessor_as(doc, index, view, count, "VEC3", encoding, min_max)
}

/// Repoints accessor `index` at a new buffer view of `count` elements of type `ty`
/// (`"VEC2"`, `"VEC3"`, ...) stored as `(componentType, normalized)`.
pub(super) fn repoint_accessor_as(
    doc: &mut Value,
    index: usize,
    view: usize,
    count: usize,
    ty: &str,
    (component, normalized): (u32, bool),
    min_max: Option<(Value, Value)>,
) -> Result<(), MeshError> {
    let acc = doc
        .get_mut("accessors")
        .and_then(|a| a.get_mut(index))
        .and_then(Value::as_object_mut)
        .ok_or_else(|| malformed("missing accessor"))?;
    for key in ["byteOffset", "sparse", "normalized", "min", "max"] {
        acc.remove(key);
    }
    acc.insert("bufferView".into(), json!(view));
    acc.insert("componentType".into(), json!(component));
    if normalized {
        acc.insert("normalized".into(), json!(true));
    }
    acc.insert("type".into(), json!(ty));
    acc.insert("count".into(), json!(count));
    if let Some((lo, hi)) = min_max {
        acc.insert("min".into(), lo);
        acc.insert("max".into(), hi);
    }
    Ok(())
}

pub(super) fn push_view(
    doc: &mut Value,
    offset: usize,
    length: usize,
    target: u32,
) -> Result<usize, MeshError> {
    let obj = doc
        .as_object_mut()
        .ok_or_else(|| malformed("not an object"))?;
    let views = obj
        .entry("bufferViews")
        .or_insert_with(|| json!([]))
        .as_array_mut()
        .ok_or_else(|| malformed("bufferViews is not an array"))?;
    views.push(json!({"buffer": 0, "byteOffset": offset, "byteLength": length, "target": target}));
    Ok(views.len() - 1)
}

/// Removes TANGENT from every primitive and morph target: tangents follow positions, so the
/// stored ones are stale once the surface moves. glTF says viewers compute MikkTSpace tangents
/// when none are given, which is more faithful than a second implementation here (MikkTSpace's
/// exact splitting rules would have to match). The accessors stay (unused, which is valid).
pub(super) fn drop_tangents(doc: &mut Value) {
    let meshes = doc.get_mut("meshes").and_then(Value::as_array_mut);
    for mesh in meshes.into_iter().flatten() {
        let prims = mesh.get_mut("primitives").and_then(Value::as_array_mut);
        for prim in prims.into_iter().flatten() {
            if let Some(a) = prim.get_mut("attributes").and_then(Value::as_object_mut) {
                a.remove("TANGENT");
            }
            let targets = prim.get_mut("targets").and_then(Value::as_array_mut);
            for t in targets
                .into_iter()
                .flatten()
                .filter_map(Value::as_object_mut)
            {
                t.remove("TANGENT");
            }
        }
    }
}

/// The input document with TANGENT and morph targets dropped (see the module docs), and its
/// buffers merged into one: every original buffer unchanged, each at an 8-aligned offset so
/// the alignment of every original view (at most 4 is required) is kept.
pub(super) fn merged_document(src: &GltfSource) -> Result<(Value, Vec<u8>), MeshError> {
    let mut doc = src.json.clone();
    drop_tangents(&mut doc);
    super::clean::drop_morph_targets(&mut doc);
    // One buffer: every original buffer unchanged, each at an 8-aligned offset so the
    // alignment of every original view (at most 4 is required) is kept.
    let mut bin: Vec<u8> = Vec::new();
    let mut base = Vec::with_capacity(src.buffers.len());
    for b in &src.buffers {
        while !bin.len().is_multiple_of(8) {
            bin.push(0);
        }
        base.push(bin.len());
        bin.extend_from_slice(b);
    }
    if let Some(views) = doc.get_mut("bufferViews").and_then(Value::as_array_mut) {
        for v in views {
            let v = v.as_object_mut().ok_or_else(|| malformed("buffer view"))?;
            let buffer = v.get("buffer").and_then(Value::as_u64).unwrap_or(0) as usize;
            let offset = v.get("byteOffset").and_then(Value::as_u64).unwrap_or(0) as usize;
            let b = base
                .get(buffer)
                .ok_or_else(|| malformed("view of a missing buffer"))?;
            v.insert("buffer".into(), json!(0));
            v.insert("byteOffset".into(), json!(offset + b));
        }
    }
    Ok((doc, bin))
}

/// Whether accessor `acc` of the input was stored through meshopt compression (`reencode`).
pub(super) fn was_compressed(src: &GltfSource, acc: usize) -> bool {
    let Some(c) = &src.compression else {
        return false;
    };
    let view = src.json["accessors"][acc]["bufferView"].as_u64();
    view.is_some_and(|v| c.attributes.iter().any(|a| a.0 as u64 == v))
}

/// Re-encodes the `recompress` views (meshopt input), drops bytes and views nothing uses any
/// more, and serializes (the end of [`write_document`], shared with `refined`).
pub(super) fn finish_document(
    mut doc: Value,
    bin: Vec<u8>,
    src: &GltfSource,
    recompress: &[(usize, usize)],
    glb: bool,
) -> Result<Vec<u8>, MeshError> {
    let mut fallback = None;
    let blobs = match &src.compression {
        Some(c) => super::reencode::mark(&mut doc, &bin, recompress, c)?,
        None => Vec::new(),
    };
    let mut bin = super::clean::compact(&mut doc, &bin)?;
    if let Some(c) = &src.compression {
        fallback = super::reencode::place(&mut doc, &mut bin, &blobs, c)?;
    }
    finish(doc, bin, glb, fallback)
}

/// Rewrites the input document with new positions (see the module docs).
pub(crate) fn write_document(
    asset: &Asset,
    src: &GltfSource,
    positions: &[[f64; 3]],
    glb: bool,
) -> Result<Vec<u8>, MeshError> {
    let (mut doc, mut bin) = merged_document(src)?;

    // KHR_mesh_quantization: positions re-quantized where sound (see `quantize`), the rest
    // as float32 in the node's unchanged space.
    // Meshopt input: the views to store compressed again (see `reencode`), the rewritten
    // POSITION and NORMAL views whose input views were compressed.
    let was_compressed = |acc: usize| was_compressed(src, acc);
    let mut recompress: Vec<(usize, usize)> = Vec::new();
    let split = asset.split_positions(positions);
    let mut requantized = vec![false; src.position_accessors.len()];
    for plan in &src.requantize {
        let mut values = Vec::new();
        for &bi in &plan.blocks {
            let b = asset
                .file
                .blocks
                .get(bi)
                .ok_or_else(|| malformed("block"))?;
            values.extend_from_slice(
                split
                    .get(b.start..b.start + b.len)
                    .ok_or_else(|| malformed("block out of range"))?,
            );
        }
        let (q, map) = quantize::quantize(plan.grid, &values);
        let mut at = 0;
        for &bi in &plan.blocks {
            let (Some(b), Some(&acc)) = (asset.file.blocks.get(bi), src.position_accessors.get(bi))
            else {
                return Err(malformed("block"));
            };
            let block_q = q.get(at..at + b.len).ok_or_else(|| malformed("block"))?;
            at += b.len;
            let (bytes, stride) = quantize::element_bytes(plan.grid.component, block_q);
            let offset = append_aligned(&mut bin, &bytes);
            let view = push_view(&mut doc, offset, bytes.len(), ARRAY_BUFFER)?;
            set_stride(&mut doc, view, stride)?;
            if was_compressed(acc) {
                recompress.push((view, stride));
            }
            let ty = (quantize::code(plan.grid.component), plan.grid.normalized);
            repoint_accessor(&mut doc, acc, view, b.len, ty, Some(int_bounds(block_q)))?;
            requantized[bi] = true;
        }
        let local = node_affine(&src.json, plan.node);
        quantize::update_node(&mut doc, plan.node, &local, &map)?;
    }
    let local: Vec<[f32; 3]> = split.iter().map(|p| p.map(|x| x as f32)).collect();
    for ((&acc, block), done) in src
        .position_accessors
        .iter()
        .zip(&asset.file.blocks)
        .zip(requantized)
    {
        if done {
            continue;
        }
        let values = local
            .get(block.start..block.start + block.len)
            .ok_or_else(|| malformed("block out of range"))?;
        let at = append_aligned(&mut bin, &vec3_bytes(values));
        let view = push_view(&mut doc, at, values.len() * 12, ARRAY_BUFFER)?;
        if was_compressed(acc) {
            set_stride(&mut doc, view, 12)?;
            recompress.push((view, 12));
        }
        let ty = (FLOAT, false);
        repoint_accessor(&mut doc, acc, view, values.len(), ty, Some(bounds(values)))?;
    }

    if let Some(world_normals) = asset.split_normals_world(positions) {
        for &(acc, bi) in &src.normal_accessors {
            let block = asset
                .file
                .blocks
                .get(bi)
                .ok_or_else(|| malformed("normal block"))?;
            let local: Vec<[f64; 3]> = world_normals
                .get(block.start..block.start + block.len)
                .ok_or_else(|| malformed("normal block out of range"))?
                .iter()
                .map(|&n| normalize_or_z(block.to_world.transpose_apply(n)))
                .collect();
            // A quantized NORMAL keeps its type (KHR_mesh_quantization allows normalized
            // byte and short): the node's new transform is a uniform scale, so local
            // directions mean what they meant.
            match quantize::accessor_type(&src.json, acc) {
                Some((c @ (DataType::I8 | DataType::I16), true)) => {
                    let q: Vec<[i64; 3]> = local
                        .iter()
                        .map(|&n| quantize::quantize_normal(c, n))
                        .collect();
                    let (bytes, stride) = quantize::element_bytes(c, &q);
                    let at = append_aligned(&mut bin, &bytes);
                    let view = push_view(&mut doc, at, bytes.len(), ARRAY_BUFFER)?;
                    set_stride(&mut doc, view, stride)?;
                    if was_compressed(acc) {
                        recompress.push((view, stride));
                    }
                    repoint_accessor(
                        &mut doc,
                        acc,
                        view,
                        q.len(),
                        (quantize::code(c), true),
                        None,
                    )?;
                }
                _ => {
                    let values: Vec<[f32; 3]> = local.iter().map(|n| n.map(|x| x as f32)).collect();
                    let at = append_aligned(&mut bin, &vec3_bytes(&values));
                    let view = push_view(&mut doc, at, values.len() * 12, ARRAY_BUFFER)?;
                    if was_compressed(acc) {
                        set_stride(&mut doc, view, 12)?;
                        recompress.push((view, 12));
                    }
                    repoint_accessor(&mut doc, acc, view, values.len(), (FLOAT, false), None)?;
                }
            }
        }
    }

    finish_document(doc, bin, src, &recompress, glb)
}

/// Sets buffer 0 (and a meshopt fallback buffer 1, with no data, when given) and serializes
/// as GLB (BIN chunk) or glTF (base64 data: URI).
pub(super) fn finish(
    mut doc: Value,
    mut bin: Vec<u8>,
    glb: bool,
    fallback: Option<Value>,
) -> Result<Vec<u8>, MeshError> {
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let buffer = if glb {
        json!({"byteLength": bin.len()})
    } else {
        let b64 = base64::engine::general_purpose::STANDARD.encode(&bin);
        json!({"byteLength": bin.len(), "uri": format!("data:application/octet-stream;base64,{b64}")})
    };
    doc.as_object_mut()
        .ok_or_else(|| malformed("not an object"))?
        .insert(
            "buffers".into(),
            Value::Array(std::iter::once(buffer).chain(fallback).collect()),
        );
    let mut json_bytes =
        serde_json::to_vec(&doc).map_err(|e| malformed(&format!("serialization: {e}")))?;
    if !glb {
        return Ok(json_bytes);
    }
    while json_bytes.len() % 4 != 0 {
        json_bytes.push(b' ');
    }
    let total = 12 + 8 + json_bytes.len() + 8 + bin.len();
    let as_u32 = |n: usize| -> Result<[u8; 4], MeshError> {
        u32::try_from(n)
            .map(u32::to_le_bytes)
            .map_err(|_| MeshError::TooLarge {
                what: "output bytes",
                value: n,
                limit: u32::MAX as usize,
            })
    };
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&as_u32(total)?);
    out.extend_from_slice(&as_u32(json_bytes.len())?);
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json_bytes);
    out.extend_from_slice(&as_u32(bin.len())?);
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin);
    Ok(out)
}

/// A new document for an asset read from OBJ: one mesh, one primitive with POSITION,
/// TEXCOORD_0 and NORMAL when the file had them, u32 indices wound like the surface.
pub(crate) fn write_new(
    asset: &Asset,
    positions: &[[f64; 3]],
    glb: bool,
) -> Result<Vec<u8>, MeshError> {
    // Far from the origin (map-grid coordinates), f32 positions would snap to a coarse grid
    // (0.5 at 5e6): store them relative to the node's translation, which JSON keeps in f64.
    // World space, like the normals: the one node written has no other transform (a refined
    // glTF's blocks keep the file's node transforms, which this document does not carry).
    let split = asset.split_world_positions(positions);
    let origin = far_origin(&split);
    let o = origin.unwrap_or([0.0; 3]);
    let local: Vec<[f32; 3]> = split
        .iter()
        .map(|p| {
            [
                (p[0] - o[0]) as f32,
                (p[1] - o[1]) as f32,
                (p[2] - o[2]) as f32,
            ]
        })
        .collect();
    let mut bin = Vec::new();
    let mut accessors = Vec::new();
    let mut views = Vec::new();
    let mut attributes = serde_json::Map::new();

    let mut add = |bin: &mut Vec<u8>, data: Vec<u8>, target: u32, accessor: Value| -> usize {
        let at = append_aligned(bin, &data);
        views.push(
            json!({"buffer": 0, "byteOffset": at, "byteLength": data.len(), "target": target}),
        );
        let mut accessor = accessor;
        if let Some(a) = accessor.as_object_mut() {
            a.insert("bufferView".into(), json!(views.len() - 1));
        }
        accessors.push(accessor);
        accessors.len() - 1
    };

    let (lo, hi) = bounds(&local);
    let pos = add(
        &mut bin,
        vec3_bytes(&local),
        ARRAY_BUFFER,
        json!({"componentType": FLOAT, "count": local.len(), "type": "VEC3", "min": lo, "max": hi}),
    );
    attributes.insert("POSITION".into(), json!(pos));
    if let Some(normals) = asset.split_normals_world(positions) {
        let values: Vec<[f32; 3]> = normals.iter().map(|n| n.map(|x| x as f32)).collect();
        let n = add(
            &mut bin,
            vec3_bytes(&values),
            ARRAY_BUFFER,
            json!({"componentType": FLOAT, "count": values.len(), "type": "VEC3"}),
        );
        attributes.insert("NORMAL".into(), json!(n));
    }
    if let Some(uvs) = &asset.file.uvs {
        let uvs: Vec<[f32; 2]> = uvs
            .iter()
            .map(|uv| uv.unwrap_or([0.0; 2]).map(|x| x as f32))
            .collect();
        let data: Vec<u8> = uvs.iter().flatten().flat_map(|x| x.to_le_bytes()).collect();
        let t = add(
            &mut bin,
            data,
            ARRAY_BUFFER,
            json!({"componentType": FLOAT, "count": uvs.len(), "type": "VEC2"}),
        );
        attributes.insert("TEXCOORD_0".into(), json!(t));
    }
    let triangles = asset.oriented_split_triangles();
    let mut index_bytes = Vec::with_capacity(triangles.len() * 12);
    for i in triangles.iter().flatten() {
        let i = u32::try_from(*i).map_err(|_| MeshError::TooLarge {
            what: "vertices for 32-bit indices",
            value: *i,
            limit: u32::MAX as usize,
        })?;
        index_bytes.extend_from_slice(&i.to_le_bytes());
    }
    let indices = add(
        &mut bin,
        index_bytes,
        ELEMENT_ARRAY_BUFFER,
        json!({"componentType": UNSIGNED_INT, "count": triangles.len() * 3, "type": "SCALAR"}),
    );
    let doc = json!({
        "asset": {"version": "2.0", "generator": "Willow"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [match origin {
            Some(t) => json!({"mesh": 0, "translation": t}),
            None => json!({"mesh": 0}),
        }],
        "meshes": [{"primitives": [{"attributes": attributes, "indices": indices, "mode": 4}]}],
        "accessors": accessors,
        "bufferViews": views,
    });
    finish(doc, bin, glb, None)
}
