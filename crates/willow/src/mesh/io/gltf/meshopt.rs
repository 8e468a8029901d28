//! `EXT_meshopt_compression` and `KHR_meshopt_compression`: buffer views stored through
//! meshoptimizer's vertex and index codecs (gltfpack `-cc`, gltf-transform `meshopt`).
//!
//! Each compressed view is decoded with the reference decoder (the `meshopt` crate, which
//! vendors meshoptimizer) into exactly the bytes its plain `bufferView` describes, written into
//! that view's range of its own buffer. That buffer is usually a *fallback* buffer with no data
//! (`"fallback": true`, no `uri`), which is allocated here. Afterwards the document is an
//! ordinary one: the extension is taken out of the views, the buffers and `extensionsUsed` /
//! `extensionsRequired`, so the document is read as plain (possibly still quantized) data.
//! Which views were compressed is kept ([`Compression`]) so that writing can re-encode them
//! (`reencode`).

use super::{decode_data_uri, Limits, MeshError};
use serde_json::Value;

/// The two names of the extension; `KHR_` is the ratified one (adds the COLOR filter and
/// version 1 of the vertex codec, which the decoder reads either way).
pub(super) const MESHOPT: [&str; 2] = ["EXT_meshopt_compression", "KHR_meshopt_compression"];

/// How a compressed view's bytes were encoded (the extension's `mode`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Mode {
    Attributes,
    Triangles,
    Indices,
}

/// The post-decode transform of an `ATTRIBUTES` view (the extension's `filter`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Filter {
    None,
    Octahedral,
    Quaternion,
    Exponential,
    Color,
}

/// One compressed view's extension object, checked.
struct Compressed {
    view: usize,
    source: usize,
    offset: usize,
    length: usize,
    stride: usize,
    count: usize,
    mode: Mode,
    filter: Filter,
    /// Where the decoded bytes go: the plain view's buffer and byte range.
    target: usize,
    target_offset: usize,
}

fn bad(view: usize, ext: &str, detail: impl std::fmt::Display) -> MeshError {
    MeshError::parse("glTF", format!("bufferView {view}: {ext}: {detail}"))
}

/// The extension name the document uses, if any.
pub(super) fn used(json: &Value) -> Option<&'static str> {
    let used = json.get("extensionsUsed").and_then(Value::as_array)?;
    MESHOPT
        .into_iter()
        .find(|m| used.iter().any(|e| e.as_str() == Some(m)))
}

/// What the input compressed: the extension's name and its `ATTRIBUTES` views (the ones
/// `reencode` may store compressed again).
#[derive(Clone, Debug)]
pub(crate) struct Compression {
    pub(super) ext: &'static str,
    /// (view, byteStride, filtered) of each `ATTRIBUTES` view, by the input's view numbers.
    pub(super) attributes: Vec<(usize, usize, bool)>,
}

/// Decodes every compressed view into place in `buffers` (from [`resolve_buffers`]) and
/// strips the extension from `json`.
pub(super) fn decompress(
    json: &mut Value,
    buffers: &mut [Vec<u8>],
    ext: &'static str,
) -> Result<Compression, MeshError> {
    let views = json.get("bufferViews").and_then(Value::as_array);
    let mut jobs = Vec::new();
    for (i, v) in views.into_iter().flatten().enumerate() {
        if let Some(e) = v.get("extensions").and_then(|x| x.get(ext)) {
            jobs.push(parse_view(i, v, e, ext, buffers)?);
        }
    }
    for job in &jobs {
        let decoded = decode(job, &buffers[job.source], ext)?;
        // In range: `parse_view` checked target_offset + count·stride ≤ the target's length.
        buffers[job.target][job.target_offset..job.target_offset + decoded.len()]
            .copy_from_slice(&decoded);
    }
    strip(json, ext);
    let attributes = jobs
        .iter()
        .filter(|j| j.mode == Mode::Attributes)
        .map(|j| (j.view, j.stride, j.filter != Filter::None))
        .collect();
    Ok(Compression { ext, attributes })
}

/// Resolves every buffer on the raw JSON: the GLB BIN chunk for buffer 0 without `uri`, base64
/// `data:` URIs, and zeros for a meshopt fallback buffer (`ext`), to be filled by decoding.
/// Each is exactly `byteLength` long.
pub(super) fn resolve_buffers(
    json: &Value,
    bin: Option<&[u8]>,
    ext: Option<&str>,
    limits: &Limits,
) -> Result<Vec<Vec<u8>>, MeshError> {
    let list = json.get("buffers").and_then(Value::as_array);
    let mut out = Vec::new();
    // Decompressed, the document is held to the size limit of an uncompressed upload, so a
    // small file cannot declare a huge fallback buffer.
    let mut fallback_bytes = 0usize;
    for (i, b) in list.into_iter().flatten().enumerate() {
        let length = b
            .get("byteLength")
            .and_then(Value::as_u64)
            .and_then(|n| usize::try_from(n).ok())
            .ok_or_else(|| MeshError::parse("glTF", format!("buffer {i}: bad byteLength")))?;
        let fallback = b
            .get("extensions")
            .and_then(|x| x.get(ext?))
            .and_then(|x| x.get("fallback"))
            .and_then(Value::as_bool)
            == Some(true);
        let mut data = match (b.get("uri").and_then(Value::as_str), bin) {
            (Some(uri), _) => decode_data_uri(uri)?,
            (None, Some(bin)) if i == 0 => bin.to_vec(),
            // Filled by decoding.
            (None, _) if fallback => {
                fallback_bytes = fallback_bytes.saturating_add(length);
                limits.check_bytes(fallback_bytes)?;
                vec![0; length]
            }
            (None, _) => {
                return Err(MeshError::truncated(format!(
                    "buffer {i} has no uri and there is no GLB BIN chunk for it"
                )))
            }
        };
        if data.len() < length {
            return Err(MeshError::truncated(format!(
                "buffer {i} declares {length} bytes but holds {}",
                data.len()
            )));
        }
        data.truncate(length);
        out.push(data);
    }
    Ok(out)
}

fn parse_view(
    i: usize,
    view: &Value,
    e: &Value,
    ext: &str,
    buffers: &[Vec<u8>],
) -> Result<Compressed, MeshError> {
    let num = |obj: &Value, key: &str, default: Option<usize>| -> Result<usize, MeshError> {
        match obj.get(key) {
            None => default.ok_or_else(|| bad(i, ext, format!("no {key}"))),
            Some(x) => x
                .as_u64()
                .and_then(|n| usize::try_from(n).ok())
                .ok_or_else(|| bad(i, ext, format!("{key} is not a non-negative integer"))),
        }
    };
    let source = num(e, "buffer", None)?;
    let offset = num(e, "byteOffset", Some(0))?;
    let length = num(e, "byteLength", None)?;
    let stride = num(e, "byteStride", None)?;
    let count = num(e, "count", None)?;
    let mode = match e.get("mode").and_then(Value::as_str) {
        Some("ATTRIBUTES") => Mode::Attributes,
        Some("TRIANGLES") => Mode::Triangles,
        Some("INDICES") => Mode::Indices,
        other => return Err(bad(i, ext, format!("unknown mode {other:?}"))),
    };
    let filter = match e.get("filter").and_then(Value::as_str) {
        None | Some("NONE") => Filter::None,
        Some("OCTAHEDRAL") => Filter::Octahedral,
        Some("QUATERNION") => Filter::Quaternion,
        Some("EXPONENTIAL") => Filter::Exponential,
        Some("COLOR") if ext == MESHOPT[1] => Filter::Color,
        other => return Err(bad(i, ext, format!("unknown filter {other:?}"))),
    };
    // The extension's rules on strides (its README, "Mode and filter"), which the decoder
    // relies on: attributes in whole 4-byte words up to 256, indices of 2 or 4 bytes.
    let stride_ok = match mode {
        Mode::Attributes => stride > 0 && stride % 4 == 0 && stride <= 256,
        Mode::Triangles | Mode::Indices => stride == 2 || stride == 4,
    };
    if !stride_ok {
        return Err(bad(
            i,
            ext,
            format!("byteStride {stride} is invalid for {mode:?}"),
        ));
    }
    if mode == Mode::Triangles && count % 3 != 0 {
        return Err(bad(
            i,
            ext,
            format!("TRIANGLES count {count} is not a multiple of 3"),
        ));
    }
    let filter_ok = match filter {
        Filter::None => true,
        _ if mode != Mode::Attributes => false,
        Filter::Octahedral | Filter::Color => stride == 4 || stride == 8,
        Filter::Quaternion => stride == 8,
        Filter::Exponential => true,
    };
    if !filter_ok {
        return Err(bad(
            i,
            ext,
            format!("filter {filter:?} with {mode:?} and byteStride {stride}"),
        ));
    }
    let source_len = buffers.get(source).map(Vec::len);
    if offset
        .checked_add(length)
        .zip(source_len)
        .is_none_or(|(end, len)| end > len)
    {
        return Err(MeshError::truncated(format!(
            "bufferView {i}: {ext} data (bytes {offset}..+{length} of buffer {source}) is past \
             the end of that buffer"
        )));
    }
    let target = num(view, "buffer", None)?;
    let target_offset = num(view, "byteOffset", Some(0))?;
    let view_length = num(view, "byteLength", None)?;
    let decoded = count
        .checked_mul(stride)
        .ok_or_else(|| bad(i, ext, "count × byteStride overflows"))?;
    if decoded != view_length {
        return Err(bad(
            i,
            ext,
            format!(
                "count {count} × byteStride {stride} = {decoded}, but the bufferView's \
                 byteLength is {view_length}"
            ),
        ));
    }
    let target_len = buffers.get(target).map(Vec::len);
    if target_offset
        .checked_add(decoded)
        .zip(target_len)
        .is_none_or(|(end, len)| end > len)
    {
        return Err(MeshError::truncated(format!(
            "bufferView {i} (bytes {target_offset}..+{decoded}) is past the end of buffer {target}"
        )));
    }
    Ok(Compressed {
        view: i,
        source,
        offset,
        length,
        stride,
        count,
        mode,
        filter,
        target,
        target_offset,
    })
}

/// Decodes one view: the codec, then the filter, into `count · stride` bytes.
fn decode(c: &Compressed, source: &[u8], ext: &str) -> Result<Vec<u8>, MeshError> {
    use meshopt::ffi;
    let input = &source[c.offset..c.offset + c.length];
    let mut out = vec![0u8; c.count * c.stride];
    // SAFETY (all calls below): `out` holds exactly count·stride bytes, the size each decoder
    // writes for `count` elements of `stride` bytes; `parse_view` checked the strides each one
    // requires (attributes: multiple of 4, ≤ 256; indices: 2 or 4; filters: their strides),
    // and `input` is a live slice passed with its own length. meshoptimizer documents its
    // decoders as safe on untrusted input (malformed data gives an error code or garbage
    // values, never an out-of-bounds access).
    let code = unsafe {
        match c.mode {
            Mode::Attributes => ffi::meshopt_decodeVertexBuffer(
                out.as_mut_ptr().cast(),
                c.count,
                c.stride,
                input.as_ptr(),
                input.len(),
            ),
            Mode::Triangles => ffi::meshopt_decodeIndexBuffer(
                out.as_mut_ptr().cast(),
                c.count,
                c.stride,
                input.as_ptr(),
                input.len(),
            ),
            Mode::Indices => ffi::meshopt_decodeIndexSequence(
                out.as_mut_ptr().cast(),
                c.count,
                c.stride,
                input.as_ptr(),
                input.len(),
            ),
        }
    };
    if code != 0 {
        return Err(bad(
            c.view,
            ext,
            format!(
                "{:?} data does not decode (meshoptimizer error {code})",
                c.mode
            ),
        ));
    }
    // SAFETY: as above; each filter rewrites count elements of `stride` bytes in place.
    unsafe {
        let (p, n, s) = (out.as_mut_ptr().cast(), c.count, c.stride);
        match c.filter {
            Filter::None => {}
            Filter::Octahedral => ffi::meshopt_decodeFilterOct(p, n, s),
            Filter::Quaternion => ffi::meshopt_decodeFilterQuat(p, n, s),
            Filter::Exponential => ffi::meshopt_decodeFilterExp(p, n, s),
            Filter::Color => ffi::meshopt_decodeFilterColor(p, n, s),
        }
    }
    Ok(out)
}

/// Removes the extension everywhere: the data is now plain.
fn strip(json: &mut Value, ext: &str) {
    for key in ["bufferViews", "buffers"] {
        let list = json.get_mut(key).and_then(Value::as_array_mut);
        for item in list.into_iter().flatten() {
            let Some(obj) = item.as_object_mut() else {
                continue;
            };
            let empty = obj
                .get_mut("extensions")
                .and_then(Value::as_object_mut)
                .map(|x| {
                    x.remove(ext);
                    x.is_empty()
                });
            if empty == Some(true) {
                obj.remove("extensions");
            }
        }
    }
    if let Some(root) = json.as_object_mut() {
        for key in ["extensionsUsed", "extensionsRequired"] {
            let empty = root.get_mut(key).and_then(Value::as_array_mut).map(|list| {
                list.retain(|e| e.as_str() != Some(ext));
                list.is_empty()
            });
            // The glTF schema gives both lists minItems 1.
            if empty == Some(true) {
                root.remove(key);
            }
        }
    }
}
