//! Writing a refined glTF (issue 26, item 5; [`crate::mesh::io::Asset::refined`]): the input's
//! document kept, with only each primitive's vertex data and indices replaced.
//!
//! Everything the unrefined writer keeps is kept: materials, textures, images, samplers,
//! nodes (hierarchy, transforms, names), meshes and their names, extensions. What changes is
//! per POSITION accessor (one block of split vertices): its vertices are the input's, in
//! their order, then the new ones of that block (`refined.rs` numbers them so), and every
//! vertex attribute of the primitives drawing it is written for that list:
//!
//! - POSITION: the new positions in the accessor's local space, float32;
//! - NORMAL: recomputed, as on every written glTF;
//! - TEXCOORD_0, TEXCOORD_n and COLOR_n: interpolated linearly (each new vertex is its edge's
//!   midpoint in attribute space, per corner, so UV seams stay split), float32;
//! - TANGENT, JOINTS_n/WEIGHTS_n and custom attributes: dropped, with a note ([`dropped`]):
//!   tangents follow the surface (viewers compute MikkTSpace tangents when none are given),
//!   and four joint influences per vertex cannot hold the union of an edge's two ends;
//! - indices: the children of each input triangle, as u32 TRIANGLES (strips and fans are
//!   written as triangle lists), each in the winding its parent had in the file.
//!
//! Accessors are repointed in place, so anything else naming them (a points primitive sharing
//! the POSITION accessor) still reads the input's vertices first, at their new positions.

use super::accessors::{dims_of, layout};
use super::write::{
    append_aligned, bounds, finish_document, malformed, merged_document, push_view,
    repoint_accessor_as, was_compressed,
};
use super::{GltfSource, ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER, FLOAT, UNSIGNED_INT};
use crate::mesh::io::refined::RefinedSource;
use crate::mesh::io::{normalize_or_z, Asset, MeshError};
use serde_json::{json, Value};
use std::ops::Range;

/// The triangles one primitive drew (file triangles `triangles`, over block `block`).
#[derive(Clone, Debug)]
pub(crate) struct Run {
    pub(crate) mesh: usize,
    pub(crate) primitive: usize,
    pub(crate) block: usize,
    pub(crate) triangles: Range<usize>,
}

/// A TEXCOORD_n (n ≥ 1) or COLOR_n accessor's values: `width` numbers per vertex of its block.
#[derive(Clone, Debug)]
pub(crate) struct BlockVarying {
    pub(crate) accessor: usize,
    pub(crate) block: usize,
    pub(crate) width: usize,
    pub(crate) values: Vec<f64>,
}

/// Reads a TEXCOORD_n or COLOR_n accessor as numbers (normalized integers mapped to [0, 1],
/// as the glTF spec defines them), checked to have one element per vertex of its block.
pub(crate) fn read_varying(
    acc: &gltf::Accessor<'_>,
    buffers: &[Vec<u8>],
    block: usize,
    count: usize,
) -> Result<BlockVarying, MeshError> {
    let width = dims_of(acc.dimensions());
    if acc.count() != count || !(2..=4).contains(&width) {
        return Err(MeshError::parse(
            "glTF",
            format!(
                "accessor {}: a TEXCOORD/COLOR attribute needs VEC2..VEC4 and one element per \
                 POSITION ({count})",
                acc.index()
            ),
        ));
    }
    let values = match layout(acc, buffers)? {
        None => vec![0.0; count * width],
        Some(l) => (0..l.count)
            .flat_map(|i| (0..width).map(move |k| (i, k)))
            .map(|(i, k)| l.get(i, k))
            .collect(),
    };
    Ok(BlockVarying {
        accessor: acc.index(),
        block,
        width,
        values,
    })
}

/// Whether a refined document keeps the attribute `name` (interpolated or recomputed).
fn kept(name: &str) -> bool {
    let numbered = |prefix: &str| {
        name.strip_prefix(prefix)
            .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
    };
    matches!(name, "POSITION" | "NORMAL") || numbered("TEXCOORD_") || numbered("COLOR_")
}

/// The attributes of the triangle primitives named in `src.runs`, by name, first seen first.
fn run_attributes(src: &GltfSource) -> Vec<String> {
    let mut names: Vec<String> = Vec::new();
    for run in &src.runs {
        let attrs = src.json["meshes"][run.mesh]["primitives"][run.primitive]["attributes"]
            .as_object()
            .into_iter()
            .flat_map(|a| a.keys());
        for a in attrs {
            if !names.contains(a) {
                names.push(a.clone());
            }
        }
    }
    names
}

/// What a refined document cannot carry, one sentence each (the job's notes).
pub(crate) fn dropped(src: &GltfSource) -> Vec<String> {
    let names = run_attributes(src);
    let mut notes = Vec::new();
    if names.iter().any(|n| n == "TANGENT") {
        notes.push(
            "refine: TANGENT is not written (tangents follow the new surface; viewers compute \
             MikkTSpace tangents when none are given)"
                .to_owned(),
        );
    }
    let skin: Vec<&str> = names
        .iter()
        .map(String::as_str)
        .filter(|n| n.starts_with("JOINTS_") || n.starts_with("WEIGHTS_"))
        .collect();
    if !skin.is_empty() {
        notes.push(format!(
            "refine: {} dropped and the skin detached from its nodes (a new vertex would need \
             the joints of both ends of its edge, more than a vertex holds)",
            skin.join(", ")
        ));
    }
    let custom: Vec<&str> = names
        .iter()
        .map(String::as_str)
        .filter(|n| !kept(n) && *n != "TANGENT" && !skin.contains(n))
        .collect();
    if !custom.is_empty() {
        notes.push(format!(
            "refine: {} dropped (an application's own attributes have no interpolation rule)",
            custom.join(", ")
        ));
    }
    notes
}

/// Repoints accessor `index` at a tightly packed float32 view of `count` elements of `ty`.
fn repoint_float(
    doc: &mut Value,
    index: usize,
    view: usize,
    count: usize,
    ty: &str,
    min_max: Option<(Value, Value)>,
) -> Result<(), MeshError> {
    repoint_accessor_as(doc, index, view, count, ty, (FLOAT, false), min_max)
}

/// Appends float32 `values` (`width` per element) as a new vertex view; returns the view.
fn push_floats(doc: &mut Value, bin: &mut Vec<u8>, values: &[f64]) -> Result<usize, MeshError> {
    let bytes: Vec<u8> = values
        .iter()
        .flat_map(|&x| (x as f32).to_le_bytes())
        .collect();
    let at = append_aligned(bin, &bytes);
    push_view(doc, at, bytes.len(), ARRAY_BUFFER)
}

/// The split vertices of input block `i` in the order its accessor lists them: the input's,
/// then the new ones (`RefinedSource::old_blocks`).
fn members(
    asset: &Asset,
    r: &RefinedSource,
    i: usize,
) -> Result<(Range<usize>, Range<usize>), MeshError> {
    let old = asset.file.blocks.get(i).ok_or_else(|| malformed("block"))?;
    let new = asset
        .file
        .blocks
        .get(r.old_blocks + i)
        .ok_or_else(|| malformed("refined block"))?;
    Ok((
        old.start..old.start + old.len,
        new.start..new.start + new.len,
    ))
}

/// Writes the refined asset into the input's document (module docs).
pub(crate) fn write(
    asset: &Asset,
    src: &GltfSource,
    r: &RefinedSource,
    positions: &[[f64; 3]],
    glb: bool,
) -> Result<Vec<u8>, MeshError> {
    let (mut doc, mut bin) = merged_document(src)?;
    let mut recompress: Vec<(usize, usize)> = Vec::new();
    let gather = |i: usize, per: &dyn Fn(usize, &mut Vec<f64>)| -> Result<Vec<f64>, MeshError> {
        let (old, new) = members(asset, r, i)?;
        let mut out = Vec::new();
        for sv in old.chain(new) {
            per(sv, &mut out);
        }
        Ok(out)
    };

    let split = asset.split_positions(positions);
    for (i, &acc) in src.position_accessors.iter().enumerate() {
        let values = gather(i, &|sv, out| {
            out.extend(split.get(sv).copied().unwrap_or([0.0; 3]));
        })?;
        let f32s: Vec<[f32; 3]> = values
            .chunks_exact(3)
            .map(|p| [p[0] as f32, p[1] as f32, p[2] as f32])
            .collect();
        let view = push_floats(&mut doc, &mut bin, &values)?;
        if was_compressed(src, acc) {
            super::write::set_stride(&mut doc, view, 12)?;
            recompress.push((view, 12));
        }
        repoint_float(&mut doc, acc, view, f32s.len(), "VEC3", Some(bounds(&f32s)))?;
    }
    if let Some(world) = asset.split_normals_world(positions) {
        for &(acc, bi) in &src.normal_accessors {
            let to_world = asset
                .file
                .blocks
                .get(bi)
                .ok_or_else(|| malformed("block"))?
                .to_world;
            let values = gather(bi, &|sv, out| {
                let n = world.get(sv).copied().unwrap_or([0.0, 0.0, 1.0]);
                out.extend(normalize_or_z(to_world.transpose_apply(n)));
            })?;
            let view = push_floats(&mut doc, &mut bin, &values)?;
            if was_compressed(src, acc) {
                super::write::set_stride(&mut doc, view, 12)?;
                recompress.push((view, 12));
            }
            repoint_float(&mut doc, acc, view, values.len() / 3, "VEC3", None)?;
        }
    }
    for v in &r.varyings {
        let w = v.width;
        let values = gather(v.block, &|sv, out| {
            out.extend(v.values.get(sv * w..(sv + 1) * w).unwrap_or(&[0.0; 4][..w]));
        })?;
        let view = push_floats(&mut doc, &mut bin, &values)?;
        let ty = ["", "", "VEC2", "VEC3", "VEC4"][w];
        repoint_float(&mut doc, v.accessor, view, values.len() / w, ty, None)?;
    }

    // Per primitive (each once, however many nodes draw it): TEXCOORD_0, indices, attributes.
    let mut done: Vec<(usize, usize)> = Vec::new();
    let mut uv_done: Vec<usize> = Vec::new();
    let mut skinned_meshes: Vec<usize> = Vec::new();
    for (run_index, run) in src.runs.iter().enumerate() {
        if done.contains(&(run.mesh, run.primitive)) {
            continue;
        }
        done.push((run.mesh, run.primitive));
        let (old, new) = members(asset, r, run.block)?;
        let local = |sv: usize| -> Result<u32, MeshError> {
            let k = if old.contains(&sv) {
                sv - old.start
            } else if new.contains(&sv) {
                old.len() + sv - new.start
            } else {
                return Err(malformed("a child triangle outside its primitive's block"));
            };
            u32::try_from(k).map_err(|_| MeshError::TooLarge {
                what: "vertices for 32-bit indices",
                value: k,
                limit: u32::MAX as usize,
            })
        };
        let per = 1usize << (2 * r.levels);
        let children = run.triangles.start * per..run.triangles.end * per;
        // Hole patches join the first primitive drawing their block (`filled.rs`).
        let first_of_block = src.runs.iter().position(|x| x.block == run.block) == Some(run_index);
        let patches: Vec<usize> = if first_of_block {
            r.patch_triangles(run.block).collect()
        } else {
            Vec::new()
        };
        let count = children.len() + patches.len();
        let mut index_bytes = Vec::with_capacity(count * 12);
        for c in children.chain(patches) {
            let t = asset
                .file
                .triangles
                .get(c)
                .ok_or_else(|| malformed("triangle"))?;
            let t = if r.flipped.get(r.root(c)).copied().unwrap_or(false) {
                [t[0], t[2], t[1]]
            } else {
                *t
            };
            for sv in t {
                index_bytes.extend_from_slice(&local(sv)?.to_le_bytes());
            }
        }
        let at = append_aligned(&mut bin, &index_bytes);
        let view = push_view(&mut doc, at, index_bytes.len(), ELEMENT_ARRAY_BUFFER)?;
        let accessors = doc
            .get_mut("accessors")
            .and_then(Value::as_array_mut)
            .ok_or_else(|| malformed("accessors"))?;
        accessors.push(json!({"bufferView": view, "componentType": UNSIGNED_INT,
            "count": count * 3, "type": "SCALAR"}));
        let indices = accessors.len() - 1;

        let prim = doc["meshes"][run.mesh]["primitives"][run.primitive]
            .as_object_mut()
            .ok_or_else(|| malformed("primitive"))?;
        prim.insert("indices".into(), json!(indices));
        prim.insert("mode".into(), json!(4));
        let attrs = prim
            .get_mut("attributes")
            .and_then(Value::as_object_mut)
            .ok_or_else(|| malformed("attributes"))?;
        if attrs.keys().any(|k| k.starts_with("JOINTS_")) {
            skinned_meshes.push(run.mesh);
        }
        attrs.retain(|name, _| kept(name));
        let uv = attrs
            .get("TEXCOORD_0")
            .and_then(Value::as_u64)
            .map(|a| a as usize);
        if let (Some(acc), Some(uvs)) = (uv, &asset.file.uvs) {
            if !uv_done.contains(&acc) {
                uv_done.push(acc);
                let values = gather(run.block, &|sv, out| {
                    out.extend(uvs.get(sv).copied().flatten().unwrap_or([0.0; 2]));
                })?;
                let view = push_floats(&mut doc, &mut bin, &values)?;
                repoint_float(&mut doc, acc, view, values.len() / 2, "VEC2", None)?;
            }
        }
    }
    // A node whose mesh lost its joints must not name a skin (glTF 2.0 §3.7.3.3).
    if let Some(nodes) = doc.get_mut("nodes").and_then(Value::as_array_mut) {
        for node in nodes.iter_mut().filter_map(Value::as_object_mut) {
            let mesh = node.get("mesh").and_then(Value::as_u64);
            if mesh.is_some_and(|m| skinned_meshes.contains(&(m as usize))) {
                node.remove("skin");
            }
        }
    }
    finish_document(doc, bin, src, &recompress, glb)
}
