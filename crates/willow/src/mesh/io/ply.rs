//! PLY (the Stanford polygon file): ASCII, binary little-endian and binary big-endian.
//!
//! The file's vertices are the `vertex` element's records, in order; faces are the `face`
//! element's `vertex_indices` (or `vertex_index`) lists, fan-triangulated. Per-vertex normals
//! (`nx ny nz`) and UVs (`s t`, `u v`, `texture_u texture_v`) are read; colours and every
//! other property and element are not needed by the flow and are kept byte for byte: writing
//! back copies the file and overwrites only `x y z` (in their declared type) and `nx ny nz`
//! (recomputed) of each vertex record, so a scanner's colours, confidences and custom
//! properties survive, as do comments, element order and face records.
//!
//! Hand-written rather than with `ply-rs`: that crate parses every record into a map of
//! property names (far too heavy for 5M-vertex scans), has no byte offsets to write back
//! into, and has not been released since 2020.

use super::text::{coordinate, splice, utf8, Words};
use super::{Asset, FileGeometry, Limits, MeshError};
use std::collections::HashMap;
use std::fmt::Write as _;

const FORMAT: &str = "PLY";

/// A PLY scalar type.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    /// The type of a name, in both the original (`uchar`) and the sized (`uint8`) spelling.
    fn parse(name: &str) -> Option<Scalar> {
        Some(match name {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    fn is_float(self) -> bool {
        matches!(self, Scalar::F32 | Scalar::F64)
    }

    /// The value at `bytes[at..]`, or `None` past the end.
    fn read(self, bytes: &[u8], at: usize, big: bool) -> Option<f64> {
        let b = bytes.get(at..at.checked_add(self.size())?)?;
        macro_rules! get {
            ($t:ty) => {{
                let arr = b.try_into().ok()?;
                if big {
                    <$t>::from_be_bytes(arr)
                } else {
                    <$t>::from_le_bytes(arr)
                }
            }};
        }
        Some(match self {
            Scalar::I8 => f64::from(get!(i8)),
            Scalar::U8 => f64::from(get!(u8)),
            Scalar::I16 => f64::from(get!(i16)),
            Scalar::U16 => f64::from(get!(u16)),
            Scalar::I32 => f64::from(get!(i32)),
            Scalar::U32 => f64::from(get!(u32)),
            Scalar::F32 => f64::from(get!(f32)),
            Scalar::F64 => get!(f64),
        })
    }

    /// Overwrites the float at `out[at..]` with `x` (only float types are ever written).
    fn write(self, out: &mut [u8], at: usize, big: bool, x: f64) {
        let bytes: Vec<u8> = match (self, big) {
            (Scalar::F64, false) => x.to_le_bytes().to_vec(),
            (Scalar::F64, true) => x.to_be_bytes().to_vec(),
            (_, false) => (x as f32).to_le_bytes().to_vec(),
            (_, true) => (x as f32).to_be_bytes().to_vec(),
        };
        if let Some(slot) = out.get_mut(at..at + bytes.len()) {
            slot.copy_from_slice(&bytes);
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Scalar(Scalar),
    /// A list: the type of its length, then of its items.
    List(Scalar, Scalar),
}

#[derive(Clone, Debug)]
struct Property {
    name: String,
    kind: Kind,
}

#[derive(Clone, Debug)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Property>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Encoding {
    Ascii,
    Binary { big: bool },
}

/// What a PLY file has beyond the surface: its bytes and where each vertex record starts.
#[derive(Clone, Debug)]
pub(crate) struct PlySource {
    bytes: Vec<u8>,
    encoding: Encoding,
    vertex_props: Vec<Property>,
    /// Byte offset of each vertex record.
    records: Vec<usize>,
    /// Property indices of x, y, z.
    xyz: [usize; 3],
    /// Property indices of nx, ny, nz, when the file has normals.
    normals: Option<[usize; 3]>,
}

fn header_error(line: usize, what: &str) -> MeshError {
    MeshError::parse(FORMAT, format!("header line {}: {what}", line + 1))
}

/// The parsed header and the byte offset where the body starts.
fn read_header(bytes: &[u8]) -> Result<(Encoding, Vec<Element>, usize), MeshError> {
    if !bytes.starts_with(b"ply") {
        return Err(match super::foreign_content(bytes) {
            Some(what) => MeshError::parse(FORMAT, format!("this is {what}, not a PLY file")),
            None => MeshError::parse(FORMAT, "missing the `ply` magic word on the first line"),
        });
    }
    let mut at = 0usize;
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    for line_no in 0.. {
        let Some(len) = bytes
            .get(at..)
            .and_then(|b| b.iter().position(|&c| c == b'\n'))
        else {
            return Err(header_error(line_no, "the file ends before `end_header`"));
        };
        let raw = bytes.get(at..at + len).unwrap_or(&[]);
        at += len + 1;
        let line = std::str::from_utf8(raw)
            .map_err(|_| header_error(line_no, "not ASCII text"))?
            .trim_end_matches('\r');
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["ply"] if line_no == 0 => {}
            _ if line_no == 0 => return Err(header_error(0, "expected `ply`")),
            ["format", f, version] => {
                if !version.starts_with('1') {
                    return Err(header_error(line_no, &format!("format version {version}")));
                }
                encoding = Some(match *f {
                    "ascii" => Encoding::Ascii,
                    "binary_little_endian" => Encoding::Binary { big: false },
                    "binary_big_endian" => Encoding::Binary { big: true },
                    other => {
                        return Err(header_error(line_no, &format!("unknown format {other:?}")))
                    }
                });
            }
            ["comment", ..] | ["obj_info", ..] | [] => {}
            ["element", name, count] => {
                let count = count
                    .parse()
                    .map_err(|_| header_error(line_no, &format!("bad element count {count:?}")))?;
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    props: Vec::new(),
                });
            }
            ["property", rest @ ..] => {
                let element = elements
                    .last_mut()
                    .ok_or_else(|| header_error(line_no, "a property before any element"))?;
                let ty = |name: &str| {
                    Scalar::parse(name)
                        .ok_or_else(|| header_error(line_no, &format!("unknown type {name:?}")))
                };
                let (kind, name) = match rest {
                    ["list", count, item, name] => (Kind::List(ty(count)?, ty(item)?), name),
                    [t, name] => (Kind::Scalar(ty(t)?), name),
                    _ => return Err(header_error(line_no, "malformed property")),
                };
                if let Kind::List(c, _) = kind {
                    if c.is_float() {
                        return Err(header_error(line_no, "a list length of float type"));
                    }
                }
                element.props.push(Property {
                    name: name.to_string(),
                    kind,
                });
            }
            ["end_header"] => break,
            _ => return Err(header_error(line_no, &format!("unexpected {line:?}"))),
        }
    }
    let encoding = encoding.ok_or_else(|| MeshError::parse(FORMAT, "no `format` line"))?;
    Ok((encoding, elements, at))
}

/// Reads the body record by record: values come out as f64 (integers are exact in f64).
enum Body<'a> {
    Ascii(Words<'a>),
    Binary {
        bytes: &'a [u8],
        at: usize,
        big: bool,
    },
}

impl Body<'_> {
    fn offset(&self) -> usize {
        match self {
            Body::Ascii(w) => w.offset(),
            Body::Binary { at, .. } => *at,
        }
    }

    fn value(&mut self, ty: Scalar, element: &str, record: usize) -> Result<f64, MeshError> {
        let short = || {
            MeshError::truncated(format!(
                "PLY body ends inside {element} {record} (the header declares more)"
            ))
        };
        match self {
            Body::Ascii(words) => {
                let (line, _, w) = words.next().ok_or_else(short)?;
                w.parse().map_err(|_| {
                    MeshError::parse(
                        FORMAT,
                        format!(
                            "{element} {record} (body line {}): bad number {w:?}",
                            line + 1
                        ),
                    )
                })
            }
            Body::Binary { bytes, at, big } => {
                let x = ty.read(bytes, *at, *big).ok_or_else(short)?;
                *at += ty.size();
                Ok(x)
            }
        }
    }

    /// Reads one record, calling `each(property, values)` (one value for a scalar).
    fn record(
        &mut self,
        element: &Element,
        index: usize,
        values: &mut Vec<f64>,
        mut each: impl FnMut(usize, &[f64]) -> Result<(), MeshError>,
    ) -> Result<(), MeshError> {
        for (p, prop) in element.props.iter().enumerate() {
            values.clear();
            match prop.kind {
                Kind::Scalar(t) => values.push(self.value(t, &element.name, index)?),
                Kind::List(c, t) => {
                    let n = self.value(c, &element.name, index)?;
                    if !(0.0..=1e6).contains(&n) || n.fract() != 0.0 {
                        return Err(MeshError::parse(
                            FORMAT,
                            format!("{} {index}: list length {n}", element.name),
                        ));
                    }
                    for _ in 0..n as usize {
                        values.push(self.value(t, &element.name, index)?);
                    }
                }
            }
            each(p, values)?;
        }
        Ok(())
    }
}

/// The index of the first property named one of `names`.
fn find(props: &[Property], names: &[&str]) -> Option<usize> {
    props.iter().position(|p| names.contains(&p.name.as_str()))
}

pub(crate) fn read(bytes: &[u8], limits: &Limits) -> Result<(FileGeometry, PlySource), MeshError> {
    let (encoding, elements, body_at) = read_header(bytes)?;
    let vertex = elements
        .iter()
        .find(|e| e.name == "vertex")
        .ok_or_else(|| MeshError::parse(FORMAT, "no `vertex` element"))?;
    limits.check_vertices(vertex.count)?;
    let props = &vertex.props;
    let axis = |n: &str| {
        let i = find(props, &[n]).ok_or_else(|| {
            MeshError::parse(FORMAT, format!("the vertex element has no `{n}` property"))
        })?;
        match props[i].kind {
            Kind::Scalar(t) if t.is_float() => Ok(i),
            _ => Err(MeshError::unsupported(format!(
                "PLY vertex property `{n}` is not float or double: integer coordinates cannot \
                 hold faired positions"
            ))),
        }
    };
    let xyz = [axis("x")?, axis("y")?, axis("z")?];
    let float_prop = |n: &str| {
        find(props, &[n]).filter(|&i| matches!(props[i].kind, Kind::Scalar(t) if t.is_float()))
    };
    let normals = match (float_prop("nx"), float_prop("ny"), float_prop("nz")) {
        (Some(a), Some(b), Some(c)) => Some([a, b, c]),
        _ => None,
    };
    let uv = [
        ("s", "t"),
        ("u", "v"),
        ("texture_u", "texture_v"),
        ("texture_s", "texture_t"),
    ]
    .into_iter()
    .find_map(|(u, v)| Some([float_prop(u)?, float_prop(v)?]));
    let faces_total = elements
        .iter()
        .find(|e| e.name == "face")
        .map_or(0, |e| e.count);
    limits.check_faces(faces_total)?;
    // Each record takes at least a byte: a header claiming more records than the body has
    // bytes is refused before anything is allocated for them.
    let declared: usize = elements
        .iter()
        .map(|e| e.count)
        .fold(0, usize::saturating_add);
    if declared > bytes.len() {
        return Err(MeshError::truncated(format!(
            "the PLY header declares {declared} records but the file has {} bytes",
            bytes.len()
        )));
    }

    let mut body = match encoding {
        Encoding::Ascii => {
            let text = utf8(bytes, FORMAT)?;
            Body::Ascii(Words::new(text, body_at))
        }
        Encoding::Binary { big } => Body::Binary {
            bytes,
            at: body_at,
            big,
        },
    };
    let mut local: Vec<[f64; 3]> = Vec::new();
    let mut records: Vec<usize> = Vec::new();
    let mut normal_values: Vec<[f64; 3]> = Vec::new();
    let mut uvs: Vec<Option<[f64; 2]>> = Vec::new();
    let mut triangles: Vec<[usize; 3]> = Vec::new();
    let mut face_of_triangle: Vec<u32> = Vec::new();
    let mut bad_faces = super::super::error::Offenders::default();
    let mut short_faces = super::super::error::Offenders::default();
    let mut non_finite = super::super::error::Offenders::default();
    let mut faces_seen = false;
    let mut values = Vec::new();
    for element in &elements {
        if element.name == "vertex" && records.is_empty() {
            local.reserve_exact(element.count);
            records.reserve_exact(element.count);
            for i in 0..element.count {
                records.push(body.offset());
                let (mut p, mut n, mut t) = ([0.0; 3], [0.0; 3], [0.0; 2]);
                body.record(element, i, &mut values, |k, v| {
                    let x = v.first().copied().unwrap_or(0.0);
                    for a in 0..3 {
                        if xyz[a] == k {
                            p[a] = x;
                        }
                        if normals.is_some_and(|nn| nn[a] == k) {
                            n[a] = x;
                        }
                    }
                    for a in 0..2 {
                        if uv.is_some_and(|uu| uu[a] == k) {
                            t[a] = x;
                        }
                    }
                    Ok(())
                })?;
                if !p.iter().all(|x| x.is_finite()) {
                    non_finite.push(i);
                }
                local.push(p);
                if normals.is_some() {
                    normal_values.push(n);
                }
                if uv.is_some() {
                    // PLY UVs have their origin at the bottom left, as OBJ's; glTF's is the
                    // top left.
                    uvs.push(Some([t[0], 1.0 - t[1]]));
                }
            }
        } else if element.name == "face" && !faces_seen {
            faces_seen = true;
            let list = find(&element.props, &["vertex_indices", "vertex_index"])
                .filter(|&i| matches!(element.props[i].kind, Kind::List(..)))
                .ok_or_else(|| {
                    MeshError::parse(FORMAT, "the face element has no `vertex_indices` list")
                })?;
            let n_vertices = vertex.count;
            for f in 0..element.count {
                body.record(element, f, &mut values, |k, v| {
                    if k != list {
                        return Ok(());
                    }
                    if v.len() < 3 {
                        short_faces.push(f);
                        return Ok(());
                    }
                    let ok = v
                        .iter()
                        .all(|&i| i >= 0.0 && i.fract() == 0.0 && (i as usize) < n_vertices);
                    if !ok {
                        bad_faces.push(f);
                        return Ok(());
                    }
                    limits.check_faces(triangles.len() + v.len() - 2)?;
                    for j in 1..v.len() - 1 {
                        triangles.push([v[0] as usize, v[j] as usize, v[j + 1] as usize]);
                        face_of_triangle.push(f as u32);
                    }
                    Ok(())
                })?;
            }
        } else {
            for r in 0..element.count {
                body.record(element, r, &mut values, |_, _| Ok(()))?;
            }
        }
    }
    if !short_faces.is_empty() {
        return Err(MeshError::parse(
            FORMAT,
            format!(
                "{} faces have fewer than 3 vertices; first (face numbers): {}",
                short_faces.count, short_faces
            ),
        ));
    }
    if !bad_faces.is_empty() {
        return Err(MeshError::IndexOutOfRange {
            faces: bad_faces,
            vertex_count: vertex.count,
        });
    }
    if !non_finite.is_empty() {
        return Err(MeshError::NonFinite {
            vertices: non_finite,
        });
    }
    if triangles.is_empty() {
        return Err(MeshError::PointsOrLinesOnly {
            points: vertex.count,
            lines: 0,
        });
    }
    let normal_keys = normals.map(|_| {
        let mut ids: HashMap<[u64; 3], u64> = HashMap::new();
        normal_values
            .iter()
            .map(|n| {
                let next = ids.len() as u64;
                *ids.entry(n.map(f64::to_bits)).or_insert(next)
            })
            .collect()
    });
    let file = FileGeometry {
        uvs: uv.map(|_| uvs),
        normal_keys,
        face_of_triangle: Some(face_of_triangle),
        ..FileGeometry::one_block(local, triangles)
    };
    let src = PlySource {
        bytes: bytes.to_vec(),
        encoding,
        vertex_props: vertex.props.clone(),
        records,
        xyz,
        normals,
    };
    Ok((file, src))
}

/// Writes the user's PLY back: the same bytes with each vertex's `x y z` replaced (in the
/// declared float type) and `nx ny nz` recomputed; everything else is copied.
pub(crate) fn write_kept(
    asset: &Asset,
    src: &PlySource,
    positions: &[[f64; 3]],
) -> Result<Vec<u8>, MeshError> {
    let new = asset.split_positions(positions);
    let normals = asset.split_normals_world(positions);
    let element = Element {
        name: "vertex".into(),
        count: src.records.len(),
        props: src.vertex_props.clone(),
    };
    // Which coordinate (0..3 position, 3..6 normal) a property holds, if any.
    let role = |k: usize| -> Option<usize> {
        (0..3).find(|&a| src.xyz[a] == k).or_else(|| {
            src.normals
                .and_then(|n| (0..3).find(|&a| n[a] == k).map(|a| a + 3))
        })
    };
    let value_of = |i: usize, r: usize| -> f64 {
        if r < 3 {
            new.get(i).map_or(0.0, |p| p[r])
        } else {
            normals
                .as_ref()
                .and_then(|n| n.get(i))
                .map_or(0.0, |n| n[r - 3])
        }
    };
    match src.encoding {
        Encoding::Binary { big } => {
            let mut out = src.bytes.clone();
            let mut values = Vec::new();
            for (i, &start) in src.records.iter().enumerate() {
                // Walk the record to find each property's offset (lists vary in length).
                let mut body = Body::Binary {
                    bytes: &src.bytes,
                    at: start,
                    big,
                };
                let mut at = start;
                let mut writes: Vec<(usize, Scalar, f64)> = Vec::new();
                body.record(&element, i, &mut values, |k, v| {
                    let prop = &element.props[k];
                    if let (Kind::Scalar(t), Some(r)) = (prop.kind, role(k)) {
                        writes.push((at, t, value_of(i, r)));
                    }
                    at += match prop.kind {
                        Kind::Scalar(t) => t.size(),
                        Kind::List(c, t) => c.size() + v.len() * t.size(),
                    };
                    Ok(())
                })?;
                for (at, t, x) in writes {
                    t.write(&mut out, at, big, x);
                }
            }
            Ok(out)
        }
        Encoding::Ascii => {
            let text = utf8(&src.bytes, FORMAT)?;
            let mut edits = Vec::with_capacity(src.records.len() * 6);
            for (i, &start) in src.records.iter().enumerate() {
                let mut words = Words::new(text, start);
                for (k, prop) in element.props.iter().enumerate() {
                    let n = match prop.kind {
                        Kind::Scalar(_) => 1,
                        Kind::List(..) => {
                            let (_, _, w) = words.next().unwrap_or((0, 0, "0"));
                            w.parse::<usize>().unwrap_or(0)
                        }
                    };
                    for _ in 0..n {
                        let Some((_, at, w)) = words.next() else {
                            break;
                        };
                        if let Some(r) = role(k) {
                            edits.push((at..at + w.len(), coordinate(value_of(i, r))));
                        }
                    }
                }
            }
            Ok(splice(text, &edits))
        }
    }
}

/// A new binary little-endian PLY (for input in another format): the file's split vertices
/// (so UV seams stay) with `double` positions, `float` normals and `s t` UVs when the input
/// had them, and faces wound like the oriented surface.
pub(crate) fn write_new(asset: &Asset, positions: &[[f64; 3]]) -> Result<Vec<u8>, MeshError> {
    let points = asset.split_world_positions(positions);
    let normals = asset.split_normals_world(positions);
    let uvs = asset.file.uvs.as_ref();
    let triangles = asset.oriented_split_triangles();
    let mut header = String::from("ply\nformat binary_little_endian 1.0\n");
    let _ = writeln!(header, "comment Willow: faired by conformal Willmore flow");
    let _ = writeln!(header, "element vertex {}", points.len());
    header.push_str("property double x\nproperty double y\nproperty double z\n");
    if normals.is_some() {
        header.push_str("property float nx\nproperty float ny\nproperty float nz\n");
    }
    if uvs.is_some() {
        header.push_str("property float s\nproperty float t\n");
    }
    let _ = writeln!(header, "element face {}", triangles.len());
    header.push_str("property list uchar int vertex_indices\nend_header\n");
    let mut out = header.into_bytes();
    for (i, p) in points.iter().enumerate() {
        for x in p {
            out.extend_from_slice(&x.to_le_bytes());
        }
        if let Some(n) = &normals {
            for x in n.get(i).copied().unwrap_or([0.0, 0.0, 1.0]) {
                out.extend_from_slice(&(x as f32).to_le_bytes());
            }
        }
        if let Some(uvs) = uvs {
            let [u, v] = uvs.get(i).copied().flatten().unwrap_or([0.0; 2]);
            for x in [u, 1.0 - v] {
                out.extend_from_slice(&(x as f32).to_le_bytes());
            }
        }
    }
    for t in &triangles {
        out.push(3);
        for &v in t {
            let v = i32::try_from(v).map_err(|_| MeshError::TooLarge {
                what: "vertices for PLY int indices",
                value: v,
                limit: i32::MAX as usize,
            })?;
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    Ok(out)
}
