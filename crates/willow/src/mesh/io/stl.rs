//! STL, binary and ASCII: a list of triangles, each with a facet normal and three corner
//! positions.
//!
//! STL has no shared vertices: the file's vertices are its distinct corner positions, numbered
//! in order of first appearance (triangle by triangle, corners in order), which is how every
//! STL reader indexes them. Written back, each triangle gets its corners' new positions and a
//! recomputed facet normal, in the file's triangle order; everything else is kept: the binary
//! 80-byte header and each triangle's 2 attribute bytes (colour in some tools), the ASCII
//! `solid` names and layout (only numbers are replaced).
//!
//! Hand-written rather than a crate: the format is two pages, and the available crates
//! (`stl_io`) read into their own indexed mesh, dropping the header, attribute bytes and the
//! ASCII text that writing back keeps.

use super::text::{splice, triple, utf8, Words};
use super::{cross, normalize_or_z, sub, Asset, FileGeometry, Limits, MeshError};
use std::collections::HashMap;
use std::ops::Range;

const FORMAT: &str = "STL";

/// Bytes of a binary STL header (80) plus its triangle count (4).
const BINARY_HEADER: usize = 84;
/// Bytes per binary triangle: normal and 3 corners as 12 f32, and 2 attribute bytes.
const BINARY_TRIANGLE: usize = 50;

/// What an STL file has beyond its triangles: its bytes and where each number sits.
#[derive(Clone, Debug)]
pub(crate) enum StlSource {
    /// The whole file; triangle `i` is at `84 + 50·i`.
    Binary(Vec<u8>),
    /// The text, and for each facet the byte ranges of its normal and its 3 `vertex` triples.
    Ascii {
        text: String,
        facets: Vec<[Range<usize>; 4]>,
    },
}

/// Distinct corner positions, numbered in order of first appearance.
#[derive(Default)]
struct Welder {
    ids: HashMap<[u64; 3], usize>,
    positions: Vec<[f64; 3]>,
}

impl Welder {
    fn id(&mut self, p: [f64; 3]) -> usize {
        // `+ 0.0` turns -0.0 into +0.0 so the two are one position.
        let key = p.map(|x| (x + 0.0).to_bits());
        *self.ids.entry(key).or_insert_with(|| {
            self.positions.push(p);
            self.positions.len() - 1
        })
    }
}

pub(crate) fn read(bytes: &[u8], limits: &Limits) -> Result<(FileGeometry, StlSource), MeshError> {
    if super::format::is_binary_stl(bytes) {
        read_binary(bytes, limits)
    } else if let Some(e) = binary_length_mismatch(bytes) {
        Err(e)
    } else {
        read_ascii(bytes, limits)
    }
}

/// The error for a binary STL whose length is not the one its triangle count gives, or `None`
/// when the bytes are better read as ASCII STL (or as the text they are, for its error).
///
/// The length is the only sure sign of a binary STL, and it failed; so the bytes are taken
/// for a broken binary STL when they are not text: invalid UTF-8 or a NUL byte, which the
/// little-endian floats of any real binary STL have and an ASCII one never does. A binary
/// header may itself begin with `solid` (many exporters write it), so that word decides
/// nothing; without this, a truncated binary file was reported as "not UTF-8 text".
fn binary_length_mismatch(bytes: &[u8]) -> Option<MeshError> {
    let is_text = !bytes.contains(&0) && std::str::from_utf8(bytes).is_ok();
    if is_text || super::format::foreign_content(bytes).is_some() {
        return None;
    }
    let len = bytes.len() as u64;
    let Some(count) = bytes.get(80..84) else {
        return Some(MeshError::parse(
            FORMAT,
            format!(
                "a binary STL has an {BINARY_HEADER}-byte header with its triangle count, \
                 but the file has only {len} bytes (and it is not ASCII STL text)"
            ),
        ));
    };
    let n = u64::from(u32::from_le_bytes([count[0], count[1], count[2], count[3]]));
    let want = BINARY_HEADER as u64 + BINARY_TRIANGLE as u64 * n;
    let body = len - BINARY_HEADER as u64;
    let whole = body / BINARY_TRIANGLE as u64;
    let extra = body % BINARY_TRIANGLE as u64;
    let hint = if len < want {
        "truncated, or the count is wrong".to_string()
    } else {
        "bytes after the last triangle, or the count is wrong".to_string()
    };
    let holds = if extra == 0 {
        format!("{whole} triangles")
    } else {
        format!("{whole} triangles and {extra} bytes")
    };
    Some(MeshError::parse(
        FORMAT,
        format!(
            "binary STL header says {n} triangles ({BINARY_HEADER} + {BINARY_TRIANGLE}·{n} = \
             {want} bytes) but the file has {len} bytes, room for {holds} ({hint})"
        ),
    ))
}

fn f32_at(bytes: &[u8], at: usize) -> f64 {
    match bytes.get(at..at + 4) {
        Some(b) => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
        None => f64::NAN,
    }
}

fn read_binary(bytes: &[u8], limits: &Limits) -> Result<(FileGeometry, StlSource), MeshError> {
    // `is_binary_stl` checked that the length is exactly 84 + 50·n.
    let n = (bytes.len() - BINARY_HEADER) / BINARY_TRIANGLE;
    limits.check_faces(n)?;
    let mut welder = Welder::default();
    let mut triangles = Vec::with_capacity(n);
    let mut non_finite = super::super::error::Offenders::default();
    for t in 0..n {
        let at = BINARY_HEADER + BINARY_TRIANGLE * t + 12;
        let mut tri = [0; 3];
        for (k, slot) in tri.iter_mut().enumerate() {
            let p = [0, 4, 8].map(|d| f32_at(bytes, at + 12 * k + d));
            if !p.iter().all(|x| x.is_finite()) {
                non_finite.push(t);
            }
            *slot = welder.id(p);
        }
        // Checked as corners arrive: the welded table must not outgrow the limit first.
        limits.check_vertices(welder.positions.len())?;
        triangles.push(tri);
    }
    finish(welder, triangles, non_finite, limits)
        .map(|file| (file, StlSource::Binary(bytes.to_vec())))
}

fn parse_error(line: usize, what: &str) -> MeshError {
    MeshError::parse(FORMAT, format!("line {}: {what}", line + 1))
}

/// Words of an ASCII STL with the line of the last one, for errors at the end of the file.
struct Scanner<'a> {
    words: std::iter::Peekable<Words<'a>>,
    line: usize,
}

impl<'a> Scanner<'a> {
    fn next(&mut self) -> Option<(usize, usize, &'a str)> {
        let w = self.words.next()?;
        self.line = w.0;
        Some(w)
    }

    /// Skips the rest of line `line` (a `solid`/`endsolid` name).
    fn skip_line(&mut self, line: usize) {
        while self.words.peek().is_some_and(|w| w.0 == line) {
            self.words.next();
        }
    }

    fn expect(&mut self, keyword: &str) -> Result<(), MeshError> {
        match self.next() {
            Some((_, _, w)) if w == keyword => Ok(()),
            Some((line, _, w)) => Err(parse_error(
                line,
                &format!("expected `{keyword}`, found {w:?}"),
            )),
            None => Err(parse_error(
                self.line,
                &format!("the file ends where `{keyword}` was expected"),
            )),
        }
    }

    /// Three numbers and the byte range they span.
    fn three(&mut self, what: &str) -> Result<([f64; 3], Range<usize>), MeshError> {
        let mut p = [0.0; 3];
        let mut span = 0..0;
        for (k, x) in p.iter_mut().enumerate() {
            let (line, at, w) = self.next().ok_or_else(|| {
                parse_error(
                    self.line,
                    &format!("{what}: the file ends inside the numbers"),
                )
            })?;
            *x = w
                .parse()
                .map_err(|_| parse_error(line, &format!("{what}: bad number {w:?}")))?;
            if k == 0 {
                span.start = at;
            }
            span.end = at + w.len();
        }
        Ok((p, span))
    }
}

fn read_ascii(bytes: &[u8], limits: &Limits) -> Result<(FileGeometry, StlSource), MeshError> {
    let text = utf8(bytes, FORMAT)?;
    let body = text.strip_prefix('\u{feff}').unwrap_or(text);
    let mut sc = Scanner {
        words: Words::new(text, text.len() - body.len()).peekable(),
        line: 0,
    };
    let mut welder = Welder::default();
    let mut triangles: Vec<[usize; 3]> = Vec::new();
    let mut facets: Vec<[Range<usize>; 4]> = Vec::new();
    let mut non_finite = super::super::error::Offenders::default();
    while let Some((line, _, w)) = sc.next() {
        if w != "solid" {
            return Err(parse_error(
                line,
                &format!("expected `solid` (ASCII STL) or a binary STL, found {w:?}"),
            ));
        }
        sc.skip_line(line);
        loop {
            match sc.next() {
                Some((_, _, "facet")) => {
                    limits.check_faces(triangles.len() + 1)?;
                    sc.expect("normal")?;
                    let (_, normal) = sc.three("facet normal")?;
                    sc.expect("outer")?;
                    sc.expect("loop")?;
                    let mut tri = [0; 3];
                    let mut spans = [normal, 0..0, 0..0, 0..0];
                    for k in 0..3 {
                        sc.expect("vertex")?;
                        let (p, span) = sc.three("vertex")?;
                        if !p.iter().all(|x| x.is_finite()) {
                            non_finite.push(triangles.len());
                        }
                        tri[k] = welder.id(p);
                        spans[k + 1] = span;
                    }
                    limits.check_vertices(welder.positions.len())?;
                    sc.expect("endloop")?;
                    sc.expect("endfacet")?;
                    triangles.push(tri);
                    facets.push(spans);
                }
                Some((l, _, "endsolid")) => {
                    sc.skip_line(l);
                    break;
                }
                Some((l, _, w)) => {
                    return Err(parse_error(
                        l,
                        &format!("expected `facet` or `endsolid`, found {w:?}"),
                    ))
                }
                // Many exporters stop without `endsolid`; nothing is lost.
                None => break,
            }
        }
    }
    let file = finish(welder, triangles, non_finite, limits)?;
    Ok((
        file,
        StlSource::Ascii {
            text: text.to_owned(),
            facets,
        },
    ))
}

/// The file geometry of welded STL corners: one block, no UVs or normals (facet normals are
/// per triangle and recomputed on writing).
fn finish(
    welder: Welder,
    triangles: Vec<[usize; 3]>,
    non_finite: super::super::error::Offenders<usize>,
    limits: &Limits,
) -> Result<FileGeometry, MeshError> {
    if !non_finite.is_empty() {
        // Named by triangle: STL has no vertex numbers of its own to name.
        return Err(MeshError::parse(
            FORMAT,
            format!(
                "{} triangles have non-finite (NaN or infinite) corners; first: {}",
                non_finite.count, non_finite
            ),
        ));
    }
    if triangles.is_empty() {
        return Err(MeshError::Empty {
            vertices: 0,
            faces: 0,
        });
    }
    limits.check_vertices(welder.positions.len())?;
    Ok(FileGeometry::one_block(welder.positions, triangles))
}

/// Unit normal of each file triangle, wound like the oriented surface, in new positions.
fn facet_normals(asset: &Asset, positions: &[[f64; 3]]) -> Vec<[f64; 3]> {
    asset
        .surface
        .triangles
        .iter()
        .map(|t| {
            let p = |v: usize| positions.get(v).copied().unwrap_or([0.0; 3]);
            normalize_or_z(cross(sub(p(t[1]), p(t[0])), sub(p(t[2]), p(t[0]))))
        })
        .collect()
}

/// The three new corner positions of each file triangle, wound like the oriented surface.
fn corners(asset: &Asset, positions: &[[f64; 3]]) -> Vec<[[f64; 3]; 3]> {
    asset
        .surface
        .triangles
        .iter()
        .map(|t| t.map(|v| positions.get(v).copied().unwrap_or([0.0; 3])))
        .collect()
}

/// Writes the user's STL back with new positions and facet normals, triangle by triangle in
/// file order; everything else (header, attribute bytes, solid names, layout) is kept.
///
/// A triangle the orientation pass flipped is written with its corners 2 and 3 swapped, so
/// the file comes out consistently wound with normals pointing out.
pub(crate) fn write_kept(asset: &Asset, src: &StlSource, positions: &[[f64; 3]]) -> Vec<u8> {
    let normals = facet_normals(asset, positions);
    let corners = corners(asset, positions);
    // The file's triangle of each surface triangle (they differ once `repair` dropped some;
    // a dropped triangle keeps its stored bytes).
    let record = |t: usize| -> usize {
        asset
            .file
            .face_of_triangle
            .as_ref()
            .and_then(|f| f.get(t))
            .map_or(t, |&f| f as usize)
    };
    match src {
        StlSource::Binary(bytes) => {
            let mut out = bytes.clone();
            for (t, (n, c)) in normals.iter().zip(&corners).enumerate() {
                let at = BINARY_HEADER + BINARY_TRIANGLE * record(t);
                let values = [*n, c[0], c[1], c[2]];
                for (k, x) in values.iter().flatten().enumerate() {
                    if let Some(slot) = out.get_mut(at + 4 * k..at + 4 * k + 4) {
                        slot.copy_from_slice(&(*x as f32).to_le_bytes());
                    }
                }
            }
            out
        }
        StlSource::Ascii { text, facets } => {
            let mut edits = Vec::with_capacity(facets.len() * 4);
            for (t, (n, c)) in normals.iter().zip(&corners).enumerate() {
                let Some(spans) = facets.get(record(t)) else {
                    continue;
                };
                edits.push((spans[0].clone(), triple(*n)));
                for k in 0..3 {
                    edits.push((spans[k + 1].clone(), triple(c[k])));
                }
            }
            splice(text, &edits)
        }
    }
}

/// A new binary STL of the surface (for input in another format): one triangle per surface
/// face in face order, f32 as the format has it, attribute bytes zero.
pub(crate) fn write_new(asset: &Asset, positions: &[[f64; 3]]) -> Result<Vec<u8>, MeshError> {
    let normals = facet_normals(asset, positions);
    let corners = corners(asset, positions);
    let count = u32::try_from(corners.len()).map_err(|_| MeshError::TooLarge {
        what: "triangles for binary STL",
        value: corners.len(),
        limit: u32::MAX as usize,
    })?;
    let mut out = Vec::with_capacity(BINARY_HEADER + BINARY_TRIANGLE * corners.len());
    // Not starting with `solid`, so no reader mistakes it for ASCII.
    out.extend_from_slice(b"Willow: faired by conformal Willmore flow");
    out.resize(80, b' ');
    out.extend_from_slice(&count.to_le_bytes());
    for (n, c) in normals.iter().zip(&corners) {
        for x in [*n, c[0], c[1], c[2]].iter().flatten() {
            out.extend_from_slice(&(*x as f32).to_le_bytes());
        }
        out.extend_from_slice(&[0, 0]);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A binary STL of `n` triangles (all corners at the origin but the count's own), its
    /// header beginning with `header`.
    fn binary(header: &[u8], n: u32) -> Vec<u8> {
        let mut b = vec![0u8; 80];
        b[..header.len()].copy_from_slice(header);
        b.extend_from_slice(&n.to_le_bytes());
        for t in 0..n {
            b.extend_from_slice(&[0u8; 12]);
            for k in 0..3u32 {
                for d in 0..3u32 {
                    let x = (t * 9 + k * 3 + d) as f32 + 0.5;
                    b.extend_from_slice(&x.to_le_bytes());
                }
            }
            b.extend_from_slice(&[0, 0]);
        }
        b
    }

    fn message(bytes: &[u8]) -> String {
        match read(bytes, &Limits::default()) {
            Ok(_) => panic!("read"),
            Err(e) => e.to_string(),
        }
    }

    /// Issue 42: a binary STL with a wrong triangle count names the count and the size, not
    /// "not UTF-8 text", whether its header begins with `solid` or not.
    #[test]
    fn a_binary_stl_with_a_wrong_count_names_the_count_and_the_size() {
        for header in [&b"binary"[..], b"solid exported by a CAD tool"] {
            let mut short = binary(header, 3);
            short.truncate(84 + 50 * 2 + 10);
            assert_eq!(
                message(&short),
                "cannot parse STL: binary STL header says 3 triangles (84 + 50·3 = 234 bytes) \
                 but the file has 194 bytes, room for 2 triangles and 10 bytes (truncated, or \
                 the count is wrong)"
            );
            let mut long = binary(header, 2);
            long.extend_from_slice(&[0u8; 50]);
            assert_eq!(
                message(&long),
                "cannot parse STL: binary STL header says 2 triangles (84 + 50·2 = 184 bytes) \
                 but the file has 234 bytes, room for 3 triangles (bytes after the last \
                 triangle, or the count is wrong)"
            );
        }
        assert!(message(&[1u8, 0, 2]).contains("only 3 bytes"));
        // Whole files still read, and ASCII text still gets the ASCII reader's errors.
        assert!(read(&binary(b"solid x", 2), &Limits::default()).is_ok());
        assert!(message(b"solid x\nfacet normal 0 0 x\n").contains("line 2"));
        assert!(message(b"hello world").contains("expected `solid`"));
    }
}
