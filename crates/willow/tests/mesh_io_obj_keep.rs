//! OBJ written back as OBJ keeps the user's file: byte for byte except the numbers on `v`
//! lines (and on `vn` lines a face uses), with the file's own vertex order and count, which
//! is also the order of `Asset::file_positions` (what streamed frames carry).

mod mesh_support;

use mesh_support::*;
use willow::mesh::io::{Asset, Format, Limits};

fn read(bytes: &[u8]) -> Asset {
    Asset::read(bytes, Format::Obj, &Limits::default()).unwrap()
}

/// Moves every welded vertex differently (a mix-up of vertices would show).
fn wobble(p: &[[f64; 3]]) -> Vec<[f64; 3]> {
    p.iter()
        .enumerate()
        .map(|(i, q)| {
            let s = 1.0 + 0.01 * (i % 7) as f64;
            [q[0] * s + 0.25, q[1] * s - 0.5, q[2] * s + 1.0 / 3.0]
        })
        .collect()
}

/// An octahedron (±x, ±y, ±z) whose `v` lines are out of face order, with unused vertices at
/// the start, middle and end, a second `v` line at +z (welded to the first), vertex colours,
/// odd spacing, names, groups, materials, smoothing groups, comments, blank lines, `vt`, `vn`
/// (one unused), mixed corner styles and relative (negative) indices.
const OCTA: &str = "\
# Willow keep-the-file test\tfile
mtllib scene.mtl

o octa
v 5 5 5 1 0 0
v 0 0 -1
v 0 1 0 0.5 0.25 1
v 1 0 0
v  0.1   0.2 0.3
v -1 0 0
v 0 0 1
v 0 -1 0
v 0 0 1.0
v 7 8 9
vt 0 0
vt 1.000 0
vt 0 1
vn 0 0 1
vn 0 0 -1
vn 0.6 0.8 0
g top
usemtl red
s 1
f 4/1/1 3/2/1 7/3/1
f 3/1/1 6/2/1 7/3/1
f 6/1 8/2 7/3
# relative indices: -3 is v 8, -7 is v 4, -2 is v 9
f -3//1 -7//1 -2//1
g bottom
usemtl blue
s off
f 3//2 4//2 2//2
f 6 3 2
f -3 -5 -9
f 4 8 2
";

/// The positions of OCTA's `v` lines, in file order.
const OCTA_V: [[f64; 3]; 10] = [
    [5.0, 5.0, 5.0],
    [0.0, 0.0, -1.0],
    [0.0, 1.0, 0.0],
    [1.0, 0.0, 0.0],
    [0.1, 0.2, 0.3],
    [-1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0],
    [0.0, -1.0, 0.0],
    [0.0, 0.0, 1.0],
    [7.0, 8.0, 9.0],
];

/// `line` with the byte range of its words `from..to` (1-based, after the keyword) cut out,
/// and those words.
fn cut_words(line: &str, from: usize, to: usize) -> (String, Vec<&str>) {
    let base = line.as_ptr() as usize;
    let words: Vec<(usize, &str)> = line
        .split_whitespace()
        .map(|w| (w.as_ptr() as usize - base, w))
        .collect();
    let (start, end) = (words[from].0, words[to - 1].0 + words[to - 1].1.len());
    let cut = format!("{}{}", &line[..start], &line[end..]);
    (cut, words[from..to].iter().map(|w| w.1).collect())
}

fn numbers(words: &[&str]) -> [f64; 3] {
    let n: Vec<f64> = words.iter().map(|w| w.parse().unwrap()).collect();
    [n[0], n[1], n[2]]
}

/// Checks `output` against `input` line by line: same line count and endings; every line
/// other than `v`/`vn` byte-identical; each `v` line identical apart from its x y z, which
/// parse to exactly `expected_v[k]` (k-th `v` line); each `vn` line identical apart from its
/// three numbers, which are a unit vector (or unchanged, if no face uses it). Returns the
/// written normals, in file order.
fn assert_kept(input: &str, output: &str, expected_v: &[[f64; 3]]) -> Vec<[f64; 3]> {
    let (a, b): (Vec<&str>, Vec<&str>) = (
        input.split_inclusive('\n').collect(),
        output.split_inclusive('\n').collect(),
    );
    assert_eq!(a.len(), b.len(), "line count");
    let mut k = 0;
    let mut normals = Vec::new();
    for (n, (x, y)) in a.iter().zip(&b).enumerate() {
        match x.split_whitespace().next() {
            Some("v") => {
                let (x_rest, _) = cut_words(x, 1, 4);
                let (y_rest, y_xyz) = cut_words(y, 1, 4);
                assert_eq!(x_rest, y_rest, "line {}: only x y z change", n + 1);
                assert_eq!(
                    numbers(&y_xyz),
                    expected_v[k],
                    "line {}: v {}",
                    n + 1,
                    k + 1
                );
                k += 1;
            }
            Some("vn") => {
                let (x_rest, _) = cut_words(x, 1, 4);
                let (y_rest, y_n) = cut_words(y, 1, 4);
                assert_eq!(x_rest, y_rest, "line {}: only the normal changes", n + 1);
                let v = numbers(&y_n);
                let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                assert!(
                    (len - 1.0).abs() < 1e-12,
                    "line {}: unit normal {v:?}",
                    n + 1
                );
                normals.push(v);
            }
            _ => assert_eq!(x, y, "line {} is kept byte for byte", n + 1),
        }
    }
    assert_eq!(k, expected_v.len(), "every `v` line checked");
    normals
}

/// The file positions an asset should write for new welded `positions`: the welded vertex's
/// new position for used `v` lines, the stored one for unused lines.
fn expected_file_positions(
    a: &Asset,
    stored: &[[f64; 3]],
    positions: &[[f64; 3]],
) -> Vec<[f64; 3]> {
    a.file_to_welded()
        .iter()
        .zip(stored)
        .map(|(w, s)| w.map_or(*s, |w| positions[w]))
        .collect()
}

fn check_octahedron(text: &str) {
    let a = read(text.as_bytes());
    assert_eq!(a.surface().vertex_count(), 6);
    assert_eq!(a.surface().face_count(), 8);
    assert_eq!(a.file_vertex_count(), 10, "one file vertex per `v` line");

    // File order is the `v` lines: unused ones included, welded copies mapped together.
    let map = a.file_to_welded();
    let used: Vec<bool> = map.iter().map(Option::is_some).collect();
    assert_eq!(
        used,
        [false, true, true, true, false, true, true, true, true, false]
    );
    assert_eq!(map[6], map[8], "the two `v` lines at +z weld together");
    let f32s =
        |p: &[[f64; 3]]| -> Vec<[f32; 3]> { p.iter().map(|q| q.map(|x| x as f32)).collect() };
    assert_eq!(a.file_positions(&a.surface().positions), f32s(&OCTA_V));
    for (fv, w) in map.iter().enumerate() {
        if let Some(w) = w {
            assert_eq!(a.surface().positions[*w], OCTA_V[fv]);
        }
    }
    assert_eq!(
        a.file_triangles()[0],
        [3, 2, 6],
        "`f 4/1/1 3/2/1 7/3/1`, 0-based"
    );
    assert_eq!(a.file_triangles()[3], [7, 3, 8], "`f -3//1 -7//1 -2//1`");

    // Written unmoved: the normals are the area-weighted face normals of their corners.
    let out = String::from_utf8(a.write(&a.surface().positions, Format::Obj).unwrap()).unwrap();
    let normals = assert_kept(text, &out, &OCTA_V);
    let (s11, s3) = (11f64.sqrt(), 3f64.sqrt());
    let want = [
        [1.0 / s11, 1.0 / s11, 3.0 / s11],
        [1.0 / s3, 1.0 / s3, -1.0 / s3],
    ];
    for (n, w) in normals.iter().zip(&want) {
        for k in 0..3 {
            assert!((n[k] - w[k]).abs() < 1e-12, "{n:?} vs {w:?}");
        }
    }
    assert!(
        out.contains("vn 0.6 0.8 0"),
        "an unused `vn` is kept as it was"
    );

    // Moved: every `v` line holds its vertex's new position exactly (unused ones: stored).
    let moved = wobble(&a.surface().positions);
    let expect = expected_file_positions(&a, &OCTA_V, &moved);
    assert_eq!(expect[6], expect[8], "welded copies get the same position");
    assert_eq!(a.file_positions(&moved), f32s(&expect));
    let out = String::from_utf8(a.write(&moved, Format::Obj).unwrap()).unwrap();
    assert_kept(text, &out, &expect);

    // Re-read: the same surface, moved.
    let b = read(out.as_bytes());
    assert_eq!(b.surface().triangles, a.surface().triangles);
    assert_eq!(b.surface().positions, moved);
    assert_eq!(b.file_to_welded(), map);
    assert_eq!(b.file_positions(&b.surface().positions), f32s(&expect));
    assert_eq!(b.corner_uvs(), a.corner_uvs());
    let t = willow::mesh::Topology::new(b.surface());
    assert!(t.is_closed() && t.genus() == 0);
    assert!(signed_volume(&b.surface().positions, &b.surface().triangles) > 0.0);
}

#[test]
fn obj_keeps_order_unused_vertices_colours_names_and_faces() {
    check_octahedron(OCTA);
}

#[test]
fn obj_with_crlf_line_endings_keeps_them() {
    let crlf = OCTA.replace('\n', "\r\n");
    check_octahedron(&crlf);
    let a = read(crlf.as_bytes());
    let out = a
        .write(&wobble(&a.surface().positions), Format::Obj)
        .unwrap();
    let out = String::from_utf8(out).unwrap();
    assert_eq!(out.matches("\r\n").count(), OCTA.lines().count());
}

#[test]
fn tetrahedron_file_positions_follow_the_v_lines() {
    // `f 1 3 2` first: welded vertices are numbered 1, 3, 2, 4 by first use; the file's
    // vertices, and so the frames, stay in `v` line order.
    let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 3\n";
    let v = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
    ];
    let a = read(text.as_bytes());
    assert_eq!(a.surface().positions[1], v[2], "welded order is first use");
    let file = a.file_positions(&a.surface().positions);
    for k in 0..4 {
        assert_eq!(
            file[k],
            v[k].map(|x| x as f32),
            "file_positions()[{k}] is `v` line {k}"
        );
    }
    assert_eq!(a.file_to_welded(), vec![Some(0), Some(2), Some(1), Some(3)]);
    assert_eq!(a.file_triangles()[0], [0, 2, 1]);
    let moved = wobble(&a.surface().positions);
    let out = String::from_utf8(a.write(&moved, Format::Obj).unwrap()).unwrap();
    assert_kept(text, &out, &expected_file_positions(&a, &v, &moved));
}

#[test]
fn spot_file_vertices_are_its_v_lines() {
    let text = include_str!("data/spot_triangulated.obj");
    let v: Vec<[f64; 3]> = text
        .lines()
        .filter(|l| l.starts_with("v "))
        .map(|l| {
            let w: Vec<&str> = l.split_whitespace().collect();
            numbers(&w[1..4])
        })
        .collect();
    assert_eq!(v.len(), 2930);
    let a = read(text.as_bytes());
    assert_eq!(a.file_vertex_count(), 2930);
    let want: Vec<[f32; 3]> = v.iter().map(|p| p.map(|x| x as f32)).collect();
    assert_eq!(a.file_positions(&a.surface().positions), want);
    let moved = wobble(&a.surface().positions);
    let out = String::from_utf8(a.write(&moved, Format::Obj).unwrap()).unwrap();
    assert_kept(text, &out, &expected_file_positions(&a, &v, &moved));
}

#[test]
fn v_weights_are_applied_and_written_as_plain_positions() {
    // `v x y z w` means (x, y, z) / w; w = 1 is kept as written, other weights are folded in.
    let text = "v 0 0 0 1\nv 2 0 0 2\nv 0 1 0\nv 0 0 1 1.0\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 3\n";
    let a = read(text.as_bytes());
    let file = a.file_positions(&a.surface().positions);
    assert_eq!(file[1], [1.0, 0.0, 0.0]);
    let moved = wobble(&a.surface().positions);
    let out = String::from_utf8(a.write(&moved, Format::Obj).unwrap()).unwrap();
    let lines: Vec<&str> = out.lines().collect();
    assert!(
        lines[0].ends_with(" 1") && lines[3].ends_with(" 1.0"),
        "{out}"
    );
    assert_eq!(
        lines[1].split_whitespace().count(),
        4,
        "w = 2 folded in: {out}"
    );
    assert_eq!(read(out.as_bytes()).surface().positions, moved);
}

#[test]
fn line_continuations_and_bad_unused_vertices_are_refused() {
    let e = Asset::read(
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 \\\n3\n",
        Format::Obj,
        &Limits::default(),
    )
    .unwrap_err();
    assert_eq!(e.code(), "unsupported", "{e}");
    assert!(e.to_string().contains("line 4"), "{e}");
    // A comment may end in a backslash.
    assert!(Asset::read(
        b"# c:\\\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
        Format::Obj,
        &Limits::default()
    )
    .is_ok());
    // An unused `v` line is streamed and written back too: it must be finite. Named by its
    // 0-based `v` line index.
    let e = Asset::read(
        b"v 0 0 0\nv nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 3 4\n",
        Format::Obj,
        &Limits::default(),
    )
    .unwrap_err();
    assert_eq!(e.code(), "non_finite_coordinate");
    assert!(e.to_string().ends_with("first: 1"), "{e}");
}
