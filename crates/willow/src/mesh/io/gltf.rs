//! glTF 2.0 and GLB.
//!
//! Reading: the GLB container is split here (with checked lengths), the JSON is parsed and
//! index-validated by the `gltf` crate, and buffers are resolved by hand from the BIN chunk or
//! base64 `data:` URIs only. Every buffer view and accessor range is checked against the bytes
//! it lives in, so a lying file is a [`MeshError::TruncatedBuffer`], never a panic.
//!
//! Writing keeps the input document as raw JSON, so extensions and extras this crate does not
//! model survive: all original buffers are concatenated unchanged into one buffer, new
//! POSITION (and NORMAL) data is appended, and those accessors are repointed in place. TANGENT
//! is dropped from the primitives (see `drop_tangents`). Images, samplers, materials, UVs,
//! indices and nodes are untouched.

use super::{
    format_name, normalize_or_z, Affine, Asset, Block, FileGeometry, Format, Limits, MeshError,
};
use base64::Engine as _;
use gltf::accessor::{DataType, Dimensions};
use gltf::mesh::Mode;
use serde_json::{json, Value};
use std::collections::HashMap;

/// Extensions that change how vertex data is stored: reading around them would give garbage.
const REFUSED_EXTENSIONS: [&str; 3] = [
    "KHR_draco_mesh_compression",
    "EXT_meshopt_compression",
    "KHR_mesh_quantization",
];

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
}

/// The JSON and BIN chunks of a GLB, or the whole input as JSON.
fn split_container(bytes: &[u8], format: Format) -> Result<(&[u8], Option<&[u8]>), MeshError> {
    let name = format_name(format);
    if !bytes.starts_with(b"glTF") {
        if format == Format::Glb {
            return Err(MeshError::parse(name, "missing the 'glTF' magic bytes"));
        }
        return Ok((bytes, None));
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

/// Byte layout of one accessor, bounds-checked against its buffer.
struct Layout<'a> {
    data: &'a [u8],
    stride: usize,
    count: usize,
    component: DataType,
    normalized: bool,
}

fn component_size(c: DataType) -> usize {
    match c {
        DataType::I8 | DataType::U8 => 1,
        DataType::I16 | DataType::U16 => 2,
        DataType::U32 | DataType::F32 => 4,
    }
}

fn dims_of(d: Dimensions) -> usize {
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
fn layout<'a>(
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
    fn get(&self, i: usize, k: usize) -> f64 {
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

/// Reads a float VEC3 accessor (POSITION, NORMAL).
fn read_vec3(
    acc: &gltf::Accessor<'_>,
    buffers: &[Vec<u8>],
    what: &str,
) -> Result<Vec<[f64; 3]>, MeshError> {
    if acc.data_type() != DataType::F32 || acc.dimensions() != Dimensions::Vec3 {
        return Err(MeshError::unsupported(format!(
            "{what} accessor {} is not float VEC3",
            acc.index()
        )));
    }
    Ok(match layout(acc, buffers)? {
        None => vec![[0.0; 3]; acc.count()],
        Some(l) => (0..l.count)
            .map(|i| [l.get(i, 0), l.get(i, 1), l.get(i, 2)])
            .collect(),
    })
}

/// Reads TEXCOORD_n: float, or normalized unsigned byte/short.
fn read_uv(acc: &gltf::Accessor<'_>, buffers: &[Vec<u8>]) -> Result<Vec<[f64; 2]>, MeshError> {
    let ok_type = match acc.data_type() {
        DataType::F32 => true,
        DataType::U8 | DataType::U16 => acc.normalized(),
        _ => false,
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

fn read_indices(acc: &gltf::Accessor<'_>, buffers: &[Vec<u8>]) -> Result<Vec<usize>, MeshError> {
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

/// Column-major glTF matrix → [`Affine`].
fn affine_of(node: &gltf::Node<'_>) -> Affine {
    let c = node.transform().matrix();
    let mut m = [[0.0; 3]; 3];
    for (r, row) in m.iter_mut().enumerate() {
        for (k, x) in row.iter_mut().enumerate() {
            *x = c[k][r] as f64;
        }
    }
    Affine {
        m,
        t: [c[3][0] as f64, c[3][1] as f64, c[3][2] as f64],
    }
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
    let json: Value =
        serde_json::from_slice(json_bytes).map_err(|e| MeshError::parse(name, e.to_string()))?;
    // Checked on the raw JSON: the gltf crate refuses unknown required extensions with a
    // generic validation error, and these deserve a precise "unsupported".
    let required = json.get("extensionsRequired").and_then(Value::as_array);
    for ext in required.into_iter().flatten().filter_map(Value::as_str) {
        if REFUSED_EXTENSIONS.contains(&ext) {
            return Err(MeshError::unsupported(format!(
                "required extension {ext} (compressed or quantized vertex data)"
            )));
        }
    }
    check_asset_version(&json)?;
    check_primitive_references(&json)?;
    check_images(&json)?;
    let root = gltf::json::Root::from_slice(json_bytes)
        .map_err(|e| MeshError::parse(name, e.to_string()))?;
    let doc = gltf::Document::from_json(root).map_err(|e| MeshError::parse(name, e.to_string()))?;

    // Resolve buffers: GLB BIN chunk or data: URIs; nothing else is ever opened.
    let mut buffers = Vec::new();
    for b in doc.buffers() {
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
        limits,
        local: Vec::new(),
        blocks: Vec::new(),
        block_of_accessor: HashMap::new(),
        position_accessors: Vec::new(),
        normal_accessors: Vec::new(),
        uvs: Vec::new(),
        normals: Vec::new(),
        triangles: Vec::new(),
        non_triangle_primitives: (0, 0),
        bad_faces: Default::default(),
    };
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
        let world = parent.then_after(&affine_of(&node));
        if let Some(mesh) = node.mesh() {
            for prim in mesh.primitives() {
                b.primitive(&prim, &world, node.index())?;
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
        normal_accessors,
        uvs,
        normals,
        triangles,
        ..
    } = b;
    let uvs = uvs.iter().any(Option::is_some).then_some(uvs);
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
    };
    let src = GltfSource {
        json,
        buffers,
        position_accessors,
        normal_accessors,
    };
    Ok((file, src))
}

/// Accumulates file vertices and triangles while walking the scene.
struct Builder<'a> {
    buffers: &'a [Vec<u8>],
    limits: &'a Limits,
    local: Vec<[f64; 3]>,
    blocks: Vec<Block>,
    block_of_accessor: HashMap<usize, usize>,
    position_accessors: Vec<usize>,
    normal_accessors: Vec<(usize, usize)>,
    uvs: Vec<Option<[f64; 2]>>,
    normals: Vec<Option<[f64; 3]>>,
    triangles: Vec<[usize; 3]>,
    non_triangle_primitives: (usize, usize),
    bad_faces: super::super::error::Offenders<usize>,
}

impl Builder<'_> {
    fn primitive(
        &mut self,
        prim: &gltf::Primitive<'_>,
        world: &Affine,
        node: usize,
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
                let positions = read_vec3(&pos, self.buffers, "POSITION")?;
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
                self.block_of_accessor
                    .insert(pos.index(), self.blocks.len() - 1);
                self.blocks.len() - 1
            }
        };
        let start = self.blocks.get(block).map_or(0, |b| b.start);
        if let Some(uv) = prim.get(&gltf::Semantic::TexCoords(0)) {
            if uv.count() != count {
                return Err(MeshError::parse(
                    "glTF",
                    "TEXCOORD_0 and POSITION counts differ",
                ));
            }
            for (i, v) in read_uv(&uv, self.buffers)?.into_iter().enumerate() {
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
            for (i, v) in read_vec3(&n, self.buffers, "NORMAL")?
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
        Ok(())
    }
}

/// Appends `data` to `bin` at a 4-byte aligned offset; returns the offset.
fn append_aligned(bin: &mut Vec<u8>, data: &[u8]) -> usize {
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let at = bin.len();
    bin.extend_from_slice(data);
    at
}

fn vec3_bytes(values: &[[f32; 3]]) -> Vec<u8> {
    values
        .iter()
        .flatten()
        .flat_map(|x| x.to_le_bytes())
        .collect()
}

/// Component-wise min and max, as JSON arrays (glTF requires them on POSITION).
fn bounds(values: &[[f32; 3]]) -> (Value, Value) {
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

fn malformed(what: &str) -> MeshError {
    MeshError::parse("glTF", format!("cannot rewrite the document: {what}"))
}

/// Repoints accessor `index` at a new tightly packed float VEC3 buffer view.
fn repoint_accessor(
    doc: &mut Value,
    index: usize,
    view: usize,
    count: usize,
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
    acc.insert("componentType".into(), json!(FLOAT));
    acc.insert("type".into(), json!("VEC3"));
    acc.insert("count".into(), json!(count));
    if let Some((lo, hi)) = min_max {
        acc.insert("min".into(), lo);
        acc.insert("max".into(), hi);
    }
    Ok(())
}

fn push_view(
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

/// Per split vertex position in its block's local space, as f32 (glTF stores f32).
fn split_f32(asset: &Asset, positions: &[[f64; 3]]) -> Vec<[f32; 3]> {
    asset
        .split_positions(positions)
        .into_iter()
        .map(|p| p.map(|x| x as f32))
        .collect()
}

/// Removes TANGENT from every primitive and morph target: tangents follow positions, so the
/// stored ones are stale once the surface moves. glTF says viewers compute MikkTSpace tangents
/// when none are given, which is more faithful than a second implementation here (MikkTSpace's
/// exact splitting rules would have to match). The accessors stay (unused, which is valid).
fn drop_tangents(doc: &mut Value) {
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

/// Rewrites the input document with new positions (see the module docs).
pub(crate) fn write_document(
    asset: &Asset,
    src: &GltfSource,
    positions: &[[f64; 3]],
    glb: bool,
) -> Result<Vec<u8>, MeshError> {
    let mut doc = src.json.clone();
    drop_tangents(&mut doc);
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

    let local = split_f32(asset, positions);
    for (&acc, block) in src.position_accessors.iter().zip(&asset.file.blocks) {
        let values = local
            .get(block.start..block.start + block.len)
            .ok_or_else(|| malformed("block out of range"))?;
        let at = append_aligned(&mut bin, &vec3_bytes(values));
        let view = push_view(&mut doc, at, values.len() * 12, ARRAY_BUFFER)?;
        repoint_accessor(&mut doc, acc, view, values.len(), Some(bounds(values)))?;
    }

    if let Some(world_normals) = asset.split_normals_world(positions) {
        for &(acc, bi) in &src.normal_accessors {
            let block = asset
                .file
                .blocks
                .get(bi)
                .ok_or_else(|| malformed("normal block"))?;
            let values: Vec<[f32; 3]> = world_normals
                .get(block.start..block.start + block.len)
                .ok_or_else(|| malformed("normal block out of range"))?
                .iter()
                .map(|&n| normalize_or_z(block.to_world.transpose_apply(n)).map(|x| x as f32))
                .collect();
            let at = append_aligned(&mut bin, &vec3_bytes(&values));
            let view = push_view(&mut doc, at, values.len() * 12, ARRAY_BUFFER)?;
            repoint_accessor(&mut doc, acc, view, values.len(), None)?;
        }
    }

    finish(doc, bin, glb)
}

/// Sets the single buffer and serializes as GLB (BIN chunk) or glTF (base64 data: URI).
fn finish(mut doc: Value, mut bin: Vec<u8>, glb: bool) -> Result<Vec<u8>, MeshError> {
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
        .insert("buffers".into(), json!([buffer]));
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
    let local = split_f32(asset, positions);
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
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": attributes, "indices": indices, "mode": 4}]}],
        "accessors": accessors,
        "bufferViews": views,
    });
    finish(doc, bin, glb)
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
