//! OFF (Geomview's object file format), with the `ST` (UVs), `C` (colours) and `N` (normals)
//! variants; `4OFF` and `nOFF` (other dimensions) are refused.
//!
//! The file's vertices are its vertex lines, in order; faces are fan-triangulated. Writing back
//! keeps the text byte for byte except each vertex's `x y z` and, for `NOFF`, its normal
//! (recomputed): colours, UVs, face lines with their colours, comments and layout stay.

use super::text::{lines_with_offsets, splice, triple, utf8};
use super::{Asset, FileGeometry, Limits, MeshError};
use std::fmt::Write as _;
use std::ops::Range;

const FORMAT: &str = "OFF";

/// What an OFF file has beyond the surface: its text and where each vertex's numbers are.
#[derive(Clone, Debug)]
pub(crate) struct OffSource {
    text: String,
    /// Byte range of each vertex's `x y z`.
    xyz: Vec<Range<usize>>,
    /// Byte range of each vertex's `nx ny nz`, for `NOFF`.
    normals: Option<Vec<Range<usize>>>,
}

fn parse_error(line: usize, what: &str) -> MeshError {
    MeshError::parse(FORMAT, format!("line {}: {what}", line + 1))
}

/// The words of a line before any `#` comment, with their byte offsets in the file.
fn words(start: usize, line: &str) -> Vec<(usize, &str)> {
    let code = line.split('#').next().unwrap_or("");
    let base = code.as_ptr() as usize;
    code.split_whitespace()
        .map(|w| (start + w.as_ptr() as usize - base, w))
        .collect()
}

fn number(line: usize, w: &str, what: &str) -> Result<f64, MeshError> {
    w.parse()
        .map_err(|_| parse_error(line, &format!("{what}: bad number {w:?}")))
}

pub(crate) fn read(bytes: &[u8], limits: &Limits) -> Result<(FileGeometry, OffSource), MeshError> {
    let text = utf8(bytes, FORMAT)?;
    // Non-blank lines with their words; comments and blank lines carry nothing.
    let mut lines = lines_with_offsets(text)
        .enumerate()
        .map(|(no, (start, line))| (no, words(start, line)))
        .filter(|(_, w)| !w.is_empty());
    let (head_no, head) = lines
        .next()
        .ok_or_else(|| MeshError::parse(FORMAT, "the file is empty"))?;
    let keyword = head.first().map_or("", |w| w.1);
    if !super::format::is_off_keyword(keyword) {
        return Err(parse_error(
            head_no,
            &format!("expected `OFF`, found {keyword:?}"),
        ));
    }
    let prefix = keyword.trim_end_matches("OFF");
    if prefix.contains('4') || prefix.contains('n') {
        return Err(MeshError::unsupported(format!(
            "{keyword}: only 3D OFF files (not 4OFF or nOFF)"
        )));
    }
    let (has_uv, has_normals) = (prefix.starts_with("ST"), prefix.contains('N'));
    let (counts_no, counts) = if head.len() > 1 {
        (head_no, head[1..].to_vec())
    } else {
        lines
            .next()
            .ok_or_else(|| MeshError::parse(FORMAT, "the file ends before the counts line"))?
    };
    let count = |k: usize, what: &str| -> Result<usize, MeshError> {
        let w = counts
            .get(k)
            .map(|w| w.1)
            .ok_or_else(|| parse_error(counts_no, &format!("expected the {what} count")))?;
        w.parse()
            .map_err(|_| parse_error(counts_no, &format!("bad {what} count {w:?}")))
    };
    let (nv, nf) = (count(0, "vertex")?, count(1, "face")?);
    limits.check_vertices(nv)?;
    limits.check_faces(nf)?;
    // Every vertex and face takes a line of at least two bytes: a count beyond that is a lie
    // told before anything is allocated for it.
    if nv.saturating_add(nf) > text.len() {
        return Err(MeshError::truncated(format!(
            "the OFF counts say {nv} vertices and {nf} faces but the file has {} bytes",
            text.len()
        )));
    }
    let mut local = Vec::with_capacity(nv);
    let mut xyz = Vec::with_capacity(nv);
    let mut normal_spans = Vec::new();
    let mut uvs = Vec::new();
    let mut non_finite = super::super::error::Offenders::default();
    for i in 0..nv {
        let (no, w) = lines.next().ok_or_else(|| {
            MeshError::truncated(format!("OFF: the file ends at vertex {i} of {nv}"))
        })?;
        let need = 3 + if has_normals { 3 } else { 0 } + if has_uv { 2 } else { 0 };
        if w.len() < need {
            return Err(parse_error(
                no,
                &format!("vertex {i}: expected at least {need} numbers"),
            ));
        }
        let mut p = [0.0; 3];
        for k in 0..3 {
            p[k] = number(no, w[k].1, "vertex")?;
        }
        if !p.iter().all(|x| x.is_finite()) {
            non_finite.push(i);
        }
        local.push(p);
        xyz.push(w[0].0..w[2].0 + w[2].1.len());
        if has_normals {
            for k in 3..6 {
                number(no, w[k].1, "vertex normal")?;
            }
            normal_spans.push(w[3].0..w[5].0 + w[5].1.len());
        }
        if has_uv {
            // UVs come last (after any colour, whose length varies).
            let n = w.len();
            let (u, v) = (
                number(no, w[n - 2].1, "vertex UV")?,
                number(no, w[n - 1].1, "vertex UV")?,
            );
            // OFF UVs have their origin at the bottom left; glTF's is the top left.
            uvs.push(Some([u, 1.0 - v]));
        }
    }
    let mut triangles = Vec::new();
    let mut face_of_triangle: Vec<u32> = Vec::new();
    let mut bad_faces = super::super::error::Offenders::default();
    for f in 0..nf {
        let (no, w) = lines.next().ok_or_else(|| {
            MeshError::truncated(format!("OFF: the file ends at face {f} of {nf}"))
        })?;
        let n = w.first().map_or(Ok(0.0), |w| number(no, w.1, "face"))?;
        if n < 3.0 || n.fract() != 0.0 || (n as usize) >= w.len() {
            return Err(parse_error(
                no,
                &format!("face {f}: expected a vertex count of 3 or more and that many indices"),
            ));
        }
        let n = n as usize;
        let mut ids = Vec::with_capacity(n);
        for (_, s) in &w[1..=n] {
            let i: usize = s
                .parse()
                .map_err(|_| parse_error(no, &format!("face {f}: bad index {s:?}")))?;
            ids.push(i);
        }
        if ids.iter().any(|&i| i >= nv) {
            bad_faces.push(f);
            continue;
        }
        limits.check_faces(triangles.len() + n - 2)?;
        for k in 1..n - 1 {
            triangles.push([ids[0], ids[k], ids[k + 1]]);
            face_of_triangle.push(f as u32);
        }
    }
    if !bad_faces.is_empty() {
        return Err(MeshError::IndexOutOfRange {
            faces: bad_faces,
            vertex_count: nv,
        });
    }
    if !non_finite.is_empty() {
        return Err(MeshError::NonFinite {
            vertices: non_finite,
        });
    }
    if triangles.is_empty() {
        return Err(MeshError::Empty {
            vertices: nv,
            faces: 0,
        });
    }
    let file = FileGeometry {
        uvs: has_uv.then_some(uvs),
        // One normal per vertex: each vertex is its own smooth group.
        normal_keys: has_normals.then(|| (0..nv as u64).collect()),
        face_of_triangle: Some(face_of_triangle),
        ..FileGeometry::one_block(local, triangles)
    };
    let src = OffSource {
        text: text.to_owned(),
        xyz,
        normals: has_normals.then_some(normal_spans),
    };
    Ok((file, src))
}

/// Writes the user's OFF back with each vertex's `x y z` (and `NOFF` normal) replaced.
pub(crate) fn write_kept(asset: &Asset, src: &OffSource, positions: &[[f64; 3]]) -> Vec<u8> {
    let new = asset.split_positions(positions);
    let normals = asset.split_normals_world(positions);
    let mut edits = Vec::with_capacity(src.xyz.len() * 2);
    for (i, span) in src.xyz.iter().enumerate() {
        edits.push((
            span.clone(),
            triple(new.get(i).copied().unwrap_or([0.0; 3])),
        ));
        if let (Some(spans), Some(n)) = (&src.normals, &normals) {
            if let (Some(s), Some(n)) = (spans.get(i), n.get(i)) {
                edits.push((s.clone(), triple(*n)));
            }
        }
    }
    splice(&src.text, &edits)
}

/// A new OFF (for input in another format): one vertex per surface vertex, triangles wound
/// like the oriented surface.
pub(crate) fn write_new(asset: &Asset, positions: &[[f64; 3]]) -> Vec<u8> {
    let mut out = String::from("OFF\n# Willow: faired by conformal Willmore flow\n");
    // A refined asset writes the file's vertices then the new ones (refined.rs); a PLY its
    // own records in file order (its numbering kept); any other its welded vertices.
    let (points, triangles) = match (
        asset.refined_vertices(positions),
        asset.split_vertex_positions(positions),
    ) {
        (Some((points, _)), _) => (points, asset.file_triangles()),
        (None, Some(points)) => (points, asset.oriented_split_triangles()),
        (None, None) => (positions.to_vec(), asset.surface.triangles.clone()),
    };
    let _ = writeln!(out, "{} {} 0", points.len(), triangles.len());
    for p in &points {
        let _ = writeln!(out, "{}", triple(*p));
    }
    for t in &triangles {
        let _ = writeln!(out, "3 {} {} {}", t[0], t[1], t[2]);
    }
    out.into_bytes()
}
