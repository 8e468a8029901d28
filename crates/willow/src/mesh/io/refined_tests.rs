//! Refining an asset: the surface is `refine`'s, UVs are interpolated per corner so seams
//! stay split, the file's own vertices keep their numbers, and every format writes it back.

use super::super::{Asset, Format, ALL_FORMATS};
use crate::mesh::refine::{loop_subdivide, MAX_REFINED_FACES};
use crate::mesh::{Limits, MeshError};

/// A unit cube as an OBJ: 8 `v`, each face its own UV square (so every cube edge is a UV
/// seam), two triangles per face, and one unused `v` line at the end.
fn cube_obj() -> String {
    let mut s = String::from("# cube\n");
    for i in 0..8 {
        let (x, y, z) = (i & 1, (i >> 1) & 1, (i >> 2) & 1);
        s += &format!("v {x} {y} {z}\n");
    }
    s += "v 5 5 5\n";
    // Outward quads (counter-clockwise seen from outside), as v indices from 1.
    let quads = [
        [1, 3, 4, 2],
        [5, 6, 8, 7],
        [1, 2, 6, 5],
        [3, 7, 8, 4],
        [1, 5, 7, 3],
        [2, 4, 8, 6],
    ];
    for (f, _) in quads.iter().enumerate() {
        let u0 = f as f64 / 6.0;
        for (du, dv) in [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)] {
            s += &format!("vt {} {}\n", u0 + du / 6.0, dv);
        }
    }
    for (f, q) in quads.iter().enumerate() {
        let t = |k: usize| format!("{}/{}", q[k], 4 * f + k + 1);
        s += &format!("f {} {} {}\n", t(0), t(1), t(2));
        s += &format!("f {} {} {}\n", t(0), t(2), t(3));
    }
    s
}

fn cube() -> Asset {
    Asset::read(cube_obj().as_bytes(), Format::Obj, &Limits::default()).expect("cube")
}

#[test]
fn the_surface_is_loops_and_the_files_vertices_keep_their_numbers() {
    let asset = cube();
    let target = 0.5 * crate::mesh::generate::mean_edge_length(asset.surface());
    let (r, how) = asset
        .refined(Some(target), &Limits::default())
        .expect("refine");
    assert_eq!(how.levels, 1);
    assert_eq!(how.vertices_before, 9);
    // The surface is exactly one Loop level of the input's surface.
    let (expected, split) = loop_subdivide(asset.surface());
    assert_eq!(r.surface(), &expected);
    // File vertices: the 9 `v` lines (the unused one included, at its stored position), then
    // one per edge between two `v` lines: 12 cube edges + 6 diagonals.
    assert_eq!(split.edges.len(), 18);
    assert_eq!(r.file_vertex_count(), 9 + 18);
    let frame = r.file_positions(&r.surface().positions);
    assert_eq!(frame.len(), 27);
    assert_eq!(frame[8], [5.0, 5.0, 5.0]);
    // Child 4t's first corner is its parent's first corner, in the file's numbering.
    let (before, after) = (asset.file_triangles(), r.file_triangles());
    assert_eq!(after.len(), 4 * before.len());
    for (t, parent) in before.iter().enumerate() {
        assert_eq!(after[4 * t][0], parent[0]);
        assert_eq!(after[4 * t + 1][1], parent[1]);
        assert_eq!(after[4 * t + 2][2], parent[2]);
        assert!(
            after[4 * t + 3].iter().all(|&v| v >= 9),
            "the middle child is all new"
        );
    }
    // The old file vertices sit where Loop moved their welded vertex.
    let to_welded = r.file_to_welded();
    for v in 0..8 {
        let w = to_welded[v].expect("used");
        let p = r.surface().positions[w].map(|x| x as f32);
        assert_eq!(frame[v], p);
    }
}

#[test]
fn uvs_are_interpolated_per_corner_and_seams_stay_split() {
    let asset = cube();
    let (r, how) = asset.refined(None, &Limits::default()).expect("refine");
    assert!(how.levels >= 2);
    let (uv0, uv) = (
        asset.corner_uvs().expect("uvs"),
        r.corner_uvs().expect("uvs kept"),
    );
    let levels = how.levels;
    assert_eq!(uv.len(), uv0.len() << (2 * levels));
    // Every corner of every descendant lies in its ancestor's UV triangle, at barycentric
    // coordinates that are multiples of 2^-levels (linear interpolation, module docs).
    let scale = (1u32 << levels) as f64;
    for (c, corners) in uv.iter().enumerate() {
        let [a, b, p] = uv0[c >> (2 * levels)].map(|x| x.map(f64::from));
        for q in corners.map(|x| x.map(f64::from)) {
            let det = (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]);
            let l1 = ((q[0] - a[0]) * (p[1] - a[1]) - (q[1] - a[1]) * (p[0] - a[0])) / det;
            let l2 = ((b[0] - a[0]) * (q[1] - a[1]) - (b[1] - a[1]) * (q[0] - a[0])) / det;
            for l in [l1, l2, 1.0 - l1 - l2] {
                assert!((-1e-5..=1.0 + 1e-5).contains(&l), "child {c}: {l}");
                assert!(
                    ((l * scale).round() - l * scale).abs() < 1e-4,
                    "child {c}: {l}"
                );
            }
        }
    }
    // A seam stays split: a vertex on a cube edge has one UV per face it touches.
    let tris = r.file_triangles();
    let mut uv_of: std::collections::HashMap<usize, Vec<[u32; 2]>> = Default::default();
    for (t, corners) in tris.iter().zip(&uv) {
        for (&v, q) in t.iter().zip(corners) {
            let key = q.map(f32::to_bits);
            let list = uv_of.entry(v).or_default();
            if !list.contains(&key) {
                list.push(key);
            }
        }
    }
    let cube_corner = uv_of.get(&0).map_or(0, Vec::len);
    assert_eq!(cube_corner, 3, "a cube corner keeps one UV per face");
    let seam = uv_of.values().filter(|l| l.len() == 2).count();
    let edge_points = 12 * ((1 << levels) - 1);
    assert_eq!(
        seam, edge_points,
        "new vertices on the 12 cube edges keep two UVs"
    );
}

#[test]
fn every_format_writes_the_refined_connectivity() {
    let (r, _) = cube().refined(None, &Limits::default()).expect("refine");
    let p = &r.surface().positions;
    for format in ALL_FORMATS {
        let bytes = r.write(p, format).expect("write");
        let back = Asset::read(&bytes, format, &Limits::default()).expect("read back");
        assert_eq!(
            back.surface().face_count(),
            r.surface().face_count(),
            "{format:?}"
        );
        assert_eq!(
            back.surface().vertex_count(),
            r.surface().vertex_count(),
            "{format:?}"
        );
        if matches!(format, Format::Obj | Format::Gltf | Format::Glb) {
            assert!(back.corner_uvs().is_some(), "{format:?} lost the UVs");
        }
    }
}

#[test]
fn a_hostile_target_names_refine() {
    let e = cube()
        .refined(Some(1e-12), &Limits::default())
        .expect_err("too fine");
    assert!(
        matches!(e, MeshError::TooLarge { limit, .. } if limit == MAX_REFINED_FACES),
        "{e}"
    );
    assert!(e.to_string().contains("refine"), "{e}");
}
