//! Writing a refined OBJ (issue 26, item 5; [`crate::mesh::io::Asset::refined`]): the user's
//! own statements kept, each face replaced by its children.
//!
//! Every line that is not vertex data or a face is copied as it is, in its order: `mtllib`,
//! `o`, `g`, `usemtl`, `s`, comments, `l` and `p`. So each child face sits where its parent's
//! `f` line was, under the same group, object, material and smoothing group. Vertex data is
//! written as one block where the file's first `v`/`vt`/`vn` line was (OBJ numbers vertices
//! over the whole file, so this changes no number, and no face refers forward):
//!
//! - `v`: the file's own `v` lines in order, with their new coordinates spliced in (as the
//!   unrefined writer does, so colours stay), then one line per new vertex (with its edge's
//!   mean colour when the file has `v` colours), so `v` line `k` is still file vertex `k`
//!   of the streamed frames;
//! - `vt`: the file's `vt` lines as they are, then one per new corner with a UV (its edge's
//!   midpoint in UV space, `refined.rs`);
//! - `vn`: one per normal group, recomputed from the new positions (as `write_new` does).
//!
//! Children are written with absolute indices, in the winding their parent had in the file.
//! Left as they were: `l` and `p` lines with relative (negative) indices now count back from
//! the end of the vertex block, so a file that mixes them with vertex data changes meaning.

use super::super::refined::RefinedSource;
use super::super::text::{coordinate, lines_with_offsets, triple};
use super::super::{Asset, UNWELDED};
use super::ObjSource;
use std::fmt::Write as _;

/// Writes the refined asset into the user's OBJ text (module docs).
pub(crate) fn write_refined(
    asset: &Asset,
    src: &ObjSource,
    r: &RefinedSource,
    positions: &[[f64; 3]],
) -> Vec<u8> {
    let eol = if src.text.contains("\r\n") {
        "\r\n"
    } else {
        "\n"
    };
    let v_new = asset.file_positions_f64(positions);

    // The vertex block: v, vt, vn (module docs).
    let mut block = String::new();
    let mut vt_lines: Vec<&str> = Vec::new();
    let mut v_line = 0usize;
    for (start, line) in lines_with_offsets(&src.text) {
        match line.split_whitespace().next() {
            Some("v") => {
                let (Some(vl), Some(p)) = (src.v_lines.get(v_line), v_new.get(v_line)) else {
                    continue;
                };
                let span = vl.span.start - start..vl.span.end - start;
                block.push_str(line.get(..span.start).unwrap_or("v "));
                block.push_str(&triple(*p));
                block.push_str(line.get(span.end..).unwrap_or(""));
                block.push_str(eol);
                v_line += 1;
            }
            Some("vt") => vt_lines.push(line),
            _ => {}
        }
    }
    for (v, p) in v_new.iter().enumerate().skip(v_line) {
        // `write!` into a String cannot fail; the results are ignored for that reason.
        let _ = write!(block, "v {}", triple(*p));
        let colour = r
            .v_colours
            .as_ref()
            .and_then(|c| c.get(v).copied().flatten());
        if let Some(c) = colour {
            let _ = write!(block, " {}", triple(c));
        }
        block.push_str(eol);
    }
    for line in &vt_lines {
        block.push_str(line);
        block.push_str(eol);
    }
    let old_vt = |sv: usize| {
        (sv < r.old_split)
            .then(|| src.vt_of_split.get(sv).copied().flatten())
            .flatten()
    };
    let mut next_vt = src.vt_count;
    let vt_of: Vec<Option<usize>> = match &asset.file.uvs {
        Some(uvs) => uvs
            .iter()
            .enumerate()
            .map(|(sv, uv)| {
                old_vt(sv).or_else(|| {
                    uv.map(|[u, v]| {
                        let _ = write!(block, "vt {} {}{eol}", coordinate(u), coordinate(1.0 - v));
                        next_vt += 1;
                        next_vt - 1
                    })
                })
            })
            .collect(),
        None => Vec::new(),
    };
    let normals = asset.group_normals(positions);
    for n in normals.iter().flatten() {
        let _ = write!(block, "vn {}{eol}", triple(*n));
    }
    let group_of = |sv: usize| -> Option<usize> {
        let (groups, _) = asset.normal_groups.as_ref()?;
        groups.get(sv).copied().filter(|&g| g != UNWELDED)
    };

    // Children of each face, contiguous in the refined triangles (children follow parents).
    let faces = asset.file.face_of_triangle.as_deref().unwrap_or(&[]);
    let mut child = 0usize;
    let mut face = 0usize;
    let mut out = String::with_capacity(src.text.len() + block.len() + 64 * faces.len());
    let mut block = Some(block);
    for (line_no, (_, line)) in lines_with_offsets(&src.text).enumerate() {
        match line.split_whitespace().next() {
            Some("v" | "vt" | "vn") => {
                if let Some(b) = block.take() {
                    out.push_str(&b);
                }
            }
            Some("f")
                if src
                    .face_lines
                    .get(face)
                    .is_some_and(|&l| l as usize == line_no) =>
            {
                while faces.get(child).is_some_and(|&f| f as usize == face) {
                    let Some(t) = asset.file.triangles.get(child) else {
                        break;
                    };
                    let t = if r.flipped.get(r.root(child)).copied().unwrap_or(false) {
                        [t[0], t[2], t[1]]
                    } else {
                        *t
                    };
                    let vts = t.map(|sv| vt_of.get(sv).copied().flatten());
                    let vns = t.map(group_of);
                    let with_vt = vts.iter().all(Option::is_some);
                    let with_vn = normals.is_some() && vns.iter().all(Option::is_some);
                    out.push('f');
                    for k in 0..3 {
                        let v = r.v_of_split.get(t[k]).copied().unwrap_or(0) + 1;
                        let (vt, vn) = (vts[k].unwrap_or(0) + 1, vns[k].unwrap_or(0) + 1);
                        let _ = match (with_vt, with_vn) {
                            (true, true) => write!(out, " {v}/{vt}/{vn}"),
                            (true, false) => write!(out, " {v}/{vt}"),
                            (false, true) => write!(out, " {v}//{vn}"),
                            (false, false) => write!(out, " {v}"),
                        };
                    }
                    out.push_str(eol);
                    child += 1;
                }
                face += 1;
            }
            _ => {
                out.push_str(line);
                out.push_str(eol);
            }
        }
    }
    if let Some(b) = block {
        out.push_str(&b);
    }
    out.into_bytes()
}
