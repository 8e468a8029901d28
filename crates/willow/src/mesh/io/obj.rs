//! Wavefront OBJ: parsed by hand from memory, written back by splicing new numbers into the
//! user's own text.
//!
//! The user's vertex numbering is the `v` lines. Faces are fan-triangulated, and each distinct
//! `v/vt/vn` corner becomes a *split vertex* (what glTF conversion, UVs and normal groups
//! need); every split vertex remembers its `v` line, so positions map back to the file's own
//! order and count, unreferenced `v` lines included.
//!
//! Writing OBJ from OBJ keeps the text byte for byte except the coordinates of each `v` line
//! and the numbers of each `vn` line some face uses: faces, `vt`, vertex colours, `o`/`g`/`s`/
//! `usemtl`/`mtllib`, comments, blank lines and line endings (CRLF too) are copied through.
//!
//! Uploads are untrusted: a first pass counts elements and checks them against [`Limits`]
//! before anything is allocated per element, every index is range-checked, and every
//! malformed line is a [`MeshError`] naming its (1-based) line number.

use super::text::{coordinate, lines_with_offsets, splice, triple, utf8};
use super::{normalize_or_z, Asset, FileGeometry, Limits, MeshError, UNWELDED};
use std::collections::HashMap;
use std::fmt::Write as _;
use std::ops::Range;

const FORMAT: &str = "OBJ";

/// What an OBJ file has that the surface does not: its text and where its numbers are.
#[derive(Clone, Debug)]
pub(crate) struct ObjSource {
    /// The file as uploaded (checked UTF-8): written back with only numbers replaced.
    text: String,
    /// Every `v` line, in file order.
    v_lines: Vec<VLine>,
    /// Byte range of the three numbers of every `vn` line, in file order.
    vn_spans: Vec<Range<usize>>,
    /// Split vertex → index of its `v` line.
    v_of_split: Vec<usize>,
    /// Split vertex → index of its `vn` line, if its corner named one.
    vn_of_split: Vec<Option<usize>>,
    /// Split vertex → index of its `vt` line, if its corner named one.
    vt_of_split: Vec<Option<usize>>,
    /// The number of `vt` lines.
    vt_count: usize,
    /// The faces under each `g` and `o` name.
    pub(crate) groups: super::groups::Groups,
    /// The 0-based line of every face (`f` statement), in file order.
    face_lines: Vec<u32>,
}

/// One `v` line: its stored position and the bytes that hold it.
#[derive(Clone, Debug)]
struct VLine {
    /// x, y, z as stored (divided by `w` when the line has one, as the OBJ spec says).
    stored: [f64; 3],
    /// Byte range of the numbers to replace: x y z, or x y z w when w ≠ 1 (the new line then
    /// has no w, so that it reads back as exactly the new position). Colours r g b stay.
    span: Range<usize>,
    /// The vertex colour r g b after x y z (a common extension of `v`), if the line has one.
    colour: Option<[f64; 3]>,
}

impl ObjSource {
    /// The number of `v` lines: the file's own vertex count.
    pub(crate) fn v_count(&self) -> usize {
        self.v_lines.len()
    }

    /// Split vertex → `v` line.
    pub(crate) fn v_of_split(&self) -> &[usize] {
        &self.v_of_split
    }

    /// The 1-based line number of face `f` (an `f` statement, from 0).
    pub(crate) fn face_line(&self, f: usize) -> Option<usize> {
        self.face_lines.get(f).map(|&l| l as usize + 1)
    }

    /// The 1-based line numbers of `v` lines `vs` (indices from 0), in one pass over the text.
    pub(crate) fn v_line_numbers(&self, vs: &[usize]) -> Vec<Option<usize>> {
        let starts: Vec<Option<usize>> = vs
            .iter()
            .map(|&v| self.v_lines.get(v).map(|l| l.span.start))
            .collect();
        let mut sorted: Vec<usize> = starts.iter().flatten().copied().collect();
        sorted.sort_unstable();
        let mut line_of: HashMap<usize, usize> = HashMap::new();
        let mut next = sorted.iter().peekable();
        let mut prev = 0;
        for (no, (start, _)) in lines_with_offsets(&self.text).enumerate() {
            while let Some(&&at) = next.peek() {
                if at < start {
                    line_of.insert(at, prev);
                    next.next();
                } else {
                    break;
                }
            }
            prev = no + 1;
        }
        for &at in next {
            line_of.insert(at, prev);
        }
        starts
            .iter()
            .map(|s| s.and_then(|at| line_of.get(&at).copied()))
            .collect()
    }

    /// The stored position of every `v` line, in file order.
    pub(crate) fn stored_positions(&self) -> Vec<[f64; 3]> {
        self.v_lines.iter().map(|v| v.stored).collect()
    }

    /// The colour of every `v` line, in file order, when some `v` line has one.
    pub(crate) fn v_colours(&self) -> Option<Vec<Option<[f64; 3]>>> {
        let colours: Vec<Option<[f64; 3]>> = self.v_lines.iter().map(|v| v.colour).collect();
        colours.iter().any(Option::is_some).then_some(colours)
    }
}

/// Element counts, to resolve relative (negative) and forward indices.
#[derive(Clone, Copy, Default)]
struct Counts {
    v: usize,
    vt: usize,
    vn: usize,
}

fn parse_error(line_no: usize, what: &str) -> MeshError {
    MeshError::parse(FORMAT, format!("line {}: {what}", line_no + 1))
}

/// The whitespace-separated words of `line` with their byte offsets in it (the same words
/// `split_whitespace` gives).
fn words_with_offsets(line: &str) -> impl Iterator<Item = (usize, &str)> {
    let base = line.as_ptr() as usize;
    line.split_whitespace()
        .map(move |w| (w.as_ptr() as usize - base, w))
}

/// Pass 1: element totals, so positive indices may point forward and limits are checked
/// before anything is allocated per element. Line continuations are refused here: the
/// writer copies lines byte for byte, and joining lines would make `v` numbers span two.
fn count_elements(text: &str, limits: &Limits) -> Result<Counts, MeshError> {
    let mut total = Counts::default();
    for (line_no, (_, line)) in lines_with_offsets(text).enumerate() {
        let keyword = line.split_whitespace().next();
        match keyword {
            Some("v") => total.v += 1,
            Some("vt") => total.vt += 1,
            Some("vn") => total.vn += 1,
            _ => {}
        }
        let comment = keyword.is_some_and(|k| k.starts_with('#'));
        if !comment && line.trim_end().ends_with('\\') {
            return Err(MeshError::unsupported(format!(
                "OBJ line {}: line continuations (a `\\` at the end of a line); join the line",
                line_no + 1
            )));
        }
    }
    limits.check_vertices(total.v)?;
    Ok(total)
}

/// The float `word`, or a parse error naming `what` and the line.
fn number(word: Option<&str>, line_no: usize, what: &str) -> Result<f64, MeshError> {
    let w = word.ok_or_else(|| parse_error(line_no, &format!("{what}: too few numbers")))?;
    w.parse()
        .map_err(|_| parse_error(line_no, &format!("{what}: bad number {w:?}")))
}

/// A `v` line: x y z, then nothing, a weight w, or a colour r g b.
fn parse_v(line: &str, line_no: usize) -> Result<VLine, MeshError> {
    let mut words = words_with_offsets(line).skip(1);
    let mut xyz = [0.0; 3];
    let mut span = 0..0;
    for (k, x) in xyz.iter_mut().enumerate() {
        let (at, w) = words
            .next()
            .ok_or_else(|| parse_error(line_no, "v: too few numbers"))?;
        *x = number(Some(w), line_no, "v")?;
        if k == 0 {
            span.start = at;
        }
        span.end = at + w.len();
    }
    let extra: Vec<(usize, &str)> = words.collect();
    let mut colour = None;
    match extra.as_slice() {
        [] => {}
        [(at, w)] => {
            let weight = number(Some(w), line_no, "v weight")?;
            if weight == 0.0 || !weight.is_finite() {
                return Err(parse_error(line_no, "v: a weight w of zero or non-finite"));
            }
            if weight != 1.0 {
                xyz = xyz.map(|x| x / weight);
                span.end = at + w.len();
            }
        }
        [r, g, b] => {
            let mut rgb = [0.0; 3];
            for (slot, (_, w)) in rgb.iter_mut().zip([r, g, b]) {
                *slot = number(Some(w), line_no, "v colour")?;
            }
            colour = Some(rgb);
        }
        _ => {
            return Err(parse_error(
                line_no,
                "v: expected x y z, x y z w, or x y z r g b",
            ))
        }
    }
    Ok(VLine {
        stored: xyz,
        span,
        colour,
    })
}

/// One face corner `v`, `v/vt`, `v//vn` or `v/vt/vn` resolved to 0-based indices. An
/// out-of-range `v` gives `Ok(None)` (the face is reported by number); an out-of-range `vt`
/// or `vn`, or anything unparsable, is a parse error.
type Corner = (usize, Option<usize>, Option<usize>);

fn parse_corner(
    word: &str,
    so_far: Counts,
    total: Counts,
    line_no: usize,
) -> Result<Option<Corner>, MeshError> {
    let mut parts = word.split('/');
    let mut resolved = [None; 3];
    let slots = [
        (so_far.v, total.v),
        (so_far.vt, total.vt),
        (so_far.vn, total.vn),
    ];
    let mut v_in_range = true;
    for (slot, (sofar, tot)) in slots.into_iter().enumerate() {
        match parts.next() {
            None | Some("") => {
                if slot == 0 {
                    return Err(parse_error(line_no, "empty vertex index"));
                }
            }
            Some(s) => {
                let i: i64 = s
                    .parse()
                    .map_err(|_| parse_error(line_no, &format!("bad index {s:?}")))?;
                // 0 is no index at all (OBJ counts from 1, or back from -1), not one past the
                // end: a syntax error of this line, not a face to report by its number.
                if i == 0 {
                    let what = ["", "vt ", "vn "][slot];
                    return Err(parse_error(
                        line_no,
                        &format!("OBJ {what}indices start at 1, got 0"),
                    ));
                }
                // Positive indices are 1-based and may point forward; negative ones count
                // back from the elements read so far.
                let index = if i > 0 {
                    usize::try_from(i - 1).ok().filter(|&k| k < tot)
                } else if i < 0 {
                    usize::try_from(i.unsigned_abs())
                        .ok()
                        .and_then(|back| sofar.checked_sub(back))
                } else {
                    None
                };
                match (index, slot) {
                    (Some(k), _) => resolved[slot] = Some(k),
                    (None, 0) => v_in_range = false,
                    (None, _) => {
                        return Err(parse_error(
                            line_no,
                            &format!("{} index {i} out of range", ["v", "vt", "vn"][slot]),
                        ))
                    }
                }
            }
        }
    }
    if parts.next().is_some() {
        return Err(parse_error(line_no, &format!("bad corner {word:?}")));
    }
    Ok(match (v_in_range, resolved[0]) {
        (true, Some(v)) => Some((v, resolved[1], resolved[2])),
        _ => None,
    })
}

/// Numbers the split vertices (distinct `v/vt/vn` corners) in order of first use.
#[derive(Default)]
struct SplitVertices {
    ids: HashMap<Corner, usize>,
    corners: Vec<Corner>,
}

impl SplitVertices {
    fn id(&mut self, c: Corner) -> usize {
        *self.ids.entry(c).or_insert_with(|| {
            self.corners.push(c);
            self.corners.len() - 1
        })
    }
}

pub(crate) fn read(bytes: &[u8], limits: &Limits) -> Result<(FileGeometry, ObjSource), MeshError> {
    let text = utf8(bytes, FORMAT)?;
    let total = count_elements(text, limits)?;

    let mut so_far = Counts::default();
    let mut v_lines: Vec<VLine> = Vec::with_capacity(total.v);
    let mut texcoords: Vec<[f64; 2]> = Vec::with_capacity(total.vt);
    let mut vn_spans: Vec<Range<usize>> = Vec::with_capacity(total.vn);
    let mut split = SplitVertices::default();
    let mut triangles: Vec<[usize; 3]> = Vec::new();
    let mut faces = 0usize;
    // Per triangle its face (`f` statement), per face its 0-based line: errors name lines.
    let mut face_of_triangle: Vec<u32> = Vec::new();
    let mut face_lines: Vec<u32> = Vec::new();
    let mut bad_faces = super::super::error::Offenders::default();
    let (mut points, mut lines) = (0usize, 0usize);
    // First line holding an `l` polyline of 3+ vertices: refused (it reads like a face).
    let mut polyline_line = None;
    let mut corners: Vec<Corner> = Vec::new();
    // The groups faces go to: those of the last `g` line and the last `o` line.
    let mut groups = super::groups::Groups::default();
    let (mut current_g, mut current_o): (Vec<usize>, Option<usize>) = (Vec::new(), None);
    for (line_no, (start, line)) in lines_with_offsets(text).enumerate() {
        let mut words = line.split_whitespace();
        let keyword = words.next();
        match keyword {
            Some("v") => {
                let mut v = parse_v(line, line_no)?;
                v.span = start + v.span.start..start + v.span.end;
                v_lines.push(v);
                so_far.v += 1;
            }
            Some("vt") => {
                let u = number(words.next(), line_no, "vt")?;
                // v is optional in the spec (default 0); a third number (w) is ignored.
                let v = words
                    .next()
                    .map_or(Ok(0.0), |w| number(Some(w), line_no, "vt"))?;
                texcoords.push([u, v]);
                so_far.vt += 1;
            }
            Some("vn") => {
                let mut at = words_with_offsets(line).skip(1);
                let mut span = 0..0;
                for k in 0..3 {
                    let (off, w) = at
                        .next()
                        .ok_or_else(|| parse_error(line_no, "vn: too few numbers"))?;
                    number(Some(w), line_no, "vn")?;
                    if k == 0 {
                        span.start = start + off;
                    }
                    span.end = start + off + w.len();
                }
                if at.next().is_some() {
                    return Err(parse_error(line_no, "vn: more than three numbers"));
                }
                vn_spans.push(span);
                so_far.vn += 1;
            }
            Some(kw @ ("f" | "l" | "p")) => {
                corners.clear();
                let mut in_range = true;
                let mut n = 0;
                for w in words {
                    n += 1;
                    match parse_corner(w, so_far, total, line_no)? {
                        Some(c) => corners.push(c),
                        None => in_range = false,
                    }
                }
                match (kw, n) {
                    // A face needs a triangle's worth of corners; dropping a shorter one would
                    // leave a hole nobody asked for.
                    ("f", 1 | 2) => {
                        return Err(parse_error(
                            line_no,
                            &format!("f: a face needs at least 3 vertices, got {n}"),
                        ))
                    }
                    ("p", _) | (_, 1) => points += 1,
                    (_, 0) => return Err(parse_error(line_no, "element without vertices")),
                    (_, 2) => lines += 1,
                    ("l", _) => {
                        lines += 1;
                        polyline_line.get_or_insert(line_no);
                    }
                    _ => {
                        limits.check_faces(triangles.len().saturating_add(n - 2))?;
                        if !in_range {
                            bad_faces.push(faces);
                        } else {
                            // A fan from the first corner, as most readers triangulate.
                            let ids: Vec<usize> = corners.iter().map(|&c| split.id(c)).collect();
                            let first = triangles.len();
                            for k in 1..ids.len() - 1 {
                                triangles.push([ids[0], ids[k], ids[k + 1]]);
                                face_of_triangle.push(faces as u32);
                            }
                            for &g in current_g.iter().chain(&current_o) {
                                groups.add(g, first..triangles.len());
                            }
                        }
                        face_lines.push(line_no as u32);
                        faces += 1;
                    }
                }
            }
            // `g a b`: the faces that follow belong to a and b; `o name`: to the object.
            // Both stay in the text as they are.
            Some("g") => current_g = words.map(|w| groups.slot(w)).collect(),
            Some("o") => {
                let name = line.trim_start()[1..].trim();
                current_o = (!name.is_empty()).then(|| groups.slot(name));
            }
            _ => {} // comments, materials, smoothing: kept as text
        }
    }
    if !bad_faces.is_empty() {
        return Err(MeshError::IndexOutOfRange {
            faces: bad_faces,
            vertex_count: total.v,
        });
    }
    if faces == 0 {
        return Err(if points + lines > 0 {
            MeshError::PointsOrLinesOnly { points, lines }
        } else {
            MeshError::Empty {
                vertices: total.v,
                faces: 0,
            }
        });
    }
    if let Some(line_no) = polyline_line {
        return Err(MeshError::unsupported(format!(
            "OBJ line {}: polylines of 3 or more vertices next to faces",
            line_no + 1
        )));
    }
    // Every `v` line is checked, used or not: unused ones are streamed and written back too.
    let mut non_finite = super::super::error::Offenders::default();
    for (i, v) in v_lines.iter().enumerate() {
        if !v.stored.iter().all(|x| x.is_finite()) {
            non_finite.push(i);
        }
    }
    if !non_finite.is_empty() {
        return Err(MeshError::NonFinite {
            vertices: non_finite,
        });
    }
    limits.check_vertices(split.corners.len())?;

    let corners = split.corners;
    let local: Vec<[f64; 3]> = corners
        .iter()
        .map(|&(v, _, _)| v_lines.get(v).map_or([0.0; 3], |l| l.stored))
        .collect();
    let uvs = corners.iter().any(|c| c.1.is_some()).then(|| {
        corners
            .iter()
            .map(|&(_, vt, _)| {
                vt.and_then(|i| texcoords.get(i))
                    .map(|uv| [uv[0], 1.0 - uv[1]])
            })
            .collect()
    });
    let normal_keys = corners.iter().any(|c| c.2.is_some()).then(|| {
        corners
            .iter()
            .map(|&(_, _, vn)| vn.map_or(u64::MAX, |i| i as u64))
            .collect()
    });
    let file = FileGeometry {
        uvs,
        normal_keys,
        face_of_triangle: Some(face_of_triangle),
        ..FileGeometry::one_block(local, triangles)
    };
    let src = ObjSource {
        text: text.to_owned(),
        v_lines,
        vn_spans,
        v_of_split: corners.iter().map(|c| c.0).collect(),
        vn_of_split: corners.iter().map(|c| c.2).collect(),
        vt_of_split: corners.iter().map(|c| c.1).collect(),
        vt_count: total.vt,
        groups,
        face_lines,
    };
    Ok((file, src))
}

/// Per `vn` line some corner uses: the unit area-weighted sum of the normals of the faces at
/// those corners, in the new positions (one `vn` per vertex gives smooth shading, one per face
/// corner group gives creases: the file's own choice is kept). Unused `vn` lines get `None`.
fn vn_normals(asset: &Asset, src: &ObjSource, positions: &[[f64; 3]]) -> Vec<Option<[f64; 3]>> {
    let mut sums: Vec<Option<[f64; 3]>> = vec![None; src.vn_spans.len()];
    for (ft, st) in asset
        .oriented_split_triangles()
        .iter()
        .zip(&asset.surface.triangles)
    {
        let p = |v: usize| positions.get(v).copied().unwrap_or([0.0; 3]);
        // |(b−a)×(c−a)| is twice the area: area weighting comes for free.
        let n = super::cross(
            super::sub(p(st[1]), p(st[0])),
            super::sub(p(st[2]), p(st[0])),
        );
        for &sv in ft {
            let vn = src.vn_of_split.get(sv).copied().flatten();
            if let Some(sum) = vn.and_then(|k| sums.get_mut(k)) {
                let s = sum.get_or_insert([0.0; 3]);
                for k in 0..3 {
                    s[k] += n[k];
                }
            }
        }
    }
    sums.into_iter().map(|s| s.map(normalize_or_z)).collect()
}

/// Writes the user's own OBJ text back with new positions: each `v` line's coordinates are
/// replaced (every `v` line, used or not; see [`Asset::file_positions`]), each used `vn`
/// line's numbers are recomputed, and every other byte is copied.
pub(crate) fn write_kept(asset: &Asset, src: &ObjSource, positions: &[[f64; 3]]) -> Vec<u8> {
    let v_new = asset.file_positions_f64(positions);
    let vn_new = vn_normals(asset, src, positions);
    // Edits in file order: `v` and `vn` lines each come in file order, so merge the two.
    let mut edits: Vec<(Range<usize>, String)> = Vec::with_capacity(v_new.len() + vn_new.len());
    for (line, p) in src.v_lines.iter().zip(&v_new) {
        edits.push((line.span.clone(), triple(*p)));
    }
    for (span, n) in src.vn_spans.iter().zip(&vn_new) {
        if let Some(n) = n {
            edits.push((span.clone(), triple(*n)));
        }
    }
    edits.sort_by_key(|(span, _)| span.start);
    splice(&src.text, &edits)
}

/// Writes a new OBJ (for glTF input or meshes made in code, which have no OBJ text to keep):
/// `v` per welded vertex (so seams cannot open), `vt` per file vertex with a UV, `vn` per
/// normal group recomputed from `positions`, and faces wound like the oriented surface.
pub(crate) fn write_new(asset: &Asset, positions: &[[f64; 3]]) -> Vec<u8> {
    let mut out = String::new();
    // `write!` into a String cannot fail; the results are ignored for that reason.
    let _ = writeln!(out, "# Written by Willow (conformal Willmore flow fairing)");
    // A refined asset writes the file's vertices then the new ones (refined.rs); any other
    // its welded vertices.
    // A PLY or OFF keeps its vertex numbering: its records are the split vertices.
    let refined = asset.refined_vertices(positions);
    let split = asset.split_vertex_positions(positions);
    let written = match (&refined, &split) {
        (Some((v, _)), _) => v.as_slice(),
        (None, Some(v)) => v.as_slice(),
        (None, None) => positions,
    };
    for p in written {
        let _ = writeln!(out, "v {}", triple(*p));
    }
    let v_of = |sv: usize, welded: usize| match (&refined, &split) {
        (Some((_, v_of_split)), _) => v_of_split.get(sv).copied().unwrap_or(welded),
        (None, Some(_)) => sv,
        (None, None) => welded,
    };
    let mut next = 0;
    let vt_of: Vec<Option<usize>> = match &asset.file.uvs {
        Some(uvs) => uvs
            .iter()
            .map(|uv| {
                uv.map(|[u, v]| {
                    let _ = writeln!(out, "vt {} {}", coordinate(u), coordinate(1.0 - v));
                    next += 1;
                    next - 1
                })
            })
            .collect(),
        None => Vec::new(),
    };
    let normals = asset.group_normals(positions);
    if let Some(normals) = &normals {
        for n in normals {
            let _ = writeln!(out, "vn {}", triple(*n));
        }
    }
    let group_of = |sv: usize| -> Option<usize> {
        let (groups, _) = asset.normal_groups.as_ref()?;
        groups.get(sv).copied().filter(|&g| g != UNWELDED)
    };
    for (ft, st) in asset
        .oriented_split_triangles()
        .iter()
        .zip(&asset.surface.triangles)
    {
        let vts = ft.map(|sv| vt_of.get(sv).copied().flatten());
        let vns = ft.map(group_of);
        let with_vt = vts.iter().all(Option::is_some);
        let with_vn = normals.is_some() && vns.iter().all(Option::is_some);
        out.push('f');
        for k in 0..3 {
            let _ = write!(out, " {}", v_of(ft[k], st[k]) + 1);
            let (vt, vn) = (vts[k].unwrap_or(0) + 1, vns[k].unwrap_or(0) + 1);
            let _ = match (with_vt, with_vn) {
                (true, true) => write!(out, "/{vt}/{vn}"),
                (true, false) => write!(out, "/{vt}"),
                (false, true) => write!(out, "//{vn}"),
                (false, false) => Ok(()),
            };
        }
        out.push('\n');
    }
    out.into_bytes()
}

mod refined;
pub(crate) use refined::write_refined;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn words_keep_offsets() {
        let words: Vec<(usize, &str)> = words_with_offsets("  v\t1  -2").collect();
        assert_eq!(words, vec![(2, "v"), (4, "1"), (7, "-2")]);
    }

    #[test]
    fn v_lines_with_weight_or_colour() {
        let v = parse_v("v 1 2 3 0.5 0.25 1", 0).unwrap();
        assert_eq!((v.stored, v.span), ([1.0, 2.0, 3.0], 2..7));
        assert_eq!(v.colour, Some([0.5, 0.25, 1.0]));
        let v = parse_v("v 1 2 3 2", 0).unwrap();
        assert_eq!((v.stored, v.span), ([0.5, 1.0, 1.5], 2..9));
        let v = parse_v("v 1 2 3 1.0", 0).unwrap();
        assert_eq!((v.stored, v.span), ([1.0, 2.0, 3.0], 2..7));
        for bad in [
            "v 1 2",
            "v 1 2 3 0",
            "v 1 2 3 4 5",
            "v 1 x 3",
            "v 1 2 3 1 2 3 4",
        ] {
            assert_eq!(parse_v(bad, 0).unwrap_err().code(), "parse_error", "{bad}");
        }
    }
}
