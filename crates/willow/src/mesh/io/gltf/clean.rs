//! What a written glTF must not carry over from its input (issue 27, item 1): bytes no buffer
//! view describes (the input's meshopt-compressed data once decoded; what is written
//! compressed is encoded anew, see `reencode`), buffer views nothing refers to (a
//! decoded Draco stream, POSITION and NORMAL data that were replaced), and morph targets that
//! no longer fit the faired base shape. Also the notes that tell the job so.

use super::draco::DRACO;
use super::meshopt::MESHOPT;
use super::{malformed, MeshError, MESH_QUANTIZATION};
use serde_json::{json, Value};

/// Extensions whose references to buffer views, if any, are all under a `bufferView` key (or
/// that have none), so unreferenced views can be found and removed safely. A document using
/// anything else keeps its views (an unknown extension may name views under other keys, e.g.
/// `EXT_structural_metadata`'s `values`); only bytes no view covers are dropped then.
const VIEW_SAFE_PREFIXES: [&str; 3] = ["KHR_materials_", "KHR_texture_", "EXT_texture_"];
const VIEW_SAFE: [&str; 3] = [
    MESH_QUANTIZATION,
    "KHR_lights_punctual",
    "EXT_mesh_gpu_instancing",
];

/// What the written document cannot keep of the input as it was, for the job to report
/// (the note on `KHR_mesh_quantization` is `quantize::plan`'s).
pub(super) fn notes(input: &Value) -> Vec<String> {
    let used: Vec<&str> = input
        .get("extensionsUsed")
        .and_then(Value::as_array)
        .into_iter()
        .flatten()
        .filter_map(Value::as_str)
        .collect();
    let mut out = Vec::new();
    for ext in MESHOPT.into_iter().filter(|e| used.contains(e)) {
        out.push(format!(
            "{ext} input: glTF/GLB results keep it for the rewritten POSITION and NORMAL \
             views (re-encoded, mode ATTRIBUTES, filter NONE: a NORMAL stored with the \
             OCTAHEDRAL filter comes back as its plain normalized type); the views the flow \
             does not rewrite (UVs, colours, animation data, indices) are stored decoded"
        ));
    }
    if used.contains(&DRACO) {
        out.push(format!(
            "{DRACO} input: glTF/GLB results store its primitives as plain float32 attributes \
             and uint32 indices (the extension removed), not re-compressed"
        ));
    }
    let (targets, primitives) = morph_target_count(input);
    if targets > 0 {
        out.push(format!(
            "morph targets dropped: {targets} targets on {primitives} primitives (and their \
             weights and weight animations) described offsets from the unfaired shape"
        ));
    }
    out
}

/// Morph targets in the document, and the primitives that have them.
fn morph_target_count(doc: &Value) -> (usize, usize) {
    let prims = doc
        .get("meshes")
        .and_then(Value::as_array)
        .into_iter()
        .flatten()
        .filter_map(|m| m.get("primitives").and_then(Value::as_array))
        .flatten();
    prims
        .filter_map(|p| p.get("targets").and_then(Value::as_array))
        .filter(|t| !t.is_empty())
        .fold((0, 0), |(n, p), t| (n + t.len(), p + 1))
}

/// Removes morph targets: each primitive's `targets`, each mesh's and node's `weights`, and
/// animation channels that drive weights (with animations left without channels). Targets
/// are offsets from the base shape the input had; on the faired shape they would deform it
/// into something neither the artist nor the flow made. Their accessors stay, unused (valid).
pub(super) fn drop_morph_targets(doc: &mut Value) {
    if morph_target_count(doc).0 == 0 {
        return;
    }
    for mesh in doc
        .get_mut("meshes")
        .and_then(Value::as_array_mut)
        .into_iter()
        .flatten()
    {
        let prims = mesh.get_mut("primitives").and_then(Value::as_array_mut);
        for prim in prims.into_iter().flatten().filter_map(Value::as_object_mut) {
            prim.remove("targets");
        }
        if let Some(m) = mesh.as_object_mut() {
            m.remove("weights");
            // three.js and Blender name targets here; without targets the names mean nothing.
            if let Some(extras) = m.get_mut("extras").and_then(Value::as_object_mut) {
                extras.remove("targetNames");
            }
        }
    }
    for node in doc
        .get_mut("nodes")
        .and_then(Value::as_array_mut)
        .into_iter()
        .flatten()
        .filter_map(Value::as_object_mut)
    {
        node.remove("weights");
    }
    if let Some(root) = doc.as_object_mut() {
        if let Some(anims) = root.get_mut("animations").and_then(Value::as_array_mut) {
            for a in anims.iter_mut() {
                if let Some(ch) = a.get_mut("channels").and_then(Value::as_array_mut) {
                    ch.retain(|c| c["target"]["path"].as_str() != Some("weights"));
                }
            }
            // The schema gives `channels` minItems 1. Nothing in core glTF refers to an
            // animation by index, so removing one renumbers nothing.
            anims.retain(|a| a["channels"].as_array().is_some_and(|c| !c.is_empty()));
            if anims.is_empty() {
                root.remove("animations");
            }
        }
    }
}

/// Does every extension the document uses refer to buffer views only under `bufferView`?
fn views_are_all_visible(doc: &Value) -> bool {
    let used = doc.get("extensionsUsed").and_then(Value::as_array);
    used.into_iter().flatten().all(|e| {
        e.as_str().is_some_and(|e| {
            VIEW_SAFE.contains(&e) || VIEW_SAFE_PREFIXES.iter().any(|p| e.starts_with(p))
        })
    })
}

/// Marks every integer under a `bufferView` key anywhere in `v`.
fn mark_views(v: &Value, used: &mut [bool]) {
    match v {
        Value::Object(o) => {
            for (k, x) in o {
                match (k.as_str(), x.as_u64()) {
                    ("bufferView", Some(i)) => {
                        if let Some(u) = usize::try_from(i).ok().and_then(|i| used.get_mut(i)) {
                            *u = true;
                        }
                    }
                    _ => mark_views(x, used),
                }
            }
        }
        Value::Array(a) => a.iter().for_each(|x| mark_views(x, used)),
        _ => {}
    }
}

/// Renumbers every integer under a `bufferView` key through `new_index`.
fn renumber_views(v: &mut Value, new_index: &[Option<usize>]) {
    match v {
        Value::Object(o) => {
            for (k, x) in o.iter_mut() {
                let target = (k == "bufferView")
                    .then(|| x.as_u64())
                    .flatten()
                    .and_then(|i| usize::try_from(i).ok())
                    .and_then(|i| new_index.get(i).copied().flatten());
                match target {
                    Some(n) => *x = json!(n),
                    None => renumber_views(x, new_index),
                }
            }
        }
        Value::Array(a) => a.iter_mut().for_each(|x| renumber_views(x, new_index)),
        _ => {}
    }
}

/// The single buffer `bin` (every view already on buffer 0) rebuilt with only the bytes some
/// kept view covers: views nothing refers to are removed first (when every extension in use
/// is known to name views only under `bufferView`, see [`VIEW_SAFE`]). Each kept run of bytes
/// keeps its offset modulo 4, so every accessor's alignment is what it was.
pub(super) fn compact(doc: &mut Value, bin: &[u8]) -> Result<Vec<u8>, MeshError> {
    let count = doc
        .get("bufferViews")
        .and_then(Value::as_array)
        .map_or(0, Vec::len);
    if views_are_all_visible(doc) {
        let mut used = vec![false; count];
        for (k, v) in doc.as_object().into_iter().flatten() {
            if k != "bufferViews" {
                mark_views(v, &mut used);
            }
        }
        if used.iter().any(|u| !u) {
            let mut next = 0;
            let new_index: Vec<Option<usize>> = used
                .iter()
                .map(|&u| {
                    u.then(|| {
                        next += 1;
                        next - 1
                    })
                })
                .collect();
            if let Some(views) = doc.get_mut("bufferViews").and_then(Value::as_array_mut) {
                let mut i = 0;
                views.retain(|_| {
                    i += 1;
                    used[i - 1]
                });
            }
            if let Some(root) = doc.as_object_mut() {
                for (k, v) in root.iter_mut() {
                    if k != "bufferViews" {
                        renumber_views(v, &new_index);
                    }
                }
            }
        }
    }
    let views = doc
        .get_mut("bufferViews")
        .and_then(Value::as_array_mut)
        .map(std::mem::take)
        .unwrap_or_default();
    // (start, end, view) by start; overlapping views share one run.
    let mut spans = Vec::with_capacity(views.len());
    for (i, v) in views.iter().enumerate() {
        let at = v.get("byteOffset").and_then(Value::as_u64).unwrap_or(0) as usize;
        let len = v.get("byteLength").and_then(Value::as_u64).unwrap_or(0) as usize;
        let end = at
            .checked_add(len)
            .filter(|&e| e <= bin.len())
            .ok_or_else(|| malformed("a buffer view past the end of the buffer"))?;
        spans.push((at, end, i));
    }
    spans.sort_unstable();
    let mut out = Vec::with_capacity(bin.len());
    let mut new_offset = vec![0usize; views.len()];
    let mut run: Option<(usize, usize, usize)> = None; // (old start, old end, new start)
    for &(at, end, i) in &spans {
        let r = match run {
            Some((s, e, n)) if at <= e => {
                if end > e {
                    out.extend_from_slice(&bin[e..end]);
                }
                (s, e.max(end), n)
            }
            _ => {
                while out.len() % 4 != at % 4 {
                    out.push(0);
                }
                let n = out.len();
                out.extend_from_slice(&bin[at..end]);
                (at, end, n)
            }
        };
        new_offset[i] = r.2 + (at - r.0);
        run = Some(r);
    }
    let mut views = views;
    for (v, &o) in views.iter_mut().zip(&new_offset) {
        if let Some(v) = v.as_object_mut() {
            v.insert("byteOffset".into(), json!(o));
        }
    }
    if let Some(root) = doc.as_object_mut() {
        if views.is_empty() {
            root.remove("bufferViews");
        } else {
            root.insert("bufferViews".into(), Value::Array(views));
        }
    }
    Ok(out)
}
