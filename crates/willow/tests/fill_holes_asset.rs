//! Holes filled on a file, not a bare surface (issue 40, item 2): the file's own vertices and
//! faces keep their numbers and coordinates, the patches are appended, and the texture
//! coordinates of a patch continue the chart around it. The written files are read back by
//! a small OBJ reader of this test's own, so the check does not lean on the writer's reader.

use willow::flow::holes::{fill_asset_holes, AssetHoles};
use willow::flow::FlowParams;
use willow::mesh::holes::HoleSize;
use willow::mesh::io::{Asset, Format};
use willow::mesh::{Limits, Topology};

const SPOT: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../../shared/meshes/spot_triangulated.obj"
);

/// `v`, `vt` and each face's `(v, vt)` corners (0-based) of an OBJ text.
struct Obj {
    v: Vec<[f64; 3]>,
    vt: Vec<[f64; 2]>,
    f: Vec<[(usize, Option<usize>); 3]>,
}

fn parse(text: &str) -> Obj {
    let mut o = Obj {
        v: Vec::new(),
        vt: Vec::new(),
        f: Vec::new(),
    };
    for line in text.lines() {
        let mut w = line.split_whitespace();
        match w.next() {
            Some("v") => {
                let x: Vec<f64> = w.take(3).map(|s| s.parse().expect("v")).collect();
                o.v.push([x[0], x[1], x[2]]);
            }
            Some("vt") => {
                let x: Vec<f64> = w.take(2).map(|s| s.parse().expect("vt")).collect();
                o.vt.push([x[0], x[1]]);
            }
            Some("f") => {
                let c: Vec<(usize, Option<usize>)> = w
                    .map(|s| {
                        let mut p = s.split('/');
                        let v: usize = p.next().and_then(|x| x.parse().ok()).expect("f v");
                        let vt = p.next().and_then(|x| x.parse::<usize>().ok());
                        (v - 1, vt.map(|t| t - 1))
                    })
                    .collect();
                assert_eq!(c.len(), 3, "the test meshes are triangulated");
                o.f.push([c[0], c[1], c[2]]);
            }
            _ => {}
        }
    }
    o
}

/// Inside one UV chart of spot's texture.
const IN_CHART: usize = 1000;
/// Where two of spot's charts meet (the hole's loop runs across their seam).
const ON_SEAM: usize = 1612;

/// Spot's OBJ with every face touching the ball around vertex `centre` (5% of the diagonal)
/// removed, its `v` and `vt` lines untouched; and the removed vertices.
fn holed_spot(centre: usize) -> (String, Vec<usize>, Obj) {
    let text = std::fs::read_to_string(SPOT).expect("the shared spot mesh");
    let obj = parse(&text);
    let (mut lo, mut hi) = ([f64::MAX; 3], [f64::MIN; 3]);
    for p in &obj.v {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    let diag = (0..3).map(|k| (hi[k] - lo[k]).powi(2)).sum::<f64>().sqrt();
    let c = obj.v[centre];
    let inside: Vec<bool> = obj
        .v
        .iter()
        .map(|p| (0..3).map(|k| (p[k] - c[k]).powi(2)).sum::<f64>().sqrt() < 0.05 * diag)
        .collect();
    let mut out = String::new();
    for line in text.lines() {
        if line.starts_with("f ") {
            let touches = line.split_whitespace().skip(1).any(|s| {
                let v: usize = s.split('/').next().and_then(|x| x.parse().ok()).expect("f");
                inside[v - 1]
            });
            if touches {
                continue;
            }
        }
        out.push_str(line);
        out.push('\n');
    }
    let removed = (0..obj.v.len()).filter(|&v| inside[v]).collect();
    (out, removed, obj)
}

/// Each vertex's UV in `obj` (the first corner naming it).
fn vertex_uvs(obj: &Obj) -> Vec<Option<[f64; 2]>> {
    let mut uv = vec![None; obj.v.len()];
    for f in &obj.f {
        for &(v, t) in f {
            if uv[v].is_none() {
                uv[v] = t.map(|t| obj.vt[t]);
            }
        }
    }
    uv
}

/// The asset's holes up to `size` filled at the defaults.
fn fill(asset: &Asset, size: HoleSize) -> AssetHoles {
    fill_asset_holes(asset, size, &FlowParams::default(), &Limits::default())
        .expect("the holes fill")
}

#[test]
fn a_filled_obj_keeps_its_numbering_and_continues_its_texture() {
    let (text, removed, original) = holed_spot(IN_CHART);
    assert!(removed.len() > 10, "the ball removes a real hole");
    let asset = Asset::read(text.as_bytes(), Format::Obj, &Limits::default()).unwrap();
    assert_eq!(Topology::new(asset.surface()).boundary_loops.len(), 1);

    let r = fill(&asset, HoleSize::Any);
    assert_eq!(r.filled, 1);
    assert!(
        r.new_vertices > 5,
        "the patch is refined: {} vertices",
        r.new_vertices
    );
    assert!(Topology::new(r.asset.surface()).is_closed());
    assert_eq!(
        r.asset.file_vertex_count(),
        original.v.len() + r.new_vertices,
        "frames carry the file's vertices, then the patch's"
    );

    let written = r
        .asset
        .write(&r.asset.surface().positions, Format::Obj)
        .unwrap();
    let out = parse(std::str::from_utf8(&written).unwrap());
    let holed = parse(&text);
    assert_eq!(out.v.len(), original.v.len() + r.new_vertices);
    assert_eq!(
        &out.v[..original.v.len()],
        &original.v[..],
        "every `v` line of the file keeps its coordinates (the removed ones their stored ones)"
    );
    assert_eq!(out.f.len(), holed.f.len() + r.new_triangles);
    assert_eq!(
        &out.f[..holed.f.len()],
        &holed.f[..],
        "the file's faces come first, unchanged"
    );
    assert_eq!(out.vt.len(), holed.vt.len() + r.new_vertices);

    // The patch's UVs continue the chart: each new vertex's UV against the UV of the nearest
    // removed vertex of the original (which sat on the cut-away surface).
    let uv_orig = vertex_uvs(&original);
    let uv_out = vertex_uvs(&out);
    let mut err = 0.0;
    let patch = uv_out.iter().zip(&out.v).skip(original.v.len());
    for (uv, &p) in patch {
        let uv = uv.expect("every patch vertex has a UV");
        let nearest = removed
            .iter()
            .min_by(|&&a, &&b| {
                let d = |q: [f64; 3]| (0..3).map(|k| (q[k] - p[k]).powi(2)).sum::<f64>();
                d(original.v[a]).total_cmp(&d(original.v[b]))
            })
            .copied()
            .unwrap();
        let want = uv_orig[nearest].expect("spot's vertices all have UVs");
        err += ((uv[0] - want[0]).powi(2) + (uv[1] - want[1]).powi(2)).sqrt();
    }
    let mean = err / r.new_vertices as f64;
    eprintln!("patch UV error against the cut-away chart: mean {mean:.4}");
    assert!(mean < 0.02, "patch UVs leave the chart: mean error {mean}");

    // The written file reads back closed.
    let back = Asset::read(&written, Format::Obj, &Limits::default()).unwrap();
    assert!(Topology::new(back.surface()).is_closed());
}

#[test]
fn a_filled_glb_keeps_its_primitive_and_reads_back_closed() {
    let (text, _, _) = holed_spot(IN_CHART);
    let obj = Asset::read(text.as_bytes(), Format::Obj, &Limits::default()).unwrap();
    let glb = obj.write(&obj.surface().positions, Format::Glb).unwrap();
    let asset = Asset::read(&glb, Format::Glb, &Limits::default()).unwrap();
    let before = asset.file_triangles().len();
    let r = fill(&asset, HoleSize::Any);
    assert_eq!(r.filled, 1);
    let written = r
        .asset
        .write(&r.asset.surface().positions, Format::Glb)
        .unwrap();
    let back = Asset::read(&written, Format::Glb, &Limits::default()).unwrap();
    assert!(Topology::new(back.surface()).is_closed());
    assert_eq!(back.file_triangles().len(), before + r.new_triangles);
    assert_eq!(
        back.file_vertex_count(),
        asset.file_vertex_count() + r.new_vertices
    );
    let uvs = back.corner_uvs().expect("the document keeps TEXCOORD_0");
    assert_eq!(uvs.len(), before + r.new_triangles);
    // The primitive's own vertices read back where they were (float32 in the file).
    let old = asset.file_world_positions(&asset.surface().positions);
    let new = back.file_world_positions(&back.surface().positions);
    for (a, b) in old.iter().zip(&new) {
        for k in 0..3 {
            assert!((a[k] - b[k]).abs() <= 1e-6 * a[k].abs().max(1.0));
        }
    }
}

#[test]
fn a_hole_size_limit_leaves_the_file_as_it_was() {
    let (text, _, _) = holed_spot(IN_CHART);
    let asset = Asset::read(text.as_bytes(), Format::Obj, &Limits::default()).unwrap();
    let r = fill(&asset, HoleSize::Vertices(3));
    assert_eq!(r.filled, 0);
    assert_eq!(r.left_open.len(), 1);
    let written = r
        .asset
        .write(&r.asset.surface().positions, Format::Obj)
        .unwrap();
    assert_eq!(
        written,
        asset
            .write(&asset.surface().positions, Format::Obj)
            .unwrap()
    );
}

#[test]
fn a_patch_across_a_uv_seam_is_written_without_uvs_and_says_so() {
    let (text, _, original) = holed_spot(ON_SEAM);
    let asset = Asset::read(text.as_bytes(), Format::Obj, &Limits::default()).unwrap();
    let r = fill(&asset, HoleSize::Any);
    assert_eq!(r.filled, 1);
    let notes = r.asset.notes();
    assert!(
        notes.iter().any(|n| n.contains("no UVs")),
        "the job must say the patch has no UVs: {notes:?}"
    );
    let written = r
        .asset
        .write(&r.asset.surface().positions, Format::Obj)
        .unwrap();
    let out = parse(std::str::from_utf8(&written).unwrap());
    let patch_faces: Vec<_> = out
        .f
        .iter()
        .filter(|f| f.iter().any(|&(v, _)| v >= original.v.len()))
        .collect();
    assert!(!patch_faces.is_empty());
    assert!(
        patch_faces
            .iter()
            .all(|f| f.iter().all(|&(_, t)| t.is_none())),
        "a face with a vertex that has no UV is written without `vt`"
    );
    assert!(Topology::new(
        Asset::read(&written, Format::Obj, &Limits::default())
            .unwrap()
            .surface()
    )
    .is_closed());
}
