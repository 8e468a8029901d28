//! Reading glTF accessors: the byte layout of an accessor in its buffer view, and positions, UVs and indices read through it; node transforms.

use crate::mesh::io::{Affine, MeshError};
use gltf::accessor::{DataType, Dimensions};

/// Byte layout of one accessor, bounds-checked against its buffer.
pub(super) struct Layout<'a> {
    pub(super) data: &'a [u8],
    pub(super) stride: usize,
    pub(super) count: usize,
    pub(super) component: DataType,
    pub(super) normalized: bool,
}

pub(super) fn component_size(c: DataType) -> usize {
    match c {
        DataType::I8 | DataType::U8 => 1,
        DataType::I16 | DataType::U16 => 2,
        DataType::U32 | DataType::F32 => 4,
    }
}

pub(super) fn dims_of(d: Dimensions) -> usize {
    match d {
        Dimensions::Scalar => 1,
        Dimensions::Vec2 => 2,
        Dimensions::Vec3 => 3,
        Dimensions::Vec4 | Dimensions::Mat2 => 4,
        Dimensions::Mat3 => 9,
        Dimensions::Mat4 => 16,
    }
}

/// The accessor's bytes, or `None` for an accessor without a buffer view (all zeros).
pub(super) fn layout<'a>(
    acc: &gltf::Accessor<'_>,
    buffers: &'a [Vec<u8>],
) -> Result<Option<Layout<'a>>, MeshError> {
    let i = acc.index();
    if acc.sparse().is_some() {
        return Err(MeshError::unsupported(format!("sparse accessor {i}")));
    }
    let Some(view) = acc.view() else {
        return Ok(None);
    };
    let component = acc.data_type();
    let dims = dims_of(acc.dimensions());
    let elem = component_size(component) * dims;
    let stride = view.stride().unwrap_or(elem);
    if stride < elem {
        return Err(MeshError::parse(
            "glTF",
            format!("accessor {i}: byteStride {stride} is smaller than its element ({elem})"),
        ));
    }
    let buffer = buffers.get(view.buffer().index()).ok_or_else(|| {
        MeshError::truncated(format!("buffer view {} has no buffer", view.index()))
    })?;
    let view_bytes = view
        .offset()
        .checked_add(view.length())
        .and_then(|end| buffer.get(view.offset()..end))
        .ok_or_else(|| {
            MeshError::truncated(format!(
                "buffer view {} (bytes {}..+{}) is past the end of buffer {} ({} bytes)",
                view.index(),
                view.offset(),
                view.length(),
                view.buffer().index(),
                buffer.len()
            ))
        })?;
    let count = acc.count();
    let data = if count == 0 {
        &[][..]
    } else {
        let end = (count - 1)
            .checked_mul(stride)
            .and_then(|x| x.checked_add(elem))
            .and_then(|x| x.checked_add(acc.offset()));
        end.and_then(|end| view_bytes.get(acc.offset()..end))
            .ok_or_else(|| {
                MeshError::truncated(format!(
                    "accessor {i} ({count} elements, stride {stride}, offset {}) runs past the end \
                     of buffer view {} ({} bytes)",
                    acc.offset(),
                    view.index(),
                    view.length()
                ))
            })?
    };
    Ok(Some(Layout {
        data,
        stride,
        count,
        component,
        normalized: acc.normalized(),
    }))
}

impl Layout<'_> {
    /// Component `k` of element `i` as f64 (normalized integers mapped to [0, 1] / [-1, 1]).
    pub(super) fn get(&self, i: usize, k: usize) -> f64 {
        let size = component_size(self.component);
        let at = i * self.stride + k * size;
        // In bounds: `layout` checked (count − 1)·stride + elem ≤ data.len(), k < dims.
        let b = &self.data[at..at + size];
        let raw = match self.component {
            DataType::F32 => return f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            DataType::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            DataType::U16 => u16::from_le_bytes([b[0], b[1]]) as f64,
            DataType::I16 => i16::from_le_bytes([b[0], b[1]]) as f64,
            DataType::U8 => b[0] as f64,
            DataType::I8 => b[0] as i8 as f64,
        };
        if !self.normalized {
            return raw;
        }
        match self.component {
            DataType::U8 => raw / 255.0,
            DataType::U16 => raw / 65535.0,
            DataType::I8 => (raw / 127.0).max(-1.0),
            DataType::I16 => (raw / 32767.0).max(-1.0),
            _ => raw,
        }
    }
}

/// A VEC3 vertex attribute.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Attribute {
    Position,
    Normal,
}

/// Reads a VEC3 accessor (POSITION, NORMAL): float, or with `KHR_mesh_quantization` the
/// types that extension allows (POSITION: signed or unsigned byte or short, normalized or
/// not; NORMAL: normalized signed byte or short), dequantized as the glTF spec says
/// (`Layout::get`); the node transforms gltfpack adds then scale them back.
pub(super) fn read_vec3(
    acc: &gltf::Accessor<'_>,
    buffers: &[Vec<u8>],
    what: Attribute,
    quantized: bool,
) -> Result<Vec<[f64; 3]>, MeshError> {
    let quantized_ok = quantized
        && match (what, acc.data_type()) {
            (Attribute::Position, DataType::I8 | DataType::U8 | DataType::I16 | DataType::U16) => {
                true
            }
            (Attribute::Normal, DataType::I8 | DataType::I16) => acc.normalized(),
            _ => false,
        };
    if (acc.data_type() != DataType::F32 && !quantized_ok) || acc.dimensions() != Dimensions::Vec3 {
        let name = match what {
            Attribute::Position => "POSITION",
            Attribute::Normal => "NORMAL",
        };
        return Err(MeshError::unsupported(format!(
            "{name} accessor {} is not float VEC3{}",
            acc.index(),
            if quantized {
                " nor a type KHR_mesh_quantization allows"
            } else {
                " (integer types need KHR_mesh_quantization)"
            }
        )));
    }
    Ok(match layout(acc, buffers)? {
        None => vec![[0.0; 3]; acc.count()],
        Some(l) => (0..l.count)
            .map(|i| [l.get(i, 0), l.get(i, 1), l.get(i, 2)])
            .collect(),
    })
}

/// Reads TEXCOORD_n: float, or normalized unsigned byte/short; with `KHR_mesh_quantization`
/// also signed, and not normalized (a `KHR_texture_transform` then scales them).
pub(super) fn read_uv(
    acc: &gltf::Accessor<'_>,
    buffers: &[Vec<u8>],
    quantized: bool,
) -> Result<Vec<[f64; 2]>, MeshError> {
    let ok_type = match acc.data_type() {
        DataType::F32 => true,
        DataType::U8 | DataType::U16 => acc.normalized() || quantized,
        DataType::I8 | DataType::I16 => quantized,
        DataType::U32 => false,
    };
    if !ok_type || acc.dimensions() != Dimensions::Vec2 {
        return Err(MeshError::unsupported(format!(
            "TEXCOORD accessor {} has an invalid type",
            acc.index()
        )));
    }
    Ok(match layout(acc, buffers)? {
        None => vec![[0.0; 2]; acc.count()],
        Some(l) => (0..l.count).map(|i| [l.get(i, 0), l.get(i, 1)]).collect(),
    })
}

pub(super) fn read_indices(
    acc: &gltf::Accessor<'_>,
    buffers: &[Vec<u8>],
) -> Result<Vec<usize>, MeshError> {
    let ok = matches!(
        acc.data_type(),
        DataType::U8 | DataType::U16 | DataType::U32
    ) && acc.dimensions() == Dimensions::Scalar
        && !acc.normalized();
    if !ok {
        return Err(MeshError::parse(
            "glTF",
            format!(
                "index accessor {} is not an unsigned integer scalar",
                acc.index()
            ),
        ));
    }
    Ok(match layout(acc, buffers)? {
        None => vec![0; acc.count()],
        Some(l) => (0..l.count).map(|i| l.get(i, 0) as usize).collect(),
    })
}

/// A node's local transform as an [`Affine`], read in f64 from the document's JSON: the
/// `gltf` crate hands transforms out in f32, which would snap a map-grid translation (5e6) to
/// a 0.5 grid. `matrix` (column-major) if given, else T·R·S from `translation`, `rotation`
/// (unit quaternion x, y, z, w) and `scale`, as the glTF spec defines them.
pub(super) fn affine_of(node: &gltf::Node<'_>, json: &serde_json::Value) -> Affine {
    node_affine(json, node.index())
}

/// [`affine_of`] for node number `node` of the raw JSON (identity if there is no such node).
pub(super) fn node_affine(json: &serde_json::Value, node: usize) -> Affine {
    let raw = &json["nodes"][node];
    let numbers = |key: &str, n: usize| -> Option<Vec<f64>> {
        let v: Vec<f64> = raw
            .get(key)?
            .as_array()?
            .iter()
            .filter_map(|x| x.as_f64())
            .collect();
        (v.len() == n).then_some(v)
    };
    if let Some(c) = numbers("matrix", 16) {
        let mut m = [[0.0; 3]; 3];
        for (r, row) in m.iter_mut().enumerate() {
            for (k, x) in row.iter_mut().enumerate() {
                *x = c[4 * k + r];
            }
        }
        return Affine {
            m,
            t: [c[12], c[13], c[14]],
        };
    }
    let t = numbers("translation", 3).unwrap_or(vec![0.0; 3]);
    let q = numbers("rotation", 4).unwrap_or(vec![0.0, 0.0, 0.0, 1.0]);
    let s = numbers("scale", 3).unwrap_or(vec![1.0; 3]);
    let (x, y, z, w) = (q[0], q[1], q[2], q[3]);
    let r = [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - z * w),
            2.0 * (x * z + y * w),
        ],
        [
            2.0 * (x * y + z * w),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - x * w),
        ],
        [
            2.0 * (x * z - y * w),
            2.0 * (y * z + x * w),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ];
    let mut m = [[0.0; 3]; 3];
    for (i, row) in m.iter_mut().enumerate() {
        for (k, v) in row.iter_mut().enumerate() {
            *v = r[i][k] * s[k];
        }
    }
    Affine {
        m,
        t: [t[0], t[1], t[2]],
    }
}
