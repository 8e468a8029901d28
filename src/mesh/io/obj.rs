//! Wavefront OBJ: read with tobj from memory, written by hand.
//!
//! Connectivity comes from the position indices (`single_index = false`): keying vertices by
//! (position, UV) would cut the surface open along every UV seam. UVs and normals stay per
//! corner. A pre-scan of the text, before tobj allocates anything, enforces the limits,
//! refuses point/line-only files, checks every face index (tobj can overflow on `f 0` or huge
//! indices) and collects `mtllib`/`usemtl` names, which tobj only reports via material files
//! we never open.

use super::{Affine, Asset, Block, FileGeometry, Limits, MeshError};
use std::collections::HashMap;
use std::fmt::Write as _;

const FORMAT: &str = "OBJ";

/// What an OBJ file has that the surface does not: the `vt` list, per-corner indices and names.
#[derive(Clone, Debug)]
pub(crate) struct ObjSource {
    /// Every `vt` tobj read, models concatenated, in OBJ's convention (origin bottom left).
    texcoords: Vec<[f64; 2]>,
    /// Per file vertex: index into `texcoords`.
    vt_of: Vec<Option<usize>>,
    /// `mtllib` file names, in order of appearance.
    mtllibs: Vec<String>,
    /// Runs of faces sharing an object/group name and material.
    groups: Vec<ObjGroup>,
}

#[derive(Clone, Debug)]
struct ObjGroup {
    name: Option<String>,
    material: Option<String>,
    faces: std::ops::Range<usize>,
}

/// A file vertex is a distinct (position bits, `vt` index, `vn` index) corner.
type CornerKey = ([u64; 3], Option<usize>, Option<usize>);

impl ObjSource {
    /// No UVs, names or libraries: for meshes made in code.
    pub(crate) fn empty(file_vertices: usize) -> ObjSource {
        ObjSource {
            texcoords: Vec::new(),
            vt_of: vec![None; file_vertices],
            mtllibs: Vec::new(),
            groups: Vec::new(),
        }
    }
}

/// Counts and names found by [`prescan`].
#[derive(Debug, Default)]
struct Prescan {
    faces: usize,
    triangles: usize,
    /// First line holding an `l` polyline of 3+ vertices: tobj reads those as faces.
    polyline_line: Option<usize>,
    points: usize,
    lines: usize,
    mtllibs: Vec<String>,
    materials: Vec<String>,
}

/// Element counts, to resolve and check face indices.
#[derive(Default)]
struct Counts {
    v: usize,
    vt: usize,
    vn: usize,
}

fn prescan(text: &str, limits: &Limits) -> Result<Prescan, MeshError> {
    // Pass 1: totals, so positive indices may point forward (as tobj allows).
    let mut total = Counts::default();
    for line in text.lines() {
        match line.split_whitespace().next() {
            Some("v") => total.v += 1,
            Some("vt") => total.vt += 1,
            Some("vn") => total.vn += 1,
            _ => {}
        }
    }
    limits.check_vertices(total.v)?;

    let mut scan = Prescan::default();
    let mut so_far = Counts::default();
    let mut bad_faces = super::super::error::Offenders::default();
    for (line_no, line) in text.lines().enumerate() {
        let mut words = line.split_whitespace();
        let keyword = words.next();
        match keyword {
            Some("v") => so_far.v += 1,
            Some("vt") => so_far.vt += 1,
            Some("vn") => so_far.vn += 1,
            Some("mtllib") => {
                let name = rest_of(line);
                if !name.is_empty() && !scan.mtllibs.iter().any(|m| m == name) {
                    scan.mtllibs.push(name.to_owned());
                }
            }
            Some("usemtl") => {
                let name = rest_of(line);
                if !name.is_empty() && !scan.materials.iter().any(|m| m == name) {
                    scan.materials.push(name.to_owned());
                }
            }
            Some(kw @ ("f" | "l" | "p")) => {
                let corners: Vec<&str> = words.collect();
                let mut in_range = true;
                for c in &corners {
                    let mut parts = c.split('/');
                    let checks = [
                        (so_far.v, total.v),
                        (so_far.vt, total.vt),
                        (so_far.vn, total.vn),
                    ];
                    for (slot, (sofar, tot)) in checks.into_iter().enumerate() {
                        match parts.next() {
                            None | Some("") => {
                                if slot == 0 {
                                    return Err(parse_error(line_no, "empty vertex index"));
                                }
                            }
                            Some(s) => {
                                let i: i64 = s.parse().map_err(|_| {
                                    parse_error(line_no, &format!("bad index {s:?}"))
                                })?;
                                let ok = if i > 0 {
                                    (i as u64) <= tot as u64
                                } else {
                                    i != 0 && i.unsigned_abs() <= sofar as u64
                                };
                                if !ok {
                                    if slot == 0 {
                                        in_range = false;
                                    } else {
                                        return Err(parse_error(
                                            line_no,
                                            &format!(
                                                "{} index {i} out of range",
                                                ["v", "vt", "vn"][slot]
                                            ),
                                        ));
                                    }
                                }
                            }
                        }
                    }
                    if parts.next().is_some() {
                        return Err(parse_error(line_no, &format!("bad corner {c:?}")));
                    }
                }
                // tobj reads `f` and `l` the same way: by corner count.
                let n = corners.len();
                match (kw, n) {
                    ("p", _) => scan.points += 1,
                    (_, 0) => return Err(parse_error(line_no, "element without vertices")),
                    (_, 1) => scan.points += 1,
                    (_, 2) => scan.lines += 1,
                    ("l", _) => {
                        scan.lines += 1;
                        scan.polyline_line.get_or_insert(line_no);
                    }
                    _ => {
                        if !in_range {
                            bad_faces.push(scan.faces);
                        }
                        scan.faces += 1;
                        scan.triangles += n - 2;
                        limits.check_faces(scan.triangles)?;
                    }
                }
            }
            _ => {}
        }
    }
    if !bad_faces.is_empty() {
        return Err(MeshError::IndexOutOfRange {
            faces: bad_faces,
            vertex_count: total.v,
        });
    }
    if scan.faces == 0 {
        return Err(if scan.points + scan.lines > 0 {
            MeshError::PointsOrLinesOnly {
                points: scan.points,
                lines: scan.lines,
            }
        } else {
            MeshError::Empty {
                vertices: total.v,
                faces: 0,
            }
        });
    }
    if let Some(line_no) = scan.polyline_line {
        return Err(MeshError::unsupported(format!(
            "line {}: polylines of 3 or more vertices next to faces (tobj would read them as faces)",
            line_no + 1
        )));
    }
    Ok(scan)
}

/// Everything after the keyword: names may contain spaces.
fn rest_of(line: &str) -> &str {
    let line = line.trim_start();
    line.split_once(char::is_whitespace)
        .map(|(_, r)| r.trim())
        .unwrap_or("")
}

fn parse_error(line_no: usize, what: &str) -> MeshError {
    MeshError::parse(FORMAT, format!("line {}: {what}", line_no + 1))
}

pub(crate) fn read(bytes: &[u8], limits: &Limits) -> Result<(FileGeometry, ObjSource), MeshError> {
    let text = std::str::from_utf8(bytes)
        .map_err(|e| MeshError::parse(FORMAT, format!("not UTF-8 text: {e}")))?;
    let scan = prescan(text, limits)?;

    let options = tobj::LoadOptions {
        single_index: false,
        triangulate: true,
        ignore_points: true,
        ignore_lines: true,
    };
    // Material files are never opened: the loader answers every `mtllib` with a stand-in for
    // each `usemtl` name, so tobj still splits models by material and reports their names.
    let stand_ins: Vec<tobj::Material> = scan
        .materials
        .iter()
        .map(|name| tobj::Material {
            name: name.clone(),
            ..Default::default()
        })
        .collect();
    let loader = |_: &std::path::Path| -> tobj::MTLLoadResult {
        let map = stand_ins
            .iter()
            .enumerate()
            .map(|(i, m)| (m.name.clone(), i))
            .collect();
        Ok((stand_ins.clone(), map))
    };
    // tobj asks for materials only on an `mtllib` line; a file with `usemtl` but no `mtllib`
    // gets a stand-in line first (read by nobody, never written out) so its names survive.
    let prefix: &[u8] = if scan.mtllibs.is_empty() && !scan.materials.is_empty() {
        b"mtllib willow-stand-in.mtl\n"
    } else {
        b""
    };
    let mut reader = std::io::Read::chain(prefix, bytes);
    let mut reader = std::io::BufReader::new(&mut reader);
    let (models, materials) = tobj::load_obj_buf(&mut reader, &options, loader)
        .map_err(|e| MeshError::parse(FORMAT, e.to_string()))?;
    let materials = materials.unwrap_or_default();

    let mut local: Vec<[f64; 3]> = Vec::new();
    let mut texcoords: Vec<[f64; 2]> = Vec::new();
    let mut vt_of: Vec<Option<usize>> = Vec::new();
    let mut vn_of: Vec<Option<usize>> = Vec::new();
    let mut triangles: Vec<[usize; 3]> = Vec::new();
    let mut groups = Vec::new();
    let mut corner_ids: HashMap<CornerKey, usize> = HashMap::new();
    let mut normal_base = 0usize;
    let mut any_normals = false;
    for model in &models {
        let m = &model.mesh;
        let tex_base = texcoords.len();
        for uv in m.texcoords.chunks_exact(2) {
            texcoords.push([uv[0], uv[1]]);
        }
        let corners = m.indices.len();
        let has_vt = !m.texcoord_indices.is_empty() && m.texcoord_indices.len() == corners;
        let has_vn = !m.normal_indices.is_empty() && m.normal_indices.len() == corners;
        any_normals |= has_vn;
        let first_face = triangles.len();
        let mut tri = [0usize; 3];
        for c in 0..corners - corners % 3 {
            let pi = m.indices[c] as usize;
            let p = match m.positions.get(3 * pi..3 * pi + 3) {
                Some(p) => [p[0], p[1], p[2]],
                None => return Err(MeshError::parse(FORMAT, "face index past the positions")),
            };
            let vt = has_vt.then(|| tex_base + m.texcoord_indices[c] as usize);
            let vn = has_vn.then(|| normal_base + m.normal_indices[c] as usize);
            let key = (p.map(|x| (x + 0.0).to_bits()), vt, vn);
            let id = *corner_ids.entry(key).or_insert_with(|| {
                local.push(p);
                vt_of.push(vt);
                vn_of.push(vn);
                local.len() - 1
            });
            tri[c % 3] = id;
            if c % 3 == 2 {
                triangles.push(tri);
            }
        }
        normal_base += m.normals.len() / 3;
        if triangles.len() > first_face {
            let name = (!model.name.is_empty() && model.name != "unnamed_object")
                .then(|| model.name.clone());
            let material = m
                .material_id
                .and_then(|i| materials.get(i))
                .map(|mat| mat.name.clone());
            groups.push(ObjGroup {
                name,
                material,
                faces: first_face..triangles.len(),
            });
        }
    }
    limits.check_vertices(local.len())?;
    limits.check_faces(triangles.len())?;

    let uvs = vt_of.iter().any(Option::is_some).then(|| {
        vt_of
            .iter()
            .map(|vt| {
                vt.and_then(|i| texcoords.get(i))
                    .map(|uv| [uv[0], 1.0 - uv[1]])
            })
            .collect()
    });
    let normal_keys = any_normals.then(|| {
        vn_of
            .iter()
            .map(|vn| vn.map_or(u64::MAX, |i| i as u64))
            .collect()
    });
    let n = local.len();
    let file = FileGeometry {
        local,
        blocks: vec![Block {
            start: 0,
            len: n,
            to_world: Affine::IDENTITY,
            to_local: Affine::IDENTITY,
        }],
        triangles,
        uvs,
        normal_keys,
    };
    let src = ObjSource {
        texcoords,
        vt_of,
        mtllibs: scan.mtllibs,
        groups,
    };
    Ok((file, src))
}

/// Writes OBJ text: `v` per welded vertex (so seams cannot open), `vt` from the source's list
/// (or one per glTF vertex with a UV), `vn` per normal group recomputed from `positions`, and
/// faces wound like the oriented surface with their original per-corner UV indices.
pub(crate) fn write(asset: &Asset, positions: &[[f64; 3]], src: Option<&ObjSource>) -> Vec<u8> {
    let mut out = String::new();
    // `write!` into a String cannot fail; the results are ignored for that reason.
    let _ = writeln!(out, "# Written by Willow (conformal Willmore flow fairing)");
    if let Some(src) = src {
        for lib in &src.mtllibs {
            let _ = writeln!(out, "mtllib {lib}");
        }
    }
    for p in positions {
        let _ = writeln!(out, "v {} {} {}", p[0], p[1], p[2]);
    }

    // vt: the source list verbatim, or one per file vertex that has a UV.
    let vt_of: Vec<Option<usize>> = match src {
        Some(src) => {
            for uv in &src.texcoords {
                let _ = writeln!(out, "vt {} {}", uv[0], uv[1]);
            }
            src.vt_of.clone()
        }
        None => match &asset.file.uvs {
            Some(uvs) => {
                let mut next = 0;
                uvs.iter()
                    .map(|uv| {
                        uv.map(|[u, v]| {
                            let _ = writeln!(out, "vt {} {}", u, 1.0 - v);
                            next += 1;
                            next - 1
                        })
                    })
                    .collect()
            }
            None => Vec::new(),
        },
    };

    let normals = asset.group_normals(positions);
    if let Some(normals) = &normals {
        for n in normals {
            let _ = writeln!(out, "vn {} {} {}", n[0], n[1], n[2]);
        }
    }
    let group_of = |fv: usize| -> Option<usize> {
        let (groups, _) = asset.normal_groups.as_ref()?;
        groups.get(fv).copied().filter(|&g| g != super::UNWELDED)
    };

    let faces = asset.oriented_file_triangles();
    let whole = [ObjGroup {
        name: None,
        material: None,
        faces: 0..faces.len(),
    }];
    let groups: &[ObjGroup] = match src {
        Some(src) if !src.groups.is_empty() => &src.groups,
        _ => &whole,
    };
    for g in groups {
        if let Some(name) = &g.name {
            let _ = writeln!(out, "o {name}");
        }
        if let Some(m) = &g.material {
            let _ = writeln!(out, "usemtl {m}");
        }
        for (ft, st) in faces
            .get(g.faces.clone())
            .unwrap_or(&[])
            .iter()
            .zip(asset.surface.triangles.get(g.faces.clone()).unwrap_or(&[]))
        {
            let vts = ft.map(|fv| vt_of.get(fv).copied().flatten());
            let vns = ft.map(group_of);
            let with_vt = vts.iter().all(Option::is_some);
            let with_vn = normals.is_some() && vns.iter().all(Option::is_some);
            out.push('f');
            for k in 0..3 {
                let _ = write!(out, " {}", st[k] + 1);
                match (with_vt, with_vn) {
                    (true, true) => {
                        let _ = write!(
                            out,
                            "/{}/{}",
                            vts[k].unwrap_or(0) + 1,
                            vns[k].unwrap_or(0) + 1
                        );
                    }
                    (true, false) => {
                        let _ = write!(out, "/{}", vts[k].unwrap_or(0) + 1);
                    }
                    (false, true) => {
                        let _ = write!(out, "//{}", vns[k].unwrap_or(0) + 1);
                    }
                    (false, false) => {}
                }
            }
            out.push('\n');
        }
    }
    out.into_bytes()
}
