//! Writing a `KHR_mesh_quantization` input back quantized (issue 27, item 1): POSITION
//! re-quantized to the input's own component type and normalization over the faired
//! surface's box, with the mesh node's transform updated to dequantize it, and quantized
//! NORMAL re-quantized to its own type.
//!
//! gltfpack stores positions as integers in [0, 2^bits) and puts the dequantization (a uniform
//! scale and a translation) on the node drawing the mesh. The faired surface may leave the
//! input's box, so the box and the node's transform are recomputed from the new positions.
//! That is sound only where the node's transform moves nothing else: a node with one mesh
//! drawn by no other node, no children, camera, skin, extension or animation of its
//! transform, and a mesh whose every POSITION accessor is its own. Elsewhere POSITION is
//! written as float32 in the node's unchanged space, and the job's note says where.

use super::accessors::component_size;
use super::{malformed, MeshError, FLOAT, MESH_QUANTIZATION};
use crate::mesh::io::Affine;
use gltf::accessor::DataType;
use serde_json::{json, Value};
use std::collections::BTreeMap;

/// The integer grid of one node's POSITION data: its component type, normalization, and the
/// integer range the input used (gltfpack's `-vp` bits), which the output uses too.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Grid {
    pub(super) component: DataType,
    pub(super) normalized: bool,
    pub(super) lo: i64,
    pub(super) hi: i64,
}

/// A node whose POSITION blocks are written re-quantized, with its transform updated.
#[derive(Clone, Debug)]
pub(super) struct Requantize {
    pub(super) node: usize,
    /// Blocks (see `FileGeometry::blocks`), which are this node's mesh's POSITION accessors.
    pub(super) blocks: Vec<usize>,
    pub(super) grid: Grid,
}

/// The divisor of a normalized integer type (glTF 2.0 §3.11, "Animations"/"Meshes":
/// `f = max(c / M, -1)`), or 1 for a type read as it is.
pub(super) fn divisor(component: DataType, normalized: bool) -> f64 {
    match (normalized, component) {
        (false, _) => 1.0,
        (true, DataType::U8) => 255.0,
        (true, DataType::U16) => 65535.0,
        (true, DataType::I8) => 127.0,
        (true, DataType::I16) => 32767.0,
        (true, _) => 1.0,
    }
}

/// The values a component type can hold (a normalized signed type without its minimum, which
/// means the same as minimum + 1).
fn type_range(component: DataType, normalized: bool) -> (i64, i64) {
    match component {
        DataType::U8 => (0, 255),
        DataType::U16 => (0, 65535),
        DataType::I8 => (if normalized { -127 } else { -128 }, 127),
        DataType::I16 => (if normalized { -32767 } else { -32768 }, 32767),
        DataType::U32 | DataType::F32 => (0, 0),
    }
}

fn data_type(code: u64) -> Option<DataType> {
    Some(match code {
        5120 => DataType::I8,
        5121 => DataType::U8,
        5122 => DataType::I16,
        5123 => DataType::U16,
        5125 => DataType::U32,
        5126 => DataType::F32,
        _ => return None,
    })
}

fn type_name(c: DataType) -> &'static str {
    match c {
        DataType::I8 => "byte",
        DataType::U8 => "unsigned byte",
        DataType::I16 => "short",
        DataType::U16 => "unsigned short",
        DataType::U32 => "unsigned int",
        DataType::F32 => "float",
    }
}

/// An accessor's component type and normalization, as the JSON says.
pub(super) fn accessor_type(json: &Value, acc: usize) -> Option<(DataType, bool)> {
    let a = json.get("accessors")?.get(acc)?;
    let c = data_type(a.get("componentType")?.as_u64()?)?;
    Some((
        c,
        a.get("normalized").and_then(Value::as_bool) == Some(true),
    ))
}

/// Why re-quantizing the POSITION of `node` (drawing `mesh`) would change something else, or
/// `None` when it would not (see the module docs).
fn unsound(json: &Value, node: usize, mesh: usize) -> Option<String> {
    let nodes = json.get("nodes").and_then(Value::as_array)?;
    let drawn_by = nodes
        .iter()
        .filter(|n| n.get("mesh").and_then(Value::as_u64) == Some(mesh as u64))
        .count();
    if drawn_by != 1 {
        return Some(format!("mesh {mesh} is drawn by {drawn_by} nodes"));
    }
    let n = nodes.get(node)?;
    for (key, what) in [
        ("children", "children"),
        ("camera", "a camera"),
        ("skin", "a skin"),
        ("extensions", "extensions"),
    ] {
        let present = n.get(key).is_some_and(|v| match v {
            Value::Array(a) => !a.is_empty(),
            Value::Object(o) => !o.is_empty(),
            _ => true,
        });
        if present {
            return Some(format!("node {node} has {what}"));
        }
    }
    let animations = json.get("animations").and_then(Value::as_array);
    let animated = animations
        .into_iter()
        .flatten()
        .filter_map(|a| a.get("channels").and_then(Value::as_array))
        .flatten()
        .any(|c| {
            c["target"]["node"].as_u64() == Some(node as u64)
                && c["target"]["path"].as_str() != Some("weights")
        });
    if animated {
        return Some(format!("node {node}'s transform is animated"));
    }
    None
}

/// Every (mesh, primitive's POSITION accessor) in the document.
fn position_uses(json: &Value) -> Vec<(usize, u64)> {
    let meshes = json.get("meshes").and_then(Value::as_array);
    let mut out = Vec::new();
    for (m, mesh) in meshes.into_iter().flatten().enumerate() {
        let prims = mesh.get("primitives").and_then(Value::as_array);
        for p in prims.into_iter().flatten() {
            if let Some(a) = p["attributes"]["POSITION"].as_u64() {
                out.push((m, a));
            }
        }
    }
    out
}

/// Which nodes get their POSITION re-quantized, and the job's note on what is written.
///
/// `blocks[i]` is (POSITION accessor, node that drew it, its values as read) for block `i`.
pub(super) fn plan(
    json: &Value,
    blocks: &[(usize, usize, &[[f64; 3]])],
    normal_accessors: &[(usize, usize)],
) -> (Vec<Requantize>, Option<String>) {
    let used = json.get("extensionsUsed").and_then(Value::as_array);
    if !used.into_iter().flatten().any(|e| e == MESH_QUANTIZATION) {
        return (Vec::new(), None);
    }
    let uses = position_uses(json);
    let pointers = used
        .into_iter()
        .flatten()
        .any(|e| e == "KHR_animation_pointer");
    let mut by_node: BTreeMap<usize, (usize, Vec<usize>)> = BTreeMap::new();
    let mut floats: Vec<String> = Vec::new();
    for (bi, &(acc, node, _)) in blocks.iter().enumerate() {
        if accessor_type(json, acc).is_none_or(|(c, _)| c == DataType::F32) {
            continue; // float POSITION stays float: nothing to keep
        }
        let meshes: Vec<usize> = uses
            .iter()
            .filter(|&&(_, a)| a == acc as u64)
            .map(|&(m, _)| m)
            .collect();
        let Some(&mesh) = meshes.first() else {
            continue; // not reached: the block was read from a primitive of some mesh
        };
        let why = if meshes.iter().any(|&m| m != mesh) {
            Some(format!(
                "POSITION accessor {acc} is shared by several meshes"
            ))
        } else if pointers {
            Some("KHR_animation_pointer may animate any node".to_string())
        } else {
            unsound(json, node, mesh)
        };
        match why {
            Some(why) => floats.push(format!("mesh {mesh} ({why})")),
            None => by_node.entry(node).or_insert((mesh, Vec::new())).1.push(bi),
        }
    }
    let mut plans = Vec::new();
    for (node, (mesh, group)) in by_node {
        let accs: Vec<usize> = group.iter().map(|&bi| blocks[bi].0).collect();
        let types: Vec<_> = accs.iter().map(|&a| accessor_type(json, a)).collect();
        let why = if uses
            .iter()
            .any(|&(m, a)| m == mesh && !accs.iter().any(|&x| x as u64 == a))
        {
            Some("some of its primitives are points, lines or float POSITION")
        } else if types.iter().any(|t| *t != types[0]) {
            Some("its primitives' POSITION types differ")
        } else {
            None
        };
        match (why, types.first().copied().flatten()) {
            (None, Some((component, normalized))) => {
                let values = group.iter().flat_map(|&bi| blocks[bi].2.iter());
                let grid = input_grid(component, normalized, values);
                plans.push(Requantize {
                    node,
                    blocks: group,
                    grid,
                });
            }
            (why, _) => floats.push(format!(
                "mesh {mesh} ({})",
                why.unwrap_or("unknown POSITION type")
            )),
        }
    }
    let normals_quantized = normal_accessors
        .iter()
        .any(|&(a, _)| accessor_type(json, a).is_some_and(|(c, _)| c != DataType::F32));
    let mut note = format!("{MESH_QUANTIZATION} input: glTF/GLB results keep it");
    let kept: Vec<String> = plans
        .iter()
        .map(|p| {
            let bits = ((p.grid.hi - p.grid.lo) as f64 + 1.0).log2().ceil();
            format!(
                "{}{} over {bits} bits (node {})",
                if p.grid.normalized { "normalized " } else { "" },
                type_name(p.grid.component),
                p.node
            )
        })
        .collect();
    if !kept.is_empty() {
        note += &format!(
            "; POSITION re-quantized to its own type ({}) over the faired surface's box, the \
             node's translation and scale updated to dequantize it",
            kept.join(", ")
        );
    }
    if !floats.is_empty() {
        note += &format!(
            "; POSITION stored as float32 in the node's unchanged space where a new node \
             transform would move something else: {}",
            floats.join(", ")
        );
    }
    if normals_quantized {
        note += "; NORMAL re-quantized to its own type";
    }
    note += "; other attributes kept as they were";
    (plans, Some(note))
}

/// The grid the input used: its type and the integer range its values span.
fn input_grid<'a>(
    component: DataType,
    normalized: bool,
    values: impl Iterator<Item = &'a [f64; 3]>,
) -> Grid {
    let d = divisor(component, normalized);
    let (mut lo, mut hi) = (i64::MAX, i64::MIN);
    for v in values.flatten() {
        let q = (v * d).round() as i64;
        lo = lo.min(q);
        hi = hi.max(q);
    }
    if lo >= hi {
        // One value (or none): nothing says which range was meant; use the whole type.
        (lo, hi) = type_range(component, normalized);
    }
    Grid {
        component,
        normalized,
        lo,
        hi,
    }
}

/// Positions (in the node's old local space) quantized onto `grid`, and the map `A` from the
/// new dequantized values to the old local space (`old = A(d(q))`, a uniform scale and a
/// translation, so normals keep their meaning): `q = lo + round((p − box_min) / h)` with one
/// step `h = (largest box side) / (hi − lo)`, so every position fits and rounding moves it at
/// most h/2 along each axis.
pub(super) fn quantize(grid: Grid, positions: &[[f64; 3]]) -> (Vec<[i64; 3]>, Affine) {
    let mut bmin = [f64::INFINITY; 3];
    let mut bmax = [f64::NEG_INFINITY; 3];
    for p in positions {
        for k in 0..3 {
            bmin[k] = bmin[k].min(p[k]);
            bmax[k] = bmax[k].max(p[k]);
        }
    }
    let side = (0..3).map(|k| bmax[k] - bmin[k]).fold(0.0, f64::max);
    let levels = (grid.hi - grid.lo) as f64;
    let h = if side > 0.0 && side.is_finite() {
        side / levels
    } else {
        1.0 // every position is the same: any step represents it exactly
    };
    let bmin = bmin.map(|x| if x.is_finite() { x } else { 0.0 });
    let q = positions
        .iter()
        .map(|p| {
            [0, 1, 2].map(|k| {
                let steps = ((p[k] - bmin[k]) / h).round();
                (grid.lo + steps as i64).clamp(grid.lo, grid.hi)
            })
        })
        .collect();
    let a = h * divisor(grid.component, grid.normalized);
    let map = Affine {
        m: [[a, 0.0, 0.0], [0.0, a, 0.0], [0.0, 0.0, a]],
        t: [0, 1, 2].map(|k| bmin[k] - grid.lo as f64 * h),
    };
    (q, map)
}

/// A unit normal on a normalized signed grid (`KHR_mesh_quantization` allows byte and short).
pub(super) fn quantize_normal(component: DataType, n: [f64; 3]) -> [i64; 3] {
    let m = divisor(component, true);
    n.map(|x| (x * m).round().clamp(-m, m) as i64)
}

/// Little-endian bytes of `values` in `component`, each element padded to a multiple of 4
/// bytes (vertex attributes must be 4-byte aligned); returns (bytes, stride).
pub(super) fn element_bytes(component: DataType, values: &[[i64; 3]]) -> (Vec<u8>, usize) {
    let size = component_size(component);
    let stride = (3 * size).next_multiple_of(4);
    let mut out = Vec::with_capacity(values.len() * stride);
    for v in values {
        for &x in v {
            match component {
                DataType::I8 | DataType::U8 => out.push(x as u8),
                _ => out.extend_from_slice(&(x as u16).to_le_bytes()),
            }
        }
        out.resize(out.len() + stride - 3 * size, 0);
    }
    (out, stride)
}

/// The glTF code of a component type.
pub(super) fn code(c: DataType) -> u32 {
    match c {
        DataType::I8 => 5120,
        DataType::U8 => 5121,
        DataType::I16 => 5122,
        DataType::U16 => 5123,
        DataType::U32 => 5125,
        DataType::F32 => FLOAT,
    }
}

/// Sets node `node`'s transform to `local ∘ map` (`local` its transform as read): a new
/// matrix if it had one, else a new translation and scale (`map` is a uniform scale and a
/// translation, so T·R·S·A = T′·R·S′ with T′ = local(A.t), S′ = S·a).
pub(super) fn update_node(
    doc: &mut Value,
    node: usize,
    local: &Affine,
    map: &Affine,
) -> Result<(), MeshError> {
    let n = doc
        .get_mut("nodes")
        .and_then(|n| n.get_mut(node))
        .and_then(Value::as_object_mut)
        .ok_or_else(|| malformed("missing node"))?;
    let a = map.m[0][0];
    if n.contains_key("matrix") {
        let m = local.then_after(map);
        let mut c = vec![0.0; 16];
        for r in 0..3 {
            for k in 0..3 {
                c[4 * k + r] = m.m[r][k];
            }
            c[12 + r] = m.t[r];
        }
        c[15] = 1.0;
        n.insert("matrix".into(), json!(c));
    } else {
        let s: Vec<f64> = match n.get("scale").and_then(Value::as_array) {
            Some(s) => s.iter().filter_map(Value::as_f64).collect(),
            None => vec![1.0; 3],
        };
        if s.len() != 3 {
            return Err(malformed("node scale"));
        }
        n.insert("translation".into(), json!(local.apply(map.t)));
        n.insert(
            "scale".into(),
            json!(s.iter().map(|x| x * a).collect::<Vec<_>>()),
        );
    }
    Ok(())
}
