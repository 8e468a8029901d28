//! STL, PLY and OFF in and out: the file's own vertex and triangle order survive a round trip,
//! only coordinates (and normals) change, and colours, UVs, attribute bytes and everything
//! else the flow does not touch are kept byte for byte. Files are generated here, with their
//! layout known, so each kept byte can be checked.

// Vertex i is checked across several parallel arrays (old bytes, new bytes, expected).
#![allow(clippy::needless_range_loop)]

use willow::mesh::generate::icosphere;
use willow::mesh::io::{Asset, Format, Limits};

fn read(bytes: &[u8], format: Format) -> Asset {
    Asset::read(bytes, format, &Limits::default()).unwrap()
}

/// A move every vertex makes differently but predictably: scale by 2 about the origin, then
/// shift. On a sphere the new outward normal at a vertex is still its radial direction.
fn moved(p: &[[f64; 3]]) -> Vec<[f64; 3]> {
    p.iter()
        .map(|q| [2.0 * q[0] + 0.5, 2.0 * q[1] - 0.25, 2.0 * q[2] + 0.125])
        .collect()
}

const SHIFT: [f64; 3] = [0.5, -0.25, 0.125];

fn radial(p: [f64; 3]) -> [f64; 3] {
    let d = [p[0] - SHIFT[0], p[1] - SHIFT[1], p[2] - SHIFT[2]];
    let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    d.map(|x| x / l)
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// A sphere shuffled so file order differs from any order the library might produce itself:
/// vertex i of the file is vertex `perm[i]` of the icosphere.
fn scanner_sphere() -> (Vec<[f64; 3]>, Vec<[usize; 3]>) {
    let m = icosphere(2);
    let n = m.positions.len();
    // A fixed permutation (multiplication by a unit mod n).
    let perm: Vec<usize> = (0..n).map(|i| (i * 37 + 11) % n).collect();
    let mut inv = vec![0; n];
    for (i, &p) in perm.iter().enumerate() {
        inv[p] = i;
    }
    let positions = perm.iter().map(|&p| m.positions[p]).collect();
    let triangles = m.triangles.iter().map(|t| t.map(|v| inv[v])).collect();
    (positions, triangles)
}

/// A scanner's per-vertex colour and confidence, distinct per vertex.
fn colour(i: usize) -> [u8; 4] {
    [
        (i * 7) as u8,
        (i * 13 + 5) as u8,
        (i * 29 + 1) as u8,
        200 + (i % 50) as u8,
    ]
}

fn uv(i: usize) -> [f32; 2] {
    [(i % 17) as f32 / 17.0, (i % 23) as f32 / 23.0]
}

// ---------------------------------------------------------------------------------------
// PLY

/// Vertex layout: float x y z, float nx ny nz, uchar red green blue alpha, float s t,
/// float confidence; then an `int` face list and a custom per-face `uchar flags`.
fn ply_header(format: &str, n: usize, f: usize) -> String {
    format!(
        "ply\nformat {format} 1.0\ncomment made by a scanner-like generator\n\
         element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n\
         property float nx\nproperty float ny\nproperty float nz\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar alpha\n\
         property float s\nproperty float t\nproperty float confidence\n\
         element face {f}\nproperty list uchar int vertex_indices\nproperty uchar flags\n\
         end_header\n"
    )
}

/// Bytes of one vertex record: 12 + 12 + 4 + 8 + 4.
const PLY_RECORD: usize = 40;

fn binary_ply(p: &[[f64; 3]], t: &[[usize; 3]], big: bool) -> Vec<u8> {
    let name = if big {
        "binary_big_endian"
    } else {
        "binary_little_endian"
    };
    let mut out = ply_header(name, p.len(), t.len()).into_bytes();
    let f = |out: &mut Vec<u8>, x: f32| {
        out.extend_from_slice(&if big {
            x.to_be_bytes()
        } else {
            x.to_le_bytes()
        })
    };
    for (i, q) in p.iter().enumerate() {
        for x in q {
            f(&mut out, *x as f32);
        }
        for _ in 0..3 {
            f(&mut out, 0.0); // stale normals: recomputed on writing
        }
        out.extend_from_slice(&colour(i));
        f(&mut out, uv(i)[0]);
        f(&mut out, uv(i)[1]);
        f(&mut out, 0.5 + i as f32);
    }
    for (k, tri) in t.iter().enumerate() {
        out.push(3);
        for &v in tri {
            let v = v as i32;
            out.extend_from_slice(&if big {
                v.to_be_bytes()
            } else {
                v.to_le_bytes()
            });
        }
        out.push(k as u8);
    }
    out
}

fn ascii_ply(p: &[[f64; 3]], t: &[[usize; 3]]) -> String {
    let mut out = ply_header("ascii", p.len(), t.len());
    for (i, q) in p.iter().enumerate() {
        let c = colour(i);
        out += &format!(
            "{} {} {} 0 0 0 {} {} {} {} {} {} {}\n",
            q[0],
            q[1],
            q[2],
            c[0],
            c[1],
            c[2],
            c[3],
            uv(i)[0],
            uv(i)[1],
            0.5 + i as f32
        );
    }
    for (k, tri) in t.iter().enumerate() {
        out += &format!("3 {} {} {} {}\n", tri[0], tri[1], tri[2], k % 256);
    }
    out
}

/// The file vertices' new positions must be the welded ones, scattered in file order.
fn expected_file_positions(a: &Asset, new: &[[f64; 3]]) -> Vec<[f64; 3]> {
    a.file_to_welded()
        .iter()
        .map(|w| new[w.expect("every vertex is used")])
        .collect()
}

fn check_read(a: &Asset, p: &[[f64; 3]], t: &[[usize; 3]]) {
    assert_eq!(a.file_vertex_count(), p.len());
    assert_eq!(a.surface().vertex_count(), p.len());
    assert_eq!(a.surface().face_count(), t.len());
    // Same triangles in the same order over file vertices (winding may be made consistent).
    for (got, want) in a.file_triangles().iter().zip(t) {
        let (mut g, mut w) = (*got, *want);
        g.sort_unstable();
        w.sort_unstable();
        assert_eq!(g, w);
    }
    // The file vertex i sits where the file put it.
    for (i, w) in a.file_to_welded().iter().enumerate() {
        let s = a.surface().positions[w.unwrap()];
        for k in 0..3 {
            assert!((s[k] - p[i][k]).abs() < 1e-6);
        }
    }
}

#[test]
fn binary_ply_with_colours_keeps_every_byte_but_positions_and_normals() {
    let (p, t) = scanner_sphere();
    for big in [false, true] {
        let bytes = binary_ply(&p, &t, big);
        assert_eq!(Format::sniff(&bytes), Some(Format::Ply));
        let a = read(&bytes, Format::Ply);
        check_read(&a, &p, &t);
        // UVs kept per vertex (glTF convention: v flipped).
        let uvs = a.corner_uvs().unwrap();
        for (corners, tri) in uvs.iter().zip(a.file_triangles()) {
            for k in 0..3 {
                let want = uv(tri[k]);
                assert!((corners[k][0] - want[0]).abs() < 1e-6);
                assert!((corners[k][1] - (1.0 - want[1])).abs() < 1e-6);
            }
        }
        let new = moved(&a.surface().positions);
        let out = a.write(&new, Format::Ply).unwrap();
        assert_eq!(out.len(), bytes.len());
        let body = bytes.len() - t.len() * 14 - p.len() * PLY_RECORD;
        assert_eq!(out[..body], bytes[..body], "header kept");
        assert_eq!(
            out[body + p.len() * PLY_RECORD..],
            bytes[body + p.len() * PLY_RECORD..],
            "faces kept"
        );
        let want = expected_file_positions(&a, &new);
        let f = |r: &[u8], k: usize| {
            let b: [u8; 4] = r[4 * k..4 * k + 4].try_into().unwrap();
            f64::from(if big {
                f32::from_be_bytes(b)
            } else {
                f32::from_le_bytes(b)
            })
        };
        for i in 0..p.len() {
            let at = body + i * PLY_RECORD;
            let (old, r) = (&bytes[at..at + PLY_RECORD], &out[at..at + PLY_RECORD]);
            assert_eq!(
                r[24..],
                old[24..],
                "colour, UV and confidence of vertex {i} kept"
            );
            let n = [f(r, 3), f(r, 4), f(r, 5)];
            for k in 0..3 {
                assert_eq!(f(r, k), want[i][k] as f32 as f64, "vertex {i} moved");
            }
            assert!((dot(n, n) - 1.0).abs() < 1e-6);
            assert!(
                dot(n, radial(want[i])) > 0.97,
                "normal of vertex {i} points out"
            );
        }
        // And it reads back as the same surface at the new positions.
        let b = read(&out, Format::Ply);
        check_read(&b, &want, &t);
    }
}

#[test]
fn ascii_ply_replaces_only_the_numbers_of_positions_and_normals() {
    let (p, t) = scanner_sphere();
    let text = ascii_ply(&p, &t);
    let a = read(text.as_bytes(), Format::Ply);
    check_read(&a, &p, &t);
    let new = moved(&a.surface().positions);
    let out = String::from_utf8(a.write(&new, Format::Ply).unwrap()).unwrap();
    let want = expected_file_positions(&a, &new);
    let (old_lines, new_lines): (Vec<&str>, Vec<&str>) =
        (text.lines().collect(), out.lines().collect());
    assert_eq!(old_lines.len(), new_lines.len());
    let header = old_lines.iter().position(|l| *l == "end_header").unwrap() + 1;
    assert_eq!(old_lines[..header], new_lines[..header]);
    for i in 0..p.len() {
        let (o, w): (Vec<&str>, Vec<&str>) = (
            old_lines[header + i].split(' ').collect(),
            new_lines[header + i].split(' ').collect(),
        );
        assert_eq!(o[6..], w[6..], "colour, UV, confidence of vertex {i}");
        for k in 0..3 {
            assert_eq!(
                w[k].parse::<f64>().unwrap(),
                want[i][k],
                "exact f64 in ASCII"
            );
        }
        let n: Vec<f64> = w[3..6].iter().map(|x| x.parse().unwrap()).collect();
        assert!(dot([n[0], n[1], n[2]], radial(want[i])) > 0.97);
    }
    assert_eq!(old_lines[header + p.len()..], new_lines[header + p.len()..]);
}

#[test]
fn ply_errors_name_the_file_face_and_refuse_integer_coordinates() {
    let text = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
                property float z\nelement face 2\nproperty list uchar int vertex_indices\n\
                end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 1 7\n";
    let e = Asset::read(text.as_bytes(), Format::Ply, &Limits::default()).unwrap_err();
    assert_eq!(e.code(), "index_out_of_range");
    assert!(e.to_string().contains("first: 1"), "{e}");
    let ints = text.replace("property float x", "property int x");
    let e = Asset::read(ints.as_bytes(), Format::Ply, &Limits::default()).unwrap_err();
    assert!(e.to_string().contains("`x` is not float"), "{e}");
    // A header that claims a billion vertices is refused before anything is allocated.
    let huge = text.replace("element vertex 3", "element vertex 1000000000");
    let e = Asset::read(huge.as_bytes(), Format::Ply, &Limits::default()).unwrap_err();
    assert_eq!(e.code(), "too_large");
    let short = binary_ply(&[[0.0; 3]; 3], &[[0, 1, 2]], false);
    let e = Asset::read(&short[..short.len() - 3], Format::Ply, &Limits::default()).unwrap_err();
    assert_eq!(e.code(), "truncated_buffer", "{e}");
}

// ---------------------------------------------------------------------------------------
// STL

/// Triangle soup with a distinct attribute word per triangle and zero normals.
fn binary_stl(p: &[[f64; 3]], t: &[[usize; 3]]) -> Vec<u8> {
    let mut out = b"solid-looking header written by a CAD tool".to_vec();
    out.resize(80, b'.');
    out.extend_from_slice(&(t.len() as u32).to_le_bytes());
    for (k, tri) in t.iter().enumerate() {
        out.extend_from_slice(&[0u8; 12]);
        for &v in tri {
            for x in p[v] {
                out.extend_from_slice(&(x as f32).to_le_bytes());
            }
        }
        out.extend_from_slice(&(k as u16 ^ 0x5a5a).to_le_bytes());
    }
    out
}

fn ascii_stl(p: &[[f64; 3]], t: &[[usize; 3]]) -> String {
    let mut out = String::from("solid my part\n");
    for tri in t {
        out += "  facet normal 0 0 0\n    outer loop\n";
        for &v in tri {
            out += &format!("      vertex {} {} {}\n", p[v][0], p[v][1], p[v][2]);
        }
        out += "    endloop\n  endfacet\n";
    }
    out + "endsolid my part\n"
}

fn f32s(b: &[u8]) -> Vec<f64> {
    b.chunks(4)
        .map(|c| f64::from(f32::from_le_bytes(c.try_into().unwrap())))
        .collect()
}

#[test]
fn binary_stl_keeps_triangle_order_header_and_attributes() {
    let m = icosphere(2);
    // Positions exact in f32, so welding by position finds every shared corner.
    let p: Vec<[f64; 3]> = m
        .positions
        .iter()
        .map(|q| q.map(|x| x as f32 as f64))
        .collect();
    let bytes = binary_stl(&p, &m.triangles);
    let a = read(&bytes, Format::Stl);
    assert_eq!(a.file_vertex_count(), p.len(), "corners welded by position");
    assert_eq!(a.surface().face_count(), m.triangles.len());
    let new = moved(&a.surface().positions);
    let out = a.write(&new, Format::Stl).unwrap();
    assert_eq!(out.len(), bytes.len());
    assert_eq!(out[..84], bytes[..84], "header and count kept");
    for (k, tri) in m.triangles.iter().enumerate() {
        let at = 84 + 50 * k;
        assert_eq!(
            out[at + 48..at + 50],
            bytes[at + 48..at + 50],
            "attribute of {k}"
        );
        let v = f32s(&out[at..at + 48]);
        let corners: Vec<[f64; 3]> = (1..4)
            .map(|c| [v[3 * c], v[3 * c + 1], v[3 * c + 2]])
            .collect();
        // Same triangle: each written corner is the moved position of one of its corners.
        let mut want: Vec<[f32; 3]> = tri
            .iter()
            .map(|&i| {
                [
                    2.0 * p[i][0] + 0.5,
                    2.0 * p[i][1] - 0.25,
                    2.0 * p[i][2] + 0.125,
                ]
                .map(|x| x as f32)
            })
            .collect();
        let mut got: Vec<[f32; 3]> = corners.iter().map(|c| c.map(|x| x as f32)).collect();
        want.sort_by(|a, b| a.partial_cmp(b).unwrap());
        got.sort_by(|a, b| a.partial_cmp(b).unwrap());
        assert_eq!(got, want, "triangle {k}");
        // The normal is the unit normal of the written corners, pointing out.
        let e1 = [0, 1, 2].map(|i| corners[1][i] - corners[0][i]);
        let e2 = [0, 1, 2].map(|i| corners[2][i] - corners[0][i]);
        let c = [
            e1[1] * e2[2] - e1[2] * e2[1],
            e1[2] * e2[0] - e1[0] * e2[2],
            e1[0] * e2[1] - e1[1] * e2[0],
        ];
        let n = [v[0], v[1], v[2]];
        let l = dot(c, c).sqrt();
        assert!(dot(n, c.map(|x| x / l)) > 0.9999, "facet normal of {k}");
        assert!(dot(n, radial(corners[0])) > 0.9, "outward {k}");
    }
}

#[test]
fn ascii_stl_replaces_only_numbers_and_welds_by_position() {
    let m = icosphere(1);
    let text = ascii_stl(&m.positions, &m.triangles);
    assert_eq!(Format::sniff(text.as_bytes()), Some(Format::Stl));
    let a = read(text.as_bytes(), Format::Stl);
    assert_eq!(a.file_vertex_count(), m.positions.len());
    let new = moved(&a.surface().positions);
    let out = String::from_utf8(a.write(&new, Format::Stl).unwrap()).unwrap();
    assert!(out.starts_with("solid my part\n  facet normal "));
    assert!(out.ends_with("endsolid my part\n"));
    let strip = |s: &str| -> Vec<String> {
        s.lines()
            .map(|l| {
                l.split_whitespace()
                    .filter(|w| w.parse::<f64>().is_err())
                    .collect::<Vec<_>>()
                    .join(" ")
            })
            .collect()
    };
    assert_eq!(strip(&out), strip(&text), "only numbers changed");
    let b = read(out.as_bytes(), Format::Stl);
    assert_eq!(b.surface().vertex_count(), m.positions.len());
    for (w, q) in b
        .file_to_welded()
        .iter()
        .zip(expected_file_positions(&a, &new))
    {
        assert_eq!(b.surface().positions[w.unwrap()], q, "ASCII keeps f64");
    }
}

// ---------------------------------------------------------------------------------------
// OFF

#[test]
fn coff_and_noff_keep_colours_faces_and_comments() {
    let (p, t) = scanner_sphere();
    let mut text = String::from("COFF\n# a comment\n");
    text += &format!("{} {} 0\n", p.len(), t.len());
    for (i, q) in p.iter().enumerate() {
        let c = colour(i);
        text += &format!(
            "{} {} {} {} {} {} {}\n",
            q[0], q[1], q[2], c[0], c[1], c[2], c[3]
        );
    }
    for tri in &t {
        text += &format!("3 {} {} {} 255 0 0\n", tri[0], tri[1], tri[2]);
    }
    assert_eq!(Format::sniff(text.as_bytes()), Some(Format::Off));
    let a = read(text.as_bytes(), Format::Off);
    check_read(&a, &p, &t);
    let new = moved(&a.surface().positions);
    let out = String::from_utf8(a.write(&new, Format::Off).unwrap()).unwrap();
    let want = expected_file_positions(&a, &new);
    let (o, n): (Vec<&str>, Vec<&str>) = (text.lines().collect(), out.lines().collect());
    assert_eq!(o[..3], n[..3]);
    for i in 0..p.len() {
        let (ow, nw): (Vec<&str>, Vec<&str>) =
            (o[3 + i].split(' ').collect(), n[3 + i].split(' ').collect());
        assert_eq!(ow[3..], nw[3..], "colour of vertex {i}");
        for k in 0..3 {
            assert_eq!(nw[k].parse::<f64>().unwrap(), want[i][k]);
        }
    }
    assert_eq!(o[3 + p.len()..], n[3 + p.len()..], "face lines kept");

    // NOFF: normals recomputed, a quad fan-triangulated.
    let noff = "NOFF\n4 1 0\n0 0 0 9 9 9\n1 0 0 9 9 9\n1 1 0 9 9 9\n0 1 0 9 9 9\n4 0 1 2 3\n";
    let a = read(noff.as_bytes(), Format::Off);
    assert_eq!(a.surface().face_count(), 2);
    let out = String::from_utf8(
        a.write(&a.surface().positions.clone(), Format::Off)
            .unwrap(),
    )
    .unwrap();
    for line in out.lines().skip(2).take(4) {
        let w: Vec<f64> = line.split(' ').map(|x| x.parse().unwrap()).collect();
        assert_eq!(w[3..].to_vec(), vec![0.0, 0.0, 1.0], "{line}");
    }
}

// ---------------------------------------------------------------------------------------
// Across formats

#[test]
fn every_format_writes_every_other_and_reads_back_the_same_surface() {
    let (p, t) = scanner_sphere();
    let sources: Vec<(Format, Vec<u8>)> = vec![
        (Format::Ply, binary_ply(&p, &t, false)),
        (Format::Off, {
            let mut s = format!("OFF\n{} {} 0\n", p.len(), t.len());
            for q in &p {
                s += &format!("{} {} {}\n", q[0], q[1], q[2]);
            }
            for x in &t {
                s += &format!("3 {} {} {}\n", x[0], x[1], x[2]);
            }
            s.into_bytes()
        }),
        (Format::Stl, binary_stl(&p, &t)),
    ];
    for (from, bytes) in &sources {
        let a = read(bytes, *from);
        let new = moved(&a.surface().positions);
        for to in willow::mesh::io::ALL_FORMATS {
            let out = a.write(&new, to).unwrap();
            assert_eq!(Format::sniff(&out), Some(to), "{from:?} → {to:?}");
            let b = read(&out, to);
            assert_eq!(b.surface().face_count(), t.len(), "{from:?} → {to:?}");
            assert_eq!(b.surface().vertex_count(), p.len(), "{from:?} → {to:?}");
            // Same surface: every vertex has a counterpart (f32 formats to f32 precision).
            for x in &b.surface().positions {
                let d = new
                    .iter()
                    .map(|y| (0..3).map(|k| (x[k] - y[k]).abs()).fold(0.0, f64::max))
                    .fold(f64::INFINITY, f64::min);
                assert!(d < 1e-6, "{from:?} → {to:?}: {x:?} is {d} from the nearest");
            }
        }
    }
    // PLY's UVs carry into glTF and back into PLY.
    let a = read(&sources[0].1, Format::Ply);
    for to in [Format::Glb, Format::Obj] {
        let out = a.write(&a.surface().positions.clone(), to).unwrap();
        let b = read(&out, to);
        let back = b
            .write(&b.surface().positions.clone(), Format::Ply)
            .unwrap();
        let c = read(&back, Format::Ply);
        assert_eq!(c.corner_uvs().unwrap().len(), a.corner_uvs().unwrap().len());
        let mut x = a.corner_uvs().unwrap().concat();
        let mut y = c.corner_uvs().unwrap().concat();
        x.sort_by(|a, b| a.partial_cmp(b).unwrap());
        y.sort_by(|a, b| a.partial_cmp(b).unwrap());
        assert_eq!(x, y, "UVs via {to:?}");
    }
}

#[test]
fn stl_vertex_limit_is_checked_as_corners_arrive() {
    let m = icosphere(1);
    let bytes = binary_stl(&m.positions, &m.triangles);
    let limits = Limits {
        max_vertices: 20,
        ..Limits::default()
    };
    let e = Asset::read(&bytes, Format::Stl, &limits).unwrap_err();
    assert_eq!(e.code(), "too_large");
    assert!(e.to_string().contains("21 vertices"), "{e}");
}
