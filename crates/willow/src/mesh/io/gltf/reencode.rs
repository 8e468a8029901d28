//! Writing a meshopt-compressed input back compressed (issue 27, item 1): the vertex
//! attribute views the input stored through `EXT_meshopt_compression` /
//! `KHR_meshopt_compression` are stored through it again, laid out as gltfpack `-cc` does.
//!
//! Re-encoded: the POSITION and NORMAL views the flow rewrites, when the input's view was
//! compressed, with filter NONE: they are written as plain integers or floats, so a NORMAL the
//! input stored with the OCTAHEDRAL filter comes back as its plain normalized byte or short
//! VEC3, which the decoder needs no filter for. Left decoded: the views the flow does not
//! rewrite (UVs, colours, animation data, indices): re-encoding them would gain nothing the
//! faired shape needs, the index codec may rotate a triangle's corners (changing the file's
//! own index order), and the filters' encoders take float input the decoded integers no
//! longer are.
//!
//! Layout (the extension's README, and gltfpack's output): the compressed bytes are in
//! buffer 0 (the GLB's BIN chunk), named by each view's extension object (`buffer`,
//! `byteOffset`, `byteLength`, `byteStride`, `count`, `mode`); the view itself describes the
//! decoded bytes in buffer 1, a fallback buffer with no data (`"fallback": true`), so the
//! extension is required.

use super::meshopt::Compression;
use super::{malformed, MeshError};
use serde_json::{json, Value};

/// A key of the temporary marker on a view to be re-encoded, between [`mark`] and [`place`]
/// (which removes it): the index of its encoded bytes.
const BLOB: &str = "willowBlob";

/// The vertex codec version each name of the extension allows: `EXT_` only version 0,
/// `KHR_` also version 1 (better compression; what gltfpack writes for it).
fn codec_version(ext: &str) -> i32 {
    if ext.starts_with("KHR_") {
        1
    } else {
        0
    }
}

/// `count` elements of `stride` bytes through meshoptimizer's vertex codec.
fn encode_vertices(data: &[u8], stride: usize, version: i32) -> Result<Vec<u8>, MeshError> {
    use meshopt::ffi;
    let count = data.len() / stride;
    // SAFETY: the bound is a pure function of its arguments.
    let bound = unsafe { ffi::meshopt_encodeVertexBufferBound(count, stride) };
    let mut out = vec![0u8; bound];
    // SAFETY: `data` holds exactly count·stride bytes (the caller checked `stride` divides
    // its length, is a multiple of 4 and at most 256, as the codec requires), and `out` is
    // `bound` bytes long, the size meshoptimizer documents as always enough.
    let size = unsafe {
        ffi::meshopt_encodeVertexBufferLevel(
            out.as_mut_ptr(),
            out.len(),
            data.as_ptr().cast(),
            count,
            stride,
            2, // meshoptimizer's default level (used by version 1 only)
            version,
        )
    };
    if size == 0 && count > 0 {
        return Err(malformed("meshopt vertex encoding failed"));
    }
    out.truncate(size);
    Ok(out)
}

/// Encodes each of `views` (view index in `doc`, byteStride; the view plain on buffer 0 at
/// its offset in `bin`) and marks it: no bytes in `bin` any more (so `clean::compact` drops
/// its plain data) and the marker that [`place`] replaces. Returns the encoded bytes. A view
/// whose stride the codec cannot take is left plain.
pub(super) fn mark(
    doc: &mut Value,
    bin: &[u8],
    views: &[(usize, usize)],
    c: &Compression,
) -> Result<Vec<Vec<u8>>, MeshError> {
    let mut blobs = Vec::new();
    let mut done: Vec<usize> = Vec::new();
    for &(i, stride) in views {
        if done.contains(&i) {
            continue;
        }
        done.push(i);
        let v = doc
            .get_mut("bufferViews")
            .and_then(|v| v.get_mut(i))
            .and_then(Value::as_object_mut)
            .ok_or_else(|| malformed("missing buffer view"))?;
        let at = v.get("byteOffset").and_then(Value::as_u64).unwrap_or(0) as usize;
        let len = v.get("byteLength").and_then(Value::as_u64).unwrap_or(0) as usize;
        let stride_ok = stride > 0 && stride.is_multiple_of(4) && stride <= 256;
        if !stride_ok || len == 0 || !len.is_multiple_of(stride) {
            continue;
        }
        let data = at
            .checked_add(len)
            .and_then(|end| bin.get(at..end))
            .ok_or_else(|| malformed("a buffer view past the end of the buffer"))?;
        blobs.push(encode_vertices(data, stride, codec_version(c.ext))?);
        v.insert("byteOffset".into(), json!(0));
        v.insert("byteLength".into(), json!(0));
        v.insert("byteStride".into(), json!(stride));
        let marker = json!({
            "byteStride": stride,
            "count": len / stride,
            "mode": "ATTRIBUTES",
            BLOB: blobs.len() - 1,
        });
        let ext = v.entry("extensions").or_insert_with(|| json!({}));
        ext.as_object_mut()
            .ok_or_else(|| malformed("buffer view extensions"))?
            .insert(c.ext.into(), marker);
    }
    Ok(blobs)
}

/// Appends the encoded bytes to `bin` (buffer 0) and points each marked view at its decoded
/// range of the fallback buffer (buffer 1), whose JSON is returned; the extension is listed as
/// used and required (a fallback buffer without data can only be read through it). `None`
/// when nothing was marked.
pub(super) fn place(
    doc: &mut Value,
    bin: &mut Vec<u8>,
    blobs: &[Vec<u8>],
    c: &Compression,
) -> Result<Option<Value>, MeshError> {
    let mut fallback = 0usize;
    let views = doc.get_mut("bufferViews").and_then(Value::as_array_mut);
    for v in views.into_iter().flatten() {
        let Some(e) = v
            .get_mut("extensions")
            .and_then(|x| x.get_mut(c.ext))
            .and_then(Value::as_object_mut)
        else {
            continue;
        };
        let Some(k) = e.remove(BLOB).and_then(|k| k.as_u64()) else {
            continue;
        };
        let blob = blobs
            .get(k as usize)
            .ok_or_else(|| malformed("meshopt marker"))?;
        let stride = e.get("byteStride").and_then(Value::as_u64).unwrap_or(0) as usize;
        let count = e.get("count").and_then(Value::as_u64).unwrap_or(0) as usize;
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        e.insert("buffer".into(), json!(0));
        e.insert("byteOffset".into(), json!(bin.len()));
        e.insert("byteLength".into(), json!(blob.len()));
        bin.extend_from_slice(blob);
        let v = v.as_object_mut().ok_or_else(|| malformed("buffer view"))?;
        v.insert("buffer".into(), json!(1));
        v.insert("byteOffset".into(), json!(fallback));
        v.insert("byteLength".into(), json!(count * stride));
        // Strides are multiples of 4, so every view in the fallback stays 4-aligned.
        fallback += count * stride;
    }
    if fallback == 0 {
        return Ok(None);
    }
    let root = doc
        .as_object_mut()
        .ok_or_else(|| malformed("not an object"))?;
    for key in ["extensionsUsed", "extensionsRequired"] {
        let list = root
            .entry(key)
            .or_insert_with(|| json!([]))
            .as_array_mut()
            .ok_or_else(|| malformed(key))?;
        if !list.iter().any(|e| e.as_str() == Some(c.ext)) {
            list.push(json!(c.ext));
        }
    }
    Ok(Some(json!({
        "byteLength": fallback,
        "extensions": {c.ext: {"fallback": true}},
    })))
}
